"""Where the mixed-precision MD step goes, phase by phase, and what of it runs in parallel.

Used by ``mixed_precision.py --phases``. The melt's Simulation is built with
``md.parallel.set_threads(T)`` (so every list, kernel and pass splits its work into the
chunks it would use on T threads), then numba is told to use one thread: every
``prange`` then runs its chunks one after the other on the calling thread, whose CPU
time (``time.thread_time``: other processes on a shared machine do not count in it)
is the work of each phase. Library functions are wrapped in timers for that (module
attributes and methods, restored afterwards; nothing in the library changes). A
phase is parallel or serial by how it runs on T threads (``PARALLEL`` below). For the
cluster kernel and the prune, whose chunks carry unequal work, each chunk is also
timed alone on this thread (the list as it ended the run: the kernel's one-chunk
entry given that chunk's rows and window; the prune's rows of that chunk), so the
slowest chunk's share of a parallel phase is measured, not assumed; the other
parallel phases split their atoms evenly and are counted as their work / T.

The estimate of T-thread speed-up is then the Amdahl-type bound
W_1 / (serial work + sum over parallel phases of their slowest chunk), with W_1 the
work of the same steps with one chunk everywhere (the 1-thread run's own chunks);
it leaves out thread wake-ups and memory bandwidth shared between the cores, so a
measured speed-up lies below it.
"""

from __future__ import annotations

import contextlib
import statistics
import time

import lj_melt  # the LAMMPS child (benchmarks/ on the path: run from mixed_precision.py)
import numba
import numpy as np

import integrators.velocity_verlet
import md
import md.forcefield
import md.neighbors.lists
import potentials._kernels as helpers
import potentials._pair_frame
from integrators import VelocityVerlet
from md.parallel import set_threads
from potentials import LennardJones

#: The force field's check of the forces (``all_finite`` threaded; before, serial).
FINITE = "all_finite" if hasattr(md.forcefield, "all_finite") else "_all_finite"
#: Phases that run their chunks on the threads (the rest run on the calling thread).
PARALLEL = {
    "kick + drift",
    "kick",
    "displacement check",
    "cache key copy",
    "cache key compare",
    "relative positions (force)",
    "relative positions (prune)",
    "cluster kernel",
    "chunk sum into atom order",
    "prune kernel",
    "search (whole build)",
    "kick + drift + check + positions",
    "chunk sum + finite check + kick",
}
if FINITE == "all_finite":
    PARALLEL.add("finite check")


class Phases:
    """Inclusive CPU times of the wrapped calls by phase name; exclusive ones derived."""

    def __init__(self) -> None:
        self.cpu: dict[str, float] = {}
        self.calls: dict[str, int] = {}
        self._stack: list[list[float]] = []  # per open call: children's CPU time

    def timed(self, name: str, function):
        def wrapper(*args, **kwargs):
            self._stack.append([0.0])
            start = time.thread_time()
            try:
                return function(*args, **kwargs)
            finally:
                spent = time.thread_time() - start
                children = self._stack.pop()[0]
                self.cpu[name] = self.cpu.get(name, 0.0) + spent - children
                self.calls[name] = self.calls.get(name, 0) + 1
                if self._stack:
                    self._stack[-1][0] += spent

        return wrapper


@contextlib.contextmanager
def _patched(phases: Phases, kept: dict):
    """The library's phase functions wrapped in ``phases``'s timers while the block runs;
    ``kept`` gets the cluster kernels' module and flags (for the chunk timings)."""
    targets = [
        (integrators.velocity_verlet, "kick_drift", "kick + drift"),
        (integrators.velocity_verlet, "kick", "kick"),
        (md.forcefield, FINITE, "finite check"),
        (md.forcefield.ForceField, "_same_key", "cache key compare"),
        (md.neighbors.lists.NeighborList, "update", "list update, the rest"),
        (md.neighbors.lists, "_largest_displacement2", "displacement check"),
        (md.neighbors.lists.NeighborList, "build", "search (whole build)"),
        (md.neighbors.lists.NeighborList, "_prune", "prune, the rest"),
        (md.neighbors.lists, "prune_pairs", "prune kernel"),
        (potentials._pair_frame.PairPotential, "_cluster_energy_forces", "force call, the rest"),
        (potentials._pair_frame.PairPotential, "_run_cluster_call", "force call, the rest"),
        (potentials._pair_frame, "cluster_atom_forces", "chunk sum into atom order"),
        # the mixed step's fused passes (potentials._step_kernels; before: none)
        (potentials._pair_frame.PairPotential, "mixed_verlet_step", "force call, the rest"),
        (potentials._pair_frame, "kick_drift_slots", "kick + drift + check + positions"),
        (potentials._pair_frame, "finish_step", "chunk sum + finite check + kick"),
    ]
    saved = []
    for owner, name, phase in targets:
        if name not in owner.__dict__:  # (before the mixed calls were kept)
            continue
        original = owner.__dict__[name]
        saved.append((owner, name, original))
        setattr(owner, name, phases.timed(phase, original))
    # _key_of is a static method: wrapped as one
    key_of = md.forcefield.ForceField.__dict__["_key_of"]
    saved.append((md.forcefield.ForceField, "_key_of", key_of))
    md.forcefield.ForceField._key_of = staticmethod(phases.timed("cache key copy", key_of.__func__))
    # the relative positions: of the force call or of a prune, told apart by the caller
    relative = md.neighbors.lists.ClusterFrame.relative_positions
    saved.append((md.neighbors.lists.ClusterFrame, "relative_positions", relative))
    in_prune = phases.timed("relative positions (prune)", relative)
    in_force = phases.timed("relative positions (force)", relative)

    def relative_positions(frame, positions, xi, xj):
        open_names = inside[-1] if inside else ""
        return (in_prune if open_names == "prune" else in_force)(frame, positions, xi, xj)

    inside: list[str] = []
    prune = md.neighbors.lists.NeighborList.__dict__["_prune"]

    def marked_prune(self, positions):
        inside.append("prune")
        try:
            return prune(self, positions)
        finally:
            inside.pop()

    md.neighbors.lists.NeighborList._prune = marked_prune
    md.neighbors.lists.ClusterFrame.relative_positions = relative_positions
    original_variant = potentials._pair_frame.variant

    def variant(kernels, entry, **flags):
        kernel = original_variant(kernels, entry, **flags)
        if entry.startswith("cluster_forces"):
            kept["kernels"], kept["flags"] = kernels, flags
            return phases.timed("cluster kernel", kernel)
        return kernel

    saved.append((potentials._pair_frame, "variant", original_variant))
    potentials._pair_frame.variant = variant
    try:
        yield
    finally:
        for owner, name, original in reversed(saved):
            setattr(owner, name, original)


def _melt(cells: int, seed: int = 87287) -> md.State:
    return md.maxwell_boltzmann(md.lattice("fcc", cells, density=0.8442), 3.0, seed=seed)


def _prune_runs(neighbors, outer, state, mark_rows, copy_rows) -> list:
    """The prune's timed runs: each chunk's marks ("prune: rows"), each chunk's copy of
    its kept pairs to their places ("prune: copy", its rows' counts put back first: a
    copy makes them offsets) and the whole prune."""
    from md.neighbors._cluster_prune import prune_pairs

    size = outer.n_pairs
    kept_starts = np.empty(outer.n_clusters + 1, np.int64)
    kept_partners = np.empty(size, np.int32)
    kept_offsets = np.empty((size, 3), np.float32)
    marks = np.empty(size, np.uint8)
    oxi = np.empty(12 * outer.n_clusters, np.float32)
    oxj = np.empty(12 * outer.n_clusters, np.float32)
    outer.relative_positions(state.positions, oxi, oxj)
    reach2 = np.float32((neighbors.list_radius * (1.0 + 1e-5)) ** 2)
    lists = (outer.starts, outer.partners, outer.offsets)
    kept = (kept_partners, kept_offsets)
    whole = (*lists, outer.bounds, oxi, oxj, reach2, kept_starts, *kept, marks)
    prune_pairs(*whole)
    places = kept_starts.copy()
    counts = np.diff(kept_starts)
    runs = []
    for c in range(len(outer.bounds) - 1):
        c0, c1 = int(outer.bounds[c]), int(outer.bounds[c + 1])

        def mark(c0=c0, c1=c1):
            mark_rows(*lists, c0, c1, oxi, oxj, reach2, marks, kept_starts)

        def copy(c0=c0, c1=c1, k=int(places[c0])):
            kept_starts[c0 + 1 : c1 + 1] = counts[c0:c1]
            copy_rows(*lists, c0, c1, marks, k, kept_starts, *kept)

        runs += [("prune: rows", c, mark), ("prune: copy", c, copy)]
    runs.append(("prune kernel, whole", 0, lambda: prune_pairs(*whole)))
    return runs


def _chunk_times(sim: md.Simulation, kept: dict, repeats: int) -> dict[str, list[float]]:
    """CPU seconds of each chunk of the cluster kernel and of the prune's rows, alone on
    this thread, over the list as it stands (median of ``repeats``, taking turns)."""
    neighbors = sim.forcefield.neighbor_list
    clusters = neighbors.clusters
    potential = sim.forcefield.potentials[0]
    state = sim.state
    kernels, flags = kept["kernels"], dict(kept["flags"])
    flags["with_virial"] = False
    serial = original_variant_of(kernels, "cluster_forces", flags)
    n_types = max(state.n_types, 1)
    table = potential._cached_tables(n_types, np.float32)
    n_clusters = clusters.n_clusters
    xi = np.empty(12 * n_clusters, np.float32)
    xj = np.empty(12 * n_clusters, np.float32)
    clusters.relative_positions(state.positions, xi, xj)
    slot_types = np.zeros(4 * n_clusters, np.int32)
    room = clusters.window_clusters
    buffers = np.empty(12 * room)
    j_sums = np.zeros(48 * room, np.float32)
    j_counts = np.zeros(room, np.int32)
    forces = np.empty((state.n_atoms, 3))
    energies, virials = np.empty(1), np.empty((1, 9))
    bounds, windows = clusters.bounds, clusters.windows
    mode = flags["mode"]

    def kernel_chunk(c):
        lists = (
            clusters.starts,
            clusters.partners,
            clusters.offsets.reshape(-1),
            np.array([bounds[c], bounds[c + 1]], np.int64),
            np.array([[windows[c, 0], windows[c, 1], 0]], np.int64),
        )
        with potentials._pair_frame.slp_vectorising():
            serial(
                xi,
                xj,
                lists,
                slot_types,
                n_types,
                table,
                mode,
                potential.data,
                False,
                flags["single"],
                buffers,
                j_sums,
                j_counts,
                clusters.atom,
                forces,
                energies,
                virials,
            )

    outer = neighbors.outer_clusters
    runs = [("cluster kernel", c, lambda c=c: kernel_chunk(c)) for c in range(len(bounds) - 1)]
    # the sum into atom order's runs: by their work where cluster_sum_runs splits it
    # (before: equal slot counts)
    slots = len(clusters.atom)
    n_runs = len(bounds) - 1
    if hasattr(helpers, "cluster_sum_runs"):
        first = 4 * helpers.cluster_sum_runs(windows, slots // 4, n_runs)
    else:
        first = [r * slots // n_runs for r in range(n_runs + 1)]
    big = np.zeros(12 * room)
    for r in range(n_runs):
        runs.append(
            (
                "chunk sum into atom order",
                r,
                lambda a=int(first[r]), b=int(first[r + 1]): helpers._slot_forces(
                    big, clusters.atom, windows, forces, a, b
                ),
            )
        )
    if outer is not None:
        try:  # the prune's two passes, marks then copies (before: one pass, then a move)
            from md.neighbors._cluster_prune import _copy_rows, _mark_rows
        except ImportError:  # (a tree before: its prune's chunks not timed)
            _copy_rows = _mark_rows = None
        if _mark_rows is not None:
            runs += _prune_runs(neighbors, outer, state, _mark_rows, _copy_rows)
    for _, _, run in runs:
        run()  # compile or load
    times: dict[tuple[str, int], list[float]] = {(name, c): [] for name, c, _ in runs}
    # the sum's runs in a loop of their own: in the step they follow the kernel, its
    # buffers still in cache, not the other phases' passes
    loops = (
        [r for r in runs if r[0] != "chunk sum into atom order"],
        [r for r in runs if r[0] == "chunk sum into atom order"],
    )
    for group in loops:
        for repeat in range(repeats):
            # in turns forwards and backwards: the first run after other work finds
            # colder caches (the kernel's first chunk took 1.04 of the second's first,
            # 0.96 of it second)
            for name, c, run in group if repeat % 2 == 0 else group[::-1]:
                start = time.thread_time()
                run()
                times[name, c].append(time.thread_time() - start)
    found: dict[str, list[float]] = {}
    for (name, _c), values in times.items():
        found.setdefault(name, []).append(statistics.median(values))
    return found


def original_variant_of(kernels, entry: str, flags: dict):
    return potentials._pair_frame.variant(kernels, entry, **flags)


def profile(cells: int, threads: int, steps: int, warm: int, repeats: int, block: int = 10):
    """The phases' CPU times over ``steps`` steps of the mixed melt in two Simulations,
    one with its work in one chunk, one in ``threads`` chunks, both run on one thread
    (after ``warm`` steps untimed), taking turns in blocks of ``block`` steps (a loaded
    machine slows both alike); then the ``threads``-chunk list's chunks' own times
    (``_chunk_times``, ``repeats`` each). Returns the two Phases, that Simulation and
    the chunk times."""
    sims, phases, kept = {}, {}, {}
    for count in (1, threads):
        set_threads(count)  # the chunks: counted from this at every build and prune
        sims[count] = md.Simulation(
            _melt(cells), [LennardJones(cutoff=2.5)], VelocityVerlet(0.005), precision="mixed"
        )
        sims[count].run(warm)  # compiles (on the threads asked for)
        phases[count] = Phases()
    try:
        for _ in range(max(steps // block, 1)):
            for count, sim in sims.items():
                set_threads(count)
                numba.set_num_threads(1)
                for potential in sim.forcefield.potentials:  # set up again, timed
                    if hasattr(potential, "_cluster_calls"):
                        potential._cluster_calls = [None, None]
                with _patched(phases[count], kept):
                    phases[count].timed("Python and the rest", sim.run)(block)
        set_threads(threads)
        numba.set_num_threads(1)
        chunks = _chunk_times(sims[threads], kept, repeats)
    finally:
        set_threads(threads)
    return phases[1], phases[threads], sims[threads], chunks


def report(cells: int, threads: int, steps: int, warm: int, repeats: int) -> None:
    """Print each phase's share of the step's work with one chunk and with ``threads``
    chunks, the slowest chunk of the uneven phases and the Amdahl bound on the speed-up."""
    steps = max(steps // 10, 1) * 10
    # as `md run` sets a process up (md._memory): without it each step's fresh force array
    # page-faulted (130 faults a step), counted in whichever phase first wrote it
    md.keep_freed_memory()
    one, many, sim, chunks = profile(cells, threads, steps, warm, repeats)
    total_one = sum(one.cpu.values())
    total_many = sum(many.cpu.values())
    neighbors = sim.forcefield.neighbor_list
    print(
        f"\nphases of {steps} mixed steps after {warm}, {4 * cells**3} atoms, CPU time of "
        f"one thread (time.thread_time), the work in 1 chunk and in {threads} chunks (two "
        f"runs on one thread, in turns of 10 steps); {neighbors.n_builds} searches and "
        f"{neighbors.n_prunes} prunes so far; ms per step:"
    )
    print(f"  {'phase':34s}{'1 chunk':>9}{'share':>7}{f'{threads} chunks':>10}{'on T':>8}  runs")
    on_threads = 0.0
    serial = 0.0
    names = sorted(set(one.cpu) | set(many.cpu), key=lambda n: -many.cpu.get(n, 0.0))
    for name in names:
        w1 = one.cpu.get(name, 0.0) / steps
        wt = many.cpu.get(name, 0.0) / steps
        parallel = name in PARALLEL
        if name == "prune kernel" and "prune: rows" in chunks:
            # the rows' chunks and the serial tail (prefix sum, moves), from the prune alone
            rows, whole = chunks["prune: rows"], chunks["prune kernel, whole"][0]
            second = "prune: move" if "prune: move" in chunks else "prune: copy"
            move = chunks.get(second, [0.0])
            tail = max(whole - sum(rows) - sum(move), 0.0)
            span = wt * (tail + max(rows) + max(move)) / whole
            serial += wt * tail / whole
            how = (
                "rows "
                + "/".join(f"{1e3 * t:.3f}" for t in rows)
                + " ms"
                + (
                    (f", {second[7:]} " + "/".join(f"{1e3 * t:.3f}" for t in move) + " ms")
                    if second in chunks
                    else ""
                )
                + f", serial tail {1e3 * tail:.3f} ms ({tail / whole:.0%})"
            )
        elif name in chunks and wt > 0.0:
            # the phase's slowest chunk's share of its chunks' work, measured alone
            share = max(chunks[name]) / sum(chunks[name])
            span = wt * share
            how = "chunks " + "/".join(f"{1e3 * t:.3f}" for t in chunks[name]) + " ms"
        elif parallel:
            span = wt / threads
            how = "even split"
        else:
            span = wt
            how = "serial"
        on_threads += span
        serial += 0.0 if parallel else wt
        if name == "search (whole build)":
            how += " (assumed; another issue's)"
        print(
            f"  {name:34s}{1e3 * w1:9.3f}{w1 * steps / total_one:7.1%}{1e3 * wt:10.3f}"
            f"{1e3 * span:8.3f}  {how}"
        )
    print(
        f"  {'all':34s}{1e3 * total_one / steps:9.3f}{'':7s}{1e3 * total_many / steps:10.3f}"
        f"{1e3 * on_threads:8.3f}"
    )
    _peer(cells, steps, total_one / steps)
    print(
        f"  serial work {serial * steps / total_many:.1%} of the {threads}-chunk work; "
        f"chunking costs {total_many / total_one - 1:+.1%} work; bound on the {threads}-thread "
        f"speed-up {total_one / steps / on_threads:.2f}x (no wake-ups, no shared bandwidth)"
    )


def _peer(cells: int, steps: int, ours: float) -> None:
    """LAMMPS's ``lj/cut`` on the same melt (one thread, the same list rule; a child
    process, ``lammps_lj_melt.py``) beside the mixed step's one-chunk work ``ours``
    [s per step]: its loop time is a wall time (its one thread may wait for a core on a
    shared machine), ours CPU time, so the ratio leans towards ours only if LAMMPS waited."""
    try:
        found = lj_melt.run_lammps(cells, steps, "check", lj_melt.lammps_environment())
    except (OSError, RuntimeError) as error:
        print(f"  LAMMPS: not run ({error})")
        return
    per_step = found["loop_time"] / steps
    sections = found.get("sections") or {}
    shares = ", ".join(
        f"{name} {100 * sections[name] / found['loop_time']:.0f} %"
        for name in ("Pair", "Neigh", "Other")
        if name in sections
    )
    print(
        f"  LAMMPS {found.get('version', '?')} lj/cut, 1 thread, this melt: "
        f"{1e3 * per_step:.3f} ms a step ({shares}; {found.get('n_builds')} builds, "
        f"loop wall time); LAMMPS / ours mixed (1 chunk, CPU) "
        f"{per_step / ours:.2f}"
    )
