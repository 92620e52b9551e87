"""A lean decomposed step and list build (issue 69): the Python a rank runs around its
compiled calls, counted on rank 0 of 2 real ranks (``mpiexec``, skipped without the
``[mpi]`` extra) on the 384-atom melt of ``_mpi_support.COUNTED_MELT``.

A step between builds (``DistributedForceField.verlet_step``) takes what a build fixes
(the halo's plan, the owned rows, the cell matrix, the compiled calls' arguments) from
what it prepared once after the build, compares the held positions inside its first
compiled call and writes the reduction's values inside its second. A step start's build
(``DistributedForceField.rebuild`` with its migration, the ghost search and the layout)
receives its messages into memory the Domain keeps, keeps the local system's State (two,
alternating as its arrays do) and its cell's copies, and calls no comprehension or
property where a loop or a length does. The trajectories are the bits of the path each
replaced (the step made of ``compute``; messages received into fresh arrays, a fresh
local State a build).
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

import md
from md.neighbors import NeighborList

#: One launch for both tests. First, Python calls on rank 0: from one step start to the
#: next (spans without a build), and inside each step start's ``rebuild`` (the list
#: search's own calls, another module's, left out); the local State and the cell's copies
#: across builds. Then the melt run again with the paths this code replaced (the step made
#: of compute and the kicks; each build's messages received into fresh arrays and a fresh
#: local State); rank 0 compares the two runs and the serial one.
SCRIPT = """\
import json, sys
sys.path.insert(0, sys.argv[1])
import numpy as np
import md
from common import simulation, system
from md.distributed import DistributedForceField, DistributedSimulation
from md.distributed.halo import Domain
from md.state import State

STEPS = 150
sim = simulation(system(), DistributedSimulation)
sim.run(30)  # (no observer: an observer's virial has every step made of compute)
forcefield, domain = sim.forcefield, sim.forcefield.domain
nl = forcefield.local.neighbor_list
calls, marks, builds, pausing = [0], [], [], [False]
states, cells = [], []


def profile(frame, event, arg):
    if event == "call" and not pausing[0]:
        calls[0] += 1


starts, rebuild, search = forcefield.start_step, forcefield.rebuild, nl.build


def start_step(*args):
    marks.append((calls[0], forcefield.n_builds))
    starts(*args)


def counted_rebuild(*args, **kwargs):
    before = calls[0]
    try:
        return rebuild(*args, **kwargs)
    finally:
        if kwargs.get("dt") is not None:  # (a step start's build, migration included)
            builds.append(calls[0] - before - 1)
        states.append(id(domain.local_state))
        cells.append(id(forcefield.reference_cell))


def uncounted_search(*args, **kwargs):
    pausing[0] = True
    try:
        return search(*args, **kwargs)
    finally:
        pausing[0] = False


forcefield.start_step, forcefield.rebuild, nl.build = start_step, counted_rebuild, uncounted_search
sys.setprofile(profile)
sim.run(STEPS - 30)
sys.setprofile(None)
steps = [b[0] - a[0] - 1 for a, b in zip(marks, marks[1:]) if a[1] == b[1]]
energies = {"lean": sim.thermo()["total_energy"]}
found = {"lean": (sim.global_view(), forcefield.n_builds)}

build = Domain.build


def fresh_exchange(self, rows, dest, source, tag, name):
    return self.ranks.exchange_rows(rows, dest, source, tag)


def fresh_build(self, *args, **kwargs):
    unshared = build(self, *args, **kwargs)
    local = self.local_state  # (a fresh State of the same arrays, as before)
    fresh = State.adopting(local.positions, local.types, local.box, local.pbc,
                           local.type_names)
    fresh.tilt = local.tilt.copy()
    self.local_state = fresh
    return unshared


DistributedForceField.verlet_step = lambda self, *args: 0
Domain.exchange_kept, Domain.build = fresh_exchange, fresh_build
again = simulation(system(), DistributedSimulation)
again.run(STEPS)
energies["before"] = again.thermo()["total_energy"]
found["before"] = (again.global_view(), again.forcefield.n_builds)
if sim.rank == 0:
    serial = simulation(system(), md.Simulation)
    serial.run(STEPS)
    a, b = found["lean"][0].state, found["before"][0].state
    print(json.dumps({
        "steps": steps, "builds": builds, "states": len(set(states)), "n_states": len(states),
        "cells": len(set(cells)),
        "positions": bool(np.array_equal(a.positions, b.positions)),
        "velocities": bool(np.array_equal(a.velocities, b.velocities)),
        "energies": energies["lean"] == energies["before"],
        "n_builds": [found["lean"][1], found["before"][1]],
        "serial": float(max(np.abs(a.positions - serial.state.positions).max(),
                            np.abs(a.velocities - serial.state.velocities).max())),
    }))
"""


def _launch(tmp_path: Path, source: str, *args: str) -> dict:
    (tmp_path / "common.py").write_text(COUNTED_MELT)
    script = tmp_path / "script.py"
    script.write_text(source)
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    }
    env.setdefault("MPIR_CVAR_ENABLE_HEAVY_YIELD", "1")  # (the 2 cores of CI are shared)
    command = ["mpiexec", "-n", "2", sys.executable, str(script), str(tmp_path), *args]
    done = subprocess.run(
        command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stderr + done.stdout
    return json.loads([line for line in done.stdout.splitlines() if line.startswith("{")][-1])


@pytest.fixture(scope="module")
def launched(tmp_path_factory) -> dict:
    """The one launch's findings (:data:`SCRIPT`)."""
    return _launch(tmp_path_factory.mktemp("lean"), SCRIPT)


@needs_mpi
def test_a_step_and_a_build_make_few_python_calls(launched):
    """Rank 0's Python calls (medians): a step between builds at most 27 (46 before, from
    one step start to the next; the pair frame's kept call over atom indices checks the
    list's arrays in one call, six before), a step start's build at most 80 besides the
    list search (108 before); its local State is one of two kept (a fresh one a build
    before), and the cell's copies are kept while the cell is (fresh ones a build before)."""
    found = launched
    steps, builds = sorted(found["steps"]), sorted(found["builds"])
    assert len(steps) >= 60 and len(builds) >= 8, found
    assert steps[len(steps) // 2] <= 27, found
    assert builds[len(builds) // 2] <= 80, found
    assert found["states"] <= 2 < found["n_states"], found
    assert found["cells"] == 1, found


@needs_mpi
def test_the_lean_paths_give_the_bits_of_the_paths_they_replaced(launched):
    """The trajectory (positions, velocities, the final total energy, builds) is the same bits as
    with the step made of ``compute`` and each build's messages received into fresh arrays
    and its local State made afresh; within 1e-10 of the serial run."""
    found = launched
    assert found["positions"] and found["velocities"] and found["energies"], found
    assert found["n_builds"][0] == found["n_builds"][1] and found["n_builds"][0] > 5, found
    assert found["serial"] < 1e-10, found


def test_the_list_gives_its_arrays_over_atom_indices_in_one_call():
    """``NeighborList.atom_lists()`` is ``(starts, neighbors)``, the same arrays, for a list
    over atom indices (O(N^2)) and one built by cells, after a build and after the next;
    one Python call where the properties made three each."""
    calls = []

    def profile(frame, event, arg):
        if event == "call":
            calls.append(frame.f_code.co_name)

    for cells, n_cells in (((3, 3, 3), "few"), ((6, 6, 6), "many")):
        lattice = md.lattice("fcc", cells, density=0.8442)
        state = md.State(positions=lattice.positions, masses=1.0, box=lattice.box)
        nl = NeighborList(2.5, 0.3)
        for _ in range(2):
            nl.build(state)
            first = nl.atom_lists()
            assert first[0] is nl.starts and first[1] is nl.neighbors, n_cells
            calls.clear()
            sys.setprofile(profile)
            again = nl.atom_lists()
            sys.setprofile(None)
            assert again[0] is first[0] and again[1] is first[1], n_cells
            assert calls == ["atom_lists"], (n_cells, calls)
            state.positions[:] += np.random.default_rng(1).normal(0.0, 0.2, state.positions.shape)
