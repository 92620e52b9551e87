"""What ``md run`` and ``md minimize`` share before and around writing: the statuses their
``execute`` reports, the checks of an output path (a writable regular file, none of the
run's inputs, claimed by no live run), and SIGINT/SIGTERM caught as a stop at the next
step (:class:`StopRequest`, :func:`catch_stop_signals`, :func:`restore_signals`).
"""

from __future__ import annotations

import os
import signal
from collections.abc import Callable
from pathlib import Path

from md._files import claim_holder, output_target
from md.config import Config, input_files
from md.errors import ConfigError
from md.interrupts import take_pending

#: Statuses of a finished :meth:`md.run.PreparedRun.execute` (and, but ``aborted``, of
#: :meth:`md.relax.PreparedMinimize.execute`).
COMPLETED, FAILED, OUTPUT_ERROR, STOPPED, ABORTED = (
    "completed",
    "failed",
    "output_error",
    "stopped",
    "aborted",
)


def writable_output(output: Path) -> Path:
    """The file an output path writes (a symlink's target); ConfigError if it cannot be one.

    Refused: a path naming no file, a directory, a special file (FIFO, device
    node, socket: never replaced), a missing or unwritable directory.
    """
    if output.name in ("", ".", ".."):
        raise ConfigError(f"output path {str(output)!r} names no file")
    if output.is_dir():
        raise ConfigError(f"output path {output} is a directory")
    try:
        target = output_target(output)
    except ValueError as error:
        raise ConfigError(str(error)) from None
    if not target.parent.is_dir():
        raise ConfigError(f"output directory {target.parent} does not exist")
    if not os.access(target.parent, os.W_OK | os.X_OK):
        raise ConfigError(f"output directory {target.parent} is not writable")
    return target


def refuse_claimed(output: Path) -> None:
    """ConfigError if a live run holds the claim on ``output`` (see md._files.exclusive_claim)."""
    holder = claim_holder(output)
    if holder is not None:
        raise ConfigError(
            f"{output} is being written by another run ({holder}); wait for it to end, "
            "or choose another --output"
        )


def _input_files(config: Config, path_or_config) -> list[Path]:
    """The files a run reads: the config, a structure file, bonds and angles files."""
    files = [] if isinstance(path_or_config, Config) else [Path(path_or_config)]
    return files + input_files(config)


def refuse_inputs_as_outputs(config: Config, config_file: str, path_or_config, outputs) -> None:
    """Raise ConfigError if an output (or its checkpoint) is one of the run's input files."""
    for source in _input_files(config, path_or_config):
        for target in outputs:
            try:
                same = source.exists() and target.exists() and os.path.samefile(source, target)
            except OSError:
                same = False
            if same or source.resolve() == target.resolve():
                raise ConfigError(
                    f"output {target} is an input of this run ({source}); choose another "
                    "--output (--overwrite never replaces the run's own inputs)"
                )


def catch_stop_signals(request: Callable[[str], None], pending: Callable[[], str | None]) -> dict:
    """SIGINT/SIGTERM call ``request(name)`` (stop at the next step); a second one stops at once.

    ``pending()`` says whether a stop was asked for already. Returns the
    handlers replaced, for :func:`restore_signals`.
    """

    def handler(signum, frame):
        if pending() is not None:
            raise KeyboardInterrupt
        request(signal.Signals(signum).name)

    previous = {}
    for signum in (signal.SIGINT, signal.SIGTERM):
        try:
            previous[signum] = signal.signal(signum, handler)
        except ValueError:  # not the main thread: leave signals alone
            break
    if previous and take_pending():  # a Ctrl-C during start-up that compilation swallowed
        request("SIGINT")
    return previous


class StopRequest:
    """A stop asked for by a signal while minimising: FIRE's ``stop`` callable."""

    def __init__(self) -> None:
        self.signal: str | None = None

    def request(self, name: str) -> None:
        self.signal = name

    def pending(self) -> str | None:
        return self.signal

    def __call__(self) -> bool:
        return self.signal is not None


def restore_signals(previous: dict) -> None:
    """Put back the handlers :func:`catch_stop_signals` replaced."""
    for signum, handler in previous.items():
        signal.signal(signum, handler)


__all__ = [
    "ABORTED",
    "COMPLETED",
    "FAILED",
    "OUTPUT_ERROR",
    "STOPPED",
    "StopRequest",
    "catch_stop_signals",
    "refuse_claimed",
    "refuse_inputs_as_outputs",
    "restore_signals",
    "writable_output",
]
