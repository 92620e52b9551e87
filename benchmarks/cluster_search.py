"""A list build's cost: mixed precision's cluster search against double's cell search.

On LAMMPS's LJ melt (fcc at reduced density 0.8442, T* = 3, rc 2.5, skin 0.3), one
double and one mixed-precision Simulation run ``--warm`` steps (the melt, and the
kernels compiled), then each repeat times, per thread count, taking turns: the double
list's build (the cell search: ``NeighborList.build``), the mixed list's build (the
cluster grid, the cluster-pair search at the outer radius and its own prune, written
in the same pass), the cluster grid alone (the atoms sorted into columns, each by z,
and cut into clusters with their boxes: part of the mixed build) and one prune of its
outer list between searches. Wall time, and
the calling thread's CPU time (steadier on a shared machine: it leaves out the time
the process waited for a core; on one thread the whole call, on more the main thread's
share only); per thread count, the medians and the median of the per-repeat ratios of
the wall times, mixed / double. A run of the MD loop amortises a search over its
prunes (about 9 searches and 30 prunes per 200 steps on this melt); ``compare.py``
and ``cluster_pruning.py --sections`` give the loop's share.

    python benchmarks/cluster_search.py                       # 32000 atoms, threads 1,2
    python benchmarks/cluster_search.py --cells 30 --repeats 21 --threads 1
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from functools import partial
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the checkout, from anywhere

import numpy as np  # noqa: E402
from _machine import machine_line  # noqa: E402

import md  # noqa: E402
from integrators import VelocityVerlet  # noqa: E402
from md.neighbors._cluster_grid import cluster_grid, column_counts  # noqa: E402
from md.neighbors._cluster_prune import prune_pairs  # noqa: E402
from md.parallel import get_threads, set_threads  # noqa: E402
from potentials import LennardJones  # noqa: E402

DENSITY, TEMPERATURE, CUTOFF, SKIN, DT, SEED = 0.8442, 3.0, 2.5, 0.3, 0.005, 87287


def melt(cells: int, precision: str, warm: int) -> md.Simulation:
    state = md.maxwell_boltzmann(md.lattice("fcc", cells, density=DENSITY), TEMPERATURE, seed=SEED)
    potential = LennardJones(epsilon=1.0, sigma=1.0, cutoff=CUTOFF, cutoff_mode="none")
    sim = md.Simulation(state, [potential], VelocityVerlet(dt=DT), skin=SKIN, precision=precision)
    sim.run(warm)
    return sim


def timed(call) -> tuple[float, float]:
    wall, cpu = time.perf_counter(), time.thread_time()
    call()
    return time.perf_counter() - wall, time.thread_time() - cpu


def pruner(nl, positions):
    """A prune of ``nl``'s outer list at ``positions`` (the pass between searches: the
    relative positions, then the atom check at the list radius), or None without one."""
    outer = nl.outer_clusters
    if outer is None:
        return None
    n, size = outer.n_clusters, outer.n_pairs
    xi, xj = np.empty(12 * n, np.float32), np.empty(12 * n, np.float32)
    starts, partners, offsets, marks = (
        np.empty(n + 1, np.int64),
        np.empty(size, np.int32),
        np.empty((size, 3), np.float32),
        np.empty(size, np.uint8),
    )
    reach2 = np.float32((nl.list_radius * (1.0 + 1e-5)) ** 2)

    def prune():
        outer.relative_positions(positions, xi, xj)
        prune_pairs(
            outer.starts,
            outer.partners,
            outer.offsets,
            outer.bounds,
            xi,
            xj,
            reach2,
            starts,
            partners,
            offsets,
            marks,
        )

    return prune


def gridder(nl, state):
    """The mixed build's cluster grid of ``state`` (its columns at the search's radius:
    the outer list's where there is one), on as many chunks as threads."""
    outer = nl.outer_clusters is not None
    radius = nl.cutoff + nl.outer_skin if outer else nl.list_radius
    ncx, ncy = column_counts(state.box, state.n_atoms, radius)
    return lambda: cluster_grid(state.positions, state.box, ncx, ncy, get_threads())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=20, help="fcc cells per edge (20)")
    parser.add_argument("--repeats", type=int, default=15, help="turns (15)")
    parser.add_argument("--threads", default="1,2", help="thread counts (1,2)")
    parser.add_argument("--warm", type=int, default=100, help="steps before timing (100)")
    args = parser.parse_args()
    md.keep_freed_memory()
    threads = [int(t) for t in args.threads.split(",")]
    print(machine_line())
    double = melt(args.cells, "double", args.warm)
    mixed = melt(args.cells, "mixed", args.warm)
    lists = {"double": double.forcefield.neighbor_list, "mixed": mixed.forcefield.neighbor_list}
    if lists["mixed"].outer_clusters is None:
        print("the mixed list has no outer list in this box: nothing to prune")
    before = get_threads()
    times: dict[tuple[int, str], list[tuple[float, float]]] = {}
    try:
        for count in threads:  # the grid's own call once per thread count, untimed
            set_threads(count)
            gridder(lists["mixed"], mixed.state)()
        for _ in range(args.repeats):
            for count in threads:
                set_threads(count)
                for name, sim in (("double", double), ("mixed", mixed)):
                    nl = lists[name]
                    times.setdefault((count, name), []).append(timed(partial(nl.build, sim.state)))
                grid = gridder(lists["mixed"], mixed.state)
                times.setdefault((count, "grid"), []).append(timed(grid))
                prune = pruner(lists["mixed"], mixed.state.positions)
                if prune is not None:
                    times.setdefault((count, "prune"), []).append(timed(prune))
    finally:
        set_threads(before)
    n = double.state.n_atoms
    print(
        f"{n} atoms, {args.repeats} repeats; ms per call, wall / CPU (medians), and the median "
        "of per-repeat ratios to the double build (wall)"
    )
    print(f"{'threads':>7} {'call':<28} {'wall ms':>8} {'CPU ms':>8} {'/ double':>9}")
    labels = {
        "double": "double: cell search",
        "mixed": "mixed: grid + search + prune",
        "grid": "mixed: the grid alone",
        "prune": "mixed: a prune",
    }
    for count in threads:
        reference = times[(count, "double")]
        for key, label in labels.items():
            runs = times.get((count, key))
            if not runs:
                continue
            wall = statistics.median(w for w, _ in runs)
            cpu = statistics.median(c for _, c in runs)
            ratio = statistics.median(w / r[0] for (w, _), r in zip(runs, reference, strict=True))
            print(f"{count:>7} {label:<28} {1e3 * wall:8.2f} {1e3 * cpu:8.2f} {ratio:9.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
