"""Cost of pressure control: a step of NVT, c_rescale NPT and MTK NPT on an LJ liquid.

The liquid (fcc start at rho* 0.7, T* 1.5, P* 2, LJ shifted at 2.5 sigma,
skin 0.3, dt 0.005) runs under Nose-Hoover chains alone, under Langevin with
stochastic cell rescaling every 10 steps, and under the MTK barostat (its
cell moves every step; the neighbour list follows the cell while it covers
it). Prints the median wall time per step over repeats, the time split and
the neighbour-list builds, and each barostat's cost relative to NVT.

    python3 benchmarks/npt.py [--cells 10] [--steps 300] [--repeats 3] [--threads 1]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

from _machine import machine_line

import md
from integrators import Langevin, NoseHooverChain
from integrators.barostats import Barostat, pressure_control
from potentials import LennardJones

TEMPERATURE, PRESSURE, DT = 1.5, 2.0, 0.005


def make_integrator(kind: str):
    if kind == "nvt":
        return NoseHooverChain(DT, temperature=TEMPERATURE, tau=0.5)
    if kind == "mtk":
        return pressure_control(
            NoseHooverChain(DT, temperature=TEMPERATURE, tau=0.5),
            Barostat("mtk", PRESSURE, tau=1.0),
        )
    return pressure_control(
        Langevin(DT, temperature=TEMPERATURE, friction=1.0, seed=2),
        Barostat("c_rescale", PRESSURE, tau=0.5, compressibility=0.1, every=10, seed=3),
    )


def time_run(kind: str, cells: int, steps: int, threads: int) -> dict:
    state = md.maxwell_boltzmann(md.lattice("fcc", cells, density=0.7), TEMPERATURE, seed=1)
    sim = md.Simulation(
        state, [LennardJones(cutoff=2.5)], make_integrator(kind), skin=0.3, threads=threads
    )
    sim.run(50)  # compilation, first list, the melt's first steps
    builds = sim.forcefield.neighbor_list.n_builds
    before = sim.timing_summary()
    start = time.perf_counter()
    sim.run(steps)
    wall = time.perf_counter() - start
    after = sim.timing_summary()
    return {
        "ms_per_step": 1e3 * wall / steps,
        "split": {k: 1e3 * (after[k] - before[k]) / steps for k in ("force", "neighbor")},
        "builds": sim.forcefield.neighbor_list.n_builds - builds,
        "n_atoms": state.n_atoms,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=10, help="fcc cells per edge (10: 4000)")
    parser.add_argument("--steps", type=int, default=300, help="timed steps per repeat")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    print(machine_line() + f"; threads {args.threads}")
    kinds = ("nvt", "c_rescale", "mtk")
    runs = {kind: [] for kind in kinds}
    for _ in range(args.repeats):  # interleaved, so a noisy moment hits every kind
        for kind in kinds:
            runs[kind].append(time_run(kind, args.cells, args.steps, args.threads))
    n_atoms = runs["nvt"][0]["n_atoms"]
    print(
        f"LJ liquid, {n_atoms} atoms, T* {TEMPERATURE}, P* {PRESSURE}, {args.steps} steps, "
        f"median of {args.repeats}"
    )
    print(f"{'run':<10}{'ms/step':>9}{'force':>8}{'neigh':>8}{'builds':>8}{'vs NVT':>8}")
    nvt = statistics.median(r["ms_per_step"] for r in runs["nvt"])
    for kind in kinds:
        median = sorted(runs[kind], key=lambda r: r["ms_per_step"])[len(runs[kind]) // 2]
        split = median["split"]
        print(
            f"{kind:<10}{median['ms_per_step']:>9.3f}{split['force']:>8.3f}"
            f"{split['neighbor']:>8.3f}{median['builds']:>8d}"
            f"{median['ms_per_step'] / nvt:>8.2f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
