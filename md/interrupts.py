"""Ctrl-C that is never lost while the ``md`` command starts.

Python turns SIGINT into a KeyboardInterrupt at the next bytecode. While numba
compiles or loads a kernel, that bytecode can be a ctypes callback of LLVM's
object cache, and an exception raised in a ctypes callback is printed
("Exception ignored ...") and dropped: the interrupt would vanish and a long
run would go on. :func:`watch` installs a handler that first records the
signal, then raises as Python's own does; whoever takes over SIGINT later (the
run's stop handler, see :mod:`md.run`) calls :func:`take_pending` and honours
one that was dropped. The ``md`` command watches while it runs
(:func:`watching`, in :func:`md.cli.main`); ``import md`` installs nothing.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator

#: Signals recorded by the start-up handler and not yet taken.
_pending: list[int] = []


def _record_and_raise(signum, frame) -> None:
    _pending.append(signum)
    raise KeyboardInterrupt


def watch() -> None:
    """Record every SIGINT from now on, then raise KeyboardInterrupt as Python does.

    Only from the main thread (elsewhere signals cannot be handled); a no-op there.
    """
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, _record_and_raise)


@contextlib.contextmanager
def watching() -> Iterator[None]:
    """:func:`watch` inside the block; SIGINT's previous handler is restored after it.

    Only from the main thread; elsewhere the block runs with signals left alone.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.getsignal(signal.SIGINT)
    watch()
    try:
        yield
    finally:
        if previous is not None:  # None: a handler not set from Python, which cannot be put back
            signal.signal(signal.SIGINT, previous)


def take_pending() -> bool:
    """Whether a SIGINT arrived since :func:`watch` (or the last call); forgets it."""
    seen = bool(_pending)
    _pending.clear()
    return seen


__all__ = ["take_pending", "watch", "watching"]
