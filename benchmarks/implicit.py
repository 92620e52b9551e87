"""Implicit Euler with Newton: iterations and cost per step, and stiff-chain time to solution.

Three measurements, each printed as medians over repeats:

(a) LJ melt (fcc 0.8442, T 3.0, cutoff 2.5, skin 0.3): one implicit Euler step
    at dt = 0.005 against one velocity Verlet step, with Newton and linear
    iterations per step; ``--scaling`` repeats this at several N to show
    how the cost grows.
(b) A Kremer-Grest bead-spring melt of similar size, with stiff harmonic
    bonds (k = 2000) instead of FENE, plus WCA: the same figures.
(c) A small stiff chain (harmonic bonds, k = 10^4, plus WCA): the wall time
    to simulate a fixed span with velocity Verlet at 90% of its measured
    stability limit, with implicit Euler at 20x, 50x and 100x that step (the
    largest that converges is its largest useful step), and with
    ``scipy.integrate.solve_ivp(method="BDF")`` given the same sparse
    Jacobian built from our Hessian.

Run from the repository root::

    python benchmarks/implicit.py                 # 32000 atoms, as in the issue
    python benchmarks/implicit.py --cells 10      # 4000 atoms, quicker
    python benchmarks/implicit.py --scaling       # cost ratio at 4k, 13.5k, 32k atoms
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

import numpy as np
import scipy.sparse as sp
from _machine import machine_line
from scipy.integrate import solve_ivp

import md
from integrators import ConvergenceError, VelocityVerlet
from integrators.implicit_euler import ImplicitEuler
from md.parallel import get_threads, set_threads
from md.polymers import polymer_melt, single_chain
from potentials import HarmonicBonds, LennardJones

WCA = 2.0 ** (1.0 / 6.0)


def _time_steps(sim, n_steps: int) -> float:
    start = time.perf_counter()
    sim.run(n_steps)
    return (time.perf_counter() - start) / n_steps


def compare_step_cost(make_system, dt: float, n_steps: int, repeats: int) -> dict:
    """Median wall time per step of VV and implicit Euler on fresh copies of a system."""
    vv_times, ie_times, newton, linear, hessians = [], [], [], [], []
    for _ in range(repeats):
        state, potentials = make_system()
        vv = md.Simulation(state.copy(), potentials, VelocityVerlet(dt))
        vv.run(1)  # first neighbour list and forces out of the timing
        vv_times.append(_time_steps(vv, n_steps))
        state, potentials = make_system()
        integrator = ImplicitEuler(dt, tol=1e-6, max_iter=50)
        ie = md.Simulation(state, potentials, integrator)
        ie.run(1)
        before = dict(integrator.statistics)
        ie_times.append(_time_steps(ie, n_steps))
        newton.append(
            (integrator.statistics["newton_iterations"] - before["newton_iterations"]) / n_steps
        )
        linear.append(
            (integrator.statistics["linear_iterations"] - before["linear_iterations"]) / n_steps
        )
        hessians.append(
            (integrator.statistics["hessian_evaluations"] - before["hessian_evaluations"]) / n_steps
        )
    vv_step, ie_step = statistics.median(vv_times), statistics.median(ie_times)
    return {
        "n_atoms": state.n_atoms,
        "vv_step_ms": 1e3 * vv_step,
        "ie_step_ms": 1e3 * ie_step,
        "ratio": ie_step / vv_step,
        "newton_per_step": statistics.median(newton),
        "linear_per_step": statistics.median(linear),
        "hessians_per_step": statistics.median(hessians),
    }


def lj_melt(cells: int):
    def make():
        state = md.maxwell_boltzmann(md.lattice("fcc", cells, density=0.8442), 3.0, seed=87287)
        return state, [LennardJones(cutoff=2.5, cutoff_mode="shift")]

    return make


def stiff_bead_spring(n_beads: int, k: float = 2000.0):
    chain_length = 50
    n_chains = max(1, n_beads // chain_length)
    state, bonds = polymer_melt(n_chains, chain_length, density=0.85, seed=5)
    md.maxwell_boltzmann(state, 1.0, seed=5)

    def make():
        return state.copy(), [
            LennardJones(cutoff=WCA, cutoff_mode="shift"),
            HarmonicBonds(bonds, k=k, r0=0.97),
        ]

    return make


def stiff_chain(n_beads: int = 50, k: float = 1.0e4):
    state, bonds = single_chain(n_beads, bond_length=0.97, seed=3)
    md.maxwell_boltzmann(state, 1.0, seed=3)

    def make():
        return state.copy(), [
            LennardJones(cutoff=WCA, cutoff_mode="shift"),
            HarmonicBonds(bonds, k=k, r0=0.97),
        ]

    return make


def _stable(make, dt: float, span: float) -> bool:
    state, potentials = make()
    sim = md.Simulation(state, potentials, VelocityVerlet(dt))
    e0 = sim.thermo()["total_energy"]
    scale = max(abs(e0), sim.thermo()["kinetic_energy"])
    try:
        sim.run(max(1, round(span / dt)))
    except md.SimulationError:
        return False
    return abs(sim.thermo()["total_energy"] - e0) < 0.5 * scale


def vv_stability_limit(make, span: float, low: float = 1e-5, high: float = 1.0) -> float:
    """Largest stable velocity Verlet dt, by bisection in log dt."""
    for _ in range(30):
        middle = np.sqrt(low * high)
        if _stable(make, middle, span):
            low = middle
        else:
            high = middle
        if high / low < 1.02:
            break
    return low


def time_to_solution(make, span: float) -> list[tuple[str, float, float, str]]:
    rows = []
    limit = vv_stability_limit(make, span=0.2 * span)
    dt = 0.9 * limit
    state, potentials = make()
    sim = md.Simulation(state, potentials, VelocityVerlet(dt))
    start = time.perf_counter()
    sim.run(round(span / dt))
    rows.append(("velocity Verlet", dt, time.perf_counter() - start, f"limit {limit:.3g}"))
    for factor in (20, 50, 100):
        dt_ie = factor * limit
        state, potentials = make()
        integrator = ImplicitEuler(dt_ie, tol=1e-6, max_iter=50)
        sim = md.Simulation(state, potentials, integrator)
        start = time.perf_counter()
        n_steps = max(1, round(span / dt_ie))
        try:
            sim.run(n_steps)
        except (ConvergenceError, md.SimulationError) as error:
            rows.append((f"implicit Euler x{factor}", dt_ie, math.nan, f"failed: {error}"))
            continue
        stats = integrator.statistics
        rows.append(
            (
                f"implicit Euler x{factor}",
                dt_ie,
                time.perf_counter() - start,
                f"Newton/step {stats['newton_iterations'] / stats['steps']:.2f}",
            )
        )
    rows.append(_bdf(make, span))
    return rows


def _bdf(make, span: float):
    state, potentials = make()
    forcefield = md.ForceField(potentials)
    n = state.n_atoms
    inverse_mass = np.repeat(1.0 / state.masses, 3)
    evaluations = [0]

    def rhs(_t, y):
        state.positions[:] = y[: 3 * n].reshape(n, 3)
        evaluations[0] += 1
        forces = forcefield.compute(state).forces.ravel()
        return np.concatenate([y[3 * n :], forces * inverse_mass])

    def jacobian(_t, y):
        state.positions[:] = y[: 3 * n].reshape(n, 3)
        hessian = forcefield.hessian(state)
        zero = sp.csr_matrix((3 * n, 3 * n))
        identity = sp.identity(3 * n, format="csr")
        return sp.bmat([[zero, identity], [-sp.diags(inverse_mass) @ hessian, zero]], "csc")

    y0 = np.concatenate([state.positions.ravel(), state.velocities.ravel()])
    start = time.perf_counter()
    result = solve_ivp(rhs, (0.0, span), y0, method="BDF", jac=jacobian, rtol=1e-6, atol=1e-8)
    wall = time.perf_counter() - start
    note = f"{result.t.size - 1} steps, {result.nfev} f-evals, {result.njev} Jacobians"
    if not result.success:
        note += f" (failed: {result.message})"
    return ("scipy BDF (sparse Jacobian)", float(np.mean(np.diff(result.t))), wall, note)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=20, help="fcc cells per edge (20: 32000)")
    parser.add_argument("--steps", type=int, default=5, help="timed steps per repeat")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--scaling", action="store_true", help="LJ melt at 10, 15, 20 cells")
    parser.add_argument("--skip-polymer", action="store_true")
    parser.add_argument("--chain-span", type=float, default=2.0, help="stiff chain span [tau]")
    parser.add_argument(
        "--threads", type=int, default=1, help="kernel threads for both integrators (1)"
    )
    args = parser.parse_args(argv)
    md.keep_freed_memory()  # as md run does (md._memory); import md leaves malloc alone
    if args.threads < 1:
        parser.error("--threads must be >= 1")
    set_threads(args.threads)
    print(machine_line())
    print(f"threads: {get_threads()} for velocity Verlet and implicit Euler alike")

    print("warm-up (numba compilation) ...", flush=True)
    compare_step_cost(lj_melt(3), 0.005, 2, 1)

    header = f"{'system':<28}{'N':>8}{'VV ms/step':>12}{'IE ms/step':>12}{'IE/VV':>8}"
    header += f"{'Newton/step':>13}{'linear/step':>13}{'Hessians/step':>15}"
    rows = []
    for cells in (10, 15, 20) if args.scaling else (args.cells,):
        rows.append(
            ("LJ melt dt 0.005", compare_step_cost(lj_melt(cells), 0.005, args.steps, args.repeats))
        )
    if not args.skip_polymer:
        n_beads = 4 * args.cells**3
        rows.append(
            (
                "bead-spring k=2000 dt 0.005",
                compare_step_cost(stiff_bead_spring(n_beads), 0.005, args.steps, args.repeats),
            )
        )
    print(header)
    for name, r in rows:
        line = f"{name:<28}{r['n_atoms']:>8}{r['vv_step_ms']:>12.2f}{r['ie_step_ms']:>12.2f}"
        line += f"{r['ratio']:>8.2f}{r['newton_per_step']:>13.2f}{r['linear_per_step']:>13.2f}"
        line += f"{r['hessians_per_step']:>15.2f}"
        print(line)

    print(f"\nStiff chain (50 beads, k = 1e4, WCA), time to simulate {args.chain_span} tau:")
    for name, dt, wall, note in time_to_solution(stiff_chain(), args.chain_span):
        print(f"  {name:<30} dt {dt:<10.3g} wall {wall:8.3f} s   {note}")


if __name__ == "__main__":
    main()
