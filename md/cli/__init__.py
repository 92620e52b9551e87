"""The ``md`` command: one module per subcommand, each with ``add_parser`` and ``main``.

The CLI builds objects and prints; the physics lives in the library, and a
run goes through :mod:`md.run` as it would from Python. Exit codes (see
:mod:`md.cli._common`): 0 success, 1 the dynamics blew up, 2 bad input
(config, structure file, existing output, unreadable trajectory, unwritable
output), 130 interrupted by SIGINT, 143 by SIGTERM (both after a checkpoint).
Nothing in the package imports the CLI.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence

from md._memory import keep_freed_memory
from md._version import __version__
from md.cli import (
    analyze,
    convert,
    info,
    integrators,
    minimize,
    render,
    run,
    sweep,
    validate,
)
from md.cli._common import EXIT_BROKEN_PIPE, EXIT_INTERRUPTED, ArgumentParser
from md.distributed.ranks import yield_when_oversubscribed
from md.interrupts import take_pending, watching

#: Subcommand modules, in the order ``md --help`` lists them.
SUBCOMMANDS = {
    "run": run,
    "minimize": minimize,
    "integrators": integrators,
    "analyze": analyze,
    "sweep": sweep,
    "info": info,
    "convert": convert,
    "render": render,
    "validate": validate,
}


def build_parser() -> ArgumentParser:
    """The ``md`` argument parser with every subcommand."""
    parser = ArgumentParser(prog="md", description="leapmd molecular dynamics engine")
    parser.add_argument("--version", action="version", version=f"leapmd {__version__}")
    subparsers = parser.add_subparsers(dest="command", required=True, parser_class=ArgumentParser)
    for module in SUBCOMMANDS.values():
        module.add_parser(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``md`` command; returns the exit code.

    The command's process-wide settings are made here, never by ``import md``:
    glibc's malloc keeps freed memory from now on, for the implicit integrators'
    temporaries (:func:`md._memory.keep_freed_memory`; it cannot be undone), and
    SIGINT is watched while the command runs, so a Ctrl-C that a compiling
    kernel swallows still stops it (:func:`md.interrupts.watching`; the previous
    handler is restored on return). Under an MPI launcher that started more ranks on
    the node than there are cores, the MPI library is told to yield the core while a
    rank waits (:func:`md.distributed.ranks.yield_when_oversubscribed`, before MPI
    starts). The console script enters through
    ``md_command.main``, which also turns a Ctrl-C while the libraries load into
    a line rather than a traceback.
    """
    keep_freed_memory()
    yield_when_oversubscribed()  # (more ranks than cores here: MPI waits yield the core)
    with watching():
        return _run_command(argv)


def _run_command(argv: Sequence[str] | None) -> int:
    args = build_parser().parse_args(argv)
    try:
        code = SUBCOMMANDS[args.command].main(args)
    except KeyboardInterrupt:
        print("md: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        # The reader went away (md info | head): stop quietly, as Unix tools do. Python
        # would report the failed flush of stdout at exit, so point it at /dev/null.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return EXIT_BROKEN_PIPE
    if take_pending():  # a Ctrl-C that a compiling kernel swallowed (md.interrupts)
        print("md: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    return code


__all__ = ["build_parser", "main"]
