"""The cluster search's window cursors and window check (issue 70).

A window's cursors move by block counts (``_count_below``, ``_count_not_above``: a
vector of z bounds compared with a limit, the lanes past the column masked off, the
rest counted) in place of a loop per cluster: the same places as a scan, for any
jump, ties at the limit and columns that end inside a block. The search's own window
check (``_keep_both``) stores each offset as four floats and keeps the pairs the
prune's check keeps, pair for pair, writing nothing past the slot after its last
candidate. The grid's wrap without a division gives the bits of the formula with one.
"""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit
from scipy.spatial import cKDTree

import md
from md.neighbors._cluster_grid import _wrap_atoms, cluster_grid, column_counts
from md.neighbors._cluster_prune import cluster_positions, keep_window_both
from md.neighbors._cluster_search import (
    _BLOCK,
    _count_below,
    _count_not_above,
    _first_above,
    _first_not_below,
    _keep_both,
    search_pairs,
)

OUTER, INNER = 4.0, 2.8


def _reach2(radius):
    return np.float32((radius * (1.0 + 1e-5)) ** 2)


@njit(cache=False)
def _counts(bounds, start, room, limit):
    return _count_below(bounds, start, room, limit), _count_not_above(bounds, start, room, limit)


@njit(cache=False)
def _cursors(top, bottom, begin, end, stop, low, high):
    return _first_not_below(top, begin, stop, low), _first_above(bottom, end, stop, high)


def _rising(rng, n):
    """Rising bounds with ties (each value drawn from a few), padded with a block of +inf."""
    values = np.sort(rng.choice(np.arange(0.0, 12.0, 0.5), n))
    return np.concatenate([values, np.full(_BLOCK, np.inf)])


def test_a_block_count_is_the_count_of_a_scan_masked_at_the_column_end(rng):
    bounds = _rising(rng, 40)
    for _ in range(300):
        start = int(rng.integers(0, 41))
        room = int(rng.integers(0, 41 - start + 1))
        limit = float(rng.choice([bounds[min(start + 3, 39)], rng.uniform(-1.0, 13.0)]))
        block = bounds[start : start + _BLOCK]
        inside = np.arange(_BLOCK) < room
        expected = (int(((block < limit) & inside).sum()), int(((block <= limit) & inside).sum()))
        assert _counts(bounds, start, room, limit) == expected
        assert _count_below.python_twin(bounds, start, room, limit) == expected[0]
        assert _count_not_above.python_twin(bounds, start, room, limit) == expected[1]


def test_the_cursors_find_a_scans_places_for_jumps_longer_than_a_block(rng):
    # one column of 30 clusters then the next column's, whose bounds start low again: a
    # block that runs past the column's end must not count them
    column = _rising(rng, 30)[:30]
    tops = np.concatenate([column, column - 5.0, np.full(_BLOCK, np.inf)])
    bottoms = tops - 0.5
    for _ in range(300):
        begin = int(rng.integers(0, 31))
        low = float(rng.choice([column[min(begin + 12, 29)], rng.uniform(-1.0, 13.0)]))
        high = low + float(rng.uniform(0.0, 6.0))
        end = int(rng.integers(begin, 31))
        scan_begin = begin
        while scan_begin < 30 and tops[scan_begin] < low:
            scan_begin += 1
        scan_end = max(end, scan_begin)
        while scan_end < 30 and bottoms[scan_end] <= high:
            scan_end += 1
        found = _cursors(tops, bottoms, begin, max(end, scan_begin), 30, low, high)
        assert found == (scan_begin, scan_end)


def _grid(state):
    ncx, ncy = column_counts(state.box, state.n_atoms, OUTER)
    first, atom, origin, lower, upper = cluster_grid(state.positions, state.box, ncx, ncy)
    xi = np.empty(3 * len(atom), np.float32)
    xj = np.empty(3 * len(atom), np.float32)
    cluster_positions(state.positions, atom, origin, xi, xj)
    return (ncx, ncy, first, lower, upper), xi, xj


@njit(cache=False)
def _window(xi, xj, ci, lo, hi, p, centres, reach2, inner2, outer, inner, k, m):
    """_keep_both's window, and keep_window_both's on copies of the same buffers."""
    got = _keep_both(
        xi, xj, ci, lo, hi, p[0], p[1], p[2], centres, reach2, inner2, *outer[:2], k, *inner[:2], m
    )
    x, y, z = centres[:, 0].copy(), centres[:, 1].copy(), centres[:, 2].copy()
    want = keep_window_both(
        xi, xj, ci, lo, hi, p[0], p[1], p[2], x, y, z, reach2, inner2, *outer[2:], k, *inner[2:], m
    )
    return got, want


def test_the_window_check_keeps_the_prunes_pairs_and_writes_one_slot_past_at_most(fcc_lattice, rng):
    state = fcc_lattice(cells=5, perturbation=0.15)
    (ncx, ncy, first, lower, upper), xi, xj = _grid(state)
    n = lower.shape[0]
    centres = np.zeros((n, 4))
    centres[:, :3] = 0.5 * (lower + upper)
    kept = near = 0
    for _ in range(40):
        ci = int(rng.integers(0, n))
        lo = int(rng.integers(0, n - 12))
        hi = lo + int(rng.integers(0, 12))
        p = centres[ci, :3] - rng.choice([-1.0, 0.0, 1.0], 3) * state.box * (rng.random() < 0.2)
        k, m = int(rng.integers(0, 5)), int(rng.integers(0, 5))
        outer = (
            np.full(40, -7, np.int32),
            np.full((40, 3), np.nan, np.float32),
            np.full(40, -7, np.int32),
            np.full((40, 3), np.nan, np.float32),
        )
        inner = tuple(a.copy() for a in outer)
        got, want = _window(
            xi, xj, ci, lo, hi, p, centres, _reach2(OUTER), _reach2(INNER), outer, inner, k, m
        )
        assert got == want
        twin = tuple(
            np.full_like(a, -7) if a.dtype == np.int32 else np.zeros_like(a) for a in outer
        )
        p32 = [float(v) for v in p]
        radii = (_reach2(OUTER), _reach2(INNER))
        ends = _keep_both.python_twin(
            xi, xj, ci, lo, hi, *p32, centres, *radii, twin[0], twin[1], k, twin[2], twin[3], m
        )
        assert ends == got
        assert np.array_equal(twin[0][k : got[0]], outer[0][k : got[0]])
        assert np.array_equal(twin[1][k : got[0]], outer[1][k : got[0]])
        assert np.array_equal(twin[2][m : got[1]], inner[0][m : got[1]])
        assert np.array_equal(twin[3][m : got[1]], inner[1][m : got[1]])
        for lists, start, end in ((outer, k, got[0]), (inner, m, got[1])):
            assert np.array_equal(lists[0][start:end], lists[2][start:end])
            assert np.array_equal(lists[1][start:end], lists[3][start:end])
            last = start + (hi - lo)  # one past the last slot written
            assert np.all(lists[0][last:] == -7)
            assert np.all(np.isnan(lists[1][last + 1 :]))
            assert np.all(np.isnan(lists[1][last, 1:]))
        kept += got[0] - k
        near += got[1] - m
    assert 0 < near < kept  # windows with pairs kept in each list, and pairs dropped


@pytest.mark.parametrize("chunks", [1, 2, 3])
def test_a_tall_box_searched_on_chunks_gives_every_atom_pair_once(chunks, rng):
    # columns of 14-18 clusters: the images in z send a cursor from a column's foot to
    # its top in one move, far past a block
    cell = md.lattice("fcc", 1, density=0.8442)
    shifts = np.stack(np.meshgrid(range(8), range(8), range(16), indexing="ij"), -1)
    sites = (cell.positions[None] + (shifts.reshape(-1, 1, 3) * cell.box)).reshape(-1, 3)
    box = cell.box * np.array([8.0, 8.0, 16.0])
    state = md.State(
        sites + rng.normal(0.0, 0.2, sites.shape), np.zeros_like(sites), np.ones(len(sites)), box
    )
    grid, xi, xj = _grid(state)
    ncx, ncy, first, lower, upper = grid
    assert (first[1:] - first[:-1]).min() > _BLOCK
    found = search_pairs(
        state.box, ncx, ncy, first, lower, upper, OUTER, chunks, 256, xi, xj, _reach2(OUTER)
    )
    assert found is not None
    starts, partners, offsets = found
    atom, origin = cluster_grid(state.positions, state.box, ncx, ncy)[1:3]
    relative = np.where(atom[:, None] >= 0, state.positions[atom] - origin, np.nan)
    rows = np.repeat(np.arange(len(starts) - 1), np.diff(starts))
    slots_i = 4 * rows[:, None] + np.arange(4)  # (pairs, 4)
    slots_j = 4 * partners[:, None].astype(np.int64) + np.arange(4)
    # each atom pair at the cluster pair's own image (its offset), not the nearest one
    d = relative[slots_i][:, :, None] - relative[slots_j][:, None, :] + offsets[:, None, None]
    close = (d * d).sum(axis=3) < OUTER**2 * (1 - 1e-6)  # NaN (fillers): False
    a, b = atom[slots_i][:, :, None], atom[slots_j][:, None, :]
    close &= (rows != partners)[:, None, None] | (a < b)
    q, u, v = np.nonzero(close)
    a, b = atom[slots_i[q, u]], atom[slots_j[q, v]]
    n = state.n_atoms
    listed = np.sort(np.minimum(a, b) * n + np.maximum(a, b))  # each atom pair as one key
    assert np.all(np.diff(listed) > 0)  # each atom pair once
    wrapped = state.positions - np.floor(state.positions / state.box) * state.box
    tree = cKDTree(wrapped, boxsize=state.box)
    expected = tree.query_pairs(OUTER * np.sqrt(1 - 1e-6), output_type="ndarray")
    assert np.array_equal(listed, np.sort(expected.min(axis=1) * n + expected.max(axis=1)))


@njit(cache=False)
def _wrapped(positions, box):
    wrapped = np.empty_like(positions)
    key = np.empty(positions.shape[0], np.int64)
    _wrap_atoms(positions, box, 3, 3, 2, wrapped, key, 0, positions.shape[0])
    return wrapped


def test_the_wrap_without_a_division_gives_the_formulas_bits(rng):
    box = np.array([7.3, 5.1, 9.9])
    inside = rng.uniform(0.0, 1.0, (200, 3)) * box
    edges = np.array(
        [[-0.0, 0.0, 5e-324], [7.3 * (1 - 1e-9), 5.1 * (1 - 2e-16), 9.9 * (1 - 1e-12)]]
    )
    outside = rng.uniform(-3.0, 3.0, (200, 3)) * box
    positions = np.concatenate([inside, edges, outside, -edges])
    formula = positions - np.floor(positions / box) * box
    formula = np.where(formula >= box, formula - box, formula)
    got = _wrapped(positions, box)
    assert np.array_equal(got.view(np.int64), formula.view(np.int64))  # -0.0 too
