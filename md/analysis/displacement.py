"""The msd analysis: ``MDAnalysis.analysis.msd.EinsteinMSD`` with FFT on positions unwrapped
with the stored images, and the Einstein diffusion coefficient.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from md.analysis._common import (
    DiffusionFit,
    _block_bounds,
    _diffusion_plan,
    _read,
    _require,
    _selected_atoms,
    _sem,
    _window_mask,
    trajectory_info,
    unit_labels,
)
from md.errors import AnalysisError
from md.trajectory import split_edges, unwrap_frames


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
