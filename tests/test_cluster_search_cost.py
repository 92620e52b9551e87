"""Issue 70: what a cluster search costs beyond its candidates.

A search on more than one chunk writes each chunk's rows into its own part of one buffer
and moves each part but the first down after the one before: the lists are that buffer's
first pairs, not a fresh copy of every chunk (the same lists as one chunk's); each chunk
writes from its place in the whole buffer, not into a slice of it (numba types a slice
as a non-contiguous array, whose loops are slower). A build's relative positions run on
the threads as a prune's do. ``benchmarks/cluster_pruning.py --sections`` times the
search, whose build passes it a keyword.
"""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import numpy as np
import pytest

import md.neighbors.lists as lists
from md.neighbors import NeighborList
from md.neighbors._cluster_grid import cluster_grid, column_counts
from md.neighbors._cluster_prune import cluster_positions
from md.neighbors._cluster_search import _column_extents, _joined, _search_columns, search_pairs
from md.parallel import get_threads, set_threads

OUTER, INNER = 4.0, 2.8
BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def _reach2(radius):
    return np.float32((radius * (1.0 + 1e-5)) ** 2)


def _grid(state):
    ncx, ncy = column_counts(state.box, state.n_atoms, OUTER)
    first, atom, origin, lower, upper = cluster_grid(state.positions, state.box, ncx, ncy)
    xi = np.empty(3 * len(atom), np.float32)
    xj = np.empty(3 * len(atom), np.float32)
    cluster_positions(state.positions, atom, origin, xi, xj)
    return (ncx, ncy, first, lower, upper), xi, xj


def _search(state, grid, xi, xj, chunks):
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
        256,
        xi,
        xj,
        _reach2(OUTER),
        _reach2(INNER),
    )


@pytest.mark.parametrize("chunks", [2, 3])
def test_a_chunked_search_gives_the_lists_of_one_chunk(chunks, fcc_lattice):
    """On 2 and 3 chunks both lists (outer and its prune) are those of one chunk, array
    for array, after each chunk's rows were moved to follow the one before."""
    state = fcc_lattice(cells=6, perturbation=0.15)
    grid, xi, xj = _grid(state)
    one = _search(state, grid, xi, xj, 1)
    more = _search(state, grid, xi, xj, chunks)
    assert len(one[1]) > len(one[4]) > 0
    for mine, theirs in zip(more, one, strict=True):
        assert np.array_equal(mine, theirs)


@pytest.mark.parametrize("gap", [0, 2, 50])
def test_the_join_moves_each_later_chunk_down_in_the_buffer_itself(gap):
    """Three chunks' rows written into one buffer, each chunk's part ``gap`` pairs longer
    than its rows: the joined list is the buffer's first pairs (a view of it, not a fresh
    copy: the code before copied every chunk), rows in order, each pair with its offset;
    with no gap nothing moves, with a small one the moves overlap their sources (done in
    order), with a large one they do not (on the threads)."""
    counts = np.array([3, 0, 5, 4, 2, 6], np.int64)  # rows of clusters 0-5
    first = np.array([0, 2, 4, 6], np.int64)  # three columns of two clusters
    column_bounds = np.array([0, 1, 2, 3], np.int64)  # a column per chunk
    used = np.array([3, 9, 8], np.int64)
    place = np.concatenate([[0], np.cumsum(used + gap)])
    partners = np.full(place[-1], -1, np.int32)
    offsets = np.full((place[-1], 3), np.nan, np.float32)
    expected = []
    for t in range(3):
        values = 100 * t + np.arange(used[t], dtype=np.int32)
        partners[place[t] : place[t] + used[t]] = values
        offsets[place[t] : place[t] + used[t]] = values[:, None] + np.float32(0.25)
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
    assert np.array_equal(joined, expected)
    assert np.array_equal(joined_offsets, np.repeat(expected[:, None] + np.float32(0.25), 3, 1))
    assert np.shares_memory(joined, partners) and np.shares_memory(joined_offsets, offsets)


def test_a_chunk_writes_the_same_rows_from_any_place_of_the_buffer(fcc_lattice):
    """The columns' rows written from place 0 and from place 37 of a larger buffer: the
    same counts, reach, partners and offsets (outer and inner), shifted by 37, and the
    pairs written returned, not the place reached; nothing written before the place."""
    state = fcc_lattice(cells=5, perturbation=0.1)
    (ncx, ncy, first, lower, upper), xi, xj = _grid(state)
    n_clusters = lower.shape[0]
    extents = _column_extents(first, lower, upper)
    results = {}
    for place in (0, 37):
        size = place + 256 * n_clusters
        partners = np.full(size, -7, np.int32)
        offsets = np.zeros((size, 3), np.float32)
        inner = (
            np.full(size, -7, np.int32),
            np.zeros((size, 3), np.float32),
            np.zeros(n_clusters, np.int64),
            _reach2(INNER),
        )
        counts = np.zeros(n_clusters, np.int64)
        reach = np.zeros(n_clusters, np.int64)
        written = _search_columns(
            state.box,
            ncx,
            ncy,
            first,
            lower,
            upper,
            extents,
            OUTER,
            0,
            ncx * ncy,
            counts,
            reach,
            partners,
            offsets,
            place,
            size,
            xi,
            xj,
            _reach2(OUTER),
            inner,
        )
        assert written == counts.sum() > 0
        assert np.all(partners[:place] == -7) and np.all(inner[0][:place] == -7)
        kept = inner[2].sum()
        results[place] = (
            counts,
            reach,
            partners[place : place + written],
            offsets[place : place + written],
            inner[2],
            inner[0][place : place + kept],
            inner[1][place : place + kept],
        )
    for mine, theirs in zip(results[37], results[0], strict=True):
        assert np.array_equal(mine, theirs)


def test_the_build_computes_its_relative_positions_on_the_threads(fcc_lattice, monkeypatch):
    """At two threads, with a system large enough for two chunks of slots, a build's
    relative positions (the search's atom check reads them) go through the threaded
    pass, as a prune's do; the list is the one-thread build's."""
    state = fcc_lattice(cells=6, perturbation=0.1)
    calls = []
    threaded = lists.cluster_positions_threaded

    def recorded(*args):
        calls.append(args[-1])
        return threaded(*args)

    monkeypatch.setattr(lists, "_MIN_PASS_ATOMS", 200)
    monkeypatch.setattr(lists, "cluster_positions_threaded", recorded)
    before = get_threads()
    built = {}
    try:
        for threads in (1, 2):
            set_threads(threads)
            nl = NeighborList(2.5, 0.3, clusters=True)
            nl.update(state)
            built[threads] = nl
            assert len(calls) == (threads > 1)
    finally:
        set_threads(before)
    assert calls == [2]
    for name in ("starts", "partners", "offsets"):
        assert np.array_equal(getattr(built[1].clusters, name), getattr(built[2].clusters, name))


def test_cluster_pruning_sections_times_the_search(capsys):
    """``cluster_pruning.py --sections`` wraps the search and the prune in timers: a
    build calls the search with a keyword (``with_reach``), which the timer passes on
    (it raised a TypeError before). A small melt, a few steps."""
    sys.path.insert(0, str(BENCHMARKS))
    try:
        script = importlib.import_module("cluster_pruning")
    finally:
        sys.path.remove(str(BENCHMARKS))
    search, prune = lists.search_pairs, lists.prune_pairs
    try:
        script.main(
            ["--cells", "6", "--outer", "1.5", "--steps", "30", "--repeats", "1"]
            + ["--warm", "5", "--sections"]
        )
    finally:
        lists.search_pairs, lists.prune_pairs = search, prune
    out = capsys.readouterr().out
    assert "where a step goes" in out
    row = out.strip().splitlines()[-1].split()
    assert row[0] == "1.5" and float(row[2]) + float(row[3]) > 0.0  # searches, prunes


def test_a_pruned_list_is_checked_without_the_general_verdict(fcc_lattice, rng):
    """An exact cluster list with an outer list, in its build's own cell: each step's
    check (from the last prune, then from the search) runs in ``update``'s short path,
    never the general ``_verdict`` (which the code before called at every step), and
    gives the prunes, searches and lists of that verdict step for step."""
    state = fcc_lattice(cells=6, perturbation=0.1)
    fast = NeighborList(2.5, 0.3, clusters=True)
    general = NeighborList(2.5, 0.3, clusters=True)
    fast.update(state)
    general.update(state)
    assert fast.outer_clusters is not None
    looks = []
    verdict = fast._verdict

    def counted(current):
        looks.append(current.step)
        return verdict(current)

    fast._verdict = counted
    for step in range(1, 31):
        state.positions += rng.normal(scale=0.05, size=state.positions.shape)
        state.step = step
        general._cell_bytes = ()  # no short path: the byte test fails, the values agree
        assert fast.update(state) == general.update(state)
        assert (fast.n_builds, fast.n_prunes) == (general.n_builds, general.n_prunes)
        for name in ("starts", "partners", "offsets"):
            assert np.array_equal(getattr(fast.clusters, name), getattr(general.clusters, name))
    assert fast.n_prunes >= 2 and fast.n_builds >= 2  # both kinds of update happened
    assert looks == []
