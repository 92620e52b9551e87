"""The mixed step's fused passes against the separate ones, at 1 and 2 threads (issue 70).

Run from the repository root::

    python benchmarks/mixed_step_passes.py                      # 32000 atoms, 1 and 2 threads
    python benchmarks/mixed_step_passes.py --repeats 7 --no-gromacs
    python benchmarks/mixed_step_passes.py --pairs --repeats 20 --block 20   # fused/separate

The LJ melt of ``lj_melt.py`` (fcc at rho* 0.8442, T* 3, LJ truncated at 2.5, skin 0.3,
velocity Verlet, dt 0.005). Per thread count three Simulations of one start: mixed
precision with velocity Verlet's fused step (``ForceField.verlet_step`` ->
``PairPotential.mixed_verlet_step``: two compiled calls around the cluster kernel), mixed
precision with the step made of the separate calls (the force field's ``verlet_step``
told to do nothing: the kicks, ``compute`` with its list check, cache copy and relative
positions, the finite check), and double precision; then Debian's GROMACS (``gmx
mdrun``, mixed precision, its own Verlet buffer, ``gromacs_lj_melt.py``) on the same
melt in the same run. Blocks of ``--block`` steps take turns (fused, separate, double in
an order that rotates from round to round, then GROMACS's run of as many steps),
``--repeats`` rounds, so that load from other processes falls on all of them alike; the
figures are medians of the blocks' rates and of the per-round ratios. Wall time: on 2
cores shared with other work, two-thread blocks stall when another process takes a core,
which the ratios within a round mostly cancel.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import gromacs_lj_melt  # noqa: E402
from _machine import machine_line  # noqa: E402

import md  # noqa: E402
from integrators import VelocityVerlet  # noqa: E402
from md.parallel import max_threads, set_threads  # noqa: E402
from potentials import LennardJones  # noqa: E402

CELLS, DENSITY, TEMPERATURE, SEED, CUTOFF, DT = 20, 0.8442, 3.0, 87287, 2.5, 0.005
KINDS = ("mixed, fused", "mixed, separate", "double")


def melt(cells: int) -> md.State:
    return md.maxwell_boltzmann(md.lattice("fcc", cells, density=DENSITY), TEMPERATURE, seed=SEED)


def simulation(cells: int, kind: str) -> md.Simulation:
    precision = "double" if kind == "double" else "mixed"
    potential = LennardJones(epsilon=1.0, sigma=1.0, cutoff=CUTOFF, cutoff_mode="none")
    sim = md.Simulation(melt(cells), [potential], VelocityVerlet(DT), precision=precision)
    if kind == "mixed, separate":  # the step made of the separate calls
        sim.forcefield.verlet_step = lambda *args: 0
    return sim


def _pairs(cells: int, count: int, block: int, rounds: int) -> None:
    """Fused against separate alone at ``count`` threads: ``rounds`` pairs of ``block``
    steps, the pair's order alternating; medians of the per-pair ratios of wall time and
    of the calling thread's CPU time (which other processes do not inflate)."""
    set_threads(count)
    sims = {kind: simulation(cells, kind) for kind in KINDS[:2]}
    for sim in sims.values():
        sim.run(20)  # compiles or loads the kernels
    wall: dict[str, list[float]] = {kind: [] for kind in sims}
    cpu: dict[str, list[float]] = {kind: [] for kind in sims}
    for r in range(rounds):
        for kind in KINDS[:2] if r % 2 == 0 else KINDS[1::-1]:
            begin, used = time.perf_counter(), time.thread_time()
            sims[kind].run(block)
            wall[kind].append(time.perf_counter() - begin)
            cpu[kind].append(time.thread_time() - used)
    fused, separate = KINDS[:2]
    ratio_wall = statistics.median(a / b for a, b in zip(wall[fused], wall[separate], strict=True))
    ratio_cpu = statistics.median(a / b for a, b in zip(cpu[fused], cpu[separate], strict=True))
    print(
        f"{count} thread(s), {4 * cells**3} atoms, {rounds} pairs of {block} steps: ms a step "
        f"fused {1e3 * statistics.median(wall[fused]) / block:.3f}, separate "
        f"{1e3 * statistics.median(wall[separate]) / block:.3f}; time fused / separate: wall "
        f"{ratio_wall:.3f}, calling thread's CPU {ratio_cpu:.3f}"
    )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cells", type=int, default=CELLS)
    parser.add_argument("--threads", default="1,2", help="thread counts, comma-separated")
    parser.add_argument("--block", type=int, default=100, help="steps per block")
    parser.add_argument("--repeats", type=int, default=5, help="rounds of blocks")
    parser.add_argument("--no-gromacs", action="store_true", help="leave GROMACS out")
    parser.add_argument("--gmx", default=None, help="the gmx binary (default: on the PATH)")
    parser.add_argument(
        "--pairs",
        action="store_true",
        help="only fused against separate, in pairs of blocks whose order alternates",
    )
    args = parser.parse_args(argv)
    threads = [int(t) for t in args.threads.split(",") if int(t) <= max_threads()]
    md.keep_freed_memory()  # as `md run` sets a process up
    if args.pairs:
        print(machine_line())
        for count in threads:
            _pairs(args.cells, count, args.block, args.repeats)
        return 0
    gmx = None if args.no_gromacs else gromacs_lj_melt.find_gmx("mixed", args.gmx)
    n_atoms = 4 * args.cells**3
    print(machine_line())
    print(
        f"LJ melt, {n_atoms} atoms, blocks of {args.block} steps in turns, {args.repeats} rounds; "
        f"GROMACS: {gmx or 'not found'}"
    )
    sims = {}
    for count in threads:
        set_threads(count)
        for kind in KINDS:
            sims[count, kind] = simulation(args.cells, kind)
            sims[count, kind].run(20)  # compiles or loads the kernels
    rates: dict[tuple[int, str], list[float]] = {key: [] for key in sims}
    for count in threads:
        rates[count, "GROMACS"] = []
    start_state = melt(args.cells)
    for repeat in range(args.repeats):
        for count in threads:
            set_threads(count)
            # the kinds in turn first: the first block after another process's run (or
            # a thread count's change) finds colder caches
            shift = repeat % len(KINDS)
            for kind in KINDS[shift:] + KINDS[:shift]:
                sim = sims[count, kind]
                begin = time.perf_counter()
                sim.run(args.block)
                rates[count, kind].append(n_atoms * args.block / (time.perf_counter() - begin))
            if gmx is not None:
                found = gromacs_lj_melt.run(gmx, start_state, args.block, count)
                rates[count, "GROMACS"].append(n_atoms * args.block / found["loop_time"])
    names = [*KINDS, "GROMACS"] if gmx is not None else list(KINDS)
    print("\nM atom-steps/s, median of the blocks (min-max):")
    for count in threads:
        for name in names:
            values = rates[count, name]
            print(
                f"  {count} thread(s)  {name:16s} {statistics.median(values) / 1e6:7.2f}  "
                f"({min(values) / 1e6:.2f}-{max(values) / 1e6:.2f})"
            )

    def ratio(a, b, count_a, count_b) -> float:
        pairs = zip(rates[count_a, a], rates[count_b, b], strict=True)
        return statistics.median(x / y for x, y in pairs)

    print("\nratios, median of the rounds' ratios:")
    for count in threads:
        print(
            f"  {count} thread(s): fused / separate "
            f"{ratio('mixed, fused', 'mixed, separate', count, count):.3f}"
            + (
                f", fused / GROMACS {ratio('mixed, fused', 'GROMACS', count, count):.2f}, "
                f"separate / GROMACS {ratio('mixed, separate', 'GROMACS', count, count):.2f}"
                if gmx is not None
                else ""
            )
        )
    if len(threads) > 1:
        low, high = threads[0], threads[-1]
        scaling = ", ".join(f"{name} {ratio(name, name, high, low):.2f}x" for name in names)
        print(f"  {low} -> {high} threads: {scaling}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
