"""The md command: runs, summaries, and every bad input stopping before output is written."""

from __future__ import annotations

import hashlib
import json
import math

import numpy as np
import pytest

from conftest import lj_config_text
from md.cli import main
from md.trajectory import open_trajectory, read_trajectory

SMALL = lj_config_text(cells=4)


def write_config(tmp_path, text=SMALL, name="run.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def replace(text: str, old: str, new: str) -> str:
    assert old in text, old
    return text.replace(old, new)


@pytest.fixture(autouse=True)
def in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)


def test_run_writes_a_trajectory_mdanalysis_opens(tmp_path, capsys):
    config = write_config(tmp_path)
    assert main(["run", str(config), "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "atom-steps/s" in out and "neighbor" in out and "drift" in out
    traj = read_trajectory(tmp_path / "out.h5")
    assert list(traj.steps) == [0, 10, 20, 30, 40]
    assert traj.n_atoms == 256
    assert traj.parameters["config"] == SMALL
    assert traj.parameters["integrator"] == {"type": "verlet", "dt": 0.005}
    assert traj.parameters["seed"] == 5
    # initial temperature is exactly the requested one (3N - 3 dof)
    assert traj.observables["temperature"][0] == pytest.approx(1.2, rel=1e-12)
    energy = traj.observables["total_energy"]
    assert np.ptp(energy) < 1e-3 * abs(energy[0])
    u = open_trajectory(tmp_path / "out.h5")
    assert u.trajectory.n_frames == 5


def test_overrides_and_same_seed_reproduces(tmp_path):
    config = write_config(tmp_path)
    assert main(["run", str(config), "--steps", "20", "-o", "a.h5", "--no-progress", "-q"]) == 0
    assert main(["run", str(config), "--steps", "20", "-o", "b.h5", "--no-progress", "-q"]) == 0
    a, b = read_trajectory(tmp_path / "a.h5"), read_trajectory(tmp_path / "b.h5")
    assert list(a.steps) == [0, 10, 20]
    np.testing.assert_array_equal(a.positions, b.positions)


def test_existing_output_is_kept_without_overwrite(tmp_path, capsys):
    config = write_config(tmp_path)
    out = tmp_path / "out.h5"
    out.write_bytes(b"an earlier result")
    assert main(["run", str(config), "--no-progress"]) == 2
    assert "out.h5" in capsys.readouterr().err
    assert out.read_bytes() == b"an earlier result"
    assert main(["run", str(config), "--no-progress", "--overwrite", "-q"]) == 0
    assert read_trajectory(out).n_frames == 5


def test_info_summarises(tmp_path, capsys):
    config = write_config(tmp_path)
    main(["run", str(config), "--no-progress", "-q"])
    capsys.readouterr()
    assert main(["info", "out.h5"]) == 0
    text = capsys.readouterr().out
    assert "256" in text and "frames" in text and "verlet" in text and "total energy" in text
    assert main(["info", "out.h5", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["n_frames"] == 5 and summary["n_atoms"] == 256
    assert summary["last_time"] == pytest.approx(40 * 0.005)


@pytest.mark.parametrize("content", [b"", b"garbage", None])
def test_info_refuses_bad_files(tmp_path, capsys, content):
    path = tmp_path / "x.h5"
    if content is not None:
        path.write_bytes(content)
    assert main(["info", str(path)]) == 2
    err = capsys.readouterr().err
    assert "x.h5" in err and "Traceback" not in err


BAD_CONFIGS = {
    "unknown top-level key": (("seed = 5", "seed = 5\ncolour = 3"), "colour"),
    "unknown key in a table": (("density = 0.8442", "density = 0.8442\ndensty = 1"), "densty"),
    "unknown potential key": (("cutoff = 2.5", "cutoff = 2.5\nepsilonn = 1"), "epsilonn"),
    "missing dt": (("dt = 0.005", ""), "dt"),
    "missing system": (("[system]", "[systemx]"), "system"),
    "wrong type dt": (("dt = 0.005", 'dt = "fast"'), "dt"),
    "zero dt": (("dt = 0.005", "dt = 0.0"), "dt"),
    "negative dt": (("dt = 0.005", "dt = -0.001"), "dt"),
    "nan dt": (("dt = 0.005", "dt = nan"), "dt"),
    "infinite density": (("density = 0.8442", "density = inf"), "density"),
    "negative mass": (("density = 0.8442", "density = 0.8442\nmass = -1.0"), "mass"),
    "zero mass": (("density = 0.8442", "density = 0.8442\nmass = 0.0"), "mass"),
    "cutoff too long": (("cutoff = 2.5", "cutoff = 3.5"), "cutoff"),
    "unknown potential": (('type = "lj"', 'type = "no_such_style"'), "no_such_style"),
    "unknown integrator": (('type = "verlet"', 'type = "magic"'), "magic"),
    "bad cutoff mode": (("cutoff = 2.5", 'cutoff = 2.5\ncutoff_mode = "soft"'), "soft"),
    "r_on beyond cutoff": (
        ("cutoff = 2.5", 'cutoff = 2.5\ncutoff_mode = "smooth"\nr_on = 3.0'),
        "r_on",
    ),
    "wrong type steps": (("steps = 40", "steps = 4.5"), "steps"),
    "negative temperature": (("temperature = 1.2", "temperature = -1.0"), "temperature"),
    "structure file missing": (
        ('lattice = "fcc"\ncells = 4\ndensity = 0.8442', 'structure = "nowhere.xyz"'),
        "nowhere.xyz",
    ),
    "invalid toml": (("[run]", "[run"), "TOML"),
    "bad cells": (("cells = 4", "cells = [4, 4]"), "cells"),
}


@pytest.mark.parametrize("case", list(BAD_CONFIGS))
def test_bad_config_exits_2_before_writing(tmp_path, capsys, case):
    (old, new), expected = BAD_CONFIGS[case]
    config = write_config(tmp_path, replace(SMALL, old, new))
    assert main(["run", str(config), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert expected in err, err
    assert "run.toml" in err or "--" in err
    assert "Traceback" not in err
    assert not (tmp_path / "out.h5").exists()


def test_missing_config_file(tmp_path, capsys):
    assert main(["run", "absent.toml"]) == 2
    assert "absent.toml" in capsys.readouterr().err


def test_bad_command_line(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["run", "x.toml", "--steps", "many"])
    assert exit_info.value.code == 2


def _structure_config(tmp_path, atoms, extra=""):
    import ase.io

    ase.io.write(tmp_path / "start.extxyz", atoms)
    text = f"""\
units = "metal"
seed = 1

[system]
structure = "start.extxyz"
temperature = 50.0
{extra}
[[potentials]]
type = "lj"
epsilon = 0.0104
sigma = 3.40
cutoff = 8.0

[integrator]
type = "verlet"
dt = 5.0

[run]
steps = 20
thermo_every = 10

[output]
path = "out.h5"
every = 10
"""
    return write_config(tmp_path, text)


def test_structure_file_in_metal_units(tmp_path):
    from ase.build import bulk

    atoms = bulk("Ar", "fcc", a=5.26, cubic=True).repeat((4, 4, 4))
    config = _structure_config(tmp_path, atoms)
    assert main(["run", str(config), "--no-progress", "-q"]) == 0
    traj = read_trajectory(tmp_path / "out.h5")
    assert traj.type_names == ("Ar",)
    np.testing.assert_allclose(traj.masses, 39.948)
    assert traj.times[-1] == pytest.approx(20 * 5 * 0.09822694788464063, rel=1e-6)  # 5 fs steps
    assert traj.observables["temperature"][0] == pytest.approx(50.0, rel=1e-12)
    u = open_trajectory(tmp_path / "out.h5")
    assert u.trajectory[-1].time == pytest.approx(0.1)  # ps
    assert set(u.atoms.types) == {"Ar"}


def test_structure_with_nan_coordinates(tmp_path, capsys):
    from ase.build import bulk

    atoms = bulk("Ar", "fcc", a=5.26, cubic=True).repeat((4, 4, 4))
    atoms.positions[3, 1] = math.nan
    config = _structure_config(tmp_path, atoms)
    assert main(["run", str(config), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "start.extxyz" in err or "structure" in err
    assert "atom 3" in err
    assert not (tmp_path / "out.h5").exists()


def test_overlapping_atoms_are_refused(tmp_path, capsys):
    from ase.build import bulk

    atoms = bulk("Ar", "fcc", a=5.26, cubic=True).repeat((4, 4, 4))
    atoms.positions[1] = atoms.positions[0]
    config = _structure_config(tmp_path, atoms)
    assert main(["run", str(config), "--no-progress"]) == 2
    assert "overlapping" in capsys.readouterr().err
    assert not (tmp_path / "out.h5").exists()


def test_blow_up_stops_with_step_and_keeps_frames(tmp_path, capsys):
    config = write_config(
        tmp_path,
        replace(replace(SMALL, "dt = 0.005", "dt = 0.2"), "steps = 40", "steps = 400"),
    )
    assert main(["run", str(config), "--no-progress", "-q"]) == 1
    err = capsys.readouterr().err
    assert "step" in err and "out.h5" in err
    step = int(err.split("step ")[1].split(":")[0])
    assert 0 < step < 400
    traj = read_trajectory(tmp_path / "out.h5")
    assert traj.n_frames >= 1
    assert traj.steps[-1] < step
    assert np.all(np.isfinite(traj.positions))
    assert open_trajectory(tmp_path / "out.h5").trajectory.n_frames == traj.n_frames


def test_output_is_hashed_unchanged_by_a_refused_run(tmp_path):
    config = write_config(tmp_path)
    assert main(["run", str(config), "--no-progress", "-q"]) == 0
    digest = hashlib.sha256((tmp_path / "out.h5").read_bytes()).hexdigest()
    bad = write_config(tmp_path, replace(SMALL, "cutoff = 2.5", "cutoff = 9.0"), "bad.toml")
    assert main(["run", str(bad), "--no-progress"]) == 2
    assert main(["run", str(config), "--no-progress"]) == 2
    assert hashlib.sha256((tmp_path / "out.h5").read_bytes()).hexdigest() == digest


EXAMPLES = sorted((__import__("pathlib").Path(__file__).parents[1] / "examples").glob("*.toml"))


# The implicit stiff chain (7 s) runs with -m slow: the default suite keeps within 10 minutes.
EXAMPLE_CASES = [
    pytest.param(p, marks=pytest.mark.slow) if p.stem == "implicit-stiff" else p for p in EXAMPLES
]


@pytest.mark.parametrize("example", EXAMPLE_CASES, ids=[p.stem for p in EXAMPLES])
def test_examples_run(tmp_path, example):
    """Every shipped example config is valid and runs (a few steps here)."""
    out = tmp_path / f"{example.stem}.h5"
    assert main(["run", str(example), "--steps", "3", "-o", str(out), "--no-progress", "-q"]) == 0
    traj = read_trajectory(out)
    assert traj.steps[0] == 0 and np.all(np.isfinite(traj.observables["total_energy"]))


POLYMER = """\
units = "lj"
seed = 3

[system]
polymer = "melt"
chains = 4
chain_length = 10
density = 0.5
temperature = 1.0

[[potentials]]
type = "lj"
cutoff = 1.122462048309373

[[potentials]]
type = "fene"
bonds = "system"

[integrator]
type = "verlet"
dt = 0.002

[run]
steps = 20

[output]
path = "out.h5"
every = 10
"""


def test_polymer_melt_from_config(tmp_path):
    config = write_config(tmp_path, POLYMER)
    assert main(["run", str(config), "--no-progress", "-q"]) == 0
    traj = read_trajectory(tmp_path / "out.h5")
    assert traj.n_atoms == 40 and traj.type_names == ("M",)
    bonded = traj.positions[0][1:10] - traj.positions[0][:9]  # chain 0 is beads 0..9
    np.testing.assert_allclose(np.linalg.norm(bonded, axis=1), 0.97, rtol=1e-9)
    assert traj.parameters["potentials"][1]["type"] == "fene"


def test_bonds_file_is_relative_to_the_config(tmp_path, monkeypatch):
    sub = tmp_path / "inputs"
    sub.mkdir()
    chains = [[10 * c + i, 10 * c + i + 1] for c in range(4) for i in range(9)]
    np.savetxt(sub / "bonds.txt", chains, fmt="%d")
    text = replace(POLYMER, 'bonds = "system"', 'bonds_file = "bonds.txt"')
    config = write_config(sub, text)
    monkeypatch.chdir(tmp_path)
    assert main(["run", str(config), "--no-progress", "-q", "-o", "b.h5"]) == 0


def test_system_bonds_need_a_polymer(tmp_path, capsys):
    text = SMALL + '\n[[potentials]]\ntype = "spring"\nbonds = "system"\nk = 1.0\nr0 = 1.0\n'
    config = write_config(tmp_path, text)
    assert main(["run", str(config), "--no-progress"]) == 2
    assert "polymer" in capsys.readouterr().err
    assert not (tmp_path / "out.h5").exists()


# A run's memory must not grow with its length (issue 33 item 9: every thermo row was kept,
# about 1 KB each). Measured in a fresh process: Python's allocated blocks over the loop,
# taken while the run's observers (the thermo table) are still alive.
_GROWTH = """
import gc, json, sys
import md.simulation
from md.cli import main

grown = {}
loop = md.simulation.Simulation.run

def measured(self, n_steps):
    gc.collect()
    before = sys.getallocatedblocks()
    loop(self, n_steps)
    gc.collect()
    grown[n_steps] = sys.getallocatedblocks() - before

md.simulation.Simulation.run = measured
for n in (10, 50, 500):
    assert main(["run", "run.toml", "--steps", str(n), "-o", f"run{n}.h5", "--no-progress"]) == 0
print(json.dumps(grown))
"""


def test_md_run_memory_does_not_grow_with_the_number_of_thermo_rows(tmp_path):
    import os
    import subprocess
    import sys
    from pathlib import Path

    config = lj_config_text(run="steps = 10\nthermo_every = 1", output='path = "run.h5"')
    (tmp_path / "run.toml").write_text(config)
    root = Path(__file__).resolve().parents[1]
    done = subprocess.run(
        [sys.executable, "-c", _GROWTH],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(root)},
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.count("\n") > 500  # the thermo table printed every step
    grown = {int(k): v for k, v in json.loads(done.stdout.strip().splitlines()[-1]).items()}
    # Kept per step between 50 and 500 steps: was ~17 blocks (a dict of floats) per row.
    assert (grown[500] - grown[50]) / 450 < 0.5, grown
