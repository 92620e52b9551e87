"""FIRE 2.0 minimisation, the capped-force push-off, md minimize and the [minimize] stage."""

from __future__ import annotations

import numpy as np
import pytest
from ase.optimize import FIRE as AseFIRE

import md
from md.calculator import MDCalculator
from md.cli import main
from md.minimize import FIRE, minimize
from md.trajectory import read_trajectory
from potentials import LennardJones

MELT = """
units = "lj"
seed = 7
[system]
polymer = "melt"
chains = 8
chain_length = 10
density = 0.85
bond_length = 0.97
temperature = 1.0
[[potentials]]
type = "lj"
cutoff = 1.122462048309373
cutoff_mode = "shift"
[[potentials]]
type = "fene"
bonds = "system"
k = 30.0
r_max = 1.5
{minimize}
[integrator]
type = "langevin"
dt = 0.005
temperature = 1.0
friction = 0.5
[run]
steps = 40
thermo_every = 10
[output]
path = "melt.h5"
every = 10
velocities = true
checkpoint_every = 20
"""
STAGE = "[minimize]\nfmax = 1.0\nmax_steps = 2000\nmax_force = 100.0"
QUIET = ("--no-progress", "-q")


@pytest.fixture(autouse=True)
def in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)


def _max_force(state, forcefield):
    forces = forcefield.compute(state).forces
    return float(np.sqrt(np.max(np.sum(forces**2, axis=1))))


def _cluster(seed=1, scale=0.05):
    state = md.lattice("fcc", 2, density=1.0, pbc=False)  # 32 atoms
    state.positions += np.random.default_rng(seed).normal(scale=scale, size=state.positions.shape)
    return state


def test_fire_reaches_fmax_on_an_lj_cluster_and_matches_ase_fire():
    state = _cluster()
    start = state.copy()
    forcefield = md.ForceField([LennardJones(cutoff=8.0)])
    energy0 = forcefield.compute(state).energy
    result = minimize(state, forcefield, fmax=1e-5, max_steps=20_000)
    assert result.converged and result.fmax <= 1e-5
    assert _max_force(state, forcefield) <= 1e-5 and result.energy < energy0
    atoms = start.to_ase()
    atoms.calc = MDCalculator([LennardJones(cutoff=8.0)], units="lj")
    AseFIRE(atoms, logfile=None).run(fmax=1e-5, steps=20_000)
    assert atoms.get_potential_energy() == pytest.approx(result.energy, abs=1e-8)


def test_fire_relaxes_a_disordered_crystal_to_the_lattice_energy():
    state = md.lattice("fcc", 4, density=0.9)
    perfect = md.ForceField([LennardJones(cutoff=2.5)]).compute(state).energy
    state.positions += np.random.default_rng(2).normal(scale=0.08, size=state.positions.shape)
    forcefield = md.ForceField([LennardJones(cutoff=2.5)])
    result = minimize(state, forcefield, fmax=1e-6, max_steps=5000)
    assert result.converged and _max_force(state, forcefield) <= 1e-6
    assert result.energy == pytest.approx(perfect, rel=1e-9)  # back on the lattice


def test_the_push_off_caps_the_forces_of_overlapping_atoms():
    """Atoms 0.3 sigma apart (force ~1e7): no step moves an atom farther than max_step."""
    state = md.State(positions=[[5, 5, 5], [5.3, 5, 5], [7, 5, 5]], box=20.0, pbc=False)
    forcefield = md.ForceField([LennardJones(cutoff=5.0)])
    assert _max_force(state, forcefield) > 1e5
    snapshots = []

    def watch(step, energy, fmax):
        snapshots.append(state.positions.copy())

    fire = FIRE(max_force=10.0, max_step=0.05)
    result = fire.run(state, forcefield, fmax=1e-4, max_steps=5000, callback=watch, report_every=1)
    assert result.converged
    steps = [np.abs(b - a).max() for a, b in zip(snapshots, snapshots[1:], strict=False)]
    assert max(steps) <= 0.05 + 1e-12
    gaps = np.diff(np.sort(state.positions[:, 0]))
    assert gaps[0] == pytest.approx(gaps[1], abs=1e-5)  # a symmetric chain of three
    assert gaps[0] == pytest.approx(2 ** (1 / 6), abs=0.01)  # near the pair minimum


def test_minimize_refuses_bad_targets():
    state, forcefield = _cluster(), md.ForceField([LennardJones(cutoff=8.0)])
    with pytest.raises(ValueError, match="fmax must be finite and > 0"):
        minimize(state, forcefield, fmax=0.0)
    with pytest.raises(ValueError, match="max_steps must be an integer >= 1"):
        minimize(state, forcefield, fmax=1e-3, max_steps=0)


def test_minimize_stage_starts_the_melt_near_its_temperature(tmp_path):
    (tmp_path / "melt.toml").write_text(MELT.format(minimize=STAGE))
    (tmp_path / "raw.toml").write_text(MELT.format(minimize="").replace("melt.h5", "raw.h5"))
    assert main(["run", "melt.toml", "--steps", "40", *QUIET]) == 0
    assert main(["run", "raw.toml", "--steps", "40", *QUIET]) == 0
    relaxed, raw = read_trajectory("melt.h5"), read_trajectory("raw.h5")
    # frame 0 is the minimised structure: its forces are below fmax
    state = relaxed.state(0)
    from md.assemble import build_components
    from md.config import load_config

    _, potentials, _ = build_components(load_config(tmp_path / "melt.toml"))
    assert _max_force(state, md.ForceField(potentials)) <= 1.0
    # the overlaps' energy is gone: the raw start heats up within 0.2 tau, the relaxed one not
    assert raw.observables["temperature"][-1] > 2.0
    assert relaxed.observables["temperature"][-1] < 1.5


def test_resume_after_the_minimize_stage_is_bit_for_bit(tmp_path):
    (tmp_path / "melt.toml").write_text(MELT.format(minimize=STAGE))
    assert main(["run", "melt.toml", "-o", "whole.h5", *QUIET]) == 0
    assert main(["run", "melt.toml", "-o", "part.h5", "--steps", "20", *QUIET]) == 0
    assert main(["run", "melt.toml", "-o", "part.h5", "--resume", *QUIET]) == 0  # no re-minimising
    whole, part = read_trajectory("whole.h5"), read_trajectory("part.h5")
    assert np.array_equal(whole.positions, part.positions)
    assert np.array_equal(whole.velocities, part.velocities)


def test_md_minimize_writes_a_structure_a_run_can_start_from(tmp_path, capsys):
    (tmp_path / "melt.toml").write_text(MELT.format(minimize=STAGE))
    assert main(["minimize", "melt.toml", "-o", "relaxed.h5"]) == 0
    out = capsys.readouterr().out
    assert "converged after" in out and "max force" in out
    relaxed = read_trajectory("relaxed.h5")
    assert relaxed.n_frames == 1 and relaxed.topology.n_bonds == 8 * 9
    start = MELT.format(minimize="").replace(
        'polymer = "melt"\nchains = 8\nchain_length = 10\ndensity = 0.85\nbond_length = 0.97',
        'structure = "relaxed.h5"',
    )
    (tmp_path / "start.toml").write_text(start.replace("melt.h5", "start.h5"))
    assert main(["run", "start.toml", *QUIET]) == 0
    assert read_trajectory("start.h5").observables["temperature"][-1] < 1.5
    assert main(["minimize", "melt.toml", "-o", "relaxed.h5"]) == 2  # exists
    assert "already exists" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("stage", "message"),
    [
        ("[minimize]\nfmax = 0.0", "fmax: must be positive"),
        ("[minimize]\nfmax = -1.0", "fmax: must be positive"),
        ("[minimize]\nmax_steps = 0", "max_steps: must be >= 1"),
        ("[minimize]\nmax_force = 0", "max_force: must be positive"),
        ("[minimize]\nfmx = 1.0", "unknown key"),
    ],
)
def test_bad_minimize_tables_exit_2_and_write_nothing(tmp_path, capsys, stage, message):
    (tmp_path / "melt.toml").write_text(MELT.format(minimize=stage))
    assert main(["run", "melt.toml", *QUIET]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "melt.h5").exists()
    assert main(["minimize", "melt.toml"]) == 2
