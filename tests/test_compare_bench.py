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

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "compare.py"


def run_compare(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(SCRIPT), *args],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=SCRIPT.parents[1],
    )


def test_quick_run_prints_a_row_for_ours(tmp_path):
    report = tmp_path / "report.json"
    done = run_compare("--quick", "--peers", "none", "--json", str(report))
    assert done.returncode == 0, done.stderr
    rows = [line.split() for line in done.stdout.splitlines() if line.startswith("leapmd ")]
    # engine, threads, atoms, steps, rate: one row per thread count in each table.
    assert any(row[1] == "1" and row[2] == "864" for row in rows), done.stdout
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
