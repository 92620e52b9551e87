"""The simulator checks' lighter launches (``tests/_gpu_checks.py``): which kernels may run
their threads one after another. A kernel whose threads meet at a barrier or trade values in
a warp primitive, itself or through a device function it reaches (by a global name or a
closure), must keep one Python thread per GPU thread; run in order, such a kernel would
stop at its first barrier. Plain Python here: no simulator, nothing compiled."""

from __future__ import annotations

import types

import _gpu_checks
import pytest

cuda = types.SimpleNamespace()  # only read by name: the functions below are never called


class Device:
    """What the simulator makes of a device function: an object holding it as ``fn``."""

    def __init__(self, fn):
        self.fn = fn


def _plain(x, i):
    x[i] = 2.0 * x[i]


def _barrier(x, i):
    x[i] = 1.0
    cuda.syncthreads()


def _shuffle(x, i):
    x[i] = cuda.shfl_down_sync(0xFFFFFFFF, x[i], 1)


def _loop_with_barrier(x):
    for i in range(3):
        if i:
            cuda.syncthreads_count(x[i])


PLAIN, BARRIER, SHUFFLE = Device(_plain), Device(_barrier), Device(_shuffle)


def _calls_plain(x):
    PLAIN(x, 0)


def _calls_barrier(x):
    PLAIN(x, 0)
    BARRIER(x, 1)


def _nested_barrier(x):
    def inner():
        cuda.syncthreads()

    inner()


def _kernel_of(device):
    def kernel(x):
        device(x, 0)

    return kernel


def _recursive(x):
    SELF(x)


SELF = Device(_recursive)


@pytest.mark.parametrize(
    ("function", "cooperates"),
    [
        (_plain, False),
        (_calls_plain, False),
        (_kernel_of(PLAIN), False),
        (_recursive, False),
        (_barrier, True),
        (_shuffle, True),
        (_loop_with_barrier, True),
        (_calls_barrier, True),
        (_nested_barrier, True),
        (_kernel_of(BARRIER), True),
        (_kernel_of(SHUFFLE), True),
        (len, True),  # no Python code to read: treated as cooperating
    ],
)
def test_a_kernel_keeps_its_threads_where_it_or_a_device_function_syncs(function, cooperates):
    assert _gpu_checks._cooperates(function) is cooperates
