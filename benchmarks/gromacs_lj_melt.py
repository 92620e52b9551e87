"""Run the LJ melt once in GROMACS (``gmx grompp`` + ``gmx mdrun``) and print its timings as JSON.

``compare.py --peers gromacs,gromacs-double`` starts this through its worker;
it also runs on its own (``md`` must be importable: the initial state is ours)::

    python benchmarks/gromacs_lj_melt.py --gmx gmx_d --threads 2 --cells 20 --steps 100

The system is the LJ melt of ``lj_melt.py`` (LAMMPS's bench/in.lj) in
argon-like GROMACS units: sigma = 0.34 nm, epsilon = 1 kJ/mol, mass = 40 amu,
so tau = sigma sqrt(m / epsilon) = 2.1503 ps (1 kJ/mol = 1 amu nm^2 ps^-2),
dt = 0.005 tau = 0.010752 ps, the cutoff 2.5 sigma = 0.85 nm. Positions,
velocities (our Gaussian T* = 3.0 draw) and the box are ours, scaled; the .gro
file carries 7 decimals (GROMACS reads the precision from the column widths),
so the initial energy matches ours to round-off. The run:

- ``cutoff-scheme = Verlet``, ``vdwtype = Cut-off`` with ``vdw-modifier = None``
  (plain truncation, as LAMMPS's lj/cut and ours), no dispersion correction;
- no electrostatics work: every charge is zero and ``coulombtype = Cut-off``;
  GROMACS's pair search flags an i-cluster for Coulomb only when it holds a
  charge, so its kernels run their LJ-only path;
- NVE leap-frog (``integrator = md``), no thermostat or barostat, no output
  but md.log (energies at the first and last step, ``nstcalcenergy = steps``);
- the pair list: GROMACS's own Verlet buffer (``verlet-buffer-tolerance``
  default, sized for nstlist from the initial temperature; mdrun may prune an
  inner list dynamically) or, with ``rlist``, a fixed list radius
  (``verlet-buffer-tolerance = -1``), both with ``nstlist`` (20) in the .mdp;
  the rlist and nstlist mdrun settled on are read back from md.log;
- ``gmx mdrun -ntmpi 1 -ntomp N -nb cpu -pin off|on|auto -noconfout``.

The time is md.log's "Wall t" (the MD loop: mdrun's setup, file reading and
the domain set-up are outside it), with GROMACS's cycle counters (Neighbor
search, Force, Update, ...) and their call counts. GROMACS's loop runs steps 0
to ``nsteps`` inclusive, each a force evaluation and an update, so ``nsteps =
steps - 1`` does ``steps`` of each, as our ``steps`` steps do after their
untimed setup force call (GROMACS's step 0 search and forces are timed; with
nstlist 20 it searches at steps 0, 20, 40, 60 and 80 of 100). The rate is
atoms x steps / wall time. The step-0 LJ energy comes from ``gmx energy``
(full float precision; md.log prints six digits). The peak resident memory of
``gmx mdrun`` (its VmHWM, read while it runs) is the whole process's.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

#: GROMACS units for the reduced LJ system: sigma [nm], epsilon [kJ/mol], mass [amu].
SIGMA, EPSILON, MASS = 0.34, 1.0, 40.0
TAU = SIGMA * math.sqrt(MASS / EPSILON)  # [ps]
#: The workload in reduced units (lj_melt.py's).
CUTOFF, DT = 2.5, 0.005
FIXED_RLIST = 2.8  # [sigma]: the cutoff plus our skin 0.3
NSTLIST = 20
#: Decimals of the .gro coordinates (velocities get one more).
GRO_DECIMALS = 7
#: Environment variable naming a gmx binary (mixed precision) and its double twin.
GMX_ENV, GMX_D_ENV = "GMX", "GMX_D"
PIN_CHOICES = ("off", "on", "auto")


# ----------------------------------------------------------------------- input files


def gro_text(positions, velocities, box, title: str = "LJ melt", decimals: int = GRO_DECIMALS):
    """A .gro file: one AR atom per residue, positions [nm] with ``decimals`` decimals in
    fields ``decimals + 5`` wide and velocities [nm/ps] with one more decimal, as GROMACS
    reads a higher-precision .gro; atom and residue numbers wrap at 100000 as it expects."""
    positions = np.asarray(positions, dtype=float)
    velocities = np.asarray(velocities, dtype=float)
    box = np.asarray(box, dtype=float)
    if positions.ndim != 2 or positions.shape[1] != 3 or velocities.shape != positions.shape:
        raise ValueError("positions and velocities must be (N, 3) arrays of one shape")
    if box.shape != (3,):
        raise ValueError(f"box must hold 3 edge lengths, got shape {box.shape}")
    width = decimals + 5
    limit = 10.0 ** (width - decimals - 2)  # the sign, digits and point must fit
    if np.abs(positions).max(initial=0.0) >= limit or np.abs(velocities).max(initial=0.0) >= (
        limit / 10
    ):
        raise ValueError(f"coordinates do not fit a .gro field {width} wide")
    xf, vf = f"{{:{width}.{decimals}f}}", f"{{:{width}.{decimals + 1}f}}"
    lines = [title, f"{len(positions):5d}"]
    for index, (x, v) in enumerate(zip(positions, velocities, strict=True)):
        number = (index + 1) % 100000
        coordinates = "".join(xf.format(c) for c in x) + "".join(vf.format(c) for c in v)
        lines.append(f"{number:5d}{'AR':<5}{'AR':>5}{number:5d}" + coordinates)
    lines.append(" ".join(f"{edge:.{decimals}f}" for edge in box))
    return "\n".join(lines) + "\n"


def topology_text(n_atoms: int) -> str:
    """The .top: one LJ atom type (sigma, epsilon, mass as above, no charge), one molecule."""
    return f"""\
[ defaults ]
; nbfunc  comb-rule  gen-pairs  fudgeLJ  fudgeQQ
  1       2          no         1.0      1.0

[ atomtypes ]
; name  mass  charge  ptype  sigma  epsilon
  AR    {MASS}  0.0  A  {SIGMA}  {EPSILON}

[ moleculetype ]
; name  nrexcl
  AR    1

[ atoms ]
; nr  type  resnr  residue  atom  cgnr  charge  mass
  1   AR    1      AR       AR    1     0.0     {MASS}

[ system ]
LJ melt (reduced units: sigma {SIGMA} nm, epsilon {EPSILON} kJ/mol, mass {MASS} amu)

[ molecules ]
AR  {n_atoms}
"""


def mdp_text(
    steps: int, rlist: float | None = None, nstlist: int = NSTLIST, modifier: str = "None"
) -> str:
    """The .mdp of a run doing ``steps`` force evaluations and updates (``nsteps = steps -
    1``: GROMACS's loop also does step ``nsteps``): NVE leap-frog, truncated LJ, no
    charges; ``rlist`` [sigma] fixes the list radius (no Verlet buffer estimate), None lets
    GROMACS size its buffer; ``modifier`` is the ``vdw-modifier`` (``Potential-shift``:
    the energy shifted to zero at the cutoff, as ours and LAMMPS's ``shift yes``)."""
    if steps < 1 or nstlist < 1:
        raise ValueError(f"steps and nstlist must be positive, got {steps} and {nstlist}")
    if rlist is not None and rlist < CUTOFF:
        raise ValueError(f"rlist {rlist} sigma is below the cutoff {CUTOFF} sigma")
    rc = CUTOFF * SIGMA
    nsteps = steps - 1
    every = max(1, nsteps)
    if rlist is None:
        buffer = "; pair-list buffer: GROMACS's estimate (verlet-buffer-tolerance default)"
    else:
        buffer = f"verlet-buffer-tolerance = -1\nrlist = {rlist * SIGMA:.6f}"
    return f"""\
; LJ melt, {DT} tau steps (tau = {TAU:.6f} ps)
integrator = md
dt = {DT * TAU:.9f}
nsteps = {nsteps}
continuation = yes
constraints = none
cutoff-scheme = Verlet
nstlist = {nstlist}
pbc = xyz
{buffer}
vdwtype = Cut-off
vdw-modifier = {modifier}
rvdw = {rc:.6f}
DispCorr = no
coulombtype = Cut-off
rcoulomb = {rc:.6f}
tcoupl = no
pcoupl = no
gen-vel = no
nstcalcenergy = {every}
nstenergy = {every}
nstlog = {every}
nstxout = 0
nstvout = 0
nstfout = 0
nstxout-compressed = 0
"""


# ------------------------------------------------------------------------- md.log


def _number(pattern: str, text: str, cast=float, group: int = 1):
    match = re.search(pattern, text, re.MULTILINE)
    return cast(match.group(group)) if match else None


#: The SIMD level GROMACS thinks fits this CPU best, as 2022 and 2026 word it.
_SIMD_BEST = (
    r"(?:SIMD instructions most likely to fit this hardware|Highest SIMD level supported by "
    r"all nodes in run|Likely fastest SIMD instructions supported by all nodes):\s+(\S+)"
)
#: A counter row: name, ranks, threads, calls, wall [s], giga-cycles, % of the total.
_COUNTER_ROW = re.compile(
    r"\s*(\S.*?\S)\s+(\d+)\s+(\d+)\s+(\d+)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)\s*$"
)


def parse_counters(text: str) -> dict[str, dict]:
    """GROMACS's cycle-accounting table ("R E A L   C Y C L E   A N D   T I M E"):
    {name: {"count": calls, "seconds": wall time}} for each row with a count."""
    start = text.find("R E A L   C Y C L E")
    if start < 0:
        return {}
    counters: dict[str, dict] = {}
    for line in text[start:].splitlines()[1:]:
        if line.strip().startswith("Total"):
            break
        # "Neighbor search        1    1         6       0.046          0.265   9.8"
        match = _COUNTER_ROW.match(line)
        if match:
            counters[match.group(1)] = {
                "count": int(match.group(4)),
                "seconds": float(match.group(5)),
            }
    return counters


def _initial_lj_energy(text: str) -> float | None:
    """The "LJ (SR)" energy [kJ/mol] of the first energy block (step 0) in md.log."""
    block = re.search(r"Energies \(kJ/mol\)\n(.*?)\n\n", text, re.DOTALL)
    if block is None:
        return None
    lines = block.group(1).splitlines()
    for names, values in zip(lines[::2], lines[1::2], strict=False):
        # 15-character columns: names right-aligned above their values
        width = 15
        for k in range(0, len(names), width):
            if names[k : k + width].strip() == "LJ (SR)":
                try:
                    return float(values[k : k + width])
                except ValueError:
                    return None
    return None


def build_info(text: str) -> dict:
    """Version, precision and SIMD level from ``gmx --version`` or an md.log header."""
    return {
        "version": _number(r"^\s*GROMACS version:\s+(\S+)", text, str),
        "precision": _number(r"^\s*Precision:\s+(\S+)", text, str),
        "simd": _number(r"^\s*SIMD instructions:\s+(\S+)", text, str),
    }


def parse_md_log(text: str) -> dict:
    """What a GROMACS md.log says about the run: version, precision, SIMD level (built
    for and best for this CPU), nonbonded kernel, the pair list mdrun used (nstlist, rlist,
    the dynamically pruned inner list), OpenMP threads, the loop's wall and core time, the
    cycle counters, the step-0 LJ energy and the conserved-energy drift.

    Raises
    ------
    ValueError
        If the log has no "Time:" line (the run did not finish).
    """
    timing = re.search(r"^\s*Time:\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)", text, re.MULTILINE)
    if timing is None:
        raise ValueError("md.log has no 'Time:' line: mdrun did not finish")
    result: dict = {
        "core_time": float(timing.group(1)),
        "loop_time": float(timing.group(2)),
        **build_info(text),
        "simd_best": _number(_SIMD_BEST, text, str),
        "kernel": _number(r"Using (.*?) nonbonded short-range kernels", text, str),
        "omp_threads": _number(r"Using (\d+) OpenMP threads?", text, int),
        "ns_per_day": _number(r"^Performance:\s+([\d.]+)", text),
        "nsteps": _number(r"^\s*nsteps\s*=\s*(\d+)", text, int),
        # from its first and last energies [kJ/mol/ps per atom]
        "conserved_drift": _number(r"Conserved energy drift:\s+([-\d.eE+]+) kJ/mol/ps", text),
    }
    # The list mdrun used: a change of nstlist overrides the .mdp's; the dual-list line
    # gives the outer list's interval and radius, and the inner list's when it prunes.
    nstlist = _number(r"^\s*nstlist\s*=\s*(\d+)", text, int)
    rlist = _number(r"^\s*rlist\s*=\s*([\d.eE+-]+)", text)
    changed = re.search(r"Changing nstlist from \d+ to (\d+), rlist from [\d.]+ to ([\d.]+)", text)
    if changed:
        nstlist, rlist = int(changed.group(1)), float(changed.group(2))
    outer, inner = (
        re.search(
            rf"{which} list: updated every\s+(\d+) steps, buffer ([\d.]+) nm, "
            r"rlist ([\d.]+) nm",
            text,
        )
        for which in ("outer", "inner")
    )
    if outer:
        nstlist, rlist = int(outer.group(1)), float(outer.group(3))
    single = re.search(
        r"Using a (?:single )?[\dx]+ pair-list setup:\s*\n\s*updated every\s+(\d+)"
        r" steps, buffer ([\d.]+) nm, rlist ([\d.]+) nm",
        text,
    )
    if single and not outer:
        nstlist, rlist = int(single.group(1)), float(single.group(3))
    result.update(
        nstlist=nstlist,
        rlist_nm=rlist,
        inner_nstlist=int(inner.group(1)) if inner else None,
        inner_rlist_nm=float(inner.group(3)) if inner else None,
        counters=parse_counters(text),
        # The flop-accounting rows of the cluster kernels: "NxN LJ [F]" without Coulomb,
        # "NxN RF Elec. + LJ [F]" with it.
        pair_kernels=sorted(set(re.findall(r"^ (NxN .*?\[[^]]*\])", text, re.MULTILINE))),
        lj_energy=_initial_lj_energy(text),
    )
    return result


# ---------------------------------------------------------------------------- running


def find_gmx(variant: str, explicit: str | None = None) -> str | None:
    """The gmx binary for ``variant`` ("mixed" or "double"): ``explicit`` if given (a path
    or a name on PATH), else $GMX / $GMX_D if set, else ``gmx`` / ``gmx_d`` on PATH; None if
    the one chosen is not an executable (a name given is never replaced by another)."""
    if variant not in ("mixed", "double"):
        raise ValueError(f"unknown GROMACS variant {variant!r}")
    name = (
        explicit
        or os.environ.get(GMX_ENV if variant == "mixed" else GMX_D_ENV)
        or ("gmx" if variant == "mixed" else "gmx_d")
    )
    return shutil.which(name)


def _child(
    command: list[str], folder: str, env: dict[str, str], stdin: str = "", watch: bool = False
) -> int | None:
    """Run a gmx command in ``folder`` (output to gmx_output.txt); with ``watch``, return
    its peak resident memory [KiB] (VmHWM, read every 0.1 s while it runs; a child's
    ru_maxrss would count this Python process's memory, which it inherits at fork).

    Raises
    ------
    RuntimeError
        If the command fails; the message holds its last error line.
    """
    output = Path(folder) / "gmx_output.txt"
    peak = None
    with open(output, "ab") as out:
        process = subprocess.Popen(
            command, cwd=folder, env=env, stdout=out, stderr=out, stdin=subprocess.PIPE
        )
        process.stdin.write(stdin.encode())
        process.stdin.close()
        status = Path(f"/proc/{process.pid}/status")
        while True:
            try:
                process.wait(timeout=0.1 if watch else None)
                break
            except subprocess.TimeoutExpired:
                peak = _high_water(status, peak)
    if process.returncode != 0:
        lines = output.read_text(errors="replace").strip().splitlines()
        errors = [line.strip() for line in lines if "rror" in line or "Fatal" in line]
        last = next((line.strip() for line in reversed(lines) if line.strip()), "no output")
        raise RuntimeError(
            f"{Path(command[0]).name} {command[1]} exit {process.returncode}: "
            f"{(errors or [last])[-1]} (see {output.name})"
        )
    return peak


def _high_water(status: Path, previous: int | None) -> int | None:
    try:
        for line in status.read_text().splitlines():
            if line.startswith("VmHWM:"):
                return max(previous or 0, int(line.split()[1]))
    except (OSError, ValueError):
        pass
    return previous


def _energy_at_step0(gmx: str, folder: str, env: dict[str, str]) -> float | None:
    """The step-0 "LJ (SR)" energy [kJ/mol] from ener.edr through ``gmx energy``."""
    try:
        _child(
            [gmx, "energy", "-f", "ener.edr", "-o", "lj.xvg", "-xvg", "none"],
            folder,
            env,
            stdin="LJ-(SR)\n\n",
        )
        first = (Path(folder) / "lj.xvg").read_text().split("\n", 1)[0].split()
        return float(first[1])
    except (RuntimeError, OSError, ValueError, IndexError):
        return None


def run(
    gmx: str,
    state,
    steps: int,
    threads: int,
    rlist: float | None = None,
    nstlist: int = NSTLIST,
    pin: str = "off",
    keep: str | None = None,
    modifier: str = "None",
) -> dict:
    """Run ``steps`` steps of ``state`` (reduced units) in GROMACS; return md.log's figures.

    ``keep``: a folder to copy the inputs, md.log and gmx's output into.
    """
    if pin not in PIN_CHOICES:
        raise ValueError(f"pin must be one of {PIN_CHOICES}, got {pin!r}")
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), GMX_MAXBACKUP="-1")
    with tempfile.TemporaryDirectory(prefix="gmx_lj_melt_") as folder:
        files = {
            "conf.gro": gro_text(
                state.positions * SIGMA, state.velocities * (SIGMA / TAU), state.box * SIGMA
            ),
            "topol.top": topology_text(state.n_atoms),
            "run.mdp": mdp_text(steps, rlist, nstlist, modifier),
        }
        for name, text in files.items():
            (Path(folder) / name).write_text(text)
        try:
            _child(
                [
                    gmx,
                    "grompp",
                    "-f",
                    "run.mdp",
                    "-c",
                    "conf.gro",
                    "-p",
                    "topol.top",
                    "-o",
                    "topol.tpr",
                    "-po",
                    "mdout.mdp",
                ],
                folder,
                env,
            )
            peak = _child(
                [
                    gmx,
                    "mdrun",
                    "-s",
                    "topol.tpr",
                    "-g",
                    "md.log",
                    "-e",
                    "ener.edr",
                    "-ntmpi",
                    "1",
                    "-ntomp",
                    str(threads),
                    "-nb",
                    "cpu",
                    "-pin",
                    pin,
                    "-noconfout",
                    "-nice",
                    "0",
                ],
                folder,
                env,
                watch=True,
            )
            log = (Path(folder) / "md.log").read_text(errors="replace")
            energy = _energy_at_step0(gmx, folder, env)
        finally:
            if keep is not None:
                Path(keep).mkdir(parents=True, exist_ok=True)
                for name in (*files, "md.log", "gmx_output.txt"):
                    if (Path(folder) / name).exists():
                        shutil.copy(Path(folder) / name, Path(keep) / name)
    result = parse_md_log(log)
    logged = result.pop("lj_energy")
    energy = logged if energy is None else energy
    search = result["counters"].get("Neighbor search", {}).get("count")
    result.update(
        n_atoms=state.n_atoms,
        threads=threads,
        binary=gmx,
        pin=pin,
        buffer="fixed" if rlist is not None else "verlet",
        rlist_sigma=None if result["rlist_nm"] is None else result["rlist_nm"] / SIGMA,
        inner_rlist_sigma=(
            None if result["inner_rlist_nm"] is None else result["inner_rlist_nm"] / SIGMA
        ),
        n_builds=search,
        potential_energy=None if energy is None else energy / EPSILON / state.n_atoms,
        mdrun_peak_kib=peak,
    )
    return result


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gmx", default=None, help="gmx binary (default $GMX, else gmx)")
    parser.add_argument("--cells", type=int, default=20, help="fcc cells per edge (20)")
    parser.add_argument("--steps", type=int, default=100, help="time steps (100)")
    parser.add_argument("--threads", type=int, default=1, help="OpenMP threads (1)")
    parser.add_argument(
        "--rlist",
        type=float,
        default=None,
        help="fixed list radius [sigma], e.g. 2.8 (default: GROMACS's buffer)",
    )
    parser.add_argument("--pin", choices=PIN_CHOICES, default="off")
    parser.add_argument("--keep", default=None, help="copy the inputs and md.log here")
    args = parser.parse_args(argv)
    gmx = find_gmx("mixed", args.gmx)
    if gmx is None:
        parser.error("no gmx binary: pass --gmx PATH or set $GMX")
    import md

    state = md.maxwell_boltzmann(md.lattice("fcc", args.cells, density=0.8442), 3.0, seed=87287)
    print(
        json.dumps(
            run(gmx, state, args.steps, args.threads, args.rlist, pin=args.pin, keep=args.keep)
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
