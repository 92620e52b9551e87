"""Pair styles on the pair-kernel frame: Morse, Mie, Buckingham, Yukawa and soft.

Each is a pair term (a plain function of r^2 and its parameters returning u
and -u'(r)/r, and one returning u and its derivatives in s = r^2) plus a
small class naming its parameters, their checks and mixing; the frame
(``potentials._pair_frame``) supplies everything else. The energies are
LAMMPS's (``pair_style morse``, ``mie/cut``, ``buck``, ``yukawa``, ``soft``).
The exponentials (and Mie's powers, as exp of a log) are :mod:`potentials.pair_math`'s,
which vectorise.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
from numba.extending import register_jitable

from md.schema import Key
from potentials._pair_frame import PairPotential, collapse_error, pair_config_keys
from potentials.pair_math import cos, exp, log, reciprocal, sin
from potentials.pair_terms import PairTerm

__all__ = ["Buckingham", "Mie", "Morse", "Soft", "Yukawa"]

Pairs = Mapping[tuple[int, int], Mapping[str, float]] | None


@register_jitable
def _in_s(r, du, d2u):
    """(du/ds, d2u/ds2) from u'(r) and u''(r), s = r^2."""
    return 0.5 * du / r, 0.25 * (d2u - du / r) / (r * r)


# ----------------------------------------------------------------------- Morse
def morse_energy(r2, d0, alpha, r0):
    """u = D0 [exp(-2 a (r - r0)) - 2 exp(-a (r - r0))] and -u'(r) / r."""
    r = math.sqrt(r2)
    inv_r = reciprocal(r)  # beside the exp, not after it (see pair_math.reciprocal)
    e = exp(-alpha * (r - r0))
    return d0 * (e * e - 2.0 * e), 2.0 * alpha * d0 * (e * e - e) * inv_r


def morse_curvature(r2, d0, alpha, r0):
    r = math.sqrt(r2)
    e = exp(-alpha * (r - r0))
    du = 2.0 * alpha * d0 * (e - e * e)
    d2u = 2.0 * alpha * alpha * d0 * (2.0 * e * e - e)
    g1, g2 = _in_s(r, du, d2u)
    return d0 * (e * e - 2.0 * e), g1, g2


class Morse(PairPotential):
    r"""Morse potential :math:`u(r) = D_0 [e^{-2\alpha(r - r_0)} - 2 e^{-\alpha(r - r_0)}]`.

    LAMMPS's ``pair_style morse``: well depth ``d0`` [energy] at ``r0``
    [length], width ``alpha`` [1/length]. No mixing: each value holds for
    every type pair unless ``pairs`` gives the pair its own. Cutoff modes and
    ``pairs`` as in :class:`potentials.LennardJones`.

    Examples
    --------
    >>> morse = Morse(d0=1.0, alpha=2.0, r0=1.2, cutoff=3.0, cutoff_mode="none")
    >>> round(morse.pair_energy(1.2), 12)
    -1.0
    """

    style = "morse"
    PARAMETERS = ("d0", "alpha", "r0")
    LIMITS = {"d0": "nonnegative", "alpha": "positive", "r0": "nonnegative"}
    CONFIG_KEYS = pair_config_keys(
        Key("d0", "number", 1.0, unit="energy", doc="The well depth D0, >= 0."),
        Key("alpha", "number", 1.0, unit="1/length", doc="The well's width alpha, > 0."),
        Key("r0", "number", 1.0, unit="length", doc="The distance of the minimum, >= 0."),
    )

    def __init__(
        self,
        d0: float = 1.0,
        alpha: float = 1.0,
        r0: float = 1.0,
        cutoff: float = 2.5,
        cutoff_mode: str = "shift",
        r_on: float | None = None,
        pairs: Pairs = None,
    ) -> None:
        super().__init__(MORSE, cutoff, cutoff_mode, r_on, pairs, d0=d0, alpha=alpha, r0=r0)


MORSE = PairTerm(morse_energy, morse_curvature, name="morse")


# ------------------------------------------------------------------------- Mie
def mie_energy(r2, cn, cm, n, m):
    """u = cn / r^n - cm / r^m and -u'(r) / r.

    The powers are exp(-n/2 log r^2) (:func:`potentials.pair_math.log` and ``exp``, which
    vectorise; ``**`` with a non-integer exponent would call the scalar pow).
    """
    inv_r2 = 1.0 / r2
    log_r2 = log(r2)
    a = cn * exp(-0.5 * n * log_r2)
    b = cm * exp(-0.5 * m * log_r2)
    return a - b, (n * a - m * b) * inv_r2


def mie_curvature(r2, cn, cm, n, m):
    inv_r2 = 1.0 / r2
    log_r2 = log(r2)
    a = cn * exp(-0.5 * n * log_r2)
    b = cm * exp(-0.5 * m * log_r2)
    g1 = 0.5 * (m * b - n * a) * inv_r2
    g2 = 0.25 * (n * (n + 2.0) * a - m * (m + 2.0) * b) * inv_r2 * inv_r2
    return a - b, g1, g2


class Mie(PairPotential):
    r"""Mie potential :math:`u(r) = C\epsilon[(\sigma/r)^n - (\sigma/r)^m]`,
    :math:`C = \frac{n}{n - m} (n/m)^{m/(n - m)}`.

    LAMMPS's ``pair_style mie/cut`` (``n`` its gamma_R, ``m`` its gamma_A;
    n = 12, m = 6 is Lennard-Jones). ``epsilon``, ``sigma``, ``n`` and ``m``
    may be given per type and are mixed: epsilon geometrically, sigma, n and m
    arithmetically (``"lorentz-berthelot"``) or geometrically
    (``"geometric"``), as LAMMPS mixes them. n > m > 0.
    """

    style = "mie"
    PARAMETERS = ("epsilon", "sigma", "n", "m")
    MIXING = {
        "lorentz-berthelot": {
            "epsilon": "geometric",
            "sigma": "arithmetic",
            "n": "arithmetic",
            "m": "arithmetic",
        },
        "geometric": {
            "epsilon": "geometric",
            "sigma": "geometric",
            "n": "geometric",
            "m": "geometric",
        },
    }
    LIMITS = {"epsilon": "nonnegative", "sigma": "positive", "n": "positive", "m": "positive"}
    CONFIG_KEYS = pair_config_keys(
        Key(
            "epsilon",
            "number, list or table",
            1.0,
            unit="energy",
            doc="The well depth, >= 0: one number, or per type (`{A = 1.0, B = 0.6}`, "
            "covering every type), mixed by `mixing`.",
        ),
        Key(
            "sigma",
            "number, list or table",
            1.0,
            unit="length",
            doc="The size, > 0, given as `epsilon` is.",
        ),
        Key(
            "n",
            "number, list or table",
            12.0,
            doc="The repulsive exponent (LAMMPS's gamma_R), larger than `m`; given as "
            "`epsilon` is.",
        ),
        Key(
            "m",
            "number, list or table",
            6.0,
            doc="The attractive exponent (LAMMPS's gamma_A), > 0; given as `epsilon` is.",
        ),
        mixing=tuple(MIXING),
        mixing_doc="The rule for unlike pairs of per-type values: epsilon geometric; sigma, n "
        "and m arithmetic (`lorentz-berthelot`) or geometric.",
    )

    def __init__(
        self,
        epsilon: float | Sequence[float] = 1.0,
        sigma: float | Sequence[float] = 1.0,
        n: float | Sequence[float] = 12.0,
        m: float | Sequence[float] = 6.0,
        cutoff: float = 2.5,
        cutoff_mode: str = "shift",
        r_on: float | None = None,
        pairs: Pairs = None,
        mixing: str = "lorentz-berthelot",
    ) -> None:
        super().__init__(
            MIE, cutoff, cutoff_mode, r_on, pairs, mixing, epsilon=epsilon, sigma=sigma, n=n, m=m
        )

    def check_pair(self, values, ti: int, tj: int) -> None:
        if not values["n"] > values["m"]:
            raise ValueError(
                f"n ({values['n']:g}) must be larger than m ({values['m']:g}) for pair "
                f"({ti}, {tj}): the repulsive exponent exceeds the attractive one"
            )

    def coefficients(self, values, ti: int, tj: int) -> tuple[float, ...]:
        """(C eps sigma^n, C eps sigma^m, n, m)."""
        eps, sigma, n, m = (np.float64(values[k]) for k in ("epsilon", "sigma", "n", "m"))
        c = n / (n - m) * (n / m) ** (m / (n - m))
        return c * eps * sigma**n, c * eps * sigma**m, n, m


MIE = PairTerm(mie_energy, mie_curvature, name="mie")


# ------------------------------------------------------------------ Buckingham
def buckingham_energy(r2, a, inv_rho, c, barrier2):
    """u = A exp(-r / rho) - C / r^6 and -u'(r) / r; u = -inf inside the barrier."""
    r = math.sqrt(r2)
    inv_r = reciprocal(r)  # beside the exp, not after it (see pair_math.reciprocal)
    inv_r2 = inv_r * inv_r
    inv_r6 = inv_r2 * inv_r2 * inv_r2
    e = a * exp(-r * inv_rho)
    # inside the barrier the dispersion's infinity, not a select of the sum: ~1 % less
    # time per pair (AVX2 code), the same bits outside it
    u = e - (c * inv_r6 if r2 >= barrier2 else math.inf)
    fr = e * inv_rho * inv_r - 6.0 * c * inv_r6 * inv_r2
    return u, fr


def buckingham_curvature(r2, a, inv_rho, c, barrier2):
    r = math.sqrt(r2)
    inv_r2 = 1.0 / r2
    inv_r6 = inv_r2 * inv_r2 * inv_r2
    e = a * exp(-r * inv_rho)
    du = -e * inv_rho + 6.0 * c * inv_r6 / r
    d2u = e * inv_rho * inv_rho - 42.0 * c * inv_r6 * inv_r2
    g1, g2 = _in_s(r, du, d2u)
    return e - c * inv_r6, g1, g2


class Buckingham(PairPotential):
    r"""Buckingham potential :math:`u(r) = A e^{-r/\rho} - C / r^6`.

    LAMMPS's ``pair_style buck``: ``a`` [energy], ``rho`` [length] > 0,
    ``c`` [energy length^6]. No mixing. With C > 0 the energy has a maximum
    at a small r (the barrier) and falls to minus infinity inside it; a pair
    that gets there raises :class:`md.errors.PairCollapseError` naming the
    atoms, their types, the distance and the step (the energy is infinite
    there, so no run continues past it). A, rho and C whose energy has no
    barrier at all (purely attractive) are refused.
    """

    style = "buckingham"
    PARAMETERS = ("a", "rho", "c")
    LIMITS = {"a": "nonnegative", "rho": "positive", "c": "nonnegative"}
    CONFIG_KEYS = pair_config_keys(
        Key("a", "number", 1.0, unit="energy", doc="The repulsion's prefactor A, >= 0."),
        Key("rho", "number", 1.0, unit="length", doc="The repulsion's range rho, > 0."),
        Key("c", "number", 0.0, unit="energy*length^6", doc="The dispersion coefficient C, >= 0."),
    )

    def __init__(
        self,
        a: float = 1.0,
        rho: float = 1.0,
        c: float = 0.0,
        cutoff: float = 2.5,
        cutoff_mode: str = "shift",
        r_on: float | None = None,
        pairs: Pairs = None,
    ) -> None:
        super().__init__(BUCKINGHAM, cutoff, cutoff_mode, r_on, pairs, a=a, rho=rho, c=c)

    def coefficients(self, values, ti: int, tj: int) -> tuple[float, ...]:
        """(A, 1/rho, C, r_b^2), r_b the barrier: where u'(r) = 0 below r = 7 rho."""
        a, rho, c = (np.float64(values[k]) for k in ("a", "rho", "c"))
        return a, 1.0 / rho, c, self.barrier(a, rho, c, ti, tj) ** 2

    @staticmethod
    def barrier(a: float, rho: float, c: float, ti: int = 0, tj: int = 0) -> float:
        """The inner root of u'(r) = 0 (the energy's maximum); 0 when C = 0.

        u'(r) = 0 where h(r) = r^7 exp(-r / rho) = 6 C rho / A; h rises to its
        maximum at r = 7 rho, so the root below it is found by bisection.
        """
        if c == 0.0:
            return 0.0
        target = 6.0 * c * rho / a if a > 0 else math.inf
        top = 7.0 * rho
        if not top**7 * exp(-7.0) > target:
            raise ValueError(
                f"a {a:g}, rho {rho:g}, c {c:g} of type pair ({ti}, {tj}) give an energy with "
                "no repulsive barrier: it falls to minus infinity at every distance below its "
                "well; increase a or reduce c"
            )
        low, high = 0.0, top
        for _ in range(200):
            middle = 0.5 * (low + high)
            if middle**7 * exp(-middle / rho) > target:
                high = middle
            else:
                low = middle
        return high

    def _explain_non_finite(self, state, neighbors) -> None:
        table = self._cached_tables(max(state.n_types, self.n_types_fixed or 1))
        error = collapse_error(
            self,
            state,
            neighbors,
            table[-1],
            "the Buckingham barrier, inside which the energy falls to minus infinity (the atoms "
            "would collapse onto each other); use a smaller time step, a gentler start, or a "
            "potential with a repulsive core",
        )
        if error is not None:
            raise error


BUCKINGHAM = PairTerm(buckingham_energy, buckingham_curvature, name="buckingham")


# ---------------------------------------------------------------------- Yukawa
def yukawa_energy(r2, a, kappa):
    """u = A exp(-kappa r) / r and -u'(r) / r."""
    r = math.sqrt(r2)
    inv_r = reciprocal(r)  # beside the exp, not after it (see pair_math.reciprocal)
    u = a * exp(-kappa * r) * inv_r
    return u, u * (kappa * r + 1.0) * inv_r * inv_r


def yukawa_curvature(r2, a, kappa):
    r = math.sqrt(r2)
    inv_r = 1.0 / r
    u = a * exp(-kappa * r) * inv_r
    du = -u * (kappa * r + 1.0) * inv_r
    d2u = u * (kappa * kappa * r2 + 2.0 * kappa * r + 2.0) * inv_r * inv_r
    g1, g2 = _in_s(r, du, d2u)
    return u, g1, g2


class Yukawa(PairPotential):
    r"""Screened Coulomb (Yukawa) potential :math:`u(r) = A e^{-\kappa r} / r`.

    LAMMPS's ``pair_style yukawa``: ``a`` [energy length] (may be given per
    type; unlike pairs mix geometrically, sqrt(A_i A_j), as LAMMPS does),
    screening ``kappa`` [1/length] >= 0.
    """

    style = "yukawa"
    PARAMETERS = ("a", "kappa")
    MIXING = {"geometric": {"a": "geometric"}}
    LIMITS = {"kappa": "nonnegative"}
    CONFIG_KEYS = pair_config_keys(
        Key(
            "a",
            "number, list or table",
            1.0,
            unit="energy*length",
            doc="The prefactor A: one number, or per type (`{A = 1.0, B = 2.0}`, covering "
            "every type), unlike pairs sqrt(A_i A_j).",
        ),
        Key("kappa", "number", 1.0, unit="1/length", doc="The screening constant kappa, >= 0."),
        mixing=tuple(MIXING),
        mixing_doc="The rule for unlike pairs of per-type `a`: geometric, as LAMMPS mixes it.",
    )

    def __init__(
        self,
        a: float | Sequence[float] = 1.0,
        kappa: float = 1.0,
        cutoff: float = 2.5,
        cutoff_mode: str = "shift",
        r_on: float | None = None,
        pairs: Pairs = None,
        mixing: str = "geometric",
    ) -> None:
        super().__init__(YUKAWA, cutoff, cutoff_mode, r_on, pairs, mixing, a=a, kappa=kappa)


YUKAWA = PairTerm(yukawa_energy, yukawa_curvature, name="yukawa")


# ------------------------------------------------------------------------ soft
def soft_energy(r2, a, k):
    """u = A [1 + cos(k r)], k = pi / rc, and -u'(r) / r (its limit A k^2 at r = 0)."""
    r = math.sqrt(r2)
    safe = r if r2 > 0.0 else 1.0
    x = k * r
    return a * (1.0 + cos(x)), (a * k * sin(x) / safe if r2 > 0.0 else a * k * k)


def soft_curvature(r2, a, k):
    r = math.sqrt(r2)
    x = k * r
    small = x < 1e-2  # series below: the exact forms cancel to nothing there
    safe = r if not small else 1.0
    g1 = -0.5 * a * k * sin(x) / safe
    g2 = 0.25 * (-a * k * k * cos(x) - 2.0 * g1) / (safe * safe)
    k2 = k * k
    g1 = g1 if not small else -0.5 * a * k2 * (1.0 - x * x / 6.0)
    g2 = g2 if not small else a * k2 * k2 * (1.0 / 12.0 - x * x / 240.0)
    return a * (1.0 + cos(x)), g1, g2


class Soft(PairPotential):
    r"""Soft repulsion :math:`u(r) = A [1 + \cos(\pi r / r_c)]`, a gentle push-off.

    LAMMPS's ``pair_style soft``: finite at r = 0 (2A), zero with zero force
    at the cutoff r_c (each pair's own), so overlapping atoms (a random
    start) are pushed apart without infinite forces. ``a`` [energy] may be
    given per type; unlike pairs mix geometrically, as LAMMPS does.
    The default cutoff mode is ``"none"`` (u(r_c) = 0 already).
    """

    style = "soft"
    PARAMETERS = ("a",)
    MIXING = {"geometric": {"a": "geometric"}}
    LIMITS = {"a": "nonnegative"}
    CONFIG_KEYS = pair_config_keys(
        Key(
            "a",
            "number, list or table",
            1.0,
            unit="energy",
            doc="The height A (u(0) = 2A), >= 0: one number, or per type (`{A = 1.0, B = 2.0}`, "
            "covering every type), unlike pairs sqrt(A_i A_j).",
        ),
        cutoff=1.0,
        cutoff_mode="none",
        mixing=tuple(MIXING),
        mixing_doc="The rule for unlike pairs of per-type `a`: geometric, as LAMMPS mixes it.",
    )

    def __init__(
        self,
        a: float | Sequence[float] = 1.0,
        cutoff: float = 1.0,
        cutoff_mode: str = "none",
        r_on: float | None = None,
        pairs: Pairs = None,
        mixing: str = "geometric",
    ) -> None:
        super().__init__(SOFT, cutoff, cutoff_mode, r_on, pairs, mixing, a=a)

    def coefficients(self, values, ti: int, tj: int) -> tuple[float, ...]:
        """(A, pi / rc)."""
        return np.float64(values["a"]), np.float64(math.pi) / np.float64(values["cutoff"])


SOFT = PairTerm(soft_energy, soft_curvature, name="soft")
