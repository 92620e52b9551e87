"""The collated results of a sweep: one row per run, CSV, per-point statistics, a plot."""

from __future__ import annotations

import csv
import io
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from md._files import write_text_atomic
from md.analysis import unit_labels
from md.errors import SweepError
from md.sweeps.plan import ALIASES, RESULTS, SweepPlan, format_value

logger = logging.getLogger(__name__)


# ------------------------------------------------------------------- table
@dataclass
class SweepTable:
    """The collated result of a sweep: one row (a dict) per run.

    Row keys: ``index``, ``label``, each varied key (dotted, as given),
    ``replica``, ``seed``, ``status`` (``done``, ``skipped``: complete
    before, ``failed``), ``message``, ``wall_s``, ``n_atoms``, ``n_frames``,
    ``units``, the result columns of :data:`RESULTS` with their ``_err``, and
    ``output``. Results are in the units of the files (NaN for failed runs).

    Examples
    --------
    >>> # table = md.sweep("lj.toml", vary={"system.temperature": [1.0, 1.5]}, replicas=3)
    >>> # table.points("pressure")   # per point: mean, replica error, n
    >>> # table.plot("pressure", "pressure.png")
    """

    keys: list[str]
    rows: list[dict]
    out: Path | None = None

    @classmethod
    def from_results(cls, plan: SweepPlan, results: list[dict]) -> SweepTable:
        rows = []
        for run, result in zip(plan.runs, results, strict=True):
            row = {"index": run.index, "label": run.label, **dict(run.point)}
            row.update(replica=run.replica, seed=run.seed)
            row.update(status=result["status"], message=result.get("message", ""))
            row["wall_s"] = result.get("wall_s", math.nan)
            for name in ("n_atoms", "n_frames", "units"):
                row[name] = result.get(name)
            for name in RESULTS:
                if name == "diffusion" and name not in result:
                    continue
                row[name] = result.get(name, math.nan)
                row[f"{name}_err"] = result.get(f"{name}_err", math.nan)
            row["output"] = str(plan.output(run)) if result["status"] != "failed" else ""
            rows.append(row)
        return cls(keys=list(plan.keys), rows=rows, out=plan.out)

    def __len__(self) -> int:
        return len(self.rows)

    def __iter__(self):
        return iter(self.rows)

    def __getitem__(self, index: int) -> dict:
        return self.rows[index]

    @property
    def columns(self) -> list[str]:
        names: list[str] = []
        for row in self.rows:
            names += [k for k in row if k not in names]
        return names

    @property
    def failed(self) -> list[dict]:
        return [row for row in self.rows if row["status"] == "failed"]

    @property
    def units(self) -> str | None:
        return next((row["units"] for row in self.rows if row.get("units")), None)

    def column(self, name: str) -> np.ndarray:
        """One result column over all runs (NaN where missing)."""
        name = resolve_column(name)
        return np.array([_number(row.get(name)) for row in self.rows])

    def points(self, column: str) -> list[dict]:
        """Mean of ``column`` over the replicas of each parameter point, with its error.

        ``err`` is the standard error over replicas (std / sqrt(n), n >= 2
        finished replicas), or with one replica that run's own block error.
        """
        column = resolve_column(column)
        groups: dict[tuple, list[dict]] = {}
        for row in self.rows:
            groups.setdefault(tuple(_hashable(row[k]) for k in self.keys), []).append(row)
        points = []
        for group in groups.values():
            values = [_number(r.get(column)) for r in group]
            values = [v for v in values if math.isfinite(v)]
            mean = float(np.mean(values)) if values else math.nan
            if len(values) >= 2:
                err = float(np.std(values, ddof=1) / math.sqrt(len(values)))
            elif len(values) == 1:
                own = [r for r in group if math.isfinite(_number(r.get(column)))][0]
                err = _number(own.get(f"{column}_err"))
            else:
                err = math.nan
            points.append(
                {
                    **{k: group[0][k] for k in self.keys},
                    "mean": mean,
                    "err": err,
                    "n": len(values),
                    "runs": len(group),
                }
            )
        return points

    def to_csv(self, path) -> Path:
        """Write the rows as CSV (atomically); returns the path."""
        path = Path(path)
        columns = self.columns
        buffer = io.StringIO()
        writer = csv.writer(buffer)
        writer.writerow(columns)
        for row in self.rows:
            writer.writerow([_csv_cell(row.get(c)) for c in columns])
        write_text_atomic(path, buffer.getvalue())
        return path

    def plot(self, column: str, path, key: str | None = None) -> Path:
        """Plot ``column`` against varied ``key`` (default the first) with replica error bars.

        One line per combination of the other varied keys; the points and
        error bars are those of :meth:`points`. Written with matplotlib's Agg
        canvas (no pyplot).
        """
        from matplotlib.figure import Figure  # heavy: matplotlib only when plotting

        column = resolve_column(column)
        if not self.keys:
            raise SweepError("plotting needs a varied key (the x axis)")
        key = key or self.keys[0]
        if key not in self.keys:
            raise SweepError(f"{key!r} is not a varied key ({', '.join(self.keys)})")
        others = [k for k in self.keys if k != key]
        series: dict[tuple, list] = {}
        for point in self.points(column):
            series.setdefault(tuple(_hashable(point[k]) for k in others), []).append(point)
        x_values = [_hashable(v) for v in dict.fromkeys(_hashable(r[key]) for r in self.rows)]
        numeric = all(isinstance(v, int | float) and not isinstance(v, bool) for v in x_values)
        fig = Figure(figsize=(6.4, 4.4))
        ax = fig.subplots()
        for other, points in series.items():
            xs = [_hashable(p[key]) for p in points]
            xs = xs if numeric else [x_values.index(x) for x in xs]
            label = ", ".join(
                f"{k} = {format_value(v)}" for k, v in zip(others, other, strict=True)
            )
            ax.errorbar(
                xs,
                [p["mean"] for p in points],
                yerr=[p["err"] for p in points],
                marker="o",
                capsize=3,
                label=label or None,
            )
        if not numeric:
            ax.set_xticks(range(len(x_values)), [format_value(v) for v in x_values])
        labels = unit_labels(self.units or "lj")
        unit = labels.get(RESULTS[column], "")
        ax.set_xlabel(key)
        ax.set_ylabel(f"{column.replace('_', ' ')} [{unit}]")
        replicas = max(p["runs"] for ps in series.values() for p in ps)
        how = "standard error over replicas" if replicas > 1 else "block standard error"
        ax.set_title(f"{column.replace('_', ' ')} vs {key} (error bars: {how})", fontsize="medium")
        if others:
            ax.legend(fontsize="small")
        fig.tight_layout()
        path = Path(path)
        fig.savefig(path, dpi=120)
        return path


def resolve_column(name: str) -> str:
    """A result column from its name or short alias (T, P, rho, V, PE, KE, E, drift, D)."""
    name = ALIASES.get(name, name)
    if name not in RESULTS:
        known = ", ".join(list(RESULTS) + list(ALIASES))
        raise SweepError(f"unknown result column {name!r} (known: {known})")
    return name


def _number(value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def _hashable(value):
    return tuple(value) if isinstance(value, list) else value


def _csv_cell(value):
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, list):
        return format_value(value)
    return value
