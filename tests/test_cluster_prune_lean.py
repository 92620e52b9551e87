"""The prune between cluster searches in two passes: marks, then the kept pairs copied.

``prune_pairs`` marks each pair of the outer list (one byte, ``_mark_near``), then each
chunk copies its marked pairs straight to their final places (``_copy_kept``; with
AVX-512 16 pairs at a time, ``_compress_kept``). The list is the one-pass prune's, pair
for pair (checked here against the atom check pair by pair, and in
tests/test_cluster_search.py against the search's own prune); what the two passes add:
the marks are the verdicts, and nothing is written past the kept pairs (the one pass
wrote every pair where the next kept one would go, and a later chunk's from where its
rows began, then moved them down).
"""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
from numba import njit

import md
from md.neighbors._cluster_grid import cluster_grid, column_counts
from md.neighbors._cluster_prune import (
    _compress_kept,
    _mark_near,
    _near_pair,
    cluster_positions,
    prune_pairs,
)
from md.neighbors._cluster_search import balanced_chunks, search_pairs

OUTER, INNER = 4.0, 2.8
_SENTINEL = -7  # a partner no prune writes


def _reach2(radius):
    return np.float32((radius * (1.0 + 1e-5)) ** 2)


def _outer_list(fcc_lattice, cells=5):
    """A rattled lattice's outer list (radius 4.0) and the relative positions of its atoms
    moved on (by up to about 0.2), where a prune to 2.8 keeps about half the pairs."""
    state = fcc_lattice(cells=cells, perturbation=0.1)
    ncx, ncy = column_counts(state.box, state.n_atoms, OUTER)
    first, atom, origin, lower, upper = cluster_grid(state.positions, state.box, ncx, ncy)
    xi = np.empty(3 * len(atom), np.float32)
    xj = np.empty_like(xi)
    cluster_positions(state.positions, atom, origin, xi, xj)
    starts, partners, offsets = search_pairs(
        state.box, ncx, ncy, first, lower, upper, OUTER, 1, 256, xi, xj, _reach2(OUTER)
    )
    moved = state.positions + np.random.default_rng(3).normal(
        scale=0.07, size=state.positions.shape
    )
    cluster_positions(moved, atom, origin, xi, xj)
    return starts, partners, offsets, xi, xj


def _reference(starts, partners, offsets, xi, xj, reach2):
    """The prune pair by pair in numpy: each row's pairs with an atom pair within reach
    (its first, the cluster with itself, always), in order; and each pair's verdict."""
    verdicts = np.zeros(len(partners), np.uint8)
    for ci in range(len(starts) - 1):
        for q in range(starts[ci], starts[ci + 1]):
            verdicts[q] = q == starts[ci] or _near_pair.python_twin(
                xi, xj, ci, partners[q], *offsets[q], reach2
            )
    rows = np.array([verdicts[a:b].sum() for a, b in zip(starts[:-1], starts[1:], strict=True)])
    kept_starts = np.concatenate([[0], np.cumsum(rows)])
    keep = verdicts.astype(bool)
    return kept_starts, partners[keep], offsets[keep], verdicts


@pytest.mark.parametrize("chunks", [1, 2, 3])
def test_the_prune_keeps_the_checked_pairs_and_writes_nothing_past_them(fcc_lattice, chunks):
    """On 1-3 chunks: the kept rows, partners and offsets are the pair-by-pair check's, the
    marks its verdicts, and the places past the kept pairs hold what they held before
    (the one-pass prune wrote there: its dropped pairs, and a later chunk's rows before
    their move)."""
    starts, partners, offsets, xi, xj = _outer_list(fcc_lattice)
    reach2 = _reach2(INNER)
    expected = _reference(starts, partners, offsets, xi, xj, reach2)
    assert 0.3 * len(partners) < len(expected[1]) < 0.7 * len(partners)
    kept_starts = np.full(len(starts), -1, np.int64)
    kept_partners = np.full(len(partners), _SENTINEL, np.int32)
    kept_offsets = np.full((len(partners), 3), np.nan, np.float32)
    marks = np.full(len(partners), 9, np.uint8)
    bounds = balanced_chunks(starts, chunks)
    assert len(np.unique(bounds)) == chunks + 1
    kept = prune_pairs(
        starts,
        partners,
        offsets,
        bounds,
        xi,
        xj,
        reach2,
        kept_starts,
        kept_partners,
        kept_offsets,
        marks,
    )
    assert kept == len(expected[1])
    assert np.array_equal(kept_starts, expected[0])
    assert np.array_equal(kept_partners[:kept], expected[1])
    assert np.array_equal(kept_offsets[:kept], expected[2])
    assert np.array_equal(marks, expected[3])
    assert np.all(kept_partners[kept:] == _SENTINEL)
    assert np.all(np.isnan(kept_offsets[kept:]))


def test_a_prune_with_empty_rows_and_short_ones(fcc_lattice):
    """Rows emptied and rows cut below one group of 16 pairs (the outer list's arrays
    kept, its starts made to skip pairs): the same as the pair-by-pair check."""
    starts, partners, offsets, xi, xj = _outer_list(fcc_lattice)
    rows = [np.arange(a, b) for a, b in zip(starts[:-1], starts[1:], strict=True)]
    rows[0] = rows[0][:0]
    rows[3] = rows[3][:0]
    for ci in range(5, len(rows), 4):
        rows[ci] = rows[ci][:7]
    pick = np.concatenate(rows)
    starts = np.concatenate([[0], np.cumsum([len(r) for r in rows])]).astype(np.int64)
    partners, offsets = partners[pick].copy(), offsets[pick].copy()
    reach2 = _reach2(INNER)
    expected = _reference(starts, partners, offsets, xi, xj, reach2)
    for chunks in (1, 2):
        out = (
            np.empty(len(starts), np.int64),
            np.full(len(partners), _SENTINEL, np.int32),
            np.full((len(partners), 3), np.nan, np.float32),
        )
        marks = np.empty(len(partners), np.uint8)
        bounds = balanced_chunks(starts, chunks)
        kept = prune_pairs(starts, partners, offsets, bounds, xi, xj, reach2, *out, marks)
        assert np.array_equal(out[0], expected[0]), chunks
        assert np.array_equal(out[1][:kept], expected[1]) and np.all(out[1][kept:] == _SENTINEL)
        assert np.array_equal(out[2][:kept], expected[2])


@njit
def _mark_all(xi, xj, starts, partners, offsets, reach2, marks, counts):
    for ci in range(starts.shape[0] - 1):
        counts[ci] = _mark_near(
            xi, xj, partners, offsets, starts[ci], starts[ci + 1], ci, reach2, marks
        )


def test_the_row_marks_equal_their_twin(fcc_lattice):
    """``_mark_near`` (the row's loop in IR) marks and counts as its Python twin, empty
    rows marking nothing."""
    starts, partners, offsets, xi, xj = _outer_list(fcc_lattice)
    starts = starts.copy()
    starts[1] = starts[0]  # an empty row
    reach2 = _reach2(INNER)
    marks = np.full(len(partners), 9, np.uint8)
    counts = np.zeros(len(starts) - 1, np.int64)
    _mark_all(xi, xj, starts, partners, offsets, reach2, marks, counts)
    twin = np.full(len(partners), 9, np.uint8)
    for ci in range(len(starts) - 1):
        count = _mark_near.python_twin(
            xi, xj, partners, offsets, starts[ci], starts[ci + 1], ci, reach2, twin
        )
        assert count == counts[ci], ci
    assert counts[0] == 0 and counts[1] > 1
    assert np.array_equal(marks, twin)
    assert set(np.unique(marks[starts[0] : starts[-1]])) == {0, 1}


@njit
def _compress(partners, offsets, marks, lo, hi, kept_partners, kept_offsets, k, end):
    return _compress_kept(partners, offsets, marks, lo, hi, kept_partners, kept_offsets, k, end)


@pytest.mark.parametrize("lo", [0, 5])
@pytest.mark.parametrize("room", [0, 3, 40])
def test_the_compress_takes_whole_groups_and_stops_before_the_end(lo, room):
    """``_compress_kept`` on random marks: the groups it takes are its twin's (16 pairs
    each while a whole group lies before ``hi`` and 16 places before ``end``; none
    without AVX-512), their marked pairs copied in order, nothing written at or past
    ``end`` (its whole-vector stores land only on places a later store writes again)."""
    rng = np.random.default_rng(11)
    n = 200
    partners = rng.integers(0, 1000, n).astype(np.int32)
    offsets = rng.normal(size=(n, 3)).astype(np.float32)
    marks = (rng.random(n) < 0.45).astype(np.uint8)
    hi = n - 9
    k = 4
    end = k + int(marks[lo:hi].sum()) - room
    results = {}
    for name, call in (("compiled", _compress), ("twin", _compress_kept.python_twin)):
        kept_partners = np.full(n, _SENTINEL, np.int32)
        kept_offsets = np.full((n, 3), np.nan, np.float32)
        q, to = call(partners, offsets, marks, lo, hi, kept_partners, kept_offsets, k, end)
        taken = np.flatnonzero(marks[lo:q]) + lo
        assert to == k + len(taken), name
        assert np.array_equal(kept_partners[k:to], partners[taken]), name
        assert np.array_equal(kept_offsets[k:to], offsets[taken]), name
        assert np.all(kept_partners[end:] == _SENTINEL) and np.all(np.isnan(kept_offsets[end:]))
        assert (q - lo) % 16 == 0 and to <= end
        results[name] = (q, to)
    assert results["compiled"] == results["twin"]
    if md._simd.ZMM:
        q = results["compiled"][0]
        assert q > lo and (q + 16 > hi or results["compiled"][1] + 16 > end)
    else:
        assert results["compiled"] == (lo, k)


_AVX2_ONLY = (
    "+64bit,+avx,+avx2,+bmi,+bmi2,+cmov,+cx16,+f16c,+fma,+lzcnt,+mmx,+movbe,+pclmul,+popcnt,"
    "+sahf,+sse,+sse2,+sse3,+sse4.1,+sse4.2,+ssse3,+xsave,-avx512f,-avx512bw,-avx512dq,"
    "-avx512vl,-avx512cd"
)

_PORTABLE_PRUNE = """
import sys
import numpy as np
import md._simd
from md.neighbors._cluster_prune import prune_pairs
from md.neighbors._cluster_search import balanced_chunks
assert not md._simd.ZMM
data = np.load(sys.argv[1])
starts, partners = data["starts"], data["partners"]
found = {}
for chunks in (1, 2):
    out = (np.empty(len(starts), np.int64), np.empty(len(partners), np.int32),
           np.empty((len(partners), 3), np.float32), np.empty(len(partners), np.uint8))
    kept = prune_pairs(starts, partners, data["offsets"], balanced_chunks(starts, chunks),
                       data["xi"], data["xj"], data["reach2"][()], *out)
    found[f"starts{chunks}"] = out[0]
    found[f"partners{chunks}"] = out[1][:kept]
    found[f"offsets{chunks}"] = out[2][:kept]
np.savez(sys.argv[2], **found)
print("ok")
"""


@pytest.mark.slow  # the prune compiled afresh for AVX2 in a child: about 20 s
@pytest.mark.skipif(not md._simd.PERMUTE, reason="an x86-64 CPU with AVX2 runs AVX2 code")
def test_the_prune_compiled_without_avx512_keeps_the_same_pairs(fcc_lattice, tmp_path):
    """Compiled for AVX2 alone (8-lane checks, the copy pair by pair: no compress), the
    prune keeps the pair-by-pair check's list on 1 and 2 chunks."""
    starts, partners, offsets, xi, xj = _outer_list(fcc_lattice)
    reach2 = _reach2(INNER)
    expected = _reference(starts, partners, offsets, xi, xj, reach2)
    np.savez(
        tmp_path / "outer.npz",
        starts=starts,
        partners=partners,
        offsets=offsets,
        xi=xi,
        xj=xj,
        reach2=reach2,
    )
    env = dict(
        os.environ,
        NUMBA_CPU_NAME="haswell",
        NUMBA_CPU_FEATURES=_AVX2_ONLY,
        NUMBA_CACHE_DIR=str(tmp_path / "numba"),
        XDG_CACHE_HOME=str(tmp_path),
    )
    command = [sys.executable, "-c", _PORTABLE_PRUNE, str(tmp_path / "outer.npz")]
    done = subprocess.run(
        [*command, str(tmp_path / "kept.npz")], env=env, capture_output=True, text=True, timeout=900
    )
    assert done.returncode == 0 and done.stdout.strip().endswith("ok"), done.stderr[-3000:]
    found = np.load(tmp_path / "kept.npz")
    for chunks in (1, 2):
        assert np.array_equal(found[f"starts{chunks}"], expected[0])
        assert np.array_equal(found[f"partners{chunks}"], expected[1])
        assert np.array_equal(found[f"offsets{chunks}"], expected[2])
