"""The Martyna-Tobias-Klein barostat with Nose-Hoover chains (integrators/mtk.py).

Checked against exact properties of the scheme and against an independent
barostat: the extended energy is conserved to second order in dt (isotropic,
anisotropic, triclinic); the step is time reversible; the mean density, the
pressure and the temperature of an LJ liquid equal those that stochastic cell
rescaling (a different NPT method) gives at the same state point; triclinic
coupling takes a sheared crystal back to zero shear stress; ``md run`` stores
the conserved energy, resumes bit for bit, and ``md analyze`` measures the
drift on it. (LAMMPS's ``fix npt`` is compared in tests/test_lammps_peer.py.)
"""

from __future__ import annotations

import numpy as np
import pytest

import md
from integrators import Langevin, NoseHooverChain, VelocityVerlet
from integrators.barostats import Barostat, PressureCoupled, pressure_control
from integrators.mtk import MartynaTobiasKlein, exp_and_phi
from md.analysis import block_average
from md.cli import main
from md.sweeps.summary import summarize
from md.trajectory import read_trajectory
from potentials import LennardJones


def _mtk_sim(
    couple="isotropic",
    dt=0.004,
    cells=4,
    density=0.7,
    temperature=1.5,
    pressure=2.0,
    shear=None,
    tau_p=1.0,
    seed=1,
):
    state = md.lattice("fcc", cells, density=density, shear=shear)
    md.maxwell_boltzmann(state, temperature, seed=seed)
    integrator = pressure_control(
        NoseHooverChain(dt, temperature=temperature, tau=0.5),
        Barostat("mtk", pressure, tau=tau_p, couple=couple),
    )
    return md.Simulation(state, [LennardJones(cutoff=2.5)], integrator)


@pytest.mark.parametrize(
    "x",
    [
        [[0.3, -0.2, 0.1], [0.0, -0.4, 0.25], [0.0, 0.0, 0.3]],  # a repeated eigenvalue
        [[0.3, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, -1e-9]],  # diagonal, one zero
    ],
    ids=["triangular", "diagonal"],
)
def test_exp_and_phi_equal_their_series(x):
    x = np.array(x)
    e, phi = exp_and_phi(x)
    term, e_series, phi_series = np.eye(3), np.zeros((3, 3)), np.zeros((3, 3))
    for k in range(30):  # term = x^k / k!
        e_series += term
        phi_series += term / (k + 1)
        term = term @ x / (k + 1)
    np.testing.assert_allclose(e, e_series, atol=1e-14)
    np.testing.assert_allclose(phi, phi_series, atol=1e-14)


@pytest.mark.parametrize("couple", ["isotropic", "anisotropic", "triclinic"])
def test_extended_energy_is_conserved_to_second_order_in_dt(couple):
    """Halving dt divides the conserved quantity's largest excursion by about four."""
    excursions = []
    for dt in (0.004, 0.002):
        sim = _mtk_sim(couple, dt=dt)
        start = sim.thermo()
        conserved, total = [], []
        for _ in range(40):
            sim.run(int(round(0.04 / dt)))
            row = sim.thermo()
            conserved.append(row["conserved_energy"] - start["conserved_energy"])
            total.append(row["total_energy"] - start["total_energy"])
        assert np.ptp(sim.integrator.omega) > 0  # the cell moved
        assert np.max(np.abs(total)) > 100 * np.max(np.abs(conserved))
        excursions.append(np.max(np.abs(conserved)))
    n_atoms = sim.state.n_atoms
    print(
        f"{couple}: largest excursion per atom {excursions[0] / n_atoms:.2e} at dt 0.004, "
        f"ratio {excursions[0] / excursions[1]:.2f}"
    )
    assert excursions[0] / n_atoms < 2e-3
    assert 3.0 < excursions[0] / excursions[1] < 5.5


def test_the_step_is_time_reversible():
    sim = _mtk_sim("triclinic")
    sim.run(50)  # get the cell and both chains moving
    start = sim.state.copy()
    sim.run(250)
    state = sim.state
    saved = sim.integrator.get_state()
    for variables in (saved, saved["chain"]):
        variables["v_xi"] = [-v for v in variables["v_xi"]]
    saved["omega"] = (-np.array(saved["omega"])).tolist()
    sim.integrator.set_state(saved)
    state.velocities *= -1.0
    sim.run(250)
    np.testing.assert_allclose(state.positions, start.positions, atol=1e-8)
    np.testing.assert_allclose(state.velocities, -start.velocities, atol=1e-8)
    np.testing.assert_allclose(state.cell, start.cell, atol=1e-10)


def _liquid_series(integrator, steps=6000, every=10):
    """Density, pressure and temperature of a 500-atom LJ liquid at T = 1.5, P = 2."""
    state = md.lattice("fcc", 5, density=0.68)
    md.maxwell_boltzmann(state, 1.5, seed=11)
    sim = md.Simulation(state, [LennardJones(cutoff=2.5)], integrator)
    sim.run(1000)
    rows = []
    sim.attach(
        lambda s: rows.append([s.thermo()[k] for k in ("density", "pressure", "temperature")]),
        every,
    )
    sim.run(steps)
    return np.array(rows)


@pytest.mark.slow  # 9-18 s; keeps the cold default suite within 10 minutes on 2 cores
def test_mtk_gives_the_density_of_stochastic_cell_rescaling():
    mtk = _liquid_series(
        pressure_control(
            NoseHooverChain(0.005, temperature=1.5, tau=0.5), Barostat("mtk", 2.0, tau=1.0)
        )
    )
    c_rescale = _liquid_series(
        PressureCoupled(
            Langevin(0.005, temperature=1.5, friction=1.0, seed=12),
            Barostat("c_rescale", 2.0, tau=0.5, compressibility=0.1, every=10, seed=13),
        )
    )
    a, b = block_average(mtk[:, 0]), block_average(c_rescale[:, 0])
    print(f"density: mtk {a.mean:.4f} +- {a.sem:.4f}, c_rescale {b.mean:.4f} +- {b.sem:.4f}")
    assert abs(a.mean - b.mean) < 4 * np.hypot(a.sem, b.sem) + 0.002
    assert block_average(mtk[:, 1]).mean == pytest.approx(2.0, abs=0.08)
    assert block_average(mtk[:, 2]).mean == pytest.approx(1.5, rel=0.02)


def test_anisotropic_mtk_brings_each_diagonal_pressure_to_the_target():
    """An fcc crystal stretched along x and squeezed along z goes back to a cube, with each
    diagonal pressure component at the target (a liquid's box shape would wander freely)."""
    sim = _mtk_sim("anisotropic", dt=0.005, cells=4, density=1.0, temperature=0.2, pressure=1.0)
    strain = np.array([1.04, 1.0, 0.97])
    sim.state.positions *= strain
    sim.state.box = sim.state.box * strain
    sim.run(1000)
    rows = []

    def record(s):
        row = s.thermo()
        rows.append([row["pxx"], row["pyy"], row["pzz"], *s.state.box])

    sim.attach(record, 10)
    sim.run(3000)
    rows = np.array(rows)
    for column in rows[:, :3].T:
        assert block_average(column).mean == pytest.approx(1.0, abs=0.15)
    edges = rows[:, 3:].mean(axis=0)
    np.testing.assert_allclose(edges, edges.mean(), rtol=0.01)


def test_triclinic_mtk_relaxes_a_sheared_crystal_to_zero_shear_stress():
    """An fcc crystal sheared by xy = 0.15 Ly: P_xy and the tilt go to zero on average."""
    sim = _mtk_sim(
        "triclinic",
        dt=0.005,
        cells=4,
        density=1.0,
        temperature=0.2,
        pressure=1.0,
        shear=(0.15, 0.0, 0.0),
        tau_p=1.0,
    )
    assert abs(sim.thermo()["pxy"]) > 0.5  # the shear stress the barostat must remove
    sim.run(1000)
    rows = []

    def record(s):
        row = s.thermo()
        rows.append([row["pxy"], *s.state.tilt, *s.state.box])

    sim.attach(record, 10)
    sim.run(3000)
    rows = np.array(rows)
    assert abs(block_average(rows[:, 0]).mean) < 0.15
    assert np.abs(rows[:, 1:4].mean(axis=0)).max() < 0.02 * rows[:, 4:].min()
    edges = rows[:, 4:].mean(axis=0)
    np.testing.assert_allclose(edges, edges.mean(), rtol=0.01)  # back to a cube


def test_mtk_needs_nose_hoover_chains_without_constraints_in_a_periodic_box():
    barostat = Barostat("mtk", 1.0, tau=1.0)
    with pytest.raises(ValueError, match="runs with its own Nose-Hoover chains"):
        pressure_control(Langevin(0.005, temperature=1.0, friction=1.0), barostat)
    with pytest.raises(ValueError, match="not an NVE integrator"):
        pressure_control(VelocityVerlet(0.005), barostat)
    with pytest.raises(ValueError, match="its own integrator"):
        PressureCoupled(NoseHooverChain(0.005, temperature=1.0, tau=0.5), barostat)
    with pytest.raises(ValueError, match="does not keep rigid bonds"):
        MartynaTobiasKlein(
            NoseHooverChain(0.005, temperature=1.0, tau=0.5, constraints=[[0, 1]]), barostat
        )
    state = md.lattice("fcc", 3, density=0.7)
    state.pbc = np.array([True, True, False])
    integrator = pressure_control(NoseHooverChain(0.005, temperature=1.0, tau=0.5), barostat)
    sim = md.Simulation(state, [LennardJones(cutoff=2.5)], integrator)
    with pytest.raises(ValueError, match="periodic along x, y and z"):
        sim.run(1)


CONFIG = """
units = "lj"
seed = 3
[system]
lattice = "fcc"
cells = 4
density = 0.7
temperature = 1.5
[[potentials]]
type = "lj"
cutoff = 2.5
[integrator]
type = "nose_hoover_chain"
dt = 0.004
temperature = 1.5
tau = 0.5
[barostat]
type = "mtk"
pressure = 2.0
tau = 1.0
couple = "{couple}"
[run]
steps = 300
thermo_every = 50
[output]
path = "npt.h5"
every = 20
checkpoint_every = 100
"""


@pytest.mark.parametrize("couple", ["isotropic", "triclinic"])
def test_md_run_with_mtk_stores_the_conserved_energy_and_resumes_bit_for_bit(
    tmp_path, monkeypatch, capsys, couple
):
    from md.analysis import thermo

    monkeypatch.chdir(tmp_path)
    (tmp_path / "npt.toml").write_text(CONFIG.format(couple=couple))
    quiet = ("--no-progress", "-q")
    assert main(["run", "npt.toml", "-o", "whole.h5", *quiet]) == 0
    assert main(["run", "npt.toml", "-o", "part.h5", "--steps", "200", *quiet]) == 0
    assert main(["run", "npt.toml", "-o", "part.h5", "--resume", *quiet]) == 0
    whole, part = read_trajectory("whole.h5"), read_trajectory("part.h5")
    assert np.ptp(whole.observables["volume"]) > 0
    assert np.array_equal(whole.positions, part.positions)
    assert np.array_equal(whole.cells(), part.cells())
    assert np.array_equal(
        whole.observables["conserved_energy"], part.observables["conserved_energy"]
    )
    result = thermo("whole.h5")
    assert result.drift_of == "conserved_energy"
    total = whole.observables["total_energy"]
    conserved = whole.observables["conserved_energy"]
    assert np.ptp(conserved) < 0.02 * np.ptp(total)
    assert abs(result.energy_drift) < 1e-3  # per atom and time unit
    row = summarize("whole.h5")  # a sweep's row: the same drift, and the density
    assert row["energy_drift_per_atom"] == result.energy_drift
    assert row["density"] == pytest.approx(np.mean(whole.observables["density"]))
    assert row["density_err"] > 0
    capsys.readouterr()
    assert main(["info", "whole.h5"]) == 0
    assert "conserved " in capsys.readouterr().out
