"""potentials.check_term: a pair or bonded term's hand-written derivatives against finite
differences of its own energy (the guide tells users to call it on their terms)."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from potentials import (
    Buckingham,
    LennardJones,
    Mie,
    Morse,
    PairTerm,
    Soft,
    TermCheck,
    Yukawa,
    angle_term,
    bond_term,
    check_term,
    pair_term,
)
from potentials._pair_codegen import TERM

# Each built-in style with its defaults (or a usual choice) and the distances it is used at:
# from near its closest approach to its cutoff.
STYLES = {
    "lj": (LennardJones(cutoff=2.5), (0.85, 2.5)),
    "morse": (Morse(d0=1.0, alpha=2.0, r0=1.1, cutoff=3.0), (0.7, 3.0)),
    "buckingham": (Buckingham(a=1000.0, rho=0.2, c=1.0, cutoff=3.0), (0.6, 3.0)),
    "yukawa": (Yukawa(a=1.0, kappa=1.5, cutoff=3.0), (0.5, 3.0)),
    "soft": (Soft(a=1.0, cutoff=1.2), (0.05, 1.2)),
    "mie": (Mie(epsilon=1.0, sigma=1.0, n=14.0, m=7.0, cutoff=2.5), (0.85, 2.5)),
}


@pytest.mark.parametrize("style", sorted(STYLES))
def test_every_built_in_term_agrees_with_finite_differences(style):
    potential, r_range = STYLES[style]
    params = potential.tables(1)[TERM:, 0]
    report = check_term(potential.term, params, r_range)
    assert isinstance(report, TermCheck) and report.term == potential.term.name
    assert set(report.errors) == {"f_over_r", "curvature u", "du_ds", "d2u_ds2"}
    assert max(report.errors.values()) < 1e-7, report


def _gaussian(r2, epsilon, sigma):
    u = epsilon * math.exp(-r2 / (sigma * sigma))
    return u, 2.0 * u / (sigma * sigma)


def _gaussian_curvature(r2, epsilon, sigma):
    u = epsilon * math.exp(-r2 / (sigma * sigma))
    return u, -u / (sigma * sigma), u / sigma**4


def test_a_correct_user_term_passes_by_name_and_in_order():
    term = PairTerm(_gaussian, _gaussian_curvature, name="gaussian")
    by_name = check_term(term, {"epsilon": 2.0, "sigma": 0.8}, (0.1, 3.0))
    in_order = check_term(term, [2.0, 0.8], (0.1, 3.0))
    assert by_name.errors == in_order.errors
    assert max(by_name.errors.values()) < 1e-7


@pytest.mark.parametrize(("mistake", "factor"), [("wrong sign", -1.0), ("factor 2", 2.0)])
def test_a_wrong_force_is_caught_and_named(mistake, factor):
    @pair_term(name="my_gaussian")
    def wrong(r2, epsilon, sigma):
        u = epsilon * math.exp(-r2 / (sigma * sigma))
        return u, factor * 2.0 * u / (sigma * sigma)

    with pytest.raises(ValueError, match="pair term my_gaussian: f_over_r disagrees") as caught:
        check_term(wrong, {"epsilon": 1.0, "sigma": 1.0}, (0.2, 3.0))
    message = str(caught.value)
    # where it is worst (the force's largest, r = sigma / sqrt 2), and both values there
    assert "worst at r = 0.70" in message
    worst = 0.707
    right = 2.0 * math.exp(-(worst**2))
    found = re.search(r"where f_over_r is (\S+) and .* differences (\S+) \(", message)
    assert found, message
    assert float(found[1]) == pytest.approx(factor * right, rel=1e-2)
    assert float(found[2]) == pytest.approx(right, rel=1e-2)


def test_a_wrong_curvature_is_caught():
    def bad_second(r2, epsilon, sigma):
        u, du_ds, d2u_ds2 = _gaussian_curvature(r2, epsilon, sigma)
        return u, du_ds, 0.5 * d2u_ds2  # (u''(r) - u'/r) / (4 r^2) with the 4 taken as 2

    term = PairTerm(_gaussian, bad_second, name="half_second")
    with pytest.raises(ValueError, match="pair term half_second: d2u_ds2 disagrees"):
        check_term(term, (1.0, 1.0), (0.2, 3.0))

    def bad_first(r2, epsilon, sigma):
        u, du_ds, d2u_ds2 = _gaussian_curvature(r2, epsilon, sigma)
        return u, -du_ds, d2u_ds2

    with pytest.raises(ValueError, match="du_ds disagrees"):
        check_term(PairTerm(_gaussian, bad_first, name="flipped"), (1.0, 1.0), (0.2, 3.0))

    def other_u(r2, epsilon, sigma):
        u, du_ds, d2u_ds2 = _gaussian_curvature(r2, epsilon, sigma)
        return u + 0.1, du_ds, d2u_ds2

    with pytest.raises(ValueError, match="curvature's u disagrees with its energy's u"):
        check_term(PairTerm(_gaussian, other_u, name="shifted"), (1.0, 1.0), (0.2, 3.0))


def test_bad_arguments_are_refused_clearly():
    term = PairTerm(_gaussian, name="gaussian")
    with pytest.raises(ValueError, match=r"lack \['sigma'\], have unknown \['sig'\]"):
        check_term(term, {"epsilon": 1.0, "sig": 1.0}, (0.5, 2.0))
    with pytest.raises(ValueError, match="takes 2 parameters"):
        check_term(term, [1.0], (0.5, 2.0))
    with pytest.raises(ValueError, match="0 < first < last"):
        check_term(term, [1.0, 1.0], (0.0, 2.0))
    with pytest.raises(ValueError, match="parameter sigma must be a finite number"):
        check_term(term, [1.0, np.nan], (0.5, 2.0))
    with pytest.raises(TypeError, match="expects a PairTerm, BondTerm or AngleTerm"):
        check_term(_gaussian, [1.0, 1.0], (0.5, 2.0))

    @pair_term
    def singular(r2, a):
        return a / (r2 - 1.0), 0.0

    with pytest.raises(ValueError, match=r"pair term singular: u is inf at r = 1"):
        check_term(singular, [1.0], (0.5, 1.5), points=3)


# ---------------------------------------------------------------- bonded terms
def test_the_built_in_bonded_terms_pass_in_each_variable():
    """Harmonic and FENE bonds (terms in r^2), harmonic angles (in theta) and cosine angles
    (in cos theta): each derivative, times the chain rule's factor, against differences
    in r or theta, over the whole range of angles, 0 and pi included."""
    from potentials import angles, springs

    cases = [
        (springs.HARMONIC, {"k": 100.0, "r0": 1.0}, (0.5, 2.0), "du_dr_over_r"),
        (springs.FENE, {"k": 30.0, "r_max": 1.5}, (0.5, 1.45), "du_dr_over_r"),
        (angles.HARMONIC, {"k": 50.0, "theta0": 1.9}, (0.0, math.pi), "du_dtheta"),
        (angles.COSINE, {"k": 50.0}, (0.0, math.pi), "du_dc"),
    ]
    for term, params, r_range, first in cases:
        report = check_term(term, params, r_range)
        assert first in report.errors and "curvature u" in report.errors, report
        assert max(report.errors.values()) < 1e-6, report


def test_a_wrong_bonded_derivative_is_caught_and_named():
    @bond_term(name="my_morse")
    def morse(r, d0, alpha, r0):
        e = math.exp(-alpha * (r - r0))
        return d0 * (1.0 - e) ** 2, 2.0 * d0 * alpha * e * (1.0 - e)

    assert check_term(morse, [1.0, 2.0, 1.0], (0.6, 3.0)).errors["du_dr"] < 1e-8

    @bond_term(name="my_spring")
    def spring(r, k):
        return 0.5 * k * r * r, -k * r  # the sign of du/dr wrong

    with pytest.raises(ValueError, match=r"bond term my_spring: du_dr disagrees .* at r = 2,"):
        check_term(spring, [1.0], (0.5, 2.0))

    @angle_term(name="my_cosine", variable="cos")
    def cosine(c, k):
        return k * (1.0 + c), k

    def bad_curvature(c, k):
        return k * (1.0 + c), k, 2.0 * k  # u is linear in c: d2u_dc2 must be 0

    assert check_term(cosine, [3.0], (0.1, 3.0)).errors["du_dc"] < 1e-8
    cosine.with_curvature(bad_curvature)
    with pytest.raises(
        ValueError,
        match=r"angle term my_cosine: d2u_dc2 \* -sin\(theta\) "
        r"disagrees .* worst at theta = ",
    ):
        check_term(cosine, [3.0], (0.1, 3.0))
    with pytest.raises(ValueError, match="two angles in radians"):
        check_term(cosine, [3.0], (0.0, 4.0))
