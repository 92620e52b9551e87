"""Writing output files so that a crash never leaves half of one (layer 0).

Every file the package writes as a whole (trajectory layouts, checkpoints,
sweep configs) goes through :func:`atomic_path`: written under a temporary
name in the target's directory, flushed to disk, then renamed over the
target, and the directory synced so the rename itself survives a power cut.
Readers therefore see the old file or the new one, never a mixture.
"""

from __future__ import annotations

import contextlib
import csv
import errno
import os
import stat
import tempfile
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

from md.errors import OutputBusyError
from md.interrupts import raise_if_stopped


def usual_permissions(descriptor: int) -> None:
    """Give a file from ``tempfile.mkstemp`` (mode 0600) the mode a plain open() would.

    That is 0666 less the process umask, so outputs renamed into place are as
    readable as any other file the user writes.
    """
    umask = os.umask(0)
    os.umask(umask)
    os.fchmod(descriptor, 0o666 & ~umask)


def sync_directory(directory) -> None:
    """Make a rename in ``directory`` durable (POSIX); harmless where it cannot be opened."""
    try:
        descriptor = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(descriptor)
    except OSError:
        pass
    finally:
        os.close(descriptor)


def fsync_file(path) -> None:
    """Flush a closed file's data to disk."""
    with open(path, "rb+") as handle:
        os.fsync(handle.fileno())


def move_into_place(source, target, exclusive: bool = False) -> None:
    """Rename a complete file over ``target`` durably (fsync file, rename, fsync directory).

    With ``exclusive``, refuse (``FileExistsError``) if ``target`` exists, atomically:
    the file is hard-linked to the new name, which fails if the name is taken.
    """
    source, target = Path(source), Path(target)
    fsync_file(source)
    if exclusive:
        os.link(source, target)
        os.unlink(source)
    else:
        os.replace(source, target)
    sync_directory(target.parent)


#: What ``stat`` calls the files that are not regular files, for messages.
_KINDS = (
    (stat.S_ISDIR, "a directory"),
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def output_target(path) -> Path:
    """The file that writing the output ``path`` replaces: a symlink's target, else ``path``.

    Outputs are written through a symbolic link into the file it points to
    (the link stays), and only ever replace regular files: a FIFO, a device
    node (``/dev/null``), a socket or a directory is refused, never unlinked.

    Raises
    ------
    ValueError
        If ``path`` (or the end of its links) exists and is not a regular file,
        or its links cannot be followed (a loop); the message names the kind.
    """
    path = Path(path)
    target = Path(os.path.realpath(path)) if path.is_symlink() else path
    try:
        mode = os.stat(target).st_mode
    except FileNotFoundError:
        return target  # a new file (or a dangling link's target, created as `>` would)
    except OSError as error:
        raise ValueError(f"output {path}: {error.strerror}") from None
    if stat.S_ISREG(mode):
        return target
    kind = next((name for test, name in _KINDS if test(mode)), "not a regular file")
    via = f" (the target of symlink {path})" if target != path else ""
    raise ValueError(
        f"output {target}{via} is {kind}; outputs are written only to regular files "
        "(--overwrite never replaces anything else): choose another output"
    )


@contextlib.contextmanager
def atomic_path(path, exclusive: bool = False) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success move it into place durably.

    The temporary file exists (empty, with the usual permissions) when the
    block starts, so writers may open it by name in any mode. If the block
    raises, the temporary file is removed and ``path`` is left as it was.
    A symbolic link is written through (its target is replaced, the link
    stays); a ``path`` that is not a regular file raises ValueError before
    anything is written (:func:`output_target`). A full disk raises OSError
    (ENOSPC) saying "disk full".

    Examples
    --------
    >>> import pathlib, tempfile
    >>> target = pathlib.Path(tempfile.mkdtemp()) / "out.txt"
    >>> with atomic_path(target) as temporary:
    ...     _ = temporary.write_text("done")
    >>> target.read_text()
    'done'
    """
    path = output_target(path)
    try:
        descriptor, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as error:
        raise output_error(error, path) from None
    temporary = Path(name)
    try:
        usual_permissions(descriptor)
        os.close(descriptor)
        yield temporary
        raise_if_stopped()  # a stop signal whose KeyboardInterrupt was swallowed
        move_into_place(temporary, path, exclusive=exclusive)
    except OSError as error:
        with contextlib.suppress(OSError):
            temporary.unlink()
        if disk_full(error):
            raise output_error(error, path) from None
        raise
    except BaseException:
        with contextlib.suppress(OSError):
            temporary.unlink()
        raise


def write_text_atomic(path, text: str) -> None:
    """Replace ``path`` with ``text`` atomically and durably."""
    with atomic_path(path) as temporary:
        temporary.write_text(text)


def write_csv_rows(path, columns: Sequence[str], rows: Iterable[dict]) -> None:
    """Write ``rows`` (dicts keyed by ``columns``) under a header line; create ``path``
    exclusively, so an existing file is never replaced (:class:`FileExistsError`)."""
    with open(path, "x", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(columns))
        writer.writeheader()
        writer.writerows(rows)


def write_bytes_atomic(path, data: bytes, exclusive: bool = False) -> None:
    """Write ``data`` to ``path`` atomically and durably (see :func:`atomic_path`).

    Python's own writes report a full disk as ``OSError`` (ENOSPC), which
    :func:`atomic_path` words as "disk full", removing the temporary file.
    """
    with atomic_path(path, exclusive=exclusive) as temporary:
        temporary.write_bytes(data)


def disk_full(error: BaseException) -> bool:
    """Whether ``error`` says the disk (or the user's quota) is full.

    Python reports it as ``OSError`` with errno ENOSPC or EDQUOT; HDF5 (through
    h5py) as a ``RuntimeError`` or ``OSError`` whose message carries the C
    library's text.
    """
    if isinstance(error, OSError) and error.errno in (errno.ENOSPC, errno.EDQUOT):
        return True
    text = str(error).lower()
    return any(
        words in text
        for words in ("no space left on device", "disk quota exceeded", "errno = 28,", "disk full")
    )


def output_error(error: BaseException, path, detail: str = "") -> OSError:
    """The ``OSError`` to report for a failed write of ``path``.

    A full disk (:func:`disk_full`) becomes ENOSPC saying "disk full: cannot
    write PATH" (and ``detail``); another ``OSError`` is returned unchanged;
    anything else (HDF5's ``RuntimeError``) becomes an ``OSError`` (EIO)
    carrying its message.
    """
    if disk_full(error):
        text = str(error)
        if "disk full" in text:
            return error if isinstance(error, OSError) else OSError(errno.ENOSPC, text)
        extra = f"; {detail}" if detail else ""
        return OSError(errno.ENOSPC, f"disk full: cannot write {path}{extra}")
    if isinstance(error, OSError):
        return error
    return OSError(errno.EIO, f"cannot write {path}: {error}")


@contextlib.contextmanager
def exclusive_claim(path) -> Iterator[Path]:
    """Hold an exclusive claim on ``path`` (a lock file ``PATH.lock``) for the block.

    The claim is an ``flock`` on ``PATH.lock``, which records the holder's pid
    and host; the kernel drops it when the holder exits, however it exits, so
    a killed run never leaves a stale claim. A second claimant fails at once
    with :class:`OutputBusyError` naming the holder. The lock file is removed
    when the block ends; a disk too full to hold it raises OSError saying
    "disk full" (the lock file is removed again).
    """
    import fcntl  # POSIX only, as flock is

    lock_path = Path(str(path) + ".lock")
    while True:
        descriptor = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                holder = os.read(descriptor, 200).decode(errors="replace").strip()
            finally:
                os.close(descriptor)
            raise OutputBusyError(
                f"{path} is being written by another run ({holder or 'unknown process'}); "
                f"wait for it to end, or choose another output"
            ) from None
        # A holder that just finished unlinks the file it locked: ours must still be there.
        try:
            current = os.path.samestat(os.fstat(descriptor), os.stat(lock_path))
        except FileNotFoundError:
            current = False
        if current:
            break
        os.close(descriptor)
    try:
        try:
            os.ftruncate(descriptor, 0)
            host = os.uname().nodename if hasattr(os, "uname") else "this host"  # not on Windows
            os.write(descriptor, f"pid {os.getpid()} on {host}".encode())
        except OSError as error:  # a full disk has no room for even these few bytes
            raise output_error(error, path, f"no room for its lock file {lock_path.name}") from None
        yield lock_path
    finally:
        with contextlib.suppress(OSError):
            os.unlink(lock_path)
        os.close(descriptor)


def claim_holder(path) -> str | None:
    """Who holds the claim on ``path`` (``"pid N on HOST"``), or None if nobody does."""
    import fcntl  # POSIX only, as flock is

    lock_path = Path(str(path) + ".lock")
    try:
        descriptor = os.open(lock_path, os.O_RDONLY)
    except OSError:
        return None
    try:
        fcntl.flock(descriptor, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.read(descriptor, 200).decode(errors="replace").strip()
        return holder or "another process"
    finally:
        os.close(descriptor)
    return None


def remove_stale_temporaries(path) -> list[Path]:
    """Remove temporaries :func:`atomic_path` left beside ``path`` (a killed writer's).

    Call only while holding :func:`exclusive_claim` on the output, so that no
    live writer owns them. Returns the removed paths.
    """
    path = Path(path)
    removed = []
    for stale in path.parent.glob(f".{path.name}.*.tmp"):
        with contextlib.suppress(OSError):
            stale.unlink()
            removed.append(stale)
    return removed


def unwritable_folder(folder) -> str | None:
    """Why files cannot be made in ``folder``, or None if they can (it may not exist yet).

    Looks at the folder, or at its nearest existing parent when it is still to
    be made: a path that is not a folder, a read-only filesystem, or no write
    permission. Nothing is created. A later write can still fail (a full
    disk), so callers handle ``OSError`` as well.
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        return f"{folder} exists and is not a folder"
    existing = folder
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        return f"{existing} is not a folder, so {folder} cannot be made"
    if os.access(existing, os.W_OK | os.X_OK):
        return None
    try:
        read_only = bool(os.statvfs(existing).f_flag & os.ST_RDONLY)
    except OSError:
        read_only = False
    why = "is on a read-only filesystem" if read_only else "is not writable"
    return f"{existing} {why}" + ("" if existing == folder else f", so {folder} cannot be made")


@contextlib.contextmanager
def removed_on_error() -> Iterator[list[Path]]:
    """Yield a list for the paths a block writes; if the block raises OSError, remove them.

    A command that writes several files (CSV files, figures) then leaves none
    of a set it could not finish (a full disk) rather than some of them.
    """
    written: list[Path] = []
    try:
        yield written
    except OSError:
        for path in written:
            with contextlib.suppress(OSError):
                Path(path).unlink()
        raise
