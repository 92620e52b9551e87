"""The halo's MPI calls from compiled code (issue 69): between list builds the ghosts'
positions, their forces back and the step's reduction go through
:mod:`md.distributed._mpi_kernels`, which calls the MPI library itself at addresses given
at run time (so numba caches the kernels, and a launch's ranks load them warm).

The MPI tests launch real ranks with ``mpiexec`` (skipped without the ``[mpi]`` extra) on a
576-atom melt; the C call's test needs no MPI.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from _mpi_support import ROOT, needs_mpi
from numba import njit

from md.distributed._mpi_kernels import c_call

#: The melt on the given decomposition, run once with the compiled exchanges and once
#: through mpi4py (``MPIRanks(compiled=False)``); rank 0 prints what each rank found.
PATHS = """\
import json, sys
import numpy as np
from mpi4py import MPI
import md
from integrators import VelocityVerlet
from potentials import LennardJones
from md.distributed import DistributedSimulation
from md.distributed.ranks import MPIRanks


def system():
    lattice = md.lattice("fcc", (6, 6, 4), density=0.8442)
    velocities = np.random.default_rng(3).normal(0.0, 1.7, lattice.positions.shape)
    return md.State(positions=lattice.positions, velocities=velocities, masses=1.0,
                    box=lattice.box)


def simulation(state, kind, **options):
    return kind(state, [LennardJones(cutoff=2.5)], VelocityVerlet(dt=0.005), skin=0.3,
                **options)


if __name__ == "__main__":
    shape = json.loads(sys.argv[2])
    found = {}
    for compiled in (True, False):
        ranks = MPIRanks(MPI.COMM_WORLD, compiled=compiled)
        sim = simulation(system(), DistributedSimulation, ranks=ranks, decomposition=shape)
        sim.run(40)
        forcefield = sim.forcefield
        found[compiled] = (
            forcefield.domain.plan() is not None,
            forcefield.domain.local_state.positions.copy(),  # owned atoms and ghosts
            forcefield.cached_forces(sim.state).copy(),
            sim.thermo()["potential_energy"],
            forcefield.n_builds,
            sim.global_view(),  # (rank 0's; None elsewhere)
        )
    on, off = found[True], found[False]
    mine = {
        "compiled": on[0],
        "mpi4py_plan": off[0],
        "ghosts": bool(np.array_equal(on[1], off[1])) and len(on[1]) > sim.state.n_atoms,
        "forces": bool(np.array_equal(on[2], off[2])),
        "energy": on[3] == off[3],
        "builds": [on[4], off[4]],
    }
    every = MPI.COMM_WORLD.allgather(mine)
    if sim.rank == 0:
        np.save(sys.argv[1], on[5].state.positions)
        same = bool(np.array_equal(on[5].state.positions, off[5].state.positions))
        print(json.dumps({"ranks": every, "positions": same}))
"""

#: The melt on 2 ranks with the mpi4py calls of every rank counted: those of its
#: communicator (an mpi4py intracommunicator of the same handle, so the compiled calls are
#: still made) and the persistent messages' runs.
COUNTED = """\
import json, sys
sys.path.insert(0, sys.argv[2])
from mpi4py import MPI
from paths import simulation, system
from md.distributed import DistributedSimulation
import md.distributed.ranks as ranks_module

counts = {}


def counting(name, found):
    def counted(*args, **kwargs):
        counts[name] = counts.get(name, 0) + 1
        return found(*args, **kwargs)
    return counted


class Counted(MPI.Intracomm):
    pass


for name in ("Allgather", "Allreduce", "allgather", "allreduce", "bcast", "gather", "Gatherv",
             "Sendrecv", "Isend", "Irecv", "Mprobe", "Send_init", "Recv_init", "Barrier"):
    setattr(Counted, name, counting(name, getattr(MPI.Intracomm, name)))
ranks_module.Messages.run = counting("Messages.run", ranks_module.Messages.run)

sim = simulation(system(), DistributedSimulation)
sim.ranks.comm = Counted(sim.ranks.comm)
forcefield = sim.forcefield
starts = forcefield.start_step
marks = []


def start_step(*args):
    marks.append((sum(counts.values()), forcefield.n_builds))
    starts(*args)


forcefield.start_step = start_step
sim.run(60)
marks.append((sum(counts.values()), forcefield.n_builds))
per_step = [b[0] - a[0] for before, a, b in zip(marks, marks[1:], marks[2:])
            if before[1] == a[1] == b[1]]
if sim.rank == 0:
    print(json.dumps({"per_step": per_step, "compiled": sim.ranks.compiled is not None}))
"""

#: One process (mpi4py's singleton rank): the compiled kernels called with messages to
#: itself; prints their results and numba's cache hits and misses.
ALONE = """\
import json
import numpy as np
from mpi4py import MPI
from md.distributed import _mpi_kernels as kernels
from md.distributed.ranks import compiled_mpi

calls = compiled_mpi(MPI.COMM_WORLD).calls
slots = np.zeros(4 + kernels.STATUS_WORDS, dtype=np.int64)
rng = np.random.default_rng(1)
positions = np.zeros((9, 3))
positions[:5] = rng.normal(size=(5, 3))
cell = np.diag([4.0, 5.0, 6.0])
# one sweep along b, to this rank through MPI: atoms 1, 3 shifted up a cell vector, 0 down
index, shifts = np.array([1, 3, 0], dtype=np.int64), np.array([1.0, -1.0])
sweeps = np.array([[1, 0, 0, 2]], dtype=np.int64)  # axis, to self, first and last swaps
# start, end, offset, count, dest, source, tag, back
table = np.array([[0, 2, 5, 2, 0, 0, 0, 0], [2, 3, 7, 1, 0, 0, 1, 2]], dtype=np.int64)
out = np.zeros((3, 3))
code = kernels.halo_forward(positions, cell, sweeps, table, shifts, index, out, slots, calls)
expected = positions[[1, 3, 0]] + np.array([[0, 5.0, 0], [0, 5.0, 0], [0, -5.0, 0]])
forward = code == 0 and bool(np.array_equal(positions[5:8], expected))
values = rng.normal(size=(9, 3))
sums = values.copy()
for j in (1, 0):
    start, end, offset = table[j, :3]
    for k in range(start, end):
        sums[index[k]] += values[offset + k - start]
back = np.zeros((3, 3))
code = kernels.halo_reverse(values, sweeps, table, index, out, back, slots, calls)
reverse = code == 0 and bool(np.array_equal(values[:5], sums[:5]))
gathered = np.zeros((1, 4))
code = kernels.gather(np.arange(4.0), gathered, calls)
gather = code == 0 and bool(np.array_equal(gathered[0], np.arange(4.0)))
largest = np.zeros(3)
code = kernels.maximum(np.array([2.0, -1.0, np.inf]), largest, calls)
gather = gather and code == 0 and largest.tolist() == [2.0, -1.0, np.inf]
stats = {}
for name in ("halo_forward", "halo_reverse", "gather", "maximum"):
    kernel = getattr(kernels, name).stats
    stats[name] = [sum(kernel.cache_hits.values()), sum(kernel.cache_misses.values())]
print(json.dumps({"results": [forward, reverse, gather], "stats": stats}))
"""


def _environment() -> dict:
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    }
    env.setdefault("MPIR_CVAR_ENABLE_HEAVY_YIELD", "1")  # (oversubscribed cores: yield)
    return env


def _launch(tmp_path: Path, name: str, source: str, n_ranks: int, *args: str) -> dict:
    script = tmp_path / f"{name}.py"
    script.write_text(source)
    command = ["mpiexec", "-n", str(n_ranks), sys.executable, str(script), *args]
    done = subprocess.run(
        command, cwd=tmp_path, env=_environment(), capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr + done.stdout
    return json.loads([line for line in done.stdout.splitlines() if line.startswith("{")][-1])


@needs_mpi
@pytest.mark.parametrize(
    "shape",
    [
        # (2 ranks: every other MPI test runs the compiled exchanges there too)
        pytest.param((2, 1, 1), marks=pytest.mark.slow),
        (3, 1, 1),  # a rank's two face neighbours differ
        (2, 2, 1),  # two sweeps to other ranks, the second sending the first's ghosts
    ],
)
def test_compiled_exchanges_give_the_mpi4py_paths_ghosts_and_forces_to_the_bit(tmp_path, shape):
    """On 2 and 3 ranks in a row and 2 x 2 bricks, 40 steps with list builds between give
    every rank the same ghosts (positions of the whole local system), forces and energy
    with the compiled exchanges as through mpi4py, bit for bit, and the trajectory
    follows the serial engine's."""
    out = tmp_path / "positions.npy"
    found = _launch(tmp_path, "paths", PATHS, int(np.prod(shape)), str(out), json.dumps(shape))
    for rank in found["ranks"]:
        assert rank["compiled"] and not rank["mpi4py_plan"], rank
        assert rank["ghosts"] and rank["forces"] and rank["energy"], rank
        assert rank["builds"][0] == rank["builds"][1] >= 2, rank
    assert found["positions"]

    sys.path.insert(0, str(tmp_path))
    try:
        import paths
    finally:
        sys.path.remove(str(tmp_path))
        sys.modules.pop("paths", None)
    from md.simulation import Simulation

    alone = paths.simulation(paths.system(), Simulation)
    alone.run(40)
    positions = np.load(out)
    gap = np.linalg.norm(positions - alone.state.positions) / np.linalg.norm(positions)
    assert gap < 1e-10


@needs_mpi
def test_a_step_between_builds_makes_no_mpi4py_call(tmp_path):
    """Between list builds a velocity Verlet step on 2 ranks makes no call through mpi4py:
    the ghosts' positions, their forces back and the evaluation's reduction are all made
    from compiled code, and so is the run's first step's agreement (before, three a step:
    the reduction's Allgather and the two sweeps' persistent messages; four in the first)."""
    (tmp_path / "paths.py").write_text(PATHS)
    found = _launch(tmp_path, "counted", COUNTED, 2, "unused", str(tmp_path))
    assert found["compiled"]
    per_step = found["per_step"]
    assert len(per_step) >= 20, per_step
    assert set(per_step) == {0}, per_step


@needs_mpi
def test_the_compiled_mpi_kernels_are_right_and_load_from_numbas_cache(tmp_path):
    """The kernels' messages to this rank itself fill the ghost rows with the shifted
    positions, add the forces back swap after swap from the last, gather and maximise; and a
    second process loads the four kernels from numba's cache, compiling none (numba-mpi's
    calls, through ctypes pointers, cannot be cached)."""
    script = tmp_path / "alone.py"
    script.write_text(ALONE)
    runs = []
    for _ in range(2):
        done = subprocess.run(
            [sys.executable, str(script)],
            cwd=tmp_path,
            env=_environment(),
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert done.returncode == 0, done.stderr + done.stdout
        runs.append(json.loads(done.stdout.splitlines()[-1]))
    for run in runs:
        assert run["results"] == [True, True, True], run
    for name, (hits, misses) in runs[1]["stats"].items():
        assert hits >= 1 and misses == 0, (name, runs[1])


def test_c_call_calls_the_function_at_an_address_as_its_python_twin_does():
    """c_call passes an int32 as a C int and an int64 as a pointer (libc's abs and strlen),
    compiled and through its Python twin alike."""
    libc = ctypes.CDLL(ctypes.util.find_library("c"))
    absolute = np.int64(ctypes.cast(libc.abs, ctypes.c_void_p).value)
    length = np.int64(ctypes.cast(libc.strlen, ctypes.c_void_p).value)
    text = np.frombuffer(b"halo sweep\0", dtype=np.uint8).copy()

    @njit
    def both(absolute, length, text):
        return (
            c_call(absolute, (np.int32(-7),)),
            c_call(length, (np.int64(text.ctypes.data),)),
        )

    assert both(absolute, length, text) == (7, 10)
    twin = c_call.python_twin
    assert twin(absolute, (np.int32(-7),)) == 7
    assert twin(length, (np.int64(text.ctypes.data),)) == 10
