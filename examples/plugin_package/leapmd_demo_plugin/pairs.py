"""A Gaussian-core pair style on leapmd's pair frame, as the built-in styles are written."""

import math

from potentials import PairPotential, pair_term


def gauss_energy(r2, a, inv_w2):
    """u = a exp(-r^2 / w^2) and -u'(r) / r = 2 u / w^2."""
    u = a * math.exp(-r2 * inv_w2)
    return u, 2.0 * inv_w2 * u


GAUSS = pair_term(gauss_energy, name="demo_gauss")


class Gauss(PairPotential):
    """Gaussian core u(r) = a exp(-(r / width)^2), width > 0.

    It declares no CONFIG_KEYS: its keys are its PARAMETERS, with the constructor's
    defaults, and the frame's cutoff, cutoff_mode, r_on and pairs.
    """

    PARAMETERS = ("a", "width")
    LIMITS = {"width": "positive"}

    def __init__(self, a=1.0, width=1.0, cutoff=3.0, cutoff_mode="shift", r_on=None, pairs=None):
        super().__init__(GAUSS, cutoff, cutoff_mode, r_on, pairs, a=a, width=width)

    def coefficients(self, values, ti, tj):
        """The term's (a, 1 / width^2) from the user's (a, width)."""
        return float(values["a"]), 1.0 / float(values["width"]) ** 2
