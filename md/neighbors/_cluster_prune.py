"""The cluster-pair list's atom-pair check: relative positions, the check in IR, the prune.

:func:`cluster_positions` writes each slot's position relative to its origin (see
:mod:`md.neighbors._cluster_grid`) in float32, in the cluster kernels' layout. A
cluster pair is kept where one of its atom pairs lies within reach: the check
(:func:`_near_pair`, one pair) is LLVM vector IR in the kernels' lanes, built from
:mod:`md._simd`'s blocks, and runs inside two loops written in IR as well: the
search's window of candidates (:func:`keep_window`, called by
:mod:`md.neighbors._cluster_search`; :func:`keep_window_both`, the two-list form, which the
search no longer calls: its own ``_keep_both`` stores each offset in one 16-byte store and
is tested against this one) and the prune's row (:func:`_mark_near`, in
:func:`prune_pairs`: GROMACS's dynamic pruning of an outer list to an inner one, which
marks each pair, then copies the marked ones to their places: :func:`_compress_kept`,
AVX-512's compress in IR where the CPU has it). Each intrinsic has a Python twin for
``NUMBA_DISABLE_JIT=1``.

The search's cached kernels hold their own copies of :func:`keep_window`; an edit here
makes those entries stale (the kernel cache stamps each entry with the modules its file
imports: ``md._kernel_cache``), so the search compiles afresh with the new helpers.
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
    load_vector,
    python_twin,
    splat,
    squared_distances,
    store_vector,
)
from md.neighbors._cluster_grid import CLUSTER, FILLER


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
_BYTE = ir.IntType(8)
# the compaction's (_compress_kept): 16 marks, 16 lanes of words and of bits
_BYTE16 = ir.VectorType(_BYTE, 16)
_WORDS = ir.IntType(32)
_WORD16 = ir.VectorType(_WORDS, 16)
_BIT16 = ir.VectorType(ir.IntType(1), 16)
_MASK16 = ir.IntType(16)


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
    marks,
):
    """Keep the pairs of the cluster list (``starts``, ``partners``, ``offsets``) that
    have an atom pair closer than sqrt(``reach2``) at the relative positions ``xi``/``xj``
    (GROMACS's dynamic pruning of an outer list to an inner one), each row in its
    order, the cluster itself still first: their row offsets into ``kept_starts`` and
    the pairs into ``kept_partners``/``kept_offsets`` (other arrays than the list's, as
    long as it). ``marks``: uint8 scratch, as long as the list (each pair's verdict).
    Returns the pairs kept.

    Two passes over the chunks ``bounds`` (i cluster ranges), each on the threads: the
    check marks each pair (:func:`_mark_near`: a row at a time in IR, the i cluster's
    vectors loaded once per row, one byte stored per pair and no store that waits on
    the verdict before it) and counts each row's kept pairs; then, from the chunks'
    totals, each chunk turns its rows' counts into offsets and copies its kept pairs
    straight to their places (:func:`_copy_kept`: with AVX-512, 16 pairs at a time by
    ``vpcompressd``). Nothing is written past a chunk's kept pairs and nothing is moved
    after (a chunk's kept pairs used to be written from where its rows begin in the
    list, then moved down: 0.10-0.15 of the prune's work on two chunks). On the
    32000-atom melt, 1 thread, 0.71 of the time of the one pass that copied each pair
    as it was checked, the next written after it only where kept (benchmarks/README.md)."""
    n_clusters = starts.shape[0] - 1
    chunks = bounds.shape[0] - 1
    totals = np.zeros(chunks + 1, np.int64)  # totals[t + 1]: chunk t's kept pairs
    if chunks == 1:
        totals[1] = _mark_rows(
            starts, partners, offsets, 0, n_clusters, xi, xj, reach2, marks, kept_starts
        )
    else:
        _mark_chunks(starts, partners, offsets, bounds, xi, xj, reach2, marks, kept_starts, totals)
    for t in range(chunks):
        totals[t + 1] += totals[t]
    kept_starts[0] = 0
    if chunks == 1:
        _copy_rows(
            starts,
            partners,
            offsets,
            0,
            n_clusters,
            marks,
            0,
            kept_starts,
            kept_partners,
            kept_offsets,
        )
    else:
        _copy_chunks(
            starts,
            partners,
            offsets,
            bounds,
            marks,
            totals,
            kept_starts,
            kept_partners,
            kept_offsets,
        )
    return totals[chunks]


@njit(cache=True, parallel=True, error_model="numpy")
def _mark_chunks(starts, partners, offsets, bounds, xi, xj, reach2, marks, kept_starts, totals):
    """:func:`_mark_rows` for each chunk of i clusters, on the threads; chunk t's total
    into ``totals[t + 1]``."""
    for t in prange(bounds.shape[0] - 1):
        totals[t + 1] = _mark_rows(
            starts, partners, offsets, bounds[t], bounds[t + 1], xi, xj, reach2, marks, kept_starts
        )


@njit(cache=True, error_model="numpy")
def _mark_rows(starts, partners, offsets, c0, c1, xi, xj, reach2, marks, kept_starts):
    """Mark the pairs of i clusters ``c0`` to ``c1`` (``marks``: 1 kept, 0 dropped), each
    row's count into ``kept_starts[ci + 1]``; returns their sum."""
    total = 0
    for ci in range(c0, c1):
        count = _mark_near(xi, xj, partners, offsets, starts[ci], starts[ci + 1], ci, reach2, marks)
        kept_starts[ci + 1] = count
        total += count
    return total


@njit(cache=True, parallel=True, error_model="numpy")
def _copy_chunks(
    starts, partners, offsets, bounds, marks, totals, kept_starts, kept_partners, kept_offsets
):
    """:func:`_copy_rows` for each chunk of i clusters, on the threads, chunk t's kept
    pairs from ``totals[t]`` on (the places of the chunks' pairs do not overlap)."""
    for t in prange(bounds.shape[0] - 1):
        _copy_rows(
            starts,
            partners,
            offsets,
            bounds[t],
            bounds[t + 1],
            marks,
            totals[t],
            kept_starts,
            kept_partners,
            kept_offsets,
        )


@njit(cache=True, error_model="numpy")
def _copy_rows(
    starts, partners, offsets, c0, c1, marks, k, kept_starts, kept_partners, kept_offsets
):
    """The rows of i clusters ``c0`` to ``c1``, marked by :func:`_mark_rows`: their counts
    in ``kept_starts[c0 + 1:c1 + 1]`` made offsets from ``k`` on, and their marked pairs
    copied to ``kept_partners``/``kept_offsets`` from ``k`` on, in order."""
    end = k
    for ci in range(c0, c1):
        end += kept_starts[ci + 1]
        kept_starts[ci + 1] = end
    _copy_kept(
        partners, offsets, marks, starts[c0], starts[c1], kept_partners, kept_offsets, k, end
    )


@njit(cache=True, error_model="numpy")
def _copy_kept(partners, offsets, marks, lo, hi, kept_partners, kept_offsets, k, end):
    """Pairs ``lo`` to ``hi`` marked kept copied to ``kept_partners``/``kept_offsets``
    from ``k`` on, in order; ``end``: ``k`` plus their count (nothing is written from
    there on). :func:`_compress_kept` takes whole groups of 16 while they fit (none
    without AVX-512); then pair by pair, each written at ``k`` and ``k`` advanced by its
    mark (no branch on the verdict), up to the last kept one."""
    q, k = _compress_kept(partners, offsets, marks, lo, hi, kept_partners, kept_offsets, k, end)
    while q < hi and k < end:
        kept_partners[k] = partners[q]
        for d in range(3):
            kept_offsets[k, d] = offsets[q, d]
        k += np.int64(marks[q])  # (an int64 under NUMBA_DISABLE_JIT too)
        q += 1


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


def _mark_near_twin(xi, xj, partners, offsets, start, end, ci, reach2, marks):
    """:func:`_mark_near` in Python (under ``NUMBA_DISABLE_JIT=1``, and its test)."""
    if start == end:
        return 0
    marks[start] = 1  # the cluster with itself: kept
    for q in range(start + 1, end):
        marks[q] = _near_pair_twin(xi, xj, ci, partners[q], *offsets[q], reach2)
    return int(marks[start:end].sum())


@python_twin(_mark_near_twin)
@intrinsic
def _mark_near(typingctx, xi, xj, partners, offsets, start, end, ci, reach2, marks):
    """Mark i cluster ``ci``'s pairs ``start`` to ``end``: ``marks[q]`` 1 where pair q has
    an atom pair within reach (:func:`_near_pair`'s check; the first, the cluster with
    itself, always), else 0; returns how many are marked.

    The row's loop is written here, not in numba, so that the i cluster's vectors are
    loaded once per row (numba's loop reloaded and re-shuffled them for every pair: the
    bytes it stores might be the float32 positions, as far as LLVM knows). A pair's
    verdict feeds only its own byte and the count, so the checks of successive pairs
    overlap; the copy that follows (:func:`_copy_kept`) reads the marks."""
    if marks.dtype != types.uint8:
        raise TypeError(f"_mark_near: uint8 marks, got {marks}")
    sig = types.int64(xi, xj, partners, offsets, start, end, ci, reach2, marks)

    def codegen(context, builder, signature, args):
        arg = signature.args
        xi_p, xj_p = (array_data(context, builder, arg[n], args[n]) for n in range(2))
        arrays = {
            n: (arg[n], context.make_array(arg[n])(context, builder, args[n])) for n in (2, 3, 8)
        }
        start_v, end_v, ci_v = (
            context.cast(builder, args[n], arg[n], types.int64) for n in (4, 5, 6)
        )
        count = cgutils.alloca_once_value(builder, ir.Constant(_I64, 0))

        def at(n, *index):
            return cgutils.get_item_pointer(context, builder, *arrays[n], list(index))

        with builder.if_then(builder.icmp_signed("<", start_v, end_v)):
            builder.store(ir.Constant(_BYTE, 1), at(8, start_v))  # the cluster with itself
            builder.store(ir.Constant(_I64, 1), count)
            size = ir.Constant(_I64, 3 * CLUSTER)
            halves = cluster_i_halves(builder, xi_p, builder.mul(ci_v, size), _LANES)
            reach = splat(builder, args[7], _VECTOR)
            first = builder.add(start_v, ir.Constant(_I64, 1))
            with cgutils.for_range_slice(builder, first, end_v, ir.Constant(_I64, 1)) as (q, _):
                offset = [builder.load(at(3, q, ir.Constant(_I64, d))) for d in range(3)]
                cj = builder.sext(builder.load(at(2, q)), _I64)
                shifted = cluster_j_less(builder, xj_p, builder.mul(cj, size), offset, lanes=_LANES)
                near = _any_near(builder, halves, shifted, reach)
                builder.store(builder.zext(near, _BYTE), at(8, q))
                builder.store(builder.add(builder.load(count), builder.zext(near, _I64)), count)
        return builder.load(count)

    return sig, codegen


#: Pairs per group of :func:`_compress_kept` (16 int32 partners in one zmm).
_GROUP = 16


def _compress_kept_twin(partners, offsets, marks, lo, hi, kept_partners, kept_offsets, k, end):
    """:func:`_compress_kept` in Python (under ``NUMBA_DISABLE_JIT=1``, and its test):
    the same groups where the intrinsic has AVX-512 (``ZMM``), none elsewhere."""
    while ZMM and lo + _GROUP <= hi and k + _GROUP <= end:
        kept = np.flatnonzero(marks[lo : lo + _GROUP]) + lo
        kept_partners[k : k + len(kept)] = partners[kept]
        kept_offsets[k : k + len(kept)] = offsets[kept]
        lo, k = lo + _GROUP, k + len(kept)
    return lo, k


@python_twin(_compress_kept_twin)
@intrinsic
def _compress_kept(
    typingctx, partners, offsets, marks, lo, hi, kept_partners, kept_offsets, k, end
):
    """Of pairs ``lo`` on, in groups of 16 while a whole group lies before ``hi`` and 16
    places before ``end``: each group's pairs marked kept (``marks``) copied to
    ``kept_partners``/``kept_offsets`` from ``k`` on, in order (other arrays than
    ``partners``/``offsets``); returns (the first pair not taken, the next place).
    Where the CPU has AVX-512 (``ZMM``), a group's 16 partners and 48 offset words are
    four zmm loads, four ``vpcompressd`` (register form, the kept lanes moved to the
    front) and four whole 64-byte stores, each at the end of the one before: the lanes
    past the kept ones land on places that later stores write again, and none at or past
    ``end``. Elsewhere it takes no group (the caller's loop copies every pair); no
    compress is emitted for that loop by LLVM itself (numba 0.68, LLVM 22)."""
    c_1d = (partners, marks, kept_partners)
    if not all(
        isinstance(a, types.Array) and a.layout == "C" for a in (*c_1d, offsets, kept_offsets)
    ):
        raise TypeError("_compress_kept: C-contiguous arrays")
    if (
        partners.dtype != types.int32
        or kept_partners.dtype != types.int32
        or offsets.dtype != types.float32
        or kept_offsets.dtype != types.float32
        or marks.dtype != types.uint8
    ):
        raise TypeError(
            f"_compress_kept: int32 partners, float32 offsets and uint8 marks, got {partners}, "
            f"{offsets}, {marks}, {kept_partners}, {kept_offsets}"
        )
    arguments = (partners, offsets, marks, lo, hi, kept_partners, kept_offsets, k, end)
    sig = types.UniTuple(types.int64, 2)(*arguments)

    def codegen(context, builder, signature, args):
        arg = signature.args
        lo_v, hi_v, k_v, end_v = (
            context.cast(builder, args[n], arg[n], types.int64) for n in (3, 4, 7, 8)
        )
        if not ZMM:
            return context.make_tuple(builder, signature.return_type, [lo_v, k_v])
        words = _WORDS.as_pointer()
        source_p, source_o, target_p, target_o = (
            builder.bitcast(array_data(context, builder, arg[n], args[n]), words)
            for n in (0, 1, 5, 6)
        )
        marks_p = array_data(context, builder, arg[2], args[2])
        compress = cgutils.get_or_insert_function(
            builder.module,
            ir.FunctionType(_WORD16, [_WORD16, _WORD16, _BIT16]),
            "llvm.x86.avx512.mask.compress.v16i32",
        )
        popcount = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(_MASK16, [_MASK16]), "llvm.ctpop.i16"
        )
        lo_at = cgutils.alloca_once_value(builder, lo_v)
        k_at = cgutils.alloca_once_value(builder, k_v)
        zero = ir.Constant(_WORD16, None)
        group = ir.Constant(_I64, _GROUP)
        check = builder.append_basic_block("compress.check")
        body = builder.append_basic_block("compress.group")
        done = builder.append_basic_block("compress.done")
        builder.branch(check)
        builder.position_at_end(check)
        q, to = builder.load(lo_at), builder.load(k_at)
        fits = builder.and_(
            builder.icmp_signed("<=", builder.add(q, group), hi_v),
            builder.icmp_signed("<=", builder.add(to, group), end_v),
        )
        builder.cbranch(fits, body, done)
        builder.position_at_end(body)
        kept = builder.icmp_unsigned(
            "!=", load_vector(builder, marks_p, q, _BYTE16), ir.Constant(_BYTE16, None)
        )

        def move(source, target, at, to, mask):
            value = load_vector(builder, source, at, _WORD16)
            store_vector(builder, builder.call(compress, [value, zero, mask]), target, to)
            return builder.zext(builder.call(popcount, [builder.bitcast(mask, _MASK16)]), _I64)

        n_kept = move(source_p, target_p, q, to, kept)
        # the offsets: 48 words, 3 a pair; word w of a group belongs to pair w // 3
        at, to3 = builder.mul(q, ir.Constant(_I64, 3)), builder.mul(to, ir.Constant(_I64, 3))
        for w in range(3):
            lanes = ir.Constant(_WORD16, [(_GROUP * w + lane) // 3 for lane in range(_GROUP)])
            mask = builder.shuffle_vector(kept, kept, lanes)
            source_at = builder.add(at, ir.Constant(_I64, _GROUP * w))
            to3 = builder.add(to3, move(source_o, target_o, source_at, to3, mask))
        builder.store(builder.add(q, group), lo_at)
        builder.store(builder.add(to, n_kept), k_at)
        builder.branch(check)
        builder.position_at_end(done)
        values = [builder.load(lo_at), builder.load(k_at)]
        return context.make_tuple(builder, signature.return_type, values)

    return sig, codegen
