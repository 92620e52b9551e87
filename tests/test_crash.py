"""Crash safety for real: kill ``md run`` with SIGKILL at random moments, then resume.

After every kill the trajectory (if it exists yet) must open in MDAnalysis and
``md info`` and hold a prefix of the uninterrupted run's frames, bit for bit;
``md run --resume`` then continues, possibly killed again, and the finished
file and final checkpoint equal those of a run that was never interrupted.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from conftest import lj_config_text
from md.checkpoint import checkpoint_path, read_checkpoint
from md.cli import main
from md.errors import TrajectoryError
from md.trajectory import open_trajectory, read_trajectory

CONFIG = lj_config_text(
    seed=11,
    temperature=1.0,
    integrator='type = "langevin"\ndt = 0.005\ntemperature = 1.0\nfriction = 1.0',
    run="steps = {steps}\nthermo_every = 1000",
    output='path = "out.h5"\nevery = 10\nvelocities = true\ncheckpoint_every = 25',
)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The uninterrupted runs, one per length, computed once."""
    cache = {}

    def get(steps):
        if steps not in cache:
            folder = tmp_path_factory.mktemp(f"reference{steps}")
            config = folder / "run.toml"
            config.write_text(CONFIG.format(steps=steps))
            out = folder / "out.h5"
            assert main(["run", str(config), "-o", str(out), "--no-progress", "-q"]) == 0
            cache[steps] = (read_trajectory(out), read_checkpoint(checkpoint_path(out)))
        return cache[steps]

    return get


def _launch(config, resume: bool) -> subprocess.Popen:
    command = [sys.executable, "-m", "md.cli", "run", str(config), "--no-progress", "-q"]
    if resume:
        command.append("--resume")
    return subprocess.Popen(
        command, cwd=config.parent, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
    )


def _check_after_kill(folder, ref) -> int:
    """The file opens everywhere and holds a bitwise prefix of the reference; return its frames."""
    out = folder / "out.h5"
    if not out.exists():
        return 0
    traj = read_trajectory(out)
    n = traj.n_frames
    if n:  # killed after the layout but before frame 0: nothing for MDAnalysis to open
        universe = open_trajectory(out)
        assert universe.trajectory.n_frames == n
        universe.trajectory.close()
    else:
        with pytest.raises(TrajectoryError, match="no frames yet"):
            open_trajectory(out)
    assert main(["info", str(out), "--json"]) == 0
    np.testing.assert_array_equal(traj.steps, ref.steps[:n])
    assert np.array_equal(traj.positions, ref.positions[:n])
    assert np.array_equal(traj.velocities, ref.velocities[:n])
    for name, values in traj.observables.items():
        assert np.array_equal(values, ref.observables[name][:n]), name
    return n


def kill_and_resume(folder, steps, ref_pair, rng, n_kills, window):
    """Run, SIGKILL at uniform random times in ``window`` seconds, resume; then finish."""
    ref, ref_checkpoint = ref_pair
    config = folder / "run.toml"
    config.write_text(CONFIG.format(steps=steps))
    log = []
    for kill in range(n_kills + 1):
        started = checkpoint_path(folder / "out.h5").exists()
        process = _launch(config, resume=started)
        if kill < n_kills:
            delay = float(rng.uniform(*window))
            time.sleep(delay)
            process.send_signal(signal.SIGKILL)
        _, err = process.communicate(timeout=120)
        log.append((kill, started, process.returncode))
        if kill == n_kills:
            assert process.returncode == 0, (log, err)
        else:
            assert process.returncode in (0, -signal.SIGKILL), (log, err)
            assert "Traceback" not in err, (log, err)
            _check_after_kill(folder, ref)
    final = read_trajectory(folder / "out.h5")
    np.testing.assert_array_equal(final.steps, ref.steps)
    assert np.array_equal(final.positions, ref.positions)
    assert np.array_equal(final.velocities, ref.velocities)
    for name, values in final.observables.items():
        assert np.array_equal(values, ref.observables[name]), name
    saved = read_checkpoint(checkpoint_path(folder / "out.h5"))
    assert saved.state.step == steps
    assert np.array_equal(saved.state.positions, ref_checkpoint.state.positions)
    assert np.array_equal(saved.state.velocities, ref_checkpoint.state.velocities)
    assert repr(saved.integrator_state) == repr(ref_checkpoint.integrator_state)
    return log


def test_killed_runs_resume_to_the_uninterrupted_result(tmp_path, reference):
    rng = np.random.default_rng(2024)
    kill_and_resume(tmp_path, 600, reference(600), rng, n_kills=2, window=(0.8, 2.0))


@pytest.mark.slow
@pytest.mark.parametrize("chain", range(20))
def test_many_random_kills(tmp_path, reference, chain):
    rng = np.random.default_rng(1000 + chain)
    kill_and_resume(tmp_path, 2000, reference(2000), rng, n_kills=4, window=(0.0, 3.5))
