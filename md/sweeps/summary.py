"""One run's summary: block-averaged results from its trajectory (through md.analysis)."""

from __future__ import annotations

import logging
import math
from typing import Any

from md import analysis
from md.sweeps.plan import RESULTS

logger = logging.getLogger(__name__)


# --------------------------------------------------------------- summaries
def summarize(path, discard: float = 0.0, diffusion: bool = False, n_blocks: int = 5) -> dict:
    """Scalar results of one output: means with block errors, drift, optionally D.

    Parameters
    ----------
    path : str or Path
        An H5MD file written by ``md run``.
    discard : float
        Leading fraction of the frames left out (equilibration), 0 <= discard < 1.
    diffusion : bool
        Also fit the Einstein diffusion coefficient to the MSD.
    n_blocks : int
        Blocks of the standard errors (see :func:`md.analysis.block_average`).

    Returns
    -------
    dict
        ``temperature``, ``pressure``, ``density``, ``volume`` and the energies
        per atom (``potential_energy_per_atom`` etc.), each with ``<name>_err``
        (block standard error of the mean), ``energy_drift_per_atom``
        [energy/time] with its error (the drift of the conserved quantity:
        total energy plus the heat bath's and barostat's for thermostatted
        runs, see :func:`md.analysis.thermo`), ``diffusion`` [length^2/time]
        with its error when asked, ``n_atoms``, ``n_frames`` (analysed),
        ``units``; in the file's units.
    """
    info = analysis.trajectory_info(path)
    start = int(math.floor(discard * info.n_frames_total))
    result = analysis.thermo(path, start=start, n_blocks=n_blocks)
    n = result.n_atoms
    row: dict[str, Any] = {"units": result.units, "n_atoms": n, "n_frames": len(result.times)}
    names = (
        "temperature",
        "pressure",
        "density",
        "volume",
        "potential_energy",
        "kinetic_energy",
        "total_energy",
    )
    for name in names:
        column = name if name in RESULTS else f"{name}_per_atom"
        scale = 1.0 / n if column.endswith("_per_atom") else 1.0
        average = result.averages.get(name)
        row[column] = average.mean * scale if average else math.nan
        row[f"{column}_err"] = average.sem * scale if average else math.nan
    row["energy_drift_per_atom"] = result.energy_drift
    row["energy_drift_per_atom_err"] = result.energy_drift_err
    if diffusion:
        fit = analysis.msd(path, start=start, n_blocks=n_blocks).diffusion
        row["diffusion"], row["diffusion_err"] = fit.value, fit.error
    return row
