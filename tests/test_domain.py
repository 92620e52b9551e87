"""The kernels of a decomposed run's migration, ghost search and look-ahead (md.domain),
against numpy's way of doing the same; no MPI needed."""

from __future__ import annotations

import numpy as np
import pytest

from md.box import cell_matrix
from md.domain import (
    append_rows,
    brick_of,
    fractional_coordinates,
    home_positions,
    leaving_along,
    local_periodic_axes,
    merged_order,
    moved_since,
    near_faces,
    nonzero_rows,
    table_rows,
    take_rows,
)
from md.state import State

BOX = np.array([10.0, 8.0, 7.0])
TILT = np.array([1.5, -0.8, 0.6])
PBC = np.array([True, True, True])


def scattered(n: int, seed: int = 0) -> np.ndarray:
    """Positions in and around the tilted cell (some an image or two away)."""
    rng = np.random.default_rng(seed)
    fractions = rng.uniform(-1.2, 2.2, (n, 3))
    return fractions @ cell_matrix(BOX, TILT)


@pytest.mark.parametrize("shape", [(2, 1, 1), (3, 2, 1), (4, 3, 2), (1, 1, 5)])
def test_leaving_along_splits_the_atoms_as_their_bricks_say(shape):
    positions = scattered(5000)
    fractions = np.empty_like(positions)
    fractional_coordinates(positions, BOX, TILT, PBC, fractions)
    bricks = np.empty((len(positions), 3), dtype=np.int64)
    grid = np.array(shape, dtype=np.int64)
    brick_of(fractions, grid, bricks)
    for axis in range(3):
        p = shape[axis]
        if p == 1:
            continue
        for coordinate in range(p):
            up, down, lost = leaving_along(positions, BOX, TILT, PBC, grid, axis, coordinate)
            delta = (bricks[:, axis] - coordinate) % p
            np.testing.assert_array_equal(up, np.flatnonzero(delta == 1))
            np.testing.assert_array_equal(down, np.flatnonzero((delta == p - 1) & (delta != 1)))
            assert lost == np.count_nonzero((delta != 0) & (delta != 1) & (delta != p - 1))
            assert len(up) > 0 and (p == 2 or len(down) > 0)


def test_merged_order_and_take_rows_equal_a_sort_by_id():
    rng = np.random.default_rng(1)
    ids = np.sort(rng.choice(100_000, 3000, replace=False)).astype(np.int64)
    gone = rng.random(len(ids)) < 0.1
    arriving = rng.choice(np.setdiff1d(np.arange(100_000), ids), 400, replace=False)
    order = merged_order(ids, gone, arriving.astype(np.int64))
    old = rng.random((len(ids), 3))
    incoming = rng.random((len(arriving), 3))
    out = np.empty((len(order), 3))
    take_rows(old, incoming, order, out)
    # numpy: keep, append, sort by id
    both_ids = np.concatenate([ids[~gone], arriving])
    by_id = np.argsort(both_ids, kind="stable")
    np.testing.assert_array_equal(out, np.concatenate([old[~gone], incoming])[by_id])
    np.testing.assert_array_equal(np.diff(both_ids[by_id]) > 0, True)
    # ids out of order: no order (the caller sorts)
    shuffled = ids.copy()
    shuffled[[5, 6]] = shuffled[[6, 5]]
    assert merged_order(shuffled, np.zeros(len(ids), dtype=bool), arriving).size == 0


def test_near_faces_and_the_sweep_rows_round_trip():
    """near_faces picks the rows below and at or above the bounds, in order; table_rows packs
    owned atoms' and ghosts' rows (fractions from the right array) and append_rows unpacks
    them as new ghosts, to the bit."""
    rng = np.random.default_rng(2)
    n, m = 2000, 300
    positions = np.concatenate([scattered(n, seed=3), scattered(m, seed=4)])
    home = rng.random((n, 3))
    ghost_fractions = rng.random((m, 3))
    ids = rng.permutation(n + m).astype(np.int64)
    types = rng.integers(0, 3, n + m).astype(np.int32)
    for column in (0, 1, 2):
        below, above = near_faces(home, n, column, 0.2, 0.7)
        np.testing.assert_array_equal(below, np.flatnonzero(home[:, column] < 0.2))
        np.testing.assert_array_equal(above, np.flatnonzero(home[:, column] >= 0.7))
    send = np.concatenate([np.sort(rng.choice(n, 50, replace=False)),
                           n + np.sort(rng.choice(m, 20, replace=False))])  # fmt: skip
    rows = np.empty((len(send), 8))
    table_rows(positions, home, ghost_fractions, ids, types, n, send, rows)
    np.testing.assert_array_equal(rows[:, :3], positions[send])
    np.testing.assert_array_equal(rows[:50, 3:6], home[send[:50]])
    np.testing.assert_array_equal(rows[50:, 3:6], ghost_fractions[send[50:] - n])
    np.testing.assert_array_equal(rows[:, 6], ids[send])
    np.testing.assert_array_equal(rows[:, 7], types[send])
    grown = len(send) + n + m
    out, out_fractions = np.zeros((grown, 3)), np.zeros((grown - n, 3))
    out_ids, out_types = np.zeros(grown, dtype=np.int64), np.zeros(grown, dtype=np.int32)
    append_rows(rows, n + m, n, out, out_fractions, out_ids, out_types)
    np.testing.assert_array_equal(out[n + m :], positions[send])
    np.testing.assert_array_equal(out_fractions[m:], rows[:, 3:6])
    np.testing.assert_array_equal(out_ids[n + m :], ids[send])
    np.testing.assert_array_equal(out_types[n + m :], types[send])
    assert not out[: n + m].any() and not out_fractions[:m].any()  # nothing else written


def test_the_look_ahead_bounds_each_atoms_next_move():
    """Velocity Verlet on a set of anharmonic oscillators: the bound moved_since gives from
    the last two moves holds for the true next position of every atom, and is exact
    (|d + s|) for atoms moving at constant velocity."""
    rng = np.random.default_rng(4)
    n, dt = 500, 0.005
    x = rng.normal(0.0, 1.0, (n, 3))
    v = rng.normal(0.0, 2.0, (n, 3))

    def force(r):
        return -4.0 * r - 3.0 * r**3

    f = force(x)
    history = [x.copy()]
    for _ in range(40):
        v += 0.5 * dt * f
        x += dt * v
        f = force(x)
        v += 0.5 * dt * f
        history.append(x.copy())
    reference = history[0]
    for k in range(2, 39):
        now, previous, before = history[k], history[k - 1], history[k - 2]
        d2, s2, c2 = moved_since(now, reference, np.eye(3), previous, before)
        assert d2 == pytest.approx(np.max(np.sum((now - reference) ** 2, axis=1)))
        assert s2 == pytest.approx(np.max(np.sum((now - previous) ** 2, axis=1)))
        true_next = np.sqrt(np.max(np.sum((history[k + 1] - reference) ** 2, axis=1)))
        assert true_next <= np.sqrt(c2)
    # constant velocity: the next move is the last one, exactly
    steady = [reference + t * 0.01 * np.ones(3) for t in range(3)]
    _, _, c2 = moved_since(steady[2], reference, np.eye(3), steady[1], steady[0])
    assert np.sqrt(c2) == pytest.approx(0.03 * np.sqrt(3))
    # without the step before: half the last move as the margin
    _, _, c2 = moved_since(steady[2], reference, np.eye(3), steady[1], np.empty((0, 3)))
    assert np.sqrt(c2) == pytest.approx(0.035 * np.sqrt(3))
    broken = steady[2].copy()
    broken[3, 1] = np.nan
    assert moved_since(broken, reference, np.eye(3), steady[1], steady[0]) == (np.inf,) * 3


def test_an_adopted_state_shares_its_arrays():
    positions = np.zeros((4, 3))
    types = np.array([0, 1, 1, 0], dtype=np.int32)
    state = State.adopting(positions, types, BOX, False, ("A", "B"))
    assert state.positions is positions and state.types is types
    assert state.n_atoms == 4 and state.n_types == 2 and not state.pbc.any()
    np.testing.assert_array_equal(state.masses, 1.0)
    np.testing.assert_array_equal(state.tilt, 0.0)


def test_local_periodic_axes_are_the_uncut_ones_whose_vector_stays_off_cut_axes():
    """A rank keeps an axis periodic (no ghosts across it) when one brick spans it and its
    cell vector (b = (xy, ly, 0), c = (xz, yz, lz)) has no component along a cut axis."""
    pbc = np.array([True, True, True])
    assert local_periodic_axes((2, 1, 1), pbc, np.zeros(3)).tolist() == [False, True, True]
    assert local_periodic_axes((1, 1, 1), pbc, np.zeros(3)).tolist() == [True, True, True]
    assert local_periodic_axes((2, 2, 2), pbc, np.zeros(3)).tolist() == [False] * 3
    # yz couples two uncut axes: both stay periodic, tilted
    assert local_periodic_axes((2, 1, 1), pbc, np.array([0.0, 0.0, 0.3])).tolist() == [
        False, True, True]  # fmt: skip
    # xy leans b along cut x; xz leans c along it
    assert local_periodic_axes((2, 1, 1), pbc, np.array([0.3, 0.0, 0.0])).tolist() == [
        False, False, True]  # fmt: skip
    assert local_periodic_axes((2, 1, 1), pbc, np.array([0.0, 0.2, 0.0])).tolist() == [
        False, True, False]  # fmt: skip
    # yz with y cut: c leans along y
    assert local_periodic_axes((1, 2, 1), pbc, np.array([0.0, 0.0, 0.3])).tolist() == [
        True, False, False]  # fmt: skip
    # an open axis is never periodic
    assert local_periodic_axes((2, 1, 1), np.array([True, False, True]), np.zeros(3)).tolist() == [
        False, False, True]  # fmt: skip


def test_home_positions_shift_exactly_the_atoms_with_an_image():
    """nonzero_rows lists the atoms whose image is not 0 (and their images); home_positions
    from that list equals positions - images @ cell for every atom, to the bit."""
    rng = np.random.default_rng(3)
    n = 2000
    positions = rng.uniform(-5.0, 15.0, (n, 3))
    images = np.zeros((n, 3), dtype=np.int64)
    crossed = rng.choice(n, 40, replace=False)
    images[crossed] = rng.integers(-2, 3, (40, 3))
    images[crossed[0]] = (0, 0, 1)  # one axis alone
    cell = cell_matrix(np.array([10.0, 9.0, 8.0]), np.array([1.5, -0.5, 2.0]))
    listed, rows = nonzero_rows(images)
    expected = np.flatnonzero(np.any(images != 0, axis=1))
    assert np.array_equal(listed, expected) and np.array_equal(rows, images[expected])
    out = np.empty_like(positions)
    home_positions(positions, listed, rows, cell, out)
    reference = positions - (images[:, :1] * cell[0] + images[:, 1:2] * cell[1]
                             + images[:, 2:] * cell[2])  # fmt: skip
    assert np.array_equal(out[listed], reference[listed])
    others = np.setdiff1d(np.arange(n), listed)
    assert np.array_equal(out[others], positions[others])
