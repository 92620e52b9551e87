"""The halo: a rank's brick, its owned atoms and the ghost shell around them.

Ghosts are found as LAMMPS's brick communication finds them: three sweeps, along
a, b and c, each sending to the two face neighbours the atoms (owned, and ghosts
from the earlier sweeps) within the reach of their faces, shifted by a cell
vector across a periodic boundary; a single brick along an axis sends to itself.
The owned atoms followed by the ghosts form the rank's local system, open along
the cut axes (images explicit) and periodic along the others whose cell vector
has no component along a cut axis (:func:`md.distributed.grid.local_periodic_axes`).
:meth:`Domain.update` sends the ghosts' positions along the sweeps, and
:meth:`Domain.reverse` their forces back along the reverse of them; the atoms
themselves move between ranks in :mod:`md.distributed.migration`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from md.box import cell_matrix, periodic_tilt, perpendicular_widths
from md.distributed._domain_kernels import (
    add_rows,
    add_sweep,
    brick_of,
    fractional_coordinates,
    ghost_rows,
    home_layout,
    home_positions,
    pack_sweep,
    shift_rows,
    sweep_append,
    sweep_send,
)
from md.distributed._mpi_kernels import halo_forward, halo_reverse
from md.distributed.grid import Grid, local_periodic_axes
from md.distributed.migration import RowStore, check_lost, lost_error, migrate
from md.distributed.ranks import MPIRanks
from md.errors import DecompositionError
from md.parallel import global_max
from md.state import State

_NO_ROWS = np.empty((0, 3))  # (never written: a copy into no rows)
#: How far, in skins, a step start's build lets owned atoms stray from their bricks: the
#: margin of its ghost shell, agreed without a reduction (:meth:`Domain.build`). Its atoms
#: have just migrated into their bricks and are laid out a step ahead, so they stray by
#: a step's move; a step moving atoms a quarter skin would rebuild the list every other
#: step, and a rank whose atoms strayed further has every rank build again.
AGREED_STRAY = 0.25


@dataclass
class _Swap:
    """One message of the ghost exchange: the local atoms ``send`` go to ``dest``, shifted
    by ``shift`` cell vectors along ``axis``; ``count`` atoms arrive from ``source`` into
    local indices ``offset`` onwards. The forces on those go back the same way."""

    send: NDArray[np.int64]
    axis: int
    shift: int
    dest: int
    source: int
    offset: int
    count: int
    tag: int


class _Sweep:
    """The swaps of one axis as one compiled pass and one set of persistent messages: their
    send lists end to end (``index``, swap j's from ``starts[j]``), shifts, ghost rows
    (``offsets``, ``counts``) and the fixed buffers the messages go from and into. The
    swaps of a sweep send only atoms laid out before the sweep's own ghosts, so they
    can be in flight together; their sums back are added swap after swap, as
    :meth:`Domain.reverse` adds them one by one."""

    def __init__(self, swaps: list[_Swap], rank: int, ranks, positions: NDArray) -> None:
        self.axis = swaps[0].axis
        self.to_self = swaps[0].dest == rank  # (one brick along the axis: both swaps)
        lengths = [len(swap.send) for swap in swaps]
        self.starts = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
        self.index = (
            np.concatenate([swap.send for swap in swaps]).astype(np.int64)
            if swaps
            else np.zeros(0, dtype=np.int64)
        )
        self.shifts = np.array([float(swap.shift) for swap in swaps])
        self.offsets = np.array([swap.offset for swap in swaps], dtype=np.int64)
        self.counts = np.array([swap.count for swap in swaps], dtype=np.int64)
        total = int(self.starts[-1])
        self.out = np.empty((total, 3))  # positions out, forces back in (aligned with index)
        self.back = np.empty((int(self.counts.sum()), 3))  # the ghosts' forces out
        self.forward = self.backward = None
        if self.to_self:
            return
        ghost_starts = np.concatenate([[0], np.cumsum(self.counts)]).astype(np.int64)
        sends, receives, returns, returned = [], [], [], []
        for j, swap in enumerate(swaps):
            part = self.out[self.starts[j] : self.starts[j + 1]]
            ghosts = positions[swap.offset : swap.offset + swap.count]
            back = self.back[ghost_starts[j] : ghost_starts[j + 1]]
            sends.append((part, swap.dest, swap.tag))
            receives.append((ghosts, swap.source, swap.tag))
            returns.append((back, swap.source, 16 + swap.tag))
            returned.append((part, swap.dest, 16 + swap.tag))
        self.forward = ranks.messages(sends, receives)
        self.backward = ranks.messages(returns, returned)

    def free(self) -> None:
        for messages in (self.forward, self.backward):
            if messages is not None:
                messages.free()


class _Plan:
    """A build's swaps as the arrays of the compiled exchanges
    (:func:`md.distributed._mpi_kernels.halo_forward` and ``halo_reverse``, which make the
    MPI calls themselves): a row a sweep (its axis, whether it goes to this rank itself,
    its swaps' rows) and a row a swap (its send list's rows in ``index``, ghost rows,
    peers, tag and ghosts' rows in ``back``: the columns the kernels module names), the
    shifts, and the buffers the messages go from and into (``out``, aligned with
    ``index``; ``back``, the ghosts' forces). The tables are those the build's ghost
    search wrote (:func:`md.distributed._domain_kernels.sweep_send`), the peers and tags
    the :class:`_Sweep` messages'; nothing is copied."""

    def __init__(self, sweeps, table, shifts, index, out, back, slots, compiled) -> None:
        self.calls = compiled.calls
        self.check = compiled.check
        self.sweeps, self.table, self.shifts, self.index = sweeps, table, shifts, index
        self.out, self.back, self.slots = out, back, slots

    def forward(self, positions: NDArray[np.float64], cell: NDArray[np.float64]) -> None:
        self.check(
            halo_forward(
                positions,
                cell,
                self.sweeps,
                self.table,
                self.shifts,
                self.index,
                self.out,
                self.slots,
                self.calls,
            )
        )

    def reverse(self, values: NDArray[np.float64]) -> None:
        self.check(
            halo_reverse(
                values,
                self.sweeps,
                self.table,
                self.index,
                self.out,
                self.back,
                self.slots,
                self.calls,
            )
        )


class Domain:
    """This rank's brick, its ghost shell and the messages that fill it.

    Parameters
    ----------
    ranks : MPIRanks
        The communicator (``rank``, ``n_ranks``, exchanges).
    grid : Grid
        The bricks; this rank's is ``grid.coordinates(ranks.rank)``.

    Attributes
    ----------
    local_state : State
        The rank's local system: its owned atoms (first ``n_owned``) at their
        images nearest the brick, then the ghosts; periodic along
        ``local_pbc``, open along the other axes.
    local_pbc : ndarray of bool
        The axes the last build left periodic (no ghosts along them).
    local_ids : ndarray of int64
        The global id of each local atom.
    reach, margin : float
        The ghost shell of the last build, and how far owned atoms had
        strayed from their bricks then [length].
    """

    def __init__(self, ranks, grid: Grid) -> None:
        self.ranks = ranks
        self.rank = ranks.rank
        self.coordinates = grid.coordinates(self.rank)
        self.shape = np.array(grid.shape, dtype=np.int64)
        self.set_grid(grid)
        self.reach = 0.0
        self.margin = 0.0
        self.n_owned = 0
        self.swaps: list[_Swap] = []
        self._sweeps: list[_Sweep] | None = None  # the swaps' messages, made at first use
        self._plan: _Plan | None = None  # or the compiled exchanges' arrays, of these swaps:
        self._plan_swaps: list[_Swap] | None = None
        self._swept: tuple | None = None  # (the last build's swap tables, if a swap is remote)
        self._tables: list[list | None] = [None, None]  # (the two sets, as the local arrays)
        self._slots: NDArray | None = None  # (the compiled exchanges' requests)
        self.imaged = np.zeros(0, dtype=np.int64)  # owned atoms away from their stored image
        self.images = np.zeros((0, 3), dtype=np.int64)  # and their images (rows of imaged)
        self.local_pbc = np.zeros(3, dtype=bool)
        self._local_periodic = False
        self._cell_key: tuple | None = None  # the cell of the last update, and its matrix
        self._cell = np.eye(3)
        self._built_tilt = b""
        self.local_state: State | None = None
        self.local_ids = np.zeros(0, dtype=np.int64)
        self._buffers: dict[object, NDArray] = {}
        self._received: dict[str, NDArray] = {}  # (exchange_kept's)
        self._adopted: list[State | None] = [None, None]  # (the local states, by parity)
        self.rows = RowStore()  # the owned atoms' arrays, kept for migrations
        #: Atoms the migrations since the last build lost (moved more than a brick), shared
        #: in the next ghost search's reduction.
        self.lost_atoms = 0
        #: Whether owned atoms strayed beyond the last build's agreed margin (see build).
        self.outgrown = False
        self._local: dict[str, list] = {}
        self._parity = 0

    def set_grid(self, grid: Grid) -> None:
        """Take ``grid``'s cuts (same shape): atoms go to their new bricks at the next
        migration (:meth:`migrate`), which must come before the next :meth:`build`."""
        if grid.shape != tuple(self.shape.tolist()):
            raise ValueError(f"a grid of {list(grid.shape)} for a domain of {self.shape.tolist()}")
        self.grid = grid
        self.bounds = grid.bounds(self.rank)
        self.center = self.bounds.mean(axis=0)
        self.cuts = grid.cut_table()
        self.thinnest = grid.thinnest()
        self._geometry_key: tuple | None = None  # (the build's cell geometry, see geometry)
        #: (the rank below, the rank above) along each axis: each build's and migration's
        self.neighbors = tuple(
            (grid.neighbor(self.rank, axis, -1), grid.neighbor(self.rank, axis, 1))
            for axis in range(3)
        )

    def fractions(self, state: State) -> NDArray[np.float64]:
        """(N, 3) coordinates of ``state``'s atoms along the cell vectors (unwrapped)."""
        out = np.empty((state.n_atoms, 3))
        fractional_coordinates(
            state.positions, state.box, periodic_tilt(state.tilt, state.pbc), state.pbc, out
        )
        return out

    def owner_of(self, state: State) -> NDArray[np.int64]:
        """The rank whose brick holds each atom of ``state`` now."""
        bricks = np.empty((state.n_atoms, 3), dtype=np.int64)
        brick_of(self.fractions(state), self.shape, self.cuts, bricks)
        _, py, pz = self.grid.shape
        return (bricks[:, 0] * py + bricks[:, 1]) * pz + bricks[:, 2]

    # ------------------------------------------------------------------ migration
    def migrate(self, state: State, carried: dict, spent: tuple = ()) -> dict:
        """Move the owned atoms, and the per-atom arrays ``carried``, to the ranks whose
        bricks hold them (:func:`md.distributed.migration.migrate`, which says what
        ``spent`` gives away). Collective.

        An atom that moved more than one brick along an axis since the last migration
        is counted in ``lost_atoms``: the :meth:`build` that follows every migration
        raises for it on every rank (its reduction shares the count).
        """
        return migrate(self, state, carried, spent)

    # -------------------------------------------------------------------- ghosts
    def build(
        self, state: State, reach: float, margin: float | None = None
    ) -> DecompositionError | None:
        """Find the ghosts within ``reach`` of the brick (widened by as far as owned atoms
        have strayed from it) and lay out the local system. Collective.

        How far the owned atoms strayed is shared in a reduction of the build's own, unless
        the caller gives a ``margin`` every rank agrees on (the same on every rank; a step
        start's build, just after a migration: see
        :meth:`md.distributed.forcefield.DistributedForceField.rebuild`) and the bricks
        are wide enough for it. The shell is then ``reach + margin`` and no rank waits for
        another here but in the ghosts' messages; a rank whose atoms strayed further is
        ``outgrown`` (:meth:`layout_holds` is False, so the next evaluation has every rank
        build again, with the reduction), and the atoms its migrations lost are returned
        as the error for the caller to share (else None) rather than raised.

        The ghost search (from the reduction of the strays on: the faces' atoms, their
        packing and messages) runs on the ranks' clock, the communication section; the
        layout of the owned atoms before it (their images nearest the brick, copied into
        the local system) does not, as LAMMPS's Comm leaves out its ``Domain::pbc``.

        Raises
        ------
        DecompositionError
            On every rank, if the migrations since the last build lost atoms (one moved
            more than a brick along an axis), or owned atoms strayed so far that the
            ghost shell would need atoms from beyond the face neighbours.
        """
        box, pbc = state.box, state.pbc
        geometry = self.geometry(state)
        tilt, cell, widths = geometry[:3]
        # The local system is written where it will stay: the owned atoms first, at their
        # images nearest the brick (a copy; only the atoms with an image of their own are
        # shifted), then each sweep's ghosts appended (the arrays grow by half when full),
        # their fractional coordinates kept beside them for the later sweeps. Sweeps send
        # rows of position (3), fractional position (3), id and type.
        n = len(state.positions)
        self._parity ^= 1  # the local arrays of the build before this one stay as they are
        memory = self._build_memory(n)
        positions, ids, types, home, images = memory[:5]
        self.imaged, self.images, strayed = home_layout(
            state.positions,
            box,
            tilt,
            pbc,
            cell,
            self.center,
            self.bounds,
            widths,
            home,
            positions[:n],
            images,  # (images, and the atoms' indices)
        )
        ids[:n] = state.ids
        types[:n] = state.types
        with self.ranks.clock:
            return self._find_ghosts(state, reach, strayed, memory, n, margin, geometry)

    def _find_ghosts(
        self,
        state: State,
        reach: float,
        strayed: float,
        memory: tuple,
        n: int,
        agreed: float | None,
        geometry: tuple,
    ) -> DecompositionError | None:
        """:meth:`build`'s ghost search and the local system's state, after the owned
        atoms' layout (the first ``n`` rows of the positions of ``memory``, the build's
        :meth:`_build_memory`, their fractions its ``home``; the ``agreed`` margin or None;
        the cell's :meth:`geometry`). Returns the lost atoms' error where it is the
        caller's to share."""
        positions, ids, types, home, _, ghost_fractions, rows, tables = memory
        box, pbc = state.box, state.pbc
        tilt, cell, widths, local_pbc, local_tilt, local_periodic, thinnest = geometry
        if agreed is not None and thinnest < reach + 2.0 * agreed:
            agreed = None  # (bricks too thin for it, on every rank alike: the reduction)
        unshared = None
        if agreed is None:
            # one reduction: how far owned atoms strayed, and the migration's lost atoms
            margin, lost = global_max(np.array([strayed, float(self.lost_atoms)]), self.ranks)
            self.lost_atoms = 0
            check_lost(lost)
            self.outgrown = False
        else:
            margin = agreed
            self.outgrown = strayed > agreed
            unshared, self.lost_atoms = lost_error(self.lost_atoms), 0
        shell = reach + margin
        if thinnest < shell + margin:
            brick = widths * self.thinnest
            axis = int(np.argmax(pbc & (brick < shell + margin)))
            raise DecompositionError(
                f"owned atoms strayed up to {margin:.3g} from their bricks inside a step, so "
                f"the ghost shell would have to reach {shell + margin:.4g} across "
                f"{'xyz'[axis]}, more than a brick ({brick[axis]:.4g}); use fewer ranks or a "
                "smaller time step"
            )
        # Each sweep is two compiled calls around its messages: sweep_send finds the atoms
        # near the faces, writes their rows (one message's, a row of counts first) and this
        # build's swap tables, which the compiled halo then uses as they are (plan);
        # sweep_append lays the arrived rows out as ghosts. The tables and send lists lie
        # in memory kept between builds (two sets, alternating as the local arrays).
        index, table, shifts, sweeps = tables
        count, start, s, remote = n, 0, 0, False
        swaps: list[_Swap] = []
        for axis in range(3):
            if not pbc[axis] or local_pbc[axis]:
                continue
            p, c = self.grid.shape[axis], self.coordinates[axis]
            reach_fraction = shell / widths[axis]
            # this sweep sends the atoms before its own ghosts, in local order
            faces = (self.bounds[0, axis] + reach_fraction, self.bounds[1, axis] - reach_fraction)
            down, up = self.neighbors[axis]
            moves = (1 if c == 0 else 0, -1 if c == p - 1 else 0)
            peers = (down, up, down == self.rank)
            while True:
                n_down, n_up, fitted = sweep_send(
                    positions, home, ghost_fractions, ids, types, n, count, axis, faces, moves,
                    peers, cell, index, rows, table, shifts, sweeps, s,
                )  # fmt: skip
                if fitted:
                    break
                self._buffer(1 + n_down + n_up, 8, "sweep rows")  # (grown)
                rows = self._held("sweep rows", 8)
                if start + n_down + n_up > len(index):
                    index = _grown(index, start, 2 * (start + n_down + n_up) + 64)
                    tables[0] = index
            sent = rows[: 1 + n_down + n_up]
            if down == self.rank:  # (one brick along the axis: both swaps to itself)
                lower, upper = sent[1 : 1 + n_down], sent[1 + n_down :]
            elif down == up:  # two bricks along the axis: both swaps' rows in one message
                lower, upper = self._both_ways(sent, down, 2 * s)
            else:
                lower, upper = self.ranks.exchange_many(
                    [
                        (sent[1 : 1 + n_down], down, up, 2 * s),
                        (sent[1 + n_down :], up, down, 2 * s + 1),
                    ]
                )
            remote = remote or down != self.rank
            arrived = len(lower) + len(upper)
            if count + arrived > len(positions):
                size = count + arrived + len(positions) // 2
                positions, ids, types = (_grown(a, count, size) for a in (positions, ids, types))
                for name, grown in (("positions", positions), ("ids", ids), ("types", types)):
                    self._local[name][self._parity] = grown  # kept for the next builds
                old = ghost_fractions
                ghost_fractions = self._buffer(size - n, 3, "ghost fractions")
                ghost_fractions[: count - n] = old[: count - n]
            after = sweep_append(
                lower, upper, count, n, positions, ghost_fractions, ids, types, table, s
            )
            middle, end, above = start + n_down, start + n_down + n_up, count + len(lower)
            swaps += [
                _Swap(index[start:middle], axis, moves[0], down, up, count, len(lower), 2 * s),
                _Swap(index[middle:end], axis, moves[1], up, down, above, len(upper), 2 * s + 1),
            ]
            count, start, s = after, end, s + 1
        self._swept = (tables, s, start, count - n) if remote else None
        self.swaps = swaps
        for sweep in self._sweeps or ():
            sweep.free()
        self._sweeps = None
        self.n_owned = n
        self.reach, self.margin = reach, margin
        self.local_ids = ids[:count]
        self.local_pbc = local_pbc
        self._local_periodic = local_periodic
        self._cell_key = None  # (the local state is new: its cell is written at the update)
        self._built_tilt = state.tilt.tobytes()
        # (the local arrays live in memory kept between builds: a fresh 10^6-atom layout
        # paid its page faults at every build, 5-10 ms on the Emerald Rapids VM)
        local = self._adopted[self._parity]  # (two, alternating as the local arrays do)
        if local is None or local.type_names != state.type_names:
            local = State.adopting(
                positions[:count], types[:count], box, local_pbc, state.type_names
            )
            self._adopted[self._parity] = local
        else:  # the build before last's State, its arrays the new ones (four arrays fewer)
            local.positions, local.types = positions[:count], types[:count]
            # (adopting's read-only stride-0 arrays, over the same one value)
            local.velocities = np.ndarray((count, 3), np.float64, local.velocities.base, 0, (0, 8))
            local.masses = np.ndarray((count,), np.float64, local.masses.base, 0, (0,))
            local.box[:] = box
            local.pbc[:] = local_pbc
        local.tilt[:] = local_tilt  # (update changes it in place)
        self.local_state = local
        return unshared

    def geometry(self, state: State) -> tuple:
        """``state``'s cell as a build uses it: its periodic tilt, matrix (rows a, b, c) and
        perpendicular widths, the local system's periodic axes, its tilt and whether it has
        a periodic axis, and the thinnest brick across a periodic axis [length]; kept while
        the cell, its periodic axes and the grid stay as they were (a build's small arrays
        and checks: ~15 us)."""
        key = (state.box.tobytes(), state.tilt.tobytes(), state.pbc.tobytes())
        if key != self._geometry_key:
            box, pbc = state.box, state.pbc
            tilt = periodic_tilt(state.tilt, pbc)
            widths = perpendicular_widths(box, tilt)
            local_pbc = local_periodic_axes(self.shape, pbc, tilt)
            bricks = (widths * self.thinnest)[pbc]
            self._geometry_values = (
                tilt,
                cell_matrix(box, tilt),
                widths,
                local_pbc,
                periodic_tilt(tilt, local_pbc),
                bool(local_pbc.any()),
                float(bricks.min()) if len(bricks) else np.inf,
            )
            self._geometry_key = key
        return self._geometry_values

    def exchange_kept(self, rows: NDArray, dest: int, source: int, tag: int, name: str) -> NDArray:
        """``ranks.exchange_rows``, the rows received into memory this Domain keeps under
        ``name`` where the ranks exchange rows as :class:`MPIRanks` does
        (:meth:`MPIRanks.exchange_kept`; not a stand-in's own ``exchange_rows``): good
        until the next exchange of that name (a migration's or a ghost sweep's)."""
        if type(self.ranks).exchange_rows is MPIRanks.exchange_rows:
            return self.ranks.exchange_kept(rows, dest, source, tag, self._received, name)
        return self.ranks.exchange_rows(rows, dest, source, tag)

    def _both_ways(self, joined: NDArray, other: int, tag: int) -> tuple:
        """Send a sweep's two swaps' rows to ``other``, the neighbour on both sides, as one
        message (``joined``: a row giving the first's count, then both, as
        :func:`sweep_send` writes them), and return the two parts of the one that arrives
        from it: the rows of its first swap and of its second, which come to this rank's
        first and second (its lower face's atoms arrive across this rank's upper face)."""
        arrived = self.exchange_kept(joined, other, other, tag, "ghost rows")
        split = 1 + int(arrived[0, 0])
        return arrived[1:split], arrived[split:]

    def layout_holds(self, state: State) -> bool:
        """Whether the last build's periodic axes still suit ``state``'s cell (a barostat
        that tilts the cell towards a cut axis needs a build with explicit images), and
        its agreed margin held its owned atoms' strays (see :meth:`build`)."""
        if self.outgrown:
            return False  # (owned atoms strayed beyond the build's agreed margin)
        if not self._local_periodic or state.tilt.tobytes() == self._built_tilt:
            return True  # (checked at every force call: the cheap answers first)
        tilt = periodic_tilt(state.tilt, state.pbc)
        return bool(np.all(local_periodic_axes(self.shape, state.pbc, tilt) | ~self.local_pbc))

    def owned_rows(self, state: State) -> NDArray[np.float64]:
        """The local system's rows of ``state``'s owned atoms, to copy their positions into
        (then :meth:`update` with ``copied``); no rows if the layout is not ``state``'s."""
        if self.local_state is None or self.n_owned != len(state.positions):
            return _NO_ROWS
        return self.local_state.positions[: self.n_owned]

    def update(self, state: State, copied: bool = False) -> None:
        """Write the owned positions into the local system (only the few at another image
        if they were ``copied`` there already, see :meth:`owned_rows`) and send the ghosts'
        (collective). The sweeps (packing and messages) run on the ranks' clock, the owned
        rows' copy before them does not (as :meth:`build`'s layout)."""
        key = (state.box.tobytes(), state.tilt.tobytes())
        if key != self._cell_key:  # (the cell changes under a barostat only)
            tilt = periodic_tilt(state.tilt, state.pbc)
            self._cell, self._cell_key = cell_matrix(state.box, tilt), key
            if self._local_periodic:  # the cell the local system's own images follow
                self.local_state.box[:] = state.box
                self.local_state.tilt[:] = periodic_tilt(tilt, self.local_pbc)
        cell = self._cell
        positions = self.local_state.positions
        owned = positions[: self.n_owned]
        if copied:
            shift_rows(state.positions, self.imaged, self.images, cell, owned)
        else:
            home_positions(state.positions, self.imaged, self.images, cell, owned)
        with self.ranks.clock:
            plan = self.plan()
            if plan is not None:  # (the messages from compiled code)
                plan.forward(positions, cell)
                return
            for sweep in self.sweeps():
                pack_sweep(
                    positions,
                    sweep.index,
                    sweep.starts,
                    sweep.shifts,
                    sweep.axis,
                    cell,
                    sweep.offsets,
                    sweep.to_self,
                    sweep.out,
                )
                if sweep.forward is not None:
                    sweep.forward.run()

    def fused_arguments(self, state: State) -> tuple | None:
        """What a fused velocity Verlet step (:meth:`md.distributed.DistributedForceField.
        verlet_step`) takes from the last build, made once a build: the tails of the
        arguments of :func:`md.distributed._verlet_kernels.step_out` (from the owned rows)
        and of ``gather_reverse_kick`` (from the sweeps), the local system, the owned atoms
        and the MPI error check; None without a compiled plan. The step runs in the build's
        cell only: its matrix, as :meth:`update`'s."""
        plan = self.plan()
        if plan is None:
            return None
        matrix = cell_matrix(state.box, periodic_tilt(state.tilt, state.pbc))
        owned = self.owned_rows(state)
        out = (owned, len(owned) > 0, self.n_owned, self.imaged, self.images, matrix)
        out += (self.local_state.positions, plan.sweeps, plan.table, plan.shifts, plan.index)
        out += (plan.out, plan.slots, plan.calls)
        back = (plan.sweeps, plan.table, plan.index, plan.out, plan.back, plan.slots, plan.calls)
        return out, back, self.local_state, self.n_owned, plan.check

    def plan(self) -> _Plan | None:
        """The compiled exchanges of the last build's swaps (made once a build), or None
        where the ranks have no compiled MPI calls (:attr:`MPIRanks.compiled`) or no swap
        goes to another rank (the sweeps to self stay :func:`pack_sweep`'s)."""
        compiled = self.ranks.compiled if isinstance(self.ranks, MPIRanks) else None
        if compiled is None or not self.swaps:
            return None
        if self._plan_swaps is not self.swaps:  # (a build lays out a new list of swaps)
            self._plan = None
            if self._swept is not None:  # (a swap to another rank: the build's tables)
                (index, table, shifts, sweeps), n_sweeps, n_sent, n_ghosts = self._swept
                if self._slots is None:
                    self._slots = compiled.slots(4)  # (a sweep's 2 swaps, 2 messages each)
                self._plan = _Plan(
                    sweeps[:n_sweeps],
                    table[: 2 * n_sweeps],
                    shifts[: 2 * n_sweeps],
                    index[:n_sent],
                    self._buffer(n_sent, 3, "halo out"),
                    self._buffer(n_ghosts, 3, "halo back"),
                    self._slots,
                    compiled,
                )
            self._plan_swaps = self.swaps
        return self._plan

    def _swap_tables(self) -> list[NDArray]:
        """This build's swap tables (of the set its parity picks): the send lists end to
        end, a row a swap, its shift, a row a sweep (:func:`sweep_send`'s columns); at
        most three sweeps of two swaps."""
        held = self._tables[self._parity]
        if held is None:
            held = [
                np.zeros(64, dtype=np.int64),
                np.zeros((6, 8), dtype=np.int64),
                np.zeros(6),
                np.zeros((3, 4), dtype=np.int64),
            ]
            self._tables[self._parity] = held
        return held

    def sweeps(self) -> list[_Sweep]:
        """The swaps grouped by axis, each group's persistent messages made once a build."""
        if self._sweeps is None:
            positions = self.local_state.positions
            by_axis: dict[int, list[_Swap]] = {}
            for swap in self.swaps:
                by_axis.setdefault(swap.axis, []).append(swap)
            self._sweeps = [
                _Sweep(group, self.rank, self.ranks, positions) for group in by_axis.values()
            ]
        return self._sweeps

    def reverse(self, values: NDArray[np.float64]) -> NDArray[np.float64]:
        """Add the ghosts' rows of ``values`` (n_local, k; C order) into their owners' rows
        along the reverse of the sweeps; return the owned rows (a view). Collective."""
        if values.shape[1] == 3 and values.flags.c_contiguous:
            plan = self.plan()
            if plan is not None:
                plan.reverse(values)
                return values[: self.n_owned]
            for sweep in reversed(self.sweeps()):
                if not sweep.to_self:
                    ghost_rows(values, sweep.offsets, sweep.counts, sweep.back)
                    sweep.backward.run()
                add_sweep(
                    values, sweep.index, sweep.starts, sweep.out, sweep.offsets, sweep.to_self
                )
            return values[: self.n_owned]
        for swap in reversed(self.swaps):
            part = values[swap.offset : swap.offset + swap.count]
            if swap.dest == self.rank:
                add_rows(values, swap.send, part)
                continue
            buffer = self._buffer(len(swap.send), values.shape[1])
            self.ranks.exchange(part, swap.source, buffer, swap.dest, 16 + swap.tag)
            add_rows(values, swap.send, buffer)
        return values[: self.n_owned]

    def reserve(self, state: State, carried: dict) -> None:
        """Give ``state``'s per-atom arrays, and those ``carried`` (name -> an array shaped
        like it), their room for migrations now (:meth:`md.distributed.migration.RowStore.
        reserve`): the first migration of a run then pays no page faults."""
        self.rows.reserve(state, carried)

    def _build_memory(self, n: int) -> tuple:
        """A build's kept memory for ``n`` owned atoms, in one call (where it fits; else
        grown by the calls it stands for): the local system's positions, ids and types
        (this build's parity, :meth:`_local_rows`; ids and types as long as the
        positions), the owned atoms' fractions (``home``, n x 3) and images (n x 4), the
        ghosts' fractions (the rest of the positions' rows), the sweeps' whole rows
        (:meth:`_held`) and this build's swap tables (:meth:`_swap_tables`)."""
        parity, local, buffers = self._parity, self._local, self._buffers
        pair = local.get("positions")
        positions = None if pair is None else pair[parity]
        if positions is None or positions.shape[0] < n + n // 2 + 64:
            positions = self._local_rows("positions", n + n // 2 + 64, (3,), np.float64)
        size = positions.shape[0]
        found = [positions]
        for name, dtype in (("ids", np.int64), ("types", np.int32)):
            pair = local.get(name)
            held = None if pair is None else pair[parity]
            if held is None or held.shape[0] < size:
                held = self._local_rows(name, size, (), dtype)
            found.append(held)
        for name, rows, k, dtype in (
            ("home", n, 3, np.float64),
            ("images", n, 4, np.int64),
            ("ghost fractions", size - n, 3, np.float64),
        ):
            held = buffers.get((name, k))
            found.append(
                held[:rows]
                if held is not None and held.shape[0] >= rows
                else self._buffer(rows, k, name, dtype)
            )
        held = buffers.get(("sweep rows", 8))
        found.append(held if held is not None else self._held("sweep rows", 8))
        tables = self._tables[parity]
        found.append(tables if tables is not None else self._swap_tables())
        return tuple(found)

    def _local_rows(self, name: str, n: int, tail: tuple, dtype) -> NDArray:
        """An array of at least n rows (of shape ``tail``) for the local system's ``name``:
        one of two kept under it, alternating from build to build (the local system of
        the last build is still in use while this one is laid out)."""
        pair = self._local.setdefault(name, [None, None])
        held = pair[self._parity]
        if held is None or held.shape[0] < n:
            held = np.empty((n + n // 8, *tail), dtype=dtype)
            pair[self._parity] = held
            other = pair[1 - self._parity]
            if other is None or other.shape[0] < n:
                # The next build's array now, its pages mapped (written): the first build
                # is a run's set-up, the next one is inside its loop, where a 10^6-atom
                # rank's fresh arrays took their page faults at the first rebuild.
                other = np.empty_like(held)
                other.fill(0)
                pair[1 - self._parity] = other
        return held

    def _held(self, name: str, k: int) -> NDArray:
        """The whole array :meth:`_buffer` keeps under (name, k) (64 rows if none yet)."""
        held = self._buffers.get((name, k))
        return held if held is not None else self._buffer(64, k, name)

    def _buffer(self, n: int, k: int, name: str = "message", dtype=np.float64) -> NDArray:
        """n rows of k values from memory this Domain keeps under (name, k): a fresh 10^8-byte
        array costs its page faults (~0.1 s) at every build."""
        held = self._buffers.get((name, k))
        if held is None or held.shape[0] < n:
            held = np.empty((n + n // 4 + 16, k), dtype=dtype)
            self._buffers[(name, k)] = held
        return held[:n]


def _grown(values: NDArray, count: int, size: int) -> NDArray:
    """A fresh array of ``size`` rows shaped and typed as ``values``, its first ``count``
    rows copied from ``values``."""
    grown = np.empty((size, *values.shape[1:]), dtype=values.dtype)
    grown[:count] = values[:count]
    return grown
