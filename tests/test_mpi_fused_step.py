"""A decomposed velocity Verlet step in compiled calls (issue 69):
``DistributedForceField.verlet_step`` makes a step between list builds with two compiled
calls around the local force call (kick, drift, displacement pass, owned rows and the
ghosts' positions sent; the reduction; the ghosts' forces back and the closing kick) and
falls back to the step made of ``compute`` and the kicks whenever anything unusual holds.

The ranks are real (``mpiexec``, skipped without the ``[mpi]`` extra); each launch runs
the same melt with the fused step and with it turned off (``verlet_step`` answering 0,
"nothing done"), so the two trajectories can be compared bit for bit.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from _mpi_support import ROOT, needs_mpi

#: The melt (unequal masses) run both ways; rank 0 prints what it found. argv: steps, a
#: step at which atom 7's velocity is made argv[3] times larger at the step start (a move
#: no look-ahead foresaw: the list outrun inside that step; 0: none), and that factor.
#: "inside": fused steps that rebuilt the list inside them.
BOTH_WAYS = """\
import json, sys
import numpy as np
from mpi4py import MPI
import md
from integrators import VelocityVerlet
from potentials import LennardJones
from md.distributed import DistributedForceField, DistributedSimulation


def system(cells=(6, 6, 4)):
    lattice = md.lattice("fcc", cells, density=0.8442)
    n = len(lattice.positions)
    velocities = np.random.default_rng(3).normal(0.0, 1.7, lattice.positions.shape)
    masses = 1.0 + 0.5 * (np.arange(n) % 3)
    return md.State(positions=lattice.positions, velocities=velocities, masses=masses,
                    box=lattice.box)


def simulation(state, kind, **options):
    return kind(state, [LennardJones(cutoff=2.5)], VelocityVerlet(dt=0.005), skin=0.3,
                **options)


def run(sim, steps, kick):
    if not kick:
        sim.run(steps)
        return
    if not isinstance(sim, DistributedSimulation):
        sim.run(kick)
        sim.state.velocities[7] *= float(sys.argv[3])
        sim.run(steps - kick)
        return
    starts = sim.forcefield.start_step

    def start_step(positions, migrated):
        if sim.state.step == kick:  # (before the step: its look-ahead did not see it)
            sim.state.velocities[sim.state.ids == 7] *= float(sys.argv[3])
        starts(positions, migrated)

    sim.forcefield.start_step = start_step
    sim.run(steps)


steps, kick = int(sys.argv[1]), int(sys.argv[2])
fused = DistributedForceField.verlet_step
codes, inside = [], [0]


def counted(self, *args):
    builds = self.n_builds
    code = fused(self, *args)
    codes.append(code)
    inside[0] += self.n_builds != builds and code == 2
    return code


found = {}
for on in (True, False):
    DistributedForceField.verlet_step = counted if on else (lambda self, *args: 0)
    sim = simulation(system(), DistributedSimulation)
    energies = []
    sim.attach(lambda s: energies.append(s.thermo()["total_energy"]), 20)
    run(sim, steps, kick)
    view = sim.global_view()
    found[on] = (view, sim.forcefield.n_builds, sim.forcefield.n_evaluations, energies)
on, off = found[True], found[False]
if MPI.COMM_WORLD.Get_rank() == 0:
    serial = simulation(system(), md.Simulation)
    run(serial, steps, kick)
    print(json.dumps({
        "positions": bool(np.array_equal(on[0].state.positions, off[0].state.positions)),
        "velocities": bool(np.array_equal(on[0].state.velocities, off[0].state.velocities)),
        "energies": on[3] == off[3],
        "builds": [on[1], off[1]],
        "evaluations": [on[2], off[2]],
        "fused": codes.count(2), "inside": inside[0],
        "steps": steps,
        "serial": float(max(np.abs(on[0].state.positions - serial.state.positions).max(),
                            np.abs(on[0].state.velocities - serial.state.velocities).max())),
    }))
"""

#: The melt on 2 ranks: the Python calls a step between list builds makes, counted under a
#: profiler on rank 0, from one step start to the next (spans that built a list left out).
CALLS = """\
import json, sys
sys.path.insert(0, sys.argv[1])
from both_ways import simulation, system
from md.distributed import DistributedSimulation

sim = simulation(system((8, 6, 6)), DistributedSimulation)  # (benchmarks/mpi_scaling's melt)
sim.run(30)
forcefield = sim.forcefield
calls, marks = [0], []
starts = forcefield.start_step


def start_step(*args):
    marks.append((calls[0], forcefield.n_builds))
    starts(*args)


def profile(frame, event, arg):
    if event == "call":
        calls[0] += 1


forcefield.start_step = start_step
sys.setprofile(profile)
sim.run(80)
sys.setprofile(None)
counts = [b[0] - a[0] - 1 for a, b in zip(marks, marks[1:]) if a[1] == b[1]]
if sim.rank == 0:
    print(json.dumps({"counts": counts}))
"""


def _launch(tmp_path: Path, name: str, source: str, n_ranks: int, *args: str) -> dict:
    script = tmp_path / f"{name}.py"
    script.write_text(source)
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    }
    env.setdefault("MPIR_CVAR_ENABLE_HEAVY_YIELD", "1")  # (oversubscribed cores: yield)
    command = ["mpiexec", "-n", str(n_ranks), sys.executable, str(script), *args]
    done = subprocess.run(
        command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stderr + done.stdout
    return json.loads([line for line in done.stdout.splitlines() if line.startswith("{")][-1])


def _check_both_ways(found: dict) -> None:
    assert found["positions"] and found["velocities"] and found["energies"], found
    assert found["builds"][0] == found["builds"][1] and found["builds"][0] > 5, found
    assert found["evaluations"][0] == found["evaluations"][1], found
    assert found["serial"] < 1e-10, found


@needs_mpi
def test_the_fused_step_gives_the_bits_of_the_step_made_of_compute(tmp_path):
    found = _launch(tmp_path, "both_ways", BOTH_WAYS, 2, "200", "0", "1")
    _check_both_ways(found)
    # the fused step made most steps: all but the observers' (a virial wanted) and the
    # first one
    assert found["fused"] >= 0.85 * found["steps"], found


@needs_mpi
def test_a_list_outrun_inside_a_fused_step_rebuilds_as_the_step_made_of_compute(tmp_path):
    found = _launch(tmp_path, "both_ways", BOTH_WAYS, 2, "120", "50", "20")
    _check_both_ways(found)
    assert found["inside"] >= 1, found  # (the outrun inside a fused step: its rebuild path)
    assert found["fused"] >= 0.85 * found["steps"], found


@needs_mpi
@pytest.mark.slow  # two launches of 3 and 4 ranks on the 2 cores of CI
@pytest.mark.parametrize("n_ranks", [3, 4])
def test_the_fused_step_on_more_ranks_gives_the_same_bits(tmp_path, n_ranks):
    found = _launch(tmp_path, "both_ways", BOTH_WAYS, n_ranks, "150", "0", "1")
    _check_both_ways(found)
    assert found["fused"] >= 0.85 * found["steps"], found


@needs_mpi
@pytest.mark.slow  # the 1152-atom melt's kernels compile cold for it (~20 s on 2 cores)
def test_a_decomposed_step_between_builds_makes_few_python_calls(tmp_path):
    (tmp_path / "both_ways.py").write_text(BOTH_WAYS.split("\nsteps, kick =")[0])
    counts = _launch(tmp_path, "calls", CALLS, 2, str(tmp_path))["counts"]
    assert len(counts) >= 30, counts
    # (the step made of compute and the kicks, before the fused step: 75 calls)
    assert sorted(counts)[len(counts) // 2] <= 45, counts
