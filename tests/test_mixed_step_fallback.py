"""Issue 70, the mixed step's fallback: a velocity Verlet step in mixed precision whose
fused pass (``PairPotential.mixed_verlet_step``) finds an atom past the cluster list's
half-skin rule (a prune or a search: about a fifth of the melt's steps) goes on from
what that pass already did. The list's update takes the displacement the pass measured
(``NeighborList.update(state, moved2)``) instead of measuring it again, and the forces
and the last kick are the potential's second call, with the positions the pass already
copied into the force field's cache (not copied again, no ``compute``).

What is tested: on such steps the displacement from the last prune is not measured
again (one pass, from the search, to choose a prune or a search), the cache's copy and
``compute`` are not made, the numbers are the general path's to the bit (on two threads'
chunks: tests/test_mixed_step_passes.py, whose two-chunk run falls back too), and forces
that are not finite after a search stop the run with the general path's error. No
timings: ``benchmarks/mixed_step_phases.py``."""

from __future__ import annotations

import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

import integrators
import md
import md.forcefield
import md.neighbors.lists
import potentials
from integrators import VelocityVerlet
from md.errors import SimulationError
from potentials import LennardJones

DT = 0.005


def simulation(fused: bool = True, cells: int = 8) -> md.Simulation:
    """The LJ melt (fcc at rho* 0.8442, T* 3; 2048 atoms: the cache keeps arrays), unequal
    masses, mixed precision; ``fused=False``: the step made of the separate calls."""
    state = md.maxwell_boltzmann(md.lattice("fcc", cells, density=0.8442), 3.0, seed=41)
    state.masses = 1.0 + 0.37 * (np.arange(state.n_atoms) % 3)
    sim = md.Simulation(state, [LennardJones(cutoff=2.5)], VelocityVerlet(dt=DT), precision="mixed")
    if not fused:
        sim.forcefield.verlet_step = lambda *args: 0
    return sim


_OURS = tuple(str(Path(module.__file__).parent) for module in (md, potentials, integrators))


def profiled(action) -> Counter:
    """Python calls of md's, potentials' and integrators' functions during ``action()``."""
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


def counting(monkeypatch, module, name: str) -> list:
    """Replace ``module.name`` by a wrapper that records each call's arguments."""
    calls = []
    original = getattr(module, name)

    def wrapper(*args, **kwargs):
        calls.append(args)
        return original(*args, **kwargs)

    monkeypatch.setattr(module, name, wrapper)
    return calls


def _same_run(a: md.Simulation, b: md.Simulation) -> None:
    assert np.array_equal(a.state.positions, b.state.positions)
    assert np.array_equal(a.state.velocities, b.state.velocities)
    la, lb = a.forcefield.neighbor_list, b.forcefield.neighbor_list
    assert (la.n_builds, la.n_prunes) == (lb.n_builds, lb.n_prunes)
    fa = a.forcefield.compute(a.state, virial=False)
    fb = b.forcefield.compute(b.state, virial=False)
    assert np.array_equal(fa.forces, fb.forces)
    assert fa.energy == fb.energy
    assert a.forcefield.n_evaluations == b.forcefield.n_evaluations


def test_a_fallback_step_measures_the_displacement_once(monkeypatch):
    """Each step that prunes or searches measures the displacement from the search's
    positions once (to choose between them), never again from the last prune's: the
    fused pass measured that one."""
    sim = simulation()
    sim.run(10)
    nl = sim.forcefield.neighbor_list
    builds, prunes, bounded = nl.n_builds, nl.n_prunes, nl.n_bounded_prunes
    calls = counting(monkeypatch, md.neighbors.lists, "_largest_displacement2")
    sim.run(60)
    changed = (nl.n_builds - builds) + (nl.n_prunes - prunes)
    assert nl.n_prunes > prunes and nl.n_builds > builds  # both kinds of fallback ran
    # one pass a fallback step (before: two), none where a bound chose the prune
    assert len(calls) == changed - (nl.n_bounded_prunes - bounded)
    held = nl.pruned_positions  # the last prune's positions (one array, written over)
    assert held is not None and all(since is not held for _, since, _ in calls)


def test_a_fallback_step_neither_copies_the_positions_again_nor_calls_compute(monkeypatch):
    """The positions the fused pass copied into the cache serve the fallback's forces:
    no second copy (``copy_into`` into the cache's key), no ``compute`` and no separate
    kick; the list's update once per fallback step, the forces by the potential's
    ``energy_forces`` then, with the finite check and the kick in one call."""
    sim = simulation()
    sim.run(10)
    nl = sim.forcefield.neighbor_list
    builds, prunes = nl.n_builds, nl.n_prunes
    copies = counting(monkeypatch, md.forcefield, "copy_into")
    steps = 60
    counts = profiled(lambda: sim.run(steps))
    changed = (nl.n_builds - builds) + (nl.n_prunes - prunes)
    assert changed > 0
    assert copies == []
    assert counts["compute"] == 0 and counts["_key_of"] == 0
    assert counts["kick_by_mass"] == 0 and counts["kick"] == 0
    assert counts["update"] == changed
    assert counts["finish_forces"] == changed
    assert counts["finish_step"] == steps - changed
    assert sim.forcefield.n_evaluations > 0


def test_the_fallback_gives_the_general_paths_numbers():
    fused, general = simulation(), simulation(fused=False)
    fused.run(80)
    general.run(80)
    assert fused.forcefield.neighbor_list.n_builds > 1
    _same_run(fused, general)


def test_forces_not_finite_after_a_search_stop_the_run_as_the_general_path():
    """An atom sent onto another in one drift (past the list's rule, so the step falls
    back and searches): the second call's forces are not finite, nothing is kicked, and
    the run stops with the general path's error at the same step."""
    errors, velocities = [], []
    for fused in (True, False):
        sim = simulation(fused=fused)
        sim.run(5)
        state = sim.state
        forces = sim.forcefield.compute(state, virial=False).forces
        # the drift of atom 3 lands 0.001 from atom 0's new place (the float32 force
        # overflows): after the first kick its velocity is (x0' + 0.001 - x3) / dt
        kicked = state.velocities[0] + 0.5 * DT * forces[0] / state.masses[0]
        landing = state.positions[0] + DT * kicked + [0.001, 0.0, 0.0]
        target = (landing - state.positions[3]) / DT
        state.velocities[3] = target - 0.5 * DT * forces[3] / state.masses[3]
        with pytest.raises(SimulationError) as caught:
            sim.run(5)
        errors.append(str(caught.value))
        velocities.append(state.velocities.copy())
    assert errors[0] == errors[1]
    assert errors[0].startswith("step 6: the force on atom 0 is [-inf")
    assert np.array_equal(velocities[0], velocities[1])  # the last kick not made
