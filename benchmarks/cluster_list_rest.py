"""The cluster list's work around its kernels on the steps that prune or search (issue 70).

A mixed-precision step whose fused pass finds an atom past the list's rule (about a fifth
of the melt's steps) prunes the outer list or searches again; around those kernels the
list then wrote the relative positions, which the cluster kernel's call wrote again from
the same positions, and measured the atoms' distance from the search's positions to
choose between a prune and a search. Now the kernel's call reads the list's relative
positions (``ClusterFrame.relative``), and a prune that a bound already allows
(``NeighborList.n_bounded_prunes``) is chosen without that pass.

Two Simulations of the LJ melt (fcc at rho* 0.8442, T* 3, rc 2.5, skin 0.3, outer skin
1.5, velocity Verlet dt 0.005, 32000 atoms) from the same start in one process: one as the
code is, one made to do again what the change spares (after each update of its list the
list's relative positions are withheld from the kernel, which then writes its own, and
each bounded prune's pass is made anyway): the same trajectory, checked at the end. After
``--warm`` steps each runs ``--block`` steps in turns, the order alternating, for
``--rounds`` pairs; printed: medians of the per-block wall and calling-thread CPU time a
step and of the per-pair ratios now / as before. Then the two spared pieces alone
(medians of ``--calls`` turns) and how often each is spared per 100 steps, and the peer
in the same run (LAMMPS ``lj/cut`` on the same melt in a child, one thread, its step and
Neigh time per build; ``--no-lammps`` to skip it)::

    python benchmarks/cluster_list_rest.py --threads 1,2 --rounds 15
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from functools import partial
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the checkout, from anywhere

import numpy as np  # noqa: E402
from _machine import machine_line  # noqa: E402
from lj_melt import lammps_environment, run_lammps  # noqa: E402

import md  # noqa: E402
from integrators import VelocityVerlet  # noqa: E402
from md.neighbors import NeighborList  # noqa: E402
from md.neighbors.lists import largest_displacement2  # noqa: E402
from md.parallel import chunk_count, set_threads  # noqa: E402
from potentials import LennardJones  # noqa: E402

CUTOFF, SKIN, OUTER, DT = 2.5, 0.3, 1.5, 0.005


def simulation(cells: int) -> md.Simulation:
    start = md.maxwell_boltzmann(md.lattice("fcc", cells, density=0.8442), 3.0, seed=1)
    sim = md.Simulation(
        start, [LennardJones(cutoff=CUTOFF)], VelocityVerlet(DT), precision="mixed", skin=SKIN
    )
    sim.forcefield.neighbor_list = NeighborList(CUTOFF, SKIN, clusters=True, outer_skin=OUTER)
    sim.forcefield.invalidate()
    return sim


def as_before(sim: md.Simulation) -> None:
    """Make ``sim``'s list do again what the change spares (the same lists and numbers)."""
    nl = sim.forcefield.neighbor_list
    update = nl.update

    def redone(state, moved2=None):
        bounded = nl.n_bounded_prunes
        rebuilt = update(state, moved2)
        if nl.n_bounded_prunes > bounded:  # the pass the bound spared
            largest_displacement2(state.positions, nl.reference_positions, 1)
        if nl.clusters is not None:
            nl.clusters.relative = None  # the kernel writes its own relative positions
        return rebuilt

    nl.update = redone  # (an instance attribute: the force field calls nl.update)


def blocks(sims: dict, steps: int, rounds: int) -> dict:
    """Per Simulation, (wall, CPU) seconds a step of each block; the order alternates."""
    found = {name: [] for name in sims}
    names = list(sims)
    for r in range(rounds):
        for name in names if r % 2 == 0 else names[::-1]:
            wall, cpu = time.perf_counter(), time.thread_time()
            sims[name].run(steps)
            found[name].append(
                ((time.perf_counter() - wall) / steps, (time.thread_time() - cpu) / steps)
            )
    return found


def alone(call, calls: int) -> tuple[float, float]:
    """Medians of the wall and CPU seconds of ``call()``."""
    walls, cpus = [], []
    for _ in range(calls):
        wall, cpu = time.perf_counter(), time.thread_time()
        call()
        walls.append(time.perf_counter() - wall)
        cpus.append(time.thread_time() - cpu)
    return statistics.median(walls), statistics.median(cpus)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", default="1,2", help="thread counts (1,2)")
    parser.add_argument("--cells", type=int, default=20, help="fcc cells a side (20)")
    parser.add_argument("--warm", type=int, default=300, help="steps before timing (300)")
    parser.add_argument("--block", type=int, default=20, help="steps a block (20)")
    parser.add_argument("--rounds", type=int, default=11, help="pairs of blocks (11)")
    parser.add_argument("--calls", type=int, default=41, help="calls of a piece alone (41)")
    parser.add_argument("--no-lammps", action="store_true", help="no LAMMPS peer line")
    args = parser.parse_args()
    threads = [int(t) for t in args.threads.split(",")]
    if min(threads) < 1 or min(args.cells, args.warm, args.block, args.rounds, args.calls) < 1:
        parser.error("thread counts, --cells, --warm, --block, --rounds and --calls >= 1")
    print(machine_line())
    print(
        f"{4 * args.cells**3} atoms, mixed, skin {SKIN}, outer skin {OUTER}; {args.rounds} "
        f"pairs of {args.block}-step blocks after {args.warm} steps"
    )
    ours = None
    for t in threads:
        set_threads(t)
        sims = {"now": simulation(args.cells), "before": simulation(args.cells)}
        as_before(sims["before"])
        for sim in sims.values():
            sim.run(args.warm)
        nl = sims["now"].forcefield.neighbor_list
        counts = (nl.n_builds, nl.n_prunes, nl.n_bounded_prunes, sims["now"].state.step)
        found = blocks(sims, args.block, args.rounds)
        same = np.array_equal(sims["now"].state.positions, sims["before"].state.positions)
        steps = sims["now"].state.step - counts[3]
        per100 = [
            100 * (now - was) / steps
            for now, was in zip(
                (nl.n_builds, nl.n_prunes, nl.n_bounded_prunes), counts[:3], strict=True
            )
        ]
        print(
            f"{t} thread(s): per 100 steps {per100[0]:.1f} searches, {per100[1]:.1f} prunes "
            f"({per100[2]:.1f} chosen by the bound); same trajectory: {same}"
        )
        for k, clock in enumerate(("wall", "CPU (calling thread)")):
            now = [b[k] for b in found["now"]]
            before = [b[k] for b in found["before"]]
            ratio = statistics.median(a / b for a, b in zip(now, before, strict=True))
            print(
                f"  step, {clock}: now {1e3 * statistics.median(now):.3f} ms, as before "
                f"{1e3 * statistics.median(before):.3f} ms, now / before {ratio:.3f}"
            )
        if t == 1:
            ours = statistics.median(b[0] for b in found["now"])
        state = sims["now"].state
        clusters = nl.clusters
        xi, xj = np.empty_like(clusters.relative[0]), np.empty_like(clusters.relative[1])
        reference = nl.reference_positions
        chunks = chunk_count(state.n_atoms, 16_000)  # as the list counts its passes
        pieces = {
            "relative positions (the kernel's call spares it, each prune and search)": (
                partial(clusters.relative_positions, state.positions, xi, xj),
                per100[0] + per100[1],
            ),
            "distance from the search (spared at each bounded prune)": (
                partial(largest_displacement2, state.positions, reference, chunks),
                per100[2],
            ),
        }
        for name, (call, spared) in pieces.items():
            wall, cpu = alone(call, args.calls)
            print(
                f"  {name}: {1e6 * wall:.1f} us wall, {1e6 * cpu:.1f} us CPU a call; "
                f"{1e3 * wall * spared / 100:.4f} ms a step spared"
            )
    if not args.no_lammps:
        peer(args.cells, ours)
    return 0


def peer(cells: int, ours: float | None) -> None:
    """LAMMPS on the same melt (100 steps, its list checked every step), one thread."""
    try:
        found = run_lammps(cells, 100, "check", lammps_environment())
    except (OSError, RuntimeError) as error:
        print(f"LAMMPS: not run ({error})")
        return
    loop, builds = found.get("loop_time"), found.get("n_builds")
    neigh = (found.get("sections") or {}).get("Neigh")
    if not loop or not builds or not neigh:
        print(f"LAMMPS {found.get('version', '?')}: no loop time, Neigh time or builds")
        return
    step = 1e3 * loop / 100
    ratio = f"; its step / our mixed step (now, 1 thread) {step / (1e3 * ours):.2f}" if ours else ""
    print(
        f"LAMMPS {found.get('version', '?')} lj/cut, 1 thread, this melt: {step:.2f} ms a "
        f"step, Neigh {1e3 * neigh / builds:.2f} ms per build ({builds} builds){ratio}"
    )


if __name__ == "__main__":
    sys.exit(main())
