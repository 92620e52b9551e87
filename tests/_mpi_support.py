"""What the tests that launch real MPI ranks share: whether ``mpiexec`` and mpi4py are
here (``needs_mpi`` skips without the ``[mpi]`` extra), the repository root for the ranks'
``PYTHONPATH``, :func:`rank_zero_json` (a script on 2 ranks, rank 0's JSON line back), and
``COUNTED_MELT``: the source of a module the ranks import, with the
384-atom LJ melt (two bricks along x on 2 ranks), its simulation and ``Counted``, a proxy
of a communicator that counts its calls by name.
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


def rank_zero_json(folder: Path, source: str, n_ranks: int = 2, timeout: float = 600) -> dict:
    """Run ``source`` as ``folder/script.py`` on ``n_ranks`` ranks (this checkout's packages
    first on ``PYTHONPATH``; MPICH's waiting ranks yield the shared cores) and return the
    last line of its output that is a JSON object (rank 0 prints it)."""
    script = folder / "script.py"
    script.write_text(source)
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    }
    env.setdefault("MPIR_CVAR_ENABLE_HEAVY_YIELD", "1")  # (the 2 cores of CI are shared)
    done = subprocess.run(
        ["mpiexec", "-n", str(n_ranks), sys.executable, str(script)],
        cwd=folder,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    assert done.returncode == 0, done.stderr + done.stdout
    return json.loads([line for line in done.stdout.splitlines() if line.startswith("{")][-1])


#: A module's source (written next to a rank's script): ``system(seed)``, ``simulation``,
#: ``Counted(comm)`` with ``counts`` per call name and ``total(names)``, and the names of
#: the collective and the point-to-point calls.
COUNTED_MELT = """\
import json, sys
import numpy as np
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
