"""The ``md`` console script's entry: :func:`md.cli.main`, with Ctrl-C at start-up a line.

Outside the ``md`` package on purpose: ``import md.cli`` first runs
``md/__init__``, which loads numpy, numba and the kernel modules (a second
or more), and a Ctrl-C in that time would print a KeyboardInterrupt
traceback. Here the import itself is inside the ``try``. Everything else the
command sets for its process (the allocator, the SIGINT watch) is set by
:func:`md.cli.main`, so ``python -m md.cli`` and the sweep's child runs get
it too; ``import md`` sets nothing.
"""

from __future__ import annotations

import sys

#: Exit code of an interrupted command (``md.cli._common.EXIT_INTERRUPTED``, not imported:
#: this module must not import ``md`` before its ``try``).
EXIT_INTERRUPTED = 130


#: Ctrl-Cs that landed in a callback while the command loaded (see :func:`_keep_interrupt`).
_LOST: list[BaseException] = []


def _keep_interrupt(unraisable, previous=sys.unraisablehook) -> None:
    """A Ctrl-C that lands in a callback (importlib's module-lock weakref callback, while
    the kernels load) is "ignored" by Python, which prints a traceback and drops the signal:
    keep it instead, for :func:`main` to honour once the import returns."""
    if isinstance(unraisable.exc_value, KeyboardInterrupt):
        _LOST.append(unraisable.exc_value)
        return
    previous(unraisable)


def main() -> int:
    """Run the ``md`` command on ``sys.argv``; return its exit code."""
    sys.unraisablehook = _keep_interrupt
    try:
        from md.cli import main as run_command  # loads numpy, numba and the kernels

        if _LOST:  # (a Ctrl-C while loading that Python would have dropped)
            raise KeyboardInterrupt
        return run_command()
    except KeyboardInterrupt:  # before md.cli.main catches it itself: while loading
        print("md: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
