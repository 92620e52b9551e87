"""Two versions of the cluster list's prune, interleaved in one process.

Loads the cluster kernels of two checkouts (as ``cluster_versions.py`` does: each
tree's ``md/neighbors/_cluster_*.py`` under names of their own) and times, taking
turns in alternating order, each one's ``prune_pairs`` of the same outer list (the
32000-atom melt's after ``--warm`` mixed steps, outer radius 4.0) to the list radius
2.8 at the melt's positions ``--moved`` steps later, the relative positions written
once before (a prune's Python and its relative positions are the same in both). Per
thread count T the outer list is split in T chunks by pairs as the list splits it;
``--work`` also times two chunks on one thread (the work two threads share: the
bound on their speed-up without the wait for a core that a loaded machine adds).
Prints whether both give the same list (starts, partners and offsets over the kept
pairs, array for array), the medians of the calling thread's CPU time and of the wall
time, and the medians of the per-repeat ratios, b / a; then the peer's list cost in
the same run (LAMMPS's ``lj/cut`` on the same melt in a child, one thread, its Neigh
time per build; ``--no-lammps`` to skip it)::

    mkdir /tmp/before && git archive HEAD~3 md | tar -x -C /tmp/before
    python benchmarks/cluster_prune_versions.py /tmp/before . --threads 1,2 --work
"""

from __future__ import annotations

import argparse
import inspect
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the checkout, from anywhere

import numpy as np  # noqa: E402
from _machine import machine_line  # noqa: E402
from cluster_search import melt  # noqa: E402
from cluster_versions import load  # noqa: E402
from lj_melt import lammps_environment, run_lammps  # noqa: E402

import md  # noqa: E402
from md.neighbors._cluster_search import balanced_chunks  # noqa: E402
from md.parallel import get_threads, set_threads  # noqa: E402


def pruner(kernels, outer, xi, xj, reach2, chunks):
    """A call of ``kernels``' prune of ``outer`` in ``chunks`` chunks, and its buffers."""
    n, size = outer.n_clusters, outer.n_pairs
    kept = (np.empty(n + 1, np.int64), np.empty(size, np.int32), np.empty((size, 3), np.float32))
    extra = ()
    if len(inspect.signature(kernels.prune_pairs.py_func).parameters) > 10:
        extra = (np.empty(size, np.uint8),)  # the marks (after issue 70's two passes)
    bounds = balanced_chunks(outer.starts, chunks)
    lists = (outer.starts, outer.partners, outer.offsets, bounds, xi, xj, reach2)

    def prune():
        return kernels.prune_pairs(*lists, *kept, *extra)

    return prune, kept


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("a", help="the first checkout, a tree with md/neighbors/ (the code before)")
    parser.add_argument("b", help="the second checkout (such as this one: .)")
    parser.add_argument("--cells", type=int, default=20, help="fcc cells per edge (20)")
    parser.add_argument("--repeats", type=int, default=21, help="turns (21)")
    parser.add_argument("--threads", default="1", help="thread counts (1)")
    parser.add_argument("--warm", type=int, default=100, help="mixed steps before (100)")
    parser.add_argument("--moved", type=int, default=5, help="steps to the prune (5)")
    parser.add_argument("--work", action="store_true", help="also 2 chunks on 1 thread")
    parser.add_argument("--no-lammps", action="store_true", help="no LAMMPS peer line")
    args = parser.parse_args()
    md.keep_freed_memory()
    print(machine_line())
    sim = melt(args.cells, "mixed", args.warm)
    neighbors = sim.forcefield.neighbor_list
    outer = neighbors.outer_clusters
    if outer is None:
        raise SystemExit("the mixed list has no outer list in this box: nothing to prune")
    sim.run(args.moved)  # the positions of a prune between searches (the outer list kept)
    if neighbors.outer_clusters is not outer:
        print("(a search came within --moved steps: the prune is of the older outer list)")
    xi = np.empty(12 * outer.n_clusters, np.float32)
    xj = np.empty_like(xi)
    outer.relative_positions(sim.state.positions, xi, xj)
    reach2 = np.float32((neighbors.list_radius * (1.0 + 1e-5)) ** 2)
    versions = {"a": load(args.a, "a"), "b": load(args.b, "b")}
    print(
        f"{sim.state.n_atoms} atoms, {outer.n_pairs} outer pairs, {args.repeats} repeats; "
        "ms (medians) and b / a (median of ratios)"
    )
    heads = ("a CPU", "b CPU", "b/a", "a wall", "b wall", "b/a")
    print(f"{'threads':>7} {'chunks':>6} {'kept':>8} " + " ".join(f"{h:>7}" for h in heads))
    runs = [(int(t), int(t)) for t in args.threads.split(",")]
    if args.work:
        runs.append((1, 2))
    before = get_threads()
    one = None  # b's prune at 1 thread, 1 chunk: CPU ms
    try:
        for threads, chunks in runs:
            set_threads(threads)
            calls = {
                name: pruner(kernels, outer, xi, xj, reach2, chunks)
                for name, kernels in versions.items()
            }
            counts = {name: call[0]() for name, call in calls.items()}  # compiled, compared
            k = counts["a"]
            same = counts["b"] == k and all(
                np.array_equal(x[: k if n else None], y[: k if n else None])
                for n, (x, y) in enumerate(zip(calls["a"][1], calls["b"][1], strict=True))
            )
            times = {"a": [], "b": []}
            for repeat in range(args.repeats):
                for name in ("a", "b") if repeat % 2 == 0 else ("b", "a"):
                    wall, cpu = time.perf_counter(), time.thread_time()
                    calls[name][0]()
                    times[name].append((time.thread_time() - cpu, time.perf_counter() - wall))
            row = []
            for j in (0, 1):
                a = [t[j] for t in times["a"]]
                b = [t[j] for t in times["b"]]
                ratio = statistics.median(y / x for x, y in zip(a, b, strict=True))
                row += [1e3 * statistics.median(a), 1e3 * statistics.median(b), ratio]
            figures = " ".join(f"{v:7.3f}" for v in row)
            print(f"{threads:>7} {chunks:>6} {k:>8} {figures}  same list: {same}")
            if (threads, chunks) == (1, 1):
                one = row[1]
    finally:
        set_threads(before)
    if not args.no_lammps:
        peer(args.cells, one)
    return 0


def peer(cells: int, ours: float | None) -> None:
    """LAMMPS's list cost on the same melt (100 steps, its own list rule: check every
    step), per build, beside ``ours`` (b's prune at 1 thread, CPU ms)."""
    try:
        found = run_lammps(cells, 100, "check", lammps_environment())
    except (OSError, RuntimeError) as error:
        print(f"LAMMPS: not run ({error})")
        return
    neigh = (found.get("sections") or {}).get("Neigh")
    builds = found.get("n_builds")
    if not neigh or not builds:
        print(f"LAMMPS {found.get('version', '?')}: no Neigh time or builds in its log")
        return
    per_build = 1e3 * neigh / builds
    ratio = f"; LAMMPS per build / b's prune at 1 thread {per_build / ours:.1f}" if ours else ""
    print(
        f"LAMMPS {found.get('version', '?')} lj/cut, 1 thread, this melt: Neigh "
        f"{per_build:.2f} ms per build ({builds} builds in 100 steps, wall time){ratio}"
    )


if __name__ == "__main__":
    sys.exit(main())
