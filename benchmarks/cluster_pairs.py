"""Would GROMACS's cluster-pair layout make our Lennard-Jones force call faster?

An experiment, not a part of the engine: the 32000-atom melt's LJ forces
(cutoff 2.5, list radius 2.8, single type, no virial) computed over a list of
cluster pairs, the layout of GROMACS's nbnxm kernels, and timed against the pair
frame's force call (``LennardJones.energy_forces`` over the slot frame) in
interleaved repeats, double and float32.

The clusters: columns of the xy plane about (4 / density)^(1/3) wide, each
sorted by z and cut into clusters of four atoms (the last one padded with
fillers, far away and apart); positions stored relative to the cluster's
centre, so float32 keeps its precision in any box. The list: for each cluster
the clusters (itself included, a periodic image as a separate entry) whose
bounding boxes come within the list radius, each pair once, with its offset
(difference of the two centres less the image shift) rounded to the kernel's
precision. The kernels (the first two vectorised by LLVM from plain loops):

``flat``
    The 4x4 atom pairs of a cluster pair as one loop of 16 lanes (i's
    coordinates stored broadcast and j's replicated, so both are contiguous
    loads); the i forces summed per lane in scratch, the j forces per lane into
    a replicated buffer, both reduced per atom at the end.
``j buffer``
    Per i-cluster, the j-clusters' shifted positions copied into contiguous
    scratch (four at a time), then one vectorised loop per i atom over all of
    them, its force a register reduction; the j forces scattered back per
    cluster. ``pair loop only`` times that loop without the copy and the
    scatter: what the layout gives if those cost nothing.
``simd 2x4``
    Written as LLVM vector IR (a numba intrinsic per i-cluster, float32 only):
    two i atoms by four j atoms in each 8-lane register (the idea of GROMACS's
    2xMM kernels), two registers per cluster pair, the i forces and the energy
    accumulated in registers across the whole j loop, a j-cluster's forces
    summed across the register's halves and added to memory once.
``pruned``
    The same over the cluster pairs that have an atom pair within the list
    radius (the bounding boxes keep about a third more), as GROMACS's pair
    search checks atom distances after the boxes.
``marking``
    The simd kernel on the whole list, also marking the cluster pairs with an atom
    pair within the list radius from the r^2 it computes anyway (GROMACS's
    dynamic pruning): the first call after a build gives the pruned list.

Each row: median ms, the median of per-repeat ratios to the frame's double call,
and the largest force difference from it. The list evaluates every atom pair of
every listed cluster pair; the line above the table gives how many that is per
pair of the frame's list.

    python benchmarks/cluster_pairs.py                 # 32000 atoms, 31 repeats
    python benchmarks/cluster_pairs.py --cells 12 --repeats 11
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the checkout, from anywhere

from _machine import machine_line  # noqa: E402

import md  # noqa: E402
from md._simd import array_data, load_vector, splat, store_vector  # noqa: E402
from md.parallel import set_threads  # noqa: E402
from potentials import LennardJones  # noqa: E402

VECTOR_MATH = {"reassoc", "contract", "nsz", "arcp"}
M = 4  # atoms per cluster
LANES = M * M  # atom pairs per cluster pair
PAD = 16  # the j buffer's rows padded to whole vector iterations (8 float32 lanes, unrolled 2)
PAD_AT = 10.0  # padding lanes' coordinates: past the cutoff from any i atom (within 2 of 0)
#: A filler's z relative to its cluster's centre: -FILLER where it is a j atom, +FILLER as an
#: i atom (so no two fillers meet), 10 apart in x within a cluster. Not farther: float32's
#: 1/r^12 underflows into slow denormals past r ~ 1400.
FILLER = 100.0


@njit(cache=True)
def cluster_grid(positions, box, density):
    """Columns, clusters and their atoms; returns (ncx, ncy, first cluster per column,
    atom per cluster slot (-1: filler), centres, bounding boxes (lo, hi), relative
    positions (clusters, 3, M))."""
    n = positions.shape[0]
    side = (M / density) ** (1.0 / 3.0)
    ncx = max(1, int(box[0] / side))
    ncy = max(1, int(box[1] / side))
    wrapped = np.empty((n, 3))
    column = np.empty(n, np.int64)
    counts = np.zeros(ncx * ncy + 1, np.int64)
    for i in range(n):
        for d in range(3):
            wrapped[i, d] = positions[i, d] % box[d]
        cx = min(int(wrapped[i, 0] * ncx / box[0]), ncx - 1)
        cy = min(int(wrapped[i, 1] * ncy / box[1]), ncy - 1)
        column[i] = cx * ncy + cy
        counts[column[i] + 1] += 1
    starts = np.cumsum(counts)
    fill = starts[:-1].copy()
    order = np.empty(n, np.int64)
    for i in range(n):
        order[fill[column[i]]] = i
        fill[column[i]] += 1
    n_columns = ncx * ncy
    first = np.zeros(n_columns + 1, np.int64)
    for c in range(n_columns):
        first[c + 1] = first[c] + (starts[c + 1] - starts[c] + M - 1) // M
    n_clusters = first[n_columns]
    atom = np.full(n_clusters * M, -1, np.int64)
    for c in range(n_columns):
        members = order[starts[c] : starts[c + 1]]
        by_z = members[np.argsort(wrapped[members, 2])]
        atom[first[c] * M : first[c] * M + by_z.shape[0]] = by_z
    centre = np.zeros((n_clusters, 3))
    bounds = np.zeros((n_clusters, 6))
    relative = np.zeros((n_clusters, 3, M))
    for cl in range(n_clusters):
        for d in range(3):
            bounds[cl, d] = np.inf
            bounds[cl, 3 + d] = -np.inf
        for b in range(M):
            i = atom[cl * M + b]
            if i >= 0:
                for d in range(3):
                    bounds[cl, d] = min(bounds[cl, d], wrapped[i, d])
                    bounds[cl, 3 + d] = max(bounds[cl, 3 + d], wrapped[i, d])
        for d in range(3):
            centre[cl, d] = 0.5 * (bounds[cl, d] + bounds[cl, 3 + d])
        for b in range(M):
            i = atom[cl * M + b]
            for d in range(3):
                relative[cl, d, b] = wrapped[i, d] - centre[cl, d] if i >= 0 else 0.0
            if i < 0:  # a filler: far from every atom (as a j atom; see FILLER)
                relative[cl, 0, b] = 10.0 * b
                relative[cl, 2, b] = -FILLER
    return ncx, ncy, first, atom, centre, bounds, relative


@njit(cache=True)
def cluster_pairs(
    box, ncx, ncy, first, centre, bounds, radius, relative=None, counts=None, sure=0.0
):
    """For each cluster, the clusters (index >= its own; itself at zero shift only)
    whose bounding boxes come within ``radius``, with offset centre_i - centre_j -
    shift. Returns (starts, partners, offsets).

    A column's clusters are sorted by z (so are their boxes' lower and upper z), so
    each neighbouring column's window of candidates is a run of its clusters that only
    moves up as ci moves up its own column (two cursors per column and image); without
    the atom check the candidates are filtered branch-free.
    With ``relative`` and ``counts`` (atoms per cluster), a pair whose boxes are
    ``sure`` or farther apart is kept only if an atom pair lies within ``radius``
    (closer boxes are kept unchecked)."""
    n_clusters = centre.shape[0]
    column_of = np.empty(n_clusters, np.int64)
    for c in range(ncx * ncy):
        column_of[first[c] : first[c + 1]] = c
    width_x, width_y = box[0] / ncx, box[1] / ncy
    reach_x = int(np.ceil(radius / width_x))
    reach_y = int(np.ceil(radius / width_y))
    tops = bounds[:, 5].copy()  # each column's upper and lower z, increasing within it
    floors = bounds[:, 2].copy()
    capacity = n_clusters * 64
    partners = np.empty(capacity, np.int32)
    offsets = np.empty((capacity, 3))
    starts = np.zeros(n_clusters + 1, np.int64)
    shift = np.zeros(3)
    r2max = radius * radius
    k = 0
    # Sliding windows: along a column the clusters' boxes rise, so for each neighbouring
    # (column, image) the window of j-clusters only moves up as ci does; two cursors per
    # slot, reset at each new i column (no binary search: its branches mispredict).
    n_slots = (2 * reach_x + 1) * (2 * reach_y + 1) * 3
    near_scratch = np.empty(64, np.int64)
    lower_at = np.full(n_slots, -1, np.int64)
    upper_at = np.full(n_slots, -1, np.int64)
    for ci in range(n_clusters):
        cx, cy = column_of[ci] // ncy, column_of[ci] % ncy
        if ci == first[column_of[ci]]:
            lower_at[:] = -1
            upper_at[:] = -1
        for dx in range(-reach_x, reach_x + 1):
            ux = (cx + dx) % ncx
            shift[0] = ((cx + dx) - ux) // ncx * box[0]
            gx = max(
                (cx + dx) * width_x - bounds[ci, 3], bounds[ci, 0] - (cx + dx + 1) * width_x, 0.0
            )
            if gx * gx >= r2max:
                continue
            for dy in range(-reach_y, reach_y + 1):
                uy = (cy + dy) % ncy
                shift[1] = ((cy + dy) - uy) // ncy * box[1]
                gy = max(
                    (cy + dy) * width_y - bounds[ci, 4],
                    bounds[ci, 1] - (cy + dy + 1) * width_y,
                    0.0,
                )
                if gx * gx + gy * gy >= r2max:
                    continue
                col = ux * ncy + uy
                if first[col + 1] <= ci:
                    continue  # a column before ci's: every pair there was listed from its side
                for dz in range(-1, 2):
                    if (dz == -1 and bounds[ci, 2] >= radius) or (
                        dz == 1 and bounds[ci, 5] + radius < box[2]
                    ):
                        continue  # the images below (above) are farther than the radius
                    shift[2] = dz * box[2]
                    zero = shift[0] == 0.0 and shift[1] == 0.0 and dz == 0
                    low = bounds[ci, 2] - radius - shift[2]  # the window in the column's frame
                    high = bounds[ci, 5] + radius - shift[2]
                    slot = ((dx + reach_x) * (2 * reach_y + 1) + dy + reach_y) * 3 + dz + 1
                    begin = lower_at[slot] if lower_at[slot] >= 0 else first[col]
                    while begin < first[col + 1] and tops[begin] < low:
                        begin += 1
                    end = max(upper_at[slot], begin)
                    while end < first[col + 1] and floors[end] <= high:
                        end += 1
                    lower_at[slot], upper_at[slot] = begin, end
                    begin = max(begin, ci)
                    end = max(end, begin)
                    if begin == ci and not zero:
                        begin += 1  # each pair once (boxes wider than twice the radius)
                    if k + (end - begin) > capacity:
                        capacity = 2 * (k + (end - begin))
                        partners = np.concatenate((partners[:k], np.empty(capacity - k, np.int32)))
                        offsets = np.concatenate((offsets[:k], np.empty((capacity - k, 3))))
                    sx, sy, sz = shift[0], shift[1], shift[2]
                    if relative is None:
                        # the boxes' gaps first (no dependence between candidates), then a
                        # branch-free compaction whose only chain is the count
                        if end - begin > near_scratch.shape[0]:
                            near_scratch = np.empty(2 * (end - begin), np.int64)
                        for j in range(end - begin):
                            cj = begin + j
                            ex = max(
                                max(
                                    bounds[cj, 0] + sx - bounds[ci, 3],
                                    bounds[ci, 0] - bounds[cj, 3] - sx,
                                ),
                                0.0,
                            )
                            ey = max(
                                max(
                                    bounds[cj, 1] + sy - bounds[ci, 4],
                                    bounds[ci, 1] - bounds[cj, 4] - sy,
                                ),
                                0.0,
                            )
                            ez = max(
                                max(
                                    bounds[cj, 2] + sz - bounds[ci, 5],
                                    bounds[ci, 2] - bounds[cj, 5] - sz,
                                ),
                                0.0,
                            )
                            near_scratch[j] = ex * ex + ey * ey + ez * ez < r2max
                        for j in range(end - begin):
                            cj = begin + j
                            partners[k] = cj
                            offsets[k, 0] = centre[ci, 0] - centre[cj, 0] - sx
                            offsets[k, 1] = centre[ci, 1] - centre[cj, 1] - sy
                            offsets[k, 2] = centre[ci, 2] - centre[cj, 2] - sz
                            k += near_scratch[j]
                        continue
                    for cj in range(begin, end):
                        gap2 = 0.0
                        for d in range(3):
                            above = bounds[cj, d] + shift[d] - bounds[ci, 3 + d]
                            below = bounds[ci, d] - bounds[cj, 3 + d] - shift[d]
                            gap = max(above, below, 0.0)
                            gap2 += gap * gap
                        if gap2 >= r2max:
                            continue
                        if gap2 >= sure * sure:
                            near = False
                            for a in range(counts[ci]):
                                for b in range(a + 1 if cj == ci else 0, counts[cj]):
                                    r2 = 0.0
                                    for d in range(3):
                                        g = (
                                            relative[ci, d, a]
                                            - relative[cj, d, b]
                                            + centre[ci, d]
                                            - centre[cj, d]
                                            - shift[d]
                                        )
                                        r2 += g * g
                                    near = near or r2 < r2max
                            if not near:
                                continue
                        partners[k] = cj
                        for d in range(3):
                            offsets[k, d] = centre[ci, d] - centre[cj, d] - shift[d]
                        k += 1
        starts[ci + 1] = k
    return starts, partners[:k].copy(), offsets[:k].copy()


def flat_kernel(real):
    """The 16 atom pairs of a cluster pair as one vector loop (see the docstring)."""

    @njit(fastmath=VECTOR_MATH, error_model="numpy")
    def kernel(xi, xj, starts, partners, offsets, rc2, fi, fj):
        cut = np.full(2 * LANES, real(rc2))  # the second half: a cluster with itself, b > a
        for a in range(M):
            for b in range(a + 1):
                cut[LANES + a * M + b] = real(-1.0)
        acc = np.zeros(4 * LANES, real)
        fj[:] = 0.0
        energy = 0.0
        for ci in range(starts.shape[0] - 1):
            bi = ci * 3 * LANES
            acc[:] = 0.0
            for k in range(starts[ci], starts[ci + 1]):
                cj = np.uint32(partners[k])
                bj = cj * 3 * LANES
                ox, oy, oz = offsets[k, 0], offsets[k, 1], offsets[k, 2]
                bc = LANES if cj == ci else 0
                for lane in range(LANES):
                    dx = xi[bi + lane] - xj[bj + lane] + ox
                    dy = xi[bi + LANES + lane] - xj[bj + LANES + lane] + oy
                    dz = xi[bi + 2 * LANES + lane] - xj[bj + 2 * LANES + lane] + oz
                    r2 = dx * dx + dy * dy + dz * dz
                    keep = r2 < cut[bc + lane]
                    # clamped: a far filler's 1/r^12 would underflow into slow denormals
                    ir2 = real(1.0) / min(r2, cut[bc + lane])
                    ir6 = ir2 * ir2 * ir2
                    fr = ir6 * (real(48.0) * ir6 - real(24.0)) * ir2 if keep else real(0.0)
                    u = real(4.0) * ir6 * (ir6 - real(1.0))
                    acc[3 * LANES + lane] += u if keep else real(0.0)
                    acc[lane] += fr * dx
                    acc[LANES + lane] += fr * dy
                    acc[2 * LANES + lane] += fr * dz
                    fj[bj + lane] -= fr * dx
                    fj[bj + LANES + lane] -= fr * dy
                    fj[bj + 2 * LANES + lane] -= fr * dz
            fi[bi : bi + 3 * LANES] = acc[: 3 * LANES]
            energy += acc[3 * LANES :].sum()
        return energy

    return kernel


def flat_forces(fi, fj):
    """Per-atom forces (clusters, 3, M) from the flat kernel's lane buffers: i lane
    a*M+b belongs to atom a, j lane a*M+b to atom b."""
    lanes_i = fi.reshape(-1, 3, M, M)
    lanes_j = fj.reshape(-1, 3, M, M)
    return lanes_i.sum(axis=3) + lanes_j.sum(axis=2)


def buffer_kernel(real, copy=True, scatter=True):
    """Per i-cluster j buffer, one vector loop per i atom (see the docstring)."""

    @njit(fastmath=VECTOR_MATH, error_model="numpy")
    def kernel(x, counts, starts, partners, offsets, rc2r, forces):
        rc2 = real(rc2r)
        most = 0
        for ci in range(starts.shape[0] - 1):
            most = max(most, starts[ci + 1] - starts[ci])
        size = M * most + PAD
        # padding until copied into (the loop-only variant reads them as they are)
        bx, by, bz = (
            np.full(size, real(PAD_AT)),
            np.full(size, real(PAD_AT)),
            np.full(size, real(PAD_AT)),
        )
        gx, gy, gz = np.zeros(size, real), np.zeros(size, real), np.zeros(size, real)
        forces[:] = 0.0
        energy = 0.0
        for ci in range(starts.shape[0] - 1):
            xs = x[ci]
            fs = forces[ci]
            for a in range(counts[ci]):  # the cluster with itself, pairs b > a
                for b in range(a + 1, counts[ci]):
                    dx, dy, dz = xs[0, a] - xs[0, b], xs[1, a] - xs[1, b], xs[2, a] - xs[2, b]
                    r2 = dx * dx + dy * dy + dz * dz
                    if r2 < rc2:
                        ir2 = real(1.0) / r2
                        ir6 = ir2 * ir2 * ir2
                        fr = ir6 * (real(48.0) * ir6 - real(24.0)) * ir2
                        energy += real(4.0) * ir6 * (ir6 - real(1.0))
                        for d, g in ((0, dx), (1, dy), (2, dz)):
                            fs[d, a] += fr * g
                            fs[d, b] -= fr * g
            m = 0
            for k in range(starts[ci], starts[ci + 1]):
                cj = np.uint32(partners[k])
                if cj == ci:
                    continue
                if copy:
                    xc = x[cj]
                    for b in range(M):
                        bx[m + b] = xc[0, b] - offsets[k, 0]
                        by[m + b] = xc[1, b] - offsets[k, 1]
                        bz[m + b] = xc[2, b] - offsets[k, 2]
                m += M
            padded = (m + PAD - 1) // PAD * PAD
            bx[m:padded] = PAD_AT
            by[m:padded] = PAD_AT
            bz[m:padded] = PAD_AT
            gx[:padded] = 0.0
            gy[:padded] = 0.0
            gz[:padded] = 0.0
            for a in range(counts[ci]):  # not the fillers (their far 1/r^12 underflows)
                xa, ya, za = xs[0, a], xs[1, a], xs[2, a]
                sx = sy = sz = e = real(0.0)
                for lane in range(padded):
                    dx = xa - bx[lane]
                    dy = ya - by[lane]
                    dz = za - bz[lane]
                    r2 = dx * dx + dy * dy + dz * dz
                    keep = r2 < rc2
                    ir2 = real(1.0) / min(r2, rc2)
                    ir6 = ir2 * ir2 * ir2
                    fr = ir6 * (real(48.0) * ir6 - real(24.0)) * ir2 if keep else real(0.0)
                    e += real(4.0) * ir6 * (ir6 - real(1.0)) if keep else real(0.0)
                    sx += fr * dx
                    sy += fr * dy
                    sz += fr * dz
                    gx[lane] += fr * dx
                    gy[lane] += fr * dy
                    gz[lane] += fr * dz
                fs[0, a] += sx
                fs[1, a] += sy
                fs[2, a] += sz
                energy += e
            if scatter:
                m = 0
                for k in range(starts[ci], starts[ci + 1]):
                    cj = np.uint32(partners[k])
                    if cj == ci:
                        continue
                    fc = forces[cj]
                    for b in range(M):
                        fc[0, b] -= gx[m + b]
                        fc[1, b] -= gy[m + b]
                        fc[2, b] -= gz[m + b]
                    m += M
        return energy

    return kernel


# ------------------------------------------------------------------ simd 2x4 (float32)
_F32 = ir.FloatType()
_I64 = ir.IntType(64)
_V4 = ir.VectorType(_F32, 4)
_V8 = ir.VectorType(_F32, 8)
_D4 = ir.VectorType(ir.DoubleType(), 4)
_FLAGS = ("contract", "reassoc", "nsz", "arcp")


def _lanes(builder, a, b, lanes):
    return builder.shuffle_vector(
        a, b, ir.Constant(ir.VectorType(ir.IntType(32), len(lanes)), lanes)
    )


def _index(n: int):
    return ir.Constant(_I64, n)


def _eight(x: float):
    return ir.Constant(_V8, [x] * 8)


@intrinsic
def _simd_i_cluster(
    typingctx, xi, xj, offsets, partners, start, end, ci, rc2, forces, near, radius2
):
    """LJ between i-cluster ``ci`` and the j-clusters ``partners[start:end]`` (flat float32
    arrays: positions [x0..x3, y0..y3, z0..z3] per cluster, offsets 3 per pair); adds the
    i forces to ``forces[ci]``, subtracts the j forces from ``forces[cj]``; returns the
    energy. ``forces`` is float32, or float64 (each cluster pair's j sums and each i
    cluster's sums then added in double). Unless ``near`` is None, ``near[k]`` is set to
    whether cluster pair k has an atom pair within ``radius2`` (squared): GROMACS's
    dynamic pruning, at no extra pass."""
    sig = types.float64(xi, xj, offsets, partners, start, end, ci, rc2, forces, near, radius2)
    marking = not isinstance(near, types.NoneType)

    def codegen(context, builder, signature, args):
        xi_p, xj_p, off_p, part_p = (
            array_data(context, builder, signature.args[n], args[n]) for n in range(4)
        )
        f_p = array_data(context, builder, signature.args[8], args[8])
        wide = signature.args[8].dtype == types.float64
        start, end, ci, rc2 = args[4:8]
        near_p = array_data(context, builder, signature.args[9], args[9]) if marking else None
        fl = _FLAGS
        base_i = builder.mul(ci, _index(12))
        own = [
            load_vector(builder, xi_p, builder.add(base_i, _index(4 * d)), _V4) for d in range(3)
        ]
        # i atoms (0, 1) and (2, 3), each broadcast over four lanes
        pairs_i = [
            [_lanes(builder, v, v, [2 * h] * 4 + [2 * h + 1] * 4) for v in own] for h in range(2)
        ]
        # the squared cutoff per lane: -1 for the pairs a cluster with itself leaves out
        # (b <= a), so one compare masks both (no mask arithmetic, which AVX2 lacks)
        cut = splat(builder, rc2, _V8)
        own_cuts = [
            builder.select(ir.Constant(ir.VectorType(ir.IntType(1), 8), keep), cut, _eight(-1.0))
            for keep in ([0, 1, 1, 1, 0, 0, 1, 1], [0, 0, 0, 1, 0, 0, 0, 0])
        ]
        if marking:
            reach = splat(builder, args[10], _V8)
            own_reach = [
                builder.select(
                    ir.Constant(ir.VectorType(ir.IntType(1), 8), keep), reach, _eight(-1.0)
                )
                for keep in ([0, 1, 1, 1, 0, 0, 1, 1], [0, 0, 0, 1, 0, 0, 0, 0])
            ]
        sums = [cgutils.alloca_once_value(builder, _eight(0.0)) for _ in range(7)]
        with cgutils.for_range_slice(builder, start, end, _index(1)) as (k, _):
            cj = builder.sext(builder.load(builder.gep(part_p, [k])), _I64)
            itself = builder.icmp_signed("==", cj, ci)
            k3 = builder.mul(k, _index(3))
            base_j = builder.mul(cj, _index(12))
            shifted = []  # x_j - offset, the four j atoms twice
            for d in range(3):
                offset = builder.load(builder.gep(off_p, [builder.add(k3, _index(d))]))
                four = load_vector(builder, xj_p, builder.add(base_j, _index(4 * d)), _V4)
                shifted.append(
                    builder.fsub(
                        _lanes(builder, four, four, [0, 1, 2, 3] * 2),
                        splat(builder, offset, _V8),
                        flags=fl,
                    )
                )
            fj = [_eight(0.0)] * 3
            within = None
            for h in range(2):
                dx = [builder.fsub(pairs_i[h][d], shifted[d], flags=fl) for d in range(3)]
                r2 = builder.fmul(dx[0], dx[0], flags=fl)
                for d in (1, 2):
                    r2 = builder.fadd(r2, builder.fmul(dx[d], dx[d], flags=fl), flags=fl)
                mask = builder.fcmp_ordered("<", r2, builder.select(itself, own_cuts[h], cut))
                if marking:
                    bound = builder.select(itself, own_reach[h], reach)
                    close = builder.fcmp_ordered("<", r2, bound)
                    within = close if within is None else builder.or_(within, close)
                ir2 = builder.fdiv(_eight(1.0), builder.select(mask, r2, _eight(1.0)), flags=fl)
                ir6 = builder.fmul(builder.fmul(ir2, ir2, flags=fl), ir2, flags=fl)
                fr = builder.fmul(
                    ir6,
                    builder.fsub(builder.fmul(_eight(48.0), ir6, flags=fl), _eight(24.0), flags=fl),
                    flags=fl,
                )
                fr = builder.select(mask, builder.fmul(fr, ir2, flags=fl), _eight(0.0))
                u = builder.fmul(
                    builder.fmul(_eight(4.0), ir6, flags=fl),
                    builder.fsub(ir6, _eight(1.0), flags=fl),
                    flags=fl,
                )
                energy = builder.load(sums[6])
                builder.store(
                    builder.fadd(energy, builder.select(mask, u, _eight(0.0)), flags=fl), sums[6]
                )
                for d in range(3):
                    g = builder.fmul(fr, dx[d], flags=fl)
                    builder.store(
                        builder.fadd(builder.load(sums[3 * h + d]), g, flags=fl), sums[3 * h + d]
                    )
                    fj[d] = builder.fadd(fj[d], g, flags=fl)
            if marking:
                anything = builder.icmp_unsigned(
                    "!=", builder.bitcast(within, ir.IntType(8)), ir.Constant(ir.IntType(8), 0)
                )
                builder.store(builder.zext(anything, ir.IntType(8)), builder.gep(near_p, [k]))
            for d in range(3):
                low = _lanes(builder, fj[d], fj[d], [0, 1, 2, 3])
                high = _lanes(builder, fj[d], fj[d], [4, 5, 6, 7])
                summed = builder.fadd(low, high, flags=fl)
                if wide:  # a double force buffer: the j sums' error does not grow
                    summed = builder.fpext(summed, _D4)
                index = builder.add(base_j, _index(4 * d))
                old = load_vector(builder, f_p, index, summed.type)
                store_vector(builder, builder.fsub(old, summed, flags=fl), f_p, index)
        for d in range(3):  # lanes 0-3: atom 0 (2), 4-7: atom 1 (3) of each pair of i atoms
            first, second = builder.load(sums[d]), builder.load(sums[3 + d])
            total = None
            for j in range(4):
                part = _lanes(builder, first, second, [j, 4 + j, 8 + j, 12 + j])
                total = part if total is None else builder.fadd(total, part, flags=fl)
            if wide:
                total = builder.fpext(total, _D4)
            index = builder.add(base_i, _index(4 * d))
            old = load_vector(builder, f_p, index, total.type)
            store_vector(builder, builder.fadd(old, total, flags=fl), f_p, index)
        lanes = builder.load(sums[6])
        energy = builder.extract_element(lanes, ir.Constant(ir.IntType(32), 0))
        for lane in range(1, 8):
            energy = builder.fadd(energy, builder.extract_element(lanes, _index(lane)))
        return builder.fpext(energy, ir.DoubleType())

    return sig, codegen


@njit(cache=True)
def simd_forces(xi, xj, offsets, starts, partners, rc2, forces, near, radius2):
    """LJ over a cluster list with the simd 2x4 kernel (float32 arrays as
    ``_simd_i_cluster`` takes them; ``rc2`` a float32). Unless ``near`` is None, also
    marks there (uint8 per cluster pair) the pairs with an atom pair within ``radius2``
    (squared, float32), for :func:`kept_pairs`."""
    forces[:] = 0.0
    energy = 0.0
    for ci in range(starts.shape[0] - 1):
        energy += _simd_i_cluster(
            xi, xj, offsets, partners, starts[ci], starts[ci + 1], ci, rc2, forces, near, radius2
        )
    return energy


@njit(cache=True)
def kept_pairs(starts, partners, offsets, near):
    """The list with only the cluster pairs ``near`` marks (starts, partners, offsets)."""
    new_starts = np.zeros_like(starts)
    count = 0
    for ci in range(starts.shape[0] - 1):
        for k in range(starts[ci], starts[ci + 1]):
            count += near[k]
        new_starts[ci + 1] = count
    # branch-free: every row written, the count advanced by the mark (one spare row)
    kept_partners = np.empty(count + 1, partners.dtype)
    kept_offsets = np.empty((count + 1, 3), offsets.dtype)
    n = 0
    for k in range(near.shape[0]):
        kept_partners[n] = partners[k]
        kept_offsets[n, 0] = offsets[k, 0]
        kept_offsets[n, 1] = offsets[k, 1]
        kept_offsets[n, 2] = offsets[k, 2]
        n += near[k]
    return new_starts, kept_partners[:n], kept_offsets[:n]


@njit(cache=True)
def slot_cluster_pairs(starts, neighbors, codes, size):
    """The cluster pairs of the frame's own list with clusters of ``size`` consecutive slots
    (its atoms sorted by cell): each atom pair (p, q, image code) gives (p // size,
    q // size, code), made canonical (lower cluster first, the code reversed with it) and
    kept once per lower cluster (a counting sort by it, then a stamp per partner and code).
    Returns (starts, partner * 27 + code). Only counted here: a kernel over these would
    first have to put each cluster's atoms at one image (a cluster may straddle an edge)."""
    n = starts.shape[0] - 1
    n_clusters = (n + size - 1) // size
    count = np.zeros(n_clusters + 1, np.int64)
    for p in range(n):
        for k in range(starts[p], starts[p + 1]):
            count[min(p // size, neighbors[k] // size) + 1] += 1
    for a in range(n_clusters):
        count[a + 1] += count[a]
    fill = count[:-1].copy()
    keys = np.empty(starts[n], np.int64)
    for p in range(n):
        for k in range(starts[p], starts[p + 1]):
            a, b, c = p // size, neighbors[k] // size, np.int64(codes[k])
            if a > b:
                a, b, c = b, a, 26 - c
            if a == b and c > 13:
                c = 26 - c  # a cluster with its own image: one of the two
            keys[fill[a]] = b * 27 + c
            fill[a] += 1
    stamp = np.full(n_clusters * 27, -1, np.int64)
    kept_starts = np.zeros(n_clusters + 1, np.int64)
    kept = np.empty(starts[n], np.int64)
    m = 0
    for a in range(n_clusters):
        for k in range(count[a], count[a + 1]):
            if stamp[keys[k]] != a:
                stamp[keys[k]] = a
                kept[m] = keys[k]
                m += 1
        kept_starts[a + 1] = m
    return kept_starts, kept[:m].copy()


def build_times(state, neighbors, density, repeats: int = 5) -> None:
    """Print the median time of the cluster list's build (grid, box search, search with the
    atom check) beside the frame's list build, and the pairs each search keeps."""

    def median_time(call):
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            value = call()
            times.append(time.perf_counter() - start)
        return statistics.median(times), value

    t_grid, grid = median_time(lambda: cluster_grid(state.positions, state.box, density))
    ncx, ncy, first, atom, centre, bounds, relative = grid
    counts = (atom >= 0).reshape(-1, M).sum(axis=1)
    t_boxes, boxes = median_time(
        lambda: cluster_pairs(state.box, ncx, ncy, first, centre, bounds, 2.8)
    )
    t_frame = median_time(lambda: neighbors.build(state))[0]
    line = (
        f"builds, median of {repeats}: the frame's list {1e3 * t_frame:.1f} ms; "
        f"clusters {1e3 * t_grid:.1f} ms + box search {1e3 * t_boxes:.1f} ms "
        f"({len(boxes[1])} pairs)"
    )
    frame = neighbors.frame
    t_slots, slots = median_time(
        lambda: slot_cluster_pairs(frame.starts, frame.neighbors, frame.codes, M)
    )
    line += (
        f"; from the frame's list, clusters of {M} slots: {1e3 * t_slots:.1f} ms "
        f"({len(slots[1])} pairs)"
    )
    for sure in (0.0, 1.0):
        t_atoms, kept = median_time(
            lambda sure=sure: cluster_pairs(
                state.box, ncx, ncy, first, centre, bounds, 2.8, relative, counts, sure
            )
        )
        line += (
            f"; with the atom check past {sure:g}: {1e3 * t_atoms:.1f} ms ({len(kept[1])} pairs)"
        )
    print(line)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=20, help="fcc cells per edge (20)")
    parser.add_argument("--repeats", type=int, default=31, help="interleaved repeats (31)")
    args = parser.parse_args(argv)
    print(machine_line())
    set_threads(1)
    state = md.lattice("fcc", args.cells, density=0.8442)
    # a liquid's disorder: the lattice's atoms displaced by 0.15 sigma (rms per axis)
    state.positions += np.random.default_rng(1).normal(0.0, 0.15, state.positions.shape)
    lj = LennardJones(cutoff=2.5, cutoff_mode="none")
    neighbors = md.NeighborList(2.5, 0.3)
    neighbors.update(state)
    reference = lj.energy_forces(state, neighbors, virial=False)
    density = state.n_atoms / np.prod(state.box)
    ncx, ncy, first, atom, centre, bounds, relative = cluster_grid(
        state.positions, state.box, density
    )
    starts, partners, offsets = cluster_pairs(state.box, ncx, ncy, first, centre, bounds, 2.8)
    n_clusters = centre.shape[0]
    real_atoms = atom >= 0
    counts = real_atoms.reshape(-1, M).sum(axis=1)  # fillers come last in a cluster
    evaluated = len(partners) * LANES
    print(
        f"{state.n_atoms} atoms in {n_clusters} clusters of {M} ({real_atoms.mean():.1%} "
        f"atoms, the rest fillers), {len(partners)} cluster pairs: {evaluated} atom pairs "
        f"evaluated, {evaluated / neighbors.n_pairs:.2f} per pair of the frame's list "
        f"({neighbors.n_pairs}); 1 thread, {args.repeats} interleaved repeats"
    )

    def per_atom(cluster_forces):
        forces = np.zeros((state.n_atoms, 3))
        forces[atom[real_atoms]] = cluster_forces.transpose(0, 2, 1).reshape(-1, 3)[real_atoms]
        return forces

    timed = {"frame (double)": lambda: lj.energy_forces(state, neighbors, virial=False)}
    gaps = {"frame (double)": 0.0}
    scale = np.abs(reference.forces).max()
    for real in (np.float64, np.float32):
        x = relative.astype(real)
        off = offsets.astype(real)
        as_i = x.copy()
        as_i[:, 2, :][~real_atoms.reshape(-1, M)] = FILLER  # fillers as i atoms
        broadcast = np.ascontiguousarray(np.repeat(as_i, M, axis=2))  # lane a*M+b: atom a
        replicated = np.ascontiguousarray(np.tile(x, (1, 1, M)))  # lane a*M+b: atom b
        fi, fj = np.zeros(broadcast.size, real), np.zeros(broadcast.size, real)
        flat = flat_kernel(real)
        xi_flat, xj_flat = broadcast.ravel(), replicated.ravel()
        name = f"flat 4x4 ({real.__name__})"
        arguments = (xi_flat, xj_flat, starts, partners, off, 6.25, fi, fj)
        timed[name] = lambda k=flat, a=arguments: k(*a)
        timed[name]()
        gaps[name] = np.abs(per_atom(flat_forces(fi, fj)) - reference.forces).max() / scale
        for label, parts in (("j buffer", (True, True)), ("pair loop only", (False, False))):
            forces = np.zeros(x.shape, real)
            kernel = buffer_kernel(real, *parts)
            name = f"{label} ({real.__name__})"
            arguments = (x, counts, starts, partners, off, 6.25, forces)
            timed[name] = lambda k=kernel, a=arguments: k(*a)
            timed[name]()
            gaps[name] = np.abs(per_atom(forces) - reference.forces).max() / scale
    build_times(state, neighbors, density)
    # the simd kernel (float32) on the list and on the pruned list, the flat one pruned
    # (the search with its atom check at every distance: no pair kept unchecked)
    kept = cluster_pairs(state.box, ncx, ncy, first, centre, bounds, 2.8, relative, counts, 0.0)
    within = cluster_pairs(state.box, ncx, ncy, first, centre, bounds, 2.5, relative, counts, 0.0)[
        1
    ]
    print(
        f"cluster pairs with an atom pair within 2.8: {len(kept[1])} "
        f"({len(kept[1]) / len(partners):.1%}), within the cutoff 2.5: {len(within)} "
        f"({len(within) / len(partners):.1%})"
    )
    x = relative.astype(np.float32)
    as_i = x.copy()
    as_i[:, 2, :][~real_atoms.reshape(-1, M)] = FILLER
    for label, lists, off in (
        ("simd 2x4", (starts, partners), offsets),
        ("simd 2x4, pruned", kept[:2], kept[2]),
    ):
        forces = np.zeros(x.shape, np.float32)
        arguments = (
            as_i.ravel(),
            x.ravel(),
            off.astype(np.float32).ravel(),
            lists[0],
            lists[1],
            np.float32(6.25),
            forces.reshape(-1),
            None,
            np.float32(0.0),
        )
        name = f"{label} (float32)"
        timed[name] = lambda a=arguments: simd_forces(*a)
        timed[name]()
        gaps[name] = np.abs(per_atom(forces) - reference.forces).max() / scale
    # the same into a double force buffer (sums of float32 cluster-pair terms in double)
    wide = np.zeros(x.shape, np.float64)
    arguments = (
        as_i.ravel(),
        x.ravel(),
        kept[2].astype(np.float32).ravel(),
        kept[0],
        kept[1],
        np.float32(6.25),
        wide.reshape(-1),
        None,
        np.float32(0.0),
    )
    timed["simd 2x4, pruned, double sums"] = lambda a=arguments: simd_forces(*a)
    timed["simd 2x4, pruned, double sums"]()
    gaps["simd 2x4, pruned, double sums"] = np.abs(per_atom(wide) - reference.forces).max() / scale
    # the prune from the kernel's own r^2 (a force call that also marks the near pairs)
    near = np.zeros(len(partners), np.uint8)
    forces = np.zeros(x.shape, np.float32)
    arguments = (
        as_i.ravel(),
        x.ravel(),
        offsets.astype(np.float32).ravel(),
        starts,
        partners,
        np.float32(6.25),
        forces.reshape(-1),
        near,
        np.float32(2.8**2),
    )
    timed["simd 2x4, marking (float32)"] = lambda a=arguments: simd_forces(*a)
    timed["simd 2x4, marking (float32)"]()
    gaps["simd 2x4, marking (float32)"] = np.abs(per_atom(forces) - reference.forces).max() / scale
    start = time.perf_counter()
    marked = kept_pairs(starts, partners, offsets, near)
    compaction = time.perf_counter() - start
    start = time.perf_counter()
    marked = kept_pairs(starts, partners, offsets, near)
    compaction = min(compaction, time.perf_counter() - start)

    def listed(lists):  # the (ci, cj) of a list
        owners = np.repeat(np.arange(len(lists[0]) - 1), np.diff(lists[0]))
        return set(zip(owners.tolist(), lists[1].tolist(), strict=True))

    differ = len(listed(marked) ^ listed(kept))
    print(
        f"the kernel's marks keep {len(marked[1])} cluster pairs ({differ} differ from the "
        f"double-precision atom check, at the float32 edge of 2.8); compacting them "
        f"{1e3 * compaction:.1f} ms"
    )
    broadcast = np.ascontiguousarray(np.repeat(as_i, M, axis=2)).ravel()
    replicated = np.ascontiguousarray(np.tile(x, (1, 1, M))).ravel()
    fi, fj = np.zeros(broadcast.size, np.float32), np.zeros(broadcast.size, np.float32)
    arguments = (broadcast, replicated, kept[0], kept[1], kept[2].astype(np.float32), 6.25, fi, fj)
    flat = flat_kernel(np.float32)
    timed["flat 4x4, pruned (float32)"] = lambda a=arguments: flat(*a)
    timed["flat 4x4, pruned (float32)"]()
    gaps["flat 4x4, pruned (float32)"] = (
        np.abs(per_atom(flat_forces(fi, fj)) - reference.forces).max() / scale
    )
    if max(gaps[name] for name in gaps if "only" not in name) > 1e-4:
        print(f"cluster forces differ from the frame's: {gaps}", file=sys.stderr)
        return 1
    times = {name: [] for name in timed}
    for _ in range(args.repeats):
        for name, call in timed.items():
            start = time.perf_counter()
            call()
            times[name].append(time.perf_counter() - start)
    base = times["frame (double)"]
    print(f"{'':28s}{'ms':>8}{'/ frame':>9}{'max dF / max F':>16}")
    for name, values in times.items():
        ratio = statistics.median(t / b for t, b in zip(values, base, strict=True))
        gap = "(skips work)" if "only" in name else f"{gaps[name]:.1e}"
        print(f"{name:28s}{1e3 * statistics.median(values):8.2f}{ratio:9.3f}{gap:>16}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
