"""The cluster-pair kernel's inner loop as LLVM vector IR, for any pair term.

:func:`cluster_row` makes, for one term's ``_pair(r2, k, table, mode, data)``
(the frame's pair function: the term with its cutoff mode, parameters from
column k of the table), a numba intrinsic that computes one i cluster against
its row of j clusters in the cluster-pair list (:mod:`md.neighbors._cluster_grid`
describes the layout). The idea is GROMACS's 2xMM kernels: two i atoms by four
j atoms fill one 8-lane float32 vector, two vectors cover a cluster pair, the
i forces and the energy stay in registers over the whole row, and a j
cluster's forces are added to its float32 lanes in memory, lane by lane (see
below). With ``lanes=16`` one vector holds the whole 4x4 cluster pair: the kernels'
width where the CPU numba compiles for has AVX-512F (``md._simd.ZMM``), 8
lanes elsewhere. On the 32000-atom melt (Emerald Rapids, one thread, the
kernel's two widths alternated in one process) 16 lanes took 0.89 of the
8-lane time (per-block ratios 0.84-0.95); compiled for AVX2 alone, where a
16-lane vector is two ymm registers, 1.07 and 0.99 in two measurements (no
gain), so AVX2 keeps 8 (``benchmarks/cluster_kernel.py --lanes 8,16``). On a
Zen 4 EPYC, whose AVX-512 runs on 256-bit units, the widths take the same time
(16 lanes 1.01 of 8): there the loop is bound by its floating-point operations
(77 instructions a pair at 16 lanes, 55 of them on zmm; 128 at 8), and a
third of them were the j forces' fold, conversion and store (without those the
kernel took 0.60 of its time; without the energy sum 0.96).

So a j cluster's forces are not folded over the i atoms pair by pair: each pair
adds its lanes (x, y, z: three vectors, fused into the term's multiply) to the
j cluster's lanes in ``j_sums``, float32, and counts the pair in ``j_counts``;
a row that brings a cluster's count to ``_J_FLUSH`` folds those lanes over the i
atoms, subtracts them from its double forces and zeroes them after its loop,
each row folds its own cluster's lanes at its end (no later row adds to them),
and the caller folds those of the clusters after its last row
(:func:`potentials._kernels.cluster_j_remainders`). No float32 sum of a j
force runs over more than ``_J_FLUSH`` pairs (one more where a row meets a
cluster at two periodic images), however many rows a cluster is the partner
of. On the Zen 4 EPYC (32000-atom melt, one thread, alternating processes)
the kernel took 0.72 of the folding kernel's time with 16 lanes (1.835
against 2.55-2.61 ms), 0.92 with 8 compiled for AVX2; the lanes with no bound
at all would take 0.71, a fold every 16 pairs inside the loop (a branch per
pair) 0.83.

The loop over a row runs one pair ahead: pair k + 1's partner, coordinates
and distances are computed before pair k's term. The chain from a partner's
index to its j forces (loads, distances, the term's division, the j sums) is
longer than the out-of-order window covers, and the kernel waited on it
(``llvm-mca`` of the loop: bound by the chain, not by its ports); ahead by one
it takes 0.81 of the time on the 32000-atom melt (AVX-512 and AVX2 code),
ahead by two or three longer again (the carried vectors spill).

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
    ZMM,
    array_data,
    cluster_i_halves,
    cluster_j_shifted,
    cluster_own_lanes,
    load_vector,
    shuffle,
    splat,
    squared_distances,
    store_vector,
)
from potentials._kernels import J_STRIDE

__all__ = ["cluster_row", "slp_vectorising"]

_F32 = ir.FloatType()
_F64 = ir.DoubleType()
_I8 = ir.IntType(8)
_I32 = ir.IntType(32)
_I64 = ir.IntType(64)
_D4 = ir.VectorType(_F64, 4)
_D8 = ir.VectorType(_F64, 8)
#: The floating-point freedom of the row's instructions and of its pair term (``_pair``,
#: compiled as a subroutine and copied into every lane): none that changes a value ("nsz"
#: only lets a zero's sign go; no "nnan"/"ninf" either: overlapping atoms must still give
#: an infinite energy). The slot frame's loops also take "reassoc", "contract" and "arcp";
#: here they only let LLVM round differently each time it optimises the code, and numba
#: optimises a kernel more than once where another function links it in. A threaded
#: kernel is such a case: numba outlines the ``prange`` body into a function of its own
#: library, optimised there and again in each library that links it; a process that
#: compiled the kernel runs the first copy (loaded first; the linked copies are weak), a
#: process that loaded it from the cache the last. With "reassoc" the two rounded
#: differently (2048 atoms, 2 threads, one force call: 1.3e-5 apart with it on the row's
#: sums, 4.8e-7 with it on the term of a two-type LJ; ``tests/test_reproducible.py``);
#: without, they are equal. The cost: the kernel took 1.11 of the time with the slot
#: frame's flags (1.09 with "contract" kept on the term, 1.02 with only the row's sums
#: strict), on the 32000-atom melt, Zen 5, one and two threads, the two versions compiled
#: side by side and timed in 30 alternating blocks (the median ratio).
_FLAGS = ("nsz",)

#: Cluster pairs whose i forces and energy are summed in float32 lanes before they are
#: added to the double sums (a power of 2). 16 took 0.95 of the time of 8 with 16 lanes
#: (0.96 with 8, within the noise there), for a float32 sum of 16 terms, not 8.
_FLUSH = 16

#: Cluster pairs whose j forces a j cluster's float32 lanes hold at most before they
#: are folded into its double forces (at the end of the row that fills them): 32 took
#: 0.96 of the kernel time of 16 (most clusters are the partners of ~30 rows of the
#: melt's list, so most lanes are folded once, at the end of their own cluster's row).
_J_FLUSH = 32

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


def _filled(x: float, lanes: int = 8):
    return ir.Constant(ir.VectorType(_F32, lanes), [x] * lanes)


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


def _j_sums_16(builder, fj, fl):
    """A 16-lane cluster pair's j forces (``fj``: x, y, z, lane 4 a + b the pair of i atom
    a and j atom b) summed over the i atoms, in double: [(x and y of j atoms 0-3, 8
    doubles, 0), (z, 4 doubles, 8)], each with its first element's place in the cluster.

    x and y are folded in one vector (their quarters of i atoms 0, 1 beside those of 2, 3,
    then the halves), z beside them, and x, y converted as one 8-double vector: 15
    vector operations where three 16 -> 8 -> 4 folds and conversions take 21 (the
    kernel is bound by its vector operations, two ports of them on AVX-512)."""
    x, y, z = fj
    low = shuffle(builder, x, y, [*range(0, 8), *range(16, 24)])  # i atoms 0, 1 of x, y
    high = shuffle(builder, x, y, [*range(8, 16), *range(24, 32)])  # i atoms 2, 3
    xy = builder.fadd(low, high, flags=fl)  # [x (0+2), x (1+3), y (0+2), y (1+3)]
    z8 = builder.fadd(
        shuffle(builder, z, z, list(range(8))), shuffle(builder, z, z, list(range(8, 16))), flags=fl
    )
    z16 = shuffle(builder, z8, z8, [*range(8), *range(8)])
    first = shuffle(builder, xy, z16, [*range(0, 4), *range(8, 12), *range(16, 20), *range(16, 20)])
    second = shuffle(
        builder, xy, z16, [*range(4, 8), *range(12, 16), *range(20, 24), *range(20, 24)]
    )
    sums = builder.fadd(first, second, flags=fl)  # [x, y, z, z] of j atoms 0-3
    xy8 = builder.fpext(shuffle(builder, sums, sums, list(range(8))), _D8)
    z4 = builder.fpext(shuffle(builder, sums, sums, list(range(8, 12))), _D4)
    return [(xy8, 0), (z4, 8)]


def _i_sums_16(builder, sums, fl):
    """The 16-lane float32 sums of the i forces x, y, z and the energy (lane 4 a + b: i
    atom a, j atom b) summed over the j atoms: [x, y, z, energy] of i atoms 0-3, one
    vector. Two rounds of two-vector shuffles and adds, 9 vector operations where the
    lanes' 16 quarters converted and added one by one take about 60."""
    x, y, z, e = sums
    rounds = []
    for first, second in ((x, y), (z, e)):  # j atoms 0 + 2, 1 + 3, of two sums beside
        low = shuffle(
            builder,
            first,
            second,
            [4 * a + b + 16 * (w // 2) for a in range(4) for w, b in enumerate((0, 1, 0, 1))],
        )
        high = shuffle(
            builder,
            first,
            second,
            [4 * a + b + 16 * (w // 2) for a in range(4) for w, b in enumerate((2, 3, 2, 3))],
        )
        rounds.append(builder.fadd(low, high, flags=fl))  # [q0 (a): x, x, y, y, ...]
    # sum k (x, y, z, energy) of atom a: lanes 4 a + 2 (k % 2) and + 1 of rounds[k // 2]
    lanes = [16 * (k // 2) + 4 * a + 2 * (k % 2) for k in range(4) for a in range(4)]
    low = shuffle(builder, rounds[0], rounds[1], lanes)
    high = shuffle(builder, rounds[0], rounds[1], [lane + 1 for lane in lanes])
    return builder.fadd(low, high, flags=fl)


def _four_sum(builder, values, first: int, fl):
    """The sum of ``values``' lanes ``first`` to ``first + 3`` (a scalar), pairwise."""
    parts = [builder.extract_element(values, ir.Constant(_I32, first + j)) for j in range(4)]
    return builder.fadd(
        builder.fadd(parts[0], parts[1], flags=fl),
        builder.fadd(parts[2], parts[3], flags=fl),
        flags=fl,
    )


def cluster_row(pair, rows, lanes: int | None = None):
    """The row intrinsic for the frame's ``pair`` dispatcher (see the module docstring),
    whose parameter tables have ``rows()`` rows (asked when a kernel compiles: the
    template's names are set only in each term's copy), in vectors of ``lanes`` float32
    (8, or 16; None: 16 where ``md._simd.ZMM``, else 8; see the module docstring).

    ``row(xi, xj, offsets, partners, start, end, ci, slot_types, n_types, table, mode,
    data, cut2, forces, j_sums, j_counts, window, virial) -> energy`` (float64):

    - ``xi``, ``xj``: float32 (clusters * 12,), each cluster [x0..x3, y0..y3, z0..z3]
      relative to its origin, for the i and the j role;
    - ``offsets`` float32 (pairs * 3,), ``partners`` int32: cluster pairs
      ``start`` to ``end`` are i cluster ``ci``'s, the first of them ``ci`` with itself
      at zero offset (only its pairs b > a are evaluated);
    - ``slot_types`` int32 per slot, or None when every atom has type 0 (column 0);
    - ``table``, ``mode``, ``data``: passed to ``pair`` (mode a literal);
    - ``cut2``: float32, the largest squared cutoff of the table;
    - ``forces`` float64 (12 per cluster from cluster ``window`` on: cluster c at
      12 (c - ``window``); the same for ``j_sums`` and ``j_counts``, so a chunk's
      scratch need only cover the clusters its rows reach): the i forces added, every
      ``_FLUSH`` pairs'
      i sums in double (so no float32 sum runs over more than ``_FLUSH`` terms, whatever
      the row's length); the j forces subtracted where a j cluster's lanes fill;
    - ``j_sums`` float32 (``J_STRIDE`` per cluster), 64-byte aligned for speed, and
      ``j_counts`` int32 (one per cluster): each cluster's j forces in float32 lanes (x, y, z
      at 0, 16, 32; lane 4 a + b the pair of i atom a and j atom b) and the cluster pairs
      in them, below ``_J_FLUSH`` after every row (a row that fills a cluster's lanes
      folds them into ``forces`` and zeroes them, and at its end folds and zeroes its own
      cluster's, which no later row adds to); the caller folds those of the clusters
      after its last row (:func:`potentials._kernels.cluster_j_remainders`), which
      zeroes them too;
    - ``virial`` float64 (9,), or None: adds offset (x) (force on the i cluster) per
      pair, the part of the virial the relative positions do not carry.
    """
    if lanes is None:
        lanes = 16 if ZMM else 8
    if lanes not in (8, 16):
        raise ValueError(f"cluster rows have 8 or 16 lanes, not {lanes}")

    @intrinsic
    def row(
        typingctx,
        xi,
        xj,
        offsets,
        partners,
        start,
        end,
        ci,
        slot_types,
        n_types,
        table,
        mode,
        data,
        cut2,
        forces,
        j_sums,
        j_counts,
        window,
        virial,
    ):
        real = table.dtype
        mode_type = getattr(mode, "literal_type", mode)  # numba: a Literal type, or a plain one
        pair_sig = typingctx.resolve_function_type(
            numba.typeof(pair), (real, types.int64, table, mode_type, data), {}
        )
        sig = types.float64(
            xi,
            xj,
            offsets,
            partners,
            start,
            end,
            ci,
            slot_types,
            n_types,
            table,
            mode,
            data,
            cut2,
            forces,
            j_sums,
            j_counts,
            window,
            virial,
        )
        single = isinstance(slot_types, types.NoneType)
        with_virial = not isinstance(virial, types.NoneType)

        def codegen(context, builder, signature, args):
            fl = _FLAGS
            (
                xi_v,
                xj_v,
                off_v,
                part_v,
                start_v,
                end_v,
                ci_v,
                types_v,
                ntypes_v,
                table_v,
                mode_v,
                data_v,
                cut_v,
                forces_v,
                js_v,
                jc_v,
                window_v,
                virial_v,
            ) = args
            arg = signature.args
            xi_p, xj_p, off_p, part_p = (
                array_data(context, builder, arg[n], args[n]) for n in range(4)
            )
            # the window's arrays, addressed by cluster: their pointers moved back by the
            # window's first cluster (once per row; before the allocation, never read there)
            shift = builder.neg(builder.sext(window_v, _I64) if window_v.type != _I64 else window_v)
            f_p = array_data(context, builder, arg[13], forces_v)
            f_p = builder.gep(f_p, [builder.mul(shift, _index(12))])
            js_p = array_data(context, builder, arg[14], js_v)
            js_p = builder.gep(js_p, [builder.mul(shift, _index(J_STRIDE))])
            jc_p = builder.gep(array_data(context, builder, arg[15], jc_v), [shift])
            vir_p = array_data(context, builder, arg[17], virial_v) if with_virial else None
            types_p = None if single else array_data(context, builder, arg[7], types_v)
            literal = getattr(arg[10], "literal_value", None)  # numba: only a Literal type has it
            mode_c = _index(literal) if literal is not None else builder.sext(mode_v, _I64)
            # not from numba's subroutine cache: it keys by code object, which is the same
            # for every term's copy of the template (CPython's code equality ignores the
            # file), so a second term would get the first one's compiled _pair
            cres = context.compile_subroutine(
                builder, pair.py_func, pair_sig, flags=_subroutine_flags(), caching=False
            )
            pair_real = context.get_value_type(pair_sig.return_type.dtype)
            table_real = context.get_value_type(real)
            base_i = builder.mul(ci_v, _index(3 * 4))
            vector = ir.VectorType(_F32, lanes)
            passes = 16 // lanes  # vectors per cluster pair
            per_pass = lanes // 4  # i atoms per vector
            pairs_i = cluster_i_halves(builder, xi_p, base_i, lanes)
            cut = splat(builder, cut_v, vector)
            own_cuts = [
                builder.select(
                    ir.Constant(ir.VectorType(ir.IntType(1), lanes), keep),
                    cut,
                    _filled(-1.0, lanes),
                )
                for keep in cluster_own_lanes(lanes)
            ]
            if lanes == 16:  # the SLP vectoriser's widest vectors: zmm (LLVM's X86 default
                # for Intel's AVX-512 CPUs is 256 bits, which splits the term in two)
                set.add(builder.function.attributes, '"prefer-vector-width"="512"')
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
            fma = cgutils.get_or_insert_function(
                builder.module, ir.FunctionType(vector, [vector] * 3), f"llvm.fma.v{lanes}f32"
            )
            # per vector of the pair: x, y, z of the i forces; then the energy
            sums = [
                cgutils.alloca_once_value(builder, _filled(0.0, lanes))
                for _ in range(3 * passes + 1)
            ]

            # the double sums. 8 lanes: in 4-lane quarters (lanes 4q to 4q + 3: one i
            # atom's); an 8-double vector is a zmm register on an AVX-512 CPU, whose use in
            # this loop (the 8-lane kernel's) made it 1.6 times as slow. 16 lanes: the
            # float32 sums folded over the j atoms first (_i_sums_16), x and y of the four
            # i atoms in one 8-double vector, z and the energy in another (0.89 of the
            # kernel's time with the quarters).
            if lanes == 8:
                wide = [
                    [
                        cgutils.alloca_once_value(builder, ir.Constant(_D4, [0.0] * 4))
                        for _ in range(per_pass)
                    ]
                    for _ in sums
                ]
            else:
                wide16 = [
                    cgutils.alloca_once_value(builder, ir.Constant(_D8, [0.0] * 8))
                    for _ in range(2)
                ]

            # the virial's offset part: per offset axis, per vector of the j sums (x and y
            # in one at 16 lanes), offset (x) those sums lane by lane, summed in the
            # vir_p slots after the row (per pair through memory it took 2.8 times as long
            # as the kernel without the virial)
            shapes = [(8, 0), (4, 8)] if lanes == 16 else [(4, 0), (4, 4), (4, 8)]
            moments = (
                [
                    [
                        cgutils.alloca_once_value(
                            builder, ir.Constant(ir.VectorType(_F64, count), [0.0] * count)
                        )
                        for count, _ in shapes
                    ]
                    for _ in range(3)
                ]
                if with_virial
                else None
            )

            def flush():
                """Add the float32 i-force and energy lanes to their double lanes, zero them."""
                if lanes == 16:
                    folded = _i_sums_16(builder, [builder.load(narrow) for narrow in sums], fl)
                    for half, total in enumerate(wide16):
                        part = shuffle(builder, folded, folded, list(range(8 * half, 8 * half + 8)))
                        part = builder.fpext(part, _D8)
                        builder.store(builder.fadd(builder.load(total), part, flags=fl), total)
                    for narrow in sums:
                        builder.store(_filled(0.0, lanes), narrow)
                    return
                for narrow, quarters in zip(sums, wide, strict=True):
                    values = builder.load(narrow)
                    for q, total in enumerate(quarters):
                        four = shuffle(builder, values, values, list(range(4 * q, 4 * q + 4)))
                        part = builder.fpext(four, _D4)
                        builder.store(builder.fadd(builder.load(total), part, flags=fl), total)
                    builder.store(_filled(0.0, lanes), narrow)

            def j_parts(fj):
                """The j forces (``fj``: x, y, z vectors) summed over the i atoms, in
                double: [(vector, its first element's place in the cluster's 12)]."""
                if lanes == 16:
                    return _j_sums_16(builder, fj, fl)
                parts = []
                for d in range(3):  # j atom b's force: the sum of lanes b, b + 4
                    low = shuffle(builder, fj[d], fj[d], list(range(4)))
                    high = shuffle(builder, fj[d], fj[d], list(range(4, 8)))
                    parts.append((builder.fpext(builder.fadd(low, high, flags=fl), _D4), 4 * d))
                return parts

            def flush_j(base_j, base_s):
                """Fold the j cluster's float32 lanes (from ``base_s`` in ``j_sums``),
                subtract them from its double forces (from ``base_j``), zero them."""
                indices = [builder.add(base_s, _index(16 * d)) for d in range(3)]
                lanes_j = [load_vector(builder, js_p, index, vector) for index in indices]
                for summed, first in j_parts(lanes_j):
                    index = builder.add(base_j, _index(first))
                    old = load_vector(builder, f_p, index, summed.type)
                    store_vector(builder, builder.fsub(old, summed, flags=fl), f_p, index)
                for index in indices:
                    store_vector(builder, _filled(0.0, lanes), js_p, index)

            def pair_at(cj, base_j, offset, separations):
                """One cluster pair: the term in every lane, the i sums, the j forces."""
                if single:
                    columns = [_index(0)] * lanes
                else:
                    tj = []
                    for b in range(4):
                        slot = builder.add(builder.mul(cj, _index(4)), _index(b))
                        t = builder.load(builder.gep(types_p, [slot]))
                        tj.append(builder.sext(t, _I64))
                fj = [None] * 3
                terms = []  # per vector: the pair forces f/r and the separations
                for h in range(passes):
                    *dx, safe = separations[h]
                    if not single:
                        columns = [
                            builder.add(type_rows[per_pass * h + lane // 4], tj[lane % 4])
                            for lane in range(lanes)
                        ]
                    u = fr = ir.Constant(vector, ir.Undefined)
                    for lane in range(lanes):
                        where = ir.Constant(_I32, lane)
                        x = builder.extract_element(safe, where)
                        if table_real != _F32:
                            x = builder.fpext(x, table_real)
                        values = context.call_internal(
                            builder,
                            cres.fndesc,
                            pair_sig,
                            [x, columns[lane], table_v, mode_c, data_v],
                        )
                        parts = [builder.extract_value(values, n) for n in range(2)]
                        if pair_real != _F32:
                            parts = [builder.fptrunc(p, _F32) for p in parts]
                        u = builder.insert_element(u, parts[0], where)
                        fr = builder.insert_element(fr, parts[1], where)
                    energy = builder.load(sums[-1])
                    builder.store(builder.fadd(energy, u, flags=fl), sums[-1])
                    for d in range(3):  # fused: the pair force f/r d enters two sums
                        total = builder.load(sums[3 * h + d])
                        builder.store(builder.call(fma, [fr, dx[d], total]), sums[3 * h + d])
                    terms.append((fr, dx))
                if with_virial:  # offset (x) the force on the i cluster from this pair,
                    for fr, dx in terms:  # in double lanes, summed after the row
                        for d in range(3):
                            fj[d] = (
                                builder.fmul(fr, dx[d], flags=fl)
                                if fj[d] is None
                                else builder.call(fma, [fr, dx[d], fj[d]])
                            )
                    parts = j_parts(fj)
                    for d in range(3):
                        o = builder.fpext(offset[d], _F64)
                        for (summed, _), slot in zip(parts, moments[d], strict=True):
                            term = builder.fmul(splat(builder, o, summed.type), summed, flags=fl)
                            builder.store(builder.fadd(builder.load(slot), term, flags=fl), slot)
                # the j forces added to the j cluster's float32 lanes, fused into the
                # term's multiply, and the pair counted; a cluster whose count reaches
                # _J_FLUSH is folded at the end of the row (a branch here, per pair, made
                # the kernel 1.06 times as slow)
                base_s = builder.mul(cj, _index(J_STRIDE))
                for d in range(3):
                    index = builder.add(base_s, _index(16 * d))
                    lanes_d = load_vector(builder, js_p, index, vector)
                    for fr, dx in terms:
                        lanes_d = builder.call(fma, [fr, dx[d], lanes_d])
                    store_vector(builder, lanes_d, js_p, index)
                count_p = builder.gep(jc_p, [cj])
                count = builder.add(builder.load(count_p), ir.Constant(_I32, 1))
                builder.store(count, count_p)
                full = builder.icmp_signed(">=", count, ir.Constant(_I32, _J_FLUSH))
                builder.store(builder.or_(builder.load(any_full), full), any_full)

            def look(k, own=False):
                """Pair k's j cluster (index, first coordinate), its offset, and per vector
                the separations and squared distances (those out of reach, or ``own``: not
                pairs of the cluster with itself, at ``cut``): what ``pair_at`` takes.

                Out of reach is min(r^2, ``cut``), one vector operation; only the cluster
                with itself, the row's first pair, evaluated before the loop, takes a
                compare and a select with its lower triangle masked. (With that mask
                chosen per pair inside the loop, the kernel took 1.06 times as long with
                16 lanes, 1.10 with AVX2's 8: 32000-atom melt, Zen 4, the two versions
                alternated in one process.)"""
                cj = builder.sext(builder.load(builder.gep(part_p, [k])), _I64)
                base_j = builder.mul(cj, _index(12))
                offset, shifted = cluster_j_shifted(builder, xj_p, base_j, off_p, k, fl, lanes)
                values = [cj, base_j, *offset]
                for h in range(passes):
                    dx, r2 = squared_distances(builder, pairs_i[h], shifted, fl)
                    limit = own_cuts[h] if own else cut
                    values += [*dx, builder.select(builder.fcmp_ordered("<", r2, limit), r2, cut)]
                return values

            def evaluate(values):
                cj, base_j, offset = values[0], values[1], values[2:5]
                separations = [values[5 + 4 * h : 9 + 4 * h] for h in range(passes)]
                pair_at(cj, base_j, offset, separations)

            # the row's first pair, the cluster with itself, on its own; then the others in
            # groups of _FLUSH cluster pairs (the first group one shorter): the i sums and
            # the energy go to double after each, so their float32 round-off does not grow
            # with the row's length (a conditional flush inside one loop made the kernel
            # 1.6 times as slow); one pair ahead: pair k + 1's loads and distances are
            # issued before pair k's term, whose inputs are then ready (the chain from a
            # partner's index to its j forces is longer than the out-of-order window
            # covers: the kernel waited on it). The pair after a row's last is its last
            # again, looked at and not used.
            step = _index(_FLUSH)
            any_full = cgutils.alloca_once_value(builder, ir.Constant(ir.IntType(1), 0))
            with builder.if_then(builder.icmp_signed("<", start_v, end_v)):
                end_less = builder.sub(end_v, _index(1))
                second = builder.add(start_v, _index(1))
                second_or_last = builder.select(
                    builder.icmp_signed("<", second, end_v), second, end_less
                )
                evaluate(look(start_v, own=True))
                ahead = [cgutils.alloca_once_value(builder, v) for v in look(second_or_last)]
                with cgutils.for_range_slice(builder, start_v, end_v, step) as (group, _):
                    last = builder.add(group, _index(_FLUSH))
                    last = builder.select(builder.icmp_signed("<", last, end_v), last, end_v)
                    begin = builder.select(builder.icmp_signed("==", group, start_v), second, group)
                    with cgutils.for_range_slice(builder, begin, last, _index(1)) as (k, _):
                        current = [builder.load(slot) for slot in ahead]
                        following = builder.add(k, _index(1))
                        following = builder.select(
                            builder.icmp_signed("<", following, end_v), following, end_less
                        )
                        for slot, value in zip(ahead, look(following), strict=True):
                            builder.store(value, slot)
                        evaluate(current)
                    flush()
                # the row's j clusters with _J_FLUSH pairs in their lanes: folded into
                # their double forces (a row adds a pair to each, two to a cluster it
                # meets at two images)
                with builder.if_then(builder.load(any_full), likely=False):
                    with cgutils.for_range_slice(builder, start_v, end_v, _index(1)) as (k, _):
                        cj = builder.sext(builder.load(builder.gep(part_p, [k])), _I64)
                        count_p = builder.gep(jc_p, [cj])
                        full = builder.icmp_signed(
                            ">=", builder.load(count_p), ir.Constant(_I32, _J_FLUSH)
                        )
                        with builder.if_then(full):
                            flush_j(builder.mul(cj, _index(12)), builder.mul(cj, _index(J_STRIDE)))
                            builder.store(ir.Constant(_I32, 0), count_p)
            # the i cluster's own j lanes: no later row adds to them (a row's partners are
            # its cluster and later ones), so they are folded into its forces here, in
            # vectors (the caller folds only those of clusters after its rows)
            flush_j(base_i, builder.mul(ci_v, _index(J_STRIDE)))
            builder.store(ir.Constant(_I32, 0), builder.gep(jc_p, [ci_v]))

            if lanes == 16:  # x, y; then z of the i cluster's atoms 0-3, and the energy
                xy, ze = (builder.load(total) for total in wide16)
                old = load_vector(builder, f_p, base_i, _D8)
                store_vector(builder, builder.fadd(old, xy, flags=fl), f_p, base_i)
                index = builder.add(base_i, _index(8))
                old = load_vector(builder, f_p, index, _D4)
                z = shuffle(builder, ze, ze, list(range(4)))
                store_vector(builder, builder.fadd(old, z, flags=fl), f_p, index)
                energy = None
                for lane in range(4, 8):
                    part = builder.extract_element(ze, ir.Constant(_I32, lane))
                    energy = part if energy is None else builder.fadd(energy, part)
            else:
                for d in range(3):  # quarter q of vector h: i atom per_pass * h + q
                    total = ir.Constant(_D4, ir.Undefined)
                    for h in range(passes):
                        for q in range(per_pass):
                            quarter = builder.load(wide[3 * h + d][q])
                            atom_sum = _four_sum(builder, quarter, 0, fl)
                            total = builder.insert_element(
                                total, atom_sum, ir.Constant(_I32, per_pass * h + q)
                            )
                    index = builder.add(base_i, _index(4 * d))
                    old = load_vector(builder, f_p, index, _D4)
                    store_vector(builder, builder.fadd(old, total, flags=fl), f_p, index)
                energy = None
                for quarter in wide[-1]:
                    values = builder.load(quarter)
                    for lane in range(4):
                        part = builder.extract_element(values, ir.Constant(_I32, lane))
                        energy = part if energy is None else builder.fadd(energy, part)
            if with_virial:
                for d in range(3):
                    for (count, first), slot in zip(shapes, moments[d], strict=True):
                        values = builder.load(slot)
                        for lane in range(0, count, 4):
                            total = _four_sum(builder, values, lane, fl)
                            target = builder.gep(vir_p, [_index(3 * d + (first + lane) // 4)])
                            builder.store(
                                builder.fadd(builder.load(target), total, flags=fl), target
                            )
            return energy

        return sig, codegen

    return row
