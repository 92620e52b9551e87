"""One system over several MPI ranks: spatial domain decomposition (mpi4py).

The cell is cut into one brick per rank (:mod:`md.domain`). Each rank *owns*
the atoms in its brick and keeps *ghost* copies of the atoms within the reach
of it (the neighbour-list radius, cutoff + skin, or more where bonds are
longer), periodic images included. Ghosts are found as LAMMPS's brick
communication finds them: three sweeps, along a, b and c, each sending to the
two face neighbours the atoms (owned, and ghosts from the earlier sweeps)
within the reach of their faces, shifted by a cell vector across a periodic
boundary; a single brick along an axis sends to itself.

A rank's owned atoms followed by its ghosts form an ordinary system, open
along the cut axes (images explicit) and periodic along the others whose cell
vector has no component along a cut axis (no ghosts there: the cell list
finds those images as a single process does,
:func:`md.domain.local_periodic_axes`), which the rank evaluates with an ordinary
:class:`md.forcefield.ForceField` (threaded kernels and all). Its neighbour
list keeps only the pairs whose designated atom it owns (the lower id when the
ids' sum is even, the higher when odd: :meth:`md.neighbors.NeighborList.keep_owned`,
which splits the pairs across each face about evenly), so every pair
is evaluated once in the whole run and pairs of two ghosts not at all; each
bond (angle) is evaluated by the owner of its first atom (vertex), with its
partners' nearest copies. The forces on ghosts then go back to their owners
along the reverse of the sweeps (newton on, in LAMMPS's terms), and the
energy and virial are plain sums over the ranks.

Per force evaluation: the owned positions are written into the local system
(each at its image nearest the brick), ghost positions are sent along the
sweeps (6 messages), the local forces are computed, the ghosts' forces are
sent back (6 messages), and one reduction sums the energy and virial and
tells every rank whether any failed. The list is rebuilt when the largest
move of any atom since the last build exceeds skin/2 (a global maximum; a
cell deformation is allowed for as :class:`md.neighbors.NeighborList` does).
Atoms migrate to the rank whose brick holds them at rebuilds taken between
steps: :class:`DistributedSimulation` rebuilds at the start of a step when
some atom's coming move could take it past the limit (each atom's next move
bounded from its last two, :func:`md.domain.moved_since`), and lays the
ghosts and the list out where the step is expected to take the atoms
(dt v + dt^2 a / 2), so that its lists last as many steps as one process's;
a rebuild forced inside a step (by an integrator's stage, or a move the
look-ahead missed) keeps the owners and widens the ghost shell by as far as
owned atoms have left their bricks, and the next step migrates them. A
migration changes only the rows that move (arrivals take the leavers' rows),
so a rank's atom order follows its history (checkpoints record it); the ghost
search runs on compiled passes over a table the Domain keeps between builds
(``md.domain``).

Reductions add in rank order on every rank (an all-gather, then a sum), so
all ranks hold the same bits and a run on P ranks is deterministic; runs on
different P agree to round-off (the force sums' order differs). Langevin's
noise is keyed by atom id and step, so it does not depend on P at all.

Nothing here runs, and mpi4py is not imported, unless a launcher started
more than one process (:func:`mpi_ranks`).
"""

from __future__ import annotations

import copy
import logging
import math
import os
import time
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from integrators.base import constraints_of
from md._files import OutputBusyError
from md.box import (
    cell_matrix,
    minimum_image,
    periodic_lengths,
    periodic_tilt,
    perpendicular_widths,
)
from md.domain import (
    Grid,
    add_rows,
    anchored_items,
    append_rows,
    balanced_cuts,
    brick_of,
    check_grid,
    choose_grid,
    fractional_coordinates,
    home_layout,
    home_positions,
    leaving_along,
    local_periodic_axes,
    moved_since,
    near_faces,
    nearest_copies,
    pack_rows,
    predicted_positions,
    refill_plan,
    refill_rows,
    shift_rows,
    table_rows,
)
from md.errors import (
    AngleCollapseError,
    CheckpointError,
    ConfigError,
    ConvergenceError,
    DecompositionError,
    NonFiniteError,
    SimulationError,
    TrajectoryError,
)
from md.forcefield import ForceField
from md.minimize import minimize
from md.neighbors import largest_displacement2
from md.parallel import (
    chunk_count,
    copy_into,
    global_max,
    global_sum,
    same_values,
    using_reductions,
)
from md.simulation import Simulation
from md.state import State
from md.topology import Topology
from potentials.base import Bonded, BondedAngles, ForceResult
from potentials.springs import BondStretchError

logger = logging.getLogger(__name__)

#: Environment variables in which launchers give the number of processes they started
#: (MPICH's and Intel MPI's hydra, Slurm's srun with PMI, Open MPI).
SIZE_VARIABLES = ("PMI_SIZE", "OMPI_COMM_WORLD_SIZE", "SLURM_STEP_NUM_TASKS")
#: A step starts with a rebuild (and migration) when some atom's next move could take it
#: past the list's limit (``md.domain.moved_since`` bounds each atom's next move from its
#: last two) with this many times the last step's largest move to spare.
LOOKAHEAD = 0.05
#: Ghost shell beyond the longest bond, in skins: the bonds of the last build may
#: stretch by a skin before the next, plus the slack of a rebuild forced inside a step.
BOND_SKINS = 2.5
#: Fewest atoms per thread worth a chunk of their own in the displacement pass.
_MIN_PASS_ATOMS = 16_000
#: The identity, for a cell that has not changed since the build.
_IDENTITY = np.eye(3)
#: No positions: no step start before the last one is known.
_NONE = np.empty((0, 3))
_NO_ROWS = np.empty((0, 3))  # (never written: a copy into no rows)
#: Stop requests as numbers, for the reduction that makes every rank see them.
_STOPS = {"SIGINT": 1.0, "SIGTERM": 2.0}


def launched_ranks() -> int:
    """How many processes the MPI launcher started this one among (1 without a launcher)."""
    for name in SIZE_VARIABLES:
        value = os.environ.get(name)
        if value:
            try:
                return max(1, int(value))
            except ValueError:
                continue
    return 1


def _in_rank_order(gathered: NDArray[np.float64]) -> NDArray[np.float64]:
    """The rows of ``gathered`` (one per rank) added in rank order."""
    total = gathered[0].copy()
    for rank in range(1, gathered.shape[0]):
        total += gathered[rank]
    return total


def ranks_per_node(ranks) -> int:
    """Ranks the launcher started on this node (they share its cores), else all of them."""
    for name in ("MPI_LOCALNRANKS", "OMPI_COMM_WORLD_LOCAL_SIZE", "SLURM_NTASKS_PER_NODE"):
        value = os.environ.get(name, "")
        if value.isdigit() and int(value) > 0:
            return int(value)
    return ranks.n_ranks


def launch_rank() -> int:
    """This process's rank as the launcher's environment gives it (0 without a launcher);
    readable before MPI starts, for deciding who prints."""
    for name in ("PMI_RANK", "OMPI_COMM_WORLD_RANK", "SLURM_PROCID"):
        value = os.environ.get(name, "")
        if value.isdigit():
            return int(value) if launched_ranks() > 1 else 0
    return 0


def on_root(ranks, value_of):
    """``value_of()`` as rank 0 computes it, on every rank (only rank 0 calls it); just
    ``value_of()`` without ranks."""
    if ranks is None:
        return value_of()
    return ranks.broadcast(value_of() if ranks.rank == 0 else None)


def mpi_ranks() -> MPIRanks | None:
    """The ranks of this run when a launcher started several processes, else None.

    Imports mpi4py only then: with one process (no launcher, or ``mpiexec -n
    1``) nothing changes and nothing is imported.

    Raises
    ------
    RuntimeError
        If a launcher started several processes but mpi4py is not installed.
    """
    if launched_ranks() <= 1:
        return None
    try:
        from mpi4py import MPI  # heavy optional dependency: only decomposed runs load MPI
    except ImportError:
        raise RuntimeError(
            f"this process is one of {launched_ranks()} that an MPI launcher started, but "
            "mpi4py is not installed, so they cannot share one system: pip install "
            "'leapmd[mpi]' (or run without mpiexec)"
        ) from None
    comm = MPI.COMM_WORLD
    return MPIRanks(comm) if comm.Get_size() > 1 else None


class CommClock:
    """Wall time spent communicating [s]: every collective call, message and its packing
    runs inside ``with clock:``; a section inside another counts once.

    Examples
    --------
    >>> clock = CommClock()
    >>> with clock:
    ...     with clock:  # nested: not counted twice
    ...         pass
    >>> clock.seconds >= 0.0
    True
    """

    def __init__(self) -> None:
        self.seconds = 0.0
        self._depth = 0
        self._start = 0.0

    def __enter__(self) -> CommClock:
        if self._depth == 0:
            self._start = time.perf_counter()
        self._depth += 1
        return self

    def __exit__(self, *exc) -> None:
        self._depth -= 1
        if self._depth == 0:
            self.seconds += time.perf_counter() - self._start


class MPIRanks:
    """An MPI communicator as a decomposed run uses it (an :class:`md.parallel.Reductions`).

    Sums are all-gathered and added in rank order, so every rank holds the
    same bits; maxima use MPI's reduction (exact in any order). Every call is
    timed on ``clock`` (a :class:`CommClock`), which the run's summary reports
    as its "comm" section.
    """

    def __init__(self, comm) -> None:
        from mpi4py import MPI  # heavy optional dependency: only decomposed runs load MPI

        self.comm = comm
        self.rank = comm.Get_rank()
        self.n_ranks = comm.Get_size()
        self.clock = CommClock()
        self._max = MPI.MAX
        self._double = MPI.DOUBLE

    def sum(self, values: NDArray[np.float64]) -> NDArray[np.float64]:
        with self.clock:
            return _in_rank_order(self.gather_values(values))

    def gather_values(self, values: NDArray[np.float64]) -> NDArray[np.float64]:
        """Every rank's ``values`` (k,), as a (P, k) array on every rank."""
        with self.clock:
            values = np.ascontiguousarray(values, dtype=np.float64).ravel()
            gathered = np.empty((self.n_ranks, values.size))
            self.comm.Allgather(values, gathered)
            return gathered

    def max(self, values: NDArray[np.float64]) -> NDArray[np.float64]:
        with self.clock:
            values = np.ascontiguousarray(values, dtype=np.float64).ravel()
            out = np.empty_like(values)
            self.comm.Allreduce(values, out, op=self._max)
            return out

    def exchange(self, send, dest: int, receive, source: int, tag: int) -> None:
        """Send ``send`` to ``dest`` while receiving ``receive`` from ``source``."""
        with self.clock:
            self.comm.Sendrecv(send, dest, tag, receive, source, tag)

    def exchange_rows(self, rows, dest: int, source: int, tag: int) -> NDArray[np.float64]:
        """Send the rows of an (n, k) float64 array to ``dest``; return those from ``source``."""
        with self.clock:
            count = np.array([rows.shape[0]], dtype=np.int64)
            incoming = np.empty(1, dtype=np.int64)
            self.comm.Sendrecv(count, dest, tag, incoming, source, tag)
            received = np.empty((int(incoming[0]), rows.shape[1]))
            self.comm.Sendrecv(np.ascontiguousarray(rows), dest, tag, received, source, tag)
            return received

    def all_objects(self, value) -> list:
        """Every rank's ``value`` (picklable), in rank order."""
        with self.clock:
            return self.comm.allgather(value)

    def broadcast(self, value, root: int = 0):
        """Rank ``root``'s ``value`` on every rank."""
        with self.clock:
            return self.comm.bcast(value, root=root)

    def gather_rows(self, rows) -> NDArray[np.float64] | None:
        """On rank 0, every rank's rows (n_r, k) stacked in rank order; None elsewhere."""
        with self.clock:
            rows = np.ascontiguousarray(rows, dtype=np.float64)
            width = rows.shape[1]
            counts = self.comm.gather(rows.size, root=0)
            if self.rank != 0:
                self.comm.Gatherv(rows, None, root=0)
                return None
            out = np.empty((sum(counts) // width if width else 0, width))
            displacements = np.concatenate([[0], np.cumsum(counts[:-1])]).astype(np.int64)
            self.comm.Gatherv(rows, [out, counts, displacements, self._double], root=0)
            return out

    def abort(self, code: int = 1) -> None:
        """End every rank at once (for an error one rank cannot share with the others)."""
        self.comm.Abort(code)


# ------------------------------------------------------------------ agreement
def agree(ranks, error: BaseException | None) -> None:
    """Raise on every rank the error of the lowest rank that has one (a collective call).

    That rank raises its error as it is; the others raise one of the same
    family (:class:`SimulationError`, :class:`ConvergenceError`, the
    :class:`NonFiniteError` kinds, ``OSError``, else ``RuntimeError``) with
    the same message, so every rank reports the same failure and none is left
    waiting for the others.
    """
    report = None if error is None else (_family(error), str(error), getattr(error, "step", 0))
    for rank, got in enumerate(ranks.all_objects(report)):
        if got is None:
            continue
        if rank == ranks.rank:
            raise error
        raise _rebuilt(*got)


def _family(error: BaseException) -> str:
    for name, kind in _FAMILIES:
        if isinstance(error, kind):
            return name
    return "runtime"


_FAMILIES = (
    ("simulation", SimulationError),
    ("convergence", ConvergenceError),
    ("decomposition", DecompositionError),
    ("nonfinite", NonFiniteError),
    ("config", ConfigError),
    ("checkpoint", CheckpointError),
    ("trajectory", TrajectoryError),
    ("busy", OutputBusyError),
    ("os", OSError),
)


def _rebuilt(family: str, message: str, step: int) -> BaseException:
    """An error of ``family`` whose text is ``message`` (SimulationError and ConvergenceError
    prefix theirs with the step; here the message already has it)."""
    if family == "simulation":
        error = SimulationError(step, "")
    elif family == "convergence":
        error = ConvergenceError(step, math.nan, message)
    else:
        return dict(_FAMILIES).get(family, RuntimeError)(message)
    error.args = (message,)
    return error


# ------------------------------------------------------------------- the domain
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
        self.imaged = np.zeros(0, dtype=np.int64)  # owned atoms away from their stored image
        self.images = np.zeros((0, 3), dtype=np.int64)  # and their images (rows of imaged)
        self.local_pbc = np.zeros(3, dtype=bool)
        self._built_tilt = b""
        self.local_state: State | None = None
        self.local_ids = np.zeros(0, dtype=np.int64)
        self._buffers: dict[object, NDArray] = {}
        self._stores: dict[object, NDArray] = {}
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

    def fractions(self, state: State) -> NDArray[np.float64]:
        """(N, 3) coordinates of ``state``'s atoms along the cell vectors (unwrapped)."""
        out = np.empty((state.n_atoms, 3))
        fractional_coordinates(state.positions, state.box, periodic_tilt(state.tilt, state.pbc),
                               state.pbc, out)  # fmt: skip
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
        bricks hold them, in one sweep per cut axis; ``state``'s arrays are replaced by
        views of arrays this Domain keeps. Collective.

        The carried arrays named in ``spent`` are the caller's to give away: each moves
        in the memory of the array it is the first rows of (a force evaluation's local
        result, owned rows then ghosts), where that has room, rather than being copied
        into memory of this Domain's first (a 10^6-atom rank's forces: 3 ms a migration).

        Each sweep changes only the rows that move (:func:`md.domain.refill_plan`):
        arriving atoms fill the rows of the leaving ones, and staying atoms past the new
        end fill what is left. A rank's atom order is so a function of its run's history
        (deterministic on any P; a checkpoint records it, see :meth:`DistributedSimulation.
        global_view`), not sorted by id: a sorted merge rewrote every row of every array
        (a 10^6-atom rank: 30 ms of a 50 ms migration on the Emerald Rapids VM).

        Raises
        ------
        DecompositionError
            On every rank, if an atom moved more than one brick along an axis
            since the last migration.
        """
        names = list(carried)
        # The state's per-atom arrays, then the carried ones: only the atoms that leave
        # are packed into rows of floats (integers are exact below 2^53).
        arrays = [state.positions, state.velocities, state.masses, state.types, state.ids]
        arrays += [np.asarray(carried[name]) for name in names]
        keys = [("state", k) for k in range(5)] + [("carried", name) for name in names]
        n = state.n_atoms
        lost = 0
        tilt = periodic_tilt(state.tilt, state.pbc)
        shape = self.shape
        for axis in range(3):
            if self.grid.shape[axis] == 1:
                continue
            ups, downs, far = leaving_along(arrays[0], state.box, tilt, state.pbc, shape,
                                            self.cuts, axis, self.coordinates[axis])  # fmt: skip
            lost += far
            upper = self.grid.neighbor(self.rank, axis, 1)
            lower = self.grid.neighbor(self.rank, axis, -1)
            from_lower = self.ranks.exchange_rows(_packed(arrays, ups), upper, lower, 2 * axis)
            from_upper = self.ranks.exchange_rows(_packed(arrays, downs), lower, upper,
                                                  2 * axis + 1)  # fmt: skip
            if len(ups) + len(downs) + len(from_lower) + len(from_upper) == 0:
                continue
            incoming = _unpacked(np.concatenate([from_lower, from_upper]), arrays)
            leaving = np.sort(np.concatenate([ups, downs]))
            m = len(incoming[0])
            plan = refill_plan(leaving, n, m)
            size = n - len(leaving) + m
            arrays = [self._refilled(key, a, n, size, b, plan,
                                    key[0] == "carried" and key[1] in spent)
                      for key, a, b in zip(keys, arrays, incoming, strict=True)]  # fmt: skip
            n = size
        state.positions, state.velocities, state.masses, state.types, state.ids = arrays[:5]
        carried = dict(zip(names, arrays[5:], strict=True))
        if global_sum(lost, self.ranks):
            raise DecompositionError(
                "an atom moved more than a brick between two neighbour-list builds; the "
                "dynamics is blowing up (time step too large?)"
            )
        return carried

    def _refilled(self, key, values: NDArray, n: int, size: int, incoming: NDArray,
                  plan, spent: bool = False) -> NDArray:  # fmt: skip
        """``values`` (n rows) after a sweep's :func:`md.domain.refill_plan`: ``size`` rows of
        the array kept under ``key``, changed in place where ``values`` already is its
        first rows (the usual case), else copied into it first; if ``values`` is
        ``spent``, the array it is the first rows of, changed in place, where that has
        the room."""
        store = _room_of(values, size) if spent else None
        if store is None:
            store = self._store(key, values, n, size)
        width = math.prod(values.shape[1:])
        sources, targets, arrivals = plan
        refill_rows(store.reshape(len(store), width), sources, targets,
                    np.ascontiguousarray(incoming).reshape(-1, width), arrivals)  # fmt: skip
        return store[:size]

    def _store(self, key, values: NDArray, n: int, size: int) -> NDArray:
        """The array kept under ``key`` for ``values``' rows, holding them in its first ``n``
        rows and room for ``size``: ``values``' own memory when it is that array's
        beginning, else a copy (into a larger array when it needs room; the room is an
        eighth more, so that a rank's count can grow for several migrations)."""
        store = self._stores.get(key)
        fits = (store is not None and store.dtype == values.dtype
                and store.shape[1:] == values.shape[1:]
                and store.shape[0] >= max(n, size))  # fmt: skip
        if fits and n and values.ctypes.data == store.ctypes.data and values.base is store:
            return store  # values are its first rows: changed in place
        if not fits:
            rows = max(n, size)
            store = np.empty((rows + rows // 8 + 16, *values.shape[1:]), dtype=values.dtype)
            self._stores[key] = store
        store[:n] = values[:n]
        return store

    # -------------------------------------------------------------------- ghosts
    def build(self, state: State, reach: float) -> None:
        """Find the ghosts within ``reach`` of the brick (widened by as far as owned atoms
        have strayed from it) and lay out the local system. Collective.

        The ghost search (from the reduction of the strays on: the faces' atoms, their
        packing and messages) runs on the ranks' clock, the communication section; the
        layout of the owned atoms before it (their images nearest the brick, copied into
        the local system) does not, as LAMMPS's Comm leaves out its ``Domain::pbc``.

        Raises
        ------
        DecompositionError
            On every rank, if owned atoms strayed so far that the ghost shell
            would need atoms from beyond the face neighbours.
        """
        box, pbc = state.box, state.pbc
        tilt = periodic_tilt(state.tilt, pbc)
        cell = cell_matrix(box, tilt)
        widths = perpendicular_widths(box, tilt)
        # The local system is written where it will stay: the owned atoms first, at their
        # images nearest the brick (a copy; only the atoms with an image of their own are
        # shifted), then each sweep's ghosts appended (the arrays grow by half when full),
        # their fractional coordinates kept beside them for the later sweeps. Sweeps send
        # rows of position (3), fractional position (3), id and type.
        n = state.n_atoms
        self._parity ^= 1  # the local arrays of the build before this one stay as they are
        positions = self._local_rows("positions", n + n // 2 + 64, (3,), np.float64)
        home = self._buffer(n, 3, "home")
        self.imaged, self.images, strayed = home_layout(
            state.positions, box, tilt, pbc, cell, self.center, self.bounds, widths, home,
            positions[:n], self._buffer(n, 3, "images", np.int64),
        )  # fmt: skip
        self._local_rows("ids", len(positions), (), np.int64)[:n] = state.ids
        self._local_rows("types", len(positions), (), np.int32)[:n] = state.types
        with self.ranks.clock:
            self._find_ghosts(state, reach, strayed, positions, home, n)

    def _find_ghosts(self, state: State, reach: float, strayed: float, positions, home,
                     n: int) -> None:  # fmt: skip
        """:meth:`build`'s ghost search and the local system's state, after the owned
        atoms' layout (``positions``' first ``n`` rows, their fractions ``home``)."""
        box, pbc = state.box, state.pbc
        tilt = periodic_tilt(state.tilt, pbc)
        cell = cell_matrix(box, tilt)
        widths = perpendicular_widths(box, tilt)
        margin = global_max(strayed, self.ranks)
        shell = reach + margin
        brick = widths * self.grid.thinnest()
        narrow = pbc & (brick < shell + margin)
        if np.any(narrow):
            axis = int(np.argmax(narrow))
            raise DecompositionError(
                f"owned atoms strayed up to {margin:.3g} from their bricks inside a step, so "
                f"the ghost shell would have to reach {shell + margin:.4g} across "
                f"{'xyz'[axis]}, more than a brick ({brick[axis]:.4g}); use fewer ranks or a "
                "smaller time step"
            )
        ids = self._local["ids"][self._parity]  # (their owned rows written by build)
        types = self._local["types"][self._parity]
        ghost_fractions = self._buffer(len(positions) - n, 3, "ghost fractions")
        count = n
        swaps: list[_Swap] = []
        local_pbc = local_periodic_axes(self.shape, pbc, tilt)
        for axis in range(3):
            if not pbc[axis] or local_pbc[axis]:
                continue
            p, c = self.grid.shape[axis], self.coordinates[axis]
            reach_fraction = shell / widths[axis]
            # this sweep sends the atoms before its own ghosts, in local order
            faces = (self.bounds[0, axis] + reach_fraction, self.bounds[1, axis] - reach_fraction)
            lower, upper = near_faces(home, n, axis, *faces)
            if count > n:
                ghost_lower, ghost_upper = near_faces(ghost_fractions, count - n, axis, *faces)
                lower = np.concatenate([lower, ghost_lower + n])
                upper = np.concatenate([upper, ghost_upper + n])
            down = self.grid.neighbor(self.rank, axis, -1)
            up = self.grid.neighbor(self.rank, axis, 1)
            for send, shift, dest, source in (
                (lower, 1 if c == 0 else 0, down, up),
                (upper, -1 if c == p - 1 else 0, up, down),
            ):
                rows = np.empty((len(send), 8))
                table_rows(positions, home, ghost_fractions, ids, types, n, send, rows)
                rows[:, :3] += shift * cell[axis]
                rows[:, 3 + axis] += shift
                tag = len(swaps)
                if dest != self.rank:
                    rows = self.ranks.exchange_rows(rows, dest, source, tag)
                if count + len(rows) > len(positions):
                    size = count + len(rows) + len(positions) // 2
                    positions, ids, types = (_grown(a, count, size) for a in (positions, ids,
                                                                               types))  # fmt: skip
                    for name, grown in (("positions", positions), ("ids", ids), ("types", types)):
                        self._local[name][self._parity] = grown  # kept for the next builds
                    old = ghost_fractions
                    ghost_fractions = self._buffer(size - n, 3, "ghost fractions")
                    ghost_fractions[: count - n] = old[: count - n]
                append_rows(rows, count, n, positions, ghost_fractions, ids, types)
                swaps.append(_Swap(send, axis, shift, dest, source, count, len(rows), tag))
                count += len(rows)
        self.swaps = swaps
        self.n_owned = n
        self.reach, self.margin = reach, margin
        self.local_ids = ids[:count]
        self.local_pbc = local_pbc
        self._built_tilt = state.tilt.tobytes()
        self.local_state = State.adopting(positions[:count], types[:count], box, local_pbc,
                                          state.type_names)  # fmt: skip
        # (the local arrays live in memory kept between builds: a fresh 10^6-atom layout
        # paid its page faults at every build, 5-10 ms on the Emerald Rapids VM)
        self.local_state.tilt = periodic_tilt(tilt, local_pbc)

    def layout_holds(self, state: State) -> bool:
        """Whether the last build's periodic axes still suit ``state``'s cell (a barostat
        that tilts the cell towards a cut axis needs a build with explicit images)."""
        if not self.local_pbc.any() or state.tilt.tobytes() == self._built_tilt:
            return True  # (checked at every force call: the cheap answers first)
        tilt = periodic_tilt(state.tilt, state.pbc)
        return bool(np.all(local_periodic_axes(self.shape, state.pbc, tilt) | ~self.local_pbc))

    def owned_rows(self, state: State) -> NDArray[np.float64]:
        """The local system's rows of ``state``'s owned atoms, to copy their positions into
        (then :meth:`update` with ``copied``); no rows if the layout is not ``state``'s."""
        if self.local_state is None or self.n_owned != state.n_atoms:
            return _NO_ROWS
        return self.local_state.positions[: self.n_owned]

    def update(self, state: State, copied: bool = False) -> None:
        """Write the owned positions into the local system (only the few at another image
        if they were ``copied`` there already, see :meth:`owned_rows`) and send the ghosts'
        (collective). The sweeps (packing and messages) run on the ranks' clock, the owned
        rows' copy before them does not (as :meth:`build`'s layout)."""
        tilt = periodic_tilt(state.tilt, state.pbc)
        cell = cell_matrix(state.box, tilt)
        if self.local_pbc.any():  # the cell the local system's own images follow
            self.local_state.box[:] = state.box
            self.local_state.tilt[:] = periodic_tilt(tilt, self.local_pbc)
        positions = self.local_state.positions
        owned = positions[: self.n_owned]
        if copied:
            shift_rows(state.positions, self.imaged, self.images, cell, owned)
        else:
            home_positions(state.positions, self.imaged, self.images, cell, owned)
        with self.ranks.clock:
            for swap in self.swaps:
                shift = swap.shift * cell[swap.axis]
                target = positions[swap.offset : swap.offset + swap.count]
                if swap.dest == self.rank:
                    pack_rows(positions, swap.send, shift, target)
                    continue
                buffer = self._buffer(len(swap.send), 3)
                pack_rows(positions, swap.send, shift, buffer)
                self.ranks.exchange(buffer, swap.dest, target, swap.source, swap.tag)

    def reverse(self, values: NDArray[np.float64]) -> NDArray[np.float64]:
        """Add the ghosts' rows of ``values`` (n_local, k; C order) into their owners' rows
        along the reverse of the sweeps; return the owned rows (a view). Collective."""
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
        """Give ``state``'s per-atom arrays their room for migrations now (a copy into the
        arrays this Domain keeps; ``state``'s arrays become views of them), and map the
        memory of the ``carried`` ones (name -> an array shaped like it), so that the first
        migration of a run does not pay their page faults (1M atoms on the Emerald Rapids
        VM: 0.108 s for the first migration, 0.040 s for later ones)."""
        n = state.n_atoms
        arrays = [state.positions, state.velocities, state.masses, state.types, state.ids]
        kept = [self._store(("state", k), a, n, n)[:n] for k, a in enumerate(arrays)]
        state.positions, state.velocities, state.masses, state.types, state.ids = kept
        for name, like in carried.items():
            if ("carried", name) not in self._stores:
                self._store(("carried", name), like, n, n).fill(0)  # written: its pages mapped

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

    def _buffer(self, n: int, k: int, name: str = "message", dtype=np.float64) -> NDArray:
        """n rows of k values from memory this Domain keeps under (name, k): a fresh 10^8-byte
        array costs its page faults (~0.1 s) at every build."""
        held = self._buffers.get((name, k))
        if held is None or held.shape[0] < n:
            held = np.empty((n + n // 4 + 16, k), dtype=dtype)
            self._buffers[(name, k)] = held
        return held[:n]


def _room_of(values: NDArray, size: int) -> NDArray | None:
    """The C-contiguous array whose first rows ``values`` are (itself, or the array it is
    a view of), if that has at least ``size`` rows; else None."""
    root = values if values.base is None else values.base
    if (not isinstance(root, np.ndarray) or root.base is not None
            or not root.flags.c_contiguous or not values.flags.c_contiguous
            or root.dtype != values.dtype or root.shape[1:] != values.shape[1:]
            or root.ctypes.data != values.ctypes.data or root.shape[0] < size):  # fmt: skip
        return None
    return root


def _grown(values: NDArray, count: int, size: int) -> NDArray:
    """A fresh array of ``size`` rows shaped and typed as ``values``, its first ``count``
    rows copied from ``values``."""
    grown = np.empty((size, *values.shape[1:]), dtype=values.dtype)
    grown[:count] = values[:count]
    return grown


def _packed(arrays, rows: NDArray[np.int64]) -> NDArray[np.float64]:
    """Rows ``rows`` of the per-atom ``arrays`` side by side, as floats (integers are exact
    below 2^53): one row per atom that leaves."""
    widths = [math.prod(a.shape[1:]) for a in arrays]
    out = np.empty((len(rows), sum(widths)))
    start = 0
    for a, width in zip(arrays, widths, strict=True):
        out[:, start : start + width] = a[rows].reshape(len(rows), width)
        start += width
    return out


def _unpacked(rows: NDArray[np.float64], like) -> list[NDArray]:
    """:func:`_packed`'s rows back as arrays of the shapes and types of ``like``."""
    out, start = [], 0
    for a in like:
        size = math.prod(a.shape[1:])
        part = rows[:, start : start + size].reshape((-1, *a.shape[1:]))
        out.append(part.astype(a.dtype))
        start += size
    return out


# ---------------------------------------------------------------- force field
@dataclass
class _Bonded:
    """A bonded potential's items indexed by their anchor atom's id (a bond's first atom,
    an angle's vertex), and the items this rank evaluated at the last build."""

    index: int  # in the force field's list
    items: NDArray[np.int64]  # (B, 2) bonds or (A, 3) angles, global ids
    types: NDArray[np.int64]
    anchor: int  # column of the anchor atom
    order: NDArray[np.int64]  # items sorted by anchor id
    starts: NDArray[np.int64]  # CSR offsets into order, by anchor id
    local: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, dtype=np.int64))


def _index_bonded(index: int, potential) -> _Bonded | None:
    """A bonded potential's items by anchor (None for a potential that lists no atoms)."""
    if isinstance(potential, Bonded):
        items, types, anchor = potential.bonds, potential.bond_types, 0
    elif isinstance(potential, BondedAngles):
        items, types, anchor = potential.angles, potential.angle_types, 1
    else:
        return None
    items = np.asarray(items, dtype=np.int64)
    order = np.argsort(items[:, anchor], kind="stable")
    n_ids = int(items.max()) + 2 if len(items) else 1
    starts = np.searchsorted(items[order, anchor], np.arange(n_ids)).astype(np.int64)
    return _Bonded(index, items, np.asarray(types, dtype=np.int64), anchor, order, starts)


def longest_arm(potentials, state: State) -> float:
    """The longest bond, or angle arm from its vertex, of ``potentials`` in ``state``
    (minimum image; 0 without bonds) [length]."""
    longest = 0.0
    for potential in potentials:
        bonded = _index_bonded(0, potential)
        if bonded is None or not len(bonded.items):
            continue
        anchors = bonded.items[:, bonded.anchor]
        for column in range(bonded.items.shape[1]):
            if column == bonded.anchor:
                continue
            d = state.positions[bonded.items[:, column]] - state.positions[anchors]
            d = minimum_image(d, state.box, state.pbc, state.tilt)
            longest = max(longest, float(np.sqrt((d * d).sum(axis=1)).max()))
    return longest


class DistributedForceField:
    """The force field of one rank of a decomposed run (the interface of ForceField).

    ``compute(state)`` takes this rank's owned atoms (``state.ids``: their
    global ids) and returns their forces, with the energy and virial of the
    whole system; results are cached while the owned positions and the cell
    stay the same. It is collective: every rank calls it at the same point.

    Parameters
    ----------
    potentials : sequence of Potential
        The whole system's potentials (bonded ones over global atom ids).
    skin : float
        Neighbour-list skin [length].
    ranks : MPIRanks
    grid : Grid
    bond_reach : float
        The longest bond (or angle arm) of the starting state [length].
    precision : {"double", "mixed"}
        Of the local force field's pair loops (see :class:`md.forcefield.ForceField`).

    Attributes
    ----------
    local : ForceField
        The force field of the rank's local system (owned atoms and ghosts);
        its neighbour list is ``neighbor_list``.
    timings : dict
        Seconds in ``"neighbor"`` (the list's checks and rebuilds, bonded items
        found) and ``"force"`` (the local kernels). The time spent
        communicating (ghost positions out and forces back, migration, the
        ghost search's messages, reductions) is not in them: it is
        ``ranks.clock.seconds``, as its own section.
    migrate_pending : bool
        The last build kept owners (it was forced inside a step): the next
        step start migrates.
    balance_every, balance_threshold
        Dynamic load balancing (off where ``balance_every`` is 0): at the first
        migration ``balance_every`` steps or more after the last check, the ranks
        share their busy seconds since then (wall time less the time they spent
        communicating, waits included); where the busiest rank's exceed the mean
        by more than the factor ``balance_threshold``, the planes between bricks
        move towards an even share (:func:`md.domain.balanced_cuts`, per cut
        axis), and the migration takes the atoms to their new bricks.
    imbalance, balances
        The busiest rank's busy seconds over the mean at the last check; how many
        checks moved the planes.
    """

    def __init__(self, potentials, skin: float, ranks, grid: Grid, bond_reach: float,
                 precision: str = "double", balance_every: int = 0,
                 balance_threshold: float = 1.05) -> None:  # fmt: skip
        self.potentials = list(potentials)
        self.ranks = ranks
        self.skin = float(skin)
        # its results are this object's to keep (cached per owned positions, _cache)
        self.local = ForceField(self.potentials, skin, precision=precision, cache=False)
        self.precision = self.local.precision
        self.neighbor_list = self.local.neighbor_list
        self.domain = Domain(ranks, grid)
        self.timings = {"neighbor": 0.0, "force": 0.0}
        self.n_evaluations = 0
        self.n_subset_evaluations = 0
        self.n_builds = 0
        self.virial_wanted = False
        self.migrate_pending = False
        #: Set by the simulation at each step start: the look-ahead measures from there.
        self.step_start = np.empty((0, 3))
        #: The step start before that (empty when atoms migrated in between).
        self.step_before = np.empty((0, 3))
        #: A stop request of this rank (1 SIGINT, 2 SIGTERM, 3 other), shared at the next
        #: evaluation; ``stop_seen`` and ``ahead`` are the largest over the ranks there.
        self.stop_code = 0.0
        self.stop_seen = 0.0
        self.ahead = 0.0
        indexed = [_index_bonded(i, p) for i, p in enumerate(self.potentials)]
        self._bonded = [b for b in indexed if b is not None]
        self.bond_reach = float(bond_reach)
        self.reference: NDArray[np.float64] | None = None
        self._reference_memory = np.empty((0, 3))  # (reference is a view of its first rows)
        self.reference_cell: tuple | None = None
        self._cell_bytes: tuple = ()
        self._cache: dict = {}
        self._exchanged: tuple | None = None
        if balance_every < 0 or not balance_threshold >= 1.0:
            raise ValueError(f"balance_every must be >= 0 and balance_threshold >= 1, got "
                             f"{balance_every} and {balance_threshold}")  # fmt: skip
        self.balance_every = int(balance_every)
        self.balance_threshold = float(balance_threshold)
        self.imbalance = 1.0
        self.balances = 0
        self._busy_mark: tuple[float, float, int] | None = None  # (wall, comm, step) then

    @property
    def cutoff(self) -> float | None:
        return self.local.cutoff

    @property
    def reach(self) -> float:
        """The ghost shell a build needs: the list radius, or the longest bond plus skins."""
        pairs = self.cutoff + self.skin if self.cutoff is not None else 0.0
        bonds = self.bond_reach + BOND_SKINS * self.skin if self._bonded else 0.0
        return max(pairs, bonds)

    def check(self, state: State) -> None:
        """Nothing to check per rank: the whole system was checked before it was cut."""

    def invalidate(self) -> None:
        """Forget cached results (and which positions the ghosts hold)."""
        self._cache.clear()
        self._exchanged = None

    def topology(self, extra=()) -> Topology:
        """The whole system's bonds and angles (as :meth:`ForceField.topology`)."""
        return ForceField(self.potentials).topology(extra)

    def hessian_operator(self, state: State):
        raise NotImplementedError("second derivatives are not available in a decomposed run")

    def hessian(self, state: State):
        raise NotImplementedError("second derivatives are not available in a decomposed run")

    # ------------------------------------------------------------------ results
    def compute(self, state: State, per_atom: bool = False, virial: bool = True) -> ForceResult:
        """Forces on ``state``'s (owned) atoms; energy and virial of the whole system."""
        return self._result(state, None, per_atom, virial)

    def compute_subset(self, state: State, which, virial: bool = False) -> ForceResult:
        """As :meth:`ForceField.compute_subset`, over the ranks."""
        which = tuple(int(i) for i in which)
        for i in which:
            if not 0 <= i < len(self.potentials):
                raise IndexError(f"potential index {i} out of range "
                                 f"(0..{len(self.potentials) - 1})")  # fmt: skip
        return self._result(state, which, False, virial)

    def _result(self, state: State, which, per_atom: bool, virial: bool) -> ForceResult:
        held = self._cache.get(which)
        usable = False
        if held is not None and _same(held[0], state):
            result = held[1]
            usable = (not per_atom or result.energies is not None) and (
                not virial or result.virial is not None
            )
        # A rank that can use its result does not compare its exchanged positions (a full
        # pass over them each step): "not exchanged" is always safe, it only sends again.
        exchanged = (not usable and self._exchanged is not None
                     and _same(self._exchanged, state))  # fmt: skip
        # Decided together: a rank that owns no atoms sees its (no) positions unchanged
        # while the others' moved, and must still evaluate and exchange with them.
        usable, exchanged = self._all_ranks(usable, exchanged)
        if usable:
            return held[1]
        virial = virial or self.virial_wanted
        result = self._evaluate(state, which, per_atom, virial, exchanged)
        if which is None:
            self.n_evaluations += 1
        else:
            self.n_subset_evaluations += 1
        self._cache[which] = (_key(state, held[0] if held else None), result)
        return result

    def _all_ranks(self, *flags: bool) -> tuple[bool, ...]:
        """Whether each of ``flags`` holds on every rank (one reduction; collective)."""
        failing = self.ranks.max(np.array([0.0 if flag else 1.0 for flag in flags]))
        return tuple(bool(value == 0.0) for value in failing)

    def _evaluate(self, state: State, which, per_atom: bool, virial: bool,
                  exchanged: bool = False) -> ForceResult:  # fmt: skip
        """Exchange, compute, share: one reduction carries the energy and virial, whether a
        rank failed or found its list outrun (then every rank rebuilds and evaluates again),
        and what the next step start needs (the look-ahead, a stop request)."""
        for _ in range(2):
            covered, ahead, finite = self.refresh(state, exchanged)
            exchanged = False  # a rebuild below lays the local system out anew
            start = time.perf_counter()
            error, result = None, None
            try:
                if which is None:
                    result = self.local.compute(self.domain.local_state, per_atom, virial)
                else:
                    result = self.local.compute_subset(self.domain.local_state, which, virial)
            except Exception as caught:  # shared with every rank below
                error = self._global_error(caught)
            middle = time.perf_counter()
            values = np.zeros(15)
            values[0] = error is not None
            if result is not None:
                values[1] = result.energy
                if virial and result.virial is not None:
                    values[2:11] = np.asarray(result.virial).ravel()
            values[11:15] = (not covered, ahead, self.stop_code, not finite)
            gathered = self.ranks.gather_values(values)  # timed on the ranks' clock
            totals, worst = _in_rank_order(gathered[:, :11]), gathered[:, 11:].max(axis=0)
            self.timings["force"] += middle - start
            if worst[3]:
                raise NonFiniteError("particle positions are not finite")
            self.ahead, self.stop_seen = float(worst[1]), float(worst[2])
            if not worst[0]:
                break
            self.rebuild(state, migrate=False)  # some rank's list was outrun: all rebuild
        if totals[0]:
            agree(self.ranks, error)
        with self.ranks.clock:
            # The local result is this evaluation's own (the local force field keeps none):
            # the ghosts' rows are summed into it in place and the owned rows returned as they
            # are (a 10^6-atom rank saves two copies of its forces a step).
            forces = self.domain.reverse(np.asarray(result.forces, dtype=np.float64))
            energies = virials = None
            if per_atom:
                energies = self.domain.reverse(np.array(result.energies)[:, None])[:, 0].copy()
                if result.virials is not None:
                    virials = self.domain.reverse(np.array(result.virials)).copy()
        if not math.isfinite(totals[1]):
            raise NonFiniteError(f"potential energy is {totals[1]}")
        return ForceResult(
            energy=float(totals[1]),
            forces=forces,
            virial=totals[2:11].reshape(3, 3).copy() if virial else None,
            energies=energies,
            virials=virials,
        )

    def _global_error(self, error: Exception) -> Exception:
        """A bonded term's error, naming the whole system's bond (angle) and atoms."""
        ids = self.domain.local_ids
        if isinstance(error, BondStretchError):
            bond = self._global_item(2, error.bond)
            return BondStretchError(bond, int(ids[error.i]), int(ids[error.j]), error.length,
                                    error.r_max)  # fmt: skip
        if isinstance(error, AngleCollapseError):
            angle = self._global_item(3, error.angle)
            return AngleCollapseError(angle, tuple(int(ids[a]) for a in error.atoms))
        return error

    def _global_item(self, width: int, local: int) -> int:
        for bonded in self._bonded:
            if bonded.items.shape[1] == width and local < len(bonded.local):
                return int(bonded.local[local])
        return local

    # ----------------------------------------------------------------- rebuilds
    def refresh(self, state: State, exchanged: bool = False) -> tuple[bool, float, bool]:
        """Bring the local system to ``state``'s positions (sending the ghosts') unless every
        rank found them ``exchanged`` already; return (whether this rank's list still
        covers the cutoff, the look-ahead ratio, whether its positions are finite).
        Collective; the first call builds."""
        if self.reference is None or self.reference.shape != state.positions.shape:
            self.rebuild(state, migrate=False)
            exchanged = False
        if exchanged:
            return True, self.ahead, True
        start, communicated = time.perf_counter(), self.ranks.clock.seconds
        mapping, allowed = self.allowance(state)
        begin = self.step_start if self.step_start.shape == state.positions.shape else None
        if mapping is None and begin is None:
            chunks = chunk_count(state.n_atoms, _MIN_PASS_ATOMS)
            moved2 = largest_displacement2(state.positions, self.reference, chunks)
            step2, coming2, copied = 0.0, moved2, False
        else:
            before = self.step_before if begin is not None else _NONE
            # the same pass writes the owned positions into the local system (not a message)
            owned = self.domain.owned_rows(state)
            moved2, step2, coming2 = moved_since(state.positions, self.reference,
                                                 _IDENTITY if mapping is None else mapping,
                                                 state.positions if begin is None else begin,
                                                 before, owned)  # fmt: skip
            copied = len(owned) > 0
        # the list's check and the owned rows of its local system; the ghosts' messages on
        # the ranks' clock
        self.domain.update(state, copied)
        self.timings["neighbor"] += (time.perf_counter() - start
                                     - (self.ranks.clock.seconds - communicated))  # fmt: skip
        self._exchanged = _key(state, self._exchanged)
        moved, step_move = math.sqrt(moved2), math.sqrt(step2)
        finite = math.isfinite(moved2)
        coming = math.sqrt(coming2) + LOOKAHEAD * step_move
        covered = moved <= allowed and self.domain.layout_holds(state)
        return covered, _ratio(coming, allowed), finite

    def coming_positions(self, state: State, dt: float,
                         out: NDArray | None = None) -> NDArray[np.float64]:  # fmt: skip
        """Where the owned atoms are expected after a step of ``dt``: r + dt v + dt^2 a / 2
        (velocity Verlet's move) with the forces at hand, r + dt v without (in ``out``,
        else a new array)."""
        forces = self.cached_forces(state)
        if out is None:
            out = np.empty_like(state.positions)
        predicted_positions(state.positions, state.velocities,
                            _NONE if forces is None else forces, state.masses, float(dt),
                            out)  # fmt: skip
        return out

    def cached_forces(self, state: State) -> NDArray[np.float64] | None:
        """The forces on ``state``'s owned atoms if they are at hand (computed at these
        positions and cell), else None; nothing is computed."""
        held = self._cache.get(None)
        if held is not None and _same(held[0], state):
            return held[1].forces
        return None

    def start_step(self, positions: NDArray[np.float64], migrated: bool) -> None:
        """Note the owned ``positions`` at a step start, keeping the last step start's
        unless atoms ``migrated`` since (the look-ahead uses both)."""
        if migrated or self.step_start.shape != positions.shape:
            self.step_before = _NONE
        else:
            self.step_before, self.step_start = self.step_start, self.step_before
        self.step_start = _copied(positions, self.step_start)

    def allowance(self, state: State) -> tuple[NDArray | None, float]:
        """(the cell's deformation since the build, None if unchanged; the largest move an
        atom may make before the list misses a pair within the cutoff) [length]."""
        cutoff = self.cutoff or 0.0
        if (state.box.tobytes(), state.tilt.tobytes()) == self._cell_bytes:
            return None, 0.5 * self.skin
        box0, tilt0 = self.reference_cell
        before = cell_matrix(np.where(state.pbc, box0, 1.0), periodic_tilt(tilt0, state.pbc))
        after = cell_matrix(np.where(state.pbc, state.box, 1.0),
                            periodic_tilt(state.tilt, state.pbc))  # fmt: skip
        mapping = np.linalg.solve(before, after)
        smallest = float(np.linalg.svd(mapping, compute_uv=False).min())
        return mapping, 0.5 * (smallest * (cutoff + self.skin) - cutoff)

    def reserve(self, state: State) -> None:
        """Map the memory the first migration writes ``state``'s arrays and the cached
        forces into, now rather than inside the run (see :meth:`Domain.reserve`)."""
        self.domain.reserve(state, {("cached", None): state.positions})

    def rebuild(self, state: State, migrate: bool, carried: dict | None = None,
                dt: float | None = None) -> dict:  # fmt: skip
        """Rebuild the ghosts and the local list at ``state``; with ``migrate``, first move
        atoms (with ``carried`` per-atom arrays and the cached forces) to the ranks of their
        bricks. Collective. Returns the carried arrays, migrated.

        With ``dt``, the time step about to be taken, the ghosts and the list are laid out
        where that step is expected to take the atoms (:meth:`coming_positions`): a rebuild
        taken at a step start then lasts as many steps as one taken after the step's move,
        as a single process's is (a list built where the atoms are would lose a step's
        worth of skin). Any build position is valid: the list is checked against it at
        every evaluation.

        Its time goes to ``timings["neighbor"]``, less the migration's and the ghost
        search's (on the ranks' clock)."""
        start, communicated = time.perf_counter(), self.ranks.clock.seconds
        carried = dict(carried or {})
        if migrate:
            # Results of the current positions travel with their atoms; older ones (a
            # minimiser migrates after moving the atoms, before evaluating) are dropped.
            self._cache = {which: held for which, held in self._cache.items()
                           if _same(held[0], state)}  # fmt: skip
            cached = {("cached", which): held[1].forces for which, held in self._cache.items()}
            if self.balance_every:
                self._balance(state)
            with self.ranks.clock:
                # (the cached forces are the evaluations' own arrays: they move in them)
                moved = self.domain.migrate(state, {**carried, **cached}, spent=tuple(cached))
            carried = {name: moved[name] for name in carried}
            for which, (_, result) in list(self._cache.items()):
                result.forces = moved[("cached", which)]
                result.energies = result.virials = None
                self._cache[which] = (_key(state), result)
        self.migrate_pending = not migrate
        # The build positions go where the last build's were (that list is done with): a
        # fresh 10^6-atom array cost its page faults at every build (the predicted
        # positions 5 -> 19 ms a build on the Zen 4 VM). No reference until it is whole.
        self.reference = None
        memory = self._reference_memory
        if memory.shape[0] < state.n_atoms:
            memory = np.empty((state.n_atoms + state.n_atoms // 8 + 16, 3))
            self._reference_memory = memory
        reference = memory[: state.n_atoms]
        at = state
        if dt is not None and state.velocities is not None:
            at = copy.copy(state)
            at.positions = self.coming_positions(state, dt, out=reference)
        reach = self.reach
        self.domain.build(at, reach)  # its ghost search on the ranks' clock
        error, longest = None, 0.0
        try:
            longest = self._localize_bonded()
            nl = self.local.neighbor_list
            if nl is not None:
                nl.keep_owned(self.domain.local_ids, self.domain.n_owned)
                nl.build(self.domain.local_state)
        except (NonFiniteError, ValueError) as caught:  # shared with every rank below
            error = caught
        longest, failed = global_max(np.array([longest, error is not None], dtype=np.float64),
                                     self.ranks)  # fmt: skip
        if failed:
            agree(self.ranks, error)
        if self._bonded:
            if longest > reach:
                raise DecompositionError(
                    f"a bond is {longest:.4g} long, beyond the ghost shell ({reach:.4g}) of "
                    "the last build; bonds must not stretch that fast"
                )
            self.bond_reach = longest
        if at is state:
            copy_into(reference, state.positions)
        self.reference = reference
        self.reference_cell = (state.box.copy(), state.tilt.copy())
        self._cell_bytes = (state.box.tobytes(), state.tilt.tobytes())
        # Built where the atoms are: the local system holds their positions. Built ahead of
        # them: the next evaluation sends positions on every rank (a rank whose atoms reach
        # their predicted positions to the last bit must not skip a collective exchange).
        self._exchanged = _key(state, self._exchanged) if at is state else None
        self.ahead = 0.0
        self.n_builds += 1
        elapsed = time.perf_counter() - start
        self.timings["neighbor"] += elapsed - (self.ranks.clock.seconds - communicated)
        return carried

    def _balance(self, state: State) -> None:
        """Move the planes between bricks towards an even share of the ranks' busy time,
        if ``balance_every`` steps have passed since the last check and the imbalance
        exceeds ``balance_threshold`` (see the class's docstring). Collective; the
        migration that follows takes the atoms to their new bricks."""
        now, communicated = time.perf_counter(), self.ranks.clock.seconds
        mark = self._busy_mark
        if mark is not None and state.step - mark[2] < self.balance_every:
            return
        self._busy_mark = (now, communicated, state.step)
        if mark is None:  # the first migration starts the clock
            return
        mine = np.zeros(self.ranks.n_ranks)
        mine[self.ranks.rank] = max((now - mark[0]) - (communicated - mark[1]), 0.0)
        with self.ranks.clock:
            busy = self.ranks.sum(mine)  # one non-zero term per entry: the same on every rank
        mean = float(busy.mean())
        self.imbalance = float(busy.max()) / mean if mean > 0.0 else 1.0
        if self.imbalance <= self.balance_threshold:
            return
        grid = self.domain.grid
        widths = perpendicular_widths(state.box, periodic_tilt(state.tilt, state.pbc))
        where = np.array([grid.coordinates(rank) for rank in range(self.ranks.n_ranks)])
        # a brick keeps room for the ghost shell and how far atoms stray before a build
        room = self.reach + self.skin
        for axis in range(3):
            p = grid.shape[axis]
            if p == 1 or p * room > widths[axis]:
                continue
            costs = np.bincount(where[:, axis], weights=busy, minlength=p)
            planes = balanced_cuts(grid.cuts[axis], costs, room / widths[axis])
            grid = grid.with_cuts(axis, planes)
        self.domain.set_grid(grid)
        self.balances += 1
        logger.info("step %d: ranks' busy time %s s (max/mean %.3f); cuts now %s", state.step,
                    np.round(busy, 4).tolist(), self.imbalance,
                    [np.round(c, 4).tolist() for c in grid.cuts])  # fmt: skip

    def _localize_bonded(self) -> float:
        """Give the local force field this rank's bonds and angles over local indices;
        return the longest bond (angle arm) among them [length]."""
        if not self._bonded:
            return 0.0  # (the id sort below: 5-7 ms a build for a 10^6-atom rank)
        domain = self.domain
        ids = domain.local_ids
        local = domain.local_state
        positions = local.positions
        lengths, inverse = periodic_lengths(local.box, local.pbc)
        tilt = periodic_tilt(local.tilt, local.pbc)
        by_id = np.argsort(ids, kind="stable")
        sorted_ids = np.ascontiguousarray(ids[by_id])
        longest = 0.0
        for bonded in self._bonded:
            chosen, anchors = anchored_items(ids[: domain.n_owned], bonded.starts, bonded.order)
            items = bonded.items[chosen]
            local = np.empty_like(items)
            for column in range(items.shape[1]):
                if column == bonded.anchor:
                    local[:, column] = anchors
                    continue
                found = np.empty(len(items), dtype=np.int64)
                distances = np.empty(len(items))
                partners = np.ascontiguousarray(items[:, column])
                nearest_copies(anchors, partners, sorted_ids, by_id, positions, lengths, inverse,
                               tilt, found, distances)  # fmt: skip
                if len(found) and found.min() < 0:
                    raise DecompositionError(
                        "a bonded atom has no copy on its partner's rank: a bond is longer "
                        "than the ghost shell"
                    )
                local[:, column] = found
                if len(distances):
                    longest = max(longest, float(distances.max()))
            bonded.local = chosen
            potential = self.potentials[bonded.index]
            types = bonded.types[chosen]
            if isinstance(potential, Bonded):
                part = potential.with_bonds(local, types)
            else:
                part = potential.with_angles(local, types)
            self.local.potentials[bonded.index] = part
        return longest


def _copied(values: NDArray[np.float64], into: NDArray[np.float64]) -> NDArray[np.float64]:
    """A copy of ``values``, in ``into``'s memory when it fits."""
    if into.shape != values.shape:
        return values.copy()
    copy_into(into, values)
    return into


def _ratio(moved: float, allowed: float) -> float:
    """moved / allowed, inf when nothing may move but something did."""
    if allowed > 0:
        return moved / allowed
    return math.inf if moved > 0 else 0.0


def _key(state: State, old: tuple | None = None) -> tuple:
    """What a result depends on: the owned positions (copied, into ``old``'s array when it
    fits) and the cell."""
    if old is not None and old[0].shape == state.positions.shape:
        copy_into(old[0], state.positions)
        positions = old[0]
    else:
        positions = state.positions.copy()
    return positions, state.box.tobytes(), state.tilt.tobytes()


def _same(key: tuple, state: State) -> bool:
    positions, box, tilt = key
    return (
        positions.shape == state.positions.shape
        and box == state.box.tobytes()
        and tilt == state.tilt.tobytes()
        and same_values(positions, state.positions)
    )


# ----------------------------------------------------------------- simulation
class DistributedSimulation(Simulation):
    """A Simulation whose system is shared by the ranks of an MPI run.

    Every rank builds it from the same whole-system ``state`` (as every rank
    of ``mpiexec -n P md run`` builds the config's system) and keeps the atoms
    of its brick: ``sim.state`` is then this rank's part (``state.ids`` its
    atoms' ids) and ``sim.forcefield`` a :class:`DistributedForceField`.
    :meth:`run`, :meth:`thermo` and the observers are collective: every rank
    calls them together. Observers run on rank 0 only, and see the whole
    system gathered there, in its original atom order (:meth:`global_view`).

    Parameters
    ----------
    state, potentials, integrator, skin, units, max_displacement, threads, precision
        As for :class:`md.simulation.Simulation`; ``state`` is the whole system.
    ranks : MPIRanks, optional
        The ranks (default: :func:`mpi_ranks`).
    decomposition : sequence of three ints, optional
        Bricks along a, b and c (default: chosen from the rank count and the
        cell, :func:`md.domain.choose_grid`).
    balance_every, balance_threshold
        Dynamic load balancing, off by default (see
        :class:`DistributedForceField`): a balanced run's trajectory depends on
        the ranks' timings, so it is no longer repeatable bit for bit.

    Raises
    ------
    ValueError
        If the integrator cannot run decomposed (RATTLE, constraints, the
        implicit methods), a potential lists atoms in a way the ranks cannot
        share, or the bricks would be thinner than the ghost shell (naming
        the largest decomposition that fits).
    """

    def __init__(self, state: State, potentials, integrator, skin: float = 0.3, units="lj",
                 max_displacement: float | None = None, threads: int | None = None, ranks=None,
                 decomposition=None, precision: str = "double", balance_every: int = 0,
                 balance_threshold: float = 1.05) -> None:  # fmt: skip
        ranks = ranks if ranks is not None else mpi_ranks()
        if ranks is None:
            raise ValueError("a DistributedSimulation needs several MPI ranks (run under mpiexec)")
        super().__init__(state, potentials, integrator, skin=skin, units=units,
                         max_displacement=max_displacement, threads=threads,
                         precision=precision)  # fmt: skip
        refuse_undistributable(integrator, self.forcefield.potentials)
        self.ranks = ranks
        whole = self.forcefield
        arm = longest_arm(whole.potentials, state)
        pairs = whole.neighbor_list.list_radius if whole.neighbor_list is not None else 0.0
        bonds = arm + BOND_SKINS * skin if arm > 0 else 0.0
        reach = max(pairs, bonds)
        what = "cutoff + skin" if pairs >= bonds else f"the longest bond + {BOND_SKINS:g} skins"
        if decomposition is None:
            shape = choose_grid(ranks.n_ranks, state.box, state.tilt, state.pbc, reach, what)
        else:
            shape = tuple(int(p) for p in decomposition)
            if math.prod(shape) != ranks.n_ranks:
                raise ValueError(f"decomposition {list(shape)} has {math.prod(shape)} bricks "
                                 f"for {ranks.n_ranks} ranks")  # fmt: skip
            check_grid(shape, state.box, state.tilt, state.pbc, reach, what)
        self.forcefield = DistributedForceField(whole.potentials, skin, ranks, Grid(shape), arm,
                                                precision=precision, balance_every=balance_every,
                                                balance_threshold=balance_threshold)  # fmt: skip
        self._masses = state.masses.copy() if ranks.rank == 0 else None
        self._types = state.types.copy() if ranks.rank == 0 else None
        self.state = self._part(state, self.forcefield.domain.owner_of(state))
        self.forcefield.rebuild(self.state, migrate=False)
        self.forcefield.migrate_pending = False
        self.forcefield.reserve(self.state)

    @property
    def rank(self) -> int:
        return self.ranks.rank

    @property
    def grid(self) -> Grid:
        """The bricks now (load balancing moves the planes between them)."""
        return self.forcefield.domain.grid

    def _part(self, state: State, owners: NDArray[np.int64], slots=None) -> State:
        """This rank's atoms of the whole system ``state`` (those ``owners`` gives it), in
        increasing id, or in the order of their ``slots`` (rows on the rank) if given."""
        mine = np.flatnonzero(owners == self.ranks.rank)
        if slots is not None:
            mine = mine[np.argsort(np.asarray(slots)[mine], kind="stable")]
        return State(
            positions=state.positions[mine], velocities=state.velocities[mine],
            masses=state.masses[mine], box=state.box, pbc=state.pbc, types=state.types[mine],
            type_names=state.type_names, step=state.step, time=state.time, tilt=state.tilt,
            ids=mine,
        )  # fmt: skip

    def attach(self, observer, interval: int = 1) -> None:
        """As :meth:`Simulation.attach`; the observer runs on rank 0 with the whole system."""
        super().attach(_Gathered(observer), interval)

    def observe(self, observer) -> None:
        """Call ``observer`` now as an attached one would be (rank 0, whole system;
        collective)."""
        _Gathered(observer)(self)

    def run(self, n_steps: int) -> None:
        """As :meth:`Simulation.run`, on every rank together."""
        with using_reductions(self.ranks):
            super().run(n_steps)

    def thermo(self) -> dict[str, float]:
        """As :meth:`Simulation.thermo`, over the whole system (collective)."""
        with using_reductions(self.ranks):
            return super().thermo()

    def minimize(self, fmax: float, max_steps: int = 10_000, **options):
        """:func:`md.minimize.minimize` of the whole system (collective); atoms migrate
        between its steps as in a run. Returns its MinimizeResult."""
        with using_reductions(self.ranks):
            return minimize(self.state, self.forcefield, fmax, max_steps,
                            between_steps=self.redistribute, **options)  # fmt: skip

    # -------------------------------------------------------------- the loop
    def request_stop(self, reason: str = "stop requested") -> None:
        """As :meth:`Simulation.request_stop`; every rank stops after the same step (the
        request is shared at the next force evaluation)."""
        super().request_stop(reason)
        self.forcefield.stop_code = _STOPS.get(reason, 3.0)

    def _stopping(self) -> bool:
        """Start a step on every rank alike, from what the last force evaluation shared:
        stop when any rank was asked to; else migrate and rebuild when the coming step
        could outrun the list (or the last build, forced inside a step, kept owners)."""
        forcefield = self.forcefield
        if forcefield.stop_seen:
            names = {value: name for name, value in _STOPS.items()}
            self.stop_requested = names.get(forcefield.stop_seen, "stop requested")
            return True
        migrating = forcefield.ahead > 1.0 or forcefield.migrate_pending
        if migrating:
            dt = getattr(self.integrator, "dt", None)
            self._guarded(lambda: self._migrate(dt=dt), self.state.step)
        forcefield.start_step(self.state.positions, migrating)
        return False

    def _migrate(self, carried: dict | None = None, dt: float | None = None) -> dict:
        """Migrate atoms (with the integrator's per-atom state and ``carried``) and rebuild
        (ahead of a step of ``dt``, see :meth:`DistributedForceField.rebuild`). Collective."""
        integrator = self.integrator
        keys = self.per_atom_keys()
        saved = integrator.get_state() if keys else {}
        extra = {key: np.asarray(saved[key]) for key in keys if saved.get(key) is not None}
        carried = {**extra, **(carried or {})}
        moved = self.forcefield.rebuild(self.state, migrate=True, carried=carried, dt=dt)
        if extra:
            saved.update({key: moved[key] for key in extra})
            integrator.set_state(saved)
        return moved

    def redistribute(self, velocities: NDArray[np.float64]) -> NDArray[np.float64]:
        """Between two steps of a minimiser (FIRE): migrate, with its ``velocities``, when
        the next step could outrun the list; return the velocities of the atoms now owned.
        Collective."""
        forcefield = self.forcefield
        migrating = forcefield.ahead > 1.0 or forcefield.migrate_pending
        if migrating:
            key = ("minimizer", "velocities")
            velocities = self._migrate({key: velocities})[key]
        forcefield.start_step(self.state.positions, migrating)
        return velocities

    def _check_displacement(self, limit: float) -> None:
        """The blow-up guard, over every rank: all stop if any atom moved too far."""
        error = None
        try:
            super()._check_displacement(limit)
        except SimulationError as caught:
            error = caught
        if global_max(0.0 if error is None else 1.0, self.ranks):
            agree(self.ranks, error)

    def timing_summary(self) -> dict[str, float]:
        """As :meth:`Simulation.timing_summary`, with the time spent communicating as a
        section of its own (halo exchange, reverse pass, migration, reductions, gathers):
        the other sections leave it out, so the sections add up to at most the wall time."""
        return {**super().timing_summary(), "comm": self.ranks.clock.seconds}

    def _comm_seconds(self) -> float:
        return self.ranks.clock.seconds

    # ------------------------------------------------------------ whole system
    def per_atom_keys(self) -> tuple[str, ...]:
        return tuple(getattr(self.integrator, "per_atom_state", ()))

    def global_view(self, forces: bool = False, thermo: bool = True) -> GlobalView | None:
        """The whole system gathered on rank 0, in its atom order (collective): a
        :class:`GlobalView` there, None on the other ranks."""
        state = self.state
        row = self.thermo() if thermo else None
        columns = [state.ids[:, None].astype(np.float64), state.positions, state.velocities]
        reference = self.forcefield.reference
        if reference is None or reference.shape != state.positions.shape:
            reference = np.full_like(state.positions, np.nan)
        columns.append(reference)
        columns.append(np.full((state.n_atoms, 1), float(self.rank)))
        if forces:
            columns.append(self.forcefield.compute(state).forces)
        keys = self.per_atom_keys()
        saved = self.integrator.get_state() if hasattr(self.integrator, "get_state") else None
        shapes = []
        for key in keys:
            value = None if saved is None else saved.get(key)
            if value is not None:
                value = np.asarray(value, dtype=np.float64)
                shapes.append((key, value.shape[1:]))
                columns.append(value.reshape(state.n_atoms, -1))
        rows = self.ranks.gather_rows(np.concatenate(columns, axis=1))
        if rows is None:
            return None
        n = rows.shape[0]
        whole = np.empty_like(rows)
        whole[rows[:, 0].astype(np.int64)] = rows
        gathered = State(
            positions=whole[:, 1:4], velocities=whole[:, 4:7], masses=self._masses, box=state.box,
            pbc=state.pbc, types=self._types, type_names=state.type_names, step=state.step,
            time=state.time, tilt=state.tilt,
        )  # fmt: skip
        start = 11  # after id, positions, velocities, build positions and rank
        gathered_forces = None
        if forces:
            gathered_forces, start = whole[:, 11:14].copy(), 14
        if saved is not None:
            saved = dict(saved)
            for key, shape in shapes:
                size = int(np.prod(shape))
                saved[key] = whole[:, start : start + size].reshape((n, *shape)).copy()
                start += size
        # Each atom's row on its rank: the gathered rows come rank after rank, each rank's
        # in its own order (a resume on this grid restores it, for the same bits).
        ranks = rows[:, 10].astype(np.int64)
        slots = np.empty(n, dtype=np.int64)
        slots[rows[:, 0].astype(np.int64)] = np.arange(n) - np.searchsorted(ranks, ranks)
        layout = {
            "grid": list(self.grid.shape),
            "cuts": [list(planes) for planes in self.grid.cuts],
            "owners": whole[:, 10].astype(np.int64),
            "slots": slots,
            "bond_reach": self.forcefield.bond_reach,
            "migrate_pending": self.forcefield.migrate_pending,
            "ahead": self.forcefield.ahead,
        }
        reference = whole[:, 7:10].copy()
        return GlobalView(
            state=gathered,
            row=row,
            integrator=_IntegratorView(self.integrator, saved),
            forcefield=_ForceFieldView(self.forcefield, gathered_forces, row, reference, layout),
            units=self.units,
        )

    def light_view(self, thermo: bool = True) -> GlobalView | None:
        """Step, time and (with ``thermo``) the thermo row of the whole system, without the
        atoms (collective): a :class:`GlobalView` on rank 0 whose ``state`` is rank 0's
        part, None on the other ranks."""
        row = self.thermo() if thermo else None
        if self.rank != 0:
            return None
        return GlobalView(state=self.state, row=row, integrator=self.integrator,
                          forcefield=None, units=self.units)  # fmt: skip

    def resume(self, state: State, reference, reference_cell=None, layout=None) -> None:
        """Continue from a checkpoint: ``state`` is its whole system, ``reference`` the
        positions of its last list build (``reference_cell`` that build's box and tilt),
        ``layout`` the decomposition it was written with, if any. The integrator's saved
        state must already be restored (whole-system arrays): it is cut here. Collective.

        On the grid and rank count that wrote it, the owners, the ghost shell and the
        list are those of the uninterrupted run, so the run continues bit for bit; on
        another, atoms go to the bricks holding their build positions, and the run agrees
        with the uninterrupted one to round-off.
        """
        forcefield = self.forcefield
        same = (
            layout is not None
            and list(layout.get("grid", [])) == list(self.grid.shape)
            and len(layout.get("owners", ())) == state.n_atoms
        )
        at_build = state.copy()
        if reference is not None:
            at_build.positions[:] = reference
            if reference_cell is not None:
                box, tilt = reference_cell
                at_build.box = np.array(box, dtype=np.float64)
                at_build.tilt = np.array(tilt, dtype=np.float64)
        if same and layout.get("cuts") is not None:  # planes moved by load balancing
            forcefield.domain.set_grid(Grid(self.grid.shape, layout["cuts"]))
        owners = (np.asarray(layout["owners"], dtype=np.int64) if same
                  else forcefield.domain.owner_of(at_build))  # fmt: skip
        slots = layout.get("slots") if same else None  # (checkpoints before it: by id)
        self.state = self._part(state, owners, slots)
        part_at_build = self._part(at_build, owners, slots)
        if same:
            forcefield.bond_reach = float(layout.get("bond_reach", forcefield.bond_reach))
        forcefield.invalidate()
        forcefield.rebuild(part_at_build, migrate=False)
        forcefield.step_start = forcefield.step_before = _NONE
        self._localize_integrator()
        forcefield.refresh(self.state)
        # What the uninterrupted run's next step start would have seen.
        forcefield.migrate_pending = bool(layout.get("migrate_pending", False)) if same else False
        forcefield.ahead = float(layout.get("ahead", 0.0)) if same else 0.0

    def _localize_integrator(self) -> None:
        """Cut the integrator's whole-system per-atom state down to this rank's atoms."""
        keys = self.per_atom_keys()
        if not keys:
            return
        saved = self.integrator.get_state()
        changed = False
        for key in keys:
            value = saved.get(key)
            if value is not None and len(value) != self.state.n_atoms:
                saved[key] = np.asarray(value)[self.state.ids]
                changed = True
        if changed:
            self.integrator.set_state(saved)


def refuse_undistributable(integrator, potentials) -> None:
    """Raise ValueError if the integrator or a potential cannot run decomposed over ranks."""
    name = integrator.describe().get("type", type(integrator).__name__)
    if constraints_of(integrator) is not None:
        raise ValueError(
            f"rigid bonds (the {name} integrator's constraints) do not run decomposed over MPI "
            "ranks: run this config on one rank (without mpiexec)"
        )
    if not getattr(integrator, "distributed", False):
        raise ValueError(
            f"the {name} integrator does not run decomposed over MPI ranks (its step needs "
            "the whole system at once, as the implicit methods' solves and XPBD's sweeps over "
            "the bonds do): run this config on one rank (without mpiexec), or choose another "
            "integrator"
        )
    for potential in potentials:
        if potential.cutoff is None and not isinstance(potential, Bonded | BondedAngles):
            raise ValueError(
                f"potential {type(potential).__name__} has no cutoff and lists no atoms, so "
                "the ranks cannot share it: run on one rank"
            )


# ------------------------------------------------------------------ views
class Elsewhere:
    """The stand-in, on the other ranks, for an observer that rank 0 holds (a trajectory
    writer): it says what the gather for it needs, and is never called."""

    uses_virial = True

    def __init__(self, store_forces: bool = False) -> None:
        self.store_forces = bool(store_forces)

    def __call__(self, sim) -> None:
        raise RuntimeError("an observer held by rank 0 was called on another rank")


class _Gathered:
    """An observer run on rank 0 with the whole system; the others take part in the gather."""

    def __init__(self, observer) -> None:
        self.observer = observer
        self.uses_virial = getattr(observer, "uses_virial", True)
        #: False for an observer that reads only the step, time and thermo (a thermo
        #: table, a progress bar): it gets them without the atoms being gathered.
        self.whole_system = getattr(observer, "whole_system", True)

    def __call__(self, sim: DistributedSimulation) -> None:
        if self.whole_system:
            view = sim.global_view(forces=bool(getattr(self.observer, "store_forces", False)),
                                   thermo=self.uses_virial)  # fmt: skip
        else:
            view = sim.light_view(thermo=self.uses_virial)
        error = None
        if view is not None:
            try:
                self.observer(view)
            except Exception as caught:  # shared with every rank below
                error = caught
        if global_max(0.0 if error is None else 1.0, sim.ranks):
            agree(sim.ranks, error)


@dataclass
class GlobalView:
    """What an observer of a decomposed run sees on rank 0: the whole system, gathered.

    It offers what observers read of a :class:`md.simulation.Simulation`:
    ``state`` (the whole system in its atom order), ``thermo()`` (computed by
    every rank together before the gather), ``integrator`` (``describe``,
    ``get_state`` with whole-system per-atom arrays, and the rest of the
    integrator) and ``forcefield`` (``compute`` giving the gathered forces,
    ``neighbor_list.reference_positions``, ``topology``), and ``units``.
    """

    state: State
    row: dict | None
    integrator: object
    forcefield: object
    units: object

    def thermo(self) -> dict[str, float]:
        if self.row is None:
            raise RuntimeError("this observer said it reads no thermo (uses_virial = False)")
        return dict(self.row)


class _IntegratorView:
    """The integrator, with ``get_state`` giving the whole system's per-atom arrays."""

    def __init__(self, integrator, saved) -> None:
        self._integrator = integrator
        self._saved = saved

    def get_state(self):
        return self._saved

    def __getattr__(self, name):
        return getattr(self._integrator, name)


@dataclass
class _ListView:
    """The neighbour list's build, for checkpoints: positions and cell of the last build
    (a rank's list is never a pruned cluster list: no prune positions, no prunes)."""

    reference_positions: NDArray[np.float64] | None
    reference_cell: tuple | None
    n_builds: int
    pruned_positions: None = None
    n_prunes: int = 0
    built_step: None = None  # ranks always look at their lists: no step to count from


class _ForceFieldView:
    """The force field as a rank-0 observer sees it (gathered forces, the build, topology)."""

    def __init__(self, forcefield, forces, row, reference, layout) -> None:
        self._forcefield = forcefield
        self._forces = forces
        self._energy = None if row is None else row["potential_energy"]
        complete = reference is not None and not np.isnan(reference).any()
        self.neighbor_list = _ListView(reference if complete else None,
                                       forcefield.reference_cell, forcefield.n_builds)  # fmt: skip
        self.decomposition = layout

    def compute(self, state: State, per_atom: bool = False, virial: bool = True) -> ForceResult:
        if self._forces is None:
            raise RuntimeError("forces were not gathered for this observer (store_forces)")
        return ForceResult(energy=self._energy, forces=self._forces, virial=None)

    def topology(self, extra=()) -> Topology:
        return self._forcefield.topology(extra)
