"""The files of ``md analyze``: per analysis a CSV file and a figure, and ``summary.json``.

:func:`md.analysis.analyze` computes the analyses and calls these writers;
each takes a result of :mod:`md.analysis` (``ThermoResult``, ``RDFResult``,
``MSDResult``, ``VACFResult``), the output folder and the unit labels
(:func:`md.analysis.unit_labels`), and writes in the file's units:

=============  =====================================================================
thermo         ``thermo.csv`` (step, time, observables), ``thermo.png``
rdf            ``rdf.csv`` (r, g and coordination number per pair), ``rdf.png``
msd            ``msd.csv`` (lag time, MSD, fitted line), ``msd.png``
vacf           ``vacf.csv`` (lag time, VACF, normalised VACF, running D), ``vacf.png``
=============  =====================================================================

Figures are matplotlib ``Figure`` objects drawn by the Agg canvas (no pyplot,
no global backend).
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

PLOT_DPI = 120


def output_files(analysis: str) -> list[str]:
    """File names one analysis writes."""
    return [f"{analysis}.csv", f"{analysis}.png"]


def write_summary(summary: dict, path: Path) -> None:
    """Write ``summary`` as strict JSON (NaN and infinities become null)."""
    with open(path, "w") as handle:
        json.dump(_finite_or_none(summary), handle, indent=2)


def _finite_or_none(value):
    """Replace NaN and infinities by None so summary.json is strict JSON."""
    if isinstance(value, dict):
        return {k: _finite_or_none(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite_or_none(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _write_csv(path: Path, columns: dict) -> None:
    names = list(columns)
    rows = zip(*(columns[n] for n in names), strict=True)
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(names)
        for row in rows:
            writer.writerow([repr(float(v)) if not isinstance(v, int) else v for v in row])


def _figure(n_rows: int = 1, height: float = 4.2):
    """A matplotlib Figure drawn by the Agg canvas (no pyplot, no global backend)."""
    from matplotlib.figure import Figure  # heavy: matplotlib only when plotting

    fig = Figure(figsize=(6.4, height * n_rows))
    axes = fig.subplots(n_rows, 1, squeeze=False)[:, 0]
    return fig, axes


def _save(fig, path: Path) -> None:
    fig.tight_layout()
    fig.savefig(path, dpi=PLOT_DPI)


THERMO_LABELS = {
    "potential_energy": ("potential", "energy"),
    "kinetic_energy": ("kinetic", "energy"),
    "total_energy": ("total", "energy"),
    "conserved_energy": ("conserved", "energy"),
    "temperature": ("temperature", "temperature"),
    "pressure": ("pressure", "pressure"),
    "volume": ("volume", "volume"),
    "density": ("density", "density"),
    **{name: (name, "pressure") for name in ("pxx", "pyy", "pzz", "pxy", "pxz", "pyz")},
}


def write_thermo(result, out: Path, labels: dict) -> None:
    columns = {"step": [int(s) for s in result.steps], f"time [{labels['time']}]": result.times}
    for name, values in result.series.items():
        unit = labels[THERMO_LABELS.get(name, (name, "energy"))[1]]
        columns[f"{name} [{unit}]"] = values
    _write_csv(out / "thermo.csv", columns)

    panels = [
        ("energy", ["potential_energy", "kinetic_energy", "total_energy", "conserved_energy"]),
        ("temperature", ["temperature"]),
        ("pressure", ["pressure"]),
    ]
    panels = [(q, [n for n in names if n in result.series]) for q, names in panels]
    panels = [(q, names) for q, names in panels if names]
    fig, axes = _figure(len(panels), height=2.6)
    n = result.n_atoms
    for ax, (quantity, names) in zip(axes, panels, strict=True):
        for name in names:
            values = result.series[name] / (n if quantity == "energy" else 1)
            ax.plot(result.times, values, label=THERMO_LABELS[name][0])
            if name in result.averages and quantity != "energy":
                ax.axhline(result.averages[name].mean, color="k", lw=0.8, ls="--")
        per_atom = " per atom" if quantity == "energy" else ""
        ax.set_ylabel(f"{quantity}{per_atom} [{labels[quantity]}]")
        if quantity == "energy":
            ax.legend(fontsize="small", loc="best")
        ax.grid(True, alpha=0.3)
    axes[-1].set_xlabel(f"time [{labels['time']}]")
    drift = result.energy_drift
    axes[0].set_title(
        f"{n} atoms; {THERMO_LABELS[result.drift_of][0]}-energy drift {drift:.3g} "
        f"{labels['drift']} per atom",
        fontsize="medium",
    )
    _save(fig, out / "thermo.png")


def write_rdf(result, out: Path, labels: dict) -> None:
    columns = {f"r [{labels['length']}]": result.r}
    for pair, values in result.g.items():
        columns[f"g_{pair}"] = values
        columns[f"n_{pair}"] = result.coordination[pair][1:]
    _write_csv(out / "rdf.csv", columns)

    fig, (ax,) = _figure()
    twin = ax.twinx()
    for pair, values in result.g.items():
        shell = result.shells[pair]
        label = f"g(r) {pair}"
        if math.isfinite(shell.r_min):
            label += f": n = {shell.coordination:.3g} within {shell.r_min:.3g}"
        (line,) = ax.plot(result.r, values, label=label)
        twin.plot(result.edges, result.coordination[pair], ls=":", color=line.get_color())
        if math.isfinite(shell.r_min):
            ax.axvline(shell.r_min, color=line.get_color(), lw=0.6, ls="--")
    first_shells = [s.coordination for s in result.shells.values() if math.isfinite(s.coordination)]
    if first_shells and max(first_shells) > 0:
        twin.set_ylim(0, 4 * max(first_shells))  # the first shells readable; the rest clipped
    ax.axhline(1.0, color="k", lw=0.6)
    ax.set_xlabel(f"r [{labels['length']}]")
    ax.set_ylabel("g(r)")
    twin.set_ylabel("coordination number n(r) (dotted)")
    ax.set_title(f"Radial distribution function ({result.n_frames} frames)")
    ax.legend(fontsize="small", loc="upper right")
    ax.grid(True, alpha=0.3)
    _save(fig, out / "rdf.png")


def write_msd(result, out: Path, labels: dict) -> None:
    d = result.diffusion
    fitted = result.intercept + 6.0 * d.value * result.lag_times
    _write_csv(
        out / "msd.csv",
        {
            f"lag_time [{labels['time']}]": result.lag_times,
            f"msd [{labels['msd']}]": result.msd,
            f"fit [{labels['msd']}]": fitted,
        },
    )
    fig, (ax, log_ax) = _figure(2, height=3.0)
    label = f"fit: D = {d.value:.4g} ± {d.error:.2g} {labels['diffusion']}"
    ax.plot(result.lag_times, result.msd, label="MSD")
    ax.plot(result.lag_times, fitted, "k--", lw=0.8, label=label)
    ax.axvspan(*d.window, color="0.9", zorder=0)
    ax.set_ylabel(f"MSD [{labels['msd']}]")
    ax.set_title(f"Mean squared displacement ({result.n_atoms} atoms; shaded: fit window)")
    ax.legend(fontsize="small", loc="upper left")
    positive = result.lag_times > 0
    log_ax.loglog(result.lag_times[positive], result.msd[positive], label="MSD")
    log_ax.loglog(
        result.lag_times[positive],
        6.0 * d.value * result.lag_times[positive],
        "k--",
        lw=0.8,
        label="6 D t",
    )
    log_ax.axvspan(*d.window, color="0.9", zorder=0)
    log_ax.set_ylabel(f"MSD [{labels['msd']}]")
    log_ax.legend(fontsize="small", loc="upper left")
    log_ax.set_xlabel(f"lag time [{labels['time']}]")
    for axis in (ax, log_ax):
        axis.grid(True, alpha=0.3)
    _save(fig, out / "msd.png")


def write_vacf(result, out: Path, labels: dict) -> None:
    d = result.diffusion
    _write_csv(
        out / "vacf.csv",
        {
            f"lag_time [{labels['time']}]": result.lag_times,
            f"vacf [{labels['vacf']}]": result.vacf,
            "vacf_normalized": result.normalized,
            f"running_D [{labels['diffusion']}]": result.running_diffusion,
        },
    )
    fig, (top, bottom) = _figure(2, height=3.0)
    top.plot(result.lag_times, result.normalized)
    top.axhline(0.0, color="k", lw=0.6)
    top.set_ylabel("VACF / VACF(0)")
    top.set_title(f"Velocity autocorrelation ({result.n_atoms} atoms)")
    top.grid(True, alpha=0.3)
    bottom.plot(result.lag_times, result.running_diffusion, label="(1/3) ∫ VACF dt")
    bottom.axvspan(*d.window, color="0.9", zorder=0)
    bottom.axhline(
        d.value,
        color="k",
        ls="--",
        label=f"D = {d.value:.4g} ± {d.error:.2g} {labels['diffusion']}",
    )
    bottom.set_xlabel(f"lag time [{labels['time']}]")
    bottom.set_ylabel(f"running D [{labels['diffusion']}]")
    bottom.legend(fontsize="small", loc="lower right")
    bottom.grid(True, alpha=0.3)
    top.set_xlim(0, _decay_span(result.lag_times, result.normalized))
    bottom.set_xlim(0, result.lag_times[-1])
    _save(fig, out / "vacf.png")


def _decay_span(lag_times, normalized) -> float:
    """Lag range that shows the VACF's decay: ten times its first zero crossing."""
    crossings = np.flatnonzero(normalized <= 0)
    if len(crossings) == 0:
        return float(lag_times[-1])
    return float(min(lag_times[-1], 10 * lag_times[max(crossings[0], 1)]))


#: The writer of each analysis.
WRITERS = {"thermo": write_thermo, "rdf": write_rdf, "msd": write_msd, "vacf": write_vacf}
