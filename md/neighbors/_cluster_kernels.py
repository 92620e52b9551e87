"""Kernels of the cluster-pair list (:class:`md.neighbors.NeighborList` with ``clusters=True``).

GROMACS's pair-search layout (its "nbnxm" grid), written here for numba: the
box's xy plane is cut into columns about (4 / density)^(1/3) wide, each
column's atoms sorted by z and cut into clusters of ``CLUSTER`` (4) atoms, the
last one of a column padded with fillers. A cluster pair is listed when one of
its atom pairs lies within the list radius (:func:`search_pairs`: per i cluster,
the neighbouring columns whose xy bounding box comes within reach of the
column's and the cluster's own, a window of j clusters in z in each, then each
candidate checked atom by atom); the pair kernels evaluate all 4 x 4 atom pairs
of each listed cluster pair, in SIMD lanes.

A cluster's atoms are stored relative to an origin per slot (the cluster's
centre plus the box lengths that wrapped the atom at the build), so float32
keeps its precision in any box; a cluster pair carries its offset, the
difference of the two centres less the periodic image shift, so the
separation of atoms a and b of clusters (i, j) is ``x[i, a] - x[j, b] +
offset``: no minimum image, and the float32 offset is the double one rounded
once.

Only fully periodic, orthorhombic cells wide enough that no cluster meets
another one's image twice (the caller checks): the slot frame serves the rest.

A note on its length (about 1300 lines, over the 800 where a module is split): its
kernels take their arrays as arguments, and the formatter writes a long argument list a
line per argument (about 140 of its lines); they are one grid and its search, and stay
together.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, prange, types
from numba.core import cgutils
from numba.extending import intrinsic

from md._simd import (
    ZMM,
    array_data,
    cluster_i_halves,
    cluster_j_less,
    python_twin,
    splat,
    squared_distances,
)

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


@njit(cache=True, parallel=True, error_model="numpy")
def cluster_grid(positions, box, ncx, ncy, chunks=1):
    """Sort atoms into columns, each by z, cut into clusters of ``CLUSTER``.

    Returns (first, atom, origin, lower, upper): ``first[c]`` the first cluster of
    column c (ncx * ncy + 1 entries); ``atom[s]`` the atom in slot s (cluster s //
    CLUSTER), -1 for a filler; ``origin[s]`` the slot's origin (the cluster's centre
    plus the wrap of its atom, which subtracted from the atom's position gives its
    place relative to the centre); the clusters' bounding boxes ``lower``/``upper``
    (clusters, 3) in the wrapped frame.

    On the threads, the same arrays bit for bit on any number: the atoms' wrap in
    ``chunks`` runs, the columns' z sorts and the clusters' boxes in parallel; the
    count and stable scatter of the atoms into columns serial (at 2 threads 0.60-0.69 of
    the time on one, 32000 atoms; at 1 thread the time of the serial loops it
    replaced, 864 atoms to 32000).

    The scatter sorts by column and by a slab in z (about one atom per column and slab),
    so that each column's z sort, an insertion sort, has only the atoms within a slab to
    order: the same order as a stable sort of the column's atoms by z.
    """
    n = positions.shape[0]
    n_columns = ncx * ncy
    slabs = max(1, n // n_columns)
    wrapped = np.empty((n, 3))
    key = np.empty(n, np.int64)
    for t in prange(chunks):
        _wrap_atoms(
            positions, box, ncx, ncy, slabs, wrapped, key, t * n // chunks, (t + 1) * n // chunks
        )
    counts, order, first = _column_order(key, n_columns, slabs)
    atom = np.full(first[-1] * CLUSTER, -1, np.int64)
    heights = np.empty(n)
    for c in prange(n_columns):
        _column_atoms(wrapped, counts, order, first, heights, atom, c, slabs)
    origin, lower, upper = _grid_boxes(first[-1])
    for cl in prange(first[-1]):
        _cluster_box(positions, wrapped, atom, origin, lower, upper, cl)
    return first, atom, origin, lower, upper


@njit(cache=True, inline="always", error_model="numpy")
def _wrap_atoms(positions, box, ncx, ncy, slabs, wrapped, key, begin, end):
    """Atoms ``begin`` to ``end`` wrapped into the box, and their keys: column times
    ``slabs`` plus the slab in z."""
    for i in range(begin, end):
        for d in range(3):
            wrapped[i, d] = positions[i, d] - np.floor(positions[i, d] / box[d]) * box[d]
            if wrapped[i, d] >= box[d]:  # rounding of a tiny negative coordinate
                wrapped[i, d] -= box[d]
        cx = min(int(wrapped[i, 0] * ncx / box[0]), ncx - 1)
        cy = min(int(wrapped[i, 1] * ncy / box[1]), ncy - 1)
        cz = min(int(wrapped[i, 2] * slabs / box[2]), slabs - 1)
        key[i] = (cx * ncy + cy) * slabs + cz


@njit(cache=True, error_model="numpy")
def _column_order(key, n_columns, slabs):
    """(counts, order, first): the atoms' offsets per key (n_columns * slabs + 1), the
    atoms grouped by key in atom order (a stable counting sort), and each column's first
    cluster (n_columns + 1)."""
    n = key.shape[0]
    n_keys = n_columns * slabs
    counts = np.zeros(n_keys + 1, np.int64)
    for i in range(n):
        counts[key[i] + 1] += 1
    for c in range(n_keys):
        counts[c + 1] += counts[c]
    fill = counts[:-1].copy()
    order = np.empty(n, np.int64)
    for i in range(n):
        order[fill[key[i]]] = i
        fill[key[i]] += 1
    first = np.zeros(n_columns + 1, np.int64)
    for c in range(n_columns):
        in_column = counts[(c + 1) * slabs] - counts[c * slabs]
        first[c + 1] = first[c] + (in_column + CLUSTER - 1) // CLUSTER
    return counts, order, first


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
def _grid_boxes(n_clusters):
    """The slots' origins (zeroed) and the clusters' lower and upper corners."""
    return (
        np.zeros((n_clusters * CLUSTER, 3)),
        np.empty((n_clusters, 3)),
        np.empty((n_clusters, 3)),
    )


@njit(cache=True, inline="always", error_model="numpy")
def _cluster_box(positions, wrapped, atom, origin, lower, upper, cl):
    """Cluster cl's bounding box (wrapped frame) and its slots' origins."""
    for d in range(3):
        lower[cl, d] = np.inf
        upper[cl, d] = -np.inf
    for b in range(CLUSTER):
        i = atom[cl * CLUSTER + b]
        if i >= 0:
            for d in range(3):
                lower[cl, d] = min(lower[cl, d], wrapped[i, d])
                upper[cl, d] = max(upper[cl, d], wrapped[i, d])
    for b in range(CLUSTER):
        s = cl * CLUSTER + b
        i = atom[s]
        for d in range(3):
            centre = 0.5 * (lower[cl, d] + upper[cl, d])
            origin[s, d] = centre + (positions[i, d] - wrapped[i, d] if i >= 0 else 0.0)


def search_pairs(
    box,
    ncx,
    ncy,
    first,
    lower,
    upper,
    radius,
    chunks,
    per_cluster,
    xi,
    xj,
    reach2,
    inner2=None,
    with_reach=False,
):
    """The cluster pairs of a list of radius ``radius``.

    The candidates, found with bounding boxes as GROMACS's pair search finds them: for
    each i cluster, the clusters j >= i of the neighbouring columns (images included)
    whose xy box (its clusters' boxes together) comes within ``radius`` of the i
    column's, then of the i cluster's own box in xy, and whose clusters' boxes overlap
    the i cluster's, widened by ``radius``, in z (a full box-to-box test per candidate on
    top of that cost more time than it saved: 1.35 of the search's time). Each pair once
    (a cluster with an image of itself at one of the two opposite shifts; the box must be
    wider than twice the cutoff, so that an atom pair lies within it at one image at
    most), each row starting with the cluster itself at zero shift, with its offset,
    centre_i - centre_j - image shift, in float32. Returns (starts, partners int32,
    offsets (pairs, 3) float32) grouped by i cluster, or None where ``per_cluster`` pairs
    of room per cluster did not suffice (search again with more). With the relative
    positions ``xi``/``xj`` (float32, see :func:`cluster_positions`) only the pairs with
    an atom pair closer than sqrt(``reach2``) are kept: each candidate is checked
    (:func:`_near_pair`'s check, its offset in registers) as it is written, and the next
    one written after it only if it is kept (0.78 of the time of writing a row and then
    checking and compacting it, at radius 4.0 on the 32000-atom melt, one thread), a
    window of candidates at a time in IR (:func:`keep_window`: the i cluster loaded once
    per window, 0.93 of the search's time with numba's loop over them); with None for
    both, every candidate. With ``inner2`` (float32, at most ``reach2``) the kept pairs
    pruned to those closer than sqrt(``inner2``) too, from the same squared distances
    (:func:`keep_window_both`): the list :func:`prune_pairs` would make of it, pair for
    pair, with no pass of its own (0.93 of the CPU time of the search and that prune on
    the 32000-atom melt at radius 4.0 and 2.8, one thread); then returned after the kept
    pairs, as (starts, partners, offsets) too. With ``with_reach``, last also per i
    cluster a bound on one past its row's last partner (as :func:`row_reach`, from the
    search's windows: no pass over the pairs), which holds for the pruned rows too.

    The columns are searched in ``chunks`` runs of about equal work
    (:func:`_column_chunks`) on the threads, each into its own part of one buffer, then
    each part but the first moved down to follow the one before (:func:`_joined`); each i
    cluster's row is written as its windows are found (:func:`_search_columns`).
    """
    found = _search_lists(
        box,
        ncx,
        ncy,
        first,
        lower,
        upper,
        radius,
        chunks,
        per_cluster,
        xi,
        xj,
        reach2,
        np.float32(-1.0 if inner2 is None else inner2),
    )
    if found is None:
        return None
    lists = found[:-1] if inner2 is not None else found[:3]
    return lists + found[-1:] if with_reach else lists


@njit(cache=True, error_model="numpy")
def _search_lists(
    box, ncx, ncy, first, lower, upper, radius, chunks, per_cluster, xi, xj, reach2, inner2
):
    """:func:`search_pairs`, the pruned rows always returned (none where ``inner2`` < 0)."""
    n_clusters = lower.shape[0]
    column_bounds = _column_chunks(box, ncx, ncy, first, radius, chunks)
    # chunk t writes its rows from place[t] of one buffer (room[t] pairs), then each chunk
    # but the first is moved down to where its rows begin in the list (_joined)
    place = np.zeros(chunks + 1, np.int64)
    for t in range(chunks):
        room = per_cluster * (first[column_bounds[t + 1]] - first[column_bounds[t]]) + 64
        place[t + 1] = place[t] + room
    part_partners = np.empty(place[chunks], np.int32)
    part_offsets = np.empty((place[chunks], 3), np.float32)
    counts = np.zeros(n_clusters, np.int64)
    reach = np.empty(n_clusters, np.int64)
    used = np.zeros(chunks, np.int64)
    parts = (part_partners, part_offsets, counts, reach, used)
    # the pruned rows: never longer than the kept ones (none written with inner2 < 0)
    room_inner = place[chunks] if inner2 > 0.0 else 0
    inner = (
        np.empty(room_inner, np.int32),
        np.empty((room_inner, 3), np.float32),
        np.zeros(n_clusters, np.int64),
        inner2,
    )
    _search_parts(
        box,
        ncx,
        ncy,
        first,
        lower,
        upper,
        _column_extents(first, lower, upper),
        radius,
        column_bounds,
        place,
        parts,
        xi,
        xj,
        reach2,
        inner,
    )
    if used.min() < 0:
        return None
    listed = _joined(counts, first, column_bounds, used, place, part_partners, part_offsets)
    inner_partners, inner_offsets, inner_counts, _ = inner
    inner_used = np.zeros(chunks, np.int64)
    for t in range(chunks):
        for ci in range(first[column_bounds[t]], first[column_bounds[t + 1]]):
            inner_used[t] += inner_counts[ci]
    pruned = _joined(
        inner_counts, first, column_bounds, inner_used, place, inner_partners, inner_offsets
    )
    return listed + pruned + (reach,)


@njit(cache=True, error_model="numpy")
def _column_chunks(box, ncx, ncy, first, radius, chunks):
    """The columns' split into ``chunks`` runs (chunks + 1 bounds) of about equal work: a
    column's, its clusters times those of the neighbouring columns it searches (each pair
    of columns from the lower one's side, so a column at the low end in x also searches
    the far side's, across the boundary, and one at the high end almost none: equal
    cluster counts gave the first of two chunks 0.59 of the work on the 32000-atom melt)."""
    n_columns = ncx * ncy
    reach_x = int(np.ceil(radius / (box[0] / ncx)))
    reach_y = int(np.ceil(radius / (box[1] / ncy)))
    work = np.zeros(n_columns + 1)
    for c in range(n_columns):
        f0, f1 = first[c], first[c + 1]
        searched = 0
        for dx in range(-reach_x, reach_x + 1):
            ux = (c // ncy + dx) % ncx
            for dy in range(-reach_y, reach_y + 1):
                col = ux * ncy + (c % ncy + dy) % ncy
                if first[col + 1] > f0:  # as the search skips a column before c's
                    searched += first[col + 1] - first[col]
        work[c + 1] = work[c] + (f1 - f0) * searched
    bounds = np.zeros(chunks + 1, np.int64)
    c = 0
    for t in range(1, chunks):
        while c < n_columns and work[c] < t * work[n_columns] / chunks:
            c += 1
        bounds[t] = c
    bounds[chunks] = n_columns
    return bounds


@njit(cache=True, error_model="numpy")
def _search_parts(
    box,
    ncx,
    ncy,
    first,
    lower,
    upper,
    extents,
    radius,
    column_bounds,
    place,
    parts,
    xi,
    xj,
    reach2,
    inner,
):
    """The search of :func:`search_pairs` into ``parts`` (the chunks' partners and
    offsets, chunk t's from ``place[t]`` to ``place[t + 1]``, the rows' counts and reach,
    the pairs each chunk used), on the threads for more than one chunk."""
    part_partners, part_offsets, counts, reach, used = parts
    if column_bounds.shape[0] == 2:
        used[0] = _search_columns(
            box,
            ncx,
            ncy,
            first,
            lower,
            upper,
            extents,
            radius,
            0,
            column_bounds[1],
            counts,
            reach,
            part_partners,
            part_offsets,
            0,
            place[1],
            xi,
            xj,
            reach2,
            inner,
        )
    else:
        _search_chunks(
            box,
            ncx,
            ncy,
            first,
            lower,
            upper,
            extents,
            radius,
            column_bounds,
            place,
            counts,
            reach,
            part_partners,
            part_offsets,
            used,
            xi,
            xj,
            reach2,
            inner,
        )


@njit(cache=True, error_model="numpy")
def _joined(counts, first, column_bounds, used, place, part_partners, part_offsets):
    """(starts, partners, offsets) of the rows of ``counts`` pairs each, written per chunk
    into ``part_partners``/``part_offsets`` (chunk t's ``used[t]`` pairs from
    ``place[t]``): the first chunk's where they are, each later one moved down to follow
    the one before (in order: a move never overwrites pairs not yet moved; on the threads
    where the two places do not overlap). The lists are the buffers' first pairs, not a
    fresh copy of every chunk's (with the whole buffers passed to each chunk, see
    :func:`_search_columns`, two chunks' work on one thread went from 1.16 to 1.09 of
    one chunk's search on the 32000-atom melt, CPU time, interleaved)."""
    n_clusters = counts.shape[0]
    chunks = used.shape[0]
    starts = np.zeros(n_clusters + 1, np.int64)
    for ci in range(n_clusters):
        starts[ci + 1] = starts[ci] + counts[ci]
    for t in range(1, chunks):
        source, target, count = place[t], starts[first[column_bounds[t]]], used[t]
        if count == 0 or target == source:
            continue
        if target + count <= source:
            move_pairs_threaded(part_partners, part_offsets, source, target, count, chunks)
        else:
            move_pairs(part_partners, part_offsets, source, target, 0, count)
    total = starts[n_clusters]
    return starts, part_partners[:total], part_offsets[:total]


@njit(cache=True, parallel=True, error_model="numpy")
def _search_chunks(
    box,
    ncx,
    ncy,
    first,
    lower,
    upper,
    extents,
    radius,
    column_bounds,
    place,
    counts,
    reach,
    part_partners,
    part_offsets,
    used,
    xi,
    xj,
    reach2,
    inner,
):
    """:func:`_search_columns` for each chunk of columns, on the threads, chunk t into
    places ``place[t]`` to ``place[t + 1]`` of the buffers."""
    for t in prange(column_bounds.shape[0] - 1):
        used[t] = _search_columns(
            box,
            ncx,
            ncy,
            first,
            lower,
            upper,
            extents,
            radius,
            column_bounds[t],
            column_bounds[t + 1],
            counts,
            reach,
            part_partners,
            part_offsets,
            place[t],
            place[t + 1],
            xi,
            xj,
            reach2,
            inner,
        )


@njit(cache=True, inline="always", error_model="numpy")
def _periodic_column(index, count, length):
    """A column index one period out of range at most, brought into it, and the shift
    (-length, 0 or length) that takes the column there."""
    if index < 0:
        return index + count, -length
    if index >= count:
        return index - count, length
    return index, 0.0


@njit(cache=True, error_model="numpy")
def _column_extents(first, lower, upper):
    """Each column's xy extent (columns, 4: x0, x1, y0, y1), its clusters' boxes together
    (empty: +inf, -inf)."""
    n_columns = first.shape[0] - 1
    extents = np.empty((n_columns, 4))
    for c in range(n_columns):
        x0 = y0 = np.inf
        x1 = y1 = -np.inf
        for cl in range(first[c], first[c + 1]):
            x0 = min(x0, lower[cl, 0])
            x1 = max(x1, upper[cl, 0])
            y0 = min(y0, lower[cl, 1])
            y1 = max(y1, upper[cl, 1])
        extents[c, 0], extents[c, 1], extents[c, 2], extents[c, 3] = x0, x1, y0, y1
    return extents


@njit(cache=True, error_model="numpy")
def _search_columns(
    box,
    ncx,
    ncy,
    first,
    lower,
    upper,
    extents,
    radius,
    c0,
    c1,
    counts,
    reach,
    partners,
    offsets,
    place0,
    place1,
    xi,
    xj,
    reach2,
    inner,
):
    """The rows of the i clusters in columns ``c0`` to ``c1`` (see :func:`search_pairs`):
    each row's length into ``counts[ci]`` and one past its last partner into
    ``reach[ci]``, the rows one after another into ``partners`` and ``offsets`` from
    place ``place0``, before ``place1``. Returns the pairs written, or minus the pairs needed
    so far where the room ran out (the caller grows it and searches again). ``extents``:
    the columns' xy boxes (:func:`_column_extents`). ``inner``: (partners, offsets,
    counts, inner2), the pruned rows' buffers (written in the same places, where
    ``inner2`` > 0) and their lengths. The whole buffers and a place, not a slice of them
    for each chunk: numba types a slice as a non-contiguous array, so that one chunk's
    search and several chunks' ran differently compiled loops.

    Per column of i clusters, first the neighbouring columns (and their images in x and
    y) whose xy box comes within ``radius`` of this column's; then per i cluster, each of
    those whose xy box comes within ``radius`` of the cluster's own, at each image in z
    the cluster reaches: the window of j clusters whose z bounds overlap the cluster's
    widened by ``radius``. Along both columns the clusters' boxes rise in z, so a window
    only moves up as i does: two cursors per neighbouring column and image, kept from one
    i cluster to the next (no search; an i cluster out of a column's reach in xy leaves
    them where they are, and the next one moves them on).
    """
    width_x, width_y = box[0] / ncx, box[1] / ncy
    reach_x = int(np.ceil(radius / width_x))
    reach_y = int(np.ceil(radius / width_y))
    n_near = (2 * reach_x + 1) * (2 * reach_y + 1)
    # the neighbouring columns of the i column in reach: index, shift, xy box (shifted)
    # and per image in z (-1, 0, +1) the window's cursors
    near_column = np.empty(n_near, np.int64)
    near_box = np.empty((n_near, 6))  # x0, x1, y0, y1, sx, sy
    begins = np.empty((n_near, 3), np.int64)
    ends = np.empty((n_near, 3), np.int64)
    all_x = 0.5 * (lower[:, 0] + upper[:, 0])  # the clusters' centres (the partners')
    all_y = 0.5 * (lower[:, 1] + upper[:, 1])
    all_z = 0.5 * (lower[:, 2] + upper[:, 2])
    bottom = lower[:, 2].copy()  # the clusters' z bounds, each contiguous for the cursors
    top = upper[:, 2].copy()
    r2max = radius * radius
    capacity = place1
    k = place0
    k_inner = place0  # the pruned rows' end
    pruned = inner[3] > 0.0
    for c in range(c0, c1):
        f0, f1 = first[c], first[c + 1]
        if f1 == f0:
            continue
        cx, cy = c // ncy, c % ncy
        n = 0
        for dx in range(-reach_x, reach_x + 1):
            ux, sx = _periodic_column(cx + dx, ncx, box[0])
            for dy in range(-reach_y, reach_y + 1):
                uy, sy = _periodic_column(cy + dy, ncy, box[1])
                col = ux * ncy + uy
                g0, g1 = first[col], first[col + 1]
                if g1 <= f0 or g1 == g0:
                    continue  # a column before c's (listed from its side) or an empty one
                x0, x1 = extents[col, 0] + sx, extents[col, 1] + sx
                y0, y1 = extents[col, 2] + sy, extents[col, 3] + sy
                gx = max(x0 - extents[c, 1], extents[c, 0] - x1, 0.0)
                gy = max(y0 - extents[c, 3], extents[c, 2] - y1, 0.0)
                if gx * gx + gy * gy >= r2max:
                    continue  # no cluster of c's comes within reach of this column
                near_column[n] = col
                near_box[n, 0], near_box[n, 1], near_box[n, 2] = x0, x1, y0
                near_box[n, 3], near_box[n, 4], near_box[n, 5] = y1, sx, sy
                for dz in range(3):
                    begins[n, dz] = ends[n, dz] = g0
                n += 1
        for ci in range(f0, f1):
            row_start = k
            inner_start = k_inner
            if k + 1 > capacity:
                return -(k + 1 - place0)
            ox, oy, oz = all_x[ci], all_y[ci], all_z[ci]
            partners[k] = ci  # the cluster with itself first (the kernels rely on it)
            offsets[k, 0] = offsets[k, 1] = offsets[k, 2] = 0.0
            k += 1
            if pruned:
                inner[0][k_inner] = ci
                inner[1][k_inner, 0] = inner[1][k_inner, 1] = inner[1][k_inner, 2] = 0.0
                k_inner += 1
            furthest = ci + 1
            # the images below and above reach only the column's lowest (highest) clusters
            dz_first = -1 if bottom[ci] < radius else 0
            dz_last = 1 if top[ci] + radius >= box[2] else 0
            for w in range(n):
                gx = max(near_box[w, 0] - upper[ci, 0], lower[ci, 0] - near_box[w, 1], 0.0)
                gy = max(near_box[w, 2] - upper[ci, 1], lower[ci, 1] - near_box[w, 3], 0.0)
                if gx * gx + gy * gy >= r2max:
                    continue  # out of reach in xy: the cursors catch up later
                g1 = first[near_column[w] + 1]
                sx, sy = near_box[w, 4], near_box[w, 5]
                for dz in range(dz_first, dz_last + 1):
                    sz = dz * box[2]
                    # a cluster meets its own image at +shift and -shift: the pair once
                    positive = sx > 0.0 or (sx == 0.0 and (sy > 0.0 or (sy == 0.0 and dz > 0)))
                    zero = sx == 0.0 and sy == 0.0 and dz == 0
                    low = bottom[ci] - radius - sz  # both rise with ci
                    high = top[ci] + radius - sz
                    begin = begins[w, dz + 1]
                    while begin < g1 and top[begin] < low:
                        begin += 1
                    end = max(ends[w, dz + 1], begin)
                    while end < g1 and bottom[end] <= high:
                        end += 1
                    begins[w, dz + 1], ends[w, dz + 1] = begin, end
                    lo = max(begin, ci)
                    # itself: first in its row; its image at -shift: listed at +shift
                    lo += (lo == ci) & ((not positive) | zero)
                    if end <= lo:
                        continue
                    if k + end - lo > capacity:
                        return -(k + end - lo - place0)
                    furthest = max(furthest, end)
                    px, py, pz = ox - sx, oy - sy, oz - sz
                    if xi is None:
                        for j in range(end - lo):  # no dependence between j: vectorised
                            partners[k + j] = lo + j
                            offsets[k + j, 0] = px - all_x[lo + j]
                            offsets[k + j, 1] = py - all_y[lo + j]
                            offsets[k + j, 2] = pz - all_z[lo + j]
                        k += end - lo
                    elif pruned:
                        # each candidate written, and kept (the next one written after
                        # it) only where an atom pair is within reach: no branch, no
                        # second pass; the inner list from the same distances
                        k, k_inner = keep_window_both(
                            xi,
                            xj,
                            ci,
                            lo,
                            end,
                            px,
                            py,
                            pz,
                            all_x,
                            all_y,
                            all_z,
                            reach2,
                            inner[3],
                            partners,
                            offsets,
                            k,
                            inner[0],
                            inner[1],
                            k_inner,
                        )
                    else:
                        k = keep_window(
                            xi,
                            xj,
                            ci,
                            lo,
                            end,
                            px,
                            py,
                            pz,
                            all_x,
                            all_y,
                            all_z,
                            reach2,
                            partners,
                            offsets,
                            k,
                        )
            counts[ci] = k - row_start
            reach[ci] = furthest
            if pruned:
                inner[2][ci] = k_inner - inner_start
    return k - place0


@njit(cache=True, error_model="numpy")
def balanced_chunks(starts, chunks):
    """Cluster ranges of ``chunks`` chunks with about equal pair counts (chunks + 1)."""
    n = starts.shape[0] - 1
    bounds = np.zeros(chunks + 1, np.int64)
    total = starts[n]
    c = 1
    for ci in range(n):
        while c < chunks and starts[ci] >= c * total / chunks:
            bounds[c] = ci
            c += 1
    while c < chunks:
        bounds[c] = n
        c += 1
    bounds[chunks] = n
    return bounds


@njit(cache=True, parallel=True, error_model="numpy")
def row_reach(starts, partners):
    """Per i cluster, one past the last cluster its row reaches (its largest partner + 1;
    a row's partners are its cluster and later ones), on the threads."""
    n = starts.shape[0] - 1
    reach = np.empty(n, np.int64)
    for ci in prange(n):
        last = np.int32(ci)
        for k in range(starts[ci], starts[ci + 1]):
            last = max(last, partners[k])
        reach[ci] = np.int64(last) + 1
    return reach


@njit(cache=True, error_model="numpy")
def chunk_windows(reach, bounds):
    """Each chunk's window of clusters (chunks, 3): its first i cluster, one past the
    last cluster any of its rows reaches (``reach``: per row, as :func:`row_reach`, or
    a bound on it), and where the window starts in scratch that holds all the chunks'
    windows one after the other (in clusters). A chunk's forces and j lanes need room
    for its window only: about the chunk's own clusters and the layer of columns its
    rows reach past them (the first chunks' reach the far side of a periodic box), not
    the whole list per thread."""
    chunks = bounds.shape[0] - 1
    windows = np.zeros((chunks, 3), np.int64)
    place = 0
    for c in range(chunks):
        first, end = bounds[c], bounds[c + 1]
        for ci in range(first, bounds[c + 1]):
            end = max(end, reach[ci])
        windows[c, 0], windows[c, 1], windows[c, 2] = first, end, place
        place += end - first
    return windows


@njit(cache=True, error_model="numpy")
def cluster_positions(positions, atom, origin, xi, xj):
    """Each slot's position relative to its origin, in float32, as the kernels read
    them: per cluster [x0..x3, y0..y3, z0..z3]; ``xi`` for the i role, ``xj`` for the
    j role (they differ only in where the fillers sit)."""
    _slot_positions(positions, atom, origin, xi, xj, 0, atom.shape[0])


@njit(cache=True, parallel=True, error_model="numpy")
def cluster_positions_threaded(positions, atom, origin, xi, xj, chunks):
    """:func:`cluster_positions` in ``chunks`` runs of slots on the threads (the same
    values: each slot's are its own)."""
    # Each run whole clusters, its slots and values passed as slices, so that every index
    # in the loop counts from zero: with a run's first slot as a bound instead, numba's
    # handling of negative indices stayed in the loop, which then took 1.9x the serial
    # form's CPU time (32000 atoms, two runs on one thread: 84 against 45 us).
    n = atom.shape[0] // CLUSTER
    for c in prange(chunks):
        a, b = CLUSTER * (c * n // chunks), CLUSTER * ((c + 1) * n // chunks)
        _slot_positions(
            positions, atom[a:b], origin[a:b], xi[3 * a : 3 * b], xj[3 * a : 3 * b], 0, b - a
        )


@njit(cache=True, inline="always", error_model="numpy")
def _slot_positions(positions, atom, origin, xi, xj, first, end):
    """:func:`cluster_positions` for slots ``first`` to ``end``."""
    for s in range(first, end):
        base = (s // CLUSTER) * 3 * CLUSTER + s % CLUSTER
        i = atom[s]
        if i >= 0:
            for d in range(3):
                value = np.float32(positions[i, d] - origin[s, d])
                xi[base + d * CLUSTER] = value
                xj[base + d * CLUSTER] = value
        else:
            xi[base] = xj[base] = np.float32(10.0 * (s % CLUSTER))
            xi[base + CLUSTER] = xj[base + CLUSTER] = np.float32(0.0)
            xi[base + 2 * CLUSTER] = np.float32(FILLER)
            xj[base + 2 * CLUSTER] = np.float32(-FILLER)


_F32 = ir.FloatType()
_I64 = ir.IntType(64)
#: The lanes of the atom check's vectors: the cluster kernel's (md._simd.ZMM).
_LANES = 16 if ZMM else 8
_VECTOR = ir.VectorType(_F32, _LANES)


def _any_near(builder, halves, shifted, reach):
    """An i1: whether any atom pair of the cluster pair (``halves`` from
    ``cluster_i_halves``, ``shifted`` from ``cluster_j_less``) is closer than sqrt of
    ``reach`` (a vector of the squared reach)."""
    within = None
    for half in halves:
        _, r2 = squared_distances(builder, half, shifted)
        close = builder.fcmp_ordered("<", r2, reach)
        within = close if within is None else builder.or_(within, close)
    bits = ir.IntType(_LANES)
    return builder.icmp_unsigned("!=", builder.bitcast(within, bits), ir.Constant(bits, 0))


def _near_both(builder, halves, shifted, reach, inner):
    """Two i1: whether any atom pair of the cluster pair is closer than sqrt of ``reach``,
    and whether any is closer than sqrt of ``inner`` (vectors of the squared reaches),
    from one set of squared distances (:func:`_any_near`'s check at two radii)."""
    within = close = None
    for half in halves:
        _, r2 = squared_distances(builder, half, shifted)
        a = builder.fcmp_ordered("<", r2, reach)
        b = builder.fcmp_ordered("<", r2, inner)
        within = a if within is None else builder.or_(within, a)
        close = b if close is None else builder.or_(close, b)
    bits = ir.IntType(_LANES)
    zero = ir.Constant(bits, 0)
    return (
        builder.icmp_unsigned("!=", builder.bitcast(within, bits), zero),
        builder.icmp_unsigned("!=", builder.bitcast(close, bits), zero),
    )


def _near_pair_twin(xi, xj, ci, cj, ox, oy, oz, reach2):
    """:func:`_near_pair` in numpy (under ``NUMBA_DISABLE_JIT=1``, and its test)."""
    own = xi[ci * 3 * CLUSTER : (ci + 1) * 3 * CLUSTER].reshape(3, CLUSTER)
    other = xj[cj * 3 * CLUSTER : (cj + 1) * 3 * CLUSTER].reshape(3, CLUSTER)
    offset = np.array([ox, oy, oz], np.float32)
    d = own[:, :, None] - (other - offset[:, None])[:, None, :]
    return bool(((d * d).sum(axis=0) < reach2).any())


@python_twin(_near_pair_twin)
@intrinsic
def _near_pair(typingctx, xi, xj, ci, cj, ox, oy, oz, reach2):
    """Whether i cluster ``ci`` and j cluster ``cj`` at offset (``ox``, ``oy``, ``oz``)
    (float32, as the list stores it) have an atom pair closer than sqrt(``reach2``), in
    the cluster kernels' layout and lanes (a 4x4 cluster pair in one 16-lane vector where
    the CPU has AVX-512, else two i atoms by four j atoms per 8-lane vector), the offset
    in registers: for a pair that is not the cluster with itself (the first of each row,
    always kept). The search and the prune run the same check (``_any_near``) inside their
    own loops (:func:`keep_window`, :func:`_keep_near`); this one pair at a time is its
    unit, which the tests hold against the atoms' own distances."""
    sig = types.boolean(xi, xj, ci, cj, ox, oy, oz, reach2)

    def codegen(context, builder, signature, args):
        xi_p, xj_p = (array_data(context, builder, signature.args[n], args[n]) for n in range(2))
        ci, cj = (context.cast(builder, args[n], signature.args[n], types.int64) for n in (2, 3))
        ox, oy, oz, reach2 = args[4:]
        size = ir.Constant(_I64, 3 * CLUSTER)
        halves = cluster_i_halves(builder, xi_p, builder.mul(ci, size), _LANES)
        reach = splat(builder, reach2, _VECTOR)
        shifted = cluster_j_less(builder, xj_p, builder.mul(cj, size), (ox, oy, oz), lanes=_LANES)
        return _any_near(builder, halves, shifted, reach)

    return sig, codegen


@njit(cache=True, error_model="numpy")
def prune_pairs(
    starts, partners, offsets, bounds, xi, xj, reach2, kept_starts, kept_partners, kept_offsets
):
    """Keep the pairs of the cluster list (``starts``, ``partners``, ``offsets``) that
    have an atom pair closer than sqrt(``reach2``) at the relative positions ``xi``/``xj``
    (GROMACS's dynamic pruning of an outer list to an inner one), each row in its
    order, the cluster itself still first: their row offsets into ``kept_starts`` and
    the pairs into ``kept_partners``/``kept_offsets`` (as long as the list). Returns the
    pairs kept.

    The chunks ``bounds`` (i cluster ranges) run on the threads, each pair checked
    (:func:`_near_pair`'s check) as it is copied, the next one copied after it only if it
    is kept (the outer list is read once; 0.85 of the time of marking a row and then
    compacting it, on one thread), a row at a time in IR (:func:`_keep_near`: the i
    cluster's vectors loaded once per row, 0.76 of the time of the same loop in numba,
    which reloaded them per pair), each chunk's kept rows written from where its
    rows begin in the list; then every chunk but the first is moved down to its place,
    in order (a move never overwrites rows not yet moved)."""
    n_clusters = starts.shape[0] - 1
    chunks = bounds.shape[0] - 1
    if chunks == 1:
        _prune_rows(
            starts,
            partners,
            offsets,
            0,
            n_clusters,
            xi,
            xj,
            reach2,
            kept_starts,
            kept_partners,
            kept_offsets,
        )
    else:
        _prune_chunks(
            starts,
            partners,
            offsets,
            bounds,
            xi,
            xj,
            reach2,
            kept_starts,
            kept_partners,
            kept_offsets,
        )
    kept_starts[0] = 0
    for ci in range(n_clusters):  # the counts, into row offsets
        kept_starts[ci + 1] += kept_starts[ci]
    for t in range(1, chunks):
        source, target = starts[bounds[t]], kept_starts[bounds[t]]
        count = kept_starts[bounds[t + 1]] - target
        if target + count <= source:  # apart (the prune keeps about half): on the threads
            move_pairs_threaded(kept_partners, kept_offsets, source, target, count, chunks)
        else:
            move_pairs(kept_partners, kept_offsets, source, target, 0, count)
    return kept_starts[n_clusters]


@njit(cache=True, error_model="numpy")
def move_pairs(partners, offsets, source, target, first, end):
    """Pairs ``source + first`` to ``source + end`` moved down to ``target + first`` on
    (``target`` < ``source``: in order, so a move never overwrites a pair not yet moved)."""
    for k in range(first, end):
        partners[target + k] = partners[source + k]
        for d in range(3):
            offsets[target + k, d] = offsets[source + k, d]


@njit(cache=True, parallel=True, error_model="numpy")
def move_pairs_threaded(partners, offsets, source, target, count, runs):
    """:func:`move_pairs` of ``count`` pairs whose places do not overlap their new ones, in
    ``runs`` runs on the threads (serial, the move of the second of two chunks' kept pairs
    took 0.10 of the prune's CPU time on the 32000-atom melt: 147 of 1457 us)."""
    for r in prange(runs):
        move_pairs(partners, offsets, source, target, r * count // runs, (r + 1) * count // runs)


@njit(cache=True, parallel=True, error_model="numpy")
def _prune_chunks(
    starts, partners, offsets, bounds, xi, xj, reach2, kept_starts, kept_partners, kept_offsets
):
    """:func:`_prune_rows` for each chunk of i clusters, on the threads."""
    for t in prange(bounds.shape[0] - 1):
        _prune_rows(
            starts,
            partners,
            offsets,
            bounds[t],
            bounds[t + 1],
            xi,
            xj,
            reach2,
            kept_starts,
            kept_partners,
            kept_offsets,
        )


@njit(cache=True, error_model="numpy")
def _prune_rows(
    starts, partners, offsets, c0, c1, xi, xj, reach2, kept_starts, kept_partners, kept_offsets
):
    """Check and compact the rows of i clusters ``c0`` to ``c1``, the kept pairs written
    one after another from ``starts[c0]`` (every pair is written, a dropped one where the
    next kept one overwrites it: no branch; never past the chunk's own rows), each row's
    count into ``kept_starts[ci + 1]``."""
    k = starts[c0]
    for ci in range(c0, c1):
        row = k
        k = _keep_near(
            xi,
            xj,
            partners,
            offsets,
            starts[ci],
            starts[ci + 1],
            ci,
            reach2,
            kept_partners,
            kept_offsets,
            k,
        )
        kept_starts[ci + 1] = k - row


def _keep_window_twin(
    xi, xj, ci, lo, hi, sx, sy, sz, all_x, all_y, all_z, reach2, partners, offsets, k
):
    """:func:`keep_window` in Python (under ``NUMBA_DISABLE_JIT=1``, and its test)."""
    for j in range(lo, hi):
        o = (np.float32(sx - all_x[j]), np.float32(sy - all_y[j]), np.float32(sz - all_z[j]))
        partners[k] = j
        offsets[k, 0], offsets[k, 1], offsets[k, 2] = o
        k += _near_pair_twin(xi, xj, ci, j, *o, reach2)
    return k


@python_twin(_keep_window_twin)
@intrinsic
def keep_window(
    typingctx, xi, xj, ci, lo, hi, sx, sy, sz, all_x, all_y, all_z, reach2, partners, offsets, k
):
    """The search's candidates ``lo`` to ``hi`` (j clusters of one window) of i cluster
    ``ci``: each written to ``partners``/``offsets`` from ``k`` on, its offset ``s -
    all[j]`` (double, then float32, per axis), and kept (the next one written after it)
    where an atom pair is closer than sqrt(``reach2``) (:func:`_near_pair`'s check);
    returns the new end. The loop in IR so that the i cluster's vectors are loaded once
    per window (numba's loop reloaded them for every candidate: its float32 stores might
    be the positions, as far as LLVM knows)."""
    if partners.dtype != types.int32 or offsets.dtype != types.float32:
        raise TypeError(
            f"keep_window: int32 partners and float32 offsets, got {partners} and {offsets}"
        )
    sig = types.int64(
        xi, xj, ci, lo, hi, sx, sy, sz, all_x, all_y, all_z, reach2, partners, offsets, k
    )

    def codegen(context, builder, signature, args):
        arg = signature.args
        xi_p, xj_p = (array_data(context, builder, arg[n], args[n]) for n in range(2))
        ci_v, lo_v, hi_v, k_v = (
            context.cast(builder, args[n], arg[n], types.int64) for n in (2, 3, 4, 14)
        )
        shift = [context.cast(builder, args[n], arg[n], types.float64) for n in (5, 6, 7)]
        centres = [
            (arg[n], context.make_array(arg[n])(context, builder, args[n])) for n in (8, 9, 10)
        ]
        reach2 = args[11]
        part_type, off_type = arg[12], arg[13]
        part_a = context.make_array(part_type)(context, builder, args[12])
        off_a = context.make_array(off_type)(context, builder, args[13])
        result = cgutils.alloca_once_value(builder, k_v)
        size = ir.Constant(_I64, 3 * CLUSTER)
        halves = cluster_i_halves(builder, xi_p, builder.mul(ci_v, size), _LANES)
        reach = splat(builder, reach2, _VECTOR)
        with cgutils.for_range_slice(builder, lo_v, hi_v, ir.Constant(_I64, 1)) as (j, _):
            to = builder.load(result)
            offset = []
            for d, (centre_type, centre) in enumerate(centres):
                at = cgutils.get_item_pointer(context, builder, centre_type, centre, [j])
                value = builder.fptrunc(builder.fsub(shift[d], builder.load(at)), _F32)
                slot = cgutils.get_item_pointer(
                    context, builder, off_type, off_a, [to, ir.Constant(_I64, d)]
                )
                builder.store(value, slot)
                offset.append(value)
            slot = cgutils.get_item_pointer(context, builder, part_type, part_a, [to])
            builder.store(builder.trunc(j, ir.IntType(32)), slot)
            shifted = cluster_j_less(builder, xj_p, builder.mul(j, size), offset, lanes=_LANES)
            near = _any_near(builder, halves, shifted, reach)
            builder.store(builder.add(to, builder.zext(near, _I64)), result)
        return builder.load(result)

    return sig, codegen


def _keep_window_both_twin(
    xi,
    xj,
    ci,
    lo,
    hi,
    sx,
    sy,
    sz,
    all_x,
    all_y,
    all_z,
    reach2,
    inner2,
    partners,
    offsets,
    k,
    inner_partners,
    inner_offsets,
    m,
):
    """:func:`keep_window_both` in Python (under ``NUMBA_DISABLE_JIT=1``, and its test)."""
    for j in range(lo, hi):
        o = (np.float32(sx - all_x[j]), np.float32(sy - all_y[j]), np.float32(sz - all_z[j]))
        partners[k] = inner_partners[m] = j
        offsets[k, 0], offsets[k, 1], offsets[k, 2] = o
        inner_offsets[m, 0], inner_offsets[m, 1], inner_offsets[m, 2] = o
        k += _near_pair_twin(xi, xj, ci, j, *o, reach2)
        m += _near_pair_twin(xi, xj, ci, j, *o, inner2)
    return k, m


@python_twin(_keep_window_both_twin)
@intrinsic
def keep_window_both(
    typingctx,
    xi,
    xj,
    ci,
    lo,
    hi,
    sx,
    sy,
    sz,
    all_x,
    all_y,
    all_z,
    reach2,
    inner2,
    partners,
    offsets,
    k,
    inner_partners,
    inner_offsets,
    m,
):
    """:func:`keep_window` writing two lists at once: each candidate also written to
    ``inner_partners``/``inner_offsets`` from ``m`` on, and kept there where an atom pair
    is closer than sqrt(``inner2``) (no farther than ``reach2``: the inner list is the
    outer one pruned, as :func:`prune_pairs` would prune it, from the same squared
    distances). Returns (the outer end, the inner end). The search's own prune, with no
    second pass over the outer list."""
    for a, b in ((partners, inner_partners), (offsets, inner_offsets)):
        if a != b:
            raise TypeError(f"keep_window_both: the inner list's arrays as the outer's, {a}")
    if partners.dtype != types.int32 or offsets.dtype != types.float32:
        raise TypeError(
            f"keep_window_both: int32 partners and float32 offsets, got {partners} and {offsets}"
        )
    arguments = (xi, xj, ci, lo, hi, sx, sy, sz, all_x, all_y, all_z, reach2, inner2)
    arguments += (partners, offsets, k, inner_partners, inner_offsets, m)
    sig = types.UniTuple(types.int64, 2)(*arguments)

    def codegen(context, builder, signature, args):
        arg = signature.args
        xi_p, xj_p = (array_data(context, builder, arg[n], args[n]) for n in range(2))
        ci_v, lo_v, hi_v, k_v, m_v = (
            context.cast(builder, args[n], arg[n], types.int64) for n in (2, 3, 4, 15, 18)
        )
        shift = [context.cast(builder, args[n], arg[n], types.float64) for n in (5, 6, 7)]
        centres = [
            (arg[n], context.make_array(arg[n])(context, builder, args[n])) for n in (8, 9, 10)
        ]
        outputs = [
            (
                (arg[p], context.make_array(arg[p])(context, builder, args[p])),
                (arg[p + 1], context.make_array(arg[p + 1])(context, builder, args[p + 1])),
            )
            for p in (13, 16)
        ]
        ends = [cgutils.alloca_once_value(builder, v) for v in (k_v, m_v)]
        size = ir.Constant(_I64, 3 * CLUSTER)
        halves = cluster_i_halves(builder, xi_p, builder.mul(ci_v, size), _LANES)
        reach = splat(builder, args[11], _VECTOR)
        inner = splat(builder, args[12], _VECTOR)
        with cgutils.for_range_slice(builder, lo_v, hi_v, ir.Constant(_I64, 1)) as (j, _):
            places = [builder.load(end) for end in ends]
            offset = []
            for d, (centre_type, centre) in enumerate(centres):
                at = cgutils.get_item_pointer(context, builder, centre_type, centre, [j])
                offset.append(builder.fptrunc(builder.fsub(shift[d], builder.load(at)), _F32))
            for ((part_type, part_a), (off_type, off_a)), to in zip(outputs, places, strict=True):
                for d in range(3):
                    slot = cgutils.get_item_pointer(
                        context, builder, off_type, off_a, [to, ir.Constant(_I64, d)]
                    )
                    builder.store(offset[d], slot)
                slot = cgutils.get_item_pointer(context, builder, part_type, part_a, [to])
                builder.store(builder.trunc(j, ir.IntType(32)), slot)
            shifted = cluster_j_less(builder, xj_p, builder.mul(j, size), offset, lanes=_LANES)
            near = _near_both(builder, halves, shifted, reach, inner)
            for end, to, kept in zip(ends, places, near, strict=True):
                builder.store(builder.add(to, builder.zext(kept, _I64)), end)
        values = [builder.load(end) for end in ends]
        return context.make_tuple(builder, signature.return_type, values)

    return sig, codegen


def _keep_near_twin(
    xi, xj, partners, offsets, start, end, ci, reach2, kept_partners, kept_offsets, k
):
    """:func:`_keep_near` in Python (under ``NUMBA_DISABLE_JIT=1``, and its test)."""
    if start == end:
        return k
    kept_partners[k] = partners[start]  # the cluster with itself: kept
    kept_offsets[k] = offsets[start]
    k += 1
    for q in range(start + 1, end):
        cj = partners[q]
        kept_partners[k] = cj
        kept_offsets[k] = offsets[q]
        k += _near_pair_twin(xi, xj, ci, cj, *offsets[q], reach2)
    return k


@python_twin(_keep_near_twin)
@intrinsic
def _keep_near(
    typingctx, xi, xj, partners, offsets, start, end, ci, reach2, kept_partners, kept_offsets, k
):
    """Copy i cluster ``ci``'s pairs ``start`` to ``end`` that have an atom pair within
    reach (:func:`_near_pair`'s check; the first, the cluster with itself, always) to
    ``kept_partners``/``kept_offsets`` from ``k`` on (which may be the same arrays, ``k``
    <= ``start``: in place); returns the end of the copied row. Every pair is written, a
    dropped one where the next kept one overwrites it (no branch), never past ``k + end
    - start``. ``offsets`` and ``kept_offsets``: (pairs, 3).

    The row's loop is written here, not in numba, so that the i cluster's vectors are
    loaded once per row: numba's loop reloaded and re-shuffled them for every pair (the
    float32 offsets it stores might be the float32 positions, as far as LLVM knows)."""
    if partners.dtype != kept_partners.dtype or offsets.dtype != kept_offsets.dtype:
        raise TypeError(
            f"_keep_near: the kept arrays as the list's, got {kept_partners} for "
            f"{partners} and {kept_offsets} for {offsets}"
        )
    sig = types.int64(
        xi, xj, partners, offsets, start, end, ci, reach2, kept_partners, kept_offsets, k
    )

    def codegen(context, builder, signature, args):
        arg = signature.args
        xi_p, xj_p = (array_data(context, builder, arg[n], args[n]) for n in range(2))
        arrays = {
            n: (arg[n], context.make_array(arg[n])(context, builder, args[n])) for n in (2, 3, 8, 9)
        }
        start_v, end_v, ci_v, k_v = (
            context.cast(builder, args[n], arg[n], types.int64) for n in (4, 5, 6, 10)
        )
        reach2 = args[7]
        result = cgutils.alloca_once_value(builder, k_v)

        def at(n, *index):
            return cgutils.get_item_pointer(context, builder, *arrays[n], list(index))

        def copy(q, to):
            """Pair q's partner and offset to place ``to``; the offset, three scalars."""
            builder.store(builder.load(at(2, q)), at(8, to))
            offset = []
            for d in range(3):
                value = builder.load(at(3, q, ir.Constant(_I64, d)))
                builder.store(value, at(9, to, ir.Constant(_I64, d)))
                offset.append(value)
            return offset

        with builder.if_then(builder.icmp_signed("<", start_v, end_v)):
            copy(start_v, k_v)  # the cluster with itself: kept
            size = ir.Constant(_I64, 3 * CLUSTER)
            halves = cluster_i_halves(builder, xi_p, builder.mul(ci_v, size), _LANES)
            reach = splat(builder, reach2, _VECTOR)
            builder.store(builder.add(k_v, ir.Constant(_I64, 1)), result)
            first = builder.add(start_v, ir.Constant(_I64, 1))
            with cgutils.for_range_slice(builder, first, end_v, ir.Constant(_I64, 1)) as (q, _):
                to = builder.load(result)
                offset = copy(q, to)
                cj = builder.sext(builder.load(at(2, q)), _I64)
                shifted = cluster_j_less(builder, xj_p, builder.mul(cj, size), offset, lanes=_LANES)
                near = _any_near(builder, halves, shifted, reach)
                builder.store(builder.add(to, builder.zext(near, _I64)), result)
        return builder.load(result)

    return sig, codegen
