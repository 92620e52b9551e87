"""How many threads the numba kernels use: one process-wide setting.

The force and neighbour kernels have a serial form (bit-for-bit
deterministic, the reference) and a threaded form that splits the atoms into
one chunk per thread, each with its own force buffer, so no two threads
write the same memory; the buffers are summed afterwards. The threaded form
is deterministic for a given thread count and agrees with the serial one to
round-off (only the order of the force sums differs).

``threads`` is chosen once per process, as OpenMP's ``OMP_NUM_THREADS`` is:
``set_threads(n)`` (``md run --threads``, ``[run] threads`` in a config,
``Simulation(threads=...)``). The default is every core numba may use
(``NUMBA_NUM_THREADS``, normally the core count).

A run decomposed over MPI ranks (:mod:`md.distributed`) sets one more, for
the duration of its collective calls (:func:`using_reductions`): there
:func:`global_sum` and :func:`global_max` reduce over every rank (the
integrators' kinetic energies, degrees of freedom and noise momenta, FIRE's
powers and norms); anywhere else they return their argument unchanged, and
nothing about MPI is imported.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Protocol

import numba
import numpy as np
from numba import njit, prange


class Reductions(Protocol):
    """Sums and maxima over the ranks of a decomposed run (see :mod:`md.distributed`)."""

    n_ranks: int

    def sum(self, values: np.ndarray) -> np.ndarray:
        """Element-wise sum over the ranks, added in rank order: the same bits on every rank."""
        ...

    def max(self, values: np.ndarray) -> np.ndarray:
        """Element-wise maximum over the ranks."""
        ...


_threads: int | None = None
#: The reductions of a decomposed run (None: this process holds the whole system).
_reductions: Reductions | None = None
#: Fewest elements per thread worth a chunk of their own in a memory-bound pass (the
#: force cache's copy and comparison of positions: 16000 atoms' worth, as the kick passes'
#: threshold in integrators._kernels).
_MIN_CHUNK_VALUES = 48_000


def max_threads() -> int:
    """Most threads the kernels can use (numba's pool size)."""
    return int(numba.config.NUMBA_NUM_THREADS)


def set_threads(threads: int | None) -> int:
    """Use ``threads`` threads in the kernels (None: all); return the number set.

    Raises
    ------
    ValueError
        If ``threads`` is not a positive integer or exceeds :func:`max_threads`.
    """
    global _threads
    if threads is None:
        threads = max_threads()
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise ValueError(f"threads must be a positive integer, got {threads!r}")
    if threads > max_threads():
        raise ValueError(
            f"threads = {threads} is more than the {max_threads()} this machine offers "
            "(numba's NUMBA_NUM_THREADS)"
        )
    _threads = threads
    numba.set_num_threads(threads)
    return threads


def get_threads() -> int:
    """Threads the kernels use now (all cores until :func:`set_threads` is called)."""
    if _threads is None:
        return set_threads(None)
    return _threads


def set_reductions(reductions: Reductions | None) -> Reductions | None:
    """Make :func:`global_sum` and :func:`global_max` reduce over ``reductions``'s ranks
    (None: this process alone); return the previous setting, for restoring it."""
    global _reductions
    previous, _reductions = _reductions, reductions
    return previous


def n_ranks() -> int:
    """Ranks the system is decomposed over (1 outside a decomposed run)."""
    return 1 if _reductions is None else _reductions.n_ranks


@contextlib.contextmanager
def using_reductions(reductions: Reductions | None) -> Iterator[None]:
    """Within the block, :func:`global_sum` and :func:`global_max` reduce over ``reductions``
    (a decomposed run's collective calls: its steps, thermo rows, minimisation)."""
    previous = set_reductions(reductions)
    try:
        yield
    finally:
        set_reductions(previous)


def global_sum(value, over: Reductions | None = None):
    """``value`` (a number or an array) summed over the ranks; ``value`` itself on one rank.

    The ranks are ``over``, else those of :func:`using_reductions`. Every rank of
    a decomposed run must call it at the same point (a collective call).
    Integers stay integers (exact below 2^53).
    """
    reductions = over if over is not None else _reductions
    if reductions is None:
        return value
    total = reductions.sum(np.atleast_1d(np.asarray(value, dtype=np.float64)))
    if np.ndim(value) == 0:
        total = total[0]
        return int(total) if isinstance(value, int | np.integer) else float(total)
    return total.reshape(np.shape(value))


def global_max(value, over: Reductions | None = None):
    """``value`` (a number or an array) maximised over the ranks (``over``, else those of
    :func:`using_reductions`); ``value`` itself on one rank."""
    reductions = over if over is not None else _reductions
    if reductions is None:
        return value
    largest = reductions.max(np.atleast_1d(np.asarray(value, dtype=np.float64)))
    return float(largest[0]) if np.ndim(value) == 0 else largest.reshape(np.shape(value))


def chunk_count(n: int, fewest: int) -> int:
    """Chunks to split ``n`` items into: one per thread, each of at least ``fewest`` items
    (below that, waking a thread costs more than it saves), and at least one."""
    return max(1, min(get_threads(), n // fewest))


def _chunks(n: int) -> int:
    return chunk_count(n, _MIN_CHUNK_VALUES)


def same_values(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two arrays of one shape are equal (NaN equals nothing), in chunks on the
    kernels' threads, each stopping at its first difference; no temporary array."""
    a, b = a.reshape(-1), b.reshape(-1)
    n = a.shape[0]
    # one chunk below two chunks' worth, on any number of threads (no thread count asked)
    chunks = 1 if n < 2 * _MIN_CHUNK_VALUES else _chunks(n)
    if chunks == 1:
        return bool(_same_values(a, b))
    return bool(_same_values_threaded(a, b, chunks))


def all_finite(values: np.ndarray) -> bool:
    """Whether no value of a C-contiguous float array is NaN or infinite, in chunks on the
    kernels' threads (the force field's check of every force, each evaluation)."""
    values = values.reshape(-1)
    n = values.shape[0]
    chunks = 1 if n < 2 * _MIN_CHUNK_VALUES else _chunks(n)
    if chunks == 1:
        return bool(_all_finite(values))
    return bool(_all_finite_threaded(values, chunks))


def copied(values: np.ndarray, into: np.ndarray) -> np.ndarray:
    """A copy of ``values``: ``into`` (C-contiguous, of the same dtype) with them written in
    where its shape is theirs, else a new array; :func:`copy_into`'s threads only where they
    would split it (below that no Python call at all: a decomposed step copies its start)."""
    if into.shape != values.shape:
        return values.copy()
    if values.size < 2 * _MIN_CHUNK_VALUES:
        into[...] = values
    else:
        copy_into(into, values)
    return into


def copy_into(destination: np.ndarray, source: np.ndarray) -> None:
    """``destination[...] = source`` for two C-contiguous arrays of one shape and dtype,
    in chunks on the kernels' threads."""
    chunks = _chunks(source.size)
    if chunks == 1:
        np.copyto(destination, source)
    else:
        _copy_threaded(destination.reshape(-1), source.reshape(-1), chunks)


#: Values compared per block by _same_values: a block has no early exit, so it vectorises.
_SAME_BLOCK = 64


@njit(cache=True)
def _same_values(a, b):
    # In blocks, each checked after it is compared: an exit at every value kept the loop
    # scalar (32000 atoms' positions: 65 -> 20 us; a force field checks them every step).
    n = a.shape[0]
    start = 0
    while start + _SAME_BLOCK <= n:
        differ = False
        for i in range(start, start + _SAME_BLOCK):
            differ |= a[i] != b[i]
        if differ:
            return False
        start += _SAME_BLOCK
    for i in range(start, n):
        if a[i] != b[i]:
            return False
    return True


@njit(cache=True)
def _all_finite(values):
    """Whether no value is NaN or infinite (one pass with no early exit: it vectorises)."""
    finite = True
    for i in range(values.shape[0]):
        finite &= abs(values[i]) < np.inf
    return finite


@njit(cache=True, parallel=True)
def _all_finite_threaded(values, chunks):
    n = values.shape[0]
    finite = np.ones(chunks, dtype=np.bool_)
    for c in prange(chunks):
        finite[c] = _all_finite(values[c * n // chunks : (c + 1) * n // chunks])
    return finite.all()


@njit(cache=True, parallel=True)
def _same_values_threaded(a, b, chunks):
    n = a.shape[0]
    same = np.ones(chunks, dtype=np.bool_)
    for c in prange(chunks):
        same[c] = _same_values(
            a[c * n // chunks : (c + 1) * n // chunks], b[c * n // chunks : (c + 1) * n // chunks]
        )
    return same.all()


@njit(cache=True, parallel=True)
def _copy_threaded(destination, source, chunks):
    n = source.shape[0]
    for c in prange(chunks):
        destination[c * n // chunks : (c + 1) * n // chunks] = source[
            c * n // chunks : (c + 1) * n // chunks
        ]
