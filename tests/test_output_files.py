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
