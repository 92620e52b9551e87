"""The ranks of a decomposed run: how many a launcher started, the communicator's
operations (:class:`MPIRanks`, over mpi4py), the clock of their communication, and
:func:`agree`, which makes every rank raise the same error.

Reductions add in rank order on every rank (an all-gather, then a sum), so all
ranks hold the same bits and a run on P ranks is deterministic. mpi4py is not
imported unless a launcher started more than one process (:func:`mpi_ranks`).
"""

from __future__ import annotations

import atexit
import ctypes
import logging
import math
import os
import time

import numpy as np
from numpy.typing import NDArray

from md._files import OutputBusyError
from md.distributed._domain_kernels import fold_gathered
from md.distributed._mpi_kernels import STATUS_WORDS, gather, gather_fold, maximum
from md.errors import (
    CheckpointError,
    ConfigError,
    ConvergenceError,
    DecompositionError,
    NonFiniteError,
    SimulationError,
    TrajectoryError,
)

logger = logging.getLogger(__name__)

#: Environment variables in which launchers give the number of processes they started
#: (MPICH's and Intel MPI's hydra, Slurm's srun with PMI, Open MPI).
SIZE_VARIABLES = ("PMI_SIZE", "OMPI_COMM_WORLD_SIZE", "SLURM_STEP_NUM_TASKS")


def launched_ranks() -> int:
    """How many processes the MPI launcher started this one among (1 without a launcher)."""
    return launched_ranks_in(os.environ)


def in_rank_order(gathered: NDArray[np.float64]) -> NDArray[np.float64]:
    """The rows of ``gathered`` (one per rank) added in rank order."""
    total = gathered[0].copy()
    for rank in range(1, gathered.shape[0]):
        total += gathered[rank]
    return total


def gather_folded(ranks, values, n_summed: int, totals, worst) -> None:
    """Every rank's ``values`` (k,) gathered, ``totals`` = their first ``n_summed`` added in
    rank order and ``worst`` = the others' largest over the ranks
    (:func:`md.distributed._domain_kernels.fold_gathered`): in one compiled call that
    makes the all-gather itself where ``ranks`` has compiled MPI calls, else through
    ``ranks.gather_values``. Collective; on the ranks' clock."""
    compiled = ranks.compiled if isinstance(ranks, MPIRanks) else None
    if compiled is None:
        fold_gathered(ranks.gather_values(values), n_summed, totals, worst)
        return
    with ranks.clock:
        gathered = np.empty((ranks.n_ranks, values.shape[0]))
        compiled.check(gather_fold(values, gathered, n_summed, totals, worst, compiled.calls))


def ranks_per_node(ranks) -> int:
    """Ranks the launcher started on this node (they share its cores), else all of them."""
    for name in ("MPI_LOCALNRANKS", "OMPI_COMM_WORLD_LOCAL_SIZE", "SLURM_NTASKS_PER_NODE"):
        value = os.environ.get(name, "")
        if value.isdigit() and int(value) > 0:
            return int(value)
    return ranks.n_ranks


#: What each MPI library reads to make a waiting rank give up its core, and the value
#: (MPICH and Intel MPI: ``MPIR_CVAR_ENABLE_HEAVY_YIELD``, sched_yield in its progress
#: loop; Open MPI: ``mpi_yield_when_idle``), read when MPI starts.
YIELD_VARIABLES = {"MPIR_CVAR_ENABLE_HEAVY_YIELD": "1", "OMPI_MCA_mpi_yield_when_idle": "1"}


def yield_when_oversubscribed(environ=None, cores: int | None = None) -> bool:
    """Before MPI starts: if the launcher started more ranks on this node than this process
    may use cores (``cores``, else its CPU affinity), tell the MPI library to yield the
    core while a rank waits (:data:`YIELD_VARIABLES`, in ``environ``, else
    ``os.environ``; a variable the user set is left as it is). Returns whether it did.

    MPI libraries poll while a rank waits for a message, which is fastest when every
    rank has a core of its own; with fewer cores the polling ranks hold them for a
    scheduler time slice while the rank they wait for cannot run, and every exchange
    of a step costs about that (the 1152-atom melt on 3 ranks on 2 cores: see
    ``benchmarks/README.md``). A process-wide setting: the ``md`` command's entry
    calls it (``md.cli.main``), never ``import md``.
    """
    environ = os.environ if environ is None else environ
    if launched_ranks_in(environ) <= 1:
        return False
    local = 0
    for name in ("MPI_LOCALNRANKS", "OMPI_COMM_WORLD_LOCAL_SIZE", "SLURM_NTASKS_PER_NODE"):
        value = environ.get(name, "")
        if value.isdigit() and int(value) > 0:
            local = int(value)
            break
    if cores is None:
        try:
            cores = len(os.sched_getaffinity(0))
        except AttributeError:  # (os.sched_getaffinity exists on Linux only)
            cores = os.cpu_count() or 1
    if not local or local <= (cores or 1):
        return False
    for name, value in YIELD_VARIABLES.items():
        environ.setdefault(name, value)
    return True


def launched_ranks_in(environ) -> int:
    """:func:`launched_ranks` as ``environ`` gives it."""
    for name in SIZE_VARIABLES:
        value = environ.get(name)
        if value:
            try:
                return max(1, int(value))
            except ValueError:
                continue
    return 1


def launch_rank() -> int:
    """This process's rank as the launcher's environment gives it (0 without a launcher);
    readable before MPI starts, for deciding who prints."""
    for name in ("PMI_RANK", "OMPI_COMM_WORLD_RANK", "SLURM_PROCID"):
        value = os.environ.get(name, "")
        if value.isdigit():
            return int(value) if launched_ranks() > 1 else 0
    return 0


def on_root(ranks, value_of):
    """``value_of()`` as rank 0 computes it, on every rank (only rank 0 calls it); just
    ``value_of()`` without ranks."""
    if ranks is None:
        return value_of()
    return ranks.broadcast(value_of() if ranks.rank == 0 else None)


def mpi_ranks() -> MPIRanks | None:
    """The ranks of this run when a launcher started several processes, else None.

    Imports mpi4py only then: with one process (no launcher, or ``mpiexec -n
    1``) nothing changes and nothing is imported.

    Raises
    ------
    RuntimeError
        If a launcher started several processes but mpi4py is not installed.
    """
    if launched_ranks() <= 1:
        return None
    try:
        from mpi4py import MPI  # heavy optional dependency: only decomposed runs load MPI
    except ImportError:
        raise RuntimeError(
            f"this process is one of {launched_ranks()} that an MPI launcher started, but "
            "mpi4py is not installed, so they cannot share one system: pip install "
            "'leapmd[mpi]' (or run without mpiexec)"
        ) from None
    comm = MPI.COMM_WORLD
    return MPIRanks(comm) if comm.Get_size() > 1 else None


class CommClock:
    """Wall time spent communicating [s]: every collective call, message and its packing
    runs inside ``with clock:``; a section inside another counts once.

    Examples
    --------
    >>> clock = CommClock()
    >>> with clock:
    ...     with clock:  # nested: not counted twice
    ...         pass
    >>> clock.seconds >= 0.0
    True
    """

    def __init__(self) -> None:
        self.seconds = 0.0
        self._depth = 0
        self._start = 0.0

    def __enter__(self) -> CommClock:
        if self._depth == 0:
            self._start = time.perf_counter()
        self._depth += 1
        return self

    def __exit__(self, *exc) -> None:
        self._depth -= 1
        if self._depth == 0:
            self.seconds += time.perf_counter() - self._start


class MPIRanks:
    """An MPI communicator as a decomposed run uses it (an :class:`md.parallel.Reductions`).

    Sums are all-gathered and added in rank order, so every rank holds the
    same bits; maxima use MPI's reduction (exact in any order). Every call is
    timed on ``clock`` (a :class:`CommClock`; :meth:`exchange_kept` within its
    caller's section), which the run's summary reports as its "comm" section.
    """

    def __init__(self, comm, compiled: bool = True) -> None:
        from mpi4py import MPI  # heavy optional dependency: only decomposed runs load MPI

        self._compiled_wanted = bool(compiled)
        self.comm = comm
        self.rank = comm.Get_rank()
        self.n_ranks = comm.Get_size()
        self.clock = CommClock()
        self._max = MPI.MAX
        self._double = MPI.DOUBLE
        self._status = MPI.Status()

    @property
    def comm(self):
        """The mpi4py communicator. Setting it also sets :attr:`compiled`: the compiled
        kernels' calls into MPI over it (None for anything but an mpi4py intracommunicator,
        or where ``compiled=False`` was asked: then the halo and reductions go through
        mpi4py)."""
        return self._comm

    @comm.setter
    def comm(self, comm) -> None:
        self._comm = comm
        self.compiled = compiled_mpi(comm) if self._compiled_wanted else None

    def sum(self, values: NDArray[np.float64]) -> NDArray[np.float64]:
        with self.clock:
            return in_rank_order(self.gather_values(values))

    def gather_values(self, values: NDArray[np.float64]) -> NDArray[np.float64]:
        """Every rank's ``values`` (k,), as a (P, k) array on every rank."""
        with self.clock:
            values = np.ascontiguousarray(values, dtype=np.float64).ravel()
            gathered = np.empty((self.n_ranks, values.size))
            if self.compiled is not None:
                self.compiled.check(gather(values, gathered, self.compiled.calls))
            else:
                self.comm.Allgather(values, gathered)
            return gathered

    def max(self, values: NDArray[np.float64]) -> NDArray[np.float64]:
        with self.clock:
            values = np.ascontiguousarray(values, dtype=np.float64).ravel()
            out = np.empty_like(values)
            if self.compiled is not None:
                self.compiled.check(maximum(values, out, self.compiled.calls))
            else:
                self.comm.Allreduce(values, out, op=self._max)
            return out

    def exchange(self, send, dest: int, receive, source: int, tag: int) -> None:
        """Send ``send`` to ``dest`` while receiving ``receive`` from ``source``."""
        with self.clock:
            self.comm.Sendrecv(send, dest, tag, receive, source, tag)

    def messages(self, sends, receives) -> Messages:
        """Persistent messages (MPI's Send_init and Recv_init): ``sends`` and ``receives``
        lists of (buffer, rank, tag), the buffers kept as they are between
        :meth:`Messages.run` calls (which send their contents and fill the receives)."""
        from mpi4py import MPI  # heavy optional dependency: only decomposed runs load MPI

        requests = [self.comm.Recv_init(buffer, rank, tag) for buffer, rank, tag in receives]
        requests += [self.comm.Send_init(buffer, rank, tag) for buffer, rank, tag in sends]
        messages = Messages(requests, self.clock, MPI.Prequest.Startall, MPI.Request.Waitall)
        if not _LIVE.registered:
            # freed before mpi4py's own exit handler (registered earlier: it runs later)
            # ends MPI, which warns of every persistent request still held
            atexit.register(_free_live)
            _LIVE.registered = True
        _LIVE.held.add(messages)
        return messages

    def exchange_rows(self, rows, dest: int, source: int, tag: int) -> NDArray[np.float64]:
        """Send the rows of an (n, k) float64 array to ``dest``; return those from ``source``."""
        return self.exchange_many([(rows, dest, source, tag)])[0]

    def exchange_kept(self, rows, dest: int, source: int, tag: int, kept: dict, name) -> NDArray:
        """:meth:`exchange_rows` of C-contiguous float64 ``rows``, received into memory kept in
        ``kept`` under ``name`` (grown when short; the rows it returns are good until the next
        call with that name): no array made, no list (a build's migration and ghost sweep).
        Called inside a section of the ranks' clock (a build's), it opens none of its own."""
        comm, status = self._comm, self._status
        request = comm.Isend(rows, dest, tag)
        message = comm.Mprobe(source, tag, status)
        width = rows.shape[1]
        count = status.Get_count(self._double) // width if width else 0
        held = kept.get(name)
        if held is None or held.shape[0] < count or held.shape[1] != width:
            held = kept[name] = np.empty((count + count // 4 + 16, width))
        received = held[:count]
        message.Recv(received)
        request.Wait()
        return received

    def exchange_many(self, exchanges) -> list[NDArray[np.float64]]:
        """:meth:`exchange_rows` for each of ``exchanges`` ((rows, dest, source, tag)), all
        in flight together: the rows received, in their order."""
        with self.clock:
            # one message each way: the arriving rows' count is read off the message
            # (MPI's matched probe), not sent ahead of it
            sending = [
                self.comm.Isend(np.ascontiguousarray(rows, dtype=np.float64), dest, tag)
                for rows, dest, _, tag in exchanges
            ]
            status = self._status
            out = []
            for rows, _, source, tag in exchanges:
                message = self.comm.Mprobe(source, tag, status)
                width = rows.shape[1]
                count = status.Get_count(self._double)
                received = np.empty((count // width if width else 0, width))
                message.Recv(received)
                out.append(received)
            for request in sending:
                request.Wait()
            return out

    def all_objects(self, value) -> list:
        """Every rank's ``value`` (picklable), in rank order."""
        with self.clock:
            return self.comm.allgather(value)

    def broadcast(self, value, root: int = 0):
        """Rank ``root``'s ``value`` on every rank."""
        with self.clock:
            return self.comm.bcast(value, root=root)

    def gather_rows(self, rows) -> NDArray[np.float64] | None:
        """On rank 0, every rank's rows (n_r, k) stacked in rank order; None elsewhere."""
        with self.clock:
            rows = np.ascontiguousarray(rows, dtype=np.float64)
            width = rows.shape[1]
            counts = self.comm.gather(rows.size, root=0)
            if self.rank != 0:
                self.comm.Gatherv(rows, None, root=0)
                return None
            out = np.empty((sum(counts) // width if width else 0, width))
            displacements = np.concatenate([[0], np.cumsum(counts[:-1])]).astype(np.int64)
            self.comm.Gatherv(rows, [out, counts, displacements, self._double], root=0)
            return out

    def abort(self, code: int = 1, message: str | None = None) -> None:
        """End every rank at once (for an error one rank cannot share with the others),
        ``message`` logged first (critical) and given a moment to reach the launcher."""
        if message is not None:
            logger.critical("%s", message)
            held, chain = [logging.lastResort], logger
            while chain is not None:  # the handlers of this logger and of those above it
                held += chain.handlers
                chain = chain.parent
            for handler in held:
                if handler is not None:
                    handler.flush()
            time.sleep(0.5)  # (the launcher forwards it before MPI ends the ranks)
        self.comm.Abort(code)


class CompiledMPI:
    """What the compiled kernels of :mod:`md.distributed._mpi_kernels` need to call MPI over
    a communicator themselves: ``calls``, an int64 array (the handles of the communicator,
    MPI_DOUBLE and MPI_MAX, then the addresses of MPI_Isend, MPI_Irecv, MPI_Wait,
    MPI_Allgather and MPI_Allreduce) passed to them (an array: a tuple of 8 integers cost
    numba's dispatch 3-4 us a call to type).

    MPICH's handles are C ints, Open MPI's pointers: an int64 carries either (a C int
    argument is the low half of its register or stack slot in the x86-64 and AArch64
    calling conventions), and each request has an 8-byte slot of its own, where an
    MPI_Request of either kind fits, waited for alone (MPI_Wait), so no size of an MPI
    type is needed."""

    def __init__(self, calls: NDArray[np.int64]) -> None:
        self.calls = calls

    @staticmethod
    def slots(n: int) -> NDArray[np.int64]:
        """Slots for ``n`` requests and a status, for one kernel's messages."""
        return np.zeros(n + STATUS_WORDS, dtype=np.int64)

    @staticmethod
    def check(code: int) -> None:
        """Raise mpi4py's exception for a kernel's non-zero MPI error code."""
        if code != 0:
            from mpi4py import MPI  # (loaded already: a communicator exists)

            raise MPI.Exception(int(code))


#: The MPI functions the compiled kernels call, in the order of ``CompiledMPI.calls``.
COMPILED_CALLS = ("MPI_Isend", "MPI_Irecv", "MPI_Wait", "MPI_Allgather", "MPI_Allreduce")


def compiled_mpi(comm) -> CompiledMPI | None:
    """The :class:`CompiledMPI` of an mpi4py intracommunicator ``comm`` (None for other
    objects, or where the MPI library's functions cannot be found through mpi4py's)."""
    from mpi4py import MPI  # heavy optional dependency: only decomposed runs load MPI

    if not isinstance(comm, MPI.Intracomm):
        return None
    try:
        library = ctypes.CDLL(MPI.__file__)  # (its symbols include the MPI library's)
        addresses = [ctypes.cast(library[name], ctypes.c_void_p).value for name in COMPILED_CALLS]
    except (OSError, AttributeError):
        return None
    handles = [ctypes.c_int64(value.handle).value for value in (comm, MPI.DOUBLE, MPI.MAX)]
    return CompiledMPI(np.array([*handles, *addresses], dtype=np.int64))


class Messages:
    """A set of persistent messages (:meth:`MPIRanks.messages`): :meth:`run` starts them all
    and waits for them (timed on the ranks' clock); :meth:`free` releases them."""

    def __init__(self, requests: list, clock: CommClock, start_all, wait_all) -> None:
        self.requests = requests
        self.clock = clock
        self._start_all = start_all
        self._wait_all = wait_all

    def run(self) -> None:
        if not self.requests:
            return
        with self.clock:
            self._start_all(self.requests)
            self._wait_all(self.requests)

    def free(self) -> None:
        for request in self.requests:
            request.Free()
        self.requests = []
        _LIVE.held.discard(self)


class _Live:
    """The Messages not freed yet (freed at exit, before MPI ends), and whether that is
    registered."""

    held: set = set()
    registered = False


_LIVE = _Live


def _free_live() -> None:
    for messages in list(_LIVE.held):
        messages.free()


# ------------------------------------------------------------------ agreement
def agree(ranks, error: BaseException | None) -> None:
    """Raise on every rank the error of the lowest rank that has one (a collective call).

    That rank raises its error as it is; the others raise one of the same
    family (:class:`SimulationError`, :class:`ConvergenceError`, the
    :class:`NonFiniteError` kinds, ``OSError``, else ``RuntimeError``) with
    the same message, so every rank reports the same failure and none is left
    waiting for the others.
    """
    if error is None:
        report = None
    else:  # the step only for the families whose rebuilt errors name it (they all have one)
        step = error.step if isinstance(error, SimulationError | ConvergenceError) else 0
        report = (_family(error), str(error), step)
    for rank, got in enumerate(ranks.all_objects(report)):
        if got is None:
            continue
        if rank == ranks.rank:
            raise error
        raise _rebuilt(*got)


def _family(error: BaseException) -> str:
    for name, kind in _FAMILIES:
        if isinstance(error, kind):
            return name
    return "runtime"


_FAMILIES = (
    ("simulation", SimulationError),
    ("convergence", ConvergenceError),
    ("decomposition", DecompositionError),
    ("nonfinite", NonFiniteError),
    ("config", ConfigError),
    ("checkpoint", CheckpointError),
    ("trajectory", TrajectoryError),
    ("busy", OutputBusyError),
    ("os", OSError),
)


def _rebuilt(family: str, message: str, step: int) -> BaseException:
    """An error of ``family`` whose text is ``message`` (SimulationError and ConvergenceError
    prefix theirs with the step; here the message already has it)."""
    if family == "simulation":
        error = SimulationError(step, "")
    elif family == "convergence":
        error = ConvergenceError(step, math.nan, message)
    else:
        return dict(_FAMILIES).get(family, RuntimeError)(message)
    error.args = (message,)
    return error
