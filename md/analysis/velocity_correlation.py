"""The vacf analysis: velocity autocorrelation by FFT and the Green-Kubo diffusion
coefficient.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

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

logger = logging.getLogger(__name__)


#: Relative difference of trapezoidal and Simpson Green-Kubo integrals above which
#: the VACF counts as too coarsely sampled.
SAMPLING_TOLERANCE = 0.05


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
