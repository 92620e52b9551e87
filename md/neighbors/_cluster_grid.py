"""The grid of the cluster-pair list (:class:`md.neighbors.NeighborList` with ``clusters=True``).

GROMACS's pair-search layout (its "nbnxm" grid), written here for numba: the
box's xy plane is cut into columns about (4 / density)^(1/3) wide
(:func:`column_counts`), each column's atoms sorted by z and cut into clusters of
``CLUSTER`` (4) atoms, the last one of a column padded with fillers
(:func:`cluster_grid`). The search over the grid is
:mod:`md.neighbors._cluster_search`; the clusters' relative positions, the atom-pair
check and the prune are :mod:`md.neighbors._cluster_prune`.

A cluster's atoms are stored relative to an origin per slot (the cluster's
centre plus the box lengths that wrapped the atom at the build), so float32
keeps its precision in any box; a cluster pair carries its offset, the
difference of the two centres less the periodic image shift, so the
separation of atoms a and b of clusters (i, j) is ``x[i, a] - x[j, b] +
offset``: no minimum image, and the float32 offset is the double one rounded
once.

Only fully periodic, orthorhombic cells wide enough that no cluster meets
another one's image twice (the caller checks): the slot frame serves the rest.

The kernels of ``_cluster_prune`` (and the search's copies of them) compile ``CLUSTER``
and ``FILLER`` in as constants; an edit here makes their cache entries stale, as the
kernel cache stamps each entry with the modules its file imports (``md._kernel_cache``),
so they compile afresh with the new values.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from md._memory import KeptArrays

#: Atoms per cluster (the kernels' i and j clusters alike).
CLUSTER = 4
#: The most atoms in one slab of a column that the grid's insertion sort takes (more: a
#: merge sort of the column).
_CROWDED_SLAB = 32
#: A filler's z relative to its cluster's origin: ``-FILLER`` in the j role, ``+FILLER``
#: in the i role (so two fillers never meet), spread 10 apart in x within a cluster. Not
#: farther: float32's 1/r^12 underflows into slow denormals past r ~ 1400, and the
#: kernels' masks keep fillers out of every sum anyway.
FILLER = 100.0
#: The fraction of a box edge below which a coordinate's quotient by the edge is surely
#: below 1 (not rounded up to it): the wrap's fast path.
_INSIDE = 1.0 - 1e-9


@njit(cache=True, error_model="numpy")
def column_counts(box, n_atoms, radius):
    """(ncx, ncy): columns about (CLUSTER / density)^(1/3) wide, so that a cluster is
    about as tall as wide; more, narrower ones where fewer would let a column meet two
    images of another within ``radius`` (2 reach + 1 columns across at least: a sparse
    system). The box must be wider than twice ``radius``."""
    density = n_atoms / (box[0] * box[1] * box[2])
    side = (CLUSTER / density) ** (1.0 / 3.0)
    counts = [0, 0]
    for axis in range(2):
        count = max(1, int(box[axis] / side))
        while count < 2 * int(np.ceil(radius * count / box[axis])) + 1:
            count += 1
        counts[axis] = count
    return counts[0], counts[1]


def cluster_grid(positions, box, ncx, ncy, chunks=1, kept: KeptArrays | None = None):
    """Sort atoms into columns, each by z, cut into clusters of ``CLUSTER``.

    Returns (first, atom, origin, lower, upper): ``first[c]`` the first cluster of
    column c (ncx * ncy + 1 entries); ``atom[s]`` the atom in slot s (cluster s //
    CLUSTER), -1 for a filler; ``origin[s]`` the slot's origin (the cluster's centre
    plus the wrap of its atom, which subtracted from the atom's position gives its
    place relative to the centre); the clusters' bounding boxes ``lower``/``upper``
    (clusters, 3) in the wrapped frame. With ``kept``, every array (these and the
    scratch) is written into the arrays kept there (:class:`KeptArrays`), views of
    them: valid until the next grid made with the same ``kept``.

    On the threads, the same arrays bit for bit on any number: the atoms' wrap in
    ``chunks`` runs, the columns' z sorts and the clusters' boxes in parallel; the
    count and stable scatter of the atoms into columns serial (at 2 threads 0.60-0.69 of
    the time on one, 32000 atoms; at 1 thread the time of the serial loops it
    replaced, 864 atoms to 32000).

    The scatter sorts by column and by a slab in z (about one atom per column and slab),
    so that each column's z sort, an insertion sort, has only the atoms within a slab to
    order: the same order as a stable sort of the column's atoms by z.
    """
    if kept is None:
        kept = KeptArrays()
    n = positions.shape[0]
    n_columns = ncx * ncy
    slabs = max(1, n // n_columns)
    # at most one padded cluster per column more than the atoms fill
    room = (n + CLUSTER - 1) // CLUSTER + n_columns
    arrays = (
        kept.take("grid wrapped", n, np.float64, (3,)),
        kept.take("grid key", n, np.int64),
        kept.take("grid counts", n_columns * slabs + 1, np.int64),
        kept.take("grid fill", n_columns * slabs, np.int64),
        kept.take("grid order", n, np.int64),
        kept.take("grid first", n_columns + 1, np.int64),
        kept.take("grid heights", n, np.float64),
        kept.take("grid atom", room * CLUSTER, np.int64),
        kept.take("grid origin", room * CLUSTER, np.float64, (3,)),
        kept.take("grid lower", room, np.float64, (3,)),
        kept.take("grid upper", room, np.float64, (3,)),
    )
    first, atom, origin, lower, upper = arrays[5], *arrays[7:]
    n_clusters = _cluster_grid(positions, box, ncx, ncy, chunks, slabs, *arrays)
    return (
        first,
        atom[: n_clusters * CLUSTER],
        origin[: n_clusters * CLUSTER],
        lower[:n_clusters],
        upper[:n_clusters],
    )


@njit(cache=True, parallel=True, error_model="numpy")
def _cluster_grid(
    positions,
    box,
    ncx,
    ncy,
    chunks,
    slabs,
    wrapped,
    key,
    counts,
    fill,
    order,
    first,
    heights,
    atom,
    origin,
    lower,
    upper,
):
    """:func:`cluster_grid` into the arrays given (the first ones scratch; ``atom``,
    ``origin``, ``lower`` and ``upper`` with room for every cluster); returns the
    clusters."""
    n = positions.shape[0]
    n_columns = ncx * ncy
    for t in prange(chunks):
        _wrap_atoms(
            positions, box, ncx, ncy, slabs, wrapped, key, t * n // chunks, (t + 1) * n // chunks
        )
    _column_order(key, n_columns, slabs, counts, fill, order, first)
    n_clusters = first[n_columns]
    atom[: n_clusters * CLUSTER] = -1
    for c in prange(n_columns):
        _column_atoms(wrapped, counts, order, first, heights, atom, c, slabs)
    for cl in prange(n_clusters):
        _cluster_box(positions, wrapped, atom, origin, lower, upper, cl)
    return n_clusters


@njit(cache=True, inline="always", error_model="numpy")
def _wrap_atoms(positions, box, ncx, ncy, slabs, wrapped, key, begin, end):
    """Atoms ``begin`` to ``end`` wrapped into the box, and their keys: column times
    ``slabs`` plus the slab in z."""
    # below inside[d] (and not negative) an atom's floor(x / box) is 0, and its wrap x + 0.0
    # (-0.0 becomes 0.0, as x - floor(x / box) * box makes it), with no division: most atoms
    inside = (box[0] * _INSIDE, box[1] * _INSIDE, box[2] * _INSIDE)
    for i in range(begin, end):
        for d in range(3):
            x = positions[i, d]
            if 0.0 <= x < inside[d]:
                wrapped[i, d] = x + 0.0
                continue
            wrapped[i, d] = x - np.floor(x / box[d]) * box[d]
            if wrapped[i, d] >= box[d]:  # rounding of a tiny negative coordinate
                wrapped[i, d] -= box[d]
        cx = min(int(wrapped[i, 0] * ncx / box[0]), ncx - 1)
        cy = min(int(wrapped[i, 1] * ncy / box[1]), ncy - 1)
        cz = min(int(wrapped[i, 2] * slabs / box[2]), slabs - 1)
        key[i] = (cx * ncy + cy) * slabs + cz


@njit(cache=True, error_model="numpy")
def _column_order(key, n_columns, slabs, counts, fill, order, first):
    """Into ``counts``, ``order`` and ``first``: the atoms' offsets per key (n_columns *
    slabs + 1), the atoms grouped by key in atom order (a stable counting sort), and each
    column's first cluster (n_columns + 1). ``fill``: scratch, n_columns * slabs."""
    n = key.shape[0]
    n_keys = n_columns * slabs
    counts[:] = 0
    for i in range(n):
        counts[key[i] + 1] += 1
    for c in range(n_keys):
        counts[c + 1] += counts[c]
    fill[:] = counts[:-1]
    for i in range(n):
        order[fill[key[i]]] = i
        fill[key[i]] += 1
    first[0] = 0
    for c in range(n_columns):
        in_column = counts[(c + 1) * slabs] - counts[c * slabs]
        first[c + 1] = first[c] + (in_column + CLUSTER - 1) // CLUSTER


@njit(cache=True, inline="always", error_model="numpy")
def _column_atoms(wrapped, counts, order, first, heights, atom, c, slabs):
    """Column c's atoms sorted by z into its clusters' slots: by slab already, then an
    insertion sort (stable: equal z keep their order, which is the atoms'); a merge sort
    where a slab holds many atoms (a film, a droplet), which would make that quadratic."""
    a, b = counts[c * slabs], counts[(c + 1) * slabs]
    base = first[c] * CLUSTER - a
    crowded = 0
    for z in range(c * slabs, (c + 1) * slabs):
        crowded = max(crowded, counts[z + 1] - counts[z])
    if crowded > _CROWDED_SLAB:
        for m in range(a, b):
            heights[m] = wrapped[order[m], 2]
        by_z = np.argsort(heights[a:b], kind="mergesort")  # stable: as the insertion sort
        for m in range(b - a):
            atom[base + a + m] = order[a + by_z[m]]
        return
    for m in range(a, b):
        i = order[m]
        z = wrapped[i, 2]
        p = m
        while p > a and heights[p - 1] > z:
            heights[p] = heights[p - 1]
            atom[base + p] = atom[base + p - 1]
            p -= 1
        heights[p] = z
        atom[base + p] = i


@njit(cache=True, inline="always", error_model="numpy")
def _cluster_box(positions, wrapped, atom, origin, lower, upper, cl):
    """Cluster cl's bounding box (wrapped frame) and its slots' origins."""
    # the corners in locals, stored once (through the arrays LLVM reloaded and stored them
    # at every atom: they might have been the positions)
    x0 = y0 = z0 = np.inf
    x1 = y1 = z1 = -np.inf
    for b in range(CLUSTER):
        i = atom[cl * CLUSTER + b]
        if i >= 0:
            x0, x1 = min(x0, wrapped[i, 0]), max(x1, wrapped[i, 0])
            y0, y1 = min(y0, wrapped[i, 1]), max(y1, wrapped[i, 1])
            z0, z1 = min(z0, wrapped[i, 2]), max(z1, wrapped[i, 2])
    lower[cl, 0], lower[cl, 1], lower[cl, 2] = x0, y0, z0
    upper[cl, 0], upper[cl, 1], upper[cl, 2] = x1, y1, z1
    centre = (0.5 * (x0 + x1), 0.5 * (y0 + y1), 0.5 * (z0 + z1))
    for b in range(CLUSTER):
        s = cl * CLUSTER + b
        i = atom[s]
        for d in range(3):
            origin[s, d] = centre[d] + (positions[i, d] - wrapped[i, d] if i >= 0 else 0.0)
