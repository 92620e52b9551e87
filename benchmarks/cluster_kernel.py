"""The mixed-precision LJ force call on the cluster list, alone: ns per cluster pair.

The 32000-atom melt (fcc at rho* 0.8442, every atom moved by a Gaussian of 0.05
sigma), LJ cut at 2.5 sigma, the cluster list of ``ForceField(precision="mixed")``
(radius 2.8); ``energy_forces(virial=False, precision="mixed")`` called ``--calls``
times on the same positions after one untimed call (the kernel, the float32 relative
positions and the sum of the chunks into atom order; the list is not rebuilt), on
``--threads`` threads. Prints the minimum and the median per call and per listed
cluster pair.

A change to the kernel is measured by running this script under the two versions
alternately, each in fresh processes with its own ``NUMBA_CACHE_DIR`` and
``XDG_CACHE_HOME`` (the kernels compile once per cache), and comparing the
per-process minima; for another instruction set, set ``NUMBA_CPU_NAME`` and
``NUMBA_CPU_FEATURES`` as in ``benchmarks/README.md``. ``--precision double`` times the
double force call on the slot frame instead (``ForceField(precision="double")``), per
listed atom pair::

    python benchmarks/cluster_kernel.py
    python benchmarks/cluster_kernel.py --precision double
    python benchmarks/cluster_kernel.py --cells 10 --calls 20 --threads 2
    python benchmarks/cluster_kernel.py --lanes 8,16

``--lanes 8,16`` times the cluster kernel alone (the engine's entry point, one thread,
no virial; without the float32 relative positions; with one chunk the kernel writes the
forces into atom order itself, cluster by cluster, where two threads' chunks are summed
by a pass after it) at each
vector width (``kernels_for(..., cluster_lanes=...)``), compiled side by side in this
process and called in alternating blocks of ``--calls`` (this VM's speed drifts by 2x
within minutes, so widths timed in separate processes do not compare): the minimum per
width and the median and range of the per-block ratios to the first width. The engine
uses 16 lanes where the CPU numba compiles for has AVX-512 (``md._simd.ZMM``), else 8;
16 lanes on an AVX2-only CPU are two registers per vector.

``--windows`` prints, instead of timing, the per-chunk scratch of the cluster kernel on
2, 4, 8, 16 and 64 chunks (threads), in lists' worth: each chunk's window of the clusters
its rows reach (``md.neighbors._cluster_search.chunk_windows``), from the outer list's row reach
as the engine takes it and from the pruned list's own::

    python benchmarks/cluster_kernel.py --windows --cells 80
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _machine import machine_line  # noqa: E402

import md  # noqa: E402
from md.forcefield import ForceField  # noqa: E402
from md.parallel import get_threads, set_threads  # noqa: E402
from potentials import LennardJones  # noqa: E402


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=20, help="fcc cells per edge (20)")
    parser.add_argument("--calls", type=int, default=40, help="timed calls (40)")
    parser.add_argument("--threads", type=int, default=1, help="threads (1)")
    parser.add_argument(
        "--precision",
        choices=("mixed", "double"),
        default="mixed",
        help="mixed: the cluster kernel (default); double: the slot frame's "
        "force call, per listed atom pair",
    )
    parser.add_argument(
        "--lanes",
        default=None,
        help="comma-separated vector widths (8, 16): the cluster kernel at "
        "each, alternated in this process (mixed only)",
    )
    parser.add_argument(
        "--blocks",
        type=int,
        default=30,
        help="alternating blocks of --calls per width with --lanes (30)",
    )
    parser.add_argument(
        "--windows",
        action="store_true",
        help="print the chunks' scratch windows in lists' worth, no timing",
    )
    args = parser.parse_args(argv)
    if args.cells < 1 or args.calls < 1 or args.threads < 1 or args.blocks < 1:
        parser.error("--cells, --calls, --threads and --blocks must be at least 1")
    widths = None
    if args.lanes is not None:
        try:
            widths = [int(x) for x in args.lanes.split(",")]
        except ValueError:
            parser.error(f"--lanes takes widths such as 8,16, not {args.lanes!r}")
        if not widths or any(w not in (8, 16) for w in widths):
            parser.error(f"--lanes takes 8 and/or 16, not {args.lanes!r}")
        if args.precision != "mixed":
            parser.error("--lanes times the cluster kernel: mixed precision only")
        args.threads = 1
    set_threads(args.threads)
    print(machine_line() + f"; {get_threads()} thread(s)")
    state = md.lattice("fcc", args.cells, density=0.8442)
    state.positions += np.random.default_rng(0).normal(scale=0.05, size=state.positions.shape)
    field = ForceField([LennardJones(cutoff=2.5)], precision=args.precision)
    try:
        field.compute(state)  # builds the list, compiles or loads the kernels
    except ValueError as error:
        sys.exit(f"--cells {args.cells}: {error}")
    clusters = field.neighbor_list.clusters
    if clusters is None and args.precision == "mixed":
        sys.exit(f"no cluster list for {state.n_atoms} atoms in this cell: use more --cells")
    potential, neighbors = field.potentials[0], field.neighbor_list
    if args.windows:
        if clusters is None:
            sys.exit("--windows: the cluster list's (mixed precision only)")
        print_windows(neighbors)
        return
    if widths is not None:
        compare_widths(potential, neighbors, state, widths, args.calls, args.blocks)
        return
    times = []
    for _ in range(args.calls):
        start = time.perf_counter()
        potential.energy_forces(state, neighbors, virial=False, precision=args.precision)
        times.append(time.perf_counter() - start)
    if clusters is not None:
        pairs, what = len(clusters.partners), "cluster pairs"
    else:
        pairs, what = neighbors.n_pairs, "listed pairs"
    best, middle = min(times), statistics.median(times)
    print(
        f"{state.n_atoms} atoms, {pairs} {what}, {args.calls} calls: "
        f"min {1e3 * best:.3f} ms ({1e9 * best / pairs:.2f} ns per {what[:-1]}), "
        f"median {1e3 * middle:.3f} ms ({1e9 * middle / pairs:.2f} ns)"
    )


def compare_widths(potential, neighbors, state, widths, calls, blocks) -> None:
    """The cluster kernel at each width in ``widths``, alternated (see the module
    docstring): the engine's own entry point, from a kernel module per width."""
    from md._simd import ZMM
    from potentials._cluster_ir import slp_vectorising
    from potentials._kernels import J_STRIDE, zeros_on_lines
    from potentials._pair_codegen import kernels_for
    from potentials._pair_frame import CUTOFF_MODES

    clusters = neighbors.clusters
    xi = np.empty(12 * clusters.n_clusters, np.float32)
    xj = np.empty_like(xi)
    clusters.relative_positions(state.positions, xi, xj)
    table = potential.tables(1).astype(np.float32)
    mode = int(CUTOFF_MODES[potential.cutoff_mode])
    lists = (
        clusters.starts,
        clusters.partners,
        clusters.offsets.reshape(-1),
        clusters.bounds,
        clusters.windows,
    )
    chunks = len(clusters.bounds) - 1
    room = clusters.window_clusters
    buffers = np.empty(12 * room)
    j_sums = zeros_on_lines(J_STRIDE * room, np.float32)
    j_counts = np.zeros(room, np.int32)
    energies, virials = np.empty(chunks), np.empty((chunks, 9))
    slot_types = np.zeros(4 * clusters.n_clusters, np.int32)
    entry = "cluster_forces_threaded" if chunks > 1 else "cluster_forces"
    name = f"{entry}__mode{mode}_with_virial0_single1"
    forces = np.empty((state.n_atoms, 3))
    arguments = (
        xi,
        xj,
        lists,
        slot_types,
        1,
        table,
        mode,
        potential.data,
        False,
        True,
        buffers,
        j_sums,
        j_counts,
        clusters.atom,
        forces,
        energies,
        virials,
    )
    kernels, sums = {}, {}
    for lanes in widths:
        kernels[lanes] = getattr(kernels_for(potential.term, "mixed", cluster_lanes=lanes), name)
        with slp_vectorising():  # compiles (or loads) here, with the SLP vectoriser
            kernels[lanes](*arguments)
        sums[lanes] = float(energies.sum())
    best = {lanes: [] for lanes in widths}
    for block in range(blocks):
        for lanes in widths if block % 2 == 0 else widths[::-1]:
            times = []
            for _ in range(calls):
                start = time.perf_counter()
                kernels[lanes](*arguments)
                times.append(time.perf_counter() - start)
            best[lanes].append(min(times))
    pairs = len(clusters.partners)
    print(
        f"{state.n_atoms} atoms, {pairs} cluster pairs; the cluster kernel alone, {blocks} "
        f"alternating blocks of {calls} calls; the engine's width here: "
        f"{16 if ZMM else 8} lanes"
    )
    first = widths[0]
    for lanes in widths:
        ratios = [b / a for a, b in zip(best[first], best[lanes], strict=True)]
        print(
            f"{lanes} lanes: min {1e3 * min(best[lanes]):.3f} ms "
            f"({1e9 * min(best[lanes]) / pairs:.2f} ns per cluster pair), energy "
            f"{sums[lanes]:.6f}; per-block ratio to {first} lanes: median "
            f"{statistics.median(ratios):.3f} ({min(ratios):.3f}-{max(ratios):.3f})"
        )


def print_windows(neighbors) -> None:
    """The chunks' windows, in lists' worth of scratch, per chunk count."""
    from md.neighbors._cluster_search import balanced_chunks, chunk_windows, row_reach

    clusters, outer = neighbors.clusters, neighbors.outer_clusters
    own = row_reach(clusters.starts, clusters.partners)
    reach = outer.reach if outer is not None else own
    n = clusters.n_clusters
    print(
        f"{n} clusters; scratch in lists' worth per chunk count (threads), from the "
        f"{'outer' if outer is not None else 'pruned'} list's row reach as the engine "
        f"takes it (the pruned list's own); one list per chunk before stop 60"
    )
    for chunks in (2, 4, 8, 16, 64):
        bounds = balanced_chunks(clusters.starts, chunks)
        worth = [
            float((w[:, 1] - w[:, 0]).sum()) / n
            for w in (chunk_windows(reach, bounds), chunk_windows(own, bounds))
        ]
        print(f"{chunks:>3} chunks: {worth[0]:.2f} ({worth[1]:.2f})")


if __name__ == "__main__":
    main()
