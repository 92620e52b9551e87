"""Functions for pair terms that vectorise where numba's own do not (exp, log, sin and
cos), and a reciprocal the compiler computes early.

LLVM turns a pair loop into vector instructions only if every call in it has
a vector form. numba's ``math.exp`` is a call to the C library's scalar
``exp`` unless numba finds Intel's SVML (``icc_rt``), so a loop computing
exp (Morse, Buckingham, Yukawa) stays scalar. :func:`exp` here is written in
arithmetic that vectorises: Cody-Waite reduction x = k ln 2 + r with
|r| <= ln 2 / 2 (k rounded by adding 1.5 * 2^52, whose low bits then give
2^k), exp(r) = 1 + r + r^2 q(r) with q a polynomial of degree 7 fitted to
minimise the largest relative error of exp(r) (not of q: near r = 0 the
factor r^2 makes q's error harmless), evaluated in Estrin's order: pairs of
terms, then pairs of pairs, so its chain of dependent steps is 4 long where
the Horner form it replaced took 13. The pair loops are limited by that chain and by
the count of operations (each pair waits for its sqrt, exp and division in
turn, and the CPU holds only a few pairs in flight). Per pair as a multiple
of LJ's cost (``benchmarks/pair_styles.py``, 1 thread, Zen 3): Horner's
degree-13 Taylor polynomial, Morse 1.75 and Buckingham 1.79; Estrin's order
with a degree-9 Chebyshev fit (1 ulp), 1.62 and 1.62, later 1.51 and 1.56
after other changes; the degree-7 fit, 1.45 and 1.48 (in-process A/B of
the three degrees, 151 repeats: degree 8, 1.46 and 1.53).

Error bound: at most 2e-14 relative (46 bits of the 53; the fit's own error
is 1.65e-14, the rest is rounding), measured against numpy's ``exp`` on a
million points of [-707, 709.78] by ``tests/test_pair_styles.py``. That is
below the 44 bits GROMACS asks of its SIMD math in double precision
(``GMX_SIMD_ACCURACY_BITS_DOUBLE``), and far below what a force field's
parameters carry. Below -708 the result is 0 (the true value is below
1e-307), above ln(DBL_MAX) = 709.7827 it overflows to infinity (within the
error bound of that edge it may round to the largest double), NaN stays NaN. In
Python (no compilation, or ``NUMBA_DISABLE_JIT=1``) :func:`exp` is
``math.exp``, correctly rounded to within the C library's 1 ulp.

:func:`log` works the same way (x = 2^e m from the bits, a polynomial for
log m; see its docstring), so that pair terms can take powers with any
exponent as ``exp(y * log(x))``: Mie's pair loop went from 6.6-7.2 to about
2.5 times LJ's cost per pair with it.

:func:`reciprocal` is 1/x, exactly IEEE's division, kept by the compiler as a
division of its own: see its docstring.
"""

from __future__ import annotations

import math

import numpy as np
from numba import types
from numba.extending import overload, register_jitable

from md._simd import bits_float, float_bits

__all__ = ["cos", "exp", "log", "reciprocal", "sin"]

_LOG2E = 1.4426950408889634
_LN2_HI = 6.93147180369123816490e-01  # ln 2 to 32 bits: k * _LN2_HI is exact for |k| < 2^20
_LN2_LO = 1.90821492927058770002e-10
#: 1.5 * 2^52: adding it rounds a float to an integer held in the low mantissa bits.
_ROUND = 6755399441055744.0
_ROUND_BITS = int(np.float64(_ROUND).view(np.int64))
#: q(r) = (exp(r) - 1 - r) / r^2 on |r| <= ln 2 / 2 as c2 + c3 r + ... + c9 r^7, fitted
#: (mpmath at 40 digits, Lawson's iteration on 600 Chebyshev nodes) to minimise the largest
#: of |r^2 (q_fit(r) - q(r)) / exp(r)|, the relative error it leaves in exp(r) = 1 + r +
#: r^2 q(r): 1.6445e-14 on a grid of 20001 points. One degree lower than a 1-ulp exp
#: needs (three multiply-adds fewer per call).
_COEFFICIENTS = (
    0.49999999999664543904,
    0.1666666666726472099,
    0.041666666962082501709,
    0.008333333095244361573,
    0.0013888811173253205598,
    0.00019841538962672452587,
    0.00002488079510201509357,
    2.7493087196024121296e-6,
)


def exp(x):
    """e^x for pair terms: math.exp in Python, a vectorisable polynomial when compiled."""
    return math.exp(x)


# Compiled as a function of its own whose only fast-math flag is "contract" (its rounding
# tricks must not be reassociated away, but a multiply-add may fuse: the polynomial's steps
# and the Cody-Waite reduction become FMAs, which only round less; Morse's pair loop went
# from 2.06 to 1.75 times LJ's cost per pair with the Horner form), which LLVM then inlines
# into the vectorised pair loops.
@overload(exp, jit_options={"fastmath": {"contract"}, "error_model": "numpy"})
def _exp_compiled(x):
    c2, c3, c4, c5, c6, c7, c8, c9 = _COEFFICIENTS
    round_bits = np.int64(_ROUND_BITS)

    def implementation(x):
        # Above 710 exp overflows: clamped there, x still gives inf (2 e^r 2^1023 past the
        # largest double), and NaN passes (a comparison with NaN is false). One minimum
        # here and one select at the end cost less than testing both ends at the end (a
        # third of the range handling's time: Buckingham's pair loop 1.48 -> 1.43 times
        # LJ's cost, AVX2 code).
        x = 710.0 if x > 710.0 else x
        # k, the integer nearest x / ln 2, as x log2(e) + 1.5 * 2^52 rounds it (one fused
        # multiply-add; the sum's low mantissa bits hold k, used again for 2^k below).
        shifted = x * _LOG2E + _ROUND
        k = shifted - _ROUND
        r = (x - k * _LN2_HI) - k * _LN2_LO
        # exp(r) = 1 + r + r^2 q(r): q's terms in Estrin's order (pairs, then pairs of pairs),
        # so that the chain of dependent steps is 4 long, not 9: a pair loop holds only a
        # few pairs in flight, so a long chain makes it wait.
        r2 = r * r
        r4 = r2 * r2
        a = c2 + c3 * r
        b = c4 + c5 * r
        c = c6 + c7 * r
        d = c8 + c9 * r
        q = (a + b * r2) + (c + d * r2) * r4
        # 2^(k - 1) from k's bits (k - 1, so that k = 1024, reached from x = 709.44 on,
        # still has a finite power of two), times 2 exp(r) = 2 + 2 (r + r^2 q).
        half_scale = bits_float((float_bits(shifted) - round_bits + np.int64(1022)) << np.int64(52))
        value = (2.0 + 2.0 * (r + r2 * q)) * half_scale
        # 0 below -708 (as it is phrased, NaN keeps the NaN computed from it).
        return 0.0 if x <= -708.0 else value

    return implementation


#: log(1 + f) = f - s (f - z P(z)), s = f / (2 + f), z = s^2, for sqrt(2)/2 <= 1 + f < sqrt(2):
#: P(z) = (2 atanh(s) - 2 s) / (s z) = 2/3 + 2 z/5 + ... as a degree-6 Chebyshev fit on
#: 0 <= z <= (3 - 2 sqrt 2)^2 (mpmath.chebyfit at 50 digits; its error below 4e-16, so
#: below 5e-18 relative in log(1 + f)).
_LOG_COEFFICIENTS = (
    0.66666666666666696862,
    0.3999999999989950449,
    0.28571428625975484921,
    0.22222211134795079855,
    0.1818288912526172208,
    0.15331721600556041269,
    0.1461644968504340586,
)
_SQRT2 = 1.4142135623730951
#: The smallest normal double; below it log scales its argument by 2^54 first.
_TINY = 2.2250738585072014e-308
_MANTISSA = 0x000FFFFFFFFFFFFF
_ONE_BITS = 0x3FF0000000000000
#: 2^52 as bits, with which an exponent field's value becomes a float by one subtraction.
_TWO52_BITS = 0x4330000000000000


def log(x):
    """Natural log for pair terms: math.log in Python, a vectorisable polynomial when compiled.

    x = 2^e m with sqrt(2)/2 <= m < sqrt(2) from the bits of x, log m = log(1 + f) from
    a polynomial (``_LOG_COEFFICIENTS``), log x = e ln 2 + log m. Measured within 1 ulp of
    numpy's log (``tests/test_pair_styles.py``); log 0 = -inf, log of a negative number
    or NaN is NaN, log inf = inf. Pair terms use it for powers with any exponent:
    ``exp(-0.5 * n * log(r2))`` is r^-n (Mie), where ``r2 ** (-0.5 * n)`` would call the
    C library's scalar pow and keep the loop scalar.
    """
    return math.log(x)


@overload(log, jit_options={"fastmath": {"contract"}, "error_model": "numpy"})
def _log_compiled(x):
    p0, p1, p2, p3, p4, p5, p6 = _LOG_COEFFICIENTS
    mantissa, one_bits, two52_bits = np.int64(_MANTISSA), np.int64(_ONE_BITS), np.int64(_TWO52_BITS)
    shift = np.int64(52)

    def implementation(x):
        tiny = x < _TINY  # subnormal (or not positive: replaced below)
        y = x * 18014398509481984.0 if tiny else x  # 2^54
        bits = float_bits(y)
        # e as a float: the exponent field put under 2^52's bits, less 2^52 and the bias.
        k = bits_float(two52_bits | (bits >> shift)) - (4503599627370496.0 + 1023.0)
        m = bits_float((bits & mantissa) | one_bits)  # in [1, 2)
        big = m > _SQRT2
        m = m * 0.5 if big else m
        k = k + 1.0 if big else k
        k = k - 54.0 if tiny else k
        f = m - 1.0
        s = f / (2.0 + f)
        z = s * s
        z2 = z * z
        z4 = z2 * z2
        q = ((p0 + p1 * z) + (p2 + p3 * z) * z2) + ((p4 + p5 * z) + p6 * z2) * z4
        value = k * _LN2_HI + (f - (s * (f - z * q) - k * _LN2_LO))
        value = value if x > 0.0 else (-math.inf if x == 0.0 else math.nan)
        return value if x < math.inf else x

    return implementation


def reciprocal(x):
    """1 / x for pair terms, computed as soon as x is known: ``inv_r = reciprocal(r)``.

    The pair loops compile with fast-math flags that let LLVM fold ``y * (1.0 / r)``
    into ``y / r``, which puts the division at the end of the pair's chain of
    dependent steps, after the exp (LLVM did so in Morse, Buckingham and Yukawa).
    Compiled without those flags, this division is left as it is and runs beside the
    exp: Morse's pair loop went from 1.54 to 1.52 and Buckingham's from 1.57 to 1.51
    times LJ's cost per pair (151 interleaved repeats, Zen 3; 1.65 -> 1.58 and
    1.64 -> 1.58 in the runs where the core ran fastest). The result is IEEE's 1 / x
    to the bit (0 gives inf, as numpy's error model does).
    """
    return 1.0 / x if x != 0.0 else math.copysign(math.inf, x)


@overload(reciprocal, jit_options={"fastmath": False, "error_model": "numpy"})
def _reciprocal_compiled(x):
    if x == types.float32:  # mixed precision: stays float32

        def single(x):
            return np.float32(1.0) / x

        return single

    def implementation(x):
        return 1.0 / x

    return implementation


# ----------------------------------------------------------------------- sin and cos
#: pi/2 in three parts (fdlibm's pio2_1, pio2_2, pio2_3: the first two of 33 bits, so that
#: k * part is exact for |k| < 2^20), for the Cody-Waite reduction x = k pi/2 + r.
_PIO2_1 = 1.57079632673412561417e00
_PIO2_2 = 6.07710050630396597660e-11
_PIO2_3 = 2.02226624871116645580e-21
_TWO_OVER_PI = 0.63661977236758134308
#: sin r = r + r^3 S(r^2) and cos r = 1 - r^2/2 + r^4 C(r^2) on |r| <= pi/4: the minimax
#: coefficients of fdlibm's __kernel_sin and __kernel_cos (errors below 2^-58).
_SIN_COEFFICIENTS = (
    -1.66666666666666324348e-01,
    8.33333333332248946124e-03,
    -1.98412698298579493134e-04,
    2.75573137070700676789e-06,
    -2.50507602534068634195e-08,
    1.58969099521155010221e-10,
)
_COS_COEFFICIENTS = (
    4.16666666666666019037e-02,
    -1.38888888888741095749e-03,
    2.48015872894767294178e-05,
    -2.75573143513906633035e-07,
    2.08757232129817482790e-09,
    -1.13596475577881948265e-11,
)


def sin(x):
    """sin x for pair terms: math.sin in Python, vectorisable arithmetic when compiled.

    x = k pi/2 + r with |r| <= pi/4 (k rounded as :func:`exp` rounds it, pi/2 in three
    parts), then the polynomials for sin r and cos r and the quadrant k mod 4 choose
    and sign one of them. Within 4e-16 absolute of numpy's sin for |x| <= 1e5 (the
    range a pair term's argument k r lives in; ``tests/test_pair_styles.py``), and the
    error grows slowly beyond (k pi/2 is no longer exact past |x| ~ 1.6e6); inf and NaN
    give NaN. ``sin(x)`` and ``cos(x)`` of one x share their reduction once inlined.
    Soft's pair loop went from 6.0 to about 1.5 times LJ's cost per pair with them.
    """
    return math.sin(x)


def cos(x):
    """cos x for pair terms: math.cos in Python, vectorisable arithmetic when compiled
    (see :func:`sin`: the same reduction and polynomials, the same error bound)."""
    return math.cos(x)


def _sin_cos_parts():
    """The compiled reduction shared by sin and cos: (sin r, cos r, k mod 4)."""
    s1, s2, s3, s4, s5, s6 = _SIN_COEFFICIENTS
    c1, c2, c3, c4, c5, c6 = _COS_COEFFICIENTS
    three = np.int64(3)

    @register_jitable(fastmath={"contract"}, error_model="numpy")
    def parts(x):
        shifted = x * _TWO_OVER_PI + _ROUND
        k = shifted - _ROUND
        quadrant = float_bits(shifted) & three  # k mod 4, negative k included
        r = ((x - k * _PIO2_1) - k * _PIO2_2) - k * _PIO2_3
        z = r * r
        z2 = z * z
        z4 = z2 * z2
        s = (s1 + s2 * z) + (s3 + s4 * z) * z2 + (s5 + s6 * z) * z4
        c = (c1 + c2 * z) + (c3 + c4 * z) * z2 + (c5 + c6 * z) * z4
        return r + r * z * s, 1.0 - 0.5 * z + z2 * c, quadrant

    return parts


_parts = _sin_cos_parts()


@register_jitable
def _in_quadrant(s, c, quadrant):
    """sin(k pi/2 + r) from sin r, cos r and k mod 4 (cos x is sin in the next quadrant)."""
    value = c if (quadrant & np.int64(1)) != 0 else s
    return -value if (quadrant & np.int64(2)) != 0 else value


@overload(sin, jit_options={"fastmath": {"contract"}, "error_model": "numpy"})
def _sin_compiled(x):
    def implementation(x):
        s, c, quadrant = _parts(x)
        return _in_quadrant(s, c, quadrant)

    return implementation


@overload(cos, jit_options={"fastmath": {"contract"}, "error_model": "numpy"})
def _cos_compiled(x):
    def implementation(x):
        s, c, quadrant = _parts(x)
        return _in_quadrant(s, c, quadrant + np.int64(1))

    return implementation
