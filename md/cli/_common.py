"""What every subcommand shares: exit codes, the argument parser class, failure messages."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from typing import TypeVar

from md.interrupts import sigterm_as_interrupt

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130
EXIT_TERMINATED = 143  # SIGTERM: 128 + 15
EXIT_BROKEN_PIPE = 141  # SIGPIPE: 128 + 13, the reader of our output went away
_T = TypeVar("_T")


class ArgumentParser(argparse.ArgumentParser):
    """argparse with ``md: error:`` messages and exit code 2 for bad usage."""

    def error(self, message: str):  # argparse's own exit code is 2 as well
        self.print_usage(sys.stderr)
        self.exit(EXIT_BAD_INPUT, f"md: error: {message}\n")


def fail(message: str) -> None:
    """Print ``md: error: MESSAGE`` to stderr (the caller returns the exit code)."""
    print(f"md: error: {message}", file=sys.stderr)


def exit_for_signal(name: str | None) -> int:
    """The exit code for a command stopped by signal ``name``: 143 for SIGTERM, else 130."""
    return EXIT_TERMINATED if name == "SIGTERM" else EXIT_INTERRUPTED


def writing_whole_file(command: str, output, body: Callable[[], int]) -> int:
    """Return ``body()``, or 130/143 with a message if SIGINT/SIGTERM stops it.

    For commands that write one file through a temporary (``md convert``,
    ``md render``): SIGTERM raises as Ctrl-C does, so the temporary is removed
    either way and the command says that nothing was written to ``output``.
    """
    with sigterm_as_interrupt() as terminated:
        try:
            code = body()
        except KeyboardInterrupt:
            code = None
        if code is not None and not terminated:
            return code
        name = terminated[0] if terminated else "SIGINT"
        if code is None:
            what = f"stopped, nothing was written to {output}"
        else:  # the signal's exception was swallowed after the file was in place
            what = f"stopped after {output} was written"
        print(f"md {command}: {name} received; {what}", file=sys.stderr)
        return exit_for_signal(name)


def built_unless_stopped(
    build: Callable[[], _T], command: str, stage: str
) -> tuple[_T | None, int | None]:
    """``build()`` (validating, building, compiling: before the command's own stop handler)
    with SIGTERM taken as a stop: ``(result, None)``, or, when a stop signal came, ``(None,
    exit code)`` after a line saying it came before ``stage`` started and nothing was written.
    The build's own errors pass through."""
    with sigterm_as_interrupt() as received:
        result = None
        try:
            result = build()
        except KeyboardInterrupt:
            if not received:
                received.append("SIGINT")
        if received:  # raised, or swallowed on its way (a compiling kernel's callback)
            print(
                f"md {command}: {received[0]} received before {stage} started; nothing was written",
                file=sys.stderr,
            )
            return None, exit_for_signal(received[0])
    return result, None
