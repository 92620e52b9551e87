"""Tabulated pair potentials read from LAMMPS ``pair_style table`` files.

A file holds sections, each a keyword line, a parameter line
``N n [R rlo rhi | RSQ rlo rhi] [FPRIME fplo fphi]`` and n lines
``index r energy force`` (blank lines and ``#`` comments anywhere). With
``R`` or ``RSQ`` the distances are recomputed evenly spaced in r or r^2 from
rlo to rhi, as LAMMPS does; without them the file's r must increase.

The table is then built as LAMMPS builds it: the file's energy and force are
splined in r (natural end slopes from the forces, or FPRIME), and sampled at
``points`` values evenly spaced in r^2 from the first distance to the cutoff,
the force stored as f/r; ``"linear"`` interpolates these linearly in r^2,
``"spline"`` through cubic splines in r^2 (LAMMPS's ``linear`` and
``spline`` styles, BITMAP and lookup excluded). When the file already has
``points`` values evenly spaced in r^2 ending at the cutoff (RSQ), linear
interpolation uses them unsplined, as LAMMPS does. A pair closer than the
table's first distance is an error (:class:`md.errors.PairCollapseError`
names it), as in LAMMPS.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numba.extending import register_jitable

from md.schema import REQUIRED, Key, check_names
from potentials._pair_codegen import TERM
from potentials._pair_frame import PairPotential, collapse_error, config_pairs, pair_config_keys
from potentials.pair_terms import PairTerm

__all__ = ["Table", "TableSection", "read_table"]

INTERPOLATIONS = ("linear", "spline")
#: The most ``points`` a table is built with: 40 MB, built point by point in Python in
#: several seconds; LAMMPS's tables use thousands (spacings of 1e-6 in r^2 at 10^6).
MAX_POINTS = 10**6
#: Arrays of one built table in the data array, each ``n`` long, in this order.
RSQ, ENERGY, FORCE, ENERGY2, FORCE2 = range(5)
#: The term's parameter that is the table's first r^2 (its parameters: offset, n, innersq,
#: invdelta, deltasq6).
INNERSQ = 2


@dataclass
class TableSection:
    """One section of a table file, as read: distances [length], energies, forces."""

    path: Path
    keyword: str
    r: np.ndarray
    energy: np.ndarray
    force: np.ndarray
    spacing: str | None  # "R", "RSQ" or None (the file's own r)
    r_low: float
    r_high: float
    slopes: tuple[float, float] | None  # FPRIME fplo fphi


def read_table(path, keyword: str) -> TableSection:
    """Read section ``keyword`` of a LAMMPS pair table file; errors name the file and line."""
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except FileNotFoundError:
        raise ValueError(f"table file {path} not found") from None
    except (OSError, UnicodeDecodeError) as error:
        raise ValueError(f"table file {path}: cannot read it ({error})") from None
    # The words of each line, '#' and what follows it dropped (LAMMPS's reader does the same).
    content = [(number, line.split("#", 1)[0].split()) for number, line in enumerate(lines, 1)]
    content = [(number, words) for number, words in content if words]
    position = 0
    while position < len(content) and content[position][1][0] != keyword:
        if position + 1 == len(content):  # a last line that starts no section of ours
            position += 1
        else:  # another section: skip its parameter line and its points
            position += 2 + _parameters(path, *content[position + 1])[0]
    if position >= len(content):
        raise ValueError(f"table file {path}: no section named {keyword!r}")
    if position + 1 >= len(content):
        raise ValueError(f"{path}:{content[position][0]}: section {keyword} has no parameter line")
    count, spacing, low, high, slopes = _parameters(path, *content[position + 1])
    rows = content[position + 2 : position + 2 + count]
    if len(rows) < count:
        last = rows[-1][0] if rows else content[position + 1][0]
        raise ValueError(
            f"{path}:{last}: section {keyword} ends after {len(rows)} of its N = {count} points"
        )
    values = np.empty((count, 3))
    for row, (number, words) in enumerate(rows):
        if len(words) != 4:
            raise ValueError(
                f"{path}:{number}: expected 'index r energy force', got {' '.join(words)!r}"
            )
        try:
            values[row] = [float(w) for w in words[1:]]
            int(words[0])
        except ValueError:
            raise ValueError(f"{path}:{number}: not numbers: {' '.join(words)!r}") from None
        if not np.all(np.isfinite(values[row])):
            raise ValueError(f"{path}:{number}: values must be finite, got {' '.join(words)!r}")
    r = values[:, 0].copy()
    i = np.arange(count)
    if spacing == "R":
        r = low + (high - low) * i / (count - 1)
    elif spacing == "RSQ":
        r = np.sqrt(low * low + (high * high - low * low) * i / (count - 1))
    else:
        low, high = float(r[0]), float(r[-1])
        bad = np.flatnonzero(np.diff(r) <= 0)
        if len(bad):
            number = rows[bad[0] + 1][0]
            raise ValueError(
                f"{path}:{number}: distances must increase, but r = {r[bad[0] + 1]:g} follows "
                f"{r[bad[0]]:g}"
            )
    if not low > 0:
        raise ValueError(f"{path}:{content[position + 1][0]}: the first distance must be > 0")
    return TableSection(
        path,
        keyword,
        r,
        values[:, 1].copy(),
        values[:, 2].copy(),
        spacing,
        float(low),
        float(high),
        slopes,
    )


def _parameters(path, number, words):
    """(N, spacing, rlo, rhi, slopes) of a parameter line."""
    count, spacing, low, high, slopes = None, None, 0.0, 0.0, None
    k = 0
    try:
        while k < len(words):
            word = words[k]
            if word == "N":
                count = int(words[k + 1])
                k += 2
            elif word in ("R", "RSQ"):
                spacing, low, high = word, float(words[k + 1]), float(words[k + 2])
                k += 3
            elif word == "FPRIME":
                slopes = (float(words[k + 1]), float(words[k + 2]))
                k += 3
            else:
                raise ValueError(
                    f"{path}:{number}: unknown table parameter {word!r} (expected N, R, RSQ, "
                    "FPRIME; BITMAP tables are not supported)"
                )
    except (IndexError, ValueError) as error:
        if "unknown table parameter" in str(error):
            raise
        raise ValueError(f"{path}:{number}: malformed parameter line {' '.join(words)!r}") from None
    if count is None:
        raise ValueError(f"{path}:{number}: the parameter line does not set N")
    if count < 2:
        raise ValueError(f"{path}:{number}: N must be at least 2, got {count}")
    if spacing is not None and not high > low:
        raise ValueError(f"{path}:{number}: {spacing} needs rlo < rhi, got {low:g} {high:g}")
    return count, spacing, low, high, slopes


# -------------------------------------------------------------- building a table
def _spline(x, y, slope_low, slope_high):
    """Second derivatives of the cubic spline through (x, y) with the given end slopes."""
    n = len(x)
    second = np.zeros(n)
    u = np.zeros(n)
    second[0] = -0.5
    u[0] = (3.0 / (x[1] - x[0])) * ((y[1] - y[0]) / (x[1] - x[0]) - slope_low)
    for i in range(1, n - 1):
        sig = (x[i] - x[i - 1]) / (x[i + 1] - x[i - 1])
        p = sig * second[i - 1] + 2.0
        second[i] = (sig - 1.0) / p
        u[i] = (y[i + 1] - y[i]) / (x[i + 1] - x[i]) - (y[i] - y[i - 1]) / (x[i] - x[i - 1])
        u[i] = (6.0 * u[i] / (x[i + 1] - x[i - 1]) - sig * u[i - 1]) / p
    qn = 0.5
    un = (3.0 / (x[n - 1] - x[n - 2])) * (
        slope_high - (y[n - 1] - y[n - 2]) / (x[n - 1] - x[n - 2])
    )
    second[n - 1] = (un - qn * u[n - 2]) / (qn * second[n - 2] + 1.0)
    for k in range(n - 2, -1, -1):
        second[k] = second[k] * second[k + 1] + u[k]
    return second


def _splint(x, y, second, at):
    """The spline (x, y, second) evaluated at ``at`` (a number)."""
    high = int(np.searchsorted(x, at, side="right"))
    high = min(max(high, 1), len(x) - 1)
    low = high - 1
    h = x[high] - x[low]
    a = (x[high] - at) / h
    b = (at - x[low]) / h
    return (
        a * y[low]
        + b * y[high]
        + ((a * a * a - a) * second[low] + (b * b * b - b) * second[high]) * (h * h) / 6.0
    )


def build_table(section: TableSection, points: int, cutoff: float, interpolation: str):
    """The (5, points) arrays (rsq, e, f/r, and de, df or e2, f2) and (innersq, delta)."""
    n = points
    inner = section.r_low if section.spacing else float(section.r[0])
    innersq = inner * inner
    delta = (cutoff * cutoff - innersq) / (n - 1)
    match = (
        interpolation == "linear"
        and len(section.r) == n
        and section.spacing == "RSQ"
        and section.r_high == cutoff
    )
    if not match:
        r_file, e_file, f_file = section.r, section.energy, section.force
        e2_file = _spline(r_file, e_file, -f_file[0], -f_file[-1])
        if section.slopes is None:
            slopes = (
                (f_file[1] - f_file[0]) / (r_file[1] - r_file[0]),
                (f_file[-1] - f_file[-2]) / (r_file[-1] - r_file[-2]),
            )
        else:
            slopes = section.slopes
        f2_file = _spline(r_file, f_file, *slopes)
    out = np.zeros((5, n))
    rsq, e, f = out[RSQ], out[ENERGY], out[FORCE]
    for i in range(n):
        rsq[i] = innersq + i * delta
        r = math.sqrt(rsq[i])
        if match:
            e[i] = section.energy[i]
            f[i] = section.force[i] / r
        else:
            e[i] = _splint(r_file, e_file, e2_file, r)
            f[i] = _splint(r_file, f_file, f2_file, r)
            if interpolation == "linear":
                f[i] /= r
    if interpolation == "linear":
        out[ENERGY2, :-1] = e[1:] - e[:-1]
        out[FORCE2, :-1] = f[1:] - f[:-1]
        return out, innersq, delta
    # End slopes of e in r^2: de/d(r^2) = -f / (2 r), f the force (not yet f/r here).
    out[ENERGY2] = _spline(rsq, e, -f[0] / (2.0 * inner), -f[-1] / (2.0 * cutoff))
    # End slopes of f/r in r^2: from FPRIME where given, else secants over a tenth of a bin.
    secant = 0.1
    if section.slopes is not None:
        low = (section.slopes[0] / math.sqrt(innersq) - f[0] / innersq) / (2.0 * math.sqrt(innersq))
    else:
        rsq2 = innersq + secant * delta
        low = (
            _splint(r_file, f_file, f2_file, math.sqrt(rsq2)) / math.sqrt(rsq2)
            - f[0] / math.sqrt(innersq)
        ) / (secant * delta)
    if section.slopes is not None and cutoff == section.r[-1]:
        high = (section.slopes[1] / cutoff - f[-1] / (cutoff * cutoff)) / (2.0 * cutoff)
    else:
        rsq2 = cutoff * cutoff
        rsq1 = rsq2 - secant * delta
        high = (
            f[-1] / math.sqrt(rsq2)
            - _splint(r_file, f_file, f2_file, math.sqrt(rsq1)) / math.sqrt(rsq1)
        ) / (secant * delta)
    f /= np.sqrt(rsq)
    out[FORCE2] = _spline(rsq, f, low, high)
    return out, innersq, delta


# ------------------------------------------------------------------ pair terms
# Functions a term calls must be compiled too: register_jitable makes them callable from
# numba (and leaves them plain Python functions).
@register_jitable
def table_linear_energy(r2, data, offset, n, innersq, invdelta, deltasq6):
    """Linear interpolation in r^2 of the table at ``data[offset:offset + 5 n]``;
    NaN below the first distance (an error the potential then names)."""
    x = (r2 - innersq) * invdelta
    k = int(min(max(x, 0.0), n - 2.0))
    base = int(offset) + k
    size = int(n)
    fraction = (r2 - data[base]) * invdelta
    e = data[base + size] + fraction * data[base + 3 * size]
    fr = data[base + 2 * size] + fraction * data[base + 4 * size]
    return (e if r2 >= innersq else math.nan), fr


def table_linear_curvature(r2, data, offset, n, innersq, invdelta, deltasq6):
    """u, and -(f/r)/2 and its slope in s = r^2 (the Jacobian of the interpolated forces)."""
    e, fr = table_linear_energy(r2, data, offset, n, innersq, invdelta, deltasq6)
    x = (r2 - innersq) * invdelta
    base = int(offset) + int(min(max(x, 0.0), n - 2.0))
    return e, -0.5 * fr, -0.5 * data[base + 4 * int(n)] * invdelta


@register_jitable
def _cubic(data, base, size, b, deltasq6, row):
    a = 1.0 - b
    lo = data[base + row * size]
    hi = data[base + row * size + 1]
    lo2 = data[base + (row + 2) * size]
    hi2 = data[base + (row + 2) * size + 1]
    return a * lo + b * hi + ((a * a * a - a) * lo2 + (b * b * b - b) * hi2) * deltasq6


@register_jitable
def table_spline_energy(r2, data, offset, n, innersq, invdelta, deltasq6):
    """Cubic-spline interpolation in r^2 (LAMMPS's ``spline``); NaN below the first distance."""
    x = (r2 - innersq) * invdelta
    k = int(min(max(x, 0.0), n - 2.0))
    base = int(offset) + k
    size = int(n)
    b = (r2 - data[base]) * invdelta
    e = _cubic(data, base, size, b, deltasq6, ENERGY)
    fr = _cubic(data, base, size, b, deltasq6, FORCE)
    return (e if r2 >= innersq else math.nan), fr


def table_spline_curvature(r2, data, offset, n, innersq, invdelta, deltasq6):
    e, fr = table_spline_energy(r2, data, offset, n, innersq, invdelta, deltasq6)
    x = (r2 - innersq) * invdelta
    base = int(offset) + int(min(max(x, 0.0), n - 2.0))
    size = int(n)
    b = (r2 - data[base]) * invdelta
    a = 1.0 - b
    lo, hi = data[base + 2 * size], data[base + 2 * size + 1]
    lo2, hi2 = data[base + 4 * size], data[base + 4 * size + 1]
    slope = (
        hi - lo + ((1.0 - 3.0 * a * a) * lo2 + (3.0 * b * b - 1.0) * hi2) * deltasq6
    ) * invdelta
    return e, -0.5 * fr, -0.5 * slope


TERMS = {
    "linear": PairTerm(
        table_linear_energy, table_linear_curvature, name="table_linear", uses_data=True
    ),
    "spline": PairTerm(
        table_spline_energy, table_spline_curvature, name="table_spline", uses_data=True
    ),
}


class Table(PairPotential):
    """A tabulated pair potential from a LAMMPS ``pair_style table`` file.

    Parameters
    ----------
    file : str or Path
        The table file.
    keyword : str
        The section to read.
    interpolation : {"linear", "spline"}
        As LAMMPS's ``pair_style table linear`` / ``spline``.
    points : int, optional
        The table length (LAMMPS's N of ``pair_style table``); default: the
        section's N.
    cutoff : float, optional
        Default: the section's last distance (rhi with R/RSQ), as in LAMMPS;
        it must lie above the first distance and not beyond the last.
    cutoff_mode : {"none", "shift", "smooth"}
        Default ``"none"`` (LAMMPS's table is not shifted).
    r_on : float, optional
        Onset of switching for ``"smooth"``, as in :class:`PairPotential`.
    pairs : mapping, optional
        ``{(ti, tj): {"file": ..., "keyword": ..., "cutoff": ..., "r_on": ...}}``:
        another table (or cutoff) for chosen type pairs.
    """

    style = "table"
    PARAMETERS = ()
    PAIR_KEYS = {"file", "keyword", "cutoff", "r_on"}
    CONFIG_KEYS = pair_config_keys(
        Key(
            "file",
            "path",
            REQUIRED,
            doc="A LAMMPS `pair_style table` file, relative to the config.",
        ),
        Key("keyword", "string", REQUIRED, doc="The section of the file to read."),
        Key(
            "interpolation",
            "string",
            "linear",
            choices=INTERPOLATIONS,
            doc="`linear` or `spline`, as LAMMPS's `pair_style table` interpolates.",
        ),
        Key(
            "points",
            "integer",
            None,
            minimum=2,
            maximum=MAX_POINTS,
            doc="The table length LAMMPS's `pair_style table` calls N: the section is "
            f"interpolated onto that many points first (at most {MAX_POINTS}).",
            default_doc="the section's own N",
        ),
        cutoff=None,
        cutoff_mode="none",
        pair_keys=("file", "keyword"),
        cutoff_doc="the section's last distance",
    )

    def __init__(
        self,
        file,
        keyword: str,
        interpolation: str = "linear",
        points: int | None = None,
        cutoff: float | None = None,
        cutoff_mode: str = "none",
        r_on: float | None = None,
        pairs: Mapping | None = None,
    ) -> None:
        if interpolation not in INTERPOLATIONS:
            raise ValueError(
                f"interpolation must be one of {', '.join(INTERPOLATIONS)}, got {interpolation!r}"
            )
        if points is not None and (
            isinstance(points, bool) or not isinstance(points, int) or not 2 <= points <= MAX_POINTS
        ):
            raise ValueError(
                f"points must be an integer from 2 to {MAX_POINTS} (each point takes 40 bytes "
                f"and is built in Python), got {points!r}"
            )
        self.file, self.keyword = file, keyword
        self.interpolation, self.points = interpolation, points
        self.table_pairs = {}  # (ti, tj) -> the pair's own file, keyword, cutoff, r_on
        for key, entry in (pairs or {}).items():
            bad = set(entry) - self.PAIR_KEYS
            if bad:
                raise ValueError(f"unknown pair parameter(s) {sorted(bad)} for pair {key}")
            ti, tj = (int(t) for t in key)
            self.table_pairs[(min(ti, tj), max(ti, tj))] = dict(entry)
        # The term's parameters of each pair's table (None: the default), read before the
        # frame builds its parameter tables from them (``coefficients``).
        self._parameters: dict = {}
        built: dict = {}
        chunks: list[np.ndarray] = []
        default = self._build(None, file, keyword, cutoff, built, chunks)
        numeric = {}
        for key, entry in self.table_pairs.items():
            own = self._build(
                key,
                entry.get("file", file),
                entry.get("keyword", keyword),
                entry.get("cutoff", cutoff),
                built,
                chunks,
            )
            numeric[key] = {"cutoff": own, **{k: entry[k] for k in ("r_on",) if k in entry}}
        super().__init__(
            TERMS[interpolation], default, cutoff_mode, r_on, numeric, data=np.concatenate(chunks)
        )

    def _build(self, key, file, keyword, cutoff, built: dict, chunks: list) -> float:
        """Read and build the table of pair ``key`` (None: the default) into ``chunks``
        (once per file, keyword and cutoff: ``built``); return its cutoff."""
        section = read_table(file, keyword)
        if cutoff is None:
            cutoff = section.r_high
        if isinstance(cutoff, bool) or not isinstance(cutoff, int | float):
            raise ValueError(f"cutoff must be a number, got {cutoff!r}")
        where = f"table {section.path} section {keyword}"
        if not section.r_low < cutoff <= section.r_high:
            raise ValueError(
                f"{where} covers r = {section.r_low:g} to {section.r_high:g}; the cutoff "
                f"{cutoff:g} must lie above its first distance and not beyond its last"
            )
        ident = (str(section.path), keyword, float(cutoff))
        if ident not in built:
            points = self.points or len(section.r)
            try:
                arrays, innersq, delta = build_table(
                    section, points, float(cutoff), self.interpolation
                )
            except MemoryError:
                raise ValueError(
                    f"{where}: points = {points} is too many to hold in memory "
                    f"({5 * 8 * points / 1e9:.3g} GB)"
                ) from None
            if not np.all(np.isfinite(arrays)):
                raise ValueError(f"{where}: the built table is not finite")
            offset = sum(len(c) for c in chunks)
            chunks.append(arrays.ravel())
            built[ident] = (float(offset), float(points), innersq, 1.0 / delta, delta * delta / 6.0)
        self._parameters[key] = built[ident]
        return float(cutoff)

    def coefficients(self, values, ti: int, tj: int) -> tuple[float, ...]:
        """The pair's table: (offset in ``data``, points, first r^2, 1 / spacing in r^2,
        spacing^2 / 6)."""
        key = (min(ti, tj), max(ti, tj))
        return self._parameters[key if key in self._parameters else None]

    def _explain_non_finite(self, state, neighbors) -> None:
        table = self._cached_tables(max(state.n_types, self.n_types_fixed or 1))
        error = collapse_error(
            self, state, neighbors, table[TERM + INNERSQ], "below the table's first distance"
        )
        if error is not None:
            raise error

    def describe(self) -> dict:
        out = super().describe()
        out.update(file=str(self.file), keyword=self.keyword, interpolation=self.interpolation)
        if self.points is not None:
            out["points"] = self.points
        if self.table_pairs:
            out["pairs"] = {f"{i}-{j}": v for (i, j), v in self.table_pairs.items()}
        return out

    @classmethod
    def from_config(cls, params: Mapping, type_names):
        """Keys: ``file``, ``keyword``, ``interpolation``, ``points``, ``cutoff``,
        ``cutoff_mode``, ``r_on`` and ``pairs`` (``{types = [a, b], file, keyword,
        cutoff, r_on}``)."""
        params = dict(params)
        check_names(params, cls.CONFIG_KEYS)
        for key in ("file", "keyword"):
            if not isinstance(params.get(key), str):
                raise ValueError(f"{key}: expected a string, got {params.get(key)!r}")
        pairs = config_pairs(
            params.pop("pairs", None), type_names, cls.PAIR_KEYS, numbers={"cutoff", "r_on"}
        )
        return cls(**params, pairs=pairs)
