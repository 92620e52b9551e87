"""An LJ liquid at T = 1.0, rho = 0.8, then ``md analyze`` on its trajectory.

    python3 examples/lj_liquid_analysis.py [--out DIR] [--overwrite]

500 atoms start on an fcc lattice at density 0.8, melt at T = 2 and are
brought to T = 1.0 by rescaling the velocities every 50 steps for 10 tau;
then 50 tau of plain NVE dynamics (velocity Verlet, dt = 0.005, LJ cut at
2.5 sigma and shifted) are written to ``lj_liquid.h5`` every 10 steps with
velocities, and ``md analyze --all`` turns the file into plots, CSV files and
``summary.json`` in ``lj_liquid_analysis/``. Under a minute in all, about
half of it the g(r) over the 1001 frames.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

import md
from integrators import VelocityVerlet
from md.cli import main as md_main
from md.thermo import temperature
from md.trajectory import H5MDWriter
from potentials import LennardJones

TARGET_T = 1.0
DENSITY = 0.8


def equilibrate(sim: md.Simulation, n_cycles: int = 40, interval: int = 50) -> None:
    """Rescale velocities to TARGET_T every ``interval`` steps (isokinetic equilibration)."""
    state = sim.state
    for _ in range(n_cycles):
        sim.run(interval)
        state.velocities *= np.sqrt(TARGET_T / temperature(state.velocities, state.masses))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trajectory", type=Path, default=Path("lj_liquid.h5"))
    parser.add_argument("--out", type=Path, default=Path("lj_liquid_analysis"))
    parser.add_argument("--steps", type=int, default=10_000, help="production steps")
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args(argv)
    if args.trajectory.exists() and not args.overwrite:
        print(f"{args.trajectory} exists; pass --overwrite", file=sys.stderr)
        return 2

    state = md.lattice("fcc", 5, density=DENSITY)
    md.maxwell_boltzmann(state, 2.0 * TARGET_T, seed=11)
    potential = LennardJones(epsilon=1.0, sigma=1.0, cutoff=2.5)
    sim = md.Simulation(state, [potential], VelocityVerlet(dt=0.005), skin=0.3)
    equilibrate(sim)
    state.step, state.time = 0, 0.0

    production = md.Simulation(state, [potential], VelocityVerlet(dt=0.005), skin=0.3)
    with H5MDWriter(
        args.trajectory, state, units="lj", velocities=True, overwrite=args.overwrite
    ) as writer:
        production.attach(writer, interval=10)
        production.run(args.steps)
    print(f"wrote {writer.n_frames} frames of {state.n_atoms} atoms to {args.trajectory}")

    command = ["analyze", str(args.trajectory), "--all", "--out", str(args.out)]
    if args.overwrite:
        command.append("--overwrite")
    return md_main(command)


if __name__ == "__main__":
    sys.exit(main())
