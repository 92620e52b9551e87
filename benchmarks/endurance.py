"""Endurance: a small LJ system for a million steps with trajectory output and checkpoints.

Reports whether resident memory stays flat and whether the total energy per
atom stays within its bound (velocity Verlet: a bounded, oscillating error, no
drift). Not part of the test suite; run it as

    python3 benchmarks/endurance.py [--steps 1000000] [--cells 3] [--every 1000]
                                    [--checkpoint-every 10000] [--dt 0.005]

Criteria printed at the end:

- memory: resident set size (VmRSS) at the last sample minus the one after
  the first 10 % of the run (allocations of the warm-up done), in MiB;
  flat when below ``--rss-tolerance`` (default 5 MiB);
- energy: the linear drift of E_total/N over the run and the largest
  excursion |E/N - E0/N|; within bound when the drift over the whole run is
  smaller than the excursion seen in the first 10 % (a bounded error does
  not grow after the first oscillations) times ``--drift-factor`` (2).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from _machine import machine_line

from integrators import VelocityVerlet
from md.build import lattice, maxwell_boltzmann
from md.checkpoint import read_checkpoint, write_checkpoint
from md.parallel import get_threads, set_threads
from md.simulation import Simulation
from md.trajectory import H5MDWriter, read_trajectory
from potentials import LennardJones


def rss_mib() -> float:
    """Current resident set size of this process [MiB] (Linux /proc)."""
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1_000_000)
    parser.add_argument("--cells", type=int, default=3, help="fcc cells per edge (4 atoms each)")
    parser.add_argument("--every", type=int, default=1000, help="frame interval")
    parser.add_argument("--checkpoint-every", type=int, default=10_000)
    parser.add_argument("--dt", type=float, default=0.005)
    parser.add_argument("--temperature", type=float, default=0.8)
    parser.add_argument("--rss-tolerance", type=float, default=5.0)
    parser.add_argument("--drift-factor", type=float, default=2.0)
    parser.add_argument("--out", type=Path, help="folder for the files (default: a temporary one)")
    parser.add_argument("--threads", type=int, default=1, help="kernel threads (1)")
    args = parser.parse_args()
    set_threads(args.threads)
    print(machine_line())
    print(f"threads: {get_threads()}")

    state = maxwell_boltzmann(lattice("fcc", args.cells, density=0.8442), args.temperature, seed=7)
    sim = Simulation(state, [LennardJones(cutoff=2.5)], VelocityVerlet(dt=args.dt), skin=0.3)
    folder_context = tempfile.TemporaryDirectory() if args.out is None else None
    folder = Path(folder_context.name) if folder_context else args.out
    folder.mkdir(parents=True, exist_ok=True)
    trajectory = folder / "endurance.h5"
    saved = folder / "endurance.h5.ckpt"
    samples: list[tuple[int, float, float]] = []  # (step, seconds, rss)
    start = time.perf_counter()

    def checkpoint(sim) -> None:
        write_checkpoint(
            saved,
            sim.state,
            sim.integrator,
            sim.forcefield,
            n_frames=writer.n_frames,
            last_frame_step=sim.state.step,
        )
        samples.append((sim.state.step, time.perf_counter() - start, rss_mib()))

    with H5MDWriter(trajectory, state, units="lj", velocities=True, overwrite=True) as writer:
        sim.attach(writer, interval=args.every)
        sim.attach(checkpoint, interval=args.checkpoint_every)
        chunk = max(args.steps // 20, 1)
        done = 0
        while done < args.steps:
            n = min(chunk, args.steps - done)
            sim.run(n)
            done += n
            print(
                f"  step {state.step:>9d}  {time.perf_counter() - start:8.1f} s  "
                f"RSS {rss_mib():7.1f} MiB",
                flush=True,
            )
    wall = time.perf_counter() - start

    traj = read_trajectory(trajectory)
    n_atoms = state.n_atoms
    energy = traj.observables["total_energy"] / n_atoms
    times = traj.times
    excursion = np.abs(energy - energy[0])
    early = excursion[: max(len(excursion) // 10, 2)].max()
    slope = np.polyfit(times, energy, 1)[0]
    drift = slope * (times[-1] - times[0])
    last = read_checkpoint(saved)
    steps_rss = np.array([s[2] for s in samples])
    after_warmup = steps_rss[len(steps_rss) // 10] if len(steps_rss) else float("nan")
    growth = steps_rss[-1] - after_warmup if len(steps_rss) else float("nan")

    print(f"\n{n_atoms} atoms, {args.steps} steps of dt {args.dt} (velocity Verlet, LJ 2.5 shift)")
    print(
        f"wall {wall:.1f} s, {args.steps / wall:,.0f} steps/s, "
        f"{n_atoms * args.steps / wall:,.0f} atom-steps/s"
    )
    print(
        f"frames {traj.n_frames}, checkpoints written {len(samples)}, last at step "
        f"{last.state.step}; file {trajectory.stat().st_size / 2**20:.1f} MiB"
    )
    print(
        f"RSS: first sample {steps_rss[0]:.1f} MiB, after 10 % {after_warmup:.1f} MiB, "
        f"end {steps_rss[-1]:.1f} MiB, max {steps_rss.max():.1f} MiB; growth after warm-up "
        f"{growth:+.2f} MiB -> {'flat' if abs(growth) < args.rss_tolerance else 'GROWING'}"
    )
    print(
        f"E/N: start {energy[0]:.8f}, largest excursion {excursion.max():.3e} "
        f"(first 10 %: {early:.3e}), linear drift over the run {drift:+.3e} "
        f"({slope:+.3e} per unit time) -> "
        f"{'within bound' if abs(drift) < args.drift_factor * early else 'DRIFTING'}"
    )
    if folder_context:
        folder_context.cleanup()


if __name__ == "__main__":
    main()
