"""A run killed inside a frame's write damages that frame only.

Linux may stop a write of several pages part way when a SIGKILL arrives (the page-cache
write loop checks for a fatal signal between pages), so the bytes of the chunk being
written can be half old and half new. With every per-frame series chunked one frame a
chunk, the chunk written is always the new frame's own, and every earlier frame keeps
its bytes; the scalar series (step, time, the observables) were chunked 1024 frames a
chunk, rewritten at every frame, and a torn write of one lost all of them (seen: "frame
0 to 90 is damaged (observables/pyz ...)" after a SIGKILL, once in ~150 kills).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

import md
from md.errors import TrajectoryError
from md.trajectory import H5MDWriter, verify_frames
from md.trajectory.retries import open_h5md

ROOT = Path(__file__).resolve().parents[1]

SERIES = (
    "particles/trajectory/position/step",
    "particles/trajectory/position/time",
    "observables/pyz/value",
    "observables/total_energy/value",
)


def _written(path: Path, frames: int) -> Path:
    state = md.build.maxwell_boltzmann(md.lattice("fcc", 2, density=0.8), 1.0, seed=3)
    with H5MDWriter(path, state) as writer:
        for step in range(frames):
            state.step = 10 * step
            thermo = {"pyz": 0.1 * step, "total_energy": -1.0 - step}
            writer.write(state, thermo=thermo)
    return path


def _tear(path: Path, dataset: str, frame: int) -> None:
    """The bytes of ``frame`` in ``dataset``'s chunk overwritten, as a write stopped part
    way leaves them (new bytes over old in the chunk the frame lies in)."""
    with h5py.File(path, "r") as f:
        values = f[dataset]
        info = values.id.get_chunk_info_by_coord((frame, *([0] * (values.ndim - 1))))
        inside = (frame - info.chunk_offset[0]) * values.dtype.itemsize
    with open(path, "r+b") as handle:
        handle.seek(info.byte_offset + inside)
        old = handle.read(4)
        handle.seek(info.byte_offset + inside)
        handle.write(bytes(b ^ 0x5A for b in old))


def test_every_per_frame_series_is_chunked_one_frame_a_chunk(tmp_path):
    path = _written(tmp_path / "t.h5", 5)
    with h5py.File(path, "r") as f:
        found = []

        def keep(name, item):  # returns None: visititems stops at any other value
            if isinstance(item, h5py.Dataset):
                found.append(item)

        f.visititems(keep)
        per_frame = [d for d in found if d.maxshape and d.maxshape[0] is None]
        assert len(per_frame) > 10
        for dataset in per_frame:
            assert dataset.chunks[0] == 1, (dataset.name, dataset.chunks)


@pytest.mark.parametrize("dataset", SERIES)
def test_a_torn_last_frame_leaves_every_earlier_frame_intact(tmp_path, dataset):
    path = _written(tmp_path / "t.h5", 40)
    _tear(path, dataset, 39)
    with pytest.raises(TrajectoryError, match=r"frame 39 is damaged"):
        verify_frames(path)
    assert verify_frames(path, 39) == 39  # what a resume from an earlier checkpoint keeps
    with h5py.File(path, "r") as f:
        if dataset.endswith("pyz/value"):
            np.testing.assert_allclose(f[dataset][:39], 0.1 * np.arange(39))


def test_verify_names_the_first_damaged_frame_of_a_long_series(tmp_path):
    """Blocks of frames read at once, and a failed block searched chunk by chunk."""
    path = _written(tmp_path / "t.h5", 300)
    _tear(path, "observables/pyz/value", 217)
    with pytest.raises(TrajectoryError, match=r"frame 217 is damaged \(observables/pyz"):
        verify_frames(path)
    assert verify_frames(path, 217) == 217


CHILD = """
import sys
import md
from md.trajectory import H5MDWriter
state = md.build.maxwell_boltzmann(md.lattice("fcc", 2, density=0.8), 1.0, seed=1)
writer = H5MDWriter(sys.argv[1], state)
thermo = {"pyz": 1.0, "pxx": 2.0, "total_energy": -3.0, "temperature": 1.0}
print("ready", flush=True)
while True:
    state.step += 1
    writer.write(state, thermo=thermo)
"""


@pytest.mark.slow
def test_runs_killed_while_writing_keep_every_frame_but_the_last(tmp_path):
    """SIGKILL at random times into a writer that writes frames back to back (~150
    kills: with 1024-frame chunks about one in 150 lost the whole first chunk)."""
    rng = np.random.default_rng(5)
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
    }
    for trial in range(150):
        path = tmp_path / f"k{trial}.h5"
        child = subprocess.Popen(
            [sys.executable, "-c", CHILD, str(path)], stdout=subprocess.PIPE, env=env, text=True
        )
        assert child.stdout.readline().strip() == "ready"
        time.sleep(rng.uniform(0.02, 0.3))
        child.send_signal(signal.SIGKILL)
        child.communicate()
        with open_h5md(path) as f:
            count = len(f["particles/trajectory/position/value"])
        try:
            verify_frames(path)
        except TrajectoryError as error:  # only the last complete frame may be damaged
            assert f"frame {count - 1} is damaged" in str(error), (trial, error)
            assert verify_frames(path, count - 1) == count - 1
        path.unlink()
