"""The communication of a decomposed run's list builds (issue 69): a build taken at a step
start shares its outcome in the step's own reduction, so it adds no collective to its
step (two before, then one: the ghost search's); a rank whose build fails still ends every rank
with its error.

The tests launch 2 real ranks with ``mpiexec`` (skipped without the ``[mpi]`` extra) on a
384-atom melt.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from _mpi_support import COUNTED_MELT, ROOT, needs_mpi

#: A 384-atom LJ melt on the ranks, with every rank's collective calls counted by a proxy
#: of its communicator between step starts. Prints rank 0's JSON; saves the positions.
COUNTED = (
    COUNTED_MELT
    + """

if __name__ == "__main__":
    from md.distributed import DistributedSimulation

    sim = simulation(system(), DistributedSimulation)
    sim.run(0)
    counted = Counted(sim.ranks.comm)
    sim.ranks.comm = counted
    forcefield = sim.forcefield
    starts = forcefield.start_step  # (called at every step's start, after its build)
    marks = []

    def start_step(*args):
        marks.append((counted.total(COLLECTIVES), forcefield.n_builds))
        starts(*args)

    forcefield.start_step = start_step
    sim.run(80)
    marks.append((counted.total(COLLECTIVES), forcefield.n_builds))
    # collectives from one step start to the next, for the spans holding one build (the
    # step's own evaluation and the next step start's migration and build) and none
    # (the run's first steps left out: its first call agrees on its held result)
    spans = [(b[0] - a[0], b[1] - a[1]) for a, b in zip(marks[2:], marks[3:])]
    view = sim.global_view()
    if sim.rank == 0:
        np.save(sys.argv[1], view.state.positions)
        print(json.dumps({
            "with_build": sorted({n for n, builds in spans if builds == 1}),
            "without": sorted({n for n, builds in spans if builds == 0}),
            "n_builds": sum(builds for _, builds in spans),
        }))
"""
)

#: The same melt, where rank 1's list build fails at the third build of the run (a step
#: start's): every rank must end with that error. Each rank writes its JSON.
FAILING = """\
import json, sys
sys.path.insert(0, sys.argv[2])
from counted import simulation, system
from md.distributed import DistributedSimulation

sim = simulation(system(), DistributedSimulation)
forcefield = sim.forcefield
neighbor_list = forcefield.local.neighbor_list
build = neighbor_list.build
first = forcefield.n_builds


def failing(*args, **kwargs):
    if sim.rank == 1 and forcefield.n_builds == first + 2:
        raise ValueError("rank 1's list could not be built")
    return build(*args, **kwargs)


neighbor_list.build = failing
try:
    sim.run(200)
    row = {"rank": sim.rank, "error": None}
except Exception as error:
    row = {"rank": sim.rank, "error": str(error), "step": sim.state.step,
           "builds": forcefield.n_builds - first}
with open(f"{sys.argv[2]}/failing_{sim.rank}.json", "w") as out:  # (ranks' prints interleave)
    json.dump(row, out)
"""


def _launch(tmp_path: Path, script: str, *arguments: str, timeout: float = 180):
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    }
    env.setdefault("MPIR_CVAR_ENABLE_HEAVY_YIELD", "1")  # (oversubscribed cores: yield)
    command = ["mpiexec", "-n", "2", sys.executable, str(tmp_path / script), *arguments]
    return subprocess.run(
        command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=timeout
    )


def _rows(done) -> list[dict]:
    return [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]


@needs_mpi
def test_a_step_start_build_adds_one_collective_and_the_run_follows_the_serial_one(tmp_path):
    """From one step start to the next, a span with a list build (the step's evaluation,
    then the next start's migration, ghost search and list) makes one collective call:
    the evaluation's reduction, which also shares the build's outcome (and the ghost
    search's lost atoms; its shell's margin is agreed without one, see
    tests/test_mpi_build_path.py); the build made two reductions of its own before
    (three), then one (two). Spans without a build make one. The trajectory still
    follows the serial engine's to 1e-10."""
    (tmp_path / "counted.py").write_text(COUNTED)
    out = tmp_path / "positions.npy"
    done = _launch(tmp_path, "counted.py", str(out))
    assert done.returncode == 0, done.stderr + done.stdout
    found = _rows(done)[-1]
    assert found["n_builds"] >= 4, found  # (the melt rebuilds every few steps)
    assert found["with_build"] == [1], found
    assert found["without"] == [1], found

    sys.path.insert(0, str(tmp_path))
    try:
        import counted
    finally:
        sys.path.remove(str(tmp_path))
        sys.modules.pop("counted", None)
    from md.simulation import Simulation

    alone = counted.simulation(counted.system(), Simulation)
    alone.run(80)
    positions = np.load(out)
    gap = np.linalg.norm(positions - alone.state.positions) / np.linalg.norm(positions)
    assert gap < 1e-10


@needs_mpi
def test_a_rank_whose_step_start_build_fails_ends_every_rank_with_its_error(tmp_path):
    """Rank 1's list build fails at a step start (its outcome is shared by the step's
    evaluation): both ranks end the run there with rank 1's message, none left waiting,
    and no step is taken after it."""
    (tmp_path / "counted.py").write_text(COUNTED)
    (tmp_path / "failing.py").write_text(FAILING)
    done = _launch(tmp_path, "failing.py", "unused", str(tmp_path))
    rows = [json.loads(path.read_text()) for path in sorted(tmp_path.glob("failing_*.json"))]
    assert [row["rank"] for row in rows] == [0, 1], done.stderr + done.stdout
    for row in rows:
        assert row["error"] == "rank 1's list could not be built", rows
    assert rows[0]["step"] == rows[1]["step"] and rows[0]["builds"] == rows[1]["builds"], rows
