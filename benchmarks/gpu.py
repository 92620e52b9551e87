"""The LJ melt on one NVIDIA GPU (``device = "cuda"``, md.cuda), beside our CPU path.

Prints the GPU model, the driver and numba-cuda versions; then, per size (64000, 256000,
2,048,000 and 16,384,000 atoms: fcc at reduced density 0.8442, T* 3.0, LJ cut at 2.5 sigma,
skin 0.3, NVE velocity Verlet, dt 0.005) and precision (double, mixed): atom-steps/s and
ns/day of the melt in argon units (tau = 2.156 ps), the median of repeats after a warm-up
that compiles; the time of one step split by kernel (CUDA events: the integrator's passes,
with the list's displacement check fused into them; the wait for the rebuild flag and the
rebuilds; the force kernels), the launches per step and the host's time per step; the cost
of one kernel launch from Python; and our CPU path on one thread on the same host (a few
steps: it is slow at these sizes).

    python3 benchmarks/gpu.py            # every size
    python3 benchmarks/gpu.py --quick    # 64000 and 2M atoms, then pytest -m cuda
    NUMBA_ENABLE_CUDASIM=1 python3 benchmarks/gpu.py --smoke   # 108 atoms, the simulator

``--quick`` is sized for a short loan of a GPU machine: the two rows, compilation included,
and the ``cuda``-marked tests, in a few minutes. The GPU rows come first, each printed as it
is measured (with its warm-up time: compilation and the first list), the CPU rows after
them, so that a loan that ends early still has the GPU figures; a row that fails prints
its error and the others still run (the exit code is then 1). The kernels are compiled once
per process (``md.cuda`` keeps them per term and precision), so the second size costs no
compilation. ``--smoke`` runs every part at a tiny size (108 atoms, LJ cut at 1.2, a few
steps) for a test on numba's CUDA simulator, whose figures mean nothing. Without
numba-cuda or a GPU (and without the simulator asked for) it says so and exits 0.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SIZES = {64_000: 25, 256_000: 40, 2_048_000: 80, 16_384_000: 160}  # atoms: fcc cells
QUICK = (64_000, 2_048_000)
ARGON_TAU_PS = 2.156
DT = 0.005


def _gpu():
    """numba.cuda if a GPU is there, else None (after saying why)."""
    try:
        from numba import cuda
    except ImportError:
        print("numba-cuda is not installed (pip install 'leapmd[cuda]'): no GPU figures")
        return None
    if os.environ.get("NUMBA_ENABLE_CUDASIM", "0") not in ("", "0"):
        print("numba's CUDA simulator (NUMBA_ENABLE_CUDASIM=1): a smoke test, no GPU figures")
        return cuda
    if not cuda.is_available():
        print("no NVIDIA GPU found (numba-cuda sees no CUDA driver or device): no GPU figures")
        return None
    return cuda


def _header(cuda) -> None:
    device = cuda.get_current_device()
    name = getattr(device, "name", "numba's CUDA simulator")
    name = name.decode() if isinstance(name, bytes) else name
    capability = getattr(device, "compute_capability", "?")
    print(f"GPU: {name}, compute capability {capability}")
    driver = _asked(lambda: cuda.cudadrv.driver.driver.get_version())
    runtime = _asked(lambda: cuda.runtime.get_version())
    print(f"CUDA driver API {driver}, runtime {runtime}")
    smi = ["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"]
    print(f"NVIDIA driver {_asked(lambda: subprocess.run(smi, capture_output=True).stdout)}")
    print(f"numba-cuda {_version('numba-cuda')}, numba {_version('numba')}")


def _asked(function) -> str:
    """What ``function()`` returns, or "?" where it cannot tell (the simulator, no tool)."""
    try:
        value = function()
        return value.decode().strip() if isinstance(value, bytes) else str(value)
    except Exception:  # noqa: BLE001 (any failure only means the figure is unknown)
        return "?"


def _version(package: str) -> str:
    try:
        return importlib.metadata.version(package)
    except importlib.metadata.PackageNotFoundError:
        return "?"


def _melt(cells: int, device: str, precision: str, cutoff: float, threads: int | None = None):
    from integrators import VelocityVerlet
    from md.build import lattice, maxwell_boltzmann
    from md.simulation import Simulation
    from potentials import LennardJones

    state = maxwell_boltzmann(lattice("fcc", cells, density=0.8442), 3.0, seed=1)
    return Simulation(
        state,
        [LennardJones(cutoff=cutoff)],
        VelocityVerlet(dt=DT),
        skin=0.3,
        precision=precision,
        device=device,
        threads=threads,
    )


def _rate(sim, steps: int, repeats: int) -> list[float]:
    """Atom-steps/s of ``repeats`` runs of ``steps`` (each run uploads and copies back)."""
    n = sim.state.n_atoms
    rates = []
    for _ in range(repeats):
        start = time.perf_counter()
        sim.run(steps)
        rates.append(n * steps / (time.perf_counter() - start))
    return rates


def _split(sim, steps: int) -> tuple[dict[str, float], float, float]:
    """Milliseconds per step by kernel group, over ``steps`` steps of the run's own engine
    (its compiled kernels) timed by CUDA events; the kernel launches per step (the list's
    rebuilds among them); and the host's milliseconds per step of the untimed steps that
    follow (each ends in the four-byte read of the rebuild flag, so the host waits for the
    device there: where this exceeds the events' sum, the launches from Python bound the
    step)."""
    engine = sim.device_engine
    engine.start(sim.state)
    total: dict[str, float] = {}
    before = engine.n_launches
    for _ in range(steps):
        for name, ms in engine.timed_step(sim.state).items():
            total[name] = total.get(name, 0.0) + ms / steps
    launches = (engine.n_launches - before) / steps
    start = time.perf_counter()
    for _ in range(steps):
        engine.step(sim.state)
    host = 1e3 * (time.perf_counter() - start) / steps
    engine.finish(sim.state)
    return total, launches, host


def _launch_cost(cuda, launches: int) -> float:
    """Microseconds per launch of an empty kernel from Python (one block of 32 threads;
    a kernel of a dozen arguments costs more: the rows' launches column and the host's time
    per step show the whole step's)."""

    @cuda.jit
    def empty(x):
        pass

    x = cuda.device_array(1)
    empty[1, 32](x)
    cuda.synchronize()
    start = time.perf_counter()
    for _ in range(launches):
        empty[1, 32](x)
    cuda.synchronize()
    return 1e6 * (time.perf_counter() - start) / launches


def _gpu_row(n: int, cells: int, precision: str, args) -> float | None:
    """Measure and print one GPU row; its rate (None if it failed, after printing why)."""
    try:
        start = time.perf_counter()
        sim = _melt(cells, "cuda", precision, args.cutoff)
        sim.run(args.warmup)  # compiles (the first size only), builds the first list
        warmup = time.perf_counter() - start
        rate = statistics.median(_rate(sim, args.steps, args.repeats))
        split, per_step, host = _split(sim, args.split_steps)
        del sim
    except Exception as error:  # noqa: BLE001 (one row's failure must not end the loan)
        print(f"{n:>11,} {precision:>9}  FAILED: {type(error).__name__}: {error}", flush=True)
        return None
    shown = ", ".join(f"{k} {v:.3f}" for k, v in split.items())
    shown += f"; sum {sum(split.values()):.3f}, host {host:.3f}"
    ns_day = rate / n * DT * ARGON_TAU_PS / 1000.0 * 86400
    print(
        f"{n:>11,} {precision:>9} {rate:>13.3e} {ns_day:>8.1f} {warmup:>9.1f} "
        f"{per_step:>9.2f}  {shown}",
        flush=True,
    )
    return rate


def _cpu_row(n: int, cells: int, args, gpu: dict) -> bool:
    """Measure and print our CPU path on one thread at this size, beside the GPU rows."""
    try:
        start = time.perf_counter()
        cpu = _melt(cells, "cpu", "double", args.cutoff, threads=1)
        cpu.run(1)  # compiles, builds the first list
        warmup = time.perf_counter() - start
        rate = statistics.median(_rate(cpu, args.cpu_steps, 1))
        del cpu
    except Exception as error:  # noqa: BLE001 (as a GPU row's)
        print(f"{n:>11,}  CPU FAILED: {type(error).__name__}: {error}", flush=True)
        return False
    ratios = ", ".join(
        f"{precision} {gpu[n, precision] / rate:.1f}x"
        for precision in ("double", "mixed")
        if gpu.get((n, precision))
    )
    print(f"{n:>11,} {rate:>13.3e} {warmup:>9.1f}  GPU/CPU: {ratios or '-'}", flush=True)
    return True


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="64000 and 2M atoms, cuda tests")
    parser.add_argument("--smoke", action="store_true", help="every part at a tiny size")
    parser.add_argument("--steps", type=int, default=200, help="steps per timed run")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--warmup", type=int, default=10, help="steps before the timed runs")
    parser.add_argument("--split-steps", type=int, default=20, help="steps timed by kernel")
    parser.add_argument("--cpu-steps", type=int, default=5, help="steps of the CPU row")
    parser.add_argument("--launches", type=int, default=2000, help="launches timed")
    parser.add_argument("--cells", type=int, help="one size: fcc cells per edge")
    parser.add_argument("--cutoff", type=float, default=2.5, help="LJ cutoff [sigma]")
    args = parser.parse_args(argv)
    if args.smoke:
        args.cells, args.cutoff, args.steps, args.repeats = 3, 1.2, 2, 1
        args.warmup = args.split_steps = args.cpu_steps = 1
        args.launches = 5
    cuda = _gpu()
    if cuda is None:
        return 0
    began = time.perf_counter()
    _header(cuda)
    print(f"kernel launch from Python: {_launch_cost(cuda, args.launches):.2f} us", flush=True)
    sizes = {n: SIZES[n] for n in (QUICK if args.quick else SIZES)}
    if args.cells is not None:
        sizes = {4 * args.cells**3: args.cells}
    print(
        f"\nLJ melt, cut at {args.cutoff} sigma, NVE velocity Verlet; on the GPU:\n"
        f"{'atoms':>11} {'precision':>9} {'atom-steps/s':>13} {'ns/day':>8} {'warm-up s':>9} "
        f"{'launches':>9}  step split (ms)"
    )
    gpu: dict = {}
    for n, cells in sizes.items():
        for precision in ("double", "mixed"):
            gpu[n, precision] = _gpu_row(n, cells, precision, args)
    print(f"\nour CPU path, one thread:\n{'atoms':>11} {'atom-steps/s':>13} {'warm-up s':>9}")
    cpu_ok = [_cpu_row(n, cells, args, gpu) for n, cells in sizes.items()]
    failed = not all(cpu_ok) or None in gpu.values()
    print(f"\n(benchmark wall time {time.perf_counter() - began:.0f} s)", flush=True)
    if args.quick:
        print("\npytest -m cuda tests/test_gpu.py tests/test_gpu_more.py:", flush=True)
        tests = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", "cuda"]
        tests += ["tests/test_gpu.py", "tests/test_gpu_more.py"]
        failed = subprocess.run(tests, cwd=ROOT).returncode != 0 or failed
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
