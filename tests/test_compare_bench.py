"""The benchmark harness benchmarks/compare.py: a smoke run and its input checks.

Speed is never asserted here; the harness prints timings, and these tests
check that it runs the workload (the LJ melt at reduced density 0.8442) and
reports it, and that bad options are refused with exit code 2.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

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


def test_bad_threads_is_refused():
    done = run_compare("--quick", "--peers", "none", "--threads", "0")
    assert done.returncode == 2
    assert "--threads" in done.stderr


def test_unknown_peer_is_refused():
    done = run_compare("--quick", "--peers", "gromacs")
    assert done.returncode == 2
    assert "gromacs" in done.stderr


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
        "implicit.py": ["--cells", "5", "--steps", "1", "--repeats", "1", "--skip-polymer",
                        "--chain-span", "0.02"],
        "npt.py": ["--cells", "5", "--steps", "5", "--repeats", "1"],
    }  # fmt: skip
    for script, args in runs.items():
        done = subprocess.run(
            [sys.executable, str(bench / script), *args],
            capture_output=True, text=True, timeout=300, cwd=bench.parent,
        )  # fmt: skip
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
        [sys.executable, str(bench / "lj_melt.py"), "--cells", "5", "--steps", "5",
         "--repeats", "1", "--threads", "2"],
        capture_output=True, text=True, timeout=300, cwd=bench.parent,
    )  # fmt: skip
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
