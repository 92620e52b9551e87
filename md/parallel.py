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
"""

from __future__ import annotations

import numba

_threads: int | None = None


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
