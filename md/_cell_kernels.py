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
runs them in turn, off the thread pool.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from md.box import cell_matrix, min_image, periodic_tilt


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
def _grid_index(x, origin, width, n, periodic, length):
    """Cell index of coordinate x along one axis, wrapped (periodic) or clamped."""
    if periodic:
        x = x - length * np.floor(x / length)
    k = int(np.floor((x - origin) / width))
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
    (n_cells + 1 CSR offsets), ``order`` (atom indices grouped by cell),
    ``sorted_wrapped[:, p]`` (shape (3, N): coordinates in rows), the
    position of atom ``order[p]`` wrapped into
    the cell (g in [0, L)) along periodic axes, so a cell's atoms are
    contiguous in memory, and ``images[p]`` (int32), the cell vectors added
    to wrap it: ``sorted_wrapped[:, p] == positions[order[p]] + images[p] @ h``
    (h the cell matrix) up to round-off, exactly for an orthorhombic box.
    Open axes are clamped to the grid, whose origin and width the caller
    chose to span the atoms.
    """
    n = positions.shape[0]
    nx, ny, nz = n_cells[0], n_cells[1], n_cells[2]
    total = nx * ny * nz
    for c in range(total + 1):
        cell_starts[c] = 0
    xy, xz, yz = tilt[0], tilt[1], tilt[2]
    sheared = xy != 0.0 or xz != 0.0 or yz != 0.0
    grid = np.empty((n, 3))
    for i in range(n):
        gx = positions[i, 0]
        gy = positions[i, 1]
        gz = positions[i, 2]
        if sheared:  # a tilt is non-zero only between periodic axes
            sz = gz / box[2] if periodic[2] else 0.0
            gy -= sz * yz
            sy = gy / box[1] if periodic[1] else 0.0
            gx -= sy * xy + sz * xz
        grid[i, 0] = gx
        grid[i, 1] = gy
        grid[i, 2] = gz
        kx = _grid_index(gx, origin[0], cell_width[0], nx, periodic[0], box[0])
        ky = _grid_index(gy, origin[1], cell_width[1], ny, periodic[1], box[1])
        kz = _grid_index(gz, origin[2], cell_width[2], nz, periodic[2], box[2])
        c = (kx * ny + ky) * nz + kz
        cell_of[i] = c
        cell_starts[c + 1] += 1
    for c in range(total):
        cell_starts[c + 1] += cell_starts[c]
    fill = cell_starts[:total].copy()
    for i in range(n):
        c = cell_of[i]
        p = fill[c]
        order[p] = i
        fill[c] += 1
        wx = -np.floor(grid[i, 0] / box[0]) if periodic[0] else 0.0
        wy = -np.floor(grid[i, 1] / box[1]) if periodic[1] else 0.0
        wz = -np.floor(grid[i, 2] / box[2]) if periodic[2] else 0.0
        x = positions[i, 0] + box[0] * wx
        y = positions[i, 1] + box[1] * wy
        z = positions[i, 2] + box[2] * wz
        if sheared:
            x += wy * xy + wz * xz
            y += wz * yz
        sorted_wrapped[0, p] = x
        sorted_wrapped[1, p] = y
        sorted_wrapped[2, p] = z
        images[p, 0] = np.int32(wx)
        images[p, 1] = np.int32(wy)
        images[p, 2] = np.int32(wz)


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
    wrapped, slot_cell, r2_max, n_cells, reach, periodic, box, tilt, cell_starts, bounds,
    capacity, starts, neighbors, codes, counts,
):  # fmt: skip
    """Half list over slots (atoms in cell order), searched in chunks on parallel threads.

    The serial driver; ``_frame_pairs_threaded`` runs the chunks on
    numba's threads. Slot p holds the atom whose wrapped position is ``wrapped[:, p]``
    (``wrapped`` is (3, N), as ``_bin_atoms`` writes it), in cell
    ``slot_cell[p]``; ``cell_starts`` gives each cell's slots. Chunk c covers
    slots ``bounds[c]`` to ``bounds[c + 1]`` and writes its pairs into its own
    region ``neighbors[c * capacity:(c + 1) * capacity]`` (and ``codes``), so
    no two threads write the same memory; ``starts[p + 1]`` is the end of row
    p counted from the start of its region, ``counts[c]`` the chunk's pair
    count (it keeps counting past ``capacity`` without writing).
    ``_compact_chunks`` then joins the regions into one CSR list.

    Cells are at least list radius / ``reach`` wide (reach 1 or 2), so
    every partner lies within ``reach`` cells along each axis. Each
    unordered pair is listed once, under the slot whose cell sees the other
    through the own cell (then under the lower slot) or one of the
    lexicographically positive offsets (13 for reach 1, 62 for reach 2).
    ``codes[k]`` names the image shift s
    of that neighbour cell, so the pair displacement is
    ``wrapped[:, p] - wrapped[:, q] - s`` with no minimum image (see
    ``_shift_table``). Requires at least 2 reach + 1 cells along every
    periodic axis, so the cells around any cell are distinct.
    """
    most = _most_per_cell(cell_starts)
    for chunk in range(bounds.shape[0] - 1):
        _frame_pairs_chunk(
            chunk, wrapped, slot_cell, r2_max, n_cells, reach, periodic, box, tilt,
            cell_starts, bounds, capacity, most, starts, neighbors, codes, counts,
        )  # fmt: skip


@njit(cache=True, parallel=True, error_model="numpy")
def _frame_pairs_threaded(
    wrapped, slot_cell, r2_max, n_cells, reach, periodic, box, tilt, cell_starts, bounds,
    capacity, starts, neighbors, codes, counts,
):  # fmt: skip
    """``_frame_pairs`` with one chunk per thread (same arguments, same result)."""
    most = _most_per_cell(cell_starts)
    for chunk in prange(bounds.shape[0] - 1):
        _frame_pairs_chunk(
            chunk, wrapped, slot_cell, r2_max, n_cells, reach, periodic, box, tilt,
            cell_starts, bounds, capacity, most, starts, neighbors, codes, counts,
        )  # fmt: skip


@njit(cache=True, error_model="numpy")
def _most_per_cell(cell_starts):
    most = 0
    for c in range(cell_starts.shape[0] - 1):
        most = max(most, cell_starts[c + 1] - cell_starts[c])
    return most


@njit(cache=True, error_model="numpy")
def _frame_pairs_chunk(
    chunk, wrapped, slot_cell, r2_max, n_cells, reach, periodic, box, tilt, cell_starts,
    bounds, capacity, most, starts, neighbors, codes, counts,
):  # fmt: skip
    """One chunk of ``_frame_pairs``: slots bounds[chunk] to bounds[chunk + 1].

    For each (x, y) neighbour column the cells along z lie next to each other
    in slot order, so they are scanned as one run of slots (two or three
    where the column wraps around the z edge), not cell by cell. A neighbour
    cell across the edge of the cell along axes with wraps (wx, wy, wz) is
    seen shifted by wx a + wy b + wz c. The runs depend only on the cell
    (``_cell_runs``): per cell, their shifted positions are copied into one
    contiguous candidate array, own column first (``_gather_run``), and each
    of the cell's slots tests them in one loop the compiler vectorises, then
    keeps those within range with a branch-free compaction (``_keep``).
    """
    base = chunk * capacity
    side = 2 * reach + 1
    size = side * side * side * most  # bounds the forward stencil's slots
    cx = np.empty(size)
    cy = np.empty(size)
    cz = np.empty(size)
    c_slot = np.empty(size, dtype=np.int32)
    c_code = np.empty(size, dtype=np.uint8)
    inside = np.empty(size, dtype=np.uint8)
    n_columns = reach * side + reach + 1  # forward (x, y) columns and the own one
    run_ends = np.empty((3 * n_columns, 2), dtype=np.int64)  # first and last slot
    run_shifts = np.empty((3 * n_columns, 3))
    run_codes = np.empty(3 * n_columns, dtype=np.int64)
    xs, ys, zs = wrapped[0], wrapped[1], wrapped[2]
    count = 0
    p = bounds[chunk]
    end = bounds[chunk + 1]
    while p < end:
        cell = slot_cell[p]
        first = cell_starts[cell]
        last = min(cell_starts[cell + 1], end)
        n_runs, own_end = _cell_runs(cell, n_cells, reach, periodic, box, tilt,
                                     cell_starts, run_ends, run_shifts, run_codes)  # fmt: skip
        # The own column from the cell's first slot: slot i skips up to itself
        # (the own cell's earlier slots list it).
        m = _gather_run(first, own_end, 0.0, 0.0, 0.0, 13, xs, ys, zs, cx, cy, cz, c_slot,
                        c_code, 0)  # fmt: skip
        for r in range(n_runs):
            m = _gather_run(
                run_ends[r, 0], run_ends[r, 1], run_shifts[r, 0], run_shifts[r, 1],
                run_shifts[r, 2], run_codes[r], xs, ys, zs, cx, cy, cz, c_slot, c_code, m,
            )  # fmt: skip
        for i in range(p, last):
            skip = i - first + 1
            # Slices from 0: indices LLVM sees are non-negative, so no wrap-around code.
            tx = cx[skip:m]
            ty = cy[skip:m]
            tz = cz[skip:m]
            flags = inside[skip:m]
            xi = xs[i]
            yi = ys[i]
            zi = zs[i]
            for k in range(tx.shape[0]):
                dx = xi - tx[k]
                dy = yi - ty[k]
                dz = zi - tz[k]
                flags[k] = dx * dx + dy * dy + dz * dz < r2_max
            count += _keep(flags, c_slot[skip:m], c_code[skip:m], base, count, capacity,
                           neighbors, codes)  # fmt: skip
            starts[i + 1] = count
        p = last
    counts[chunk] = count


@njit(cache=True, inline="always", error_model="numpy")
def _gather_run(first, last, sx, sy, sz, code, xs, ys, zs, cx, cy, cz, c_slot, c_code, m):
    """Append slots first..last-1, shifted by s, to the candidates at m; return the new end."""
    n = last - first
    fx = xs[first:last]
    fy = ys[first:last]
    fz = zs[first:last]
    tx = cx[m : m + n]
    ty = cy[m : m + n]
    tz = cz[m : m + n]
    t_slot = c_slot[m : m + n]
    t_code = c_code[m : m + n]
    for k in range(n):
        tx[k] = fx[k] + sx
        ty[k] = fy[k] + sy
        tz[k] = fz[k] + sz
        t_slot[k] = first + k
        t_code[k] = code
    return m + n


@njit(cache=True, inline="always", error_model="numpy")
def _keep(flags, slots, slot_codes, base, count, capacity, neighbors, codes):
    """Write the flagged candidates' slots and codes at ``base + count``; return how many.

    Branch-free when the whole candidate row fits in the chunk's capacity
    (every candidate is written, the next overwrites it unless flagged);
    past the capacity, only what fits is written and the rest counted.
    """
    n = flags.shape[0]
    found = 0
    if count + n <= capacity:
        out = neighbors[base + count : base + count + n]
        out_codes = codes[base + count : base + count + n]
        for k in range(n):
            out[found] = slots[k]
            out_codes[found] = slot_codes[k]
            found += flags[k]
        return found
    for k in range(n):
        if flags[k]:
            if count + found < capacity:
                neighbors[base + count + found] = slots[k]
                codes[base + count + found] = slot_codes[k]
            found += 1
    return found


@njit(cache=True, error_model="numpy")
def _cell_runs(cell, n_cells, reach, periodic, box, tilt, cell_starts, run_ends, run_shifts,
               run_codes):  # fmt: skip
    """The runs of slots a slot of ``cell`` is searched against, and their image shifts.

    Writes the runs into ``run_ends`` (first, last slot), ``run_shifts``
    and ``run_codes`` and returns their number and the end of the own
    column's run above the cell (its start depends on the slot: the caller
    scans it from the next slot). Every other run is one of the forward
    columns, or the own column wrapped around the z edge.
    """
    xy, xz, yz = tilt[0], tilt[1], tilt[2]
    nx, ny, nz = n_cells[0], n_cells[1], n_cells[2]
    cx = cell // (ny * nz)
    cy = (cell // nz) % ny
    cz = cell % nz
    n_runs = 0
    own_end = 0
    for ox in range(0, reach + 1):
        kx, wx = _neighbor_cell(cx, ox, nx, periodic[0])
        if kx < 0:
            continue
        for oy in range(-reach, reach + 1):
            if ox == 0 and oy < 0:
                continue
            ky, wy = _neighbor_cell(cy, oy, ny, periodic[1])
            if ky < 0:
                continue
            column = (kx * ny + ky) * nz
            code = (wx + 1) * 9 + (wy + 1) * 3
            sx = wx * box[0] + wy * xy
            sy = wy * box[1]
            own = ox == 0 and oy == 0
            low = cz if own else cz - reach
            high = cz + reach
            last = cell_starts[column + min(high, nz - 1) + 1]
            if own:
                own_end = last
            else:
                run_ends[n_runs, 0] = cell_starts[column + max(low, 0)]
                run_ends[n_runs, 1] = last
                run_shifts[n_runs, 0] = sx
                run_shifts[n_runs, 1] = sy
                run_shifts[n_runs, 2] = 0.0
                run_codes[n_runs] = code + 1
                n_runs += 1
            if periodic[2] and low < 0:  # the cells below z = 0, seen from the top
                run_ends[n_runs, 0] = cell_starts[column + low + nz]
                run_ends[n_runs, 1] = cell_starts[column + nz]
                run_shifts[n_runs, 0] = sx - xz
                run_shifts[n_runs, 1] = sy - yz
                run_shifts[n_runs, 2] = -box[2]
                run_codes[n_runs] = code
                n_runs += 1
            if periodic[2] and high >= nz:  # the cells above the top, seen from z = 0
                run_ends[n_runs, 0] = cell_starts[column]
                run_ends[n_runs, 1] = cell_starts[column + high - nz + 1]
                run_shifts[n_runs, 0] = sx + xz
                run_shifts[n_runs, 1] = sy + yz
                run_shifts[n_runs, 2] = box[2]
                run_codes[n_runs] = code + 2
                n_runs += 1
    return n_runs, own_end


@njit(cache=True, error_model="numpy")
def _compact_chunks(bounds, capacity, counts, starts, neighbors, codes):
    """Join the chunk regions written by ``_frame_pairs`` into one CSR list; return its length.

    Regions move towards the front (never onto data not yet moved), and row
    ends become absolute.
    """
    offset = 0
    starts[0] = 0
    for chunk in range(bounds.shape[0] - 1):
        base = chunk * capacity
        if offset != base:
            for k in range(counts[chunk]):
                neighbors[offset + k] = neighbors[base + k]
                codes[offset + k] = codes[base + k]
        for p in range(bounds[chunk], bounds[chunk + 1]):
            starts[p + 1] += offset
        offset += counts[chunk]
    return offset


def _shift_table(box, pbc, tilt):
    """(27, 3) image shifts named by the codes of ``_frame_pairs``.

    Code 9 dx + 3 dy + dz means the shift (dx - 1) a + (dy - 1) b + (dz - 1) c.
    """
    digits = np.array([(a, b, c) for a in range(3) for b in range(3) for c in range(3)])
    return (digits - 1.0) @ cell_matrix(np.where(pbc, box, 0.0), periodic_tilt(tilt, pbc))


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


@njit(cache=True, error_model="numpy")
def _max_displacement2(positions, reference):
    """Largest squared displacement since ``reference``; inf if any coordinate is not finite."""
    n = positions.shape[0]
    worst = 0.0
    for i in range(n):
        d2 = 0.0
        for a in range(3):
            x = positions[i, a]
            if not np.isfinite(x):
                return np.inf
            d = x - reference[i, a]
            d2 += d * d
        if d2 > worst:
            worst = d2
    return worst
