"""Thermodynamic quantities from arrays, and analysis of the trajectories we write.

The pure numpy helpers the engine calls every step (:func:`kinetic_energy`,
:func:`degrees_of_freedom`, :func:`temperature`, :func:`pressure`) live in
:mod:`md.thermo` and are re-exported here. What this module adds:

* Analyses of an H5MD file written by :class:`md.trajectory.H5MDWriter`:
  :func:`thermo` (time series, block-averaged means, energy drift),
  :func:`rdf` (g(r) per type pair from MDAnalysis's ``capped_distance``,
  normalised frame by frame with each frame's volume; coordination numbers),
  :func:`msd` (``MDAnalysis.analysis.msd.EinsteinMSD``
  with FFT, Einstein diffusion coefficient) and :func:`vacf` (velocity
  autocorrelation by FFT, Green-Kubo diffusion coefficient).

Every analysis takes ``start``, ``stop`` and ``step``, which select stored
frames exactly as ``slice(start, stop, step)`` (and as MDAnalysis's
``AnalysisBase.run``) does.

Units
-----
Results are in the units the file stores: reduced units for ``lj`` runs
(sigma, tau, epsilon) and Angstrom, ps, eV, K for ``metal`` runs (times in ps,
not the engine's internal time unit). :func:`unit_labels` names them.

Unwrapping
----------
The MSD uses positions unwrapped with the stored periodic images,
``position + image @ cell`` (``image * edges`` for an orthorhombic box),
which is exact (velocities are not used to unwrap). The VACF uses the stored velocities only.

What is written here rather than taken from a library
-----------------------------------------------------
* :func:`block_average`: contiguous blocks and the standard error of their
  means (a fixed number of blocks; no library routine for it is at hand).
* :func:`velocity_autocorrelation`: the Wiener-Khinchin autocorrelation with
  ``scipy.fft`` (zero-padded to avoid wrap-around, normalised per lag by the
  number of time origins), vectorised over atoms; the same estimator as
  ``tidynamics.acf``, which loops over one series at a time.
* Statistical errors of diffusion coefficients: the selected frames are cut
  into ``n_blocks`` consecutive time blocks, D is measured in each block over
  the same lag window, and the standard error of the block values is
  reported (the value itself comes from the whole selection). Time blocks,
  unlike groups of atoms, also catch fluctuations that all atoms share.
* First peak and first minimum of g(r) via ``scipy.signal.find_peaks``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np
from numpy.typing import NDArray

from md._files import removed_on_error, unwritable_folder
from md.analysis_output import WRITERS, output_files, write_summary
from md.box import perpendicular_widths
from md.errors import AnalysisError, TrajectoryError
from md.render import render
from md.trajectory import (
    attr_text,
    maybe_json,
    open_h5md,
    open_trajectory,
    split_edges,
    unwrap_frames,
    verify_frames,
)
from md.units import get_units

logger = logging.getLogger(__name__)

ANALYSES = ("thermo", "rdf", "msd", "vacf")
#: Default window for diffusion fits, as fractions of the longest lag of one time block.
DEFAULT_WINDOW = (0.1, 0.5)
#: Fewest frames in a time block of a diffusion error estimate.
MIN_BLOCK_FRAMES = 10
#: Fewest frames for MSD and VACF (the default window then holds two lags).
MIN_DIFFUSION_FRAMES = 5
#: Relative difference of trapezoidal and Simpson Green-Kubo integrals above which
#: the VACF counts as too coarsely sampled.
SAMPLING_TOLERANCE = 0.05


# ------------------------------------------------------------ array analyses


@dataclass(frozen=True)
class BlockAverage:
    """Mean of a time series with its block-averaged standard error.

    Attributes
    ----------
    mean : float
        Mean over all samples.
    std : float
        Sample standard deviation (ddof = 1) of the samples; NaN for one sample.
    sem : float
        Standard error of the mean from ``n_blocks`` contiguous block means;
        NaN with fewer than two blocks.
    n_blocks : int
        Number of blocks used.
    """

    mean: float
    std: float
    sem: float
    n_blocks: int


def block_average(values, n_blocks: int = 5) -> BlockAverage:
    """Return the mean and its standard error from contiguous block means.

    The series is cut into ``n_blocks`` equal blocks (at most one sample per
    block; the earliest ``len % n_blocks`` samples are left out of the
    blocks, not of the mean). When blocks are longer than the correlation
    time, their means are independent and ``std(block means) / sqrt(n_blocks)``
    estimates the standard error of the mean; shorter blocks underestimate it.

    Parameters
    ----------
    values : array_like, shape (n,)
        The time series.
    n_blocks : int
        Number of blocks (>= 2 for an error estimate).
    """
    values = np.asarray(values, dtype=np.float64)
    n = len(values)
    if values.ndim != 1 or n == 0:
        raise ValueError(f"block_average needs a non-empty 1-D series, got shape {values.shape}")
    if n_blocks < 1:
        raise ValueError(f"n_blocks must be >= 1, got {n_blocks}")
    n_blocks = min(int(n_blocks), n)
    size = n // n_blocks
    means = values[n - n_blocks * size :].reshape(n_blocks, size).mean(axis=1)
    sem = float(means.std(ddof=1) / math.sqrt(n_blocks)) if n_blocks > 1 else math.nan
    std = float(values.std(ddof=1)) if n > 1 else math.nan
    return BlockAverage(mean=float(values.mean()), std=std, sem=sem, n_blocks=n_blocks)


def velocity_autocorrelation(velocities: NDArray[np.float64], chunk: int | None = None) -> NDArray:
    """Return the per-atom velocity autocorrelation by FFT.

    ``C_i(k) = (1 / (F - k)) sum_t v_i(t) . v_i(t + k)`` for lags
    ``k = 0 .. F - 1``, averaged over all time origins (Wiener-Khinchin with
    zero padding to at least 2F, so no periodic wrap-around).

    Parameters
    ----------
    velocities : ndarray, shape (F, N, 3)
        Velocities on evenly spaced frames [length/time].
    chunk : int, optional
        Atoms transformed at once; by default as many as keep the spectrum
        near 256 MB.

    Returns
    -------
    ndarray of float64, shape (F, N)
        ``C_i(k)`` [length^2/time^2]; average over axis 1 for the VACF.
    """
    import scipy.fft  # scipy submodule: loaded only by this analysis

    velocities = np.asarray(velocities, dtype=np.float64)
    n_frames, n_atoms = velocities.shape[:2]
    n_fft = scipy.fft.next_fast_len(2 * n_frames, real=True)
    origins = (n_frames - np.arange(n_frames)).astype(np.float64)
    if chunk is None:
        chunk = max(1, int(2**28 // (16 * 3 * (n_fft // 2 + 1))))
    result = np.empty((n_frames, n_atoms))
    for first in range(0, n_atoms, chunk):
        block = velocities[:, first : first + chunk, :]
        spectrum = scipy.fft.rfft(block, n=n_fft, axis=0)
        power = spectrum.real**2 + spectrum.imag**2
        correlation = scipy.fft.irfft(power, n=n_fft, axis=0)[:n_frames]
        result[:, first : first + chunk] = correlation.sum(axis=2) / origins[:, None]
    return result


# --------------------------------------------------------------- file access
@dataclass
class TrajectoryInfo:
    """What an H5MD file holds, for the frames an analysis selected.

    Times are in the file's time unit (tau or ps), lengths in its length unit.
    """

    path: Path
    units: str
    n_atoms: int
    n_frames_total: int
    frames: NDArray[np.int64]
    steps: NDArray[np.int64]
    times: NDArray[np.float64]
    pbc: NDArray[np.bool_]
    types: NDArray[np.int32]
    type_names: tuple[str, ...]
    has_velocities: bool
    observables: tuple[str, ...]
    min_edge: float  # smallest box width (edge, or face distance of a tilted cell) over the frames

    @property
    def n_frames(self) -> int:
        return len(self.frames)

    @property
    def frame_range(self) -> slice:
        """The selection as a slice with explicit non-negative bounds."""
        return _as_slice(self.frames)

    def frame_interval(self) -> float:
        """Time between selected frames; AnalysisError if they are not evenly spaced."""
        if self.n_frames < 2:
            raise AnalysisError(f"{self.path}: needs at least two frames, selected {self.n_frames}")
        spacing = np.diff(self.times)
        dt = float(spacing.mean())
        if not (dt > 0 and np.allclose(spacing, dt, rtol=1e-6, atol=0.0)):
            raise AnalysisError(
                f"{self.path}: the selected frames are not evenly spaced in time (intervals "
                f"{spacing.min():g} to {spacing.max():g}); select an evenly spaced part with "
                "start/stop/step"
            )
        return dt

    def missing(self, analysis: str) -> str | None:
        """Why ``analysis`` cannot run on this selection, or None if it can."""
        if self.n_frames == 0:
            return f"no frames selected (the file has {self.n_frames_total})"
        if analysis == "thermo":
            if "total_energy" not in self.observables:
                return "the file stores no thermodynamic observables"
        elif analysis == "rdf":
            if not self.pbc.all():
                return (
                    "g(r) needs a box periodic along x, y and z (boundary "
                    f"{['periodic' if p else 'none' for p in self.pbc]})"
                )
        elif analysis in ("msd", "vacf"):
            if analysis == "vacf" and not self.has_velocities:
                return (
                    "the file stores no velocities (set velocities = true under [output] "
                    "to store them)"
                )
            if self.n_frames < MIN_DIFFUSION_FRAMES:
                return (
                    f"{analysis} needs at least {MIN_DIFFUSION_FRAMES} frames, selected "
                    f"{self.n_frames}"
                )
        else:
            raise ValueError(f"unknown analysis {analysis!r} (known: {', '.join(ANALYSES)})")
        return None


def trajectory_info(path, start=None, stop=None, step=None) -> TrajectoryInfo:
    """Describe an H5MD file and the frames ``slice(start, stop, step)`` selects.

    Raises
    ------
    md.trajectory.TrajectoryError
        If the file is missing, not HDF5, or not in our H5MD layout.
    AnalysisError
        If ``step`` is not a positive integer.
    """

    path = Path(path)
    with open_h5md(path) as f:
        try:
            group = f["particles/trajectory"]
            parameters = f["parameters"].attrs if "parameters" in f else {}
            units = attr_text(parameters.get("units", "lj"))
            n_total = len(group["position/step"])
            frames = _select(n_total, start, stop, step)
            sel = _as_slice(frames)
            names = maybe_json(parameters.get("type_names", "[]"))
            types = group["species"][()].astype(np.int32)
            if not names:
                names = [f"T{t}" for t in range(int(types.max()) + 1)] if len(types) else []
            edges = group["box/edges/value"][sel] if len(frames) else np.zeros((0, 3))
            widths = np.array(
                [perpendicular_widths(b, t) for b, t in zip(*split_edges(edges), strict=True)]
            )
            observables = ()
            if "observables" in f:
                observables = tuple(
                    name
                    for name, element in f["observables"].items()
                    if len(frames) and np.isfinite(element["value"][sel]).any()
                )
            return TrajectoryInfo(
                path=path,
                units=units,
                n_atoms=len(types),
                n_frames_total=n_total,
                frames=frames,
                steps=group["position/step"][sel] if len(frames) else np.zeros(0, np.int64),
                times=group["position/time"][sel] if len(frames) else np.zeros(0),
                pbc=np.array([attr_text(b) == "periodic" for b in group["box"].attrs["boundary"]]),
                types=types,
                type_names=tuple(str(n) for n in names),
                has_velocities="velocity" in group,
                observables=observables,
                min_edge=float(widths.min()) if len(widths) else math.nan,
            )
        except (KeyError, TypeError, OSError) as error:
            raise TrajectoryError(f"{path}: not a trajectory written by leapmd ({error})") from None


def unit_labels(units: str) -> dict[str, str]:
    """Labels of the quantities in a file of unit system ``units`` (for axes and tables)."""
    labels = dict(get_units(units).labels)
    length, time = labels["length"], labels["time"]
    labels["diffusion"] = f"{length}^2/{time}"
    labels["msd"] = f"{length}^2"
    labels["vacf"] = f"{length}^2/{time}^2"
    labels["drift"] = f"{labels['energy']}/{time}"
    return labels


def _select(n_frames: int, start, stop, step) -> NDArray[np.int64]:
    for name, value in (("start", start), ("stop", stop), ("step", step)):
        if value is not None and (
            isinstance(value, bool) or not isinstance(value, int | np.integer)
        ):
            raise AnalysisError(f"{name} must be an integer frame index, got {value!r}")
    if step is not None and step < 1:
        raise AnalysisError(f"step must be a positive integer, got {step}")
    return np.arange(n_frames, dtype=np.int64)[slice(start, stop, step)]


def _as_slice(frames: NDArray[np.int64]) -> slice:
    if len(frames) == 0:
        return slice(0, 0, 1)
    step = int(frames[1] - frames[0]) if len(frames) > 1 else 1
    return slice(int(frames[0]), int(frames[-1]) + 1, step)


def _require(info: TrajectoryInfo, analysis: str) -> None:
    reason = info.missing(analysis)
    if reason is not None:
        raise AnalysisError(f"{info.path}: cannot compute {analysis}: {reason}")


def _read(info: TrajectoryInfo, name: str) -> NDArray:
    """Read ``particles/trajectory/<name>/value`` on the selected frames (file units)."""
    with h5py.File(info.path, "r") as f:
        return f[f"particles/trajectory/{name}/value"][_as_slice(info.frames)]


def _diffusion_plan(
    n_frames: int, dt: float, window, n_blocks: int, what: str, unit: str
) -> tuple[float, float, int]:
    """Resolve the lag window [time] and the number of time blocks for a D estimate.

    Blocks hold at least ``MIN_BLOCK_FRAMES`` frames. The default window is
    ``DEFAULT_WINDOW`` times the longest lag of one block (of the whole
    selection when there are fewer than two blocks); a given window reduces
    the number of blocks until each spans at least twice its end.
    """
    if isinstance(n_blocks, bool) or not isinstance(n_blocks, int | np.integer) or n_blocks < 1:
        raise AnalysisError(f"n_blocks must be a positive integer, got {n_blocks!r}")
    longest = (n_frames - 1) * dt
    blocks = min(int(n_blocks), n_frames // MIN_BLOCK_FRAMES)
    if window is None:
        span = (n_frames // blocks - 1) * dt if blocks >= 2 else longest
        t0, t1 = DEFAULT_WINDOW[0] * span, DEFAULT_WINDOW[1] * span
    else:
        t0, t1 = (float(w) for w in window)
        if not (0 <= t0 < t1):
            raise AnalysisError(f"{what}: the fit window needs 0 <= start < end, got {t0:g}:{t1:g}")
        if t1 > longest * (1 + 1e-9):
            raise AnalysisError(
                f"{what}: the fit window {t0:g}:{t1:g} {unit} ends beyond the longest lag, "
                f"{longest:g} {unit}"
            )
        while blocks >= 2 and (n_frames // blocks - 1) * dt < 2 * t1:
            blocks -= 1
    return t0, t1, max(blocks, 1)


def _window_mask(lag_times: NDArray, t0: float, t1: float, what: str, unit: str) -> NDArray:
    mask = (lag_times >= t0 * (1 - 1e-9)) & (lag_times <= t1 * (1 + 1e-9))
    if mask.sum() < 2:
        raise AnalysisError(
            f"{what}: the fit window {t0:g}:{t1:g} {unit} holds {int(mask.sum())} lag time(s); "
            f"lags run from 0 to {lag_times[-1]:g} {unit} every {lag_times[1] - lag_times[0]:g} "
            f"{unit}"
        )
    return mask


def _block_bounds(n_frames: int, n_blocks: int) -> list[tuple[int, int]]:
    if n_blocks < 2:
        return []
    length = n_frames // n_blocks
    return [(b * length, (b + 1) * length) for b in range(n_blocks)]


def _sem(values: Sequence[float]) -> float:
    values = np.asarray(values, dtype=np.float64)
    return float(values.std(ddof=1) / math.sqrt(len(values))) if len(values) > 1 else math.nan


def _selected_atoms(info: TrajectoryInfo, select: str) -> NDArray[np.int64]:
    """Atom indices an MDAnalysis selection string picks (on a topology-only Universe)."""
    if select in (None, "all"):
        return np.arange(info.n_atoms)
    import MDAnalysis as mda  # heavy: MDAnalysis on first use

    universe = mda.Universe.empty(info.n_atoms, trajectory=False)
    universe.add_TopologyAttr("types", [info.type_names[t] for t in info.types])
    try:
        indices = universe.select_atoms(select).indices
    except Exception as error:  # MDAnalysis raises several types for bad selections
        raise AnalysisError(f"bad atom selection {select!r}: {error}") from None
    if len(indices) == 0:
        raise AnalysisError(
            f"atom selection {select!r} matches no atoms (types: {', '.join(info.type_names)})"
        )
    return indices


# -------------------------------------------------------------------- thermo
@dataclass
class ThermoResult:
    """Thermodynamic time series of a trajectory and their averages.

    Attributes
    ----------
    steps, times : ndarray, shape (F,)
        Step numbers and times [time] of the selected frames.
    series : dict of str to ndarray, shape (F,)
        Observables present in the file (``potential_energy``, ``kinetic_energy``,
        ``total_energy`` [energy], ``temperature`` [temperature], ``pressure``
        [energy/length^3]), total not per atom.
    averages : dict of str to BlockAverage
        Mean, standard deviation and block-averaged standard error of each
        series that is finite on every selected frame.
    energy_drift, energy_drift_err : float
        Slope of a least-squares line through the conserved quantity per atom
        against time, and its standard error [energy/time]; NaN with fewer
        than 3 frames. The conserved quantity is ``conserved_energy`` when the
        file stores it (a thermostatted or barostatted run: total energy plus
        the heat bath's and the barostat's), else ``total_energy``.
    energy_fluctuation : float
        Standard deviation of that quantity per atom about the line [energy].
    drift_of : str
        Which series the drift was measured on.
    """

    units: str
    n_atoms: int
    steps: NDArray[np.int64]
    times: NDArray[np.float64]
    series: dict[str, NDArray[np.float64]]
    averages: dict[str, BlockAverage]
    energy_drift: float
    energy_drift_err: float
    energy_fluctuation: float
    compressibility: float = math.nan
    drift_of: str = "total_energy"

    def summary(self) -> dict:
        """Scalar results as plain data (for ``summary.json``)."""
        out = {
            name: {"mean": a.mean, "std": a.std, "sem": a.sem, "n_blocks": a.n_blocks}
            for name, a in self.averages.items()
        }
        out["energy_drift_per_atom"] = self.energy_drift
        out["energy_drift_per_atom_err"] = self.energy_drift_err
        out["energy_fluctuation_per_atom"] = self.energy_fluctuation
        out["energy_drift_of"] = self.drift_of
        out["isothermal_compressibility"] = self.compressibility
        out["n_frames"] = len(self.times)
        return out


def thermo(path, start=None, stop=None, step=None, n_blocks: int = 5) -> ThermoResult:
    """Time series and averages of the thermodynamic observables of an H5MD file.

    Parameters
    ----------
    path : str or Path
        Trajectory written by :class:`md.trajectory.H5MDWriter`.
    start, stop, step : int, optional
        Frame selection, as ``slice(start, stop, step)``.
    n_blocks : int
        Blocks for the standard errors (see :func:`block_average`).

    Examples
    --------
    >>> # result = thermo("run.h5", start=10)
    >>> # result.averages["temperature"].mean, result.energy_drift
    """
    from scipy import stats  # scipy submodule: loaded only by this analysis

    info = trajectory_info(path, start, stop, step)
    _require(info, "thermo")
    series = {}
    with h5py.File(info.path, "r") as f:
        for name in info.observables:
            series[name] = f[f"observables/{name}/value"][_as_slice(info.frames)].astype(float)
    averages = {
        name: block_average(values, n_blocks)
        for name, values in series.items()
        if np.isfinite(values).all()
    }
    drift = drift_err = fluctuation = math.nan
    drift_of = "total_energy"
    if "conserved_energy" in series and np.isfinite(series["conserved_energy"]).all():
        drift_of = "conserved_energy"
    total = series[drift_of] / info.n_atoms
    if len(total) >= 3 and np.isfinite(total).all() and np.ptp(info.times) > 0:
        fit = stats.linregress(info.times, total)
        drift, drift_err = float(fit.slope), float(fit.stderr)
        fluctuation = float(np.std(total - (fit.intercept + fit.slope * info.times)))
    compressibility = math.nan
    if "volume" in series and "temperature" in series:
        compressibility = isothermal_compressibility(
            series["volume"], float(np.mean(series["temperature"])), get_units(info.units).kB
        )
    return ThermoResult(
        units=info.units,
        n_atoms=info.n_atoms,
        steps=info.steps,
        times=info.times,
        series=series,
        averages=averages,
        energy_drift=drift,
        energy_drift_err=drift_err,
        energy_fluctuation=fluctuation,
        compressibility=compressibility,
        drift_of=drift_of,
    )


def isothermal_compressibility(volumes, temperature: float, kB: float = 1.0) -> float:
    """Return kappa_T = var(V) / (kB T <V>) from volume fluctuations [length^3/energy].

    Valid for volumes sampled in the isothermal-isobaric ensemble; NaN when the
    volume does not fluctuate (a constant-volume run) or is not finite.

    Examples
    --------
    >>> round(isothermal_compressibility([9.0, 11.0, 9.0, 11.0], temperature=2.0), 6)
    0.05
    """
    v = np.asarray(volumes, dtype=np.float64)
    if len(v) < 2 or not np.all(np.isfinite(v)) or not temperature > 0:
        return math.nan
    variance = float(np.var(v))
    if variance <= 1e-24 * float(np.mean(v)) ** 2:
        return math.nan
    return variance / (kB * temperature * float(np.mean(v)))


# ----------------------------------------------------------------------- RDF
@dataclass(frozen=True)
class Shell:
    """First coordination shell read off a g(r).

    ``r_peak``/``g_peak`` locate the highest peak; ``r_min`` is the first
    minimum after it (NaN if none is found) and ``coordination`` the mean
    number of partners within ``r_min``.
    """

    r_peak: float
    g_peak: float
    r_min: float
    g_min: float
    coordination: float


@dataclass
class RDFResult:
    """Radial distribution functions per type pair.

    Attributes
    ----------
    edges : ndarray, shape (bins + 1,)
        Bin edges [length]; ``r`` are the bin centres.
    g : dict of str to ndarray, shape (bins,)
        g(r) per pair, keyed ``"A-B"`` (``"all"`` for every atom when there are
        several types).
    coordination : dict of str to ndarray, shape (bins + 1,)
        Mean number of B atoms at distances from ``edges[0]`` to ``edges[k]`` of
        an A atom (0 at the first edge; the usual n(r) when the range starts at 0).
    shells : dict of str to Shell
        First peak, first minimum and first-shell coordination per pair.
    """

    units: str
    n_frames: int
    edges: NDArray[np.float64]
    g: dict[str, NDArray[np.float64]]
    coordination: dict[str, NDArray[np.float64]]
    shells: dict[str, Shell]

    @property
    def r(self) -> NDArray[np.float64]:
        return 0.5 * (self.edges[1:] + self.edges[:-1])

    def coordination_at(self, pair: str, r: float) -> float:
        """Mean number of partners within ``r`` [length] (linear between bin edges)."""
        return float(np.interp(r, self.edges, self.coordination[pair]))

    def summary(self) -> dict:
        out = {
            pair: {
                "first_peak_r": s.r_peak,
                "first_peak_g": s.g_peak,
                "first_min_r": s.r_min,
                "first_min_g": s.g_min,
                "coordination": s.coordination,
            }
            for pair, s in self.shells.items()
        }
        out["n_frames"] = self.n_frames
        out["range"] = [float(self.edges[0]), float(self.edges[-1])]
        out["bins"] = len(self.edges) - 1
        return out


def rdf(
    path,
    bins: int = 200,
    r_range: tuple[float, float] | None = None,
    pairs: Sequence[tuple[str, str]] | None = None,
    start=None,
    stop=None,
    step=None,
    verbose: bool = False,
) -> RDFResult:
    """Radial distribution functions, normalised frame by frame with each frame's volume.

    Pair distances come from ``MDAnalysis.lib.distances.capped_distance``
    (minimum image in any cell, triclinic included). Each frame's histogram
    is normalised with that frame's density N_B / V before frames are
    averaged, so g(r) stays right when the volume fluctuates (constant
    pressure); MDAnalysis's ``InterRDF`` divides by the mean volume instead.
    Same-type pairs exclude each atom's distance to itself, so an ideal gas
    gives g = 1 with the N (N - 1) normalisation. The coordination number is
    the cumulative pair count divided by frames and A atoms.

    Parameters
    ----------
    bins : int
        Number of bins.
    r_range : (float, float), optional
        [length]; default 0 to half the smallest cell width of the selected
        frames (the edge for orthorhombic boxes), which is also the largest
        range allowed (minimum image).
    pairs : sequence of (str, str), optional
        Type-name pairs; default every pair of types (and ``"all"`` when there
        are several types).
    start, stop, step : int, optional
        Frame selection.
    verbose : bool
        Show a progress bar over frames.
    """
    from MDAnalysis.lib.distances import capped_distance  # heavy: MDAnalysis on first use
    from scipy.signal import find_peaks  # scipy submodule: loaded only by this analysis

    info = trajectory_info(path, start, stop, step)
    _require(info, "rdf")
    if isinstance(bins, bool) or not isinstance(bins, int | np.integer) or bins < 1:
        raise AnalysisError(f"bins must be a positive integer, got {bins!r}")
    half = 0.5 * info.min_edge
    r_min, r_max = (0.0, half) if r_range is None else (float(v) for v in r_range)
    if not (0 <= r_min < r_max):
        raise AnalysisError(f"RDF range must satisfy 0 <= r_min < r_max, got {r_min:g}:{r_max:g}")
    if r_max > half * (1 + 1e-9):
        raise AnalysisError(
            f"RDF range up to {r_max:g} exceeds half the smallest cell width ({half:g}) of the "
            "selected frames; the minimum image cannot see farther"
        )
    names = list(info.type_names)
    present = [n for t, n in enumerate(names) if np.any(info.types == t)]
    if pairs is None:
        pairs = [("all", "all")] if len(present) > 1 else []
        pairs += [(a, b) for i, a in enumerate(present) for b in present[i:]]
    if not pairs:
        raise AnalysisError("no type pairs to compute g(r) for")
    for a, b in pairs:
        if (a == "all") != (b == "all"):
            raise AnalysisError(f"pair ({a!r}, {b!r}): 'all' pairs only with 'all'")
    universe = open_trajectory(info.path)
    types = universe.atoms.types

    def group(name):
        if name == "all":
            return universe.atoms
        if name not in present:
            raise AnalysisError(f"no atoms of type {name!r} (types: {', '.join(present)})")
        return universe.atoms[types == name]

    groups = {(a, b): (group(a), group(b)) for a, b in pairs}
    edges = np.linspace(r_min, r_max, int(bins) + 1)
    shell = 4.0 / 3.0 * np.pi * np.diff(edges**3)
    counts = {key: np.zeros(int(bins)) for key in groups}
    weighted = {key: np.zeros(int(bins)) for key in groups}  # counts times the frame's volume
    sel = info.frame_range
    frames = universe.trajectory[sel.start : sel.stop : sel.step]
    for ts in _progress(frames, verbose, "g(r)"):
        volume = float(ts.volume)
        for (a, b), (g1, g2) in groups.items():
            found, distances = capped_distance(
                g1.positions, g2.positions, max_cutoff=r_max, min_cutoff=None, box=ts.dimensions
            )
            if a == b:  # the same group: drop each atom's distance to itself
                distances = distances[found[:, 0] != found[:, 1]]
            histogram = np.histogram(distances, bins=edges)[0].astype(np.float64)
            counts[(a, b)] += histogram
            weighted[(a, b)] += histogram * volume
    n_frames = max(info.n_frames, 1)
    g, coordination, shells = {}, {}, {}
    for (a, b), (g1, g2) in groups.items():
        key = "all" if (a, b) == ("all", "all") else f"{a}-{b}"
        n_pairs = len(g1) * len(g2) - (len(g1) if a == b else 0)
        values = weighted[(a, b)] / (n_frames * n_pairs * shell)
        cumulative = np.concatenate([[0.0], np.cumsum(counts[(a, b)])]) / (n_frames * len(g1))
        g[key], coordination[key] = values, cumulative
        shells[key] = _first_shell(edges, values, cumulative, find_peaks)
    return RDFResult(
        units=info.units,
        n_frames=info.n_frames,
        edges=edges,
        g=g,
        coordination=coordination,
        shells=shells,
    )


def _progress(frames, verbose: bool, what: str):
    """``frames``, with a tqdm bar when ``verbose``."""
    if not verbose:
        return frames
    from tqdm.auto import tqdm  # progress bar: only when asked for

    return tqdm(frames, desc=what)


def _first_shell(edges, values, cumulative, find_peaks) -> Shell:
    centres = 0.5 * (edges[1:] + edges[:-1])
    if not np.any(values > 0):
        return Shell(math.nan, math.nan, math.nan, math.nan, math.nan)
    i_peak = int(np.argmax(values))
    g_peak = float(values[i_peak])
    minima, _ = find_peaks(-values[i_peak:], prominence=0.1 * g_peak)
    if len(minima) == 0:
        return Shell(float(centres[i_peak]), g_peak, math.nan, math.nan, math.nan)
    i_min = i_peak + int(minima[0])
    r_min = float(centres[i_min])
    return Shell(
        r_peak=float(centres[i_peak]),
        g_peak=g_peak,
        r_min=r_min,
        g_min=float(values[i_min]),
        coordination=float(np.interp(r_min, edges, cumulative)),
    )


# ----------------------------------------------------------------------- MSD
@dataclass
class DiffusionFit:
    """A self-diffusion coefficient and how it was obtained.

    ``value`` [length^2/time] comes from all selected frames; ``error`` is
    the standard error over ``n_blocks`` consecutive time blocks measured
    over the same lag ``window`` [time] (NaN with fewer than two blocks).
    """

    value: float
    error: float
    window: tuple[float, float]
    n_blocks: int
    method: str

    def summary(self) -> dict:
        return {
            "D": self.value,
            "D_err": self.error,
            "window": list(self.window),
            "n_blocks": self.n_blocks,
            "method": self.method,
        }


@dataclass
class MSDResult:
    """Mean squared displacement and the Einstein diffusion coefficient.

    Attributes
    ----------
    lag_times : ndarray, shape (F,)
        [time], from 0.
    msd : ndarray, shape (F,)
        Mean over atoms and time origins [length^2].
    diffusion : DiffusionFit
        D = slope / 6 of a least-squares line through the MSD over the window.
    intercept : float
        Intercept of that line [length^2] (for plotting it).
    """

    units: str
    n_atoms: int
    lag_times: NDArray[np.float64]
    msd: NDArray[np.float64]
    diffusion: DiffusionFit
    intercept: float

    def summary(self) -> dict:
        return {
            **self.diffusion.summary(),
            "n_frames": len(self.lag_times),
            "n_atoms": self.n_atoms,
        }


def msd(
    path,
    window: tuple[float, float] | None = None,
    select: str = "all",
    n_blocks: int = 5,
    start=None,
    stop=None,
    step=None,
    verbose: bool = False,
) -> MSDResult:
    """Mean squared displacement via ``MDAnalysis.analysis.msd.EinsteinMSD`` (FFT).

    Positions are unwrapped with the stored images (exact), then shifted by
    each atom's first selected position before they reach MDAnalysis, whose
    frames hold float32: the MSD is translation invariant per atom, and
    displacements keep float32's relative precision where absolute
    coordinates would not. The diffusion coefficient is the slope of a
    least-squares line over ``window`` divided by 6 (3-D Einstein relation);
    its error comes from the same fit in ``n_blocks`` time blocks (see
    :class:`DiffusionFit`).

    Parameters
    ----------
    window : (float, float), optional
        Lag-time window of the fit [time]; default 10 % to 50 % of the
        longest lag of one time block (of the whole selection without blocks).
    select : str
        MDAnalysis selection of the atoms (e.g. ``"type A"``).
    n_blocks : int
        Time blocks for the standard error of D (fewer when the selection
        or the window needs it; 1 for no error estimate).
    start, stop, step : int, optional
        Frame selection (the frames must be evenly spaced in time).
    verbose : bool
        Show MDAnalysis's progress bars.
    """
    import MDAnalysis as mda  # heavy: MDAnalysis on first use
    from MDAnalysis.analysis.msd import EinsteinMSD  # heavy: MDAnalysis on first use
    from MDAnalysis.coordinates.memory import MemoryReader  # heavy: MDAnalysis on first use

    info = trajectory_info(path, start, stop, step)
    _require(info, "msd")
    dt = info.frame_interval()
    atoms = _selected_atoms(info, select)
    positions = _read(info, "position")[:, atoms]
    images = _read(info, "image")[:, atoms]
    boxes, tilts = split_edges(_read(info, "box/edges"))
    unwrapped = unwrap_frames(positions, images, boxes, tilts)
    displacements = unwrapped - unwrapped[:1]
    universe = mda.Universe.empty(len(atoms), trajectory=False)
    universe.load_new(displacements, format=MemoryReader, order="fac", dt=dt)
    unit = unit_labels(info.units)["time"]
    t0, t1, n_blocks = _diffusion_plan(info.n_frames, dt, window, n_blocks, "MSD", unit)

    def einstein(first: int, last: int, show: bool) -> NDArray:
        analysis = EinsteinMSD(universe, select="all", msd_type="xyz", fft=True)
        try:
            analysis.run(start=first, stop=last, verbose=show)
        except ImportError as error:
            raise AnalysisError(f"the FFT MSD needs the tidynamics package: {error}") from None
        series = np.asarray(analysis.results.timeseries, dtype=np.float64)
        series[0] = 0.0  # exact by definition; the FFT leaves round-off there
        return series

    mean_msd = einstein(0, info.n_frames, verbose)
    lag_times = np.arange(info.n_frames) * dt
    mask = _window_mask(lag_times, t0, t1, "MSD", unit)
    slope, intercept = np.polyfit(lag_times[mask], mean_msd[mask], 1)
    block_d = []
    for first, last in _block_bounds(info.n_frames, n_blocks):
        lags, block_mask = lag_times[: last - first], mask[: last - first]
        series = einstein(first, last, False)
        block_d.append(np.polyfit(lags[block_mask], series[block_mask], 1)[0] / 6.0)
    fit = DiffusionFit(
        value=float(slope / 6.0),
        error=_sem(block_d),
        window=(t0, t1),
        n_blocks=max(len(block_d), 1),
        method="Einstein: slope of MSD / 6",
    )
    return MSDResult(
        units=info.units,
        n_atoms=len(atoms),
        lag_times=lag_times,
        msd=mean_msd,
        diffusion=fit,
        intercept=float(intercept),
    )


# ---------------------------------------------------------------------- VACF
@dataclass
class VACFResult:
    """Velocity autocorrelation and the Green-Kubo diffusion coefficient.

    Attributes
    ----------
    lag_times : ndarray, shape (F,)
        [time], from 0.
    vacf : ndarray, shape (F,)
        <v(0) . v(t)> averaged over atoms and time origins [length^2/time^2].
    running_diffusion : ndarray, shape (F,)
        (1/3) of the trapezoidal integral of the VACF from 0 to t [length^2/time].
    diffusion : DiffusionFit
        Mean of ``running_diffusion`` over the window (the plateau).
    simpson_diffusion : float
        The same plateau mean with Simpson's rule
        (``scipy.integrate.cumulative_simpson``) [length^2/time]; far from
        ``diffusion.value`` when the frames are too sparse to resolve the
        VACF's initial decay.
    warnings : list of str
        Doubts about the result (coarse sampling), also logged.
    """

    units: str
    n_atoms: int
    lag_times: NDArray[np.float64]
    vacf: NDArray[np.float64]
    running_diffusion: NDArray[np.float64]
    diffusion: DiffusionFit
    simpson_diffusion: float = math.nan
    warnings: list[str] = field(default_factory=list)

    @property
    def normalized(self) -> NDArray[np.float64]:
        """VACF divided by its value at zero lag."""
        return self.vacf / self.vacf[0] if self.vacf[0] != 0 else np.full_like(self.vacf, np.nan)

    def summary(self) -> dict:
        return {
            **self.diffusion.summary(),
            "vacf_0": float(self.vacf[0]),
            "D_simpson": self.simpson_diffusion,
            "warnings": list(self.warnings),
            "n_frames": len(self.lag_times),
            "n_atoms": self.n_atoms,
        }


def vacf(
    path,
    window: tuple[float, float] | None = None,
    select: str = "all",
    n_blocks: int = 5,
    start=None,
    stop=None,
    step=None,
) -> VACFResult:
    """Velocity autocorrelation (FFT) and the Green-Kubo diffusion coefficient.

    D(t) = (1/3) int_0^t <v(0) . v(t')> dt' (trapezoidal rule,
    ``scipy.integrate.cumulative_trapezoid``); the reported D is its mean over
    ``window``. Averaging the running integral over the same window as the
    MSD fit makes the two estimates comparable: the MSD slope at lag t is
    6 D(t). The plateau is also computed with Simpson's rule; when the two
    rules differ by more than ``SAMPLING_TOLERANCE`` (relative), the frames are
    too far apart to resolve the VACF's initial decay (an LJ liquid at
    T = 1, rho = 0.8 needs frames at most about 0.05 tau apart) and the result
    carries a warning.

    Parameters
    ----------
    window : (float, float), optional
        Lag-time window of the plateau [time]; default as for :func:`msd`.
    select, n_blocks, start, stop, step
        As for :func:`msd`.
    """
    # scipy submodule: loaded only by this analysis
    from scipy.integrate import cumulative_trapezoid

    try:
        from scipy.integrate import cumulative_simpson  # scipy >= 1.12
    except ImportError:  # pragma: no cover - older scipy: no sampling check
        cumulative_simpson = None

    info = trajectory_info(path, start, stop, step)
    _require(info, "vacf")
    dt = info.frame_interval()
    atoms = _selected_atoms(info, select)
    velocities = _read(info, "velocity")[:, atoms]
    unit = unit_labels(info.units)["time"]
    t0, t1, n_blocks = _diffusion_plan(info.n_frames, dt, window, n_blocks, "VACF", unit)
    lag_times = np.arange(info.n_frames) * dt
    mask = _window_mask(lag_times, t0, t1, "VACF", unit)

    def plateau(block: NDArray) -> tuple[NDArray, NDArray, float]:
        correlation = velocity_autocorrelation(block).mean(axis=1)
        lags = lag_times[: len(correlation)]
        running = cumulative_trapezoid(correlation, lags, initial=0.0) / 3.0
        return correlation, running, float(running[mask[: len(lags)]].mean())

    mean_vacf, running, value = plateau(velocities)
    block_d = [
        plateau(velocities[first:last])[2] for first, last in _block_bounds(info.n_frames, n_blocks)
    ]
    fit = DiffusionFit(
        value=value,
        error=_sem(block_d),
        window=(t0, t1),
        n_blocks=max(len(block_d), 1),
        method="Green-Kubo: mean over the window of (1/3) int_0^t VACF",
    )
    simpson, doubts = math.nan, []
    if cumulative_simpson is not None:
        simpson = float(cumulative_simpson(mean_vacf, x=lag_times, initial=0.0)[mask].mean() / 3)
    if abs(simpson - value) > SAMPLING_TOLERANCE * max(abs(value), abs(simpson)):
        doubts.append(
            f"VACF frames {dt:g} {unit} apart are too sparse to integrate reliably: the "
            f"trapezoidal and Simpson rules give D = {value:.4g} and {simpson:.4g}; store "
            "velocities more often"
        )
        logger.warning("%s: %s", info.path, doubts[-1])
    return VACFResult(
        units=info.units,
        n_atoms=len(atoms),
        lag_times=lag_times,
        vacf=mean_vacf,
        running_diffusion=running,
        diffusion=fit,
        simpson_diffusion=simpson,
        warnings=doubts,
    )


# --------------------------------------------------------------- analyze a file
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
                render(self.info.path, out / "snapshot.png", frame=int(self.info.frames[-1]),
                       overwrite=True)  # fmt: skip


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
