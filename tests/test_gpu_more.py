"""The GPU path, second part: a CPU checkpoint resumed on the device, the device run's own
summary, the tuning of the device step (the sort along the cells' Morton curve, the block
scan of the cell counts, the fused passes' launches per step) and the GPU benchmark's
smoke test, all on numba's CUDA simulator (``tests/_gpu_checks.py --more`` in a
subprocess, as ``tests/test_gpu.py`` runs the rest), and on a real GPU for the tests
marked ``cuda``.
"""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from test_gpu import HAVE_NUMBA_CUDA, ROOT, _checks, _gpu_present

#: Launches of a step that does not rebuild the list (one pair potential): docs/guide/gpu.md.
LAUNCHES = {"verlet": 3, "leapfrog": 3, "bussi": 4, "langevin": 6}


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    if not HAVE_NUMBA_CUDA:
        pytest.skip("numba-cuda not installed")
    return _checks(tmp_path_factory, True, "--more")


@pytest.fixture(scope="module")
def on_gpu(tmp_path_factory):
    if not _gpu_present():
        pytest.skip("no NVIDIA GPU")
    return _checks(tmp_path_factory, False, "--more")


def _judge_resume(results: dict) -> None:
    for name in ("leapfrog", "langevin"):
        assert results[f"resume_{name}_codes"] == [0] * 3, name
        assert results[f"resume_{name}_said_gpu"], name
        assert results[f"resume_{name}_frames"] == [5, 5], name
        # a CPU checkpoint continued on the device: the CPU's continuation, to round-off
        assert results[f"resume_{name}_position"] < 1e-12, name
        assert results[f"resume_{name}_velocity"] < 1e-12, name
        assert results[f"resume_{name}_energies"] < 1e-12, name


def _judge_summary(results: dict) -> None:
    assert results["summary_code"] == 0
    on_gpu, on_cpu = results["summary_builds"]
    # the device's own builds (the CPU list's were reported before: one at the start and
    # one for the last thermo row), the same as the CPU's over the same steps
    assert on_cpu > 2
    assert on_gpu == on_cpu
    lines = results["summary_lines"]
    assert any(line.startswith("device ") for line in lines)  # one section for the steps
    assert not any(line.startswith(("force ", "neighbor ")) for line in lines)
    assert not any("thread(s)" in line for line in lines)


def _judge_tuning(results: dict) -> None:
    assert min(results["sort_grid"]) >= 3
    assert results["sort_morton_ordered"]
    assert not results["sort_row_major_ordered"]  # the curve, not the plain cell order
    assert results["sort_cells_keep_order"]
    assert results["scan_error"] == 0
    assert results["launches_per_step"] == LAUNCHES
    for name in ("verlet_mixed", "leapfrog", "bussi", "langevin"):
        assert results[f"sorted_{name}_sorts"] > 2, name  # sorted again within the run
        limit = 1e-6 if "mixed" in name else 1e-10  # mixed: float32 terms, 8 steps
        assert results[f"sorted_{name}_positions"] < limit, name
        assert results[f"sorted_{name}_velocities"] < limit, name


def test_a_cpu_checkpoint_resumes_on_the_device_to_round_off(simulated):
    _judge_resume(simulated)


def test_a_device_run_reports_its_own_list_builds(simulated):
    _judge_summary(simulated)


def test_the_device_sorts_along_a_morton_curve_scans_in_parallel_and_fuses_passes(simulated):
    _judge_tuning(simulated)


@pytest.mark.cuda
def test_the_same_on_a_gpu(on_gpu):
    _judge_resume(on_gpu)
    _judge_summary(on_gpu)
    _judge_tuning(on_gpu)


@pytest.mark.slow
@pytest.mark.skipif(not HAVE_NUMBA_CUDA, reason="numba-cuda not installed")
def test_every_kernel_is_typed_and_lowered_by_the_gpu_target(tmp_path_factory):
    """Where NVVM or NVRTC is missing (and ``tests/test_gpu.py``'s compile for sm_90 is
    skipped), every kernel still goes through the CUDA target's typing and lowering to
    LLVM IR, which the simulator skips (it runs the Python); one that uses ``np.rint`` is
    rejected there. Slow (half a minute of compiling): run with ``-m slow``."""
    results = _checks(tmp_path_factory, False, "--lower")
    assert results["ptx_nvvm"] is True, results["ptx_nvvm"]
    assert results["ptx_rejects_rint"]
    assert results["ptx_failed"] == {}
    assert len(results["ptx_compiled"]) == 16 + 2 * 7 + 1 + 4


@pytest.mark.skipif(not HAVE_NUMBA_CUDA, reason="numba-cuda not installed")
def test_the_gpu_benchmark_runs_on_the_simulator(tmp_path):
    """``benchmarks/gpu.py`` at a tiny size under the simulator: every figure printed, no
    crash path left for a short GPU loan to find."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "NUMBA_ENABLE_CUDASIM": "1"}
    command = [sys.executable, str(ROOT / "benchmarks" / "gpu.py"), "--smoke"]
    done = subprocess.run(command, env=env, cwd=tmp_path, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    out = done.stdout
    for shown in ("GPU:", "numba-cuda", "kernel launch from Python", "atom-steps/s", "ns/day"):
        assert shown in out, shown
    rows = [line.split() for line in out.splitlines() if line.strip().startswith("108 ")]
    gpu = [row for row in rows if row[1] in ("double", "mixed")]
    assert [row[1] for row in gpu] == ["double", "mixed"], out
    for row in gpu:
        assert {"forces", "integrate", "neighbors"} <= set(row), row
        assert float(row[2]) > 0 and float(row[5]) >= 3  # atom-steps/s; launches a step
    assert len(rows) == 3 and "GPU/CPU:" in rows[2], out  # the CPU row beside them
