"""The kernels of a decomposed run's migration, ghost search and look-ahead (md.distributed),
against numpy's way of doing the same; no MPI needed."""

from __future__ import annotations

import numpy as np
import pytest

from md.box import cell_matrix
from md.distributed._domain_kernels import (
    brick_of,
    fractional_coordinates,
    home_layout,
    home_positions,
    leaving_along,
    moved_since,
    predicted_positions,
    refill_plan,
    refill_rows,
)
from md.distributed.grid import Grid, balanced_cuts, local_periodic_axes
from md.state import State

BOX = np.array([10.0, 8.0, 7.0])
TILT = np.array([1.5, -0.8, 0.6])
PBC = np.array([True, True, True])


def scattered(n: int, seed: int = 0) -> np.ndarray:
    """Positions in and around the tilted cell (some an image or two away)."""
    rng = np.random.default_rng(seed)
    fractions = rng.uniform(-1.2, 2.2, (n, 3))
    return fractions @ cell_matrix(BOX, TILT)


def uneven(shape, seed: int = 3) -> Grid:
    """A grid of ``shape`` whose cuts were moved (as load balancing moves them)."""
    rng = np.random.default_rng(seed)
    cuts = []
    for p in shape:
        widths = rng.uniform(0.5, 1.5, p)
        cuts.append(np.concatenate([[0.0], np.cumsum(widths)[:-1] / widths.sum(), [1.0]]))
    return Grid(shape, tuple(cuts))


def placed(shape, even: bool):
    """Scattered positions, their fractions, a grid of ``shape`` (even or with moved
    planes) and each position's brick by :func:`brick_of`."""
    positions = scattered(5000)
    fractions = np.empty_like(positions)
    fractional_coordinates(positions, BOX, TILT, PBC, fractions)
    grid = Grid(shape) if even else uneven(shape)
    bricks = np.empty((len(positions), 3), dtype=np.int64)
    brick_of(fractions, np.array(shape), grid.cut_table(), bricks)
    return positions, fractions, grid, bricks


@pytest.mark.parametrize("even", [True, False])
@pytest.mark.parametrize("shape", [(2, 1, 1), (3, 2, 1), (4, 3, 2), (1, 1, 5)])
def test_brick_of_puts_each_atom_between_its_bricks_planes(shape, even):
    _, fractions, grid, bricks = placed(shape, even)
    wrapped = fractions - np.floor(fractions)
    for axis in range(3):
        expected = np.searchsorted(grid.cuts[axis], wrapped[:, axis], side="right") - 1
        np.testing.assert_array_equal(bricks[:, axis], expected)
    if even:  # the even grid's planes are c / p: the same as truncating s * p
        np.testing.assert_array_equal(bricks, np.floor(wrapped * np.array(shape)).astype(int))


@pytest.mark.parametrize("even", [True, False])
@pytest.mark.parametrize("shape", [(2, 1, 1), (3, 2, 1), (4, 3, 2), (1, 1, 5)])
def test_leaving_along_splits_the_atoms_as_their_bricks_say(shape, even):
    positions, _, planes, bricks = placed(shape, even)
    grid, cuts = np.array(shape, dtype=np.int64), planes.cut_table()
    for axis in range(3):
        p = shape[axis]
        if p == 1:
            continue
        for coordinate in range(p):
            up, down, lost = leaving_along(positions, BOX, TILT, PBC, grid, cuts, axis, coordinate)
            delta = (bricks[:, axis] - coordinate) % p
            np.testing.assert_array_equal(up, np.flatnonzero(delta == 1))
            np.testing.assert_array_equal(down, np.flatnonzero((delta == p - 1) & (delta != 1)))
            assert lost == np.count_nonzero((delta != 0) & (delta != 1) & (delta != p - 1))
            assert len(up) > 0 and (p == 2 or len(down) > 0)


@pytest.mark.parametrize(
    ("n", "n_leaving", "m"),
    [
        (3000, 300, 400),
        (3000, 400, 300),
        (3000, 300, 300),
        (3000, 0, 50),
        (3000, 50, 0),
        (50, 50, 7),
        (50, 50, 0),
        (0, 0, 9),
        (10, 3, 0),
    ],
)
def test_the_refill_plan_keeps_every_staying_and_arriving_atom_once_and_moves_few(n, n_leaving, m):
    rng = np.random.default_rng(n + 7 * n_leaving + m)
    ids = rng.permutation(100_000)[:n].astype(np.int64)
    arriving = np.setdiff1d(np.arange(100_000, 101_000), ids)[:m]
    leaving = np.sort(rng.choice(n, n_leaving, replace=False)).astype(np.int64)
    size = n - n_leaving + m
    values = np.zeros((max(n, size) + 5, 2))
    values[:n, 0], values[:n, 1] = ids, ids * 0.5  # each row's data follows its id
    before = values.copy()
    incoming = np.stack([arriving, arriving * 0.5], axis=1).astype(np.float64)
    sources, targets, arrivals = refill_plan(leaving, n, m)
    refill_rows(values, sources, targets, incoming, arrivals)
    kept = values[:size]
    expected = np.concatenate([np.delete(ids, leaving), arriving])
    np.testing.assert_array_equal(np.sort(kept[:, 0]), np.sort(expected))
    np.testing.assert_array_equal(kept[:, 1], kept[:, 0] * 0.5)
    # O(moved): only holes, the new end and the arrivals' rows are written
    assert len(sources) <= n_leaving and len(arrivals) == m
    untouched = np.setdiff1d(np.arange(size), np.concatenate([targets, arrivals]))
    np.testing.assert_array_equal(kept[untouched], before[untouched])
    # the same plan again: the same rows (a run on P ranks is deterministic)
    again = refill_plan(leaving, n, m)
    for a, b in zip(again, (sources, targets, arrivals), strict=True):
        np.testing.assert_array_equal(a, b)


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
    none, copy = np.empty((0, 3)), np.empty((n, 3))
    for k in range(2, 39):
        now, previous, before = history[k], history[k - 1], history[k - 2]
        d2, s2, c2 = moved_since(now, reference, np.eye(3), previous, before, copy)
        np.testing.assert_array_equal(copy, now)  # the positions copied in the same pass
        assert d2 == pytest.approx(np.max(np.sum((now - reference) ** 2, axis=1)))
        assert s2 == pytest.approx(np.max(np.sum((now - previous) ** 2, axis=1)))
        true_next = np.sqrt(np.max(np.sum((history[k + 1] - reference) ** 2, axis=1)))
        assert true_next <= np.sqrt(c2)
    # constant velocity: the next move is the last one, exactly
    steady = [reference + t * 0.01 * np.ones(3) for t in range(3)]
    _, _, c2 = moved_since(steady[2], reference, np.eye(3), steady[1], steady[0], none)
    assert np.sqrt(c2) == pytest.approx(0.03 * np.sqrt(3))
    # without the step before: half the last move as the margin
    _, _, c2 = moved_since(steady[2], reference, np.eye(3), steady[1], none, none)
    assert np.sqrt(c2) == pytest.approx(0.035 * np.sqrt(3))
    broken = steady[2].copy()
    broken[3, 1] = np.nan
    assert moved_since(broken, reference, np.eye(3), steady[1], steady[0], none) == (np.inf,) * 3


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
        False,
        True,
        True,
    ]
    # xy leans b along cut x; xz leans c along it
    assert local_periodic_axes((2, 1, 1), pbc, np.array([0.3, 0.0, 0.0])).tolist() == [
        False,
        False,
        True,
    ]
    assert local_periodic_axes((2, 1, 1), pbc, np.array([0.0, 0.2, 0.0])).tolist() == [
        False,
        True,
        False,
    ]
    # yz with y cut: c leans along y
    assert local_periodic_axes((1, 2, 1), pbc, np.array([0.0, 0.0, 0.3])).tolist() == [
        True,
        False,
        False,
    ]
    # an open axis is never periodic
    assert local_periodic_axes((2, 1, 1), np.array([True, False, True]), np.zeros(3)).tolist() == [
        False,
        False,
        True,
    ]


@pytest.mark.parametrize("pbc", [(True, True, True), (True, False, True)])
def test_home_layout_puts_each_atom_at_the_image_nearest_the_brick(pbc):
    """home_layout's one pass equals the definition: fractional coordinates, the image
    nearest the brick centre, positions - images @ cell (to the bit: a plain copy where
    the image is 0), the atoms with an image listed, and how far the farthest strays;
    home_positions (the per-step copy) from that list gives the same positions."""
    rng = np.random.default_rng(3)
    n = 2000
    pbc = np.array(pbc)
    box, tilt = np.array([10.0, 9.0, 8.0]), np.array([1.5, -0.5, 2.0])
    tilt = np.where([pbc[1], pbc[2], pbc[2]], tilt, 0.0)  # as md.box.periodic_tilt
    cell = cell_matrix(box, tilt)
    bounds = np.array([[0.5, 0.0, 0.25], [1.0, 1.0, 0.75]])  # brick (1, 0, 1) of 2 x 1 x 2
    center = bounds.mean(axis=0)
    widths = np.array([10.0, 9.0, 8.0])
    reach = np.minimum(0.6 * (bounds[1] - bounds[0]), 0.49)  # past the brick, within a cell
    inside = center + rng.uniform(-1.0, 1.0, (n, 3)) * reach
    images = np.zeros((n, 3), dtype=np.int64)
    crossed = rng.choice(n, 40, replace=False)
    images[crossed] = rng.integers(-2, 3, (40, 3))
    images[crossed[0]] = (0, 0, 1)  # one axis alone
    images[:, ~pbc] = 0
    inside[:, ~pbc] = 0.5  # open axes: fraction 0.5 by definition
    positions = (inside + images) @ cell
    home, out = np.empty((n, 3)), np.empty((n, 3))
    scratch = np.empty((n, 3), dtype=np.int64)
    imaged, rows, strayed = home_layout(
        positions, box, tilt, pbc, cell, center, bounds, widths, home, out, scratch
    )
    fractions = np.empty((n, 3))
    fractional_coordinates(positions, box, tilt, pbc, fractions)
    found = np.where(pbc, np.floor(fractions - center + 0.5), 0.0).astype(np.int64)
    np.testing.assert_array_equal(found, images)
    expected = np.flatnonzero(np.any(images != 0, axis=1))
    assert np.array_equal(imaged, expected) and np.array_equal(rows, images[expected])
    np.testing.assert_array_equal(home, fractions - found)
    reference = positions - (
        images[:, :1] * cell[0] + images[:, 1:2] * cell[1] + images[:, 2:] * cell[2]
    )
    assert np.array_equal(out[imaged], reference[imaged])
    others = np.setdiff1d(np.arange(n), imaged)
    assert np.array_equal(out[others], positions[others])
    outside = np.maximum(np.maximum(bounds[0] - home, home - bounds[1]), 0.0) * widths
    assert strayed == outside[:, pbc].max() and strayed > 0  # (open axes never stray)
    again = np.empty_like(out)
    home_positions(positions, imaged, rows, cell, again)
    np.testing.assert_array_equal(again, out)


def test_predicted_positions_take_a_velocity_verlet_step_of_the_free_motion():
    """r + dt v + dt^2 F / (2 m); without forces r + dt v (to round-off of the formula)."""
    rng = np.random.default_rng(5)
    positions, velocities, forces = (rng.normal(size=(50, 3)) for _ in range(3))
    masses = rng.uniform(0.5, 2.0, 50)
    out = np.empty_like(positions)
    predicted_positions(positions, velocities, forces, masses, 0.01, out)
    expected = positions + 0.01 * velocities + 0.5 * 0.01**2 * forces / masses[:, None]
    np.testing.assert_allclose(out, expected, rtol=0, atol=1e-15)
    predicted_positions(positions, velocities, np.empty((0, 3)), masses, 0.01, out)
    np.testing.assert_allclose(out, positions + 0.01 * velocities, rtol=0, atol=1e-15)


class Loopback:
    """Rank 0 of a 2 x 1 x 1 grid, its neighbour played by the test: every row exchange
    returns the next of ``answers`` and keeps what was sent; reductions are identities."""

    rank, n_ranks = 0, 2

    def __init__(self, answers) -> None:
        from md.distributed import CommClock

        self.answers, self.sent, self.clock = list(answers), [], CommClock()

    def exchange_rows(self, rows, dest, source, tag):
        self.sent.append(np.array(rows))
        return self.answers.pop(0)

    def exchange_many(self, exchanges):
        return [self.exchange_rows(*exchange) for exchange in exchanges]

    def sum(self, values):
        return values

    def max(self, values):
        return values


def atoms(ids, x_low, x_high, seed):
    """Atoms ``ids`` with x in [x_low, x_high) of a 10^3 box, velocities and the extra
    per-atom column following the id (so that every row can be checked)."""
    rng = np.random.default_rng(seed)
    ids = np.asarray(ids, dtype=np.int64)
    positions = np.column_stack(
        [rng.uniform(x_low, x_high, len(ids)), rng.uniform(0, 10, (len(ids), 2))]
    )
    state = State(
        positions=positions,
        velocities=np.outer(ids, [1.0, 2.0, 3.0]),
        masses=1.0 + ids,
        box=np.full(3, 10.0),
        pbc=np.ones(3, bool),
        types=ids % 2,
        type_names=("A", "B"),
    )
    state.ids = ids
    return state, {"extra": ids * 0.5}


def test_migration_keeps_every_atom_once_in_place_and_grows_past_its_room():
    """Domain.migrate on a loopback neighbour: leavers are sent (all of their columns),
    arrivals kept, every row's data still its atom's; a second migration changes the
    same memory (the state's arrays are views of the Domain's); many arrivals grow it."""
    from md.distributed.halo import Domain
    from md.distributed.migration import _packed

    state, carried = atoms(range(200), 0.0, 5.0, 1)
    state.positions[:30, 0] += 5.0  # 30 atoms now in the other brick: they leave
    newcomers, extra = atoms(range(1000, 1040), 0.5, 4.5, 2)
    arriving = _packed(
        [
            newcomers.positions,
            newcomers.velocities,
            newcomers.masses,
            newcomers.types,
            newcomers.ids,
            extra["extra"],
        ],
        np.arange(40),
    )
    nothing = np.empty((0, arriving.shape[1]))
    ranks = Loopback([arriving, nothing] * 3)
    domain = Domain(ranks, Grid((2, 1, 1)))
    domain.reserve(state, {})

    def check(state, carried, expected):
        assert sorted(state.ids.tolist()) == sorted(expected)
        np.testing.assert_array_equal(state.velocities, np.outer(state.ids, [1.0, 2.0, 3.0]))
        np.testing.assert_array_equal(state.masses, 1.0 + state.ids)
        np.testing.assert_array_equal(state.types, state.ids % 2)
        np.testing.assert_array_equal(carried["extra"], state.ids * 0.5)
        assert np.all(state.positions[:, 0] < 5.0)

    carried = domain.migrate(state, carried)
    sent = np.concatenate(ranks.sent[:2])
    assert sorted(sent[:, 8].astype(int).tolist()) == list(range(30))  # ids column
    check(state, carried, [*range(30, 200), *range(1000, 1040)])
    before = state.positions
    # a second sweep: 5 leave, 20 more arrive (ids 2000...), in the same memory
    state.positions[:5, 0] += 5.0
    gone = state.ids[:5].tolist()
    newcomers, extra = atoms(range(2000, 2020), 0.5, 4.5, 3)
    ranks.answers[0] = _packed(
        [
            newcomers.positions,
            newcomers.velocities,
            newcomers.masses,
            newcomers.types,
            newcomers.ids,
            extra["extra"],
        ],
        np.arange(20),
    )
    expected = sorted(set(state.ids.tolist()) - set(gone)) + list(range(2000, 2020))
    carried = domain.migrate(state, carried)
    check(state, carried, expected)
    assert np.shares_memory(state.positions, before)  # in place: 225 rows of 241 kept
    # 300 arrivals: past the eighth of room kept, the arrays grow and keep every atom
    newcomers, extra = atoms(range(5000, 5300), 0.5, 4.5, 4)
    ranks.answers[0] = _packed(
        [
            newcomers.positions,
            newcomers.velocities,
            newcomers.masses,
            newcomers.types,
            newcomers.ids,
            extra["extra"],
        ],
        np.arange(300),
    )
    expected = state.ids.tolist() + list(range(5000, 5300))
    carried = domain.migrate(state, carried)
    check(state, carried, expected)
    assert not np.shares_memory(state.positions, before)


def test_spent_carried_arrays_move_in_their_own_memory_where_it_has_room():
    """Domain.migrate moves a carried array named in ``spent`` (as a force evaluation's
    result: the owned atoms' rows, then ghosts' rows no longer needed) in the array it
    is the first rows of, where that has room for the atoms owned after it; without
    room, or not spent, it goes into the Domain's memory and the caller's array is left
    as it was. Every row stays its atom's."""
    from md.distributed.halo import Domain
    from md.distributed.migration import _packed

    def forces_of(ids):
        return np.outer(ids, [-1.0, 0.5, 2.0])

    state, carried = atoms(range(200), 0.0, 5.0, 7)
    state.positions[:30, 0] += 5.0  # 30 leave, 40 arrive: 210 owned after
    local = np.vstack([forces_of(state.ids), np.full((50, 3), np.nan)])  # 50 ghosts' rows
    tight = forces_of(state.ids)  # no room for 210 rows
    kept = forces_of(state.ids)  # not spent
    carried.update(spent=local[:200], tight=tight, kept=kept)
    newcomers, extra = atoms(range(1000, 1040), 0.5, 4.5, 8)
    arrays = [
        newcomers.positions,
        newcomers.velocities,
        newcomers.masses,
        newcomers.types,
        newcomers.ids,
        extra["extra"],
        *[forces_of(newcomers.ids)] * 3,
    ]
    ranks = Loopback([_packed(arrays, np.arange(40)), np.empty((0, 19))])
    domain = Domain(ranks, Grid((2, 1, 1)))
    domain.reserve(state, {})
    moved = domain.migrate(state, carried, spent=("spent", "tight"))
    assert sorted(state.ids.tolist()) == [*range(30, 200), *range(1000, 1040)]
    for name in ("spent", "tight", "kept"):
        np.testing.assert_array_equal(moved[name], forces_of(state.ids))
    assert np.shares_memory(moved["spent"], local)  # moved where it was: no copy
    assert not np.shares_memory(moved["tight"], tight)
    assert not np.shares_memory(moved["kept"], kept)
    np.testing.assert_array_equal(tight, forces_of(np.arange(200)))  # left as it was
    np.testing.assert_array_equal(kept, forces_of(np.arange(200)))


class OneRank:
    """A communicator of one rank: reductions are identities, no messages."""

    rank, n_ranks = 0, 1

    def __init__(self) -> None:
        from md.distributed import CommClock

        self.clock = CommClock()

    def sum(self, values):
        return values

    def max(self, values):
        return values

    def gather_values(self, values):
        return np.asarray(values, dtype=np.float64).reshape(1, -1)


def test_each_build_keeps_its_positions_in_the_memory_of_the_last_builds():
    """A decomposed force field's list builds (ahead of a step of dt, where velocity
    Verlet takes the atoms, or where they are) keep their positions in one array from
    build to build (a fresh one paid its page faults at every build: 5 -> 19 ms for a
    10^6-atom rank's predicted positions), and the list checks the atoms against them."""
    import md
    from md.distributed import DistributedForceField
    from potentials import LennardJones

    state = md.lattice("fcc", (4, 4, 4), density=0.8442)
    rng = np.random.default_rng(9)
    state.velocities = rng.normal(0.0, 1.0, state.positions.shape)
    state.ids = np.arange(state.n_atoms)
    ff = DistributedForceField(
        [LennardJones(1.0, 1.0, 2.5)],
        skin=0.3,
        ranks=OneRank(),
        grid=Grid((1, 1, 1)),
        bond_reach=0.0,
    )
    forces = ff.compute(state).forces
    first = ff.reference
    np.testing.assert_array_equal(first, state.positions)
    dt = 0.005
    ff.rebuild(state, migrate=True, dt=dt)
    expected = state.positions + dt * state.velocities + 0.5 * dt**2 * forces
    np.testing.assert_allclose(ff.reference, expected, rtol=0, atol=1e-14)
    assert np.shares_memory(ff.reference, first)
    state.positions[:] = expected  # the step went as predicted: the list still covers it
    covered, ahead, finite = ff.refresh(state)
    assert covered and finite and ahead == 0.0
    ff.rebuild(state, migrate=False)  # where the atoms are
    np.testing.assert_array_equal(ff.reference, state.positions)
    assert np.shares_memory(ff.reference, first)
    assert not np.shares_memory(ff.reference, state.positions)


def test_grid_bounds_follow_its_cuts_and_bad_cuts_are_refused():
    grid = uneven((3, 2, 1))
    for rank in range(grid.n_ranks):
        c = grid.coordinates(rank)
        lower, upper = grid.bounds(rank)
        for axis in range(3):
            assert lower[axis] == grid.cuts[axis][c[axis]]
            assert upper[axis] == grid.cuts[axis][c[axis] + 1]
    np.testing.assert_allclose(grid.thinnest(), [min(np.diff(c)) for c in grid.cuts])
    assert Grid((2, 1, 1)).bounds(1).tolist() == [[0.5, 0.0, 0.0], [1.0, 1.0, 1.0]]
    for cuts in (((0.0, 0.7, 0.6, 1.0),), ((0.0, 1.0),), ((0.1, 0.5, 1.0),)):
        with pytest.raises(ValueError, match="cuts along x must be 3 increasing"):
            Grid((2, 1, 1), (*cuts, (0.0, 1.0), (0.0, 1.0)))


def test_balanced_cuts_share_the_modelled_work_evenly():
    """With the work spread evenly within each slab (the model), a full step puts every
    plane where the work below it is its share; a damped step goes part of the way; no
    plane moves more than half a slab; a balanced axis stays; slabs keep their minimum."""
    rng = np.random.default_rng(5)
    unclipped = 0
    for p in (2, 3, 5, 5, 5):
        cuts = np.array(uneven((p, 1, 1), seed=int(rng.integers(100))).cuts[0])
        density = rng.uniform(0.7, 1.4, p)  # work per unit fraction in each slab
        costs = density * np.diff(cuts)
        edges = np.concatenate([[0.0], np.cumsum(costs)])
        inner = slice(1, p)
        # the plane below which the model's work is k / p of the total, by bisection
        shares = np.arange(1, p) * edges[-1] / p
        targets = np.array([_bisect(cuts, edges, share) for share in shares])
        halves = 0.5 * np.minimum(np.diff(cuts)[:-1], np.diff(cuts)[1:])
        for damping in (1.0, 0.5):
            moved = balanced_cuts(cuts, costs, minimum=0.01, damping=damping)
            step = np.clip(damping * (targets - cuts[inner]), -halves, halves)
            np.testing.assert_allclose(moved[inner], cuts[inner] + step, atol=1e-12)
            assert moved[0] == 0.0 and moved[-1] == 1.0 and np.all(np.diff(moved) > 0.01)
        if np.all(np.abs(targets - cuts[inner]) < halves):
            unclipped += 1
            full = balanced_cuts(cuts, costs, minimum=0.01, damping=1.0)
            np.testing.assert_allclose(
                np.diff(np.interp(full, cuts, edges)), edges[-1] / p, rtol=1e-10
            )
    assert unclipped >= 2  # the even share itself was checked
    even = balanced_cuts([0.0, 0.25, 0.5, 0.75, 1.0], [2.0, 2.0, 2.0, 2.0], minimum=0.1)
    np.testing.assert_allclose(even, [0.0, 0.25, 0.5, 0.75, 1.0], atol=1e-15)
    # a slab no thinner than the minimum, however slow its rank
    squeezed = balanced_cuts([0.0, 0.5, 1.0], [1000.0, 1.0], minimum=0.45, damping=1.0)
    np.testing.assert_allclose(squeezed, [0.0, 0.45, 1.0])
    with pytest.raises(ValueError, match="do not fit"):
        balanced_cuts([0.0, 0.5, 1.0], [1.0, 2.0], minimum=0.6)


def _bisect(cuts, edges, share: float) -> float:
    """The fraction x where the model's work below x, interp(x, cuts, edges), is share."""
    lo, hi = 0.0, 1.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if np.interp(mid, cuts, edges) < share else (lo, mid)
    return 0.5 * (lo + hi)


def test_the_second_ghost_build_lays_the_local_system_out_in_memory_made_at_the_first():
    """Domain.build alternates between two sets of local arrays (the last build's system
    stays in use while the next is laid out). The first build, a run's set-up, makes and
    writes both, so that the second, the first inside a run's loop, allocates none (a
    10^6-atom rank paid ~0.09 s of page faults there, counted as communication); the local
    state's velocities and masses are views, not arrays written at every build."""
    import tracemalloc

    from md.distributed.halo import Domain

    state, _ = atoms(range(20000), 0.0, 5.0, 5)
    no_ghosts = np.zeros((1, 8))  # (both swaps in one message: a row of counts, no rows)
    domain = Domain(Loopback([no_ghosts] * 4), Grid((2, 1, 1)))
    domain.reserve(state, {})
    domain.build(state, 0.1)  # a thin shell: few ghosts sent, little packed
    first = domain.local_state.positions
    local_bytes = first.nbytes + domain.local_ids.nbytes
    state.positions[:, 1] += 0.01  # the next build's positions
    tracemalloc.start()
    try:
        domain.build(state, 0.1)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    second = domain.local_state.positions
    assert not np.shares_memory(first, second)  # the other set: the first is still whole
    moved = (second[:, 1] - first[:, 1] + 5.0) % 10.0 - 5.0  # y is periodic (box 10)
    np.testing.assert_allclose(moved, 0.01, atol=1e-12)
    assert domain.n_owned == len(second) == 20000  # (the neighbour sent no ghosts)
    # the arrays of the owned atoms alone: 0.5 of local_bytes now (temporaries), 3.1
    # before (the next set made here, and fresh velocities and masses for the local state)
    assert peak < local_bytes, (peak, local_bytes)


def test_the_comm_clock_holds_the_ghosts_search_and_messages_not_the_owned_layout(monkeypatch):
    """What the run summary's comm section counts (docs/guide/mpi.md): a build's ghost
    search (the faces' atoms, their packing, the messages) and a step's ghost positions
    run on the ranks' clock; the owned atoms' layout before them (at a build their images
    nearest the brick, at a step their rows' copy) does not, as LAMMPS's Comm leaves out
    its Domain::pbc."""
    import md.distributed.halo as halo
    from md.distributed.halo import Domain

    class Clock:
        """A CommClock that says whether it is running."""

        def __init__(self) -> None:
            self.depth, self.seconds = 0, 0.0

        def __enter__(self):
            self.depth += 1
            return self

        def __exit__(self, *exc) -> None:
            self.depth -= 1

    class Neighbour(Loopback):
        def messages(self, sends, receives):
            """Persistent messages whose run keeps what is sent and receives zeros."""
            ranks = self

            class Messages:
                def run(self):
                    with ranks.clock:
                        ranks.sent += [np.array(buffer) for buffer, _, _ in sends]
                        for buffer, _, _ in receives:
                            buffer[...] = 0.0

                def free(self):
                    pass

            return Messages()

    ranks = Neighbour([np.zeros((1, 8))] * 4)  # (no ghosts: both swaps' message, counts)
    ranks.clock = Clock()
    calls = []
    for name in (
        "home_layout",
        "sweep_send",
        "pack_sweep",
        "home_positions",
        "shift_rows",
    ):
        kernel = getattr(halo, name)

        def recorded(*args, _kernel=kernel, _name=name):
            calls.append((_name, ranks.clock.depth > 0))
            return _kernel(*args)

        monkeypatch.setattr(halo, name, recorded)
    state, _ = atoms(range(2000), 0.0, 5.0, 6)
    domain = Domain(ranks, Grid((2, 1, 1)))
    domain.reserve(state, {})
    domain.build(state, 0.5)
    domain.update(state)  # every owned row copied (home_positions)
    domain.update(state, copied=True)  # the rows were copied by the caller (shift_rows)
    on_clock = {name: {inside for called, inside in calls if called == name} for name, _ in calls}
    assert on_clock == {
        "home_layout": {False},
        "sweep_send": {True},
        "pack_sweep": {True},
        "home_positions": {False},
        "shift_rows": {False},
    }
    assert ranks.clock.depth == 0 and len(ranks.sent) == 1 + 4  # the sweep's rows, 2 x 2 steps
