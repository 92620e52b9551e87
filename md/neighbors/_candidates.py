"""The cell search's candidate test (``_near_bits``, the ``_near_pack`` family, ``_keep``):
the distance test of 8-lane blocks of candidates as LLVM-IR intrinsics built from
``md._simd`` (compare masks; the hits packed by AVX2 lane permutes where numba compiles
for AVX2, else by scanning a bit mask), each with a Python twin for
``NUMBA_DISABLE_JIT=1``. Called by the search in ``_cell_kernels`` (see its docstring).
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

from md._simd import (
    PERMUTE,
    array_data,
    bit_count,
    compare_mask,
    is_vector_array,
    load_vector,
    permute_lanes,
    python_twin,
    splat,
    store_vector,
    trailing_zeros,
)


class _Candidates:
    """IR of the search's candidate test (``_near_bits``, the ``_near_pack`` family): the
    distance test of one block of 8 candidates."""

    def __init__(self, context, builder, signature, args):
        f64, i32 = ir.DoubleType(), ir.IntType(32)
        self.builder = builder
        self.doubles = ir.VectorType(f64, 8)
        self.words = ir.VectorType(i32, 8)
        self.centre = [splat(builder, args[k], self.doubles) for k in range(3)]
        self.r2 = splat(builder, args[3], self.doubles)
        self.arrays = [
            array_data(context, builder, signature.args[k], args[k]) for k in (4, 5, 6, 7)
        ]
        self.start = args[8]

    def block(self, block):
        """(packed values, <8 x i1> near) of candidates start + 8 block + 0..7: closer
        than sqrt(r2_max), left to right as dx dx + dy dy + dz dz (the brute-force
        search's arithmetic: the same candidates pass)."""
        builder = self.builder
        index = builder.add(self.start, ir.Constant(ir.IntType(64), 8 * block))
        kinds = (self.doubles, self.doubles, self.doubles, self.words)
        *coordinates, values = (
            load_vector(builder, a, index, v) for a, v in zip(self.arrays, kinds, strict=True)
        )
        dx, dy, dz = (builder.fsub(c, t) for c, t in zip(self.centre, coordinates, strict=True))
        d2 = builder.fadd(
            builder.fadd(builder.fmul(dx, dx), builder.fmul(dy, dy)), builder.fmul(dz, dz)
        )
        return values, builder.fcmp_ordered("<", d2, self.r2)


def _near_lanes(xi, yi, zi, r2_max, tx, ty, tz, start, count):
    """Python twin of ``_Candidates``: bool per candidate start..start+count-1, closer than
    sqrt(r2_max), with the same arithmetic (no fused multiply-add)."""
    lanes = slice(start, start + count)
    with np.errstate(over="ignore", invalid="ignore"):  # lanes past the last are any bits
        dx, dy, dz = xi - tx[lanes], yi - ty[lanes], zi - tz[lanes]
        return dx * dx + dy * dy + dz * dz < r2_max


def _candidate_types(tx, ty, tz, packed):
    """Whether the candidate arrays are what ``_Candidates`` reads."""
    wanted = (types.float64, types.float64, types.float64, types.uint32)
    return all(is_vector_array(a, d) for a, d in zip((tx, ty, tz, packed), wanted, strict=True))


def _near_bits_twin(xi, yi, zi, r2_max, tx, ty, tz, packed, start):
    """``_near_bits`` in Python (``md._simd.python_twin``)."""
    near = _near_lanes(xi, yi, zi, r2_max, tx, ty, tz, start, 64)
    return np.uint64(sum(1 << int(k) for k in np.flatnonzero(near)))


@python_twin(_near_bits_twin)
@intrinsic
def _near_bits(typingctx, xi, yi, zi, r2_max, tx, ty, tz, packed, start):
    """Bit k set where candidate ``start + k`` (k < 64) is closer than sqrt(r2_max).

    Eight blocks of ``_Candidates``, each block's <8 x i1> mask put straight
    into the word (a movemask: numba has no way to say it). Reads 64 entries
    from ``start`` of the C-contiguous float64 ``tx, ty, tz`` and uint32
    ``packed``: they need that many readable entries past their last
    candidate, and the caller masks the bits past it.
    """
    if not _candidate_types(tx, ty, tz, packed):
        return None
    sig = types.uint64(
        types.float64,
        types.float64,
        types.float64,
        types.float64,
        tx,
        ty,
        tz,
        packed,
        types.intp,
    )

    def codegen(context, builder, signature, args):
        i64 = ir.IntType(64)
        test = _Candidates(context, builder, signature, args)
        word = ir.Constant(i64, 0)
        for block in range(8):
            _, near = test.block(block)
            shifted = builder.shl(compare_mask(builder, near), ir.Constant(i64, 8 * block))
            word = builder.or_(word, shifted)
        return word

    return sig, codegen


def _permute_packer(blocks: int, whole: bool):
    """``_near_pack`` by AVX2 permutes (only where ``md._simd.PERMUTE``) for ``blocks``
    blocks of 8 candidates; ``whole``: all of them valid (no lane count test).

    Per block of 8 candidates (``_Candidates``), the near lanes' packed
    values move to the front of the vector (``permute_lanes``); all 8 lanes
    are stored at ``out[at:]`` and ``at`` advances by the kept count, so the
    next block overwrites the rest: no loop, no branch per candidate or hit.
    """

    def typer(typingctx, xi, yi, zi, r2_max, tx, ty, tz, packed, start, valid, table, out, at):
        if not (_candidate_types(tx, ty, tz, packed) and is_vector_array(out, types.uint32)):
            return None
        sig = types.int64(
            types.float64,
            types.float64,
            types.float64,
            types.float64,
            tx,
            ty,
            tz,
            packed,
            types.intp,
            types.intp,
            table,
            out,
            types.intp,
        )
        return sig, codegen

    def codegen(context, builder, signature, args):
        i32 = ir.IntType(32)
        test = _Candidates(context, builder, signature, args)
        valid = splat(builder, builder.trunc(args[9], i32), test.words)
        rows = array_data(context, builder, signature.args[10], args[10])
        target = array_data(context, builder, signature.args[11], args[11])
        at = args[12]
        for block in range(blocks):
            values, kept = test.block(block)
            if not whole:
                lanes = ir.Constant(test.words, [8 * block + k for k in range(8)])
                kept = builder.and_(kept, builder.icmp_signed("<", lanes, valid))
            mask = compare_mask(builder, kept)
            store_vector(builder, permute_lanes(builder, values, mask, rows), target, at)
            at = builder.add(at, builder.ctpop(mask))
        return at

    def twin(xi, yi, zi, r2_max, tx, ty, tz, packed, start, valid, table, out, at):
        """The same in Python (``md._simd.python_twin``): each block's 8 lanes stored as
        the permute leaves them (kept values first, then lane 0's as the table's zeros
        pick)."""
        for block in range(blocks):
            first = start + 8 * block
            kept = _near_lanes(xi, yi, zi, r2_max, tx, ty, tz, first, 8)
            if not whole:
                kept &= 8 * block + np.arange(8) < valid
            mask = int(np.dot(kept, 1 << np.arange(8)))
            out[at : at + 8] = packed[first : first + 8][table[mask]]
            at += int(kept.sum())
        return np.int64(at)

    typer.__name__ = f"_near_pack_{blocks}_{'whole' if whole else 'partial'}"
    return python_twin(twin)(intrinsic(typer))


_near_pack_permute_whole = _permute_packer(8, whole=True)


_near_pack_permute_block = _permute_packer(1, whole=False)


@njit(cache=True, inline="always", error_model="numpy")
def _near_pack_blocks(xi, yi, zi, r2_max, tx, ty, tz, packed, start, valid, table, out, at):
    """``_near_pack`` by AVX2 permutes, block by block: a range's last, partial word
    tests only the blocks it has."""
    done = 0
    while done < valid:
        at = _near_pack_permute_block(
            xi, yi, zi, r2_max, tx, ty, tz, packed, start + done, valid - done, table, out, at
        )
        done += 8
    return at


@njit(cache=True, inline="always", error_model="numpy")
def _near_pack_scan(xi, yi, zi, r2_max, tx, ty, tz, packed, start, valid, table, out, at):
    """``_near_pack`` on any CPU: ``_near_bits``, then the set bits one by one."""
    m = _near_bits(xi, yi, zi, r2_max, tx, ty, tz, packed, start)
    if valid < 64:
        m &= (np.uint64(1) << np.uint64(valid)) - np.uint64(1)
    end = np.uint64(at)  # unsigned indices: no negative-index wrap code in the loop
    row = packed[start:]
    while m:
        out[end] = row[np.uint64(trailing_zeros(m))]
        end += np.uint64(1)
        m &= m - np.uint64(1)
    return np.int64(end)


#: Write the candidates start..start+valid-1 (valid <= 64) closer than sqrt(r2_max),
#: their packed values, at ``out[at:]`` in order; return the new end. The 8 entries
#: from it on may be overwritten (the permute path stores whole blocks).
_near_pack = _near_pack_blocks if PERMUTE else _near_pack_scan


#: ``_near_pack`` for exactly 64 candidates (``valid`` ignored).
_near_pack_whole = _near_pack_permute_whole if PERMUTE else _near_pack_scan


@njit(cache=True, inline="always", error_model="numpy")
def _keep(xi, yi, zi, r2_max, cx, cy, cz, c_packed, first, last, masks, base, count, capacity, out):
    """List the candidates first..last-1 closer than sqrt(r2_max), packed, at
    ``out[base + count:]``; return how many: the exact path near the end of a
    chunk's region.

    The search uses ``_near_pack`` while its region has room for every
    candidate and a block's spill; here the bit masks are counted first and
    nothing is written past ``capacity``: past it the hits are only counted.
    """
    n = last - first
    n_words = (n + 63) // 64
    found = 0
    for w in range(n_words):
        m = _near_bits(xi, yi, zi, r2_max, cx, cy, cz, c_packed, first + 64 * w)
        if w == n_words - 1 and n % 64:
            m &= (np.uint64(1) << np.uint64(n % 64)) - np.uint64(1)
        masks[w] = m
        found += bit_count(m)
    if count + found <= capacity:
        at = np.uint64(base + count)
        for w in range(n_words):
            m = masks[w]
            row = c_packed[first + 64 * w :]
            while m:
                out[at] = row[np.uint64(trailing_zeros(m))]
                at += np.uint64(1)
                m &= m - np.uint64(1)
    return found
