"""The thermo analysis: time series of the stored observables, block-averaged means,
energy drift, isothermal compressibility.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import h5py
import numpy as np
from numpy.typing import NDArray

from md.analysis._common import BlockAverage, _as_slice, _require, block_average, trajectory_info
from md.units import get_units


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
