"""Two versions of the cluster kernels, interleaved in one process: grid + search.

Loads the cluster kernels of two checkouts (each a tree with ``md/neighbors/``, such as
one exported from git) as two sets of modules and times, taking turns in alternating
order, each one's mixed build of LAMMPS's LJ melt (as ``cluster_search.py``: the
32000-atom melt after ``--warm`` steps): the cluster grid, the relative positions and the
cluster-pair search at the outer radius (4.0) with its own prune (2.8), and the grid
alone. Prints whether both give the same lists, the medians of the calling thread's CPU
time and of the wall time, and the medians of the per-repeat ratios, b / a. A change to
one kernel measured against the code before it, in one process, so that load from other
processes hits both alike. A tree whose ``cluster_grid`` and ``search_pairs`` take
``kept`` (since issue 70's kept buffers) gets one ``md._memory.KeptArrays`` for all its
calls, as its NeighborList keeps one from build to build::

    mkdir /tmp/before && git archive HEAD~3 md | tar -x -C /tmp/before
    python benchmarks/cluster_versions.py /tmp/before .

A tree's modules are ``md/neighbors/_cluster_grid.py``, ``_cluster_prune.py`` and
``_cluster_search.py`` (issue 70's split), or for a tree from before that split the one
``md/neighbors/_cluster_kernels.py``. Each tree's are imported under names of their own
(``_cluster_grid_a``, ...), in import order, each one's imports of its siblings
(``from md.neighbors._cluster_grid import ...``) given the same tree's copy; everything
else they import (``md._simd``) is this checkout's. Their kernels are cached beside the
package's kernel cache folder (``md._kernel_cache``), in a folder per tag: not in the
package's own, where a tree's copies, compiled under their own module names, would take
the places of its kernels (the package then failed to load them: "No module named
'_cluster_search_b'").
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import inspect
import statistics
import sys
import time
import types
from collections.abc import Iterator
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the checkout, from anywhere

import numpy as np  # noqa: E402
from _machine import machine_line  # noqa: E402
from cluster_search import melt  # noqa: E402
from numba.core import config  # noqa: E402

import md  # noqa: E402
from md._kernel_cache import cache_directory  # noqa: E402
from md._memory import KeptArrays  # noqa: E402
from md.parallel import get_threads, set_threads  # noqa: E402

OUTER, INNER = 4.0, 2.8


#: The cluster kernels' modules of ``md/neighbors/`` in import order: since issue 70's
#: split, then before it.
LAYOUTS = (("_cluster_grid", "_cluster_prune", "_cluster_search"), ("_cluster_kernels",))


@contextlib.contextmanager
def _versions_cache(tag: str) -> Iterator[None]:
    """numba's cache folder, while a tree's modules are decorated, one of this script's
    own per tag (a user's ``NUMBA_CACHE_DIR`` wins)."""
    if config.CACHE_DIR:
        yield
        return
    config.CACHE_DIR = str(cache_directory().parent / "numba-versions" / tag)
    try:
        yield
    finally:
        config.CACHE_DIR = ""


def load(tree: str, tag: str) -> types.SimpleNamespace:
    """The cluster kernels of the checkout ``tree`` (its modules imported as
    ``<module>_<tag>``), their names together in one namespace."""
    folder = Path(tree) / "md" / "neighbors"
    names = next((n for n in LAYOUTS if all((folder / f"{m}.py").is_file() for m in n)), None)
    if names is None:
        raise SystemExit(f"{tree}: no cluster kernels in {folder} (neither of {LAYOUTS})")
    kernels = types.SimpleNamespace()
    package = {}  # the package's own modules of these names, put back afterwards
    try:
        for name in names:
            spec = importlib.util.spec_from_file_location(f"{name}_{tag}", folder / f"{name}.py")
            module = importlib.util.module_from_spec(spec)
            sys.modules[spec.name] = module
            with _versions_cache(tag):
                spec.loader.exec_module(module)
            # the next modules' "from md.neighbors.<name> import ..." take this tree's copy
            package.setdefault(f"md.neighbors.{name}", sys.modules.get(f"md.neighbors.{name}"))
            sys.modules[f"md.neighbors.{name}"] = module
            vars(kernels).update(vars(module))
    finally:
        for full, module in package.items():
            if module is None:
                sys.modules.pop(full, None)
            else:
                sys.modules[full] = module
    return kernels


def _takes_kept(function) -> bool:
    """Whether a tree's ``function`` takes ``kept`` (arrays kept from call to call, as the
    NeighborList keeps them since issue 70's buffers; a tree from before makes its own)."""
    return "kept" in inspect.signature(getattr(function, "py_func", function)).parameters


def builder(kernels, positions, box, chunks):
    """One mixed build's kernel calls with ``kernels``: (grid, whole build) callables,
    each call into the same kept arrays where the tree's kernels take them."""
    ncx, ncy = kernels.column_counts(box, len(positions), OUTER)
    reach2 = np.float32((OUTER * (1 + 1e-5)) ** 2)
    inner2 = np.float32((INNER * (1 + 1e-5)) ** 2)
    kept = KeptArrays()
    grid_kept = {"kept": kept} if _takes_kept(kernels.cluster_grid) else {}
    search_kept = {"kept": kept} if _takes_kept(kernels.search_pairs) else {}

    def grid():
        return kernels.cluster_grid(positions, box, ncx, ncy, chunks, **grid_kept)

    def build():
        first, atom, origin, lower, upper = grid()
        if grid_kept:
            xi = kept.take("relative i", 3 * len(atom), np.float32)
            xj = kept.take("relative j", 3 * len(atom), np.float32)
        else:
            xi = np.empty(3 * len(atom), np.float32)
            xj = np.empty_like(xi)
        kernels.cluster_positions(positions, atom, origin, xi, xj)
        return kernels.search_pairs(
            box,
            ncx,
            ncy,
            first,
            lower,
            upper,
            OUTER,
            chunks,
            128,
            xi,
            xj,
            reach2,
            inner2,
            **search_kept,
        )

    return grid, build


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("a", help="the first checkout, a tree with md/neighbors/ (the code before)")
    parser.add_argument("b", help="the second checkout (such as this one: .)")
    parser.add_argument("--cells", type=int, default=20, help="fcc cells per edge (20)")
    parser.add_argument("--repeats", type=int, default=15, help="turns (15)")
    parser.add_argument("--threads", default="1", help="thread counts (1)")
    parser.add_argument("--warm", type=int, default=100, help="steps before timing (100)")
    args = parser.parse_args()
    md.keep_freed_memory()
    print(machine_line())
    state = melt(args.cells, "double", args.warm).state
    versions = {"a": load(args.a, "a"), "b": load(args.b, "b")}
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
