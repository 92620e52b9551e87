"""Thermodynamic quantities from arrays, and analysis of the trajectories we write.

The pure numpy helpers the engine calls every step (:func:`kinetic_energy`,
:func:`degrees_of_freedom`, :func:`temperature`, :func:`pressure`) live in
:mod:`md.thermo`. What this package adds:

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

Modules
-------
One module per analysis: :mod:`~md.analysis.thermo_stats` (``thermo``),
:mod:`~md.analysis.pair_correlation` (``rdf``), :mod:`~md.analysis.displacement`
(``msd``), :mod:`~md.analysis.velocity_correlation` (``vacf``); what they share
(``TrajectoryInfo``, block averages, the diffusion fits' windows) in ``_common``;
:mod:`~md.analysis.prepare` (``prepare_analysis`` / ``analyze``: what ``md analyze``
does) and :mod:`~md.analysis.output` (its CSV files, figures and ``summary.json``).
The public names are importable from ``md.analysis``.
"""

from md.analysis._common import (
    ANALYSES,
    DEFAULT_WINDOW,
    MIN_BLOCK_FRAMES,
    MIN_DIFFUSION_FRAMES,
    BlockAverage,
    DiffusionFit,
    TrajectoryInfo,
    block_average,
    trajectory_info,
    unit_labels,
)
from md.analysis.displacement import MSDResult, msd
from md.analysis.pair_correlation import RDFResult, Shell, rdf
from md.analysis.prepare import AnalysisResults, PreparedAnalysis, analyze, prepare_analysis
from md.analysis.thermo_stats import ThermoResult, isothermal_compressibility, thermo
from md.analysis.velocity_correlation import (
    SAMPLING_TOLERANCE,
    VACFResult,
    vacf,
    velocity_autocorrelation,
)
from md.errors import AnalysisError  # re-exported: md.analysis raised it before it was a package

__all__ = [
    "ANALYSES",
    "DEFAULT_WINDOW",
    "MIN_BLOCK_FRAMES",
    "MIN_DIFFUSION_FRAMES",
    "SAMPLING_TOLERANCE",
    "AnalysisError",
    "AnalysisResults",
    "BlockAverage",
    "DiffusionFit",
    "MSDResult",
    "PreparedAnalysis",
    "RDFResult",
    "Shell",
    "ThermoResult",
    "TrajectoryInfo",
    "VACFResult",
    "analyze",
    "block_average",
    "isothermal_compressibility",
    "msd",
    "prepare_analysis",
    "rdf",
    "thermo",
    "trajectory_info",
    "unit_labels",
    "vacf",
    "velocity_autocorrelation",
]
