"""A decomposed rank's neighbour list searches only the rows it keeps (issue 69).

A rank's local system is its owned atoms followed by ghost copies of other ranks' atoms
(``md.distributed.halo``); ``NeighborList.keep_owned`` lists only the pairs whose
designated atom it owns. The search runs over the owned atoms' rows alone (owned partners
by the half rule, ghost partners all around), so no pair of two ghosts is a candidate and
the pair kernels walk no ghost row. Here the ranks' local systems are cut by hand as the
halo cuts them (bricks along x, or x and y; the ghost shell one list radius wide, open
along the cut axes), with no MPI: every pair of the whole system is listed on exactly one
rank, each rank's list is the brute-force one over the pairs it owns, ghost rows are
empty, and the ranks' forces summed by owner are the serial forces.
"""

from __future__ import annotations

import itertools
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import md
from md.neighbors import NeighborList
from md.parallel import get_threads, set_threads
from potentials import LennardJones

ROOT = Path(__file__).resolve().parents[1]
CUTOFF, SKIN = 1.5, 0.3
RADIUS = CUTOFF + SKIN


def _melt(cells, seed=0):
    """A perturbed fcc lattice at the LJ melt's density, periodic, atoms in lattice order."""
    state = md.lattice("fcc", cells, density=0.8442)
    rng = np.random.default_rng(seed)
    state.positions += rng.uniform(-0.15, 0.15, state.positions.shape)
    return state


def _local_systems(state, grid, shell=RADIUS):
    """Each rank's local system of ``state`` cut into ``grid`` bricks, as the halo lays it
    out: (State, global ids, owned count) per rank, its owned atoms first (in global
    order), then every image of an atom within ``shell`` of the brick along the cut axes;
    open along the cut axes, periodic along the others."""
    box = state.box
    cut = [axis for axis in range(3) if grid[axis] > 1]
    wrapped = state.positions % box
    systems = []
    for brick in itertools.product(*[range(p) for p in grid]):
        low = np.array([brick[a] * box[a] / grid[a] for a in range(3)])
        high = np.array([(brick[a] + 1) * box[a] / grid[a] for a in range(3)])
        inside = np.all((wrapped[:, cut] >= low[cut]) & (wrapped[:, cut] < high[cut]), axis=1)
        owned = np.flatnonzero(inside)
        positions, ids = [wrapped[owned]], [owned]
        for shift in itertools.product((-1, 0, 1), repeat=len(cut)):
            moved = wrapped.copy()
            moved[:, cut] += np.array(shift) * box[cut]
            near = np.all(
                (moved[:, cut] >= low[cut] - shell) & (moved[:, cut] < high[cut] + shell), axis=1
            )
            if not any(shift):
                near &= ~inside
            positions.append(moved[near])
            ids.append(np.flatnonzero(near))
        pbc = np.array([grid[a] == 1 for a in range(3)])
        local = md.State(positions=np.concatenate(positions), box=box.copy(), pbc=pbc)
        systems.append((local, np.concatenate(ids).astype(np.int64), len(owned)))
    return systems


def _designates(a, b):
    return (a < b) != ((a + b) % 2 == 1)


def _pairs_within(state, radius):
    """Sorted (P, 2) pairs i < j closer than ``radius`` by the minimum image (brute force)."""
    d = state.positions[:, None] - state.positions[None]
    d = md.box.minimum_image(d, state.box, state.pbc, state.tilt)
    i, j = np.nonzero(np.triu((d**2).sum(axis=-1) < radius**2, k=1))
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


def _as_global(pairs, ids):
    """Local pairs as sorted (P, 2) global id pairs (smaller first), rows sorted."""
    g = np.sort(ids[pairs], axis=1)
    return g[np.lexsort((g[:, 1], g[:, 0]))]


@pytest.mark.parametrize(
    ("cells", "grid", "threads"),
    [
        ((8, 6, 6), (2, 1, 1), 1),  # the cell search, 2 slabs
        ((9, 6, 6), (3, 1, 1), 1),  # 3 slabs: each rank's ghosts from two others
        ((8, 8, 5), (2, 2, 1), 1),  # bricks cut along x and y: corner ghosts too
        ((10, 8, 8), (2, 1, 1), 2),  # two search chunks on two threads
        ((6, 2, 2), (2, 1, 1), 1),  # periodic widths too small for cells: the O(N^2) search
    ],
)
def test_ranks_list_every_pair_once_each_its_own_by_brute_force(cells, grid, threads):
    """Each rank's list is the brute-force list of its local system restricted to the pairs
    it owns (an owned atom with a later owned atom, or with a ghost whose pair designates
    the owned atom), and over the ranks every pair of the whole system appears once."""
    state = _melt(cells)
    everything = _pairs_within(state, RADIUS)
    listed = []
    for local, ids, n_owned in _local_systems(state, grid):
        nl = _rank_list(local, ids, n_owned, threads)
        assert nl.used_cells == (cells != (6, 2, 2))
        pairs = _pairs_within(local, RADIUS)
        a, b = pairs[:, 0], pairs[:, 1]
        own = (a < n_owned) & ((b < n_owned) | _designates(ids[a], ids[b]))
        np.testing.assert_array_equal(nl.pairs(), pairs[own])
        if nl.order is not None:  # each pair's image code gives its separation
            rows = np.repeat(np.arange(local.n_atoms), np.diff(nl.slot_starts))
            q = nl.slot_neighbors.astype(np.int64)
            frame = nl.frame_positions(local.positions)
            d = md.box.minimum_image(
                local.positions[nl.order[rows]] - local.positions[nl.order[q]],
                local.box,
                local.pbc,
            )
            np.testing.assert_allclose(frame[rows] - frame[q] - nl.shifts[nl.codes], d, atol=1e-9)
            crossing = np.bincount(rows, weights=nl.codes != 13, minlength=local.n_atoms) > 0
            assert np.all(nl.shifted_rows[crossing])
        listed.append(_as_global(nl.pairs(), ids))
    together = np.concatenate(listed)
    together = together[np.lexsort((together[:, 1], together[:, 0]))]
    np.testing.assert_array_equal(together, everything)


@pytest.mark.parametrize("cells", [(8, 6, 6), (6, 2, 2)])
def test_a_rank_list_has_no_ghost_rows_and_its_kernels_walk_owned_rows_only(cells):
    """The rows of a rank's list are its owned atoms' (every ghost's row is empty, so no
    ghost pair was searched from a ghost), and the pair kernels' chunks end at the last
    owned row. Before, the cell search had a row for every local atom and kept in a ghost's
    row its pairs with owned atoms (on a rank of the 1152-atom melt cut in two, 494 ghost
    rows held 8 % of the pairs, each row searched for ghost partners too), and the kernels
    walked every row."""
    state = _melt(cells)
    for local, ids, n_owned in _local_systems(state, (2, 1, 1)):
        assert 0 < n_owned < local.n_atoms
        nl = _rank_list(local, ids, n_owned)
        lengths = np.diff(nl.slot_starts)
        rows_of = np.arange(local.n_atoms) if nl.order is None else nl.order
        ghost_rows = rows_of >= n_owned
        assert lengths[ghost_rows].sum() == 0
        assert lengths[~ghost_rows].sum() == nl.n_pairs > 0
        assert np.all(rows_of[:n_owned] < n_owned)  # the owned atoms' rows first
        assert nl.bounds[0] == 0 and nl.bounds[-1] == n_owned
        if nl.frame is not None:
            assert nl.frame.bounds[-1] == n_owned


def test_zero_owned_atoms_and_no_ghosts():
    """A rank that owns no atoms lists no pair (and no rows); a rank with no ghosts lists
    every pair of its atoms."""
    state = _melt((7, 7, 7))
    ids = np.arange(state.n_atoms, dtype=np.int64)
    empty = _rank_list(state, ids, 0)
    assert empty.used_cells and empty.n_pairs == 0
    assert np.all(empty.bounds == 0) and not empty.shifted_rows.any()
    alone = _rank_list(state, ids, state.n_atoms)
    np.testing.assert_array_equal(alone.pairs(), _pairs_within(state, RADIUS))


@pytest.mark.parametrize("grid", [(2, 1, 1), (2, 2, 1)])
def test_the_ranks_forces_summed_by_owner_are_the_serial_forces(grid):
    """LJ over each rank's list (the slot-frame kernel, owned rows only), the ghosts' forces
    added to their owners' by global id: the serial forces and energy to 1e-10."""
    state = _melt((8, 8, 6))
    lj = LennardJones(cutoff=CUTOFF)
    serial = NeighborList(CUTOFF, SKIN)
    serial.build(state)
    expected = lj.energy_forces(state, serial)
    forces, energy = np.zeros_like(state.positions), 0.0
    for local, ids, n_owned in _local_systems(state, grid):
        nl = _rank_list(local, ids, n_owned)
        assert nl.frame is not None
        result = lj.energy_forces(local, nl)
        np.add.at(forces, ids, result.forces)
        energy += result.energy
    np.testing.assert_allclose(forces, expected.forces, rtol=0, atol=1e-10)
    assert energy == pytest.approx(expected.energy, rel=1e-12)


_PYTHON_MODE = """
import json, sys
import numpy as np
sys.path.insert(0, {tests!r})
from test_mpi_local_rows import _local_systems, _melt, _rank_list
local, ids, n_owned = _local_systems(_melt((6, 5, 5)), (2, 1, 1))[0]
nl = _rank_list(local, ids, n_owned)
print(json.dumps({{"cells": nl.used_cells, "pairs": nl.pairs().tolist(),
                  "bounds": nl.bounds.tolist(), "codes": nl.codes.tolist()}}))
"""


def test_the_rank_search_runs_as_python_under_disable_jit():
    """The owned-rows search with numba off (``NUMBA_DISABLE_JIT=1``: the candidate tests'
    Python twins) lists the same pairs, codes and chunks as the compiled one."""
    script = _PYTHON_MODE.format(tests=str(ROOT / "tests"))
    found = {}
    for mode in ("0", "1"):
        env = {**os.environ, "NUMBA_DISABLE_JIT": mode}
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
        done = subprocess.run(
            [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=600
        )
        assert done.returncode == 0, done.stderr
        found[mode] = json.loads(done.stdout.strip().splitlines()[-1])
    assert found["1"]["cells"] and found["1"]["pairs"]
    assert found["0"] == found["1"]
