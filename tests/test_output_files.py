"""Outputs on a full disk, claims, special files and temporaries (issue 33), in real processes.

The disk-full cases mount a small tmpfs (root only; skipped where mounting is
not permitted) and run the ``md`` command in a child process, since what
broke was the process itself (segmentation faults and bus errors in HDF5).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from conftest import lj_config_text

import md
from md.cli import main

QUIET = ["-q", "--no-progress"]


def _md(args, cwd: Path, timeout: float = 900, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "md.cli", *args], cwd=cwd, capture_output=True, text=True,
        timeout=timeout, **kwargs,
    )  # fmt: skip


@pytest.fixture
def small_disk(tmp_path):
    """Factory: ``small_disk(kb)`` mounts a tmpfs of ``kb`` KiB and returns its folder."""
    mounted = []

    def mount(kb: int) -> Path:
        folder = tmp_path / f"disk{len(mounted)}_{kb}k"
        folder.mkdir()
        if shutil.which("mount") is None or not hasattr(os, "geteuid") or os.geteuid() != 0:
            pytest.skip("mounting a small tmpfs needs root")
        done = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={kb}k", "tmpfs", str(folder)],
            capture_output=True, text=True,
        )  # fmt: skip
        if done.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()}")
        mounted.append(folder)
        return folder

    yield mount
    for folder in mounted:
        subprocess.run(["umount", "-l", str(folder)], capture_output=True)


@pytest.fixture
def run_config(tmp_path):
    """500 LJ atoms: the checkpoint (~40 kB) and the layout fill a disk of 40-88 kB
    at every stage of creating the outputs."""
    path = tmp_path / "run.toml"
    path.write_text(lj_config_text(cells=5, run="steps = 20"))
    return path


def _assert_disk_full_and_nothing_left(done, disk: Path) -> None:
    assert done.returncode == 2, (done.returncode, done.stderr[-2000:])
    assert "disk full" in done.stderr, done.stderr[-2000:]
    assert "Traceback" not in done.stderr, done.stderr[-2000:]
    assert sorted(p.name for p in disk.iterdir()) == []


# ------------------------------------------------------------ item 1: md run, full disk
@pytest.mark.parametrize("kb", [56, 80])
def test_md_run_on_a_full_disk_exits_2_and_leaves_nothing(run_config, small_disk, kb):
    """Before: a bus error at 56 kB (HDF5 freed a dataset of a file whose flush had
    failed), a RuntimeError traceback at 80 kB."""
    disk = small_disk(kb)
    done = _md(["run", str(run_config), "-o", str(disk / "out.h5"), *QUIET], run_config.parent)
    _assert_disk_full_and_nothing_left(done, disk)


@pytest.mark.slow
@pytest.mark.parametrize("kb", [40, 48, 56, 64, 72, 80, 88])
def test_md_run_on_a_full_disk_at_every_size_three_times(run_config, small_disk, kb):
    disk = small_disk(kb)
    for _ in range(3):
        done = _md(["run", str(run_config), "-o", str(disk / "out.h5"), *QUIET], run_config.parent)
        _assert_disk_full_and_nothing_left(done, disk)


def test_a_frame_hdf5_cannot_write_is_reported_without_crashing(tmp_path, small_disk):
    """The writer checks the room before each frame; where that check is beaten (another
    process filled the disk meanwhile), HDF5's failed write must still end in an OSError
    saying "disk full" and a process that exits normally, keeping the frames before it."""
    disk = small_disk(400)
    script = tmp_path / "fill.py"
    script.write_text(
        textwrap.dedent(f"""
        import numpy as np
        from md.state import State
        from md.trajectory import H5MDWriter, read_trajectory, verify_frames

        H5MDWriter._check_space = lambda self, frame: None  # as if another process beat it
        rng = np.random.default_rng(1)
        state = State(positions=5 * rng.random((108, 3)), velocities=np.zeros((108, 3)),
                      masses=np.ones(108), box=np.full(3, 5.0), pbc=np.ones(3, bool))
        writer = H5MDWriter({str(disk / "x.h5")!r}, state, velocities=True)
        try:
            for step in range(100000):
                state.step = step
                writer.write(state, thermo={{}})
        except OSError as error:
            print("refused:", error)
        writer.close()
        verify_frames({str(disk / "x.h5")!r}, writer.n_frames)  # the kept frames are intact
        print("kept", writer.n_frames, "read", read_trajectory({str(disk / "x.h5")!r}).n_frames)
    """)
    )
    done = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, timeout=300,
        env={**os.environ, "PYTHONPATH": str(Path(md.__file__).resolve().parents[1])},
    )  # fmt: skip
    assert done.returncode == 0, (done.returncode, done.stderr[-2000:])
    assert "refused: [Errno 28] disk full: cannot write frame" in done.stdout, done.stdout
    kept, read = (int(n) for n in done.stdout.split("kept ")[1].split(" read "))
    assert kept > 0 and read in (kept, kept + 1)  # the frame that failed may have landed


# ------------------------------------------------ items 1 and 12: md minimize, full disk
def _remount(folder: Path, kb: int) -> None:
    done = subprocess.run(
        ["mount", "-o", f"remount,size={kb}k", str(folder)], capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr


@pytest.mark.parametrize("kb", [8, 40, 96])
def test_md_minimize_on_a_full_disk_leaves_nothing_and_the_rerun_works(run_config, small_disk, kb):
    """Before: a bus error at 8 kB; a zero-frame file at 96 kB that refused the re-run."""
    disk = small_disk(kb)
    command = ["minimize", str(run_config), "-o", str(disk / "relaxed.h5"), "-q"]
    done = _md(command, run_config.parent)
    _assert_disk_full_and_nothing_left(done, disk)
    _remount(disk, 4096)  # room made: the same command now works
    again = _md(command, run_config.parent)
    assert again.returncode == 0, again.stderr
    from md.trajectory import read_trajectory

    assert read_trajectory(disk / "relaxed.h5").n_frames == 1


# ------------------------------------------ item 5: md minimize never overwrites an input
@pytest.mark.parametrize("which", ["config", "structure_xyz", "structure_h5"])
def test_md_minimize_refuses_to_write_over_its_own_inputs(tmp_path, monkeypatch, capsys, which):
    import ase.build
    import ase.io

    monkeypatch.chdir(tmp_path)
    crystal = ase.build.bulk("Ar", "fcc", a=5.26, cubic=True).repeat(4)
    ase.io.write(tmp_path / "start.xyz", crystal)
    structure = "start.xyz"
    if which == "structure_h5":  # an H5MD structure, as md minimize itself writes
        source = tmp_path / "source.toml"
        source.write_text(_argon_config("start.xyz"))
        assert main(["minimize", "source.toml", "-o", "start.h5", "-q"]) == 0
        structure = "start.h5"
    config = tmp_path / "run.toml"
    config.write_text(_argon_config(structure))
    target = {"config": config, "structure_xyz": tmp_path / "start.xyz"}.get(
        which, tmp_path / "start.h5"
    )
    before = target.read_bytes()
    code = main(["minimize", str(config), "-o", str(target), "--overwrite", "-q"])
    assert code == 2
    assert "is an input of this run" in capsys.readouterr().err
    assert target.read_bytes() == before


def _argon_config(structure: str) -> str:
    return (
        f'units = "metal"\n[system]\nstructure = "{structure}"\n'
        '[[potentials]]\ntype = "lj"\nepsilon = 0.0104\nsigma = 3.4\ncutoff = 8.0\n'
        '[integrator]\ntype = "verlet"\ndt = 1.0\n[run]\nsteps = 5\n'
    )


# ------------------------------------- items 14, 17, 18: md minimize's arguments and output
@pytest.mark.parametrize(
    ("option", "message"),
    [
        (["--fmax", "inf"], "--fmax must be finite and > 0, got inf"),
        (["--fmax", "1e309"], "--fmax must be finite and > 0, got inf"),
        (["--max-force", "inf"], "--max-force must be finite and > 0, got inf"),
        (["--max-steps", str(10**20)], "--max-steps must be at most"),
        (["--threads", "100000"], "--threads: threads = 100000 is more than"),
        (["-o", "relaxed.xyz"], "md convert relaxed.h5 relaxed.xyz"),
    ],
)
def test_md_minimize_refuses_bad_arguments_with_a_message(
    run_config, monkeypatch, capsys, option, message
):
    monkeypatch.chdir(run_config.parent)
    assert main(["minimize", str(run_config), *option, "-q"]) == 2
    err = capsys.readouterr().err
    assert message in err, err
    assert sorted(p.name for p in run_config.parent.iterdir()) == ["run.toml"]


def test_md_minimize_takes_threads_from_the_option_and_from_the_config(run_config, monkeypatch):
    from md.parallel import get_threads, set_threads

    monkeypatch.chdir(run_config.parent)
    try:
        assert main(["minimize", str(run_config), "--threads", "1", "-q", "-o", "a.h5"]) == 0
        assert get_threads() == 1
        text = run_config.read_text().replace("steps = 20", "steps = 20\nthreads = 100000")
        run_config.write_text(text)
        assert main(["minimize", str(run_config), "-q", "-o", "b.h5"]) == 2  # [run] threads
        assert not (run_config.parent / "b.h5").exists()
    finally:
        set_threads(None)


SLOW_MINIMIZE = "[minimize]\nfmax = 1e-30\nmax_steps = 100000000\nreport_every = 10\n"


@pytest.mark.parametrize("command", ["minimize", "run"])
def test_sigterm_while_minimising_says_so_and_writes_nothing(tmp_path, command):
    """Before: md minimize (and md run's [minimize] stage) died silently on SIGTERM."""
    import signal

    config = tmp_path / "melt.toml"
    text = lj_config_text(cells=4, temperature=0.0)
    config.write_text(text.replace("[integrator]", SLOW_MINIMIZE + "[integrator]"))
    # fmax = 1e-30 is below the crystal's round-off forces: FIRE runs until stopped
    extra = ["--no-progress"] if command == "run" else []
    process = subprocess.Popen(
        [sys.executable, "-m", "md.cli", command, str(config), *extra],
        cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        for line in process.stdout:  # wait until FIRE is under way
            if "energy" in line and "max force" in line:
                break
        process.send_signal(signal.SIGTERM)
        _, err = process.communicate(timeout=300)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 143, err
    assert "SIGTERM received" in err and "nothing was written" in err, err
    assert "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["melt.toml"]


# ------------------------------------- item 17: "no checkpoint was written" when one exists
def test_a_resumed_run_that_fills_the_disk_names_the_checkpoint_it_resumed_from(
    tmp_path, small_disk
):
    disk = small_disk(4096)
    config = tmp_path / "run.toml"
    config.write_text(
        lj_config_text(
            run="steps = 20",
            output=f'path = "{disk / "out.h5"}"\nevery = 10\nvelocities = true\n'
            "checkpoint_every = 0",  # a checkpoint at the start and at the end only
        )
    )
    assert _md(["run", str(config), *QUIET], tmp_path).returncode == 0
    free = os.statvfs(disk).f_bavail * os.statvfs(disk).f_frsize
    (disk / "filler").write_bytes(b"\0" * (free - 120_000))  # room for a few frames
    full = _md(["run", str(config), "--resume", "--steps", "100000", *QUIET], tmp_path)
    assert full.returncode == 2, full.stderr
    assert "disk full" in full.stderr and "no checkpoint was written" not in full.stderr
    assert f"the last checkpoint (step 20) in {disk / 'out.h5.ckpt'}" in full.stderr, full.stderr
    (disk / "filler").unlink()
    again = _md(["run", str(config), "--resume", "--steps", "60", *QUIET], tmp_path)
    assert again.returncode == 0, again.stderr
    from md.trajectory import read_trajectory

    assert read_trajectory(disk / "out.h5").steps.tolist() == [0, 10, 20, 30, 40, 50, 60]
