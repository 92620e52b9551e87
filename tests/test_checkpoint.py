"""Checkpoints and --resume: exact continuation, atomic writes, refusals, signals, blow-ups."""

from __future__ import annotations

import hashlib
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

import md
from conftest import lj_config_text
from md.checkpoint import (
    CheckpointError,
    checkpoint_path,
    read_checkpoint,
    restore,
    write_checkpoint,
)
from md.cli import main
from md.trajectory import read_trajectory

INTEGRATORS = {
    "verlet": 'type = "verlet"\ndt = 0.005',
    "leapfrog": 'type = "leapfrog"\ndt = 0.005',
    "rkf45": 'type = "rkf45"\ndt = 0.02\ntol = 1e-5',
    "pefrl": 'type = "pefrl"\ndt = 0.005',
    "langevin": 'type = "langevin"\ndt = 0.005\ntemperature = 1.0\nfriction = 2.0',
    # their predictor extrapolates the accelerations of the last steps (saved with them)
    "implicit_euler": 'type = "implicit_euler"\ndt = 0.005\ntol = 1e-8',
    "implicit_midpoint": 'type = "implicit_midpoint"\ndt = 0.005\ntol = 1e-8',
}


def config_text(integrator="verlet", steps=60):
    return lj_config_text(
        integrator=INTEGRATORS[integrator],
        run=f"steps = {steps}\nthermo_every = 10",
        output='path = "out.h5"\nevery = 10\nvelocities = true\ncheckpoint_every = 20',
    )


@pytest.fixture(autouse=True)
def in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)


def run(*args) -> int:
    return main(["run", *map(str, args), "--no-progress", "-q"])


def digest(path) -> str:
    return hashlib.sha256(open(path, "rb").read()).hexdigest()


def assert_same_trajectory(a_path, b_path):
    a, b = read_trajectory(a_path), read_trajectory(b_path)
    np.testing.assert_array_equal(a.steps, b.steps)
    np.testing.assert_array_equal(a.times, b.times)
    # Bit for bit: array_equal on float64, no tolerance.
    assert np.array_equal(a.positions, b.positions)
    assert np.array_equal(a.velocities, b.velocities)
    assert a.observables.keys() == b.observables.keys()
    for name in a.observables:
        assert np.array_equal(a.observables[name], b.observables[name]), name


@pytest.mark.parametrize("integrator", sorted(INTEGRATORS))
def test_resume_after_a_lost_tail_is_bitwise_identical(tmp_path, integrator):
    """Stop at 20, resume to 40, lose everything after the step-20 checkpoint, resume to 60."""
    config = tmp_path / "run.toml"
    config.write_text(config_text(integrator))
    assert run(config, "-o", "full.h5") == 0

    assert run(config, "-o", "cut.h5", "--steps", "20") == 0
    at_20 = tmp_path / "at_20.ckpt"
    shutil.copy(checkpoint_path("cut.h5"), at_20)
    assert run(config, "-o", "cut.h5", "--steps", "40", "--resume") == 0
    assert list(read_trajectory("cut.h5").steps) == [0, 10, 20, 30, 40]
    # As if killed after step 40 with the last checkpoint at step 20:
    shutil.copy(at_20, checkpoint_path("cut.h5"))
    assert run(config, "-o", "cut.h5", "--resume") == 0

    assert_same_trajectory("full.h5", "cut.h5")
    final_full = read_checkpoint(checkpoint_path("full.h5"))
    final_cut = read_checkpoint(checkpoint_path("cut.h5"))
    assert final_cut.state.step == final_full.state.step == 60
    assert final_cut.state.time == final_full.state.time
    assert np.array_equal(final_cut.state.positions, final_full.state.positions)
    assert np.array_equal(final_cut.state.velocities, final_full.state.velocities)
    assert repr(final_cut.integrator_state) == repr(final_full.integrator_state)


def test_integrator_state_is_what_makes_the_continuation_exact(tmp_path):
    """Control for the test above: without the saved half-step velocities leapfrog drifts off."""
    from integrators import Leapfrog
    from md.build import lattice, maxwell_boltzmann
    from md.simulation import Simulation
    from potentials import LennardJones

    def new_sim(state):
        return Simulation(state, [LennardJones(cutoff=2.5)], Leapfrog(dt=0.005))

    reference = new_sim(maxwell_boltzmann(lattice("fcc", 3, density=0.8442), 1.2, seed=3))
    reference.run(20)
    path = write_checkpoint(
        tmp_path / "c.ckpt", reference.state, reference.integrator, reference.forcefield
    )
    reference.run(20)
    saved = read_checkpoint(path)
    results = {}
    for with_state in (True, False):
        sim = new_sim(saved.state.copy())
        if with_state:
            restore(saved, sim.integrator, sim.forcefield)
        sim.run(20)
        results[with_state] = sim.state
    assert np.array_equal(results[True].positions, reference.state.positions)
    assert np.array_equal(results[True].velocities, reference.state.velocities)
    assert not np.array_equal(results[False].velocities, reference.state.velocities)


def test_resume_refuses_changed_physics_and_changes_nothing(tmp_path, capsys):
    config = tmp_path / "run.toml"
    config.write_text(config_text(steps=20))
    assert run(config) == 0
    files = {p: digest(p) for p in ("out.h5", checkpoint_path("out.h5"))}
    config.write_text(config_text(steps=40).replace("dt = 0.005", "dt = 0.004"))
    capsys.readouterr()
    assert run(config, "--resume") == 2
    err = capsys.readouterr().err
    assert "integrator.dt: 0.005 -> 0.004" in err and err.count("\n") == 1
    assert "Traceback" not in err
    config.write_text(config_text(steps=40).replace("cutoff = 2.5", "cutoff = 2.4"))
    assert run(config, "--resume") == 2
    assert "potentials[0].cutoff: 2.5 -> 2.4" in capsys.readouterr().err
    assert {p: digest(p) for p in files} == files
    # steps, thermo_every and the frame interval may change:
    config.write_text(config_text(steps=40).replace("every = 10", "every = 5"))
    assert run(config, "--resume") == 0
    assert list(read_trajectory("out.h5").steps) == [0, 10, 20, 25, 30, 35, 40]


def test_resume_refuses_a_trajectory_of_another_run(tmp_path, capsys):
    config = tmp_path / "run.toml"
    config.write_text(config_text(steps=20))
    assert run(config, "-o", "a.h5") == 0
    assert run(config, "-o", "b.h5") == 0
    shutil.copy(checkpoint_path("a.h5"), checkpoint_path("b.h5"))
    before = digest("b.h5")
    capsys.readouterr()
    assert run(config, "-o", "b.h5", "--steps", "40", "--resume") == 2
    assert "run id" in capsys.readouterr().err
    assert digest("b.h5") == before


def test_fresh_run_refuses_to_replace_a_checkpoint(tmp_path, capsys):
    config = tmp_path / "run.toml"
    config.write_text(config_text(steps=20))
    ckpt = checkpoint_path("out.h5")
    ckpt.write_bytes(b"keep me")
    assert run(config) == 2
    assert str(ckpt) in capsys.readouterr().err
    assert ckpt.read_bytes() == b"keep me" and not os.path.exists("out.h5")


def test_checkpoint_write_is_atomic(tmp_path, monkeypatch):
    from integrators import VelocityVerlet
    from md.build import lattice

    state = lattice("fcc", 2, density=0.8442)
    path = write_checkpoint(tmp_path / "c.ckpt", state, VelocityVerlet(dt=0.005), n_frames=3)
    before = digest(path)

    def broken_savez(handle, **arrays):
        handle.write(b"PK\x03\x04 half a zip")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np, "savez", broken_savez)
    state.step = 99
    with pytest.raises(OSError):
        write_checkpoint(path, state, VelocityVerlet(dt=0.005), n_frames=4)
    assert digest(path) == before and read_checkpoint(path).n_frames == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.ckpt"]  # no temporary left


@pytest.mark.parametrize("content", [b"", b"garbage", b"PK\x03\x04truncated zip", None])
def test_unreadable_checkpoint_is_refused(tmp_path, content):
    path = tmp_path / "c.ckpt"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(CheckpointError, match="c.ckpt"):
        read_checkpoint(path)


def test_blow_up_names_the_step_and_keeps_the_last_good_checkpoint(tmp_path, capsys):
    config = tmp_path / "run.toml"
    text = (
        config_text(steps=200)
        .replace("dt = 0.005", "dt = 0.05")
        .replace("temperature = 1.2", "temperature = 30.0")
    )
    config.write_text(text.replace("checkpoint_every = 20", "checkpoint_every = 1"))
    assert run(config) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    failed = int(err.split("step ")[1].split(":")[0])
    assert "too large" in err
    saved = read_checkpoint(checkpoint_path("out.h5"))
    assert saved.state.step == failed - 1  # the last good step
    assert np.all(np.isfinite(saved.state.positions))
    traj = read_trajectory("out.h5")
    assert traj.n_frames == saved.n_frames and traj.steps[-1] < failed


def test_output_directory_missing_or_read_only(tmp_path, capsys):
    config = tmp_path / "run.toml"
    config.write_text(config_text(steps=20))
    assert run(config, "-o", tmp_path / "missing" / "out.h5") == 2
    assert "does not exist" in capsys.readouterr().err
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        if os.access(locked, os.W_OK):
            pytest.skip("running as a user who can write anywhere")
        assert run(config, "-o", locked / "out.h5") == 2
        assert "not writable" in capsys.readouterr().err
    finally:
        locked.chmod(0o700)


def _wait_for_frames(path, n, process, timeout=60.0):
    import h5py

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert process.poll() is None, process.communicate()
        try:
            with h5py.File(path, "r", locking=False) as f:
                if len(f["particles/trajectory/position/step"]) >= n:
                    return
        except (OSError, KeyError):
            pass
        time.sleep(0.05)
    raise TimeoutError(path)


@pytest.mark.parametrize("signum, code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_signal_checkpoints_and_resume_completes_identically(tmp_path, signum, code):
    config = tmp_path / "run.toml"
    config.write_text(config_text("langevin", steps=100_000).replace("cells = 3", "cells = 4"))
    command = [sys.executable, "-m", "md.cli", "run", str(config), "--no-progress", "-q"]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _wait_for_frames(tmp_path / "out.h5", 3, process)
    process.send_signal(signum)
    _, err = process.communicate(timeout=60)
    assert process.returncode == code, err
    assert signal.Signals(signum).name in err and "--resume" in err and "Traceback" not in err
    saved = read_checkpoint(checkpoint_path(tmp_path / "out.h5"))
    traj = read_trajectory(tmp_path / "out.h5")
    assert saved.n_frames == traj.n_frames and saved.state.step >= traj.steps[-1]
    stop = saved.state.step + 30
    assert run(config, "--resume", "--steps", stop) == 0
    assert run(config, "-o", "full.h5", "--steps", stop) == 0
    assert_same_trajectory("full.h5", "out.h5")


def test_a_list_kept_through_cell_changes_is_restored_as_it_was(tmp_path):
    """A barostat moved the cell after the last build: the restored list is built in the
    build's cell and follows to the current one, so its pairs, codes and shifts, hence the
    force summation order, are the uninterrupted run's."""
    from integrators import VelocityVerlet
    from md.forcefield import ForceField
    from potentials import LennardJones

    state = md.maxwell_boltzmann(md.lattice("fcc", 6, density=0.8), 1.0, seed=2)
    ff = ForceField([LennardJones(cutoff=2.5)], skin=0.4)
    ff.compute(state)
    for scale in (1.004, 1.003, 0.999):
        state.positions *= scale
        state.box = state.box * scale
        ff.compute(state)
    nl = ff.neighbor_list
    assert nl.n_builds == 1 and nl.n_followed == 3
    path = write_checkpoint(tmp_path / "c.npz", state, VelocityVerlet(0.005), ff)
    checkpoint = read_checkpoint(path)
    again = ForceField([LennardJones(cutoff=2.5)], skin=0.4)
    restore(checkpoint, VelocityVerlet(0.005), again)
    other = again.neighbor_list
    for name in ("order", "images", "slot_starts", "slot_neighbors", "codes", "shifts", "lengths"):
        np.testing.assert_array_equal(getattr(other, name), getattr(nl, name))
    assert again.compute(checkpoint.state).energy == ff.compute(state).energy
