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


#: The signal lists of the :func:`sigterm_as_interrupt` blocks now open, innermost last.
_writing_blocks: list[list[str]] = []


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[list[str]]:
    """Inside the block, SIGTERM raises KeyboardInterrupt, as Ctrl-C does.

    A command that writes a file whole (through a temporary file) then
    cleans up on ``kill`` as on Ctrl-C, instead of dying with its temporary
    file left behind. Yields a list that holds the name of each stop signal
    (``"SIGTERM"``, ``"SIGINT"``) that came, so the command can say which one
    stopped it. Both are recorded before they raise: an exception raised
    where Python only prints it (a weakref callback, a ``__del__``, a ctypes
    callback) is lost, and :func:`raise_if_stopped`, which
    :func:`md._files.atomic_path` calls before it moves a file into place,
    raises it again. The previous handlers are restored at the end; outside
    the main thread this does nothing.
    """
    received: list[str] = []

    def handler(signum, frame):
        received.append(signal.Signals(signum).name)
        raise KeyboardInterrupt

    if threading.current_thread() is not threading.main_thread():
        yield received
        return
    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGTERM, signal.SIGINT)}
    _writing_blocks.append(received)
    try:
        yield received
    finally:
        _writing_blocks.remove(received)
        for sig, handler_before in previous.items():
            if handler_before is not None:  # None: set outside Python, cannot be put back
                signal.signal(sig, handler_before)


def raise_if_stopped() -> None:
    """Raise KeyboardInterrupt if a stop signal came inside an open :func:`sigterm_as_interrupt`.

    For the last moment before a result becomes visible: a signal whose
    exception was swallowed on its way still stops the command there.
    """
    if any(_writing_blocks):
        raise KeyboardInterrupt


__all__ = ["raise_if_stopped", "sigterm_as_interrupt", "take_pending", "watch", "watching"]
