"""RESPA against velocity Verlet at the inner step, on a polymer melt with stiff bonds.

A melt of bead-spring chains (Lennard-Jones with cutoff 2.5 between all beads,
the slow and costly force; stiff harmonic bonds k = 2000 (--k), r0 = 0.97, the
fast and cheap one; bond period 2 pi sqrt(mu / k) = 0.099 tau), relaxed by
FIRE first and run at T ~ 1 in NVE. For velocity Verlet at steps h and RESPA
at outer steps dt = n h with n bond substeps, it prints the energy error
(max |E(t) - E(0)| per atom over the run), the wall time, and the speed-up of
each RESPA run over the velocity Verlet run at its inner step, whose bonds it
resolves equally: at equal energy error when the slow forces' error stays
below the bonds'. The outer step is kept below a third of the bond period
(the resonance limit is near half of it; see integrators/respa.py).

    python3 benchmarks/respa.py [--chains 50] [--time 2]
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
from _machine import machine_line

import md
from integrators import RESPA, VelocityVerlet
from md.minimize import minimize
from md.polymers import polymer_melt
from potentials import HarmonicBonds, LennardJones


def melt(chains: int, k_bond: float):
    state, bonds = polymer_melt(chains, 20, density=0.85, bond_length=0.97, seed=4)
    potentials = [LennardJones(cutoff=2.5), HarmonicBonds(bonds, k=k_bond, r0=0.97)]
    minimize(state, md.ForceField(potentials), fmax=1.0, max_steps=5000, max_force=100.0)
    md.maxwell_boltzmann(state, 1.0, seed=5)
    return state, potentials


def measure(integrator, start, potentials, span):
    state = start.copy()
    sim = md.Simulation(state, potentials, integrator, skin=0.3, threads=1)
    energies = []
    sim.attach(lambda s: energies.append(s.thermo()["total_energy"]), 25)
    n_steps = round(span / integrator.dt)
    begin = time.perf_counter()
    sim.run(n_steps)
    wall = time.perf_counter() - begin
    e = np.array(energies)
    return float(np.abs(e - e[0]).max() / state.n_atoms), wall


def equal_error_wall(baseline: dict, error: float) -> float:
    """Velocity Verlet's wall time at energy error ``error``, on the log-log line of its runs.

    The line through the measured (error, wall) points of velocity Verlet
    (error ~ h^2, wall ~ 1/h, so wall ~ error^(-1/2) in theory) is followed,
    extrapolating where needed.
    """
    points = sorted(baseline.values())
    (e1, w1), (e2, w2) = points[0], points[-1]
    slope = np.log(w2 / w1) / np.log(e2 / e1)
    return float(w1 * (error / e1) ** slope)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--chains", type=int, default=50)
    parser.add_argument("--time", type=float, default=2.0)
    parser.add_argument("--k", type=float, default=2000.0, help="bond spring constant")
    parser.add_argument("--steps", default="0.001,0.002", help="velocity Verlet steps h")
    args = parser.parse_args(argv)
    print(machine_line() + "; threads 1")
    start, potentials = melt(args.chains, args.k)
    period = 2 * np.pi * np.sqrt(0.5 / args.k)
    print(f"polymer melt: {start.n_atoms} beads, bond period {period:.4f} tau, run {args.time} tau")
    print(
        f"{'integrator':<28}{'max|dE|/N':>12}{'wall s':>9}{'vs VV(h)':>10}"
        f"{'vs VV at equal error':>22}"
    )
    baseline = {}
    steps = [float(h) for h in args.steps.split(",")]
    for h in steps:
        error, wall = measure(VelocityVerlet(h), start, potentials, args.time)
        baseline[h] = (error, wall)
        print(f"{'verlet dt=' + str(h):<28}{error:>12.3e}{wall:>9.2f}")
    for h in steps:
        for n in (2, 4, 8):
            dt = n * h
            if dt > period / 3:
                continue
            error, wall = measure(RESPA(dt, inner_steps=n), start, potentials, args.time)
            ref_error, ref_wall = baseline[h]
            label = f"respa dt={dt:g} n={n} (h={h})"
            print(
                f"{label:<28}{error:>12.3e}{wall:>9.2f}{ref_wall / wall:>9.2f}x"
                f"{equal_error_wall(baseline, error) / wall:>21.2f}x",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
