"""The cluster search that prunes its own list as it writes it.

A search with an outer list (``search_pairs`` with ``inner2``) writes, beside the outer
list, the list a prune of it would make: the same pairs, offsets and rows, pair for pair,
on any number of chunks; the list a :class:`NeighborList` builds that way holds every
atom pair within the list radius, on one thread and two alike, and after a prune, a
resize and a search whose room ran out.
"""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit

from md.neighbors import NeighborList
from md.neighbors._cluster_grid import cluster_grid, column_counts
from md.neighbors._cluster_prune import (
    _near_pair,
    cluster_positions,
    keep_window,
    keep_window_both,
    prune_pairs,
)
from md.neighbors._cluster_search import _column_chunks, balanced_chunks, search_pairs
from md.parallel import get_threads, set_threads

OUTER, INNER = 4.0, 2.8


def _reach2(radius):
    return np.float32((radius * (1.0 + 1e-5)) ** 2)


def _grid(state, radius):
    ncx, ncy = column_counts(state.box, state.n_atoms, radius)
    first, atom, origin, lower, upper = cluster_grid(state.positions, state.box, ncx, ncy)
    xi = np.empty(3 * len(atom), np.float32)
    xj = np.empty(3 * len(atom), np.float32)
    cluster_positions(state.positions, atom, origin, xi, xj)
    return (ncx, ncy, first, lower, upper), atom, xi, xj


def _search(state, grid, xi, xj, chunks, room=256, inner=True):
    ncx, ncy, first, lower, upper = grid
    return search_pairs(
        state.box,
        ncx,
        ncy,
        first,
        lower,
        upper,
        OUTER,
        chunks,
        room,
        xi,
        xj,
        _reach2(OUTER),
        _reach2(INNER) if inner else None,
    )


def _pruned(outer, xi, xj, chunks):
    """The outer list pruned by ``prune_pairs`` (the prune between searches)."""
    starts, partners, offsets = outer
    kept_starts = np.empty_like(starts)
    kept_partners = np.empty_like(partners)
    kept_offsets = np.empty_like(offsets)
    bounds = balanced_chunks(starts, chunks)
    kept = prune_pairs(
        starts,
        partners,
        offsets,
        bounds,
        xi,
        xj,
        _reach2(INNER),
        kept_starts,
        kept_partners,
        kept_offsets,
        np.empty(len(partners), np.uint8),
    )
    return kept_starts, kept_partners[:kept], kept_offsets[:kept]


def _systems(fcc_lattice, random_gas):
    return {
        "rattled fcc, 500 atoms": fcc_lattice(cells=5, perturbation=0.1),
        "gas, 150 atoms, tall box": random_gas(150, (8.5, 9.0, 16.0), min_distance=0.7, images=1),
    }


@pytest.mark.parametrize("name", ["rattled fcc, 500 atoms", "gas, 150 atoms, tall box"])
def test_the_search_writes_the_list_its_prune_would_make_on_any_chunks(
    name, fcc_lattice, random_gas
):
    """The search's own prune (``inner2``) gives the pairs, offsets and rows of
    ``prune_pairs`` on the outer list, which is the search's without ``inner2``; on 1, 2
    and 3 chunks the same lists bit for bit."""
    state = _systems(fcc_lattice, random_gas)[name]
    grid, _, xi, xj = _grid(state, OUTER)
    plain = _search(state, grid, xi, xj, 1, inner=False)
    assert len(plain) == 3
    reference = _pruned(plain, xi, xj, 1)
    assert 0 < len(reference[1]) < len(plain[1])
    for chunks in (1, 2, 3):
        found = _search(state, grid, xi, xj, chunks)
        assert len(found) == 6
        for mine, theirs in zip(found, (*plain, *reference), strict=True):
            assert mine.dtype == theirs.dtype
            assert np.array_equal(mine, theirs), chunks


def test_a_search_out_of_room_asks_for_more_and_then_gives_both_lists(fcc_lattice):
    state = fcc_lattice(cells=5, perturbation=0.1)
    grid, _, xi, xj = _grid(state, OUTER)
    for chunks in (1, 2):
        assert _search(state, grid, xi, xj, chunks, room=2) is None
    roomy = _search(state, grid, xi, xj, 2, room=512)
    assert all(
        np.array_equal(a, b) for a, b in zip(roomy, _search(state, grid, xi, xj, 1), strict=True)
    )


@njit
def _window_pairs(xi, xj, rows, spans, shifts, centres, reach2, inner2, both, outer_only):
    k = kept = k_outer = 0
    p, o, ip, io = both
    q, oq = outer_only
    for w in range(rows.shape[0]):
        args = (shifts[w, 0], shifts[w, 1], shifts[w, 2], centres[0], centres[1], centres[2])
        k, kept = keep_window_both(
            xi, xj, rows[w], spans[w, 0], spans[w, 1], *args, reach2, inner2, p, o, k, ip, io, kept
        )
        k_outer = keep_window(
            xi, xj, rows[w], spans[w, 0], spans[w, 1], *args, reach2, q, oq, k_outer
        )
    return k, kept, k_outer


@njit
def _near(xi, xj, ci, cj, offset, reach2):
    return _near_pair(xi, xj, ci, cj, offset[0], offset[1], offset[2], reach2)


def test_the_two_list_window_keeps_the_outer_windows_pairs_and_its_inner_subset(fcc_lattice, rng):
    """``keep_window_both`` (loop in IR): its outer list is ``keep_window``'s; its inner
    list, the outer pairs ``_near_pair`` keeps at the inner reach, in order; its Python
    twin writes the same."""
    state = fcc_lattice(cells=5, perturbation=0.1)
    grid, _, xi, xj = _grid(state, INNER)
    lower, upper = grid[3], grid[4]
    centres = np.ascontiguousarray((0.5 * (lower + upper)).T)
    n = len(lower)
    rows = rng.integers(0, n, 30)
    spans = np.stack([np.maximum(rows - 10, 0), np.minimum(rows + 10, n)], axis=1)
    spans[3, 1] = spans[3, 0]  # an empty window
    images = np.zeros((30, 3))
    images[::5] = rng.choice([-1.0, 1.0], (6, 3))
    shifts = centres.T[rows] - images * state.box
    room = int((spans[:, 1] - spans[:, 0]).sum()) + 1
    both = (
        np.zeros(room, np.int32),
        np.zeros((room, 3), np.float32),
        np.zeros(room, np.int32),
        np.zeros((room, 3), np.float32),
    )
    outer_only = (np.zeros(room, np.int32), np.zeros((room, 3), np.float32))
    reach2, inner2 = _reach2(3.4), _reach2(2.2)
    k, kept, k_outer = _window_pairs(
        xi, xj, rows, spans, shifts, centres, reach2, inner2, both, outer_only
    )
    assert k == k_outer and 0 < kept < k < room - 1
    assert np.array_equal(both[0][:k], outer_only[0][:k])
    assert np.array_equal(both[1][:k], outer_only[1][:k])
    expected = []
    for w in range(30):
        for j in range(spans[w, 0], spans[w, 1]):
            offset = (shifts[w] - centres[:, j]).astype(np.float32)
            if _near(xi, xj, rows[w], j, offset, inner2):
                expected.append((j, offset))
    assert kept == len(expected)
    assert np.array_equal(both[2][:kept], [j for j, _ in expected])
    assert np.array_equal(both[3][:kept], np.array([o for _, o in expected]))
    twin = tuple(np.zeros_like(a) for a in both)
    k_twin = kept_twin = 0
    for w in range(30):
        k_twin, kept_twin = keep_window_both.python_twin(
            xi,
            xj,
            rows[w],
            spans[w, 0],
            spans[w, 1],
            *shifts[w],
            *centres,
            reach2,
            inner2,
            twin[0],
            twin[1],
            k_twin,
            twin[2],
            twin[3],
            kept_twin,
        )
    assert (k_twin, kept_twin) == (k, kept)
    for a, b, length in zip(twin, both, (k, k, kept, kept), strict=True):
        assert np.array_equal(a[:length], b[:length])


def _listed(state, clusters, radius=INNER):
    """The atom pairs (i < j) of the cluster list within ``radius``, with how often each
    is listed (by the pair's own relative positions and offset, in double)."""
    atom = clusters.atom.reshape(-1, 4)
    rel = (state.positions[np.maximum(clusters.atom, 0)] - clusters.origin).reshape(-1, 4, 3)
    rows = np.repeat(np.arange(clusters.n_clusters), np.diff(clusters.starts))
    partners = clusters.partners.astype(np.int64)
    d = rel[rows][:, :, None] - rel[partners][:, None, :] + clusters.offsets[:, None, None]
    close = np.einsum("kabx,kabx->kab", d, d) < radius**2
    close &= (atom[rows][:, :, None] >= 0) & (atom[partners][:, None, :] >= 0)
    own = clusters.starts[:-1]  # each row's first pair: the cluster with itself
    close[own] &= np.triu(np.ones((4, 4), bool), k=1)
    k, a, b = np.nonzero(close)
    i, j = atom[rows[k], a], atom[partners[k], b]
    counts = {}
    for pair in zip(np.minimum(i, j).tolist(), np.maximum(i, j).tolist(), strict=True):
        counts[pair] = counts.get(pair, 0) + 1
    return counts


def _within(state, radius):
    d = state.positions[:, None] - state.positions[None]
    d -= state.box * np.round(d / state.box)
    i, j = np.nonzero(np.triu(np.einsum("abk,abk->ab", d, d) < radius**2, k=1))
    return set(zip(i.tolist(), j.tolist(), strict=True))


def _built(state, threads):
    before = get_threads()
    try:
        set_threads(threads)
        nl = NeighborList(2.5, 0.3, clusters=True)
        nl.update(state)
        return nl
    finally:
        set_threads(before)


def test_the_built_list_holds_every_pair_once_and_is_the_same_on_two_threads(fcc_lattice):
    """A build with an outer list (radius 4.0, the list 2.8): the list the kernels read,
    the search's own prune, lists each atom pair within 2.8 exactly once (O(N^2) minimum
    image), the same arrays on one thread and two, and equal to a prune of the outer list."""
    state = fcc_lattice(cells=6, perturbation=0.15)
    one, two = _built(state, 1), _built(state, 2)
    assert one.outer_clusters is not None
    listed = _listed(state, one.clusters)
    assert set(listed) == _within(state, INNER)
    assert set(listed.values()) == {1}
    for name in ("starts", "partners", "offsets", "atom", "origin"):
        assert np.array_equal(getattr(one.clusters, name), getattr(two.clusters, name)), name
    outer = one.outer_clusters
    xi = np.empty(12 * outer.n_clusters, np.float32)
    xj = np.empty_like(xi)
    outer.relative_positions(state.positions, xi, xj)
    reference = _pruned((outer.starts, outer.partners, outer.offsets), xi, xj, 1)
    for mine, theirs in zip(
        (one.clusters.starts, one.clusters.partners, one.clusters.offsets), reference, strict=True
    ):
        assert np.array_equal(mine, theirs)


def test_prunes_and_a_resize_after_the_searchs_own_prune_keep_every_pair(fcc_lattice, rng):
    """The prunes between searches write over the search's relative positions (its
    buffers, kept for them): after moves that prune, the list still holds every pair
    within the cutoff, and each pair within the list radius at the prune; then a system
    of another size (new buffers) is searched afresh."""
    state = fcc_lattice(cells=6, perturbation=0.1)
    nl = NeighborList(2.5, 0.3, clusters=True)
    nl.update(state)
    for _ in range(3):
        state.positions += rng.normal(scale=0.04, size=state.positions.shape)
        nl.update(state)
        assert _within(state, 2.5) <= set(_listed(state, nl.clusters, 2.5))
        at_prune = state.copy()
        at_prune.positions = nl.pruned_positions
        assert set(_listed(at_prune, nl.clusters)) == _within(at_prune, INNER)
    assert nl.n_prunes >= 1 and nl.n_builds == 1
    bigger = fcc_lattice(cells=7, perturbation=0.1)
    nl.update(bigger)
    assert nl.n_builds == 2 and nl.outer_clusters is not None
    assert set(_listed(bigger, nl.clusters)) == _within(bigger, INNER)


@pytest.mark.parametrize("chunks", [2, 3])
def test_the_search_splits_its_columns_into_chunks_of_about_equal_work(chunks, fcc_lattice):
    """Each pair of columns is searched from the lower one's side, so the columns at the
    low end in x search the far side's too, across the boundary: the chunks are cut by
    that work (the candidates each chunk's columns check), not by their cluster counts."""
    state = fcc_lattice(cells=8, perturbation=0.1)
    grid, _, _, _ = _grid(state, OUTER)
    ncx, ncy, first, lower, upper = grid
    starts = search_pairs(
        state.box, ncx, ncy, first, lower, upper, OUTER, 1, 256, None, None, _reach2(OUTER)
    )[0]
    bounds = _column_chunks(state.box, ncx, ncy, first, OUTER, chunks)
    assert bounds[0] == 0 and bounds[-1] == ncx * ncy and np.all(np.diff(bounds) > 0)
    shares = np.diff(starts[first[bounds]]) / starts[-1]
    assert shares.max() < 1.12 / chunks, shares
