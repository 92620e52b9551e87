"""A decomposed run's list builds and whole-system gathers (issue 69): what a build sends
and agrees on, and what a gather carries an atom.

The MPI tests launch 2 real ranks with ``mpiexec`` (skipped without the ``[mpi]`` extra)
on a 384-atom melt (two bricks along x).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
HAVE_MPI = shutil.which("mpiexec") is not None and (
    subprocess.run([sys.executable, "-c", "import mpi4py"], capture_output=True).returncode == 0
)
needs_mpi = pytest.mark.skipif(not HAVE_MPI, reason="needs mpi4py and mpiexec (the [mpi] extra)")

#: The 384-atom melt on the ranks, and a proxy of a communicator that counts its calls.
COMMON = """\
import json, sys
import md
from integrators import VelocityVerlet
from potentials import LennardJones

COLLECTIVES = {"Allreduce", "Allgather", "allgather", "bcast", "gather", "Gatherv",
               "Barrier", "allreduce", "Reduce", "reduce"}
MESSAGES = {"Isend", "Send", "Sendrecv", "Mprobe", "Recv", "Irecv", "Probe"}


def system(seed=7):
    lattice = md.lattice("fcc", (6, 4, 4), density=0.8442)
    velocities = np.random.default_rng(seed).normal(0.0, 1.7, lattice.positions.shape)
    return md.State(positions=lattice.positions, velocities=velocities, masses=1.0,
                    box=lattice.box)


def simulation(state, kind, **options):
    return kind(state, [LennardJones(cutoff=2.5)], VelocityVerlet(dt=0.005), skin=0.3,
                **options)


class Counted:
    def __init__(self, comm):
        self._comm, self.counts = comm, {}

    def __getattr__(self, name):
        found = getattr(self._comm, name)
        if not callable(found):
            return found

        def counted(*args, **kwargs):
            self.counts[name] = self.counts.get(name, 0) + 1
            return found(*args, **kwargs)

        return counted

    def total(self, names):
        return sum(n for name, n in self.counts.items() if name in names)
"""

#: Gathers for a plain observer (a trajectory frame) and for one that stores the layout
#: (a checkpoint writer), recording each gather's width; prints rank 0's JSON.
GATHERS = """\
import json, sys
sys.path.insert(0, sys.argv[1])
from common import simulation, system
from md.distributed import DistributedSimulation

sim = simulation(system(), DistributedSimulation)
widths = []
gather = sim.ranks.gather_rows


def recorded(rows):
    widths.append(int(rows.shape[1]))
    return gather(rows)


sim.ranks.gather_rows = recorded
seen = {}


def frame(view):
    seen["frame"] = view.forcefield.decomposition


class Layout:
    store_layout = True

    def __call__(self, view):
        seen["layout"] = view.forcefield.decomposition
        seen["reference"] = view.forcefield.neighbor_list.reference_positions is not None


sim.run(12)
sim.observe(frame)
frame_width = widths[-1]
sim.observe(Layout())
layout_width = widths[-1]
if sim.rank == 0:
    print(json.dumps({
        "frame": frame_width,
        "layout": layout_width,
        "frame_keys": sorted(seen["frame"]),
        "layout_keys": sorted(seen["layout"]),
        "step_start": seen["layout"]["step_start"] is not None,
        "reference": seen["reference"],
    }))
"""


def _launch(tmp_path: Path, script: str, source: str, *arguments: str, timeout: float = 240):
    (tmp_path / "common.py").write_text(COMMON)
    (tmp_path / script).write_text(source)
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    }
    env.setdefault("MPIR_CVAR_ENABLE_HEAVY_YIELD", "1")  # (oversubscribed cores: yield)
    command = ["mpiexec", "-n", "2", sys.executable, str(tmp_path / script), *arguments]
    return subprocess.run(
        command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=timeout
    )


def _last_json(done) -> dict:
    return json.loads([line for line in done.stdout.splitlines() if line.startswith("{")][-1])


@needs_mpi
def test_a_frame_gathers_the_atoms_and_only_a_checkpoint_gathers_the_layout(tmp_path):
    """A trajectory frame's gather carries 7 numbers an atom (id, position, velocity); it
    carried 17 before (the build position, the rank and the last two step starts too),
    which only the checkpoint writer's gather (``store_layout``) still carries, with the
    owners, slots, step starts and build positions a resume reads."""
    done = _launch(tmp_path, "gathers.py", GATHERS, str(tmp_path))
    assert done.returncode == 0, done.stderr + done.stdout
    found = _last_json(done)
    assert found["frame"] == 7, found
    assert found["layout"] == 17, found
    for key in ("owners", "slots", "step_start", "step_before"):
        assert key in found["layout_keys"] and key not in found["frame_keys"], found
    assert found["step_start"] and found["reference"], found
