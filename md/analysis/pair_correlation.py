"""The rdf analysis: g(r) per type pair from MDAnalysis's ``capped_distance``, normalised
frame by frame with each frame's volume; coordination numbers, first shell.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from md.analysis._common import _progress, _require, trajectory_info
from md.errors import AnalysisError
from md.trajectory import open_trajectory


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
