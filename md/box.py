"""All box geometry in one place: cell matrices, minimum image and wrapping.

A periodic cell is kept in the *restricted triclinic* form that LAMMPS and
HOOMD-blue use: edge lengths ``box = (Lx, Ly, Lz)`` and tilt factors
``tilt = (xy, xz, yz)``, so the cell vectors (rows of :func:`cell_matrix`) are

    a = (Lx, 0, 0),  b = (xy, Ly, 0),  c = (xz, yz, Lz).

Any right- or left-handed cell can be rotated into this form
(:func:`restricted_cell`); the edges of ASE, MDAnalysis and the trajectory
files go through it. A tilt factor couples two axes and may be non-zero only
when both are periodic. Orthorhombic boxes (zero tilt) are the common case and
cost nothing extra: kernels multiply by the zero tilts.

Kernels receive the box as three arrays computed here: ``periodic_lengths``
and their inverses, zero along open axes (so the minimum image is a no-op
there without a branch), and the tilt factors. The minimum image reduces a
displacement along c, then b, then a (:func:`min_image`); that finds the
nearest image of every pair closer than half the smallest perpendicular width
of the cell (:func:`perpendicular_widths`), whatever the tilt, which is the
condition neighbour lists check.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

#: Tilt factors in the order they are stored: (xy, xz, yz).
TILT_NAMES = ("xy", "xz", "yz")
#: The two axes each tilt factor couples.
TILT_AXES = ((0, 1), (0, 2), (1, 2))


def cell_matrix(box, tilt=None) -> NDArray[np.float64]:
    """Return the (3, 3) cell matrix, one cell vector per row (lower triangular)."""
    box = np.asarray(box, dtype=np.float64)
    xy, xz, yz = (0.0, 0.0, 0.0) if tilt is None else np.asarray(tilt, dtype=np.float64)
    return np.array([[box[0], 0.0, 0.0], [xy, box[1], 0.0], [xz, yz, box[2]]])


def is_orthorhombic(tilt) -> bool:
    return tilt is None or not np.any(np.asarray(tilt) != 0.0)


def perpendicular_widths(box, tilt=None) -> NDArray[np.float64]:
    """Distances between opposite faces of the cell along each axis [length].

    For an orthorhombic box these are the edges; tilt only makes them shorter.
    The minimum-image convention holds for pairs closer than half the smallest.
    A zero edge (an open axis without a length, as a slab read without its c
    vector) counts as a unit edge, so the widths across the others stay finite.
    """
    box = np.asarray(box, dtype=np.float64)
    if is_orthorhombic(tilt):
        return box.copy()
    h = cell_matrix(np.where(box > 0.0, box, 1.0), tilt)
    volume = abs(np.linalg.det(h))
    a, b, c = h
    return np.array(
        [
            volume / np.linalg.norm(np.cross(b, c)),
            volume / np.linalg.norm(np.cross(c, a)),
            volume / np.linalg.norm(np.cross(a, b)),
        ]
    )


def periodic_lengths(box: NDArray[np.float64], pbc: NDArray[np.bool_]):
    """Return ``(lengths, inverse_lengths)``, zero along non-periodic axes."""
    lengths = np.where(pbc, box, 0.0).astype(np.float64)
    inverse = np.zeros(3)
    inverse[pbc] = 1.0 / box[pbc]
    return lengths, inverse


def periodic_tilt(tilt, pbc) -> NDArray[np.float64]:
    """Tilt factors as kernels take them: a float64 (3,) array, zero where an axis is open."""
    out = np.zeros(3) if tilt is None else np.array(tilt, dtype=np.float64)
    pbc = np.asarray(pbc, dtype=bool)
    for k, (i, j) in enumerate(TILT_AXES):
        if not (pbc[i] and pbc[j]):
            out[k] = 0.0
    return out


def minimum_image(displacements: NDArray[np.float64], box, pbc, tilt=None) -> NDArray[np.float64]:
    """Return displacement vectors reduced to their minimum image (numpy)."""
    lengths, inverse = periodic_lengths(np.asarray(box, float), np.asarray(pbc, bool))
    xy, xz, yz = periodic_tilt(tilt, pbc)
    d = np.array(displacements, dtype=np.float64)
    n = np.rint(d[..., 2] * inverse[2])
    d[..., 2] -= n * lengths[2]
    d[..., 1] -= n * yz
    d[..., 0] -= n * xz
    n = np.rint(d[..., 1] * inverse[1])
    d[..., 1] -= n * lengths[1]
    d[..., 0] -= n * xy
    d[..., 0] -= lengths[0] * np.rint(d[..., 0] * inverse[0])
    return d


def fractional(positions, box, pbc, tilt=None) -> NDArray[np.float64]:
    """Cell coordinates times the edge lengths ("sheared back" coordinates).

    Along a periodic axis the value is ``s * L`` with s the fractional
    coordinate along that cell vector, so wrapping by one cell vector changes
    it by exactly L and no other; along an open axis it is the coordinate.
    Equal to the positions for an orthorhombic box.
    """
    box = np.asarray(box, dtype=np.float64)
    xy, xz, yz = periodic_tilt(tilt, pbc)
    g = np.array(positions, dtype=np.float64)
    if xy == 0.0 and xz == 0.0 and yz == 0.0:
        return g
    sz = g[..., 2] / box[2] if yz or xz else 0.0
    g[..., 1] -= sz * yz
    sy = g[..., 1] / box[1] if xy else 0.0
    g[..., 0] -= sy * xy + sz * xz
    return g


def wrap(positions: NDArray[np.float64], box, pbc, tilt=None):
    """Return ``(wrapped, images)``: positions mapped into the cell on periodic axes.

    ``images`` counts cell vectors: ``wrapped + images @ cell_matrix(box,
    tilt)`` recovers the input up to round-off. Open axes are left as they
    are, with image 0.
    """
    box = np.asarray(box, dtype=np.float64)
    pbc = np.asarray(pbc, dtype=bool)
    positions = np.asarray(positions, dtype=np.float64)
    g = fractional(positions, box, pbc, tilt)
    images = np.zeros(np.shape(positions), dtype=np.int32)
    images[:, pbc] = np.floor(g[:, pbc] / box[pbc]).astype(np.int32)
    h = cell_matrix(box, periodic_tilt(tilt, pbc))
    wrapped = positions - images @ h
    # floor() can leave a value equal to L after the subtraction by round-off.
    g = fractional(wrapped, box, pbc, tilt)
    over = np.zeros(images.shape, dtype=bool)
    over[:, pbc] = g[:, pbc] >= box[pbc]
    if over.any():
        images += over
        wrapped -= over.astype(np.float64) @ h
    return wrapped, images


def restricted_cell(cell, what: str = "cell"):
    """Return ``(box, tilt, rotation)`` of any (3, 3) cell matrix (rows: cell vectors).

    ``rotation`` is the orthogonal matrix Q with ``cell @ Q`` lower triangular
    with a positive diagonal (a along x, b in the xy plane): positions in the
    engine's frame are ``user_positions @ Q``, and forces and stresses go back
    as ``f @ Q.T`` and ``Q @ sigma @ Q.T``. Q is exactly the identity for a
    cell that is already lower triangular with a positive diagonal, so those
    pass through bit for bit. A left-handed cell keeps its lattice: its third
    vector is negated (the same lattice), so Q is always a rotation. Rows of
    zeros (open axes with no length) are allowed when the other rows are
    orthogonal to them.

    Raises
    ------
    ValueError
        If ``cell`` is not a finite (3, 3) matrix, or its rows are linearly
        dependent.
    """
    h = np.asarray(cell, dtype=np.float64)
    if h.shape != (3, 3):
        raise ValueError(f"{what} must be a (3, 3) matrix, got shape {h.shape}")
    if not np.all(np.isfinite(h)):
        raise ValueError(f"{what} has entries that are not finite: {h.tolist()}")
    scale = max(1.0, float(np.abs(h).max()))
    tolerance = 1e-12 * scale
    upper = np.array([h[0, 1], h[0, 2], h[1, 2]])
    if np.all(np.abs(upper) <= tolerance):
        # Already in the engine's frame (or a diagonal cell with negative
        # entries, whose lattice is that of their absolute values).
        box = np.abs(np.diag(h)).copy()
        tilt = np.array([h[1, 0], h[2, 0], h[2, 1]])
        if np.all(np.diag(h) >= 0) or np.all(np.abs(tilt) <= tolerance):
            return box, np.where(np.abs(tilt) <= tolerance, 0.0, tilt), np.eye(3)
    norms = np.linalg.norm(h, axis=1)
    zero = norms <= tolerance
    if zero.any():
        raise ValueError(
            f"{what} has a zero cell vector (an open axis) and is not aligned with the "
            f"coordinate axes; only a diagonal cell may have zero rows: {h.tolist()}"
        )
    a, b, c = h
    e1 = a / norms[0]
    b_perp = b - (b @ e1) * e1
    if np.linalg.norm(b_perp) <= tolerance:
        raise ValueError(f"{what} has parallel cell vectors a and b: {h.tolist()}")
    e2 = b_perp / np.linalg.norm(b_perp)
    e3 = np.cross(e1, e2)
    if abs(c @ e3) <= tolerance:
        raise ValueError(f"{what} has linearly dependent cell vectors: {h.tolist()}")
    if c @ e3 < 0:
        c = -c  # a left-handed cell: the same lattice with the third vector reversed
    rotation = np.stack([e1, e2, e3], axis=1)
    lower = np.stack([a, b, c]) @ rotation
    box = np.array([lower[0, 0], lower[1, 1], lower[2, 2]])
    tilt = np.array([lower[1, 0], lower[2, 0], lower[2, 1]])
    return box, np.where(np.abs(tilt) <= tolerance, 0.0, tilt), rotation


def reduced_tilt(box, tilt, pbc) -> NDArray[np.float64]:
    """Tilt factors brought within half an edge by changing the cell basis.

    The same lattice, described by the shortest tilts (LAMMPS "flips" its box
    this way when a sheared cell tilts too far): ``|xy| <= Lx/2``,
    ``|xz| <= Lx/2`` and ``|yz| <= Ly/2``. Positions need no change: they
    are unwrapped, and wrapped positions are recomputed from the new cell.
    """
    box = np.asarray(box, dtype=np.float64)
    xy, xz, yz = periodic_tilt(tilt, pbc)
    if pbc[1] and pbc[2] and box[1] > 0:
        n = np.rint(yz / box[1])  # c -= n b
        yz -= n * box[1]
        xz -= n * xy
    if pbc[0] and box[0] > 0:
        xz -= np.rint(xz / box[0]) * box[0]  # c -= m a
        xy -= np.rint(xy / box[0]) * box[0]  # b -= m a
    return np.array([xy, xz, yz])


#: Room left between the outermost atom and a side of :func:`enclosing_cell` it defines.
_MARGIN = 0.5


def enclosing_cell(positions, box, pbc, tilt=None):
    """Return ``(origin, lengths, tilt)`` of a cell that holds the atoms along open axes.

    What viewers and file formats that need a box with a volume are given.
    Periodic axes keep their edge (origin 0); an open axis spans its stored
    edge ``[0, L]``, widened where atoms lie outside it, or, where the edge is
    zero (a cluster or slab read from a file without a cell there), the
    atoms' extent alone: their bounding box. A side that atoms define lies
    half a length unit beyond the outermost one (LAMMPS assigns an atom to a
    box only if ``lo <= x < hi``).
    Tilts that involve an open axis are dropped, as the kernels drop them.
    """
    pbc = np.asarray(pbc, dtype=bool)
    lengths = np.array(box, dtype=np.float64)
    origin = np.zeros(3)
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    for axis in np.flatnonzero(~pbc):
        low, high = 0.0, float(lengths[axis])
        if len(positions):
            first, last = float(positions[:, axis].min()), float(positions[:, axis].max())
            if not high > 0.0 or first < low:
                low = first - _MARGIN
            if not high > 0.0 or last >= high:
                high = last + _MARGIN
        if not high > low:
            low, high = low - _MARGIN, high + _MARGIN
        origin[axis], lengths[axis] = low, high - low
    return origin, lengths, periodic_tilt(tilt, pbc)


def cell_deformation(box_before, tilt_before, box_after, tilt_after, pbc) -> NDArray[np.float64]:
    """The deformation M that took the cell from before to after (rows: ``H1 = H0 M``).

    Positions that followed the cell affinely moved as ``r -> r M`` (what a
    barostat does). A cell whose tilt was flipped to the equivalent shorter
    one (:func:`reduced_tilt`) after the move is recognised: its basis change,
    an integer matrix U with ``H1 ~ U H0`` for a small deformation, is undone
    first. Open axes take a unit length, so M is the identity along them.
    """
    pbc = np.asarray(pbc, dtype=bool)
    before = cell_matrix(np.where(pbc, box_before, 1.0), periodic_tilt(tilt_before, pbc))
    after = cell_matrix(np.where(pbc, box_after, 1.0), periodic_tilt(tilt_after, pbc))
    basis = np.rint(after @ np.linalg.inv(before))
    if not np.array_equal(basis, np.eye(3)) and abs(round(np.linalg.det(basis))) == 1:
        after = np.linalg.solve(basis, after)  # the cell before its flip
    return np.linalg.solve(before, after)


@njit(cache=True, inline="always", error_model="numpy")
def min_image_component(d, length, inverse):
    """Minimum image of one displacement component (length 0: open axis)."""
    return d - length * np.rint(d * inverse)


@njit(cache=True, inline="always", error_model="numpy")
def min_image(dx, dy, dz, lengths, inverse, tilt):
    """Minimum image of a displacement in a restricted triclinic cell: along c, b, then a.

    ``lengths`` and ``inverse`` are zero along open axes, ``tilt`` is
    (xy, xz, yz); for zero tilt this is the orthorhombic minimum image.
    """
    n = np.rint(dz * inverse[2])
    dz -= n * lengths[2]
    dy -= n * tilt[2]
    dx -= n * tilt[1]
    n = np.rint(dy * inverse[1])
    dy -= n * lengths[1]
    dx -= n * tilt[0]
    dx -= lengths[0] * np.rint(dx * inverse[0])
    return dx, dy, dz


@njit(cache=True, inline="always", error_model="numpy")
def separation(positions, i, j, lengths, inverse, tilt):
    """Minimum image of ``positions[i] - positions[j]`` (see :func:`min_image`)."""
    return min_image(
        positions[i, 0] - positions[j, 0],
        positions[i, 1] - positions[j, 1],
        positions[i, 2] - positions[j, 2],
        lengths,
        inverse,
        tilt,
    )
