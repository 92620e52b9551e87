"""More ranks than cores (issue 69): the 1152-atom melt's step on P ranks with the MPI
library polling while a rank waits (MPICH's default) and yielding the core
(``MPIR_CVAR_ENABLE_HEAVY_YIELD=1``, what the ``md`` command sets for itself when a
launcher started more ranks on the node than there are cores:
``md.distributed.ranks.yield_when_oversubscribed``), ours and LAMMPS's alike (the same
MPICH library, the wheel's), every run a fresh ``mpiexec`` launch of ``_mpi_worker.py``.

    python benchmarks/mpi_oversubscribed.py                    # 3 and 4 ranks, 3 repeats
    python benchmarks/mpi_oversubscribed.py --ranks 2 3 --repeats 5

Repeats go round-robin over all runs (interleaved); prints the CPU model and vector ISA,
the median us a step of each, each engine's yield / poll ratio and ours / LAMMPS's.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from _machine import machine_line  # noqa: E402
from mpi_scaling import TINY_CELLS, TINY_STEPS, launch, probe_lammps  # noqa: E402

from md.distributed.ranks import YIELD_VARIABLES  # noqa: E402

WAITS = ("poll", "yield")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ranks", type=int, nargs="+", default=[3, 4], help="ranks (3 4)")
    parser.add_argument("--repeats", type=int, default=3, help="repeats (3)")
    parser.add_argument("--steps", type=int, default=TINY_STEPS[False], help="steps a run")
    parser.add_argument("--no-lammps", action="store_true", help="ours only")
    parser.add_argument("--timeout", type=float, default=600, help="seconds per launch")
    args = parser.parse_args(argv)
    print(machine_line())
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    print(f"{cores} cores; load average before the runs: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    engines = ["ours"]
    if not args.no_lammps:
        found, note = probe_lammps()
        print(note)
        engines += ["lammps"] if found else []
    saved = {name: os.environ.get(name) for name in YIELD_VARIABLES}
    steps: dict[tuple, list[float]] = {}
    try:
        for repeat in range(args.repeats):
            for ranks in args.ranks:
                for wait in WAITS:
                    for name, value in YIELD_VARIABLES.items():
                        if wait == "yield":
                            os.environ[name] = value
                        else:
                            os.environ.pop(name, None)
                    for engine in engines:
                        payload = {
                            "engine": engine,
                            "cells": list(TINY_CELLS),
                            "steps": args.steps,
                            "threads": 1,
                            "ranks": ranks,
                        }
                        result = launch(None, payload, args.timeout)
                        step = result["loop_time"] / result["n_steps"]
                        steps.setdefault((engine, ranks, wait), []).append(step)
                        print(
                            f"  [{repeat + 1}/{args.repeats}] {engine:<6} {ranks} ranks, "
                            f"{wait:<5}: {step * 1e6:9.1f} us a step",
                            flush=True,
                        )
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    print(f"load average after the runs: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    print(
        f"\nmedian us a step of the {4 * TINY_CELLS[0] * TINY_CELLS[1] * TINY_CELLS[2]}-atom melt"
    )
    header = "ranks  " + "  ".join(f"{e} {w:<5}" for e in engines for w in WAITS)
    print(header + "  " + "  ".join(f"{e} yield/poll" for e in engines) + "  ours/lammps yield")
    for ranks in args.ranks:
        median = {(e, w): statistics.median(steps[(e, ranks, w)]) for e in engines for w in WAITS}
        row = f"{ranks:>5}  " + "  ".join(
            f"{median[(e, w)] * 1e6:>{len(e) + 6}.1f}" for e in engines for w in WAITS
        )
        row += "  " + "  ".join(
            f"{median[(e, 'yield')] / median[(e, 'poll')]:>{len(e) + 11}.2f}" for e in engines
        )
        if "lammps" in engines:
            row += f"  {median[('ours', 'yield')] / median[('lammps', 'yield')]:>17.2f}"
        print(row)
    return 0


if __name__ == "__main__":
    sys.exit(main())
