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


def main() -> int:
    """Run the ``md`` command on ``sys.argv``; return its exit code."""
    try:
        from md.cli import main as run_command  # loads numpy, numba and the kernels

        return run_command()
    except KeyboardInterrupt:  # before md.cli.main catches it itself: while loading
        print("md: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
