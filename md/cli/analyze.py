"""``md analyze TRAJ.h5``: thermodynamics, g(r), MSD and VACF of a trajectory, with plots.

The analyses live in :mod:`md.analysis`; this module parses the options,
checks what the file holds before computing anything, and writes per
analysis a PNG plot and a CSV file of the data behind it, plus
``summary.json`` with the scalar results, and prints a short table.

Files written in the output folder (default ``analysis-<trajectory stem>``):

=============  =====================================================================
thermo         ``thermo.csv`` (step, time, observables), ``thermo.png``
rdf            ``rdf.csv`` (r, g and coordination number per pair), ``rdf.png``
msd            ``msd.csv`` (lag time, MSD, fitted line), ``msd.png``
vacf           ``vacf.csv`` (lag time, VACF, normalised VACF, running D), ``vacf.png``
always         ``summary.json``
``--all``      ``snapshot.png``: the last selected frame drawn by :mod:`md.render`
=============  =====================================================================

An analysis named on the command line that the file cannot support (no
velocities for ``--vacf``, fewer than 5 frames for ``--msd``, an open box
for ``--rdf``) stops the command with exit code 2 before anything is
computed; with ``--all`` (or no analysis named) such analyses are skipped
with a note. Existing output files are only replaced with ``--overwrite``.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

from md import analysis as an
from md.analysis import ANALYSES
from md.cli._common import EXIT_BAD_INPUT, EXIT_OK, fail
from md.errors import AnalysisError, TrajectoryError
from md.render import render
from md.trajectory import verify_frames

PLOT_DPI = 120


def add_parser(subparsers) -> None:
    """Add ``md analyze`` and its options."""
    parser = subparsers.add_parser("analyze", help="thermo, g(r), MSD, VACF of a trajectory")
    parser.add_argument("trajectory", type=Path, help="H5MD file written by md run")
    for name, text in (
        ("thermo", "energies, temperature, pressure: averages, errors, energy drift"),
        ("rdf", "radial distribution function per type pair, coordination number"),
        ("msd", "mean squared displacement, Einstein diffusion coefficient"),
        ("vacf", "velocity autocorrelation, Green-Kubo diffusion coefficient"),
    ):
        parser.add_argument(f"--{name}", action="store_true", help=text)
    parser.add_argument(
        "--all",
        action="store_true",
        help="every analysis the file supports (the default when none is named), and "
        "snapshot.png, a picture of the last selected frame",
    )
    parser.add_argument(
        "--out", type=Path, help="output folder (default analysis-<trajectory stem>)"
    )
    parser.add_argument("--start", type=int, help="first frame (index, as in Python slices)")
    parser.add_argument("--stop", type=int, help="frame to stop before")
    parser.add_argument("--step", type=int, help="use every step-th frame")
    parser.add_argument("--rdf-bins", type=int, default=200, help="g(r) bins (default 200)")
    parser.add_argument(
        "--rdf-range",
        help="g(r) range [length]: RMAX or RMIN:RMAX (default 0 to half the smallest cell width)",
    )
    parser.add_argument(
        "--fit",
        help="lag-time window T0:T1 [time] of the MSD fit and the Green-Kubo plateau "
        "(default 10%% to 50%% of the longest lag in one of the --blocks)",
    )
    parser.add_argument(
        "--select", default="all", help="MDAnalysis selection for MSD and VACF, e.g. 'type A'"
    )
    parser.add_argument(
        "--blocks",
        type=int,
        default=5,
        help="time blocks for the standard errors of averages and of D (default 5)",
    )
    parser.add_argument("--overwrite", action="store_true", help="replace existing output files")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def output_files(analysis: str) -> list[str]:
    """File names one analysis writes."""
    return [f"{analysis}.csv", f"{analysis}.png"]


def main(args) -> int:
    """Body of ``md analyze``; returns the exit code."""
    explicit = [name for name in ANALYSES if getattr(args, name)]
    wanted = list(ANALYSES) if args.all or not explicit else explicit
    try:
        info = an.trajectory_info(args.trajectory, args.start, args.stop, args.step)
        verify_frames(args.trajectory)  # damaged frames: a message naming the frame
        if info.n_frames == 0:
            raise an.AnalysisError(
                f"{args.trajectory}: the frame selection start={args.start}, stop={args.stop}, "
                f"step={args.step} selects no frames (the file has {info.n_frames_total})"
            )
        rdf_range = _parse_range(args.rdf_range, "--rdf-range", allow_single=True)
        window = _parse_range(args.fit, "--fit", allow_single=False)
        if args.blocks < 1:
            raise an.AnalysisError(f"--blocks must be >= 1, got {args.blocks}")
        if args.rdf_bins < 1:
            raise an.AnalysisError(f"--rdf-bins must be >= 1, got {args.rdf_bins}")
        selected, notes = [], []
        for name in wanted:
            reason = info.missing(name)
            if reason is None:
                selected.append(name)
            elif name in explicit:
                raise an.AnalysisError(f"{args.trajectory}: cannot compute {name}: {reason}")
            else:
                notes.append(f"{name} skipped: {reason}")
        if not selected:
            raise an.AnalysisError(f"{args.trajectory}: nothing to analyse ({'; '.join(notes)})")
        out = args.out or Path(f"analysis-{args.trajectory.stem}")
        if out.exists() and not out.is_dir():
            raise an.AnalysisError(f"output path {out} exists and is not a folder")
        names = [f for name in selected for f in output_files(name)] + ["summary.json"]
        if args.all:
            names.append("snapshot.png")
        existing = [str(out / f) for f in names if (out / f).exists()]
        if existing and not args.overwrite:
            raise an.AnalysisError(
                f"output file(s) exist: {', '.join(existing)}; pass --overwrite or --out"
            )
    except (TrajectoryError, an.AnalysisError) as error:
        fail(str(error))
        return EXIT_BAD_INPUT

    labels = an.unit_labels(info.units)
    print(
        f"md analyze: {info.path}, {info.n_atoms} atoms, {info.n_frames} of "
        f"{info.n_frames_total} frames (slice {info.frame_range.start}:"
        f"{info.frame_range.stop}:{info.frame_range.step}), units {info.units}; "
        f"{', '.join(selected)}"
    )
    for note in notes:
        print(f"  {note}")
    frames = {"start": args.start, "stop": args.stop, "step": args.step}
    verbose = not args.no_progress
    results = {}
    try:
        for name in selected:
            if name == "thermo":
                results[name] = an.thermo(args.trajectory, **frames, n_blocks=args.blocks)
            elif name == "rdf":
                results[name] = an.rdf(
                    args.trajectory,
                    bins=args.rdf_bins,
                    r_range=rdf_range,
                    **frames,
                    verbose=verbose,
                )
            elif name == "msd":
                results[name] = an.msd(
                    args.trajectory,
                    window=window,
                    select=args.select,
                    n_blocks=args.blocks,
                    **frames,
                    verbose=verbose,
                )
            else:
                results[name] = an.vacf(
                    args.trajectory,
                    window=window,
                    select=args.select,
                    n_blocks=args.blocks,
                    **frames,
                )
    except (TrajectoryError, an.AnalysisError) as error:
        fail(str(error))
        return EXIT_BAD_INPUT

    for result in results.values():
        for doubt in getattr(result, "warnings", ()):
            print(f"  warning: {doubt}")
    out.mkdir(parents=True, exist_ok=True)
    writers = {"thermo": _write_thermo, "rdf": _write_rdf, "msd": _write_msd, "vacf": _write_vacf}
    for name, result in results.items():
        writers[name](result, out, labels)
    summary = {
        "trajectory": str(info.path),
        "units": info.units,
        "unit_labels": labels,
        "n_atoms": info.n_atoms,
        "frames": {
            **frames,
            "n_selected": info.n_frames,
            "n_stored": info.n_frames_total,
            "first_time": float(info.times[0]),
            "last_time": float(info.times[-1]),
        },
        "skipped": notes,
        **{name: result.summary() for name, result in results.items()},
    }
    with open(out / "summary.json", "w") as handle:
        json.dump(_finite_or_none(summary), handle, indent=2)
    _print_table(results, labels)
    written = [f for name in results for f in output_files(name)] + ["summary.json"]
    if args.all:
        render(args.trajectory, out / "snapshot.png", frame=int(info.frames[-1]), overwrite=True)
        written.append("snapshot.png")
    print(f"Wrote {', '.join(written)} to {out}/")
    return EXIT_OK


# ----------------------------------------------------------------- helpers
def _parse_range(text: str | None, option: str, allow_single: bool):
    if text is None:
        return None
    parts = text.split(":")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) == 1 and allow_single:
        values = [0.0, values[0]]
    low, high = ("MIN", "MAX") if allow_single else ("START", "END")
    form = "MAX or MIN:MAX" if allow_single else f"{low}:{high}"
    if len(values) != 2 or not all(math.isfinite(v) for v in values):
        raise AnalysisError(f"{option} must be {form} (numbers), got {text!r}")
    if not 0 <= values[0] < values[1]:
        raise AnalysisError(f"{option} needs 0 <= {low} < {high}, got {text!r}")
    return tuple(values)


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


_THERMO_LABELS = {
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


def _write_thermo(result, out: Path, labels: dict) -> None:
    columns = {"step": [int(s) for s in result.steps], f"time [{labels['time']}]": result.times}
    for name, values in result.series.items():
        unit = labels[_THERMO_LABELS.get(name, (name, "energy"))[1]]
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
            ax.plot(result.times, values, label=_THERMO_LABELS[name][0])
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
        f"{n} atoms; {_THERMO_LABELS[result.drift_of][0]}-energy drift {drift:.3g} "
        f"{labels['drift']} per atom",
        fontsize="medium",
    )
    _save(fig, out / "thermo.png")


def _write_rdf(result, out: Path, labels: dict) -> None:
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


def _write_msd(result, out: Path, labels: dict) -> None:
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


def _write_vacf(result, out: Path, labels: dict) -> None:
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


def _print_table(results: dict, labels: dict) -> None:
    rows = []
    if "thermo" in results:
        t = results["thermo"]
        for name, average in t.averages.items():
            quantity = _THERMO_LABELS.get(name, (name, "energy"))[1]
            rows.append((f"<{name}>", average.mean, average.sem, labels[quantity]))
        which = "conserved-energy" if t.drift_of == "conserved_energy" else "energy"
        rows.append((f"{which} drift per atom", t.energy_drift, t.energy_drift_err,
                     labels["drift"]))  # fmt: skip
        rows.append((f"{which} fluctuation per atom", t.energy_fluctuation, None,
                     labels["energy"]))  # fmt: skip
        if math.isfinite(t.compressibility):  # the volume fluctuated: an NPT run
            unit = f"{labels['volume']}/{labels['energy']}"
            rows.append(("isothermal compressibility", t.compressibility, None, unit))
    if "rdf" in results:
        for pair, shell in results["rdf"].shells.items():
            rows.append((f"g(r) {pair} first peak r", shell.r_peak, None, labels["length"]))
            rows.append((f"g(r) {pair} first peak height", shell.g_peak, None, ""))
            rows.append((f"g(r) {pair} first minimum r", shell.r_min, None, labels["length"]))
            rows.append((f"coordination {pair} (r < r_min)", shell.coordination, None, ""))
    for name, method in (("msd", "MSD"), ("vacf", "VACF")):
        if name in results:
            d = results[name].diffusion
            window = f"{d.window[0]:.3g}-{d.window[1]:.3g}"
            rows.append((f"D ({method}, lags {window})", d.value, d.error, labels["diffusion"]))
    print(f"{'quantity':<38}{'value':>14}{'error':>12}  unit")
    for label, value, error, unit in rows:
        error_text = f"{error:>12.3g}" if error is not None and math.isfinite(error) else " " * 12
        print(f"{label:<38}{value:>14.6g}{error_text}  {unit}")
