"""The Dask tasks: run one sweep member as an ``md run`` child process, under a lock, resumable."""

from __future__ import annotations

import logging
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

from md._files import move_into_place
from md.checkpoint import checkpoint_path
from md.sweeps.plan import CONFIG_DIR, LOG_DIR, PARTIAL_DIR, output_verdict
from md.sweeps.summary import summarize

logger = logging.getLogger(__name__)


# --------------------------------------------------------------- the tasks
def execute_run(spec: dict, options: dict) -> dict:
    """Dask task: run one ``md run`` (unless its output is complete) and summarise it.

    Idempotent: safe to run again after a worker died in the middle of it.
    Returns a dict with ``label``, ``status`` (``done``, ``skipped`` or
    ``failed``), ``message``, ``wall_s``, ``worker`` and the summary.
    """
    try:
        return _execute(spec, options)
    finally:  # in the same event stream as the start, so counts of runs in flight stay right
        _emit(options["topic"], {"event": "end", "label": spec["label"]})


def _execute(spec: dict, options: dict) -> dict:
    import fcntl  # POSIX only: the per-run lock

    out, label = Path(spec["out"]), spec["label"]
    final = out / f"{label}.h5"
    config = out / CONFIG_DIR / f"{label}.toml"
    started = time.time()
    result = {"label": label, "status": "failed", "message": "", "wall_s": math.nan}
    result["worker"] = _worker_address()
    if not config.is_file():
        result["message"] = (
            f"{config} not found on worker {result['worker']}: the output folder must be on a "
            "filesystem shared by the client and the workers"
        )
        return result
    (out / PARTIAL_DIR).mkdir(exist_ok=True)
    with open(out / PARTIAL_DIR / f"{label}.lock", "a+") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # a run still going elsewhere finishes first
        verdict = output_verdict(final, spec["config_text"], spec["n_frames"], spec["last_step"])
        if verdict == "complete":
            result["status"] = "skipped"
        elif verdict is not None:
            result["message"] = f"{final} exists and is not a complete run of it ({verdict})"
            return result
        else:
            partial = out / PARTIAL_DIR / label
            partial.mkdir(exist_ok=True)
            status, message = _run_child(spec, config, partial, lock, options)
            result["status"], result["message"] = status, message
            result["wall_s"] = time.time() - started
            shutil.rmtree(partial, ignore_errors=True)  # moved into place, or failed
            if status != "done":
                return result
    try:
        result.update(
            summarize(final, options["discard"], options["diffusion"], options["n_blocks"])
        )
    except ValueError as error:  # AnalysisError, TrajectoryError
        result["message"] = f"summary: {error}"
    return result


def _run_child(spec: dict, config: Path, partial: Path, lock, options: dict) -> tuple[str, str]:
    """Run ``md run`` in a child process into ``partial``; move a complete output into place."""
    out, label = Path(spec["out"]), spec["label"]
    output = partial / f"{label}.h5"
    log_path = out / LOG_DIR / f"{label}.log"
    modes = ["--resume", "--overwrite"] if checkpoint_path(output).exists() else ["--overwrite"]
    env = dict(os.environ)
    for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        env.setdefault(name, "1")
    code = None
    for mode in modes:
        command = [
            sys.executable,
            "-m",
            "md.cli.sweep_child",
            str(os.getpid()),
            "run",
            str(config),
            "--output",
            str(output),
            "--threads",
            "1",
            "--no-progress",
            "--quiet",
            mode,
        ]
        with open(log_path, "a") as log:
            log.write(
                f"# {time.strftime('%Y-%m-%d %H:%M:%S')} on {_worker_address()}: md run "
                f"{config.name} {mode}\n"
            )
            log.flush()
            child = subprocess.Popen(
                command,
                stdout=log,
                stderr=subprocess.STDOUT,
                env=env,
                cwd=out,
                pass_fds=(lock.fileno(),),
                stdin=subprocess.DEVNULL,
            )
            _emit(
                options["topic"],
                {
                    "event": "start",
                    "label": label,
                    "worker": _worker_address(),
                    "pid": os.getpid(),
                    "child": child.pid,
                    "time": time.time(),
                    "again": mode != modes[0],  # a refused resume started afresh: no retry
                },
            )
            code = child.wait()
        if code == 0:
            verdict = output_verdict(
                output, spec["config_text"], spec["n_frames"], spec["last_step"]
            )
            if verdict == "complete":
                move_into_place(output, out / f"{label}.h5")
                return "done", ""
            if mode == "--resume":
                continue  # a checkpoint of other settings: start afresh
            return "failed", f"md run finished but its output is incomplete ({verdict})"
        if not (code == 2 and mode == "--resume"):  # a refused resume starts afresh
            break
    return "failed", _failure_message(code, log_path)


def _failure_message(code: int, log_path: Path) -> str:
    if code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = str(-code)
        why = " (out of memory?)" if -code == signal.SIGKILL else ""
        return f"md run was killed by signal {name}{why}; see {log_path}"
    message = ""
    try:
        for line in log_path.read_text(errors="replace").splitlines():
            if line.startswith("md: error:") or line.startswith("md run: SIG"):
                message = line.removeprefix("md: error:").strip()
                # The partial files it names are removed; the log keeps the whole message.
                message = message.split(". Frames written so far are kept in")[0]
    except OSError:
        pass
    return f"md run exit {code}: {message or 'no message'} (log {log_path})"


def _worker_address() -> str:
    try:
        from distributed import get_worker  # Dask: imported only when a sweep runs

        return str(get_worker().address)
    except (ImportError, ValueError):
        return f"pid {os.getpid()}"


def _emit(topic: str, message: dict) -> None:
    try:
        from distributed import get_worker  # Dask: imported only when a sweep runs

        get_worker().log_event(topic, message)
    except (ImportError, ValueError):  # not on a Dask worker
        pass
