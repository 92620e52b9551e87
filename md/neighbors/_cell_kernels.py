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
     before it writes near the end of the chunk's region;
   - a single chunk is unpacked into slots and a one-byte image code per pair
     at its end; several are joined by ``_join_chunks``, on the threads: each
     chunk is unpacked straight to its place in the list where that overlaps
     no other chunk's region (with two chunks, always), the rest in place and
     then moved (memmove, ``md._simd.move_within``).
3. ``_balanced_bounds`` splits the rows into chunks of equal pair counts for
   the pair kernels.

When a periodic axis has room for fewer than 5 half-radius cells,
``_small_box_kernels._small_box_list`` builds the same slot frame by an O(N^2)
search over the periodic images instead; ``_brute_force_pairs`` (over atom
indices, minimum image) where that does not serve (a periodic width under the
list radius). It is also the reference the cell search is tested against. A rank
of a decomposed run searches only its owned atoms' rows (``_owned_kernels``, with
this module's gather and ``designates``). ``_atom_space_list``
translates a slot list into one over atom indices for potentials that read
``neighbors.starts``/``neighbors.neighbors``.

Where the parts live
--------------------
This module holds the search (``_frame_pairs`` and what it calls, the slot layout, the
gather, the designated-atom rule) and ``_brute_force_pairs``; the candidate test's LLVM IR
(``_near_bits``, the ``_near_pack`` family, ``_keep``) is in ``_candidates``; the build
around the search (``_cell_list``, binning, joining the chunks, ``_balanced_bounds``, the
shift table, the atom-space list and the rebuild check) in ``_build_kernels``.

A note on its length (about 850 lines, over the 800 where a module is split): its
kernels take their arrays as arguments, and the formatter writes a long argument list a
line per argument (about 250 of its lines); they are one search and stay together.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, prange, types
from numba.extending import intrinsic

from md._simd import (
    PERMUTATIONS,
    array_data,
    is_vector_array,
    load_vector,
    python_twin,
    splat,
    store_vector,
)
from md.box import min_image
from md.neighbors._candidates import _keep, _near_pack, _near_pack_whole

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
                xi - positions[j, 0],
                yi - positions[j, 1],
                zi - positions[j, 2],
                lengths,
                inverse,
                tilt,
            )
            if dx * dx + dy * dy + dz * dz < r2_max:
                if count < capacity:
                    neighbors[count] = j
                count += 1
        starts[i + 1] = count
    return count


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


@njit(cache=True, inline="always", error_model="numpy")
def _frame_pairs(
    wrapped,
    slot_cell,
    r2_max,
    n_cells,
    reach,
    periodic,
    box,
    tilt,
    cell_starts,
    layout,
    bounds,
    capacity,
    starts,
    neighbors,
    codes,
    counts,
):
    """Half list over slots (atoms in cell order), searched in chunks on parallel threads.

    The serial driver; ``_frame_pairs_threaded`` runs the chunks on
    numba's threads. Inlined into its caller (``_cell_list``): a compiled driver of
    its own would be one more module that links the chunk kernel in and optimises it
    again. Slot p holds the atom whose wrapped position is ``wrapped[:, p]``
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
    (A rank of a decomposed run searches its own rows instead: ``_owned_kernels``.)
    ``codes[k]`` names the image shift s
    of that neighbour cell, so the pair displacement is
    ``wrapped[:, p] - wrapped[:, q] - s`` with no minimum image (see
    ``_shift_table``). Requires at least 2 reach + 1 cells along every
    periodic axis, so the cells around any cell are distinct.
    """
    planes, tags, most = layout
    for chunk in range(bounds.shape[0] - 1):
        _frame_pairs_chunk(
            chunk,
            wrapped,
            slot_cell,
            r2_max,
            n_cells,
            reach,
            periodic,
            box,
            tilt,
            cell_starts,
            planes,
            tags,
            bounds,
            capacity,
            most,
            starts,
            neighbors,
            codes,
            counts,
        )


@njit(cache=True, parallel=True, error_model="numpy")
def _frame_pairs_threaded(
    wrapped,
    slot_cell,
    r2_max,
    n_cells,
    reach,
    periodic,
    box,
    tilt,
    cell_starts,
    layout,
    bounds,
    capacity,
    starts,
    neighbors,
    codes,
    counts,
):
    """``_frame_pairs`` with one chunk per thread (same arguments, same result)."""
    planes, tags, most = layout
    for chunk in prange(bounds.shape[0] - 1):
        _frame_pairs_chunk(
            np.int64(chunk),  # the serial driver's index type: one compile, not two
            wrapped,
            slot_cell,
            r2_max,
            n_cells,
            reach,
            periodic,
            box,
            tilt,
            cell_starts,
            planes,
            tags,
            bounds,
            capacity,
            most,
            starts,
            neighbors,
            codes,
            counts,
        )


@njit(cache=True, error_model="numpy")
def _frame_pairs_chunk(
    chunk,
    wrapped,
    slot_cell,
    r2_max,
    n_cells,
    reach,
    periodic,
    box,
    tilt,
    cell_starts,
    planes,
    tags,
    bounds,
    capacity,
    most,
    starts,
    neighbors,
    codes,
    counts,
):
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
    """
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
    own = (
        np.empty(own_size),
        np.empty(own_size),
        np.empty(own_size),
        np.empty(own_size, dtype=np.uint32),
        np.empty(reach + 1, dtype=np.int64),
    )
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
            column,
            n_cells,
            reach,
            ghost,
            periodic,
            box,
            tilt,
            planes,
            runs,
            run_shifts,
            cx,
            cy,
            cz,
            c_packed,
            z_start,
            own,
        )
        for i in range(p, stop):
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
                # (the range's words written out here: a helper holding this loop cost
                # about 60 ns a call, whatever the range, a third of the search's time)
                w = first
                while w + 64 <= last:
                    at = _near_pack_whole(
                        xs[i],
                        ys[i],
                        zs[i],
                        r2_max,
                        cx,
                        cy,
                        cz,
                        c_packed,
                        w,
                        64,
                        PERMUTATIONS,
                        packed_list,
                        at,
                    )
                    w += 64
                if w < last:
                    at = _near_pack(
                        xs[i],
                        ys[i],
                        zs[i],
                        r2_max,
                        cx,
                        cy,
                        cz,
                        c_packed,
                        w,
                        last - w,
                        PERMUTATIONS,
                        packed_list,
                        at,
                    )
                w = i + 1
                while w < own_last:  # a crowded column may hold more than a word
                    at = _near_pack(
                        xs[i],
                        ys[i],
                        zs[i],
                        r2_max,
                        xs,
                        ys,
                        zs,
                        tags,
                        w,
                        min(64, own_last - w),
                        PERMUTATIONS,
                        packed_list,
                        at,
                    )
                    w += 64
                w = 0
                while w < ghost_last:
                    at = _near_pack(
                        xs[i],
                        ys[i],
                        zs[i],
                        r2_max,
                        own[0],
                        own[1],
                        own[2],
                        own[3],
                        w,
                        min(64, ghost_last - w),
                        PERMUTATIONS,
                        packed_list,
                        at,
                    )
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
                    count += _keep(
                        xs[i],
                        ys[i],
                        zs[i],
                        r2_max,
                        tx,
                        ty,
                        tz,
                        tp,
                        a,
                        b,
                        masks,
                        base,
                        count,
                        capacity,
                        packed_list,
                    )
            # (past the capacity nothing was written: the count stays an upper bound)
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
    _fill_columns(
        0, n_cells[0] * n_cells[1], wrapped, cell_starts, n_cells, planes, tags, slot_cell
    )
    return planes, tags, most


@njit(cache=True, parallel=True, error_model="numpy")
def _slot_layout_threaded(wrapped, cell_starts, n_cells, slot_cell, chunks):
    """``_slot_layout`` with the (x, y) columns filled in ``chunks`` chunks on numba's
    threads."""
    planes, tags, most = _layout_arrays(wrapped.shape[1], cell_starts, n_cells)
    n_columns = n_cells[0] * n_cells[1]
    for c in prange(chunks):
        _fill_columns(
            c * n_columns // chunks,
            (c + 1) * n_columns // chunks,
            wrapped,
            cell_starts,
            n_cells,
            planes,
            tags,
            slot_cell,
        )
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
def _gather_column(
    column,
    n_cells,
    reach,
    ghost,
    periodic,
    box,
    tilt,
    planes,
    runs,
    run_shifts,
    cx,
    cy,
    cz,
    c_packed,
    z_start,
    own,
):
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
                plane_starts[row + first_y],
                plane_starts[row + run_last[r] + 1],
                shift_x[r] + wz * xz,
                shift_y[r] + wz * yz,
                wz * box[2],
                code_xy[r] + wz,
                px,
                py,
                pz,
                p_slot,
                cx,
                cy,
                cz,
                c_packed,
                m,
            )
    z_start[nz + 2 * ghost] = m
    ox_, oy_, oz_, o_packed, o_start = own
    m = 0
    for k in range(ghost):  # the own column's bottom cells, one cell vector c up
        o_start[k] = m
        cell = (k * nx + kx0) * ny + ky0
        m = _gather_run(
            plane_starts[cell],
            plane_starts[cell + 1],
            xz,
            yz,
            box[2],
            9 + 3 + 2,
            px,
            py,
            pz,
            p_slot,
            ox_,
            oy_,
            oz_,
            o_packed,
            m,
        )
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
        _copy_block(
            xs, ys, zs, slots, first + done, sx, sy, sz, tag, cx, cy, cz, c_packed, m + done
        )
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
        xs,
        ys,
        zs,
        slots,
        types.intp,
        types.float64,
        types.float64,
        types.float64,
        types.uint32,
        cx,
        cy,
        cz,
        c_packed,
        types.intp,
    )

    def codegen(context, builder, signature, args):
        width = GATHER_BLOCK
        vector = ir.VectorType(ir.DoubleType(), width)
        words = ir.VectorType(ir.IntType(32), width)
        data = [
            array_data(context, builder, signature.args[k], args[k])
            for k in range(14)
            if k not in (4, 5, 6, 7, 8, 13)
        ]
        sources, targets = data[:4], data[4:]
        first, m = args[4], args[13]
        for source, target, shift in zip(sources[:3], targets[:3], args[5:8], strict=True):
            moved = builder.fadd(
                load_vector(builder, source, first, vector), splat(builder, shift, vector)
            )
            store_vector(builder, moved, target, m)
        tagged = builder.or_(
            load_vector(builder, sources[3], first, words), splat(builder, args[8], words)
        )
        store_vector(builder, tagged, targets[3], m)
        return context.get_dummy_value()

    return sig, codegen


@njit(cache=True, inline="always", error_model="numpy")
def designates(a, b):
    """Whether the atom with id ``a`` (not ``b``) is the one of pair (a, b) whose owner
    evaluates the pair in a decomposed run: the smaller id when the ids' sum is even,
    the larger when it is odd. Each rank then takes about half of the pairs across
    each face of its brick; the smaller id alone gave the rank holding the lower ids
    every pair across both faces of a 2 x 1 x 1 brick (4-6 % more pairs than the
    other rank, which then waited at every step)."""
    return (a < b) != (((a + b) & 1) == 1)
