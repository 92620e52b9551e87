"""Mixed against double precision: force-call time, MD rate, force error and NVE drift.

On the LJ melt's configuration (fcc at reduced density 0.8442, cutoff 2.5,
skin 0.3): the time of ``energy_forces(virial=False)`` in each precision, each
over its ForceField's own list (double: the slot frame; mixed: the cluster
pairs, where the cell allows), taking turns within each repeat (a loaded
machine slows both alike), the median of the per-repeat ratios mixed/double;
the MD loop's rate (velocity Verlet, dt 0.005) in each precision, again
interleaved; the largest force
difference relative to the largest force; and the NVE energy drift of each
over ``--drift-steps`` steps of a smaller melt (LAMMPS's: fcc at T = 3, run
2000 steps in double first, so that every run starts from the same liquid),
as the total energy's change from the first step to the last per atom per
tau (GROMACS's "Conserved energy drift" is the same difference) and as the
slope of a straight-line fit. ``--gromacs`` runs that melt in GROMACS too
(``gmx``, mixed precision: ``--gmx PATH`` or ``$GMX``; and ``gmx_d``), from
the same positions and velocities, with the list radius fixed at 2.8 sigma
(our cutoff plus skin), nstlist 10 and the energy shifted at the cutoff as ours
is (``vdw-modifier = Potential-shift``), and prints its drift beside ours.
Compilation is excluded (a warm-up call).

    python benchmarks/mixed_precision.py                       # 32000 atoms, 1 and 2 threads
    python benchmarks/mixed_precision.py --threads 1 --repeats 31 --drift-steps 20000
    python benchmarks/mixed_precision.py --threads 1 --gromacs --gmx /path/to/avx512/gmx
    python benchmarks/mixed_precision.py --drift-only --gromacs --seeds 5   # drifts of 5 liquids
    python benchmarks/mixed_precision.py --phases --threads 2 --steps 200   # the step's phases

``--phases`` prints instead where the mixed step's work goes, phase by phase, with one
chunk and with as many chunks as each ``--threads`` count above 1 (both run on one
thread: CPU times, which other processes on a shared machine do not inflate as they do
wall times), which phases are serial, each uneven phase's slowest chunk, and the bound
that puts on the speed-up (``benchmarks/_phases.py``).
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the checkout, from anywhere

import _phases  # noqa: E402
from _machine import machine_line  # noqa: E402

import md  # noqa: E402
from integrators import VelocityVerlet  # noqa: E402
from md.build import maxwell_boltzmann  # noqa: E402
from md.forcefield import ForceField  # noqa: E402
from md.parallel import get_threads, set_threads  # noqa: E402
from potentials import LennardJones  # noqa: E402

PRECISIONS = ("double", "mixed")
DT = 0.005


def melt(cells: int, temperature: float, seed: int = 1) -> md.State:
    return maxwell_boltzmann(md.lattice("fcc", cells, density=0.8442), temperature, seed=seed)


def force_calls(cells: int, repeats: int) -> dict:
    """Median seconds per force call in each precision and the median per-repeat ratio."""
    state = melt(cells, 1.0)
    state.positions += np.random.default_rng(0).normal(scale=0.05, size=state.positions.shape)
    fields = {p: ForceField([LennardJones(cutoff=2.5)], precision=p) for p in PRECISIONS}
    results = {p: f.compute(state, virial=False) for p, f in fields.items()}  # warm-up
    error = (
        np.abs(results["mixed"].forces - results["double"].forces).max()
        / np.abs(results["double"].forces).max()
    )
    # each precision over its own list: the slot frame for double, the cluster pairs that
    # ForceField(precision="mixed") builds where the cell allows
    lists = {p: f.neighbor_list for p, f in fields.items()}
    potentials = {p: f.potentials[0] for p, f in fields.items()}
    times = {p: [] for p in PRECISIONS}
    for _ in range(repeats):
        for precision in PRECISIONS:
            start = time.perf_counter()
            potentials[precision].energy_forces(
                state, lists[precision], virial=False, precision=precision
            )
            times[precision].append(time.perf_counter() - start)
    ratios = [m / d for m, d in zip(times["mixed"], times["double"], strict=True)]
    return {
        "double": statistics.median(times["double"]),
        "mixed": statistics.median(times["mixed"]),
        "ratio": statistics.median(ratios),
        "error": error,
    }


def md_rates(cells: int, steps: int, repeats: int) -> dict:
    """Median atom-steps per second of the MD loop in each precision (interleaved)."""
    sims = {
        p: md.Simulation(
            melt(cells, 1.0), [LennardJones(cutoff=2.5)], VelocityVerlet(DT), precision=p
        )
        for p in PRECISIONS
    }
    for sim in sims.values():
        sim.run(10)  # warm-up
    rates = {p: [] for p in PRECISIONS}
    for _ in range(repeats):
        for precision, sim in sims.items():
            start = time.perf_counter()
            sim.run(steps)
            rates[precision].append(sim.state.n_atoms * steps / (time.perf_counter() - start))
    ratios = [m / d for m, d in zip(rates["mixed"], rates["double"], strict=True)]
    return {
        "double": statistics.median(rates["double"]),
        "mixed": statistics.median(rates["mixed"]),
        "ratio": statistics.median(ratios),
    }


def liquid(cells: int, seed: int = 3) -> md.State:
    """The melt after 2000 steps from fcc at T = 3 (double; velocities from ``seed``), the
    drift runs' start: on one thread, so that the start (and so the drifts) is the same
    for any --threads (the force sums' order follows the chunk count)."""
    threads = get_threads()
    sim = md.Simulation(
        melt(cells, 3.0, seed=seed), [LennardJones(cutoff=2.5)], VelocityVerlet(DT), threads=1
    )
    try:
        sim.run(2000)
    finally:
        set_threads(threads)
    state = sim.state.copy()
    state.step, state.time = 0, 0.0
    return state


def drift(start: md.State, steps: int, precision: str, every: int = 1) -> tuple[float, float]:
    """(end-point, |fit slope|) drift of the total energy per atom per tau over ``steps``
    NVE steps from ``start``; ``every`` > 1: the list rebuilt every that many steps with
    no check (GROMACS's nstlist), not exact."""
    sim = md.Simulation(
        start.copy(),
        [LennardJones(cutoff=2.5)],
        VelocityVerlet(DT),
        precision=precision,
        neighbor_every=every,
        neighbor_check=every == 1,
    )
    every = max(steps // 50, 1)
    times, energies = [0.0], [sim.thermo()["total_energy"]]
    for _ in range(steps // every):
        sim.run(every)
        times.append(sim.state.time)
        energies.append(sim.thermo()["total_energy"])
    n = sim.state.n_atoms
    return (
        (energies[-1] - energies[0]) / times[-1] / n,
        abs(np.polyfit(times, energies, 1)[0]) / n,
    )


def gromacs_drifts(start: md.State, steps: int, binaries: dict) -> dict:
    """GROMACS's conserved-energy drift per atom per tau (reduced units) of the same melt."""
    import gromacs_lj_melt as gmx

    found = {}
    for variant, explicit in binaries.items():
        binary = gmx.find_gmx(variant, explicit)
        if binary is None:
            print(f"note: no GROMACS {variant}-precision binary; skipped")
            continue
        result = gmx.run(
            binary, start, steps, 1, rlist=gmx.FIXED_RLIST, nstlist=10, modifier="Potential-shift"
        )
        drift_ps = result["conserved_drift"]  # kJ/mol/ps per atom; epsilon = 1 kJ/mol
        label = f"GROMACS {result.get('version', '?')} {variant} ({result.get('simd', '?')})"
        found[label] = None if drift_ps is None else drift_ps * gmx.TAU
    return found


def _compared(ours: list[float], theirs: list[float], name: str) -> str:
    """How often our |drift| is the smaller over the liquids, the two-sided sign test's p
    (no better, no worse: each liquid a coin), and a bootstrap 90 % interval (resampled
    liquids, 10^4 draws) of the ratio of the medians."""
    n = len(ours)
    below = sum(o < t for o, t in zip(ours, theirs, strict=True))
    tail = sum(math.comb(n, k) for k in range(min(below, n - below) + 1)) / 2**n
    draws = np.random.default_rng(0).integers(0, n, size=(10_000, n))
    ratios = np.median(np.asarray(ours)[draws], axis=1) / np.maximum(
        np.median(np.asarray(theirs)[draws], axis=1), 1e-300
    )
    low, high = np.percentile(ratios, [5, 95])
    return (
        f"ours mixed below {name} in {below} of {n} liquids (sign test p = "
        f"{min(1.0, 2 * tail):.2g}); ratio of the medians "
        f"{statistics.median(ours) / max(statistics.median(theirs), 1e-300):.2f}, "
        f"bootstrap 90 % interval {low:.2f}-{high:.2f}"
    )


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=20, help="fcc cells per edge (20)")
    parser.add_argument("--threads", default="1,2", help="thread counts (1,2)")
    parser.add_argument("--repeats", type=int, default=21, help="interleaved repeats (21)")
    parser.add_argument("--steps", type=int, default=100, help="MD steps per repeat (100)")
    parser.add_argument("--drift-cells", type=int, default=8, help="drift run's cells (8)")
    parser.add_argument("--drift-steps", type=int, default=10_000, help="drift steps (10000)")
    parser.add_argument("--gromacs", action="store_true", help="GROMACS's drift beside ours")
    parser.add_argument("--gmx", default=None, help="GROMACS mixed binary (default $GMX, gmx)")
    parser.add_argument("--gmx-d", default=None, help="GROMACS double binary (default gmx_d)")
    parser.add_argument(
        "--seeds",
        type=int,
        default=1,
        help="drift runs from this many liquids (velocity seeds 3, 4, ...), "
        "with the medians of the drifts and of their ratios (1)",
    )
    parser.add_argument("--drift-only", action="store_true", help="skip the timings")
    parser.add_argument(
        "--phases",
        action="store_true",
        help="only the mixed step's phases: work with 1 and with T chunks, serial share",
    )
    parser.add_argument(
        "--every",
        type=int,
        default=1,
        help="also ours mixed with the list rebuilt every N steps and no check"
        " (GROMACS's rule: its drift runs use nstlist 10, rlist 2.8)",
    )
    args = parser.parse_args(argv)
    if args.seeds < 1:
        parser.error(f"--seeds must be at least 1, got {args.seeds}")
    if args.every < 1:
        parser.error(f"--every must be at least 1, got {args.every}")
    print(machine_line())
    if args.phases:
        for threads in (int(t) for t in args.threads.split(",")):
            if threads > 1:
                _phases.report(args.cells, threads, args.steps, 20, max(args.repeats // 3, 3))
        return
    n_atoms = 4 * args.cells**3
    for threads in () if args.drift_only else (int(t) for t in args.threads.split(",")):
        set_threads(threads)
        calls = force_calls(args.cells, args.repeats)
        rates = md_rates(args.cells, args.steps, max(args.repeats // 3, 3))
        print(
            f"\n{n_atoms} atoms, {threads} thread(s), medians of {args.repeats} interleaved "
            "repeats:"
        )
        print(
            f"  force call   double {1e3 * calls['double']:.2f} ms, mixed "
            f"{1e3 * calls['mixed']:.2f} ms: mixed/double {calls['ratio']:.3f}"
        )
        print(
            f"  MD loop      double {rates['double'] / 1e6:.2f} M atom-steps/s, mixed "
            f"{rates['mixed'] / 1e6:.2f} M: mixed/double {rates['ratio']:.3f}"
        )
        print(f"  max |F_mixed - F_double| / max |F|: {calls['error']:.1e}")
    print(
        f"\nNVE drift, {4 * args.drift_cells**3} atoms of liquid, {args.drift_steps} "
        f"steps of dt {DT} (total energy per atom per tau: last minus first; |slope| of a "
        "line fit):"
    )
    table = {}  # engine -> end-point drift per seed
    lazy = f"ours mixed (every {args.every}, no check)"
    for seed in range(3, 3 + args.seeds):
        start = liquid(args.drift_cells, seed)
        if args.seeds > 1:
            print(f" liquid of seed {seed}:")
        for precision in PRECISIONS:
            ends, fit = drift(start, args.drift_steps, precision)
            table.setdefault(f"ours {precision}", []).append(ends)
            print(f"  ours {precision:<8}{ends:+.2e}   fit {fit:.2e}")
        if args.every > 1:
            ends, fit = drift(start, args.drift_steps, "mixed", args.every)
            table.setdefault(lazy, []).append(ends)
            print(f"  {lazy} {ends:+.2e}   fit {fit:.2e}")
        if args.gromacs:
            found = gromacs_drifts(
                start, args.drift_steps, {"mixed": args.gmx, "double": args.gmx_d}
            )
            for label, value in found.items():
                print(
                    f"  {label}: "
                    + ("no drift line in md.log" if value is None else f"{value:+.2e}")
                )
                table.setdefault(label, []).append(math.nan if value is None else value)
    magnitudes = {name: [abs(x) for x in values] for name, values in table.items()}
    mixed, double = magnitudes["ours mixed"], magnitudes["ours double"]
    ratios = [m / max(d, 1e-300) for m, d in zip(mixed, double, strict=True)]
    if args.seeds > 1:
        print(
            f" medians over {args.seeds} liquids of |drift|: "
            + ", ".join(
                f"{name} {statistics.median(values):.2e}" for name, values in magnitudes.items()
            )
        )
    print(
        f"  |mixed| / |double| (last minus first) {statistics.median(ratios):.2f}"
        + (" (median over the liquids)" if args.seeds > 1 else "")
        + " (target: within 10)"
    )
    for name, values in magnitudes.items():
        if "GROMACS" in name and " mixed " in name and not any(map(math.isnan, values)):
            for ours_name in ("ours mixed", lazy) if lazy in magnitudes else ("ours mixed",):
                ours = magnitudes[ours_name]
                against = statistics.median(
                    m / max(g, 1e-300) for m, g in zip(ours, values, strict=True)
                )
                print(
                    f"  |{ours_name}| / |{name}| {against:.2f}"
                    + (" (median over the liquids)" if args.seeds > 1 else "")
                    + " (target: at most 1)"
                )
                if args.seeds > 1:
                    print("  " + _compared(ours, values, name).replace("ours mixed", ours_name, 1))


if __name__ == "__main__":
    main()
