"""The list of one rank of a decomposed run (``NeighborList.keep_owned``): rows of owned
atoms only, searched as the rank keeps them, so that no pair of two ghosts is ever a
candidate and the pair kernels walk no ghost row.

The local system is the rank's owned atoms (``0 .. n_owned - 1``) followed by ghost copies
of other ranks' atoms. ``_owned_cell_list`` (one compiled call, as ``_cell_list`` is for
the whole-system search) bins the owned atoms and the ghosts apart on one grid: slots
``0 .. n_owned - 1`` hold the owned atoms by cell, the later slots the ghosts by cell.
Each owned slot's row is searched in two parts:

- the owned atoms of the forward half of the 5 x 5 x 5 half-radius cells around its own
  (the cell search's half rule, ``_cell_kernels._gather_column`` and the own column read
  in place): every owned pair once;
- the ghosts of the 125 cells around it (a ghost has no row of its own), copied once per
  column of owned cells (``_gather_around``) in segments, the ghosts of one x cell of one
  z cell with one image shift, each with a box of their x and z ranges (``_slab_ranges``:
  per x cell and per z cell, the ghosts' least and greatest coordinate): the row tests
  the segments whose box comes within the list radius of it in x and z (consecutive ones
  as one range: those it skips hold no partner, so the row's partners and their order are
  the full shell's), and keeps those whose pair designates the owned atom
  (``_cell_kernels.designates``, on the slots' global ids) as it writes them. On a slab
  of the 1152-atom melt that is about half the ghosts of the full shell.

The candidate tests are the cell search's (``_candidates``), their loops over a range
written out in the row loop, as in ``_frame_pairs_chunk`` (a compiled helper holding that
loop cost about 60 ns a call, as much as its tests). The rows of the ghost slots
are empty, and the pair kernels' chunk bounds end at the last owned slot, so a ghost costs
the force call its position and its force only. ``_owned_brute_force_pairs`` is the O(N^2)
search of the same list over atom indices (a local system too small for the cells).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from md._simd import PERMUTATIONS
from md.box import min_image
from md.neighbors._build_kernels import (
    _balanced_bounds,
    _bin_pass,
    _cell_offsets,
    _join_chunks,
    _scatter_pass,
)
from md.neighbors._candidates import _keep, _near_pack, _near_pack_whole
from md.neighbors._cell_kernels import (
    _CODE_SHIFT,
    _SLOT_MASK,
    ROW_PADDING,
    _gather_column,
    _gather_run,
    _neighbor_cell,
    _slot_layout,
    _slot_layout_threaded,
    designates,
)


@njit(cache=True, error_model="numpy")
def _owned_cell_list(
    positions,
    n_owned,
    ids,
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
    tested,
):
    """A rank's list in one compiled call: bin the owned atoms and the ghosts apart, search
    the owned rows (``_owned_pairs``), join the chunks.

    Returns (order, images, starts, bounds, count, shifted) as ``_cell_list`` does: slots
    ``0 .. n_owned - 1`` are the owned atoms (atoms below ``n_owned``) by cell, the rest
    the ghosts by cell; only owned rows hold pairs, ``bounds`` (the pair kernels' chunks)
    ends at ``n_owned``, and ``shifted`` flags the owned rows near a periodic edge (the
    ghost rows: none). ``ids`` (N,) are the atoms' global ids. A chunk that finds more
    pairs than its region of ``len(neighbors) // chunks`` entries holds makes count minus
    the largest chunk's count (grow both buffers to that many per chunk and call again).
    The binning is serial (one pass over the atoms); the search and the join run on
    numba's threads when ``chunks`` > 1. ``tested[c]`` (int64, at least ``chunks``) gets the
    number of ghost candidates chunk c tested (``_owned_pairs_chunk``).
    """
    n = positions.shape[0]
    total = n_cells[0] * n_cells[1] * n_cells[2]
    cell_of = np.empty(n, dtype=np.int64)
    moved = np.empty((n, 3))
    wraps = np.empty((n, 3), dtype=np.int32)
    owned_counts = np.zeros((1, total), dtype=np.int64)
    ghost_counts = np.zeros((1, total), dtype=np.int64)
    for first, last, counts in ((0, n_owned, owned_counts), (n_owned, n, ghost_counts)):
        _bin_pass(
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
            counts[0],
        )
    owned_starts = np.empty(total + 1, dtype=np.int64)
    ghost_starts = np.empty(total + 1, dtype=np.int64)
    _cell_offsets(owned_counts, owned_starts)
    _cell_offsets(ghost_counts, ghost_starts)
    for c in range(total + 1):  # the ghosts' slots follow the owned atoms'
        ghost_starts[c] += n_owned
    for c in range(total):
        ghost_counts[0, c] += n_owned
    order = np.empty(n, dtype=np.int64)
    wrapped = np.empty((3, n + ROW_PADDING))
    wrapped[:, n:] = 0.0
    images = np.empty((n, 3), dtype=np.int32)
    _scatter_pass(0, n_owned, cell_of, moved, wraps, owned_counts[0], order, wrapped, images)
    _scatter_pass(n_owned, n, cell_of, moved, wraps, ghost_counts[0], order, wrapped, images)
    slot_cell = cell_of  # reused: the cell of each slot, in slot order
    if chunks > 1:
        owned_layout = _slot_layout_threaded(wrapped, owned_starts, n_cells, slot_cell, chunks)
    else:
        owned_layout = _slot_layout(wrapped, owned_starts, n_cells, slot_cell)
    ghost_planes, _, ghost_most = _slot_layout(wrapped, ghost_starts, n_cells, slot_cell)
    ghost_ranges = _slab_ranges(ghost_planes, n_cells)
    slot_ids = np.empty(n, dtype=np.int64)
    for p in range(n):
        slot_ids[p] = ids[order[p]]
    search = np.empty(chunks + 1, dtype=np.int64)
    for c in range(chunks + 1):
        search[c] = c * n_owned // chunks
    starts = np.zeros(n + 1, dtype=np.int64)
    found = np.zeros(chunks, dtype=np.int64)
    capacity = min(neighbors.shape[0], codes.shape[0]) // chunks
    planes, tags, most = owned_layout
    if chunks > 1:  # one chunk stays off numba's thread pool: no wake-ups on a busy machine
        _owned_pairs_threaded(
            wrapped,
            slot_cell,
            slot_ids,
            r2_max,
            n_cells,
            reach,
            periodic,
            box,
            tilt,
            owned_starts,
            planes,
            tags,
            most,
            ghost_planes,
            ghost_most,
            ghost_ranges,
            search,
            capacity,
            starts,
            neighbors,
            codes,
            found,
            tested,
        )
    else:
        _owned_pairs(
            wrapped,
            slot_cell,
            slot_ids,
            r2_max,
            n_cells,
            reach,
            periodic,
            box,
            tilt,
            owned_starts,
            planes,
            tags,
            most,
            ghost_planes,
            ghost_most,
            ghost_ranges,
            search,
            capacity,
            starts,
            neighbors,
            codes,
            found,
            tested,
        )
    largest = found.max()
    if largest > capacity:
        return order, images, starts, search, -largest, np.empty(0, dtype=np.bool_)
    if chunks > 1:
        count = _join_chunks(search, capacity, found, starts, neighbors, codes)
    else:
        count = found[0]
    for p in range(n_owned + 1, n + 1):  # the ghosts' rows: empty
        starts[p] = count
    shifted = _owned_shifted_rows(owned_starts, n, n_cells, reach, periodic)
    return order, images, starts, _balanced_bounds(starts[: n_owned + 1], chunks), count, shifted


@njit(cache=True, error_model="numpy")
def _owned_pairs(
    wrapped,
    slot_cell,
    slot_ids,
    r2_max,
    n_cells,
    reach,
    periodic,
    box,
    tilt,
    owned_starts,
    planes,
    tags,
    most,
    ghost_planes,
    ghost_most,
    ghost_ranges,
    bounds,
    capacity,
    starts,
    neighbors,
    codes,
    counts,
    tested,
):
    """The owned rows' search, chunk after chunk (``_owned_pairs_chunk``)."""
    for chunk in range(bounds.shape[0] - 1):
        _owned_pairs_chunk(
            chunk,
            wrapped,
            slot_cell,
            slot_ids,
            r2_max,
            n_cells,
            reach,
            periodic,
            box,
            tilt,
            owned_starts,
            planes,
            tags,
            most,
            ghost_planes,
            ghost_most,
            ghost_ranges,
            bounds,
            capacity,
            starts,
            neighbors,
            codes,
            counts,
            tested,
        )


@njit(cache=True, parallel=True, error_model="numpy")
def _owned_pairs_threaded(
    wrapped,
    slot_cell,
    slot_ids,
    r2_max,
    n_cells,
    reach,
    periodic,
    box,
    tilt,
    owned_starts,
    planes,
    tags,
    most,
    ghost_planes,
    ghost_most,
    ghost_ranges,
    bounds,
    capacity,
    starts,
    neighbors,
    codes,
    counts,
    tested,
):
    """``_owned_pairs`` with one chunk per thread (the same list). The chunk's index goes
    in as an int64, as ``_owned_pairs`` gives it (a prange body's own index is a uint64:
    the chunk kernel compiled twice, tests/test_compile_chain.py)."""
    for chunk in prange(bounds.shape[0] - 1):
        _owned_pairs_chunk(
            np.int64(chunk),
            wrapped,
            slot_cell,
            slot_ids,
            r2_max,
            n_cells,
            reach,
            periodic,
            box,
            tilt,
            owned_starts,
            planes,
            tags,
            most,
            ghost_planes,
            ghost_most,
            ghost_ranges,
            bounds,
            capacity,
            starts,
            neighbors,
            codes,
            counts,
            tested,
        )


@njit(cache=True, inline="always", error_model="numpy")
def _keep_designated(out, first, last, slot_ids, own_id):
    """Keep, in place, the packed ghost partners ``out[first:last]`` of the owned atom with
    global id ``own_id`` whose pair designates it; return the new end."""
    kept = first
    for k in range(first, last):
        value = out[k]
        out[kept] = value  # written always, counted when kept: no branch to mispredict
        kept += designates(own_id, slot_ids[value & _SLOT_MASK])
    return kept


@njit(cache=True, error_model="numpy")
def _owned_pairs_chunk(
    chunk,
    wrapped,
    slot_cell,
    slot_ids,
    r2_max,
    n_cells,
    reach,
    periodic,
    box,
    tilt,
    owned_starts,
    planes,
    tags,
    most,
    ghost_planes,
    ghost_most,
    ghost_ranges,
    bounds,
    capacity,
    starts,
    neighbors,
    codes,
    counts,
    tested,
):
    """One chunk of the owned rows' search: owned slots ``search[chunk]`` to
    ``search[chunk + 1]``, into its region of ``neighbors`` (``_frame_pairs_chunk``'s
    layout: rows counted from the region's start, packed slots and codes unpacked by
    the join, or here when there is one chunk).

    Per (x, y) column of owned slots: the owned candidates of its forward columns and its
    own column as the whole-system search takes them (``_gather_column``), and the ghosts
    of the 25 columns around it, its own included, in segments (``_gather_around``). Row
    i (z cell cz) tests the owned ones as that search does (a half list), then the ghosts
    of the segments of z cells cz - reach to cz + reach whose box lies within the list
    radius of it in x and z (``_near_segments``), and keeps those whose pair designates
    atom i (``_keep_designated``) while they are in the cache; ``tested[chunk]`` counts
    the ghosts tested. (As in ``_frame_pairs_chunk``,
    ``ghost`` counts the image cells past each end of a periodic z axis and
    ``ghost_last`` the own column's images above its top; the ghost atoms' candidates
    are the ``g`` arrays.)
    """
    nz = n_cells[2]
    most_cell, most_column = most
    base = chunk * capacity
    # a segment is skipped when its bound reaches this (a hair above r2_max: the bound is
    # computed as the test computes a distance, so r2_max itself would do)
    r2_reach = r2_max * (1.0 + 1e-12)
    ghost = reach if periodic[2] else 0  # image cells past each z end
    n_z = nz + 2 * ghost
    n_forward = reach * (2 * reach + 1) + reach
    size = n_forward * (most_column + 2 * ghost * most_cell)
    cx = np.empty(size + 64)
    cy = np.empty(size + 64)
    cz = np.empty(size + 64)
    c_packed = np.empty(size + 64, dtype=np.uint32)
    z_start = np.empty(n_z + 1, dtype=np.int64)
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
    g_size = (2 * reach + 1) ** 2 * (ghost_most[1] + 2 * ghost * ghost_most[0])
    gx = np.empty(g_size + 64)
    gy = np.empty(g_size + 64)
    gz = np.empty(g_size + 64)
    g_packed = np.empty(g_size + 64, dtype=np.uint32)
    g_start = np.empty(n_z + 1, dtype=np.int64)
    g_runs = np.empty((4, 2 * (2 * reach + 1)), dtype=np.int64)
    g_shifts = np.empty((2, 2 * (2 * reach + 1)))
    n_segments = n_z * 2 * (2 * reach + 1)  # at most one a run
    segments = np.empty(n_segments + 1, dtype=np.int64)
    segment_box = np.empty((4, n_segments))
    segment_z = np.empty(n_z + 1, dtype=np.int64)
    ranges = np.empty((2, n_segments), dtype=np.int64)  # a row's runs of segments
    masks = np.empty(max(size, g_size) // 64 + 2, dtype=np.uint64)
    xs, ys, zs = wrapped[0], wrapped[1], wrapped[2]
    packed_list = neighbors.view(np.uint32)
    count = 0
    n_tested = 0
    p = bounds[chunk]
    end = bounds[chunk + 1]
    while p < end:
        column = slot_cell[p] // nz
        stop = min(owned_starts[column * nz + nz], end)
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
        _gather_around(
            column,
            n_cells,
            reach,
            ghost,
            periodic,
            box,
            tilt,
            ghost_planes,
            ghost_ranges,
            g_runs,
            g_shifts,
            gx,
            gy,
            gz,
            g_packed,
            g_start,
            segments,
            segment_box,
            segment_z,
        )
        for i in range(p, stop):
            kz = slot_cell[i] - column * nz
            low = max(kz - reach + ghost, 0)
            high = min(kz + reach + ghost, n_z - 1) + 1
            first, last = z_start[low], z_start[high]
            g_first, g_last = g_start[low], g_start[high]
            own_last = owned_starts[column * nz + min(kz + reach, nz - 1) + 1]
            above = kz + reach - nz + 1 if ghost else 0
            ghost_last = own[4][above] if above > 0 else 0
            n_candidates = (last - first) + (own_last - i - 1) + ghost_last + (g_last - g_first)
            split = count  # where the row's ghost partners begin
            if count + n_candidates + 8 <= capacity:
                # room for every candidate and a block's spill: written as they are tested
                at = base + count
                # (the range's words written out here: a helper holding this loop cost
                # about 60 ns a call, whatever the range, more than its blocks' tests)
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
                while w < own_last:
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
                split = at - base
                # the ghosts: the segments that may hold a partner, consecutive ones as one
                # range (those between hold none, so the row's partners and order stay)
                n_ranges = _near_segments(
                    xs[i],
                    zs[i],
                    r2_reach,
                    segment_z[low],
                    segment_z[high],
                    segments,
                    segment_box,
                    ranges,
                )
                for k in range(n_ranges):
                    w, g_end = ranges[0, k], ranges[1, k]
                    n_tested += g_end - w
                    while w + 64 <= g_end:
                        at = _near_pack_whole(
                            xs[i],
                            ys[i],
                            zs[i],
                            r2_max,
                            gx,
                            gy,
                            gz,
                            g_packed,
                            w,
                            64,
                            PERMUTATIONS,
                            packed_list,
                            at,
                        )
                        w += 64
                    if w < g_end:
                        at = _near_pack(
                            xs[i],
                            ys[i],
                            zs[i],
                            r2_max,
                            gx,
                            gy,
                            gz,
                            g_packed,
                            w,
                            g_end - w,
                            PERMUTATIONS,
                            packed_list,
                            at,
                        )
                count = at - base
            else:
                for r in range(4):  # forward cells, own column, its images, the ghosts
                    if r == 0:
                        tx, ty, tz, tp, a, b = cx, cy, cz, c_packed, first, last
                    elif r == 1:
                        tx, ty, tz, tp, a, b = xs, ys, zs, tags, i + 1, own_last
                    elif r == 2:
                        tx, ty, tz, tp, a, b = own[0], own[1], own[2], own[3], 0, ghost_last
                    else:
                        split = count
                        n_tested += g_last - g_first
                        tx, ty, tz, tp, a, b = gx, gy, gz, g_packed, g_first, g_last
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
            if count <= capacity:
                count = (
                    _keep_designated(packed_list, base + split, base + count, slot_ids, slot_ids[i])
                    - base
                )
            starts[i + 1] = count
        p = stop
    counts[chunk] = count
    tested[chunk] = n_tested
    if bounds.shape[0] == 2 and count <= capacity:  # the only chunk: unpack it here, hot
        listed = packed_list[:count]
        listed_codes = codes[:count]
        for k in range(count):
            listed_codes[k] = listed[k] >> _CODE_SHIFT
        for k in range(count):
            listed[k] &= _SLOT_MASK


@njit(cache=True, error_model="numpy")
def _gather_around(
    column,
    n_cells,
    reach,
    ghost,
    periodic,
    box,
    tilt,
    planes,
    ranges,
    runs,
    run_shifts,
    cx,
    cy,
    cz,
    c_packed,
    z_start,
    segments,
    segment_box,
    segment_z,
):
    """Copy the ghost candidates of one (x, y) column of owned slots: per z cell (cell
    zc - ghost from ``z_start[zc]``, with ``ghost`` image cells past each end of a periodic
    z axis), the cells of all columns within ``reach`` along x and y, its own included,
    from the ghosts' ``planes`` (``_slot_layout``), shifted by their image, as
    ``_gather_column`` copies the forward ones (rows of cells along y as runs, one or two
    where a row wraps). ``runs`` and ``run_shifts``: scratch, (4, 2 (2 reach + 1)) and
    (2, 2 (2 reach + 1)).

    The candidates come in segments, the runs of one z cell and one x cell with the same
    shift (``segments[s]`` to ``segments[s + 1]``; those of z cell zc from
    ``segment_z[zc]``), each with a box that holds its candidates: ``segment_box[:, s]`` =
    (x low, x high, z low, z high), the x and z ranges of the ghosts in its x and z cells
    (``ranges``, ``_slab_ranges``) moved by its shift, added as the copy adds it (a
    candidate's coordinate is never outside its box, rounding included)."""
    px, py, pz, p_slot, plane_starts = planes
    xy, xz, yz = tilt[0], tilt[1], tilt[2]
    nx, ny, nz = n_cells[0], n_cells[1], n_cells[2]
    kx0 = column // ny
    ky0 = column % ny
    run_x, run_first, run_last, code_xy = runs[0], runs[1], runs[2], runs[3]
    shift_x, shift_y = run_shifts[0], run_shifts[1]
    n_runs = 0
    for ox in range(-reach, reach + 1):
        kx, wx = _neighbor_cell(kx0, ox, nx, periodic[0])
        if kx < 0:
            continue
        last_wy = 2  # no run open
        for oy in range(-reach, reach + 1):
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
    x_low, x_high, z_low, z_high = ranges
    m = 0
    s = 0
    for zc in range(nz + 2 * ghost):
        z_start[zc] = m
        segment_z[zc] = s
        kz, wz = _neighbor_cell(zc - ghost, 0, nz, periodic[2])
        layer = kz * nx
        sz = wz * box[2]
        open_x = -1  # the x cell and shift of the segment open
        open_shift = 0.0
        for r in range(n_runs):
            row = (layer + run_x[r]) * ny
            begin, end = plane_starts[row + run_first[r]], plane_starts[row + run_last[r] + 1]
            if begin == end:  # (most runs beside a brick's interior: no ghost there)
                continue
            sx = shift_x[r] + wz * xz
            if run_x[r] != open_x or sx != open_shift:
                segments[s] = m
                segment_box[0, s] = x_low[run_x[r]] + sx
                segment_box[1, s] = x_high[run_x[r]] + sx
                segment_box[2, s] = z_low[kz] + sz
                segment_box[3, s] = z_high[kz] + sz
                s += 1
                open_x = run_x[r]
                open_shift = sx
            m = _gather_run(
                begin,
                end,
                sx,
                shift_y[r] + wz * yz,
                sz,
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
    segment_z[nz + 2 * ghost] = s
    segments[s] = m


@njit(cache=True, inline="always", error_model="numpy")
def _near_segments(x, z, r2_reach, first, last, segments, segment_box, ranges):
    """Of segments first..last-1 (``_gather_around``), those whose box lies closer than
    sqrt(r2_reach) to (x, z) in x and z, consecutive ones joined: ``ranges[:, k]`` = (first
    candidate, end) of run k; returns their number. The box's distance is computed as the
    candidate test computes a distance (differences, squares, then their sum), so no
    candidate of a segment left out is nearer than the box."""
    x_low, x_high, z_low, z_high = segment_box[0], segment_box[1], segment_box[2], segment_box[3]
    n = 0
    was_near = False
    for s in range(first, last):
        ax = x_low[s] - x
        bx = x - x_high[s]
        ax = ax if ax > bx else bx
        ax = ax if ax > 0.0 else 0.0
        az = z_low[s] - z
        bz = z - z_high[s]
        az = az if az > bz else bz
        az = az if az > 0.0 else 0.0
        near = ax * ax + az * az < r2_reach
        if near:
            if not was_near:
                ranges[0, n] = segments[s]
                n += 1
            ranges[1, n - 1] = segments[s + 1]
        was_near = near
    return n


@njit(cache=True, error_model="numpy")
def _slab_ranges(planes, n_cells):
    """(x low, x high, z low, z high): per x cell, the least and greatest x of the atoms in
    ``planes`` (``_slot_layout``) in cells of that x cell; per z cell, the same of z
    (+inf, -inf where there is none)."""
    px, _, pz, _, plane_starts = planes
    nx, ny, nz = n_cells[0], n_cells[1], n_cells[2]
    x_low = np.full(nx, np.inf)
    x_high = np.full(nx, -np.inf)
    z_low = np.full(nz, np.inf)
    z_high = np.full(nz, -np.inf)
    for kz in range(nz):
        z_min, z_max = np.inf, -np.inf
        for kx in range(nx):
            row = (kz * nx + kx) * ny
            x_min, x_max = x_low[kx], x_high[kx]
            for k in range(plane_starts[row], plane_starts[row + ny]):
                x, z = px[k], pz[k]
                x_min = x if x < x_min else x_min
                x_max = x if x > x_max else x_max
                z_min = z if z < z_min else z_min
                z_max = z if z > z_max else z_max
            x_low[kx], x_high[kx] = x_min, x_max
        z_low[kz], z_high[kz] = z_min, z_max
    return x_low, x_high, z_low, z_high


@njit(cache=True, error_model="numpy")
def _owned_shifted_rows(owned_starts, n, n_cells, reach, periodic):
    """Per slot, whether its row may hold a pair with an image shift: an owned slot whose
    cell lies within ``reach`` cells of a periodic edge, either way along any axis (its
    ghost partners come from every side); a ghost slot's row is empty."""
    nx, ny, nz = n_cells[0], n_cells[1], n_cells[2]
    shifted = np.zeros(n, dtype=np.bool_)
    cell = 0
    for kx in range(nx):
        near_x = periodic[0] and (kx < reach or kx + reach >= nx)
        for ky in range(ny):
            near_xy = near_x or (periodic[1] and (ky < reach or ky + reach >= ny))
            for kz in range(nz):
                flag = near_xy or (periodic[2] and (kz < reach or kz + reach >= nz))
                for p in range(owned_starts[cell], owned_starts[cell + 1]):
                    shifted[p] = flag
                cell += 1
    return shifted


@njit(cache=True, error_model="numpy")
def _owned_brute_force_pairs(
    positions, n_owned, ids, lengths, inverse, tilt, r2_max, starts, neighbors
):
    """O(N^2) list of a rank over atom indices (minimum image): the owned atoms' rows, each
    with its later owned atoms and the ghosts (atoms from ``n_owned`` on) whose pair
    designates it (``designates`` on the global ``ids``); the ghosts' rows are empty.
    Returns the pair count (past ``len(neighbors)`` nothing more is written)."""
    n = positions.shape[0]
    capacity = neighbors.shape[0]
    count = 0
    starts[0] = 0
    for i in range(n_owned):
        xi = positions[i, 0]
        yi = positions[i, 1]
        zi = positions[i, 2]
        own_id = ids[i]
        for j in range(i + 1, n):
            if j >= n_owned and not designates(own_id, ids[j]):
                continue
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
    for i in range(n_owned, n):
        starts[i + 1] = count
    return count
