"""The benchmark harness benchmarks/compare.py: a smoke run and its input checks.

Speed is never asserted here; the harness prints timings, and these tests
check that it runs the workload (the LJ melt at reduced density 0.8442) and
reports it, and that bad options are refused with exit code 2.
"""

from __future__ import annotations

import importlib
import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import md._simd

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "compare.py"


def run_compare(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(SCRIPT), *args],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=SCRIPT.parents[1],
    )


@pytest.mark.slow  # keeps the default suite within its 10 minutes
def test_quick_run_prints_a_row_for_ours(tmp_path):
    report = tmp_path / "report.json"
    done = run_compare("--quick", "--peers", "none", "--json", str(report))
    assert done.returncode == 0, done.stderr
    rows = [line.split() for line in done.stdout.splitlines() if line.startswith("leapmd ")]
    # engine, threads, atoms, steps, rate: one row per thread count in each table.
    assert any(row[1] == "1" and row[2] == "864" for row in rows), done.stdout
    # the issue-20 target on the neighbour share is checked and said, per thread count
    verdict = [line for line in done.stdout.splitlines() if "neighbour work below 15%" in line]
    assert len(verdict) == 1 and " at 1t (" in verdict[0], done.stdout
    data = json.loads(report.read_text())
    ours = [m for m in data["comparison"] if m["label"] == "leapmd"]
    assert ours
    for measured in ours:
        assert measured["n_atoms"] == 4 * 6**3
        assert all(math.isfinite(r) and r > 0 for r in measured["rates"])
        run = measured["runs"][0]
        # The rate is atoms x steps / loop time, and the time split adds up to the loop.
        steps = measured["job"]["steps"]
        assert math.isclose(measured["rates"][0], run["n_atoms"] * steps / run["loop_time"])
        assert math.isclose(sum(run["sections"].values()), run["loop_time"], rel_tol=1e-9)
        # The fcc crystal at rho* 0.8442 with LJ cut at 2.5 (no shift): LAMMPS's bench/in.lj
        # prints E_pair = -6.7733681 at step 0.
        assert math.isclose(run["potential_energy"], -6.7733681, rel_tol=1e-7)


@pytest.mark.slow
def test_mixed_adds_our_mixed_precision_row_on_the_same_melt(tmp_path):
    report = tmp_path / "report.json"
    done = run_compare(
        "--quick", "--peers", "none", "--mixed", "--no-scaling", "--json", str(report)
    )
    assert done.returncode == 0, done.stderr
    assert "mixed/peer" in done.stdout, done.stdout
    rows = [line.split() for line in done.stdout.splitlines() if line.startswith("leapmd mixed ")]
    assert any(row[2] == "1" for row in rows), done.stdout  # engine label is two words
    data = json.loads(report.read_text())
    mixed = [m for m in data["comparison"] if m["label"] == "leapmd mixed"]
    assert mixed and all(m["runs"][0]["precision"] == "mixed" for m in mixed)
    double = next(m for m in data["comparison"] if m["label"] == "leapmd")
    reference = double["runs"][0]["potential_energy"]
    for measured in mixed:
        energy = measured["runs"][0]["potential_energy"]
        # the same crystal as the double row, its energy to float32 round-off (not equal:
        # the pair terms really ran in float32)
        assert math.isclose(energy, reference, rel_tol=1e-5) and energy != reference


def test_bad_threads_is_refused():
    done = run_compare("--quick", "--peers", "none", "--threads", "0")
    assert done.returncode == 2
    assert "--threads" in done.stderr


def test_unknown_peer_is_refused():
    done = run_compare("--quick", "--peers", "namd")
    assert done.returncode == 2
    assert "namd" in done.stderr


def test_existing_json_is_not_overwritten(tmp_path):
    report = tmp_path / "report.json"
    report.write_text("keep")
    done = run_compare("--quick", "--peers", "none", "--json", str(report))
    assert done.returncode == 2
    assert "--overwrite" in done.stderr
    assert report.read_text() == "keep"


@pytest.mark.slow  # keeps the default suite within its 10 minutes
def test_every_benchmark_names_the_machine_and_the_threads_of_its_rows():
    bench = SCRIPT.parent
    runs = {
        "compare.py": ["--quick", "--peers", "none"],
        "lj_melt.py": ["--cells", "5", "--steps", "5", "--repeats", "1", "--no-lammps"],
        "implicit.py": [
            "--cells",
            "5",
            "--steps",
            "1",
            "--repeats",
            "1",
            "--skip-polymer",
            "--chain-span",
            "0.02",
        ],
        "npt.py": ["--cells", "5", "--steps", "5", "--repeats", "1"],
    }
    for script, args in runs.items():
        done = subprocess.run(
            [sys.executable, str(bench / script), *args],
            capture_output=True,
            text=True,
            timeout=300,
            cwd=bench.parent,
        )
        assert done.returncode == 0, (script, done.stderr)
        header = done.stdout.splitlines()[:4]
        machine = [line for line in header if line.startswith("machine: ")]
        assert machine and any(
            isa in machine[0] for isa in ("AVX", "SSE", "x86", "arm", "aarch")
        ), (
            script,
            header,
        )
        assert "thread" in done.stdout, script
    # lj_melt.py labels its rows with their thread count, and runs LAMMPS only at 1 thread.
    done = subprocess.run(
        [
            sys.executable,
            str(bench / "lj_melt.py"),
            "--cells",
            "5",
            "--steps",
            "5",
            "--repeats",
            "1",
            "--threads",
            "2",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=bench.parent,
    )
    assert done.returncode == 0, done.stderr
    assert "leapmd (2 thread(s))" in done.stdout and "LAMMPS not run" in done.stdout


def test_vector_check_counts_packed_double_arithmetic_only():
    """The parser behind compare.py's "vectorised:" line: packed double FMAs, products,
    sums, compares, divisions and roots on ymm/zmm count; scalar (sd) and xmm ones do not."""
    sys.path.insert(0, str(SCRIPT.parent))
    try:
        from _vector_check import packed_counts
    finally:
        sys.path.remove(str(SCRIPT.parent))
    assembly = """
        vfmadd231pd	%ymm1, %ymm2, %ymm3
        vfnmsub213pd	(%rax), %zmm4, %zmm5
        vmulpd	%zmm1, %zmm2, %zmm3
        vcmpltpd	%ymm23, %ymm7, %k1
        vdivpd	%ymm1, %ymm2, %ymm3
        vsqrtpd	%ymm1, %ymm2
        vmulsd	%xmm1, %xmm2, %xmm3
        vaddpd	%xmm1, %xmm2, %xmm3
        vfmadd231sd	%xmm1, %xmm2, %xmm3
        vmovupd	%ymm1, (%rax)
    """
    assert packed_counts(assembly) == {"ymm": 4, "zmm": 2}


# ------------------------------------------------------------------ the GROMACS peer

#: The parts of a GROMACS md.log the harness reads, as GROMACS 2022 writes them (a run of
#: this melt: 32000 atoms, 2 OpenMP threads, 100 force evaluations).
MD_LOG = """\
              :-) GROMACS - gmx mdrun, 2022.5-Debian_2022.5_2 (-:

GROMACS version:    2022.5-Debian_2022.5_2
Precision:          mixed
MPI library:        thread_mpi
SIMD instructions:  SSE4.1

Highest SIMD level supported by all nodes in run: AVX2_256
SIMD instructions selected at compile time:       SSE4.1

Input Parameters:
   integrator                     = md
   nsteps                         = 99
   cutoff-scheme                  = Verlet
   nstlist                        = 20
   verlet-buffer-tolerance        = 0.005
   rlist                          = 0.896

Using 2 OpenMP threads

Using SIMD 4x4 nonbonded short-range kernels

Using a 4x4 pair-list setup:
  updated every 20 steps, buffer 0.046 nm, rlist 0.896 nm

   Energies (kJ/mol)
        LJ (SR)   Coulomb (SR)      Potential    Kinetic En.   Total Energy
   -2.16749e+05    0.00000e+00   -2.16749e+05    1.43995e+05   -7.27540e+04
    Temperature Pressure (bar)
    3.60816e+02   -1.56420e+03

 Computing:                               M-Number         M-Flops  % Flops
-----------------------------------------------------------------------------
 Pair Search distance check              17.649566         158.846     1.6
 NxN LJ [F]                             281.909488        9303.013    95.3
 NxN LJ [V&F]                             4.861712         209.054     2.1

     R E A L   C Y C L E   A N D   T I M E   A C C O U N T I N G

On 1 MPI rank, each using 2 OpenMP threads

 Computing:          Num   Num      Call    Wall time         Giga-Cycles
                     Ranks Threads  Count      (s)         total sum    %
-----------------------------------------------------------------------------
 Neighbor search        1    2          5       1.048          5.124   3.4
 Force                  1    2        100       8.342         40.801  27.1
 NB X/F buffer ops.     1    2        195      10.563         51.663  34.3
 Update                 1    2        100       7.257         35.491  23.5
 Rest                                           3.624         17.722  11.8
-----------------------------------------------------------------------------
 Total                                         30.833        150.802 100.0
-----------------------------------------------------------------------------

               Core t (s)   Wall t (s)        (%)
       Time:       61.667       30.833      200.0
                 (ns/day)    (hour/ns)
Performance:        3.013        7.966
"""

#: The list lines of a run with dynamic pruning and a changed nstlist (GROMACS 2026 wording).
MD_LOG_DUAL = """\
Likely fastest SIMD instructions supported by all nodes: AVX_512
SIMD instructions selected at compile time:              AVX2_256
   nstlist                        = 10
   rlist                          = 0.9
Changing nstlist from 10 to 25, rlist from 0.9 to 0.95

Using SIMD2xMM 4x8 nonbonded short-range kernels

Using a dual 4x8 pair-list setup updated with dynamic pruning:
  outer list: updated every 25 steps, buffer 0.104 nm, rlist 0.954 nm
  inner list: updated every  4 steps, buffer 0.011 nm, rlist 0.861 nm
       Time:        1.000        0.500      200.0
"""


def _benchmark_module(name: str):
    """A script of benchmarks/ imported as a module (the folder is not a package)."""
    sys.path.insert(0, str(SCRIPT.parent))
    try:
        return importlib.import_module(name)
    finally:
        sys.path.remove(str(SCRIPT.parent))


def _gromacs_module():
    return _benchmark_module("gromacs_lj_melt")


def test_md_log_parsing_reads_time_counters_list_and_simd():
    gmx = _gromacs_module()
    log = gmx.parse_md_log(MD_LOG)
    assert (log["loop_time"], log["core_time"]) == (30.833, 61.667)
    assert log["version"] == "2022.5-Debian_2022.5_2" and log["precision"] == "mixed"
    assert (log["simd"], log["simd_best"], log["kernel"]) == ("SSE4.1", "AVX2_256", "SIMD 4x4")
    assert (log["omp_threads"], log["nsteps"], log["nstlist"]) == (2, 99, 20)
    assert log["rlist_nm"] == 0.896 and log["inner_nstlist"] is None
    # The counters: one row each with its call count and wall time; "Rest" has no count.
    assert log["counters"] == {
        "Neighbor search": {"count": 5, "seconds": 1.048},
        "Force": {"count": 100, "seconds": 8.342},
        "NB X/F buffer ops.": {"count": 195, "seconds": 10.563},
        "Update": {"count": 100, "seconds": 7.257},
    }
    # LJ-only cluster kernels ran: no "Elec." row, so zero charges cost no Coulomb work.
    assert log["pair_kernels"] == ["NxN LJ [F]", "NxN LJ [V&F]"]
    assert log["lj_energy"] == -2.16749e05
    assert gmx.build_info(MD_LOG) == {
        "version": "2022.5-Debian_2022.5_2",
        "precision": "mixed",
        "simd": "SSE4.1",
    }


def test_md_log_parsing_takes_the_list_mdrun_used():
    """A changed nstlist and a dual list: the outer list's interval and radius win over the
    .mdp's, and the pruned inner list is reported."""
    gmx = _gromacs_module()
    log = gmx.parse_md_log(MD_LOG_DUAL)
    assert (log["nstlist"], log["rlist_nm"]) == (25, 0.954)
    assert (log["inner_nstlist"], log["inner_rlist_nm"]) == (4, 0.861)
    assert (log["simd_best"], log["kernel"]) == ("AVX_512", "SIMD2xMM 4x8")
    unfinished = MD_LOG.split("               Core t")[0]
    with pytest.raises(ValueError, match="Time:"):
        gmx.parse_md_log(unfinished)


def _gro_fields(text: str, decimals: int):
    """Read a .gro back by GROMACS's rule: fields as wide as the distance between the
    first line's decimal points."""
    lines = text.splitlines()
    n = int(lines[1])
    first = lines[2]
    points = [i for i, c in enumerate(first) if c == "."]
    width = points[1] - points[0]
    assert width == decimals + 5
    rows = np.array(
        [
            [float(line[20 + k * width : 20 + (k + 1) * width]) for k in range(6)]
            for line in lines[2 : 2 + n]
        ]
    )
    box = np.array([float(v) for v in lines[2 + n].split()])
    return n, rows[:, :3], rows[:, 3:], box, lines[2 : 2 + n]


def test_gro_file_is_the_melt_at_its_density():
    import md

    gmx = _gromacs_module()
    cells = 5
    state = md.maxwell_boltzmann(md.lattice("fcc", cells, density=0.8442), 3.0, seed=87287)
    sigma, tau = gmx.SIGMA, gmx.TAU
    assert math.isclose(tau, 0.34 * math.sqrt(40.0))  # ps, for 1 kJ/mol and 40 amu
    text = gmx.gro_text(
        state.positions * sigma, state.velocities * (sigma / tau), state.box * sigma
    )
    n, positions, velocities, box, lines = _gro_fields(text, gmx.GRO_DECIMALS)
    assert n == 4 * cells**3 == len(positions)
    # The box: cells fcc cells of edge (4 / 0.8442)^(1/3) sigma, in nm; the density is ours.
    edge = cells * (4 / 0.8442) ** (1 / 3) * sigma
    np.testing.assert_allclose(box, [edge] * 3, rtol=1e-7)
    assert math.isclose(n / np.prod(box / sigma), 0.8442, rel_tol=1e-6)
    # Positions and velocities round-trip to the written precision, inside the box.
    np.testing.assert_allclose(positions, state.positions * sigma, atol=0.51e-7)
    np.testing.assert_allclose(velocities, state.velocities * (sigma / tau), atol=0.51e-8)
    assert positions.min() >= 0 and (positions < box).all()
    # The temperature the velocities carry: T* 3.0 is 3 epsilon / kB = 360.8 K here.
    kinetic = 0.5 * gmx.MASS * (velocities**2).sum()  # kJ/mol
    dof = 3 * n - 3
    assert math.isclose(2 * kinetic / (dof * 0.0083144626), 3.0 / 0.0083144626, rel_tol=1e-5)
    # Atom and residue numbers count from 1; one atom per residue.
    assert lines[0][:20] == "    1AR      AR    1" and lines[-1][:5] == f"{n:5d}"


def test_gro_numbers_wrap_and_bad_coordinates_are_refused():
    gmx = _gromacs_module()
    n = 100_001
    positions = np.zeros((n, 3))
    text = gmx.gro_text(positions, positions, np.ones(3), decimals=3)
    lines = text.splitlines()
    assert lines[1].strip() == str(n)
    assert lines[2 + 99_998][:5] == "99999" and lines[2 + 99_999][:5] == "    0"
    with pytest.raises(ValueError, match="field"):
        gmx.gro_text(np.full((1, 3), 1e6), np.zeros((1, 3)), np.ones(3))
    with pytest.raises(ValueError, match="shape"):
        gmx.gro_text(np.zeros((2, 3)), np.zeros((3, 3)), np.ones(3))


def _mdp_values(text: str) -> dict[str, str]:
    values = {}
    for line in text.splitlines():
        line = line.split(";")[0]
        if "=" in line:
            key, value = (part.strip() for part in line.split("=", 1))
            values[key] = value
    return values


def test_mdp_is_nve_truncated_lj_without_charges_work():
    gmx = _gromacs_module()
    own = _mdp_values(gmx.mdp_text(100))
    # steps force evaluations: GROMACS's loop runs steps 0 .. nsteps inclusive
    assert own["nsteps"] == "99" and own["integrator"] == "md"
    assert math.isclose(float(own["dt"]), 0.005 * 0.34 * math.sqrt(40.0), rel_tol=1e-8)
    assert math.isclose(float(own["rvdw"]), 0.85) and math.isclose(float(own["rcoulomb"]), 0.85)
    assert own["vdw-modifier"] == "None" and own["DispCorr"] == "no"
    assert own["coulombtype"] == "Cut-off" and own["cutoff-scheme"] == "Verlet"
    assert own["tcoupl"] == own["pcoupl"] == "no" and own["nstlist"] == "20"
    assert "rlist" not in own and "verlet-buffer-tolerance" not in own  # GROMACS's own buffer
    fixed = _mdp_values(gmx.mdp_text(100, rlist=2.8))
    assert fixed["verlet-buffer-tolerance"] == "-1"
    assert math.isclose(float(fixed["rlist"]), 2.8 * 0.34)
    with pytest.raises(ValueError, match="cutoff"):
        gmx.mdp_text(100, rlist=2.4)
    with pytest.raises(ValueError, match="positive"):
        gmx.mdp_text(0)
    topology = gmx.topology_text(32000)
    molecules = topology.split("[ molecules ]")[1].split()
    assert molecules == ["AR", "32000"]
    atomtype = topology.split("[ atomtypes ]")[1].splitlines()[2].split()
    assert atomtype == ["AR", "40.0", "0.0", "A", "0.34", "1.0"]  # no charge


@pytest.mark.slow  # a benchmark script run whole (kept out of the default run: its compile time)
def test_gromacs_peer_without_binary_is_skipped_with_a_note(tmp_path):
    """No gmx anywhere: the harness says how to get one and runs the rest."""
    missing = str(tmp_path / "no-gmx")
    done = run_compare(
        "--quick",
        "--peers",
        "gromacs,gromacs-double",
        "--gmx",
        missing,
        "--gmx-d",
        missing,
        "--no-vector-check",
    )
    assert done.returncode == 0, done.stderr
    assert "gromacs skipped" in done.stdout and "gromacs-double skipped" in done.stdout
    assert "apt-get install gromacs" in done.stdout
    assert any(line.startswith("leapmd ") for line in done.stdout.splitlines())


def test_bad_gmx_rlist_is_refused():
    done = run_compare("--quick", "--peers", "none", "--gmx-rlist", "2.0")
    assert done.returncode == 2
    assert "--gmx-rlist" in done.stderr


@pytest.mark.slow  # two GROMACS runs and ours: about a minute
@pytest.mark.skipif(
    shutil.which("gmx") is None or shutil.which("gmx_d") is None,
    reason="GROMACS (gmx and gmx_d) is not installed",
)
def test_gromacs_peers_run_the_same_melt(tmp_path):
    """With gmx and gmx_d installed, both run the melt: their initial energy agrees with ours
    (GROMACS mixed to its single-precision sum), their rates are finite and their list
    radius reaches the cutoff."""
    report = tmp_path / "report.json"
    done = run_compare(
        "--quick",
        "--peers",
        "gromacs,gromacs-double",
        "--threads",
        "1",
        "--no-scaling",
        "--no-vector-check",
        "--json",
        str(report),
    )
    assert done.returncode == 0, done.stderr
    assert "same system" in done.stdout and "WARNING" not in done.stdout, done.stdout
    data = json.loads(report.read_text())
    gromacs = [m for m in data["comparison"] if m["job"]["engine"] == "gromacs"]
    assert sorted(m["job"]["variant"] for m in gromacs) == ["double", "mixed"]
    for measured in gromacs:
        assert all(math.isfinite(r) and r > 0 for r in measured["rates"])
        run = measured["runs"][0]
        assert run["rlist_sigma"] >= 2.5 and run["nstlist"] >= 1
        assert run["precision"] == measured["job"]["variant"]


MIXED = SCRIPT.parent / "mixed_precision.py"


@pytest.mark.slow  # a benchmark script run whole (kept out of the default run: its compile time)
def test_mixed_precision_bench_drifts_over_seeds_and_refuses_no_seeds():
    """benchmarks/mixed_precision.py --drift-only --seeds 2: one block per liquid, each with
    both precisions' drifts, then the medians (no timing, no GROMACS); --seeds 0 exits 2."""

    def run(*args):
        return subprocess.run(
            [sys.executable, str(MIXED), *args],
            capture_output=True,
            text=True,
            timeout=300,
            cwd=MIXED.parents[1],
        )

    done = run(
        "--drift-only", "--seeds", "2", "--drift-cells", "3", "--drift-steps", "20", "--every", "10"
    )
    assert done.returncode == 0, done.stderr
    out = done.stdout
    assert out.count("liquid of seed") == 2 and out.count("\n  ours mixed  ") == 2, out
    # --every: ours mixed once more with the list rebuilt every 10 steps, no check
    assert out.count("\n  ours mixed (every 10, no check) ") == 2, out
    assert "medians over 2 liquids" in out and "(median over the liquids)" in out, out
    assert "force call" not in out, out  # --drift-only
    refused = run("--seeds", "0")
    assert refused.returncode == 2 and "--seeds must be at least 1, got 0" in refused.stderr
    refused = run("--every", "0")
    assert refused.returncode == 2 and "--every must be at least 1, got 0" in refused.stderr


PRUNING = SCRIPT.parent / "cluster_pruning.py"


@pytest.mark.slow  # a benchmark script run whole (kept out of the default run: its compile time)
def test_cluster_pruning_bench_prints_a_row_per_outer_skin_and_refuses_bad_ones():
    """benchmarks/cluster_pruning.py: the list without an outer one never prunes, the one
    with it prunes and lists more outer pairs than inner ones; bad --outer exits 2."""

    def run(*args):
        return subprocess.run(
            [sys.executable, str(PRUNING), *args],
            capture_output=True,
            text=True,
            timeout=300,
            cwd=PRUNING.parents[1],
        )

    done = run(
        "--cells", "6", "--outer", "0.3,1.2", "--steps", "40", "--repeats", "1", "--warm", "20"
    )
    assert done.returncode == 0, done.stderr
    rows = {
        line.split()[0]: line.split()
        for line in done.stdout.splitlines()
        if line.split() and line.split()[0] in ("0.3", "1.2")
    }
    # outer skin, ms/step, searches, prunes, pairs, outer pairs, ratio
    assert rows["0.3"][3] == "0" and rows["0.3"][5] == "-", done.stdout
    assert int(rows["1.2"][3]) > 0 and int(rows["1.2"][5]) > int(rows["1.2"][4]), done.stdout
    assert float(rows["0.3"][6]) == 1.0
    for bad in ("0.3,-1", "a,b"):
        refused = run("--outer", bad)
        assert refused.returncode == 2 and "--outer" in refused.stderr, refused.stderr
    # --sections: where a step goes; the searches and prunes are timed, and the parts add
    # up to no more than the step
    split = run(
        "--cells",
        "6",
        "--outer",
        "1.2",
        "--steps",
        "40",
        "--repeats",
        "1",
        "--warm",
        "20",
        "--sections",
    )
    assert split.returncode == 0, split.stderr
    lines = split.stdout.splitlines()
    header = next(
        i
        for i, line in enumerate(lines)
        if line.split()[:2] == ["outer", "skin"] and "force" in line
    )
    step = float(next(line.split()[1] for line in lines if line.split()[:1] == ["1.2"]))
    parts = [float(x) for x in lines[header + 1].split()[1:]]
    assert lines[header + 1].split()[0] == "1.2" and len(parts) == 5, lines
    assert all(x >= 0 for x in parts) and parts[0] > 0 and parts[1] > 0, parts
    assert sum(parts) <= 1.05 * step, (parts, step)
    # --every: a row with GROMACS's rule (every N steps, no check): no prunes, no outer list
    lazy = run(
        "--cells",
        "6",
        "--outer",
        "1.2",
        "--steps",
        "40",
        "--repeats",
        "1",
        "--warm",
        "20",
        "--every",
        "10",
    )
    assert lazy.returncode == 0, lazy.stderr
    row = next(
        line.split() for line in lazy.stdout.splitlines() if line.split()[:2] == ["every", "10"]
    )
    # every, 10, ms/step, searches, prunes, pairs, outer pairs, ratio
    assert row[4] == "0" and row[6] == "-" and float(row[3]) >= 3, lazy.stdout
    refused = run("--every", "-2")
    assert refused.returncode == 2 and "--every" in refused.stderr, refused.stderr


def test_the_drift_comparison_counts_liquids_and_bounds_the_ratio():
    """mixed_precision.py's multi-liquid summary: how often ours is the smaller |drift|,
    the two-sided sign test (3 of 3: p = 2 / 8; 2 of 4: 1) and a bootstrap interval that
    holds the ratio of the medians."""
    sys.path.insert(0, str(SCRIPT.parent))
    try:
        from mixed_precision import _compared
    finally:
        sys.path.remove(str(SCRIPT.parent))
    line = _compared([1.0, 1.0, 1.0], [2.0, 2.0, 2.0], "peer")
    assert "below peer in 3 of 3 liquids (sign test p = 0.25)" in line, line
    assert "ratio of the medians 0.50, bootstrap 90 % interval 0.50-0.50" in line, line
    mixed = _compared([1.0, 3.0, 2.0, 5.0], [2.0, 1.0, 4.0, 4.0], "peer")
    assert "in 2 of 4 liquids (sign test p = 1)" in mixed, mixed
    low, high = (float(x) for x in mixed.split("interval ")[1].split("-"))
    assert low <= 2.5 / 3.0 <= high, mixed


@pytest.mark.slow  # a benchmark script run whole (kept out of the default run: its compile time)
def test_cluster_kernel_bench_times_the_call_and_refuses_a_small_cell():
    """benchmarks/cluster_kernel.py on a small melt: the machine line, then the call's
    time per cluster pair (per listed pair with --precision double); a cell too small for
    the cutoff exits non-zero, saying why."""
    script = SCRIPT.parent / "cluster_kernel.py"

    def run(*args):
        return subprocess.run(
            [sys.executable, str(script), *args],
            capture_output=True,
            text=True,
            timeout=600,
            cwd=SCRIPT.parents[1],
        )

    done = run("--cells", "6", "--calls", "3")
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("machine: "), done.stdout
    line = done.stdout.splitlines()[-1]
    assert line.startswith("864 atoms, ") and "ns per cluster pair" in line, line
    assert float(line.split("min ")[1].split()[0]) > 0
    double = run("--cells", "6", "--calls", "3", "--precision", "double")
    assert double.returncode == 0, double.stderr
    line = double.stdout.splitlines()[-1]
    assert line.startswith("864 atoms, ") and "ns per listed pair" in line, line
    listed = int(line.split("atoms, ")[1].split()[0])
    assert 864 * 20 < listed < 864 * 60  # half a list within 2.8 sigma at rho* 0.8442: ~38
    refused = run("--cells", "2")
    assert refused.returncode != 0 and "too long for the box" in refused.stderr, refused.stderr
    assert run("--calls", "0").returncode == 2
    assert run("--precision", "single").returncode == 2
    for bad in (("--lanes", "4"), ("--lanes", "8,x"), ("--lanes", "8", "--precision", "double")):
        refused = run("--cells", "6", *bad)
        assert refused.returncode == 2 and "--lanes" in refused.stderr, refused.stderr
    # --windows: the chunks' scratch in lists' worth: more than one list, less than one per
    # chunk, growing with the chunks; the engine's (from the outer list's reach) no smaller
    # than the pruned list's own
    windows = run("--cells", "10", "--windows")
    assert windows.returncode == 0, windows.stderr
    rows = [line.split() for line in windows.stdout.splitlines() if "chunks:" in line]
    worth = {int(row[0]): (float(row[2]), float(row[3].strip("()"))) for row in rows}
    assert sorted(worth) == [2, 4, 8, 16, 64], windows.stdout
    for chunks, (engine, own) in worth.items():
        assert 1.0 < own <= engine < chunks, (chunks, engine, own)
    assert worth[2][0] < worth[64][0]


@pytest.mark.slow  # two cluster kernels compiled in a child process: about 25 s
@pytest.mark.skipif(not md._simd.PERMUTE, reason="16 lanes compile for x86-64 with AVX2 or more")
def test_cluster_kernel_bench_compares_the_row_widths_in_one_process():
    """``--lanes 8,16``: the cluster kernel at both widths, alternated, each the same sum of pair
    terms (energies to float32 round-off of each other), with the per-block ratios."""
    script = SCRIPT.parent / "cluster_kernel.py"
    done = subprocess.run(
        [
            sys.executable,
            str(script),
            "--cells",
            "6",
            "--calls",
            "2",
            "--blocks",
            "2",
            "--lanes",
            "8,16",
        ],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=SCRIPT.parents[1],
    )
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0].startswith("machine: ")
    assert "the cluster kernel alone, 2 alternating" in lines[1], lines
    rows = {int(line.split()[0]): line for line in lines[2:]}
    assert set(rows) == {8, 16}, lines
    energies = {
        lanes: float(line.split("energy ")[1].split(";")[0]) for lanes, line in rows.items()
    }
    assert abs(energies[16] - energies[8]) < 1e-5 * abs(energies[8]), energies
    assert "median 1.000" in rows[8] and float(rows[16].split("median ")[1].split()[0]) > 0


def test_per_repeat_ratios_pair_the_rounds_and_take_their_median(capsys):
    compare = _benchmark_module("compare")

    def measured(engine, variant, threads, loop_times, simd=None):
        job = compare.Job(engine=engine, threads=threads, cells=20, steps=100, variant=variant)
        runs = [
            {"n_atoms": 32000, "loop_time": t, **({"simd": simd} if simd else {})}
            for t in loop_times
        ]
        return compare.Measured(job, runs)

    # rounds 1-3: ours double 1.0, 2.0, 1.0 s; GROMACS double 2.0, 2.0, 4.0 s: ratios 2, 1, 4
    ours = measured("ours", "", 1, [1.0, 2.0, 1.0])
    mixed = measured("ours", "mixed", 1, [0.5, 4.0, 4.0])
    peer = measured("gromacs", "double", 1, [2.0, 2.0, 4.0], simd="AVX_512")
    other_threads = measured("gromacs", "double", 2, [1.0, 1.0, 1.0], simd="AVX_512")
    assert compare.repeat_ratios(peer, ours) == [2.0, 1.0, 4.0]
    compare.print_repeat_ratios([ours, mixed, peer, other_threads])
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("ours / peer per repeat")
    assert any(
        "leapmd / GROMACS double (AVX_512), 1t 32k: median 2.00 (2.00, 1.00, 4.00)" in line
        for line in lines
    ), lines
    # the median of the per-round ratios: 4, 0.5, 1 -> 1, where the ratio of the medians
    # (0.8 M / 1.6 M atom-steps/s) would say 0.5
    assert any(
        "leapmd mixed / GROMACS double (AVX_512), 1t 32k: median 1.00 (4.00, 0.50, 1.00)" in line
        for line in lines
    ), lines
    # no row of ours at 2 threads: the 2-thread peer gets no line
    assert not any(" 2t " in line for line in lines), lines


#: Run in a child: set up two threads, warm up as the worker does, take a timed system's
#: setup force call, then list every numba dispatcher that gained a compiled or loaded
#: version in the 40 steps after it (what the timed loop would pay for).
_LOADS_IN_THE_LOOP = """
import gc, json, sys
sys.path.insert(0, sys.argv[1])
import md
from md.parallel import get_threads, set_threads
from numba.core.dispatcher import Dispatcher

md.keep_freed_memory()
set_threads(2)
if get_threads() < 2:
    print(json.dumps(None))
    sys.exit()
import _compare_worker as worker

def versions():
    return {id(d): (d, len(d.overloads)) for d in gc.get_objects()
            if issubclass(type(d), Dispatcher)}

found = {}
for precision in ("double", "mixed"):
    worker.warm_up(worker.WARMUP_CELLS, precision)
    if sys.argv[2] == "both":
        worker.warm_up(worker.WARMUP_CELLS_THREADED, precision)
    sim = worker._our_simulation(20, precision)
    sim.forcefield.compute(sim.state)  # time_loop's untimed setup
    nl = sim.forcefield.neighbor_list
    builds, prunes, before = nl.n_builds, nl.n_prunes, versions()
    sim.run(40)
    found[precision] = {
        "new": sorted(d.py_func.__qualname__ for key, (d, n) in versions().items()
                      if n > before.get(key, (None, 0))[1]),
        "builds": nl.n_builds - builds, "prunes": nl.n_prunes - prunes}
print(json.dumps(found))
"""


@pytest.mark.slow  # the benchmark's own harness at its 32000 atoms on two threads (~40 s cold)
@pytest.mark.parametrize("warm_ups", ["both", "small"])
def test_the_warm_up_leaves_no_kernel_to_load_in_a_two_thread_timed_loop(warm_ups):
    """On two threads the 32000-atom melt splits its passes over the atoms into chunks,
    whose threaded kernels the 864-atom warm-up never calls: numba loaded them in the
    timed loop's first step (24 ms of a 250 ms run). The worker's second warm-up takes
    them; without it (``small``) the loop still loads them, which shows the check can
    see such a load."""
    done = subprocess.run(
        [sys.executable, "-c", _LOADS_IN_THE_LOOP, str(SCRIPT.parent), warm_ups],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=SCRIPT.parents[1],
    )
    assert done.returncode == 0, done.stderr
    found = json.loads(done.stdout)
    if found is None:
        pytest.skip("numba runs fewer than two threads here")
    # the 40 steps searched and (mixed) pruned: the loop's list paths were taken
    assert found["double"]["builds"] >= 1 and found["mixed"]["builds"] >= 1, found
    assert found["mixed"]["prunes"] >= 1, found
    if warm_ups == "both":
        assert found == {k: {**v, "new": []} for k, v in found.items()}, found
    else:
        assert "_kick_drift_threaded" in found["double"]["new"], found


def test_the_gromacs_rule_adds_our_rows_with_its_list_and_the_ratios_keep_the_exact_ones():
    """``--gromacs-rule``: ours (and ours mixed) once more with GROMACS's list rule (every 20
    steps, no check, skin 0.332), labelled by it; the table's ours/peer and mixed/peer
    columns still take the exact rows."""
    compare = _benchmark_module("compare")
    worker = _benchmark_module("_compare_worker")
    args = compare.build_parser().parse_args(["--mixed", "--gromacs-rule", "--peers", "none"])
    args.threads = [1]  # as main() parses it
    jobs = compare.comparison_jobs(args, set())
    rules = {(j.variant, j.neigh) for j in jobs if j.engine == "ours"}
    assert rules == {("", "check"), ("mixed", "check"), ("", "every20"), ("mixed", "every20")}
    labels = {j.label for j in jobs if j.neigh == "every20"}
    assert labels == {"leapmd (every20)", "leapmd mixed (every20)"}
    assert worker.GROMACS_RULE == {"every": 20, "check": False, "skin": 0.332}
    with pytest.raises(ValueError, match="unknown list rule 'every5'"):
        worker._our_simulation(3, neigh="every5")

    def measured(variant, neigh, loop_time):
        job = compare.Job("ours", 1, 20, 100, variant, neigh=neigh)
        return compare.Measured(job, [{"n_atoms": 32000, "loop_time": loop_time}])

    peer = compare.Measured(
        compare.Job("gromacs", 1, 20, 100, "mixed"), [{"n_atoms": 32000, "loop_time": 1.0}]
    )
    rows = [measured("mixed", "every20", 0.5), measured("mixed", "check", 2.0), peer]
    assert compare.ratio_to_ours(peer, rows, "mixed") == 0.5  # the exact row's, not 2.0


def _scaling_runs(module, model, here, cells, ranks: int, steps: int = 100) -> object:
    """A ``mpi_scaling.Measured`` of one run whose times are ``model``'s for ``cells`` on
    ``ranks``: the loop its step time, the rank's own work c(n) n (1 + h g), the
    rebuilds gamma n (1 + g) each."""
    job = module.Job(model.name, tuple(cells), steps, ranks, 1)
    n = job.n_atoms / ranks
    ghosts = model.ghosts(cells, ranks)[0] if ranks > 1 else 0.0
    own = model.cost(n) * n * (1 + model.ghost_cost * ghosts)
    builds = round(model.builds * steps)
    run = {
        "n_steps": steps,
        "loop_time": model.step(cells, ranks, *here) * steps,
        "sections": {
            "force": own * steps,
            "neighbor": 0.0,
            "integrate": 0.0,
            "rebuild_comm": model.rebuild * builds * n * (1 + ghosts),
        },
        "n_builds": builds,
        "local_atoms": [[n, ghosts * n]] * ranks,
    }
    return module.Measured(job, [run])


def test_the_mpi_scaling_model_gives_back_the_costs_its_runs_were_made_with():
    """benchmarks/mpi_scaling.py's model of a decomposed step (StepModel): calibrated on
    runs made from a model of known costs (the 1152-, 32000- and 2M-atom melts on 1 and 2
    ranks), it finds those costs again, so also its efficiency at any P; a brick of ours
    has ghost shells on the faces of its cut axes only, LAMMPS's on all six (the
    periodic images of the uncut ones)."""
    module = _benchmark_module("mpi_scaling")
    here = (3.5e-6, 3.2e9)
    truth = module.StepModel(
        "ours",
        images=False,
        per_atom={1152: 2.2e-7, 32000: 2.0e-7, 2048000: 2.25e-7},
        ghost_cost=0.7,
        decomposed_fixed=4e-4,
        rebuild=2.5e-8,
        builds=0.2,
    )
    cells = [module.TINY_CELLS, *(c for _, c, _ in module.SIZES[False])]
    measured = {}
    for size in cells:
        for ranks in (1, 2):
            item = _scaling_runs(module, truth, here, size, ranks)
            measured[item.job] = item
    found = module.calibrate("ours", measured, False, here)
    assert found.per_atom == pytest.approx(truth.per_atom, rel=1e-9)
    for name in ("ghost_cost", "decomposed_fixed", "rebuild", "builds"):
        assert getattr(found, name) == pytest.approx(getattr(truth, name), rel=1e-9), name
    assert found.cost(2000) == found.per_atom[1152]  # the nearest measured size
    assert found.cost(700_000) == found.per_atom[2048000]
    big = module.SIZES[False][-1][1]
    one, many = found.step(big, 1, *here), found.step(big, 64, *here)
    assert found.efficiency(big, 64, *here) == pytest.approx(one / (64 * many), rel=1e-12)
    assert found.efficiency(big, 1024, *here) < found.efficiency(big, 64, *here) < 1.0
    box = module.melt_box((80, 80, 80))
    lx = box[0] / 2
    assert module.ghosts_per_atom(box, (2, 1, 1), images=False) == pytest.approx(
        2 * module.SHELL / lx, rel=1e-12
    )
    shells = (lx + 2 * module.SHELL) * (box[1] + 2 * module.SHELL) ** 2
    assert module.ghosts_per_atom(box, (2, 1, 1)) == pytest.approx(
        shells / (lx * box[1] ** 2) - 1, rel=1e-12
    )
