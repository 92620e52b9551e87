"""Bad input never costs data: random configs, broken structures and broken HDF5 files.

Every generated case must either run (exit 0; 1 if the dynamics blows up) or
stop with exit 2 and exactly one ``md: error:`` line, with no traceback, and
leave every file that existed before untouched.
"""

from __future__ import annotations

import contextlib
import copy
import hashlib
import io
import itertools
import os
import shutil
import tempfile
from pathlib import Path

import h5py
import numpy as np
import pytest
from _configs import argon_structure_run, to_toml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from md.checkpoint import checkpoint_path
from md.cli import main

BASE = {
    "units": "lj",
    "seed": 3,
    "system": {"lattice": "fcc", "cells": 3, "density": 0.8442, "temperature": 1.0},
    "potentials": [{"type": "lj", "cutoff": 2.5}],
    "integrator": {"type": "verlet", "dt": 0.005},
    "run": {"steps": 5, "thermo_every": 5},
    "output": {"path": "new.h5", "every": 5, "checkpoint_every": 5},
}

#: Magnitudes past what the engine can use (int64, float64 and 2**53 edges).
EXTREMES = [2**53 + 1, 2**63, 2**64, 10**23, -(10**23), 1e300, -1e300, 5e-324, 1e-300, 1e308]
#: Every numeric key of a config (the fuzzing below also reaches the rest).
NUMERIC_KEYS = [
    ("", "seed"),
    ("system", "cells"),
    ("system", "density"),
    ("system", "temperature"),
    ("system", "mass"),
    ("system", "lattice_constant"),
    ("potentials.0", "cutoff"),
    ("potentials.0", "epsilon"),
    ("potentials.0", "sigma"),
    ("potentials.0", "r_on"),
    ("integrator", "dt"),
    ("run", "steps"),
    ("run", "skin"),
    ("run", "thermo_every"),
    ("run", "threads"),
    ("output", "every"),
    ("output", "checkpoint_every"),
]

SCALARS = st.one_of(
    st.integers(-3, 5),
    st.sampled_from([0, -1, 10**6, 2**63 - 1]),
    st.sampled_from(EXTREMES),
    st.floats(allow_nan=True, allow_infinity=True, width=64),
    st.sampled_from([0.0, -0.0, 1e-300, 1e300, 0.5, 2.5]),
    st.booleans(),
    st.text(max_size=6),
    st.sampled_from(["fcc", "lj", "verlet", "metal", "existing.h5", "sub/x.h5", "."]),
)
VALUES = st.one_of(
    SCALARS,
    st.lists(SCALARS, max_size=4),
    st.dictionaries(st.text(max_size=4), SCALARS, max_size=2),
)
KEYS = {
    "": ["units", "seed", "bogus"],
    "system": [
        "lattice",
        "cells",
        "density",
        "lattice_constant",
        "temperature",
        "mass",
        "pbc",
        "type_name",
        "structure",
        "polymer",
    ],
    "potentials.0": ["type", "cutoff", "epsilon", "sigma", "cutoff_mode", "r_on", "bonds"],
    "integrator": ["type", "dt", "tol", "temperature", "friction", "tau", "seed"],
    "run": ["steps", "skin", "thermo_every"],
    "output": ["path", "every", "velocities", "forces", "checkpoint_every"],
}


@st.composite
def configs(draw):
    data = {
        k: (dict(v) if isinstance(v, dict) else [dict(e) for e in v] if isinstance(v, list) else v)
        for k, v in BASE.items()
    }
    for _ in range(draw(st.integers(1, 3))):
        where = draw(st.sampled_from(sorted(KEYS)))
        table = (
            data
            if where == ""
            else data["potentials"][0]
            if where == "potentials.0"
            else (data.setdefault(where, {}))
        )
        if not isinstance(table, dict):
            continue
        key = draw(st.sampled_from(KEYS[where]))
        if draw(st.integers(0, 4)) == 0:
            table.pop(key, None)
        else:
            table[key] = draw(VALUES)
    if draw(st.integers(0, 5)) == 0:
        data[draw(st.sampled_from(sorted(KEYS)[1:]))] = draw(SCALARS)  # a table made a value
    return data


def _snapshot(folder: Path) -> dict:
    return {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in folder.rglob("*") if p.is_file()}


def run_cli(argv) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = main(argv)
    return code, err.getvalue()


def check_outcome(code: int, err: str) -> None:
    assert "Traceback" not in err, err
    assert code in (0, 1, 2), (code, err)
    if code != 0:
        errors = [line for line in err.splitlines() if line.startswith("md: error:")]
        assert len(errors) == 1 and len(errors[0]) > len("md: error: ") + 10, err


@pytest.fixture
def workspace():
    with tempfile.TemporaryDirectory() as name:
        folder = Path(name)
        (folder / "existing.h5").write_bytes(b"an earlier result")
        (folder / "sub").mkdir()
        yield folder


def _in(folder: Path):
    class _Chdir(contextlib.ContextDecorator):
        def __enter__(self):
            self.old = os.getcwd()
            os.chdir(folder)

        def __exit__(self, *exc):
            os.chdir(self.old)

    return _Chdir()


@pytest.mark.parametrize("where_key", NUMERIC_KEYS, ids=lambda wk: ".".join(filter(None, wk)))
def test_extreme_magnitudes_of_every_numeric_key(workspace, where_key):
    """Each numeric key at magnitudes past the int64/float64/2**53 edges: a run (possibly
    one that reports its own blow-up, exit 1) or exit 2 naming the key, never a
    traceback, never a touched file; steps come from the config here, not --steps."""
    where, key = where_key
    for value, smooth in itertools.product(EXTREMES, (False, True)):
        data = copy.deepcopy(BASE)
        table = (
            data
            if where == ""
            else data["potentials"][0]
            if where == "potentials.0"
            else (data[where])
        )
        table[key] = value
        if smooth:
            data["potentials"][0]["cutoff_mode"] = "smooth"
        config = workspace / "run.toml"
        config.write_text(to_toml(data))
        before = _snapshot(workspace)
        with _in(workspace):
            code, err = run_cli(["run", str(config), "--no-progress", "-q"])
        check_outcome(code, err)
        if code == 2:
            assert key in err or "cutoff" in err or "box" in err, (value, err)
        after = _snapshot(workspace)
        for path, digest in before.items():
            assert after.get(path) == digest, (path, value, err)
        for path in set(after) - set(before):
            path.unlink()


@pytest.mark.parametrize("steps", [str(2**53 + 1), str(2**63), str(10**23), "-1"])
def test_steps_out_of_range_on_the_command_line(workspace, steps):
    config = workspace / "run.toml"
    config.write_text(to_toml(BASE))
    before = _snapshot(workspace)
    with _in(workspace):
        code, err = run_cli(["run", str(config), "--no-progress", "-q", "--steps", steps])
    check_outcome(code, err)
    assert code == 2 and "--steps" in err
    assert _snapshot(workspace) == before


@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(data=configs(), resume=st.booleans())
def test_random_configs_run_or_exit_2_without_touching_files(workspace, data, resume):
    config = workspace / "run.toml"
    config.write_text(to_toml(data))
    before = _snapshot(workspace)
    argv = ["run", str(config), "--no-progress", "-q", "--steps", "5"]
    with _in(workspace):
        code, err = run_cli(argv + (["--resume"] if resume else []))
    check_outcome(code, err)
    after = _snapshot(workspace)
    for path, digest in before.items():
        assert after.get(path) == digest, (path, err)
    for path in set(after) - set(before):  # clean up what a successful run wrote
        path.unlink()


@pytest.mark.parametrize(
    ("run_table", "flags", "expected"),
    [
        ({}, ["--threads", "0"], "--threads: threads must be a positive integer, got 0"),
        ({}, ["--threads", "100000"], "--threads: threads = 100000 is more than the"),
        ({"threads": "two"}, [], "[run] threads: expected an integer, got 'two'"),
        ({"threads": 0}, [], "[run] threads"),
    ],
)
def test_bad_thread_counts_exit_2_before_any_output(workspace, run_table, flags, expected):
    from md.parallel import get_threads

    before_threads = get_threads()
    data = {**BASE, "run": {**BASE["run"], **run_table}}
    config = workspace / "run.toml"
    config.write_text(to_toml(data))
    before = _snapshot(workspace)
    with _in(workspace):
        code, err = run_cli(["run", str(config), "--no-progress", "-q", *flags])
    check_outcome(code, err)
    assert code == 2 and expected in err, err
    assert _snapshot(workspace) == before
    assert get_threads() == before_threads  # a refused setting changes nothing


def _xyz(positions, box, symbols=None, pbc="T T T", count=None) -> str:
    n = len(positions) if count is None else count
    lattice = " ".join(str(x) for x in np.diag(box).ravel())
    lines = [str(n), f'Lattice="{lattice}" Properties=species:S:1:pos:R:3 pbc="{pbc}"']
    for i, p in enumerate(positions):
        lines.append(f"{(symbols or ['Ar'] * len(positions))[i]} {p[0]} {p[1]} {p[2]}")
    return "\n".join(lines) + "\n"


STRUCTURE_CONFIG = argon_structure_run("s.xyz", run="steps = 5", output='path = "s.h5"\nevery = 5')


def _structures():
    rng = np.random.default_rng(5)
    box = np.full(3, 20.0)
    gas = rng.uniform(0, 20, (12, 3))
    overlapping = gas.copy()
    overlapping[1] = overlapping[0]
    outside = gas + [45.0, -30.0, 61.0]
    nan = gas.copy()
    nan[3, 1] = np.nan
    return {
        "overlapping": (_xyz(overlapping, box), 2),
        "outside_the_box": (_xyz(outside, box), 0),
        "empty": (_xyz(np.zeros((0, 3)), box), 2),
        "one_atom": (_xyz(gas[:1], box), 0),
        "nan_coordinate": (_xyz(nan, box), 2),
        "zero_box_length": (_xyz(gas, np.array([20.0, 0.0, 20.0])), 2),
        "count_line_too_large": (_xyz(gas, box, count=40), 2),
        "count_line_huge": (_xyz(gas, box, count=10**12), 2),  # ase.io alone would spin
        "unknown_element": (_xyz(gas, box, symbols=["Xx"] * 12), 2),
        "not_a_structure": ("\x00\x01 binary junk \xff", 2),
    }


@pytest.mark.parametrize("name", sorted(_structures()))
def test_bad_structures(workspace, name):
    text, expected = _structures()[name]
    (workspace / "s.xyz").write_text(text)
    (workspace / "run.toml").write_text(STRUCTURE_CONFIG)
    before = _snapshot(workspace)
    with _in(workspace):
        code, err = run_cli(["run", "run.toml", "--no-progress", "-q"])
    check_outcome(code, err)
    assert code == expected, err
    if code == 2:
        assert _snapshot(workspace) == before
    if name == "outside_the_box":  # positions are not wrapped, and the run equals a wrapped one
        from md.trajectory import read_trajectory

        traj = read_trajectory(workspace / "s.h5")
        assert np.allclose(
            traj.positions[0],
            np.array([[float(x) for x in line.split()[1:]] for line in text.splitlines()[2:]]),
        )


# ------------------------------------------------------------ broken HDF5 files
@pytest.fixture(scope="module")
def good_run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("good")
    config = folder / "run.toml"
    config.write_text(to_toml(BASE).replace('"new.h5"', '"out.h5"'))
    with _in(folder):
        assert run_cli(["run", "run.toml", "--no-progress", "-q", "--steps", "20"])[0] == 0
    return folder


def _corruptions(good: Path, target: Path):
    data = (good / "out.h5").read_bytes()
    rng = np.random.default_rng(9)
    yield "truncated_half", data[: len(data) // 2]
    yield "truncated_header", data[:100]
    flipped = bytearray(data)
    for i in rng.integers(0, len(data), 200):
        flipped[i] ^= 0xFF
    yield "random_bytes_flipped", bytes(flipped)
    zeroed = bytearray(data)
    zeroed[:2048] = b"\x00" * 2048
    yield "superblock_zeroed", bytes(zeroed)
    with h5py.File(target, "w") as f:  # an HDF5 file that is not ours
        f["data"] = np.arange(10)
    yield "foreign_hdf5", target.read_bytes()
    with h5py.File(target, "w") as f:  # H5MD-looking but missing datasets
        f.create_group("h5md")
        f.create_group("particles/trajectory/position")
    yield "h5md_without_data", target.read_bytes()


@pytest.mark.parametrize(
    "case",
    [
        "truncated_half",
        "truncated_header",
        "random_bytes_flipped",
        "superblock_zeroed",
        "foreign_hdf5",
        "h5md_without_data",
    ],
)
def test_broken_trajectories_to_info_and_resume(good_run, tmp_path, case):
    shutil.copy(good_run / "run.toml", tmp_path / "run.toml")
    shutil.copy(checkpoint_path(good_run / "out.h5"), checkpoint_path(tmp_path / "out.h5"))
    content = dict(_corruptions(good_run, tmp_path / "scratch.h5"))[case]
    (tmp_path / "scratch.h5").unlink()
    (tmp_path / "out.h5").write_bytes(content)
    before = _snapshot(tmp_path)
    with _in(tmp_path):
        code, err = run_cli(["info", "out.h5"])
        if code != 0:  # flipped bytes may miss everything that matters
            check_outcome(code, err)
            assert code == 2 and "out.h5" in err
        code, err = run_cli(["analyze", "out.h5", "--thermo", "--out", "analysis", "--no-progress"])
        if code != 0:
            check_outcome(code, err)
            assert code == 2 and "out.h5" in err
            assert not (tmp_path / "analysis").exists()
        else:
            shutil.rmtree(tmp_path / "analysis")
        code, err = run_cli(["run", "run.toml", "--no-progress", "-q", "--steps", "40", "--resume"])
    if code != 0:
        check_outcome(code, err)
        assert code == 2 and "out.h5" in err
        assert _snapshot(tmp_path) == before
    else:  # only possible if the damage spared every dataset read
        assert case == "random_bytes_flipped"


@pytest.mark.parametrize("content", [b"", b"junk", None])
def test_broken_checkpoint_to_resume(good_run, tmp_path, content):
    shutil.copy(good_run / "run.toml", tmp_path / "run.toml")
    shutil.copy(good_run / "out.h5", tmp_path / "out.h5")
    ckpt = checkpoint_path(tmp_path / "out.h5")
    if content is not None:
        ckpt.write_bytes(content)
    before = _snapshot(tmp_path)
    with _in(tmp_path):
        code, err = run_cli(["run", "run.toml", "--no-progress", "-q", "--steps", "40", "--resume"])
    check_outcome(code, err)
    assert code == 2 and "ckpt" in err
    assert _snapshot(tmp_path) == before


def test_disk_full_keeps_the_frames_written(tmp_path):
    """A file-size limit (RLIMIT_FSIZE) stands in for a full disk: the writer checks the
    room before each frame (free space and this limit), so the run stops cleanly and
    every frame written stays readable."""
    import resource
    import signal
    import subprocess
    import sys

    config = tmp_path / "run.toml"
    data = dict(BASE, output=dict(BASE["output"], path="out.h5", every=1, checkpoint_every=1000))
    config.write_text(to_toml(data))

    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (300_000, 300_000))

    command = [
        sys.executable,
        "-m",
        "md.cli",
        "run",
        str(config),
        "--no-progress",
        "-q",
        "--steps",
        "100000",
    ]
    result = subprocess.run(
        command, cwd=tmp_path, preexec_fn=limit, capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr and "cannot write" in result.stderr
    from md.trajectory import open_trajectory, read_trajectory

    traj = read_trajectory(tmp_path / "out.h5")
    assert traj.n_frames > 5
    np.testing.assert_array_equal(traj.steps, np.arange(traj.n_frames))
    assert np.all(np.isfinite(traj.positions))
    universe = open_trajectory(tmp_path / "out.h5")
    assert universe.trajectory.n_frames == traj.n_frames
    universe.trajectory.close()


def test_writer_refuses_a_frame_the_disk_cannot_hold(tmp_path, monkeypatch):
    """With (simulated) no free space the writer raises ENOSPC before touching the file,
    and the frames already written read back intact."""
    import errno
    import os
    from types import SimpleNamespace

    import md
    from md.trajectory import H5MDWriter, read_trajectory

    state = md.lattice("fcc", 2, density=0.8)
    path = tmp_path / "full.h5"
    with H5MDWriter(path, state, units="lj") as writer:
        for _ in range(3):
            state.step += 1
            writer.write(state)
        real = os.statvfs(tmp_path)
        monkeypatch.setattr(
            "md.trajectory.writer.os.statvfs",
            lambda _path: SimpleNamespace(f_bavail=1, f_frsize=real.f_frsize),
        )
        state.step += 1
        with pytest.raises(OSError) as caught:
            writer.write(state)
        assert caught.value.errno == errno.ENOSPC and "3 frames written are intact" in str(
            caught.value
        )
    monkeypatch.undo()
    traj = read_trajectory(path)
    np.testing.assert_array_equal(traj.steps, [1, 2, 3])


@pytest.mark.parametrize("mass", [5e-324, 1e308])
def test_a_mass_whose_inverse_or_kinetic_energy_overflows_is_refused(workspace, mass):
    data = copy.deepcopy(BASE)
    data["system"]["mass"] = mass
    config = workspace / "run.toml"
    config.write_text(to_toml(data))
    before = _snapshot(workspace)
    with _in(workspace):
        code, err = run_cli(["run", str(config), "--no-progress", "-q"])
    check_outcome(code, err)
    if mass < 1:  # 1 / 5e-324 overflows: refused up front, naming the mass
        assert code == 2 and "mass" in err, err
        assert _snapshot(workspace) == before
