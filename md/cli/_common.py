"""What every subcommand shares: exit codes, the argument parser class, failure messages."""

from __future__ import annotations

import argparse
import sys

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130
EXIT_TERMINATED = 143  # SIGTERM: 128 + 15
EXIT_BROKEN_PIPE = 141  # SIGPIPE: 128 + 13, the reader of our output went away


class ArgumentParser(argparse.ArgumentParser):
    """argparse with ``md: error:`` messages and exit code 2 for bad usage."""

    def error(self, message: str):  # argparse's own exit code is 2 as well
        self.print_usage(sys.stderr)
        self.exit(EXIT_BAD_INPUT, f"md: error: {message}\n")


def fail(message: str) -> None:
    """Print ``md: error: MESSAGE`` to stderr (the caller returns the exit code)."""
    print(f"md: error: {message}", file=sys.stderr)
