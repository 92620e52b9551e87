"""Outputs on a full disk, claims, special files and temporaries (issue 33), in real processes.

The disk-full cases mount a small tmpfs (root only; skipped where mounting is
not permitted) and run the ``md`` command in a child process, since what
broke was the process itself (segmentation faults and bus errors in HDF5).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import md
from conftest import lj_config_text
from md.cli import main

QUIET = ["-q", "--no-progress"]


def _md(args, cwd: Path, timeout: float = 900, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "md.cli", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=timeout,
        **kwargs,
    )


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
        [sys.executable, str(script)],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "PYTHONPATH": str(Path(md.__file__).resolve().parents[1])},
    )
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


@pytest.mark.parametrize("kb", [8, pytest.param(40, marks=pytest.mark.slow), 96])
def test_md_minimize_on_a_full_disk_leaves_nothing_and_the_rerun_works(
    run_config, monkeypatch, small_disk, kb
):
    """Before: a bus error at 8 kB; a zero-frame file at 96 kB that refused the re-run."""
    disk = small_disk(kb)
    command = ["minimize", str(run_config), "-o", str(disk / "relaxed.h5"), "-q"]
    done = _md(command, run_config.parent)
    _assert_disk_full_and_nothing_left(done, disk)
    _remount(disk, 4096)  # room made: the same command now works
    monkeypatch.chdir(run_config.parent)
    assert main(command) == 0
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
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
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
    tmp_path, monkeypatch, capsys, small_disk
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
    monkeypatch.chdir(tmp_path)
    assert main(["run", str(config), *QUIET]) == 0
    free = os.statvfs(disk).f_bavail * os.statvfs(disk).f_frsize
    (disk / "filler").write_bytes(b"\0" * (free - 120_000))  # room for a few frames
    capsys.readouterr()
    assert main(["run", str(config), "--resume", "--steps", "100000", *QUIET]) == 2
    err = capsys.readouterr().err
    assert "disk full" in err and "no checkpoint was written" not in err
    assert f"the last checkpoint (step 20) in {disk / 'out.h5.ckpt'}" in err, err
    (disk / "filler").unlink()
    assert main(["run", str(config), "--resume", "--steps", "60", *QUIET]) == 0
    from md.trajectory import read_trajectory

    assert read_trajectory(disk / "out.h5").steps.tolist() == [0, 10, 20, 30, 40, 50, 60]


# ---------------------------------------------- item 3: md convert on a full disk
@pytest.fixture(scope="module")
def trajectory_500(tmp_path_factory):
    """21 frames of 500 atoms."""
    folder = tmp_path_factory.mktemp("traj500")
    config = folder / "run.toml"
    output = 'path = "t.h5"\nevery = 10'
    config.write_text(lj_config_text(cells=5, run="steps = 200", output=output))
    assert _md(["run", str(config), *QUIET], folder).returncode == 0
    return folder / "t.h5"


@pytest.mark.parametrize(("suffix", "kb"), [("dcd", 16), ("dcd", 64), ("xtc", 48)])
def test_md_convert_on_a_full_disk_exits_2_and_leaves_nothing(
    trajectory_500, small_disk, suffix, kb
):
    """Before: "Wrote 21 frames" and exit 0, leaving a short file (the XTC and DCD writers
    are C code that does not check its writes)."""
    disk = small_disk(kb)
    done = _md(
        ["convert", str(trajectory_500), str(disk / f"out.{suffix}"), "--no-progress"],
        disk.parent,
    )
    _assert_disk_full_and_nothing_left(done, disk)


# ------------------------------------------------ item 14: md convert --step
def test_md_convert_refuses_a_huge_step_with_a_message(trajectory_500, tmp_path, capsys):
    out = tmp_path / "out.xyz"
    assert main(["convert", str(trajectory_500), str(out), "--step", str(10**23)]) == 2
    err = capsys.readouterr().err
    assert "step must be at most" in err and "Traceback" not in err, err
    assert not out.exists()
    # a step beyond the frames (but countable) takes the first frame, as a slice does
    assert main(["convert", str(trajectory_500), str(out), "--step", str(10**6)]) == 0
    assert out.read_text().count("step=") == 1


# ----------------------------------- item 4: nothing replaces a running run's output
def test_no_command_replaces_the_output_of_a_running_run(
    tmp_path, monkeypatch, capsys, trajectory_500
):
    """Before: md minimize and md convert --overwrite replaced it (and --resume failed)."""
    import signal
    import time

    config = tmp_path / "long.toml"
    config.write_text(
        lj_config_text(
            run="steps = 10000000\nthermo_every = 1000000",
            output='path = "live.h5"\nevery = 50\ncheckpoint_every = 1000',
        )
    )
    live = tmp_path / "live.h5"
    link = tmp_path / "link.h5"
    link.symlink_to(live)
    run = subprocess.Popen(
        [sys.executable, "-m", "md.cli", "run", str(config), *QUIET],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 600
        while not (tmp_path / "live.h5.ckpt").exists() or not live.exists():
            assert run.poll() is None and time.monotonic() < deadline, run.communicate()
            time.sleep(0.1)
        time.sleep(1.0)
        for target in (live, link):
            for command in (
                ["minimize", str(config), "-o", str(target), "--overwrite", "-q"],
                ["convert", str(trajectory_500), str(target), "--format", "xyz", "--overwrite"],
            ):
                inode = live.stat().st_ino
                monkeypatch.chdir(tmp_path)
                assert main(command) == 2, command
                err = capsys.readouterr().err
                assert "being written by another run" in err and f"pid {run.pid}" in err, err
                assert live.stat().st_ino == inode  # not replaced
                assert link.is_symlink()
        assert run.poll() is None  # the run goes on
    finally:
        run.send_signal(signal.SIGTERM)
        _, err = run.communicate(timeout=300)
    assert run.returncode == 143, err
    resume = ["run", str(config), "--resume", "--steps", str(_steps(live) + 100), *QUIET]
    assert main(resume) == 0
    from md.trajectory import verify_frames

    verify_frames(live)  # every frame intact after the resume


def _steps(path: Path) -> int:
    from md.checkpoint import read_checkpoint

    return read_checkpoint(Path(str(path) + ".ckpt")).state.step


def test_md_render_respects_a_claim_on_its_picture(tmp_path, trajectory_500):
    """md render claims its output as md run does, so two writers never share a picture."""
    from md._files import exclusive_claim

    picture = tmp_path / "shot.png"
    picture.write_bytes(b"old")
    with exclusive_claim(picture):
        done = _md(["render", str(trajectory_500), "-o", str(picture), "--overwrite"], tmp_path)
    assert done.returncode == 2 and "being written by another run" in done.stderr, done.stderr
    assert picture.read_bytes() == b"old"


# ------------------------------------ item 7: special files and symlinks as outputs
def _special(path: Path, kind: str) -> None:
    import stat

    if kind == "fifo":
        os.mkfifo(path)
        return
    if not hasattr(os, "geteuid") or os.geteuid() != 0:
        pytest.skip("making a device node needs root")
    os.mknod(path, stat.S_IFCHR | 0o666, os.makedev(1, 3))  # what /dev/null is


def _output_command(command: str, tmp_path: Path, target: Path, trajectory: Path) -> list[str]:
    config = tmp_path / "small.toml"
    config.write_text(lj_config_text(run="steps = 10"))
    return {
        "run": ["run", str(config), "-o", str(target), "--overwrite", *QUIET],
        "minimize": ["minimize", str(config), "-o", str(target), "--overwrite", "-q"],
        "convert": ["convert", str(trajectory), str(target), "--overwrite", "--no-progress"],
        "render": ["render", str(trajectory), "-o", str(target), "--overwrite", "--size", "64"],
    }[command]


SUFFIX = {"run": ".h5", "minimize": ".h5", "convert": ".xyz", "render": ".png"}


@pytest.mark.parametrize("kind", ["fifo", "device"])
@pytest.mark.parametrize("command", ["run", "minimize", "convert", "render"])
def test_overwrite_never_replaces_a_special_file(
    tmp_path, monkeypatch, capsys, trajectory_500, command, kind
):
    """Before: --overwrite unlinked a FIFO or a device node and put a regular file there."""
    import stat

    monkeypatch.chdir(tmp_path)
    target = tmp_path / f"special{SUFFIX[command]}"
    _special(target, kind)
    before = os.lstat(target)
    assert main(_output_command(command, tmp_path, target, trajectory_500)) == 2
    err = capsys.readouterr().err
    assert ("a FIFO" if kind == "fifo" else "a character device") in err, err
    assert "not a regular file" in err or "only to regular files" in err
    after = os.lstat(target)
    assert after.st_ino == before.st_ino and stat.S_IFMT(after.st_mode) == stat.S_IFMT(
        before.st_mode
    )


@pytest.mark.parametrize("command", ["run", "minimize", "convert", "render"])
def test_overwrite_writes_through_a_symlink_into_its_target(
    tmp_path, monkeypatch, trajectory_500, command
):
    """Before: the link was replaced by a regular file and its target left as it was."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "real").mkdir()
    target = tmp_path / "real" / f"target{SUFFIX[command]}"
    target.write_bytes(b"old contents")
    link = tmp_path / f"link{SUFFIX[command]}"
    link.symlink_to(target)
    assert main(_output_command(command, tmp_path, link, trajectory_500)) == 0
    assert link.is_symlink() and link.resolve() == target
    assert target.read_bytes() != b"old contents"
    if command in ("run", "minimize"):
        from md.trajectory import read_trajectory

        assert read_trajectory(link).n_frames >= 1


@pytest.mark.parametrize("command", ["run", "minimize", "convert", "render"])
def test_a_disk_without_a_byte_left_is_reported_by_every_command(
    tmp_path, monkeypatch, capsys, small_disk, trajectory_500, command
):
    """Before: md minimize ended in a traceback (ENOSPC writing the claim's lock file),
    md run said "No space left on device" without naming it."""
    disk = small_disk(64)
    with open(disk / "filler", "wb") as filler, contextlib.suppress(OSError):
        filler.write(b"\0" * (1 << 20))  # fills the disk: not a byte left
    assert os.statvfs(disk).f_bavail == 0
    monkeypatch.chdir(tmp_path)
    target = disk / f"out{SUFFIX[command]}"
    assert main(_output_command(command, tmp_path, target, trajectory_500)) == 2
    err = capsys.readouterr().err
    assert "disk full" in err, err
    assert sorted(p.name for p in disk.iterdir()) == ["filler"]


# ------------------------------- item 8: an interrupted md convert leaves no temporaries
@pytest.fixture(scope="module")
def long_trajectory(tmp_path_factory):
    """300 frames of 2000 atoms (no dynamics needed): converting them to extxyz takes seconds."""
    import numpy as np

    from md.state import State
    from md.trajectory import H5MDWriter

    path = tmp_path_factory.mktemp("long") / "t.h5"
    rng = np.random.default_rng(3)
    n = 2000
    state = State(
        positions=20 * rng.random((n, 3)),
        velocities=np.zeros((n, 3)),
        masses=np.ones(n),
        box=np.full(3, 20.0),
        pbc=np.ones(3, bool),
    )
    with H5MDWriter(path, state) as writer:
        for step in range(300):
            state.step = step
            writer.write(state)
    return path


def _convert_until_its_temporary_appears(trajectory: Path, out: Path) -> subprocess.Popen:
    import time

    process = subprocess.Popen(
        [sys.executable, "-m", "md.cli", "convert", str(trajectory), str(out), "--no-progress"],
        cwd=out.parent,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 300
    while not list(out.parent.glob(f".{out.name}.*.tmp")):
        assert process.poll() is None and time.monotonic() < deadline, process.communicate()
        time.sleep(0.01)
    return process


@pytest.mark.parametrize("name", ["SIGTERM", "SIGINT"])
def test_a_signal_during_md_convert_says_so_and_leaves_no_temporary(
    tmp_path, long_trajectory, name
):
    """Before: SIGTERM ended md convert silently (exit -15) with its temporary left."""
    import signal

    out = tmp_path / "out.extxyz"
    process = _convert_until_its_temporary_appears(long_trajectory, out)
    process.send_signal(getattr(signal, name))
    _, err = process.communicate(timeout=300)
    assert process.returncode == (143 if name == "SIGTERM" else 130), err
    assert f"{name} received; stopped, nothing was written to {out}" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_the_next_md_convert_removes_a_killed_conversions_temporary(tmp_path, long_trajectory):
    import signal

    out = tmp_path / "out.extxyz"
    process = _convert_until_its_temporary_appears(long_trajectory, out)
    process.send_signal(signal.SIGKILL)  # nothing can clean up after this
    process.communicate(timeout=300)
    assert list(tmp_path.glob(".out.extxyz.*.tmp"))
    assert main(["convert", str(long_trajectory), str(out), "--stop", "3", "--no-progress"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.extxyz"]


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # the lost one
def test_a_stop_signal_whose_exception_is_swallowed_still_stops_a_whole_file_write(
    tmp_path, capsys
):
    """Before (CI, stop 39): SIGTERM landed in a weakref callback, Python printed "Exception
    ignored" and md convert went on to write its file and exit 0."""
    import os
    import signal

    from md._files import atomic_path
    from md.cli._common import writing_whole_file

    class SignalledWhileCollected:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGTERM)  # its KeyboardInterrupt is raised here, and lost

    out = tmp_path / "out.txt"

    def body() -> int:
        with atomic_path(out) as temporary:
            temporary.write_text("complete")
            SignalledWhileCollected()
        return 0

    assert writing_whole_file("convert", out, body) == 143
    assert "SIGTERM received; stopped, nothing was written to" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
