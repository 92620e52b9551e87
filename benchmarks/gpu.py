"""The LJ melt on one NVIDIA GPU (``device = "cuda"``, md.cuda), beside our CPU path.

Prints the GPU model, the driver and numba-cuda versions; then, per size (64000, 256000,
2,048,000 and 16,384,000 atoms: fcc at reduced density 0.8442, T* 3.0, LJ cut at 2.5 sigma,
skin 0.3, NVE velocity Verlet, dt 0.005) and precision (double, mixed): atom-steps/s and
ns/day of the melt in argon units (tau = 2.156 ps), the median of repeats after a warm-up
that compiles; the time of one step split by kernel (CUDA events: integrator passes, the
list's check and rebuilds, the force kernels); the cost of one kernel launch from Python;
and our CPU path on one thread on the same host (a few steps: it is slow at these sizes).

    python3 benchmarks/gpu.py            # every size
    python3 benchmarks/gpu.py --quick    # 64000 and 2M atoms, then pytest -m cuda

``--quick`` is sized for a short loan of a GPU machine: the two rows, compilation included,
and the ``cuda``-marked tests, in a few minutes. Without numba-cuda or a GPU it says so and
exits 0.
"""

from __future__ import annotations

import argparse
import importlib.metadata
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


def _melt(cells: int, device: str, precision: str, threads: int | None = None):
    from integrators import VelocityVerlet
    from md.build import lattice, maxwell_boltzmann
    from md.simulation import Simulation
    from potentials import LennardJones

    state = maxwell_boltzmann(lattice("fcc", cells, density=0.8442), 3.0, seed=1)
    return Simulation(
        state,
        [LennardJones(cutoff=2.5)],
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


def _split(sim, steps: int = 20) -> dict[str, float]:
    """Milliseconds per step by kernel group, over ``steps`` timed steps."""
    from md.cuda.engine import DeviceEngine

    engine = DeviceEngine(sim.state, sim.forcefield, sim.integrator)
    engine.start(sim.state)
    total: dict[str, float] = {}
    for _ in range(steps):
        for name, ms in engine.timed_step(sim.state).items():
            total[name] = total.get(name, 0.0) + ms / steps
    engine.finish(sim.state)
    return total


def _launch_cost(cuda, launches: int = 2000) -> float:
    """Microseconds per launch of an empty kernel from Python (one block of 32 threads)."""

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


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="64000 and 2M atoms, cuda tests")
    parser.add_argument("--steps", type=int, default=200, help="steps per timed run")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--cpu-steps", type=int, default=5, help="steps of the CPU row")
    parser.add_argument("--cells", type=int, help="one size: fcc cells per edge (a smoke test)")
    args = parser.parse_args(argv)
    cuda = _gpu()
    if cuda is None:
        return 0
    _header(cuda)
    print(f"kernel launch from Python: {_launch_cost(cuda):.2f} us")
    sizes = QUICK if args.quick else tuple(SIZES)
    if args.cells is not None:
        SIZES[4 * args.cells**3] = args.cells
        sizes = (4 * args.cells**3,)
    ns_per_step = DT * ARGON_TAU_PS / 1000.0
    print(
        f"\n{'atoms':>11} {'precision':>9} {'atom-steps/s':>13} {'ns/day':>8} "
        f"{'CPU 1 thread':>13} {'GPU/CPU':>8}  step split (ms)"
    )
    for n in sizes:
        cpu = _melt(SIZES[n], "cpu", "double", threads=1)
        cpu.run(1)  # compiles
        cpu_rate = statistics.median(_rate(cpu, args.cpu_steps, 1))
        del cpu
        for precision in ("double", "mixed"):
            sim = _melt(SIZES[n], "cuda", precision)
            sim.run(10)  # compiles, builds the first list
            rate = statistics.median(_rate(sim, args.steps, args.repeats))
            split = _split(sim)
            shown = ", ".join(f"{k} {v:.3f}" for k, v in split.items())
            ns_day = rate / n * ns_per_step * 86400
            print(
                f"{n:>11,} {precision:>9} {rate:>13.3e} {ns_day:>8.1f} {cpu_rate:>13.3e} "
                f"{rate / cpu_rate:>8.1f}  {shown}",
                flush=True,
            )
            del sim
    if args.quick:
        print("\npytest -m cuda tests/test_gpu.py:", flush=True)
        tests = [sys.executable, "-m", "pytest", "-q", "-m", "cuda", "tests/test_gpu.py"]
        return subprocess.run(tests, cwd=ROOT).returncode
    return 0


if __name__ == "__main__":
    sys.exit(main())
