"""The bounded prune: pairs whose verdict cannot have changed are not checked again.

Each outer pair keeps the margin by which its closest atom pair missed or made the list
radius at its last check, each cluster the farthest its atoms drifted between prunes;
a prune checks atom by atom only the pairs whose clusters drifted farther than their
margin since, and gives the list of the full check pair for pair (``prune_pairs``), on
one chunk and several, with fewer atom checks than the full check's one per pair.
"""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit

from md.neighbors import NeighborList
from md.neighbors._cluster_kernels import (
    _near_min_pair,
    _near_min_pair_twin,
    balanced_chunks,
    cluster_drift,
    prune_pairs,
    prune_pairs_bounded,
)
from md.parallel import get_threads, set_threads


@njit
def _compiled_near_min_pair(xi, xj, ci, cj, ox, oy, oz, reach2):
    return _near_min_pair(xi, xj, ci, cj, ox, oy, oz, reach2)


def _full_prune(outer, xi, xj, reach2, chunks):
    """The outer list pruned by ``prune_pairs``: every pair checked."""
    kept_starts = np.empty_like(outer.starts)
    kept_partners = np.empty_like(outer.partners)
    kept_offsets = np.empty_like(outer.offsets)
    kept = prune_pairs(
        outer.starts,
        outer.partners,
        outer.offsets,
        balanced_chunks(outer.starts, chunks),
        xi,
        xj,
        reach2,
        kept_starts,
        kept_partners,
        kept_offsets,
    )
    return kept_starts, kept_partners[:kept], kept_offsets[:kept]


@pytest.mark.parametrize("threads", [1, 2])
def test_a_neighbor_list_prunes_to_the_full_checks_list_with_fewer_checks(
    threads, fcc_lattice, rng
):
    """A cluster list moved in small steps (a prune every few of them, searches now and
    then): after every prune, the list is the full check's at those positions, array for
    array, and the prunes together checked well under one pair in two atom by atom
    (the code before checked every pair but each row's first at each prune)."""
    before = get_threads()
    set_threads(threads)
    try:
        state = fcc_lattice(cells=6, perturbation=0.05)
        nl = NeighborList(2.5, 0.3, clusters=True)
        nl.update(state)
        full_checks = prunes = 0
        for step in range(1, 61):
            state.positions += rng.normal(scale=0.03, size=state.positions.shape)
            state.step = step
            pruned = nl.n_prunes
            nl.update(state)
            if nl.n_prunes == pruned:
                continue
            prunes += 1
            outer = nl.outer_clusters
            full_checks += outer.n_pairs - outer.n_clusters
            xi = np.empty(12 * outer.n_clusters, np.float32)
            xj = np.empty_like(xi)
            outer.relative_positions(state.positions, xi, xj)
            reference = _full_prune(outer, xi, xj, nl._prune_reach2(), len(outer.bounds) - 1)
            for name, theirs in zip(("starts", "partners", "offsets"), reference, strict=True):
                mine = getattr(nl.clusters, name)
                assert mine.dtype == theirs.dtype
                assert np.array_equal(mine, theirs), (step, name)
        assert prunes >= 4 and nl.n_builds >= 2, (prunes, nl.n_builds)
        assert 0 < nl.n_prune_checks < 0.5 * full_checks, (nl.n_prune_checks, full_checks)
    finally:
        set_threads(before)


def test_the_bounded_kernel_gives_the_full_checks_list_at_any_drift(fcc_lattice, rng):
    """``prune_pairs_bounded`` against ``prune_pairs`` on one outer list moved by
    displacements small and large, on 1 and 3 chunks: the same kept pairs each time;
    the first call (no verdicts yet) checks every pair, small moves after it few, and a
    move past every margin all of them again."""
    state = fcc_lattice(cells=6, perturbation=0.1)
    nl = NeighborList(2.5, 0.3, clusters=True)
    nl.update(state)
    outer = nl.outer_clusters
    n, size = outer.n_clusters, outer.n_pairs
    reach2 = nl._prune_reach2()
    for chunks in (1, 3):
        bounds = balanced_chunks(outer.starts, chunks)
        drift = np.zeros(n)
        thresholds = np.zeros(size, np.float32)
        marks = np.empty(size, np.uint8)
        checks = np.empty(size, np.int32)
        since = state.positions.copy()
        positions = since.copy()
        counts = []
        for scale in (0.0, 0.01, 0.01, 0.02, 0.5):
            positions = positions + rng.normal(scale=scale, size=positions.shape)
            cluster_drift(positions, since, outer.atom, drift, chunks)
            since = positions.copy()
            xi = np.empty(12 * n, np.float32)
            xj = np.empty_like(xi)
            outer.relative_positions(positions, xi, xj)
            kept_starts = np.empty_like(outer.starts)
            kept_partners = np.empty_like(outer.partners)
            kept_offsets = np.empty_like(outer.offsets)
            kept, checked = prune_pairs_bounded(
                outer.starts,
                outer.partners,
                outer.offsets,
                bounds,
                xi,
                xj,
                reach2,
                drift,
                thresholds,
                marks,
                checks,
                kept_starts,
                kept_partners,
                kept_offsets,
            )
            reference = _full_prune(outer, xi, xj, reach2, chunks)
            mine = (kept_starts, kept_partners[:kept], kept_offsets[:kept])
            for a, b in zip(mine, reference, strict=True):
                assert np.array_equal(a, b), (chunks, scale)
            counts.append(int(checked))
        rows_firsts = size - n
        assert counts[0] == rows_firsts  # nothing known yet: every pair but the rows' first
        assert max(counts[1:4]) < 0.5 * rows_firsts, counts
        assert counts[4] > 0.9 * rows_firsts, counts  # moved past (nearly) every margin


def test_the_closest_pair_check_matches_its_twin_and_the_atoms(fcc_lattice):
    """``_near_min_pair`` (compiled, in the cluster kernels' lanes) gives its numpy twin's
    verdict and the smallest squared distance of the 16 atom pairs, on a listed outer
    list's pairs."""
    state = fcc_lattice(cells=6, perturbation=0.1)
    nl = NeighborList(2.5, 0.3, clusters=True)
    nl.update(state)
    outer = nl.outer_clusters
    xi = np.empty(12 * outer.n_clusters, np.float32)
    xj = np.empty_like(xi)
    outer.relative_positions(state.positions, xi, xj)
    reach2 = nl._prune_reach2()
    rows = np.repeat(np.arange(outer.n_clusters), np.diff(outer.starts))
    verdicts = set()
    for q in range(0, outer.n_pairs, 7):
        ci, cj = int(rows[q]), int(outer.partners[q])
        args = (xi, xj, ci, cj, *outer.offsets[q], reach2)
        near, closest2 = _compiled_near_min_pair(*args)
        twin_near, twin_closest2 = _near_min_pair_twin(*args)
        assert near == twin_near and near == (closest2 < reach2)
        assert closest2 == twin_closest2, q
        verdicts.add(bool(near))
    assert verdicts == {True, False}


def test_the_drift_is_each_clusters_farthest_atom(fcc_lattice, rng):
    """``cluster_drift`` adds each cluster's farthest move (fillers left out), on any
    number of chunks, and a non-finite position makes its cluster's drift non-finite."""
    state = fcc_lattice(cells=6, perturbation=0.1)
    nl = NeighborList(2.5, 0.3, clusters=True)
    nl.update(state)
    atom = nl.clusters.atom
    moved = state.positions + rng.normal(scale=0.1, size=state.positions.shape)
    step = np.sqrt(((moved - state.positions) ** 2).sum(axis=1))
    slots = np.where(atom >= 0, step[np.maximum(atom, 0)], 0.0).reshape(-1, 4)
    expected = 1.0 + slots.max(axis=1)
    for chunks in (1, 2, 5):
        drift = np.ones(len(atom) // 4)
        cluster_drift(moved, state.positions, atom, drift, chunks)
        assert np.allclose(drift, expected, rtol=1e-14, atol=0.0)
    moved[int(atom[0])] = np.nan
    drift = np.zeros(len(atom) // 4)
    cluster_drift(moved, state.positions, atom, drift, 1)
    assert not np.isfinite(drift[0]) and np.isfinite(drift[1:]).all()
