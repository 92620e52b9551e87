"""Kernels that make their MPI calls themselves: the halo's sweeps between list builds
(pack, send, receive, unpack in one compiled call) and the reduction's all-gather.

The calls go to the MPI library through the addresses of its functions, given to the
kernels at run time with the communicator's and datatype's handles
(:class:`md.distributed.ranks.CompiledMPI`, one int64 array ``calls``), never baked into
the code: numba caches these kernels on disk as any other (``cache=True``), and each rank of a
launch loads them instead of compiling them cold. (numba-mpi's functions reference
ctypes function pointers, which numba cannot cache: each process would compile them, a
few seconds a launch.) :func:`c_call` is the one intrinsic: it calls a C function at an
address with integer arguments, each of its own width (an int64 also carries a C
``int`` argument, a handle of MPICH's: see :class:`md.distributed.ranks.CompiledMPI`); its
Python twin calls through ctypes under ``NUMBA_DISABLE_JIT=1``.

The arithmetic is that of :func:`md.distributed._domain_kernels.pack_sweep`,
``ghost_rows`` and ``add_sweep`` (the same bits as the mpi4py path: a test compares
them), the messages those of ``md.distributed.halo._Sweep`` (the same peers and tags, a
sweep's receives posted before its sends). A non-zero MPI error code ends a kernel and
is returned; the caller raises it.
"""

from __future__ import annotations

import ctypes

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

from md._simd import python_twin
from md.distributed._domain_kernels import (
    AXIS,
    BACK,
    COUNT,
    DEST,
    END,
    FIRST,
    LAST,
    OFFSET,
    SOURCE,
    START,
    TAG,
    TO_SELF,
    fold_gathered,
)


def _c_call(address, args):
    """:func:`c_call` from Python, through ctypes."""
    kinds = [ctypes.c_int32 if isinstance(a, np.int32) else ctypes.c_int64 for a in args]
    function = ctypes.CFUNCTYPE(ctypes.c_int32, *kinds)(int(address))
    return np.int32(function(*(int(a) for a in args)))


@python_twin(_c_call)
@intrinsic
def c_call(typingctx, address, args):
    """Call the C function at ``address`` (an int64) with the integers of the tuple ``args``
    (each of its own width); return its int32 result."""
    if not isinstance(address, types.Integer) or not isinstance(args, types.BaseTuple):
        return None
    if not all(isinstance(t, types.Integer) and t.bitwidth in (32, 64) for t in args.types):
        return None
    sig = types.int32(address, args)

    def codegen(context, builder, signature, llargs):
        target, packed = llargs
        values = cgutils.unpack_tuple(builder, packed, len(args.types))
        kind = ir.FunctionType(ir.IntType(32), [value.type for value in values])
        function = builder.inttoptr(target, kind.as_pointer())
        return builder.call(function, values)

    return sig, codegen


@njit(cache=True, inline="always")
def _address(array):
    return np.int64(array.ctypes.data)


# The exchanges' ``table`` (a row a swap: START, END, OFFSET, COUNT, DEST, SOURCE, TAG,
# BACK) and ``sweeps`` (a row a sweep: AXIS, TO_SELF, FIRST, LAST) have the columns of the
# swap tables a build's ghost search writes (md.distributed._domain_kernels.sweep_send).
#: The entries of ``calls``: the handles of the communicator, MPI_DOUBLE and MPI_MAX, then
#: the addresses of MPI_Isend, MPI_Irecv, MPI_Wait, MPI_Allgather and MPI_Allreduce.
COMM, DOUBLE, MAX, ISEND, IRECV, WAIT, ALLGATHER, ALLREDUCE = range(8)
#: int64 words at the end of ``slots`` for the MPI_Status a wait fills (MPICH's are 20
#: bytes, Open MPI's 24).
STATUS_WORDS = 8


@njit(cache=True, error_model="numpy")
def _message(send, rows, first_row, n_rows, peer, tag, slots, slot, calls):
    """Post one message of ``n_rows`` rows of 3 doubles of ``rows`` from ``first_row``:
    a send to (``send``) or a receive from ``peer``, its request in ``slots[slot]``.
    0 or the MPI error code."""
    return c_call(
        calls[ISEND] if send else calls[IRECV],
        (
            _address(rows[first_row:]),
            np.int32(3 * n_rows),
            calls[DOUBLE],
            np.int32(peer),
            np.int32(tag),
            calls[COMM],
            _address(slots[slot:]),
        ),
    )


@njit(cache=True, error_model="numpy")
def _wait(n, slots, calls):
    """Wait for the requests in the first ``n`` slots (8 bytes each, where an MPI_Request of
    either kind fits), one after another. 0 or the first MPI error code."""
    status = _address(slots[slots.shape[0] - STATUS_WORDS :])
    for r in range(n):
        code = c_call(calls[WAIT], (_address(slots[r:]), status))
        if code != 0:
            return code
    return 0


@njit(cache=True, error_model="numpy")
def halo_forward(positions, cell, sweeps, table, shifts, index, out, slots, calls):
    """The halo update's sweeps in order. Swap j (row j of ``table``) takes the rows
    ``index[START:END]`` of ``positions`` shifted by ``shifts[j]`` cell vectors along its
    sweep's axis, into ``positions`` from row ``OFFSET`` (a sweep ``TO_SELF``) or into
    ``out``'s same rows, sent to ``DEST`` with tag ``TAG`` while ``COUNT`` rows arrive from
    ``SOURCE`` into ``positions`` from row ``OFFSET``; a sweep's receives are posted before
    its sends. Returns 0, or the first MPI error code."""
    for s in range(sweeps.shape[0]):
        axis = sweeps[s, AXIS]
        first, last = sweeps[s, FIRST], sweeps[s, LAST]
        local = sweeps[s, TO_SELF] != 0
        for j in range(first, last):
            s0 = shifts[j] * cell[axis, 0]
            s1 = shifts[j] * cell[axis, 1]
            s2 = shifts[j] * cell[axis, 2]
            start, offset = table[j, START], table[j, OFFSET]
            for k in range(start, table[j, END]):
                i = index[k]
                row = offset + k - start if local else k
                target = positions if local else out
                target[row, 0] = positions[i, 0] + s0
                target[row, 1] = positions[i, 1] + s1
                target[row, 2] = positions[i, 2] + s2
        if local:
            continue
        n = 0
        for j in range(first, last):
            t = table[j]
            code = _message(
                False, positions, t[OFFSET], t[COUNT], t[SOURCE], t[TAG], slots, n, calls
            )
            if code != 0:
                return code
            n += 1
        for j in range(first, last):
            t = table[j]
            code = _message(
                True, out, t[START], t[END] - t[START], t[DEST], t[TAG], slots, n, calls
            )
            if code != 0:
                return code
            n += 1
        code = _wait(n, slots, calls)
        if code != 0:
            return code
    return 0


@njit(cache=True, error_model="numpy")
def halo_reverse(values, sweeps, table, index, out, back, slots, calls):
    """The reverse of :func:`halo_forward` for (n_local, 3) ``values``: sweep after sweep
    from the last, swap j's ghost rows (``COUNT`` from ``OFFSET``) copied into ``back``
    from row ``BACK`` and sent to ``SOURCE`` with tag ``16 + TAG`` while the sums for its
    rows ``index[START:END]`` arrive from ``DEST`` into ``out``'s same rows; then added into
    ``values`` swap after swap from the sweep's last (a sweep ``TO_SELF`` adds its own
    ghost rows). Returns 0, or the first MPI error code."""
    for s in range(sweeps.shape[0] - 1, -1, -1):
        first, last = sweeps[s, FIRST], sweeps[s, LAST]
        local = sweeps[s, TO_SELF] != 0
        if not local:
            for j in range(first, last):
                row = table[j, BACK]
                for k in range(table[j, OFFSET], table[j, OFFSET] + table[j, COUNT]):
                    back[row, 0] = values[k, 0]
                    back[row, 1] = values[k, 1]
                    back[row, 2] = values[k, 2]
                    row += 1
            n = 0
            for j in range(first, last):
                t = table[j]
                code = _message(
                    False, out, t[START], t[END] - t[START], t[DEST], 16 + t[TAG], slots, n, calls
                )
                if code != 0:
                    return code
                n += 1
            for j in range(first, last):
                t = table[j]
                code = _message(
                    True, back, t[BACK], t[COUNT], t[SOURCE], 16 + t[TAG], slots, n, calls
                )
                if code != 0:
                    return code
                n += 1
            code = _wait(n, slots, calls)
            if code != 0:
                return code
        for j in range(last - 1, first - 1, -1):
            start, offset = table[j, START], table[j, OFFSET]
            for k in range(start, table[j, END]):
                i = index[k]
                row = offset + k - start if local else k
                source = values if local else out
                values[i, 0] += source[row, 0]
                values[i, 1] += source[row, 1]
                values[i, 2] += source[row, 2]
    return 0


@njit(cache=True, error_model="numpy")
def gather(values, gathered, calls):
    """Every rank's ``values`` (k,) into the rows of ``gathered`` (P, k), in rank order (MPI's
    all-gather). Returns 0, or the MPI error code."""
    k = np.int32(values.shape[0])
    return c_call(
        calls[ALLGATHER],
        (_address(values), k, calls[DOUBLE], _address(gathered), k, calls[DOUBLE], calls[COMM]),
    )


@njit(cache=True, error_model="numpy")
def gather_fold(values, gathered, n_summed, totals, worst, calls):
    """:func:`gather`, then :func:`md.distributed._domain_kernels.fold_gathered` of it: the one
    reduction of a force evaluation in one call. Returns 0, or the MPI error code."""
    code = gather(values, gathered, calls)
    if code == 0:
        fold_gathered(gathered, n_summed, totals, worst)
    return code


@njit(cache=True, error_model="numpy")
def maximum(values, out, calls):
    """``out`` = the largest of every rank's ``values`` (k,), element by element (MPI's
    all-reduce with MPI_MAX: exact in any order). Returns 0, or the MPI error code."""
    k = np.int32(values.shape[0])
    return c_call(
        calls[ALLREDUCE],
        (_address(values), _address(out), k, calls[DOUBLE], calls[MAX], calls[COMM]),
    )
