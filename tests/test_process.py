"""Process-wide settings belong to the ``md`` command, never to ``import md``.

The command keeps freed memory (glibc's ``mallopt``, :mod:`md._memory`) and
watches SIGINT while it runs (:mod:`md.interrupts`); a library imported into
someone's notebook or ASE script must change neither, nor ``sys.excepthook``.
Each check runs in a fresh process whose ``ctypes`` hands out a recording
``mallopt`` (so nothing is set and every call is seen) and whose
``signal.signal`` records what is installed for SIGINT.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from md._memory import MMAP_THRESHOLD, TRIM_THRESHOLD
from tests.conftest import lj_config_text

ROOT = Path(__file__).resolve().parents[1]

_RECORDING = '''
import ctypes, json, signal, sys

mallopt_calls = []


class _Recording(ctypes.CDLL):
    """A C library whose mallopt records its calls and changes nothing."""

    def __getattr__(self, name):
        if name == "mallopt":
            def mallopt(parameter, value):
                mallopt_calls.append([int(parameter), int(value)])
                return 1
            return mallopt
        return super().__getattr__(name)


ctypes.CDLL = _Recording
ctypes.cdll = ctypes.LibraryLoader(_Recording)
sigint_handlers = []
_signal = signal.signal


def _recording_signal(signum, handler):
    if signum == signal.SIGINT:
        sigint_handlers.append(getattr(handler, "__qualname__", repr(handler)))
    return _signal(signum, handler)


signal.signal = _recording_signal
excepthook, sigint = sys.excepthook, signal.getsignal(signal.SIGINT)


def report(**extra):
    print(json.dumps({
        "mallopt": mallopt_calls, "sigint_handlers": sigint_handlers,
        "excepthook_kept": sys.excepthook is excepthook,
        "sigint_kept": signal.getsignal(signal.SIGINT) is sigint, **extra,
    }))
'''

_LIBRARY = """
import md, potentials, integrators
from integrators.implicit_euler import ImplicitEuler
state = md.lattice("fcc", 3, density=0.8442)
md.maxwell_boltzmann(state, temperature=1.0, seed=1)
for integrator in (integrators.VelocityVerlet(0.005), ImplicitEuler(0.005)):
    md.Simulation(state.copy(), [potentials.LennardJones(cutoff=2.5)], integrator).run(3)
sim, summary = md.run_config("run.toml", steps=5)
report(status=summary.status)
"""

_COMMAND = """
import md_command
sys.argv = ["md", "run", "run.toml", "-q", "--no-progress"]
report(code=md_command.main())
"""


def _environment() -> dict[str, str]:
    """This checkout first on the path: md_command is a top-level module beside md."""
    paths = [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])]
    return {**os.environ, "PYTHONPATH": os.pathsep.join(paths)}


def _recorded(code: str, cwd: Path) -> dict:
    (cwd / "run.toml").write_text(lj_config_text(run="steps = 5"))
    done = subprocess.run(
        [sys.executable, "-c", _RECORDING + code],
        cwd=cwd,
        env=_environment(),
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_importing_md_and_running_changes_nothing_process_wide(tmp_path):
    """``import md``, two small simulations (velocity Verlet and implicit Euler) and
    ``md.run_config``: no mallopt call, no excepthook, and SIGINT's handler as it was
    (run_config catches SIGINT while it runs and puts the handler back)."""
    seen = _recorded(_LIBRARY, tmp_path)
    assert seen["status"] == "completed"
    assert seen["mallopt"] == []
    assert seen["excepthook_kept"]
    assert seen["sigint_kept"]


def test_the_md_command_keeps_freed_memory_and_watches_sigint(tmp_path):
    """The console script's entry sets both (the same recording sees them: the test above
    would see them too), and hands SIGINT back as it found it when it returns."""
    seen = _recorded(_COMMAND, tmp_path)
    assert seen["code"] == 0
    assert seen["mallopt"] == [[-1, TRIM_THRESHOLD], [-3, MMAP_THRESHOLD]]
    assert seen["sigint_handlers"][0] == "_record_and_raise"  # md.interrupts.watch, first
    assert seen["sigint_kept"]
    assert seen["excepthook_kept"]


def test_the_console_script_enters_through_md_command():
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert project["project"]["scripts"]["md"] == "md_command:main"
    assert "md_command" in project["tool"]["setuptools"]["py-modules"]


def test_md_command_exit_code_for_an_interrupt_is_the_clis():
    import md_command
    from md.cli._common import EXIT_INTERRUPTED

    assert md_command.EXIT_INTERRUPTED == EXIT_INTERRUPTED
