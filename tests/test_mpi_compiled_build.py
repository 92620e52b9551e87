"""A decomposed list build's compiled pieces (issue 69): a ghost sweep's face search, rows
and swap tables as compiled passes (``sweep_send``, ``sweep_append``) into memory kept
between builds, the compiled halo's plan made of those tables as they are, and a
migration's pack and refill as one compiled call each.

No MPI here: a loopback neighbour plays the other rank (the MPI tests of the halo, the
builds and the trajectories, ``tests/test_mpi*.py``, run the same code between real
ranks).
"""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

import md.distributed.migration as migration
from md.box import cell_matrix
from md.distributed import CommClock
from md.distributed.grid import Grid
from md.distributed.halo import Domain
from md.distributed.ranks import CompiledMPI, MPIRanks
from md.state import State


class Echo(MPIRanks):
    """Rank 0 of a 2 x 1 x 1 grid whose neighbour sends back what it was sent (the rows
    arrive in memory kept here: no array is made for them), or the next of ``answers``;
    reductions are identities; its compiled MPI is never called (a build and its plan
    make no MPI call)."""

    rank, n_ranks = 0, 2

    def __init__(self, answers=()) -> None:  # (no communicator: MPIRanks' own not run)
        self.clock = CommClock()
        self.compiled = CompiledMPI(np.zeros(8, dtype=np.int64))
        self.answers = list(answers)
        self.sent: list[tuple] = []
        self._kept: dict[int, np.ndarray] = {}

    def exchange_rows(self, rows, dest, source, tag):
        self.sent.append((len(rows), float(np.sum(rows))))
        if self.answers:
            return self.answers.pop(0)
        held = self._kept.get(tag)
        if held is None or held.shape[0] < len(rows):
            held = self._kept[tag] = np.empty((2 * len(rows) + 8, rows.shape[1]))
        held[: len(rows)] = rows
        return held[: len(rows)]

    def exchange_many(self, exchanges):
        return [self.exchange_rows(*exchange) for exchange in exchanges]

    def max(self, values):  # (the reductions: identities, as on one rank)
        return values

    def sum(self, values):
        return values


def _gas(n: int, seed: int, ids_from: int = 0, x_range=(0.0, 5.0)) -> State:
    """n atoms in the lower half along x of a 10^3 box (rank 0's brick of 2 x 1 x 1), with
    velocities, masses and types that follow their ids (so that every row can be
    checked)."""
    rng = np.random.default_rng(seed)
    ids = np.arange(ids_from, ids_from + n, dtype=np.int64)
    positions = np.column_stack([rng.uniform(*x_range, n), rng.uniform(0, 10, (n, 2))])
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
    return state


def test_a_sweep_sends_the_atoms_near_its_faces_in_local_order_with_their_rows():
    """sweep_send: the atoms before ``count`` (owned, then the earlier sweeps' ghosts) whose
    fraction along the axis is below the lower face go down, at or above the upper one
    up, each list in local order, after the last sweep's lists; its message is a row of
    counts then the rows (position shifted by the swap's cell vectors, fractions shifted
    along the axis, id, type); its swap and sweep table rows. Too little room: nothing
    written, the sizes returned. sweep_append lays the rows out as ghosts."""
    from md.distributed._domain_kernels import sweep_append, sweep_send

    rng = np.random.default_rng(5)
    n_owned, n_ghosts, axis = 40, 25, 1
    count = n_owned + n_ghosts
    room = count + 50
    positions = rng.uniform(0.0, 10.0, (room, 3))
    owned = rng.uniform(-0.1, 0.6, (n_owned, 3))
    ghosts = np.zeros((room - n_owned, 3))
    ghosts[:n_ghosts] = rng.uniform(-0.1, 0.6, (n_ghosts, 3))
    ids = rng.permutation(1000)[:room].astype(np.int64)
    types = (ids % 3).astype(np.int32)
    cell = cell_matrix(np.array([10.0, 9.0, 8.0]), np.array([0.5, -0.3, 0.2]))
    faces, moves, peers = (0.1, 0.45), (1, 0), (3, 5, False)
    table = np.zeros((6, 8), dtype=np.int64)
    table[1] = (0, 7, 0, 0, 0, 0, 1, 0)  # the last sweep's second swap: index up to 7
    table[1, 2:4], table[1, 7] = (n_owned, 11), 4  # (its ghosts: 11 from row 4 of back)
    shifts, sweeps = np.zeros(6), np.zeros((3, 4), dtype=np.int64)
    fractions = np.vstack([owned, ghosts[:n_ghosts]])
    down = np.flatnonzero(fractions[:, axis] < faces[0])
    up = np.flatnonzero(fractions[:, axis] >= faces[1])
    assert len(down) > 3 and len(up) > 3

    def send(index, rows):
        return sweep_send(
            positions, owned, ghosts, ids, types, n_owned, count, axis, faces, moves, peers,
            cell, index, rows, table, shifts, sweeps, 1,
        )  # fmt: skip

    before = table.copy()
    short = np.full(7 + len(down) + len(up) - 1, -1, dtype=np.int64)
    assert send(short, np.zeros((64, 8))) == (len(down), len(up), False)
    assert np.all(short == -1) and np.array_equal(table, before)  # nothing written
    index, rows = np.full(100, -1, dtype=np.int64), np.full((100, 8), np.nan)
    assert send(index, rows) == (len(down), len(up), True)
    sent = np.concatenate([down, up])
    np.testing.assert_array_equal(index[7 : 7 + len(sent)], sent)
    np.testing.assert_array_equal(rows[0], [len(down), 0, 0, 0, 0, 0, 0, 0])
    move = np.where(np.arange(len(sent)) < len(down), moves[0], moves[1])
    expected = np.column_stack(
        [positions[sent] + move[:, None] * cell[axis], fractions[sent], ids[sent], types[sent]]
    )
    expected[:, 3 + axis] += move
    np.testing.assert_array_equal(rows[1 : 1 + len(sent)], expected)
    end = 7 + len(down)
    np.testing.assert_array_equal(table[2, [0, 1, 4, 5, 6]], [7, end, 3, 5, 2])
    np.testing.assert_array_equal(table[3, [0, 1, 4, 5, 6]], [end, end + len(up), 5, 3, 3])
    np.testing.assert_array_equal(shifts[2:4], moves)
    np.testing.assert_array_equal(sweeps[1], [axis, 0, 2, 4])

    # what arrives (here: what was sent) becomes ghosts count onwards
    arrived_down, arrived_up = rows[1 : 1 + len(down)], rows[1 + len(down) : 1 + len(sent)]
    after = sweep_append(
        arrived_down, arrived_up, count, n_owned, positions, ghosts, ids, types, table, 1
    )
    assert after == count + len(sent)
    np.testing.assert_array_equal(positions[count:after], expected[:, :3])
    np.testing.assert_array_equal(ghosts[n_ghosts : n_ghosts + len(sent)], expected[:, 3:6])
    np.testing.assert_array_equal(ids[count:after], ids[sent])
    np.testing.assert_array_equal(types[count:after], types[sent])
    np.testing.assert_array_equal(table[2, [2, 3, 7]], [count, len(down), 15])
    np.testing.assert_array_equal(table[3, [2, 3, 7]], [count + len(down), len(up), 15 + len(down)])


def test_the_compiled_halo_plan_is_the_ghost_search_tables_kept_between_builds():
    """Domain.plan, the compiled exchanges' arrays, holds the swaps of the last build as
    the swaps say (a row a swap: its send list's rows, ghost rows, peers, tag, ghosts'
    rows among all; a row a sweep; the shifts; the send lists end to end), in memory the
    build's ghost search wrote them into and kept: the build after next writes the same
    memory (two sets, alternating as the local arrays), and a build with its plan then
    makes no array of the ghosts' size (it made the rows of each swap, their
    concatenation and the plan's tables and buffers afresh at every build before)."""
    state = _gas(20000, 11)
    ranks = Echo()
    domain = Domain(ranks, Grid((2, 1, 1)))
    domain.reserve(state, {})
    plans, peak = [], None
    for build in range(3):
        state.positions[:, 1] += 0.01
        if build < 2:
            domain.build(state, 1.0)
            plan = domain.plan()
        else:  # (both sets of kept memory made: what the build and its plan allocate)
            tracemalloc.start()
            try:
                domain.build(state, 1.0)
                plan = domain.plan()
                _, peak = tracemalloc.get_traced_memory()
            finally:
                tracemalloc.stop()
        plans.append(plan)
        swaps = domain.swaps
        assert len(swaps) == 2 and swaps[0].count > 1000  # (a thick shell: many ghosts)
        backs = np.cumsum([0] + [swap.count for swap in swaps])
        ends = np.cumsum([len(swap.send) for swap in swaps])
        np.testing.assert_array_equal(
            plan.table,
            [
                (end - len(w.send), end, w.offset, w.count, w.dest, w.source, w.tag, back)
                for w, end, back in zip(swaps, ends, backs[:-1], strict=True)
            ],
        )
        np.testing.assert_array_equal(plan.sweeps, [[0, 0, 0, 2]])
        np.testing.assert_array_equal(plan.shifts, [float(swap.shift) for swap in swaps])
        np.testing.assert_array_equal(plan.index, np.concatenate([w.send for w in swaps]))
        assert plan.out.shape == (len(plan.index), 3)
        assert plan.back.shape == (backs[-1], 3)
        # the ghosts are the atoms sent, shifted (the neighbour echoes them)
        ghosts = domain.local_state.positions[domain.n_owned :]
        shift = np.repeat([swap.shift for swap in swaps], [swap.count for swap in swaps])
        sent = domain.local_state.positions[plan.index]
        np.testing.assert_array_equal(ghosts[:, 1:], sent[:, 1:])
        np.testing.assert_array_equal(ghosts[:, 0], sent[:, 0] + shift * 10.0)
    first, second, third = plans
    for name in ("index", "table", "sweeps", "shifts"):
        assert np.shares_memory(getattr(third, name), getattr(first, name)), name
        assert not np.shares_memory(getattr(second, name), getattr(first, name)), name
    for name in ("out", "back"):  # (used inside an exchange only: one buffer)
        assert np.shares_memory(getattr(third, name), getattr(second, name)), name
    ghost_rows = 8 * 8 * len(third.index)  # (the rows the sweep sent)
    assert peak < 0.05 * ghost_rows, (peak, ghost_rows)


def _migrating(seed: int, bricks: int):
    """Rank 0's 300 atoms of ``bricks`` along x, 40 of which have left its brick (with three
    bricks, some up and some down), carried arrays and the neighbours' messages (60 atoms
    arriving from below, none from above), packed as a migration packs them."""
    width = 10.0 / bricks
    state = _gas(300, seed, x_range=(0.0, width - 0.1))
    state.positions[:40, 0] += np.linspace(width, 10.0 - width, 40)  # they leave
    carried = {"forces": np.outer(state.ids, [-1.0, 0.5, 2.0]), "extra": state.ids * 0.25}
    newcomers = _gas(60, seed + 1, ids_from=1000, x_range=(0.5, width - 0.5))
    arrays = [
        newcomers.positions,
        newcomers.velocities,
        newcomers.masses,
        newcomers.types,
        newcomers.ids,
        np.outer(newcomers.ids, [-1.0, 0.5, 2.0]),
        newcomers.ids * 0.25,
    ]
    arriving = np.column_stack([a.reshape(60, -1).astype(float) for a in arrays])
    return state, carried, [arriving, np.zeros((0, arriving.shape[1]))]


class Loopback(Echo):
    """Echo, but a message's rows are only summed (not kept) and the answers are given."""


@pytest.mark.parametrize("bricks", [2, 3])
@pytest.mark.parametrize("compiled", [True, False])
def test_a_migration_sends_and_refills_the_same_rows_compiled_or_not(monkeypatch, compiled, bricks):
    """Domain.migrate packs the leaving atoms' rows and refills the arrays with the arriving
    ones as one compiled call each where the arrays allow (the state's usual types, the
    carried ones C-contiguous float64), numpy's calls otherwise: the same messages, the
    same rows in the same order, bit for bit, whichever runs (one message each way with two
    bricks along the axis, two with three)."""
    reference_state, reference_carried, answers = _migrating(3, bricks)
    reference = Domain(Loopback([a.copy() for a in answers]), Grid((bricks, 1, 1)))
    reference.reserve(reference_state, {})
    monkeypatch.setattr(migration, "_compiled_layout", _numpy_layout)
    moved_reference = reference.migrate(reference_state, reference_carried)
    monkeypatch.undo()

    state, carried, answers = _migrating(3, bricks)
    if not compiled:
        carried["extra"] = carried["extra"].astype(np.float32)  # (numpy's path)
        reference_extra = moved_reference["extra"].astype(np.float32)
    domain = Domain(Loopback(answers), Grid((bricks, 1, 1)))
    domain.reserve(state, {})
    moved = domain.migrate(state, carried)
    assert domain.ranks.sent == reference.ranks.sent  # (rows and their sums)
    assert len(domain.ranks.sent) == (1 if bricks == 2 else 2)
    assert all(rows > 0 for rows, _ in domain.ranks.sent)  # (atoms left both ways)
    assert sorted(state.ids.tolist()) == [*range(40, 300), *range(1000, 1060)]
    for name in ("positions", "velocities", "masses", "types", "ids"):
        np.testing.assert_array_equal(getattr(state, name), getattr(reference_state, name))
        assert getattr(state, name).dtype == getattr(reference_state, name).dtype
    np.testing.assert_array_equal(moved["forces"], moved_reference["forces"])
    np.testing.assert_array_equal(moved["forces"], np.outer(state.ids, [-1.0, 0.5, 2.0]))
    extra = moved_reference["extra"] if compiled else reference_extra
    np.testing.assert_array_equal(moved["extra"], extra)
    assert moved["extra"].dtype == carried["extra"].dtype


def _numpy_layout(arrays):
    """migration's numpy path for any arrays (the width of their rows as it counts it)."""
    return False, sum(int(np.prod(a.shape[1:])) for a in arrays)


def test_a_migration_holds_the_indices_of_the_atoms_it_moves_not_their_rows():
    """A migration's outgoing rows go from memory kept between migrations, and its refill
    reads the arriving rows where they arrived: what it allocates is the moving atoms'
    indices (their lists and the refill's plan), under 16 bytes a moving atom (before:
    the pack's rows and each array's fancy-indexed copy, the arrivals' concatenation and
    each array's converted copy, 390 kB for these 1500 leaving and 2000 arriving atoms)."""
    state = _gas(6000, 8)
    carried = {"forces": np.outer(state.ids, [-1.0, 0.5, 2.0])}
    newcomers = _gas(2000, 9, ids_from=10000, x_range=(0.5, 4.5))
    arriving = np.column_stack(
        [
            newcomers.positions,
            newcomers.velocities,
            newcomers.masses,
            newcomers.types,
            newcomers.ids,
            np.outer(newcomers.ids, [-1.0, 0.5, 2.0]),
        ]
    )
    ranks = Loopback([arriving[:0], arriving])
    domain = Domain(ranks, Grid((2, 1, 1)))
    domain.reserve(state, carried)
    state.positions[state.ids < 1500, 0] += 5.0
    carried = domain.migrate(state, carried)  # (1500 leave: the outgoing rows' memory made)
    state.positions[state.ids < 3000, 0] += 5.0  # 1500 more leave, 2000 arrive
    tracemalloc.start()
    try:
        carried = domain.migrate(state, carried)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert sorted(state.ids.tolist()) == [*range(3000, 6000), *range(10000, 12000)]
    np.testing.assert_array_equal(carried["forces"], np.outer(state.ids, [-1.0, 0.5, 2.0]))
    np.testing.assert_array_equal(state.velocities, np.outer(state.ids, [1.0, 2.0, 3.0]))
    assert peak < 16 * (1500 + 2000), peak
