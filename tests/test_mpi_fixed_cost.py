"""The fixed cost of a decomposed step (issue 69): one reduction a step, the halo's sweeps
compiled and sent as persistent messages, and the decisions that used to take reductions
of their own still taken alike on every rank.

The MPI tests launch 2 real ranks with ``mpiexec`` (skipped without the ``[mpi]`` extra)
on a 384-atom melt; the kernels' test needs no MPI.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from _mpi_support import COUNTED_MELT, ROOT, needs_mpi

from md.distributed._domain_kernels import (
    add_rows,
    add_sweep,
    ghost_rows,
    pack_rows,
    pack_sweep,
)

#: A 384-atom LJ melt (two bricks of cutoff + skin along x), with the collectives and the
#: messages of every rank counted by a proxy of its communicator. Prints rank 0's JSON.
COUNTED = (
    COUNTED_MELT
    + """

if __name__ == "__main__":
    from md.distributed import DistributedSimulation

    sim = simulation(system(3), DistributedSimulation)
    counted = Counted(sim.ranks.comm)
    sim.ranks.comm = counted
    forcefield = sim.forcefield
    starts = forcefield.start_step  # (called at every step's start)
    marks = []

    def start_step(*args):
        marks.append((counted.total(COLLECTIVES), counted.counts.get("Sendrecv", 0),
                      forcefield.n_builds))
        starts(*args)

    forcefield.start_step = start_step
    sim.run(60)
    marks.append((counted.total(COLLECTIVES), counted.counts.get("Sendrecv", 0),
                  forcefield.n_builds))
    # (collectives, Sendrecv) of each step whose start, and the step before's, saw no build
    per_step = [
        (b[0] - a[0], b[1] - a[1])
        for before, a, b in zip(marks, marks[1:], marks[2:])
        if before[2] == a[2] == b[2]
    ]
    # one rank's atom moved past the list's limit between two runs: every rank rebuilds
    builds = forcefield.n_builds
    first = sim.ranks.all_objects(int(sim.state.ids[0]))
    if sim.rank == 1:
        sim.state.positions[0, 0] += 0.2
    sim.run(5)
    rebuilt = sim.ranks.all_objects(forcefield.n_builds - builds)
    view = sim.global_view()
    if sim.rank == 0:
        np.save(sys.argv[1], view.state.positions)
        print(json.dumps({"per_step": per_step, "rebuilt": rebuilt, "moved": first[1]}))
"""
)


def _launch(tmp_path: Path, source: str, n_ranks: int = 2, timeout: float = 180):
    script = tmp_path / "counted.py"
    script.write_text(source)
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    }
    env.setdefault("MPIR_CVAR_ENABLE_HEAVY_YIELD", "1")  # (oversubscribed cores: yield)
    out = tmp_path / "positions.npy"
    command = ["mpiexec", "-n", str(n_ranks), sys.executable, str(script), str(out)]
    done = subprocess.run(
        command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=timeout
    )
    return done, out


@needs_mpi
def test_a_decomposed_step_makes_one_reduction_and_no_blocking_message(tmp_path):
    """Between list builds a velocity Verlet step on 2 ranks makes exactly one collective
    call (its evaluation's reduction: energy, virial, the rebuild decision, the step's
    agreement) and no Sendrecv (the halo goes as persistent messages); it made three
    reductions (two agreements on held results, then the evaluation's) and four Sendrecv
    before. (The run's first step agrees once on its held result.) An atom one rank
    moves past the list's limit between runs makes every rank rebuild, and the run still
    follows the serial one."""
    done, out = _launch(tmp_path, COUNTED)
    assert done.returncode == 0, done.stderr + done.stdout
    found = json.loads([line for line in done.stdout.splitlines() if line.startswith("{")][-1])
    per_step = found["per_step"]
    assert len(per_step) >= 20, per_step  # most steps between builds
    # (the run's first step agrees on its held result once: the steps have shown nothing yet)
    assert per_step[0] == [2, 0] and {tuple(step) for step in per_step[1:]} == {(1, 0)}, per_step
    assert found["rebuilt"][0] >= 1 and len(set(found["rebuilt"])) == 1, found["rebuilt"]

    sys.path.insert(0, str(tmp_path))
    try:
        import counted
    finally:
        sys.path.remove(str(tmp_path))
        sys.modules.pop("counted", None)
    from md.simulation import Simulation

    alone = counted.simulation(counted.system(3), Simulation)
    alone.run(60)
    alone.state.positions[found["moved"], 0] += 0.2
    alone.run(5)
    positions = np.load(out)
    gap = np.linalg.norm(positions - alone.state.positions) / np.linalg.norm(positions)
    assert gap < 1e-10


@pytest.mark.parametrize("to_self", [False, True])
def test_compiled_sweeps_equal_the_swap_by_swap_passes(to_self):
    """A sweep's positions packed in one pass equal pack_rows swap by swap (with each
    swap's shift, a cell vector); its forces added back in one pass equal add_rows swap
    after swap in reverse, to the bit; the ghosts' rows gathered for the messages back
    are theirs."""
    rng = np.random.default_rng(5)
    n, counts = 40, (7, 5)
    positions = rng.normal(size=(n + sum(counts), 3)) * 3.0
    cell = np.array([[9.5, 0.0, 0.0], [1.25, 8.0, 0.0], [0.5, 0.75, 7.0]])
    sends = [rng.choice(n, size=c, replace=False).astype(np.int64) for c in counts]
    shifts = np.array([1.0, -1.0])
    offsets = np.array([n, n + counts[0]], dtype=np.int64)
    starts = np.array([0, counts[0], sum(counts)], dtype=np.int64)
    index = np.concatenate(sends)
    axis = 1

    expected = positions.copy()
    rows = []
    for send, shift, offset in zip(sends, shifts, offsets, strict=True):
        packed = np.empty((len(send), 3))
        pack_rows(expected, send, shift * cell[axis], packed)
        rows.append(packed)
        if to_self:
            expected[offset : offset + len(send)] = packed
    got = positions.copy()
    out = np.empty((len(index), 3))
    pack_sweep(got, index, starts, shifts, axis, cell, offsets, to_self, out)
    if to_self:
        np.testing.assert_array_equal(got, expected)
    else:
        np.testing.assert_array_equal(out, np.concatenate(rows))

    forces = rng.normal(size=positions.shape)
    back = rng.normal(size=(len(index), 3))  # the rows the other ranks send back
    expected = forces.copy()
    for j in (1, 0):
        part = slice(starts[j], starts[j + 1])
        ghosts = expected[offsets[j] : offsets[j] + counts[j]] if to_self else back[part]
        add_rows(expected, sends[j], np.ascontiguousarray(ghosts))
    got = forces.copy()
    add_sweep(got, index, starts, back, offsets, to_self)
    np.testing.assert_array_equal(got, expected)

    gathered = np.empty((sum(counts), 3))
    ghost_rows(forces, offsets, np.array(counts, dtype=np.int64), gathered)
    np.testing.assert_array_equal(gathered, forces[n:])


#: Velocity Verlet that, from step 10 on, nudges the atoms after its last force evaluation
#: of a step: the steps before showed the ranks that the step-start call finds the atoms
#: where the last evaluation left them, so the promise breaks.
NUDGED = """\
import sys
sys.path.insert(0, sys.argv[2])
from counted import simulation, system
from integrators import VelocityVerlet
from md.distributed import DistributedSimulation


class Nudged(VelocityVerlet):
    def step(self, state, forcefield):
        super().step(state, forcefield)
        if state.step >= 10:
            state.positions[:, 0] += 1e-9


sim = simulation(system(3), DistributedSimulation)
sim.integrator = Nudged(0.005)
sim.run(30)
print("no stop")
"""


@needs_mpi
def test_an_integrator_that_breaks_the_steps_pattern_ends_every_rank_with_why(tmp_path):
    """An integrator that starts moving atoms between its last evaluation of a step and the
    next step's first call, after steps that did not, ends the run on every rank (no rank
    left waiting for another) with a message that says so."""
    (tmp_path / "counted.py").write_text(COUNTED)
    script = tmp_path / "nudged.py"
    script.write_text(NUDGED)
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    }
    env.setdefault("MPIR_CVAR_ENABLE_HEAVY_YIELD", "1")
    command = ["mpiexec", "-n", "2", sys.executable, str(script), "unused", str(tmp_path)]
    done = subprocess.run(
        command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=180
    )
    assert done.returncode != 0 and "no stop" not in done.stdout
    assert "moved atoms between its last force evaluation" in done.stderr, done.stderr
