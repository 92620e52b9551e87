"""``python -m md.cli.sweep_child PARENT_PID run ...``: ``md run`` that dies with its parent.

The sweep's Dask tasks start each run this way (see :mod:`md.sweeps.tasks`):
on Linux the child asks the kernel to kill it when its parent, the Dask
worker, dies (``PR_SET_PDEATHSIG``), so a retried task never writes beside a
run still going. The library is loaded before that request (``python -m``
imports ``md`` and ``md.cli`` before this module): a worker that dies in the
meantime is seen by the parent check after it, and the child exits.
"""

from __future__ import annotations

import os
import signal
import sys

from md.cli import main as md_main

#: Exit code when the parent (the Dask worker) died before this run started.
EXIT_ORPHANED = 137


def main(argv: list[str]) -> int:
    if len(argv) < 2 or not argv[0].isdigit():
        print(
            "usage: python -m md.cli.sweep_child PARENT_PID run ... (used by md sweep)",
            file=sys.stderr,
        )
        return 2
    parent = int(argv[0])
    if sys.platform.startswith("linux"):
        try:
            import ctypes  # Linux only: the prctl call below

            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            pass
    if os.getppid() != parent:
        return EXIT_ORPHANED  # the worker died while starting this run
    return md_main(argv[1:])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
