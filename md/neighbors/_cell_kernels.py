"""Numba kernels for neighbour search (arrays and scalars only).

Lists are half lists in CSR form: ``neighbors[starts[i]:starts[i + 1]]`` are
the partners of row i, each unordered pair within the list radius listed
exactly once. The O(N^2) search lists atom indices (minimum image); the cell
search lists *slots*, atoms sorted by cell and wrapped into the box, with a
one-byte code per pair naming its periodic image (see ``md.neighbors``).
Kernels write into caller-owned arrays and return (or store) the number of
pairs found; when that exceeds the capacity of the buffer they keep counting
without writing, so the caller can grow the buffer and call again. Kernels
with a ``_threaded`` twin run their chunks on numba's threads; the plain one
runs them in turn, off the thread pool. The candidate tests are LLVM-IR
intrinsics built from ``md._simd`` (vector blocks, compare masks, AVX2 lane
permutes where numba compiles for AVX2, a portable bit-mask scan elsewhere).

The rebuild check
-----------------
``NeighborList.update`` asks ``_largest_displacement2`` whether any atom moved
more than skin/2 since the last build: one compiled entry for the serial and
the threaded pass (``_max_displacement2_threaded``), so the threaded one loads
at the first check of any run; it also catches non-finite positions. When a
barostat changed the cell, the build's positions are first mapped affinely
into the new cell and the allowance shrinks with the deformation's smallest
singular value, so the list is kept and its lengths, tilt and shifts follow
the cell (see ``md.neighbors``).

A build
-------
A build is one compiled call, ``_cell_list``. The grid, lengths and image
shifts of an unchanged periodic cell are kept from the last build, so the
build makes few interpreter calls, each slow once the pair kernels have
flushed the caches. In order:

1. ``_bin_atoms``, a counting sort by cell (threaded: ``_bin_atoms_threaded``,
   same result), gives the slot order: atoms sorted by (x, y) column and z
   cell, wrapped into the box, their coordinates stored by row.
2. ``_frame_pairs`` (one chunk of slots per thread: ``_frame_pairs_threaded``)
   writes the half list over the forward half of the 5 x 5 x 5 half-radius
   cells around each slot:

   - ``_slot_layout`` (threaded over (x, y) columns: ``_slot_layout_threaded``,
     ``_fill_columns``) lays the slots out again by z cell, x, y, so that a
     row of cells along y in one z layer is contiguous, and in the same pass
     writes each slot's cell and packed tag;
   - per (x, y) column, ``_gather_column`` copies the forward cells, as such
     rows (3 runs per z cell), shifted by their image, into one candidate
     array ordered by z cell (image cells past a periodic z edge included;
     slot and image code packed in a uint32; runs copied in vector blocks of
     ``GATHER_BLOCK`` entries by ``_gather_run`` and ``_copy_block``);
   - each slot tests that array's range of z cells cz - 2 to cz + 2, its own
     column's later slots up to cz + 2 read in place from the coordinate rows
     (padded by ``ROW_PADDING``; the earlier slots list their pairs with it),
     and near a periodic top the images of the column's bottom cells, in
     8-lane vector blocks (LLVM-IR intrinsics): ``_near_pack`` writes the
     hits' packed slot and code as it tests, by AVX2 lane permutes on x86
     with AVX2 (``_near_pack_blocks``), else by scanning a bit mask
     (``_near_pack_scan``: ``_near_bits``, then cttz); ``_keep`` counts
     before it writes near the end of the chunk's region; for a rank of a
     decomposed run, the rows beside ghosts then keep only the pairs whose
     designated atom is owned (``designates``, ``_keep_owned_row``, per
     column flags from ``_slot_owners``);
   - a single chunk is unpacked into slots and a one-byte image code per pair
     at its end; several are joined by ``_join_chunks``, on the threads: each
     chunk is unpacked straight to its place in the list where that overlaps
     no other chunk's region (with two chunks, always), the rest in place and
     then moved (memmove, ``md._simd.move_within``).
3. ``_balanced_bounds`` splits the rows into chunks of equal pair counts for
   the pair kernels.

``_brute_force_pairs`` (over atom indices, minimum image) replaces all of
this when a periodic axis has room for fewer than 5 half-radius cells; it is
also the reference the cell search is tested against. ``_atom_space_list``
translates a slot list into one over atom indices for potentials that read
``neighbors.starts``/``neighbors.neighbors``.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, prange, types
from numba.extending import intrinsic

from md._simd import (
    PERMUTATIONS,
    PERMUTE,
    array_data,
    bit_count,
    bits_float,
    compare_mask,
    float_bits,
    is_vector_array,
    load_vector,
    move_within,
    permute_lanes,
    python_twin,
    splat,
    store_vector,
    trailing_zeros,
)
from md.box import cell_matrix, min_image, periodic_tilt

#: The cell search packs a candidate's slot and image code into one uint32: slot in the
#: low bits, code (< 27) in the top five. So a list holds at most MAX_SLOTS atoms.
_CODE_SHIFT = np.uint32(27)
#: The code of an unshifted pair (no wrap along any axis: 9 + 3 + 1).
UNSHIFTED_CODE = 13
_SLOT_MASK = np.uint32((1 << 27) - 1)
MAX_SLOTS = 1 << 27
#: Entries the cell search's gather copies at once (see ``_gather_run``): the (z, x, y)
#: layout it copies from (``_slot_layout``) has this many readable entries past the end.
GATHER_BLOCK = 8
#: Entries past the last slot that the coordinate rows must have, finite: the search
#: reads each slot's own column straight from them, up to a test word (64) at a time.
ROW_PADDING = 64


@njit(cache=True, error_model="numpy")
def _brute_force_pairs(positions, lengths, inverse, tilt, r2_max, starts, neighbors):
    """O(N^2) half list (minimum image); the reference the cell search is tested against."""
    n = positions.shape[0]
    capacity = neighbors.shape[0]
    count = 0
    starts[0] = 0
    for i in range(n):
        xi = positions[i, 0]
        yi = positions[i, 1]
        zi = positions[i, 2]
        for j in range(i + 1, n):
            dx, dy, dz = min_image(
                xi - positions[j, 0], yi - positions[j, 1], zi - positions[j, 2],
                lengths, inverse, tilt,
            )  # fmt: skip
            if dx * dx + dy * dy + dz * dz < r2_max:
                if count < capacity:
                    neighbors[count] = j
                count += 1
        starts[i + 1] = count
    return count


@njit(cache=True, inline="always", error_model="numpy")
def _grid_cell(g, origin, inverse_width, n):
    """Cell index of a (wrapped) coordinate g along one axis, clamped to the grid."""
    k = int(np.floor((g - origin) * inverse_width))
    if k < 0:
        k = 0
    elif k >= n:
        k = n - 1
    return k


@njit(cache=True, error_model="numpy")
def _bin_atoms(
    positions, origin, cell_width, n_cells, periodic, box, tilt, cell_of, cell_starts, order,
    sorted_wrapped, images,
):  # fmt: skip
    """Counting sort of atoms by cell (cells of the restricted triclinic cell).

    Atoms are binned by their sheared-back coordinates g (``md.box.fractional``:
    the fractional coordinate times the edge along periodic axes), in which
    the cell is a rectangular box of edges ``box``; ``tilt`` (xy, xz, yz) is
    zero for an orthorhombic box, where g is the position. Writes
    ``cell_of[i]`` (flat cell index of atom i), ``cell_starts``
    (n_cells + 1 CSR offsets), ``order`` (atom indices grouped by cell, in
    index order within a cell),
    ``sorted_wrapped[:, p]`` (shape (3, N): coordinates in rows), the
    position of atom ``order[p]`` wrapped into
    the cell (g in [0, L)) along periodic axes, so a cell's atoms are
    contiguous in memory, and ``images[p]`` (int32), the cell vectors added
    to wrap it: ``sorted_wrapped[:, p] == positions[order[p]] + images[p] @ h``
    (h the cell matrix) up to round-off, exactly for an orthorhombic box.
    Open axes are clamped to the grid, whose origin and width the caller
    chose to span the atoms. ``_bin_atoms_threaded`` (same arguments and
    ``chunks``) gives the same result on numba's threads.
    """
    n = positions.shape[0]
    total = n_cells[0] * n_cells[1] * n_cells[2]
    counts = np.zeros((1, total), dtype=np.int64)
    moved = np.empty((n, 3))  # wrapped positions, by atom
    wraps = np.empty((n, 3), dtype=np.int32)
    _bin_pass(0, n, positions, origin, cell_width, n_cells, periodic, box, tilt, cell_of,
              moved, wraps, counts[0])  # fmt: skip
    _cell_offsets(counts, cell_starts)
    _scatter_pass(0, n, cell_of, moved, wraps, counts[0], order, sorted_wrapped, images)


@njit(cache=True, parallel=True, error_model="numpy")
def _bin_atoms_threaded(
    positions, origin, cell_width, n_cells, periodic, box, tilt, cell_of, cell_starts, order,
    sorted_wrapped, images, chunks,
):  # fmt: skip
    """``_bin_atoms`` with its two passes over atoms in ``chunks`` chunks on numba's
    threads; each chunk's atoms take their places in a cell after the earlier
    chunks', so the result is the serial one."""
    n = positions.shape[0]
    total = n_cells[0] * n_cells[1] * n_cells[2]
    counts = np.zeros((chunks, total), dtype=np.int64)
    moved = np.empty((n, 3))
    wraps = np.empty((n, 3), dtype=np.int32)
    for c in prange(chunks):
        _bin_pass(c * n // chunks, (c + 1) * n // chunks, positions, origin, cell_width,
                  n_cells, periodic, box, tilt, cell_of, moved, wraps, counts[c])  # fmt: skip
    _cell_offsets(counts, cell_starts)
    for c in prange(chunks):
        _scatter_pass(c * n // chunks, (c + 1) * n // chunks, cell_of, moved, wraps, counts[c],
                      order, sorted_wrapped, images)  # fmt: skip


@njit(cache=True, inline="always", error_model="numpy")
def _bin_pass(first, last, positions, origin, cell_width, n_cells, periodic, box, tilt, cell_of,
              moved, wraps, counts):  # fmt: skip
    """Atoms first..last-1: cell, wrapped position and wraps; ``counts`` per cell."""
    nx, ny, nz = n_cells[0], n_cells[1], n_cells[2]
    xy, xz, yz = tilt[0], tilt[1], tilt[2]
    sheared = xy != 0.0 or xz != 0.0 or yz != 0.0
    # Products with reciprocals, not divisions (the divisions were most of the time).
    # Cells come from the wrapped coordinates themselves, so an atom's cell and its
    # wrapped position agree even where a product rounds across an edge.
    inverse_box = 1.0 / box
    inverse_width = 1.0 / cell_width
    for i in range(first, last):
        x = positions[i, 0]
        y = positions[i, 1]
        z = positions[i, 2]
        gx, gy, gz = x, y, z
        if sheared:  # a tilt is non-zero only between periodic axes
            sz = gz * inverse_box[2] if periodic[2] else 0.0
            gy -= sz * yz
            sy = gy * inverse_box[1] if periodic[1] else 0.0
            gx -= sy * xy + sz * xz
        wx = -np.floor(gx * inverse_box[0]) if periodic[0] else 0.0
        wy = -np.floor(gy * inverse_box[1]) if periodic[1] else 0.0
        wz = -np.floor(gz * inverse_box[2]) if periodic[2] else 0.0
        kx = _grid_cell(gx + box[0] * wx, origin[0], inverse_width[0], nx)
        ky = _grid_cell(gy + box[1] * wy, origin[1], inverse_width[1], ny)
        kz = _grid_cell(gz + box[2] * wz, origin[2], inverse_width[2], nz)
        c = (kx * ny + ky) * nz + kz
        cell_of[i] = c
        counts[c] += 1
        x += box[0] * wx
        y += box[1] * wy
        z += box[2] * wz
        if sheared:
            x += wy * xy + wz * xz
            y += wz * yz
        moved[i, 0] = x
        moved[i, 1] = y
        moved[i, 2] = z
        wraps[i, 0] = np.int32(wx)
        wraps[i, 1] = np.int32(wy)
        wraps[i, 2] = np.int32(wz)


@njit(cache=True, inline="always", error_model="numpy")
def _cell_offsets(counts, cell_starts):
    """``cell_starts`` from the chunks' counts (chunks, cells), and each chunk's count
    replaced by the slot where its first atom of that cell goes."""
    at = 0
    for c in range(counts.shape[1]):
        cell_starts[c] = at
        for chunk in range(counts.shape[0]):
            here = counts[chunk, c]
            counts[chunk, c] = at
            at += here
    cell_starts[counts.shape[1]] = at


@njit(cache=True, inline="always", error_model="numpy")
def _scatter_pass(first, last, cell_of, moved, wraps, fill, order, sorted_wrapped, images):
    """Atoms first..last-1 to their slots, from the slots ``fill`` (per cell) on."""
    for i in range(first, last):
        c = cell_of[i]
        p = fill[c]
        order[p] = i
        fill[c] += 1
        sorted_wrapped[0, p] = moved[i, 0]
        sorted_wrapped[1, p] = moved[i, 1]
        sorted_wrapped[2, p] = moved[i, 2]
        images[p, 0] = wraps[i, 0]
        images[p, 1] = wraps[i, 1]
        images[p, 2] = wraps[i, 2]


@njit(cache=True, inline="always", error_model="numpy")
def _neighbor_cell(c, offset, n, periodic):
    """Index of the adjacent cell c + offset along one axis and its wrap (-1, 0 or 1).

    Returns (-1, 0) past the edge of an open axis.
    """
    k = c + offset
    if k < 0:
        if not periodic:
            return -1, 0
        return k + n, -1
    if k >= n:
        if not periodic:
            return -1, 0
        return k - n, 1
    return k, 0


@njit(cache=True, error_model="numpy")
def _frame_pairs(
    wrapped, slot_cell, r2_max, n_cells, reach, periodic, box, tilt, cell_starts, layout,
    bounds, capacity, starts, neighbors, codes, counts, owners,
):  # fmt: skip
    """Half list over slots (atoms in cell order), searched in chunks on parallel threads.

    The serial driver; ``_frame_pairs_threaded`` runs the chunks on
    numba's threads. Slot p holds the atom whose wrapped position is ``wrapped[:, p]``
    (``wrapped`` is (3, N + ``ROW_PADDING``), as ``_bin_atoms`` writes it,
    with finite padding past the last slot), in cell
    ``slot_cell[p]``; ``cell_starts`` gives each cell's slots, and ``layout``
    is ``_slot_layout``'s (planes, tags, most) for them. Chunk c covers
    slots ``bounds[c]`` to ``bounds[c + 1]`` and writes its pairs into its own
    region ``neighbors[c * capacity:(c + 1) * capacity]`` (and ``codes``), so
    no two threads write the same memory; ``starts[p + 1]`` is the end of row
    p counted from the start of its region, ``counts[c]`` the chunk's pair
    count (it keeps counting past ``capacity`` without writing).
    The pairs of several chunks are left packed (slot and code in one
    uint32, ``MAX_SLOTS``): ``_join_chunks`` unpacks them and joins the
    regions into one CSR list. A single chunk unpacks its own at its end.

    Cells are at least list radius / ``reach`` wide (reach 1 or 2), so
    every partner lies within ``reach`` cells along each axis. Each
    unordered pair is listed once, under the slot whose cell sees the other
    through the own cell (then under the lower slot) or one of the
    lexicographically positive offsets (13 for reach 1, 62 for reach 2).
    ``owners`` = (slot_owned, slot_ids, column_mixed) (``_slot_owners``) keeps
    only the pairs a rank of a decomposed run evaluates, row by row as the
    search writes them (empty arrays: every pair).
    ``codes[k]`` names the image shift s
    of that neighbour cell, so the pair displacement is
    ``wrapped[:, p] - wrapped[:, q] - s`` with no minimum image (see
    ``_shift_table``). Requires at least 2 reach + 1 cells along every
    periodic axis, so the cells around any cell are distinct.
    """
    planes, tags, most = layout
    for chunk in range(bounds.shape[0] - 1):
        _frame_pairs_chunk(
            chunk, wrapped, slot_cell, r2_max, n_cells, reach, periodic, box, tilt,
            cell_starts, planes, tags, bounds, capacity, most, starts, neighbors, codes, counts,
            owners,
        )  # fmt: skip


@njit(cache=True, parallel=True, error_model="numpy")
def _frame_pairs_threaded(
    wrapped, slot_cell, r2_max, n_cells, reach, periodic, box, tilt, cell_starts, layout,
    bounds, capacity, starts, neighbors, codes, counts, owners,
):  # fmt: skip
    """``_frame_pairs`` with one chunk per thread (same arguments, same result)."""
    planes, tags, most = layout
    for chunk in prange(bounds.shape[0] - 1):
        _frame_pairs_chunk(
            chunk, wrapped, slot_cell, r2_max, n_cells, reach, periodic, box, tilt,
            cell_starts, planes, tags, bounds, capacity, most, starts, neighbors, codes, counts,
            owners,
        )  # fmt: skip


@njit(cache=True, error_model="numpy")
def _frame_pairs_chunk(
    chunk, wrapped, slot_cell, r2_max, n_cells, reach, periodic, box, tilt, cell_starts,
    planes, tags, bounds, capacity, most, starts, neighbors, codes, counts, owners,
):  # fmt: skip
    """One chunk of ``_frame_pairs``: slots bounds[chunk] to bounds[chunk + 1].

    The slots of one (x, y) column of cells are consecutive and in z order.
    Per column, the slots of its forward neighbour columns (``reach`` cells
    around along y, and ahead along x) are copied, shifted by their image,
    into one contiguous candidate array ordered by z cell, with ``reach``
    image cells past each end of a periodic z axis (``_gather_column``). A
    slot i in z cell cz then tests three ranges: the candidates of z cells
    cz - reach to cz + reach, its own column's later slots up to z cell
    cz + reach (read in place, packed values from ``tags``; the earlier
    slots list their pairs with i), and, near the top of a periodic z axis,
    the images of the column's bottom cells. The tests run in vector blocks
    of 8. ``_near_pack`` writes the hits' packed values
    as it tests (AVX2 permutes, or bit masks scanned bit by bit on other
    CPUs); near the end of the chunk's region ``_keep`` counts before it
    writes. A neighbour cell across the edge of
    the cell along axes with wraps (wx, wy, wz) is seen shifted by
    wx a + wy b + wz c, named by code 9 (wx + 1) + 3 (wy + 1) + wz + 1. A
    candidate carries its slot and code packed in one uint32 (``MAX_SLOTS``).
    With ``owners`` (a rank's list), a row found beside a ghost (a ghost's
    own row, or one in a column with ghosts within ``reach`` columns) keeps
    only its pairs whose designated atom (``designates``) is owned
    (``_keep_owned_row``), while its hits are in the cache.
    """
    slot_owned, slot_ids, column_mixed = owners
    filtering = slot_owned.shape[0] > 0
    nz = n_cells[2]
    most_cell, most_column = most
    base = chunk * capacity
    ghost = reach if periodic[2] else 0  # image cells past each z end
    n_z = nz + 2 * ghost
    n_columns = reach * (2 * reach + 1) + reach  # the forward columns
    size = n_columns * (most_column + 2 * ghost * most_cell)
    # readable past the last candidate: a gather block, a test word
    cx = np.empty(size + 64)
    cy = np.empty(size + 64)
    cz = np.empty(size + 64)
    c_packed = np.empty(size + 64, dtype=np.uint32)
    z_start = np.empty(n_z + 1, dtype=np.int64)  # candidates of z cell zc - ghost
    masks = np.empty(size // 64 + 1, dtype=np.uint64)
    own_size = reach * most_cell + 64
    own = (np.empty(own_size), np.empty(own_size), np.empty(own_size),
           np.empty(own_size, dtype=np.uint32), np.empty(reach + 1, dtype=np.int64))  # fmt: skip
    runs = np.empty((4, 2 * reach + 2), dtype=np.int64)
    run_shifts = np.empty((2, 2 * reach + 2))
    xs, ys, zs = wrapped[0], wrapped[1], wrapped[2]
    packed_list = neighbors.view(np.uint32)  # the search writes packed values, unpacked last
    count = 0
    p = bounds[chunk]
    end = bounds[chunk + 1]
    while p < end:
        column = slot_cell[p] // nz
        stop = min(cell_starts[column * nz + nz], end)
        _gather_column(
            column, n_cells, reach, ghost, periodic, box, tilt, planes, runs, run_shifts, cx,
            cy, cz, c_packed, z_start, own,
        )  # fmt: skip
        mixed = column_mixed[column] if filtering else False
        for i in range(p, stop):
            row_begin = count
            kz = slot_cell[i] - column * nz
            first = z_start[max(kz - reach + ghost, 0)]  # forward cells cz -/+ reach
            last = z_start[min(kz + reach + ghost, n_z - 1) + 1]
            # the own column's later slots up to z cell cz + reach (the earlier ones list
            # their pairs with i), and past a periodic top its bottom cells' images
            own_last = cell_starts[column * nz + min(kz + reach, nz - 1) + 1]
            above = kz + reach - nz + 1 if ghost else 0
            ghost_last = own[4][above] if above > 0 else 0
            if count + (last - first) + (own_last - i - 1) + ghost_last + 8 <= capacity:
                # room for every candidate and a block's spill: write as they are tested
                # (here, not in _keep: the inlined branch there slowed the loop by 25%)
                at = base + count
                w = first
                while w + 64 <= last:
                    at = _near_pack_whole(xs[i], ys[i], zs[i], r2_max, cx, cy, cz, c_packed,
                                          w, 64, PERMUTATIONS, packed_list, at)  # fmt: skip
                    w += 64
                if w < last:
                    at = _near_pack(xs[i], ys[i], zs[i], r2_max, cx, cy, cz, c_packed, w,
                                    last - w, PERMUTATIONS, packed_list, at)  # fmt: skip
                w = i + 1
                while w < own_last:  # a crowded column may hold more than a word
                    at = _near_pack(xs[i], ys[i], zs[i], r2_max, xs, ys, zs, tags, w,
                                    min(64, own_last - w), PERMUTATIONS, packed_list,
                                    at)  # fmt: skip
                    w += 64
                w = 0
                while w < ghost_last:
                    at = _near_pack(xs[i], ys[i], zs[i], r2_max, own[0], own[1], own[2],
                                    own[3], w, min(64, ghost_last - w), PERMUTATIONS,
                                    packed_list, at)  # fmt: skip
                    w += 64
                count = at - base
            else:
                for r in range(3):  # forward cells, own column, its images above the top
                    if r == 0:
                        tx, ty, tz, tp, a, b = cx, cy, cz, c_packed, first, last
                    elif r == 1:
                        tx, ty, tz, tp, a, b = xs, ys, zs, tags, i + 1, own_last
                    else:
                        tx, ty, tz, tp, a, b = own[0], own[1], own[2], own[3], 0, ghost_last
                    count += _keep(xs[i], ys[i], zs[i], r2_max, tx, ty, tz, tp, a, b, masks,
                                   base, count, capacity, packed_list)  # fmt: skip
            # (past the capacity nothing was written: the count stays an upper bound)
            if (mixed or (filtering and not slot_owned[i])) and count <= capacity:
                count = _keep_owned_row(packed_list, base + row_begin, base + count,
                                        slot_owned, slot_ids, i) - base  # fmt: skip
            starts[i + 1] = count
        p = stop
    counts[chunk] = count
    if bounds.shape[0] == 2 and count <= capacity:  # the only chunk: unpack it here, hot
        listed = packed_list[:count]
        listed_codes = codes[:count]
        for k in range(count):
            listed_codes[k] = listed[k] >> _CODE_SHIFT
        for k in range(count):
            listed[k] &= _SLOT_MASK


@njit(cache=True, error_model="numpy")
def _slot_layout(wrapped, cell_starts, n_cells, slot_cell):
    """What the search reads besides the slots' rows, in one pass over the slots.

    Returns (planes, tags, most) and fills ``slot_cell`` (each slot's cell):

    - ``planes`` = (x, y, z, slot, plane_starts): the slots again, ordered by
      z cell, then x, then y (cell (kz nx + kx) ny + ky), coordinates and slot
      number in that order, padded with ``GATHER_BLOCK`` finite entries, and
      each cell's start. Along y, the cells of one z layer and x row are then
      contiguous, so the search copies its candidates in runs of several
      cells;
    - ``tags``: the packed values of slots 0 .. ``wrapped.shape[1]`` - 1 seen
      with no image shift (code 13);
    - ``most``: the most slots in one cell and in one (x, y) column.

    ``_slot_layout_threaded`` fills the (x, y) columns on numba's threads.
    """
    planes, tags, most = _layout_arrays(wrapped.shape[1], cell_starts, n_cells)
    _fill_columns(0, n_cells[0] * n_cells[1], wrapped, cell_starts, n_cells, planes, tags,
                  slot_cell)  # fmt: skip
    return planes, tags, most


@njit(cache=True, parallel=True, error_model="numpy")
def _slot_layout_threaded(wrapped, cell_starts, n_cells, slot_cell, chunks):
    """``_slot_layout`` with the (x, y) columns filled in ``chunks`` chunks on numba's
    threads."""
    planes, tags, most = _layout_arrays(wrapped.shape[1], cell_starts, n_cells)
    n_columns = n_cells[0] * n_cells[1]
    for c in prange(chunks):
        _fill_columns(c * n_columns // chunks, (c + 1) * n_columns // chunks, wrapped,
                      cell_starts, n_cells, planes, tags, slot_cell)  # fmt: skip
    return planes, tags, most


@njit(cache=True, error_model="numpy")
def _layout_arrays(size, cell_starts, n_cells):
    """The arrays of ``_slot_layout``, with the cell starts, the padding and ``most``
    filled in (one pass over the cells)."""
    nx, ny, nz = n_cells[0], n_cells[1], n_cells[2]
    n = cell_starts[nx * ny * nz]
    plane_starts = np.empty(nx * ny * nz + 1, dtype=np.int64)
    at = 0
    k = 0
    most_cell = 0
    for kz in range(nz):
        for column in range(nx * ny):
            cell = column * nz + kz
            plane_starts[k] = at
            k += 1
            in_cell = cell_starts[cell + 1] - cell_starts[cell]
            most_cell = max(most_cell, in_cell)
            at += in_cell
    plane_starts[k] = at
    most_column = 0
    for c in range(0, nx * ny * nz, nz):
        most_column = max(most_column, cell_starts[c + nz] - cell_starts[c])
    # Every slot's entry is written by _fill_columns; only the padding needs values.
    px = np.empty(n + GATHER_BLOCK)
    py = np.empty(n + GATHER_BLOCK)
    pz = np.empty(n + GATHER_BLOCK)
    slot = np.empty(n + GATHER_BLOCK, dtype=np.uint32)
    px[n:] = 0.0
    py[n:] = 0.0
    pz[n:] = 0.0
    slot[n:] = 0
    tags = np.empty(size, dtype=np.uint32)
    for p in range(n, size):
        tags[p] = _UNSHIFTED | np.uint32(p)
    return (px, py, pz, slot, plane_starts), tags, (most_cell, most_column)


#: The packed code of a candidate seen with no image shift.
_UNSHIFTED = np.uint32(UNSHIFTED_CODE) << _CODE_SHIFT


@njit(cache=True, inline="always", error_model="numpy")
def _fill_columns(first, last, wrapped, cell_starts, n_cells, planes, tags, slot_cell):
    """The slots of (x, y) columns first..last-1, read in slot order: into ``planes``
    at their cells' places there, and their tags and cells (``_slot_layout``).

    Reads in slot order and writes a cell's run at a time; filling by z
    layer instead (reads strided by the column length, writes in order) took
    a third longer in a run."""
    px, py, pz, slot, plane_starts = planes
    nx, ny, nz = n_cells[0], n_cells[1], n_cells[2]
    layer = nx * ny
    for column in range(first, last):
        for kz in range(nz):
            cell = column * nz + kz
            at = plane_starts[kz * layer + column]
            for p in range(cell_starts[cell], cell_starts[cell + 1]):
                px[at] = wrapped[0, p]
                py[at] = wrapped[1, p]
                pz[at] = wrapped[2, p]
                slot[at] = p
                at += 1
                tags[p] = _UNSHIFTED | np.uint32(p)
                slot_cell[p] = cell


@njit(cache=True, error_model="numpy")
def _gather_column(column, n_cells, reach, ghost, periodic, box, tilt, planes, runs,
                   run_shifts, cx, cy, cz, c_packed, z_start, own):  # fmt: skip
    """Copy the candidates of one (x, y) column for ``_frame_pairs_chunk``.

    Per z cell (cell zc - ghost from ``z_start[zc]``), the column's forward
    neighbour cells: for x offset 0 the cells at y offsets 1 to reach, for x
    offsets 1 to reach those at -reach to reach. In ``planes``
    (``_slot_layout``) each such row of cells is one run of slots, or two
    where it wraps along y; they go to ``cx, cy, cz`` shifted by their
    image (slots and codes packed in ``c_packed``). The column's own slots
    need no copy (the search reads them where they are), except its
    ``ghost`` bottom cells seen above the top of a periodic z axis: those go
    to ``own`` = (x, y, z, packed, starts), cell k from ``starts[k]``.
    ``runs`` (int64) and ``run_shifts`` (float64), shape (4, 2 reach + 2) and
    (2, 2 reach + 2), are scratch for the runs.
    """
    px, py, pz, p_slot, plane_starts = planes
    xy, xz, yz = tilt[0], tilt[1], tilt[2]
    nx, ny, nz = n_cells[0], n_cells[1], n_cells[2]
    kx0 = column // ny
    ky0 = column % ny
    # Runs of cells along y in one x row: x cell, first and last y cell, code and
    # shift from the wraps along x and y.
    run_x, run_first, run_last, code_xy = runs[0], runs[1], runs[2], runs[3]
    shift_x, shift_y = run_shifts[0], run_shifts[1]
    n_runs = 0
    for ox in range(0, reach + 1):
        kx, wx = _neighbor_cell(kx0, ox, nx, periodic[0])
        if kx < 0:
            continue
        last_wy = 2  # no run open
        for oy in range(1 if ox == 0 else -reach, reach + 1):
            ky, wy = _neighbor_cell(ky0, oy, ny, periodic[1])
            if ky < 0:
                last_wy = 2
                continue
            if wy == last_wy:
                run_last[n_runs - 1] = ky
                continue
            run_x[n_runs] = kx
            run_first[n_runs] = ky
            run_last[n_runs] = ky
            shift_x[n_runs] = wx * box[0] + wy * xy
            shift_y[n_runs] = wy * box[1]
            code_xy[n_runs] = (wx + 1) * 9 + (wy + 1) * 3 + 1
            last_wy = wy
            n_runs += 1
    m = 0
    for zc in range(nz + 2 * ghost):
        z_start[zc] = m
        kz, wz = _neighbor_cell(zc - ghost, 0, nz, periodic[2])
        layer = kz * nx
        for r in range(n_runs):
            first_y = run_first[r]
            row = (layer + run_x[r]) * ny
            m = _gather_run(
                plane_starts[row + first_y], plane_starts[row + run_last[r] + 1],
                shift_x[r] + wz * xz, shift_y[r] + wz * yz, wz * box[2], code_xy[r] + wz,
                px, py, pz, p_slot, cx, cy, cz, c_packed, m,
            )  # fmt: skip
    z_start[nz + 2 * ghost] = m
    ox_, oy_, oz_, o_packed, o_start = own
    m = 0
    for k in range(ghost):  # the own column's bottom cells, one cell vector c up
        o_start[k] = m
        cell = (k * nx + kx0) * ny + ky0
        m = _gather_run(plane_starts[cell], plane_starts[cell + 1], xz, yz, box[2], 9 + 3 + 2,
                        px, py, pz, p_slot, ox_, oy_, oz_, o_packed, m)  # fmt: skip
    o_start[ghost] = m


@njit(cache=True, inline="always", error_model="numpy")
def _gather_run(first, last, sx, sy, sz, code, xs, ys, zs, slots, cx, cy, cz, c_packed, m):
    """Append entries first..last-1, shifted by s, to the candidates at m; return the new end.

    ``c_packed`` gets each entry's slot with the image code in its top bits
    (``MAX_SLOTS``). Copies whole blocks of ``GATHER_BLOCK`` entries
    (``_copy_block``), so a short run takes one block; what lies past
    ``last`` is copied too and overwritten by the next run or never read. So
    the source arrays need ``GATHER_BLOCK`` readable entries past their last
    one, and the candidate arrays as many past their last candidate.
    """
    tag = np.uint32(code) << _CODE_SHIFT
    done = 0
    while True:
        _copy_block(xs, ys, zs, slots, first + done, sx, sy, sz, tag, cx, cy, cz, c_packed,
                    m + done)  # fmt: skip
        done += GATHER_BLOCK
        if done >= last - first:
            return m + last - first


def _copy_block_twin(xs, ys, zs, slots, first, sx, sy, sz, tag, cx, cy, cz, c_packed, m):
    """``_copy_block`` in Python (``md._simd.python_twin``)."""
    block = slice(first, first + GATHER_BLOCK)
    to = slice(m, m + GATHER_BLOCK)
    cx[to] = xs[block] + sx
    cy[to] = ys[block] + sy
    cz[to] = zs[block] + sz
    c_packed[to] = slots[block] | tag


@python_twin(_copy_block_twin)
@intrinsic
def _copy_block(typingctx, xs, ys, zs, slots, first, sx, sy, sz, tag, cx, cy, cz, c_packed, m):
    """Copy ``GATHER_BLOCK`` entries from ``first`` to the candidates at ``m``: coordinates
    plus (sx, sy, sz), slots or'ed with ``tag``.

    As vectors (one load, add and store per array): numba's element loop
    here stayed scalar, the compiler unsure that source and target differ.
    """
    doubles = (xs, ys, zs, cx, cy, cz)
    if not (
        all(is_vector_array(a, types.float64) for a in doubles)
        and is_vector_array(slots, types.uint32)
        and is_vector_array(c_packed, types.uint32)
    ):
        return None
    sig = types.void(
        xs, ys, zs, slots, types.intp, types.float64, types.float64, types.float64,
        types.uint32, cx, cy, cz, c_packed, types.intp,
    )  # fmt: skip

    def codegen(context, builder, signature, args):
        width = GATHER_BLOCK
        vector = ir.VectorType(ir.DoubleType(), width)
        words = ir.VectorType(ir.IntType(32), width)
        data = [array_data(context, builder, signature.args[k], args[k]) for k in range(14)
                if k not in (4, 5, 6, 7, 8, 13)]  # fmt: skip
        sources, targets = data[:4], data[4:]
        first, m = args[4], args[13]
        for source, target, shift in zip(sources[:3], targets[:3], args[5:8], strict=True):
            moved = builder.fadd(load_vector(builder, source, first, vector),
                                 splat(builder, shift, vector))  # fmt: skip
            store_vector(builder, moved, target, m)
        tagged = builder.or_(load_vector(builder, sources[3], first, words),
                             splat(builder, args[8], words))  # fmt: skip
        store_vector(builder, tagged, targets[3], m)
        return context.get_dummy_value()

    return sig, codegen


class _Candidates:
    """IR of the search's candidate test (``_near_bits``, the ``_near_pack`` family): the
    distance test of one block of 8 candidates."""

    def __init__(self, context, builder, signature, args):
        f64, i32 = ir.DoubleType(), ir.IntType(32)
        self.builder = builder
        self.doubles = ir.VectorType(f64, 8)
        self.words = ir.VectorType(i32, 8)
        self.centre = [splat(builder, args[k], self.doubles) for k in range(3)]
        self.r2 = splat(builder, args[3], self.doubles)
        self.arrays = [
            array_data(context, builder, signature.args[k], args[k]) for k in (4, 5, 6, 7)
        ]
        self.start = args[8]

    def block(self, block):
        """(packed values, <8 x i1> near) of candidates start + 8 block + 0..7: closer
        than sqrt(r2_max), left to right as dx dx + dy dy + dz dz (the brute-force
        search's arithmetic: the same candidates pass)."""
        builder = self.builder
        index = builder.add(self.start, ir.Constant(ir.IntType(64), 8 * block))
        kinds = (self.doubles, self.doubles, self.doubles, self.words)
        *coordinates, values = (
            load_vector(builder, a, index, v) for a, v in zip(self.arrays, kinds, strict=True)
        )
        dx, dy, dz = (builder.fsub(c, t) for c, t in zip(self.centre, coordinates, strict=True))
        d2 = builder.fadd(
            builder.fadd(builder.fmul(dx, dx), builder.fmul(dy, dy)), builder.fmul(dz, dz)
        )
        return values, builder.fcmp_ordered("<", d2, self.r2)


def _near_lanes(xi, yi, zi, r2_max, tx, ty, tz, start, count):
    """Python twin of ``_Candidates``: bool per candidate start..start+count-1, closer than
    sqrt(r2_max), with the same arithmetic (no fused multiply-add)."""
    lanes = slice(start, start + count)
    with np.errstate(over="ignore", invalid="ignore"):  # lanes past the last are any bits
        dx, dy, dz = xi - tx[lanes], yi - ty[lanes], zi - tz[lanes]
        return dx * dx + dy * dy + dz * dz < r2_max


def _candidate_types(tx, ty, tz, packed):
    """Whether the candidate arrays are what ``_Candidates`` reads."""
    wanted = (types.float64, types.float64, types.float64, types.uint32)
    return all(is_vector_array(a, d) for a, d in zip((tx, ty, tz, packed), wanted, strict=True))


def _near_bits_twin(xi, yi, zi, r2_max, tx, ty, tz, packed, start):
    """``_near_bits`` in Python (``md._simd.python_twin``)."""
    near = _near_lanes(xi, yi, zi, r2_max, tx, ty, tz, start, 64)
    return np.uint64(sum(1 << int(k) for k in np.flatnonzero(near)))


@python_twin(_near_bits_twin)
@intrinsic
def _near_bits(typingctx, xi, yi, zi, r2_max, tx, ty, tz, packed, start):
    """Bit k set where candidate ``start + k`` (k < 64) is closer than sqrt(r2_max).

    Eight blocks of ``_Candidates``, each block's <8 x i1> mask put straight
    into the word (a movemask: numba has no way to say it). Reads 64 entries
    from ``start`` of the C-contiguous float64 ``tx, ty, tz`` and uint32
    ``packed``: they need that many readable entries past their last
    candidate, and the caller masks the bits past it.
    """
    if not _candidate_types(tx, ty, tz, packed):
        return None
    sig = types.uint64(
        types.float64, types.float64, types.float64, types.float64, tx, ty, tz, packed,
        types.intp,
    )  # fmt: skip

    def codegen(context, builder, signature, args):
        i64 = ir.IntType(64)
        test = _Candidates(context, builder, signature, args)
        word = ir.Constant(i64, 0)
        for block in range(8):
            _, near = test.block(block)
            shifted = builder.shl(compare_mask(builder, near), ir.Constant(i64, 8 * block))
            word = builder.or_(word, shifted)
        return word

    return sig, codegen


def _permute_packer(blocks: int, whole: bool):
    """``_near_pack`` by AVX2 permutes (only where ``md._simd.PERMUTE``) for ``blocks``
    blocks of 8 candidates; ``whole``: all of them valid (no lane count test).

    Per block of 8 candidates (``_Candidates``), the near lanes' packed
    values move to the front of the vector (``permute_lanes``); all 8 lanes
    are stored at ``out[at:]`` and ``at`` advances by the kept count, so the
    next block overwrites the rest: no loop, no branch per candidate or hit.
    """

    def typer(typingctx, xi, yi, zi, r2_max, tx, ty, tz, packed, start, valid, table, out, at):
        if not (_candidate_types(tx, ty, tz, packed) and is_vector_array(out, types.uint32)):
            return None
        sig = types.int64(
            types.float64, types.float64, types.float64, types.float64, tx, ty, tz, packed,
            types.intp, types.intp, table, out, types.intp,
        )  # fmt: skip
        return sig, codegen

    def codegen(context, builder, signature, args):
        i32 = ir.IntType(32)
        test = _Candidates(context, builder, signature, args)
        valid = splat(builder, builder.trunc(args[9], i32), test.words)
        rows = array_data(context, builder, signature.args[10], args[10])
        target = array_data(context, builder, signature.args[11], args[11])
        at = args[12]
        for block in range(blocks):
            values, kept = test.block(block)
            if not whole:
                lanes = ir.Constant(test.words, [8 * block + k for k in range(8)])
                kept = builder.and_(kept, builder.icmp_signed("<", lanes, valid))
            mask = compare_mask(builder, kept)
            store_vector(builder, permute_lanes(builder, values, mask, rows), target, at)
            at = builder.add(at, builder.ctpop(mask))
        return at

    def twin(xi, yi, zi, r2_max, tx, ty, tz, packed, start, valid, table, out, at):
        """The same in Python (``md._simd.python_twin``): each block's 8 lanes stored as
        the permute leaves them (kept values first, then lane 0's as the table's zeros
        pick)."""
        for block in range(blocks):
            first = start + 8 * block
            kept = _near_lanes(xi, yi, zi, r2_max, tx, ty, tz, first, 8)
            if not whole:
                kept &= 8 * block + np.arange(8) < valid
            mask = int(np.dot(kept, 1 << np.arange(8)))
            out[at : at + 8] = packed[first : first + 8][table[mask]]
            at += int(kept.sum())
        return np.int64(at)

    typer.__name__ = f"_near_pack_{blocks}_{'whole' if whole else 'partial'}"
    return python_twin(twin)(intrinsic(typer))


_near_pack_permute_whole = _permute_packer(8, whole=True)
_near_pack_permute_block = _permute_packer(1, whole=False)


@njit(cache=True, inline="always", error_model="numpy")
def _near_pack_blocks(xi, yi, zi, r2_max, tx, ty, tz, packed, start, valid, table, out, at):
    """``_near_pack`` by AVX2 permutes, block by block: a range's last, partial word
    tests only the blocks it has."""
    done = 0
    while done < valid:
        at = _near_pack_permute_block(xi, yi, zi, r2_max, tx, ty, tz, packed, start + done,
                                      valid - done, table, out, at)  # fmt: skip
        done += 8
    return at


@njit(cache=True, inline="always", error_model="numpy")
def _near_pack_scan(xi, yi, zi, r2_max, tx, ty, tz, packed, start, valid, table, out, at):
    """``_near_pack`` on any CPU: ``_near_bits``, then the set bits one by one."""
    m = _near_bits(xi, yi, zi, r2_max, tx, ty, tz, packed, start)
    if valid < 64:
        m &= (np.uint64(1) << np.uint64(valid)) - np.uint64(1)
    end = np.uint64(at)  # unsigned indices: no negative-index wrap code in the loop
    row = packed[start:]
    while m:
        out[end] = row[np.uint64(trailing_zeros(m))]
        end += np.uint64(1)
        m &= m - np.uint64(1)
    return np.int64(end)


#: Write the candidates start..start+valid-1 (valid <= 64) closer than sqrt(r2_max),
#: their packed values, at ``out[at:]`` in order; return the new end. The 8 entries
#: from it on may be overwritten (the permute path stores whole blocks).
_near_pack = _near_pack_blocks if PERMUTE else _near_pack_scan
#: ``_near_pack`` for exactly 64 candidates (``valid`` ignored).
_near_pack_whole = _near_pack_permute_whole if PERMUTE else _near_pack_scan


@njit(cache=True, inline="always", error_model="numpy")
def designates(a, b):
    """Whether the atom with id ``a`` (not ``b``) is the one of pair (a, b) whose owner
    evaluates the pair in a decomposed run: the smaller id when the ids' sum is even,
    the larger when it is odd. Each rank then takes about half of the pairs across
    each face of its brick; the smaller id alone gave the rank holding the lower ids
    every pair across both faces of a 2 x 1 x 1 brick (4-6 % more pairs than the
    other rank, which then waited at every step)."""
    return (a < b) != (((a + b) & 1) == 1)


@njit(cache=True, inline="always", error_model="numpy")
def _keep_owned_row(out, first, last, slot_owned, slot_ids, i):
    """Keep, in place, row i's packed pairs ``out[first:last]`` whose designated atom
    (``designates``) is owned (``_keep_owned_pairs``'s rule); return the new end."""
    own = slot_owned[i] != 0
    own_id = slot_ids[i]
    kept = first
    for k in range(first, last):
        value = out[k]
        q = value & _SLOT_MASK
        if own:
            keep = slot_owned[q] != 0 or designates(own_id, slot_ids[q])
        else:
            keep = slot_owned[q] != 0 and designates(slot_ids[q], own_id)
        out[kept] = value  # written always, counted when kept: no branch to mispredict
        kept += keep
    return kept


@njit(cache=True, error_model="numpy")
def _slot_owners(order, ids, n_owned, cell_starts, n_cells, reach, periodic):
    """(slot_owned, slot_ids, column_mixed) for ``_frame_pairs``'s filter: per slot,
    whether its atom is owned (index < ``n_owned``) and its global id; per (x, y)
    column, whether a ghost lies in it or in a column within ``reach`` along x or
    y (its rows' partners may then be ghosts). Empty ``ids``: three empty arrays."""
    if ids.shape[0] == 0:
        return (np.empty(0, dtype=np.uint8), np.empty(0, dtype=np.int64),
                np.empty(0, dtype=np.bool_))  # fmt: skip
    n = order.shape[0]
    slot_owned = np.empty(n, dtype=np.uint8)
    slot_ids = np.empty(n, dtype=np.int64)
    for p in range(n):
        a = order[p]
        slot_owned[p] = a < n_owned
        slot_ids[p] = ids[a]
    nx, ny, nz = n_cells[0], n_cells[1], n_cells[2]
    has_ghost = np.zeros(nx * ny, dtype=np.bool_)
    for column in range(nx * ny):
        for p in range(cell_starts[column * nz], cell_starts[column * nz + nz]):
            if slot_owned[p] == 0:
                has_ghost[column] = True
                break
    column_mixed = np.zeros(nx * ny, dtype=np.bool_)
    for column in range(nx * ny):
        kx0 = column // ny
        ky0 = column % ny
        for ox in range(-reach, reach + 1):
            kx, _ = _neighbor_cell(kx0, ox, nx, periodic[0])
            if kx < 0:
                continue
            for oy in range(-reach, reach + 1):
                ky, _ = _neighbor_cell(ky0, oy, ny, periodic[1])
                if ky >= 0 and has_ghost[kx * ny + ky]:
                    column_mixed[column] = True
    return slot_owned, slot_ids, column_mixed


@njit(cache=True, inline="always", error_model="numpy")
def _keep(xi, yi, zi, r2_max, cx, cy, cz, c_packed, first, last, masks, base, count, capacity,
          out):  # fmt: skip
    """List the candidates first..last-1 closer than sqrt(r2_max), packed, at
    ``out[base + count:]``; return how many: the exact path near the end of a
    chunk's region.

    The search uses ``_near_pack`` while its region has room for every
    candidate and a block's spill; here the bit masks are counted first and
    nothing is written past ``capacity``: past it the hits are only counted.
    """
    n = last - first
    n_words = (n + 63) // 64
    found = 0
    for w in range(n_words):
        m = _near_bits(xi, yi, zi, r2_max, cx, cy, cz, c_packed, first + 64 * w)
        if w == n_words - 1 and n % 64:
            m &= (np.uint64(1) << np.uint64(n % 64)) - np.uint64(1)
        masks[w] = m
        found += bit_count(m)
    if count + found <= capacity:
        at = np.uint64(base + count)
        for w in range(n_words):
            m = masks[w]
            row = c_packed[first + 64 * w :]
            while m:
                out[at] = row[np.uint64(trailing_zeros(m))]
                at += np.uint64(1)
                m &= m - np.uint64(1)
    return found


@njit(cache=True, error_model="numpy")
def _cell_list(
    positions, origin, cell_width, n_cells, reach, periodic, box, tilt, r2_max, chunks,
    neighbors, codes, ids, n_owned,
):  # fmt: skip
    """The cell search's whole build in one compiled call: bin, search, join.

    Returns (order, images, starts, bounds, count, shifted): the slots
    (``_bin_atoms``), the row starts of the joined half list, whose pairs are
    ``neighbors[:count]`` with image codes ``codes[:count]`` (``_frame_pairs``),
    the rows of ``chunks`` chunks with about equal numbers of pairs
    (``_balanced_bounds``), and which rows may have a pair with an image
    shift (``_shifted_rows``).
    The search runs in ``chunks`` chunks (on numba's threads when more than
    one), each in its region of ``len(neighbors) // chunks`` entries of both
    buffers. When a chunk finds more pairs than that, nothing is joined and
    count is minus the largest chunk's count: grow both buffers to hold that
    many per chunk and call again. With ``ids`` (N,) (a rank of a decomposed
    run, ``NeighborList.keep_owned``: atoms below ``n_owned`` are its own) the
    list keeps only the pairs whose designated atom is owned (``designates``), filtered
    by the search (empty ``ids``: every pair).

    One call rather than a dozen small numpy ones between the kernels: in a
    run, the pair kernels have evicted the interpreter's working set from the
    caches, and each small call costs ten times what it costs in a loop of
    its own.
    """
    n = positions.shape[0]
    n_total = n_cells[0] * n_cells[1] * n_cells[2]
    cell_of = np.empty(n, dtype=np.int64)
    cell_starts = np.empty(n_total + 1, dtype=np.int64)
    order = np.empty(n, dtype=np.int64)
    # By coordinate: the search reads contiguous runs, whole blocks past the last slot.
    wrapped = np.empty((3, n + ROW_PADDING))
    wrapped[:, n:] = 0.0
    images = np.empty((n, 3), dtype=np.int32)
    if chunks > 1:
        _bin_atoms_threaded(positions, origin, cell_width, n_cells, periodic, box, tilt,
                            cell_of, cell_starts, order, wrapped, images, chunks)  # fmt: skip
    else:
        _bin_atoms(positions, origin, cell_width, n_cells, periodic, box, tilt, cell_of,
                   cell_starts, order, wrapped, images)  # fmt: skip
    slot_cell = cell_of  # reused: the cell of each slot, in slot order
    if chunks > 1:
        layout = _slot_layout_threaded(wrapped, cell_starts, n_cells, slot_cell, chunks)
    else:
        layout = _slot_layout(wrapped, cell_starts, n_cells, slot_cell)
    bounds = np.empty(chunks + 1, dtype=np.int64)
    for c in range(chunks + 1):
        bounds[c] = c * n // chunks
    starts = np.zeros(n + 1, dtype=np.int64)
    counts = np.zeros(chunks, dtype=np.int64)
    capacity = min(neighbors.shape[0], codes.shape[0]) // chunks
    owners = _slot_owners(order, ids, n_owned, cell_starts, n_cells, reach, periodic)
    if chunks > 1:  # one chunk stays off numba's thread pool: no wake-ups on a busy machine
        _frame_pairs_threaded(wrapped, slot_cell, r2_max, n_cells, reach, periodic, box, tilt,
                              cell_starts, layout, bounds, capacity, starts, neighbors, codes,
                              counts, owners)  # fmt: skip
    else:
        _frame_pairs(wrapped, slot_cell, r2_max, n_cells, reach, periodic, box, tilt,
                     cell_starts, layout, bounds, capacity, starts, neighbors, codes,
                     counts, owners)  # fmt: skip
    most = counts.max()
    if most > capacity:
        return order, images, starts, bounds, -most, np.empty(0, dtype=np.bool_)
    if chunks > 1:
        count = _join_chunks(bounds, capacity, counts, starts, neighbors, codes)
    else:  # unpacked by the search; rows counted from the buffer's start
        count = counts[0]
    shifted = _shifted_rows(cell_starts, n_cells, reach, periodic)
    return order, images, starts, _balanced_bounds(starts, chunks), count, shifted


@njit(cache=True, parallel=True, error_model="numpy")
def _join_chunks(bounds, capacity, counts, starts, neighbors, codes):
    """Unpack the chunk regions written by ``_frame_pairs`` (in more than one chunk) on
    numba's threads and join them into one CSR list; return its length."""
    offsets, moves = _join_plan(capacity, counts)
    for chunk in prange(counts.shape[0]):
        block = np.empty(_UNPACK_BLOCK, dtype=np.uint32)
        _unpack_chunk(chunk, bounds, capacity, counts, offsets, moves, starts, neighbors, codes,
                      block)  # fmt: skip
    return _join_rest(capacity, counts, offsets, moves, neighbors, codes)


#: Entries ``_unpack_chunk`` reads ahead of its writes (4 KB: they stay in L1).
_UNPACK_BLOCK = 1024


@njit(cache=True, inline="always", error_model="numpy")
def _join_plan(capacity, counts):
    """Where each chunk's pairs go in the joined list, and which chunks can be unpacked
    straight there while the others are read: those whose place overlaps no other
    chunk's region (with two chunks, both)."""
    chunks = counts.shape[0]
    offsets = np.zeros(chunks + 1, dtype=np.int64)
    for c in range(chunks):
        offsets[c + 1] = offsets[c] + counts[c]
    moves = np.ones(chunks, dtype=np.bool_)
    for c in range(chunks):
        for d in range(chunks):
            if d != c and offsets[c] < d * capacity + counts[d] and d * capacity < offsets[c + 1]:
                moves[c] = False
    return offsets, moves


@njit(cache=True, inline="always", error_model="numpy")
def _unpack_chunk(chunk, bounds, capacity, counts, offsets, moves, starts, neighbors, codes,
                  block):  # fmt: skip
    """Chunk ``chunk``'s packed pairs as slots and codes: at their place in the joined list
    if ``moves[chunk]``, else where they are; its row ends made absolute.

    The place is never after the region, so copying forward through ``block``
    (read a block, then write it) never overwrites a value not yet read.
    """
    base = chunk * capacity
    target = offsets[chunk] if moves[chunk] else base
    packed = neighbors.view(np.uint32)
    count = counts[chunk]
    if target == base:  # in place: two loops over the region, each one vectorised
        listed = packed[base : base + count]
        listed_codes = codes[base : base + count]
        for k in range(count):
            listed_codes[k] = listed[k] >> _CODE_SHIFT
        for k in range(count):
            listed[k] &= _SLOT_MASK
    else:
        k = 0
        while k < count:  # three simple loops over slices: each one vectorised
            m = min(_UNPACK_BLOCK, count - k)
            values = block[:m]
            source = packed[base + k : base + k + m]
            for j in range(m):
                values[j] = source[j]
            to_codes = codes[target + k : target + k + m]
            for j in range(m):
                to_codes[j] = values[j] >> _CODE_SHIFT
            to_slots = neighbors[target + k : target + k + m]
            for j in range(m):
                to_slots[j] = values[j] & _SLOT_MASK
            k += m
    offset = offsets[chunk]
    for p in range(bounds[chunk] + 1, bounds[chunk + 1] + 1):
        starts[p] += offset


@njit(cache=True, inline="always", error_model="numpy")
def _join_rest(capacity, counts, offsets, moves, neighbors, codes):
    """Move the chunks unpacked in place to their places, in order (``memmove``: a
    region and its place may overlap); return the joined list's length."""
    for chunk in range(counts.shape[0]):
        base = chunk * capacity
        if not moves[chunk] and offsets[chunk] != base:
            move_within(neighbors, offsets[chunk], base, counts[chunk])
            move_within(codes, offsets[chunk], base, counts[chunk])
    return offsets[counts.shape[0]]


@njit(cache=True, error_model="numpy")
def _shifted_rows(cell_starts, n_cells, reach, periodic):
    """Per slot, whether its row may hold a pair with an image shift (a code other than
    ``UNSHIFTED_CODE``); the pair kernels gather the other rows' partners without
    reading codes and shifts (LJ's force call -5 % at 32000 atoms).

    From the slot's cell alone, as ``_frame_pairs`` searches: its candidates lie
    0 to ``reach`` cells ahead along x, ``reach`` either way along y and z, so
    only a cell that near the edge of a periodic axis sees images (a third of
    the rows at 32000 atoms, a seventh at 500000). A flag may be set on a row
    whose pairs all turn out unshifted, never left off one that has a shift.
    Cell by cell (``cell_starts``: the slots of cell (x ny + y) nz + z), with no
    integer division per slot (three per slot took 0.4 ms at 32000 atoms, 7 % of
    a build).
    """
    nx, ny, nz = n_cells[0], n_cells[1], n_cells[2]
    shifted = np.empty(cell_starts[nx * ny * nz], dtype=np.bool_)
    cell = 0
    for kx in range(nx):
        near_x = periodic[0] and kx + reach >= nx
        for ky in range(ny):
            near_xy = near_x or (periodic[1] and (ky < reach or ky + reach >= ny))
            for kz in range(nz):
                flag = near_xy or (periodic[2] and (kz < reach or kz + reach >= nz))
                for p in range(cell_starts[cell], cell_starts[cell + 1]):
                    shifted[p] = flag
                cell += 1
    return shifted


@njit(cache=True, error_model="numpy")
def _balanced_bounds(starts, chunks):
    """Row ranges of ``chunks`` chunks holding about equal numbers of pairs.

    Chunk c starts at the first row that starts at or after pair c P / chunks
    (rounded up; P pairs in all), never before the chunk ahead of it.
    """
    n = starts.shape[0] - 1
    bounds = np.empty(chunks + 1, dtype=np.int64)
    bounds[0] = 0
    for c in range(1, chunks):
        target = -(-starts[n] * c // chunks)
        bounds[c] = max(np.searchsorted(starts, target), bounds[c - 1])
    bounds[chunks] = n
    return bounds


#: Row k: the cell-vector multiples (dx - 1, dy - 1, dz - 1) of code k = 9 dx + 3 dy + dz.
_CODE_WRAPS = np.array(
    [(a - 1.0, b - 1.0, c - 1.0) for a in range(3) for b in range(3) for c in range(3)]
)


def _shift_table(box, pbc, tilt):
    """(27, 3) image shifts named by the codes of ``_frame_pairs``.

    Code 9 dx + 3 dy + dz means the shift (dx - 1) a + (dy - 1) b + (dz - 1) c.
    """
    return _CODE_WRAPS @ cell_matrix(np.where(pbc, box, 0.0), periodic_tilt(tilt, pbc))


@njit(cache=True, error_model="numpy")
def _atom_space_list(order, starts, neighbors, atom_starts, atom_neighbors):
    """Rewrite a slot-space half list as a list over atom indices, rows in atom order."""
    n = order.shape[0]
    atom_starts[0] = 0
    for p in range(n):
        atom_starts[order[p] + 1] = starts[p + 1] - starts[p]
    for a in range(n):
        atom_starts[a + 1] += atom_starts[a]
    for p in range(n):
        destination = atom_starts[order[p]]
        for k in range(starts[p], starts[p + 1]):
            atom_neighbors[destination + k - starts[p]] = order[neighbors[k]]


@njit(cache=True, parallel=True, error_model="numpy")
def _max_displacement2_threaded(positions, reference, chunks):
    """``_max_displacement2`` over ``chunks`` chunks of atoms on numba's threads."""
    n = positions.shape[0]
    worst = np.zeros(chunks)
    for c in prange(chunks):
        a, b = c * n // chunks, (c + 1) * n // chunks
        worst[c] = _max_displacement2(positions[a:b], reference[a:b])
    return worst.max()


@njit(cache=True, error_model="numpy")
def _largest_displacement2(positions, reference, chunks):
    """``_max_displacement2``, on numba's threads in ``chunks`` chunks when more than one.

    One compiled entry for both: the threaded kernel is loaded with it, at the
    first list check of any size, not at the first one of a large system
    (loading a parallel kernel from numba's cache takes milliseconds).
    """
    if chunks > 1:
        return _max_displacement2_threaded(positions, reference, chunks)
    return _max_displacement2(positions, reference)


#: Bit patterns: all but the sign bit, and +inf (every NaN's magnitude bits are above it).
_MAGNITUDE = np.int64(0x7FFFFFFFFFFFFFFF)
_INF_BITS = np.int64(0x7FF0000000000000)


@njit(cache=True, error_model="numpy")
def _max_displacement2(positions, reference):
    """Largest squared displacement since ``reference``; inf if any coordinate is not finite
    (``reference`` is finite).

    The maximum is taken over the bit patterns of the squared displacements
    with the sign bit cleared: for non-negative floats they order as the
    numbers do, and inf and every NaN lie above all finite ones. An integer
    maximum with no early exit is a loop the compiler vectorises (a float
    maximum that must see NaNs is not).
    """
    n = positions.shape[0]
    worst = np.int64(0)
    for i in range(n):
        dx = positions[i, 0] - reference[i, 0]
        dy = positions[i, 1] - reference[i, 1]
        dz = positions[i, 2] - reference[i, 2]
        worst = max(worst, float_bits(dx * dx + dy * dy + dz * dz) & _MAGNITUDE)
    if worst >= _INF_BITS:
        return np.inf
    return bits_float(worst)


@njit(cache=True, error_model="numpy")
def _largest_coordinates(positions, copy):
    """Largest |coordinate| along x, y and z (zeros for no atoms; inf where any is not
    finite), as a tuple of floats; ``positions`` copied into ``copy`` on the way.

    One read of the positions for both (a build's first look at them: the
    check of where they are, and the reference the rebuild test measures
    from), and no numpy call on the result.
    """
    largest = np.zeros(3)
    for i in range(positions.shape[0]):
        for a in range(3):
            value = positions[i, a]
            copy[i, a] = value
            x = abs(value)
            if not x <= largest[a]:  # also NaN
                largest[a] = x if np.isfinite(x) else np.inf
    return largest[0], largest[1], largest[2]


@njit(cache=True, error_model="numpy")
def _keep_owned_pairs(order, starts, neighbors, codes, ids, n_owned):
    """Keep, in place, only the listed pairs whose designated atom (``designates``) is
    owned; return the new pair count.

    The pair filter of a rank in a decomposed run (``NeighborList.keep_owned``): atoms
    ``0 .. n_owned - 1`` are the rank's own, the rest ghost copies of other ranks' atoms
    (or periodic images), ``ids`` their global ids. Each pair of the whole system is then
    kept on exactly one rank, and ghost-ghost pairs on none. ``order``: the atom in each
    slot (empty for a list over atom indices); ``codes``: one per pair, or empty. The
    kept pairs keep their order; ``starts`` is rewritten.
    """
    n = starts.shape[0] - 1
    slot_ids = np.empty(n, dtype=np.int64)
    slot_owned = np.empty(n, dtype=np.uint8)  # 0 or 1: summed below
    for p in range(n):
        a = order[p] if order.shape[0] > 0 else p
        slot_ids[p] = ids[a]
        slot_owned[p] = a < n_owned
    with_codes = codes.shape[0] > 0
    kept = 0
    begin = starts[0]
    # The test per pair is ordered so that its branches are predictable: an owned row
    # keeps its owned partners (nearly all of them) without comparing ids, a ghost row
    # drops its ghost partners likewise; the ids are compared only across the brick's
    # face. (Comparing ids first, a coin toss per pair where the ids follow no spatial
    # order, cost 0.19 s against 0.05 s on 26 million pairs.)
    for p in range(n):
        end = starts[p + 1]
        own_id = slot_ids[p]
        if slot_owned[p]:
            ghosts = 0  # a read-only count first: most owned rows have no ghost partner,
            for k in range(begin, end):  # and those move as one block (0.052 -> 0.031 s)
                ghosts += 1 - slot_owned[neighbors[k]]
            if ghosts == 0:
                if kept != begin:
                    for k in range(begin, end):
                        neighbors[kept + k - begin] = neighbors[k]
                    if with_codes:
                        for k in range(begin, end):
                            codes[kept + k - begin] = codes[k]
                kept += end - begin
            else:
                for k in range(begin, end):
                    q = neighbors[k]
                    if slot_owned[q] or designates(own_id, slot_ids[q]):
                        neighbors[kept] = q
                        if with_codes:
                            codes[kept] = codes[k]
                        kept += 1
        else:
            for k in range(begin, end):
                q = neighbors[k]
                if slot_owned[q] and designates(slot_ids[q], own_id):
                    neighbors[kept] = q
                    if with_codes:
                        codes[kept] = codes[k]
                    kept += 1
        begin = end
        starts[p + 1] = kept
    return kept
