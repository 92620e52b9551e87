"""Numba kernels for neighbour search (arrays and scalars only).

Lists are half lists in CSR form: ``neighbors[starts[i]:starts[i + 1]]`` are
the partners j of atom i, each unordered pair within the list radius (by
minimum image) listed exactly once.
Kernels write into caller-owned arrays and return the number of pairs found;
when that exceeds the capacity of ``neighbors`` they keep counting without
writing, so the caller can grow the buffer and call again.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from md.box import _min_image


@njit(cache=True, error_model="numpy")
def _brute_force_pairs(positions, lengths, inverse, r2_max, starts, neighbors):
    """O(N^2) half list; the reference the cell search is tested against."""
    n = positions.shape[0]
    capacity = neighbors.shape[0]
    count = 0
    starts[0] = 0
    for i in range(n):
        xi = positions[i, 0]
        yi = positions[i, 1]
        zi = positions[i, 2]
        for j in range(i + 1, n):
            dx = _min_image(xi - positions[j, 0], lengths[0], inverse[0])
            dy = _min_image(yi - positions[j, 1], lengths[1], inverse[1])
            dz = _min_image(zi - positions[j, 2], lengths[2], inverse[2])
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
    cell_of,
    cell_starts,
    order,
    sorted_wrapped,
):
    """Counting sort of atoms by cell.

    Writes ``cell_of[i]`` (flat cell index of atom i), ``cell_starts``
    (n_cells + 1 CSR offsets), ``order`` (atom indices grouped by cell) and
    ``sorted_wrapped[p]``, the position of atom ``order[p]`` wrapped into
    [0, L) along periodic axes, so a cell's atoms are contiguous in memory.
    Open axes are clamped to the grid, whose origin and width the caller
    chose to span the atoms.
    """
    n = positions.shape[0]
    nx, ny, nz = n_cells[0], n_cells[1], n_cells[2]
    total = nx * ny * nz
    for c in range(total + 1):
        cell_starts[c] = 0
    for i in range(n):
        kx = _grid_index(positions[i, 0], origin[0], cell_width[0], nx, periodic[0], box[0])
        ky = _grid_index(positions[i, 1], origin[1], cell_width[1], ny, periodic[1], box[1])
        kz = _grid_index(positions[i, 2], origin[2], cell_width[2], nz, periodic[2], box[2])
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
        for a in range(3):
            x = positions[i, a]
            if periodic[a]:
                x = x - box[a] * np.floor(x / box[a])
            sorted_wrapped[p, a] = x


@njit(cache=True, inline="always", error_model="numpy")
def _neighbor_cell(c, offset, n, periodic, length):
    """Index of the adjacent cell c + offset along one axis and the image shift.

    Returns (-1, 0.0) past the edge of an open axis.
    """
    k = c + offset
    if k < 0:
        if not periodic:
            return -1, 0.0
        return k + n, -length
    if k >= n:
        if not periodic:
            return -1, 0.0
        return k - n, length
    return k, 0.0


@njit(cache=True, error_model="numpy")
def _cell_pairs(
    sorted_wrapped, r2_max, n_cells, periodic, box, cell_of, cell_starts, order, starts, neighbors
):
    """Half list from a cell grid, scanning the own cell and 13 forward neighbours.

    Each unordered pair is listed once: within a cell, under the atom that
    comes first in the sorted order; across cells, under the atom whose cell
    sees the other through one of the 13 lexicographically positive offsets.
    Rows are in atom order, but a row may hold j < i. The image shift of a
    neighbour cell is fixed per cell, so no per-candidate minimum image is
    needed. Requires at least three cells along every periodic axis, so the
    27 cells around any cell are distinct.
    """
    n = sorted_wrapped.shape[0]
    nx, ny, nz = n_cells[0], n_cells[1], n_cells[2]
    capacity = neighbors.shape[0]
    rank = np.empty(n, dtype=np.int64)
    for p in range(n):
        rank[order[p]] = p
    most = 0
    for c in range(nx * ny * nz):
        most = max(most, cell_starts[c + 1] - cell_starts[c])
    row = np.empty(14 * most, dtype=np.int32)  # candidates of one atom, written branch-free
    count = 0
    starts[0] = 0
    for i in range(n):
        c = cell_of[i]
        cx = c // (ny * nz)
        cy = (c // nz) % ny
        cz = c % nz
        ri = rank[i]
        xi = sorted_wrapped[ri, 0]
        yi = sorted_wrapped[ri, 1]
        zi = sorted_wrapped[ri, 2]
        found = 0
        for ox in range(0, 2):
            kx, sx = _neighbor_cell(cx, ox, nx, periodic[0], box[0])
            if kx < 0:
                continue
            for oy in range(-1, 2):
                if ox == 0 and oy < 0:
                    continue
                ky, sy = _neighbor_cell(cy, oy, ny, periodic[1], box[1])
                if ky < 0:
                    continue
                for oz in range(-1, 2):
                    if ox == 0 and oy == 0 and oz < 0:
                        continue
                    kz, sz = _neighbor_cell(cz, oz, nz, periodic[2], box[2])
                    if kz < 0:
                        continue
                    other = (kx * ny + ky) * nz + kz
                    first = cell_starts[other]
                    if other == c:
                        first = ri + 1
                    for p in range(first, cell_starts[other + 1]):
                        dx = xi - (sorted_wrapped[p, 0] + sx)
                        dy = yi - (sorted_wrapped[p, 1] + sy)
                        dz = zi - (sorted_wrapped[p, 2] + sz)
                        row[found] = order[p]
                        found += dx * dx + dy * dy + dz * dz < r2_max
        for k in range(found):
            if count + k < capacity:
                neighbors[count + k] = row[k]
        count += found
        starts[i + 1] = count
    return count


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
