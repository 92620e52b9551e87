"""Analyse a file as ``md analyze`` does: :func:`prepare_analysis` checks the analyses
against the file and writes nothing; :meth:`PreparedAnalysis.run` computes them and
writes their files and ``summary.json``; :func:`analyze` does both.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from md._files import removed_on_error, unwritable_folder
from md.analysis._common import ANALYSES, TrajectoryInfo, trajectory_info, unit_labels
from md.analysis.displacement import msd
from md.analysis.output import WRITERS, output_files, write_summary
from md.analysis.pair_correlation import rdf
from md.analysis.thermo_stats import thermo
from md.analysis.velocity_correlation import vacf
from md.errors import AnalysisError
from md.render import render
from md.trajectory import verify_frames


@dataclass
class AnalysisResults:
    """What :meth:`PreparedAnalysis.run` computed and wrote.

    Attributes
    ----------
    info : TrajectoryInfo
        The file and the frames selected.
    results : dict
        Analysis name -> its result (:class:`ThermoResult`, :class:`RDFResult`,
        :class:`MSDResult`, :class:`VACFResult`), in :data:`ANALYSES` order.
    skipped : list of str
        Analyses left out, each with why (``"vacf skipped: ..."``).
    summary : dict
        What ``summary.json`` holds (NaN where the file has null).
    labels : dict
        Unit labels of the file's quantities (:func:`unit_labels`).
    out : Path
        The output folder; ``files`` are the names written there.
    """

    info: TrajectoryInfo
    results: dict
    skipped: list[str]
    summary: dict
    labels: dict[str, str]
    out: Path
    files: list[str]

    @property
    def warnings(self) -> list[str]:
        """Doubts about the results (a VACF sampled too sparsely to integrate)."""
        vacf_result = self.results.get("vacf")
        return list(vacf_result.warnings) if vacf_result is not None else []


@dataclass
class PreparedAnalysis:
    """Analyses checked against a file, with nothing computed or written (see
    :func:`prepare_analysis`)."""

    info: TrajectoryInfo
    selected: list[str]
    skipped: list[str]
    out: Path
    files: list[str]
    options: dict
    overwrite: bool = False
    snapshot: bool = False

    def run(self, verbose: bool = False) -> AnalysisResults:
        """Compute the analyses, write their files and ``summary.json``; return the results.

        ``verbose`` shows progress bars of the long analyses (on stderr).

        Raises
        ------
        AnalysisError, TrajectoryError
            If the data do not support a parameter (a g(r) range beyond half
            the cell, a fit window beyond the longest lag, a selection that
            matches no atoms); nothing is written then.
        OSError
            If the files cannot be written; those this call wrote are removed.
        """
        info, options = self.info, self.options
        path = info.path
        frames = {key: options[key] for key in ("start", "stop", "step")}
        results = {}
        for name in self.selected:
            if name == "thermo":
                results[name] = thermo(path, **frames, n_blocks=options["n_blocks"])
            elif name == "rdf":
                results[name] = rdf(
                    path,
                    bins=options["rdf_bins"],
                    r_range=options["rdf_range"],
                    **frames,
                    verbose=verbose,
                )
            elif name == "msd":
                results[name] = msd(
                    path,
                    window=options["window"],
                    select=options["select"],
                    n_blocks=options["n_blocks"],
                    **frames,
                    verbose=verbose,
                )
            else:
                results[name] = vacf(
                    path,
                    window=options["window"],
                    select=options["select"],
                    n_blocks=options["n_blocks"],
                    **frames,
                )
        labels = unit_labels(info.units)
        summary = {
            "trajectory": str(path),
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
            "skipped": self.skipped,
            **{name: result.summary() for name, result in results.items()},
        }
        self._write(results, summary, labels)
        return AnalysisResults(
            info, results, self.skipped, summary, labels, self.out, list(self.files)
        )

    def _write(self, results: dict, summary: dict, labels: dict) -> None:
        out = self.out
        with removed_on_error() as written:
            out.mkdir(parents=True, exist_ok=True)
            for name, result in results.items():
                written += [out / f for f in output_files(name)]
                WRITERS[name](result, out, labels)
            written.append(out / "summary.json")
            write_summary(summary, out / "summary.json")
            if self.snapshot:
                written.append(out / "snapshot.png")
                render(
                    self.info.path,
                    out / "snapshot.png",
                    frame=int(self.info.frames[-1]),
                    overwrite=True,
                )


def prepare_analysis(
    path,
    wanted: Sequence[str] | None = None,
    required: Sequence[str] = (),
    *,
    start=None,
    stop=None,
    step=None,
    rdf_bins: int = 200,
    rdf_range: tuple[float, float] | None = None,
    window: tuple[float, float] | None = None,
    select: str = "all",
    n_blocks: int = 5,
    out=None,
    overwrite: bool = False,
    snapshot: bool = False,
) -> PreparedAnalysis:
    """Check what ``md analyze`` would compute on a file; compute and write nothing.

    Parameters
    ----------
    path : str or Path
        An H5MD file written by ``md run``.
    wanted : sequence of str, optional
        Analyses among :data:`ANALYSES`, each of which the file must support;
        None: every analysis the file supports, the others skipped with a note.
    required : sequence of str
        Analyses that must be supported even when ``wanted`` is None.
    start, stop, step : int, optional
        Frames ``slice(start, stop, step)``.
    rdf_bins, rdf_range : int, (float, float)
        g(r) bins and range [length] (default 0 to half the smallest cell width).
    window : (float, float), optional
        Lag-time window [time] of the MSD fit and the Green-Kubo plateau.
    select : str
        MDAnalysis selection for MSD and VACF.
    n_blocks : int
        Time blocks of the standard errors.
    out : str or Path, optional
        Output folder (default ``analysis-<file stem>``).
    overwrite : bool
        Replace existing output files.
    snapshot : bool
        Also draw the last selected frame as ``snapshot.png`` (:mod:`md.render`).

    Raises
    ------
    TrajectoryError
        If the file is not a readable trajectory of ours (or a frame is damaged).
    AnalysisError
        For an option that cannot work (naming it), a wanted analysis the file
        cannot support, output files that exist, or an unwritable output folder.
    """
    unknown = [name for name in [*(wanted or ()), *required] if name not in ANALYSES]
    if unknown:
        raise AnalysisError(f"unknown analysis {unknown[0]!r} (known: {', '.join(ANALYSES)})")
    path = Path(path)
    info = trajectory_info(path, start, stop, step)
    verify_frames(path)  # damaged frames: a message naming the frame
    if info.n_frames == 0:
        raise AnalysisError(
            f"{path}: the frame selection start={start}, stop={stop}, step={step} selects no "
            f"frames (the file has {info.n_frames_total})"
        )
    _check_range(rdf_range, "--rdf-range", ("MIN", "MAX"))
    _check_range(window, "--fit", ("START", "END"))
    for option, value in (("--blocks", n_blocks), ("--rdf-bins", rdf_bins)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
            raise AnalysisError(f"{option} must be >= 1, got {value}")
    strict = set(required) | set(wanted or ())
    selected, skipped = [], []
    for name in ANALYSES if wanted is None else [n for n in ANALYSES if n in wanted]:
        reason = info.missing(name)
        if reason is None:
            selected.append(name)
        elif name in strict:
            raise AnalysisError(f"{path}: cannot compute {name}: {reason}")
        else:
            skipped.append(f"{name} skipped: {reason}")
    if not selected:
        raise AnalysisError(f"{path}: nothing to analyse ({'; '.join(skipped)})")
    out = Path(out) if out is not None else Path(f"analysis-{path.stem}")
    problem = unwritable_folder(out)
    if problem is not None:
        raise AnalysisError(f"output folder {out}: {problem}; choose another --out")
    files = [f for name in selected for f in output_files(name)] + ["summary.json"]
    if snapshot:
        files.append("snapshot.png")
    existing = [str(out / f) for f in files if (out / f).exists()]
    if existing and not overwrite:
        raise AnalysisError(
            f"output file(s) exist: {', '.join(existing)}; pass --overwrite or --out"
        )
    options = {
        "start": start,
        "stop": stop,
        "step": step,
        "rdf_bins": rdf_bins,
        "rdf_range": rdf_range,
        "window": window,
        "select": select,
        "n_blocks": n_blocks,
    }
    return PreparedAnalysis(info, selected, skipped, out, files, options, overwrite, snapshot)


def analyze(path, wanted: Sequence[str] | None = None, *, verbose: bool = False, **options):
    """Analyse a trajectory as ``md analyze`` does: compute, write the files, return the results.

    :func:`prepare_analysis` (``wanted`` and ``options`` are its arguments)
    then :meth:`PreparedAnalysis.run`; returns an :class:`AnalysisResults`.

    Examples
    --------
    >>> from md.analysis import analyze
    >>> done = analyze("lj.h5", ["thermo", "msd"], out="analysis-lj")  # doctest: +SKIP
    >>> done.results["msd"].diffusion.value, done.files  # doctest: +SKIP
    """
    return prepare_analysis(path, wanted, **options).run(verbose=verbose)


def _check_range(values, option: str, names: tuple[str, str]) -> None:
    if values is None:
        return
    low, high = names
    try:
        first, last = (float(v) for v in values)
    except (TypeError, ValueError):
        raise AnalysisError(f"{option} must be two numbers {low}, {high}, got {values!r}") from None
    if not (math.isfinite(first) and math.isfinite(last) and 0 <= first < last):
        raise AnalysisError(f"{option} needs 0 <= {low} < {high}, got {first:g}:{last:g}")
