"""A decomposed run resumed from any of its checkpoints continues bit for bit.

``tests/test_mpi.py::test_a_rank_killed_ends_the_run_and_the_checkpoint_resumes_it``
failed about one run in four: the kill lands at a random step, so the run resumes from
the checkpoint of step 100, 200, 300, ... The ranks decide at each step start whether
atoms migrate from a look-ahead that measures from the last two step starts; a resume
knew neither, so after some checkpoints (step 300 of this melt) its first steps'
look-ahead crossed 1 a step earlier than the uninterrupted run's, the atoms migrated a
step early and the force sums took another order. Here every checkpoint of one run is
kept and resumed, a few steps each, in one launch of two ranks.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from md.checkpoint import read_checkpoint

ROOT = Path(__file__).resolve().parents[1]
HAVE_MPI = shutil.which("mpiexec") is not None and (
    subprocess.run([sys.executable, "-c", "import mpi4py"], capture_output=True).returncode == 0
)

#: The 384-atom LJ melt of tests/test_mpi.py, a checkpoint every 10 steps.
CONFIG = """\
units = "lj"
seed = 87287
[system]
lattice = "fcc"
cells = [6, 4, 4]
density = 0.8442
temperature = 3.0
[[potentials]]
type = "lj"
cutoff = 2.5
cutoff_mode = "shift"
[integrator]
type = "verlet"
dt = 0.005
[run]
steps = 400
skin = 0.3
thermo_every = 100
[output]
path = "melt.h5"
every = 10
velocities = true
checkpoint_every = 10
"""

#: Runs the melt whole, keeping a copy of each checkpoint (and the trajectory then), and
#: resumes each checkpoint of RESUMED for AHEAD steps; rank 0 prints the steps whose
#: resumed state differs from the whole run's checkpoint there.
SCRIPT = """\
import shutil
import numpy as np
from mpi4py import MPI
import md, md.checkpoint
from md.checkpoint import read_checkpoint

comm = MPI.COMM_WORLD

RESUMED, AHEAD = range(20, 400 - 10, 10), 10
saving = md.checkpoint.Checkpointer.__call__
def save(self, sim):  # runs on rank 0 only (with the whole system)
    saving(self, sim)
    if self.path.name == "whole.h5.ckpt":
        step = sim.state.step
        shutil.copy(self.path, f"kept{step}.ckpt")
        shutil.copy(self.path.with_name("whole.h5"), f"kept{step}.h5")
md.checkpoint.Checkpointer.__call__ = save

_, summary = md.run_config("melt.toml", output="whole.h5")
assert summary.status == "completed", summary.message
differ = []
for step in RESUMED:
    if comm.rank == 0:
        shutil.copy(f"kept{step}.h5", f"resumed{step}.h5")
        shutil.copy(f"kept{step}.ckpt", f"resumed{step}.h5.ckpt")
    comm.Barrier()
    _, summary = md.run_config(
        "melt.toml", output=f"resumed{step}.h5", steps=step + AHEAD, resume=True
    )
    assert summary.status == "completed", summary.message
    if comm.rank == 0:
        resumed = read_checkpoint(f"resumed{step}.h5.ckpt").state
        whole = read_checkpoint(f"kept{step + AHEAD}.ckpt").state
        assert resumed.step == whole.step == step + AHEAD
        same = np.array_equal(resumed.positions, whole.positions) and np.array_equal(
            resumed.velocities, whole.velocities
        )
        if not same:
            differ.append(step)
if comm.rank == 0:
    print("resumed", len(RESUMED), "differ", differ)
"""


@pytest.mark.skipif(not HAVE_MPI, reason="needs mpi4py and mpiexec (the [mpi] extra)")
def test_every_checkpoint_of_a_decomposed_run_resumes_to_its_bits(tmp_path):
    (tmp_path / "melt.toml").write_text(CONFIG)
    (tmp_path / "resume_all.py").write_text(SCRIPT)
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
        "MPIR_CVAR_ENABLE_HEAVY_YIELD": "1",  # (fewer cores than ranks: yield, not poll)
    }
    done = subprocess.run(
        ["mpiexec", "-n", "2", sys.executable, "resume_all.py"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr + done.stdout
    words = done.stdout.split()
    assert words[:2] == ["resumed", "37"], done.stdout
    assert done.stdout.strip().endswith("differ []"), done.stdout
    # the resumes continued the whole run's trajectory: its frames up to the checkpoint,
    # then the frames of the steps after it
    last = read_checkpoint(tmp_path / "resumed300.h5.ckpt")
    assert last.state.step == 310 and last.n_frames == 32 and last.last_frame_step == 310
