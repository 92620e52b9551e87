"""The cluster-pair kernel's inner loop as LLVM vector IR, for any pair term.

:func:`cluster_row` makes, for one term's ``_pair(r2, k, table, mode, data)``
(the frame's pair function: the term with its cutoff mode, parameters from
column k of the table), a numba intrinsic that computes one i cluster against
its row of j clusters in the cluster-pair list (:mod:`md._cluster_kernels`
describes the layout). The idea is GROMACS's 2xMM kernels: two i atoms by four
j atoms fill one 8-lane float32 vector, two vectors cover a cluster pair, the
i forces and the energy stay in registers over the whole row, and a j
cluster's forces are summed across the two halves and added to memory once.

What numba cannot spell is the registers: in a loop LLVM keeps such per-lane
sums in memory (a numba 4x4 cluster loop measured no faster than the slot
frame). So the geometry, the masks and the sums are written here as vector IR,
and the pair term is the frame's own ``_pair``, compiled as a subroutine and
called once per lane: eight straight-line copies, which LLVM's SLP vectoriser
turns back into vector instructions. numba runs that vectoriser only when
``numba.config.SLP_VECTORIZE`` is set, read when a function's module is
optimised; :func:`slp_vectorising` sets it around the first call of a kernel
that uses this intrinsic (the Python layer calls every cluster kernel inside
it). Measured on LJ (32000-atom melt, 1 thread): the same time as LJ written
by hand in vector IR; eight scalar copies without the vectoriser, 3.4 times
as long.

The intrinsic has no Python twin (``md._simd.python_twin``): under
``NUMBA_DISABLE_JIT=1`` the neighbour list builds no clusters, so the slot
frame, which runs as Python, serves mixed precision instead.

Lanes whose pair is out of the list radius, or not a pair (an atom with
itself, the lower triangle of a cluster with itself, fillers) are evaluated
at r^2 = the table's largest squared cutoff, where every type pair's term is
zero (the frame's ``inside`` test) and finite, never at a filler's distance,
whose 1/r^12 would underflow into slow denormals in float32.
"""

from __future__ import annotations

import contextlib
import threading

import numba
from llvmlite import ir
from numba import types
from numba.core import cgutils, compiler
from numba.core.cpu import FastMathOptions
from numba.extending import intrinsic

from md._simd import (
    CLUSTER_OWN_LANES,
    array_data,
    cluster_i_halves,
    cluster_j_shifted,
    load_vector,
    shuffle,
    splat,
    squared_distances,
    store_vector,
)

__all__ = ["cluster_row", "slp_vectorising"]

_F32 = ir.FloatType()
_F64 = ir.DoubleType()
_I8 = ir.IntType(8)
_I32 = ir.IntType(32)
_I64 = ir.IntType(64)
_V8 = ir.VectorType(_F32, 8)
_D4 = ir.VectorType(_F64, 4)
_MASK8 = ir.VectorType(ir.IntType(1), 8)
#: As the frame's pair loops: sums may be reassociated into lanes, multiply-adds fused;
#: no "nnan"/"ninf" (overlapping atoms must still give an infinite energy).
_FLAGS = ("contract", "reassoc", "nsz", "arcp")

#: Cluster pairs whose i forces and energy are summed in float32 lanes before they are
#: added to the double sums (a power of 2).
_FLUSH = 8

_SLP_LOCK = threading.Lock()


@contextlib.contextmanager
def slp_vectorising():
    """Compile with LLVM's SLP vectoriser while inside (see the module docstring)."""
    with _SLP_LOCK:
        before = numba.config.SLP_VECTORIZE
        numba.config.SLP_VECTORIZE = 1
        try:
            yield
        finally:
            numba.config.SLP_VECTORIZE = before


def _index(n: int):
    return ir.Constant(_I64, n)


def _eight(x: float):
    return ir.Constant(_V8, [x] * 8)


def _subroutine_flags():
    flags = compiler.Flags()
    flags.error_model = "numpy"
    flags.fastmath = FastMathOptions(set(_FLAGS))
    return flags


def _local_column(context, builder, table_type, table, rows: int):
    """A copy of ``table``'s column 0 (``rows`` values) in a stack array, as an array of
    the same type and shape (rows, 1). The term's parameter loads from it are then
    known not to alias the force stores, and LLVM keeps them in registers over the row
    (from the table itself it reloads them for every cluster pair)."""
    source = context.make_array(table_type)(context, builder, table)
    element = context.get_data_type(table_type.dtype)
    local = cgutils.alloca_once(builder, element, size=rows)
    columns = builder.extract_value(source.shape, 1)
    for r in range(rows):
        value = builder.load(builder.gep(source.data, [builder.mul(_index(r), columns)]))
        builder.store(value, builder.gep(local, [_index(r)]))
    model = context.data_model_manager[table_type]
    size = _index(context.get_abi_sizeof(element))
    copy = builder.insert_value(table, local, model.get_field_position("data"))
    copy = builder.insert_value(copy, _index(rows), model.get_field_position("nitems"))
    for field, values in (("shape", (_index(rows), _index(1))), ("strides", (size, size))):
        for axis, value in enumerate(values):
            copy = builder.insert_value(copy, value, [model.get_field_position(field), axis])
    return copy


def cluster_row(pair, rows):
    """The row intrinsic for the frame's ``pair`` dispatcher (see the module docstring),
    whose parameter tables have ``rows()`` rows (asked when a kernel compiles: the
    template's names are set only in each term's copy).

    ``row(xi, xj, offsets, partners, start, end, ci, slot_types, n_types, table, mode,
    data, cut2, forces, virial) -> energy`` (float64):

    - ``xi``, ``xj``: float32 (clusters * 12,), each cluster [x0..x3, y0..y3, z0..z3]
      relative to its origin, for the i and the j role;
    - ``offsets`` float32 (pairs * 3,), ``partners`` int32: cluster pairs
      ``start`` to ``end`` are i cluster ``ci``'s, the first of them ``ci`` with itself
      at zero offset (only its pairs b > a are evaluated);
    - ``slot_types`` int32 per slot, or None when every atom has type 0 (column 0);
    - ``table``, ``mode``, ``data``: passed to ``pair`` (mode a literal);
    - ``cut2``: float32, the largest squared cutoff of the table;
    - ``forces`` float64 (clusters * 12,): the i forces added, the j forces subtracted,
      each cluster pair's j sums and every ``_FLUSH`` pairs' i sums added in double (so
      no float32 sum runs over more than 8 ``_FLUSH`` terms, whatever the row's length);
    - ``virial`` float64 (9,), or None: adds offset (x) (force on the i cluster) per
      pair, the part of the virial the relative positions do not carry.
    """

    @intrinsic
    def row(typingctx, xi, xj, offsets, partners, start, end, ci, slot_types, n_types,
            table, mode, data, cut2, forces, virial):  # fmt: skip
        real = table.dtype
        mode_type = getattr(mode, "literal_type", mode)
        pair_sig = typingctx.resolve_function_type(
            numba.typeof(pair), (real, types.int64, table, mode_type, data), {}
        )
        sig = types.float64(xi, xj, offsets, partners, start, end, ci, slot_types, n_types,
                            table, mode, data, cut2, forces, virial)  # fmt: skip
        single = isinstance(slot_types, types.NoneType)
        with_virial = not isinstance(virial, types.NoneType)

        def codegen(context, builder, signature, args):
            fl = _FLAGS
            (xi_v, xj_v, off_v, part_v, start_v, end_v, ci_v, types_v, ntypes_v, table_v,
             mode_v, data_v, cut_v, forces_v, virial_v) = args  # fmt: skip
            arg = signature.args
            xi_p, xj_p, off_p, part_p = (array_data(context, builder, arg[n], args[n])
                                         for n in range(4))  # fmt: skip
            f_p = array_data(context, builder, arg[13], forces_v)
            vir_p = array_data(context, builder, arg[14], virial_v) if with_virial else None
            types_p = None if single else array_data(context, builder, arg[7], types_v)
            literal = getattr(arg[10], "literal_value", None)
            mode_c = _index(literal) if literal is not None else builder.sext(mode_v, _I64)
            # not from numba's subroutine cache: it keys by code object, which is the same
            # for every term's copy of the template (CPython's code equality ignores the
            # file), so a second term would get the first one's compiled _pair
            cres = context.compile_subroutine(builder, pair.py_func, pair_sig,
                                              flags=_subroutine_flags(), caching=False)  # fmt: skip
            pair_real = context.get_value_type(pair_sig.return_type.dtype)
            table_real = context.get_value_type(real)
            base_i = builder.mul(ci_v, _index(3 * 4))
            pairs_i = cluster_i_halves(builder, xi_p, base_i)  # i atoms (0, 1) and (2, 3)
            cut = splat(builder, cut_v, _V8)
            own_cuts = [builder.select(ir.Constant(_MASK8, keep), cut, _eight(-1.0))
                        for keep in CLUSTER_OWN_LANES]  # fmt: skip
            if single:  # every lane reads column 0: from a local copy
                type_rows = None
                table_v = _local_column(context, builder, arg[9], table_v, rows())
            else:  # column of lane l: type(i atom) * n_types + type(j atom)
                n_types_v = builder.sext(ntypes_v, _I64) if ntypes_v.type != _I64 else ntypes_v
                type_rows = []
                for a in range(4):
                    slot = builder.add(builder.mul(ci_v, _index(4)), _index(a))
                    t = builder.sext(builder.load(builder.gep(types_p, [slot])), _I64)
                    type_rows.append(builder.mul(t, n_types_v))
            sums = [cgutils.alloca_once_value(builder, _eight(0.0)) for _ in range(7)]

            # the double lanes in 4-lane halves: an 8-double vector is a zmm register on an
            # AVX-512 CPU, whose use in this loop made it 1.6 times as slow
            wide = [[cgutils.alloca_once_value(builder, ir.Constant(_D4, [0.0] * 4))
                     for _ in range(2)] for _ in range(7)]  # fmt: skip

            def flush():
                """Add the float32 i-force and energy lanes to their double lanes, zero them."""
                for narrow, halves in zip(sums, wide, strict=True):
                    lanes = builder.load(narrow)
                    for half, total in enumerate(halves):
                        four = shuffle(builder, lanes, lanes, list(range(4 * half, 4 * half + 4)))
                        part = builder.fpext(four, _D4)
                        builder.store(builder.fadd(builder.load(total), part, flags=fl), total)
                    builder.store(_eight(0.0), narrow)

            # groups of _FLUSH cluster pairs: the i sums and the energy go to double after
            # each, so their float32 round-off does not grow with the row's length (a
            # conditional flush inside one loop made the kernel 1.6 times as slow)
            step = _index(_FLUSH)
            with cgutils.for_range_slice(builder, start_v, end_v, step) as (group, _):
                last = builder.add(group, _index(_FLUSH))
                last = builder.select(builder.icmp_signed("<", last, end_v), last, end_v)
                with cgutils.for_range_slice(builder, group, last, _index(1)) as (k, _):
                    cj = builder.sext(builder.load(builder.gep(part_p, [k])), _I64)
                    itself = builder.icmp_signed("==", k, start_v)  # listed first in its row
                    base_j = builder.mul(cj, _index(12))
                    offset, shifted = cluster_j_shifted(builder, xj_p, base_j, off_p, k, fl)
                    if single:
                        columns = [_index(0)] * 8
                    else:
                        tj = []
                        for b in range(4):
                            slot = builder.add(builder.mul(cj, _index(4)), _index(b))
                            t = builder.load(builder.gep(types_p, [slot]))
                            tj.append(builder.sext(t, _I64))
                    fj = [_eight(0.0)] * 3
                    for h in range(2):
                        dx, r2 = squared_distances(builder, pairs_i[h], shifted, fl)
                        limit = builder.select(itself, own_cuts[h], cut)
                        mask = builder.fcmp_ordered("<", r2, limit)
                        safe = builder.select(mask, r2, cut)
                        if not single:
                            columns = [builder.add(type_rows[2 * h + lane // 4], tj[lane % 4])
                                       for lane in range(8)]  # fmt: skip
                        u = fr = ir.Constant(_V8, ir.Undefined)
                        for lane in range(8):
                            where = ir.Constant(_I32, lane)
                            x = builder.extract_element(safe, where)
                            if table_real != _F32:
                                x = builder.fpext(x, table_real)
                            values = context.call_internal(
                                builder, cres.fndesc, pair_sig,
                                [x, columns[lane], table_v, mode_c, data_v],
                            )  # fmt: skip
                            parts = [builder.extract_value(values, n) for n in range(2)]
                            if pair_real != _F32:
                                parts = [builder.fptrunc(p, _F32) for p in parts]
                            u = builder.insert_element(u, parts[0], where)
                            fr = builder.insert_element(fr, parts[1], where)
                        energy = builder.load(sums[6])
                        builder.store(builder.fadd(energy, u, flags=fl), sums[6])
                        for d in range(3):
                            g = builder.fmul(fr, dx[d], flags=fl)
                            builder.store(builder.fadd(builder.load(sums[3 * h + d]), g, flags=fl),
                                          sums[3 * h + d])  # fmt: skip
                            fj[d] = builder.fadd(fj[d], g, flags=fl)
                    totals = []
                    for d in range(3):
                        low = shuffle(builder, fj[d], fj[d], [0, 1, 2, 3])
                        high = shuffle(builder, fj[d], fj[d], [4, 5, 6, 7])
                        summed = builder.fpext(builder.fadd(low, high, flags=fl), _D4)
                        index = builder.add(base_j, _index(4 * d))
                        old = load_vector(builder, f_p, index, _D4)
                        store_vector(builder, builder.fsub(old, summed, flags=fl), f_p, index)
                        if with_virial:
                            total = builder.extract_element(summed, ir.Constant(_I32, 0))
                            for lane in range(1, 4):
                                total = builder.fadd(total, builder.extract_element(
                                    summed, ir.Constant(_I32, lane)), flags=fl)  # fmt: skip
                            totals.append(total)
                    if with_virial:  # offset (x) the force on the i cluster from this pair
                        for d in range(3):
                            o = builder.fpext(offset[d], _F64)
                            for e in range(3):
                                slot = builder.gep(vir_p, [_index(3 * d + e)])
                                term = builder.fmul(o, totals[e], flags=fl)
                                added = builder.fadd(builder.load(slot), term, flags=fl)
                                builder.store(added, slot)
                flush()
            for d in range(3):  # lanes 0-3: atom 0 (2), 4-7: atom 1 (3), per pair of i atoms
                total = None
                for h in range(2):  # half 0 of pair h: i atom 2h, half 1: i atom 2h + 1
                    for half in range(2):
                        lanes = builder.load(wide[3 * h + d][half])
                        parts = [builder.extract_element(lanes, ir.Constant(_I32, j))
                                 for j in range(4)]  # fmt: skip
                        atom_sum = builder.fadd(builder.fadd(parts[0], parts[1], flags=fl),
                                                builder.fadd(parts[2], parts[3], flags=fl),
                                                flags=fl)  # fmt: skip
                        slot = 2 * h + half
                        total = builder.insert_element(
                            ir.Constant(_D4, ir.Undefined) if total is None else total, atom_sum,
                            ir.Constant(_I32, slot))  # fmt: skip
                index = builder.add(base_i, _index(4 * d))
                old = load_vector(builder, f_p, index, _D4)
                store_vector(builder, builder.fadd(old, total, flags=fl), f_p, index)
            energy = None
            for half in wide[6]:
                lanes = builder.load(half)
                for lane in range(4):
                    part = builder.extract_element(lanes, ir.Constant(_I32, lane))
                    energy = part if energy is None else builder.fadd(energy, part)
            return energy

        return sig, codegen

    return row
