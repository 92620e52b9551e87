"""What the analyses share: the file's frames and units (TrajectoryInfo), block averages,
the diffusion fits' windows and time blocks, progress bars. Re-exported by
:mod:`md.analysis`; private to the package otherwise.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
from numpy.typing import NDArray

from md.box import perpendicular_widths
from md.errors import AnalysisError, TrajectoryError
from md.trajectory import attr_text, maybe_json, open_h5md, split_edges
from md.units import get_units

ANALYSES = ("thermo", "rdf", "msd", "vacf")


#: Default window for diffusion fits, as fractions of the longest lag of one time block.
DEFAULT_WINDOW = (0.1, 0.5)


#: Fewest frames in a time block of a diffusion error estimate.
MIN_BLOCK_FRAMES = 10


#: Fewest frames for MSD and VACF (the default window then holds two lags).
MIN_DIFFUSION_FRAMES = 5


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


def _progress(frames, verbose: bool, what: str):
    """``frames``, with a tqdm bar when ``verbose``."""
    if not verbose:
        return frames
    from tqdm.auto import tqdm  # progress bar: only when asked for

    return tqdm(frames, desc=what)


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
