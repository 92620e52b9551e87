"""Reliability, round 4 (issue 65): hints that work, pairs that are not lost silently,
keys that are not ignored, and the leftovers; with real processes where it matters."""

from __future__ import annotations

import logging
import os
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from test_mpi import needs_mpi

import md
from conftest import lj_config_text
from integrators import VelocityVerlet
from md.cli import main
from potentials import LennardJones

ROOT = Path(__file__).resolve().parents[1]
QUIET = ["-q", "--no-progress"]


def _md_words(command: str) -> list[str]:
    """A printed ``md ...`` command as this interpreter runs it (``md`` -> python -m md.cli)."""
    words = shlex.split(command)
    at = words.index("md")
    return [*words[:at], sys.executable, "-m", "md.cli", *words[at + 1 :]]


def _env() -> dict:
    return {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    }


def _frames(path: Path) -> int:
    from md.errors import TrajectoryError
    from md.trajectory import read_frame_steps

    try:
        return len(read_frame_steps(path)[0]) if path.exists() else 0
    except TrajectoryError:
        return 0


def _wait_for_frames(path: Path, n: int, process, timeout: float = 180.0) -> None:
    deadline = time.monotonic() + timeout
    while _frames(path) < n:
        assert process.poll() is None, process.communicate()
        assert time.monotonic() < deadline, "timed out waiting for frames"
        time.sleep(0.05)


# ------------------------------------------- item 3: the "continue with" hint works
def test_the_hint_after_sigterm_repeats_the_output_and_the_resume_continues(tmp_path):
    """Before: ``-o PATH`` was dropped from the hint, which then failed with "no
    checkpoint found" (the config names another output)."""
    config = tmp_path / "run.toml"
    config.write_text(
        lj_config_text(
            run="steps = 40\nthermo_every = 1000000",
            output='path = "named.h5"\nevery = 50\ncheckpoint_every = 1000000',
        )
    )
    first = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "md.cli",
            "run",
            str(config),
            "-o",
            "chosen.h5",
            "--steps",
            "50000000",
            *QUIET,
        ],
        cwd=tmp_path,
        env=_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        _wait_for_frames(tmp_path / "chosen.h5", 2, first)
        first.send_signal(signal.SIGTERM)
        _, err = first.communicate(timeout=120)
    finally:
        if first.poll() is None:
            first.kill()
    assert first.returncode == 143, err
    hint = err.split("Continue with: ")[1].strip()
    assert "--output chosen.h5" in hint and "--steps 50000000" in hint, hint
    assert not (tmp_path / "named.h5").exists()
    stopped_at = md.checkpoint.read_checkpoint(tmp_path / "chosen.h5.ckpt").state.step
    # The hint, run as printed, resumes this run (and is stopped again in turn).
    again = subprocess.Popen(
        _md_words(hint),
        cwd=tmp_path,
        env=_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        line = again.stdout.readline()
        assert f"resuming at step {stopped_at}" in line, (line, again.stderr.read())
        _wait_for_frames(tmp_path / "chosen.h5", _frames(tmp_path / "chosen.h5") + 1, again)
        again.send_signal(signal.SIGTERM)
        _, err = again.communicate(timeout=120)
    finally:
        if again.poll() is None:
            again.kill()
    assert again.returncode == 143, err
    assert md.checkpoint.read_checkpoint(tmp_path / "chosen.h5.ckpt").state.step > stopped_at


@pytest.fixture
def small_disk(tmp_path):
    """Factory: ``small_disk(kb)`` mounts a tmpfs of ``kb`` KiB and returns its folder."""
    mounted = []

    def mount(kb: int) -> Path:
        folder = tmp_path / f"disk{len(mounted)}"
        folder.mkdir()
        if shutil.which("mount") is None or not hasattr(os, "geteuid") or os.geteuid() != 0:
            pytest.skip("mounting a small tmpfs needs root")
        done = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={kb}k", "tmpfs", str(folder)],
            capture_output=True,
            text=True,
        )
        if done.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()}")
        mounted.append(folder)
        return folder

    yield mount
    for folder in mounted:
        subprocess.run(["umount", "-l", str(folder)], capture_output=True)


def _half_the_room(config: Path, steps: int, folder: Path) -> int:
    """Half the bytes the run of ``config`` for ``steps`` steps writes (its trajectory and
    checkpoint, measured by running it serially into ``folder``): room a full run
    cannot fit in, whatever the file layout's overheads."""
    folder.mkdir()
    probe = folder / "probe.h5"
    cwd = os.getcwd()
    os.chdir(folder)
    try:
        assert main(["run", str(config), "-o", str(probe), "--steps", str(steps), *QUIET]) == 0
    finally:
        os.chdir(cwd)
    return sum(f.stat().st_size for f in folder.iterdir()) // 2


def test_the_hint_after_a_full_disk_repeats_the_output_and_resumes(
    tmp_path, small_disk, monkeypatch, capsys
):
    disk = small_disk(4096)
    config = tmp_path / "run.toml"
    config.write_text(
        lj_config_text(
            run="steps = 20",
            output='path = "named.h5"\nevery = 10\nvelocities = true\ncheckpoint_every = 10',
        )
    )
    monkeypatch.chdir(tmp_path)
    room = _half_the_room(config, 300, tmp_path / "probe")
    free = os.statvfs(disk).f_bavail * os.statvfs(disk).f_frsize
    (disk / "filler").write_bytes(b"\0" * (free - room))
    output = disk / "out.h5"
    assert main(["run", str(config), "-o", str(output), "--steps", "300", *QUIET]) == 2
    err = capsys.readouterr().err
    assert "disk full" in err, err
    assert "continue with: " in err, err
    hint = err.split("continue with: ")[1].strip()
    assert f"--output {output}" in hint and "--steps 300" in hint, hint
    (disk / "filler").unlink()
    assert main(_md_words(hint)[3:]) == 0, capsys.readouterr().err  # md run ... as printed
    from md.trajectory import read_trajectory

    assert read_trajectory(output).steps.tolist() == list(range(0, 301, 10))


def test_a_checkpoint_that_cannot_be_written_says_so(tmp_path, small_disk):
    """Before: a full disk at a checkpoint named the file only: not that it was the
    checkpoint, at which step, nor that the one before is intact."""
    from md.checkpoint import Checkpointer

    disk = small_disk(64)
    sim = md.Simulation(
        md.maxwell_boltzmann(md.lattice("fcc", 4, density=0.8442), 1.0, seed=1),
        [LennardJones(cutoff=2.5)],
        VelocityVerlet(0.005),
    )

    class Frames:
        n_frames, last_step = 3, 20

    free = os.statvfs(disk).f_bavail * os.statvfs(disk).f_frsize
    (disk / "filler").write_bytes(b"\0" * (free - 4096))  # 256 atoms: ~30 kB do not fit
    saver = Checkpointer(disk / "out.h5.ckpt", Frames(), {}, "id", "run.toml")
    with pytest.raises(OSError) as raised:
        saver(sim)
    message = str(raised.value)
    assert "disk full" in message and f"checkpoint {disk / 'out.h5.ckpt'}" in message, message
    assert "at step 0" in message
    assert not (disk / "out.h5.ckpt").exists()


# --------------------------------------------- item 4: pairs lost between looks are said
def _melt(every: int, check: bool) -> md.Simulation:
    state = md.maxwell_boltzmann(md.lattice("fcc", 4, density=0.8442), 1.5, seed=4)
    return md.Simulation(
        state,
        [LennardJones(cutoff=2.5)],
        VelocityVerlet(0.005),
        neighbor_every=every,
        neighbor_check=check,
    )


@pytest.mark.parametrize("check", [False, True])
def test_looks_that_find_atoms_past_half_the_skin_are_counted_and_warned_once(caplog, check):
    """Before: every = 40 lost pairs silently (``check`` or not): the engine measured
    nothing at a look without the check, and said nothing at one with it."""
    sim = _melt(40, check)
    nl = sim.forcefield.neighbor_list
    late, expected = 0, 0
    with caplog.at_level(logging.WARNING, logger="md.neighbors"):
        sim.forcefield.compute(sim.state)
        for _ in range(200):
            reference = nl.reference_positions.copy()
            built = nl.built_step
            sim.run(1)
            if nl.built_step != built:  # a look that rebuilt: how far had the atoms gone?
                moved = np.sqrt(((sim.state.positions - reference) ** 2).sum(axis=1)).max()
                expected += moved > 0.5 * nl.skin
            late = nl.n_late_looks
    assert late == expected and late >= 3, (late, expected)
    warnings = [
        r
        for r in caplog.records
        if "pairs within the cutoff may have been missed" in r.getMessage()
    ]
    assert len(warnings) == 1, caplog.text
    exact = _melt(1, True)
    exact.run(200)
    assert exact.forcefield.neighbor_list.n_late_looks == 0


def test_md_run_reports_late_looks_in_its_summary_and_warns(tmp_path, monkeypatch):
    config = tmp_path / "run.toml"
    config.write_text(
        lj_config_text(
            cells=4, temperature=1.5, run="steps = 200\nneighbor_every = 50\nneighbor_check = false"
        )
    )
    done = subprocess.run(
        [sys.executable, "-m", "md.cli", "run", str(config), *QUIET],
        cwd=tmp_path,
        env=_env(),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    count = int(done.stdout.split("Late looks: ")[1].split()[0])
    assert count >= 2, done.stdout
    assert done.stderr.count("pairs within the cutoff may have been missed") == 1, done.stderr
    _, summary = md.run_config(config, output=tmp_path / "again.h5")
    assert summary.late_looks == count


# ---------------------------------- item 5: a decomposition without ranks is refused
@pytest.mark.parametrize("shape", ["[2, 1, 1]", "[1, 2, 1]"])
def test_a_decomposition_on_one_process_is_refused(tmp_path, capsys, monkeypatch, shape):
    """Before: ignored, the run went on as one process."""
    config = tmp_path / "run.toml"
    config.write_text(lj_config_text(run=f"steps = 10\ndecomposition = {shape}"))
    monkeypatch.chdir(tmp_path)
    assert main(["run", str(config), *QUIET]) == 2
    err = capsys.readouterr().err
    assert "[run] decomposition" in err and "mpiexec -n 2" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.toml"]  # nothing written
    config.write_text(lj_config_text(run="steps = 10\ndecomposition = [1, 1, 1]"))
    assert main(["run", str(config), *QUIET]) == 0  # one brick is one process


# --------------------------------------------------------------- item 10: leftovers
@pytest.mark.parametrize("fast", ["true", "3", "2.5"])
def test_respa_fast_that_is_no_list_is_refused_by_name(tmp_path, capsys, fast):
    """Before: ``fast = true`` said "'bool' object is not iterable"."""
    config = tmp_path / "run.toml"
    config.write_text(lj_config_text(integrator=f'type = "respa"\ndt = 0.005\nfast = {fast}'))
    assert main(["run", str(config), "-o", str(tmp_path / "o.h5"), *QUIET]) == 2
    err = capsys.readouterr().err
    assert 'fast must be "bonded" or a list of potential indices' in err, err
    assert "iterable" not in err


def test_sigterm_to_md_minimize_before_fire_starts_says_so(tmp_path):
    """Before: the default SIGTERM ended it silently (killed by the signal, 143 in a shell)
    while it built the system; here the signal comes from within that build."""
    config = tmp_path / "melt.toml"
    config.write_text(lj_config_text())
    done = _sigterm_while_building(tmp_path, config, "minimize", "prepare_minimize")
    assert done.returncode == 143, (done.returncode, done.stderr)
    assert "SIGTERM received before minimising started; nothing was written" in done.stderr
    assert "Traceback" not in done.stderr


def test_the_automatic_grid_refusal_names_the_smaller_count_that_works():
    """Before: 3 ranks on a cell that takes [2, 2, 1] were told only of the 4-rank grid."""
    from md.distributed import choose_grid

    with pytest.raises(ValueError) as raised:
        choose_grid(3, [6.0, 6.0, 3.0], None, [True] * 3, 2.8)
    message = str(raised.value)
    assert "2 ranks work as well (grid [2, 1, 1])" in message, message
    assert "the largest decomposition that fits is [2, 2, 1] (4 ranks)" in message
    with pytest.raises(ValueError) as raised:  # above the largest: that one is the answer
        choose_grid(5, [6.0, 6.0, 3.0], None, [True] * 3, 2.8)
    assert "work as well" not in str(raised.value)
    assert "[2, 2, 1] (4 ranks)" in str(raised.value)


def test_md_info_shows_the_ranks_and_grid_a_file_records(tmp_path, capsys):
    """Before: the parameters held them, md info did not say."""
    from md.trajectory import H5MDWriter

    state = md.lattice("fcc", 2, density=0.8)
    path = tmp_path / "ranks.h5"
    with H5MDWriter(path, state, parameters={"mpi_ranks": 4, "decomposition": [2, 2, 1]}) as writer:
        writer.write(state)
    assert main(["info", str(path)]) == 0
    assert "mpi ranks    4 (bricks 2 x 2 x 1)" in capsys.readouterr().out
    plain = tmp_path / "plain.h5"
    with H5MDWriter(plain, state) as writer:
        writer.write(state)
    assert main(["info", str(plain)]) == 0
    assert "mpi ranks" not in capsys.readouterr().out


def test_the_mpi_guide_lists_every_refused_integrator_and_xpbd_is_not_called_rattle():
    import integrators
    from integrators.xpbd import XPBD
    from md.distributed import refuse_undistributable

    refused = sorted(
        name
        for name, cls in integrators.INTEGRATORS.items()
        if not getattr(cls, "distributed", False)
    )
    assert {"bdf2", "trapezoidal", "gauss_legendre4", "xpbd", "rattle"} <= set(refused)
    guide = (ROOT / "docs/guide/mpi.md").read_text()
    paragraph = guide.split("Refused under several ranks")[1].split("\n\n")[0]
    for name in refused:
        assert f"`{name}`" in paragraph, name
    with pytest.raises(ValueError) as raised:
        refuse_undistributable(XPBD(0.005), [])
    message = str(raised.value)
    assert "the xpbd integrator does not run decomposed" in message
    assert "RATTLE" not in message


# ------------------------------------------------------ under MPI (2 ranks, 48 atoms)
#: 48 LJ atoms (fcc 3 x 2 x 2, cutoff 1.5): two bricks along x of at least cutoff + skin.
SMALL = """\
units = "lj"
seed = 11
[system]
lattice = "fcc"
cells = [3, 2, 2]
density = 0.8442
temperature = 1.5
[[potentials]]
type = "lj"
cutoff = 1.5
cutoff_mode = "shift"
[integrator]
{integrator}
[run]
steps = {steps}
thermo_every = 1000
[output]
path = "named.h5"
every = 10
velocities = true
checkpoint_every = 10
"""


def _mpi_words(n_ranks: int) -> list[str]:
    return ["mpiexec", "-n", str(n_ranks), sys.executable, "-m", "md.cli"]


def _mpi_env() -> dict:
    # MPICH's waiting ranks would take the cores from the one they wait for: yield instead.
    return {**_env(), "MPIR_CVAR_ENABLE_HEAVY_YIELD": "1"}


@needs_mpi
def test_the_hint_under_mpiexec_names_the_ranks_and_resumes(tmp_path, small_disk):
    """A full disk on 2 ranks: the hint is ``mpiexec -n 2 md run ... --output ... --resume``,
    and run as printed (once there is room) it completes the run. Before: ``md run CONFIG
    --resume``, which looked for the config's output and found no checkpoint."""
    disk = small_disk(4096)
    config = tmp_path / "run.toml"
    config.write_text(SMALL.format(integrator='type = "verlet"\ndt = 0.005', steps=20))
    room = _half_the_room(config, 400, tmp_path / "probe")
    free = os.statvfs(disk).f_bavail * os.statvfs(disk).f_frsize
    (disk / "filler").write_bytes(b"\0" * (free - room))
    output = disk / "out.h5"
    full = subprocess.run(
        [*_mpi_words(2), "run", str(config), "-o", str(output), "--steps", "400", *QUIET],
        cwd=tmp_path,
        env=_mpi_env(),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert full.returncode == 2, full.stderr + full.stdout
    assert "disk full" in full.stderr, full.stderr
    hint = full.stderr.split("continue with: ")[1].strip()
    assert hint.startswith("mpiexec -n 2 md run ") and f"--output {output}" in hint, hint
    (disk / "filler").unlink()
    again = subprocess.run(
        _md_words(hint) + QUIET,
        cwd=tmp_path,
        env=_mpi_env(),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert again.returncode == 0, again.stderr + again.stdout
    assert "resuming at step" in again.stdout
    from md.trajectory import read_trajectory

    assert read_trajectory(output).steps.tolist() == list(range(0, 401, 10))


@needs_mpi
def test_rkf45_on_two_ranks_takes_the_serial_substeps(tmp_path):
    """Before: the step-size factor, smooth in the error estimate, passed the estimate's
    last bits (forces summed in another order on 2 ranks) on to every later substep,
    where they grew: with a smooth cutoff 2 ranks took other substeps (297 accepted and
    242 rejected against the serial 292 and 220) and were 1e-6 from the serial positions
    after 20 steps. The factor rounded to a power of 2^(1/4): the same substeps, the
    positions to round-off."""
    config = tmp_path / "rkf.toml"
    text = SMALL.format(integrator='type = "rkf45"\ndt = 0.02\ntol = 1e-7', steps=20)
    config.write_text(text.replace('cutoff_mode = "shift"', 'cutoff_mode = "smooth"\nr_on = 1.2'))
    _, serial = md.run_config(config, output=tmp_path / "serial.h5")
    assert serial.status == "completed", serial.message
    assert serial.statistics["rejected"] > 0  # the control is at work
    script = tmp_path / "ranks.py"
    script.write_text(
        "import sys, md\n"
        "from mpi4py import MPI\n"
        "_, summary = md.run_config(sys.argv[1], output=sys.argv[2])\n"
        "assert summary.status == 'completed', summary.message\n"
        "if MPI.COMM_WORLD.rank == 0:  # one rank prints: two could interleave their lines\n"
        "    print('statistics', summary.statistics['accepted'], summary.statistics['rejected'])\n"
    )
    done = subprocess.run(
        ["mpiexec", "-n", "2", sys.executable, str(script), str(config), "ranks.h5"],
        cwd=tmp_path,
        env=_mpi_env(),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr + done.stdout
    words = done.stdout.split("statistics")[1].split()
    assert [int(words[0]), int(words[1])] == [
        serial.statistics["accepted"],
        serial.statistics["rejected"],
    ]
    from md.trajectory import read_trajectory

    a, b = read_trajectory(tmp_path / "serial.h5"), read_trajectory(tmp_path / "ranks.h5")
    assert a.steps.tolist() == b.steps.tolist() == [0, 10, 20]
    gap = np.abs(a.positions - b.positions).max()  # unwrapped
    assert gap < 1e-12, gap


def test_sigterm_to_md_run_while_it_builds_says_so(tmp_path):
    """As md minimize: a SIGTERM while the run is built (and compiled) ended it silently,
    killed by the signal; now it says so, writes nothing and exits 143."""
    config = tmp_path / "melt.toml"
    config.write_text(lj_config_text())
    done = _sigterm_while_building(tmp_path, config, "run", "prepare")
    assert done.returncode == 143, (done.returncode, done.stderr)
    assert "SIGTERM received before the run started; nothing was written" in done.stderr
    assert "Traceback" not in done.stderr
    assert not list(tmp_path.glob("*.h5*"))


def _sigterm_while_building(tmp_path, config, command: str, builder: str):
    """Run ``md COMMAND CONFIG`` in a child whose build (``md.cli.COMMAND.BUILDER``) sends
    the process SIGTERM and then waits: the signal comes from within the build."""
    script = tmp_path / "kill_early.py"
    script.write_text(
        "import os, signal, sys, time\n"
        f"import md.cli.{command} as command\n"
        "def building(*args, **kwargs):\n"
        "    os.kill(os.getpid(), signal.SIGTERM)\n"
        "    time.sleep(5)\n"
        "    raise AssertionError('the signal did not stop the build')\n"
        f"command.{builder} = building\n"
        "from md.cli import main\n"
        f"sys.exit(main(['{command}', sys.argv[1]]))\n"
    )
    return subprocess.run(
        [sys.executable, str(script), str(config)],
        cwd=tmp_path,
        env=_env(),
        capture_output=True,
        text=True,
        timeout=120,
    )
