"""Migration: a rank's owned atoms, and the per-atom arrays that go with them, move to the
ranks whose bricks hold them (:meth:`md.distributed.halo.Domain.migrate`).

One sweep per cut axis sends the atoms that left the brick across either face to
that face's neighbour, packed into rows of floats with their per-atom arrays
(integers are exact below 2^53). Each sweep changes only the rows that move
(:func:`refill_plan`): arriving atoms fill the leavers' rows. The arrays live in
a :class:`RowStore`, memory kept between migrations with room to grow, so that a
migration neither allocates nor takes page faults in the usual case.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from md.distributed._domain_kernels import (
    leaving_along,
    pack_leaving,
    refill_plan,
    refill_rows,
    same_start,
    unpack_arriving,
)
from md.errors import DecompositionError
from md.state import State


class RowStore:
    """The per-atom arrays of a rank, kept between migrations under a key each (the
    state's arrays ``("state", k)``, the carried ones ``("carried", name)``)."""

    def __init__(self) -> None:
        self._stores: dict[object, NDArray] = {}

    def refilled(
        self, key, values: NDArray, n: int, size: int, incoming: NDArray, plan, spent: bool = False
    ) -> NDArray:
        """``values`` (n rows) after a sweep's :func:`refill_plan`: ``size`` rows of
        the array kept under ``key``, changed in place where ``values`` already is its
        first rows (the usual case), else copied into it first; if ``values`` is
        ``spent``, the array it is the first rows of, changed in place, where that has
        the room."""
        store = self.target(key, values, n, size, spent)
        width = math.prod(values.shape[1:])
        sources, targets, arrivals = plan
        refill_rows(
            store.reshape(len(store), width),
            sources,
            targets,
            np.ascontiguousarray(incoming).reshape(-1, width),
            arrivals,
        )
        return store[:size]

    def target(self, key, values: NDArray, n: int, size: int, spent: bool = False) -> NDArray:
        """The array a sweep leaving ``size`` rows refills in place for ``values`` (n rows):
        :meth:`store`'s, or where ``values`` is ``spent``, the array it is the first rows
        of, where that has the room (see :meth:`refilled`)."""
        store = _room_of(values, size) if spent else None
        return self.store(key, values, n, size) if store is None else store

    def message(self, key, n: int, width: int) -> NDArray[np.float64]:
        """n rows of ``width`` floats kept under ``key`` (a migration's outgoing rows: sent
        and waited for before the next use)."""
        held = self._stores.get(("message", key))
        if held is None or held.shape[0] < n or held.shape[1] != width:
            held = np.empty((n + n // 4 + 16, width))
            self._stores[("message", key)] = held
        return held[:n]

    def store(self, key, values: NDArray, n: int, size: int) -> NDArray:
        """The array kept under ``key`` for ``values``' rows, holding them in its first ``n``
        rows and room for ``size``: ``values``' own memory when it is that array's
        beginning, else a copy (into a larger array when it needs room; the room is an
        eighth more, so that a rank's count can grow for several migrations)."""
        store = self._stores.get(key)
        fits = (
            store is not None
            and store.dtype == values.dtype
            and store.shape[1:] == values.shape[1:]
            and store.shape[0] >= max(n, size)
        )
        if fits and n and values.base is store and same_start(values, store):
            return store  # values are its first rows: changed in place
        if not fits:
            rows = max(n, size)
            store = np.empty((rows + rows // 8 + 16, *values.shape[1:]), dtype=values.dtype)
            self._stores[key] = store
        store[:n] = values[:n]
        return store

    def reserve(self, state: State, carried: dict) -> None:
        """Give ``state``'s per-atom arrays their room for migrations now (a copy into the
        arrays kept here; ``state``'s arrays become views of them), and map the memory of
        the ``carried`` ones (name -> an array shaped like it), so that the first
        migration of a run does not pay their page faults (1M atoms on the Emerald Rapids
        VM: 0.108 s for the first migration, 0.040 s for later ones)."""
        n = state.n_atoms
        arrays = [state.positions, state.velocities, state.masses, state.types, state.ids]
        kept = [self.store(("state", k), a, n, n)[:n] for k, a in enumerate(arrays)]
        state.positions, state.velocities, state.masses, state.types, state.ids = kept
        for name, like in carried.items():
            if ("carried", name) not in self._stores:
                self.store(("carried", name), like, n, n).fill(0)  # written: its pages mapped


def migrate(domain, state: State, carried: dict, spent: tuple = ()) -> dict:
    """Move ``domain``'s owned atoms, and the per-atom arrays ``carried``, to the ranks whose
    bricks hold them, in one sweep per cut axis; ``state``'s arrays are replaced by
    views of arrays ``domain.rows`` keeps (a :class:`RowStore`). Collective.

    ``domain`` is the rank's :class:`md.distributed.halo.Domain` (its ranks, grid, brick
    coordinates and cut planes). The carried arrays named in ``spent`` are the caller's
    to give away: each moves in the memory of the array it is the first rows of (a force
    evaluation's local result, owned rows then ghosts), where that has room, rather than
    being copied into kept memory first (a 10^6-atom rank's forces: 3 ms a migration).

    Each sweep changes only the rows that move (:func:`refill_plan`): arriving atoms fill
    the rows of the leaving ones, and staying atoms past the new end fill what is left. A
    rank's atom order is so a function of its run's history (deterministic on any P; a
    checkpoint records it, see :meth:`md.distributed.simulation.DistributedSimulation.
    global_view`), not sorted by id: a sorted merge rewrote every row of every array (a
    10^6-atom rank: 30 ms of a 50 ms migration on the Emerald Rapids VM).

    The atoms that moved more than a brick along an axis since the last migration are
    added to ``domain.lost_atoms``; the ghost search that follows shares them and raises
    (:func:`check_lost`) on every rank.
    """
    names = list(carried)
    # The state's per-atom arrays, then the carried ones: only the atoms that leave
    # are packed into rows of floats (integers are exact below 2^53). (Plain loops: a
    # comprehension is a Python call of its own, at every migration.)
    arrays = [state.positions, state.velocities, state.masses, state.types, state.ids]
    keys = list(_STATE_KEYS)
    for name in names:
        arrays.append(np.asarray(carried[name]))
        keys.append(("carried", name))
    # The pack and the sweep's refill are a compiled call each where the arrays are the
    # state's usual ones and the carried ones C-contiguous float64 (else numpy does the
    # same in Python: the same message layout and rows).
    compiled, width = _compiled_layout(arrays)
    n = len(state.positions)
    lost = 0
    tilt = domain.geometry(state)[0]  # (the periodic tilt, kept while the cell is)
    grid, ranks = domain.grid, domain.ranks
    for axis in range(3):
        if grid.shape[axis] == 1:
            continue
        ups, downs, far = leaving_along(
            arrays[0],
            state.box,
            tilt,
            state.pbc,
            domain.shape,
            domain.cuts,
            axis,
            domain.coordinates[axis],
        )
        lost += far
        lower, upper = domain.neighbors[axis]
        flat = _flat(arrays) if compiled else None
        if grid.shape[axis] == 2:
            # Two bricks along the axis: both neighbours are the one other rank, and every
            # leaver is in ``ups`` (``downs`` stays empty), so one message each way.
            going = _packed(arrays, ups, flat, domain.rows, "up", width)
            from_lower = domain.exchange_kept(going, upper, lower, 2 * axis, "migration")
            from_upper = from_lower[:0]
        else:
            going_up = _packed(arrays, ups, flat, domain.rows, "up", width)
            going_down = _packed(arrays, downs, flat, domain.rows, "down", width)
            from_lower, from_upper = ranks.exchange_many(
                [(going_up, upper, lower, 2 * axis), (going_down, lower, upper, 2 * axis + 1)]
            )
        m = len(from_lower) + len(from_upper)
        if len(ups) + len(downs) + m == 0:
            continue
        size = n - len(ups) - len(downs) + m  # (ups and downs are different atoms)
        if compiled:
            stores = [
                domain.rows.target(key, a, n, size, key[0] == "carried" and key[1] in spent)
                for key, a in zip(keys, arrays, strict=True)
            ]
            unpack_arriving(ups, downs, n, from_lower, from_upper, *stores[:5], _flat(stores))
            arrays = [store[:size] for store in stores]
            n = size
            continue
        incoming = _unpacked(np.concatenate([from_lower, from_upper]), arrays)
        leaving = np.sort(np.concatenate([ups, downs]))
        plan = refill_plan(leaving, n, m)
        arrays = [
            domain.rows.refilled(key, a, n, size, b, plan, key[0] == "carried" and key[1] in spent)
            for key, a, b in zip(keys, arrays, incoming, strict=True)
        ]
        n = size
    state.positions, state.velocities, state.masses, state.types, state.ids = arrays[:5]
    carried = dict(zip(names, arrays[5:], strict=True))
    # (shared in the ghost search's reduction, which follows every migration: see
    # check_lost)
    domain.lost_atoms += lost
    return carried


def check_lost(lost: float) -> None:
    """Raise the migration's error if ``lost`` (the atoms that moved more than a brick, over
    every rank) is not 0: called by every rank alike after the reduction that shares it.

    Raises
    ------
    DecompositionError
        If an atom moved more than one brick along an axis since the last migration.
    """
    error = lost_error(lost)
    if error is not None:
        raise error


def lost_error(lost: float) -> DecompositionError | None:
    """The error :func:`check_lost` raises for ``lost`` atoms (None for none), for a rank
    that shares it later (a step start's build, in the step's reduction)."""
    if not lost:
        return None
    return DecompositionError(
        "an atom moved more than a brick between two neighbour-list builds; the "
        "dynamics is blowing up (time step too large?)"
    )


def _room_of(values: NDArray, size: int) -> NDArray | None:
    """The C-contiguous array whose first rows ``values`` are (itself, or the array it is
    a view of), if that has at least ``size`` rows; else None."""
    root = values if values.base is None else values.base
    if (
        not isinstance(root, np.ndarray)
        or root.base is not None
        or not root.flags.c_contiguous
        or not values.flags.c_contiguous
        or root.dtype != values.dtype
        or root.shape[1:] != values.shape[1:]
        or not same_start(root, values)
        or root.shape[0] < size
    ):
        return None
    return root


_NO_COLUMNS = np.zeros((0, 0))  # (ends the carried arrays' tuple: never indexed)
_STATE_KEYS = tuple(("state", k) for k in range(5))
_STATE_TYPES = ((np.float64, 2), (np.float64, 2), (np.float64, 1), (np.int32, 1), (np.int64, 1))


def _compiled_layout(arrays) -> tuple[bool, int]:
    """Whether :func:`pack_leaving` and :func:`unpack_arriving` take ``arrays`` (the state's
    positions, velocities, masses, types and ids, then the carried ones: the state's of
    their usual types, the carried ones C-contiguous float64, all C-contiguous), and the
    message's width (floats a row). Plain loops: this runs at every migration."""
    compiled, width = True, 0
    for k, a in enumerate(arrays):
        row = math.prod(a.shape[1:])
        width += row
        if k < 5:
            dtype, ndim = _STATE_TYPES[k]
            usual = a.dtype == dtype and a.ndim == ndim and (ndim == 1 or row == 3)
        else:
            usual = a.dtype == np.float64
        compiled = compiled and usual and a.flags.c_contiguous
    return compiled, width


def _flat(arrays) -> tuple:
    """The carried arrays (after the state's five) as 2-D views, one row an atom, and the
    empty one that ends the tuple (so that it is never empty)."""
    flat = []
    for a in arrays[5:]:
        flat.append(a.reshape(len(a), math.prod(a.shape[1:])))
    flat.append(_NO_COLUMNS)
    return tuple(flat)


def _packed(arrays, rows: NDArray[np.int64], flat=None, store=None, key=None, width=0):
    """Rows ``rows`` of the per-atom ``arrays`` side by side, as floats (integers are exact
    below 2^53): one row per atom that leaves. With ``flat`` (:func:`_flat` of them, where
    :func:`_compiled_layout` holds), one compiled call into memory ``store`` keeps under
    ``key``."""
    if flat is not None:
        out = store.message(key, len(rows), width)
        pack_leaving(rows, *arrays[:5], flat, out)
        return out
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
