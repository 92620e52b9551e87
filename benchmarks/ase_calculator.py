"""MDCalculator against ASE's LennardJones (and asap3's when installed), under ASE.

Argon in metal units: an fcc crystal (a = 5.26 Angstrom, atoms displaced by
up to 0.05 Angstrom), epsilon 0.0104 eV, sigma 3.40 Angstrom, cutoff 8.5
Angstrom with the energy shifted to zero there (ASE's plain mode; asap3's
``modified=True``), at 2048 (8^3 cells) and 32000 (20^3 cells) atoms. Run
from the repository root::

    python benchmarks/ase_calculator.py
    python benchmarks/ase_calculator.py --sizes 2048 --md-steps 200 --no-asap

Two measurements per calculator and size:

evaluations
    Energy + forces per second: each evaluation moves every atom to a new
    random displacement (up to 0.01 Angstrom) from a fixed start, so no
    calculator can serve it from a cache and none needs to rebuild its
    neighbour list (that is the steady state of MD between rebuilds), then
    asks for energy and forces. The first call (list build, numba
    compilation) is untimed. Median over ``--evals`` evaluations.
velocity Verlet
    ``ase.md.verlet.VelocityVerlet`` with 5 fs steps from 100 K
    (Maxwell-Boltzmann, fixed seed), i.e. ASE's Python integrator driving
    each calculator, neighbour-list rebuilds included. ``--md-steps`` steps
    (1000) in ``--md-blocks`` blocks; the median time per step over blocks.

ASE's own LennardJones loops over atoms in Python and is 100-1000 times
slower, so it gets fewer evaluations (``--ase-evals``) and a shorter run
(``--ase-md-steps``), reported per step; it is measured at every size, never
extrapolated (``--ase-max-atoms`` leaves it out above a size). Ratios are
taken to the peers measured in the same run. Every calculator is checked to
give the same energy first. All run on one thread (numba, asap3 and ASE's
numpy code alike are serial here).
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
import warnings
from collections.abc import Callable

import numpy as np
from _machine import machine_line

import md
from md import units
from md.calculator import MDCalculator
from md.parallel import get_threads, set_threads
from potentials import LennardJones

EPSILON, SIGMA, CUTOFF = 0.0104, 3.40, 8.5
LATTICE_CONSTANT = 5.26
TEMPERATURE = 100.0
DT_FS = 5.0
SEED = 2024


def argon(n_atoms: int, seed: int = SEED):
    """fcc argon with ``n_atoms`` = 4 n^3 atoms, rattled, with 100 K velocities (ase.Atoms)."""
    from ase.build import bulk

    cells = round((n_atoms / 4) ** (1 / 3))
    if 4 * cells**3 != n_atoms:
        raise SystemExit(f"--sizes: {n_atoms} is not an fcc crystal of 4 n^3 atoms")
    atoms = bulk("Ar", "fcc", a=LATTICE_CONSTANT, cubic=True).repeat(cells)
    rng = np.random.default_rng(seed)
    atoms.positions += rng.uniform(-0.05, 0.05, size=atoms.positions.shape)
    state = md.State.from_ase(atoms)
    md.maxwell_boltzmann(state, TEMPERATURE, seed=rng, kB=units.kB)
    return state.to_ase()


def calculators(skin: float, use_asap: bool) -> dict[str, Callable[[], object] | None]:
    """Factories of the calculators compared (None where one is not installed)."""
    from ase.calculators.lj import LennardJones as AseLennardJones

    factories: dict[str, Callable[[], object] | None] = {
        "ours": lambda: MDCalculator(
            [LennardJones(epsilon=EPSILON, sigma=SIGMA, cutoff=CUTOFF, cutoff_mode="shift")],
            skin=skin,
        ),
        "ase": lambda: AseLennardJones(epsilon=EPSILON, sigma=SIGMA, rc=CUTOFF),
        "asap3": None,
    }
    if use_asap:
        try:
            from asap3 import LennardJones as AsapLennardJones

            factories["asap3"] = lambda: AsapLennardJones(
                [18], [EPSILON], [SIGMA], rCut=CUTOFF, modified=True
            )
        except ImportError:
            pass
    return factories


def time_evaluations(atoms, factories: dict, n_evals: dict, seed: int = SEED) -> dict:
    """Seconds per energy + forces evaluation of each calculator, interleaved.

    Every calculator gets its own copy of ``atoms``; the first call (list
    build, compilation) is untimed. Round r times one evaluation of every
    calculator that still has evaluations left (``n_evals[name]``), so load
    from other processes hits all of them alike.
    """
    rng = np.random.default_rng(seed)
    start = atoms.positions.copy()
    displacements = [
        start + rng.uniform(-0.01, 0.01, size=start.shape) for _ in range(max(n_evals.values()))
    ]
    systems, results = {}, {}
    for name, factory in factories.items():
        copy = atoms.copy()
        copy.calc = factory()
        begin = time.perf_counter()
        energy = copy.get_potential_energy()
        copy.get_forces()
        systems[name] = copy
        results[name] = {"energy": energy, "first": time.perf_counter() - begin, "times": []}
    for r, positions in enumerate(displacements):
        for name, system in systems.items():
            if r >= n_evals[name]:
                continue
            system.positions = positions
            begin = time.perf_counter()
            system.get_potential_energy()
            system.get_forces()
            results[name]["times"].append(time.perf_counter() - begin)
    for result in results.values():
        result["median"] = statistics.median(result["times"])
    return results


def time_verlet(atoms, factories: dict, n_steps: dict, n_blocks: int) -> dict:
    """Seconds per ASE VelocityVerlet step of each calculator: median over blocks.

    After 5 untimed steps each, blocks of every calculator alternate (one
    block in all for those given fewer steps than blocks).
    """
    from ase.md.verlet import VelocityVerlet

    runs = {}
    for name, factory in factories.items():
        copy = atoms.copy()
        copy.calc = factory()
        dyn = VelocityVerlet(copy, timestep=DT_FS * units.fs)
        dyn.run(5)  # warm-up: list build, compilation
        runs[name] = (copy, dyn, copy.get_total_energy(), [])
    for block in range(n_blocks):
        for name, (_copy, dyn, _, per_step) in runs.items():
            blocks = n_blocks if n_steps[name] >= n_blocks else 1
            if block >= blocks:
                continue
            steps = n_steps[name] // blocks + (1 if block < n_steps[name] % blocks else 0)
            begin = time.perf_counter()
            dyn.run(steps)
            per_step.append((time.perf_counter() - begin) / steps)
    results = {}
    for name, (copy, _dyn, e_start, per_step) in runs.items():
        calc = copy.calc
        results[name] = {
            "median": statistics.median(per_step),
            "drift": (copy.get_total_energy() - e_start) / len(copy),
            "builds": calc.forcefield.neighbor_list.n_builds
            if isinstance(calc, MDCalculator)
            else None,
            "steps": n_steps[name],
        }
    return results


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="2048,32000", help="atom counts, 4 n^3 each")
    parser.add_argument("--evals", type=int, default=20, help="timed evaluations (ours, asap3)")
    parser.add_argument("--ase-evals", type=int, default=3, help="timed evaluations, ASE's LJ")
    parser.add_argument("--md-steps", type=int, default=1000, help="VelocityVerlet steps")
    parser.add_argument("--md-blocks", type=int, default=5, help="blocks for the step median")
    parser.add_argument("--ase-md-steps", type=int, default=10, help="steps with ASE's LJ")
    parser.add_argument(
        "--ase-max-atoms", type=int, default=10**9, help="leave ASE's LJ out above this size"
    )
    parser.add_argument("--skin", type=float, default=0.5, help="our neighbour skin [A]")
    parser.add_argument("--no-asap", action="store_true", help="leave asap3 out")
    parser.add_argument(
        "--threads",
        type=int,
        default=1,
        help="our kernel threads (default 1: asap3 and ASE's LJ run on one thread)",
    )
    args = parser.parse_args(argv)
    if args.threads < 1:
        parser.error("--threads must be >= 1")
    set_threads(args.threads)
    print(machine_line())
    print(
        f"threads: ours {get_threads()}, asap3 1, ASE's LJ 1"
        + ("" if args.threads == 1 else " (ratios below are NOT at equal thread counts)")
    )
    sizes = [int(s) for s in args.sizes.split(",") if s.strip()]
    factories = calculators(args.skin, not args.no_asap)
    if factories["asap3"] is None:
        print(
            "asap3 not measured: "
            + ("--no-asap" if args.no_asap else "not installed (pip install asap3; it builds")
            + ("" if args.no_asap else " from source, a few minutes)")
        )
    warnings.simplefilter("ignore", DeprecationWarning)
    print(
        f"argon fcc, a = {LATTICE_CONSTANT} A, LJ epsilon {EPSILON} eV, sigma {SIGMA} A, "
        f"cutoff {CUTOFF} A (energy-shifted); our skin {args.skin} A; ASE VelocityVerlet "
        f"dt {DT_FS} fs from {TEMPERATURE} K"
    )
    rows = []
    for n in sizes:
        atoms = argon(n)
        chosen = {
            name: factory
            for name, factory in factories.items()
            if factory is not None and not (name == "ase" and n > args.ase_max_atoms)
        }
        n_evals = {name: args.ase_evals if name == "ase" else args.evals for name in chosen}
        n_steps = {name: args.ase_md_steps if name == "ase" else args.md_steps for name in chosen}
        print(f"  {n} atoms: {', '.join(chosen)}; evaluations {n_evals}, MD steps {n_steps}")
        evaluations = time_evaluations(atoms, chosen, n_evals)
        verlets = time_verlet(atoms, chosen, n_steps, args.md_blocks)
        results = {name: (evaluations[name], verlets[name]) for name in chosen}
        energies = {name: r[0]["energy"] for name, r in results.items()}
        reference = energies["ours"]
        for name, energy in energies.items():
            if abs(energy - reference) > 1e-9 * abs(reference):
                print(f"WARNING: {name} energy {energy!r} differs from ours {reference!r}")
        rows.append((n, results, energies))

    print()
    print(
        f"{'atoms':>6} {'calculator':<10}{'evals/s':>11}{'ms/eval':>10}{'first s':>9}"
        f"{'VV ms/step':>12}{'VV steps':>9}{'drift eV/atom':>15}{'builds':>8}"
    )
    for n, results, _ in rows:
        for name, (evaluation, verlet) in results.items():
            builds = "" if verlet["builds"] is None else str(verlet["builds"])
            print(
                f"{n:>6} {name:<10}{1 / evaluation['median']:>11.1f}"
                f"{1e3 * evaluation['median']:>10.3f}{evaluation['first']:>9.3f}"
                f"{1e3 * verlet['median']:>12.3f}{verlet['steps']:>9d}"
                f"{verlet['drift']:>15.2e}{builds:>8}"
            )
    print()
    equal = "equal threads (1)" if get_threads() == 1 else f"ours on {get_threads()} threads"
    print(f"Ratios (ours faster by; < 1 means slower), medians measured in this run, {equal}:")
    for n, results, energies in rows:
        ours_eval, ours_vv = results["ours"][0]["median"], results["ours"][1]["median"]
        for peer in ("ase", "asap3"):
            if peer not in results:
                print(f"  {n:>6} atoms vs {peer:<6} not measured")
                continue
            eval_ratio = results[peer][0]["median"] / ours_eval
            vv_ratio = results[peer][1]["median"] / ours_vv
            spread = abs(energies[peer] - energies["ours"]) / abs(energies["ours"])
            print(
                f"  {n:>6} atoms vs {peer:<6} energy+forces {eval_ratio:8.2f}x   "
                f"VelocityVerlet step {vv_ratio:8.2f}x   (energies agree to {spread:.1e})"
            )
    aims = []
    for n, results, _ in rows:
        if n == 2048 and "ase" in results:
            ratio = results["ase"][0]["median"] / results["ours"][0]["median"]
            aims.append(
                f">= 100x ASE's LJ at 2048 atoms: {ratio:.0f}x "
                f"{'met' if ratio >= 100 else 'NOT met'}"
            )
        if "asap3" in results:
            ratio = results["asap3"][1]["median"] / results["ours"][1]["median"]
            aims.append(
                f"within 2x of asap3 under ASE's VelocityVerlet at {n} atoms: "
                f"{ratio:.2f}x {'met' if ratio >= 0.5 else 'NOT met'}"
            )
    if aims:
        print("Aims: " + "; ".join(aims))
    return 0 if all(math.isfinite(r[1]["ours"][0]["median"]) for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
