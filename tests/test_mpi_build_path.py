"""A decomposed run's list builds and whole-system gathers (issue 69): what a build sends
and agrees on, and what a gather carries an atom.

The MPI tests launch 2 real ranks with ``mpiexec`` (skipped without the ``[mpi]`` extra)
on a 384-atom melt (two bricks along x).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from _mpi_support import COUNTED_MELT, ROOT, needs_mpi

#: The 384-atom melt on the ranks, and a proxy of a communicator that counts its calls.
COMMON = COUNTED_MELT

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


def _launch(
    tmp_path: Path, script: str, source: str, *arguments: str, ranks: int = 2, timeout: float = 240
):
    (tmp_path / "common.py").write_text(COMMON)
    (tmp_path / script).write_text(source)
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    }
    env.setdefault("MPIR_CVAR_ENABLE_HEAVY_YIELD", "1")  # (oversubscribed cores: yield)
    command = ["mpiexec", "-n", str(ranks), sys.executable, str(tmp_path / script), *arguments]
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


#: Collective calls and point-to-point sends of every rank between step starts, over the
#: spans holding one list build (the step's evaluation, then the next start's migration,
#: ghost search and list) and none; prints rank 0's JSON and saves the positions.
SPANS = """\
import json, sys
sys.path.insert(0, sys.argv[2])
import numpy as np
from common import COLLECTIVES, Counted, simulation, system
import md.distributed.forcefield
from md.distributed import DistributedSimulation

if len(sys.argv) > 3:  # a step start's agreed stray, in skins
    md.distributed.forcefield.AGREED_STRAY = float(sys.argv[3])
sim = simulation(system(), DistributedSimulation)
sim.run(0)
counted = Counted(sim.ranks.comm)
sim.ranks.comm = counted
forcefield = sim.forcefield
starts = forcefield.start_step  # (called at every step's start, after its build)
marks = []


def start_step(*args):
    marks.append((counted.total(COLLECTIVES), counted.total({"Isend"}), forcefield.n_builds))
    starts(*args)


forcefield.start_step = start_step
sim.run(80)
marks.append((counted.total(COLLECTIVES), counted.total({"Isend"}), forcefield.n_builds))
spans = [tuple(b[k] - a[k] for k in range(3)) for a, b in zip(marks[2:], marks[3:])]
view = sim.global_view()
if sim.rank == 0:
    np.save(sys.argv[1], view.state.positions)
    print(json.dumps({
        "with_build": sorted({(c, s) for c, s, builds in spans if builds == 1}),
        "without": sorted({(c, s) for c, s, builds in spans if builds == 0}),
        "n_builds": sum(builds for _, _, builds in spans),
        "most": max(builds for _, _, builds in spans),
    }))
"""


@needs_mpi
def test_a_step_start_build_adds_no_collective_and_one_message_each_way(tmp_path):
    """From one step start to the next, a span with a list build makes one collective call,
    the step's evaluation's, as a span without one: the build's ghost search shares no
    reduction of its own (it made one before: two in all), since its shell takes a
    margin every rank agrees on. Its migration and ghost search send one message each
    (two bricks along x: both neighbours are one rank; two each before: four sends). The
    trajectory still follows the serial engine's to 1e-10."""
    out = tmp_path / "positions.npy"
    done = _launch(tmp_path, "spans.py", SPANS, str(out), str(tmp_path))
    assert done.returncode == 0, done.stderr + done.stdout
    found = _last_json(done)
    assert found["n_builds"] >= 4, found  # (the melt rebuilds every few steps)
    assert found["with_build"] == [[1, 2]], found
    assert found["without"] == [[1, 0]], found
    assert found["most"] == 1, found  # (no rank's atoms strayed past the agreed margin)
    _follows_the_serial_run(tmp_path, out, 80)


@needs_mpi
def test_atoms_straying_past_the_agreed_margin_have_every_rank_build_again(tmp_path):
    """With a step start's agreed stray made tiny (1e-6 skins), atoms laid out a step ahead
    stray past it at most builds: the rank that sees it has every rank build again at
    the step's evaluation (spans of two builds, the second with the ranks' reduction),
    and the trajectory still follows the serial engine's to 1e-10."""
    out = tmp_path / "positions.npy"
    done = _launch(tmp_path, "spans.py", SPANS, str(out), str(tmp_path), "1e-6")
    assert done.returncode == 0, done.stderr + done.stdout
    found = _last_json(done)
    assert found["most"] == 2, found
    _follows_the_serial_run(tmp_path, out, 80)


def _follows_the_serial_run(tmp_path: Path, out: Path, n_steps: int) -> None:
    sys.path.insert(0, str(tmp_path))
    try:
        import common
    finally:
        sys.path.remove(str(tmp_path))
        sys.modules.pop("common", None)
    from md.simulation import Simulation

    alone = common.simulation(common.system(), Simulation)
    alone.run(n_steps)
    positions = np.load(out)
    gap = np.linalg.norm(positions - alone.state.positions) / np.linalg.norm(positions)
    assert gap < 1e-10


def test_more_ranks_than_cores_tell_the_mpi_library_to_yield_and_others_do_not():
    """Under a launcher that started more ranks on the node than there are cores, the
    ``md`` command's entry sets the MPI libraries' yield variables before MPI starts
    (the polling waits took the cores from the ranks they waited for); with a core per
    rank, without a launcher, or where the user set the variable, nothing changes."""
    from md.distributed.ranks import YIELD_VARIABLES, yield_when_oversubscribed

    crowded = {"PMI_SIZE": "3", "MPI_LOCALNRANKS": "3"}
    assert yield_when_oversubscribed(crowded, cores=2)
    assert all(crowded[name] == value for name, value in YIELD_VARIABLES.items())
    roomy = {"PMI_SIZE": "2", "MPI_LOCALNRANKS": "2"}
    assert not yield_when_oversubscribed(roomy, cores=2) and set(roomy) == {
        "PMI_SIZE",
        "MPI_LOCALNRANKS",
    }
    alone: dict = {}
    assert not yield_when_oversubscribed(alone, cores=1) and not alone
    chosen = {"PMI_SIZE": "4", "MPI_LOCALNRANKS": "4", "MPIR_CVAR_ENABLE_HEAVY_YIELD": "0"}
    assert yield_when_oversubscribed(chosen, cores=2)
    assert chosen["MPIR_CVAR_ENABLE_HEAVY_YIELD"] == "0"  # (the user's choice kept)


def test_the_md_command_sets_the_yield_before_mpi_starts(monkeypatch):
    """``md.cli.main`` makes the setting at its entry (a process-wide one: ``import md``
    leaves the environment as it was)."""
    import md.cli

    seen = []
    monkeypatch.setattr(md.cli, "yield_when_oversubscribed", lambda: seen.append("yield"))
    monkeypatch.setattr(md.cli, "_run_command", lambda argv: seen.append("command") or 0)
    assert md.cli.main(["--version"]) == 0
    assert seen == ["yield", "command"]


#: Four bricks along x (288 atoms): between two runs, rank 1 moves an atom it owns two
#: bricks on and the next step start migrates, which loses it. Each rank writes its JSON.
LOST = """\
import json, sys
sys.path.insert(0, sys.argv[1])
import numpy as np
import md
from common import simulation
from md.distributed import DistributedSimulation

lattice = md.lattice("fcc", (8, 3, 3), density=0.8442)
velocities = np.random.default_rng(5).normal(0.0, 1.0, lattice.positions.shape)
state = md.State(positions=lattice.positions, velocities=velocities, masses=1.0,
                 box=lattice.box)
sim = simulation(state, DistributedSimulation)
sim.run(10)
if sim.rank == 1:
    sim.state.positions[0, 0] += 0.5 * sim.state.box[0]
sim.forcefield.migrate_pending = True  # (the next step start migrates, on every rank)
try:
    sim.run(20)
    row = {"rank": sim.rank, "error": None}
except Exception as error:
    row = {"rank": sim.rank, "error": str(error), "kind": type(error).__name__,
           "step": sim.state.step}
with open(f"{sys.argv[1]}/lost_{sim.rank}.json", "w") as out:  # (ranks' prints interleave)
    json.dump(row, out)
"""


@needs_mpi
def test_an_atom_lost_by_a_step_start_migration_ends_every_rank_with_why(tmp_path):
    """An atom that moved more than a brick between two builds is lost by the migration
    (four bricks along x: it lands two away); the step start's build shares that in the
    step's reduction, and every rank ends the run at the same step with the message."""
    done = _launch(tmp_path, "lost.py", LOST, str(tmp_path), ranks=4)
    rows = [json.loads(path.read_text()) for path in sorted(tmp_path.glob("lost_*.json"))]
    assert [row["rank"] for row in rows] == [0, 1, 2, 3], done.stderr + done.stdout
    for row in rows:
        assert row["error"] is not None and "moved more than a brick" in row["error"], rows
    assert len({row["step"] for row in rows}) == 1, rows
