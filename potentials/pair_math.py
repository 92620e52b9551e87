"""Functions for pair terms that vectorise where numba's own do not.

LLVM turns a pair loop into vector instructions only if every call in it has
a vector form. numba's ``math.exp`` is a call to the C library's scalar
``exp`` unless numba finds Intel's SVML (``icc_rt``), so a loop computing
exp (Morse, Buckingham, Yukawa) stays scalar. :func:`exp` here is written in
arithmetic that vectorises: Cody-Waite reduction x = k ln 2 + r with
|r| <= ln 2 / 2, exp(r) by its Taylor polynomial to degree 13 (truncation
below 1e-17 relative), and 2^k assembled from its bits.

Error bound: at most 1 unit in the last place of numpy's ``exp`` over
[-707, 709] (measured: ``tests/test_pair_styles.py`` checks 1 ulp on a
million points); below -708 the result is 0 (the true value is below 1e-307),
above 709.78 it is infinite, NaN stays NaN. In Python (no compilation, or
``NUMBA_DISABLE_JIT=1``) :func:`exp` is ``math.exp``.
"""

from __future__ import annotations

import math

import numpy as np
from numba.extending import overload

from md._simd import bits_float, float_bits

__all__ = ["exp"]

_LOG2E = 1.4426950408889634
_LN2_HI = 6.93147180369123816490e-01  # ln 2 to 32 bits: k * _LN2_HI is exact for |k| < 2^20
_LN2_LO = 1.90821492927058770002e-10
#: 1.5 * 2^52: adding it rounds a float to an integer held in the low mantissa bits.
_ROUND = 6755399441055744.0
_ROUND_BITS = int(np.float64(_ROUND).view(np.int64))
_TAYLOR = tuple(1.0 / math.factorial(k) for k in range(14))


def exp(x):
    """e^x for pair terms: math.exp in Python, a vectorisable polynomial when compiled."""
    return math.exp(x)


# Compiled as a function of its own whose only fast-math flag is "contract" (its rounding
# tricks must not be reassociated away, but a multiply-add may fuse: the Horner steps and
# the Cody-Waite reduction become FMAs, which only round less; Morse's pair loop went from
# 2.06 to 1.75 times LJ's cost per pair), which LLVM then inlines into the vectorised pair
# loops.
@overload(exp, jit_options={"fastmath": {"contract"}, "error_model": "numpy"})
def _exp_compiled(x):
    c2, c3, c4, c5, c6, c7, c8, c9, c10, c11, c12, c13 = _TAYLOR[2:]
    round_bits = np.int64(_ROUND_BITS)

    def implementation(x):
        k = np.floor(x * _LOG2E + 0.5)  # the integer nearest x / ln 2
        r = (x - k * _LN2_HI) - k * _LN2_LO
        p = c13
        p = p * r + c12
        p = p * r + c11
        p = p * r + c10
        p = p * r + c9
        p = p * r + c8
        p = p * r + c7
        p = p * r + c6
        p = p * r + c5
        p = p * r + c4
        p = p * r + c3
        p = p * r + c2
        p = p * r + 1.0
        p = p * r + 1.0
        # 2^k from k's bits: k + 1.5 * 2^52 holds k in its low mantissa bits.
        scale = bits_float((float_bits(k + _ROUND) - round_bits + np.int64(1023)) << np.int64(52))
        value = p * scale
        value = value if x > -708.0 else 0.0
        return value if x < 709.78 else (math.inf if x == x else x)

    return implementation

