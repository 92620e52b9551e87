"""Issue 69, the serial step's fixed cost (third round): what a velocity Verlet step of a
small box does besides its kernels.

Tested: the calls that went stay gone (Python calls per step, counted by the profiler
hook), and the shortcuts that replaced them give the numbers of before, bit for bit (the
kicks with 1/m taken inside the compiled pass against numpy's inverse masses; the force
cache's key made once per call; a run's stop and communication asked only where a subclass
asks for them). No timings: those are ``benchmarks/small_boxes.py``'s.
"""

from __future__ import annotations

import sys
from collections import Counter

import numpy as np
import pytest

import md
from integrators import VelocityVerlet
from integrators._kernels import kick, kick_drift
from integrators.base import IntegratorBase
from md.errors import NonFiniteError
from md.neighbors import NeighborList
from potentials import LennardJones

DT = 0.005
SKIN = 0.3


def melt(cells: int, seed: int = 7) -> md.State:
    """The LJ melt of benchmarks/small_boxes.py: fcc at rho* 0.8442, T* 3."""
    return md.maxwell_boltzmann(md.lattice("fcc", cells, density=0.8442), 3.0, seed=seed)


def lj() -> LennardJones:
    return LennardJones(cutoff=2.5, cutoff_mode="none")


class NumpyVerlet(IntegratorBase):
    """Velocity Verlet as it was before: numpy's inverse masses, the chunked kick passes."""

    order = 2

    def __init__(self, dt: float) -> None:
        self.dt = dt

    def step(self, state, forcefield) -> None:
        forces = forcefield.compute(state, virial=False).forces
        inverse_masses = 1.0 / state.masses
        half = 0.5 * self.dt
        kick_drift(state.positions, state.velocities, forces, inverse_masses, half, self.dt)
        forces = forcefield.compute(state, virial=False).forces
        kick(state.velocities, forces, inverse_masses, half)
        self.end_step(state)

    def reset(self) -> None:
        pass

    def describe(self) -> dict:
        return {"type": "numpy-verlet", "dt": self.dt}


def calls_per_step(sim: md.Simulation, steps: int) -> float:
    counts = Counter()

    def profile(frame, event, arg):
        counts[event] += 1

    sys.setprofile(profile)
    try:
        for _ in range(steps):
            sim.run(1)
    finally:
        sys.setprofile(None)
    return counts["call"] / steps


@pytest.mark.parametrize("cells", [3, 5])  # 108 atoms (small-box search), 500 (cells)
def test_a_verlet_step_makes_at_most_25_python_calls(cells):
    """A velocity Verlet step of the melt, over 100 steps with list builds among them, made
    30 Python calls (numba's dispatchers included) before this round and 23 after: the
    kicks' wrappers and the inverse masses gone, the pair frame's check and the run's
    stop and communication asks inline."""
    sim = md.Simulation(melt(cells), [lj()], VelocityVerlet(dt=DT), skin=SKIN)
    sim.run(20)
    builds = sim.forcefield.neighbor_list.n_builds
    calls = calls_per_step(sim, 100)
    assert sim.forcefield.neighbor_list.n_builds > builds  # builds counted in the average
    assert calls <= 25


@pytest.mark.parametrize("cells", [3, 5])
def test_verlet_is_numpys_inverse_masses_bit_for_bit(cells):
    """Unequal masses (1/m not exact in binary), 120 steps with builds and virial steps:
    the positions, velocities and energies of the numpy-inverse-masses step to the bit."""
    runs = []
    for integrator in (VelocityVerlet(dt=DT), NumpyVerlet(dt=DT)):
        state = melt(cells)
        state.masses = 1.0 + 0.37 * (np.arange(state.n_atoms) % 3)
        sim = md.Simulation(state, [lj()], integrator, skin=SKIN)
        sim.attach(lambda s: s.thermo(), 30)
        sim.run(120)
        runs.append(sim)
    ours, before = runs
    assert ours.forcefield.neighbor_list.n_builds > 5
    assert np.array_equal(ours.state.positions, before.state.positions)
    assert np.array_equal(ours.state.velocities, before.state.velocities)
    assert ours.thermo()["total_energy"] == before.thermo()["total_energy"]


def test_the_force_cache_keeps_the_key_it_compared():
    """A miss's key is the one kept: the same positions are then a hit (no evaluation),
    and a change in place after it, of a position or of the box, is a miss again."""
    state = melt(3)
    ff = md.ForceField([lj()], skin=SKIN)
    first = ff.compute(state)
    assert ff.compute(state) is first and ff.n_evaluations == 1
    state.positions[5, 1] += 1e-9
    second = ff.compute(state)
    assert ff.n_evaluations == 2 and second is not first
    assert ff.compute(state) is second and ff.n_evaluations == 2
    state.box[0] *= 1.0 + 1e-12
    assert ff.compute(state) is not second and ff.n_evaluations == 3
    state.types[3] = 0  # the same value: the same bytes, a hit
    assert ff.n_evaluations == 3
    ff.compute(state)
    assert ff.n_evaluations == 3


def test_a_stop_requested_by_an_observer_ends_the_run_there():
    sim = md.Simulation(melt(3), [lj()], VelocityVerlet(dt=DT), skin=SKIN)
    sim.attach(lambda s: s.request_stop() if s.state.step == 7 else None, 1)
    sim.run(50)
    assert sim.state.step == 7


def test_a_subclass_is_still_asked_to_stop_and_for_its_communication():
    """A subclass that overrides ``_stopping`` and ``_comm_seconds`` (as a decomposed run
    does) is asked both every step; its communication seconds are left out of the
    integrator's."""

    class Asked(md.Simulation):
        asked = 0
        comm = 0

        def _stopping(self) -> bool:
            self.asked += 1
            return self.asked > 5

        def _comm_seconds(self) -> float:
            self.comm += 1
            return 1000.0 * self.comm  # far more than the whole run's time

    sim = Asked(melt(3), [lj()], VelocityVerlet(dt=DT), skin=SKIN)
    sim.run(50)
    assert sim.state.step == 5 and sim.asked == 6
    assert sim.comm >= 10
    assert sim.timings["integrate"] < 0  # each step's 1000 s counted elsewhere


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_a_build_refuses_an_atom_billions_of_box_lengths_away(axis):
    """The build's bound on how far a coordinate may lie from a periodic box (2e9 box
    lengths, compared axis by axis without a generator now): beyond it NonFiniteError,
    ten lengths away the same list as the atom wrapped back."""
    state = melt(3)
    nl = NeighborList(cutoff=2.5, skin=SKIN)
    far = state.copy()
    far.positions[4, axis] += 3e9 * state.box[axis]
    with pytest.raises(NonFiniteError, match="box lengths from the box"):
        nl.build(far)
    near = state.copy()
    near.positions[4, axis] += 10 * state.box[axis]
    nl.build(near)
    wrapped = NeighborList(cutoff=2.5, skin=SKIN)
    wrapped.build(state)
    assert np.array_equal(nl.pairs(), wrapped.pairs())
