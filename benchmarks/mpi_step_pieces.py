"""One decomposed step between list builds, piece by piece (issue 69).

    mpiexec -n 2 python benchmarks/mpi_step_pieces.py               # 2000 steps, a minute
    mpiexec -n 2 python benchmarks/mpi_step_pieces.py --steps 4000 --profiled 300
    mpiexec -n 2 python benchmarks/mpi_step_pieces.py --ab --blocks 21   # fused on / off
    mpiexec -n 2 python benchmarks/mpi_step_pieces.py --cells 6,6,4 --ab-kept   # 576 atoms
    mpiexec -n 2 python benchmarks/mpi_step_pieces.py --ab-direct   # the direct pair call

On the 1152-atom LJ melt (``examples/lj_melt.toml`` on 8 x 6 x 6 cells, two bricks along
x, as ``mpi_scaling.py`` runs it; ``--cells`` for others), velocity Verlet, no observers:
the run loop's step (a step start, ``integrator.step``) taken apart. Each piece's own
thread CPU time and wall time a step (the pieces nested in it left out, so the pieces add
up to the step), medians over the steps that made no list build (a step start that
migrates, or a rebuild forced inside a step, is left out); then, over ``--profiled`` more
such steps under a profiler, each piece's Python calls, mpi4py calls and numpy
allocations a step (numba's own allocations are not counted), and the Python functions
called most a step.

The pieces: the step start (``_stopping``: the stop and migration decision, the step
start's copy, ``step_begins``), velocity Verlet's own lines, the force field's fused
step (``verlet_step``: its own lines, its first compiled call ``step_out`` and its second,
``gather_reverse_kick``: the all-gather, its fold, the reverse sweep and the kick; where it
does not serve the step, or in the code before it, velocity Verlet's kick + drift and
closing kick and the calls below), the force field's cache and in-step decision (``compute``,
``_result``, ``_in_step_decision``), ``_evaluate``'s own lines (the reduction's values,
the error checks, the ``ForceResult``), ``refresh``'s own lines with ``allowance``, the
displacement pass ``moved_since`` (compiled; it also writes the owned rows), the halo
update's own lines (``Domain.update``: the cell key, the images' shift) and its compiled
sweep (``halo_forward``, the messages inside), the local force field (its Python, the
list's check, the pair kernel's call, which ``verlet_step`` makes itself where the local
list holds: ``ForceField.pair_call``), the all-gather and fold (``gather_folded``),
the last build's settling, the reverse's own lines and its compiled sweep
(``halo_reverse``), and ``end_step``.

With ``--ab``, instead: the fused step on and off (``verlet_step`` answering 0, "nothing
done": the step made of ``compute`` and the kicks, as before it) in alternating blocks of
200 steps of one launch, build steps included; each rank's thread CPU time and wall time a
step, medians over the blocks, and on/off per block (median). With ``--ab-kept``, the same
for the pair frame's kept call over a list of atom indices (``PairPotential._atom_call``,
which a rank's O(N^2) local list takes: the 576-atom melt, ``--cells 6,6,4``, whose 6.7
sigma z edge is too thin for cells) on and off (off: forgotten before each pair call, so
every call takes the slow path, as before it; one Python call more a step than that code).
With ``--ab-direct``, the same for the fused step's own call of the local pair kernel
(``ForceField.pair_call``) on and off (off: ``pair_call`` answering None, so the local
``compute`` makes every step's pair call, as before it), with each rank's thread CPU
outside its ``CommClock`` sections too ("own", as ``mpi_scaling.py`` measures it) and the
median difference per block pair. ``--cells`` sets the melt's fcc cells (8,6,6: 1152 atoms).

Prints the CPU model and vector ISA. A wrapped call costs more than a bare one (printed:
most of it lands in the own time of the piece it is nested in), so the pieces' sum is
above a bare step's time, also printed (the same steps without the wrappers, the
median of blocks alternating with the wrapped ones). On a shared machine the absolute
times move with the load; read the shares.
"""

from __future__ import annotations

import argparse
import collections
import json
import statistics
import sys
import time
import types
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from _machine import machine_line  # noqa: E402
from _mpi_worker import _count_own_cpu, _simulation  # noqa: E402  (the melt, decomposed)
from mpi_build_path import (  # noqa: E402
    CELLS,
    _CountedAllocations,
    _CountedMPI,
    _Pieces,
    _wrapper_cost,
)

#: The local pair kernel's piece: through ``energy_forces``, or the call ``verlet_step``
#: makes itself where the local list holds (``ForceField.pair_call``).
PAIR = "pair kernel (energy_forces or direct)"
#: The pieces of a step, in the order they run (their own time each).
PIECES = (
    "step start (_stopping)",
    "VelocityVerlet.step own lines",
    "DistributedForceField.verlet_step own lines",
    "step_out: kick, drift, moves, halo sweep (compiled)",
    "kick + drift (compiled)",
    "compute/_result: cache, in-step decision",
    "_evaluate own lines (values, checks, ForceResult)",
    "refresh own lines + allowance",
    "moved_since (compiled, owned copy)",
    "Domain.update own lines",
    "halo sweep (compiled halo_forward)",
    "local ForceField.compute own lines",
    "local list check (NeighborList.update)",
    PAIR,
    "all-gather + fold (gather_folded)",
    "all-gather + fold (compiled gather_fold)",
    "_settle_build",
    "Domain.reverse own lines",
    "reverse sweep (compiled halo_reverse)",
    "gather_reverse_kick: all-gather, fold, reverse, kick (compiled)",
    "closing kick (compiled)",
    "end_step",
)


class _StepPieces(_Pieces):
    """:class:`mpi_build_path._Pieces` that also counts, per piece, the wrapped calls made
    directly inside it (each adds about a wrapper's cost to that piece's own time, which
    ``corrected`` takes off)."""

    def __init__(self) -> None:
        super().__init__()
        self.reset()

    def reset(self) -> None:
        self.wall = dict.fromkeys(PIECES, 0.0)
        self.cpu = dict.fromkeys(PIECES, 0.0)
        self.children = dict.fromkeys(PIECES, 0)
        self.counts = {name: [0, 0, 0] for name in PIECES}

    def wrap(self, owner, attribute: str, name) -> None:
        super().wrap(owner, attribute, name)
        timed = getattr(owner, attribute)
        pieces = self

        def counted(*args, **kwargs):
            if pieces.stack:
                pieces.children[pieces.stack[-1][0]] += 1
            return timed(*args, **kwargs)

        setattr(owner, attribute, counted)


class _Switch:
    """The wrappers ``_Pieces.wrap`` sets, which can be taken off and put back."""

    def __init__(self, pieces: _Pieces) -> None:
        self.pieces, self.held = pieces, []

    def wrap(self, owner, attribute: str, name: str) -> None:
        own = attribute in vars(owner)
        original = vars(owner)[attribute] if own else None
        self.pieces.wrap(owner, attribute, name)
        self.held.append((owner, attribute, own, original, getattr(owner, attribute)))

    def off(self) -> None:
        for owner, attribute, own, original, _ in self.held:
            if own:
                setattr(owner, attribute, original)
            else:
                delattr(owner, attribute)

    def on(self) -> None:
        for owner, attribute, _, _, wrapped in self.held:
            setattr(owner, attribute, wrapped)


def _wrap_step(pieces: _Switch, sim) -> None:
    """Wrap the calls of a decomposed velocity Verlet step (on their instances, or the
    module globals the calling modules look up) into ``pieces``."""
    import integrators.velocity_verlet as vv
    import md.distributed.forcefield as dff
    import md.distributed.halo as halo

    forcefield, domain = sim.forcefield, sim.forcefield.domain
    local = forcefield.local
    integrator = sim.integrator
    wrapped = (
        (sim, "_stopping", "step start (_stopping)"),
        (integrator, "step", "VelocityVerlet.step own lines"),
        (forcefield, "verlet_step", "DistributedForceField.verlet_step own lines"),
        (dff, "step_out", "step_out: kick, drift, moves, halo sweep (compiled)"),
        (vv, "kick_drift_by_mass", "kick + drift (compiled)"),
        (vv, "kick_by_mass", "closing kick (compiled)"),
        (forcefield, "compute", "compute/_result: cache, in-step decision"),
        (forcefield, "_result", "compute/_result: cache, in-step decision"),
        (forcefield, "_in_step_decision", "compute/_result: cache, in-step decision"),
        (forcefield, "_evaluate", "_evaluate own lines (values, checks, ForceResult)"),
        (forcefield, "_attempt", "_evaluate own lines (values, checks, ForceResult)"),
        (forcefield, "_finish", "_evaluate own lines (values, checks, ForceResult)"),
        (forcefield, "_shared", "_evaluate own lines (values, checks, ForceResult)"),
        (forcefield, "refresh", "refresh own lines + allowance"),
        (forcefield, "allowance", "refresh own lines + allowance"),
        (dff, "moved_since", "moved_since (compiled, owned copy)"),
        (domain, "update", "Domain.update own lines"),
        (halo, "halo_forward", "halo sweep (compiled halo_forward)"),
        (local, "compute", "local ForceField.compute own lines"),
        (local.neighbor_list, "update", "local list check (NeighborList.update)"),
        *((p, "energy_forces", PAIR) for p in local.potentials),
        (dff, "gather_folded", "all-gather + fold (gather_folded)"),
        (dff, "gather_fold", "all-gather + fold (compiled gather_fold)"),
        (forcefield, "_settle_build", "_settle_build"),
        (domain, "reverse", "Domain.reverse own lines"),
        (halo, "halo_reverse", "reverse sweep (compiled halo_reverse)"),
        (
            dff,
            "gather_reverse_kick",
            "gather_reverse_kick: all-gather, fold, reverse, kick (compiled)",
        ),
        (integrator, "end_step", "end_step"),
    )
    for owner, attribute, name in wrapped:
        if hasattr(owner, attribute):  # (the code before issue 69's fused step lacks some)
            pieces.wrap(owner, attribute, name)
    if hasattr(local, "pair_call"):  # (the pair kernel verlet_step calls itself: timed too)
        handed, timing = local.pair_call, pieces.pieces

        def pair_call(state):
            call = handed(state)
            if call is None:
                return None
            holder = types.SimpleNamespace(kernel=call[0])
            timing.wrap(holder, "kernel", PAIR)
            return (holder.kernel, *call[1:])

        local.pair_call = pair_call


def _one_step(sim) -> bool:
    """One step of the run loop's (its timing lines left out); whether it built a list."""
    builds = sim.forcefield.n_builds
    if sim._stopping():
        raise RuntimeError("the run was asked to stop")
    sim.integrator.step(sim.state, sim.forcefield)
    return sim.forcefield.n_builds != builds


def _bare_blocks(sim, comm, steps: int) -> float:
    """The median wall time a step of ``steps`` unwrapped steps (build steps included)."""
    comm.Barrier()
    start = time.perf_counter()
    for _ in range(steps):
        _one_step(sim)
    return (time.perf_counter() - start) / steps


def time_step_pieces(steps: int, profiled: int, comm, cells=CELLS) -> dict:
    sim = _simulation(cells)
    sim.run(50)  # compiled, and the layout of a run
    block = 100
    bare = [_bare_blocks(sim, comm, block) for _ in range(3)]
    pieces = _StepPieces()
    wrapper = _wrapper_cost()
    switch = _Switch(pieces)
    _wrap_step(switch, sim)
    wall = {name: [] for name in (*PIECES, "step")}
    cpu = {name: [] for name in (*PIECES, "step")}
    corrected = {name: [] for name in (*PIECES, "step")}
    wrapped_blocks, kept, skipped = [], 0, 0
    comm.Barrier()
    block_start = time.perf_counter()
    for k in range(steps):
        pieces.reset()
        start, thread = time.perf_counter(), time.thread_time()
        built = _one_step(sim)
        spent_wall, spent_cpu = time.perf_counter() - start, time.thread_time() - thread
        if built:
            skipped += 1
        else:
            kept += 1
            wall["step"].append(spent_wall)
            cpu["step"].append(spent_cpu)
            nested = sum(pieces.children.values()) + 1  # (the step's own wrapped call)
            corrected["step"].append(spent_cpu - wrapper * nested)
            for name in PIECES:
                wall[name].append(pieces.wall[name])
                cpu[name].append(pieces.cpu[name])
                corrected[name].append(pieces.cpu[name] - wrapper * pieces.children[name])
        if (k + 1) % block == 0:  # the bare steps alternate with the wrapped ones
            wrapped_blocks.append((time.perf_counter() - block_start) / block)
            switch.off()
            bare.append(_bare_blocks(sim, comm, block))
            switch.on()
            comm.Barrier()
            block_start = time.perf_counter()
    # Calls, counted over more steps under a profiler (the build steps' left out).
    ranks = sim.forcefield.ranks
    held = ranks.comm, ranks._status
    functions: collections.Counter = collections.Counter()
    c_calls = [0]
    counted_steps = 0
    totals = {name: [0, 0, 0] for name in PIECES}

    def profile(frame, event, arg) -> None:
        if event == "call":
            if frame.f_code.co_filename not in (_Pieces.wrap.__code__.co_filename, __file__):
                pieces.count(0)
                code = frame.f_code
                functions[f"{Path(code.co_filename).name}:{code.co_name}"] += 1
        elif event == "c_call":
            c_calls[0] += 1

    allocations = _CountedAllocations(pieces)
    ranks._comm, ranks._status = (_CountedMPI(a, pieces) for a in held)
    comm.Barrier()
    try:
        for _ in range(profiled):
            before_counts = {name: list(c) for name, c in pieces.counts.items()}
            before_functions, before_c = collections.Counter(functions), c_calls[0]
            sys.setprofile(profile)
            with allocations:
                built = _one_step(sim)
            sys.setprofile(None)
            if built:  # forget this step's counts
                pieces.counts = before_counts
                functions.clear()
                functions.update(before_functions)
                c_calls[0] = before_c
            else:
                counted_steps += 1
    finally:
        sys.setprofile(None)
        ranks._comm, ranks._status = held
    totals = {name: [c / max(counted_steps, 1) for c in pieces.counts[name]] for name in PIECES}
    return {
        "wrapper": wrapper,
        "kept": kept,
        "skipped": skipped,
        "bare": statistics.median(bare),
        "wrapped": statistics.median(wrapped_blocks),
        "python_calls": sum(functions.values()) / max(counted_steps, 1),
        "c_calls": c_calls[0] / max(counted_steps, 1),
        "functions": [
            (name, count / max(counted_steps, 1)) for name, count in functions.most_common(30)
        ],
        **{
            name: {
                "wall": statistics.median(wall[name]),
                "cpu": statistics.median(cpu[name]),
                "corrected": statistics.median(corrected[name]),
                "calls": totals.get(name),
            }
            for name in wall
        },
    }


def _forgetting(potential):
    """``potential.energy_forces`` with its kept call over atom indices forgotten first."""
    method = type(potential).energy_forces

    def energy_forces(*args, **kwargs):
        potential._atom_call = None
        return method(potential, *args, **kwargs)

    return energy_forces


def time_ab(blocks: int, comm, steps: int = 200, cells=CELLS, what: str = "fused") -> dict:
    """The fused step (``what``: ``"kept"``, the pair frame's kept call over atom indices;
    ``"direct"``, the fused step's own call of the local pair kernel) on and off in
    alternating blocks of ``steps`` (see the docstring)."""
    sim = _simulation(cells)
    sim.run(50)  # compiled, and the layout of a run
    forcefield = sim.forcefield
    if not hasattr(forcefield, "verlet_step"):
        raise SystemExit("--ab needs the fused step (DistributedForceField.verlet_step)")
    local = forcefield.local
    potentials = local.potentials
    if what == "kept" and not all(hasattr(p, "_atom_call") for p in potentials):
        raise SystemExit("--ab-kept needs the kept call over atom indices (_atom_call)")
    if what == "direct" and not hasattr(local, "pair_call"):
        raise SystemExit("--ab-direct needs the direct pair call (ForceField.pair_call)")
    inside = _count_own_cpu(forcefield.ranks.clock)
    spent: dict[str, list] = {f"{n} {k}": [] for n in ("on", "off") for k in ("wall", "cpu", "own")}
    for _ in range(blocks):
        for name in ("on", "off"):
            if name == "off" and what == "kept":
                for potential in potentials:
                    potential.energy_forces = _forgetting(potential)
            elif name == "off" and what == "direct":
                local.pair_call = lambda state: None  # (the local compute every step)
                forcefield.invalidate()  # (the pair call prepared since the build forgotten)
            elif name == "off":
                forcefield.verlet_step = lambda *args: 0  # (nothing done)
            comm.Barrier()
            start, thread, polled = time.perf_counter(), time.thread_time(), inside["cpu"]
            for _ in range(steps):
                _one_step(sim)
            cpu = time.thread_time() - thread
            spent[f"{name} wall"].append((time.perf_counter() - start) / steps)
            spent[f"{name} cpu"].append(cpu / steps)
            spent[f"{name} own"].append((cpu - (inside["cpu"] - polled)) / steps)
            if name == "off" and what == "kept":
                for potential in potentials:
                    del potential.energy_forces  # (the class's method again)
            elif name == "off" and what == "direct":
                del local.pair_call  # (the class's method again)
                forcefield.invalidate()  # (as the off blocks start: the same transition)
            elif name == "off":
                del forcefield.verlet_step  # (the class's method again)
    figures = {key: statistics.median(values) for key, values in spent.items()}
    for kind in ("wall", "cpu", "own"):
        pairs = list(zip(spent[f"on {kind}"], spent[f"off {kind}"], strict=True))
        figures[f"on/off {kind}"] = statistics.median(a / b for a, b in pairs)
        figures[f"on-off {kind}"] = statistics.median(a - b for a, b in pairs)
    return figures


def print_ab(mine: list, comm, blocks: int, cells=CELLS, what: str = "fused") -> None:
    print(machine_line())
    what = {
        "kept": "the kept pair call over atom indices",
        "direct": "the fused step's direct call of the local pair kernel",
    }.get(what, "the fused step")
    print(
        f"{_atoms(cells)}-atom melt on {comm.Get_size()} ranks: {what} on and off, {blocks} "
        "alternating blocks of 200 steps (build steps included), us a step, medians "
        "('own': thread CPU outside the ranks' CommClock sections, as mpi_scaling.py's)"
    )
    print(
        "  rank   on wall  off wall  on/off    on CPU  off CPU  on/off    on own  off own"
        "  on/off  on-off own"
    )
    for rank, f in enumerate(mine):
        print(
            f"  {rank:4d}  {f['on wall'] * 1e6:8.1f}  {f['off wall'] * 1e6:8.1f}  "
            f"{f['on/off wall']:6.3f}  {f['on cpu'] * 1e6:8.1f} {f['off cpu'] * 1e6:8.1f}  "
            f"{f['on/off cpu']:6.3f}  {f['on own'] * 1e6:8.1f} {f['off own'] * 1e6:8.1f}  "
            f"{f['on/off own']:6.3f}  {f['on-off own'] * 1e6:9.1f}"
        )


def _atoms(cells) -> int:
    return 4 * cells[0] * cells[1] * cells[2]


def print_step_pieces(mine: list, comm, cells=CELLS) -> None:
    print(machine_line())
    print(
        f"{_atoms(cells)}-atom melt on {comm.Get_size()} ranks: one step between list builds "
        "taken apart (each piece's own time; medians over the steps, us a step)"
    )
    header = (
        "  piece"
        + " " * 45
        + "".join(f"  r{r} wall  r{r} CPU  r{r} less" for r in range(len(mine)))
        + "  py calls  mpi4py  np allocs"
    )
    print(header)
    for name in (*PIECES, "step"):
        times = "".join(
            f" {rank[name]['wall'] * 1e6:8.1f} {rank[name]['cpu'] * 1e6:8.1f}"
            f" {rank[name]['corrected'] * 1e6:8.1f}"
            for rank in mine
        )
        calls = mine[0][name]["calls"]
        counts = "" if calls is None else "".join(f" {c:8.1f}" for c in calls)
        print(f"  {name:<50}{times}{counts}")
    sums = [sum(rank[name]["corrected"] for name in PIECES) for rank in mine]
    print(
        "  ('less': the CPU time less a wrapper's cost for each wrapped call made directly "
        "in the piece; those medians add up to "
        + " / ".join(f"{s * 1e6:.1f}" for s in sums)
        + " us; steps kept / with a build left out: "
        + ", ".join(f"{rank['kept']} / {rank['skipped']}" for rank in mine)
        + ")"
    )
    print(
        "  a step's wall time, wrapped / bare (median blocks of 100, build steps included): "
        + ", ".join(f"{rank['wrapped'] * 1e6:.1f} / {rank['bare'] * 1e6:.1f}" for rank in mine)
        + " us"
    )
    print(
        f"  (a timed call costs {mine[0]['wrapper'] * 1e6:.2f} us more than a bare one, most of "
        "it in the own time of the piece it is nested in)"
    )
    r0 = mine[0]
    print(
        f"  rank 0, a step: {r0['python_calls']:.1f} Python calls (the wrappers' left out), "
        f"{r0['c_calls']:.1f} calls of C functions from Python; the Python functions called "
        "most:"
    )
    for name, count in r0["functions"]:
        print(f"    {count:6.1f}  {name}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2000, help="timed steps (2000)")
    parser.add_argument("--profiled", type=int, default=200, help="steps counted (200)")
    parser.add_argument("--json", help="write the figures to this file (rank 0)")
    parser.add_argument("--ab", action="store_true", help="the fused step on / off")
    parser.add_argument(
        "--ab-kept", action="store_true", help="the kept pair call over atom indices on / off"
    )
    parser.add_argument(
        "--ab-direct", action="store_true", help="the fused step's direct pair call on / off"
    )
    parser.add_argument("--blocks", type=int, default=21, help="--ab's blocks (21)")
    parser.add_argument(
        "--cells", default=",".join(map(str, CELLS)), help="the melt's fcc cells (8,6,6)"
    )
    args = parser.parse_args(argv)
    cells = tuple(int(c) for c in args.cells.split(","))
    if len(cells) != 3 or min(cells) < 1:
        parser.error(f"--cells takes three positive integers, got {args.cells!r}")
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    import md

    md.keep_freed_memory()  # as `md run` sets a process up
    if args.ab or args.ab_kept or args.ab_direct:
        what = "kept" if args.ab_kept else "direct" if args.ab_direct else "fused"
        mine = comm.gather(time_ab(args.blocks, comm, cells=cells, what=what), root=0)
        if comm.Get_rank() == 0:
            print_ab(mine, comm, args.blocks, cells, what)
            if args.json:
                Path(args.json).write_text(json.dumps(mine, indent=2))
        return 0
    mine = comm.gather(time_step_pieces(args.steps, args.profiled, comm, cells), root=0)
    if comm.Get_rank() == 0:
        print_step_pieces(mine, comm, cells)
        if args.json:
            Path(args.json).write_text(json.dumps(mine, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
