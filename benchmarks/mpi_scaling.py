"""MPI scaling of the LJ melt: ours (``md.distributed``) next to LAMMPS on the same ranks.

    python benchmarks/mpi_scaling.py              # about 10 minutes on 2 cores
    python benchmarks/mpi_scaling.py --quick      # a smoke run, about 2 minutes
    python benchmarks/mpi_scaling.py --fixed-only --repeats 7   # (e) alone, 2-3 minutes

Prints the machine (CPU model, vector ISA, cores, load), then

(a) strong scaling of the 32000-atom LJ melt (``examples/lj_melt.toml``) and
    of a 2,048,000-atom melt (the same config on an 80^3-cell lattice: same
    density and temperature) on 1 rank x 1 thread, 2 ranks x 1 thread and
    1 rank x 2 threads, each next to LAMMPS with the same ranks and threads
    (``mpiexec -n P`` of ``_mpi_worker.py``; LAMMPS's OPENMP package for its
    threads);
(b) the seconds a step spends communicating, at equal atoms per rank (the same
    melt on the same ranks): ours is the run summary's "comm" section (halo
    exchange, reverse pass, migration and reductions), LAMMPS's its "Comm" row,
    both averaged over the ranks and divided by the steps (seconds, not a share
    of the loop: a loop twice as fast doubles the share of equal seconds);
(c) weak scaling at 32000 atoms per rank (1 rank: 20^3 cells, 2 ranks:
    40 x 20 x 20 cells);
(d) the latency and bandwidth of messages between two ranks here (a mpi4py
    ping-pong), and a decomposed step's messages alone, as before issue 69 and since;
(e) the fixed cost of a decomposed step on 1, 2, 3 and 4 ranks: the per-step loop
    time of a tiny melt (1152 atoms) on P ranks less 1/P of its time on one rank
    (issue 69's figure; 3 and 4 ranks oversubscribe a 2-core machine, so theirs
    holds the contention too), ours next to LAMMPS's, and ours also in each rank's own
    CPU time a step (thread time outside its MPI calls: the waits left out);
(f) a model of each engine's parallel efficiency at 64 and 1024 ranks from these
    figures and the tiny melt on 2 ranks (the fixed costs of a step), checked on
    the runs it was not fitted to (see ``benchmarks/README.md``).

``--balance-every N`` adds, at each size, ours on 2 ranks x 1 thread with dynamic
load balancing (``[run] balance_every = N``, threshold 1.02): its rate, comm share and
ratio to 1 rank x 2 threads are printed below (a) and (b). ``--bind`` launches every
run with ``mpiexec -bind-to core:T`` (each rank on T cores of its own, T its threads;
ours and LAMMPS alike): on a machine whose cores run at different speeds a rank then stays on its
core, which load balancing can allow for.

Every run is a fresh ``mpiexec`` launch; repeats go round-robin over all the
runs (interleaved), and the tables give medians and the min-max. Rates are
atom-steps per second of the timed loop (setup, the first list and forces
excluded, as LAMMPS's "Loop time"). Ranks wait by polling (MPICH's default),
as LAMMPS's do: on a machine with fewer free cores than ranks x threads the
rows measure the contention, not the code.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

from _machine import machine_line
from lj_melt import find_libmpi

HERE = Path(__file__).resolve().parent
WORKER = HERE / "_mpi_worker.py"
#: (label, cells, steps): the full run and --quick.
SIZES = {
    False: [("32000", (20, 20, 20), 200), ("2M", (80, 80, 80), 20)],
    True: [("32000", (20, 20, 20), 50), ("256000", (40, 40, 40), 10)],
}
#: (ranks, threads per rank) of the strong-scaling rows.
LAYOUTS = [(1, 1), (2, 1), (1, 2)]
#: Weak scaling: 32000 atoms (20^3 fcc cells) per rank, the ranks stacked along x.
WEAK_CELLS = 20
#: The smallest melt, for the model's fixed costs of a step: 1152 atoms, two bricks of cutoff
#: + skin along x on 2 ranks (steps: the full run and --quick).
TINY_CELLS, TINY_STEPS = (8, 6, 6), {False: 1000, True: 200}
#: The ranks of the tiny melt's runs: the fixed cost of a decomposed step on each.
TINY_RANKS = (1, 2, 3, 4)
#: Issue 69's target for the fixed cost of a decomposed step on 2 ranks [s].
TARGET_FIXED = 25e-6
#: The imbalance (busiest rank's busy time over the mean) at which --balance-every moves planes.
BALANCE_THRESHOLD = 1.02
#: Issue 35's targets on a 2-core machine.
TARGET_RANKS_OVER_THREADS = 0.85


@dataclass(frozen=True)
class Job:
    engine: str  # "ours" or "lammps"
    cells: tuple[int, int, int]
    steps: int
    ranks: int
    threads: int
    balance_every: int = 0  # ours: dynamic load balancing (0: off)

    @property
    def n_atoms(self) -> int:
        return 4 * self.cells[0] * self.cells[1] * self.cells[2]


@dataclass
class Measured:
    job: Job
    runs: list[dict] = field(default_factory=list)

    def rates(self) -> list[float]:
        return [self.job.n_atoms * r["n_steps"] / r["loop_time"] for r in self.runs]

    def median(self) -> float:
        return statistics.median(self.rates()) if self.runs else float("nan")

    def comm_share(self, key: str = "comm_share") -> float:
        """Median over the repeats of the mean share over the ranks (``comm_share_min``:
        of the least-waiting rank's share)."""
        if not self.runs:
            return float("nan")
        return statistics.median(r.get(key, r["comm_share"]) for r in self.runs)


def environment(threads: int) -> dict[str, str]:
    """Each rank's environment: OMP threads for LAMMPS, libmpi on the loader path, this
    checkout first on the Python path."""
    env = dict(os.environ, OMP_NUM_THREADS=str(threads))
    paths = [str(HERE.parent), *[p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]]
    env["PYTHONPATH"] = os.pathsep.join(paths)
    folder = find_libmpi()
    if folder is not None:
        libs = [p for p in env.get("LD_LIBRARY_PATH", "").split(os.pathsep) if p]
        env["LD_LIBRARY_PATH"] = os.pathsep.join([str(folder), *libs])
    return env


def launch(job: Job | None, payload: dict, timeout: float, bind: bool = False) -> dict:
    """Run the worker on ``payload['ranks']`` ranks (``bind``: each on cores of its own,
    one per thread: ``mpiexec -bind-to core:T``); return rank 0's JSON line."""
    ranks = payload.pop("ranks", 1)
    binding = ["-bind-to", f"core:{int(payload.get('threads', 1))}"] if bind else []
    command = [
        "mpiexec",
        *binding,
        "-n",
        str(ranks),
        sys.executable,
        str(WORKER),
        json.dumps(payload),
    ]
    done = subprocess.run(
        command,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=environment(int(payload.get("threads", 1))),
    )
    lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
    if done.returncode != 0 or not lines:
        what = "probe" if job is None else f"{job.engine} {job.ranks}x{job.threads} {job.cells}"
        raise RuntimeError(f"{what} failed (exit {done.returncode}): {done.stderr[-1500:]}")
    return json.loads(lines[-1])


def probe_lammps() -> tuple[bool, str]:
    """Whether LAMMPS runs here under ``mpiexec -n 2`` (built with MPI, sees 2 ranks)."""
    try:
        found = launch(None, {"engine": "probe", "ranks": 2}, timeout=120)
    except (RuntimeError, subprocess.TimeoutExpired) as error:
        return False, f"LAMMPS does not run under mpiexec here: {str(error)[:300]}"
    if not found["has_mpi_support"] or found["world_size"] != 2:
        return False, f"this LAMMPS ({found['version']}) was built without MPI: left out"
    omp = "with" if found["omp"] else "without"
    return True, f"LAMMPS {found['version']}, MPI (2 ranks seen), {omp} OPENMP"


def jobs_for(quick: bool, lammps: bool, balance_every: int = 0) -> list[Job]:
    engines = ["ours", "lammps"] if lammps else ["ours"]
    jobs = []
    for _, cells, steps in SIZES[quick]:
        for ranks, threads in LAYOUTS:
            jobs += [Job(engine, cells, steps, ranks, threads) for engine in engines]
        if balance_every:
            jobs.append(Job("ours", cells, steps, 2, 1, balance_every))
    weak_steps = SIZES[quick][0][2]
    weak = (2 * WEAK_CELLS, WEAK_CELLS, WEAK_CELLS)
    jobs += [Job(engine, weak, weak_steps, 2, 1) for engine in engines]
    jobs += [
        Job(engine, TINY_CELLS, TINY_STEPS[quick], ranks, 1)
        for ranks in TINY_RANKS
        for engine in engines
    ]
    return jobs


def measure(
    jobs: list[Job], repeats: int, timeout: float, bind: bool = False, velocities: str = "gaussian"
) -> dict[Job, Measured]:
    measured = {job: Measured(job) for job in jobs}
    for repeat in range(repeats):
        for job in jobs:
            payload = {
                "engine": job.engine,
                "cells": list(job.cells),
                "steps": job.steps,
                "threads": job.threads,
                "ranks": job.ranks,
            }
            if job.balance_every:
                payload.update(balance_every=job.balance_every, balance_threshold=BALANCE_THRESHOLD)
            if job.engine == "lammps":
                payload["velocities"] = velocities
            result = launch(job, payload, timeout, bind)
            measured[job].runs.append(result)
            balanced = f", balanced ({result['balances']} moves)" if job.balance_every else ""
            print(
                f"  [{repeat + 1}/{repeats}] {job.engine:<6}{balanced} {job.ranks} rank(s) x "
                f"{job.threads} thread(s), {job.n_atoms} atoms: "
                f"{job.n_atoms * result['n_steps'] / result['loop_time'] / 1e6:.2f} M "
                f"atom-steps/s, comm {100 * result['comm_share']:.1f} %",
                flush=True,
            )
    return measured


def spread(item: Measured) -> str:
    rates = item.rates()
    return f"{min(rates) / 1e6:.2f}-{max(rates) / 1e6:.2f}" if rates else "-"


def busy_spread(item: Measured) -> str:
    """The median over the repeats of the busiest rank's force and neighbour time over the
    least busy one's (each engine's own sections: ours force + neighbor, LAMMPS's Pair +
    Neigh, their max over min; an upper bound for LAMMPS, whose max and min may be two
    ranks)."""
    spreads = [r.get("busy_spread") for r in item.runs]
    return "-" if not spreads or None in spreads else f"{statistics.median(spreads):.2f}"


def build_count(item: Measured) -> str:
    """The median list builds of the timed loops (the same workload: about the same count)."""
    counts = [r.get("n_builds") for r in item.runs]
    return "-" if not counts or None in counts else f"{statistics.median(counts):g}"


def run_comm(run: dict, key: str = "comm_share") -> float:
    """One run's communication seconds a step (``key``: the mean rank's share, or the least
    communicating rank's, times the loop time)."""
    return run.get(key, run["comm_share"]) * run["loop_time"] / run["n_steps"]


def comm_per_step(item: Measured | None, key: str = "comm_share") -> float:
    """The median over the repeats of the communication seconds a step (:func:`run_comm`)."""
    if item is None or not item.runs:
        return float("nan")
    return statistics.median(run_comm(r, key) for r in item.runs)


def cell(value: float, fmt: str = ".2f") -> str:
    return "-" if value != value else format(value, fmt)


def print_table(headers: list[str], rows: list[list[str]]) -> None:
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(headers)]
    print("  ".join(h.rjust(w) for h, w in zip(headers, widths, strict=True)))
    for row in rows:
        print("  ".join(c.rjust(w) for c, w in zip(row, widths, strict=True)))


def find(measured: dict[Job, Measured], **match) -> Measured | None:
    match.setdefault("balance_every", 0)
    for job, item in measured.items():
        if all(getattr(job, key) == value for key, value in match.items()):
            return item
    return None


def report(measured: dict[Job, Measured], quick: bool, lammps: bool) -> dict:
    figures: dict = {}
    print(
        "\n(a) Strong scaling: median M atom-steps/s (min-max); speed-up over the same "
        "engine's 1 x 1; ours/LAMMPS at the same ranks and threads"
    )
    for label, cells, _ in SIZES[quick]:
        rows = []
        base = {
            e: find(measured, engine=e, cells=cells, ranks=1, threads=1) for e in ("ours", "lammps")
        }
        for ranks, threads in LAYOUTS:
            ours = find(measured, engine="ours", cells=cells, ranks=ranks, threads=threads)
            peer = find(measured, engine="lammps", cells=cells, ranks=ranks, threads=threads)
            row = [
                f"{label}",
                f"{ranks} x {threads}",
                cell(ours.median() / 1e6),
                spread(ours),
                cell(ours.median() / base["ours"].median()),
            ]
            if lammps:
                row += [
                    cell(peer.median() / 1e6),
                    spread(peer),
                    cell(peer.median() / base["lammps"].median()),
                    cell(ours.median() / peer.median()),
                ]
            rows.append(row)
            figures[f"{label} {ranks}x{threads}"] = {
                "ours": ours.median(),
                "lammps": peer.median() if peer else None,
                "ours_comm": ours.comm_share(),
                "lammps_comm": peer.comm_share() if peer else None,
            }
        headers = ["atoms", "ranks x threads", "ours", "min-max", "speed-up"]
        if lammps:
            headers += ["LAMMPS", "min-max", "speed-up", "ours/LAMMPS"]
        print_table(headers, rows)
        two_ranks = find(measured, engine="ours", cells=cells, ranks=2, threads=1).median()
        two_threads = find(measured, engine="ours", cells=cells, ranks=1, threads=2).median()
        ratio = two_ranks / two_threads
        figures[f"{label} ranks/threads"] = ratio
        print(
            f"  ours, 2 ranks x 1 thread / 1 rank x 2 threads at {label} atoms: {ratio:.2f} "
            f"(target >= {TARGET_RANKS_OVER_THREADS} on the 2M melt)"
        )
        balanced = [
            item for job, item in measured.items() if job.balance_every and job.cells == cells
        ]
        if balanced:
            item = balanced[0]
            ratio = item.median() / two_threads
            figures[f"{label} balanced 2x1"] = {
                "ours": item.median(),
                "ours_comm": item.comm_share(),
                "ours_comm_min": item.comm_share("comm_share_min"),
                "over_1x2": ratio,
            }
            print(
                f"  ours balanced (every {item.job.balance_every} steps), 2 x 1: "
                f"{item.median() / 1e6:.2f} M atom-steps/s ({spread(item)}), comm "
                f"{100 * item.comm_share():.1f} % (least rank "
                f"{100 * item.comm_share('comm_share_min'):.1f} %), / 1 x 2: "
                f"{ratio:.2f}"
            )

    print(
        "\n(b) Seconds a step spends communicating at equal atoms per rank (median over "
        "repeats, mean over ranks; share of the loop beside it)"
    )
    rows = []
    for label, cells, _ in SIZES[quick]:
        for ranks, threads in LAYOUTS:
            if ranks == 1:
                continue  # (one rank: ours has no comm section, LAMMPS copies to itself)
            ours = find(measured, engine="ours", cells=cells, ranks=ranks, threads=threads)
            peer = find(measured, engine="lammps", cells=cells, ranks=ranks, threads=threads)
            row = [
                label,
                f"{ranks} x {threads}",
                f"{1e6 * comm_per_step(ours):.1f}",
                f"{1e6 * comm_per_step(ours, 'comm_share_min'):.1f}",
                f"{100 * ours.comm_share():.1f} %",
                build_count(ours),
                busy_spread(ours),
            ]
            if lammps:
                row += [
                    f"{1e6 * comm_per_step(peer):.1f}",
                    f"{1e6 * comm_per_step(peer, 'comm_share_min'):.1f}",
                    f"{100 * peer.comm_share():.1f} %",
                    build_count(peer),
                    busy_spread(peer),
                ]
            rows.append(row)
            figures[f"{label} {ranks}x{threads} comm seconds"] = {
                "ours": comm_per_step(ours),
                "lammps": comm_per_step(peer) if peer else None,
            }
    headers = ["atoms", "ranks x threads", "ours us/step", "least rank", "share", "builds"]
    headers += ["busy"]
    if lammps:
        headers += ["LAMMPS us/step", "least rank", "share", "builds", "busy"]
    print_table(headers, rows)
    for label, cells, _ in SIZES[quick]:
        peer = find(measured, engine="lammps", cells=cells, ranks=2, threads=1)
        if peer is None:
            continue
        runs = [("ours", find(measured, engine="ours", cells=cells, ranks=2, threads=1))]
        runs += [
            (f"ours balanced (every {job.balance_every})", item)
            for job, item in measured.items()
            if job.balance_every and job.cells == cells
        ]
        for name, item in runs:
            mine, theirs = comm_per_step(item), comm_per_step(peer)
            verdict = "met" if mine <= theirs else "not met"
            print(
                f"  target: {name} comm seconds a step at 2 x 1 on the {label} melt no more "
                f"than LAMMPS's: {1e6 * mine:.1f} us against {1e6 * theirs:.1f} us ({verdict})"
            )
            # the repeats go round-robin: run i of each engine is of the same round
            rounds = list(zip(item.runs, peer.runs, strict=False))
            lower = sum(run_comm(a) <= run_comm(b) for a, b in rounds)
            pairs = ", ".join(f"{1e6 * run_comm(a):.0f}/{1e6 * run_comm(b):.0f}" for a, b in rounds)
            print(
                f"    per round ({name}/LAMMPS, us): {pairs}; {name} no more in {lower} "
                f"of {len(rounds)}"
            )
    print(
        "  (builds: the neighbour-list builds in the timed loop, each with a migration and a "
        "ghost search; busy: the busiest rank's force and neighbour time over the least "
        "busy one's, the imbalance the other rank's comm section waits out. 'least rank': "
        "the seconds of the rank that communicated least, mostly its own messages, since "
        "the other waited for it: the mean holds the waits)"
    )

    print(
        f"\n(c) Weak scaling: {4 * WEAK_CELLS**3} atoms per rank; efficiency = rate per rank "
        "on 2 ranks / rate on 1"
    )
    rows = []
    one = (WEAK_CELLS,) * 3
    two = (2 * WEAK_CELLS, WEAK_CELLS, WEAK_CELLS)
    for engine in ("ours", "lammps") if lammps else ("ours",):
        single = find(measured, engine=engine, cells=one, ranks=1, threads=1)
        double = find(measured, engine=engine, cells=two, ranks=2, threads=1)
        efficiency = double.median() / 2 / single.median()
        figures[f"weak {engine}"] = efficiency
        rows.append(
            [
                engine,
                cell(single.median() / 1e6),
                cell(double.median() / 1e6),
                f"{efficiency:.2f}",
                f"{100 * double.comm_share():.1f} %",
            ]
        )
    print_table(["engine", "1 rank", "2 ranks", "efficiency", "comm at 2"], rows)
    return figures


def print_pingpong() -> dict | None:
    """(d) Latency and bandwidth of messages between two ranks of this machine."""
    try:
        found = launch(None, {"engine": "pingpong", "ranks": 2}, timeout=300)
    except (RuntimeError, subprocess.TimeoutExpired) as error:
        print(f"\n(d) ping-pong failed: {str(error)[:300]}")
        return None
    print(
        "\n(d) Messages between 2 ranks on this machine (mpi4py ping-pong, half the round "
        "trip, median)"
    )
    rows = []
    for size, seconds in zip(found["sizes"], found["seconds"], strict=True):
        rows.append([f"{size} B", f"{seconds * 1e6:.1f} us", f"{size / seconds / 1e9:.2f} GB/s"])
    print_table(["message", "time", "rate"], rows)
    print(f"  all-gather of 16 doubles over 2 ranks: {found['allgather_16'] * 1e6:.1f} us")
    try:
        pattern = launch(None, {"engine": "pattern", "ranks": 2}, timeout=300)
    except (RuntimeError, subprocess.TimeoutExpired) as error:
        print(f"  step's messages: failed: {str(error)[:300]}")
        return found
    found["pattern"] = pattern
    print(
        f"  a step's messages alone ({pattern['rows']} rows a ghost message, no work between): "
        f"before issue 69 (3 collectives, 4 Sendrecv) {pattern['before']['median'] * 1e6:.1f} "
        f"us a step (best block {pattern['before']['best'] * 1e6:.1f}), since (1 collective, "
        f"2 persistent rounds) {pattern['since']['median'] * 1e6:.1f} us (best "
        f"{pattern['since']['best'] * 1e6:.1f})"
    )
    return found


#: Inter-node messages: a typical InfiniBand (EDR/HDR) figure at the MPI level, assumed,
#: not measured here: latency [s] and bandwidth [bytes/s].
INFINIBAND = (1.5e-6, 10e9)
#: The LJ melt: number density, cutoff + skin (the ghost shell) [sigma].
DENSITY, SHELL = 0.8442, 2.8


def ghosts_per_atom(box, grid, images: bool = True) -> float:
    """Ghost atoms per owned atom of a brick of ``box / grid``, the ghost shell r = SHELL
    wide: ((Lx + 2r)(Ly + 2r)(Lz + 2r) - Lx Ly Lz) / (Lx Ly Lz) with ``images`` (LAMMPS:
    the periodic images along an uncut axis are ghosts too), else with a shell on the
    faces of the cut axes only (ours: an uncut axis stays periodic in the rank's list)."""
    edges = [b / p for b, p in zip(box, grid, strict=True)]
    shells = [2 * SHELL if images or p > 1 else 0.0 for p in grid]
    inner = edges[0] * edges[1] * edges[2]
    outer = math.prod(e + r for e, r in zip(edges, shells, strict=True))
    return (outer - inner) / inner


def melt_box(cells) -> list[float]:
    """The box of the LJ melt on ``cells`` fcc cells (4 atoms a cell at DENSITY)."""
    edge = (4 / DENSITY) ** (1 / 3)
    return [c * edge for c in cells]


def melt_grid(cells, ranks: int) -> tuple[int, ...]:
    """The bricks ``md.distributed.grid.choose_grid`` cuts the melt's box into for ``ranks``."""
    if str(HERE.parent) not in sys.path:  # (called for every term of the model)
        sys.path.insert(0, str(HERE.parent))
    from md.distributed import choose_grid

    if ranks == 1:
        return (1, 1, 1)
    return tuple(choose_grid(ranks, melt_box(cells), None, [True] * 3, SHELL))


#: The sections of each engine's step that are its own work (not messages or waits).
BUSY = {"ours": ("force", "neighbor", "integrate"), "lammps": ("Pair", "Neigh", "Modify")}


@dataclass
class StepModel:
    """One engine's time of a step on each of P ranks [s], for n = N / P atoms a brick
    with g ghosts per owned atom (:func:`ghosts_per_atom`; LAMMPS's count the periodic
    images of uncut axes):

        T_1 = c(N) N
        T_P = c(n) n (1 + h g) + 4 k alpha + 2 x 24 B x g n / beta + r log2(P) alpha
              + b gamma n (1 + g) + t

    c(n): the same engine's cost per atom-step on one rank and thread, measured on the
    melt nearest n atoms (1152, 32000 or 2M atoms: small ones run from the caches, and
    their fixed costs of a step are in it); h: a ghost's share of the rank's own work
    (pairs, list, integration) against an owned atom's, from the busy time of the
    32000-atom melt on 2 ranks (on a VM whose vCPUs slow each other down, that is in it
    too); k cut axes, each with 2 position and 2 force messages a step; r reductions a
    step (ours 1 since issue 69: the evaluation's, which carries the energy, virial and
    every agreement; LAMMPS 1: its neighbour check's, thermo rows aside); b builds a
    step, each with a migration and a ghost search of gamma per local atom (ours
    measured on 2 ranks; LAMMPS's are in its Comm, left to its other terms);
    t: what a decomposed step costs besides (the calls' own time, their bookkeeping, a
    step's waits), from the 1152-atom melt on 2 ranks less the other terms.
    """

    name: str
    images: bool
    per_atom: dict = field(default_factory=dict)  # atoms -> c
    ghost_cost: float = 0.0
    decomposed_fixed: float = 0.0
    rebuild: float = 0.0
    builds: float = 0.0
    reductions: float = 1.0

    def cost(self, n: float) -> float:
        """c at the measured size nearest n atoms (by ratio)."""
        nearest = min(self.per_atom, key=lambda size: abs(math.log(size / n)))
        return self.per_atom[nearest]

    def ghosts(self, cells, ranks: int) -> tuple[float, tuple]:
        grid = melt_grid(cells, ranks)
        return ghosts_per_atom(melt_box(cells), grid, self.images), grid

    def step(
        self, cells, ranks: int, latency: float, bandwidth: float, fixed: bool = True
    ) -> float:
        """T_P for the melt on ``cells`` (without t if not ``fixed``)."""
        n_atoms = 4 * math.prod(cells)
        if ranks == 1:
            return self.cost(n_atoms) * n_atoms
        ghosts, grid = self.ghosts(cells, ranks)
        n = n_atoms / ranks
        cut = sum(p > 1 for p in grid)
        work = self.cost(n) * n * (1 + self.ghost_cost * ghosts)
        messages = 4 * cut * latency + 2 * 24 * ghosts * n / bandwidth
        reductions = self.reductions * math.log2(ranks) * latency
        rebuilds = self.builds * self.rebuild * n * (1 + ghosts)
        return work + messages + reductions + rebuilds + (self.decomposed_fixed if fixed else 0.0)

    def efficiency(self, cells, ranks: int, latency: float, bandwidth: float) -> float:
        """T_1 over P T_P."""
        one = self.step(cells, 1, latency, bandwidth)
        return one / (ranks * self.step(cells, ranks, latency, bandwidth))


def step_seconds(item: Measured) -> float:
    """The median time of a step of ``item``'s loop [s]."""
    return item.job.n_atoms / item.median()


def busy_seconds(item: Measured) -> float:
    """The median over the repeats of a rank's own work a step (:data:`BUSY`'s sections,
    mean over the ranks) [s]."""
    keys = BUSY[item.job.engine]
    return statistics.median(
        sum(r["sections"].get(k, 0.0) for k in keys) / r["n_steps"] for r in item.runs
    )


def calibrate(
    engine: str, measured: dict[Job, Measured], quick: bool, here: tuple[float, float]
) -> StepModel | None:
    """:class:`StepModel` of ``engine`` from its runs here (None if some are missing)."""
    middle, large = SIZES[quick][0][1], SIZES[quick][-1][1]
    ones = [
        find(measured, engine=engine, cells=c, ranks=1, threads=1)
        for c in (TINY_CELLS, middle, large)
    ]
    tiny = find(measured, engine=engine, cells=TINY_CELLS, ranks=2, threads=1)
    two = find(measured, engine=engine, cells=middle, ranks=2, threads=1)
    big = find(measured, engine=engine, cells=large, ranks=2, threads=1)
    if any(item is None or not item.runs for item in [*ones, tiny, two, big]):
        return None
    model = StepModel(engine, images=engine != "ours")
    model.per_atom = {item.job.n_atoms: 1.0 / item.median() for item in ones}
    ghosts, _ = model.ghosts(middle, 2)
    owned = two.job.n_atoms / 2 * model.cost(two.job.n_atoms / 2)
    # (h and t cannot be negative: a negative fit is the noise of the medians, taken as 0)
    model.ghost_cost = max((busy_seconds(two) / owned - 1) / ghosts, 0.0)
    if engine == "ours":
        model.builds = statistics.median(r["n_builds"] / r["n_steps"] for r in big.runs)
        model.rebuild = statistics.median(
            r["sections"]["rebuild_comm"]
            / max(r["n_builds"], 1)
            / (sum(sum(x) for x in r["local_atoms"]) / len(r["local_atoms"]))
            for r in big.runs
        )
    model.decomposed_fixed = max(
        step_seconds(tiny) - model.step(TINY_CELLS, 2, *here, fixed=False), 0.0
    )
    return model


def own_seconds(item: Measured) -> float:
    """The median over the repeats of a rank's own CPU time a step (``own_cpu``: thread
    time outside its MPI calls, mean over the ranks) [s]."""
    return statistics.median(r.get("own_cpu", float("nan")) / r["n_steps"] for r in item.runs)


def print_fixed(measured: dict[Job, Measured], lammps: bool) -> dict:
    """(e) The fixed cost of a decomposed step: the tiny melt's time a step on P ranks less
    1/P of its time on one rank (median over the repeats of each), ours and LAMMPS's."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    print(
        f"\n(e) Fixed cost of a decomposed step: the {4 * math.prod(TINY_CELLS)}-atom melt's "
        "loop time a step on P ranks (1 thread each) less 1/P of its time on one rank, "
        f"median over repeats; {cores} cores here, so P > {cores} is oversubscribed (its "
        "figure holds the ranks' contention for the cores)"
    )
    figures: dict = {}
    rows = []
    engines = ("ours", "lammps") if lammps else ("ours",)
    one = {e: find(measured, engine=e, cells=TINY_CELLS, ranks=1, threads=1) for e in engines}
    for ranks in TINY_RANKS:
        row = [str(ranks), "yes" if ranks > (cores or 1) else "no"]
        for engine in engines:
            item = find(measured, engine=engine, cells=TINY_CELLS, ranks=ranks, threads=1)
            if item is None or not item.runs or one[engine] is None:
                row += ["-", "-"]
                continue
            step = step_seconds(item)
            fixed = step - step_seconds(one[engine]) / ranks
            figures[f"{engine} {ranks}"] = {"step": step, "fixed": fixed}
            row += [f"{step * 1e6:.1f}", f"{fixed * 1e6:.1f}" if ranks > 1 else "-"]
            if engine == "ours":
                own = own_seconds(item)
                own_fixed = own - own_seconds(one[engine]) / ranks
                figures[f"{engine} {ranks}"].update(own=own, own_fixed=own_fixed)
                row += [f"{own * 1e6:.1f}", f"{own_fixed * 1e6:.1f}" if ranks > 1 else "-"]
        rows.append(row)
    headers = ["ranks", "oversubscribed"]
    for engine in engines:
        headers += [f"{engine} us/step", "fixed us"]
        if engine == "ours":
            headers += ["own CPU us", "own fixed"]
    print_table(headers, rows)
    print(
        "  (own CPU: a rank's thread CPU time a step outside its MPI calls, mean over the "
        "ranks, less 1/P of one rank's for its fixed part: the work of a decomposed step "
        "without the waits a shared machine's other jobs add to the wall clock)"
    )
    ours = figures.get("ours 2")
    if ours is not None:
        verdict = "met" if ours["fixed"] <= TARGET_FIXED else "not met"
        print(
            f"  target: ours fixed cost at 2 ranks <= {TARGET_FIXED * 1e6:.0f} us: "
            f"{ours['fixed'] * 1e6:.1f} us ({verdict})"
        )
    return figures


def print_model(measured: dict[Job, Measured], quick: bool, pingpong: dict | None) -> dict:
    """(e) The model of each engine's efficiency at 64 and 1024 ranks for the larger melt
    (:class:`StepModel`, from its runs here), with this machine's messages and with
    InfiniBand's; checked against the runs it was not fitted to."""
    if not pingpong:
        return {}
    # Latency of the smallest message; bandwidth at 1 MB, the size of a halo message of a
    # brick of about a million atoms.
    megabyte = pingpong["sizes"].index(1 << 20)
    here = (pingpong["seconds"][0], pingpong["sizes"][megabyte] / pingpong["seconds"][megabyte])
    models = [m for m in (calibrate(e, measured, quick, here) for e in ("ours", "lammps")) if m]
    if not models:
        return {}
    cells = SIZES[quick][-1][1]
    n_atoms = 4 * math.prod(cells)
    print(
        f"\n(f) Model of the parallel efficiency at {n_atoms} atoms from each engine's runs "
        "here (see benchmarks/README.md)"
    )
    print(
        "  T_1 = c(N) N;  T_P = c(n) n (1 + h g) + 4 k alpha + 48 B g n / beta "
        "+ r log2(P) alpha + b gamma n (1 + g) + t"
    )
    print(
        f"  messages: here {here[0] * 1e6:.1f} us + {here[1] / 1e9:.1f} GB/s (measured); "
        f"between nodes {INFINIBAND[0] * 1e6:.1f} us + {INFINIBAND[1] / 1e9:.0f} GB/s "
        "(typical InfiniBand, assumed)"
    )
    figures: dict = {}
    weak = (2 * WEAK_CELLS, WEAK_CELLS, WEAK_CELLS)
    for model in models:
        costs = ", ".join(f"{c * 1e9:.0f} ns at {n}" for n, c in sorted(model.per_atom.items()))
        print(
            f"  {model.name}: c {costs} atoms; h = {model.ghost_cost:.2f}, t = "
            f"{model.decomposed_fixed * 1e6:.0f} us, b = {model.builds:.2f}, gamma = "
            f"{model.rebuild * 1e9:.0f} ns, r = {model.reductions:g}"
        )
        parameters = vars(model).copy()
        parameters["per_atom"] = {str(k): v for k, v in model.per_atom.items()}
        figures[f"{model.name} parameters"] = parameters
        checks = []
        for label, check_cells in ((f"{n_atoms} atoms", cells), ("weak", weak)):
            item = find(measured, engine=model.name, cells=check_cells, ranks=2, threads=1)
            if item is None or not item.runs:
                continue
            predicted, actual = model.step(check_cells, 2, *here), step_seconds(item)
            figures[f"{model.name} check {label}"] = [predicted, actual]
            checks.append(
                f"{item.job.n_atoms} atoms on 2 ranks {predicted * 1e3:.2f} ms a "
                f"step, measured {actual * 1e3:.2f}"
            )
        print(f"    checks (not fitted): {'; '.join(checks)}")
    rows = []
    for ranks in (2, 64, 1024):
        grid = melt_grid(cells, ranks)
        row = [str(ranks), " x ".join(map(str, grid)), f"{n_atoms // ranks}"]
        for model in models:
            row.append(f"{model.ghosts(cells, ranks)[0]:.2f}")
            for name, (latency, bandwidth) in (("here", here), ("infiniband", INFINIBAND)):
                value = model.efficiency(cells, ranks, latency, bandwidth)
                figures[f"{model.name} {ranks} {name}"] = value
                row.append(f"{value:.2f}")
            one = find(measured, engine=model.name, cells=cells, ranks=1, threads=1)
            two = find(measured, engine=model.name, cells=cells, ranks=2, threads=1)
            row.append(f"{two.median() / 2 / one.median():.2f}" if ranks == 2 else "-")
        rows.append(row)
    headers = ["ranks", "grid", "atoms/rank"]
    for model in models:
        headers += [f"{model.name} g", "E here", "E InfiniBand", "E measured"]
    print_table(headers, rows)
    print(
        "  (g: ghosts per owned atom, LAMMPS's with the periodic images of uncut axes; "
        "E: T_1 / (P T_P), measured: the 2-rank rate over twice the 1-rank rate; load "
        "balance perfect but for the waits in t)"
    )
    return figures


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--quick",
        action="store_true",
        help="32000 and 256000 atoms, few steps, 1 repeat (a smoke run)",
    )
    parser.add_argument("--repeats", type=int, default=None, help="repeats (3; --quick 1)")
    parser.add_argument("--no-lammps", action="store_true", help="our engine only")
    parser.add_argument("--timeout", type=float, default=600, help="seconds per launch (600)")
    parser.add_argument("--json", help="write the medians to this file")
    parser.add_argument(
        "--bind",
        action="store_true",
        help="each rank on cores of its own, one per thread (mpiexec -bind-to core:T)",
    )
    parser.add_argument(
        "--lammps-velocities",
        choices=("gaussian", "uniform"),
        default="gaussian",
        help="LAMMPS's initial velocities: gaussian (default; ours are "
        "Maxwell-Boltzmann) or uniform (its bench/in.lj)",
    )
    parser.add_argument(
        "--fixed-only",
        action="store_true",
        help="only the 1152-atom melt on 1-4 ranks and table (e), the fixed cost",
    )
    parser.add_argument(
        "--balance-every",
        type=int,
        default=0,
        metavar="N",
        help="also ours on 2 ranks with load balancing every N steps",
    )
    args = parser.parse_args(argv)
    repeats = args.repeats or (1 if args.quick else 3)
    print(machine_line())
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    print(f"load average before the runs: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    lammps = False
    if not args.no_lammps:
        lammps, note = probe_lammps()
        print(note)
    jobs = jobs_for(args.quick, lammps, args.balance_every)
    if args.fixed_only:
        jobs = [job for job in jobs if job.cells == TINY_CELLS]
    bound = ", every rank bound to cores of its own (mpiexec -bind-to core:T)" if args.bind else ""
    print(f"{len(jobs)} runs x {repeats} repeats, interleaved{bound}:")
    if lammps:
        print(f"LAMMPS draws {args.lammps_velocities} initial velocities (ours: Gaussian)")
    measured = measure(jobs, repeats, args.timeout, args.bind, args.lammps_velocities)
    if args.fixed_only:
        figures = {"fixed": print_fixed(measured, lammps)}
        if args.json:
            figures["runs"] = [
                {"job": vars(job), "runs": item.runs} for job, item in measured.items()
            ]
            Path(args.json).write_text(json.dumps(figures, indent=2))
        return 0
    figures = report(measured, args.quick, lammps)
    pingpong = print_pingpong()
    figures["fixed"] = print_fixed(measured, lammps)
    if pingpong:
        figures["pingpong"] = pingpong
        figures["model"] = print_model(measured, args.quick, pingpong)
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    print(f"\nload average after the runs: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    if args.json:
        figures["runs"] = [{"job": vars(job), "runs": item.runs} for job, item in measured.items()]
        Path(args.json).write_text(json.dumps(figures, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
