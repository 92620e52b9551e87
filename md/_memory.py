"""Keep freed memory in the process: large temporaries must not cost page faults.

A step of the implicit integrators allocates and frees dozens of arrays of
3N doubles (gradients, CG vectors, products, trial positions), each 768 kB
for 32000 atoms. glibc's malloc serves such sizes with ``mmap`` or from the
top of its heap, and returns the pages to the kernel when they are freed
(``munmap``, or trimming the heap once its free top passes a threshold that
it adapts as it goes). The next array is then new memory, and writing it
page-faults on every 4 kB page. Under a hypervisor a fault costs several
microseconds: on the 32000-atom LJ melt an implicit Euler step took about
1900 faults and 35 ms with glibc's defaults, and 24 faults and 26 ms with
freed memory kept (2-core AMD EPYC VM); whether the adaptive thresholds
settled well differed from process to process, which is what made the
step's time bimodal. Velocity Verlet reuses its buffers and saw no faults
either way.

:func:`keep_freed_memory` fixes glibc's thresholds instead: blocks below
:data:`MMAP_THRESHOLD` come from the heap, and the heap is trimmed only once
:data:`TRIM_THRESHOLD` bytes are free at its top, so freed temporaries are
reused in place. The process so keeps up to that much freed memory (its peak
is unchanged). With another C library, or with ``LEAPMD_KEEP_FREED_MEMORY=0``
in the environment, it does nothing.
This is the allocator's own documented tuning (``mallopt(3)``, the settings
of the ``MALLOC_MMAP_THRESHOLD_`` and ``MALLOC_TRIM_THRESHOLD_`` environment
variables, which act only from a process's start), in place of buffer pools
written into every module that makes temporaries.

Who calls it: the ``md`` command (:func:`md.cli.main`, so every subcommand and
the sweep's child runs), once. Not ``import md``, which leaves the process as
it found it, and not :meth:`md.Simulation.run`, although it matters there too
for the implicit integrators. Measured with ``python benchmarks/freed_memory.py``
(32000-atom LJ melt, one thread, each repeat a fresh process, the settings
interleaved; a 2-core AMD EPYC VM shared with other jobs): an implicit Euler
step took 472 ms with glibc's defaults (median of 5 processes; 3671 page
faults per step) and 241 ms with freed memory kept (0 faults), 1.8 times as
long (1.5 to 4.0 per pair); velocity Verlet made no faults either way and its
times differed only by the noise (medians 36 and 33 ms, pairs 0.6 to 1.4). But
a run cannot set it and put it back: glibc has no call that reads the
thresholds, and setting either switches off its adaptive thresholds for the
rest of the process (``mallopt(3)``). So a Python program that steps the
implicit integrators on large systems calls ``md.keep_freed_memory()`` once
itself, knowing it is for the whole process.

So the hot paths that make the same large arrays at each neighbour-list build (the
cluster list's grid, search and prunes; the cluster kernel's scratch, whose length
follows the list's clusters) keep them instead, in a :class:`KeptArrays`: a library
user who never calls :func:`keep_freed_memory` then takes no page faults there
either (on the 32000-atom mixed melt, ``benchmarks/cluster_pruning.py``'s faults/step).
"""

from __future__ import annotations

import ctypes
import logging
import os

import numpy as np

logger = logging.getLogger(__name__)

#: mallopt parameter numbers (glibc's malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
#: Blocks up to this size come from the heap (glibc's largest allowed value on 64-bit).
MMAP_THRESHOLD = 32 * 1024 * 1024
#: Free memory the heap keeps at its top before it returns pages to the kernel.
TRIM_THRESHOLD = 512 * 1024 * 1024

_applied: bool | None = None


def keep_freed_memory() -> bool:
    """Set glibc's malloc to reuse freed memory rather than return it; True if set.

    Idempotent; False (and nothing changed) without glibc's ``mallopt`` or
    when ``LEAPMD_KEEP_FREED_MEMORY=0``.
    """
    global _applied
    if _applied is not None:
        return _applied
    _applied = False
    if os.environ.get("LEAPMD_KEEP_FREED_MEMORY", "1") == "0":
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt  # the process's own C library
    except (OSError, AttributeError):  # no mallopt (macOS)
        logger.debug("no mallopt: freed memory is returned as the C library decides")
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    # mallopt returns 1 on success; the trim threshold first, so a refused mmap
    # threshold (an older glibc's smaller maximum) still leaves the heap untrimmed.
    trimmed = mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD) == 1
    mapped = mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD) == 1
    _applied = trimmed and mapped
    if not _applied:
        logger.debug("mallopt refused: trim threshold %s, mmap threshold %s", trimmed, mapped)
    return _applied


class KeptArrays:
    """Arrays kept between calls, by name, for a caller that makes the same arrays again
    and again (:class:`md.neighbors.NeighborList`'s grid, search and prune, at every
    build; the cluster kernel's scratch): :meth:`take` hands out the first ``length``
    rows of the array kept under a name, made afresh only where it is too short (then
    with a sixteenth more room, so that a list a little longer than the last does not
    make it again) or of another dtype or row shape; never shrunk. So the memory that a
    build writes is the last build's, its pages mapped already: with glibc's own malloc
    thresholds each build's fresh arrays of megabytes were fresh pages from the kernel,
    page faults at their first touch (see above). What :meth:`take` hands out stays
    valid until the next call of it for that name, which writes the same memory again."""

    def __init__(self) -> None:
        self._arrays: dict[str, np.ndarray] = {}

    def take(self, name: str, length: int, dtype, row: tuple = ()) -> np.ndarray:
        """The first ``length`` rows (of shape ``row``) of the array kept as ``name``
        (uninitialised: as :func:`numpy.empty`)."""
        kept = self._arrays.get(name)
        dtype = np.dtype(dtype)
        if kept is None or kept.shape[0] < length or kept.dtype != dtype or kept.shape[1:] != row:
            kept = self._arrays[name] = None  # dropped before its successor is made
            kept = np.empty((length + length // 16,) + tuple(row), dtype)
            self._arrays[name] = kept
        return kept[:length]
