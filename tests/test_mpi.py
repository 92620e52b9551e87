"""One system over several MPI ranks (md.distributed): ``mpiexec -n P md run``.

Each test launches real ranks with ``mpiexec`` (the ``[mpi]`` extra: mpi4py and
the mpich wheel) and is skipped without them. The systems are small, so that a
launch takes seconds even with the ranks oversubscribed on two cores.
"""

from __future__ import annotations

import importlib
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from _mpi_support import ROOT, needs_mpi

import md
from md.checkpoint import read_checkpoint

#: The LAMMPS LJ melt (fcc at density 0.8442 started at T = 3), 384 atoms: the cell is
#: 10.1 x 6.7 x 6.7, wide enough for 3 bricks along x and 2 x 2 of cutoff + skin = 2.8.
MELT = """\
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
type = "{integrator}"
dt = 0.005
{extra}
[run]
steps = {steps}
skin = 0.3
thermo_every = 100
{run_extra}
[output]
path = "melt.h5"
every = 100
velocities = true
"""


def write_config(
    folder: Path,
    name: str = "melt.toml",
    integrator: str = "verlet",
    extra: str = "",
    steps: int = 500,
    run_extra: str = "",
) -> Path:
    path = folder / name
    path.write_text(
        MELT.format(integrator=integrator, extra=extra, steps=steps, run_extra=run_extra)
    )
    return path


def launch(n_ranks: int, *args: str, cwd: Path, timeout: float = 240):
    """Run ``python -m md.cli ARGS`` (or ``python ARGS`` when the first is a script) on
    ``n_ranks`` MPI ranks with this checkout first on the path."""
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    }
    # MPICH's ranks poll while they wait; on a machine with fewer cores than ranks they
    # would take the cores from the rank they wait for: yield instead.
    env.setdefault("MPIR_CVAR_ENABLE_HEAVY_YIELD", "1")
    command = ["mpiexec", "-n", str(n_ranks), sys.executable]
    command += list(args) if args[0].endswith(".py") else ["-m", "md.cli", *args]
    return subprocess.run(
        command, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout
    )


def unwrapped(path: Path, frame: int = -1) -> np.ndarray:
    """Positions of a frame of an H5MD file, unwrapped with their images."""
    with h5py.File(path, "r") as f:
        group = f["particles/trajectory"]
        edges = group["box/edges/value"][frame]
        images = group["image/value"][frame]
        shifts = images @ edges if edges.ndim == 2 else images * edges  # (3, 3): rows a, b, c
        return group["position/value"][frame] + shifts


def relative_gap(path: Path, reference: Path, frame: int = -1) -> float:
    """|x - x_ref| / |x_ref| over all positions of a frame."""
    expected = unwrapped(reference, frame)
    return float(np.linalg.norm(unwrapped(path, frame) - expected) / np.linalg.norm(expected))


def launch_script(tmp_path: Path, name: str, source: str, n_ranks: int, timeout: float):
    """Write ``source`` as ``NAME.py``, run it on ``n_ranks`` ranks with the path of a
    ``positions.npy`` to write, and import it here (for its one-process twin). Returns
    (the finished launch, its stdout's words, the module, the saved positions)."""
    script = tmp_path / f"{name}.py"
    script.write_text(source)
    out = tmp_path / "positions.npy"
    done = launch(n_ranks, str(script), str(out), cwd=tmp_path, timeout=timeout)
    assert done.returncode == 0, done.stderr + done.stdout
    sys.path.insert(0, str(tmp_path))
    try:
        module = importlib.import_module(name)
    finally:
        sys.path.remove(str(tmp_path))
        sys.modules.pop(name, None)
    return done, done.stdout.split(), module, np.load(out)


def gap_to(positions: np.ndarray, alone) -> float:
    """|x - x_serial| / |x_serial| against a one-process Simulation ``alone``."""
    return float(
        np.linalg.norm(positions - alone.state.positions) / np.linalg.norm(alone.state.positions)
    )


@pytest.fixture(scope="module")
def serial(tmp_path_factory):
    """The melt run on one process, as the reference."""
    folder = tmp_path_factory.mktemp("serial")
    config = write_config(folder)
    sim, summary = md.run_config(config, output=folder / "serial.h5")
    assert summary.status == "completed"
    (folder / "builds").write_text(str(sim.forcefield.neighbor_list.n_builds))
    return folder / "serial.h5"


@needs_mpi
@pytest.mark.parametrize("n_ranks", [2, 3, 4])
def test_lj_melt_over_ranks_follows_the_serial_run(serial, tmp_path, n_ranks):
    config = write_config(tmp_path)
    out = tmp_path / "out.h5"
    done = launch(n_ranks, "run", str(config), "--output", str(out), "--no-progress", cwd=tmp_path)
    assert done.returncode == 0, done.stderr + done.stdout
    # rank 0 alone speaks for the run
    assert done.stdout.count("md run: 384 atoms over") == 1, done.stdout
    assert done.stdout.count("Wrote 6 frames") == 1
    with h5py.File(serial, "r") as a, h5py.File(out, "r") as b:
        for name in ("position/step", "species", "mass"):
            np.testing.assert_array_equal(
                a[f"particles/trajectory/{name}"][()], b[f"particles/trajectory/{name}"][()]
            )
        # frame 0, before any force: the same atoms in the same order, bit for bit
        for name in ("position/value", "velocity/value", "image/value"):
            np.testing.assert_array_equal(
                a[f"particles/trajectory/{name}"][0], b[f"particles/trajectory/{name}"][0]
            )
        assert b["parameters"].attrs["mpi_ranks"] == n_ranks
        for name in ("potential_energy", "total_energy", "pressure"):
            np.testing.assert_allclose(
                b[f"observables/{name}/value"][()], a[f"observables/{name}/value"][()], rtol=1e-9
            )
    # After 500 steps of a chaotic liquid only the order of the force sums differs:
    # round-off, amplified by the dynamics, stays below 1e-10 of the positions.
    reference, positions = unwrapped(serial), unwrapped(out)
    relative = np.linalg.norm(positions - reference) / np.linalg.norm(reference)
    assert relative < 1e-10
    assert relative > 0.0 or n_ranks == 1  # the ranks really summed in another order
    sections = summary_sections(done.stdout)
    assert sections["comm"] > 0.0
    assert_sections_within_wall(sections, loop_time(done.stdout), tolerance=5e-4)
    # Rebuilds taken at step starts, laid out where the step takes the atoms, come as
    # often as one process's (77 here; a list built where the atoms were: 100).
    builds = int(done.stdout.split("Neighbour list builds: ")[1].split()[0])
    alone = int((serial.parent / "builds").read_text())
    assert abs(builds - alone) <= 0.05 * alone + 2


def summary_sections(stdout: str) -> dict[str, float]:
    """The seconds of each row of the run summary's section table."""
    table = stdout.split("Section")[1].split("Neighbour list builds")[0]
    rows = [line.split() for line in table.splitlines()[1:] if line.strip()]
    return {row[0]: float(row[1]) for row in rows}


def loop_time(stdout: str) -> float:
    return float(stdout.split("Loop time ")[1].split(" s ")[0])


def assert_sections_within_wall(sections: dict, wall: float, tolerance: float = 0.0) -> None:
    """The sections (comm included; "other" is the rest) are disjoint: they add up to at
    most the loop's wall time, and none is negative."""
    counted = {name: seconds for name, seconds in sections.items() if name != "other"}
    assert set(counted) == {"force", "neighbor", "integrate", "output", "comm"}, counted
    assert min(counted.values()) >= -tolerance, counted
    assert sum(counted.values()) <= wall + tolerance, (counted, wall)


@needs_mpi
def test_run_config_under_mpiexec_gathers_one_file(serial, tmp_path):
    config = write_config(tmp_path)
    script = tmp_path / "drive.py"
    script.write_text(
        "import sys, md\n"
        "sim, summary = md.run_config(sys.argv[1], output=sys.argv[2])\n"
        "assert summary.status == 'completed', summary.message\n"
        "with open(f'rank{sim.rank}.txt', 'w') as f:\n"
        "    print(sim.ranks.n_ranks, sim.state.n_atoms, *sim.grid.shape, file=f)\n"
        "    print(summary.wall, *(f'{k}={v!r}' for k, v in summary.timings.items()), file=f)\n"
    )
    out = tmp_path / "lib.h5"
    done = launch(2, str(script), str(config), str(out), cwd=tmp_path)
    assert done.returncode == 0, done.stderr + done.stdout
    texts = [(tmp_path / f"rank{r}.txt").read_text().splitlines() for r in range(2)]
    lines = [text[0].split() for text in texts]
    owned = [int(line[1]) for line in lines]
    for text in texts:  # every rank's sections, comm its own, within its wall time
        wall, *timings = text[1].split()
        sections = {k: float(v) for k, v in (item.split("=") for item in timings)}
        assert sections["comm"] > 0.0
        assert_sections_within_wall(sections, float(wall))
    assert all(line[0] == "2" and line[2:] == ["2", "1", "1"] for line in lines)
    assert sum(owned) == 384 and min(owned) > 0  # each rank holds its brick's atoms
    relative = np.linalg.norm(unwrapped(out) - unwrapped(serial)) / np.linalg.norm(
        unwrapped(serial)
    )
    assert relative < 1e-10


#: Atoms in the first third of a cell three times the lattice's length along x: on three
#: bricks along x the other two ranks own no atoms (and only ghosts, or nothing).
VACUUM = (
    "import sys\n"
    "import numpy as np\n"
    "import md\n"
    "from integrators import VelocityVerlet\n"
    "from potentials import LennardJones\n"
    "def system():\n"
    "    lattice = md.lattice('fcc', (4, 4, 4), density=0.8442)\n"
    "    box = lattice.box.copy()\n"
    "    box[0] *= 3.0\n"
    "    velocities = np.random.default_rng(7).normal(0.0, 1.0, lattice.positions.shape)\n"
    "    return md.State(positions=lattice.positions, velocities=velocities, masses=1.0,\n"
    "                    box=box)\n"
    "def simulation(state, **options):\n"
    "    return options.pop('kind')(state, [LennardJones(cutoff=2.5)],\n"
    "                               VelocityVerlet(dt=0.002), skin=0.3, **options)\n"
    "if __name__ == '__main__':\n"
    "    from md.distributed import DistributedSimulation\n"
    "    sim = simulation(system(), kind=DistributedSimulation, decomposition=[3, 1, 1])\n"
    "    owned = sim.ranks.all_objects(sim.state.n_atoms)\n"
    "    sim.run(40)\n"
    "    energy = sim.thermo()['potential_energy']\n"
    "    view = sim.global_view()\n"
    "    if sim.rank == 0:\n"
    "        np.save(sys.argv[1], view.state.positions)\n"
    "        print('owned', *owned, 'energy', repr(energy))\n"
)


@needs_mpi
def test_ranks_that_own_no_atoms_keep_step_with_the_others(tmp_path):
    """Two of three bricks empty (vacuum): every evaluation, exchange and reduction is still
    taken by every rank together (a rank with no atoms once saw its positions 'unchanged'
    and skipped them: a hang), and the run follows the serial one."""
    done, words, vacuum, positions = launch_script(tmp_path, "vacuum", VACUUM, 3, timeout=120)
    assert words[:4] == ["owned", "256", "0", "0"], done.stdout
    from md.simulation import Simulation

    alone = vacuum.simulation(vacuum.system(), kind=Simulation)
    alone.run(40)
    assert float(words[5]) == pytest.approx(alone.thermo()["potential_energy"], rel=1e-12)
    assert gap_to(positions, alone) < 1e-12


PROBE = (
    "import sys, md\n"
    "from md.simulation import Simulation\n"
    "sim, summary = md.run_config(sys.argv[1], output=sys.argv[2], steps=int(sys.argv[3]))\n"
    "assert summary.status == 'completed'\n"
    "assert type(sim) is Simulation, type(sim)\n"
    "assert 'mpi4py' not in sys.modules\n"
    "print('serial', sim.state.n_atoms)\n"
)


def test_one_process_imports_no_mpi(tmp_path):
    """Without a launcher a run is the serial engine and never loads mpi4py."""
    config = write_config(tmp_path)
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("PMI_SIZE", "OMPI_COMM_WORLD_SIZE", "SLURM_STEP_NUM_TASKS")
    }
    env["PYTHONPATH"] = str(ROOT)
    done = subprocess.run(
        [sys.executable, "-c", PROBE, str(config), str(tmp_path / "a.h5"), "20"],
        env=env,
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert done.returncode == 0, done.stderr
    assert "serial 384" in done.stdout


@needs_mpi
def test_one_rank_under_mpiexec_is_the_serial_run(serial, tmp_path):
    config = write_config(tmp_path)
    script = tmp_path / "probe.py"
    script.write_text(PROBE)
    out = tmp_path / "a.h5"
    done = launch(1, str(script), str(config), str(out), "500", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert "serial 384" in done.stdout
    np.testing.assert_array_equal(unwrapped(out), unwrapped(serial))  # bit for bit


def test_launched_without_mpi4py_is_refused(tmp_path):
    """A launcher's several processes with no mpi4py: a clear refusal, exit 2, no output."""
    config = write_config(tmp_path)
    code = (
        "import sys\n"
        "sys.modules['mpi4py'] = None  # as if it were not installed\n"
        "from md.cli import main\n"
        "sys.exit(main(sys.argv[1:]))\n"
    )
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PMI_SIZE": "2", "PMI_RANK": "0"}
    out = tmp_path / "x.h5"
    done = subprocess.run(
        [sys.executable, "-c", code, "run", str(config), "--output", str(out)],
        env=env,
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert done.returncode == 2, done.stderr
    assert "mpi4py is not installed" in done.stderr
    assert not out.exists()


# ------------------------------------------------------------------ refusals
def _refused(tmp_path, n_ranks: int, config: Path) -> str:
    out = tmp_path / "refused.h5"
    done = launch(n_ranks, "run", str(config), "--output", str(out), "--no-progress", cwd=tmp_path)
    assert done.returncode == 2, done.stderr + done.stdout
    assert not out.exists() and not Path(str(out) + ".ckpt").exists()
    assert done.stderr.count("md: error:") == 1, done.stderr  # rank 0 alone reports
    return done.stderr


@needs_mpi
def test_a_list_looked_at_every_n_steps_is_refused_under_ranks(tmp_path):
    """``[run] neighbor_every``/``neighbor_check`` are for one process: refused before
    anything is written, naming the keys."""
    config = write_config(tmp_path, run_extra="neighbor_every = 10\nneighbor_check = false")
    message = _refused(tmp_path, 2, config)
    assert "neighbor_every and neighbor_check" in message and "one rank" in message


@needs_mpi
def test_bricks_thinner_than_the_shell_are_refused(tmp_path):
    config = write_config(tmp_path, run_extra="decomposition = [4, 1, 1]")
    message = _refused(tmp_path, 4, config)
    # 10.08 / 4 = 2.52 < 2.8; the largest grid that fits is 3 x 2 x 2
    assert "[run] decomposition" in message
    assert "thinner than cutoff + skin = 2.8" in message
    assert "[3, 2, 2] (12 ranks)" in message


@needs_mpi
@pytest.mark.slow  # several launches of up to 4 ranks
def test_too_many_ranks_for_the_cell_are_refused(tmp_path):
    config = write_config(tmp_path)
    message = _refused(tmp_path, 5, config)  # 5 bricks along any axis are too thin
    assert "5 ranks cannot share this cell" in message
    assert "[3, 2, 2]" in message


@needs_mpi
@pytest.mark.parametrize(
    ("integrator", "extra", "expected"),
    [
        ("implicit_euler", "", "does not run decomposed over MPI ranks"),
        pytest.param(
            "implicit_midpoint",
            "",
            "does not run decomposed over MPI ranks",
            marks=pytest.mark.slow,
        ),
        pytest.param(
            "rattle",
            "[integrator.constraints]\nbonds = [[0, 1]]",
            "rigid bonds",
            marks=pytest.mark.slow,
        ),
    ],
)
def test_undistributed_integrators_are_refused(tmp_path, integrator, extra, expected):
    config = write_config(tmp_path, integrator=integrator, extra=extra)
    message = _refused(tmp_path, 2, config)
    assert expected in message
    assert "one rank" in message


# ------------------------------------------------------- beyond the LJ melt
#: A bead-spring melt (FENE + WCA, Kremer-Grest, with cosine angles) relaxed by FIRE,
#: then in a Langevin bath: bonds and angles cross the bricks, the minimiser migrates
#: atoms, and the noise is keyed by (seed, step, atom id), so every rank count draws the
#: same kicks.
POLYMER = """\
units = "lj"
seed = 7
[system]
polymer = "melt"
chains = 20
chain_length = 25
density = 0.85
bond_length = 0.97
temperature = 1.0
[[potentials]]
type = "lj"
cutoff = 1.122462048309373
cutoff_mode = "shift"
[[potentials]]
type = "fene"
bonds = "system"
k = 30.0
r_max = 1.5
[[potentials]]
type = "angle_cosine"
angles = "system"
k = 2.0
[minimize]
fmax = 1.0
max_steps = 2000
max_force = 100.0
[integrator]
type = "langevin"
dt = 0.005
temperature = 1.0
friction = 0.5
[run]
steps = 500
thermo_every = 100
[output]
path = "polymer.h5"
every = 100
"""


def _serial_and_ranks(tmp_path, text: str, n_ranks: int) -> tuple[Path, Path, str]:
    config = tmp_path / "config.toml"
    config.write_text(text)
    _, summary = md.run_config(config, output=tmp_path / "serial.h5")
    assert summary.status == "completed", summary.message
    out = tmp_path / "ranks.h5"
    done = launch(n_ranks, "run", str(config), "--output", str(out), "--no-progress", cwd=tmp_path)
    assert done.returncode == 0, done.stderr + done.stdout
    return tmp_path / "serial.h5", out, done.stdout


@needs_mpi
@pytest.mark.slow  # keeps the default suite within its 10 minutes (each rank compiles, cold)
def test_mixed_precision_over_ranks_follows_the_serial_mixed_run(tmp_path):
    """Each rank's pair loops run in float32 too: 2 ranks follow the serial mixed run to
    float32 round-off grown over 100 steps, and both differ from the double run by more."""
    config = write_config(tmp_path, steps=100, run_extra='precision = "mixed"')
    serial_out, out, stdout = _serial_and_ranks(tmp_path, config.read_text(), 2)
    assert "over 2 MPI ranks" in stdout and "mixed precision" in stdout
    double = tmp_path / "double.toml"
    double.write_text(config.read_text().replace('precision = "mixed"', ""))
    _, summary = md.run_config(double, output=tmp_path / "double.h5")
    assert summary.status == "completed"
    gap = relative_gap(out, serial_out)
    assert gap < 1e-5, gap
    assert relative_gap(tmp_path / "double.h5", serial_out) > 1e-9


@needs_mpi
@pytest.mark.slow  # keeps the default suite within its 10 minutes
def test_polymer_melt_over_ranks_follows_the_serial_run(tmp_path):
    serial_out, out, stdout = _serial_and_ranks(tmp_path, POLYMER, 3)
    assert "over 3 MPI ranks" in stdout
    # the minimiser took the same path (its step count is printed)
    with h5py.File(serial_out, "r") as a, h5py.File(out, "r") as b:
        for name in ("fene", "angle_cosine"):
            np.testing.assert_array_equal(
                a[f"connectivity/{name}"][()], b[f"connectivity/{name}"][()]
            )
    reference, positions = unwrapped(serial_out), unwrapped(out)
    assert np.linalg.norm(positions - reference) / np.linalg.norm(reference) < 1e-10
    np.testing.assert_allclose(unwrapped(out, 0), unwrapped(serial_out, 0), rtol=0, atol=1e-9)


@needs_mpi
@pytest.mark.parametrize(
    "couple",
    [
        "isotropic",
        # the cell tilts from the first step on: the ranks' y and z axes, periodic in
        # their local systems while the cell is orthorhombic, need explicit images then
        pytest.param("triclinic", marks=pytest.mark.slow),
    ],
)
def test_npt_volume_follows_the_serial_run(tmp_path, couple):
    """c_rescale barostat with Langevin, 200 steps: the bricks follow the cell."""
    text = MELT.format(
        integrator="langevin",
        extra="temperature = 1.0\nfriction = 1.0",
        steps=200,
        run_extra="",
    ).replace(
        "[run]",
        '[barostat]\ntype = "c_rescale"\npressure = 1.0\ntau = 1.0\n'
        f'compressibility = 0.1\ncouple = "{couple}"\n[run]',
    )
    serial_out, out, _ = _serial_and_ranks(tmp_path, text, 2)
    with h5py.File(serial_out, "r") as a, h5py.File(out, "r") as b:
        volume = a["observables/volume/value"][()]
        assert volume[-1] > 1.05 * volume[0]  # the cell really moved (P starts near 5)
        np.testing.assert_allclose(b["observables/volume/value"][()], volume, rtol=1e-12)
        if couple == "triclinic":
            tilt = a["particles/trajectory/box/edges/value"][()][:, 1, 0]  # b's x: xy
            assert np.all(tilt[1:] != 0.0)
    reference = unwrapped(serial_out)
    assert np.linalg.norm(unwrapped(out) - reference) / np.linalg.norm(reference) < 1e-10


@needs_mpi
@pytest.mark.slow  # several launches of up to 4 ranks
def test_checkpoint_resumes_on_another_rank_count(serial, tmp_path):
    """Half the melt on 2 ranks, the rest on 3 ranks and, from the same checkpoint, on
    2 ranks again (bit for bit with an uninterrupted 2-rank run) and on one process."""
    config = write_config(tmp_path)
    first = tmp_path / "first.h5"
    done = launch(
        2,
        "run",
        str(config),
        "--output",
        str(first),
        "--steps",
        "250",
        "--no-progress",
        cwd=tmp_path,
    )
    assert done.returncode == 0, done.stderr
    copies = {}
    for name in ("two", "three", "one"):
        copies[name] = tmp_path / f"{name}.h5"
        shutil.copy(first, copies[name])
        shutil.copy(str(first) + ".ckpt", str(copies[name]) + ".ckpt")
    for name, n_ranks in (("two", 2), ("three", 3)):
        done = launch(
            n_ranks,
            "run",
            str(config),
            "--output",
            str(copies[name]),
            "--resume",
            "--no-progress",
            cwd=tmp_path,
        )
        assert done.returncode == 0, done.stderr
    _, summary = md.run_config(config, output=copies["one"], resume=True)
    assert summary.status == "completed"
    whole = tmp_path / "whole.h5"
    done = launch(2, "run", str(config), "--output", str(whole), "--no-progress", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    np.testing.assert_array_equal(unwrapped(copies["two"]), unwrapped(whole))
    reference = unwrapped(serial)
    for name in ("three", "one"):
        with h5py.File(copies[name], "r") as f:
            assert list(f["particles/trajectory/position/step"][()]) == [0, 100, 200, 300, 400, 500]
        relative = np.linalg.norm(unwrapped(copies[name]) - reference) / np.linalg.norm(reference)
        assert relative < 1e-10


@needs_mpi
def test_a_blow_up_stops_every_rank_with_the_serial_message(tmp_path):
    """dt = 0.04 blows the hot melt up at step 2: every rank stops, exit 1 as in serial,
    the same message (global atom id and step), the step-0 checkpoint intact."""
    config = write_config(tmp_path)
    config.write_text(config.read_text().replace("dt = 0.005", "dt = 0.04"))
    out = tmp_path / "blow.h5"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    serial_run = subprocess.run(
        [
            sys.executable,
            "-m",
            "md.cli",
            "run",
            str(config),
            "--output",
            str(tmp_path / "s.h5"),
            "--no-progress",
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert serial_run.returncode == 1
    done = launch(3, "run", str(config), "--output", str(out), "--no-progress", cwd=tmp_path)
    assert done.returncode == 1, done.stderr
    message = [line for line in done.stderr.splitlines() if line.startswith("md: error:")]
    expected = [line for line in serial_run.stderr.splitlines() if line.startswith("md: error:")]
    assert len(message) == 1 and "step 2: atom" in message[0]
    assert message[0].replace(str(out), "X") == expected[0].replace(str(tmp_path / "s.h5"), "X")
    saved = read_checkpoint(str(out) + ".ckpt")
    assert saved.state.step == 0 and saved.state.n_atoms == 384


@needs_mpi
@pytest.mark.slow  # several launches of up to 4 ranks
@pytest.mark.parametrize(
    "shear, n_ranks, bricks",
    [
        ((0.3, 0.1, 0.2), 4, "2 x 1 x 2"),  # y's vector leans along cut x: explicit images
        ((0.0, 0.0, 0.25), 2, "2 x 1 x 1"),  # y and z stay periodic on each rank, tilted yz
    ],
)
def test_tilted_cell_over_ranks_follows_the_serial_run(tmp_path, shear, n_ranks, bricks):
    """A triclinic melt cut into bricks: ghosts cross tilted faces, or (2 x 1 x 1 with
    only yz tilted) each rank's cell list finds the y and z images itself, tilted.

    The runs differ only in the order of the force sums: at step 100 by round-off
    (1e-15 of the positions), then the chaotic liquid amplifies it about 20 times
    per 100 steps (the same rate as for the orthorhombic melt), to about 2e-10 at
    step 500; a missed or doubled pair would show at once.
    """
    text = MELT.format(integrator="verlet", extra="", steps=500, run_extra="").replace(
        "temperature = 3.0", f"temperature = 3.0\nshear = {list(shear)}"
    )
    serial_out, out, stdout = _serial_and_ranks(tmp_path, text, n_ranks)
    assert f"bricks {bricks}" in stdout
    gaps = [relative_gap(out, serial_out, frame) for frame in range(6)]
    assert gaps[0] == 0.0
    assert gaps[1] < 1e-14
    assert gaps[3] < 1e-11
    assert gaps[5] < 1e-9


#: Every integrator that runs decomposed, as [integrator] tables (one launch runs them all).
INTEGRATOR_TABLES = {
    "verlet": 'type = "verlet"\ndt = 0.005',
    "leapfrog": 'type = "leapfrog"\ndt = 0.005',
    "explicit_euler": 'type = "explicit_euler"\ndt = 0.001',
    "symplectic_euler": 'type = "symplectic_euler"\ndt = 0.002',
    "stormer_verlet": 'type = "stormer_verlet"\ndt = 0.005',
    "yoshida4": 'type = "yoshida4"\ndt = 0.005',
    "yoshida6": 'type = "yoshida6"\ndt = 0.005',
    "pefrl": 'type = "pefrl"\ndt = 0.005',
    "blanes_moan": 'type = "blanes_moan"\ndt = 0.005',
    "blanes_moan_rkn": 'type = "blanes_moan_rkn"\ndt = 0.005',
    "rk4": 'type = "rk4"\ndt = 0.002',
    "rkf45": 'type = "rkf45"\ndt = 0.02\ntol = 1e-5',
    "langevin": 'type = "langevin"\ndt = 0.005\ntemperature = 1.0\nfriction = 2.0',
    "bussi": 'type = "bussi"\ndt = 0.005\ntemperature = 1.0\ntau = 0.5',
    "nose_hoover_chain": 'type = "nose_hoover_chain"\ndt = 0.005\ntemperature = 1.0\ntau = 0.5',
    "berendsen": 'type = "berendsen"\ndt = 0.005\ntemperature = 1.0\ntau = 0.5',
}


@needs_mpi
@pytest.mark.slow  # several launches of up to 4 ranks
def test_every_distributed_integrator_follows_the_serial_run(tmp_path):
    """60 steps of the melt with each integrator on 2 ranks and on one process."""
    for name, table in INTEGRATOR_TABLES.items():
        text = MELT.format(integrator="verlet", extra="", steps=60, run_extra="")
        text = text.replace('type = "verlet"\ndt = 0.005', table)
        (tmp_path / f"{name}.toml").write_text(text.replace("every = 100", "every = 30"))
        _, summary = md.run_config(tmp_path / f"{name}.toml", output=tmp_path / f"{name}_1.h5")
        assert summary.status == "completed", (name, summary.message)
    script = tmp_path / "all.py"
    script.write_text(
        "import sys, md\n"
        f"for name in {list(INTEGRATOR_TABLES)!r}:\n"
        "    _, summary = md.run_config(f'{name}.toml', output=f'{name}_2.h5')\n"
        "    assert summary.status == 'completed', (name, summary.message)\n"
    )
    done = launch(2, str(script), cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    for name in INTEGRATOR_TABLES:
        with h5py.File(tmp_path / f"{name}_2.h5", "r") as f:
            assert list(f["particles/trajectory/position/step"][()]) == [0, 30, 60]
        gap = relative_gap(tmp_path / f"{name}_2.h5", tmp_path / f"{name}_1.h5")
        assert gap < 1e-12, (name, gap)


@needs_mpi
@pytest.mark.slow  # a 3000-step run on 2 ranks, killed, resumed, and run again whole
def test_a_rank_killed_ends_the_run_and_the_checkpoint_resumes_it(tmp_path):
    """SIGKILL to rank 1 mid-run: the launcher ends rank 0 too (nothing hangs), and the
    last checkpoint resumes to the same bits as an uninterrupted run on the same ranks."""
    text = MELT.format(integrator="verlet", extra="", steps=3000, run_extra="")
    config = tmp_path / "long.toml"
    config.write_text(
        text.replace("velocities = true", "velocities = true\ncheckpoint_every = 100")
    )
    out = tmp_path / "killed.h5"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MPIR_CVAR_ENABLE_HEAVY_YIELD": "1"}
    command = [
        "mpiexec",
        "-n",
        "2",
        sys.executable,
        "-m",
        "md.cli",
        "run",
        str(config),
        "--output",
        str(out),
        "--no-progress",
        "-q",
    ]
    launcher = subprocess.Popen(
        command, cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    try:
        deadline = time.monotonic() + 200
        while time.monotonic() < deadline and not (
            Path(str(out) + ".ckpt").exists() and read_checkpoint(str(out) + ".ckpt").state.step
        ):
            time.sleep(0.5)
        ranks = [p for p in Path("/proc").iterdir() if p.name.isdigit()]
        victims = []
        for process in ranks:
            try:
                environ = (process / "environ").read_bytes().split(b"\0")
                cmdline = (process / "cmdline").read_bytes()
            except OSError:
                continue
            if b"PMI_RANK=1" in environ and str(out).encode() in cmdline:
                victims.append(int(process.name))
        assert len(victims) == 1
        os.kill(victims[0], signal.SIGKILL)
        assert launcher.wait(timeout=120) != 0  # rank 0 was ended as well
    finally:
        if launcher.poll() is None:
            launcher.kill()
    saved = read_checkpoint(str(out) + ".ckpt")
    assert 0 < saved.state.step < 3000
    done = launch(
        2, "run", str(config), "--output", str(out), "--resume", "--no-progress", cwd=tmp_path
    )
    assert done.returncode == 0, done.stderr
    whole = tmp_path / "whole.h5"
    done = launch(2, "run", str(config), "--output", str(whole), "--no-progress", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    np.testing.assert_array_equal(unwrapped(out), unwrapped(whole))


# --------------------------------------------------------------- one rank fails
#: ``md run`` with two faults planted on one rank (given by the FAULT_RANK variable; a
#: one-process run is rank 0), each from the step-10 checkpoint on: ``overlap`` puts two
#: atoms of a listed pair on top of each other inside that rank's brick (its LJ energy
#: is then not finite), ``disk`` makes that rank's disk report no free space to the
#: trajectory writer. Each rank writes its exit code to ``exit<rank>.txt``.
FAULTY_RUN = """\
import os, sys
from pathlib import Path
import numpy as np
import md.checkpoint
from md.forcefield import ForceField
from md.trajectory import H5MDWriter

rank = int(os.environ.get("PMI_RANK", "0")) if int(os.environ.get("PMI_SIZE", "1")) > 1 else 0
fault, target = os.environ["FAULT"], int(os.environ["FAULT_RANK"])
armed = Path("armed")

saving = md.checkpoint.Checkpointer.__call__
def save(self, sim):
    saving(self, sim)
    if sim.state.step == 10:
        armed.touch()  # rank 0 saves; the ranks agree after it, so all see the file
md.checkpoint.Checkpointer.__call__ = save

evaluating = ForceField._evaluate
def overlapping(self, state, *args, **kwargs):
    if fault == "overlap" and rank == target and armed.exists():
        starts, neighbors = self.neighbor_list.starts, self.neighbor_list.neighbors
        rows = np.repeat(np.arange(len(starts) - 1), np.diff(starts))
        gaps = np.linalg.norm(state.positions[rows] - state.positions[neighbors], axis=1)
        k = int(np.flatnonzero(gaps < 2.5)[0])  # a pair within the cutoff, not through a
        state.positions[neighbors[k]] = state.positions[rows[k]]  # wall: on top of each other
    return evaluating(self, state, *args, **kwargs)
ForceField._evaluate = overlapping

fusing = ForceField.verlet_step
def unfused(self, state, *args, **kwargs):  # (the fused step bypasses _evaluate)
    if fault == "overlap" and armed.exists():
        return 0  # nothing done: the step goes through compute, and so _evaluate
    return fusing(self, state, *args, **kwargs)
ForceField.verlet_step = unfused

checking = H5MDWriter._check_space
def full(self, frame):
    if fault == "disk" and rank == target and armed.exists():
        real = os.statvfs
        os.statvfs = lambda path: os.statvfs_result((4096, 4096, 1000, 0, 0, 100, 0, 0, 0, 255))
        try:
            return checking(self, frame)
        finally:
            os.statvfs = real
    return checking(self, frame)
H5MDWriter._check_space = full

from md.cli import main
code = 1
try:
    code = main(sys.argv[1:])
finally:
    Path(f"exit{rank}.txt").write_text(str(code))
sys.exit(code)
"""


def _faulty_runs(tmp_path: Path, fault: str, rank: int):
    """The faulty run on one process and on 2 ranks (the fault on ``rank``): (serial, ranks)
    results, each with its output path."""
    config = write_config(tmp_path, steps=40)
    config.write_text(
        config.read_text().replace(
            '"melt.h5"\nevery = 100', '"melt.h5"\nevery = 5\ncheckpoint_every = 10'
        )
    )
    script = tmp_path / "faulty.py"
    script.write_text(FAULTY_RUN)
    results = []
    for n_ranks in (1, 2):
        folder = tmp_path / f"p{n_ranks}"
        folder.mkdir()
        out = folder / "melt.h5"
        args = [str(script), "run", str(config), "--output", str(out), "--no-progress"]
        env = {
            **os.environ,
            "FAULT": fault,
            "FAULT_RANK": str(rank if n_ranks > 1 else 0),
            "PYTHONPATH": str(ROOT),
            "MPIR_CVAR_ENABLE_HEAVY_YIELD": "1",
        }
        command = [sys.executable, *args]
        if n_ranks > 1:
            command = ["mpiexec", "-n", str(n_ranks), *command]
        done = subprocess.run(
            command, cwd=folder, env=env, capture_output=True, text=True, timeout=240
        )
        codes = [int((folder / f"exit{r}.txt").read_text()) for r in range(n_ranks)]
        errors = [
            line.replace(str(out), "OUT")
            for line in done.stderr.splitlines()
            if line.startswith("md: error:")
        ]
        results.append((done, codes, errors, out))
    return results


@needs_mpi
@pytest.mark.slow  # a run on one process and one on 2 ranks: about 11 s
def test_one_rank_with_a_non_finite_energy_stops_every_rank_as_a_serial_run(tmp_path):
    """Two atoms on top of each other in rank 1's brick at step 11: both ranks stop with
    the serial run's message and exit code (1), and the step-10 checkpoint is intact."""
    (serial, serial_codes, expected, _), (done, codes, errors, out) = _faulty_runs(
        tmp_path, "overlap", rank=1
    )
    assert serial.returncode == 1 and serial_codes == [1], serial.stderr[-2000:]
    assert len(expected) == 1 and "step 11: potential energy is" in expected[0], expected
    assert done.returncode == 1, done.stderr[-2000:]
    assert codes == [1, 1]  # every rank ended, with the serial exit code
    assert errors == expected  # rank 0 alone reports, in the serial words
    saved = read_checkpoint(str(out) + ".ckpt")
    assert saved.state.step == 10 and saved.state.n_atoms == 384
    assert np.all(np.isfinite(saved.state.positions))
    with h5py.File(out, "r") as f:  # the frames before the failure are readable
        assert list(f["particles/trajectory/position/step"][()]) == [0, 5, 10]


@needs_mpi
@pytest.mark.slow  # a run on one process and one on 2 ranks: about 10 s
def test_a_full_disk_on_rank_0_stops_every_rank_with_exit_2(tmp_path):
    """Rank 0's disk fills after the step-10 checkpoint: the step-15 frame is refused,
    every rank stops, exit 2 as in serial, "disk full" in the message, and the frames and
    the checkpoint written before are intact."""
    (serial, serial_codes, expected, _), (done, codes, errors, out) = _faulty_runs(
        tmp_path, "disk", rank=0
    )
    assert serial.returncode == 2 and serial_codes == [2], serial.stderr[-2000:]
    assert done.returncode == 2, done.stderr[-2000:]
    assert codes == [2, 2]
    assert len(errors) == 1 and "disk full" in errors[0], done.stderr[-2000:]
    # the serial words, but the hint to continue starts the run on its ranks again
    assert errors == [e.replace(" md run ", " mpiexec -n 2 md run ") for e in expected]
    assert "Traceback" not in done.stderr
    saved = read_checkpoint(str(out) + ".ckpt")
    assert saved.state.step == 10 and saved.state.n_atoms == 384
    with h5py.File(out, "r") as f:
        assert list(f["particles/trajectory/position/step"][()]) == [0, 5, 10]


#: The 384-atom melt on two ranks with rank 1 made slow (a pair potential that sleeps there
#: at every evaluation): load balancing must move the plane between the bricks so that
#: rank 1 owns fewer atoms, and the trajectory must still be the serial one.
SLOW_RANK = (
    "import sys, time\n"
    "import numpy as np\n"
    "import md\n"
    "from integrators import VelocityVerlet\n"
    "from potentials import LennardJones\n"
    "class SlowOnRankOne(LennardJones):\n"
    "    def energy_forces(self, *args, **kwargs):\n"
    "        from mpi4py import MPI\n"
    "        if MPI.COMM_WORLD.Get_rank() == 1:\n"
    "            time.sleep(0.004)\n"
    "        return super().energy_forces(*args, **kwargs)\n"
    "def system():\n"
    "    lattice = md.lattice('fcc', (6, 4, 4), density=0.8442)\n"
    "    velocities = np.random.default_rng(3).normal(0.0, 1.7, lattice.positions.shape)\n"
    "    return md.State(positions=lattice.positions, velocities=velocities, masses=1.0,\n"
    "                    box=lattice.box)\n"
    "def simulation(state, kind, potential=LennardJones, **options):\n"
    "    return kind(state, [potential(cutoff=2.5)], VelocityVerlet(dt=0.005), skin=0.3,\n"
    "                **options)\n"
    "if __name__ == '__main__':\n"
    "    from md.distributed import DistributedSimulation\n"
    "    sim = simulation(system(), DistributedSimulation, SlowOnRankOne,\n"
    "                     decomposition=[2, 1, 1], balance_every=10, balance_threshold=1.02)\n"
    "    sim.run(150)\n"
    "    owned = sim.ranks.all_objects(sim.state.n_atoms)\n"
    "    view = sim.global_view()\n"
    "    if sim.rank == 0:\n"
    "        np.save(sys.argv[1], view.state.positions)\n"
    "        ff = sim.forcefield\n"
    "        print('owned', *owned, 'balances', ff.balances, 'cut', ff.domain.grid.cuts[0][1],\n"
    "              'layout', view.forcefield.decomposition['cuts'][0][1])\n"
)


@needs_mpi
def test_load_balancing_shrinks_a_slow_ranks_brick_and_keeps_the_trajectory(tmp_path):
    done, words, slow_rank, positions = launch_script(
        tmp_path, "slow_rank", SLOW_RANK, 2, timeout=180
    )
    assert words[0] == "owned" and words[3] == "balances", done.stdout
    owned = [int(words[1]), int(words[2])]
    cut, saved = float(words[6]), float(words[8])
    assert int(words[4]) >= 3  # moved the plane at most checks
    assert cut > 0.55 and saved == cut  # rank 1's brick [cut, 1) shrank; checkpoints keep it
    assert sum(owned) == 384 and owned[1] < 0.8 * owned[0], owned
    from md.simulation import Simulation

    alone = slow_rank.simulation(slow_rank.system(), Simulation)
    alone.run(150)
    assert gap_to(positions, alone) < 1e-10


@needs_mpi
@pytest.mark.slow  # two launches
def test_a_balanced_run_checkpoints_its_cuts_and_resumes(serial, tmp_path):
    """[run] balance_every with threshold 1 moves the planes at every check (two ranks'
    busy times always differ); the checkpoint records them, a resume on the same grid
    takes them back, and the run agrees with the serial one."""
    config = write_config(tmp_path, run_extra="balance_every = 20\nbalance_threshold = 1.0")
    out = tmp_path / "out.h5"
    done = launch(
        2, "run", str(config), "--output", str(out), "--steps", "250", "--no-progress", cwd=tmp_path
    )
    assert done.returncode == 0, done.stderr + done.stdout
    cuts = read_checkpoint(str(out) + ".ckpt").decomposition["cuts"]
    assert cuts[0][1] != 0.5 and cuts[1] == [0.0, 1.0], cuts
    done = launch(
        2, "run", str(config), "--output", str(out), "--resume", "--no-progress", cwd=tmp_path
    )
    assert done.returncode == 0, done.stderr + done.stdout
    assert relative_gap(out, serial) < 1e-10
