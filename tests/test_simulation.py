"""The Simulation loop: one force evaluation per step, observers (step 0 once, intervals,
continued runs), argument checks, and blow-ups that raise with their step."""

from __future__ import annotations

import numpy as np
import pytest

import md
from integrators import VelocityVerlet
from potentials import LennardJones


def lj_simulation(state, dt, cutoff_mode="smooth"):
    """LJ (cutoff 2.5) and velocity Verlet at ``dt`` on ``state``."""
    return md.Simulation(
        state, [LennardJones(cutoff=2.5, cutoff_mode=cutoff_mode)], VelocityVerlet(dt=dt)
    )


class Recorder:
    """Observer keeping (step, time, total energy) rows."""

    def __init__(self, energy=False) -> None:
        self.steps: list[int] = []
        self.times: list[float] = []
        self.energies: list[float] = []
        self.energy = energy

    def __call__(self, sim) -> None:
        self.steps.append(sim.state.step)
        self.times.append(sim.state.time)
        if self.energy:
            self.energies.append(sim.thermo()["total_energy"] / sim.state.n_atoms)


# ---------------------------------------------------------------- bookkeeping


def test_one_force_evaluation_per_step(fcc_lattice):
    sim = lj_simulation(fcc_lattice(cells=3, temperature=1.0), 0.005)
    pressures = []
    sim.attach(lambda s: pressures.append(s.thermo()["pressure"]), interval=7)
    sim.run(50)
    # The fresh run evaluates step 0 once, then each step reuses the last forces;
    # observed steps compute the virial with their forces, so thermo() costs nothing.
    assert sim.forcefield.n_evaluations == 51
    assert len(pressures) == 1 + 50 // 7
    sim.run(30)
    assert sim.forcefield.n_evaluations == 81
    sim.thermo()  # step 80 was not observed: its evaluation skipped the virial
    assert sim.forcefield.n_evaluations == 82
    sim.thermo()  # now served from the cache
    assert sim.forcefield.n_evaluations == 82


# ------------------------------------------------------------------ observers


def test_fresh_run_observes_step_zero_once_and_respects_intervals(fcc_lattice):
    sim = lj_simulation(fcc_lattice(cells=3, temperature=1.0), 0.005)
    every, fifth = Recorder(), Recorder()
    sim.attach(every)
    sim.attach(fifth, interval=5)
    sim.run(12)
    assert every.steps == list(range(13))
    assert fifth.steps == [0, 5, 10]
    np.testing.assert_allclose(every.times, 0.005 * np.arange(13), rtol=1e-12)
    sim.run(8)  # continued: step 12 is not observed again
    assert every.steps == list(range(21))
    assert fifth.steps == [0, 5, 10, 15, 20]


def test_zero_step_run_then_continue(fcc_lattice):
    sim = lj_simulation(fcc_lattice(cells=3, temperature=1.0), 0.005)
    recorder = Recorder()
    sim.attach(recorder, interval=2)
    sim.run(0)
    assert recorder.steps == [0]
    sim.run(0)
    sim.run(4)
    assert recorder.steps == [0, 2, 4]


def test_continued_state_is_not_observed_before_its_first_step(fcc_lattice):
    state = fcc_lattice(cells=3, temperature=1.0)
    first = lj_simulation(state, 0.005)
    first.run(20)
    second = lj_simulation(state, 0.005)  # e.g. a restart from a saved state
    recorder = Recorder()
    second.attach(recorder, interval=5)
    second.run(10)
    assert recorder.steps == [25, 30]


@pytest.mark.parametrize("interval", [0, -1, 1.5, True, "2"])
def test_invalid_observer_interval_raises(interval, dimer):
    sim = md.Simulation(dimer(), [LennardJones(cutoff=2.5)], VelocityVerlet(dt=0.005))
    with pytest.raises(ValueError, match="interval"):
        sim.attach(Recorder(), interval=interval)


@pytest.mark.parametrize("n_steps", [-1, 2.0, True])
def test_invalid_step_count_raises(n_steps, dimer):
    sim = md.Simulation(dimer(), [LennardJones(cutoff=2.5)], VelocityVerlet(dt=0.005))
    with pytest.raises(ValueError, match="n_steps"):
        sim.run(n_steps)


# ------------------------------------------------------------------- blow-ups


def test_huge_time_step_raises_with_the_failing_step(fcc_lattice):
    state = fcc_lattice(cells=3, temperature=1.0)
    sim = lj_simulation(state, 0.1, cutoff_mode="shift")
    recorder = Recorder()
    sim.attach(recorder)
    with pytest.raises(md.SimulationError) as caught:
        sim.run(1000)
    error = caught.value
    assert error.step > 0
    assert f"step {error.step}" in str(error)
    assert isinstance(error.__cause__, md.NonFiniteError)
    # Observers saw every step before the failing one, and no later step.
    assert recorder.steps == list(range(error.step))


def test_overlapping_atoms_raise_at_step_zero(dimer):
    sim = md.Simulation(dimer(r=0.0), [LennardJones(cutoff=2.5)], VelocityVerlet(dt=0.005))
    with pytest.raises(md.SimulationError, match="step 0") as caught:
        sim.run(10)
    assert caught.value.step == 0
