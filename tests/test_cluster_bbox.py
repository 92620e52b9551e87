"""The cluster search's bounding boxes (issue 70): columns' and clusters' xy boxes.

The search lists a candidate only where the j column's xy box (its clusters' boxes
together, at the image) comes within the radius of the i column's and of the i cluster's
own box; the lists it keeps still hold every atom pair within the list radius (and the
outer list every pair within the outer radius), checked against an O(N^2) minimum-image
search on gases, uneven and tall boxes, a film and pairs placed across a corner of the
box. The search also returns each row's reach, a bound on its last partner, which holds
for the pruned rows too; the grid's column sort (by slab, then an insertion sort) puts
each column's atoms in the order of a stable sort by z.
"""

from __future__ import annotations

import numpy as np
import pytest

from md.neighbors import NeighborList
from md.neighbors._cluster_grid import CLUSTER, cluster_grid, column_counts
from md.neighbors._cluster_prune import cluster_positions
from md.neighbors._cluster_search import search_pairs
from md.state import State

OUTER, INNER = 4.0, 2.8


def _reference_pairs(state, radius):
    """Set of (i, j), i < j, closer than ``radius`` by minimum image."""
    d = state.positions[:, None, :] - state.positions[None, :, :]
    d -= state.box * np.round(d / state.box)
    r2 = np.einsum("ijk,ijk->ij", d, d)
    i, j = np.nonzero(np.triu(r2 < radius * radius, k=1))
    return set(zip(i.tolist(), j.tolist(), strict=True))


def _listed_pairs(state, clusters, radius):
    """The atom pairs within ``radius`` of the listed cluster pairs, from the atoms'
    positions and the pairs' offsets (centre_i - centre_j - shift), as a list."""
    atoms = clusters.atom.reshape(-1, CLUSTER)
    real = atoms >= 0
    rel = state.positions[np.maximum(clusters.atom, 0)] - clusters.origin
    rel = rel.reshape(-1, CLUSTER, 3)
    found = []
    for ci in range(clusters.n_clusters):
        for k in range(clusters.starts[ci], clusters.starts[ci + 1]):
            cj = clusters.partners[k]
            d = rel[ci][:, None, :] - rel[cj][None, :, :] + clusters.offsets[k].astype(float)
            close = (np.einsum("abk,abk->ab", d, d) < radius * radius) & np.outer(
                real[ci], real[cj]
            )
            if k == clusters.starts[ci]:
                close = np.triu(close, k=1)
            for a, b in zip(*np.nonzero(close), strict=True):
                i, j = atoms[ci, a], atoms[cj, b]
                found.append((min(i, j), max(i, j)))
    return found


def _assert_holds_every_pair(state, clusters, radius):
    found = _listed_pairs(state, clusters, radius)
    assert len(found) == len(set(found)), "an atom pair is listed twice"
    missing = _reference_pairs(state, radius) - set(found)
    assert not missing, sorted(missing)[:5]


def _film(rng):
    """300 atoms in a film 1.5 thick in a tall box: each column's atoms in one or two of
    the grid sort's slabs, and the box mostly empty in z."""
    box = np.array([11.0, 11.5, 30.0])
    positions = np.column_stack(
        [rng.uniform(0, box[0], 300), rng.uniform(0, box[1], 300), rng.uniform(14, 15.5, 300)]
    )
    return State(positions=positions, masses=np.ones(300), box=box, pbc=True)


def _corner_pairs():
    """Few atoms, two pairs just within the outer radius across the box's edges and
    corner (x and y wrapped at once, then x, y and z), each atom alone near its column's
    side: the columns' xy boxes are a point each."""
    box = np.array([12.0, 12.5, 13.0])
    step = (OUTER - 1e-3) / np.sqrt(2.0)
    step3 = (OUTER - 1e-3) / np.sqrt(3.0)
    positions = np.array(
        [
            [0.01, 0.02, 6.0],
            [box[0] - step + 0.01, box[1] - step + 0.02, 6.0],
            [0.03, 0.04, 0.05],
            [box[0] - step3 + 0.03, box[1] - step3 + 0.04, box[2] - step3 + 0.05],
            [6.0, 6.2, 3.0],
            [3.0, 9.1, 10.0],
            [9.0, 3.3, 9.5],
        ]
    )
    return State(positions=positions, masses=np.ones(len(positions)), box=box, pbc=True)


def _systems(fcc_lattice, random_gas, rng):
    return {
        "rattled fcc": fcc_lattice(cells=5, perturbation=0.1),
        "gas, cubic": random_gas(200, 11.0, min_distance=0.7, images=2),
        "gas, uneven edges": random_gas(250, (10.5, 12.0, 14.5), min_distance=0.7),
        "gas, tall box": random_gas(150, (8.5, 9.0, 24.0), min_distance=0.7, images=1),
        "film": _film(rng),
        "pairs across a corner": _corner_pairs(),
    }


NAMES = [
    "rattled fcc",
    "gas, cubic",
    "gas, uneven edges",
    "gas, tall box",
    "film",
    "pairs across a corner",
]


@pytest.mark.parametrize("name", NAMES)
def test_the_lists_hold_every_pair_within_their_radius(name, fcc_lattice, random_gas, rng):
    """The search's outer list holds every atom pair within the outer radius once, and its
    own prune of it every pair within the inner radius, on one chunk and two; the list a
    NeighborList builds (with an outer list or without, as the box allows) every pair
    within the list radius."""
    state = _systems(fcc_lattice, random_gas, rng)[name]
    for chunks in (1, 2):
        grid, atom, origin, found = _search(state, OUTER, inner=INNER, chunks=chunks)
        for rows, radius in ((found[0:3], OUTER), (found[3:6], INNER)):
            _assert_holds_every_pair(state, _Rows(atom, origin, *rows), radius)
    nl = NeighborList(2.5, 0.3, clusters=True)
    nl.update(state)
    assert nl.clusters is not None, name
    _assert_holds_every_pair(state, nl.clusters, nl.list_radius)
    placed = nl.clusters.atom[nl.clusters.atom >= 0]
    assert sorted(placed.tolist()) == list(range(state.n_atoms))


class _Rows:
    """A searched list's rows with the grid's slots, as ``_listed_pairs`` reads them."""

    def __init__(self, atom, origin, starts, partners, offsets):
        self.atom, self.origin = atom, origin
        self.starts, self.partners, self.offsets = starts, partners, offsets
        self.n_clusters = len(starts) - 1


def _search(state, radius, inner=None, xi=True, chunks=1):
    ncx, ncy = column_counts(state.box, state.n_atoms, radius)
    first, atom, origin, lower, upper = cluster_grid(state.positions, state.box, ncx, ncy)
    rel_i = np.empty(3 * len(atom), np.float32)
    rel_j = np.empty(3 * len(atom), np.float32)
    cluster_positions(state.positions, atom, origin, rel_i, rel_j)
    found = search_pairs(
        state.box,
        ncx,
        ncy,
        first,
        lower,
        upper,
        radius,
        chunks,
        512,
        rel_i if xi else None,
        rel_j if xi else None,
        np.float32((radius * (1 + 1e-5)) ** 2),
        None if inner is None else np.float32((inner * (1 + 1e-5)) ** 2),
        with_reach=True,
    )
    return (ncx, ncy, first, lower, upper), atom, origin, found


@pytest.mark.parametrize("name", ["gas, cubic", "gas, uneven edges", "pairs across a corner"])
def test_every_candidate_comes_within_reach_of_its_columns_box(name, fcc_lattice, random_gas, rng):
    """Every candidate (the search with no atom check) has its j column's xy box, at the
    pair's image, within the radius of the i cluster's box in xy: a column whose
    rectangle comes within reach but whose atoms do not gives no candidates."""
    state = _systems(fcc_lattice, random_gas, rng)[name]
    (ncx, ncy, first, lower, upper), _, _, (starts, partners, offsets, _) = _search(
        state, OUTER, xi=False
    )
    column_of = np.repeat(np.arange(ncx * ncy), np.diff(first))
    extent = np.full((ncx * ncy, 4), [np.inf, -np.inf, np.inf, -np.inf])
    for cl, col in enumerate(column_of):
        extent[col, 0] = min(extent[col, 0], lower[cl, 0])
        extent[col, 1] = max(extent[col, 1], upper[cl, 0])
        extent[col, 2] = min(extent[col, 2], lower[cl, 1])
        extent[col, 3] = max(extent[col, 3], upper[cl, 1])
    centres = 0.5 * (lower + upper)
    rows = np.repeat(np.arange(len(starts) - 1), np.diff(starts))
    for ci, cj, offset in zip(rows, partners, offsets.astype(float), strict=True):
        # the j cluster's image sits at centre_i - offset: its shift in x and y
        shift = np.round((centres[ci] - offset - centres[cj]) / state.box) * state.box
        ex = extent[column_of[cj]] + np.repeat(shift[:2], 2)
        gx = max(ex[0] - upper[ci, 0], lower[ci, 0] - ex[1], 0.0)
        gy = max(ex[2] - upper[ci, 1], lower[ci, 1] - ex[3], 0.0)
        assert gx * gx + gy * gy < OUTER * OUTER, (ci, cj, gx, gy)


@pytest.mark.parametrize("chunks", [1, 2, 3])
def test_the_searchs_reach_bounds_each_rows_last_partner_in_both_lists(
    chunks, fcc_lattice, random_gas, rng
):
    """``with_reach``: per i cluster at least one past its last partner, in the outer rows
    and the pruned ones, and never past the last cluster."""
    state = random_gas(250, (10.5, 12.0, 14.5), min_distance=0.7)
    (_, _, first, _, _), _, _, found = _search(state, OUTER, inner=INNER, chunks=chunks)
    reach = found[-1]
    n_clusters = int(first[-1])
    assert reach.shape == (n_clusters,) and reach.max() <= n_clusters
    for starts, partners in (found[0:2], found[3:5]):
        for ci in range(n_clusters):
            row = partners[starts[ci] : starts[ci + 1]]
            assert row[0] == ci
            assert row.max() + 1 <= reach[ci]


def _crowded(rng):
    """200 atoms at random and 40 more at one height in one corner of the box: a slab of
    the grid's sort with more atoms than its insertion sort takes (a merge sort)."""
    box = np.array([12.0, 12.0, 12.0])
    positions = np.vstack(
        [
            rng.uniform(0, 12.0, (200, 3)),
            np.column_stack([rng.uniform(0.1, 0.5, (40, 2)), np.full(40, 5.0)]),
        ]
    )
    return State(positions=positions[rng.permutation(240)], masses=np.ones(240), box=box, pbc=True)


@pytest.mark.parametrize("name", ["gas, tall box", "film", "crowded slab"])
def test_the_grid_sorts_each_column_by_z_stably(name, fcc_lattice, random_gas, rng):
    """Each column's atoms rise in z, equal heights in atom order (copies of atoms at
    equal z; a slab of 40 atoms at one height), whichever sort the column took."""
    if name == "crowded slab":
        state = _crowded(rng)
    else:
        state = _systems(fcc_lattice, random_gas, rng)[name]
        state.positions[:20, 2] = state.positions[20:40, 2]  # equal heights
    ncx, ncy = column_counts(state.box, state.n_atoms, OUTER)
    first, atom, _, _, _ = cluster_grid(state.positions, state.box, ncx, ncy)
    wrapped = state.positions % state.box
    for c in range(ncx * ncy):
        slots = atom[first[c] * CLUSTER : first[c + 1] * CLUSTER]
        ids = slots[slots >= 0]
        expected = sorted(ids.tolist(), key=lambda i: (wrapped[i, 2], i))
        assert ids.tolist() == expected, c
