"""Small LLVM-IR building blocks for numba kernels, where numba has no way to say it.

numba compiles Python loops to LLVM IR, and LLVM vectorises what it can
prove safe; but some single machine operations have no Python spelling:

- ``trailing_zeros`` and ``bit_count`` (LLVM's ``cttz`` and ``ctpop``: one
  instruction each where the CPU has them), to walk the set bits of a mask;
- ``float_bits`` and ``bits_float``, a float64 read as its int64 bit pattern
  and back (for a maximum over non-negative floats that must also see NaNs:
  the integer maximum vectorises, a float maximum that checks for NaN does not);
- helpers for intrinsics that compute on LLVM vectors (``splat``, ``shuffle``,
  ``array_data``, ``load_vector``, ``compare_mask``; and the lanes of the
  cluster-pair kernels, ``cluster_i_halves``, ``cluster_j_shifted`` (``cluster_j_less``),
  ``squared_distances``, shared by the list's atom check in md and the force
  kernel in potentials), and ``PERMUTE``, whether the
  kernels are compiled for an x86 CPU with AVX2, whose ``vpermd`` moves
  selected lanes of a vector to its front (``permute_lanes``, with
  ``PERMUTATIONS``). Kernels that use it keep a portable path for every
  other CPU. ``ZMM`` says whether that CPU has AVX-512F (16 float32 lanes
  per register: the cluster kernel's vector width);
- ``gather_rows4``, ``gather_shifted_rows4`` (image shifts added) and
  ``scatter_sub_rows4``: four rows of an (N, 3) array read into (or
  subtracted from) three columns through 16-byte loads and transposes in
  registers, for the slot frame's partner gather and force scatter (LLVM
  does not vectorise a gather of rows by index);
- ``move_within``: C's ``memmove`` inside one array (numba's slice assignment
  copies overlapping slices through a temporary, element by element);
- ``stream_store`` and ``store_fence``: a non-temporal store (LLVM's
  ``!nontemporal``; ``movnti``/``movntsd`` on x86, a plain store where the
  CPU has none) and the fence that orders such stores, for outputs of tens
  of MB that a plain store would first read into the cache.

The CPU is the one numba compiles for: ``NUMBA_CPU_FEATURES`` when set, else
the host's (numba's own rule; its cache keys compiled code on the same).
No numba or llvmlite function here is private; none of them has a
well-kept library equivalent, which is why they are written out here.

Every intrinsic has a Python twin (:func:`python_twin`) that computes the same
thing with numpy: under ``NUMBA_DISABLE_JIT=1`` the kernels run as Python (to
step through one in a debugger, or for coverage and tracebacks), numba cannot
call an intrinsic from Python, and the twin stands in for it. Each twin is
tested against its intrinsic (tests/test_disable_jit.py).
"""

from __future__ import annotations

import platform
from collections.abc import Callable

import numpy as np
from llvmlite import binding, ir
from numba import types
from numba.core import cgutils, config
from numba.extending import intrinsic


def _compiled_features() -> set[str]:
    """The CPU features numba compiles for (``+avx2``, ``-avx512f``, ...)."""
    features = config.CPU_FEATURES
    if features is None:
        features = binding.get_host_cpu_features().flatten()
    return set(features.split(","))


_X86 = platform.machine().lower() in ("x86_64", "amd64")

#: True when the kernels are compiled for x86-64 with AVX2 (``permute_lanes`` exists).
PERMUTE = _X86 and "+avx2" in _compiled_features()

#: True when they are compiled for x86-64 with AVX-512F: 16 float32 lanes in one
#: register (a zmm), where the cluster kernel takes a whole 4x4 cluster pair at once.
ZMM = _X86 and "+avx512f" in _compiled_features() and "-evex512" not in _compiled_features()


def python_twin(twin: Callable) -> Callable:
    """Decorate an intrinsic with ``twin``, a plain function computing the same from Python.

    The intrinsic keeps it as ``.python_twin`` (so tests compare the two), and
    under ``NUMBA_DISABLE_JIT=1``, where kernels run as Python and numba
    refuses to call an intrinsic, the decorated name is the twin itself.
    """

    def decorate(compiled):
        compiled.python_twin = twin
        return twin if config.DISABLE_JIT else compiled

    return decorate


def _permutation_table() -> np.ndarray:
    """(256, 8) int32: row m lists the set bits of the 8-bit mask m, then zeros."""
    table = np.zeros((256, 8), dtype=np.int32)
    for m in range(256):
        lanes = [k for k in range(8) if m >> k & 1]
        table[m, : len(lanes)] = lanes
    return table


#: Lane orders for ``permute_lanes``: row m brings the lanes set in m to the front.
PERMUTATIONS = _permutation_table()


def _trailing_zeros(word) -> np.int64:
    word = int(word)
    return np.int64((word & -word).bit_length() - 1)


def _bit_count(word) -> np.int64:
    return np.int64(int(word).bit_count())


def _float_bits(x) -> np.int64:
    return np.float64(x).view(np.int64)


def _bits_float(bits) -> np.float64:
    return np.int64(bits).view(np.float64)


@python_twin(_trailing_zeros)
@intrinsic
def trailing_zeros(typingctx, word):
    """Index of the lowest set bit of a non-zero uint64 (LLVM's cttz), as an int64."""
    sig = types.int64(types.uint64)

    def codegen(context, builder, signature, args):
        return builder.cttz(args[0], ir.Constant(ir.IntType(1), 1))

    return sig, codegen


@python_twin(_bit_count)
@intrinsic
def bit_count(typingctx, word):
    """Number of set bits of a uint64 (LLVM's ctpop), as an int64."""
    sig = types.int64(types.uint64)

    def codegen(context, builder, signature, args):
        return builder.ctpop(args[0])

    return sig, codegen


@python_twin(_float_bits)
@intrinsic
def float_bits(typingctx, x):
    """The bit pattern of a float64 as an int64."""
    sig = types.int64(types.float64)

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(64))

    return sig, codegen


@python_twin(_bits_float)
@intrinsic
def bits_float(typingctx, bits):
    """The float64 of an int64 bit pattern (inverse of ``float_bits``)."""
    sig = types.float64(types.int64)

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())

    return sig, codegen


# IR helpers for intrinsics (called inside their codegen).


def is_vector_array(array, dtype) -> bool:
    """Whether a numba type is a C-contiguous 1-D array of ``dtype`` (raw pointer reads)."""
    return (
        isinstance(array, types.Array)
        and array.ndim == 1
        and array.layout == "C"
        and array.dtype == dtype
    )


def splat(builder, value, vector: ir.VectorType):
    """``value`` in every lane of a ``vector``."""
    undefined = ir.Constant(vector, ir.Undefined)
    one = builder.insert_element(undefined, value, ir.Constant(ir.IntType(32), 0))
    lanes = ir.Constant(ir.VectorType(ir.IntType(32), vector.count), [0] * vector.count)
    return builder.shuffle_vector(one, undefined, lanes)


def shuffle(builder, a, b, lanes):
    """The lanes of ``a`` then ``b`` (numbered on) that ``lanes`` lists, as one vector."""
    return builder.shuffle_vector(
        a, b, ir.Constant(ir.VectorType(ir.IntType(32), len(lanes)), lanes)
    )


_V4 = ir.VectorType(ir.FloatType(), 4)
_I64 = ir.IntType(64)


def cluster_own_lanes(lanes: int = 8) -> list[list[int]]:
    """Per vector of ``lanes`` (8 or 16), the lanes that count in a cluster with itself
    (j atom after i atom): lane l of vector h pairs i atom (lanes // 4) h + l // 4 with j
    atom l % 4."""
    rows = lanes // 4
    return [
        [int(lane % 4 > rows * h + lane // 4) for lane in range(lanes)] for h in range(4 // rows)
    ]


def cluster_i_halves(builder, xi, base, lanes: int = 8):
    """An i cluster's atoms as float32 vectors of ``lanes`` (8 or 16), one [x, y, z] per
    vector of the cluster pair: ``xi`` points at float32 [x0..x3, y0..y3, z0..z3] from
    ``base``; with 8 lanes vector h holds atom 2h in lanes 0-3 and atom 2h + 1 in lanes
    4-7, with 16 one vector holds atom a in lanes 4a to 4a + 3."""
    own = [
        load_vector(builder, xi, builder.add(base, ir.Constant(_I64, 4 * d)), _V4) for d in range(3)
    ]
    rows = lanes // 4
    return [
        [
            shuffle(builder, v, v, [a for a in range(rows * h, rows * h + rows) for _ in range(4)])
            for v in own
        ]
        for h in range(4 // rows)
    ]


def cluster_j_shifted(builder, xj, base, offsets, pair, flags=(), lanes: int = 8):
    """Pair ``pair``'s offset (three float32 scalars from ``offsets``, 3 per pair) and its
    j cluster's atoms less it, each coordinate a vector of ``lanes`` holding the four j
    atoms ``lanes / 4`` times (``xj`` laid out as in :func:`cluster_i_halves`, from
    ``base``)."""
    first = builder.mul(pair, ir.Constant(_I64, 3))
    offset = [
        builder.load(builder.gep(offsets, [builder.add(first, ir.Constant(_I64, d))]))
        for d in range(3)
    ]
    return offset, cluster_j_less(builder, xj, base, offset, flags, lanes)


def cluster_j_less(builder, xj, base, offset, flags=(), lanes: int = 8):
    """A j cluster's atoms less ``offset`` (three float32 scalars), each coordinate a
    vector of ``lanes`` holding the four j atoms ``lanes / 4`` times (``xj`` laid out as in
    :func:`cluster_i_halves`, from ``base``): :func:`cluster_j_shifted` with the offset
    already in registers."""
    vector = ir.VectorType(ir.FloatType(), lanes)
    shifted = []
    for d in range(3):
        four = load_vector(builder, xj, builder.add(base, ir.Constant(_I64, 4 * d)), _V4)
        repeated = shuffle(builder, four, four, [0, 1, 2, 3] * (lanes // 4))
        shifted.append(builder.fsub(repeated, splat(builder, offset[d], vector), flags=flags))
    return shifted


def squared_distances(builder, half, shifted, flags=()):
    """(separations [dx, dy, dz], r^2) of a half's eight atom pairs: ``half`` from
    :func:`cluster_i_halves`, ``shifted`` from :func:`cluster_j_shifted`."""
    separation = [builder.fsub(half[d], shifted[d], flags=flags) for d in range(3)]
    r2 = builder.fmul(separation[0], separation[0], flags=flags)
    for d in (1, 2):
        r2 = builder.fadd(r2, builder.fmul(separation[d], separation[d], flags=flags), flags=flags)
    return separation, r2


def array_data(context, builder, array_type, array):
    """Pointer to the first element of a numba array value."""
    return context.make_array(array_type)(context, builder, array).data


def _element_bytes(vector: ir.VectorType) -> int:
    element = vector.element
    if isinstance(element, ir.DoubleType):
        return 8
    return 4 if isinstance(element, ir.FloatType) else element.width // 8


def load_vector(builder, pointer, index, vector: ir.VectorType):
    """The ``vector.count`` elements from ``pointer[index]`` (element alignment only)."""
    address = builder.bitcast(builder.gep(pointer, [index]), vector.as_pointer())
    return builder.load(address, align=_element_bytes(vector))


def store_vector(builder, value, pointer, index) -> None:
    """Store a vector at ``pointer[index]`` (element alignment only)."""
    address = builder.bitcast(builder.gep(pointer, [index]), value.type.as_pointer())
    builder.store(value, address, align=_element_bytes(value.type))


def compare_mask(builder, condition) -> ir.Value:
    """An <8 x i1> condition as an i64 with bit k = lane k (a movemask)."""
    return builder.zext(builder.bitcast(condition, ir.IntType(8)), ir.IntType(64))


def permute_lanes(builder, values, mask, table):
    """The lanes of the <8 x i32> ``values`` set in ``mask`` (i64 < 256), moved to the
    front, in order (the lanes after them undefined); ``table`` points at
    ``PERMUTATIONS``. AVX2's vpermd: only where ``PERMUTE``."""
    words = ir.VectorType(ir.IntType(32), 8)
    permd = cgutils.get_or_insert_function(
        builder.module, ir.FunctionType(words, [words, words]), "llvm.x86.avx2.permd"
    )
    row = builder.mul(mask, ir.Constant(ir.IntType(64), 8))
    return builder.call(permd, [values, load_vector(builder, table, row, words)])


def _stream_store(array, index, value) -> None:
    array[index] = value


def _store_fence() -> None:
    """Python's stores are ordered already."""


def _move_within(array, to, start, count) -> None:
    array[to : to + count] = array[start : start + count]  # numpy copies overlaps first


@python_twin(_stream_store)
@intrinsic
def stream_store(typingctx, array, index, value):
    """``array[index] = value`` as a non-temporal store: written to memory through the
    write-combining buffers, past the caches, with no read of the line first. For large
    outputs that are not read again soon; a ``store_fence()`` after the last one orders
    them before what follows."""
    sig = types.void(array, types.uint64, array.dtype)

    def codegen(context, builder, signature, args):
        data = array_data(context, builder, signature.args[0], args[0])
        pointer = builder.gep(data, [args[1]])
        store = builder.store(args[2], pointer)
        flag = builder.module.add_metadata([ir.Constant(ir.IntType(32), 1)])
        store.set_metadata("nontemporal", flag)
        return context.get_dummy_value()

    return sig, codegen


@python_twin(_store_fence)
@intrinsic
def store_fence(typingctx):
    """A full memory fence (``mfence`` on x86): every earlier store, non-temporal ones
    included, is visible before any later memory access."""
    sig = types.void()

    def codegen(context, builder, signature, args):
        builder.fence("seq_cst")
        return context.get_dummy_value()

    return sig, codegen


@python_twin(_move_within)
@intrinsic
def move_within(typingctx, array, to, start, count):
    """``array[to:to + count] = array[start:start + count]`` for a contiguous 1-D array,
    overlap allowed (LLVM's ``memmove``: the C library's, at memory speed). No bounds
    check: the caller keeps both ranges inside the array."""
    if not (isinstance(array, types.Array) and array.ndim == 1 and array.layout == "C"):
        return None
    sig = types.void(array, types.int64, types.int64, types.int64)

    def codegen(context, builder, signature, args):
        data = array_data(context, builder, signature.args[0], args[0])
        itemsize = context.get_abi_sizeof(context.get_data_type(signature.args[0].dtype))
        cgutils.raw_memmove(
            builder,
            builder.gep(data, [args[1]]),
            builder.gep(data, [args[2]]),
            args[3],
            itemsize,
        )
        return context.get_dummy_value()

    return sig, codegen


def _gather_rows4(rows, partners, k, gx, gy, gz) -> None:
    for n in range(k, k + 4):
        q = partners[n]
        gx[n], gy[n], gz[n] = rows[q, 0], rows[q, 1], rows[q, 2]


def _gather_shifted_rows4(rows, partners, shifts, codes, k, gx, gy, gz) -> None:
    for n in range(k, k + 4):
        q, code = partners[n], codes[n]
        gx[n] = rows[q, 0] + shifts[code, 0]
        gy[n] = rows[q, 1] + shifts[code, 1]
        gz[n] = rows[q, 2] + shifts[code, 2]


def _scatter_sub_rows4(rows, partners, k, fx, fy, fz) -> None:
    for n in range(k, k + 4):
        q = partners[n]
        rows[q, 0] -= fx[n]
        rows[q, 1] -= fy[n]
        rows[q, 2] -= fz[n]


def _rows_and_partners(context, builder, signature, args, k):
    """Data pointers of the (N, 3) rows and the three columns, and the four partners'
    first elements (3 q) from ``partners[k:k + 4]``."""
    rows, partners = (array_data(context, builder, signature.args[n], args[n]) for n in (0, 1))
    columns = [array_data(context, builder, signature.args[n], args[n]) for n in (-3, -2, -1)]
    firsts = []
    for n in range(4):
        at = builder.add(k, ir.Constant(_I64, n))
        q = builder.load(builder.gep(partners, [at]))
        firsts.append(builder.mul(builder.zext(q, _I64), ir.Constant(_I64, 3)))
    return rows, columns, firsts


def _rows4_types(rows, partners, columns) -> bool:
    """Whether ``rows`` is a C-contiguous (N, 3) float64 or float32 array, ``partners``
    C-contiguous int32 or uint32, and ``columns`` C-contiguous of the rows' type (raw
    pointer reads)."""
    return (
        isinstance(rows, types.Array)
        and rows.ndim == 2
        and rows.layout == "C"
        and rows.dtype in (types.float64, types.float32)
        and isinstance(partners, types.Array)
        and partners.ndim == 1
        and partners.layout == "C"
        and partners.dtype in (types.int32, types.uint32)
        and all(is_vector_array(c, rows.dtype) for c in columns)
    )


def _vectors(context, array_type) -> tuple[ir.VectorType, ir.VectorType]:
    """2- and 4-lane vectors of ``array_type``'s elements."""
    element = context.get_value_type(array_type.dtype)
    return ir.VectorType(element, 2), ir.VectorType(element, 4)


def _gather_codegen(shifted: bool):
    """The code of ``gather_rows4`` (``shifted``: of ``gather_shifted_rows4``)."""

    def codegen(context, builder, signature, args):
        k = args[-4]
        data, columns, firsts = _rows_and_partners(context, builder, signature, args, k)
        two, four = _vectors(context, signature.args[0])
        if shifted:
            table = array_data(context, builder, signature.args[2], args[2])
            codes = array_data(context, builder, signature.args[3], args[3])
        pairs, zs = [], []
        for n, first in enumerate(firsts):
            xy = load_vector(builder, data, first, two)
            z = builder.load(builder.gep(data, [builder.add(first, ir.Constant(_I64, 2))]))
            if shifted:  # the same additions as scalar code: the same bits
                code = builder.load(builder.gep(codes, [builder.add(k, ir.Constant(_I64, n))]))
                row = builder.mul(builder.zext(code, _I64), ir.Constant(_I64, 3))
                xy = builder.fadd(xy, load_vector(builder, table, row, two))
                z = builder.fadd(
                    z, builder.load(builder.gep(table, [builder.add(row, ir.Constant(_I64, 2))]))
                )
            pairs.append(xy)
            zs.append(z)
        low = shuffle(builder, pairs[0], pairs[2], [0, 1, 2, 3])  # x0 y0 x2 y2
        high = shuffle(builder, pairs[1], pairs[3], [0, 1, 2, 3])  # x1 y1 x3 y3
        x = shuffle(builder, low, high, [0, 4, 2, 6])
        y = shuffle(builder, low, high, [1, 5, 3, 7])
        z = ir.Constant(four, ir.Undefined)
        for n, value in enumerate(zs):
            z = builder.insert_element(z, value, ir.Constant(ir.IntType(32), n))
        for column, value in zip(columns, (x, y, z), strict=True):
            store_vector(builder, value, column, k)
        return context.get_dummy_value()

    return codegen


@python_twin(_gather_rows4)
@intrinsic
def gather_rows4(typingctx, rows, partners, k, gx, gy, gz):
    """``gx[n], gy[n], gz[n] = rows[q]`` for the four partners q = ``partners[n]``, n = k
    to k + 3, of a C-contiguous (N, 3) float64 (or float32) array: per partner a 16-byte
    (8-byte) load of (x, y) and a load of z, transposed in registers into a 4-lane store per column
    (where a loop of scalar copies spends three loads and three stores per partner).
    Partner slots are read as unsigned (non-negative); no bounds checks: the caller
    keeps k + 3 inside ``partners`` and each q inside ``rows``."""
    if not _rows4_types(rows, partners, (gx, gy, gz)):
        return None
    return types.void(rows, partners, types.int64, gx, gy, gz), _gather_codegen(False)


@python_twin(_gather_shifted_rows4)
@intrinsic
def gather_shifted_rows4(typingctx, rows, partners, shifts, codes, k, gx, gy, gz):
    """:func:`gather_rows4` with each partner's image shift added: ``rows[q] +
    shifts[codes[n]]`` (``shifts`` a C-contiguous (S, 3) table of the rows' type, ``codes`` uint8
    from index 0 as ``partners``)."""
    if not (
        _rows4_types(rows, partners, (gx, gy, gz))
        and _rows4_types(shifts, partners, ())
        and shifts.dtype == rows.dtype
        and isinstance(codes, types.Array)
        and codes.ndim == 1
        and codes.layout == "C"
        and codes.dtype == types.uint8
    ):
        return None
    sig = types.void(rows, partners, shifts, codes, types.int64, gx, gy, gz)
    return sig, _gather_codegen(True)


@python_twin(_scatter_sub_rows4)
@intrinsic
def scatter_sub_rows4(typingctx, rows, partners, k, fx, fy, fz):
    """``rows[q] -= (fx[n], fy[n], fz[n])`` for the four partners q = ``partners[n]``, n =
    k to k + 3, which must be distinct: the three columns loaded as 4-lane vectors and
    transposed in registers, then per partner one subtraction of (x, y) as a pair and
    one of z (the same roundings as scalar code). No bounds checks, as
    :func:`gather_rows4`."""
    if not _rows4_types(rows, partners, (fx, fy, fz)):
        return None
    sig = types.void(rows, partners, types.int64, fx, fy, fz)

    def codegen(context, builder, signature, args):
        data, columns, firsts = _rows_and_partners(context, builder, signature, args, args[2])
        two, four = _vectors(context, signature.args[0])
        x, y, z = (load_vector(builder, column, args[2], four) for column in columns)
        even = shuffle(builder, x, y, [0, 4, 2, 6])  # x0 y0 x2 y2
        odd = shuffle(builder, x, y, [1, 5, 3, 7])  # x1 y1 x3 y3
        for n, first in enumerate(firsts):
            source = even if n % 2 == 0 else odd
            half = shuffle(builder, source, source, [2 * (n // 2), 2 * (n // 2) + 1])
            old = load_vector(builder, data, first, two)
            store_vector(builder, builder.fsub(old, half), data, first)
            at = builder.gep(data, [builder.add(first, ir.Constant(_I64, 2))])
            value = builder.extract_element(z, ir.Constant(ir.IntType(32), n))
            builder.store(builder.fsub(builder.load(at), value), at)
        return context.get_dummy_value()

    return sig, codegen
