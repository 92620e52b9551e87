"""Where the pair frame's Lennard-Jones force call spends its time.

The frame's per-row passes (see ``potentials/_pair_kernels.py``): gather the
partners' positions (with their image shifts) into contiguous scratch, the
vectorised pair loop, the sum of atom i's force, and the scatter of the
partners' forces. This script times a replica of that loop (single type,
cutoff mode "none", no virial; checked to give the frame's energy bit for bit and
its forces to round-off: atom i's force is a sum inside the vectorised pair loop,
which each loop's vectoriser may group its own way) with parts left out, in
interleaved repeats, beside the frame itself with and without its unshifted-row
gather (``SlotFrame.shifted``: the same potential given a list whose frame has
every row marked shifted). Each
row: median time, per listed pair, and the median of per-repeat ratios to the
full replica. A variant without a part computes wrong forces: it only shows
what the part costs. Two more rows time the replica in float32 throughout (slot
positions, shifts, gathered partners, arithmetic, pair forces; the scatter into a
float32 or a double buffer): what a float32 slot frame could gain at most, with
its force error against double printed.

    python benchmarks/frame_breakdown.py                  # 32000 atoms, 1 thread, 41 repeats
    python benchmarks/frame_breakdown.py --cells 50 --repeats 11 --threads 2
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from numba import njit

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the checkout, from anywhere

from _machine import machine_line  # noqa: E402

import md  # noqa: E402
from md.parallel import set_threads  # noqa: E402
from potentials import LennardJones  # noqa: E402
from potentials._kernels import (  # noqa: E402
    _gather_partners,
    _gather_unshifted,
    _scatter_partners,
)

VECTOR_MATH = {"reassoc", "contract", "nsz", "arcp"}
LANES = 4


F32 = np.float32


def replica(gather: bool, arithmetic: bool, row_sum: bool, scatter: bool, real=np.float64):
    """The frame's chunk loop for one chunk, with the named parts kept.

    ``real`` np.float32: the loop in float32 throughout (slot positions, shifts,
    gathered partners, arithmetic, pair forces, padded to eight lanes; the energy
    summed per row in float32, then in double): a float32 slot frame's loop (the
    plan of stop 48's note keeps positions relative to their cell, so that float32
    keeps its precision in any box; plain float32 positions serve the timing). The
    force buffer passed in is float32 or double (then a conversion per partner)."""
    lanes = LANES if real is np.float64 else 2 * LANES
    per_row = real is not np.float64  # double: the energy summed per pair, as the frame
    frame_scatter = real is np.float64  # the frame's own scatter (double rows only)

    @njit(fastmath=VECTOR_MATH, error_model="numpy")
    def loop(frame, shifts, starts, neighbors, codes, shifted, buffer, rc2, c6, c12, far):
        n = frame.shape[0]
        for p in range(n):
            buffer[p, 0] = 0.0
            buffer[p, 1] = 0.0
            buffer[p, 2] = 0.0
        most = lanes
        for p in range(n):
            most = max(most, starts[p + 1] - starts[p] + lanes)
        gx, gy, gz = np.zeros(most, real), np.zeros(most, real), np.zeros(most, real)
        sfx, sfy, sfz = np.zeros(most, real), np.zeros(most, real), np.zeros(most, real)
        one, zero, twelve, six = real(1.0), real(0.0), real(12.0), real(6.0)
        energy = 0.0
        for p in range(n):
            xi, yi, zi = frame[p, 0], frame[p, 1], frame[p, 2]
            partners = neighbors[starts[p] : starts[p + 1]]
            m = partners.shape[0]
            if gather:
                if shifted[p]:
                    _gather_partners(
                        frame, shifts, partners, codes[starts[p] : starts[p + 1]], gx, gy, gz
                    )
                else:
                    _gather_unshifted(frame, partners, gx, gy, gz)
            padded = (m + (lanes - 1)) & ~(lanes - 1) if m > 0 else 0
            for k in range(m, padded):
                gx[k] = xi + far
                gy[k] = yi
                gz[k] = zi
            row = zero
            fxi = fyi = fzi = zero
            for k in range(padded):
                dx = xi - gx[k]
                dy = yi - gy[k]
                dz = zi - gz[k]
                r2 = dx * dx + dy * dy + dz * dz
                inside = one if r2 < rc2 else zero
                if arithmetic:
                    inv_r2 = one / r2
                    inv_r6 = inv_r2 * inv_r2 * inv_r2
                    a = c12 * inv_r6 * inv_r6
                    b = c6 * inv_r6
                    u, fr = a - b, (twelve * a - six * b) * inv_r2
                else:
                    u, fr = r2, c6
                if per_row:
                    row += u * inside
                else:
                    energy += u * inside
                fr *= inside
                sfx[k] = fr * dx
                sfy[k] = fr * dy
                sfz[k] = fr * dz
                if row_sum:  # in the pair loop, as the frame sums it
                    fxi += sfx[k]
                    fyi += sfy[k]
                    fzi += sfz[k]
            if per_row:
                energy += row
            if scatter:
                if frame_scatter:
                    _scatter_partners(buffer, partners, sfx, sfy, sfz)
                else:
                    for k in range(m):
                        q = np.uint32(partners[k])
                        buffer[q, 0] -= sfx[k]
                        buffer[q, 1] -= sfy[k]
                        buffer[q, 2] -= sfz[k]
            if row_sum:
                buffer[p, 0] += fxi
                buffer[p, 1] += fyi
                buffer[p, 2] += fzi
        return energy

    return loop


class EveryRowShifted:
    """A neighbour list seen with every row of its frame marked shifted: the pair frame
    then gathers every row with its codes and shifts, as it did before the flags."""

    def __init__(self, neighbors: md.NeighborList) -> None:
        self.list_radius = neighbors.list_radius
        self.frame = dataclasses.replace(
            neighbors.frame, shifted=np.ones_like(neighbors.frame.shifted)
        )


VARIANTS = {
    "replica (all parts)": (True, True, True, True),
    "without LJ arithmetic": (True, False, True, True),
    "without gather": (False, True, True, True),
    "without scatter": (True, True, True, False),
    "without sum, scatter": (True, True, False, False),
    "pair loop only": (False, True, False, False),
    "rows only (no parts)": (False, False, False, False),
}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=20, help="fcc cells per edge (20)")
    parser.add_argument("--repeats", type=int, default=41, help="interleaved repeats (41)")
    parser.add_argument("--threads", type=int, default=1, help="threads of the frame (1)")
    args = parser.parse_args(argv)
    print(machine_line())
    set_threads(args.threads)
    state = md.lattice("fcc", args.cells, density=0.8442)
    state.positions += np.random.default_rng(1).normal(0.0, 0.05, state.positions.shape)
    lj = LennardJones(cutoff=2.5, cutoff_mode="none")
    neighbors = md.NeighborList(2.5, 0.3)
    neighbors.update(state)
    frame = neighbors.frame
    every_row = EveryRowShifted(neighbors)

    def call(listed):
        return lj.energy_forces(state, listed, virial=False)

    reference = call(neighbors)
    slot_positions = state.positions[frame.order] + frame.images * state.box
    buffer = np.zeros_like(slot_positions)
    inputs = (
        slot_positions,
        frame.shifts,
        frame.starts,
        frame.neighbors,
        frame.codes,
        frame.shifted,
        buffer,
        6.25,
        4.0,
        4.0,
        2.51,
    )
    loops = {name: replica(*parts) for name, parts in VARIANTS.items()}
    variant_inputs = {}
    energy = loops["replica (all parts)"](*inputs)
    forces = np.empty_like(buffer)
    forces[frame.order] = buffer
    same = energy == reference.energy and np.array_equal(forces, reference.forces)
    apart = float(np.max(np.abs(forces - reference.forces)) / np.max(np.abs(reference.forces)))
    if args.threads > 1 or not same:
        print(
            f"replica against the frame: {'same bits' if same else 'DIFFERENT'} "
            f"({args.threads} thread(s): the replica runs one chunk); energy "
            f"{energy - reference.energy:+.3g} apart, forces {apart:.2g} of the largest"
        )
    # The float32 replicas (a float32 slot frame's loop): same list, float32 inputs.
    single = (
        slot_positions.astype(F32),
        frame.shifts.astype(F32),
        frame.starts,
        frame.neighbors,
        frame.codes,
        frame.shifted,
    )
    constants = (F32(6.25), F32(4.0), F32(4.0), F32(2.51))
    for name, wide in (
        ("float32 replica, float32 buffer", False),
        ("float32 replica, double buffer", True),
    ):
        out = np.zeros(buffer.shape, np.float64 if wide else F32)
        loop32 = replica(True, True, True, True, real=F32)
        loops[name] = loop32
        inputs32 = (*single, out, *constants)
        energy32 = loop32(*inputs32)
        forces32 = np.empty(buffer.shape)
        forces32[frame.order] = out
        gap = np.abs(forces32 - reference.forces).max() / np.abs(reference.forces).max()
        print(
            f"{name}: energy {energy32:.8g} (double {reference.energy:.8g}), max |F32 - F| "
            f"/ max |F| = {gap:.1e}"
        )
        variant_inputs[name] = inputs32
    for name, loop in loops.items():
        loop(*variant_inputs.get(name, inputs))  # compile
    call(every_row)
    timed = {
        "frame LJ": lambda: call(neighbors),
        "frame LJ, every row shifted": lambda: call(every_row),
    }
    for name, loop in loops.items():
        arguments = variant_inputs.get(name, inputs)
        timed[name] = lambda loop=loop, arguments=arguments: loop(*arguments)
    times = {name: [] for name in timed}
    for _ in range(args.repeats):
        for name, run in timed.items():
            start = time.perf_counter()
            run()
            times[name].append(time.perf_counter() - start)
    pairs = neighbors.n_pairs
    print(
        f"{state.n_atoms} atoms, {pairs} listed pairs, {frame.shifted.mean():.0%} of the rows "
        f"marked shifted; {args.repeats} interleaved repeats; the frame on {args.threads} "
        f"thread(s), the replica on 1; replica same bits as the frame: {same}"
    )
    base = times["replica (all parts)"]
    print(f"{'':30s}{'ms':>8}{'ns/pair':>9}{'/ replica':>11}")
    for name, values in times.items():
        ratio = statistics.median(t / b for t, b in zip(values, base, strict=True))
        median = statistics.median(values)
        print(f"{name:30s}{1e3 * median:8.2f}{1e9 * median / pairs:9.2f}{ratio:11.3f}")


if __name__ == "__main__":
    main()
