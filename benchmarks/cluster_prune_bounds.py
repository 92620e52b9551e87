"""The bounded prune against the full one, prune by prune, in one MD run of the mixed melt.

On LAMMPS's LJ melt (fcc at reduced density 0.8442, T* = 3, rc 2.5, skin 0.3, velocity
Verlet dt 0.005, mixed precision on the cluster list with its outer list), the run's own
prunes between searches (``NeighborList._prune``: the relative positions, the clusters'
drifts and the bounded check, which checks atom by atom only the pairs whose verdict
may have changed) each timed beside a full prune of the same outer list at the same
positions (the relative positions and ``prune_pairs``, every pair checked, the code
before), in turns whose order alternates; the two lists compared pair for pair. Prints
per thread count the medians (wall and the calling thread's CPU ms), the median of the
per-prune ratios bounded / full, the share of pairs the bounded prune checked, and the
double list's cell search per build in the same process beside them; then LAMMPS's
neighbour time per build on the same melt (a child process, ``lammps_lj_melt.py``, one
thread), when the ``lammps`` module is there.

    python benchmarks/cluster_prune_bounds.py                  # 32000 atoms, threads 1,2
    python benchmarks/cluster_prune_bounds.py --threads 1 --steps 300 --no-lammps
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from functools import partial
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the checkout, from anywhere

import lj_melt  # noqa: E402
import numpy as np  # noqa: E402
from _machine import machine_line  # noqa: E402
from cluster_search import melt, pruner  # noqa: E402

import md  # noqa: E402
from md.parallel import get_threads, set_threads  # noqa: E402


def timed(call) -> tuple[float, float]:
    wall, cpu = time.perf_counter(), time.thread_time()
    call()
    return time.perf_counter() - wall, time.thread_time() - cpu


def prunes_of(sim: md.Simulation, steps: int) -> list[dict]:
    """Run ``steps`` steps, each prune of the run's list timed beside a full one."""
    nl = sim.forcefield.neighbor_list
    bounded = nl._prune
    found: list[dict] = []

    def both(positions):
        outer = nl.outer_clusters
        full = pruner(nl, positions)
        checks = nl.n_prune_checks
        record = {"pairs": outer.n_pairs - outer.n_clusters}
        if len(found) % 2:
            record["full"] = timed(full)
            record["bounded"] = timed(lambda: bounded(positions))
        else:
            record["bounded"] = timed(lambda: bounded(positions))
            record["full"] = timed(full)
        record["checked"] = nl.n_prune_checks - checks
        # the full prune's list, made again for the comparison (untimed)
        starts, partners, offsets = _full_list(nl, positions)
        mine = nl.clusters
        record["same"] = (
            np.array_equal(mine.starts, starts)
            and np.array_equal(mine.partners, partners)
            and np.array_equal(mine.offsets, offsets)
        )
        found.append(record)

    nl._prune = both
    try:
        sim.run(steps)
    finally:
        del nl._prune
    return found


def _full_list(nl, positions):
    from md.neighbors._cluster_kernels import prune_pairs  # the benchmark's reference only

    outer = nl.outer_clusters
    n, size = outer.n_clusters, outer.n_pairs
    xi, xj = np.empty(12 * n, np.float32), np.empty(12 * n, np.float32)
    outer.relative_positions(positions, xi, xj)
    starts = np.empty(n + 1, np.int64)
    partners = np.empty(size, np.int32)
    offsets = np.empty((size, 3), np.float32)
    kept = prune_pairs(
        outer.starts,
        outer.partners,
        outer.offsets,
        outer.bounds,
        xi,
        xj,
        nl._prune_reach2(),
        starts,
        partners,
        offsets,
    )
    return starts, partners[:kept], offsets[:kept]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=20, help="fcc cells per edge (20)")
    parser.add_argument("--steps", type=int, default=200, help="timed steps per thread count")
    parser.add_argument("--threads", default="1,2", help="thread counts (1,2)")
    parser.add_argument("--warm", type=int, default=100, help="steps before timing (100)")
    parser.add_argument("--no-lammps", action="store_true", help="leave LAMMPS out")
    args = parser.parse_args()
    md.keep_freed_memory()
    threads = [int(t) for t in args.threads.split(",")]
    print(machine_line())
    mixed = melt(args.cells, "mixed", args.warm)
    double = melt(args.cells, "double", 5)
    if mixed.forcefield.neighbor_list.outer_clusters is None:
        print("the mixed list has no outer list in this box: nothing to prune")
        return 0
    dnl = double.forcefield.neighbor_list
    before = get_threads()
    rows = []
    try:
        for count in threads:
            set_threads(count)
            mixed.run(20)  # the threaded kernels loaded, untimed
            found = prunes_of(mixed, args.steps)
            dnl.build(double.state)
            builds = [timed(partial(dnl.build, double.state)) for _ in range(7)]
            rows.append((count, found, builds))
    finally:
        set_threads(before)
    n = mixed.state.n_atoms
    print(
        f"{n} atoms, {args.steps} steps per thread count; a prune between searches, ms "
        "(medians; wall / calling thread's CPU), bounded / full (median of per-prune wall "
        "and CPU ratios), the pairs the bounded prune checked, the double cell search per build"
    )
    print(
        f"{'threads':>7} {'prunes':>6} {'full ms':>15} {'bounded ms':>15} {'b/f wall':>8} "
        f"{'b/f CPU':>8} {'checked':>8} {'same':>5} {'double build ms':>16}"
    )
    for count, found, builds in rows:
        if not found:
            print(f"{count:>7} {0:>6} (no prune in the timed steps)")
            continue

        def med(key, part, runs=found):
            return 1e3 * statistics.median(r[key][part] for r in runs)

        ratio = [
            statistics.median(r["bounded"][p] / r["full"][p] for r in found if r["full"][p] > 0)
            for p in (0, 1)
        ]
        share = sum(r["checked"] for r in found) / sum(r["pairs"] for r in found)
        same = all(r["same"] for r in found)
        dwall = 1e3 * statistics.median(w for w, _ in builds)
        dcpu = 1e3 * statistics.median(c for _, c in builds)
        print(
            f"{count:>7} {len(found):>6} {med('full', 0):7.3f}/{med('full', 1):7.3f} "
            f"{med('bounded', 0):7.3f}/{med('bounded', 1):7.3f} {ratio[0]:8.3f} {ratio[1]:8.3f} "
            f"{share:8.1%} {str(same):>5} {dwall:8.3f}/{dcpu:7.3f}"
        )
    if not args.no_lammps:
        try:
            result = lj_melt.run_lammps(args.cells, 100, "check", lj_melt.lammps_environment())
        except (OSError, RuntimeError) as error:
            print(f"LAMMPS: not run ({error})")
        else:
            neigh = (result.get("sections") or {}).get("Neigh")
            builds = result.get("n_builds")
            if neigh and builds:
                print(
                    f"LAMMPS {result.get('version', '?')} lj/cut, 1 thread, this melt, 100 "
                    f"steps: Neigh {1e3 * neigh / builds:.2f} ms per build ({builds} builds)"
                )
            else:
                print(f"LAMMPS: no Neigh section or build count in {sorted(result)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
