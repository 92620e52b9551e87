"""``md analyze TRAJ.h5``: thermodynamics, g(r), MSD and VACF of a trajectory, with plots.

The work is :func:`md.analysis.prepare_analysis` (checks what the file holds
before computing anything) and :meth:`md.analysis.PreparedAnalysis.run`
(computes, and writes per analysis a PNG plot and a CSV file of the data
behind it, :mod:`md.analysis.output`, plus ``summary.json`` with the scalar
results); this module parses the options, prints a short table and maps
errors to exit code 2.

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

import math
from pathlib import Path

from md.analysis import ANALYSES, prepare_analysis
from md.analysis.output import THERMO_LABELS
from md.cli._common import EXIT_BAD_INPUT, EXIT_OK, fail
from md.errors import AnalysisError, TrajectoryError


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


def main(args) -> int:
    """Body of ``md analyze``; returns the exit code."""
    explicit = [name for name in ANALYSES if getattr(args, name)]  # argparse's flag per name
    try:
        prepared = prepare_analysis(
            args.trajectory,
            None if args.all or not explicit else explicit,
            required=explicit,
            start=args.start,
            stop=args.stop,
            step=args.step,
            rdf_bins=args.rdf_bins,
            rdf_range=_parse_range(args.rdf_range, "--rdf-range", allow_single=True),
            window=_parse_range(args.fit, "--fit", allow_single=False),
            select=args.select,
            n_blocks=args.blocks,
            out=args.out,
            overwrite=args.overwrite,
            snapshot=args.all,
        )
    except (TrajectoryError, AnalysisError) as error:
        fail(str(error))
        return EXIT_BAD_INPUT
    info, span = prepared.info, prepared.info.frame_range
    print(
        f"md analyze: {info.path}, {info.n_atoms} atoms, {info.n_frames} of "
        f"{info.n_frames_total} frames (slice {span.start}:{span.stop}:{span.step}), units "
        f"{info.units}; {', '.join(prepared.selected)}"
    )
    for note in prepared.skipped:
        print(f"  {note}")
    try:
        done = prepared.run(verbose=not args.no_progress)
    except (TrajectoryError, AnalysisError) as error:
        fail(str(error))
        return EXIT_BAD_INPUT
    except OSError as error:
        fail(f"cannot write the analysis files in {prepared.out}: {error}")
        return EXIT_BAD_INPUT
    for doubt in done.warnings:
        print(f"  warning: {doubt}")
    _print_table(done.results, done.labels)
    print(f"Wrote {', '.join(done.files)} to {done.out}/")
    return EXIT_OK


# ----------------------------------------------------------------- helpers
def _parse_range(text: str | None, option: str, allow_single: bool):
    """``MAX`` or ``MIN:MAX`` (``START:END``) as two numbers; the library checks their order."""
    if text is None:
        return None
    try:
        values = [float(p) for p in text.split(":")]
    except ValueError:
        values = []
    if len(values) == 1 and allow_single:
        values = [0.0, values[0]]
    form = "MAX or MIN:MAX" if allow_single else "START:END"
    if len(values) != 2 or not all(math.isfinite(v) for v in values):
        raise AnalysisError(f"{option} must be {form} (numbers), got {text!r}")
    return tuple(values)


def _print_table(results: dict, labels: dict) -> None:
    rows = []
    if "thermo" in results:
        t = results["thermo"]
        for name, average in t.averages.items():
            quantity = THERMO_LABELS.get(name, (name, "energy"))[1]
            rows.append((f"<{name}>", average.mean, average.sem, labels[quantity]))
        which = "conserved-energy" if t.drift_of == "conserved_energy" else "energy"
        rows.append(
            (f"{which} drift per atom", t.energy_drift, t.energy_drift_err, labels["drift"])
        )
        rows.append((f"{which} fluctuation per atom", t.energy_fluctuation, None, labels["energy"]))
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
