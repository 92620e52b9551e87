"""The cluster list's grid, search and prunes write into arrays the NeighborList keeps.

Each cluster search used to make its grid, part buffers, lists and relative positions
afresh (and each search's first prune its buffers): megabytes of fresh memory per search,
which with glibc's own malloc thresholds were fresh pages and page faults at first touch
(benchmarks/cluster_pruning.py's faults/step). Now a ``KeptArrays`` on the list holds them
from search to search: the next search writes the same memory (a list is valid while it
is the current one), and lists exactly what a fresh NeighborList lists.
"""

from __future__ import annotations

import numpy as np

from md._memory import KeptArrays
from md.neighbors import NeighborList
from potentials import LennardJones

CUTOFF, SKIN, OUTER_SKIN = 2.5, 0.3, 0.9


def _arrays(nl):
    """The arrays of the list's current frames: the pruned one's, the outer one's."""
    inner, outer = nl.clusters, nl.outer_clusters
    return {
        "atom": outer.atom,
        "origin": outer.origin,
        "starts": inner.starts,
        "partners": inner.partners,
        "offsets": inner.offsets,
        "relative i": inner.relative[0],
        "relative j": inner.relative[1],
        "outer starts": outer.starts,
        "outer partners": outer.partners,
        "outer offsets": outer.offsets,
        "reach": outer.reach,
    }


def _same_lists(nl, fresh):
    for name, array in _arrays(fresh).items():
        assert np.array_equal(_arrays(nl)[name], array), name
    assert nl.clusters.n_pairs < nl.outer_clusters.n_pairs  # (pruned: a real outer list)


def test_a_search_and_its_prunes_write_the_last_ones_memory_and_list_as_a_fresh_list(
    fcc_lattice, rng
):
    """Two searches at the same positions, the old lists held across the second: the
    second writes the same memory (the old code made every array afresh, which a held
    array's memory cannot be), and the lists, pruned and outer, and the relative
    positions are a fresh NeighborList's, array for array; then a search at moved
    positions and a prune after it: the same memory, a fresh list's lists."""
    state = fcc_lattice(cells=6, perturbation=0.05)
    nl = NeighborList(CUTOFF, SKIN, clusters=True, outer_skin=OUTER_SKIN)
    nl.build(state)
    assert nl.outer_clusters is not None
    held = _arrays(nl)
    nl.build(state)
    for name, array in _arrays(nl).items():
        assert np.shares_memory(array, held[name]), name
    fresh = NeighborList(CUTOFF, SKIN, clusters=True, outer_skin=OUTER_SKIN)
    fresh.build(state)
    _same_lists(nl, fresh)

    moved = state.copy()
    moved.positions += rng.uniform(-0.05, 0.05, size=moved.positions.shape)
    nl.build(moved)
    for name, array in _arrays(nl).items():
        assert np.shares_memory(array, held[name]), name
    fresh = NeighborList(CUTOFF, SKIN, clusters=True, outer_skin=OUTER_SKIN)
    fresh.build(moved)
    _same_lists(nl, fresh)

    # a prune (moved past half the skin, within the prune distance): into the memory of
    # the first search's prune, the list a fresh list's prune makes
    pruned_at = moved.copy()
    pruned_at.positions += rng.uniform(-0.12, 0.12, size=moved.positions.shape)
    prunes = nl.n_prunes
    assert not nl.update(pruned_at) and nl.n_prunes == prunes + 1
    first_prune = {"partners": nl.clusters.partners, "offsets": nl.clusters.offsets}
    assert not fresh.update(pruned_at)
    _same_lists(nl, fresh)
    nl.build(moved)
    assert not nl.update(pruned_at) and nl.n_prunes == prunes + 2
    assert np.shares_memory(nl.clusters.partners, first_prune["partners"])
    assert np.shares_memory(nl.clusters.offsets, first_prune["offsets"])
    _same_lists(nl, fresh)


def test_kept_arrays_grow_when_short_and_are_never_shrunk():
    """``take`` hands out the first rows of the kept array: the same memory for as many
    rows or fewer, a new array (with room to spare) only for more, or another dtype or
    row shape."""
    kept = KeptArrays()
    first = kept.take("a", 100, np.float32, (3,))
    assert first.shape == (100, 3) and first.dtype == np.float32
    shorter = kept.take("a", 40, np.float32, (3,))
    assert shorter.shape == (40, 3) and np.shares_memory(shorter, first)
    again = kept.take("a", 100, np.float32, (3,))
    assert np.shares_memory(again, first)
    longer = kept.take("a", 200, np.float32, (3,))
    assert longer.shape == (200, 3) and not np.shares_memory(longer, first)
    assert np.shares_memory(kept.take("a", 205, np.float32, (3,)), longer)  # room to spare
    assert not np.shares_memory(kept.take("a", 10, np.float64, (3,)), longer)
    assert kept.take("b", 10, np.int32).shape == (10,)


def test_the_cluster_kernels_scratch_follows_a_search_of_other_clusters_in_place(fcc_lattice, rng):
    """The pair frame's per-cluster scratch (its length the list's clusters, which change
    from search to search) is written in place after a search with other clusters (the
    old code made it afresh for every other count), and the forces are a fresh
    potential's."""
    state = fcc_lattice(cells=6, perturbation=0.05)
    potential = LennardJones(cutoff=CUTOFF)
    nl = NeighborList(CUTOFF, SKIN, clusters=True, outer_skin=OUTER_SKIN)
    nl.build(state)
    potential.energy_forces(state, nl, precision="mixed")
    clusters, held = nl.clusters.n_clusters, potential._cluster_scratch[:3]
    moved = state.copy()
    while nl.clusters.n_clusters == clusters:  # (the columns' padding: other clusters)
        moved.positions += rng.uniform(-0.1, 0.1, size=moved.positions.shape)
        nl.build(moved)
    result = potential.energy_forces(moved, nl, precision="mixed")
    for array, before in zip(potential._cluster_scratch[:3], held, strict=True):
        assert len(array) != len(before) and np.shares_memory(array, before)
    fresh_list = NeighborList(CUTOFF, SKIN, clusters=True, outer_skin=OUTER_SKIN)
    fresh_list.build(moved)
    fresh = LennardJones(cutoff=CUTOFF).energy_forces(moved, fresh_list, precision="mixed")
    assert result.energy == fresh.energy
    assert np.array_equal(result.forces, fresh.forces)
