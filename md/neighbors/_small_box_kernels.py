"""The slot frame of a box too narrow for the cell search (fewer than five half-radius cells
along a periodic axis: the LJ liquid below about 500 atoms), by an O(N^2) search over the
periodic images: ``_small_box_list`` (one compiled call, as ``_build_kernels._cell_list``
is for the cell search), its row kernels (``_nearest_images`` and the cell search's
candidate test, ``_turned_images`` for a second image, ``_sheared_row`` for a tilted
cell), and ``_drop_repeats`` for its list over atom indices.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from md._simd import PERMUTATIONS
from md.neighbors._build_kernels import _balanced_bounds, _bin_atoms
from md.neighbors._candidates import _near_pack
from md.neighbors._cell_kernels import _CODE_SHIFT, _SLOT_MASK


@njit(cache=True, error_model="numpy")
def _small_box_list(positions, periodic, box, tilt, r2_max, chunks, neighbors, codes):
    """The slot list of a box too narrow for the cell search, by an O(N^2) search over images.

    For a cell with room for fewer than five half-radius cells along a periodic axis:
    atoms are wrapped into the cell as ``_bin_atoms`` wraps them (one cell, so the slots
    keep atom order: ``order`` is 0 .. N - 1) and every slot pair is tested; the list is
    the cell search's slot frame (pairs with image codes: the pair kernels need no minimum
    image). The caller sees that every periodic perpendicular width is longer than the
    list radius: then no pair has an image within reach at a shift of two cell vectors or
    more, and the codes' shifts of -1, 0 or 1 along each axis find every image.

    A pair has one entry per image within reach: more than one only in a cell narrower
    than twice the list radius (the 108-atom LJ liquid), where ``repeats`` is returned
    True; at most one of them is within the cutoff, which is under half of every width.
    In an orthorhombic cell each row takes the later slots' nearest images
    (``_nearest_images``, a loop the compiler vectorises), keeps those within reach by the
    cell search's candidate test (``_near_pack``: 8-lane blocks, no branch per pair) and,
    in a cell under twice the list radius wide, adds each hit's other images within reach
    (``_turned_images``). A tilted cell takes ``_sheared_row``: the shifts tried nested c,
    b, a as the restricted triclinic cell is (a shift along c that puts the z separation
    out of reach is not tried along b or a).

    Returns (order, images, starts, bounds, count, shifted, repeats) as ``_cell_list``
    does (count: minus the pairs found where they overflow ``neighbors`` or ``codes``;
    grow both and call again), ``shifted`` exact per row.
    """
    n = positions.shape[0]
    cell_of = np.empty(n, dtype=np.int64)
    cell_starts = np.empty(2, dtype=np.int64)
    order = np.empty(n, dtype=np.int64)
    wrapped = np.empty((3, n))
    images = np.empty((n, 3), dtype=np.int32)
    _bin_atoms(
        positions,
        np.zeros(3),
        np.ones(3),
        np.ones(3, dtype=np.int64),
        periodic,
        box,
        tilt,
        cell_of,
        cell_starts,
        order,
        wrapped,
        images,
    )
    lengths = np.zeros(3)
    halves = np.full(3, np.inf)  # no image along an open axis
    for a in range(3):
        if periodic[a]:
            lengths[a] = box[a]
            halves[a] = 0.5 * box[a]
    sheared = tilt[0] != 0.0 or tilt[1] != 0.0 or tilt[2] != 0.0
    turns = False  # whether a pair may have a second image within reach
    for a in range(3):
        if periodic[a] and box[a] * box[a] < 4.0 * r2_max:
            turns = True
    # per row: the later slots' nearest separations and packed (code, slot), then the
    # hits, each padded for the candidate test's whole blocks (64 entries)
    ex = np.zeros(n + _SMALL_PADDING)
    ey = np.zeros(n + _SMALL_PADDING)
    ez = np.zeros(n + _SMALL_PADDING)
    packed = np.zeros(n + _SMALL_PADDING, dtype=np.uint32)
    hits = np.empty(n + _SMALL_PADDING, dtype=np.uint32)
    capacity = min(neighbors.shape[0], codes.shape[0])
    starts = np.zeros(n + 1, dtype=np.int64)
    shifted = np.zeros(n, dtype=np.bool_)
    count = 0
    repeats = False
    for p in range(n):
        if sheared:
            count, more = _sheared_row(p, wrapped, lengths, tilt, r2_max, neighbors, codes, count)
            repeats = repeats or more
        else:
            m = _nearest_images(p, wrapped, lengths, halves, ex, ey, ez, packed)
            found = 0
            for first in range(0, m, 64):
                found = _near_pack(
                    0.0,
                    0.0,
                    0.0,
                    r2_max,
                    ex,
                    ey,
                    ez,
                    packed,
                    first,
                    min(64, m - first),
                    PERMUTATIONS,
                    hits,
                    found,
                )
            for h in range(found):
                value = hits[h]
                q = np.int32(value & _SLOT_MASK)
                code = np.uint8(value >> _CODE_SHIFT)
                if count < capacity:
                    neighbors[count] = q
                    codes[count] = code
                count += 1
                if turns:
                    t = q - p - 1
                    before = count
                    count = _turned_images(
                        q, code, ex[t], ey[t], ez[t], lengths, r2_max, neighbors, codes, count
                    )
                    repeats = repeats or count > before
        for k in range(starts[p], min(count, capacity)):
            if codes[k] != 13:
                shifted[p] = True
                break
        starts[p + 1] = count
    if count > capacity:
        return order, images, starts, np.zeros(chunks + 1, np.int64), -count, shifted, repeats
    return order, images, starts, _balanced_bounds(starts, chunks), count, shifted, repeats


#: Entries past the last slot of ``_small_box_list``'s row arrays: the candidate test
#: reads whole words of 64.
_SMALL_PADDING = 64


@njit(cache=True, inline="always", error_model="numpy")
def _nearest_images(p, wrapped, lengths, halves, ex, ey, ez, packed):
    """Row p of ``_small_box_list`` in an orthorhombic cell: the nearest image of each later
    slot q, its separation at ``ex, ey, ez[q - p - 1]`` and ``(code << _CODE_SHIFT) | q`` in
    ``packed`` (branch-free: a loop the compiler vectorises); returns the count."""
    n = wrapped.shape[1]
    xp, yp, zp = wrapped[0, p], wrapped[1, p], wrapped[2, p]
    lx, ly, lz = lengths[0], lengths[1], lengths[2]
    hx, hy, hz = halves[0], halves[1], halves[2]
    m = n - p - 1
    for t in range(m):
        q = p + 1 + t
        dx = xp - wrapped[0, q]
        dy = yp - wrapped[1, q]
        dz = zp - wrapped[2, q]
        kx = np.int32(dx > hx) - np.int32(dx < -hx)
        ky = np.int32(dy > hy) - np.int32(dy < -hy)
        kz = np.int32(dz > hz) - np.int32(dz < -hz)
        ex[t] = dx - kx * lx
        ey[t] = dy - ky * ly
        ez[t] = dz - kz * lz
        code = np.uint32(13 + 9 * kx + 3 * ky + kz)
        packed[t] = (code << _CODE_SHIFT) | np.uint32(q)
    return m


@njit(cache=True, inline="always", error_model="numpy")
def _turned_images(q, code, ex, ey, ez, lengths, r2_max, neighbors, codes, count):
    """The images of a pair other than its nearest (separation ex, ey, ez, image ``code``)
    within reach, in an orthorhombic cell under twice the list radius wide along some axis:
    the nearest with its shift turned over along some axes (one cell vector more towards
    the other side). A turn along axis a adds (L_a - |e_a|)^2 - e_a^2 >= 0 to r^2, so most
    pairs are rejected by the cheapest turn alone. Returns the new count (entries written
    while under the buffers' capacity)."""
    capacity = min(neighbors.shape[0], codes.shape[0])
    lx, ly, lz = lengths[0], lengths[1], lengths[2]
    r2 = ex * ex + ey * ey + ez * ez
    mx = (lx - abs(ex)) ** 2 - ex * ex if lx > 0.0 else np.inf  # inf: an open axis
    my = (ly - abs(ey)) ** 2 - ey * ey if ly > 0.0 else np.inf
    mz = (lz - abs(ez)) ** 2 - ez * ez if lz > 0.0 else np.inf
    if r2 + min(mx, my, mz) >= r2_max:
        return count
    # code 9 (kx + 1) + 3 (ky + 1) + (kz + 1); a turn moves k by one towards the sign of e
    tx = 9 if ex > 0.0 else -9
    ty = 3 if ey > 0.0 else -3
    tz = 1 if ez > 0.0 else -1
    for turns in range(1, 8):
        extra = 0.0
        turned = np.int64(code)
        if turns & 4:
            extra += mx
            turned += tx
        if turns & 2:
            extra += my
            turned += ty
        if turns & 1:
            extra += mz
            turned += tz
        if r2 + extra < r2_max:
            if count < capacity:
                neighbors[count] = q
                codes[count] = turned
            count += 1
    return count


@njit(cache=True, inline="always", error_model="numpy")
def _sheared_row(p, wrapped, lengths, tilt, r2_max, neighbors, codes, count):
    """Row p of ``_small_box_list`` in a tilted cell: every image within reach, the shifts
    tried nested c, b, a (see there). Returns the count and whether a pair had more than
    one image (never, in a cell whose widths are over twice the list radius)."""
    n = wrapped.shape[1]
    capacity = min(neighbors.shape[0], codes.shape[0])
    xp, yp, zp = wrapped[0, p], wrapped[1, p], wrapped[2, p]
    lx, ly, lz = lengths[0], lengths[1], lengths[2]
    reach_x = 1 if lx > 0.0 else 0
    reach_y = 1 if ly > 0.0 else 0
    reach_z = 1 if lz > 0.0 else 0
    xy, xz, yz = tilt[0], tilt[1], tilt[2]
    repeats = False
    for q in range(p + 1, n):
        dx = xp - wrapped[0, q]
        dy = yp - wrapped[1, q]
        dz = zp - wrapped[2, q]
        found = 0
        for kz in range(-reach_z, reach_z + 1):
            ez = dz - kz * lz
            z2 = ez * ez
            if z2 >= r2_max:
                continue
            for ky in range(-reach_y, reach_y + 1):
                ey = dy - kz * yz - ky * ly
                yz2 = z2 + ey * ey
                if yz2 >= r2_max:
                    continue
                for kx in range(-reach_x, reach_x + 1):
                    ex = dx - kz * xz - ky * xy - kx * lx
                    if yz2 + ex * ex < r2_max:
                        if count < capacity:
                            neighbors[count] = q
                            codes[count] = 9 * (kx + 1) + 3 * (ky + 1) + kz + 1
                        count += 1
                        found += 1
        if found > 1:
            repeats = True
    return count, repeats


@njit(cache=True, error_model="numpy")
def _drop_repeats(starts, neighbors):
    """Keep the first of each run of equal partners in a row (a pair listed once per image),
    in place; returns the pairs kept (``starts`` rewritten)."""
    n = starts.shape[0] - 1
    kept = 0
    first = starts[0]
    for i in range(n):
        last = starts[i + 1]
        previous = -1
        for k in range(first, last):
            if neighbors[k] != previous:
                previous = neighbors[k]
                neighbors[kept] = previous
                kept += 1
        first = last
        starts[i + 1] = kept
    return kept
