"""The cluster list's dynamic pruning: the MD loop of the mixed-precision melt per outer skin.

On LAMMPS's LJ melt (fcc at reduced density 0.8442, T* = 3 start, rc 2.5, skin 0.3,
velocity Verlet dt 0.005, mixed precision on the cluster-pair list), one Simulation
per outer skin (``NeighborList(..., clusters=True, outer_skin=...)``; an outer skin
equal to the skin searches at cutoff + skin and never prunes), each run past the
melt's first ``--warm`` steps, then ``--steps`` steps per repeat, taking turns within
each repeat. Prints per outer skin the median time per step, the searches and prunes
per repeat, the outer and inner list sizes in cluster pairs, and the median of the
per-repeat ratios to the first outer skin given. Compilation is excluded (the warm-up).
``--sections`` also prints where a step goes per outer skin: the force call, the list
(its searches and prunes, each call timed: ``md.neighbors.lists``' ``search_pairs`` and
``prune_pairs`` wrapped in timers, the rest of a search's build and the per-step
displacement check) and the integrator, in ms per step. ``--every N`` adds a row with
GROMACS's list rule (``neighbor_every=N``, no check, no outer list, skin ``--every-skin``,
0.332: rlist 2.832 as GROMACS's Verlet buffer picks for nstlist 20 on this melt); not
exact, so its ratio is not the pruning's but the rule's. ``faults/step``: the process's
minor page faults (``getrusage``'s ``ru_minflt``) per step, median over the repeats;
``CPU ms``: the process's CPU time (user and system, all its threads) per step, median;
``--keep-freed`` calls ``md.keep_freed_memory()`` first, as the ``md`` command does (the
default leaves glibc's own thresholds, as a Python program or a benchmark's worker has
them; the setting holds for the whole process, so compare the two in separate runs).

    python benchmarks/cluster_pruning.py                        # outer 0.3, 0.9, 1.2, 1.5
    python benchmarks/cluster_pruning.py --threads 2 --outer 0.3,1.2 --repeats 5
    python benchmarks/cluster_pruning.py --outer 1.5 --sections --threads 2
    python benchmarks/cluster_pruning.py --outer 1.5 --every 20 --repeats 7 --threads 2
    python benchmarks/cluster_pruning.py --outer 1.5 --sections --keep-freed
"""

from __future__ import annotations

import argparse
import resource
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the checkout, from anywhere

from _machine import machine_line  # noqa: E402

import md  # noqa: E402
import md.neighbors.lists  # noqa: E402
from integrators import VelocityVerlet  # noqa: E402
from md.build import maxwell_boltzmann  # noqa: E402
from md.neighbors import NeighborList  # noqa: E402
from md.parallel import set_threads  # noqa: E402
from potentials import LennardJones  # noqa: E402

CUTOFF, SKIN, DT = 2.5, 0.3, 0.005


def simulation(cells: int, outer: float, every: int = 1, skin: float = SKIN) -> md.Simulation:
    """The mixed melt with the cluster list of ``outer`` skin; ``every`` > 1: the list
    rebuilt every that many steps with no check, at ``skin``, no outer list."""
    start = maxwell_boltzmann(md.lattice("fcc", cells, density=0.8442), 3.0, seed=1)
    sim = md.Simulation(
        start, [LennardJones(cutoff=CUTOFF)], VelocityVerlet(DT), precision="mixed", skin=skin
    )
    sim.forcefield.neighbor_list = NeighborList(
        CUTOFF, skin, clusters=True, outer_skin=outer, every=every, check=every == 1
    )
    sim.forcefield.invalidate()
    return sim


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=20, help="fcc cells per edge (20)")
    parser.add_argument("--threads", type=int, default=1, help="threads (1)")
    parser.add_argument(
        "--outer",
        default="0.3,0.9,1.2,1.5",
        help="outer skins, the first the reference (0.3,0.9,1.2,1.5)",
    )
    parser.add_argument("--steps", type=int, default=200, help="steps per repeat (200)")
    parser.add_argument("--repeats", type=int, default=3, help="interleaved repeats (3)")
    parser.add_argument("--warm", type=int, default=300, help="steps before timing (300)")
    parser.add_argument(
        "--sections",
        action="store_true",
        help="also where a step goes: force, searches, prunes, integrator",
    )
    parser.add_argument(
        "--keep-freed",
        action="store_true",
        help="call md.keep_freed_memory() first (as the md command does); default: glibc's own",
    )
    parser.add_argument(
        "--every",
        type=int,
        default=0,
        help="also a row with the list rebuilt every N steps, no check",
    )
    parser.add_argument(
        "--every-skin",
        type=float,
        default=0.332,
        help="that row's skin (0.332: GROMACS's rlist 2.832 for nstlist 20)",
    )
    args = parser.parse_args(argv)
    try:
        outers = [float(x) for x in args.outer.split(",")]
    except ValueError:
        parser.error(f"--outer takes comma-separated numbers, got {args.outer!r}")
    if any(not outer >= 0 for outer in outers):
        parser.error(f"--outer skins must be >= 0, got {args.outer!r}")
    if args.every < 0 or (args.every and not args.every_skin > 0):
        parser.error(
            f"--every must be >= 1 (0: no such row) and --every-skin > 0, got "
            f"{args.every} and {args.every_skin}"
        )
    for name in ("cells", "threads", "steps", "repeats"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be at least 1, got {getattr(args, name)}")
    set_threads(args.threads)
    kept = md.keep_freed_memory() if args.keep_freed else False
    print(machine_line())
    print(
        f"{4 * args.cells**3} atoms, {args.threads} thread(s), mixed precision, skin {SKIN}; "
        f"{args.repeats} repeats of {args.steps} steps after {args.warm}; freed memory "
        f"{'kept (md.keep_freed_memory)' if kept else 'as glibc keeps it (its defaults)'}"
    )
    sims = {f"{outer:g}": simulation(args.cells, outer) for outer in outers}
    if args.every:
        sims[f"every {args.every}"] = simulation(
            args.cells, args.every_skin, args.every, args.every_skin
        )
    for sim in sims.values():
        sim.run(args.warm)
    rows = list(sims)
    times = {row: [] for row in rows}
    counts = {row: [] for row in rows}
    faults = {row: [] for row in rows}
    cpu = {row: [] for row in rows}
    calls = _timed_calls() if args.sections else None
    split = {row: [] for row in rows}
    for _ in range(args.repeats):
        for outer, sim in sims.items():
            nl = sim.forcefield.neighbor_list
            builds, prunes = nl.n_builds, nl.n_prunes
            before = _seconds(sim, calls)
            usage = resource.getrusage(resource.RUSAGE_SELF)
            start = time.perf_counter()
            sim.run(args.steps)
            times[outer].append((time.perf_counter() - start) / args.steps)
            done = resource.getrusage(resource.RUSAGE_SELF)
            faults[outer].append((done.ru_minflt - usage.ru_minflt) / args.steps)
            seconds = done.ru_utime + done.ru_stime - usage.ru_utime - usage.ru_stime
            cpu[outer].append(seconds / args.steps)
            counts[outer].append((nl.n_builds - builds, nl.n_prunes - prunes))
            after = _seconds(sim, calls)
            split[outer].append({k: (after[k] - before[k]) / args.steps for k in after})
    reference = times[rows[0]]
    print(
        f"{'outer skin':>10} {'ms/step':>8} {'searches':>9} {'prunes':>7} {'pairs':>8} "
        f"{'outer pairs':>11} {'ratio':>6} {'faults/step':>11} {'CPU ms':>7}"
    )
    for outer in rows:
        nl = sims[outer].forcefield.neighbor_list
        ratio = statistics.median(t / r for t, r in zip(times[outer], reference, strict=True))
        searches = statistics.median(c[0] for c in counts[outer])
        prunes = statistics.median(c[1] for c in counts[outer])
        pairs = nl.clusters.n_pairs if nl.clusters is not None else "-"
        outer_pairs = nl.outer_clusters.n_pairs if nl.outer_clusters is not None else "-"
        print(
            f"{outer:>10} {1e3 * statistics.median(times[outer]):>8.2f} {searches:>9g} "
            f"{prunes:>7g} {pairs:>8} {outer_pairs:>11} {ratio:>6.3f} "
            f"{statistics.median(faults[outer]):>11.2f} {1e3 * statistics.median(cpu[outer]):>7.2f}"
        )
    if calls is None:
        return
    print(
        "where a step goes, ms per step (median over the repeats): the force call; the list:"
        " searches (search_pairs), prunes (prune_pairs, a search's own included), the rest"
        " (grid, relative positions, the displacement check); the integrator"
    )
    names = ("force", "search", "prune", "list rest", "integrator")
    print(f"{'outer skin':>10} " + " ".join(f"{name:>10}" for name in names))
    for outer in rows:
        parts = split[outer]
        rest = [p["neighbor"] - p["search"] - p["prune"] for p in parts]
        values = [statistics.median(p[k] for p in parts) for k in ("force", "search", "prune")]
        values += [statistics.median(rest), statistics.median(p["integrate"] for p in parts)]
        print(f"{outer:>10} " + " ".join(f"{1e3 * v:>10.3f}" for v in values))


def _timed_calls() -> dict:
    """Wrap ``md.neighbors.lists``' search and prune kernels in timers (seconds in total)."""
    totals = {"search": 0.0, "prune": 0.0}
    for key, name in (("search", "search_pairs"), ("prune", "prune_pairs")):
        kernel = getattr(md.neighbors.lists, name)

        def timed(*args, _kernel=kernel, _key=key, **keywords):
            start = time.perf_counter()
            try:
                return _kernel(*args, **keywords)
            finally:
                totals[_key] += time.perf_counter() - start

        setattr(md.neighbors.lists, name, timed)
    return totals


def _seconds(sim: md.Simulation, calls: dict | None) -> dict:
    """The run's seconds so far: force call, list, integrator and, if timed, the
    searches and prunes (all the runs' together: taken as differences around one)."""
    return {
        "force": sim.forcefield.timings["force"],
        "neighbor": sim.forcefield.timings["neighbor"],
        "integrate": sim.timings["integrate"],
        **(calls or {}),
    }


if __name__ == "__main__":
    main()
