"""Higher-order symplectic splittings: measured order, reversibility, symplecticity, energy.

The test system is a small open Lennard-Jones cluster whose every pair stays
inside the cutoff, so the forces are analytic along the trajectory: a pair
crossing a cutoff would add error terms of the order set by the cutoff's
smoothness and hide the methods' own orders (sixth order needs the force's
sixth derivative to exist along the path).
"""

from __future__ import annotations

import numpy as np
import pytest

import md
from integrators import INTEGRATORS, RK4, ExplicitEuler, VelocityVerlet
from integrators.splitting import (
    DRIFT,
    KICK,
    METHODS,
    PEFRL,
    BlanesMoan,
    BlanesMoanRKN,
    Splitting,
    Yoshida4,
    Yoshida6,
    compose,
)
from potentials import LennardJones

NAMED = [Yoshida4, Yoshida6, PEFRL, BlanesMoan, BlanesMoanRKN]
IDS = [cls.__name__ for cls in NAMED]
SPAN = 0.5


def _cluster(cells=2, temperature=0.3, seed=3) -> md.State:
    state = md.lattice("fcc", cells, density=0.9, pbc=False)
    return md.maxwell_boltzmann(state, temperature, seed=seed)


def _run(integrator, state, n_steps):
    sim = md.Simulation(state, [LennardJones(cutoff=8.0)], integrator, skin=0.3)
    sim.run(n_steps)
    return sim


def _final_positions(cls, dt):
    n = round(SPAN / dt)
    state = _cluster()
    _run(cls(SPAN / n), state, n)
    return state.positions


@pytest.fixture(scope="module")
def reference():
    """Yoshida 6 at dt = SPAN / 8192; its own error (against half that step) is ~1e-14."""
    return _final_positions(Yoshida6, SPAN / 8192)


def _rms(a, b):
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


@pytest.mark.parametrize("cls", NAMED, ids=IDS)
def test_measured_order_is_the_methods_order(cls, reference):
    dts = SPAN / np.array([32, 64, 128, 256])
    errors = [_rms(_final_positions(cls, dt), reference) for dt in dts]
    assert min(errors) > 1e-12, "errors reached the reference's floor: fit would be biased"
    slope = np.polyfit(np.log(dts), np.log(errors), 1)[0]
    assert slope == pytest.approx(cls.order, abs=0.15), (errors, slope)


def test_optimised_methods_beat_the_triple_jump_at_equal_work(reference):
    """PEFRL and Blanes-Moan exist for their small error constants: compare at equal forces."""
    work = 384  # force evaluations over the span

    def error(cls):
        per_step = cls(0.01).force_evaluations
        return _rms(_final_positions(cls, SPAN / (work // per_step)), reference)

    assert error(PEFRL) < 0.2 * error(Yoshida4)
    assert error(BlanesMoan) < 0.2 * error(Yoshida4)


@pytest.mark.parametrize("cls", NAMED, ids=IDS)
def test_time_reversible_to_round_off(cls):
    state = _cluster()
    start = state.positions.copy(), state.velocities.copy()
    sim = _run(cls(0.005), state, 200)
    state.velocities *= -1.0
    sim.run(200)
    state.velocities *= -1.0
    scale = np.abs(start[0]).max()
    assert np.abs(state.positions - start[0]).max() < 1e-12 * scale
    assert np.abs(state.velocities - start[1]).max() < 1e-10


def _step_map(integrator, state0):
    """One step as a function of the phase-space point z = (x, v) (unit masses)."""
    n = state0.n_atoms

    def advance(z):
        state = md.State(
            positions=z[: 3 * n].reshape(n, 3),
            velocities=z[3 * n :].reshape(n, 3),
            box=state0.box,
            pbc=False,
        )
        forcefield = md.ForceField([LennardJones(cutoff=8.0)])
        integrator.step(state, forcefield)
        return np.concatenate([state.positions.ravel(), state.velocities.ravel()])

    return advance


def _jacobian(integrator, state0, h=1e-6):
    advance = _step_map(integrator, state0)
    z0 = np.concatenate([state0.positions.ravel(), state0.velocities.ravel()])
    columns = []
    for k in range(len(z0)):
        dz = np.zeros_like(z0)
        dz[k] = h
        columns.append((advance(z0 + dz) - advance(z0 - dz)) / (2 * h))
    return np.array(columns).T


def _symplectic_defect(jacobian):
    d = len(jacobian) // 2
    omega = np.block([[np.zeros((d, d)), np.eye(d)], [-np.eye(d), np.zeros((d, d))]])
    return float(np.abs(jacobian.T @ omega @ jacobian - omega).max())


def _small_cluster():
    state = md.State(
        positions=[[0, 0, 0], [1.12, 0, 0], [0.5, 1.0, 0.1], [0.4, 0.3, 1.05]],
        box=20.0,
        pbc=False,
    )
    return md.maxwell_boltzmann(state, 0.5, seed=2)


@pytest.mark.parametrize("cls", NAMED, ids=IDS)
def test_one_step_preserves_the_symplectic_form(cls):
    """J^T Omega J = Omega and det J = 1 for the step map (unit masses), to difference error."""
    jacobian = _jacobian(cls(0.02), _small_cluster())
    assert _symplectic_defect(jacobian) < 1e-8  # central differences reach ~4e-10
    assert np.linalg.det(jacobian) == pytest.approx(1.0, abs=1e-8)


@pytest.mark.parametrize("cls", [RK4, ExplicitEuler], ids=["RK4", "ExplicitEuler"])
def test_the_symplecticity_check_fails_for_non_symplectic_methods(cls):
    jacobian = _jacobian(cls(0.02), _small_cluster())
    assert _symplectic_defect(jacobian) > 1e-6  # RK4 1.3e-5, explicit Euler 3e-2


@pytest.mark.parametrize("cls", NAMED, ids=IDS)
def test_long_runs_keep_the_energy_without_drift(cls):
    """10^4 steps: the energy error stays bounded and its trend is within its own noise."""
    state = _cluster(temperature=0.5)
    sim = md.Simulation(state, [LennardJones(cutoff=8.0)], cls(0.01), skin=0.3)
    energies = []
    sim.attach(lambda s: energies.append(s.thermo()["total_energy"]), interval=50)
    sim.run(10_000)
    energies = np.array(energies) / state.n_atoms
    times = np.arange(len(energies)) * 0.5
    slope, intercept = np.polyfit(times, energies, 1)
    noise = np.std(energies - (slope * times + intercept))
    assert np.abs(energies - energies[0]).max() < 5e-4  # Yoshida 4: 1.3e-4
    assert abs(slope) * times[-1] < max(3 * noise, 1e-9)


def test_force_evaluations_per_step_match_the_table():
    for cls in NAMED:
        state = _cluster()
        sim = _run(cls(0.005), state, 1)
        before = sim.forcefield.n_evaluations
        sim.run(10)
        assert sim.forcefield.n_evaluations - before == 10 * cls(0.005).force_evaluations


def test_a_verlet_table_is_velocity_verlet_bit_for_bit():
    a, b = _cluster(), _cluster()
    _run(Splitting(0.005, compose([1.0]), name="verlet"), a, 50)
    _run(VelocityVerlet(0.005), b, 50)
    # Splitting kicks and drifts separately; VelocityVerlet fuses the first kick and the
    # drift in one kernel: the same arithmetic in the same order.
    assert np.array_equal(a.positions, b.positions)
    assert np.array_equal(a.velocities, b.velocities)


@pytest.mark.parametrize(
    ("table", "message"),
    [
        ([], "at least one kick"),
        ([(KICK, 0.5), (DRIFT, 1.0), (KICK, 0.4)], "kick coefficients sum"),
        ([(KICK, 0.25), (DRIFT, 0.5), (KICK, 0.75), (DRIFT, 0.5)], "not symmetric"),
        ([(KICK, 0.5), (DRIFT, float("nan")), (KICK, 0.5)], "bad table entry"),
    ],
)
def test_bad_tables_are_refused(table, message):
    with pytest.raises(ValueError, match=message):
        Splitting(0.01, table)


def test_registered_and_described_by_name(tmp_path, monkeypatch, lj_config):
    from md.cli import main

    for name in METHODS:
        assert INTEGRATORS[name](0.01).describe() == {"type": name, "dt": 0.01}
    monkeypatch.chdir(tmp_path)
    (tmp_path / "run.toml").write_text(lj_config(integrator='type = "pefrl"\ndt = 0.01'))
    assert main(["run", "run.toml", "--no-progress", "-q"]) == 0
