"""What keeping freed memory (``md._memory.keep_freed_memory``) buys a step, from Python.

``md run`` sets glibc's malloc to keep freed memory; ``import md`` does not.
This measures whether a Python user's ``Simulation.run`` would gain from it:
the LJ melt (fcc 0.8442, T 3.0, cutoff 2.5) stepped by implicit Euler (its
Newton solves allocate and free arrays of 3N doubles every step) or by
velocity Verlet, each repeat in a fresh process (the setting cannot be
undone within one), glibc's defaults and kept memory interleaved. Printed:
the median over repeats of each process's median step time, and minor page
faults per step.

Run from the repository root::

    python benchmarks/freed_memory.py                        # 32000 atoms, implicit Euler
    python benchmarks/freed_memory.py --integrator verlet --repeats 3
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys

from _machine import machine_line

_CHILD = """
import json, resource, sys, time
import md
from md._memory import keep_freed_memory
from integrators import VelocityVerlet
from integrators.implicit_euler import ImplicitEuler
from potentials import LennardJones

mode, cells, integrator, steps, threads = sys.argv[1:6]
kept = keep_freed_memory() if mode == "kept" else False
state = md.lattice("fcc", int(cells), density=0.8442)
md.maxwell_boltzmann(state, temperature=3.0, seed=87287)
step = ImplicitEuler(0.005) if integrator == "implicit_euler" else VelocityVerlet(0.005)
sim = md.Simulation(state, [LennardJones(cutoff=2.5)], step, threads=int(threads))
sim.run(2)  # kernels loaded, first list and forces out of the figures
times, faults = [], []
for _ in range(int(steps)):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    start = time.perf_counter()
    sim.run(1)
    times.append(time.perf_counter() - start)
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
times.sort()
faults.sort()
print(json.dumps({"kept": kept, "step": times[len(times) // 2],
                  "faults": faults[len(faults) // 2]}))
"""


def measure(mode: str, args) -> dict:
    environment = {**os.environ, "LEAPMD_KEEP_FREED_MEMORY": "1"}
    out = subprocess.run(
        [
            sys.executable,
            "-c",
            _CHILD,
            mode,
            str(args.cells),
            args.integrator,
            str(args.steps),
            str(args.threads),
        ],
        capture_output=True,
        text=True,
        check=True,
        env=environment,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=20, help="fcc cells per edge (20: 32000)")
    parser.add_argument(
        "--integrator", choices=("implicit_euler", "verlet"), default="implicit_euler"
    )
    parser.add_argument("--steps", type=int, default=15, help="timed steps per process")
    parser.add_argument("--repeats", type=int, default=5, help="processes per setting")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    print(machine_line())
    print(
        f"{4 * args.cells**3} atoms, {args.integrator}, {args.threads} thread(s), "
        f"{args.steps} steps x {args.repeats} processes per setting"
    )
    results: dict[str, list[dict]] = {"default": [], "kept": []}
    for _ in range(args.repeats):
        for mode in results:  # interleaved, so load on the machine hits both alike
            results[mode].append(measure(mode, args))
    for mode, runs in results.items():
        steps = [1e3 * r["step"] for r in runs]
        faults = [r["faults"] for r in runs]
        print(
            f"{mode:>8}: step {statistics.median(steps):6.1f} ms "
            f"(processes {' '.join(f'{s:.1f}' for s in steps)}), "
            f"page faults per step {statistics.median(faults):.0f}"
        )
    ratio = [
        d["step"] / k["step"] for d, k in zip(results["default"], results["kept"], strict=True)
    ]
    print(
        f"default / kept, per repeat pair: {' '.join(f'{r:.2f}' for r in ratio)} "
        f"(median {statistics.median(ratio):.2f})"
    )


if __name__ == "__main__":
    main()
