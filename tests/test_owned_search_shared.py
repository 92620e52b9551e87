"""A rank's owned-row search tests only the ghosts of the shell's segments near each row
(issue 69).

``NeighborList.keep_owned``'s cell search (``md.neighbors._owned_kernels``) copies the
ghosts around each column of owned cells once, in segments (one x cell of one z cell), and
an owned row tests the ghosts of the segments whose box comes within the list radius of it
in x and z, where it tested every ghost of the 125 cells around it before. The list is the
same: here the local systems are cut by hand (thin and thick slabs, bricks cut along two
and three axes, a triclinic cell, periodic images along the uncut axes) and each rank's
list is checked against brute force; the count of ghosts tested is checked against the
pairs it must find and, on a system built for it, against zero.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

import md
from md.neighbors import NeighborList
from md.parallel import get_threads, set_threads

CUTOFF, SKIN = 1.5, 0.3
RADIUS = CUTOFF + SKIN


def _cell(cells, tilt_yz=0.0):
    """A perturbed fcc lattice at the LJ melt's density in a cell of edges ``box`` with the
    (y, z) tilt ``tilt_yz`` (x-y and x-z tilts zero: a cut along x is a plane), every atom
    inside the cell."""
    state = md.lattice("fcc", cells, density=0.8442)
    box = state.box.copy()
    rng = np.random.default_rng(7)
    fractions = (state.positions / box + rng.uniform(-0.02, 0.02, state.positions.shape)) % 1.0
    matrix = np.array([[box[0], 0.0, 0.0], [0.0, box[1], 0.0], [0.0, tilt_yz, box[2]]])
    positions = fractions @ matrix  # rows: a fraction of each cell vector
    tilt = np.array([0.0, 0.0, tilt_yz])
    return md.State(positions=positions, box=box, pbc=np.ones(3, bool), tilt=tilt), fractions


def _local_systems(state, fractions, grid):
    """Each brick's local system as the halo lays it out: owned atoms first (by global
    id), then every image of another atom within one list radius of the brick along the
    cut axes (open), periodic along the others; cuts along the cell vectors' fractions,
    the shell measured along x, y and z (edges of the cut axes: the tilt couples only y
    and z, never a cut axis to another, in the systems here)."""
    box = state.box
    cut = [axis for axis in range(3) if grid[axis] > 1]
    systems = []
    for brick in itertools.product(*[range(p) for p in grid]):
        low = np.array([brick[a] / grid[a] for a in range(3)])
        high = np.array([(brick[a] + 1) / grid[a] for a in range(3)])
        inside = np.all((fractions[:, cut] >= low[cut]) & (fractions[:, cut] < high[cut]), axis=1)
        owned = np.flatnonzero(inside)
        positions, ids = [state.positions[owned]], [owned]
        shell = RADIUS / box[cut]
        for shift in itertools.product((-1, 0, 1), repeat=len(cut)):
            moved = fractions[:, cut] + np.array(shift)
            near = np.all((moved >= low[cut] - shell) & (moved < high[cut] + shell), axis=1)
            if not any(shift):
                near &= ~inside
            image = state.positions[near].copy()
            image[:, cut] += np.array(shift) * box[cut]
            positions.append(image)
            ids.append(np.flatnonzero(near))
        pbc = np.array([grid[a] == 1 for a in range(3)])
        local = md.State(
            positions=np.concatenate(positions), box=box.copy(), pbc=pbc, tilt=state.tilt.copy()
        )
        systems.append((local, np.concatenate(ids).astype(np.int64), len(owned)))
    return systems


def _designates(a, b):
    return (a < b) != ((a + b) % 2 == 1)


def _separations(state):
    d = state.positions[:, None] - state.positions[None]
    return md.box.minimum_image(d, state.box, state.pbc, state.tilt)


def _pairs_within(state):
    """Sorted (P, 2) pairs i < j closer than the list radius (brute force)."""
    near = (_separations(state) ** 2).sum(axis=-1) < RADIUS**2
    i, j = np.nonzero(np.triu(near, k=1))
    return np.stack([i, j], axis=1).astype(np.int64)


def _rank_list(local, ids, n_owned, threads=1):
    nl = NeighborList(CUTOFF, SKIN)
    nl.keep_owned(ids, n_owned)
    before = get_threads()
    set_threads(threads)
    try:
        nl.build(local)
    finally:
        set_threads(before)
    return nl


@pytest.mark.parametrize(
    ("cells", "grid", "tilt_yz", "threads"),
    [
        ((8, 6, 6), (2, 1, 1), 0.0, 1),  # thick slabs: the ghosts' far x cells, then near
        ((12, 6, 6), (4, 1, 1), 0.0, 1),  # thin slabs: every owned cell next to ghosts
        ((8, 8, 5), (2, 2, 1), 0.0, 1),  # bricks cut along x and y: corner ghosts
        ((8, 8, 8), (2, 2, 2), 0.0, 1),  # cut along all three: no periodic axis left
        ((8, 7, 6), (2, 1, 1), 2.1, 1),  # a triclinic cell, sheared along the uncut axes
        ((12, 7, 7), (2, 1, 1), 0.0, 2),  # two search chunks on two threads
    ],
)
def test_a_rank_list_is_the_brute_force_list_of_the_pairs_it_owns(cells, grid, tilt_yz, threads):
    """Each rank's list holds exactly its owned atoms' pairs (an owned atom with a later
    owned one, or with a ghost whose pair designates it), with image codes that give each
    pair's separation; every ghost partner was one of the ghosts the search tested."""
    state, fractions = _cell(cells, tilt_yz)
    for local, ids, n_owned in _local_systems(state, fractions, grid):
        nl = _rank_list(local, ids, n_owned, threads)
        assert nl.used_cells
        pairs = _pairs_within(local)
        a, b = pairs[:, 0], pairs[:, 1]
        own = (a < n_owned) & ((b < n_owned) | _designates(ids[a], ids[b]))
        np.testing.assert_array_equal(nl.pairs(), pairs[own])
        rows = np.repeat(np.arange(local.n_atoms), np.diff(nl.slot_starts))
        q = nl.slot_neighbors.astype(np.int64)
        frame = nl.frame_positions(local.positions)
        d = _separations(local)[nl.order[rows], nl.order[q]]
        np.testing.assert_allclose(frame[rows] - frame[q] - nl.shifts[nl.codes], d, atol=1e-9)
        owned_ghost = int(np.sum((a < n_owned) & (b >= n_owned)))
        assert owned_ghost <= nl.ghost_candidates  # every owned-ghost pair within reach


def test_ghosts_out_of_reach_of_every_row_are_not_tested():
    """Owned atoms in a thin sheet at x in [0, 0.3) and ghosts in one at x in [-3.3, -3)
    (a list radius 1.8): the ghosts lie in the cells around the owned ones (the grid's
    cells are about 1 wide along x), so the search tested each owned row against them
    before; now their segments' boxes are out of reach in x, and none is tested."""
    rng = np.random.default_rng(3)
    box = np.array([20.0, 6.0, 6.0])
    owned = rng.uniform((0.0, 0.0, 0.0), (0.3, 6.0, 6.0), (60, 3))
    ghosts = rng.uniform((-3.3, 0.0, 0.0), (-3.0, 6.0, 6.0), (60, 3))
    local = md.State(
        positions=np.concatenate([owned, ghosts]), box=box, pbc=np.array([False, True, True])
    )
    nl = _rank_list(local, np.arange(120, dtype=np.int64), 60)
    assert nl.used_cells
    pairs = _pairs_within(local)
    owned_pairs = pairs[pairs[:, 1] < 60]
    assert np.all(pairs[pairs[:, 0] < 60, 1] < 60)  # (no owned-ghost pair within reach)
    np.testing.assert_array_equal(nl.pairs(), owned_pairs)
    assert nl.ghost_candidates == 0


def test_the_ghosts_tested_on_a_melt_rank_lie_near_their_rows():
    """On a rank of the melt cut in two slabs a row tests at least the ghosts it pairs with,
    and only ghosts near it in x and z: a segment is tested when its box, one cell wide
    along x and z (cells here about 0.52 list radii wide), comes within a radius of the row,
    so a ghost tested lies within r + sqrt(2) w < 1.8 r of it in (x, z), and, being in the
    cells around the row's, within 3 cells (< 1.6 r) along y."""
    state, fractions = _cell((8, 6, 6))
    local, ids, n_owned = _local_systems(state, fractions, (2, 1, 1))[0]
    nl = _rank_list(local, ids, n_owned)
    d = _separations(local)[:n_owned, n_owned:]
    within = int(np.sum((d**2).sum(axis=-1) < RADIUS**2))
    near = (d[..., 0] ** 2 + d[..., 2] ** 2 < (1.8 * RADIUS) ** 2) & (
        np.abs(d[..., 1]) < 1.6 * RADIUS
    )
    assert 0 < within <= nl.ghost_candidates <= int(near.sum())


def test_lists_without_keep_owned_test_no_ghost():
    state, _ = _cell((6, 6, 6))
    nl = NeighborList(CUTOFF, SKIN)
    nl.build(state)
    assert nl.ghost_candidates == 0
