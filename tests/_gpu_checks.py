"""The GPU path against the CPU path, run as a script: ``python3 tests/_gpu_checks.py OUT``
(``OUT --ptx``: every kernel compiled for the GPU target instead, without a GPU; ``OUT
--lower``: the same, only typed and lowered to LLVM IR, where NVVM is missing; ``OUT
--more``: the checks of ``tests/test_gpu_more.py`` instead).

``tests/test_gpu.py`` runs it in a subprocess, on numba's CUDA simulator
(``NUMBA_ENABLE_CUDASIM=1``, which numba reads when ``numba.cuda`` is first imported, so
not in the test process) and, for the tests marked ``cuda``, on a real GPU; it writes the
measured differences as JSON to OUT for the tests to judge. Systems are tiny (the
simulator runs each GPU thread as a Python thread), and on the simulator the blocks of a
kernel that never syncs run their threads in order in one thread (:func:`_lighter_launches`:
the same kernels' Python, half the checks' CPU time).
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import sys
import tempfile
import threading
import time
import warnings
from pathlib import Path

#: sys.setswitchinterval on the simulator (seconds; Python's default is 0.005).
SIMULATOR_SWITCH_INTERVAL = 0.0005


#: Names whose use makes a kernel's threads cooperate within a block (barriers, warp
#: votes and shuffles): such a kernel needs the simulator's one Python thread per GPU thread.
_COOPERATIVE = ("sync", "shfl", "ballot", "activemask", "lanemask", "match_", "cg")


def _cooperates(function, seen: set | None = None) -> bool:
    """Whether ``function`` (a kernel's Python function under the simulator) or a device
    function it reaches through its globals or closure calls a block barrier or a warp
    primitive. Unsure (no code object): True."""
    seen = set() if seen is None else seen
    if id(function) in seen:
        return False
    seen.add(id(function))
    code = getattr(function, "__code__", None)
    if code is None:
        return True
    names, stack = set(), [code]
    while stack:
        item = stack.pop()
        names.update(item.co_names)
        stack.extend(c for c in item.co_consts if hasattr(c, "co_names"))
    if any(name.startswith(_COOPERATIVE) for name in names):
        return True
    reached = [function.__globals__.get(name) for name in names]
    reached += [cell.cell_contents for cell in function.__closure__ or ()]
    for item in reached:
        inner = getattr(item, "fn", None)  # a simulated device function
        if callable(inner) and _cooperates(inner, seen):
            return True
    return False


def _lighter_launches() -> bool:
    """On numba's CUDA simulator, run the threads of a block whose kernel never cooperates
    (no barrier, no warp primitive: see :func:`_cooperates`) one after another in this
    thread, in thread order (one of the schedules a GPU may take), instead of starting a
    Python thread per GPU thread and polling them; kernels that cooperate still get the
    simulator's threads. The kernels' Python runs unchanged. A test-only speed-up of the
    checks (numba-cuda 0.30's simulator internals); False, and nothing changed, where
    those internals differ."""
    import numpy as np

    try:
        from numba.cuda.simulator import kernel
        from numba.cuda.simulator.kernelapi import Dim3
    except ImportError:
        return False
    manager = getattr(kernel, "BlockManager", None)
    threaded = getattr(manager, "run", None)
    if threaded is None or not hasattr(manager, "__init__"):
        return False
    decided: dict = {}

    def run(self, grid_point, *args):
        function = self._f
        if function not in decided:
            decided[function] = _cooperates(function)
        if decided[function] or self._debug:
            return threaded(self, grid_point, *args)
        here = threading.current_thread()
        here.blockIdx = Dim3(*grid_point)
        x, y, _ = self._block_dim
        try:
            for point in np.ndindex(*self._block_dim):
                here.threadIdx = Dim3(*point)
                here.thread_id = point[0] + x * (point[1] + y * point[2])
                function(*args)
        finally:
            del here.blockIdx, here.threadIdx, here.thread_id
        return None

    manager.run = run
    swap = getattr(kernel, "swapped_cuda_module", None)
    if swap is not None:
        kernel.swapped_cuda_module = _swap_where_needed(swap)
    return True


def _swap_where_needed(swap):
    """The simulator's ``swapped_cuda_module``, which points a function's module globals
    that name ``numba.cuda`` at the launch's fake module (scanning those globals at every
    call of a device function), skipped for globals that name no CUDA module (a pair
    term's arithmetic): the same calls, without the scan."""
    import contextlib

    from numba import cuda

    plain: dict = {}

    def swapped(function, fake):
        names = function.__globals__
        key = (id(names), len(names))
        if key not in plain:
            plain[key] = not any(v is cuda or v is fake for v in names.values())
        if plain[key]:
            return contextlib.nullcontext()
        return swap(function, fake)

    return swapped


def _states():
    """Two small periodic LJ systems: 108 atoms in 3 x 3 x 3 cells (the cell search; in
    shuffled order, which the device's sort by cell changes), and
    32 atoms (perturbed) of two types (the O(N^2) search)."""
    import numpy as np

    from md.build import lattice, maxwell_boltzmann

    cells = maxwell_boltzmann(lattice("fcc", 3, density=0.5), 1.0, seed=3)
    shuffled = np.random.default_rng(6).permutation(cells.n_atoms)  # far from cell order
    cells.positions[:] = cells.positions[shuffled]
    cells.velocities[:] = cells.velocities[shuffled]
    small = maxwell_boltzmann(lattice("fcc", 2, density=0.9), 1.5, seed=4)
    rng = np.random.default_rng(5)
    small.positions += rng.normal(0.0, 0.05, small.positions.shape)
    small.types = (np.arange(small.n_atoms) % 2).astype(np.int32)
    small.type_names = ["A", "B"]
    return cells, small


def _relative(a, b) -> float:
    import numpy as np

    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))


def check_lists(results: dict) -> None:
    """The device list against the O(N^2) pairs within the list radius, both searches;
    the sums over one block and over several."""
    import numpy as np
    from numba import cuda

    from md.cuda.engine import DeviceEngine
    from md.forcefield import ForceField
    from potentials import LennardJones

    for name, state, cutoff in zip(("cells", "all_pairs"), _states(), (1.7, 1.3), strict=True):
        forcefield = ForceField([LennardJones(cutoff=cutoff)], skin=0.3)
        engine = DeviceEngine(state, forcefield, None)
        engine.start(state)
        counts = engine.arrays["counts"].copy_to_host()
        neighbors = engine.arrays["neighbors"].copy_to_host()
        user = engine.perm  # device row d holds atom user[d] (sorted by cell at the build)
        results[f"list_{name}_sorted"] = bool(np.any(user != np.arange(state.n_atoms)))
        found = {
            (int(user[i]), int(user[neighbors[k, i]]))
            for i in range(state.n_atoms)
            for k in range(counts[i])
        }
        d = state.positions[:, None, :] - state.positions[None, :, :]
        d -= state.box * np.rint(d / state.box)
        r2 = np.sum(d * d, axis=2)
        n = state.n_atoms
        radius2 = (cutoff + 0.3) ** 2
        expected = {(i, j) for i in range(n) for j in range(n) if i != j and r2[i, j] < radius2}
        results[f"list_{name}_used_cells"] = bool(engine.use_cells)
        results[f"list_{name}_missing"] = len(expected - found)
        results[f"list_{name}_extra"] = len(found - expected)
        results[f"list_{name}_pairs"] = len(expected)
        # the sums over three blocks of 64 threads (108 atoms take one by default): two
        # blocks hold atoms; the totals as the CPU's
        one = engine.result()
        engine.sum_blocks = 3
        engine.arrays["partial"] = cuda.device_array((3, 8))
        three = engine.result()
        cpu = forcefield.compute(state)
        results[f"sums_{name}_blocks"] = max(
            abs(x.energy - cpu.energy) / abs(cpu.energy) for x in (one, three)
        )


def check_forces(results: dict) -> None:
    """Device forces, energy and virial against the CPU path's, every cutoff mode, two
    terms, two types, double and mixed precision."""
    from md.cuda.engine import DeviceEngine
    from md.forcefield import ForceField
    from potentials import LennardJones, Morse

    _, small = _states()
    cases = {
        "lj_shift": lambda: [LennardJones(cutoff=1.3)],
        "lj_smooth_2types": lambda: [
            LennardJones(
                cutoff=1.3,
                cutoff_mode="smooth",
                pairs={(0, 1): {"epsilon": 0.5, "sigma": 0.9}},
            )
        ],
        "morse_none_plus_lj": lambda: [
            Morse(d0=0.3, alpha=2.0, r0=1.0, cutoff=1.25, cutoff_mode="none"),
            LennardJones(cutoff=1.1),
        ],
    }
    for precision in ("double", "mixed"):
        for name, potentials in cases.items():
            forcefield = ForceField(potentials(), skin=0.3, precision=precision)
            cpu = forcefield.compute(small)
            engine = DeviceEngine(small, ForceField(potentials(), 0.3, precision), None)
            engine.start(small)
            gpu = engine.result()
            key = f"forces_{precision}_{name}"
            results[key + "_force"] = _relative(gpu.forces, cpu.forces)
            results[key + "_energy"] = abs(gpu.energy - cpu.energy) / abs(cpu.energy)
            results[key + "_virial"] = _relative(gpu.virial, cpu.virial)


def check_runs(results: dict) -> None:
    """Velocity Verlet, leapfrog, Langevin and Bussi runs, and their thermo (the bath's
    energy too), against the CPU's: Langevin's noise is keyed by seed, step and atom id on
    both, Bussi's drawn from the integrator's one stream on the host."""
    from integrators import Bussi, Langevin, Leapfrog, VelocityVerlet
    from md.simulation import Simulation
    from potentials import LennardJones

    def langevin(dt):
        return Langevin(dt=dt, temperature=1.2, friction=2.0, seed=7)

    def bussi(dt):
        return Bussi(dt=dt, temperature=1.2, tau=0.05, seed=8)

    for name, integrator, index, steps in (
        ("verlet", VelocityVerlet, 1, 100),
        ("verlet_cells", VelocityVerlet, 0, 30),
        ("leapfrog", Leapfrog, 1, 30),
        ("langevin", langevin, 1, 30),
        ("bussi", bussi, 1, 30),
    ):
        states = [_states()[index] for _ in range(2)]
        cutoff = (1.7, 1.3)[index]
        runs = [
            Simulation(s, [LennardJones(cutoff=cutoff)], integrator(dt=0.005), device=device)
            for s, device in zip(states, ("cpu", "cuda"), strict=True)
        ]
        seen = []
        runs[1].attach(lambda sim, seen=seen: seen.append(sim.thermo()), interval=10)
        for sim in runs:
            sim.run(steps // 2)
            sim.run(steps - steps // 2)  # two runs: the device state is uploaded again
        cpu, gpu = states
        results[f"run_{name}_positions"] = _relative(gpu.positions, cpu.positions)
        results[f"run_{name}_velocities"] = _relative(gpu.velocities, cpu.velocities)
        results[f"run_{name}_steps"] = [gpu.step, cpu.step, gpu.time == cpu.time]
        thermo_cpu, thermo_gpu = runs[0].thermo(), seen[-1]
        keys = ["potential_energy", "kinetic_energy", "pressure", "temperature"]
        keys += ["conserved_energy"] if "conserved_energy" in thermo_cpu else []
        results[f"run_{name}_thermo"] = max(
            abs(thermo_gpu[k] - thermo_cpu[k]) / abs(thermo_cpu[k]) for k in keys
        )
        results[f"run_{name}_statistics"] = getattr(runs[0].integrator, "statistics", 0) == (
            getattr(runs[1].integrator, "statistics", 0)
        )
        results[f"run_{name}_thermo_step"] = int(thermo_gpu["step"])
        results[f"run_{name}_builds"] = runs[1]._engine.n_builds


def check_polymer(results: dict) -> None:
    """A bead-spring melt (WCA, FENE, harmonic and cosine angles): forces against the CPU
    path's, and a 100-step velocity Verlet run."""
    from integrators import VelocityVerlet
    from md.build import maxwell_boltzmann
    from md.cuda.engine import DeviceEngine
    from md.forcefield import ForceField
    from md.polymers import chain_angles, polymer_melt
    from md.simulation import Simulation
    from potentials import CosineAngles, FENEBonds, HarmonicAngles, LennardJones

    def melt():
        state, bonds = polymer_melt(6, 8, seed=1)
        angles = chain_angles(6, 8)
        potentials = [
            LennardJones(cutoff=2 ** (1 / 6)),
            FENEBonds(bonds, k=30.0, r_max=1.5),
            HarmonicAngles(angles[::2], k=5.0, theta0=2.0),
            CosineAngles(angles[1::2], k=2.0),
        ]
        return maxwell_boltzmann(state, 1.0, seed=2), potentials

    state, potentials = melt()
    cpu = ForceField(potentials, skin=0.3).compute(state)
    engine = DeviceEngine(state, ForceField(melt()[1], skin=0.3), None)
    engine.start(state)
    gpu = engine.result()
    results["polymer_force"] = _relative(gpu.forces, cpu.forces)
    results["polymer_energy"] = abs(gpu.energy - cpu.energy) / abs(cpu.energy)
    results["polymer_virial"] = _relative(gpu.virial, cpu.virial)
    runs = []
    for device in ("cpu", "cuda"):
        state, potentials = melt()
        sim = Simulation(state, potentials, VelocityVerlet(dt=0.005), device=device)
        sim.run(100)
        runs.append(state)
    results["polymer_run_positions"] = _relative(runs[1].positions, runs[0].positions)
    results["polymer_run_velocities"] = _relative(runs[1].velocities, runs[0].velocities)


def check_checkpoint(results: dict, folder: Path) -> None:
    """``md run --device cuda`` (on the simulator where the environment asks for it), after
    a ``[minimize]`` stage on the CPU, for 30
    steps, resumed on the CPU to 60, against 60 on the
    CPU; a leapfrog run, so the half-step velocities go through the checkpoint."""
    import h5py
    import numpy as np

    from md.cli import main

    text = "\n".join(
        [
            'units = "lj"',
            "seed = 2",
            "[system]",
            'lattice = "fcc"\ncells = 2\ndensity = 0.9\ntemperature = 1.2',
            "[[potentials]]",
            'type = "lj"\ncutoff = 1.3',
            "[integrator]",
            'type = "leapfrog"\ndt = 0.005',
            "[run]",
            "steps = 60\nthermo_every = 10\nskin = 0.3",
            "[minimize]",  # on the CPU, before the dynamics go to the device
            "fmax = 0.5",
            "[output]",
            "every = 10\nvelocities = true\ncheckpoint_every = 10",
        ]
    )
    config = folder / "run.toml"
    config.write_text(text + "\n")
    command = ["run", str(config), "-q", "--no-progress", "-o"]
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        codes = [main([*command, str(folder / "gpu.h5"), "--steps", "30", "--device", "cuda"])]
    results["checkpoint_said_gpu"] = "on the GPU" in printed.getvalue()
    codes += [
        main([*command, str(folder / "gpu.h5"), "--resume", "--device", "cpu"]),
        main([*command, str(folder / "cpu.h5")]),
    ]
    results["checkpoint_codes"] = codes
    with h5py.File(folder / "gpu.h5") as gpu, h5py.File(folder / "cpu.h5") as cpu:
        particles = "particles/trajectory"
        results["checkpoint_frames"] = [
            len(gpu[f"{particles}/position/step"]),
            len(cpu[f"{particles}/position/step"]),
        ]
        results["checkpoint_positions"] = _relative(
            gpu[f"{particles}/position/value"][...], cpu[f"{particles}/position/value"][...]
        )
        results["checkpoint_velocities"] = _relative(
            gpu[f"{particles}/velocity/value"][...], cpu[f"{particles}/velocity/value"][...]
        )
        energies = [f["observables/potential_energy/value"][...] for f in (gpu, cpu)]
        results["checkpoint_energy"] = float(np.max(np.abs(energies[0] - energies[1])))


def _md_run(arguments: list[str]) -> tuple[int, str]:
    """``md run`` with ``arguments``: its exit code and what it printed."""
    from md.cli import main

    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = main(["run", *arguments, "-q", "--no-progress"])
    return code, printed.getvalue()


def _builds(printed: str) -> int:
    """The neighbour-list builds a run's summary reports (the device's where it ran there)."""
    import re

    found = re.search(r"Neighbour list builds(?: on the device)?: (\d+)", printed)
    return int(found.group(1)) if found else -1


def check_resume_on_gpu(results: dict, folder: Path) -> None:
    """A CPU run checkpointed at step 20, resumed with ``--device cuda`` to 40, against 40
    steps on the CPU (leapfrog: its half-step velocities; Langevin: its noise and heat
    bath); and the list builds a fresh device run's summary reports against the CPU's
    over the same 20 steps (the same rule, the same trajectory: the same builds; a resumed
    run differs, as the CPU's list comes back with the checkpoint and the device builds its
    own at the start)."""
    import h5py
    import numpy as np

    integrators = {
        "leapfrog": 'type = "leapfrog"\ndt = 0.005',
        "langevin": 'type = "langevin"\ndt = 0.005\ntemperature = 1.2\nfriction = 2.0',
    }
    for name, integrator in integrators.items():
        text = "\n".join(
            [
                'units = "lj"\nseed = 3',
                '[system]\nlattice = "fcc"\ncells = 2\ndensity = 0.9\ntemperature = 1.5',
                '[[potentials]]\ntype = "lj"\ncutoff = 1.3',
                f"[integrator]\n{integrator}",
                "[run]\nsteps = 40\nthermo_every = 10\nskin = 0.2",
                "[output]\nevery = 10\nvelocities = true\ncheckpoint_every = 10",
            ]
        )
        config = folder / f"resume_{name}.toml"
        config.write_text(text + "\n")
        paths = {k: str(folder / f"resume_{name}_{k}.h5") for k in ("gpu", "whole", "fresh")}
        code, first = _md_run([str(config), "-o", paths["gpu"], "--steps", "20"])
        codes = [code]
        code, on_gpu = _md_run([str(config), "-o", paths["gpu"], "--resume", "--device", "cuda"])
        codes.append(code)
        codes.append(_md_run([str(config), "-o", paths["whole"]])[0])
        results[f"resume_{name}_codes"] = codes
        results[f"resume_{name}_said_gpu"] = "on the GPU" in on_gpu
        if name == "leapfrog":  # a fresh device run's summary
            command = [str(config), "-o", paths["fresh"], "--steps", "20", "--device", "cuda"]
            code, fresh = _md_run(command)
            results["summary_code"] = code
            results["summary_builds"] = [_builds(fresh), _builds(first)]
            results["summary_lines"] = fresh.splitlines()[-12:]
        with h5py.File(paths["gpu"]) as gpu, h5py.File(paths["whole"]) as whole:
            particles = "particles/trajectory"
            results[f"resume_{name}_frames"] = [
                len(f[f"{particles}/position/step"]) for f in (gpu, whole)
            ]
            for element in ("position", "velocity"):
                results[f"resume_{name}_{element}"] = _relative(
                    gpu[f"{particles}/{element}/value"][...],
                    whole[f"{particles}/{element}/value"][...],
                )
            worst = 0.0
            for quantity in ("potential_energy", "kinetic_energy", "conserved_energy"):
                path = f"observables/{quantity}/value"
                if path in whole:
                    a, b = gpu[path][...], whole[path][...]
                    worst = max(worst, float(np.max(np.abs(a - b)) / np.max(np.abs(b))))
            results[f"resume_{name}_energies"] = worst


def _over_blocks(engine):
    """``engine.start`` that then takes the sums over three blocks of 16 threads (two hold
    atoms of a 32-atom system; the last to finish adds the rows)."""
    from numba import cuda

    start = engine.start

    def started(state):
        start(state)
        engine.sum_threads, engine.sum_blocks = 16, 3
        engine.arrays["partial"] = cuda.device_array((3, engine.arrays["partial"].shape[1]))

    return started


def check_tuning(results: dict) -> None:
    """The device's sort along the cells' Morton curve, its scan of the cell counts, and
    the launches per step."""
    import numpy as np
    from numba import cuda

    from integrators import Bussi, Langevin, Leapfrog, VelocityVerlet
    from md.cuda import _kernels as kernels
    from md.cuda.engine import DeviceEngine
    from md.forcefield import ForceField
    from md.simulation import Simulation
    from potentials import LennardJones

    # the rows after the first build's sort: their cells' Morton codes (bits interleaved
    # here, x highest of each triple) never decrease, and each cell's atoms keep their order
    cells, small = _states()
    engine = DeviceEngine(cells, ForceField([LennardJones(cutoff=1.7)], skin=0.3), None)
    engine.start(cells)
    n_cells = np.array(engine.n_cells)
    s = cells.positions[engine.perm] / cells.box
    xyz = np.minimum(((s - np.floor(s)) * n_cells).astype(np.int64), n_cells - 1)
    codes = np.zeros(cells.n_atoms, np.int64)
    for bit in range(4):
        for place in range(3):
            codes |= ((xyz[:, place] >> bit) & 1) << (3 * bit + 2 - place)
    row_major = (xyz[:, 0] * n_cells[1] + xyz[:, 1]) * n_cells[2] + xyz[:, 2]
    results["sort_grid"] = [int(c) for c in n_cells]
    results["sort_morton_ordered"] = bool(np.all(np.diff(codes) >= 0))
    results["sort_row_major_ordered"] = bool(np.all(np.diff(row_major) >= 0))
    same_cell = np.diff(codes) == 0
    results["sort_cells_keep_order"] = bool(np.all(np.diff(engine.perm)[same_cell] > 0))
    # the scan: more cells than threads (runs of 47), and fewer
    rng = np.random.default_rng(9)
    worst = 0
    for n, threads in ((3000, 64), (5, 32)):
        counts = rng.integers(0, 9, n).astype(np.int32)
        d_counts = cuda.to_device(counts)
        starts, cursors = cuda.device_array(n + 1, np.int32), cuda.to_device(np.ones(n, np.int32))
        kernels._cell_starts[1, threads](d_counts, starts, cursors)
        expected = np.concatenate([[0], np.cumsum(counts)])
        worst = max(worst, int(np.max(np.abs(starts.copy_to_host() - expected))))
        worst = max(
            worst, int(np.max(d_counts.copy_to_host())), int(np.max(cursors.copy_to_host()))
        )
    results["scan_error"] = worst
    # runs that sort the rows at every build (every integrator's pass after a rebuild
    # reads the sorted arrays), in double and, for velocity Verlet, mixed precision
    for name, integrator, precision in (
        ("verlet_mixed", VelocityVerlet, "mixed"),
        ("leapfrog", Leapfrog, "double"),
        ("bussi", lambda dt: Bussi(dt=dt, temperature=1.2, tau=0.05, seed=8), "double"),
        ("langevin", lambda dt: Langevin(dt, temperature=1.2, friction=2.0, seed=7), "double"),
    ):
        states = [small.copy() for _ in range(2)]
        runs = [  # a thin skin: a rebuild every few steps
            Simulation(
                s,
                [LennardJones(cutoff=1.3)],
                integrator(0.005),
                skin=0.06,
                precision=precision,
                device=device,
            )
            for s, device in zip(states, ("cpu", "cuda"), strict=True)
        ]
        engine = runs[1].device_engine
        engine.sort_every = 1
        if name in ("bussi", "langevin"):  # their fused sums over several blocks
            engine.start = _over_blocks(engine)
        for sim in runs:
            sim.run(8)
        results[f"sorted_{name}_sorts"] = runs[1].device_engine.n_sorts
        results[f"sorted_{name}_positions"] = _relative(states[1].positions, states[0].positions)
        results[f"sorted_{name}_velocities"] = _relative(states[1].velocities, states[0].velocities)
    # launches of a step that does not rebuild the list, once the run is under way
    launches = {}
    for name, integrator in (
        ("verlet", VelocityVerlet(dt=0.002)),
        ("leapfrog", Leapfrog(dt=0.002)),
        ("bussi", Bussi(dt=0.002, temperature=1.2, tau=0.05, seed=8)),
        ("langevin", Langevin(dt=0.002, temperature=1.2, friction=2.0, seed=7)),
    ):
        state = small.copy()
        sim = Simulation(state, [LennardJones(cutoff=1.3)], integrator, device="cuda")
        engine = sim.device_engine
        engine.start(state)
        counted = []
        for _ in range(3):
            before, builds = engine.n_launches, engine.n_builds
            engine.step(state)
            if engine.n_builds == builds:
                counted.append(engine.n_launches - before)
        engine.finish(state)
        launches[name] = counted[-1] if counted else -1
    results["launches_per_step"] = launches


def _lowering():
    """A stand-in for ``cuda.compile_ptx`` where NVVM is missing: the kernel typed and
    lowered by the CUDA target to LLVM IR for sm_90 (``compile_cuda``), short of the NVVM
    step. numba-cuda asks NVVM only for its data layout and IR version before that step,
    so a stand-in gives NVVM's 64-bit layout (numba-cuda 0.30's internals: this is a test
    helper, not library code). It catches what the simulator cannot (a numpy function the
    target lacks, a type the target cannot lower), not what only NVVM would reject."""
    import numba
    from numba.cuda import compiler
    from numba.cuda.cudadrv import nvvm

    class StandIn:
        data_layout = (
            "e-p:64:64:64-i1:8:8-i8:8:8-i16:16:16-i32:32:32-i64:64:64-i128:128:128-f32:32:32"
            "-f64:64:64-v16:16:16-v32:32:32-v64:64:64-v128:128:128-n16:32:64"
        )

        def get_ir_version(self):
            return (2, 0, 3, 1)

    nvvm.NVVM = StandIn

    def lower(function, signature, cc=(9, 0)):
        return compiler.compile_cuda(function, numba.types.void, signature, cc=cc)

    return lower


def check_ptx(results: dict, lower: bool = False) -> None:
    """Every kernel compiled to PTX for the H100/H200 (sm_90) without a GPU, as the CUDA
    target types it (the simulator runs the Python and misses what that target lacks,
    such as ``np.rint``): the generic kernels, the force kernel of every built-in pair
    style in double and mixed precision and of every built-in bond and angle style. Needs
    NVVM (``numba-cuda[cu12]``); ``lower``: only typed and lowered to LLVM IR, without
    NVVM (:func:`_lowering`)."""
    import numba
    import numpy as np
    from numba import cuda

    from integrators.langevin import noise_of_atom
    from md.cuda import _kernels as kernels
    from potentials import (
        Buckingham,
        CosineAngles,
        FENEBonds,
        HarmonicAngles,
        HarmonicBonds,
        LennardJones,
        Mie,
        Morse,
        Soft,
        Table,
        Yukawa,
    )
    from potentials.device_terms import bonded_function, pair_function

    compile_to = _lowering() if lower else cuda.compile_ptx
    try:
        from numba.cuda.cudadrv.nvvm import NVVM

        NVVM()

        def _probe(x):
            x[0] = 1.0

        # the whole tool chain, on a one-line kernel (plain numba-cuda can have NVVM and
        # still lack NVRTC, which compiling needs too)
        compile_to(_probe, (numba.float64[:],), cc=(9, 0))

        def _rint(x):
            x[0] = np.rint(x[0])

        try:  # and a kernel the CUDA target rejects (no np.rint on scalars) is rejected
            compile_to(_rint, (numba.float64[:],), cc=(9, 0))
            results["ptx_rejects_rint"] = False
        except Exception:  # noqa: BLE001
            results["ptx_rejects_rint"] = True
    except Exception as error:  # noqa: BLE001 (no CUDA compiler: nothing to compile with)
        results["ptx_nvvm"] = str(error)[:200]
        return
    results["ptx_nvvm"] = True
    f2, f1 = np.zeros((4, 3)), np.zeros(4)
    i1, i2, l1 = np.zeros(4, np.int32), np.zeros((4, 4), np.int32), np.zeros(3, np.int64)
    observables = np.zeros((4, kernels.N_OBSERVABLES))
    f4, one = np.zeros((4, 4)), np.zeros(1, np.int32)
    generic = {
        "_cell_of": (f4, f1, l1, i1, i1, i1),
        "_cell_starts": (i1, i1, i1),
        "_scatter": (i1, i1, i1, i1),
        "_sort_cells": (i1, i1),
        "_search_cells": (f4, f1, f1, f1, l1, i1, i1, i1, 1.0, i2, i1),
        "_search_all": (f4, f1, f1, f1, 1.0, i2, i1),
        "_remember": (f4, f2, i1, 4, i1),
        "_kick_drift_check": (f4, f2, f2, f1, 1.0, 1.0, 1.0, f2, 1.0, i1, True),
        "_drift_check": (f4, f2, 1.0, f2, 1.0, i1),
        "_kick": (f2, f2, f1, 1.0),
        "_synchronise": (f2, f2, f2, f1, 1.0),
        "_kick_scale_kinetic": (f2, f2, f1, f1, 1.0, 1.0, observables, one, np.zeros(1)),
        "_relax_bath": (f2, f2, f1, 1.0, True, observables, one, np.zeros(7)),
        "_sum_observables": (observables, f2, f1, observables, one, np.zeros(8)),
        "_gather": (i1, i1, i1),
        "_gather_rows": (f4, i1, f4),
    }
    compiled, failed = [], {}

    def compile_ptx(name, kernel, arguments):
        signature = tuple(numba.typeof(a) for a in arguments)
        try:
            compile_to(kernel.py_func, signature, cc=(9, 0))
            compiled.append(name)
        except Exception as error:  # noqa: BLE001 (recorded for the test to show)
            failed[name] = f"{type(error).__name__}: {str(error)[:300]}"

    for name, arguments in generic.items():
        compile_ptx(name, getattr(kernels, name), arguments)
    r = np.linspace(0.8, 2.6, 50)
    styles = {
        "lj": LennardJones(cutoff=2.5),
        "morse": Morse(cutoff=2.5),
        "mie": Mie(cutoff=2.5),
        "buckingham": Buckingham(a=1000.0, rho=0.2, c=1.0, cutoff=2.5),
        "yukawa": Yukawa(cutoff=2.5),
        "soft": Soft(cutoff=1.0),
    }
    with tempfile.TemporaryDirectory() as folder:  # a LAMMPS table of r^-12
        path = Path(folder) / "wall.table"
        rows = [f"{i + 1} {x:.17g} {x**-12:.17g} {12 * x**-13:.17g}" for i, x in enumerate(r)]
        path.write_text(f"WALL\nN {len(r)} R 0.8 2.6\n\n" + "\n".join(rows) + "\n")
        styles["table"] = Table(path, "WALL", cutoff=2.5)
    for precision in ("double", "mixed"):
        for name, potential in styles.items():
            pair, table, mode, data, real = pair_function(potential, 1, precision)
            arguments = (f4, 1, i2, i1, f1, f1, f1, table, mode, data, True, f2, observables)
            compile_ptx(f"pair_{name}_{precision}", kernels.pair_kernel(pair, real), arguments)
    word = np.uint64(1)
    noise = kernels.noise_kernel(noise_of_atom)
    noise_arguments = (word, word, word, np.zeros(4, np.int64), f1, f2, f2, f1, observables)
    compile_ptx("noise", noise, (*noise_arguments, one, np.zeros(7)))
    bonds, angles = np.array([[0, 1], [1, 2]]), np.array([[0, 1, 2]])
    bonded = {
        "spring": HarmonicBonds(bonds, k=1.0, r0=1.0),
        "fene": FENEBonds(bonds),
        "angle_harmonic": HarmonicAngles(angles, k=1.0, theta0=2.0),
        "angle_cosine": CosineAngles(angles, k=1.0),
    }
    for name, potential in bonded.items():
        kind, term, params, items, item_types, table = bonded_function(potential)
        factory = kernels.bond_kernel if kind == "bond" else kernels.angle_kernel
        starts, entries = np.zeros(5, np.int64), np.zeros(4, np.int64)
        arguments = (f4, f1, f1, f1, items, item_types, table, starts, entries, f2, observables)
        compile_ptx(f"{kind}_{name}", factory(term, params), arguments)
    results["ptx_compiled"] = compiled
    results["ptx_failed"] = failed


def main(argv: list[str]) -> int:
    # the simulator runs Philox's uint64 products as numpy scalars, which warn as they wrap
    warnings.filterwarnings("ignore", "overflow encountered", RuntimeWarning)
    if os.environ.get("NUMBA_ENABLE_CUDASIM") == "1":
        # The simulator runs a block's threads as Python threads and polls them in a loop
        # that holds the interpreter lock: with the default 5 ms switch interval a launch
        # waits mostly on that poll. A shorter interval halves the checks' CPU time.
        sys.setswitchinterval(SIMULATOR_SWITCH_INTERVAL)
        _lighter_launches()
    out = Path(argv[0])
    results: dict = {}
    if argv[1:] in (["--ptx"], ["--lower"]):
        check_ptx(results, lower=argv[1:] == ["--lower"])
        out.write_text(json.dumps(results, indent=1))
        return 0
    if argv[1:] == ["--more"]:  # tests/test_gpu_more.py's
        seconds = results["seconds"] = {}
        start = time.process_time()
        check_tuning(results)
        seconds["check_tuning"] = time.process_time() - start
        start = time.process_time()
        check_resume_on_gpu(results, out.parent)
        seconds["check_resume_on_gpu"] = time.process_time() - start
        out.write_text(json.dumps(results, indent=1))
        return 0
    seconds = results["seconds"] = {}
    for check in (check_lists, check_forces, check_runs, check_polymer):
        start = time.process_time()
        check(results)
        seconds[check.__name__] = time.process_time() - start
    start = time.process_time()
    check_checkpoint(results, out.parent)
    seconds["check_checkpoint"] = time.process_time() - start
    out.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
