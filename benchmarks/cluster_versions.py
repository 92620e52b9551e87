"""Two versions of the cluster kernels' module, interleaved in one process: grid + search.

Loads two copies of ``md/neighbors/_cluster_kernels.py`` (each a file, such as one
taken from git) as two modules and times, taking turns in alternating order, each
one's mixed build of LAMMPS's LJ melt (as ``cluster_search.py``: the 32000-atom melt
after ``--warm`` steps): the cluster grid, the relative positions and the cluster-pair
search at the outer radius (4.0) with its own prune (2.8), and the grid alone. Prints
whether both give the same lists, the medians of the calling thread's CPU time and of
the wall time, and the medians of the per-repeat ratios, b / a. A change to one
kernel measured against the code before it, in one process, so that load from other
processes hits both alike::

    git show HEAD~3:md/neighbors/_cluster_kernels.py > /tmp/before.py
    python benchmarks/cluster_versions.py /tmp/before.py md/neighbors/_cluster_kernels.py
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the checkout, from anywhere

import numpy as np  # noqa: E402
from _machine import machine_line  # noqa: E402
from cluster_search import melt  # noqa: E402

import md  # noqa: E402
from md.parallel import get_threads, set_threads  # noqa: E402

OUTER, INNER = 4.0, 2.8


def load(path: str, name: str):
    """The module in ``path``, imported as ``name`` (its kernels cached beside it)."""
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def builder(kernels, positions, box, chunks):
    """One mixed build's kernel calls with ``kernels``: (grid, whole build) callables."""
    ncx, ncy = kernels.column_counts(box, len(positions), OUTER)
    reach2 = np.float32((OUTER * (1 + 1e-5)) ** 2)
    inner2 = np.float32((INNER * (1 + 1e-5)) ** 2)

    def grid():
        return kernels.cluster_grid(positions, box, ncx, ncy, chunks)

    def build():
        first, atom, origin, lower, upper = grid()
        xi = np.empty(3 * len(atom), np.float32)
        xj = np.empty_like(xi)
        kernels.cluster_positions(positions, atom, origin, xi, xj)
        return kernels.search_pairs(
            box, ncx, ncy, first, lower, upper, OUTER, chunks, 128, xi, xj, reach2, inner2
        )

    return grid, build


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("a", help="the first module file (the code before)")
    parser.add_argument("b", help="the second module file")
    parser.add_argument("--cells", type=int, default=20, help="fcc cells per edge (20)")
    parser.add_argument("--repeats", type=int, default=15, help="turns (15)")
    parser.add_argument("--threads", default="1", help="thread counts (1)")
    parser.add_argument("--warm", type=int, default=100, help="steps before timing (100)")
    args = parser.parse_args()
    md.keep_freed_memory()
    print(machine_line())
    state = melt(args.cells, "double", args.warm).state
    versions = {"a": load(args.a, "_cluster_kernels_a"), "b": load(args.b, "_cluster_kernels_b")}
    before = get_threads()
    print(
        f"{state.n_atoms} atoms, {args.repeats} repeats; ms (medians) and b / a (median of ratios)"
    )
    heads = ("a CPU", "b CPU", "b/a", "a wall", "b wall", "b/a")
    print(f"{'threads':>7} {'call':<24} " + " ".join(f"{h:>7}" for h in heads))
    try:
        for count in (int(t) for t in args.threads.split(",")):
            set_threads(count)
            calls = {
                name: builder(kernels, state.positions, state.box, count)
                for name, kernels in versions.items()
            }
            lists = {name: call[1]() for name, call in calls.items()}  # compiled, and compared
            same = all(np.array_equal(x, y) for x, y in zip(lists["a"], lists["b"], strict=True))
            print(f"{count:>7} same lists: {same}")
            for part, label in ((1, "grid + search + prune"), (0, "the grid alone")):
                times = {"a": [], "b": []}
                for repeat in range(args.repeats):
                    for name in ("a", "b") if repeat % 2 == 0 else ("b", "a"):
                        wall, cpu = time.perf_counter(), time.thread_time()
                        calls[name][part]()
                        times[name].append((time.thread_time() - cpu, time.perf_counter() - wall))
                row = []
                for k in (0, 1):
                    a = [t[k] for t in times["a"]]
                    b = [t[k] for t in times["b"]]
                    ratio = statistics.median(y / x for x, y in zip(a, b, strict=True))
                    row += [1e3 * statistics.median(a), 1e3 * statistics.median(b), ratio]
                figures = " ".join(
                    f"{v:7.3f}" if k % 3 == 2 else f"{v:7.2f}" for k, v in enumerate(row)
                )
                print(f"{count:>7} {label:<24} {figures}")
    finally:
        set_threads(before)
    return 0


if __name__ == "__main__":
    sys.exit(main())
