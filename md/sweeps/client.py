"""Dask client, progress events and the driver that submits a sweep's runs."""

from __future__ import annotations

import contextlib
import logging
import math
import os
import shutil
import signal
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

from md._files import write_text_atomic
from md.errors import SweepError
from md.sweeps.plan import (
    CONFIG_DIR,
    LOG_DIR,
    PARTIAL_DIR,
    TABLE_FILE,
    SweepPlan,
    check_outputs,
)
from md.sweeps.table import SweepTable
from md.sweeps.tasks import execute_run

logger = logging.getLogger(__name__)


# -------------------------------------------------------- progress, client
@dataclass
class SweepProgress:
    """Where a sweep stands; handed to the ``progress`` callback.

    Attributes
    ----------
    total, done, skipped, failed : int
        Runs in the sweep; finished here; complete before; failed.
    running : dict of str to dict
        Runs in flight: label to ``{"worker", "pid", "child", "time"}``.
    retried : int
        Runs started again after their worker died.
    elapsed : float
        Seconds since the sweep was submitted.
    eta : float or None
        Estimated seconds to the end (None until a run has finished).
    finished : list of dict
        Result rows of the runs finished since the previous call.
    """

    total: int
    done: int = 0
    skipped: int = 0
    failed: int = 0
    running: dict = field(default_factory=dict)
    retried: int = 0
    elapsed: float = 0.0
    eta: float | None = None
    finished: list = field(default_factory=list)

    @property
    def n_finished(self) -> int:
        return self.done + self.skipped + self.failed


class _Tracker:
    """Collects start events (Dask's event loop thread) and results (the caller's)."""

    def __init__(self, total: int) -> None:
        self.lock = threading.Lock()
        self.wake = threading.Event()
        self.progress = SweepProgress(total=total)
        self.started: set[str] = set()
        self.start_time = time.monotonic()
        self.first_start: float | None = None

    def on_event(self, event) -> None:
        message = event[1] if isinstance(event, tuple | list) else event
        if not isinstance(message, dict):
            return
        if message.get("event") == "end":
            with self.lock:
                self.progress.running.pop(message.get("label"), None)
            self.wake.set()
            return
        if message.get("event") != "start":
            return
        with self.lock:
            label = message["label"]
            if label in self.started and not message.get("again"):
                self.progress.retried += 1
            self.started.add(label)
            self.progress.running[label] = {
                k: message.get(k) for k in ("worker", "pid", "child", "time")
            }
            if self.first_start is None:
                self.first_start = time.monotonic()
        self.wake.set()

    def finish(self, row: dict) -> None:
        with self.lock:
            self.progress.running.pop(row["label"], None)
            status = row["status"]
            if status == "done":
                self.progress.done += 1
            elif status == "skipped":
                self.progress.skipped += 1
            else:
                self.progress.failed += 1
            self.progress.finished.append(row)

    def forget_workers(self, alive: set[str]) -> None:
        """Drop runs shown as running on workers that have left (they will be rerun)."""
        with self.lock:
            for label, info in list(self.progress.running.items()):
                if info.get("worker") not in alive:
                    del self.progress.running[label]

    def snapshot(self) -> SweepProgress:
        with self.lock:
            p = self.progress
            now = time.monotonic()
            p.elapsed = now - self.start_time
            ran = p.done + p.failed
            remaining = p.total - p.n_finished
            if ran and self.first_start is not None:
                p.eta = (now - self.first_start) / ran * remaining
            elif not remaining:
                p.eta = 0.0
            snapshot = SweepProgress(**{**p.__dict__, "running": dict(p.running)})
            p.finished = []
            return snapshot


#: Seconds to wait for a Dask scheduler to answer (``md sweep --timeout``).
CONNECT_TIMEOUT = 30.0


@contextlib.contextmanager
def connect(
    client=None,
    scheduler: str | None = None,
    workers: int | None = None,
    timeout: float = CONNECT_TIMEOUT,
) -> Iterator[Any]:
    """A Dask ``Client``: ``client`` itself, one for ``scheduler``, or a new ``LocalCluster``.

    The local cluster has ``workers`` single-threaded worker processes
    (default: one per core this process may use). What this function
    creates it closes on exit; a given ``client`` is left open.

    Raises
    ------
    SweepError
        If Dask is not installed, ``workers`` is not positive or is given
        with a scheduler, or the scheduler cannot be reached.
    """
    if client is not None:
        if scheduler is not None or workers is not None:
            raise SweepError("give a Dask client, or a scheduler address or a worker count")
        yield client
        return
    try:
        from distributed import Client, LocalCluster  # Dask: imported only when a sweep runs
    except ImportError as error:
        raise SweepError(
            f"md sweep needs Dask's distributed scheduler: pip install 'dask[distributed]' "
            f"({error})"
        ) from None
    if scheduler is not None:
        if workers is not None:
            raise SweepError(
                "--workers sets the size of the local cluster; with --scheduler the "
                "cluster's own workers run the sweep"
            )
        remote = _client_within(Client, scheduler, timeout)
        try:
            yield remote
        finally:
            remote.close()
        return
    if workers is None:
        # (os.sched_getaffinity exists on Linux only)
        workers = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
        workers = workers or os.cpu_count() or 1
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise SweepError(f"workers must be a positive integer, got {workers!r}")
    # The worker processes inherit an ignored SIGINT: Ctrl-C in the terminal reaches the
    # whole process group, and only this process should answer it (cancel the sweep);
    # workers that caught it too would print tracebacks while shutting down.
    with _sigint_ignored():
        cluster = LocalCluster(
            n_workers=workers,
            threads_per_worker=1,
            processes=True,
            dashboard_address=":0",
            silence_logs=logging.ERROR,
        )
    try:
        local = Client(cluster)
        try:
            yield local
        finally:
            local.close()
    finally:
        cluster.close()


def run_sweep(
    plan: SweepPlan,
    client,
    overwrite: bool = False,
    diffusion: bool = False,
    discard: float = 0.0,
    n_blocks: int = 5,
    progress: Callable[[SweepProgress], None] | None = None,
    interval: float = 1.0,
) -> SweepTable:
    """Execute a planned sweep on ``client``, collate it, write ``OUT/sweep.csv``.

    Runs whose outputs are complete are only summarised. ``progress`` is
    called from this thread about every ``interval`` seconds and whenever a
    run starts or finishes. Interrupting (KeyboardInterrupt) cancels the runs
    not yet started.

    Returns
    -------
    SweepTable
        One row per run, in plan order (failed runs included, with messages).
    """
    if not 0.0 <= discard < 1.0:
        raise SweepError(f"discard must be a fraction in [0, 1), got {discard!r}")
    if isinstance(n_blocks, bool) or not isinstance(n_blocks, int) or n_blocks < 1:
        raise SweepError(f"n_blocks must be a positive integer, got {n_blocks!r}")
    _prepare(plan, overwrite)
    topic = f"md-sweep-{uuid.uuid4().hex[:12]}"
    options = {"topic": topic, "discard": discard, "diffusion": diffusion, "n_blocks": n_blocks}
    tracker = _Tracker(len(plan.runs))
    client.subscribe_topic(topic, tracker.on_event)
    futures = {}
    try:
        for run in plan.runs:
            future = client.submit(
                execute_run, run.spec(plan.out), options, key=f"{topic}-{run.label}", pure=False
            )
            future.add_done_callback(lambda _: tracker.wake.set())
            futures[future] = run
        rows: dict[int, dict] = {}
        pending = set(futures)
        last_check = 0.0
        while pending:
            tracker.wake.clear()
            for future in [f for f in pending if f.done()]:
                pending.discard(future)
                run = futures[future]
                try:
                    row = future.result()
                except Exception as error:  # KilledWorker, a task that raised
                    row = {
                        "label": run.label,
                        "status": "failed",
                        "message": f"{type(error).__name__}: {error}",
                        "wall_s": math.nan,
                    }
                rows[run.index] = row
                tracker.finish(row)
            now = time.monotonic()
            if pending and now - last_check > 2.0:
                last_check = now
                with contextlib.suppress(Exception):  # information only
                    tracker.forget_workers(set(client.scheduler_info()["workers"]))
            if progress is not None:
                progress(tracker.snapshot())
            if pending:
                tracker.wake.wait(interval)
    except BaseException:
        client.cancel(list(futures))
        raise
    finally:
        with contextlib.suppress(Exception):
            client.unsubscribe_topic(topic)
    partial = plan.out / PARTIAL_DIR
    if partial.is_dir() and not any(p.is_dir() for p in partial.iterdir()):
        shutil.rmtree(partial, ignore_errors=True)  # only lock files left
    table = SweepTable.from_results(plan, [rows[run.index] for run in plan.runs])
    table.to_csv(plan.out / TABLE_FILE)
    return table


def _prepare(plan: SweepPlan, overwrite: bool) -> None:
    """Create the output folders, write the run configs, remove what overwrite replaces."""
    check_outputs(plan, overwrite)
    out = plan.out
    for folder in (out, out / CONFIG_DIR, out / LOG_DIR, out / PARTIAL_DIR):
        folder.mkdir(exist_ok=True)
    for run in plan.runs:
        if overwrite:
            plan.output(run).unlink(missing_ok=True)
            shutil.rmtree(out / PARTIAL_DIR / run.label, ignore_errors=True)
        path = out / CONFIG_DIR / f"{run.label}.toml"
        if not path.exists() or path.read_text() != run.config_text:
            write_text_atomic(path, run.config_text)


def _client_within(client_class, scheduler: str, timeout: float):
    """``Client(scheduler)``, or SweepError if no Dask scheduler answers within ``timeout`` s.

    Dask's own timeout covers the TCP connection, not the handshake after it:
    a port that accepts and stays silent would hang for ever, and one that
    answers another protocol can make it try to allocate absurd buffers. So
    the client is made in a helper thread that is abandoned on timeout.
    """
    if not (isinstance(timeout, int | float) and math.isfinite(timeout) and timeout > 0):
        raise SweepError(f"--timeout must be a positive number of seconds, got {timeout!r}")
    outcome: dict[str, Any] = {}

    def attempt() -> None:
        try:
            outcome["client"] = client_class(scheduler, timeout=f"{timeout}s")
        except BaseException as error:  # noqa: BLE001 - any failure means "not a scheduler"
            outcome["error"] = error

    thread = threading.Thread(target=attempt, name="md-sweep-connect", daemon=True)
    thread.start()
    thread.join(timeout)
    if thread.is_alive():
        raise SweepError(
            f"no Dask scheduler answered at {scheduler} within {timeout:g} s (--timeout); "
            "is the address right, and is it a Dask scheduler?"
        )
    if "error" in outcome:
        error = outcome["error"]
        raise SweepError(
            f"cannot connect to the Dask scheduler at {scheduler}: {type(error).__name__}: "
            f"{str(error)[:200]} (is it a Dask scheduler?)"
        )
    return outcome["client"]


@contextlib.contextmanager
def _sigint_ignored():
    """Ignore SIGINT while the block starts child processes (main thread only)."""
    try:
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    except ValueError:  # not the main thread: signals are not ours to change
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
