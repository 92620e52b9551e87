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
go to the six face neighbours (:mod:`md.distributed.halo`). This module holds the
grid arithmetic and the choice of grid (it imports no MPI); the kernels of the
exchange that work in the grid's coordinates are in
``md/distributed/_domain_kernels.py``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from md.box import TILT_AXES, perpendicular_widths


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
                raise ValueError(
                    f"the cuts along {'xyz'[axis]} must be {p + 1} increasing "
                    f"fractions from 0 to 1, got {list(planes)}"
                )
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
        return np.array(
            [[self.cuts[a][c[a]] for a in range(3)], [self.cuts[a][c[a] + 1] for a in range(3)]]
        )

    def cut_table(self) -> NDArray[np.float64]:
        """(3, max p + 1) array of the cuts, each row padded with 1.0 (for the kernels)."""
        table = np.ones((3, max(self.shape) + 1))
        for axis, planes in enumerate(self.cuts):
            table[axis, : len(planes)] = planes
        return table

    def thinnest(self) -> NDArray[np.float64]:
        """(3,): the thinnest brick along each axis, as a fraction of the cell."""
        return np.array([min(np.diff(planes)) for planes in self.cuts])

    def balanced(self, busy, widths, room: float) -> Grid:
        """This grid with its planes moved towards an even share of the ranks' ``busy``
        seconds (:func:`balanced_cuts` along each cut axis), every brick at least ``room``
        wide (the cell's perpendicular ``widths``) [length]."""
        grid = self
        where = np.array([self.coordinates(rank) for rank in range(self.n_ranks)])
        for axis in range(3):
            p = self.shape[axis]
            if p == 1 or p * room > widths[axis]:
                continue
            costs = np.bincount(where[:, axis], weights=busy, minlength=p)
            grid = grid.with_cuts(axis, balanced_cuts(grid.cuts[axis], costs, room / widths[axis]))
        return grid

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


def choose_grid(
    n_ranks: int, box, tilt, pbc, reach: float, what: str = "cutoff + skin"
) -> tuple[int, int, int]:
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


__all__ = [
    "Grid",
    "balanced_cuts",
    "brick_widths",
    "check_grid",
    "choose_grid",
    "grid_candidates",
    "largest_grid",
    "local_periodic_axes",
]
