"""A cell-list build around the search (see ``_cell_kernels``' docstring): ``_cell_list``,
the one compiled call of a build; the counting sort by cell (``_bin_atoms``); joining the
search's chunks (``_join_chunks``); the pair kernels' chunk bounds (``_balanced_bounds``);
the image-shift table; the list over atom indices (``_atom_space_list``); the rebuild
check (``_largest_displacement2``, ``_largest_coordinates``). The slot frame of a box too
narrow for the cells is ``_small_box_kernels``'.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from md._simd import bits_float, float_bits, move_within
from md.box import cell_matrix, periodic_tilt
from md.neighbors._cell_kernels import (
    _CODE_SHIFT,
    _SLOT_MASK,
    ROW_PADDING,
    _frame_pairs,
    _frame_pairs_threaded,
    _slot_layout,
    _slot_layout_threaded,
)


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
    positions,
    origin,
    cell_width,
    n_cells,
    periodic,
    box,
    tilt,
    cell_of,
    cell_starts,
    order,
    sorted_wrapped,
    images,
):
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
    _bin_pass(
        0,
        n,
        positions,
        origin,
        cell_width,
        n_cells,
        periodic,
        box,
        tilt,
        cell_of,
        moved,
        wraps,
        counts[0],
    )
    _cell_offsets(counts, cell_starts)
    _scatter_pass(0, n, cell_of, moved, wraps, counts[0], order, sorted_wrapped, images)


@njit(cache=True, parallel=True, error_model="numpy")
def _bin_atoms_threaded(
    positions,
    origin,
    cell_width,
    n_cells,
    periodic,
    box,
    tilt,
    cell_of,
    cell_starts,
    order,
    sorted_wrapped,
    images,
    chunks,
):
    """``_bin_atoms`` with its two passes over atoms in ``chunks`` chunks on numba's
    threads; each chunk's atoms take their places in a cell after the earlier
    chunks', so the result is the serial one."""
    n = positions.shape[0]
    total = n_cells[0] * n_cells[1] * n_cells[2]
    counts = np.zeros((chunks, total), dtype=np.int64)
    moved = np.empty((n, 3))
    wraps = np.empty((n, 3), dtype=np.int32)
    for c in prange(chunks):
        _bin_pass(
            c * n // chunks,
            (c + 1) * n // chunks,
            positions,
            origin,
            cell_width,
            n_cells,
            periodic,
            box,
            tilt,
            cell_of,
            moved,
            wraps,
            counts[c],
        )
    _cell_offsets(counts, cell_starts)
    for c in prange(chunks):
        _scatter_pass(
            c * n // chunks,
            (c + 1) * n // chunks,
            cell_of,
            moved,
            wraps,
            counts[c],
            order,
            sorted_wrapped,
            images,
        )


@njit(cache=True, inline="always", error_model="numpy")
def _bin_pass(
    first,
    last,
    positions,
    origin,
    cell_width,
    n_cells,
    periodic,
    box,
    tilt,
    cell_of,
    moved,
    wraps,
    counts,
):
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


@njit(cache=True, error_model="numpy")
def _cell_list(
    positions,
    origin,
    cell_width,
    n_cells,
    reach,
    periodic,
    box,
    tilt,
    r2_max,
    chunks,
    neighbors,
    codes,
):
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
    many per chunk and call again. (A rank of a decomposed run builds its list with
    ``_owned_kernels._owned_cell_list``.)

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
        _bin_atoms_threaded(
            positions,
            origin,
            cell_width,
            n_cells,
            periodic,
            box,
            tilt,
            cell_of,
            cell_starts,
            order,
            wrapped,
            images,
            chunks,
        )
    else:
        _bin_atoms(
            positions,
            origin,
            cell_width,
            n_cells,
            periodic,
            box,
            tilt,
            cell_of,
            cell_starts,
            order,
            wrapped,
            images,
        )
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
    if chunks > 1:  # one chunk stays off numba's thread pool: no wake-ups on a busy machine
        _frame_pairs_threaded(
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
        )
    else:
        _frame_pairs(
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
        )
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
        _unpack_chunk(
            chunk, bounds, capacity, counts, offsets, moves, starts, neighbors, codes, block
        )
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
def _unpack_chunk(chunk, bounds, capacity, counts, offsets, moves, starts, neighbors, codes, block):
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
def _cell_grid(positions, periodic, box, across, radius, reach, max_cells):
    """(origin, width, n_cells, fits) of the cell grid of ``NeighborList._grid``.

    Along a periodic axis the grid spans the cell (``box``, its perpendicular width
    ``across``); along an open one the atoms (at least ``radius`` wide). ``n_cells``:
    ``floor(width * reach / radius)`` cells per axis, at least one, no more than
    ``max_cells`` in all (the busiest axis that can shrink halved until they fit: wider
    cells are still correct); ``fits``: every periodic axis has 2 reach + 1 of them.
    """
    n = positions.shape[0]
    origin = np.zeros(3)
    extent = np.empty(3)
    n_cells = np.empty(3, dtype=np.int64)
    fewest = np.empty(3, dtype=np.int64)
    for a in range(3):
        if periodic[a]:
            extent[a] = box[a]
            span = across[a]
            fewest[a] = 2 * reach + 1
        else:
            low = np.inf
            high = -np.inf
            for i in range(n):
                low = min(low, positions[i, a])
                high = max(high, positions[i, a])
            origin[a] = low
            extent[a] = max(high - low, radius)
            span = extent[a]
            fewest[a] = 1
        # clipped in floating point first: a cluster that flew apart can span more
        # cells than an int64 holds
        n_cells[a] = np.int64(min(max(np.floor(span * reach / radius), 1.0), float(max_cells)))
    fits = True
    for a in range(3):
        if n_cells[a] < fewest[a]:
            fits = False
    while fits and float(n_cells[0]) * n_cells[1] * n_cells[2] > max_cells:
        axis = -1  # the busiest axis that can shrink
        for a in range(3):
            if n_cells[a] > fewest[a] and (axis < 0 or n_cells[a] > n_cells[axis]):
                axis = a
        if axis < 0:
            break
        n_cells[axis] = max(n_cells[axis] // 2, fewest[axis])
    return origin, extent / n_cells, n_cells, fits


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
