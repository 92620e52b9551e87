"""Counter-based Gaussian noise: Philox4x64-10 keyed by a seed, counted by (step, atom).

Langevin dynamics needs three Gaussian numbers per atom and step. Drawn from
one sequential stream they depend on how atoms are ordered and split among
processes; drawn as ``philox(key, counter = (step, atom id, 0, 0))`` they are
a function of the seed, the step and the atom alone, so a trajectory is the
same whether the system runs on one process or is cut over many
(:mod:`md.distributed`), and a resumed run needs no generator state.

Philox4x64-10 (Salmon et al., SC'11) is the counter-based generator numpy
ships as ``numpy.random.Philox``: ``philox4x64(key, counter)`` here equals
the first four outputs of ``Philox(key=key, counter=counter - 1)`` (numpy
counts up before each block), which the tests check. The 64-bit products
are split into 32-bit halves, as numba has no 128-bit integers. Each block
gives four 53-bit uniforms, paired by Box-Muller into four normals.

References
----------
J. K. Salmon, M. A. Moraes, R. O. Dror, D. E. Shaw, "Parallel random numbers:
as easy as 1, 2, 3", SC'11 (2011).
"""

from __future__ import annotations

import numpy as np
from numba import njit

_M0 = np.uint64(0xD2E7470EE14C6C93)
_M1 = np.uint64(0xCA5A826395121157)
_W0 = np.uint64(0x9E3779B97F4A7C15)
_W1 = np.uint64(0xBB67AE8584CAA73B)
_LOW = np.uint64(0xFFFFFFFF)
_32 = np.uint64(32)
_11 = np.uint64(11)
_TWO_PI = 2.0 * np.pi
_UNIT = 2.0**-53


def seed_key(seed) -> np.ndarray:
    """The two 64-bit key words of ``seed`` (an int, a list of ints, a numpy Generator, or
    None for fresh entropy), through numpy's SeedSequence."""
    if isinstance(seed, np.random.Generator):
        return seed.integers(0, 2**64, size=2, dtype=np.uint64)
    try:
        return np.random.SeedSequence(seed).generate_state(2, dtype=np.uint64)
    except (TypeError, ValueError) as error:
        raise ValueError(f"seed must be an integer, a list of integers or None ({error})") from None


@njit(cache=True, inline="always")
def _mulhilo(a, b):
    """(high, low) 64-bit words of the 128-bit product a * b."""
    a_lo = a & _LOW
    a_hi = a >> _32
    b_lo = b & _LOW
    b_hi = b >> _32
    lo_lo = a_lo * b_lo
    hi_lo = a_hi * b_lo
    lo_hi = a_lo * b_hi
    hi_hi = a_hi * b_hi
    middle = (lo_lo >> _32) + (hi_lo & _LOW) + (lo_hi & _LOW)
    high = hi_hi + (hi_lo >> _32) + (lo_hi >> _32) + (middle >> _32)
    return high, a * b


@njit(cache=True)
def philox4x64(k0, k1, c0, c1, c2, c3):
    """Philox4x64-10 of the counter (c0, c1, c2, c3) under the key (k0, k1): four uint64."""
    for r in range(10):
        if r > 0:
            k0 = k0 + _W0
            k1 = k1 + _W1
        hi0, lo0 = _mulhilo(_M0, c0)
        hi1, lo1 = _mulhilo(_M1, c2)
        c0, c1, c2, c3 = hi1 ^ c1 ^ k0, lo1, hi0 ^ c3 ^ k1, lo0
    return c0, c1, c2, c3


@njit(cache=True, inline="always")
def _uniform(word):
    """A uniform float in (0, 1] from the top 53 bits of a uint64."""
    return ((word >> _11) + np.uint64(1)) * _UNIT


@njit(cache=True, inline="always")
def atom_gaussians(k0, k1, s, atom):
    """The three standard normal numbers of counter (s, atom) under the key (k0, k1), all
    uint64: Box-Muller on Philox's four words. ``gaussian_noise``'s per atom, and the
    GPU path's (``md.cuda`` compiles this function for the device)."""
    zero = np.uint64(0)
    w0, w1, w2, w3 = philox4x64(k0, k1, s, atom, zero, zero)
    r = np.sqrt(-2.0 * np.log(_uniform(w0)))
    angle = _TWO_PI * _uniform(w1)
    g2 = np.sqrt(-2.0 * np.log(_uniform(w2))) * np.cos(_TWO_PI * _uniform(w3))
    return r * np.cos(angle), r * np.sin(angle), g2


@njit(cache=True)
def gaussian_noise(key, step, ids, out):
    """Write three standard normal numbers per atom into ``out`` (N, 3): those of counter
    (step, ids[i]) under ``key`` (two uint64), the same wherever atom ids[i] is held."""
    k0 = np.uint64(key[0])
    k1 = np.uint64(key[1])
    s = np.uint64(step)
    for i in range(out.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = atom_gaussians(k0, k1, s, np.uint64(ids[i]))
