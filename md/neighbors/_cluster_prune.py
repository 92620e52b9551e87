"""The cluster-pair list's atom-pair check: relative positions, the check in IR, the prune.

:func:`cluster_positions` writes each slot's position relative to its origin (see
:mod:`md.neighbors._cluster_grid`) in float32, in the cluster kernels' layout. A
cluster pair is kept where one of its atom pairs lies within reach: the check
(:func:`_near_pair`, one pair) is LLVM vector IR in the kernels' lanes, built from
:mod:`md._simd`'s blocks, and runs inside two loops written in IR as well: the
search's window of candidates (:func:`keep_window`, :func:`keep_window_both`, called by
:mod:`md.neighbors._cluster_search`) and the prune's row (:func:`_keep_near`, in
:func:`prune_pairs`: GROMACS's dynamic pruning of an outer list to an inner one). Each
intrinsic has a Python twin for ``NUMBA_DISABLE_JIT=1``. :func:`move_pairs` moves a
chunk's rows down to follow the one before, for the prune and the search alike.

numba's cache checks only a kernel's own file: the search's cached kernels hold their
own copies of :func:`keep_window`, :func:`keep_window_both` and :func:`move_pairs`,
which a warm cache keeps after an edit here until ``_cluster_search.py`` changes too or
the kernel cache folder (``md._kernel_cache.cache_directory()``) is cleared.
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
