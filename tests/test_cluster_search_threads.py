"""Issue 70: the chunked cluster search on the threads, and its join.

A search on more than one chunk writes each chunk's rows into its own part of one
buffer, the chunks claimed one at a time by the threads (``_claim``: an atomic
increment in IR), so that a thread that starts late leaves its chunks to the others;
then it moves each part but the first down to follow the one before, one block per
array (``_move_rows``: a ``memmove`` in IR, with a numpy twin), on the calling thread:
no pair-by-pair loop and no threaded region of its own. The lists are those of one
chunk, array for array, on any number of chunks and threads, however the parts overlap
their places.
"""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit, prange

from md.neighbors._cluster_grid import cluster_grid, column_counts
from md.neighbors._cluster_prune import cluster_positions
from md.neighbors._cluster_search import (
    _claim,
    _column_chunks,
    _joined,
    _move_rows,
    search_pairs,
)
from md.parallel import get_threads, max_threads, set_threads

OUTER, INNER = 4.0, 2.8


@njit(cache=True)
def _move_compiled(array, source, target, count):
    _move_rows(array, source, target, count)


def _arrays(n):
    values = np.arange(n, dtype=np.int32) * 7 - 11
    rows = np.stack([values + 0.25, -values - 0.5, values * 2.0], axis=1).astype(np.float32)
    return values, rows


@pytest.mark.parametrize(
    ("source", "target", "count"),
    [
        (20, 3, 10),  # apart
        (20, 13, 10),  # overlapping, down (the join's case when a part's gap is small)
        (13, 20, 10),  # overlapping, up
        (5, 5, 9),  # in place
        (30, 0, 0),  # nothing
        (1, 0, 39),  # by one row, almost all of it
    ],
)
def test_a_block_move_is_numpys_copy_for_any_overlap(source, target, count):
    """The compiled block move of int32 rows and of (n, 3) float32 rows gives what its
    numpy twin gives (and a copy through a temporary), rows outside the target
    untouched, whether or not the two ranges overlap and in either direction."""
    for array in _arrays(40):
        expected = array.copy()
        expected[target : target + count] = array[source : source + count].copy()
        compiled, twin = array.copy(), array.copy()
        _move_compiled(compiled, source, target, count)
        _move_rows.python_twin(twin, source, target, count)
        assert np.array_equal(compiled, expected)
        assert np.array_equal(twin, expected)


@njit(cache=True, parallel=True)
def _claims(workers, counter, seen):
    for _ in prange(workers):
        while True:
            k = _claim(counter)
            if k >= seen.shape[0]:
                break
            seen[k] += 1  # each number by the one thread that claimed it


def test_each_claim_gets_a_number_of_its_own_on_two_threads():
    """Two threads claiming from one counter as fast as they can: every number from 0 up
    is claimed once, none twice or never (a plain load, add and store would hand the
    same number to both threads now and then), and the counter ends one past per
    thread's last, refused claim; the Python twin counts the same on one thread."""
    if max_threads() < 2:
        pytest.skip("one core: no two threads to race")
    before = get_threads()
    try:
        set_threads(2)
        seen = np.zeros(200_000, np.int64)
        counter = np.zeros(1, np.int64)
        _claims(2, counter, seen)
        assert np.all(seen == 1) and counter[0] == seen.shape[0] + 2
    finally:
        set_threads(before)
    counter = np.zeros(1, np.int64)
    assert [_claim.python_twin(counter) for _ in range(3)] == [0, 1, 2] and counter[0] == 3


def test_the_join_gives_the_rows_in_order_whatever_the_gap_before_each_part():
    """Three chunks whose parts lie 0 to 12 pairs past where their rows begin in the
    list (so each later part's move overlaps its source by anything from all to none of
    it): the joined partners and offsets are the chunks' pairs in order, the lists the
    buffers' first pairs."""
    counts = np.array([3, 0, 5, 4, 2, 6], np.int64)  # rows of clusters 0-5
    first = np.array([0, 2, 4, 6], np.int64)  # three columns of two clusters
    column_bounds = np.array([0, 1, 2, 3], np.int64)
    used = np.array([3, 9, 8], np.int64)
    for gap in range(13):
        place = np.array([0, 3 + gap, 12 + 2 * gap, 20 + 3 * gap], np.int64)
        partners = np.full(place[-1], -1, np.int32)
        offsets = np.full((place[-1], 3), np.nan, np.float32)
        expected = []
        for t in range(3):
            values = 100 * t + np.arange(used[t], dtype=np.int32)
            partners[place[t] : place[t] + used[t]] = values
            offsets[place[t] : place[t] + used[t]] = values[:, None] + np.float32(0.5)
            expected.append(values)
        expected = np.concatenate(expected)
        starts, joined, joined_offsets = _joined(
            counts,
            first,
            column_bounds,
            used,
            place,
            partners,
            offsets,
            np.empty(len(counts) + 1, np.int64),
        )
        assert np.array_equal(starts, np.concatenate([[0], np.cumsum(counts)]))
        assert np.array_equal(joined, expected), gap
        assert np.array_equal(joined_offsets, np.repeat(expected[:, None] + np.float32(0.5), 3, 1))
        assert np.shares_memory(joined, partners) and np.shares_memory(joined_offsets, offsets)


def _search(state, chunks, room=256):
    ncx, ncy = column_counts(state.box, state.n_atoms, OUTER)
    first, atom, origin, lower, upper = cluster_grid(state.positions, state.box, ncx, ncy)
    xi = np.empty(3 * len(atom), np.float32)
    xj = np.empty(3 * len(atom), np.float32)
    cluster_positions(state.positions, atom, origin, xi, xj)
    reach2 = np.float32((OUTER * (1.0 + 1e-5)) ** 2)
    inner2 = np.float32((INNER * (1.0 + 1e-5)) ** 2)
    found = search_pairs(
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
        reach2,
        inner2,
        with_reach=True,
    )
    return found, (ncx, ncy, first)


@pytest.mark.parametrize("threads", [1, 2])
def test_more_chunks_than_threads_and_columns_give_the_lists_of_one_chunk(threads, fcc_lattice):
    """On 2, 3, 5 and 12 chunks (12 more than the box's columns hold work for: some
    chunks empty), on one thread and two: both lists, their row starts and the rows'
    reach are one chunk's, array for array, with the room of 256 pairs a cluster and
    with the least room that holds them (the parts close together, the moves
    overlapping their sources)."""
    state = fcc_lattice(cells=6, perturbation=0.15)
    before = get_threads()
    try:
        set_threads(min(threads, before))
        one, (ncx, ncy, first) = _search(state, 1)
        assert len(one[1]) > len(one[4]) > 0
        for chunks in (2, 3, 5, 12):
            bounds = _column_chunks(state.box, ncx, ncy, first, OUTER, chunks)
            assert bounds[0] == 0 and bounds[-1] == ncx * ncy and np.all(np.diff(bounds) >= 0)
            # the room the build starts with, and the least that holds the pairs (the
            # parts close together): a search whose room ran out returns None
            tight = len(one[1]) // len(one[0])
            for room in (256, tight):
                more, _ = _search(state, chunks, room)
                while more is None:
                    room += 4
                    more, _ = _search(state, chunks, room)
                for mine, theirs in zip(more, one, strict=True):
                    assert np.array_equal(mine, theirs), (chunks, room)
    finally:
        set_threads(before)


def test_the_chunks_work_model_is_the_columns_clusters_times_those_they_search(fcc_lattice):
    """The chunk bounds from the work model (each column's clusters times those of the
    neighbouring columns it searches, the columns before it left out) cut its running
    sum where a plain numpy count of the same model cuts it."""
    state = fcc_lattice(cells=6, perturbation=0.15)
    ncx, ncy = column_counts(state.box, state.n_atoms, OUTER)
    first = cluster_grid(state.positions, state.box, ncx, ncy)[0]
    reach_x = int(np.ceil(OUTER / (state.box[0] / ncx)))
    reach_y = int(np.ceil(OUTER / (state.box[1] / ncy)))
    sizes = np.diff(first)
    work = np.zeros(ncx * ncy + 1)
    for c in range(ncx * ncy):
        cx, cy = divmod(c, ncy)
        searched = sum(
            sizes[((cx + dx) % ncx) * ncy + (cy + dy) % ncy]
            for dx in range(-reach_x, reach_x + 1)
            for dy in range(-reach_y, reach_y + 1)
            if first[((cx + dx) % ncx) * ncy + (cy + dy) % ncy + 1] > first[c]
        )
        work[c + 1] = work[c] + sizes[c] * searched
    n_columns = ncx * ncy
    for chunks in (2, 3, 4):
        bounds = _column_chunks(state.box, ncx, ncy, first, OUTER, chunks)
        cuts = [t * work[-1] / chunks for t in range(1, chunks)]
        inside = [next((c for c in range(n_columns) if work[c] >= cut), n_columns) for cut in cuts]
        assert list(bounds) == [0, *inside, n_columns], chunks
