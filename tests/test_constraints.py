"""Rigid bonds: SHAKE/RATTLE keep lengths, conserve energy like velocity Verlet, give the
constraint forces, remove degrees of freedom, and fail loudly; configs build them."""

from __future__ import annotations

import math

import numpy as np
import pytest

import md
from integrators import BondConstraints, ConstraintError, Langevin, Rattle
from integrators.rattle import constrained_verlet_step
from md.cli import main
from md.config import ConfigError, integrator_from_config, parse_config
from md.observers import ThermoLog
from md.polymers import polymer_melt
from md.studies import statistical_inefficiency
from potentials import LennardJones

WCA = 2.0 ** (1.0 / 6.0)


def _wca():
    return [LennardJones(cutoff=WCA, cutoff_mode="shift")]


@pytest.fixture(scope="module")
def melt():
    """10 chains of 8 beads with unit bonds, WCA repulsion, thermalised at T = 1."""
    state, bonds = polymer_melt(10, 8, density=0.7, bond_length=1.0, seed=3)
    md.maxwell_boltzmann(state, 1.0, seed=2)
    constraints = BondConstraints(bonds, lengths=1.0, tol=1e-10)
    sim = md.Simulation(
        state, _wca(), Langevin(0.002, 1.0, friction=5.0, seed=1, constraints=constraints)
    )
    sim.run(1000)
    state.step, state.time = 0, 0.0
    return state, bonds


def _velocity_errors(state, bonds, dt):
    i, j = bonds[:, 0], bonds[:, 1]
    r = md.box.minimum_image(state.positions[i] - state.positions[j], state.box, state.pbc)
    v = state.velocities[i] - state.velocities[j]
    return np.abs(np.einsum("ij,ij->i", r, v)) * dt / np.einsum("ij,ij->i", r, r)


def _run_nve(state, bonds, dt, time, tol=1e-10, interval=10):
    constraints = BondConstraints(bonds, lengths=1.0, tol=tol)
    sim = md.Simulation(state.copy(), _wca(), Rattle(dt, constraints))
    log = ThermoLog()
    sim.attach(log, interval=interval)
    worst = 0.0
    for _ in range(round(time / dt) // 100):
        sim.run(100)
        worst = max(worst, constraints.errors(sim.state).max())
    return sim, log.rows, worst


def test_rattle_keeps_bonds_at_length_over_thousands_of_steps(melt):
    state, bonds = melt
    sim, rows, worst = _run_nve(state, bonds, 0.004, 20.0)  # 5000 steps
    assert sim.state.step == 5000
    assert worst <= 1.01e-10  # every 100 steps, every bond, within tol
    assert _velocity_errors(sim.state, bonds, 0.004).max() <= 1.01e-10
    momentum = (sim.state.masses[:, None] * sim.state.velocities).sum(axis=0)
    assert np.abs(momentum).max() < 1e-10


def test_constrained_nve_energy_is_conserved_like_velocity_verlet(melt):
    """Energy fluctuation that shrinks fourfold when dt halves (second order), and no
    drift beyond 5e-4 kT per atom over 20 tau (the fluctuation's size at dt = 0.004;
    what remains wanders with either sign, from the WCA force's kink at the cutoff)."""
    state, bonds = melt
    spreads = []
    for dt in (0.004, 0.002):
        sim, rows, _ = _run_nve(state, bonds, dt, 20.0, interval=round(0.04 / dt))
        times = np.array([r["time"] for r in rows])
        energy = np.array([r["total_energy"] for r in rows]) / state.n_atoms
        slope, intercept = np.polyfit(times, energy, 1)
        spread = np.std(energy - slope * times - intercept)
        assert abs(slope) * times[-1] < 5e-4
        spreads.append(spread)
    assert 3.0 < spreads[0] / spreads[1] < 5.0
    assert spreads[0] < 5e-4  # per atom, at T = 1


def test_rattle_is_time_reversible(melt):
    state, bonds = melt
    constraints = BondConstraints(bonds, lengths=1.0, tol=1e-13, max_iter=5000)
    forcefield = md.ForceField(_wca())
    work = state.copy()
    constraints.bind(work, 0.004)
    start = work.copy()
    for _ in range(300):
        constrained_verlet_step(work, forcefield, 0.004, constraints)
    work.velocities *= -1
    for _ in range(300):
        constrained_verlet_step(work, forcefield, 0.004, constraints)
    assert np.abs(work.positions - start.positions).max() < 1e-8
    assert np.abs(work.velocities + start.velocities).max() < 1e-7


def test_constraint_forces_match_the_dynamics(melt):
    """m (v(t + h) - v(t - h)) / 2h - F(t) from tiny RATTLE steps equals the solved forces."""
    state, bonds = melt
    h = 1e-4
    constraints = BondConstraints(bonds, lengths=1.0, tol=1e-14, max_iter=10000)
    forcefield = md.ForceField(_wca())
    work = state.copy()
    constraints.bind(work, h)
    constrained_verlet_step(work, forcefield, h, constraints)
    before = work.velocities.copy()
    constrained_verlet_step(work, forcefield, h, constraints)
    middle = work.copy()
    forces = forcefield.compute(middle).forces
    constrained_verlet_step(work, forcefield, h, constraints)
    dynamics = middle.masses[:, None] * (work.velocities - before) / (2 * h) - forces
    solved, virial = constraints.constraint_forces(middle, forces)
    scale = np.abs(solved).max()
    assert scale > 1.0  # bonds carry real tension
    np.testing.assert_allclose(solved, dynamics, rtol=0, atol=1e-4 * scale)
    np.testing.assert_allclose(solved.sum(axis=0), 0.0, atol=1e-9 * scale)
    np.testing.assert_allclose(virial, virial.T, atol=1e-12 * scale)


def test_rigid_dimer_gas_pressure_is_the_molecular_ideal_gas(rng):
    """Non-interacting rigid dimers: 2K + tr W_c = sum over molecules of M V_com^2,
    so P = 2 K_trans / 3V, the ideal gas of molecules, exactly at every instant."""
    n_molecules, box = 30, 12.0
    centres = rng.uniform(0, box, size=(n_molecules, 3))
    axes = rng.normal(size=(n_molecules, 3))
    axes /= np.linalg.norm(axes, axis=1)[:, None]
    masses = np.tile([1.0, 3.0], n_molecules)
    positions = np.repeat(centres, 2, axis=0) + np.kron(axes, [[0.5], [-0.5]]).reshape(-1, 3)
    state = md.State(positions=positions, masses=masses, box=box, pbc=True)
    md.maxwell_boltzmann(state, 1.0, seed=rng)
    bonds = np.arange(2 * n_molecules).reshape(-1, 2)
    quiet = [LennardJones(epsilon=0.0, cutoff=1.0)]
    sim = md.Simulation(state, quiet, Langevin(0.005, 1.0, friction=1.0, seed=1, constraints=bonds))
    for _ in range(3):
        sim.run(50)
        momenta = (masses[:, None] * state.velocities).reshape(n_molecules, 2, 3).sum(axis=1)
        molecular = np.einsum("ij,ij->", momenta, momenta) / (4.0)  # M = 4
        expected = molecular / (3 * box**3)
        assert sim.thermo()["pressure"] == pytest.approx(expected, rel=1e-8)
    # Without the constraint virial the atomic kinetic pressure would be wrong:
    kinetic = 0.5 * np.einsum("i,ij,ij->", masses, state.velocities, state.velocities)
    assert 2 * kinetic / (3 * box**3) > 1.3 * expected


def test_temperature_counts_one_degree_of_freedom_less_per_bond(melt):
    """Langevin with rigid bonds equilibrates at the target only if the temperature
    uses 3N - 3 - B degrees of freedom (3N - 3 would read 100 B / (3N - 3) % low)."""
    state, bonds = melt
    integrator = Langevin(
        0.004, 1.0, friction=5.0, seed=4, constraints=BondConstraints(bonds, lengths=1.0)
    )
    sim = md.Simulation(state.copy(), _wca(), integrator)
    log = ThermoLog()
    sim.attach(log, interval=4)
    sim.run(6000)
    n_dof = 3 * state.n_atoms - 3 - len(bonds)
    assert integrator.degrees_of_freedom(state.n_atoms) == n_dof
    row = log.rows[-1]
    assert row["temperature"] == pytest.approx(2 * row["kinetic_energy"] / n_dof, rel=1e-12)
    temperatures = np.array([r["temperature"] for r in log.rows])
    g = statistical_inefficiency(temperatures)
    error = math.sqrt(temperatures.var() * g / len(temperatures))
    assert abs(temperatures.mean() - 1.0) < 3.5 * error
    assert error < 0.1 * len(bonds) / (3 * state.n_atoms - 3)  # the test can tell


@pytest.mark.parametrize(
    "make",
    [
        lambda c: Rattle(0.004, c),
        lambda c: Langevin(0.004, 1.0, friction=1.0, seed=2, constraints=c),
    ],
    ids=["rattle", "langevin"],
)
def test_saved_state_resumes_exactly_with_starting_lengths(melt, make):
    """Lengths taken from the first state travel in get_state(): a run resumed from a
    later state (whose bonds are only within tol = 1e-8 of them) continues the same
    trajectory, up to the round-off of a neighbour list rebuilt in another order
    (md run also restores the list, and its resumed runs match bit for bit)."""
    state, bonds = melt
    first = make(BondConstraints(bonds, tol=1e-8))
    sim = md.Simulation(state.copy(), _wca(), first)
    sim.run(30)
    saved_state, saved = sim.state.copy(), first.get_state()
    sim.run(30)
    second = make(BondConstraints(bonds, tol=1e-8))
    second.constraints.bind(saved_state, 0.004)  # as md run does before restoring
    assert second.describe() == first.describe()
    second.set_state(saved)
    resumed = md.Simulation(saved_state, _wca(), second)
    resumed.run(30)
    np.testing.assert_allclose(resumed.state.positions, sim.state.positions, rtol=0, atol=1e-11)
    np.testing.assert_allclose(resumed.state.velocities, sim.state.velocities, rtol=0, atol=1e-10)


def test_first_step_puts_the_state_on_the_constraint_surface(dimer):
    state = dimer(r=1.3)
    state.velocities[:] = [[0.5, 0.2, 0.0], [-0.1, 0.0, 0.3]]
    constraints = BondConstraints([[0, 1]], lengths=1.0, tol=1e-12)
    sim = md.Simulation(state, [LennardJones(epsilon=0.0)], Rattle(0.01, constraints))
    momentum = state.velocities.sum(axis=0)
    sim.run(1)
    assert constraints.errors(state).max() < 1e-12
    assert _velocity_errors(state, constraints.bonds, 0.01).max() < 1e-12
    np.testing.assert_allclose(state.velocities.sum(axis=0), momentum, atol=1e-14)


def test_failure_names_the_step_and_the_bond(melt):
    state, bonds = melt
    constraints = BondConstraints(bonds, lengths=1.0, tol=1e-12, max_iter=2)
    sim = md.Simulation(state.copy(), _wca(), Rattle(0.004, constraints))
    with pytest.raises(
        ConstraintError,
        match=r"step 1: SHAKE .* did not converge in 2 "
        r"iterations: bond \d+ \(atoms \d+-\d+\)",
    ) as caught:
        sim.run(5)
    assert caught.value.step == 1 and caught.value.residual > 1e-12
    # A step so long that a bond turns past 90 degrees cannot be corrected at all.
    constraints = BondConstraints(bonds, lengths=1.0)
    hot = state.copy()
    hot.velocities *= 30.0
    with pytest.raises(ConstraintError, match="step 1:"):
        md.Simulation(hot, _wca(), Rattle(0.05, constraints)).run(1)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"bonds": [[0, 1], [1, 0]]}, "more than once"),
        ({"bonds": [[0, 0]]}, "itself"),
        ({"bonds": [[0, 1]], "lengths": -1.0}, "lengths"),
        ({"bonds": [[0, 1]], "tol": 0.0}, "tol"),
        ({"bonds": [[0, 1]], "max_iter": 0}, "max_iter"),
    ],
)
def test_bad_constraints_are_named(kwargs, message):
    with pytest.raises(ValueError, match=message):
        BondConstraints(**kwargs)


def test_constraints_beyond_the_state_are_refused(dimer):
    with pytest.raises(ValueError, match="atom beyond"):
        md.Simulation(dimer(), [LennardJones()], Rattle(0.01, [[0, 5]])).run(1)


# ------------------------------------------------------------------ configs
RIGID = """\
units = "lj"
seed = 3

[system]
polymer = "melt"
chains = 4
chain_length = 10
density = 0.5
bond_length = 1.0
temperature = 1.0

[[potentials]]
type = "lj"
cutoff = 1.122462048309373

[integrator]
type = "{kind}"
dt = 0.004
{extra}
[integrator.constraints]
bonds = "system"
tol = 1e-9
{constraints}
[run]
steps = 200
thermo_every = 100

[output]
path = "out.h5"
every = 100
"""


def _write(tmp_path, kind="langevin", extra="temperature = 1.0\nfriction = 2.0", constraints=""):
    path = tmp_path / "rigid.toml"
    path.write_text(RIGID.format(kind=kind, extra=extra, constraints=constraints))
    return path


def test_config_builds_rigid_bonds_from_the_polymer(tmp_path):
    from md.config import build_system, load_config

    config = load_config(_write(tmp_path))
    state, bonds = build_system(config)
    integrator = integrator_from_config(config.integrator, config.source, bonds)
    assert isinstance(integrator, Langevin)
    assert integrator.constraints.n_constraints == 36 and integrator.constraints.tol == 1e-9
    assert (
        main(["run", str(_write(tmp_path)), "--no-progress", "-q", "-o", str(tmp_path / "out.h5")])
        == 0
    )
    traj = md.trajectory.read_trajectory(tmp_path / "out.h5")
    lengths = np.linalg.norm(np.diff(traj.positions[-1][:10], axis=0), axis=1)
    np.testing.assert_allclose(lengths, 1.0, rtol=2e-9)
    assert traj.parameters["integrator"]["constraints"]["n_constraints"] == 36


def test_rattle_from_config_runs(tmp_path):
    path = _write(tmp_path, kind="rattle", extra="")
    assert main(["run", str(path), "--no-progress", "-q", "-o", str(tmp_path / "o.h5")]) == 0


@pytest.mark.parametrize(
    ("kind", "extra", "constraints", "message"),
    [
        ("verlet", "", "", "does not apply constraints; use one of rattle"),
        ("rattle", "", "colour = 1", "colour"),
        ("rattle", "", "lengths = [1.0, 2.0]", "lengths"),
    ],
)
def test_bad_constraint_configs_exit_2(tmp_path, capsys, kind, extra, constraints, message):
    path = _write(tmp_path, kind=kind, extra=extra, constraints=constraints)
    assert main(["run", str(path), "--no-progress", "-q", "-o", str(tmp_path / "o.h5")]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "o.h5").exists()


def test_system_bonds_need_a_polymer():
    import tomllib

    text = RIGID.format(kind="rattle", extra="", constraints="").replace(
        'polymer = "melt"\nchains = 4\nchain_length = 10\ndensity = 0.5\nbond_length = 1.0',
        'lattice = "fcc"\ncells = 3\ndensity = 0.8',
    )
    config = parse_config(tomllib.loads(text), source="rigid.toml")
    with pytest.raises(ConfigError, match="needs bonds from \\[system\\]"):
        integrator_from_config(config.integrator, config.source, None)


def test_constraint_failure_in_md_run_exits_1_naming_the_step(tmp_path, capsys):
    """dt = 0.2 lets the overlapping start's WCA forces throw beads far past their bonds."""
    path = _write(tmp_path, kind="rattle", extra="")
    path.write_text(path.read_text().replace("dt = 0.004", "dt = 0.2"))
    assert main(["run", str(path), "--no-progress", "-q", "-o", str(tmp_path / "o.h5")]) == 1
    err = capsys.readouterr().err
    assert "step 1: SHAKE" in err and "bond" in err and "1 frames" in err


def test_constraints_that_cannot_be_met_at_the_start_exit_2(tmp_path, capsys):
    path = _write(tmp_path, kind="rattle", extra="", constraints="max_iter = 1")
    assert main(["run", str(path), "--no-progress", "-q", "-o", str(tmp_path / "o.h5")]) == 2
    err = capsys.readouterr().err
    assert "[integrator.constraints]" in err and "did not converge" in err
    assert not (tmp_path / "o.h5").exists()
