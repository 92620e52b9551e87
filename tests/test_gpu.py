"""The GPU path (``md.cuda``, ``device = "cuda"``): its kernels against the CPU path's, and
every refusal.

The device checks run ``tests/_gpu_checks.py`` in a subprocess, once per module: on numba's
CUDA simulator (``NUMBA_ENABLE_CUDASIM=1``, read when ``numba.cuda`` is first imported, so
it cannot be switched on inside this test process without changing what other test files
in the same worker see), and, for the tests marked ``cuda``, on a real GPU where numba-cuda
finds one. The refusals run here: they stop before any kernel is compiled.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import md.cuda
from integrators import NoseHooverChain, VelocityVerlet
from md.build import lattice, maxwell_boltzmann
from md.cli import main
from md.errors import ConfigError, DeviceError
from md.run import run_config
from md.simulation import Simulation
from potentials import ForceResult, HarmonicBonds, LennardJones

ROOT = Path(__file__).resolve().parents[1]
HAVE_NUMBA_CUDA = importlib.util.find_spec("numba_cuda") is not None


def _checks(tmp_path_factory, simulator: bool, *options: str) -> dict:
    folder = tmp_path_factory.mktemp("gpu_sim" if simulator else "gpu")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("NUMBA_ENABLE_CUDASIM", None)
    if simulator:
        env["NUMBA_ENABLE_CUDASIM"] = "1"
    out = folder / "results.json"
    done = subprocess.run(
        [sys.executable, str(ROOT / "tests" / "_gpu_checks.py"), str(out), *options],
        env=env,
        cwd=folder,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(out.read_text())


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    if not HAVE_NUMBA_CUDA:
        pytest.skip("numba-cuda not installed")
    return _checks(tmp_path_factory, simulator=True)


def _gpu_present() -> bool:
    if not HAVE_NUMBA_CUDA or md.cuda.simulator_requested():
        return False
    probe = "from numba import cuda; print(cuda.is_available())"
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_ENABLE_CUDASIM"}
    done = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True)
    return done.stdout.strip() == "True"


@pytest.fixture(scope="module")
def on_gpu(tmp_path_factory):
    if not _gpu_present():
        pytest.skip("no NVIDIA GPU")
    return _checks(tmp_path_factory, simulator=False)


def _judge(results: dict) -> None:
    """What the checks must show, on the simulator or a GPU."""
    for name in ("cells", "all_pairs"):
        assert results[f"list_{name}_pairs"] > 0
        assert results[f"list_{name}_missing"] == 0, name
        assert results[f"list_{name}_extra"] == 0, name
    assert results["list_cells_used_cells"] and not results["list_all_pairs_used_cells"]
    # the atoms were sorted by cell on the device, and every result is in the user's order
    assert results["list_cells_sorted"] and results["list_all_pairs_sorted"]
    forces = [k for k in results if k.startswith("forces_")]
    assert len(forces) == 18
    assert results["sums_cells_blocks"] < 1e-12 and results["sums_all_pairs_blocks"] < 1e-12
    for key in forces:
        limit = 1e-12 if "_double_" in key else 3e-7  # mixed: float32 round-off
        assert results[key] < limit, (key, results[key])
    runs = {"verlet": 100, "verlet_cells": 30, "leapfrog": 30, "langevin": 30, "bussi": 30}
    for name, steps in runs.items():
        assert results[f"run_{name}_steps"] == [steps, steps, True]
        assert results[f"run_{name}_positions"] < 1e-10, name
        assert results[f"run_{name}_velocities"] < 1e-10, name
        assert results[f"run_{name}_thermo"] < 1e-10, name
        assert results[f"run_{name}_thermo_step"] == steps
        assert results[f"run_{name}_builds"] > 1  # the list was rebuilt on the device
        assert results[f"run_{name}_statistics"], name
    assert results["polymer_force"] < 1e-12
    assert results["polymer_energy"] < 1e-12
    assert results["polymer_virial"] < 1e-12
    assert results["polymer_run_positions"] < 1e-10
    assert results["polymer_run_velocities"] < 1e-10
    assert results["checkpoint_codes"] == [0, 0, 0]  # md run --device cuda, then on the CPU
    assert results["checkpoint_said_gpu"]
    assert results["checkpoint_frames"] == [7, 7]
    assert results["checkpoint_positions"] < 1e-10
    assert results["checkpoint_velocities"] < 1e-10
    assert results["checkpoint_energy"] < 1e-10


def test_device_kernels_and_runs_match_the_cpu_on_the_simulator(simulated):
    _judge(simulated)


@pytest.mark.cuda
def test_device_kernels_and_runs_match_the_cpu_on_a_gpu(on_gpu):
    _judge(on_gpu)


@pytest.mark.skipif(not HAVE_NUMBA_CUDA, reason="numba-cuda not installed")
def test_every_kernel_compiles_for_the_gpu_target(tmp_path_factory):
    """The kernels typed and compiled by the CUDA target itself (PTX for sm_90), which the
    simulator does not do: it runs the Python (an ``np.rint`` the target lacks passed
    there). Needs NVVM, which ``numba-cuda[cu12]`` brings; skipped without it."""
    results = _checks(tmp_path_factory, False, "--ptx")
    if results["ptx_nvvm"] is not True:
        pytest.skip(f"no CUDA compiler (NVVM, NVRTC) to compile with: {results['ptx_nvvm']}")
    assert results["ptx_failed"] == {}
    # the 16 generic kernels, 7 pair styles in two precisions, Langevin's noise, 2 bond and 2
    # angle styles
    assert len(results["ptx_compiled"]) == 16 + 2 * 7 + 1 + 4


# ------------------------------------------------------------------ refusals
def _system():
    return maxwell_boltzmann(lattice("fcc", 2, density=0.9), 1.0, seed=1)


class Tether:
    """A potential of no frame (a harmonic pull of every atom to the origin)."""

    cutoff = None

    def check(self, state) -> None:
        pass

    def energy_forces(self, state, neighbors=None, per_atom=False, virial=True):
        return ForceResult(
            energy=0.5 * float(np.sum(state.positions**2)),
            forces=-state.positions,
            virial=np.zeros((3, 3)),
        )


@pytest.fixture
def gpu_found(monkeypatch):
    """As if numba-cuda and a GPU were there: what the refusals check next."""
    monkeypatch.setattr(md.cuda, "numba_cuda_installed", lambda: True)
    monkeypatch.setattr(md.cuda, "gpu_found", lambda: True)


def test_default_device_is_the_cpu():
    sim = Simulation(_system(), [LennardJones(cutoff=1.3)], VelocityVerlet(dt=0.005))
    assert sim.device == "cpu"


def test_an_unknown_device_is_refused():
    with pytest.raises(ValueError, match="device must be one of 'cpu', 'cuda', got 'gpu'"):
        Simulation(_system(), [LennardJones(cutoff=1.3)], VelocityVerlet(dt=0.005), device="gpu")


def test_missing_numba_cuda_is_named_with_how_to_install(monkeypatch):
    monkeypatch.setattr(md.cuda, "numba_cuda_installed", lambda: False)
    with pytest.raises(DeviceError, match=r"numba-cuda is not installed.*leapmd\[cuda\]"):
        Simulation(_system(), [LennardJones(cutoff=1.3)], VelocityVerlet(dt=0.005), device="cuda")


def test_no_gpu_without_the_simulator_is_refused(monkeypatch):
    monkeypatch.delenv("NUMBA_ENABLE_CUDASIM", raising=False)
    monkeypatch.setattr(md.cuda, "numba_cuda_installed", lambda: True)
    monkeypatch.setattr(md.cuda, "gpu_found", lambda: False)
    with pytest.raises(DeviceError, match="no usable NVIDIA GPU.*NUMBA_ENABLE_CUDASIM=1"):
        Simulation(_system(), [LennardJones(cutoff=1.3)], VelocityVerlet(dt=0.005), device="cuda")


@pytest.mark.parametrize(
    ("potentials", "integrator", "options", "named"),
    [
        (
            [LennardJones(cutoff=1.3)],
            NoseHooverChain(dt=0.005, temperature=1.0, tau=0.1),
            {},
            "NoseHooverChain",
        ),
        ([LennardJones(cutoff=1.3), Tether()], VelocityVerlet(dt=0.005), {}, "Tether"),
        (
            [HarmonicBonds(bonds=[(0, 1)], k=1.0, r0=1.0), LennardJones(cutoff=1.3)],
            VelocityVerlet(dt=0.005),
            {},
            "needs a pair potential, listed first",
        ),
        ([LennardJones(cutoff=1.3)], VelocityVerlet(dt=0.005), {"neighbor_every": 5}, "every"),
    ],
)
def test_what_is_not_ported_is_refused_by_name(gpu_found, potentials, integrator, options, named):
    with pytest.raises(DeviceError, match=named):
        Simulation(_system(), potentials, integrator, device="cuda", **options)


CONFIG = """units = "lj"
seed = 1
[system]
lattice = "fcc"
cells = 2
density = 0.9
temperature = 1.0
[[potentials]]
type = "lj"
cutoff = 1.3
[integrator]
{integrator}
[run]
steps = 10
{run}
[output]
every = 5
"""


def _config(tmp_path, integrator='type = "verlet"\ndt = 0.005', run="") -> Path:
    path = tmp_path / "run.toml"
    path.write_text(CONFIG.format(integrator=integrator, run=run))
    return path


def test_the_cli_refuses_before_writing_anything(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(md.cuda, "numba_cuda_installed", lambda: False)
    config = _config(tmp_path)
    output = tmp_path / "out.h5"
    code = main(["run", str(config), "--device", "cuda", "-o", str(output), "--no-progress"])
    assert code == 2
    assert "numba-cuda is not installed" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.toml"]


@pytest.mark.parametrize(
    ("integrator", "named"),
    [
        ('type = "implicit_euler"\ndt = 0.005', "ImplicitEuler"),
        ('type = "respa"\ndt = 0.005', "RESPA"),
    ],
)
def test_the_config_key_refuses_unported_integrators(tmp_path, gpu_found, integrator, named):
    config = _config(tmp_path, integrator, run='device = "cuda"')
    with pytest.raises(ConfigError, match=f'device = "cuda".*{named}'):
        run_config(config, output=tmp_path / "out.h5")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.toml"]


def test_a_barostat_is_refused(tmp_path, gpu_found):
    langevin = 'type = "langevin"\ndt = 0.005\ntemperature = 1.0\nfriction = 1.0'
    config = _config(tmp_path, langevin, run='device = "cuda"')
    barostat = '[barostat]\ntype = "c_rescale"\npressure = 1.0\ntau = 1.0\n'
    config.write_text(config.read_text() + barostat)
    with pytest.raises(ConfigError, match='device = "cuda".*a barostat'):
        run_config(config, output=tmp_path / "out.h5")


def test_the_config_key_takes_only_cpu_or_cuda(tmp_path):
    with pytest.raises(ConfigError, match="device"):
        run_config(_config(tmp_path, run='device = "tpu"'), output=tmp_path / "out.h5")
