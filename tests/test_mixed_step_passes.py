"""Issue 70, the mixed step's memory-bound passes: velocity Verlet's mixed-precision step
over the exact cluster-pair list as two threaded passes around the cluster kernel
(``ForceField.verlet_step`` -> ``PairPotential.mixed_verlet_step``,
``potentials._step_kernels``): the first kick, drift, the list's displacement check, the
cache's copy of the positions and the kernel's relative positions in one pass; the chunks'
sum into atom order with the finite check and the last kick in the other.

What is tested: that the fused step is what runs while the list holds (the separate
passes are not called), that it gives the general path's numbers to the bit (positions,
velocities, forces, list builds and prunes) on one chunk and on two, on either of velocity
Verlet's branches, that a value that is not finite stops it with the general path's error,
and that the double path's serial fused step is not made where velocity Verlet's passes
would run on the threads. No timings: ``benchmarks/mixed_precision.py --phases``."""

from __future__ import annotations

import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

import integrators
import integrators.velocity_verlet
import md
import md.neighbors.lists
import potentials
import potentials._kernels
import potentials._step_kernels
from integrators import VelocityVerlet
from md.errors import SimulationError
from md.parallel import get_threads, max_threads, set_threads
from potentials import LennardJones, PairPotential

DT = 0.005


@pytest.fixture
def threads():
    """Set the thread count inside a test; the one before is restored after it."""
    before = get_threads()
    yield set_threads
    set_threads(before)


def melt(cells: int, seed: int = 23) -> md.State:
    """The LJ melt (fcc at rho* 0.8442, T* 3), unequal masses (1/m not exact in binary)."""
    state = md.maxwell_boltzmann(md.lattice("fcc", cells, density=0.8442), 3.0, seed=seed)
    state.masses = 1.0 + 0.37 * (np.arange(state.n_atoms) % 3)
    return state


def simulation(cells: int, fused: bool = True, precision: str = "mixed") -> md.Simulation:
    sim = md.Simulation(
        melt(cells), [LennardJones(cutoff=2.5)], VelocityVerlet(dt=DT), precision=precision
    )
    if not fused:  # the general path: kicks, compute (list check, cluster kernel), kick
        sim.forcefield.verlet_step = lambda *args: 0
    return sim


#: The packages whose calls are counted (not numba's: a kernel compiled on the way calls
#: functions of the same names).
_OURS = tuple(str(Path(module.__file__).parent) for module in (md, potentials, integrators))


def profiled(action) -> Counter:
    """Python calls of md's, potentials' and integrators' functions during ``action()``,
    by function name."""
    counts = Counter()

    def profile(frame, event, arg):
        if event == "call" and frame.f_code.co_filename.startswith(_OURS):
            counts[frame.f_code.co_name] += 1

    sys.setprofile(profile)
    try:
        action()
    finally:
        sys.setprofile(None)
    return counts


def _same_run(a: md.Simulation, b: md.Simulation) -> None:
    assert np.array_equal(a.state.positions, b.state.positions)
    assert np.array_equal(a.state.velocities, b.state.velocities)
    la, lb = a.forcefield.neighbor_list, b.forcefield.neighbor_list
    assert (la.n_builds, la.n_prunes) == (lb.n_builds, lb.n_prunes)
    fa = a.forcefield.compute(a.state, virial=False).forces
    fb = b.forcefield.compute(b.state, virial=False).forces
    assert np.array_equal(fa, fb)
    assert a.forcefield.n_evaluations == b.forcefield.n_evaluations


def test_the_mixed_step_is_two_passes_and_the_kernel_while_the_list_holds():
    """2048 atoms (the cache keeps arrays), 60 steps with prunes among them: each step
    whose check holds is the fused step (one pass before the kernel, none of the separate
    kicks, list update, relative positions or cache copy); the others fall back after
    the drift, once each, to the list's update and the force call apart."""
    sim = simulation(8)
    sim.run(10)
    nl = sim.forcefield.neighbor_list
    builds, prunes = nl.n_builds, nl.n_prunes
    steps = 60
    counts = profiled(lambda: sim.run(steps))
    changed = (nl.n_builds - builds) + (nl.n_prunes - prunes)
    assert changed > 0  # the fallback ran too
    assert counts["kick_drift_slots"] == steps  # every step's first pass is the fused one
    assert counts["update"] == changed  # the list's update only where the check failed
    assert counts["_key_of"] == 0  # the cache's copy is the fused pass's, also then
    # the relative positions apart only where a prune writes them (the force call then
    # reads the list's: tests/test_cluster_list_rest.py)
    assert counts["relative_positions"] == nl.n_prunes - prunes
    assert counts["finish_step"] == steps - changed  # after the kernel: one call


@pytest.mark.parametrize("cells", [6, 8])  # 864 atoms (the cache's bytes: not fused), 2048
def test_the_fused_mixed_step_gives_the_general_paths_numbers(cells):
    fused, general = simulation(cells), simulation(cells, fused=False)
    fused.run(70)
    general.run(70)
    assert fused.forcefield.neighbor_list.n_prunes > 0
    _same_run(fused, general)


@pytest.mark.skipif(max_threads() < 2, reason="numba offers one thread")
def test_the_fused_step_in_two_chunks_on_the_large_branch_gives_the_same_numbers(
    threads, monkeypatch
):
    """The passes, the list and the kernel in two chunks on two threads (their fewest
    atoms per chunk lowered so that 2048 atoms split), and velocity Verlet's branch of
    32000 atoms and more (its threshold lowered): the fused step runs there too, with the
    general path's numbers; the sum into atom order's runs split by their work."""
    threads(2)
    monkeypatch.setattr(potentials._step_kernels, "_MIN_PASS_SLOTS", 500)
    monkeypatch.setattr(potentials._kernels, "_MIN_PASS_SLOTS", 500)
    monkeypatch.setattr(md.neighbors.lists, "_MIN_PASS_ATOMS", 500)
    monkeypatch.setattr(integrators.velocity_verlet, "SERIAL_ATOMS", 1000)
    fused, general = simulation(8), simulation(8, fused=False)
    fused.run(1)
    general.run(1)
    assert len(fused.forcefield.neighbor_list.clusters.bounds) == 3
    counts = profiled(lambda: fused.run(50))
    general.run(50)
    assert counts["kick_drift_slots"] == 50
    assert counts["finish_step"] > 25  # the two chunks' sum, the finite check, the kick
    assert counts["kick_drift"] == 0  # the separate passes: the last kick of a fallback
    assert counts["kick"] == 0 < counts["update"]  # a fallback's kick: the second call
    _same_run(fused, general)


def test_a_position_that_is_not_finite_stops_the_fused_step_as_the_general_one():
    """A velocity made NaN: the fused pass drifts its atom to NaN, its check fails, and
    the list's update says what, as in the general path (same step, same message)."""
    errors = []
    for fused in (True, False):
        sim = simulation(8, fused=fused)
        sim.run(5)
        sim.state.velocities[17, 1] = np.nan
        with pytest.raises(SimulationError) as caught:
            sim.run(5)
        errors.append(str(caught.value))
    assert errors[0] == errors[1]
    assert "not finite" in errors[0]


def test_the_double_step_is_not_fused_where_velocity_verlets_passes_are_threaded():
    """The double path's fused step is one serial call: ``threaded`` (velocity Verlet's
    branch of 32000 atoms and more) leaves that step to the threaded passes (0, nothing
    done), while the same call without it makes the step."""
    sim = simulation(5, precision="double")
    sim.run(3)
    ff, state = sim.forcefield, sim.state
    before = state.positions.copy()
    assert ff.verlet_step(state, 0.5 * DT, DT, True) == 0
    assert np.array_equal(state.positions, before)
    assert ff.verlet_step(state, 0.5 * DT, DT) == 2


def test_a_subclass_with_its_own_energy_forces_is_asked_not_fused():
    """A pair potential that overrides ``energy_forces`` is called by the general path."""
    seen = []

    class Counted(LennardJones):
        def energy_forces(self, *args, **kwargs):
            seen.append(1)
            return super().energy_forces(*args, **kwargs)

    assert issubclass(Counted, PairPotential)
    sim = md.Simulation(melt(8), [Counted(cutoff=2.5)], VelocityVerlet(dt=DT), precision="mixed")
    sim.run(10)
    assert len(seen) >= 10


def test_a_list_looked_at_every_few_steps_takes_the_general_path():
    """``neighbor_every`` > 1 (not the exact list): the list's own look decides, so the
    fused step is not made (``NeighborList.cluster_check`` says None)."""
    sim = md.Simulation(
        melt(8),
        [LennardJones(cutoff=2.5)],
        VelocityVerlet(dt=DT),
        precision="mixed",
        neighbor_every=2,
    )
    sim.run(3)
    assert sim.forcefield.neighbor_list.cluster_check(sim.state) is None
    counts = profiled(lambda: sim.run(10))
    assert counts["kick_drift_slots"] == 0
    assert counts["compute"] == 20  # the general path: the cached forces, then the new
