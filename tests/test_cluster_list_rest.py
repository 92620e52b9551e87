"""Issue 70, the cluster list's work around its kernels on a step that prunes or searches.

Two things of such a step (a fifth of the mixed melt's steps) are no longer done twice:

- The relative positions: the prune (or the search) writes them into the list's own
  buffers (``ClusterFrame.relative``) at the step's positions, and the cluster kernel's
  call after it reads them there instead of writing them again.
- The distance from the search's positions, which chooses a prune over a search: where the
  distance since the last prune plus that prune's own bound on its distance from the
  search already lies within the prune distance, the prune is chosen without measuring it
  (``NeighborList.n_bounded_prunes``); else it is measured as before.

What is tested: both are skipped where they may be, a direct force call at other
positions writes its own, and every prune or search obeys the rule measured exactly (so
the lists are those of before; the trajectories bit for bit the general path's:
tests/test_mixed_step_fallback.py, test_mixed_step_passes.py). No timings:
``benchmarks/cluster_pruning.py --sections``.
"""

from __future__ import annotations

import numpy as np

import md
import md.neighbors.lists
from integrators import VelocityVerlet
from md.neighbors import ClusterFrame
from potentials import LennardJones

DT = 0.005


def simulation(fused: bool = True) -> md.Simulation:
    """The LJ melt (fcc at rho* 0.8442, T* 3), 2048 atoms, mixed precision on the pruned
    cluster list; ``fused=False``: the step made of the separate calls (the general path)."""
    state = md.maxwell_boltzmann(md.lattice("fcc", 8, density=0.8442), 3.0, seed=7)
    sim = md.Simulation(state, [LennardJones(cutoff=2.5)], VelocityVerlet(dt=DT), precision="mixed")
    if not fused:
        sim.forcefield.verlet_step = lambda *args: 0
    return sim


def counting(monkeypatch, owner, name: str) -> list:
    """Replace ``owner.name`` by a wrapper that records each call's arguments."""
    calls = []
    original = getattr(owner, name)

    def wrapper(*args, **kwargs):
        calls.append(args)
        return original(*args, **kwargs)

    monkeypatch.setattr(owner, name, wrapper)
    return calls


def largest_distance(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.max(np.sum((a - b) ** 2, axis=1))))


def test_a_step_that_prunes_or_searches_writes_the_relative_positions_once(monkeypatch):
    """The kernel's call after the list's prune or search reads the relative positions the
    list wrote at the same positions (before: written again, 40-90 us at 32000 atoms)."""
    sim = simulation()
    sim.run(10)
    nl = sim.forcefield.neighbor_list
    assert nl.outer_clusters is not None  # pruned between searches
    builds, prunes = nl.n_builds, nl.n_prunes
    calls = counting(monkeypatch, ClusterFrame, "relative_positions")
    sim.run(60)
    assert nl.n_builds > builds and nl.n_prunes > prunes
    assert len(calls) == nl.n_prunes - prunes  # the prunes' own, none in the force calls
    for _ in range(10):  # to a step that kept the list: the fused pass wrote the positions
        if not np.array_equal(nl.pruned_positions, sim.state.positions):
            break
        sim.run(1)
    # the kernel's buffers are the list's: they hold this step's, not the prune's
    xi, xj = nl.clusters.relative
    want_i, want_j = np.empty_like(xi), np.empty_like(xj)
    nl.clusters.relative_positions(sim.state.positions, want_i, want_j)
    assert np.array_equal(xi, want_i) and np.array_equal(xj, want_j)


def test_forces_over_a_pruned_list_at_other_positions_are_those_of_the_positions():
    """A direct call over a list whose buffers hold another instant's relative positions
    writes its own (only the step's second call, right after the list's update, reads
    them as they are)."""
    sim = simulation()
    sim.run(15)
    state, nl = sim.state, sim.forcefield.neighbor_list
    moved = state.copy()
    rng = np.random.default_rng(3)
    moved.positions += rng.uniform(-0.02, 0.02, moved.positions.shape)  # within the skin
    potential = sim.forcefield.potentials[0]
    got = potential.energy_forces(moved, nl, virial=False, precision="mixed")
    fresh_list = md.neighbors.NeighborList(2.5, 0.3, clusters=True)
    fresh_list.update(moved)
    want = LennardJones(cutoff=2.5).energy_forces(moved, fresh_list, precision="mixed")
    # another list (another grid: other float32 sums), the same physics
    assert np.allclose(got.forces, want.forces, rtol=1e-4, atol=1e-3)


def test_the_bound_spares_the_distance_from_the_search_and_keeps_the_rule(monkeypatch):
    """Prunes chosen by the bound (no pass measuring the distance from the search), one
    pass for each other step that prunes or searches; each prune then lay within the prune
    distance of the search's positions and each search beyond it, as measured exactly."""
    sim = simulation()
    sim.run(10)
    nl = sim.forcefield.neighbor_list
    limit = 0.5 * (nl.outer_skin - nl.skin)
    builds, prunes, bounded = nl.n_builds, nl.n_prunes, nl.n_bounded_prunes
    calls = counting(monkeypatch, md.neighbors.lists, "_largest_displacement2")
    for _ in range(80):
        search = nl.reference_positions
        n_builds, n_prunes = nl.n_builds, nl.n_prunes
        sim.run(1)
        if nl.n_builds > n_builds:  # searched: beyond the prune distance of the last search
            assert largest_distance(nl.reference_positions, search) > limit
        elif nl.n_prunes > n_prunes:
            assert largest_distance(nl.pruned_positions, search) <= limit
    changed = (nl.n_builds - builds) + (nl.n_prunes - prunes)
    spared = nl.n_bounded_prunes - bounded
    assert nl.n_builds > builds and spared > 0
    assert len(calls) == changed - spared
