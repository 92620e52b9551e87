"""The geometry of a run decomposed over MPI ranks: one brick of the cell per rank.

The cell is cut in its own (fractional) coordinates into a grid of
``px x py x pz`` bricks, as LAMMPS's ``comm_style brick`` does: brick
``(cx, cy, cz)`` holds the atoms whose fractional coordinates ``s`` (the
wrapped position ``s @ cell``, ``0 <= s < 1`` along periodic axes) lie in
``[cuts_a[cx], cuts_a[cx + 1])`` along a, and so on, where the cuts of an
axis start even (``cx / px``) and move when the run balances its ranks'
work (:func:`balanced_cuts`, as LAMMPS's ``fix balance ... shift``). A
tilted cell gives parallelepiped bricks; a barostat's cell change moves
them with the cell. Open axes are never cut.

Each rank keeps copies (*ghosts*) of the atoms within the *reach* of its
brick: the neighbour list's radius (cutoff + skin), or more where bonds are
longer. So a brick must be at least that wide across each cut axis
(perpendicular width over the count along it), and the messages only ever
go to the six face neighbours (:mod:`md.distributed`). This module holds the
grid arithmetic, the choice of grid and the kernels of the exchange (it
imports no MPI; ``md`` imports it so numba caches its kernels with the rest).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from md.box import TILT_AXES, perpendicular_widths, separation


@dataclass(frozen=True)
class Grid:
    """A ``px x py x pz`` grid of bricks, one per rank.

    Rank ``r`` sits at ``(cx, cy, cz)`` with ``r = (cx * py + cy) * pz + cz``.
    ``cuts`` gives, per axis, the ``p + 1`` fractional coordinates of the
    planes between its bricks, from 0 to 1 (default: even, ``c / p``).

    Examples
    --------
    >>> grid = Grid((2, 3, 1))
    >>> grid.n_ranks, grid.coordinates(4), grid.rank_of((1, 1, 0))
    (6, (1, 1, 0), 4)
    >>> grid.neighbor(4, axis=1, step=1), grid.neighbor(4, axis=1, step=-1)
    (5, 3)
    >>> Grid((2, 1, 1), cuts=((0.0, 0.6, 1.0), (0.0, 1.0), (0.0, 1.0))).bounds(1).tolist()
    [[0.6, 0.0, 0.0], [1.0, 1.0, 1.0]]
    """

    shape: tuple[int, int, int]
    cuts: tuple[tuple[float, ...], ...] | None = None

    def __post_init__(self) -> None:
        shape = tuple(int(p) for p in self.shape)
        object.__setattr__(self, "shape", shape)
        if self.cuts is None:
            cuts = tuple(tuple(c / p for c in range(p + 1)) for p in shape)
        else:
            cuts = tuple(tuple(float(c) for c in axis) for axis in self.cuts)
        for axis, (p, planes) in enumerate(zip(shape, cuts, strict=True)):
            steps = np.diff(planes)
            if len(planes) != p + 1 or planes[0] != 0.0 or planes[-1] != 1.0 or np.any(steps <= 0):
                raise ValueError(f"the cuts along {'xyz'[axis]} must be {p + 1} increasing "
                                 f"fractions from 0 to 1, got {list(planes)}")  # fmt: skip
        object.__setattr__(self, "cuts", cuts)

    @property
    def n_ranks(self) -> int:
        return math.prod(self.shape)

    def coordinates(self, rank: int) -> tuple[int, int, int]:
        _, py, pz = self.shape
        return rank // (py * pz), (rank // pz) % py, rank % pz

    def rank_of(self, coordinates) -> int:
        _, py, pz = self.shape
        cx, cy, cz = (int(c) % p for c, p in zip(coordinates, self.shape, strict=True))
        return (cx * py + cy) * pz + cz

    def neighbor(self, rank: int, axis: int, step: int) -> int:
        """The rank ``step`` (+1 or -1) bricks along ``axis``, periodically."""
        coordinates = list(self.coordinates(rank))
        coordinates[axis] += step
        return self.rank_of(coordinates)

    def bounds(self, rank: int) -> NDArray[np.float64]:
        """(2, 3): the brick's lower and upper fractional coordinates."""
        c = self.coordinates(rank)
        return np.array([[self.cuts[a][c[a]] for a in range(3)],
                         [self.cuts[a][c[a] + 1] for a in range(3)]])  # fmt: skip

    def cut_table(self) -> NDArray[np.float64]:
        """(3, max p + 1) array of the cuts, each row padded with 1.0 (for the kernels)."""
        table = np.ones((3, max(self.shape) + 1))
        for axis, planes in enumerate(self.cuts):
            table[axis, : len(planes)] = planes
        return table

    def thinnest(self) -> NDArray[np.float64]:
        """(3,): the thinnest brick along each axis, as a fraction of the cell."""
        return np.array([min(np.diff(planes)) for planes in self.cuts])

    def with_cuts(self, axis: int, planes) -> Grid:
        """This grid with the cuts along ``axis`` replaced by ``planes``."""
        cuts = list(self.cuts)
        cuts[axis] = tuple(float(c) for c in planes)
        return Grid(self.shape, tuple(cuts))


def local_periodic_axes(shape, pbc, tilt) -> NDArray[np.bool_]:
    """The axes a rank's local system keeps periodic: those the grid does not cut (one
    brick spans them) whose cell vector has no component along a cut axis.

    Along such an axis the rank's cell list finds the periodic images itself (image
    codes, as a single process does), so the ghost shell need not copy the rank's own
    atoms across it: a 2 x 1 x 1 grid's ghosts are the atoms near the two cut faces
    (about 8 % of a rank's atoms for the 2M-atom melt), not those plus the images
    across the four other faces (18 %). The vector of axis j has component
    ``tilt[k]`` along axis i for (i, j) = ``TILT_AXES[k]``: a non-zero tilt towards a
    cut axis keeps j explicit (its image would cross the cut).
    """
    local = np.asarray(pbc, dtype=bool) & (np.asarray(shape) == 1)
    for k, (i, j) in enumerate(TILT_AXES):  # (x, y), (x, z), (y, z): j after i
        if tilt[k] != 0.0 and not local[i]:
            local[j] = False
    return local


def brick_widths(shape, box, tilt, pbc) -> NDArray[np.float64]:
    """Perpendicular width of a brick across each axis [length] (inf along open axes)."""
    widths = perpendicular_widths(box, tilt) / np.asarray(shape, dtype=np.float64)
    return np.where(np.asarray(pbc, dtype=bool), widths, np.inf)


def largest_grid(box, tilt, pbc, reach: float) -> tuple[int, int, int]:
    """The most bricks along each axis that are still ``reach`` wide (1 along open axes)."""
    widths = perpendicular_widths(box, tilt)
    return tuple(
        max(1, int(math.floor(width / reach * (1.0 + 1e-12)))) if periodic else 1
        for width, periodic in zip(widths.tolist(), np.asarray(pbc).tolist(), strict=True)
    )


def check_grid(shape, box, tilt, pbc, reach: float, what: str = "cutoff + skin") -> None:
    """Raise ValueError if a brick of ``shape`` is thinner than ``reach`` across a periodic
    axis, or an open axis is cut; the message names the largest grid that fits.

    ``what`` says what the reach is made of, for the message.
    """
    shape = tuple(int(p) for p in shape)
    pbc = np.asarray(pbc, dtype=bool)
    if len(shape) != 3 or any(p < 1 for p in shape):
        raise ValueError(f"decomposition must be three positive integers, got {list(shape)}")
    cut_open = [axis for axis in range(3) if shape[axis] > 1 and not pbc[axis]]
    if cut_open:
        raise ValueError(
            f"decomposition {list(shape)} cuts the open axis {'xyz'[cut_open[0]]}; only "
            "periodic axes are cut into bricks (give 1 there)"
        )
    widths = brick_widths(shape, box, tilt, pbc)
    thin = [axis for axis in range(3) if pbc[axis] and widths[axis] < reach]
    if not thin:
        return
    axis = thin[0]
    largest = largest_grid(box, tilt, pbc, reach)
    if shape[axis] == 1:
        raise ValueError(
            f"the cell is {widths[axis]:.4g} wide across {'xyz'[axis]}, less than {what} = "
            f"{reach:.4g}, the shell of ghost atoms each rank keeps: too small a system to "
            "share between ranks; run it on one rank"
        )
    raise ValueError(
        f"decomposition {list(shape)} cuts the cell into bricks {widths[axis]:.4g} wide "
        f"across {'xyz'[axis]}, thinner than {what} = {reach:.4g}, the shell of ghost "
        f"atoms each rank keeps; the largest decomposition that fits this cell is "
        f"{list(largest)} ({math.prod(largest)} ranks): run on at most that many ranks, "
        "or on a larger system"
    )


def choose_grid(n_ranks: int, box, tilt, pbc, reach: float,
                what: str = "cutoff + skin") -> tuple[int, int, int]:  # fmt: skip
    """The grid of ``n_ranks`` bricks with the least brick surface that fits the cell.

    Only periodic axes are cut, and every brick is at least ``reach`` wide
    (see :func:`check_grid`). Among the grids that fit, the one whose bricks
    have the smallest surface (the ghost shell's volume, hence the halo
    traffic) wins; ties go to the grid listed first (more bricks along x).

    Raises
    ------
    ValueError
        If no grid of ``n_ranks`` fits, naming the largest that does.

    Examples
    --------
    >>> choose_grid(4, [20.0, 20.0, 10.0], None, [True] * 3, 2.8)
    (2, 2, 1)
    >>> choose_grid(6, [30.0, 20.0, 10.0], None, [True] * 3, 2.8)
    (3, 2, 1)
    """
    pbc = np.asarray(pbc, dtype=bool)
    widths = perpendicular_widths(box, tilt)
    best, best_area = None, math.inf
    for shape in _factorisations(n_ranks):
        if any(p > 1 and not periodic for p, periodic in zip(shape, pbc, strict=True)):
            continue
        brick = widths / np.array(shape, dtype=np.float64)
        if any(w < reach for w, periodic in zip(brick, pbc, strict=True) if periodic):
            continue
        area = brick[0] * brick[1] + brick[1] * brick[2] + brick[0] * brick[2]
        if area < best_area * (1.0 - 1e-12):
            best, best_area = shape, area
    if best is None:
        largest = largest_grid(box, tilt, pbc, reach)
        raise ValueError(
            f"{n_ranks} ranks cannot share this cell: no grid of {n_ranks} bricks keeps "
            f"every brick {what} = {reach:.4g} wide (the shell of ghost atoms each rank "
            f"keeps; cell widths {np.round(widths, 4).tolist()}); "
            + _counts_that_fit(n_ranks, largest)
        )
    return best


def _counts_that_fit(n_ranks: int, largest) -> str:
    """What a refusal of ``n_ranks`` says fits: the most ranks below it that some grid
    within ``largest`` takes, and ``largest`` itself."""
    top = math.prod(largest)
    fitting: dict[int, tuple[int, int, int]] = {}
    for a in range(largest[0], 0, -1):  # the first grid of a count cuts x most
        for b in range(largest[1], 0, -1):
            for c in range(largest[2], 0, -1):
                fitting.setdefault(a * b * c, (a, b, c))
    below = max((count for count in fitting if 1 < count < n_ranks), default=None)
    whole = f"the largest decomposition that fits is {list(largest)} ({top} ranks)"
    if top == 1:
        return f"{whole}: too small a system to share between ranks; run it on one rank"
    if below is None or below == top:
        return whole
    return f"{below} ranks work as well (grid {list(fitting[below])}), and {whole}"


def _factorisations(n: int):
    """Every (px, py, pz) with px py pz = n, px largest first."""
    for px in range(n, 0, -1):
        if n % px:
            continue
        for py in range(n // px, 0, -1):
            if (n // px) % py:
                continue
            yield px, py, n // px // py


def grid_candidates(n: int) -> list[tuple[int, int, int]]:
    """Every grid of ``n`` bricks (for messages and tests)."""
    return list(_factorisations(n))


def balanced_cuts(cuts, costs, minimum: float, damping: float = 0.5) -> NDArray[np.float64]:
    """Cuts along one axis that share the work ``costs`` evenly between its slabs.

    ``cuts`` are the axis's ``p + 1`` planes (fractions, 0 to 1), ``costs`` the work
    measured in each of its ``p`` slabs (the busy seconds of the ranks in it), taken as
    spread evenly across each slab: the targets are the planes that give every slab
    ``sum(costs) / p`` under that model (LAMMPS's ``balance shift`` does the same per
    dimension). Each inner plane moves ``damping`` of the way to its target (the model
    is only right near the planes; a full step overshoots), at most half the narrower
    slab beside it (so no atom's brick moves by more than one), and every slab keeps at
    least ``minimum`` of the cell (the ghost shell must fit in a brick).

    Examples
    --------
    >>> balanced_cuts([0.0, 0.5, 1.0], [3.0, 1.0], minimum=0.1, damping=1.0).tolist()
    [0.0, 0.3333333333333333, 1.0]
    >>> balanced_cuts([0.0, 0.5, 1.0], [3.0, 1.0], minimum=0.1).tolist()
    [0.0, 0.41666666666666663, 1.0]
    """
    cuts = np.asarray(cuts, dtype=np.float64)
    costs = np.maximum(np.asarray(costs, dtype=np.float64), 1e-300)
    p = len(costs)
    if len(cuts) != p + 1 or p * minimum > 1.0 + 1e-12:
        raise ValueError(f"{p} slabs of at least {minimum:.4g} do not fit cuts {cuts.tolist()}")
    cumulative = np.concatenate([[0.0], np.cumsum(costs)])
    targets = np.interp(np.arange(1, p) * cumulative[-1] / p, cumulative, cuts)
    widths = np.diff(cuts)
    new = cuts.copy()
    for k in range(1, p):
        limit = 0.5 * min(widths[k - 1], widths[k])
        new[k] = cuts[k] + np.clip(damping * (targets[k - 1] - cuts[k]), -limit, limit)
    for k in range(1, p):  # every slab at least minimum wide (feasible: p * minimum <= 1)
        new[k] = min(max(new[k], new[k - 1] + minimum), 1.0 - (p - k) * minimum)
    return new


# ------------------------------------------------------------------- kernels


@njit(cache=True, inline="always", error_model="numpy")
def _cell_fractions(positions, i, inverse, tilt, pbc):
    """Atom i's coordinates along the cell vectors, (sx, sy, sz); 0.5 along open axes.
    ``inverse`` holds 1 / box (:func:`_inverse_lengths`): every kernel that places atoms
    takes its fractions from here, so that they agree on the bricks to the last bit."""
    sz = positions[i, 2] * inverse[2] if pbc[2] else 0.5
    sy = (positions[i, 1] - sz * tilt[2]) * inverse[1] if pbc[1] else 0.5
    x = positions[i, 0] - sy * tilt[0] - sz * tilt[1]
    sx = x * inverse[0] if pbc[0] else 0.5
    return sx, sy, sz


@njit(cache=True, inline="always", error_model="numpy")
def _inverse_lengths(box):
    """1 / box, what :func:`_cell_fractions` multiplies by: a pass over 10^6 atoms dividing
    by the lengths took 3.9 ms on a Zen 4 EPYC (bound by the divider), multiplying 1.7."""
    return np.array([1.0 / box[0], 1.0 / box[1], 1.0 / box[2]])


@njit(cache=True, error_model="numpy")
def fractional_coordinates(positions, box, tilt, pbc, out):
    """Write each position's coordinates along the cell vectors (``s`` with ``r = s @ cell``)
    into ``out`` (N, 3); 0.5 along open axes, which are never cut. ``tilt`` is zero where
    an axis it couples is open (``md.box.periodic_tilt``)."""
    inverse = _inverse_lengths(box)
    for i in range(positions.shape[0]):
        sx, sy, sz = _cell_fractions(positions, i, inverse, tilt, pbc)
        out[i, 0] = sx
        out[i, 1] = sy
        out[i, 2] = sz


@njit(cache=True, inline="always", error_model="numpy")
def _slab(s, p, planes):
    """The slab of ``p`` holding the fraction ``s`` in [0, 1): the even grid's guess,
    then moved to the slab whose planes (a row of :meth:`Grid.cut_table`) enclose it."""
    c = min(max(int(s * p), 0), p - 1)  # s in [0, 1): truncation is the floor
    while c > 0 and s < planes[c]:
        c -= 1
    while c < p - 1 and s >= planes[c + 1]:
        c += 1
    return c


@njit(cache=True, error_model="numpy")
def brick_of(fractions, shape, cuts, out):
    """Write the grid coordinates of the brick holding each wrapped fractional position
    (rows of ``fractions``, taken modulo 1) into ``out`` (N, 3), int64; ``cuts`` is the
    grid's :meth:`Grid.cut_table`."""
    for i in range(fractions.shape[0]):
        for a in range(3):
            s = fractions[i, a] - np.floor(fractions[i, a])
            out[i, a] = _slab(s, shape[a], cuts[a])


@njit(cache=True, error_model="numpy")
def home_layout(positions, box, tilt, pbc, cell, center, bounds, widths, home, out, rows):
    """The owned atoms of a build at the periodic images nearest the brick centred on
    ``center``, in one pass: each atom's fractional coordinates there (``home``, N x 3;
    0.5 along open axes, which are never cut, as :func:`fractional_coordinates`), its
    position there (``out``: positions - n @ cell, ``cell``'s rows a, b, c, a plain copy
    where n = 0) and, for the atoms whose image n is not 0, their indices and images
    (``rows``, scratch of N x 3 int64). ``bounds`` are the brick's (2, 3) lower and upper
    fractional corners, ``widths`` the cell's perpendicular widths.

    Returns (imaged, images, strayed): the atoms with an image of their own
    (increasing), their images (int64 rows) and how far the farthest atom lies
    outside the brick [length]."""
    strayed = 0.0
    count = 0
    imaged = np.empty(positions.shape[0], dtype=np.int64)
    inverse = _inverse_lengths(box)
    for i in range(positions.shape[0]):
        sx, sy, sz = _cell_fractions(positions, i, inverse, tilt, pbc)
        kx = np.floor(sx - center[0] + 0.5) if pbc[0] else 0.0
        ky = np.floor(sy - center[1] + 0.5) if pbc[1] else 0.0
        kz = np.floor(sz - center[2] + 0.5) if pbc[2] else 0.0
        hx, hy, hz = sx - kx, sy - ky, sz - kz
        home[i, 0], home[i, 1], home[i, 2] = hx, hy, hz
        if pbc[0]:
            strayed = max(strayed, max(bounds[0, 0] - hx, hx - bounds[1, 0], 0.0) * widths[0])
        if pbc[1]:
            strayed = max(strayed, max(bounds[0, 1] - hy, hy - bounds[1, 1], 0.0) * widths[1])
        if pbc[2]:
            strayed = max(strayed, max(bounds[0, 2] - hz, hz - bounds[1, 2], 0.0) * widths[2])
        if kx != 0.0 or ky != 0.0 or kz != 0.0:
            for a in range(3):
                out[i, a] = positions[i, a] - (kx * cell[0, a] + ky * cell[1, a] + kz * cell[2, a])
            rows[count, 0], rows[count, 1], rows[count, 2] = int(kx), int(ky), int(kz)
            imaged[count] = i
            count += 1
        else:
            out[i, 0], out[i, 1], out[i, 2] = positions[i, 0], positions[i, 1], positions[i, 2]
    return imaged[:count].copy(), rows[:count].copy(), strayed


@njit(cache=True, error_model="numpy")
def leaving_along(positions, box, tilt, pbc, shape, cuts, axis, coordinate):
    """The atoms whose bricks lie one step up and one step down ``axis`` from the brick at
    ``coordinate`` along it (index arrays, increasing), and how many lie further away: the
    split of one migration sweep, in one pass (bricks as :func:`brick_of` of
    :func:`fractional_coordinates` finds them). With two bricks along the axis, "up"
    takes both neighbours."""
    n = positions.shape[0]
    p = shape[axis]
    up = np.empty(n, dtype=np.int64)
    down = np.empty(n, dtype=np.int64)
    n_up = 0
    n_down = 0
    lost = 0
    inverse = _inverse_lengths(box)
    own_lower, own_upper = cuts[axis][coordinate], cuts[axis][coordinate + 1]
    for i in range(n):
        # only the fractions the axis needs (z's for all, y's for x and y), as
        # _cell_fractions computes them
        sz = positions[i, 2] * inverse[2] if pbc[2] else 0.5
        f = sz
        if axis < 2:
            sy = (positions[i, 1] - sz * tilt[2]) * inverse[1] if pbc[1] else 0.5
            f = sy
            if axis == 0:
                x = positions[i, 0] - sy * tilt[0] - sz * tilt[1]
                f = x * inverse[0] if pbc[0] else 0.5
        f = f - np.floor(f)
        if own_lower <= f < own_upper:
            continue  # most atoms: still in this slab, as _slab would find
        c = _slab(f, p, cuts[axis])
        if c == coordinate:
            continue
        delta = c - coordinate if c > coordinate else c - coordinate + p
        if delta == 1:
            up[n_up] = i
            n_up += 1
        elif delta == p - 1:
            down[n_down] = i
            n_down += 1
        else:
            lost += 1
    return up[:n_up].copy(), down[:n_down].copy(), lost


@njit(cache=True, error_model="numpy")
def refill_plan(leaving, n, m):
    """Where a migration sweep puts the rows of a rank's arrays, in place: ``leaving`` (the
    rows that leave, increasing) of ``n`` rows, ``m`` rows arriving. Returns (sources,
    targets, arrivals): row ``sources[k]`` moves to row ``targets[k]``, arriving row j
    goes to ``arrivals[j]``; afterwards the first ``n - len(leaving) + m`` rows hold every
    staying and arriving atom. Arrivals fill the holes the leavers left (the lowest
    first), then go past the end; holes left over are filled by the staying rows past the
    new end, lowest first. Only the rows that move are touched: O(moved), not O(n)."""
    g = leaving.shape[0]
    size = n - g + m
    arrivals = np.empty(m, dtype=np.int64)
    filled = min(m, g)
    for j in range(filled):
        arrivals[j] = leaving[j]
    for j in range(filled, m):
        arrivals[j] = n + j - filled
    holes = 0  # holes below the new end, among leaving[filled:]
    for k in range(filled, g):
        if leaving[k] < size:
            holes += 1
    sources = np.empty(holes, dtype=np.int64)
    targets = np.empty(holes, dtype=np.int64)
    tail = size  # the staying rows at or past the new end, in increasing order
    skip = filled
    while skip < g and leaving[skip] < size:
        skip += 1
    for k in range(holes):
        while skip < g and leaving[skip] == tail:
            skip += 1
            tail += 1
        targets[k] = leaving[filled + k]
        sources[k] = tail
        tail += 1
    return sources, targets, arrivals


@njit(cache=True, error_model="numpy")
def refill_rows(values, sources, targets, incoming, arrivals):
    """Apply :func:`refill_plan` to a 2-D array in place: values[targets[k]] =
    values[sources[k]], then values[arrivals[j]] = incoming[j]."""
    for k in range(sources.shape[0]):
        for a in range(values.shape[1]):
            values[targets[k], a] = values[sources[k], a]
    for j in range(arrivals.shape[0]):
        for a in range(values.shape[1]):
            values[arrivals[j], a] = incoming[j, a]


@njit(cache=True, error_model="numpy")
def table_rows(positions, owned_fractions, ghost_fractions, ids, types, n_owned, send, out):
    """The rows a ghost sweep sends, one per local atom ``send[k]``: its position (3), its
    fractional coordinates (3: an owned atom's from ``owned_fractions``, a ghost's from
    ``ghost_fractions``, both at the image the local system holds), id and type."""
    for k in range(send.shape[0]):
        i = send[k]
        for a in range(3):
            out[k, a] = positions[i, a]
        if i < n_owned:
            for a in range(3):
                out[k, 3 + a] = owned_fractions[i, a]
        else:
            for a in range(3):
                out[k, 3 + a] = ghost_fractions[i - n_owned, a]
        out[k, 6] = ids[i]
        out[k, 7] = types[i]


@njit(cache=True, error_model="numpy")
def append_rows(rows, start, n_owned, positions, ghost_fractions, ids, types):
    """:func:`table_rows`' rows, received, as local atoms ``start`` onwards (ghosts)."""
    for k in range(rows.shape[0]):
        i = start + k
        for a in range(3):
            positions[i, a] = rows[k, a]
            ghost_fractions[i - n_owned, a] = rows[k, 3 + a]
        ids[i] = np.int64(rows[k, 6])
        types[i] = np.int32(rows[k, 7])


@njit(cache=True, error_model="numpy")
def near_faces(data, end, column, lower, upper):
    """Rows before ``end`` of fractional coordinates ``data`` (owned atoms' or ghosts')
    whose ``column`` lies below ``lower`` and at or above ``upper``: the atoms one sweep
    sends down and up."""
    below = np.empty(end, dtype=np.int64)
    above = np.empty(end, dtype=np.int64)
    n_below = 0
    n_above = 0
    for i in range(end):
        f = data[i, column]
        if f < lower:
            below[n_below] = i
            n_below += 1
        if f >= upper:
            above[n_above] = i
            n_above += 1
    return below[:n_below].copy(), above[:n_above].copy()


@njit(cache=True, error_model="numpy")
def home_positions(positions, listed, images, cell, out):
    """out[i] = positions[i] - n_i @ cell: each atom at the image nearest its brick
    (``cell``: rows a, b, c), where n_i is ``images[k]`` for ``i = listed[k]`` and 0 for
    every atom not listed (most of them: only atoms that crossed a periodic face since
    the positions were last wrapped have an image of their own). One copy and a short
    pass, not a product per atom: the same values (x - 0 is x)."""
    for i in range(positions.shape[0]):
        for a in range(3):
            out[i, a] = positions[i, a]
    shift_rows(positions, listed, images, cell, out)


@njit(cache=True, error_model="numpy")
def shift_rows(positions, listed, images, cell, out):
    """:func:`home_positions` for the listed atoms only (the others already copied)."""
    for k in range(listed.shape[0]):
        i = listed[k]
        n0, n1, n2 = images[k, 0], images[k, 1], images[k, 2]
        for a in range(3):
            out[i, a] = positions[i, a] - (n0 * cell[0, a] + n1 * cell[1, a] + n2 * cell[2, a])


@njit(cache=True, error_model="numpy")
def predicted_positions(positions, velocities, forces, masses, dt, out):
    """out = positions + dt v + dt^2 F / (2 m): where a velocity Verlet step of ``dt`` takes
    each atom; without the dt^2 term when ``forces`` has no rows."""
    half = 0.5 * dt * dt
    with_forces = forces.shape[0] == positions.shape[0]
    for i in range(positions.shape[0]):
        kick = half / masses[i] if with_forces else 0.0
        for a in range(3):
            move = dt * velocities[i, a]
            if with_forces:
                move += kick * forces[i, a]
            out[i, a] = positions[i, a] + move
    return out


@njit(cache=True, error_model="numpy")
def pack_rows(values, indices, shift, out):
    """out[k] = values[indices[k]] + shift (one row added to every row)."""
    for k in range(indices.shape[0]):
        i = indices[k]
        for a in range(values.shape[1]):
            out[k, a] = values[i, a] + shift[a]


@njit(cache=True, error_model="numpy")
def add_rows(values, indices, rows):
    """values[indices[k]] += rows[k], in order (``indices`` never repeat within a call)."""
    for k in range(indices.shape[0]):
        i = indices[k]
        for a in range(values.shape[1]):
            values[i, a] += rows[k, a]


@njit(cache=True, error_model="numpy")
def moved_since(positions, reference, mapping, previous, before, copy):
    """Return (largest squared distance of an atom from its build position carried along with
    the cell, ``reference[i] @ mapping``; largest squared move since ``previous``; the
    largest squared distance from the build position an atom may reach in its next move),
    all inf if a position is not finite. With ``copy`` (as many rows as ``positions``,
    else no rows), the positions are copied into it in the same pass (a decomposed run's
    local system takes its owned positions so, with one read of them a step).

    The next move is taken as the last one, s = x - previous, give or take how much the
    last move differed from the one before, (previous - before): |d + s| + 1.5 |s - s'|
    for each atom, d its distance from the build position (with no ``before``, rows 0,
    half its last move instead). A velocity Verlet move changes by dt^2 a from one step
    to the next, so that much of a margin is each atom's own, not the fastest one's.
    """
    since_build = 0.0
    since_previous = 0.0
    coming = 0.0
    finite = True
    known = before.shape[0] == positions.shape[0]
    copying = copy.shape[0] == positions.shape[0]
    for i in range(positions.shape[0]):
        d2 = 0.0
        s2 = 0.0
        c2 = 0.0
        e2 = 0.0
        for a in range(3):
            x = positions[i, a]
            if copying:
                copy[i, a] = x
            mapped = (reference[i, 0] * mapping[0, a] + reference[i, 1] * mapping[1, a]
                      + reference[i, 2] * mapping[2, a])  # fmt: skip
            d = x - mapped
            s = x - previous[i, a]
            d2 += d * d
            s2 += s * s
            c2 += (d + s) * (d + s)
            if known:
                e = s - (previous[i, a] - before[i, a])
                e2 += e * e
        if not (d2 < np.inf and s2 < np.inf):  # also NaN
            finite = False
        since_build = max(since_build, d2)
        since_previous = max(since_previous, s2)
        margin = 1.5 * np.sqrt(e2) if known else 0.5 * np.sqrt(s2)
        reach = np.sqrt(c2) + margin
        coming = max(coming, reach * reach)
    if not finite:
        return np.inf, np.inf, np.inf
    return since_build, since_previous, coming


@njit(cache=True, error_model="numpy")
def anchored_items(owned_ids, starts, order):
    """The items (bonds, angles) whose anchor atom is owned, and the local index of that
    anchor: ``order[starts[g]:starts[g + 1]]`` are the items of atom id g."""
    total = 0
    for i in range(owned_ids.shape[0]):
        g = owned_ids[i]
        if g + 1 < starts.shape[0]:
            total += starts[g + 1] - starts[g]
    items = np.empty(total, dtype=np.int64)
    anchors = np.empty(total, dtype=np.int64)
    k = 0
    for i in range(owned_ids.shape[0]):
        g = owned_ids[i]
        if g + 1 >= starts.shape[0]:
            continue
        for b in range(starts[g], starts[g + 1]):
            items[k] = order[b]
            anchors[k] = i
            k += 1
    return items, anchors


@njit(cache=True, error_model="numpy")
def nearest_copies(anchors, partners, sorted_ids, by_id, positions, lengths, inverse, tilt,
                   found, distances):  # fmt: skip
    """For each item k, the local copy of atom id ``partners[k]`` nearest to local atom
    ``anchors[k]`` (-1 and inf if it has none): ``sorted_ids`` are the local atoms' ids in
    increasing order, ``by_id`` the local index of each. Distances are minimum images
    along the local system's periodic axes (``lengths``, ``inverse`` and ``tilt`` as
    :func:`md.box.separation` takes them; zero along open axes)."""
    n = sorted_ids.shape[0]
    for k in range(anchors.shape[0]):
        a = anchors[k]
        g = partners[k]
        j = np.searchsorted(sorted_ids, g)
        best = -1
        best2 = np.inf
        while j < n and sorted_ids[j] == g:
            c = by_id[j]
            dx, dy, dz = separation(positions, c, a, lengths, inverse, tilt)
            d2 = dx * dx + dy * dy + dz * dz
            if d2 < best2:
                best, best2 = c, d2
            j += 1
        found[k] = best
        distances[k] = np.sqrt(best2)


__all__ = [
    "Grid",
    "add_rows",
    "append_rows",
    "anchored_items",
    "balanced_cuts",
    "brick_of",
    "brick_widths",
    "check_grid",
    "choose_grid",
    "fractional_coordinates",
    "grid_candidates",
    "home_layout",
    "home_positions",
    "largest_grid",
    "local_periodic_axes",
    "leaving_along",
    "moved_since",
    "near_faces",
    "nearest_copies",
    "pack_rows",
    "predicted_positions",
    "refill_plan",
    "refill_rows",
    "shift_rows",
    "table_rows",
]
