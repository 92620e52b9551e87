"""``md sweep CONFIG.toml --vary KEY=V1,V2 ...``: many ``md run``s on a Dask cluster.

The sweep itself lives in :mod:`md.sweeps`; this module parses the options,
validates every run before any starts (a bad key or value: exit 2), shows
the progress of the whole sweep on stderr, prints the collated table and
writes the figure.

Files in the output folder (default ``sweep-<config stem>``):

==================  ================================================================
``<label>.h5``      each run's trajectory (only once the run is complete)
``configs/``        each run's complete config (``md run`` reproduces the run)
``logs/``           each run's ``md run`` output, one block per attempt
``sweep.csv``       one row per run: varied values, replica, seed, status, results
``<column>.png``    with ``--plot COLUMN``: that result against the first varied key
==================  ================================================================

Exit codes: 0 every run complete; 1 some runs failed (the others completed
and are in the table); 2 bad input (nothing was run); 130 interrupted.
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

from tqdm import tqdm

from md import sweeps as sw
from md.analysis import unit_labels
from md.cli._common import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK, fail


def add_parser(subparsers) -> None:
    """Add ``md sweep`` and its options."""
    parser = subparsers.add_parser("sweep", help="runs over varied keys and replicas, on Dask")
    parser.add_argument("config", type=Path, help="base TOML config (as for md run)")
    parser.add_argument(
        "--vary",
        action="append",
        default=[],
        metavar="KEY=V1,V2,...",
        help="a dotted config key and its values, e.g. system.temperature=0.8,1.2 or "
        "integrator.dt=0.002:0.006:3 (MIN:MAX:N); repeat for a cartesian product",
    )
    parser.add_argument(
        "--replicas", type=int, default=1, help="runs per point with different seeds (default 1)"
    )
    parser.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="Dask scheduler address, e.g. tcp://10.0.0.5:8786 (default: a local cluster)",
    )
    parser.add_argument(
        "--max-runs",
        type=int,
        default=sw.MAX_RUNS,
        help=f"refuse sweeps of more runs than this (default {sw.MAX_RUNS})",
    )
    parser.add_argument(
        "--timeout",
        type=float,
        default=sw.CONNECT_TIMEOUT,
        help=f"seconds to wait for the scheduler to answer (default {sw.CONNECT_TIMEOUT:g})",
    )
    parser.add_argument(
        "--workers",
        type=int,
        help="worker processes of the local cluster, one thread each (default: one per core)",
    )
    parser.add_argument("--out", type=Path, help="output folder (default sweep-<config stem>)")
    parser.add_argument(
        "--diffusion", action="store_true", help="also fit each run's MSD diffusion coefficient"
    )
    parser.add_argument(
        "--discard",
        type=float,
        default=0.0,
        help="leading fraction of each run's frames left out of the averages (default 0)",
    )
    parser.add_argument(
        "--blocks", type=int, default=5, help="blocks for the standard errors (default 5)"
    )
    parser.add_argument(
        "--plot",
        metavar="COLUMN",
        help="plot this result against the first varied key, e.g. pressure, temperature, "
        "total_energy_per_atom, diffusion (or T, P, rho, V, PE, KE, E, drift, D)",
    )
    parser.add_argument(
        "--overwrite", action="store_true", help="redo runs whose outputs already exist"
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress line")


def main(args) -> int:
    """Body of ``md sweep``; returns the exit code."""
    try:
        vary, plot = sw.check_options(
            args.vary,
            args.replicas,
            max_runs=args.max_runs,
            discard=args.discard,
            n_blocks=args.blocks,
            workers=args.workers,
            scheduler=args.scheduler,
            diffusion=args.diffusion,
            plot=args.plot,
        )
        n_runs = sw.count_runs(vary, args.replicas)
        print(f"md sweep: planning and validating {n_runs} run(s) ...", flush=True)
        plan = sw.plan_sweep(args.config, vary, args.replicas, args.out, max_runs=args.max_runs)
        complete = sw.check_outputs(plan, args.overwrite)
    except sw.SweepError as error:
        fail(str(error))
        return EXIT_BAD_INPUT

    points = len(plan.runs) // plan.replicas
    varied = "; ".join(
        f"{k} = {', '.join(map(sw.format_value, v))}" for k, v in plan.values.items()
    )
    print(
        f"md sweep: {len(plan.runs)} runs ({points} point(s) x {plan.replicas} replica(s))"
        f"{': ' + varied if varied else ''}; output {plan.out}"
        + (f"; {len(complete)} already complete" if complete else "")
    )
    printer = _ProgressPrinter(len(plan.runs), disable=args.no_progress)
    try:
        connection = sw.connect(
            scheduler=args.scheduler, workers=args.workers, timeout=args.timeout
        )
        with connection as client:
            if args.scheduler is None:
                n_workers = len(client.scheduler_info()["workers"])
                print(f"md sweep: running on a local cluster of {n_workers} worker(s)")
            else:
                print(f"md sweep: running on the Dask scheduler at {args.scheduler}")
            table = sw.run_sweep(
                plan,
                client,
                overwrite=args.overwrite,
                diffusion=args.diffusion,
                discard=args.discard,
                n_blocks=args.blocks,
                progress=printer,
            )
    except sw.SweepError as error:
        printer.close()
        fail(str(error))
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        printer.close()
        fail(
            "interrupted; runs not started were cancelled. Complete outputs are kept; run the "
            "same command again to finish the rest"
        )
        return EXIT_INTERRUPTED
    printer.close()
    print_table(table)
    written = [str(plan.out / sw.TABLE_FILE)]
    if plot is not None:
        if any(math.isfinite(v) for v in table.column(plot)):
            written.append(str(table.plot(plot, plan.out / f"{plot}.png")))
        else:
            print(f"md sweep: no run has a value of {plot}; no plot drawn", file=sys.stderr)
    print(f"Wrote {', '.join(written)}")
    if table.failed:
        print(
            f"md sweep: {len(table.failed)} of {len(table)} runs failed (see above and "
            f"{plan.out / sw.LOG_DIR}); running the same command again retries them",
            file=sys.stderr,
        )
        return EXIT_FAILED
    return EXIT_OK


class _ProgressPrinter:
    """Show a :class:`md.sweeps.SweepProgress`: a tqdm line on a terminal, else status lines."""

    def __init__(self, total: int, disable: bool) -> None:
        self.interactive = sys.stderr.isatty() and not disable
        self.disable = disable
        self.bar = tqdm(
            total=total,
            unit="run",
            desc="md sweep",
            disable=not self.interactive,
            dynamic_ncols=True,
            leave=False,
            bar_format="{desc}: {n_fmt}/{total_fmt} runs |{bar}| {postfix}",
        )
        self.shown = 0
        self.counts: tuple = ()
        self.printed = 0.0

    def __call__(self, progress) -> None:
        for row in progress.finished:
            if row["status"] == "failed":
                self._write(f"md sweep: run {row['label']} failed: {row['message']}")
        line = _status_line(progress)
        if self.interactive:
            self.bar.update(progress.n_finished - self.shown)
            self.shown = progress.n_finished
            self.bar.set_postfix_str(line, refresh=True)
            return
        # Not a terminal: a line when the counts change, else one a minute.
        counts = (progress.n_finished, len(progress.running), progress.failed, progress.retried)
        now = time.monotonic()
        if not self.disable and (counts != self.counts or now - self.printed > 60):
            print(f"md sweep: {progress.n_finished}/{progress.total} runs, {line}", file=sys.stderr)
            self.counts, self.printed = counts, now

    def _write(self, text: str) -> None:
        if self.interactive:
            self.bar.write(text, file=sys.stderr)
        else:
            print(text, file=sys.stderr)

    def close(self) -> None:
        self.bar.close()


def _status_line(progress) -> str:
    eta = "?" if progress.eta is None else _clock(progress.eta)
    retried = f", retried {progress.retried}" if progress.retried else ""
    return (
        f"done {progress.done + progress.skipped}, running {len(progress.running)}, "
        f"failed {progress.failed}{retried}, elapsed {_clock(progress.elapsed)}, ETA {eta}"
    )


def _clock(seconds: float) -> str:
    seconds = int(round(seconds))
    hours, rest = divmod(seconds, 3600)
    return f"{hours}:{rest // 60:02d}:{rest % 60:02d}" if hours else f"{rest // 60}:{rest % 60:02d}"


_WIDTH = 24  # of a result column: "-1.23456e-05 +- 1.2e-06"


def print_table(table) -> None:
    """Print one row per run, and per point (mean and replica error) with replicas."""
    labels = unit_labels(table.units or "lj")
    short = sw.short_names(table.keys)
    columns = [
        ("temperature", "T", labels["temperature"]),
        ("pressure", "P", labels["pressure"]),
        ("potential_energy_per_atom", "PE/atom", labels["energy"]),
        ("total_energy_per_atom", "E/atom", labels["energy"]),
        ("energy_drift_per_atom", "drift/atom", labels["drift"]),
    ]
    if any(row.get("density_err", 0.0) > 0.0 for row in table.rows):  # the volume moved: NPT
        columns.insert(2, ("density", "rho", labels["density"]))
    if any("diffusion" in row for row in table.rows):
        columns.append(("diffusion", "D", labels["diffusion"]))
    key_widths = [max(len(short[k]), 8) for k in table.keys]
    header = "".join(f"{short[k]:>{w}}" for k, w in zip(table.keys, key_widths, strict=True))
    header += f"{'rep':>5}{'status':>9}" + "".join(f"{name:>{_WIDTH}}" for _, name, _ in columns)
    print(header)
    for row in table.rows:
        cells = "".join(
            f"{sw.format_value(row[k]):>{w}}" for k, w in zip(table.keys, key_widths, strict=True)
        )
        cells += f"{row['replica']:>5}{row['status']:>9}"
        if row["status"] == "failed":
            print(cells + f"  {row['message']}")
            continue
        cells += "".join(
            _with_error(row.get(c, math.nan), row.get(f"{c}_err", math.nan)) for c, _, _ in columns
        )
        print(cells)
    units = ", ".join(f"{name} [{unit}]" for _, name, unit in columns)
    print(f"({units}; +- block standard errors of each run)")
    if table.keys and len(table.rows) > len(
        {tuple(map(str, (r[k] for k in table.keys))) for r in table.rows}
    ):
        print("Per point, mean over replicas +- standard error over replicas:")
        keys = "".join(f"{short[k]:>{w}}" for k, w in zip(table.keys, key_widths, strict=True))
        print(keys + f"{'n':>5}{'':>9}" + "".join(f"{name:>{_WIDTH}}" for _, name, _ in columns))
        per_column = [table.points(c) for c, _, _ in columns]
        for index, point in enumerate(per_column[0]):
            cells = "".join(
                f"{sw.format_value(point[k]):>{w}}"
                for k, w in zip(table.keys, key_widths, strict=True)
            )
            cells += f"{point['n']:>5}{'':>9}"
            cells += "".join(_with_error(p[index]["mean"], p[index]["err"]) for p in per_column)
            print(cells)


def _with_error(value, error) -> str:
    if value is None or not math.isfinite(value):
        return f"{'-':>{_WIDTH}}"
    if error is None or not math.isfinite(error):
        return f"{value:>{_WIDTH}.6g}"
    return f"{f'{value:.6g} +- {error:.2g}':>{_WIDTH}}"
