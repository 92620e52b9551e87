"""Check a hand-written term's derivatives against finite differences of its own energy.

:func:`check_term` takes a pair term (:class:`~potentials.pair_terms.PairTerm`)
or a bonded one (:class:`~potentials.BondTerm`, :class:`~potentials.AngleTerm`),
evaluates it in Python over a range of distances or angles and compares the
derivatives it returns with central differences of the energy it returns. The
guide (docs/guide/pair-potentials.md) tells users to call it on their terms.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from potentials._bonded_frame import AngleTerm, BondedTerm
from potentials.pair_terms import PairTerm, is_number

__all__ = ["TermCheck", "check_term"]

#: Central differences: a relative step small enough that the truncation error (step^2)
#: is far below the tolerance, large enough that rounding (1e-16 / step) is too.
STEP = 1e-5
#: Per bonded form (kind, variable): the names energy and curvature return.
_BONDED_NAMES = {
    ("bond", "r"): ("du_dr", "d2u_dr2"),
    ("bond", "r2"): ("du_dr_over_r", "d2u_dr2"),
    ("angle", "theta"): ("du_dtheta", "d2u_dtheta2"),
    ("angle", "cos"): ("du_dc", "d2u_dc2"),
}


@dataclass(frozen=True)
class TermCheck:
    """What :func:`check_term` found: the largest error of each quantity it compared.

    Attributes
    ----------
    term : str
        The term's name.
    r_range : tuple of float
        The distances checked, (first, last).
    points : int
        How many distances.
    errors : dict of str to float
        Per quantity (``f_over_r``; with a curvature also ``curvature u``, ``du_ds``,
        ``d2u_ds2``), the largest difference from finite differences of the term's
        own energy (or, for ``curvature u``, from the energy's u) over the range,
        relative to the largest magnitude of that quantity there.
    """

    term: str
    r_range: tuple[float, float]
    points: int
    errors: dict[str, float]


def check_term(
    term, params, r_range, *, points: int = 201, tolerance: float = 1e-6, data=None
) -> TermCheck:
    """Check a term's hand-written derivatives against finite differences of its energy.

    Evaluates the term in Python at ``points`` distances spread evenly over
    ``r_range`` and compares, at each: ``f_over_r`` times r with -du/dr from a
    central difference of the energy's u in r; and, where the term has a
    curvature, its u with the energy's, its ``du_ds`` with a central difference
    of u in s = r^2 and its ``d2u_ds2`` with a central difference of its own
    ``du_ds``. Each error is taken relative to the largest magnitude of the
    derivative over the range (so a zero crossing is no trouble); a correct term
    agrees to about 1e-8, a wrong sign or factor to order one.

    A bond term (``BondTerm``) is checked over bond lengths r in ``r_range``
    and an angle term (``AngleTerm``) over angles theta in radians, whatever
    its variable: its derivative (``du_dr``, ``du_dr_over_r`` times r,
    ``du_dtheta``, ``du_dc`` times -sin theta) against a central difference of
    u in r or theta, and its curvature's u and second derivative (``d2u_dr2``,
    ``d2u_dtheta2``, ``d2u_dc2`` times -sin theta) against its energy's u and a
    central difference of its own first derivative in r, theta or c.

    Parameters
    ----------
    term : PairTerm, BondTerm or AngleTerm
        The term (made by ``pair_term``, ``bond_term``, ``angle_term`` or their
        classes).
    params : mapping or sequence
        The parameters: by name (``{"epsilon": 1.0, ...}``) or in the order of
        ``term.parameters``.
    r_range : (float, float)
        The first and last distance, ``0 < first < last``: where the term is
        used (from near the closest approach to the cutoff); for an angle term,
        the first and last angle in radians, ``0 <= first < last <= pi``.
    points : int
        How many distances (at least 3).
    tolerance : float
        The largest relative error accepted.
    data : ndarray, optional
        The data array of a term with ``uses_data``.

    Returns
    -------
    TermCheck
        The largest relative error of each quantity.

    Raises
    ------
    ValueError
        Naming the term and the quantity that disagrees, the distance where it is
        worst and both values there; or a bad ``params``, ``r_range`` or
        ``points``, or a value that is not finite in the range.

    Examples
    --------
    >>> from potentials import pair_term
    >>> @pair_term
    ... def harmonic(r2, k):
    ...     return 0.5 * k * r2, -k
    >>> check_term(harmonic, {"k": 2.0}, (0.5, 2.0)).errors["f_over_r"] < 1e-6
    True
    """
    if not isinstance(term, PairTerm | BondedTerm):
        raise TypeError(
            f"check_term expects a PairTerm, BondTerm or AngleTerm (see "
            f"potentials.pair_term, bond_term, angle_term), got {term!r}"
        )
    kind = "pair" if isinstance(term, PairTerm) else term.KIND
    values = _parameter_values(term, params, kind)
    try:
        first, last = (float(r) for r in r_range)
    except (TypeError, ValueError):
        raise ValueError(f"r_range must be two values (first, last), got {r_range!r}") from None
    if isinstance(term, AngleTerm):
        if not 0.0 <= first < last <= math.pi:
            raise ValueError(
                f"r_range of an angle term must be two angles in radians "
                f"0 <= first < last <= pi, got {r_range!r}"
            )
    elif not 0.0 < first < last < math.inf:
        raise ValueError(f"r_range must be two distances 0 < first < last, got {r_range!r}")
    if isinstance(points, bool) or not isinstance(points, int) or points < 3:
        raise ValueError(f"points must be an integer of at least 3, got {points!r}")
    if isinstance(term, BondedTerm):
        return _check_bonded(term, values, (first, last), points, tolerance)
    r = np.linspace(first, last, points)
    step = STEP
    name = f"pair term {term.name}"

    def energy(r2: float) -> tuple[float, float]:
        with np.errstate(all="ignore"):  # a value that is not finite is reported below
            return term.energy_at(r2, values, data)

    def finite(quantity: str, array: np.ndarray) -> np.ndarray:
        bad = np.flatnonzero(~np.isfinite(array))
        if bad.size:
            raise ValueError(
                f"{name}: {quantity} is {array[bad[0]]:g} at r = {r[bad[0]]:.6g} "
                f"(in r_range {r_range!r}): check it where it is finite"
            )
        return array

    u, f_over_r = (
        finite(q, a)
        for q, a in zip(("u", "f_over_r"), np.array([energy(x * x) for x in r]).T, strict=True)
    )
    h = step * r
    du_dr = np.array(
        [energy((x + d) ** 2)[0] - energy((x - d) ** 2)[0] for x, d in zip(r, h, strict=True)]
    ) / (2.0 * h)
    errors = {}
    errors["f_over_r"] = _compare(
        name,
        "f_over_r",
        "-du/dr / r from its energy's differences",
        r,
        f_over_r * r,
        -finite("du/dr", du_dr),
        scale=r,
        tolerance=tolerance,
    )
    if term.curvature is not None:

        def curvature(r2: float) -> tuple[float, float, float]:
            with np.errstate(all="ignore"):
                return term.curvature_at(r2, values, data)

        s = r * r
        returned = np.array([curvature(x) for x in s]).T
        u_c, du_ds, d2u_ds2 = (
            finite(q, a)
            for q, a in zip(("curvature's u", "du_ds", "d2u_ds2"), returned, strict=True)
        )
        hs = step * s
        above = np.array([curvature(x + d) for x, d in zip(s, hs, strict=True)]).T
        below = np.array([curvature(x - d) for x, d in zip(s, hs, strict=True)]).T
        du_ds_fd = np.array(
            [energy(x + d)[0] - energy(x - d)[0] for x, d in zip(s, hs, strict=True)]
        ) / (2.0 * hs)
        errors["curvature u"] = _compare(
            name, "curvature's u", "its energy's u", r, u_c, u, tolerance=tolerance
        )
        errors["du_ds"] = _compare(
            name,
            "du_ds",
            "the differences of its energy's u in s = r^2",
            r,
            du_ds,
            finite("du/ds", du_ds_fd),
            tolerance=tolerance,
        )
        d2 = finite("d2u/ds2", (above[1] - below[1]) / (2.0 * hs))
        errors["d2u_ds2"] = _compare(
            name,
            "d2u_ds2",
            "the differences of its du_ds in s = r^2",
            r,
            d2u_ds2,
            d2,
            tolerance=tolerance,
        )
    return TermCheck(term.name, (first, last), points, errors)


def _check_bonded(term: BondedTerm, values, r_range, points: int, tolerance: float):
    """check_term for a bond term (over r) or an angle term (over theta)."""
    first_name, second_name = _BONDED_NAMES[term.KIND, term.variable]
    name = f"{term.KIND} term {term.name}"
    y = np.linspace(*r_range, points)  # r or theta
    x = {"r": y, "r2": y * y, "theta": y, "cos": np.cos(y)}[term.variable]
    # d(variable)/dy where the term's derivative is in its variable, r for du_dr_over_r
    factor = {"r": 1.0, "r2": y, "theta": 1.0, "cos": -np.sin(y)}[term.variable]
    # a step in y, relative where y is a length; in radians for angles (theta may be 0)
    h = STEP * (y if term.KIND == "bond" else np.ones_like(y))
    below, above = y - h, y + h  # theta a step beyond 0 or pi: cos of it is inside [-1, 1]
    to_x = {"r": lambda v: v, "r2": lambda v: v * v, "theta": lambda v: v, "cos": np.cos}[
        term.variable
    ]

    def evaluate(method, points_x) -> np.ndarray:
        with np.errstate(all="ignore"):
            return np.array([method(float(v), values) for v in points_x]).T

    def finite(quantity: str, array: np.ndarray) -> np.ndarray:
        bad = np.flatnonzero(~np.isfinite(array))
        if bad.size:
            raise ValueError(
                f"{name}: {quantity} is {array[bad[0]]:g} at {_at(term, y[bad[0]])} "
                f"(in r_range {r_range!r}): check it where it is finite"
            )
        return array

    u, d1 = (
        finite(q, a) for q, a in zip(("u", first_name), evaluate(term.energy_at, x), strict=True)
    )
    spacing = above - below
    du_fd = finite(
        "the difference of u",
        (evaluate(term.energy_at, to_x(above))[0] - evaluate(term.energy_at, to_x(below))[0])
        / spacing,
    )
    along = "theta" if term.KIND == "angle" else "r"
    shown_as = {"r2": f"{first_name} * r", "cos": f"{first_name} * -sin(theta)"}
    errors = {
        first_name: _compare(
            name,
            shown_as.get(term.variable, first_name),
            f"the differences of its u in {along}",
            y,
            d1 * factor,
            du_fd,
            tolerance=tolerance,
            where=lambda v: _at(term, v),
        )
    }
    if term.curvature is not None:
        u_c, d1_c, d2 = (
            finite(q, a)
            for q, a in zip(
                ("curvature's u", first_name, second_name),
                evaluate(term.curvature_at, x),
                strict=True,
            )
        )
        errors["curvature u"] = _compare(
            name,
            "curvature's u",
            "its energy's u",
            y,
            u_c,
            u,
            tolerance=tolerance,
            where=lambda v: _at(term, v),
        )
        # the first derivative in the form the second one differentiates: du/dr for r2
        first = (lambda v, d: d * v) if term.variable == "r2" else (lambda v, d: d)
        up = first(above, evaluate(term.curvature_at, to_x(above))[1])
        down = first(below, evaluate(term.curvature_at, to_x(below))[1])
        given = d2 * (factor if term.variable == "cos" else 1.0)
        errors[second_name] = _compare(
            name,
            f"{second_name} * -sin(theta)" if term.variable == "cos" else second_name,
            f"the differences of its {'du_dr_over_r * r' if term.variable == 'r2' else first_name}"
            f" in {along}",
            y,
            given,
            finite("the difference", (up - down) / spacing),
            tolerance=tolerance,
            where=lambda v: _at(term, v),
        )
    return TermCheck(term.name, r_range, points, errors)


def _at(term, y: float) -> str:
    return f"theta = {y:.6g}" if isinstance(term, AngleTerm) else f"r = {y:.6g}"


def _parameter_values(term, params, kind: str) -> tuple[float, ...]:
    """``params`` (by name or in order) as the term's parameter values, checked."""
    names = term.parameters
    if isinstance(params, Mapping):
        missing = [n for n in names if n not in params]
        extra = [n for n in params if n not in names]
        if missing or extra:
            raise ValueError(
                f"{kind} term {term.name} takes parameters {list(names)}; params "
                f"lack {missing}, have unknown {extra}"
            )
        values = [params[n] for n in names]
    elif isinstance(params, str) or not isinstance(params, Sequence | np.ndarray):
        raise ValueError(
            f"params must be a mapping by name or a sequence of "
            f"{len(names)} numbers, got {params!r}"
        )
    else:
        values = list(params)
        if len(values) != len(names):
            raise ValueError(
                f"{kind} term {term.name} takes {len(names)} parameters "
                f"{list(names)}, got {len(values)}: {values!r}"
            )
    for n, v in zip(names, values, strict=True):
        if not is_number(v) or not math.isfinite(float(v)):
            raise ValueError(
                f"{kind} term {term.name}: parameter {n} must be a finite number, got {v!r}"
            )
    return tuple(float(v) for v in values)


def _compare(
    name: str,
    quantity: str,
    against: str,
    r: np.ndarray,
    given: np.ndarray,
    expected: np.ndarray,
    *,
    tolerance: float,
    scale=None,
    where=None,
) -> float:
    """The largest |given - expected| relative to the largest |expected| (or |given|);
    ValueError naming where it is worst if beyond ``tolerance``. ``scale`` divides both
    values shown (f_over_r is compared times r, shown as itself); ``where`` says where a
    value of ``r`` is (default ``r = ...``)."""
    size = max(float(np.max(np.abs(expected))), float(np.max(np.abs(given))))
    difference = np.abs(given - expected)
    error = np.where(difference == 0.0, 0.0, difference / (size or 1.0))
    worst = int(np.argmax(error))
    if error[worst] > tolerance:
        shown_given, shown_expected = given[worst], expected[worst]
        if scale is not None:
            shown_given, shown_expected = shown_given / scale[worst], shown_expected / scale[worst]
        raise ValueError(
            f"{name}: {quantity} disagrees with {against}: worst at "
            f"{where(r[worst]) if where else f'r = {r[worst]:.6g}'}, "
            f"where {quantity} is {shown_given:.8g} and {against} {shown_expected:.8g} "
            f"(error {error[worst]:.3g} of the largest magnitude, tolerance {tolerance:.3g})"
        )
    return float(error[worst])
