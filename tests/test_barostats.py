"""Barostats (stochastic cell rescaling, Berendsen): isotropic, anisotropic and triclinic coupling.

Exact answers: an ideal gas under isotropic NPT has <V> = (N + 1) kT / P and
var(V) / (kT <V>) = 1 / P (the compressibility); thermodynamic consistency:
the compressibility from volume fluctuations equals -(1/V) dV/dP from the mean
volumes at neighbouring pressures.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest

import md
from integrators import Langevin, VelocityVerlet
from integrators.barostats import Barostat, PressureCoupled
from md.checkpoint import read_checkpoint, restore, write_checkpoint
from md.cli import main
from md.trajectory import read_trajectory
from potentials import HarmonicBonds, LennardJones

N_GAS = 100


def _ideal_gas_volumes(pressure, kind="c_rescale", steps=20_000, seed=1):
    """Volumes sampled every 10 steps after 2000, for N_GAS ideal-gas atoms at kT = 1."""
    rng = np.random.default_rng(seed)
    state = md.State(positions=rng.uniform(0, 4.6, size=(N_GAS, 3)), box=4.6)
    md.maxwell_boltzmann(state, 1.0, seed=seed)
    no_forces = HarmonicBonds(np.zeros((0, 2), dtype=int), k=1.0, r0=1.0)
    integrator = PressureCoupled(
        Langevin(0.01, temperature=1.0, friction=2.0, seed=seed + 1),
        Barostat(kind, pressure, tau=0.5, compressibility=1.0, every=1, seed=seed + 2),
    )
    sim = md.Simulation(state, [no_forces], integrator)
    volumes = []
    sim.attach(lambda s: volumes.append(s.state.volume), 10)
    sim.run(steps)
    return np.array(volumes[200:])


@pytest.fixture(scope="module")
def gas_at_1():
    return _ideal_gas_volumes(1.0)


def test_ideal_gas_mean_volume_is_n_plus_1_kt_over_p(gas_at_1):
    assert gas_at_1.mean() == pytest.approx((N_GAS + 1) * 1.0 / 1.0, rel=0.03)


@pytest.mark.slow  # 9-18 s; keeps the cold default suite within 10 minutes on 2 cores
def test_compressibility_from_fluctuations_matches_the_equation_of_state(gas_at_1):
    from md.analysis import isothermal_compressibility

    kappa_fluct = isothermal_compressibility(gas_at_1, temperature=1.0)
    low, high = _ideal_gas_volumes(0.8, seed=5).mean(), _ideal_gas_volumes(1.25, seed=7).mean()
    kappa_eos = -(high - low) / (1.25 - 0.8) / gas_at_1.mean()
    assert kappa_fluct == pytest.approx(1.0, rel=0.15)  # exact: 1/P
    assert kappa_fluct == pytest.approx(kappa_eos, rel=0.2)


def test_berendsen_relaxes_the_volume_but_suppresses_its_fluctuations(gas_at_1):
    berendsen = _ideal_gas_volumes(1.0, kind="berendsen")
    assert berendsen.mean() == pytest.approx(gas_at_1.mean(), rel=0.05)
    assert berendsen.var() < 0.3 * gas_at_1.var()


def _liquid_sim(kind="c_rescale", every=10):
    state = md.maxwell_boltzmann(md.lattice("fcc", 4, density=0.8), 1.0, seed=3)
    integrator = PressureCoupled(
        Langevin(0.005, temperature=1.0, friction=1.0, seed=4),
        Barostat(kind, 1.0, tau=1.0, compressibility=0.1, every=every, seed=5),
    )
    return md.Simulation(state, [LennardJones(cutoff=2.5)], integrator)


def test_conserved_quantity_includes_p0_v_and_the_barostat_work():
    sim = _liquid_sim()
    start = sim.thermo()
    sim.run(1000)
    end = sim.thermo()
    assert end["volume"] != start["volume"]
    # total energy moves by ~hundreds (the box relaxes); the conserved quantity by < 1
    assert abs(end["total_energy"] - start["total_energy"]) > 50
    assert abs(end["conserved_energy"] - start["conserved_energy"]) < 1.0
    assert sim.integrator.statistics["barostat_moves"] == 100


def test_get_and_set_state_continue_bit_for_bit(tmp_path):
    """Through a checkpoint (the integrator's state, and the neighbour list built where it
    was, at the cell it had then: its wraps decide the last bits of the separations)."""
    a, b = _liquid_sim(), _liquid_sim()
    a.run(200)
    b.run(100)
    write_checkpoint(tmp_path / "at100.ckpt", b.state, b.integrator, b.forcefield)
    checkpoint = read_checkpoint(tmp_path / "at100.ckpt")
    c = _liquid_sim()
    c.state.positions[:], c.state.velocities[:] = (
        checkpoint.state.positions,
        checkpoint.state.velocities,
    )
    c.state.box, c.state.step = checkpoint.state.box.copy(), checkpoint.state.step
    c.state.time = checkpoint.state.time
    restore(checkpoint, c.integrator, c.forcefield)
    c.run(100)
    b.run(100)
    assert np.array_equal(b.state.positions, a.state.positions)
    assert np.array_equal(c.state.box, a.state.box)
    assert np.allclose(c.state.positions, a.state.positions, atol=1e-10)


def test_a_barostat_needs_a_thermostat_and_valid_parameters():
    with pytest.raises(ValueError, match="needs a thermostat"):
        PressureCoupled(VelocityVerlet(0.005), Barostat("c_rescale", 1.0, 1.0, 0.1))
    with pytest.raises(ValueError, match="unknown barostat 'mttk'"):
        Barostat("mttk", 1.0, 1.0, 0.1)
    with pytest.raises(ValueError, match="the c_rescale barostat needs a compressibility"):
        Barostat("c_rescale", 1.0, 1.0)
    with pytest.raises(ValueError, match="tau must be finite and > 0"):
        Barostat("c_rescale", 1.0, 0.0, 0.1)
    with pytest.raises(ValueError, match="unknown couple = 'sideways'"):
        Barostat("c_rescale", 1.0, 1.0, 0.1, couple="sideways")


CONFIG = """
units = "lj"
seed = 3
[system]
lattice = "fcc"
cells = 4
density = 0.8
temperature = 1.0
[[potentials]]
type = "lj"
cutoff = 2.5
[integrator]
{integrator}
[barostat]
{barostat}
[run]
steps = 60
thermo_every = 20
[output]
path = "npt.h5"
every = 20
checkpoint_every = 20
"""
LANGEVIN = 'type = "langevin"\ndt = 0.005\ntemperature = 1.0\nfriction = 1.0'
C_RESCALE = 'type = "c_rescale"\npressure = 1.0\ntau = 1.0'
NHC = 'type = "nose_hoover_chain"\ndt = 0.005\ntemperature = 1.0\ntau = 0.5'
MTK = 'type = "mtk"\npressure = 1.0\ntau = 2.0'


@pytest.fixture(autouse=True)
def in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)


def test_md_run_with_a_barostat_stores_volume_and_resumes_bit_for_bit(tmp_path):
    (tmp_path / "npt.toml").write_text(CONFIG.format(integrator=LANGEVIN, barostat=C_RESCALE))
    quiet = ("--no-progress", "-q")
    assert main(["run", "npt.toml", "-o", "whole.h5", *quiet]) == 0
    assert main(["run", "npt.toml", "-o", "part.h5", "--steps", "40", *quiet]) == 0
    assert main(["run", "npt.toml", "-o", "part.h5", "--resume", *quiet]) == 0
    whole, part = read_trajectory("whole.h5"), read_trajectory("part.h5")
    assert np.ptp(whole.observables["volume"]) > 0  # the box moved
    assert np.array_equal(whole.boxes, part.boxes)
    assert np.array_equal(whole.positions, part.positions)
    assert np.array_equal(whole.observables["volume"], part.observables["volume"])


@pytest.mark.parametrize(
    ("integrator", "barostat", "message"),
    [
        (LANGEVIN, 'type = "mttk"\npressure = 1.0\ntau = 1.0', "[barostat] type: must be one of"),
        (LANGEVIN, MTK, "[barostat] type: the mtk barostat runs with its own Nose-Hoover chains"),
        (NHC, MTK + "\ncompressibility = 0.1", "[barostat] compressibility: does not apply"),
        (NHC, MTK + "\nevery = 5", "[barostat] every: does not apply to the mtk barostat"),
        (
            NHC + "\n[integrator.constraints]\nbonds = [[0, 1]]",
            MTK,
            "the mtk barostat does not keep [integrator.constraints]",
        ),
        (LANGEVIN, 'type = "c_rescale"\npressure = 1.0\ntau = 0.0', "tau: must be positive"),
        (LANGEVIN, 'type = "c_rescale"\npressure = 1.0\ntau = -1', "tau: must be positive"),
        (LANGEVIN, C_RESCALE + '\ncouple = "sideways"', "[barostat] couple: must be one of"),
        ('type = "verlet"\ndt = 0.005', C_RESCALE, "needs a thermostat"),
        (LANGEVIN, 'type = "c_rescale"\ntau = 1.0', "missing required key [barostat] pressure"),
    ],
)
def test_bad_barostat_input_exits_2_and_writes_nothing(
    tmp_path, capsys, integrator, barostat, message
):
    (tmp_path / "npt.toml").write_text(CONFIG.format(integrator=integrator, barostat=barostat))
    assert main(["run", "npt.toml", "--no-progress", "-q"]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "npt.h5").exists()


def test_berendsen_config_warns_that_it_does_not_sample_npt(tmp_path, caplog):
    from md.config import load_config

    berendsen = C_RESCALE.replace("c_rescale", "berendsen")
    (tmp_path / "npt.toml").write_text(CONFIG.format(integrator=LANGEVIN, barostat=berendsen))
    with caplog.at_level(logging.WARNING):
        config = load_config(tmp_path / "npt.toml")
    assert config.barostat.type == "berendsen"
    assert "does not sample the isothermal-isobaric ensemble" in caplog.text


def test_metal_pressure_in_bar_and_a_sweep_over_pressure(tmp_path):
    from md.config import load_config
    from md.sweeps.plan import plan_sweep
    from md.units import eV_per_A3_in_bar

    metal = (
        CONFIG.replace('units = "lj"', 'units = "metal"')
        .replace("density = 0.8", 'lattice_constant = 5.26\nmass = 39.948\ntype_name = "Ar"')
        .replace("temperature = 1.0\n[[", "temperature = 100.0\n[[")
        .replace("cutoff = 2.5", "epsilon = 0.0104\nsigma = 3.4\ncutoff = 8.0")
    )
    metal = metal.format(
        integrator=LANGEVIN.replace("temperature = 1.0", "temperature = 100.0")
        .replace("friction = 1.0", "friction = 0.01")
        .replace("dt = 0.005", "dt = 5.0"),
        barostat='type = "c_rescale"\npressure = 1.0\ntau = 1000.0',
    )
    (tmp_path / "metal.toml").write_text(metal)
    config = load_config(tmp_path / "metal.toml")
    assert config.barostat.get("pressure") == pytest.approx(1.0 / eV_per_A3_in_bar)  # 1 bar
    (tmp_path / "npt.toml").write_text(CONFIG.format(integrator=LANGEVIN, barostat=C_RESCALE))
    plan = plan_sweep(tmp_path / "npt.toml", vary=["barostat.pressure=0.5,1.0,2.0"])
    assert len(plan.runs) == 3


# ------------------------------------------------------------ anisotropic and triclinic
def _npt_series(couple, shear=None, temperature=1.5, pressure=2.0, density=0.75, steps=4000):
    """Density, pressure tensor and tilts every 10 steps (the first quarter dropped)."""
    state = md.lattice("fcc", 5, density=density, shear=shear)
    md.maxwell_boltzmann(state, temperature, seed=1)
    integrator = PressureCoupled(
        Langevin(0.005, temperature=temperature, friction=1.0, seed=2),
        Barostat(
            "c_rescale", pressure, tau=0.5, compressibility=0.1, couple=couple, every=10, seed=3
        ),
    )
    sim = md.Simulation(state, [LennardJones(epsilon=1.0, sigma=1.0, cutoff=2.5)], integrator)
    rows = []

    def record(s):
        thermo = s.thermo()
        rows.append(
            [s.state.n_atoms / s.state.volume]
            + [thermo[k] for k in ("pxx", "pyy", "pzz", "pxy", "pxz", "pyz")]
            + [*s.state.tilt, *s.state.box]
        )

    sim.attach(record, 10)
    sim.run(steps)
    rows = np.array(rows)
    return rows[len(rows) // 4 :], sim.state


def test_anisotropic_coupling_gives_the_isotropic_density_and_a_hydrostatic_pressure():
    from md.analysis import block_average

    isotropic, _ = _npt_series("isotropic")
    anisotropic, state = _npt_series("anisotropic")
    assert np.ptp(anisotropic[:, 10:13] / anisotropic[:, 10:11], axis=0)[1:].max() > 0.01
    a, b = block_average(isotropic[:, 0]), block_average(anisotropic[:, 0])
    assert abs(a.mean - b.mean) < 4 * np.hypot(a.sem, b.sem) + 0.002
    for column in (1, 2, 3):  # each diagonal component at the target pressure
        assert block_average(anisotropic[:, column]).mean == pytest.approx(2.0, rel=0.05)
    assert state.is_orthorhombic


def test_triclinic_coupling_relaxes_a_sheared_crystal_to_zero_shear_stress():
    """An fcc crystal sheared by xy = 0.15 Ly: the cell shears back and P_xy goes to zero."""
    from md.analysis import block_average

    state = md.lattice("fcc", 5, density=1.0, shear=(0.15, 0.0, 0.0))
    md.maxwell_boltzmann(state, 0.2, seed=1)
    forces = md.ForceField([LennardJones(epsilon=1.0, sigma=1.0, cutoff=2.5)]).compute(state)
    start = md.thermo.pressure_tensor(state.velocities, state.masses, forces.virial, state.volume)
    assert abs(start[0, 1]) > 0.5  # the shear stress the barostat must remove
    series, final = _npt_series(
        "triclinic", shear=(0.15, 0.0, 0.0), temperature=0.2, pressure=1.0, density=1.0
    )
    assert abs(block_average(series[:, 4]).mean) < 0.15
    assert np.abs(series[:, 7:10]).max() < 0.1 * series[:, 10:13].min()  # tilts near zero
    edges = series[:, 10:13].mean(axis=0)
    np.testing.assert_allclose(edges, edges.mean(), rtol=0.01)  # back to a cube
    for column in (1, 2, 3):
        assert block_average(series[:, column]).mean == pytest.approx(1.0, rel=0.05)
    assert np.all(np.abs(final.tilt) <= 0.5 * final.box[[0, 0, 1]])


def test_triclinic_coupling_in_a_config_writes_cell_matrices(tmp_path):
    barostat = C_RESCALE + '\ncouple = "triclinic"'
    (tmp_path / "npt.toml").write_text(
        CONFIG.format(integrator=LANGEVIN, barostat=barostat).replace("cells = 4", "cells = 5")
    )
    assert main(["run", "npt.toml", "--no-progress", "-q"]) == 0
    traj = read_trajectory("npt.h5")
    assert traj.cells().shape == (traj.n_frames, 3, 3)
    assert np.any(traj.tilts[-1] != 0.0)  # the cell sheared
    import h5py

    with h5py.File("npt.h5") as f:
        assert f["particles/trajectory/box/edges/value"].ndim == 3


# ------------------------------------------- the blow-up guard under a moving cell (issue 33)
NPT_GUARD = """
units = "lj"
seed = 11
[system]
lattice = "fcc"
cells = {cells}
density = {density}
temperature = {temperature}
{shear}
[[potentials]]
type = "lj"
cutoff = 2.5
[integrator]
type = "langevin"
dt = {dt}
temperature = {temperature}
friction = 1.0
[barostat]
type = "c_rescale"
pressure = {pressure}
tau = {tau}
compressibility = {compressibility}
couple = "{couple}"
[run]
steps = {steps}
thermo_every = 100
[output]
path = "npt.h5"
every = 50
"""
GUARD_CASES = {
    # Each of these stopped at step 10 ("atom ... moved 0.6-0.85 in one step, more than the
    # skin") before the guard measured motion relative to the moving cell.
    "pressure 30": dict(
        cells=5, density=0.8442, temperature=1.0, pressure=30.0, compressibility=0.1
    ),
    "cavitation": dict(cells=6, density=0.75, temperature=0.9, pressure=-2.0, compressibility=1.0),
    "dilute gas": dict(cells=4, density=0.05, temperature=1.0, pressure=2.0, compressibility=1.0),
    "sheared by 0.5": dict(
        cells=5,
        density=0.8442,
        temperature=0.5,
        pressure=0.0,
        compressibility=0.1,
        couple="triclinic",
        shear="shear = [0.5, 0.0, 0.0]",
    ),
}


def _guard_config(tmp_path, **values):
    settings = dict(dt=0.005, tau=1.0, couple="isotropic", shear="", steps=300) | values
    (tmp_path / "npt.toml").write_text(NPT_GUARD.format(**settings))


@pytest.mark.parametrize("case", GUARD_CASES)
def test_the_blow_up_guard_does_not_count_the_barostats_affine_move(tmp_path, capsys, case):
    """The box's own move carries far atoms more than the skin: not a blow-up."""
    _guard_config(tmp_path, **GUARD_CASES[case])
    assert main(["run", "npt.toml", "--no-progress", "-q"]) == 0, capsys.readouterr().err
    traj = read_trajectory("npt.h5")
    volume, pressure = traj.observables["volume"], traj.observables["pressure"]
    start = volume[0]
    if case == "pressure 30":
        assert volume[-1] < 0.8 * start
        assert np.mean(pressure[2:]) == pytest.approx(30.0, rel=0.15)
    elif case == "dilute gas":
        assert volume[-1] < 0.3 * start  # compressed towards P = 2
    elif case == "cavitation":
        assert volume[-1] > 2 * start  # stretched past what the liquid holds: it cavitates
    else:  # the shear stress is relaxed, the cell sheared back
        assert abs(traj.observables["pxy"][0]) > 10
        assert np.abs(traj.observables["pxy"][2:]).max() < 1.0
        assert traj.tilts[-1, 0] < 0.9 * traj.tilts[0, 0]


def test_a_blow_up_under_a_barostat_is_still_caught(tmp_path, capsys):
    _guard_config(tmp_path, **GUARD_CASES["pressure 30"] | dict(dt=0.04, tau=100.0))
    assert main(["run", "npt.toml", "--no-progress", "-q"]) == 1
    assert "in one step, more than the neighbour-list skin 0.3" in capsys.readouterr().err


def test_an_absurd_barostat_move_is_named_with_the_box_strain_and_tau(tmp_path, capsys):
    _guard_config(tmp_path, **GUARD_CASES["pressure 30"] | dict(tau=0.3))
    assert main(["run", "npt.toml", "--no-progress", "-q"]) == 1
    err = capsys.readouterr().err
    assert "step 10: the barostat moved the box by 17.2% in one step" in err
    assert "use a larger [barostat] tau" in err


def test_the_displacement_guard_sees_through_a_tilt_flip():
    """A move right after the cell's tilt flipped to the shorter one (a lattice-basis change,
    no motion): the deformation is the barostat's, not the flip's."""
    from md.box import cell_deformation, reduced_tilt

    box, tilt, pbc = np.array([6.0, 6.0, 6.0]), np.array([2.99, 0.0, 0.0]), np.ones(3, bool)
    mu = np.eye(3)
    mu[1, 0] = 0.01  # a small shear that takes xy past Lx / 2
    cell = md.box.cell_matrix(box, tilt) @ mu
    new_box = np.diag(cell).copy()
    new_tilt = reduced_tilt(new_box, cell[[1, 2, 2], [0, 0, 1]], pbc)
    assert new_tilt[0] < 0  # flipped
    np.testing.assert_allclose(cell_deformation(box, tilt, new_box, new_tilt, pbc), mu, atol=1e-14)


def _manual_npt_snippet(root) -> str:
    """The first TOML block under the manual's "Pressure control" heading (was README's)."""
    page = (root / "docs" / "guide" / "thermostats-and-barostats.md").read_text()
    section = page[page.index("## Pressure control") :]
    start = section.index("```toml\n") + len("```toml\n")
    return section[start : section.index("```", start)]


@pytest.mark.slow
def test_the_documented_npt_snippet_runs_the_32000_atom_melt(tmp_path):
    """examples/lj_melt.toml under the manual's (formerly README's) NPT snippet stopped at
    step 20 as "blowing up" (atom 31999 moved 0.37); it runs its 1000 steps to T 1 and P 1."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    text = (root / "examples" / "lj_melt.toml").read_text()
    head, _, tail = text.partition("[integrator]")
    tail = tail[tail.index("[run]") :]
    snippet = _manual_npt_snippet(root)
    assert "[barostat]" in snippet and 'type = "c_rescale"' in snippet
    (tmp_path / "npt.toml").write_text(head + snippet.strip() + "\n\n" + tail)
    done = subprocess.run(
        [sys.executable, "-m", "md.cli", "run", "npt.toml", "--no-progress", "-q"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        env={**__import__("os").environ, "PYTHONPATH": str(root)},
    )
    assert done.returncode == 0, done.stderr
    traj = read_trajectory(tmp_path / "lj_melt.h5")
    assert traj.steps[-1] == 1000
    assert np.mean(traj.observables["temperature"][-4:]) == pytest.approx(1.0, rel=0.05)
    assert np.mean(traj.observables["pressure"][-4:]) == pytest.approx(1.0, abs=0.3)


# ------------------------------------------------------- overshoot and open axes (issue 33)
@pytest.mark.parametrize("couple", ["isotropic", "anisotropic"])
@pytest.mark.parametrize("barostat", ["pressure = 1.0\ntau = 0.001", "pressure = 500.0\ntau = 1.0"])
def test_a_berendsen_move_that_overshoots_fails_with_a_message(tmp_path, capsys, couple, barostat):
    """1 - beta dt (P0 - P) / tau < 0: was a TypeError (the complex cube root) when isotropic."""
    barostat = f'type = "berendsen"\n{barostat}\ncouple = "{couple}"'
    (tmp_path / "npt.toml").write_text(CONFIG.format(integrator=LANGEVIN, barostat=barostat))
    assert main(["run", "npt.toml", "--no-progress", "-q"]) == 1
    err = capsys.readouterr().err
    assert "step 10: the berendsen barostat's " in err
    assert "its move overshoots" in err and "use a larger [barostat] tau" in err
    assert "Traceback" not in err
    assert read_trajectory("npt.h5").n_frames == 1  # the frames before it are kept


def test_berendsen_scale_factor_is_the_real_cube_root():
    barostat = Barostat("berendsen", 1.0, tau=0.001, compressibility=0.1)
    assert barostat.scale_factor(0.0, 100.0, 1.0, 0.05) == pytest.approx(-(4.0 ** (1 / 3)))
    assert barostat.scale_factor(0.999, 100.0, 1.0, 0.05) == pytest.approx(0.995 ** (1 / 3))


OPEN_SYSTEM = CONFIG.replace("temperature = 1.0\n[[", "temperature = 1.0\npbc = {pbc}\n[[")


@pytest.mark.parametrize(
    ("pbc", "barostat", "message"),
    [
        ("false", C_RESCALE, "the c_rescale barostat needs periodic axes"),
        ("false", C_RESCALE.replace("c_rescale", "berendsen"), "the berendsen barostat needs"),
        ("false", C_RESCALE + '\ncouple = "anisotropic"', "periodic along none"),
        (
            "[true, true, false]",
            C_RESCALE,
            "isotropic coupling scales all three edges, but the system is open along z",
        ),
        (
            "[true, true, false]",
            MTK,
            "[barostat]: the mtk barostat needs a box periodic along "
            "x, y and z; the system is open along z",
        ),
    ],
)
def test_a_barostat_refuses_what_it_cannot_scale(tmp_path, capsys, pbc, barostat, message):
    integrator = NHC if "mtk" in barostat else LANGEVIN
    config = OPEN_SYSTEM.replace("{pbc}", pbc).format(integrator=integrator, barostat=barostat)
    (tmp_path / "npt.toml").write_text(config)
    assert main(["run", "npt.toml", "--no-progress", "-q"]) == 2
    err = capsys.readouterr().err
    assert message in err
    assert "cannot create" not in err
    assert not (tmp_path / "npt.h5").exists() and not (tmp_path / "npt.h5.ckpt").exists()


def test_anisotropic_coupling_of_a_slab_keeps_the_open_edge(tmp_path):
    barostat = C_RESCALE + '\ncouple = "anisotropic"'
    config = OPEN_SYSTEM.replace("{pbc}", "[true, true, false]")
    (tmp_path / "npt.toml").write_text(config.format(integrator=LANGEVIN, barostat=barostat))
    assert main(["run", "npt.toml", "--no-progress", "-q"]) == 0
    boxes = read_trajectory("npt.h5").boxes
    assert np.all(boxes[:, 2] == boxes[0, 2]) and np.ptp(boxes[:, 0]) > 0


def test_the_python_api_refuses_an_open_cluster_too():
    state = md.lattice("fcc", 4, density=0.8, pbc=False)
    md.maxwell_boltzmann(state, 1.0, seed=1)
    integrator = PressureCoupled(
        Langevin(0.005, temperature=1.0, friction=1.0, seed=2),
        Barostat("c_rescale", 1.0, tau=1.0, compressibility=0.1),
    )
    sim = md.Simulation(state, [LennardJones(cutoff=2.5)], integrator)
    with pytest.raises(ValueError, match="periodic along none"):
        sim.run(10)
