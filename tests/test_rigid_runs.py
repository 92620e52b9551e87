"""Rigid bodies through ``md run`` (issue 68): configs, refusals, checkpoints (the
exclusions: ``test_rigid_exclusions.py``)."""

from __future__ import annotations

import shutil

import h5py
import numpy as np
import pytest
from test_rigid import TRIMER, TRIMER_MASSES

from md.assemble import build_simulation
from md.checkpoint import checkpoint_path, read_checkpoint
from md.cli import main
from md.config import load_config
from md.errors import ConfigError
from md.forcefield import ForceField
from md.rigid import RigidBodies
from md.rigid_setup import lammps_molecule_ids
from md.trajectory import open_trajectory, read_trajectory
from potentials.lennard_jones import LennardJones

CONFIG = """units = "lj"
seed = 11
[system]
polymer = "melt"
chains = 12
chain_length = 3
density = 0.05
bond_length = 1.0
temperature = 1.0
[[potentials]]
type = "lj"
cutoff = 2.5
[integrator]
type = "velocity_verlet"
dt = 0.002
[rigid]
rotation = "ROTATION"
[run]
steps = 60
thermo_every = 10
[output]
path = "out.h5"
every = 10
velocities = true
checkpoint_every = 20
"""


@pytest.fixture(autouse=True)
def in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)


def run(*args) -> int:
    return main(["run", *map(str, args), "--no-progress", "-q"])


@pytest.mark.parametrize("rotation", ["no_squish", "richardson"])
def test_resume_is_bitwise_identical(tmp_path, rotation):
    """Stop at 20, resume to 40, lose everything after step 20, resume to 60."""
    config = tmp_path / "run.toml"
    config.write_text(CONFIG.replace("ROTATION", rotation))
    assert run(config, "-o", "full.h5") == 0
    assert run(config, "-o", "cut.h5", "--steps", "20") == 0
    shutil.copy(checkpoint_path("cut.h5"), "at_20.ckpt")
    assert run(config, "-o", "cut.h5", "--steps", "40", "--resume") == 0
    shutil.copy("at_20.ckpt", checkpoint_path("cut.h5"))
    assert run(config, "-o", "cut.h5", "--resume") == 0
    a, b = read_trajectory("full.h5"), read_trajectory("cut.h5")
    assert list(b.steps) == [0, 10, 20, 30, 40, 50, 60]
    assert np.array_equal(a.positions, b.positions)
    assert np.array_equal(a.velocities, b.velocities)
    full = read_checkpoint(checkpoint_path("full.h5"))
    cut = read_checkpoint(checkpoint_path("cut.h5"))
    for name, value in full.integrator_state.items():
        assert np.array_equal(value, cut.integrator_state[name]), name
    assert full.integrator_state["quaternions"].shape == (12, 4)
    # Body centres and quaternions beside the atoms, resumed frames included.
    with h5py.File("full.h5", "r") as full_file, h5py.File("cut.h5", "r") as cut_file:
        centres = full_file["rigid/centre/value"][()]
        quaternions = full_file["rigid/orientation/value"][()]
        assert centres.shape == (7, 12, 3) and quaternions.shape == (7, 12, 4)
        assert np.array_equal(centres, cut_file["rigid/centre/value"][()])
        assert np.array_equal(quaternions, cut_file["rigid/orientation/value"][()])
        assert list(full_file["rigid/centre/step"][()]) == list(a.steps)
    assert np.allclose(np.linalg.norm(quaternions, axis=-1), 1.0, atol=1e-14)
    masses = a.masses.reshape(12, 3)
    x = a.positions.reshape(7, 12, 3, 3)
    assert np.allclose(
        (masses[None, :, :, None] * x).sum(2) / masses.sum(1)[None, :, None], centres
    )
    # MDAnalysis sees the constituents as atoms, where our reader puts them.
    universe = open_trajectory("full.h5")  # an MDAnalysis Universe
    assert universe.atoms.n_atoms == 36 and len(universe.trajectory) == 7
    universe.trajectory[-1]
    wrapped = a.positions[-1] - np.floor(a.positions[-1] / a.boxes[-1]) * a.boxes[-1]
    assert np.allclose(universe.atoms.positions, wrapped, atol=2e-5 * a.boxes[-1].max())
    # The bodies held their shape: every constituent pair keeps its distance.
    for frame in (0, -1):
        x = a.positions[frame].reshape(12, 3, 3)
        d = np.linalg.norm(x[:, [0, 0, 1]] - x[:, [1, 2, 2]], axis=-1)
        x0 = a.positions[0].reshape(12, 3, 3)
        assert np.allclose(d, np.linalg.norm(x0[:, [0, 0, 1]] - x0[:, [1, 2, 2]], axis=-1))


BATHS = {
    "rigid_langevin": 'type = "langevin"\ntemperature = 1.0\nfriction = 1.0',
    "rigid_bussi": 'type = "bussi"\ntemperature = 1.0\ntau = 0.2',
    "rigid_nose_hoover_chain": 'type = "nose_hoover_chain"\ntemperature = 1.0\ntau = 0.2',
}


@pytest.mark.parametrize("kind", sorted(BATHS))
def test_thermostat_configs_run_bodies_and_resume(tmp_path, kind):
    text = CONFIG.replace("ROTATION", "no_squish")
    text = text.replace('type = "velocity_verlet"', BATHS[kind])
    config = tmp_path / "run.toml"
    config.write_text(text)
    assert run(config, "-o", "full.h5") == 0
    assert run(config, "-o", "cut.h5", "--steps", "20") == 0
    assert run(config, "-o", "cut.h5", "--resume") == 0
    a, b = read_trajectory("full.h5"), read_trajectory("cut.h5")
    assert np.array_equal(a.positions, b.positions)
    assert np.array_equal(a.velocities, b.velocities)
    assert read_checkpoint(checkpoint_path("full.h5")).integrator["type"] == kind
    if kind == "rigid_nose_hoover_chain":  # the chain's energy in the conserved one
        assert np.all(np.isfinite(a.observables["conserved_energy"]))


def test_thermo_has_both_temperatures(tmp_path, capsys):
    config = tmp_path / "run.toml"
    config.write_text(CONFIG.replace("ROTATION", "dlm").replace("steps = 60", "steps = 10"))
    assert main(["run", str(config), "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "TempTrans" in out and "TempRot" in out


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (
            (
                'type = "velocity_verlet"',
                'type = "berendsen"\ntemperature = 1.0\ntau = 1.0',
            ),
            "velocity Verlet, Langevin, Bussi or Nose-Hoover chains",
        ),
        (('rotation = "ROTATION"', 'rotation = "euler"'), "rotation"),
        (("chains = 12", "chains = 12\nmass = 0.0"), "mass"),
    ],
)
def test_bad_rigid_input_exits_2_and_writes_nothing(tmp_path, capsys, change, message):
    config = tmp_path / "bad.toml"
    config.write_text(CONFIG.replace(*change).replace("ROTATION", "no_squish"))
    assert run(config) == 2
    err = capsys.readouterr().err
    assert "md: error:" in err and message in err and "bad.toml" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.toml"]


def _data_file(path, molecules, positions):
    """A LAMMPS data file (atom_style full) of unit-mass atoms with these molecule ids."""
    lines = ["LAMMPS data file", "", f"{len(molecules)} atoms", "1 atom types", ""]
    lines += ["0 10 xlo xhi", "0 10 ylo yhi", "0 10 zlo zhi", "", "Masses", "", "1 1.0", ""]
    lines += ["Atoms # full", ""]
    # written in reverse id order: the ids, not the lines, give the atoms' order
    for i in reversed(range(len(molecules))):
        x, y, z = positions[i]
        lines.append(f"{i + 1} {molecules[i]} 1 0.0 {x} {y} {z}")
    path.write_text("\n".join(lines) + "\n")


DATA_CONFIG = """units = "lj"
[system]
structure = "bodies.data"
[[potentials]]
type = "lj"
cutoff = 2.5
[integrator]
type = "velocity_verlet"
dt = 0.002
[rigid]
bodies = "molecules"
[run]
steps = 10
[output]
path = "out.h5"
"""
BODY_POSITIONS = [[1, 1, 1], [2, 1, 1], [1, 2, 1], [5, 5, 5], [6, 5, 5], [5.5, 6, 5], [8, 8, 8]]


def test_bodies_from_a_data_files_molecule_column(tmp_path):
    _data_file(tmp_path / "bodies.data", [1, 1, 1, 2, 2, 2, 0], BODY_POSITIONS)
    (tmp_path / "run.toml").write_text(DATA_CONFIG)
    sim = build_simulation(load_config(tmp_path / "run.toml"), None, tmp_path / "x", None)
    bodies = sim.integrator.bodies
    assert bodies.n_bodies == 2 and bodies.free.tolist() == [6]
    assert bodies.members.tolist() == [0, 1, 2, 3, 4, 5]
    assert bodies.n_dof() == 6 + 6 + 3 - 3
    assert sim.integrator.describe()["rotation"] == "no_squish"


@pytest.mark.parametrize(
    ("molecules", "message"),
    [([1, 1, 1, 2, 2, 2, 3], "single atom"), ([1, 1, 1, 1, 1, 1, 0], "half the box")],
)
def test_bad_bodies_in_a_data_file_exit_2(tmp_path, capsys, molecules, message):
    _data_file(tmp_path / "bodies.data", molecules, BODY_POSITIONS)
    (tmp_path / "run.toml").write_text(DATA_CONFIG)
    assert run(tmp_path / "run.toml") == 2
    err = capsys.readouterr().err
    assert "md: error:" in err and "[rigid] bodies" in err and message in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bodies.data", "run.toml"]


def test_refused_under_mpi(tmp_path):
    config = tmp_path / "run.toml"
    config.write_text(CONFIG.replace("ROTATION", "no_squish"))
    with pytest.raises(ConfigError, match="MPI"):
        build_simulation(load_config(config), None, tmp_path / "x", None, ranks=object())


def test_pressure_is_the_rigid_body_virial(rng):
    """At rest, 3 P V = -dU/d(ln lambda) with the centres (and box) scaled by lambda and
    the bodies kept rigid, by central differences; the atomic virial alone fails it."""
    from test_rigid import _trimer_gas

    from integrators.rigid import RigidNVE
    from md.simulation import Simulation

    state, ids = _trimer_gas(rng)
    state.velocities[:] = 0.0
    bodies = RigidBodies.from_molecules(state, ids)
    bodies.place(state)
    sim = Simulation(state, [LennardJones(cutoff=2.0)], RigidNVE(0.001, bodies))
    row = sim.thermo()

    def energy(scale):
        scaled = state.copy()
        scaled.box = state.box * scale
        shift = (scale - 1.0) * bodies.centres
        scaled.positions[bodies.members] += shift[bodies.owner]
        return ForceField([LennardJones(cutoff=2.0)]).compute(scaled).energy

    h = 1e-6
    derivative = (energy(1 + h) - energy(1 - h)) / (2 * h)
    assert 3 * row["pressure"] * row["volume"] == pytest.approx(-derivative, rel=1e-6)
    atomic = np.trace(ForceField([LennardJones(cutoff=2.0)]).compute(state).virial)
    assert atomic != pytest.approx(-derivative, rel=1e-3)


@pytest.mark.parametrize(
    "command", [["minimize"], ["integrators", "--integrators", "no_squish,verlet"]]
)
def test_other_commands_refuse_rigid_bodies(tmp_path, capsys, command):
    config = tmp_path / "run.toml"
    config.write_text(CONFIG.replace("ROTATION", "no_squish"))
    assert main([command[0], str(config), *command[1:]]) == 2
    err = capsys.readouterr().err
    assert "[rigid]" in err and "md: error:" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.toml"]


def test_md_integrators_measures_the_rotational_family(tmp_path, capsys):
    """On a [rigid] config md integrators compares the four rotational methods: in a force
    field each is second order (the kicks around the rotation are)."""
    import csv

    config = tmp_path / "run.toml"
    config.write_text(CONFIG.replace("ROTATION", "no_squish"))
    argv = ["integrators", str(config), "--dt-range", "0.001,0.002,0.004", "--time", "0.04"]
    assert main([*argv, "--equilibrate", "10", "--out", str(tmp_path / "study")]) == 0
    out = capsys.readouterr().out
    for name in ("no_squish", "dlm", "richardson", "rk4"):
        assert name in out
    with open(tmp_path / "study" / "integrators.csv") as handle:
        rows = list(csv.DictReader(handle))
    orders = {row["integrator"]: float(row["order"]) for row in rows}
    assert set(orders) == {"no_squish", "dlm", "richardson", "rk4"}
    for name, order in orders.items():
        assert order == pytest.approx(2.0, abs=0.25), (name, order)


TEMPLATE_CONFIG = """units = "lj"
seed = 4
[system]
lattice = "sc"
cells = 3
lattice_constant = 2.5
temperature = 1.0
[[potentials]]
type = "lj"
cutoff = 2.5
[integrator]
type = "velocity_verlet"
dt = 0.002
[rigid]
bodies = "template"
template = [[0, 0, 0], [1, 0, 0], [0.3, 0.8, 0]]
template_masses = [1, 2, 3]
[run]
steps = 20
[output]
path = "out.h5"
"""


def test_a_template_on_every_lattice_site(tmp_path):
    """27 trimers, one per simple-cubic site, each its centre on the site, turned at
    random, the template's shape kept; velocities canonical for the bodies."""
    (tmp_path / "run.toml").write_text(TEMPLATE_CONFIG)
    sim = build_simulation(load_config(tmp_path / "run.toml"), None, tmp_path / "x", None)
    bodies = sim.integrator.bodies
    assert bodies.n_bodies == 27 and len(bodies.free) == 0
    sites = np.indices((3, 3, 3)).reshape(3, -1).T * 2.5  # the sc builder's sites
    gaps = bodies.centres[:, None, :] - sites[None, :, :]
    gaps -= 7.5 * np.rint(gaps / 7.5)  # minimum image in the 7.5 box
    nearest = np.linalg.norm(gaps, axis=-1).min(axis=1)
    assert np.all(nearest < 1e-12)
    assert len({int(i) for i in np.linalg.norm(gaps, axis=-1).argmin(axis=1)}) == 27
    x = sim.state.positions.reshape(27, 3, 3)
    d = np.linalg.norm(x[:, [0, 0, 1]] - x[:, [1, 2, 2]], axis=-1)
    assert np.allclose(d, np.linalg.norm(TRIMER[[0, 0, 1]] - TRIMER[[1, 2, 2]], axis=-1))
    assert np.allclose(sim.state.masses, np.tile(TRIMER_MASSES, 27))
    assert np.std(bodies.quaternions[:, 0]) > 0.1  # turned, not aligned
    row = sim.thermo()
    assert 0.6 < row["translational_temperature"] < 1.4
    assert 0.6 < row["rotational_temperature"] < 1.4


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (
            ("template = [[0, 0, 0], [1, 0, 0], [0.3, 0.8, 0]]", "template = [[0, 0, 0]]"),
            "two or more",
        ),
        (('bodies = "template"', 'bodies = "molecules"'), "exactly when"),
        (("template_masses = [1, 2, 3]", "template_masses = [1, 2]"), "2 masses for 3"),
        (("template_masses = [1, 2, 3]", "template_masses = [1, 0, 3]"), "positive"),
    ],
)
def test_bad_templates_exit_2(tmp_path, capsys, change, message):
    (tmp_path / "run.toml").write_text(TEMPLATE_CONFIG.replace(*change))
    assert run(tmp_path / "run.toml") == 2
    err = capsys.readouterr().err
    assert "md: error:" in err and "[rigid]" in err and message in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.toml"]


def test_a_template_run_resumes_bitwise(tmp_path):
    text = TEMPLATE_CONFIG.replace(
        'path = "out.h5"', 'path = "out.h5"\nevery = 5\nvelocities = true'
    )
    (tmp_path / "run.toml").write_text(text)
    assert run(tmp_path / "run.toml", "-o", "full.h5") == 0
    assert run(tmp_path / "run.toml", "-o", "cut.h5", "--steps", "10") == 0
    assert run(tmp_path / "run.toml", "-o", "cut.h5", "--resume") == 0
    a, b = read_trajectory("full.h5"), read_trajectory("cut.h5")
    assert list(b.steps) == [0, 5, 10, 15, 20]
    assert np.array_equal(a.positions, b.positions)
    assert np.array_equal(a.velocities, b.velocities)


def test_convert_writes_the_bodies_as_molecules(tmp_path):
    """md convert of a template run (no bonds) to LAMMPS data: the molecule column holds
    the bodies, as fix rigid ... molecule needs, and our reader takes them back."""
    (tmp_path / "run.toml").write_text(TEMPLATE_CONFIG)
    assert run(tmp_path / "run.toml") == 0
    assert main(["convert", "out.h5", "out.data", "--no-progress"]) == 0
    found = lammps_molecule_ids(tmp_path / "out.data")
    assert found.tolist() == np.repeat(np.arange(1, 28), 3).tolist()


def test_resume_after_sigkill_is_bitwise_identical(tmp_path):
    """md run in a child process killed with SIGKILL after some checkpoints; the resumed
    run ends where an uninterrupted one does, frames and bodies bit for bit."""
    import signal
    import subprocess
    import sys
    import time

    text = CONFIG.replace("ROTATION", "no_squish").replace("steps = 60", "steps = 1000000")
    text = text.replace("checkpoint_every = 20", "checkpoint_every = 40")
    config = tmp_path / "run.toml"
    config.write_text(text)
    command = [sys.executable, "-m", "md.cli", "run", str(config), "--no-progress", "-q"]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    ckpt = checkpoint_path(tmp_path / "out.h5")
    while time.monotonic() < deadline:
        assert process.poll() is None, process.communicate()
        try:
            if read_checkpoint(ckpt).state.step >= 80:
                break
        except (OSError, ValueError):
            pass
        time.sleep(0.05)
    process.send_signal(signal.SIGKILL)
    process.communicate(timeout=60)
    assert process.returncode == -signal.SIGKILL
    stop = read_checkpoint(ckpt).state.step + 30
    assert run(config, "--resume", "--steps", stop) == 0
    assert run(config, "-o", "full.h5", "--steps", stop) == 0
    a, b = read_trajectory("full.h5"), read_trajectory("out.h5")
    assert list(a.steps) == list(b.steps)
    assert np.array_equal(a.positions, b.positions)
    assert np.array_equal(a.velocities, b.velocities)
    with h5py.File("full.h5", "r") as full_file, h5py.File("out.h5", "r") as cut_file:
        for name in ("centre", "orientation"):
            assert np.array_equal(
                full_file[f"rigid/{name}/value"][()], cut_file[f"rigid/{name}/value"][()]
            )


NPT_CONFIG = (
    TEMPLATE_CONFIG.replace("cells = 3", "cells = 4")
    .replace("lattice_constant = 2.5", "lattice_constant = 2.2")
    .replace("temperature = 1.0", "temperature = 1.5")
    .replace(
        'type = "velocity_verlet"\ndt = 0.002',
        'type = "langevin"\ndt = 0.004\ntemperature = 1.5\nfriction = 2.0\n'
        '[barostat]\ntype = "c_rescale"\npressure = 0.5\ntau = 0.5\ncompressibility = 1.0\n'
        "every = 1",
    )
)


def test_c_rescale_barostat_scales_the_bodies_centres(tmp_path):
    """64 trimers at T = 1.5 and P = 0.5 under Langevin and stochastic cell rescaling: the
    gas contracts to a liquid, the bodies keep their shapes, the mean pressure of the
    second half is the target within 4 standard errors (block means), and the conserved
    energy (with both reservoirs) stays within 1e-3 of the energy that flowed."""
    (tmp_path / "run.toml").write_text(NPT_CONFIG)
    sim = build_simulation(load_config(tmp_path / "run.toml"), None, tmp_path / "x", None)
    first = sim.thermo()
    rows = []
    for _ in range(120):
        sim.run(10)
        rows.append(sim.thermo())
    assert rows[-1]["volume"] < 0.6 * first["volume"]
    x = sim.state.positions.reshape(64, 3, 3)
    d = np.linalg.norm(x[:, [0, 0, 1]] - x[:, [1, 2, 2]], axis=-1)
    assert np.allclose(d, np.linalg.norm(TRIMER[[0, 0, 1]] - TRIMER[[1, 2, 2]], axis=-1))
    pressures = np.array([r["pressure"] for r in rows[40:]]).reshape(8, -1).mean(axis=1)
    error = pressures.std(ddof=1) / np.sqrt(len(pressures))
    assert abs(pressures.mean() - 0.5) < 4 * error + 0.02, (pressures.mean(), error)
    flowed = abs(rows[-1]["total_energy"] - first["total_energy"])
    drift = abs(rows[-1]["conserved_energy"] - first["conserved_energy"])
    assert flowed > 100.0 and drift < 1e-3 * flowed, (drift, flowed)


@pytest.mark.parametrize("couple", ["anisotropic", "triclinic"])
def test_anisotropic_barostats_move_the_centres(tmp_path, couple):
    """Anisotropic and triclinic c_rescale on bodies: the cell changes shape, the bodies
    keep theirs, and the conserved energy stays within 1e-3 of the energy that flowed."""
    text = NPT_CONFIG.replace("every = 1", f'every = 1\ncouple = "{couple}"')
    (tmp_path / "run.toml").write_text(text)
    sim = build_simulation(load_config(tmp_path / "run.toml"), None, tmp_path / "x", None)
    first = sim.thermo()
    box = sim.state.box.copy()
    sim.run(600)
    last = sim.thermo()
    assert not np.allclose(sim.state.box / sim.state.box[0], box / box[0], rtol=1e-3)
    x = sim.state.positions.reshape(64, 3, 3)
    d = np.linalg.norm(x[:, [0, 0, 1]] - x[:, [1, 2, 2]], axis=-1)
    assert np.allclose(d, np.linalg.norm(TRIMER[[0, 0, 1]] - TRIMER[[1, 2, 2]], axis=-1))
    flowed = abs(last["total_energy"] - first["total_energy"])
    drift = abs(last["conserved_energy"] - first["conserved_energy"])
    assert flowed > 100.0 and drift < 1e-3 * flowed, (drift, flowed)


def test_other_barostats_are_refused_with_bodies(tmp_path, capsys):
    text = (
        NPT_CONFIG.replace('type = "c_rescale"', 'type = "mtk"')
        .replace(
            'type = "langevin"\ndt = 0.004\ntemperature = 1.5\nfriction = 2.0',
            'type = "nose_hoover_chain"\ndt = 0.004\ntemperature = 1.5\ntau = 0.4',
        )
        .replace("compressibility = 1.0\nevery = 1\n", "")
    )
    (tmp_path / "run.toml").write_text(text)
    assert run(tmp_path / "run.toml") == 2
    err = capsys.readouterr().err
    assert "[rigid]" in err and "c_rescale or berendsen" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.toml"]


def test_refused_on_another_device(tmp_path):
    """A [run] device other than the CPU (the GPU path's key, where it exists) is refused."""
    import dataclasses

    config = tmp_path / "run.toml"
    config.write_text(CONFIG.replace("ROTATION", "no_squish"))
    loaded = load_config(config)

    @dataclasses.dataclass(frozen=True)
    class RunWithDevice:
        device: str = "cuda"

        def __getattr__(self, name):  # the rest of [run] as loaded
            return getattr(loaded.run, name)

    on_gpu = dataclasses.replace(loaded, run=RunWithDevice())
    with pytest.raises(ConfigError, match="CPU only"):
        build_simulation(on_gpu, None, tmp_path / "x", None)


def test_an_npt_run_keeps_the_bodies_in_its_trajectory(tmp_path):
    """Under a barostat (the integrator wrapped) the H5MD file still gets the bodies."""
    text = NPT_CONFIG.replace("steps = 20", "steps = 20\n").replace(
        'path = "out.h5"', 'path = "out.h5"\nevery = 10'
    )
    (tmp_path / "run.toml").write_text(text)
    assert run(tmp_path / "run.toml") == 0
    with h5py.File("out.h5", "r") as f:
        assert f["rigid/centre/value"].shape == (3, 64, 3)
        assert f["rigid/molecule"][()].max() == 64
