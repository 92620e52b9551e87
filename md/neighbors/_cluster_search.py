"""The search of the cluster-pair list, and the chunks of the list it makes.

A cluster pair is listed when one of its atom pairs lies within the list radius
(:func:`search_pairs`: per i cluster of the grid of :mod:`md.neighbors._cluster_grid`,
the neighbouring columns whose xy bounding box comes within reach of the column's and
the cluster's own, a window of j clusters in z in each, then each candidate checked
atom by atom with :mod:`md.neighbors._cluster_prune`'s check). LLVM IR here: the
windows' cursors step by block counts (:func:`_count_below`, :func:`_count_not_above`),
the two-list window check's loop (:func:`_keep_both`), the join's block moves
(:func:`_move_rows`) and the threads' claims of chunks (:func:`_claim`), each with a
Python twin. The pair kernels evaluate all 4 x 4 atom
pairs of each listed cluster pair, in SIMD lanes. The list's chunks for the threads:
:func:`balanced_chunks`, :func:`row_reach`, :func:`chunk_windows`.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import get_num_threads, njit, prange, types
from numba.core import cgutils
from numba.extending import intrinsic

from md._memory import KeptArrays
from md._simd import (
    ZMM,
    array_data,
    cluster_i_halves,
    cluster_j_less,
    load_vector,
    python_twin,
    splat,
    squared_distances,
    store_vector,
)
from md.neighbors._cluster_grid import CLUSTER
from md.neighbors._cluster_prune import keep_window


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
    kept=None,
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
    (:func:`_keep_both`, :func:`keep_window_both`'s check with each offset stored as one
    vector): the list :func:`prune_pairs` would make of it, pair for
    pair, with no pass of its own (0.93 of the CPU time of the search and that prune on
    the 32000-atom melt at radius 4.0 and 2.8, one thread); then returned after the kept
    pairs, as (starts, partners, offsets) too. With ``with_reach``, last also per i
    cluster a bound on one past its row's last partner (as :func:`row_reach`, from the
    search's windows: no pass over the pairs), which holds for the pruned rows too.

    The columns are searched in ``chunks`` runs of about equal work
    (:func:`_column_chunks`) on the threads (each thread claims the next chunk not yet
    claimed: :func:`_search_chunks`), each into its own part of one buffer, then
    each part but the first moved down to follow the one before, a block per array
    (:func:`_joined`); each i
    cluster's row is written as its windows are found (:func:`_search_columns`).

    With ``kept`` (:class:`md._memory.KeptArrays`) the buffers, and so the
    lists returned (views of them), are the arrays kept there: valid until the next search
    with the same ``kept``, which writes them again (no fresh pages at each search).
    """
    if kept is None:
        kept = KeptArrays()
    n_clusters = lower.shape[0]
    # each chunk's rows get per_cluster pairs of room per cluster, and 64 (_search_lists)
    room = per_cluster * n_clusters + 64 * chunks
    room_inner = room if inner2 is not None else 0
    buffers = (
        kept.take("search partners", room, np.int32),
        kept.take("search offsets", room, np.float32, (3,)),
        kept.take("search counts", n_clusters, np.int64),
        kept.take("search reach", n_clusters, np.int64),
        kept.take("search starts", n_clusters + 1, np.int64),
        kept.take("search inner partners", room_inner, np.int32),
        kept.take("search inner offsets", room_inner, np.float32, (3,)),
        kept.take("search inner counts", n_clusters, np.int64),
        kept.take("search inner starts", n_clusters + 1, np.int64),
    )
    found = _search_lists(
        box,
        ncx,
        ncy,
        first,
        lower,
        upper,
        radius,
        chunks,
        min(chunks, get_num_threads()),
        per_cluster,
        xi,
        xj,
        reach2,
        np.float32(-1.0 if inner2 is None else inner2),
        buffers,
    )
    if found is None:
        return None
    lists = found[:-1] if inner2 is not None else found[:3]
    return lists + found[-1:] if with_reach else lists


@njit(cache=True, error_model="numpy")
def _search_lists(
    box,
    ncx,
    ncy,
    first,
    lower,
    upper,
    radius,
    chunks,
    workers,
    per_cluster,
    xi,
    xj,
    reach2,
    inner2,
    buffers,
):
    """:func:`search_pairs`, the pruned rows always returned (none where ``inner2`` < 0),
    the chunks claimed by ``workers`` threads, into ``buffers`` (part partners and
    offsets, per_cluster * clusters + 64 * chunks pairs of room; counts, reach and
    starts per cluster; the same for the pruned rows, their parts' room none where
    ``inner2`` < 0: they are never longer than the kept ones)."""
    part_partners, part_offsets, counts, reach, starts = buffers[:5]
    inner_partners, inner_offsets, inner_counts, inner_starts = buffers[5:]
    column_bounds = _column_chunks(box, ncx, ncy, first, radius, chunks)
    # chunk t writes its rows from place[t] of one buffer (room[t] pairs), then each chunk
    # but the first is moved down to where its rows begin in the list (_joined)
    place = np.zeros(chunks + 1, np.int64)
    for t in range(chunks):
        room = per_cluster * (first[column_bounds[t + 1]] - first[column_bounds[t]]) + 64
        place[t + 1] = place[t] + room
    counts[:] = 0
    inner_counts[:] = 0
    used = np.zeros(chunks, np.int64)
    parts = (part_partners, part_offsets, counts, reach, used)
    inner = (inner_partners, inner_offsets, inner_counts, inner2)
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
        workers,
    )
    if used.min() < 0:
        return None
    listed = _joined(counts, first, column_bounds, used, place, part_partners, part_offsets, starts)
    inner_used = np.zeros(chunks, np.int64)
    for t in range(chunks):
        for ci in range(first[column_bounds[t]], first[column_bounds[t + 1]]):
            inner_used[t] += inner_counts[ci]
    pruned = _joined(
        inner_counts,
        first,
        column_bounds,
        inner_used,
        place,
        inner_partners,
        inner_offsets,
        inner_starts,
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
    bounds = np.zeros(chunks + 1, np.int64)
    bounds[chunks] = n_columns
    if chunks == 1:
        return bounds  # (no work to weigh: 25 us of the melt's 1-thread search)
    reach_x = int(np.ceil(radius / (box[0] / ncx)))
    reach_y = int(np.ceil(radius / (box[1] / ncy)))
    work = np.zeros(n_columns + 1)
    for c in range(n_columns):
        f0, f1 = first[c], first[c + 1]
        searched = 0
        if f1 > f0:  # (an empty column's work is none: no division or sweep for it)
            cx, cy = c // ncy, c % ncy
            for dx in range(-reach_x, reach_x + 1):
                ux = _periodic_column(cx + dx, ncx, 0.0)[0]
                for dy in range(-reach_y, reach_y + 1):
                    col = ux * ncy + _periodic_column(cy + dy, ncy, 0.0)[0]
                    if first[col + 1] > f0:  # as the search skips a column before c's
                        searched += first[col + 1] - first[col]
        work[c + 1] = work[c] + (f1 - f0) * searched
    c = 0
    for t in range(1, chunks):
        while c < n_columns and work[c] < t * work[n_columns] / chunks:
            c += 1
        bounds[t] = c
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
    workers,
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
            column_bounds[0],  # 0, as an int64: a literal 0 compiled a second copy
            column_bounds[1],
            counts,
            reach,
            part_partners,
            part_offsets,
            place[0],
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
            workers,
            np.zeros(1, np.int64),
        )


@njit(cache=True, error_model="numpy")
def _joined(counts, first, column_bounds, used, place, part_partners, part_offsets, starts):
    """(starts, partners, offsets) of the rows of ``counts`` pairs each (``starts``
    written: clusters + 1), written per chunk
    into ``part_partners``/``part_offsets`` (chunk t's ``used[t]`` pairs from
    ``place[t]``): the first chunk's where they are, each later one moved down to follow
    the one before, in order (a move never overwrites pairs not yet moved), each array's
    part as one block (:func:`_move_rows`: a ``memmove``), on the calling thread. The
    lists are the buffers' first pairs, not a fresh copy of every chunk's (with the whole
    buffers passed to each chunk, see :func:`_search_columns`, two chunks' work on one
    thread went from 1.16 to 1.09 of one chunk's search on the 32000-atom melt, CPU time,
    interleaved). The pair-by-pair moves this replaced (a loop per pair's partner and
    offsets, threaded where the places did not overlap: two more threaded regions) took
    0.53 ms for the second of two chunks' parts there (both lists, 1 thread, the fastest
    of 25 calls); the blocks take 0.21, row starts included, and no threads: at 2
    threads the threaded loops took 0.36 + 0.17 at best, no faster than one."""
    n_clusters = counts.shape[0]
    chunks = used.shape[0]
    starts[0] = 0
    for ci in range(n_clusters):
        starts[ci + 1] = starts[ci] + counts[ci]
    for t in range(1, chunks):
        source, target, count = place[t], starts[first[column_bounds[t]]], used[t]
        if count > 0 and target != source:
            _move_rows(part_partners, source, target, count)
            _move_rows(part_offsets, source, target, count)
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
    workers,
    claimed,
):
    """:func:`_search_columns` for each chunk of columns, chunk t into places ``place[t]``
    to ``place[t + 1]`` of the buffers, on ``workers`` threads (at most numba's), each
    claiming the next chunk not yet claimed (:func:`_claim`) until none is left. Where
    a thread starts late (a core busy with other work), the others take its chunks:
    the chunks are not dealt out in advance. Each chunk writes its own places, so the
    lists do not depend on which thread searched which chunk. ``claimed``: one int64,
    0, the counter (the caller's: numba does not know that a claim writes it, and a
    counter made in a threaded function read 0 after its loop in a test)."""
    n_parts = column_bounds.shape[0] - 1
    for _ in prange(workers):
        while True:
            t = _claim(claimed)
            if t >= n_parts:
                break
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


def _claim_twin(counter):
    """:func:`_claim` in Python (under ``NUMBA_DISABLE_JIT=1``, and its test)."""
    value = int(counter[0])
    counter[0] += 1
    return value


@python_twin(_claim_twin)
@intrinsic
def _claim(typingctx, counter):
    """``counter[0]`` (int64) raised by one in one atomic step; returns the value before:
    each thread that calls it on the same counter gets a number of its own."""
    if not isinstance(counter, types.Array) or counter.dtype != types.int64:
        raise TypeError(f"_claim: an int64 array, got {counter}")
    sig = types.int64(counter)

    def codegen(context, builder, signature, args):
        pointer = array_data(context, builder, signature.args[0], args[0])
        return builder.atomic_rmw("add", pointer, ir.Constant(_I64, 1), "monotonic")

    return sig, codegen


def _move_rows_twin(array, source, target, count):
    """:func:`_move_rows` in numpy (under ``NUMBA_DISABLE_JIT=1``, and its test)."""
    array[target : target + count] = array[source : source + count].copy()


@python_twin(_move_rows_twin)
@intrinsic
def _move_rows(typingctx, array, source, target, count):
    """Rows ``source`` to ``source + count`` of the C-contiguous ``array`` moved to
    ``target`` on: one ``memmove`` of their bytes (the two ranges may overlap)."""
    if not isinstance(array, types.Array) or array.layout != "C":
        raise TypeError(f"_move_rows: a C-contiguous array, got {array}")
    sig = types.void(array, source, target, count)

    def codegen(context, builder, signature, args):
        arg = signature.args
        rows = context.make_array(arg[0])(context, builder, args[0])
        source_v, target_v, count_v = (
            context.cast(builder, args[n], arg[n], types.int64) for n in (1, 2, 3)
        )
        row_bytes = builder.extract_value(rows.strides, 0)
        data = builder.bitcast(rows.data, cgutils.voidptr_t)
        begin = builder.gep(data, [builder.mul(source_v, row_bytes)])
        to = builder.gep(data, [builder.mul(target_v, row_bytes)])
        cgutils.raw_memmove(builder, to, begin, count_v, row_bytes)
        return context.get_dummy_value()

    return sig, codegen


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


#: The z bounds a window cursor compares in one step (a vector of float64: one 512-bit
#: register with AVX-512). A cursor moves by 0-2 clusters from one i cluster to the next
#: on the 32000-atom melt, so one step almost always finds its place: the branch that
#: ended the plain loop, mispredicted at about every window, is gone (the search 0.90-0.92
#: of its time, one thread; blocks of 4 and 16 took 0.95 and 0.97).
_BLOCK = 8
_I64 = ir.IntType(64)


def _count_twin(bounds, start, room, limit, strict):
    """:func:`_count_below` (``strict``) or :func:`_count_not_above` in numpy."""
    block = bounds[start : start + _BLOCK]
    below = block < limit if strict else block <= limit
    return int((below & (np.arange(_BLOCK) < room)).sum())


def _count_codegen(strict):
    """The IR of a block count: ``_BLOCK`` bounds from ``start`` compared with ``limit``,
    the lanes from ``room`` on masked off, the set lanes counted."""

    def codegen(context, builder, signature, args):
        arg = signature.args
        data = array_data(context, builder, arg[0], args[0])
        start, room = (context.cast(builder, args[n], arg[n], types.int64) for n in (1, 2))
        limit = context.cast(builder, args[3], arg[3], types.float64)
        vector = ir.VectorType(ir.DoubleType(), _BLOCK)
        words = ir.VectorType(_I64, _BLOCK)
        values = load_vector(builder, data, start, vector)
        below = builder.fcmp_ordered("<" if strict else "<=", values, splat(builder, limit, vector))
        lanes = ir.Constant(words, list(range(_BLOCK)))
        inside = builder.icmp_signed("<", lanes, splat(builder, room, words))
        bits = builder.bitcast(builder.and_(below, inside), ir.IntType(_BLOCK))
        count = builder.module.declare_intrinsic("llvm.ctpop", [ir.IntType(_BLOCK)])
        return builder.zext(builder.call(count, [bits]), _I64)

    return codegen


def _count_below_twin(bounds, start, room, limit):
    """:func:`_count_below` in numpy (under ``NUMBA_DISABLE_JIT=1``, and its test)."""
    return _count_twin(bounds, start, room, limit, True)


@python_twin(_count_below_twin)
@intrinsic
def _count_below(typingctx, bounds, start, room, limit):
    """How many of the ``_BLOCK`` float64 ``bounds`` from ``start`` that lie before
    ``start + room`` are below ``limit``: one vector compare and a population count, no
    branch. ``bounds`` must hold ``start + _BLOCK`` values (those past ``room`` are
    read and not counted)."""
    return types.int64(bounds, start, room, limit), _count_codegen(True)


def _count_not_above_twin(bounds, start, room, limit):
    """:func:`_count_not_above` in numpy (under ``NUMBA_DISABLE_JIT=1``, and its test)."""
    return _count_twin(bounds, start, room, limit, False)


@python_twin(_count_not_above_twin)
@intrinsic
def _count_not_above(typingctx, bounds, start, room, limit):
    """:func:`_count_below` with ``<=``: how many of the block are at most ``limit``."""
    return types.int64(bounds, start, room, limit), _count_codegen(False)


#: The lanes of the atom check's vectors: the cluster kernel's (md._simd.ZMM).
_LANES = 16 if ZMM else 8
_F32 = ir.FloatType()


def _keep_both_twin(
    xi, xj, ci, lo, hi, px, py, pz, centres, reach2, inner2, partners, offsets, k, near, nearo, m
):
    """:func:`_keep_both` in numpy (under ``NUMBA_DISABLE_JIT=1``, and its test)."""
    own = xi[ci * 3 * CLUSTER : (ci + 1) * 3 * CLUSTER].reshape(3, CLUSTER)
    for j in range(lo, hi):
        o = (np.array([px, py, pz]) - centres[j, :3]).astype(np.float32)
        other = xj[j * 3 * CLUSTER : (j + 1) * 3 * CLUSTER].reshape(3, CLUSTER)
        d = own[:, :, None] - (other - o[:, None])[:, None, :]
        r2 = (d * d).sum(axis=0)
        partners[k] = near[m] = j
        offsets[k] = nearo[m] = o
        k += bool((r2 < reach2).any())
        m += bool((r2 < inner2).any())
    return k, m


@python_twin(_keep_both_twin)
@intrinsic
def _keep_both(
    typingctx,
    xi,
    xj,
    ci,
    lo,
    hi,
    px,
    py,
    pz,
    centres,
    reach2,
    inner2,
    partners,
    offsets,
    k,
    near_partners,
    near_offsets,
    m,
):
    """The search's window of candidates ``lo`` to ``hi`` (j clusters) of i cluster ``ci``,
    each written to the outer list (``partners``/``offsets`` from ``k`` on) and the inner
    one (``near_partners``/``near_offsets`` from ``m`` on) with its offset ``(px, py, pz)
    - centres[j]`` (double, then float32), and kept in each (the next one written after
    it) where an atom pair is closer than sqrt(``reach2``), sqrt(``inner2``): the check of
    :func:`md.neighbors._cluster_prune.keep_window_both`, pair for pair, with the centres
    as rows of four (``centres``, (clusters, 4) float64, the fourth 0) so that an offset is
    one vector subtraction, one conversion and one 16-byte store per list (the fourth
    float lands on the next slot's first, which the next pair or row overwrites: the
    caller leaves a slot spare at the end of its room). Returns (outer end, inner end)."""
    for array in (offsets, near_offsets):
        if array.dtype != types.float32 or array.ndim != 2 or array.layout != "C":
            raise TypeError(f"_keep_both: C-contiguous (pairs, 3) float32 offsets, got {array}")
    if centres.dtype != types.float64 or centres.layout != "C":
        raise TypeError(f"_keep_both: C-contiguous (clusters, 4) float64 centres, got {centres}")
    arguments = (xi, xj, ci, lo, hi, px, py, pz, centres, reach2, inner2)
    arguments += (partners, offsets, k, near_partners, near_offsets, m)
    sig = types.UniTuple(types.int64, 2)(*arguments)

    def codegen(context, builder, signature, args):
        arg = signature.args
        xi_p, xj_p, centres_p = (array_data(context, builder, arg[n], args[n]) for n in (0, 1, 8))
        ci_v, lo_v, hi_v, k_v, m_v = (
            context.cast(builder, args[n], arg[n], types.int64) for n in (2, 3, 4, 13, 16)
        )
        quad = ir.VectorType(ir.DoubleType(), 4)
        shift = ir.Constant(quad, [0.0] * 4)
        for d, n in enumerate((5, 6, 7)):
            value = context.cast(builder, args[n], arg[n], types.float64)
            shift = builder.insert_element(shift, value, ir.Constant(ir.IntType(32), d))
        outputs = [
            (
                (arg[p], context.make_array(arg[p])(context, builder, args[p])),
                array_data(context, builder, arg[p + 1], args[p + 1]),
            )
            for p in (11, 14)
        ]
        ends = [cgutils.alloca_once_value(builder, v) for v in (k_v, m_v)]
        size = ir.Constant(_I64, 3 * CLUSTER)
        halves = cluster_i_halves(builder, xi_p, builder.mul(ci_v, size), _LANES)
        lanes = ir.VectorType(_F32, _LANES)
        radii = [splat(builder, args[n], lanes) for n in (9, 10)]
        with cgutils.for_range_slice(builder, lo_v, hi_v, ir.Constant(_I64, 1)) as (j, _):
            places = [builder.load(end) for end in ends]
            centre = load_vector(builder, centres_p, builder.mul(j, ir.Constant(_I64, 4)), quad)
            offset4 = builder.fptrunc(builder.fsub(shift, centre), ir.VectorType(_F32, 4))
            for ((part_type, part_a), off_p), to in zip(outputs, places, strict=True):
                store_vector(builder, offset4, off_p, builder.mul(to, ir.Constant(_I64, 3)))
                slot = cgutils.get_item_pointer(context, builder, part_type, part_a, [to])
                builder.store(builder.trunc(j, ir.IntType(32)), slot)
            offset = [
                builder.extract_element(offset4, ir.Constant(ir.IntType(32), d)) for d in range(3)
            ]
            shifted = cluster_j_less(builder, xj_p, builder.mul(j, size), offset, lanes=_LANES)
            within = [None, None]
            for half in halves:
                _, r2 = squared_distances(builder, half, shifted)
                for q, radius in enumerate(radii):
                    close = builder.fcmp_ordered("<", r2, radius)
                    within[q] = close if within[q] is None else builder.or_(within[q], close)
            bits = ir.IntType(_LANES)
            for end, to, close in zip(ends, places, within, strict=True):
                kept = builder.icmp_unsigned(
                    "!=", builder.bitcast(close, bits), ir.Constant(bits, 0)
                )
                builder.store(builder.add(to, builder.zext(kept, _I64)), end)
        values = [builder.load(end) for end in ends]
        return context.make_tuple(builder, signature.return_type, values)

    return sig, codegen


@njit(cache=True, inline="always", error_model="numpy")
def _first_not_below(top, begin, stop, low):
    """The first cluster from ``begin`` (before ``stop``) whose top is not below
    ``low``, else ``stop``; ``top`` rises from ``begin`` to ``stop``, so the clusters
    below ``low`` are the first ones, and a block that counts fewer than ``_BLOCK`` of
    them has found the place."""
    while True:
        step = _count_below(top, begin, stop - begin, low)
        begin += step
        if step < _BLOCK:
            return begin


@njit(cache=True, inline="always", error_model="numpy")
def _first_above(bottom, end, stop, high):
    """The first cluster from ``end`` (before ``stop``) whose bottom is above ``high``,
    else ``stop`` (as :func:`_first_not_below`)."""
    while True:
        step = _count_not_above(bottom, end, stop - end, high)
        end += step
        if step < _BLOCK:
            return end


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
    them where they are, and the next one moves them on), each moved by counting the
    bounds below its limit in blocks of ``_BLOCK`` (:func:`_first_not_below`,
    :func:`_first_above`): no branch per cluster passed.
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
    # the clusters' centres (the partners'), also as one row of four per cluster, and
    # their z bounds, each contiguous for the cursors, with a block's worth past the
    # last cluster (+inf: counted by no cursor) so that a block never reads past them;
    # in one loop (numba's array expressions, each a temporary: 30 us of each chunk's
    # search on the 32000-atom melt)
    n_clusters = lower.shape[0]
    all_x = np.empty(n_clusters)
    all_y = np.empty(n_clusters)
    all_z = np.empty(n_clusters)
    centres = np.empty((n_clusters, 4))
    bottom = np.full(n_clusters + _BLOCK, np.inf)
    top = np.full(n_clusters + _BLOCK, np.inf)
    for cl in range(n_clusters):
        x = 0.5 * (lower[cl, 0] + upper[cl, 0])
        y = 0.5 * (lower[cl, 1] + upper[cl, 1])
        z = 0.5 * (lower[cl, 2] + upper[cl, 2])
        all_x[cl], all_y[cl], all_z[cl] = x, y, z
        centres[cl, 0], centres[cl, 1], centres[cl, 2], centres[cl, 3] = x, y, z, 0.0
        bottom[cl], top[cl] = lower[cl, 2], upper[cl, 2]
    r2max = radius * radius
    capacity = place1 - 1  # a pair's offset is stored as four floats: one slot spare
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
                    begin = _first_not_below(top, begins[w, dz + 1], g1, low)
                    end = _first_above(bottom, max(ends[w, dz + 1], begin), g1, high)
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
                        k, k_inner = _keep_both(
                            xi,
                            xj,
                            ci,
                            lo,
                            end,
                            px,
                            py,
                            pz,
                            centres,
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
