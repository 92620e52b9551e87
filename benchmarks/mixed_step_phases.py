"""Where one mixed-precision velocity Verlet step goes, phase by phase (issue 70).

Run from the repository root::

    python benchmarks/mixed_step_phases.py                   # 32000 atoms, 1 and 2 threads
    python benchmarks/mixed_step_phases.py --rounds 15 --calls 10 --threads 1
    python benchmarks/mixed_step_phases.py --fallback --rounds 15   # the fallback, now/before

The LJ melt of ``lj_melt.py`` (fcc at rho* 0.8442, T* 3, LJ truncated at 2.5, skin 0.3,
velocity Verlet, dt 0.005) in mixed precision, run 300 steps; then, on that state's
list and kernel prepared by the run, each phase of the fused step
(``ForceField.verlet_step`` -> ``PairPotential.mixed_verlet_step``) called alone on
copies of the arrays it writes:

- the force cache's comparison at the step's start (``same_values`` of the positions
  and the cache's copy);
- the fused pass without the relative positions (kick, drift, cache copy, half-skin
  check: ``kick_drift_slots`` told that the list does not hold);
- the relative positions (the fused pass with them, less the pass without);
- the cluster kernel;
- the sum into atom order with the finite check and the last kick (``finish_step``);

two passes that a fallback step made a second time before issue 70's round (the
displacement from the last prune, the cache copy), and the whole step (blocks of
``--block`` steps of the Simulation, the fallback steps among them: the list's prune or
search, the forces over the new list, the kick), with the list's update per fallback
step from the force field's timings. ``--fallback``: the whole step with the fallback as
now against as before (the list's update measuring again, ``compute`` and its copy, the
integrator's kick), two Simulations in one process. The phases take turns
in an order that rotates from round to round (``--rounds``, each phase ``--calls`` calls
a round), so that load from other processes falls on all of them alike; figures are
medians over the rounds of the per-call wall time, and the share of each phase in the
sum of the phases. Two threads on 2 cores shared with other work stall now and then;
the medians and the rotation mostly cancel that, absolute figures do not.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _machine import machine_line  # noqa: E402

import md  # noqa: E402
from integrators import VelocityVerlet  # noqa: E402
from md.neighbors.lists import largest_displacement2  # noqa: E402
from md.parallel import copy_into, max_threads, same_values, set_threads  # noqa: E402
from potentials import LennardJones  # noqa: E402
from potentials._step_kernels import (  # noqa: E402
    cluster_runs,
    finish_step,
    kick_drift_slots,
    pass_chunks,
)

CELLS, DENSITY, TEMPERATURE, SEED, CUTOFF, DT = 20, 0.8442, 3.0, 87287, 2.5, 0.005


def _simulation(cells: int) -> md.Simulation:
    state = md.maxwell_boltzmann(md.lattice("fcc", cells, density=DENSITY), TEMPERATURE, seed=SEED)
    potential = LennardJones(epsilon=1.0, sigma=1.0, cutoff=CUTOFF, cutoff_mode="none")
    return md.Simulation(state, [potential], VelocityVerlet(DT), precision="mixed")


def _phases(sim: md.Simulation, block: int) -> dict:
    """The phases as callables of no argument, each one call of that phase."""
    ff, state = sim.forcefield, sim.state
    potential, nl = ff.potentials[0], ff.neighbor_list
    # the arrays the run left: the kept cluster call (list, scratch), the cache's copy
    prepared = potential._cluster_calls[0][-1]
    scratch, clusters = prepared[2], prepared[3]
    atom = clusters.atom
    held, allowed2 = nl.cluster_check(state)
    key = ff._key[0].copy()
    positions, velocities = state.positions.copy(), state.velocities.copy()
    forces = ff.compute(state, virial=False).forces.copy()
    chunks = pass_chunks(state.n_atoms)
    runs = cluster_runs(clusters.windows, len(atom))
    fresh = forces.copy()

    def compare():
        same_values(key, positions)

    def displacement():  # a fallback's second measure before issue 70's round
        largest_displacement2(positions, held, chunks)

    def copy():  # a fallback's second cache copy before it
        copy_into(key, positions)

    def fused_pass(allowed):
        kick_drift_slots(
            positions,
            velocities,
            forces,
            state.masses,
            0.0,  # no kick, no drift: the same arithmetic and memory traffic, state kept
            0.0,
            held,
            allowed,
            key,
            atom,
            clusters.origin,
            scratch[0],
            scratch[1],
            chunks,
        )

    def kernel():
        potential._cluster_kernel(prepared, state, False, fresh)

    def finish():
        finish_step(
            scratch[3],
            atom,
            clusters.windows,
            fresh,
            runs,
            scratch[6],
            velocities,
            state.masses,
            0.0,
            chunks,
        )

    def steps():
        sim.run(block)

    return {
        "cache comparison": compare,
        "fused pass, no relative positions": lambda: fused_pass(-1.0),
        "fused pass with relative positions": lambda: fused_pass(float("inf")),
        "cluster kernel": kernel,
        "sum into atom order + finite + kick": finish,
        "steps": steps,
        "displacement pass": displacement,
        "cache copy": copy,
    }


def measure(count: int, cells: int, rounds: int, calls: int, block: int) -> None:
    set_threads(count)
    sim = _simulation(cells)
    sim.run(300)  # compiles or loads the kernels; the liquid, its list pruned and searched
    phases = _phases(sim, block)
    times: dict[str, list[float]] = {name: [] for name in phases}
    nl, ff = sim.forcefield.neighbor_list, sim.forcefield
    fallbacks, neighbor = [], []
    names = list(phases)
    for r in range(rounds):
        order = names[r % len(names) :] + names[: r % len(names)]
        for name in order:
            n = 1 if name == "steps" else calls
            if name == "steps":
                before = (nl.n_builds + nl.n_prunes, ff.timings["neighbor"])
            begin = time.perf_counter()
            for _ in range(n):
                phases[name]()
            elapsed = time.perf_counter() - begin
            if name == "steps":
                times[name].append(elapsed / block)
                fallbacks.append(nl.n_builds + nl.n_prunes - before[0])
                neighbor.append((ff.timings["neighbor"] - before[1]) / block)
            else:
                times[name].append(elapsed / n)
    us = {name: 1e6 * statistics.median(values) for name, values in times.items()}
    relative = us["fused pass with relative positions"] - us["fused pass, no relative positions"]
    parts = {
        "cache comparison": us["cache comparison"],
        "fused pass: kick, drift, copy, check": us["fused pass, no relative positions"],
        "relative positions": relative,
        "cluster kernel": us["cluster kernel"],
        "sum into atom order + finite + kick": us["sum into atom order + finite + kick"],
    }
    total = sum(parts.values())
    n_atoms = sim.state.n_atoms
    share = statistics.median(fallbacks) / block
    list_us = 1e6 * statistics.median(neighbor)
    print(f"{count} thread(s), {n_atoms} atoms, {rounds} rounds (medians), us a call:")
    for name, value in parts.items():
        print(f"  {name:40s} {value:9.1f}  {100 * value / total:5.1f} %")
    print(f"  {'phases of a fused step, summed':40s} {total:9.1f}")
    print(
        f"  {'whole step (run of ' + str(block) + ' steps)':40s} {us['steps']:9.1f}"
        f"  fallback steps {100 * share:.0f} %, the list's update {list_us:.1f} us a step"
        f" ({list_us / share if share else 0.0:.0f} us per fallback step)"
    )
    print(f"  {'rest (Python, fallback forces, ...)':40s} {us['steps'] - total - list_us:9.1f}")
    print(
        f"  passes a fallback step no longer repeats: displacement {us['displacement pass']:.1f},"
        f" cache copy {us['cache copy']:.1f}"
    )


def _as_before(sim: md.Simulation) -> md.Simulation:
    """``sim`` with the fallback as it was before issue 70's round: the list's update
    measures the displacement again and the force field's ``compute``, its cache copy
    and velocity Verlet's own kick make the rest of the step (the same bits)."""
    nl, potential = sim.forcefield.neighbor_list, sim.forcefield.potentials[0]
    update, step = nl.update, potential.mixed_verlet_step
    nl.update = lambda state, moved2=None: update(state)
    potential.mixed_verlet_step = lambda state, neighbors, kicks, *rest: (
        None if kicks is None else step(state, neighbors, kicks, *rest)
    )
    return sim


def fallback(count: int, cells: int, rounds: int, block: int) -> None:
    """The fallback as now against as before, two Simulations of one start in one process
    (the same trajectory, so the same steps prune or search), blocks of ``block`` steps
    taking turns, the order alternating: medians of the per-pair ratios of wall time
    and of the calling thread's CPU time."""
    set_threads(count)
    sims = {"now": _simulation(cells), "before": _as_before(_simulation(cells))}
    for sim in sims.values():
        sim.run(300)
    wall = {name: [] for name in sims}
    cpu = {name: [] for name in sims}
    for r in range(rounds):
        for name in ("now", "before") if r % 2 == 0 else ("before", "now"):
            begin, used = time.perf_counter(), time.thread_time()
            sims[name].run(block)
            wall[name].append(time.perf_counter() - begin)
            cpu[name].append(time.thread_time() - used)
    a, b = sims["now"].state, sims["before"].state
    same = bool((a.positions == b.positions).all() and (a.velocities == b.velocities).all())
    ratio_wall = statistics.median(x / y for x, y in zip(wall["now"], wall["before"], strict=True))
    ratio_cpu = statistics.median(x / y for x, y in zip(cpu["now"], cpu["before"], strict=True))
    ms = {name: 1e3 * statistics.median(v) / block for name, v in wall.items()}
    print(
        f"{count} thread(s), fallback now / before, {rounds} blocks of {block} steps each: "
        f"wall {ratio_wall:.3f}, calling thread's CPU {ratio_cpu:.3f} (ms a step "
        f"{ms['now']:.3f} / {ms['before']:.3f}); same trajectory: {same}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--threads", default="1,2", help="thread counts (1,2)")
    parser.add_argument("--cells", type=int, default=CELLS, help="fcc cells a side (20)")
    parser.add_argument("--rounds", type=int, default=11, help="rounds of turns (11)")
    parser.add_argument("--calls", type=int, default=20, help="calls of a phase a round (20)")
    parser.add_argument("--block", type=int, default=20, help="steps of a whole-step block (20)")
    parser.add_argument(
        "--fallback",
        action="store_true",
        help="the fallback steps' path now against as before, in one process",
    )
    args = parser.parse_args()
    print(machine_line())
    for count in (int(t) for t in args.threads.split(",")):
        if count > max_threads():
            print(f"{count} threads: numba offers {max_threads()}, skipped")
            continue
        if args.fallback:
            fallback(count, args.cells, 2 * args.rounds, args.block)
        else:
            measure(count, args.cells, args.rounds, args.calls, args.block)


if __name__ == "__main__":
    main()
