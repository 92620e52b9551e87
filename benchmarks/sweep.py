"""Throughput of ``md sweep`` on a local Dask cluster of 1 and 2 workers (runs per minute).

The sweep: 16 small runs, 4 temperatures x 4 replicas of an LJ liquid (fcc
start at density 0.8442, ``--cells`` per edge, 4 atoms per cell), velocity
Verlet with dt = 0.005 for ``--steps`` steps, a frame every 100 steps. Run
from the repository root::

    python benchmarks/sweep.py                       # 16 runs of 500 atoms x 1000 steps, 3 repeats
    python benchmarks/sweep.py --cells 3 --steps 200 --repeats 1

Each repeat times, in the same order, three ways of doing the same 16 runs:

* ``serial``: ``md run --threads 1`` of each run's config one after another
  in child processes, with no Dask at all (the baseline a shell loop gives);
* ``dask, 1 worker`` and ``dask, 2 workers``: ``md.sweeps.run_sweep`` on a
  ``LocalCluster`` of that many single-threaded worker processes (the
  cluster is started before the clock starts and closed after it stops).

The time runs from submitting the first run to the collated table (each
run's summary included), into a fresh output folder. A warm-up run first
keeps numba compilation out. Reported: the median over repeats of the
runs per minute, and the ratios 2 workers / 1 worker (scaling) and
1 worker / serial (Dask's overhead). The machine's core count bounds the
scaling; other work on the machine lowers it.
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _machine import machine_line

from md import sweeps as sw

CONFIG = """\
units = "lj"
seed = 2024

[system]
lattice = "fcc"
cells = {cells}
density = 0.8442
temperature = 1.0

[[potentials]]
type = "lj"
cutoff = 2.5
cutoff_mode = "shift"

[integrator]
type = "verlet"
dt = 0.005

[run]
steps = {steps}
thermo_every = {steps}

[output]
path = "unused.h5"
every = 100
"""
VARY = {"system.temperature": [0.8, 1.0, 1.2, 1.4]}
REPLICAS = 4


def time_serial(plan: sw.SweepPlan, folder: Path) -> float:
    """Seconds to run every config of ``plan`` one after another with ``md run``."""
    folder.mkdir()
    configs = []
    for run in plan.runs:
        path = folder / f"{run.label}.toml"
        path.write_text(run.config_text)
        configs.append((path, folder / f"{run.label}.h5"))
    start = time.perf_counter()
    for config, output in configs:
        subprocess.run(
            [
                sys.executable,
                "-m",
                "md.cli",
                "run",
                str(config),
                "--output",
                str(output),
                "--threads",
                "1",
                "--no-progress",
                "--quiet",
            ],
            check=True,
            stdout=subprocess.DEVNULL,
        )
    return time.perf_counter() - start


def time_dask(config: Path, out: Path, workers: int) -> float:
    """Seconds for ``run_sweep`` of the benchmark sweep on a fresh local cluster."""
    from distributed import Client, LocalCluster

    plan = sw.plan_sweep(config, VARY, REPLICAS, out=out)
    cluster = LocalCluster(
        n_workers=workers,
        threads_per_worker=1,
        processes=True,
        dashboard_address=":0",
        silence_logs=logging.ERROR,
    )
    try:
        with Client(cluster) as client:
            client.wait_for_workers(workers)
            start = time.perf_counter()
            table = sw.run_sweep(plan, client)
            elapsed = time.perf_counter() - start
    finally:
        cluster.close()
    failed = [row["label"] for row in table if row["status"] != "done"]
    if failed:
        raise RuntimeError(f"runs failed: {', '.join(failed)}")
    return elapsed


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=5, help="fcc cells per edge (default 5)")
    parser.add_argument("--steps", type=int, default=1000, help="steps per run (default 1000)")
    parser.add_argument("--repeats", type=int, default=3, help="repeats (default 3)")
    parser.add_argument(
        "--workers", default="1,2", help="local cluster sizes to time (default 1,2)"
    )
    args = parser.parse_args(argv)
    sizes = [int(w) for w in args.workers.split(",")]
    n_runs = len(VARY["system.temperature"]) * REPLICAS
    n_atoms = 4 * args.cells**3
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    print(machine_line())
    print(
        f"md sweep throughput: {n_runs} runs of {n_atoms} atoms x {args.steps} steps "
        f"(LJ, velocity Verlet), {args.repeats} repeat(s), {cores} core(s) available; "
        "every run on 1 thread in every row (serial loop and Dask workers alike)"
    )
    work = Path(tempfile.mkdtemp(prefix="md-sweep-bench-"))
    try:
        config = work / "bench.toml"
        config.write_text(CONFIG.format(cells=args.cells, steps=args.steps))
        warm = sw.plan_sweep(config, {}, 1, out=work / "warm")
        time_serial(sw.SweepPlan(warm.config, [], {}, 1, warm.out, warm.runs[:1]), work / "warm")
        times: dict[str, list[float]] = {"serial": []}
        times.update({f"dask, {w} worker(s)": [] for w in sizes})
        for repeat in range(args.repeats):
            plan = sw.plan_sweep(config, VARY, REPLICAS, out=work / f"unused-{repeat}")
            times["serial"].append(time_serial(plan, work / f"serial-{repeat}"))
            for w in sizes:
                elapsed = time_dask(config, work / f"dask-{w}-{repeat}", w)
                times[f"dask, {w} worker(s)"].append(elapsed)
            line = ", ".join(f"{name} {values[-1]:.1f} s" for name, values in times.items())
            print(f"  repeat {repeat + 1}: {line}", flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(f"{'':<22}{'median s':>10}{'runs/min':>10}{'s/run':>8}")
    rates = {}
    for name, values in times.items():
        median = statistics.median(values)
        rates[name] = 60.0 * n_runs / median
        print(f"{name:<22}{median:>10.2f}{rates[name]:>10.1f}{median / n_runs:>8.2f}")
    one = rates.get("dask, 1 worker(s)")
    for w in sizes:
        if w != 1 and one:
            print(f"scaling {w} workers / 1 worker: {rates[f'dask, {w} worker(s)'] / one:.2f}x")
    if one:
        print(f"dask 1 worker / serial md run loop: {one / rates['serial']:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
