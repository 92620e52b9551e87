"""Work-precision on SciMLBenchmarks' liquid argon: energy error against cost per integrator.

The system is the one of the SciMLBenchmarks page "Liquid argon benchmarks"
(https://docs.sciml.ai/SciMLBenchmarksOutput/stable/NBodySimulator/liquid_argon/,
source benchmarks/NBodySimulator/liquid_argon.jmd of SciML/SciMLBenchmarks.jl):
N = 350 argon atoms, T = 120 K with epsilon = kB * 120 K (so T* = 1),
sigma = 3.4 A, rho = 1374 kg/m^3 (L = 7.569 sigma, rho* = 0.807),
m = 39.95 * 1.6747e-27 kg, a Lennard-Jones cutoff R = 3.5 sigma, atoms on the
nodes of a cubic grid (ceil(N^(1/3)) per edge, the first N nodes) with
Gaussian velocities of standard deviation sqrt(kB T / m), run in reduced
units to t = 40. Their potential is plain truncation at R (cutoff_mode
"none" here); ``--cutoff-mode shift`` removes the energy jump of each pair
crossing R.

As they do, every integrator runs at dt = tau * c, c its cost per step
relative to velocity Verlet (here its force evaluations per step), so that
points with one tau cost about the same. The page's own per-step costs
(normalised to VelocityVerlet) are printed next to ours measured in the same
run: VerletLeapfrog 1.05, CalvoSanz4 2.38, McAte5 2.92, Yoshida6 3.74,
KahanLi8 8.44, SofSpa10 15.76.

    python3 benchmarks/work_precision.py                       # t = 40, three taus
    python3 benchmarks/work_precision.py --time 4 --taus 1e-3,2e-3

Prints the CPU, then one row per run; writes work_precision_argon.csv and
work_precision_argon.png (energy error against wall time and force calls).
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import time

import numpy as np
from _machine import machine_line

import md
from integrators import INTEGRATORS
from potentials import LennardJones

#: SciMLBenchmarks' per-step costs relative to VelocityVerlet (their page, hard-coded there).
THEIR_COSTS = {
    "VelocityVerlet": 1.00,
    "VerletLeapfrog": 1.05,
    "PseudoVerletLeapfrog": 0.98,
    "McAte2": 1.02,
    "CalvoSanz4": 2.38,
    "McAte5": 2.92,
    "Yoshida6": 3.74,
    "KahanLi8": 8.44,
    "SofSpa10": 15.76,
}
#: Ours that correspond to theirs.
PEERS = {"verlet": "VelocityVerlet", "leapfrog": "VerletLeapfrog", "yoshida6": "Yoshida6"}


def liquid_argon(seed: int = 1) -> md.State:
    """The SciMLBenchmarks liquid argon start in reduced units (see the module docstring)."""
    n_atoms = 350
    mass = 39.95 * 1.6747e-27  # kg, as on their page
    length = (mass * n_atoms / 1374.0) ** (1.0 / 3.0) / 3.4e-10  # box edge / sigma
    per_edge = math.ceil(n_atoms ** (1.0 / 3.0))
    grid = np.array(
        [[i, j, k] for i in range(per_edge) for j in range(per_edge) for k in range(per_edge)]
    )[:n_atoms]
    spacing = length / per_edge
    velocities = np.random.default_rng(seed).normal(size=(n_atoms, 3))  # sd sqrt(kT/m) = 1
    return md.State(positions=(grid + 0.5) * spacing, velocities=velocities, box=length)


def run(name: str, dt: float, final_time: float, cutoff_mode: str, samples: int = 400):
    cls = INTEGRATORS[name]
    n_steps = max(1, round(final_time / dt))
    dt = final_time / n_steps
    state = liquid_argon()
    potential = LennardJones(cutoff=3.5, cutoff_mode=cutoff_mode)
    sim = md.Simulation(state, [potential], cls(dt), skin=0.3, threads=1)
    energies = []
    sample_wall = [0.0]

    def sample(s) -> None:
        start = time.perf_counter()
        energies.append(s.thermo()["total_energy"])
        sample_wall[0] += time.perf_counter() - start

    sim.attach(sample, interval=max(1, n_steps // samples))
    before = sim.forcefield.n_evaluations
    start = time.perf_counter()
    try:
        sim.run(n_steps)
    except md.SimulationError as error:  # past the stability limit: a point with no error
        print(f"  {name} at dt = {dt:.3g}: {error}", file=sys.stderr)
        nan = math.nan
        return {
            "integrator": name,
            "dt": dt,
            "steps": n_steps,
            "force_evaluations": nan,
            "wall": nan,
            "max_energy_error": nan,
            "final_energy_error": nan,
            "wall_per_step": nan,
        }
    wall = time.perf_counter() - start - sample_wall[0]
    energies.append(sim.thermo()["total_energy"])
    e = (np.array(energies) - energies[0]) / state.n_atoms
    return {
        "integrator": name,
        "dt": dt,
        "steps": n_steps,
        "force_evaluations": sim.forcefield.n_evaluations - before,
        "wall": wall,
        "max_energy_error": float(np.max(np.abs(e))),
        "final_energy_error": float(abs(e[-1])),
        "wall_per_step": wall / n_steps,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--time", type=float, default=40.0, help="final time, reduced (40)")
    parser.add_argument("--taus", default="1e-3,2e-3,4e-3", help="base steps tau (comma list)")
    parser.add_argument(
        "--integrators", default="verlet,leapfrog,yoshida4,pefrl,blanes_moan,yoshida6,rk4"
    )
    parser.add_argument("--cutoff-mode", default="none", choices=("none", "shift", "smooth"))
    parser.add_argument("--out", default="work_precision_argon", help="CSV/PNG name stem")
    args = parser.parse_args(argv)
    names = [n.strip() for n in args.integrators.split(",") if n.strip()]
    taus = [float(t) for t in args.taus.split(",")]
    print(machine_line() + "; threads 1")
    print(
        f"liquid argon (SciMLBenchmarks): N = 350, L = {liquid_argon().box[0]:.4f} sigma, "
        f"R = 3.5 sigma ({args.cutoff_mode}), t = {args.time:g}, dt = tau x force calls per step"
    )
    rows = []
    header = (
        f"{'integrator':<16}{'tau':>8}{'dt':>10}{'steps':>8}{'f calls':>9}{'wall s':>9}"
        f"{'max|dE|/N':>12}{'|dE(t)|/N':>12}"
    )
    print(header)
    for tau in taus:
        for name in names:
            calls = getattr(INTEGRATORS[name](1.0), "force_evaluations", None) or (
                4 if name == "rk4" else 1
            )
            row = run(name, tau * calls, args.time, args.cutoff_mode)
            row["tau"] = tau
            rows.append(row)
            print(
                f"{name:<16}{tau:>8.0e}{row['dt']:>10.3g}{row['steps']:>8}"
                f"{row['force_evaluations']:>9}{row['wall']:>9.2f}"
                f"{row['max_energy_error']:>12.3e}{row['final_energy_error']:>12.3e}",
                flush=True,
            )
    verlet = [r["wall_per_step"] for r in rows if r["integrator"] == "verlet"]
    if verlet:
        base = float(np.nanmedian(verlet))
        print("\nper-step cost relative to velocity Verlet (median over taus) vs SciMLBenchmarks':")
        for name in names:
            mine = [r["wall_per_step"] for r in rows if r["integrator"] == name]
            ours = float(np.nanmedian(mine))
            theirs = THEIR_COSTS.get(PEERS.get(name, ""), math.nan)
            print(f"  {name:<16} ours {ours / base:6.2f}   theirs {theirs:6.2f}")
    with open(f"{args.out}.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    _plot(rows, names, f"{args.out}.png")
    print(f"wrote {args.out}.csv, {args.out}.png")
    return 0


def _plot(rows, names, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    for k, name in enumerate(names):
        mine = sorted((r for r in rows if r["integrator"] == name), key=lambda r: r["dt"])
        for ax, work in zip(axes, ("wall", "force_evaluations"), strict=True):
            ax.loglog(
                [r[work] for r in mine],
                [r["max_energy_error"] for r in mine],
                "o-",
                color=f"C{k % 10}",
                label=name,
            )
    axes[0].set_xlabel("wall time [s]")
    axes[1].set_xlabel("force evaluations")
    for ax in axes:
        ax.set_ylabel("max |E(t) - E(0)| per atom [eps]")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize="small")
    fig.suptitle("Liquid argon (SciMLBenchmarks setup): energy error against cost")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    sys.exit(main())
