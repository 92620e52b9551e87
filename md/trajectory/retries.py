"""Opening an H5MD file that a run may be writing: transient read errors retried, a file
read again while its writer added frames meanwhile.
"""

from __future__ import annotations

import time
from pathlib import Path

import h5py

from md.errors import TrajectoryError

#: Signs of an HDF5 error caused by a concurrent writer's frame in flight, not by damage.
_TRANSIENT = ("truncated file", "addr overflow", "eoa", "stored_eof")


def retry_transient(action, attempts: int = 20, pause: float = 0.05):
    """Run ``action()``, retrying for up to a second while it fails as a live writer's
    half-written frame makes reads fail (the run flushes each frame whole)."""
    for attempt in range(attempts):
        try:
            return action()
        except (OSError, AttributeError) as error:  # MDAnalysis's reader: AttributeError
            transient = any(sign in str(error).lower() for sign in _TRANSIENT) or (
                isinstance(error, AttributeError) and "_file" in str(error)
            )
            if not transient or attempt == attempts - 1:
                raise
            time.sleep(pause)
    return None


def _file_signature(path: Path) -> tuple[int, int] | None:
    try:
        stat = path.stat()
    except OSError:
        return None
    return stat.st_size, stat.st_mtime_ns


def while_written(path: Path, read, settle: float = 0.1, patience: float = 5.0):
    """Run ``read()`` (which opens ``path`` itself), again while the file is being written.

    A reader that opens the file while a run flushes a frame can see the
    frame's datasets grown before its data, which reads as a truncated file
    ("addr overflow") or a failed checksum. Such an error is believed only
    once the file has stayed unchanged (size and modification time) from
    the start of the read to ``settle`` seconds after it failed; while the
    file keeps changing the read is tried again with a fresh open, for up to
    ``patience`` seconds. A damaged file that nothing writes is reported
    after one extra pause of ``settle`` seconds.
    """
    deadline = time.monotonic() + patience
    while True:
        before = _file_signature(path)
        try:
            return read()
        except TrajectoryError:
            if before is None:  # no file: nothing is writing it
                raise
            time.sleep(settle)
            if _file_signature(path) == before or time.monotonic() > deadline:
                raise


def open_h5md(path: Path) -> h5py.File:
    if not path.exists():
        raise TrajectoryError(f"{path}: no such file")
    try:
        # Read-only; a file a run is writing can be read, since the writer takes no
        # HDF5 file lock. A frame being written can leave the file's recorded end
        # briefly ahead of its real end: such opens are retried.
        f = retry_transient(lambda: h5py.File(path, "r"))
    except OSError as error:
        raise TrajectoryError(f"{path}: not a readable HDF5 file ({error})") from None
    try:
        ours = "h5md" in f and "particles" in f
    except (RuntimeError, OSError, KeyError) as error:  # damaged metadata
        f.close()
        raise TrajectoryError(f"{path}: a damaged HDF5 file ({error})") from None
    if not ours:
        f.close()
        raise TrajectoryError(
            f"{path}: an HDF5 file, but not in the H5MD layout (no h5md/particles)"
        )
    return f
