"""Velocity Verlet: conservation, reversibility, exactness, its registry entry and dt checks.

The Simulation loop's own tests are in test_simulation.py, the ForceField's in
test_forcefield.py."""

from __future__ import annotations

import numpy as np
import pytest
from test_simulation import Recorder, lj_simulation

import md
from conftest import Tether
from integrators import INTEGRATORS, VelocityVerlet
from potentials import LennardJones

LJ_DENSITY = 0.8442


def _liquid(cells=5, temperature=1.5, seed=7):
    state = md.lattice("fcc", cells, density=LJ_DENSITY)
    return md.maxwell_boltzmann(state, temperature, seed=seed)


# ----------------------------------------------------------- energy behaviour

RUN_TIME = 10.0  # tau, after 1 tau of melting at dt = 0.005
SAMPLE_EVERY = 0.05  # tau


@pytest.fixture(scope="module")
def nve_runs():
    """Total energy per atom E(t) of a 500-atom LJ liquid (rc 2.5, smooth) at two time steps."""
    melt = lj_simulation(_liquid(), 0.005)
    melt.run(200)
    runs = {}
    for dt in (0.005, 0.0025):
        sim = lj_simulation(melt.state.copy(), dt)
        sim.state.step, sim.state.time = 0, 0.0
        recorder = Recorder(energy=True)
        sim.attach(recorder, interval=round(SAMPLE_EVERY / dt))
        sim.run(round(RUN_TIME / dt))
        assert 0.5 < sim.thermo()["temperature"] < 1.5  # a liquid, not a crystal or a gas
        runs[dt] = (np.array(recorder.times), np.array(recorder.energies))
    return runs


def test_total_energy_fluctuation_is_bounded(nve_runs):
    times, energies = nve_runs[0.005]
    assert times[-1] == pytest.approx(RUN_TIME)
    assert len(energies) == round(RUN_TIME / SAMPLE_EVERY) + 1
    # Shadow-Hamiltonian wobble at dt = 0.005: ~1e-4 eps per atom, 1e-4 of kT.
    assert energies.std() < 2e-4
    assert np.abs(energies - energies[0]).max() < 1e-3


def test_total_energy_does_not_drift(nve_runs):
    """Fitted drift over 10 tau: below 1e-4 eps/atom at dt = 0.005 and 2.5e-5 at dt / 2.

    Both bounds lie at about the rms fluctuation of the run, so only a
    systematic trend (a non-symplectic step, a force inconsistent with the
    energy, stale neighbour lists) exceeds them.
    """
    for dt, bound in ((0.005, 1e-4), (0.0025, 2.5e-5)):
        times, energies = nve_runs[dt]
        slope, _ = np.polyfit(times, energies, 1)
        assert abs(slope * RUN_TIME) < bound, f"dt={dt}: drift {slope * RUN_TIME:.3g} eps/atom"


def test_energy_fluctuation_falls_fourfold_when_dt_halves(nve_runs):
    ratio = nve_runs[0.005][1].std() / nve_runs[0.0025][1].std()
    assert 3.0 < ratio < 5.0


@pytest.mark.slow
def test_long_run_has_no_drift():
    """10^5 steps (500 tau) of a 256-atom liquid: drift below 2e-4 eps per atom."""
    sim = lj_simulation(_liquid(cells=4, temperature=1.2, seed=3), 0.005)
    sim.run(200)
    recorder = Recorder(energy=True)
    sim.attach(recorder, interval=100)
    sim.run(100_000)
    times, energies = np.array(recorder.times), np.array(recorder.energies)
    slope, _ = np.polyfit(times - times[0], energies, 1)
    assert abs(slope * (times[-1] - times[0])) < 2e-4
    assert np.abs(energies - energies[0]).max() < 2e-3


# ------------------------------------------------------------------ exactness


def test_harmonic_oscillator_follows_the_discrete_analytic_solution():
    """Velocity Verlet on x'' = -w^2 x: x_n = x0 cos(n t) + (dt v0 / sin t) sin(n t),
    cos t = 1 - (w dt)^2 / 2, and it conserves 1/2 m v^2 + 1/2 k (1 - (w dt)^2 / 4) x^2 exactly."""
    k, mass, dt, n_steps = 3.0, 2.0, 0.1, 1000
    omega = np.sqrt(k / mass)
    anchors = np.array([[0.0, 0.0, 0.0], [5.0, 5.0, 5.0]])
    x0 = np.array([[1.0, -0.5, 0.25], [-0.3, 0.0, 0.7]])
    v0 = np.array([[0.0, 0.4, -1.0], [0.2, 0.1, 0.0]])
    state = md.State(positions=anchors + x0, velocities=v0.copy(), masses=mass, box=10.0, pbc=False)
    sim = md.Simulation(state, [Tether(k, anchors)], VelocityVerlet(dt=dt))
    shadow = []
    sim.attach(
        lambda s: shadow.append(
            0.5 * mass * np.sum(s.state.velocities**2)
            + 0.5 * k * (1 - (omega * dt) ** 2 / 4) * np.sum((s.state.positions - anchors) ** 2)
        )
    )
    sim.run(n_steps)
    theta = np.arccos(1 - (omega * dt) ** 2 / 2)
    n = n_steps
    x_n = x0 * np.cos(n * theta) + dt * v0 / np.sin(theta) * np.sin(n * theta)
    v_n = v0 * np.cos(n * theta) - np.sin(theta) / dt * x0 * np.sin(n * theta)
    np.testing.assert_allclose(state.positions - anchors, x_n, atol=1e-11)
    np.testing.assert_allclose(state.velocities, v_n, atol=1e-11)
    np.testing.assert_allclose(shadow, shadow[0], rtol=1e-12)
    assert state.step == n_steps and state.time == pytest.approx(n_steps * dt, rel=1e-12)


def test_matches_a_hand_written_velocity_verlet(fcc_lattice):
    state = fcc_lattice(cells=3, perturbation=0.05, temperature=1.0)
    lj = LennardJones(cutoff=2.5, cutoff_mode="shift")
    dt = 0.004
    positions, velocities = state.positions.copy(), state.velocities.copy()
    forces = lj.energy_forces(state, None).forces
    reference = state.copy()
    for _ in range(25):
        velocities += 0.5 * dt * forces / state.masses[:, None]
        positions += dt * velocities
        reference.positions[:] = positions
        forces = lj.energy_forces(reference, None).forces
        velocities += 0.5 * dt * forces / state.masses[:, None]
    sim = md.Simulation(state, [lj], VelocityVerlet(dt=dt))
    sim.run(25)
    np.testing.assert_allclose(state.positions, positions, rtol=0, atol=1e-12)
    np.testing.assert_allclose(state.velocities, velocities, rtol=0, atol=1e-11)


def test_time_reversibility(fcc_lattice):
    """Forward 200 steps, reverse the velocities, 200 steps back: the start to ~1e-10."""
    state = fcc_lattice(cells=3, perturbation=0.05, temperature=1.0)
    start_positions, start_velocities = state.positions.copy(), state.velocities.copy()
    sim = lj_simulation(state, 0.005)
    sim.run(200)
    assert np.abs(state.positions - start_positions).max() > 0.1  # it really went somewhere
    state.velocities *= -1.0
    sim.run(200)
    np.testing.assert_allclose(state.positions, start_positions, rtol=0, atol=1e-10)
    np.testing.assert_allclose(state.velocities, -start_velocities, rtol=0, atol=1e-9)


def test_total_momentum_is_conserved(fcc_lattice):
    state = fcc_lattice(cells=3, perturbation=0.05, temperature=2.0)
    state.velocities += [0.3, -0.1, 0.2]  # a drifting centre of mass
    momentum = (state.masses[:, None] * state.velocities).sum(axis=0)
    sim = lj_simulation(state, 0.005, cutoff_mode="shift")
    sim.run(100)
    np.testing.assert_allclose(
        (state.masses[:, None] * state.velocities).sum(axis=0), momentum, atol=1e-11
    )


# ------------------------------------------------------- registry and arguments


def test_registry_names_velocity_verlet():
    assert INTEGRATORS["verlet"] is VelocityVerlet
    assert VelocityVerlet(dt=0.002).describe() == {"type": "verlet", "dt": 0.002}


@pytest.mark.parametrize("dt", [0.0, -0.001, np.nan, np.inf, "fast"])
def test_invalid_dt_raises(dt):
    with pytest.raises(ValueError, match="dt"):
        VelocityVerlet(dt=dt)
