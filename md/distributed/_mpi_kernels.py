"""Kernels that make their MPI calls themselves: the halo's sweeps between list builds
(pack, send, receive, unpack in one compiled call) and the reduction's all-gather.

The calls go to the MPI library through the addresses of its functions, given to the
kernels at run time with the communicator's and datatype's handles
(:class:`md.distributed.ranks.CompiledMPI`, one tuple ``mpi``), never baked into the
code: numba caches these kernels on disk as any other (``cache=True``), and each rank of a
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
from md.distributed._domain_kernels import fold_gathered


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


@njit(cache=True, error_model="numpy")
def _wait(n, requests, status, mpi):
    """Wait for the first ``n`` requests (8-byte slots), one after another; 0 or the first
    MPI error code."""
    for r in range(n):
        code = c_call(mpi[5], (_address(requests[r:]), _address(status)))
        if code != 0:
            return code
    return 0


@njit(cache=True, error_model="numpy")
def halo_forward(
    positions,
    cell,
    axes,
    to_self,
    sweep_swaps,
    starts,
    shifts,
    offsets,
    counts,
    dests,
    sources,
    tags,
    index,
    out,
    requests,
    statuses,
    mpi,
):
    """The halo update's sweeps in order: each swap j's rows ``index[starts[j]:starts[j+1]]``
    of ``positions`` shifted by ``shifts[j]`` cell vectors along its sweep's axis, into
    ``positions`` from row ``offsets[j]`` (a sweep ``to_self``) or into ``out``'s same rows
    and sent to ``dests[j]`` with tag ``tags[j]``, while ``counts[j]`` rows arrive from
    ``sources[j]`` into ``positions`` from row ``offsets[j]``. Returns 0, or the first MPI
    error code."""
    comm, double, isend, irecv = mpi[0], mpi[1], mpi[3], mpi[4]
    for s in range(axes.shape[0]):
        axis = axes[s]
        first, last = sweep_swaps[s], sweep_swaps[s + 1]
        local = to_self[s] != 0
        for j in range(first, last):
            s0 = shifts[j] * cell[axis, 0]
            s1 = shifts[j] * cell[axis, 1]
            s2 = shifts[j] * cell[axis, 2]
            for k in range(starts[j], starts[j + 1]):
                i = index[k]
                row = offsets[j] + k - starts[j] if local else k
                target = positions if local else out
                target[row, 0] = positions[i, 0] + s0
                target[row, 1] = positions[i, 1] + s1
                target[row, 2] = positions[i, 2] + s2
        if local:
            continue
        n = 0
        for j in range(first, last):
            code = c_call(
                irecv,
                (
                    _address(positions[offsets[j] :]),
                    np.int32(3 * counts[j]),
                    double,
                    np.int32(sources[j]),
                    np.int32(tags[j]),
                    comm,
                    _address(requests[n:]),
                ),
            )
            if code != 0:
                return code
            n += 1
        for j in range(first, last):
            code = c_call(
                isend,
                (
                    _address(out[starts[j] :]),
                    np.int32(3 * (starts[j + 1] - starts[j])),
                    double,
                    np.int32(dests[j]),
                    np.int32(tags[j]),
                    comm,
                    _address(requests[n:]),
                ),
            )
            if code != 0:
                return code
            n += 1
        code = _wait(n, requests, statuses, mpi)
        if code != 0:
            return code
    return 0


@njit(cache=True, error_model="numpy")
def halo_reverse(
    values,
    axes,
    to_self,
    sweep_swaps,
    starts,
    offsets,
    counts,
    dests,
    sources,
    tags,
    index,
    out,
    back,
    back_starts,
    requests,
    statuses,
    mpi,
):
    """The reverse of :func:`halo_forward` for (n_local, 3) ``values``: sweep after sweep
    from the last, the ghosts' rows sent back to ``sources[j]`` (from ``back``, swap j's
    from row ``back_starts[j]``) with tag ``16 + tags[j]`` while the sums for the rows
    ``index[starts[j]:starts[j+1]]`` arrive from ``dests[j]`` into ``out``'s same rows, then
    added into ``values`` swap after swap from the sweep's last (a sweep ``to_self`` adds its
    own ghost rows). Returns 0, or the first MPI error code."""
    comm, double, isend, irecv = mpi[0], mpi[1], mpi[3], mpi[4]
    for s in range(axes.shape[0] - 1, -1, -1):
        first, last = sweep_swaps[s], sweep_swaps[s + 1]
        local = to_self[s] != 0
        if not local:
            for j in range(first, last):
                row = back_starts[j]
                for k in range(offsets[j], offsets[j] + counts[j]):
                    back[row, 0] = values[k, 0]
                    back[row, 1] = values[k, 1]
                    back[row, 2] = values[k, 2]
                    row += 1
            n = 0
            for j in range(first, last):
                code = c_call(
                    irecv,
                    (
                        _address(out[starts[j] :]),
                        np.int32(3 * (starts[j + 1] - starts[j])),
                        double,
                        np.int32(dests[j]),
                        np.int32(16 + tags[j]),
                        comm,
                        _address(requests[n:]),
                    ),
                )
                if code != 0:
                    return code
                n += 1
            for j in range(first, last):
                code = c_call(
                    isend,
                    (
                        _address(back[back_starts[j] :]),
                        np.int32(3 * counts[j]),
                        double,
                        np.int32(sources[j]),
                        np.int32(16 + tags[j]),
                        comm,
                        _address(requests[n:]),
                    ),
                )
                if code != 0:
                    return code
                n += 1
            code = _wait(n, requests, statuses, mpi)
            if code != 0:
                return code
        for j in range(last - 1, first - 1, -1):
            for k in range(starts[j], starts[j + 1]):
                i = index[k]
                row = offsets[j] + k - starts[j] if local else k
                source = values if local else out
                values[i, 0] += source[row, 0]
                values[i, 1] += source[row, 1]
                values[i, 2] += source[row, 2]
    return 0


@njit(cache=True, error_model="numpy")
def gather(values, gathered, mpi):
    """Every rank's ``values`` (k,) into the rows of ``gathered`` (P, k), in rank order (MPI's
    all-gather). Returns 0, or the MPI error code."""
    comm, double, allgather = mpi[0], mpi[1], mpi[6]
    k = np.int32(values.shape[0])
    return c_call(
        allgather,
        (_address(values), k, double, _address(gathered), k, double, comm),
    )


@njit(cache=True, error_model="numpy")
def gather_fold(values, gathered, n_summed, totals, worst, mpi):
    """:func:`gather`, then :func:`md.distributed._domain_kernels.fold_gathered` of it: the one
    reduction of a force evaluation in one call. Returns 0, or the MPI error code."""
    code = gather(values, gathered, mpi)
    if code == 0:
        fold_gathered(gathered, n_summed, totals, worst)
    return code


@njit(cache=True, error_model="numpy")
def maximum(values, out, mpi):
    """``out`` = the largest of every rank's ``values`` (k,), element by element (MPI's
    all-reduce with MPI_MAX: exact in any order). Returns 0, or the MPI error code."""
    comm, double, largest, allreduce = mpi[0], mpi[1], mpi[2], mpi[7]
    k = np.int32(values.shape[0])
    return c_call(allreduce, (_address(values), _address(out), k, double, largest, comm))
