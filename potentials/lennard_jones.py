"""Lennard-Jones pair potential with per-type parameters and three cutoff modes."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from md.schema import Key
from potentials._pair_frame import CUTOFF_MODES, PairPotential, pair_config_keys
from potentials.pair_terms import PairTerm

__all__ = ["CUTOFF_MODES", "MIXING_RULES", "LennardJones"]

MIXING_RULES = ("lorentz-berthelot", "geometric")


def lj_energy(r2, c6, c12):
    """u = c12 / r^12 - c6 / r^6 and -u'(r) / r, with c6 = 4 eps sigma^6, c12 = 4 eps sigma^12."""
    inv_r2 = 1.0 / r2
    inv_r6 = inv_r2 * inv_r2 * inv_r2
    a = c12 * inv_r6 * inv_r6
    b = c6 * inv_r6
    return a - b, (12.0 * a - 6.0 * b) * inv_r2


def lj_curvature(r2, c6, c12):
    """u and its first two derivatives with respect to s = r^2."""
    inv_r2 = 1.0 / r2
    inv_r6 = inv_r2 * inv_r2 * inv_r2
    a = c12 * inv_r6 * inv_r6
    b = c6 * inv_r6
    return a - b, (3.0 * b - 6.0 * a) * inv_r2, (42.0 * a - 12.0 * b) * inv_r2 * inv_r2


LJ_TERM = PairTerm(lj_energy, lj_curvature, name="lj")


class LennardJones(PairPotential):
    r"""Lennard-Jones potential :math:`u(r) = 4\epsilon[(\sigma/r)^{12} - (\sigma/r)^6]`.

    Parameters
    ----------
    epsilon, sigma : float or sequence of float
        Well depth [energy] and size [length]; one value for every type, or
        one per type (index = type) mixed into pair values by ``mixing``.
    cutoff : float
        Pair cutoff [length] for every pair not overridden in ``pairs``.
    cutoff_mode : {"none", "shift", "smooth"}
        ``"none"``: truncated, energy and force jump at the cutoff.
        ``"shift"``: energy shifted by u(cutoff) so it is continuous there;
        the force still jumps (ASE's LennardJones default).
        ``"smooth"``: u(r) is multiplied by the switching polynomial
        S(s) = (rc^2 - s)^2 (rc^2 + 2 s - 3 ro^2) / (rc^2 - ro^2)^3 in
        s = r^2 between ``r_on`` and the cutoff (1 below, 0 above), so energy
        and force are continuous; the same function ASE's ``smooth=True``
        uses, so results compare directly.
    r_on : float, optional
        Onset of switching for ``"smooth"`` [length]; defaults to 0.66 times
        each pair's cutoff (ASE's default).
    pairs : mapping, optional
        Explicit pair parameters overriding mixing:
        ``{(ti, tj): {"epsilon": ..., "sigma": ..., "cutoff": ..., "r_on": ...}}``
        (any subset of the keys).
    mixing : {"lorentz-berthelot", "geometric"}
        Rule for unlike pairs: epsilon_ij = sqrt(epsilon_i epsilon_j) in both;
        sigma_ij = (sigma_i + sigma_j) / 2 (Lorentz-Berthelot) or
        sqrt(sigma_i sigma_j) (geometric).

    Notes
    -----
    The pair term (:func:`lj_energy`, :func:`lj_curvature`) runs on the pair
    frame (``potentials._pair_frame``), which supplies the lists, threads,
    cutoff modes, virials and Hessians.

    Examples
    --------
    >>> lj = LennardJones(epsilon=1.0, sigma=1.0, cutoff=2.5)
    >>> abs(lj.pair_energy(2.5 - 1e-9)) < 1e-8  # shifted: continuous at the cutoff
    True
    """

    style = "lj"
    PARAMETERS = ("epsilon", "sigma")
    MIXING = {
        "lorentz-berthelot": {"epsilon": "geometric", "sigma": "arithmetic"},
        "geometric": {"epsilon": "geometric", "sigma": "geometric"},
    }
    LIMITS = {"epsilon": "nonnegative", "sigma": "positive"}
    CONFIG_KEYS = pair_config_keys(
        Key(
            "epsilon",
            "number, list or table",
            1.0,
            unit="energy",
            doc="The well depth: one number, or per type (`{Ar = 0.0104, Kr = 0.014}`, "
            "covering every type), mixed by `mixing`.",
        ),
        Key(
            "sigma",
            "number, list or table",
            1.0,
            unit="length",
            doc="The size, given as `epsilon` is.",
        ),
        mixing=MIXING_RULES,
        mixing_doc="The rule for unlike pairs of per-type values: epsilon geometric; sigma "
        "arithmetic (`lorentz-berthelot`) or geometric.",
    )

    def __init__(
        self,
        epsilon: float | Sequence[float] = 1.0,
        sigma: float | Sequence[float] = 1.0,
        cutoff: float = 2.5,
        cutoff_mode: str = "shift",
        r_on: float | None = None,
        pairs: Mapping[tuple[int, int], Mapping[str, float]] | None = None,
        mixing: str = "lorentz-berthelot",
    ) -> None:
        super().__init__(
            LJ_TERM, cutoff, cutoff_mode, r_on, pairs, mixing, epsilon=epsilon, sigma=sigma
        )

    def coefficients(self, values, ti: int, tj: int) -> tuple[float, float]:
        """(c6, c12) = (4 eps sigma^6, 4 eps sigma^12)."""
        epsilon, sigma = np.float64(values["epsilon"]), np.float64(values["sigma"])
        s6 = sigma**6
        return 4.0 * epsilon * s6, 4.0 * epsilon * s6 * s6

    def cutoff_energy(self, coefficients, rc2: float) -> float:
        c6, c12 = coefficients
        inv_rc6 = 1.0 / rc2**3
        return c12 * inv_rc6 * inv_rc6 - c6 * inv_rc6
