"""Structures from any file ASE reads, and exact State <-> ase.Atoms round trips."""

from __future__ import annotations

import ase
import ase.io
import ase.units
import numpy as np
import pytest
from _configs import argon_structure_run
from ase.build import bulk

import md
from md.cli import main
from md.trajectory import read_trajectory


# ------------------------------------------------------------ exact round trips
def _atoms(rng) -> ase.Atoms:
    atoms = ase.Atoms(
        symbols=["Cu", "Ar", "Cu", "H", "Ar", "Kr"],
        positions=rng.uniform(-3.0, 12.0, size=(6, 3)),
        cell=np.diag([7.0, 8.0, 0.0]),
        pbc=[True, True, False],
    )
    atoms.set_momenta(rng.normal(size=(6, 3)) * 3.0)
    return atoms


def test_atoms_to_state_to_atoms_is_exact(rng):
    atoms = _atoms(rng)
    back = md.State.from_ase(atoms).to_ase()
    np.testing.assert_array_equal(back.get_momenta(), atoms.get_momenta())
    np.testing.assert_array_equal(back.positions, atoms.positions)
    np.testing.assert_array_equal(back.get_masses(), atoms.get_masses())  # ASE's table
    np.testing.assert_array_equal(back.cell[:], atoms.cell[:])
    np.testing.assert_array_equal(back.pbc, atoms.pbc)
    np.testing.assert_array_equal(back.numbers, atoms.numbers)


def test_state_to_atoms_to_state_is_exact(rng):
    masses = np.array([39.948, 1.008, 83.798, 12.011])  # m v / m != v for many of these
    types = np.arange(400) % 4
    state = md.State(
        positions=rng.uniform(0, 10, size=(400, 3)),
        velocities=rng.normal(size=(400, 3)) * 0.01,
        masses=masses[types],
        box=[10.0, 11.0, 12.0],
        pbc=[True, False, True],
        types=types,
        type_names=("Ar", "H", "Kr", "C"),
    )
    m = state.masses[:, None]
    assert not np.array_equal(m * state.velocities / m, state.velocities)  # rounding bites
    back = md.State.from_ase(state.to_ase(), type_names=state.type_names)
    np.testing.assert_array_equal(back.velocities, state.velocities)
    np.testing.assert_array_equal(back.positions, state.positions)
    np.testing.assert_array_equal(back.masses, state.masses)
    np.testing.assert_array_equal(back.box, state.box)
    np.testing.assert_array_equal(back.pbc, state.pbc)
    np.testing.assert_array_equal(back.types, state.types)
    assert back.type_names == state.type_names


def test_changed_momenta_are_not_overridden(rng):
    """What each side remembers is used only while it still matches."""
    atoms = _atoms(rng)
    state = md.State.from_ase(atoms)
    state.velocities[0, 0] += 1.0
    atoms_back = state.to_ase()
    np.testing.assert_allclose(
        atoms_back.get_velocities(), state.velocities, rtol=1e-15, atol=1e-15
    )
    atoms_back.set_momenta(atoms_back.get_momenta() * 2.0)
    again = md.State.from_ase(atoms_back)
    np.testing.assert_allclose(again.velocities, 2.0 * state.velocities, rtol=1e-14)


def test_reduced_type_names_round_trip_through_tags(fcc_lattice):
    state = md.State(positions=np.eye(3) * 2.0, box=5.0, types=[1, 0, 1], type_names=("LJ1", "LJ2"))
    atoms = state.to_ase()
    assert atoms.get_chemical_symbols() == ["X", "X", "X"]
    back = md.State.from_ase(atoms, types_from="tags")
    np.testing.assert_array_equal(back.types, state.types)
    assert back.type_names == ("LJ1", "LJ2")


def test_types_by_symbol_order_and_errors(rng):
    atoms = _atoms(rng)
    state = md.State.from_ase(atoms, type_names=["Kr", "Ar", "H", "Cu"])
    assert [state.type_names[t] for t in state.types] == atoms.get_chemical_symbols()
    with pytest.raises(ValueError, match="atom 0 is Cu"):
        md.State.from_ase(atoms, type_names=["Ar", "H", "Kr"])
    atoms.cell = [[7, 0, 0], [1, 8, 0], [0, 0, 9]]  # a triclinic cell is taken as it is
    np.testing.assert_array_equal(md.State.from_ase(atoms).tilt, [1, 0, 0])


# -------------------------------------------------------- structure = "file"
def _config(tmp_path, name, system="temperature = 40.0", units=""):
    path = tmp_path / "run.toml"
    top = "\n".join(line for line in ("seed = 4", units) if line)
    path.write_text(
        argon_structure_run(
            name,
            system=system,
            top=top,
            dt=5.0,
            run="steps = 4\nthermo_every = 2",
            output='path = "out.h5"\nevery = 2\nvelocities = true',
        )
    )
    return path


@pytest.fixture(autouse=True)
def in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)


@pytest.mark.parametrize(
    ("name", "write_format", "read_format"),
    [
        ("argon.xyz", "extxyz", None),
        ("argon.cif", "cif", None),
        ("POSCAR", "vasp", None),
        ("argon.data", "lammps-data", "lammps-data"),
    ],
)
def test_any_ase_format_runs_in_metal_units(tmp_path, name, write_format, read_format):
    atoms = bulk("Ar", "fcc", a=5.26, cubic=True).repeat(4)
    atoms.rattle(0.02, seed=1)
    kwargs = {"masses": True, "atom_style": "atomic"} if write_format == "lammps-data" else {}
    ase.io.write(tmp_path / name, atoms, format=write_format, **kwargs)
    system = "temperature = 40.0" + (f'\nformat = "{read_format}"' if read_format else "")
    assert main(["run", str(_config(tmp_path, name, system)), "--no-progress", "-q"]) == 0
    traj = read_trajectory(tmp_path / "out.h5")
    assert traj.units.name == "metal"  # the default for structure files
    assert traj.type_names == ("Ar",)
    np.testing.assert_allclose(traj.masses, 39.948, rtol=1e-6)  # ASE's table (or the file's)
    np.testing.assert_allclose(traj.times[-1], 4 * 5.0 * ase.units.fs, rtol=1e-12)
    np.testing.assert_allclose(traj.boxes[0], 4 * 5.26, rtol=1e-9)
    # The same sites as the file (formats may reorder atoms or wrap them into the cell).
    box = traj.boxes[0]
    d = traj.positions[0][:, None, :] - atoms.positions[None, :, :]
    d -= box * np.round(d / box)
    assert np.sqrt((d * d).sum(axis=2)).min(axis=1).max() < 1e-5
    assert traj.observables["temperature"][0] == pytest.approx(40.0, rel=1e-10)


def test_format_key_reads_a_file_its_name_does_not_describe(tmp_path, capsys):
    atoms = bulk("Ar", "fcc", a=5.26, cubic=True).repeat(4)
    ase.io.write(tmp_path / "argon.structure", atoms, format="extxyz")
    config = _config(tmp_path, "argon.structure")
    assert main(["run", str(config), "--no-progress", "-q"]) == 2
    err = capsys.readouterr().err
    assert "argon.structure" in err and "cannot read" in err
    assert not (tmp_path / "out.h5").exists()
    config = _config(tmp_path, "argon.structure", 'temperature = 40.0\nformat = "extxyz"')
    assert main(["run", str(config), "--no-progress", "-q"]) == 0


def test_masses_per_symbol_and_velocities_from_the_file(tmp_path):
    atoms = bulk("Ar", "fcc", a=5.26, cubic=True).repeat(4)
    atoms.numbers[::4] = 36  # a quarter krypton
    rng = np.random.default_rng(2)
    atoms.set_momenta(rng.normal(size=(len(atoms), 3)) * 0.05)
    ase.io.write(tmp_path / "mix.xyz", atoms, format="extxyz")
    stored = ase.io.read(tmp_path / "mix.xyz")
    config = _config(tmp_path, "mix.xyz", "mass = { Ar = 40.0 }")  # no temperature: keep v
    assert main(["run", str(config), "--no-progress", "-q"]) == 0
    traj = read_trajectory(tmp_path / "out.h5")
    assert traj.type_names == ("Ar", "Kr")
    expected = np.where(atoms.numbers == 36, ase.data.atomic_masses[36], 40.0)
    np.testing.assert_array_equal(traj.masses, expected)
    # The file's velocities are kept (momenta / the file's masses) when masses are overridden.
    np.testing.assert_allclose(traj.velocities[0], stored.get_velocities(), rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize(
    ("system", "message"),
    [
        ("mass = { Xe = 131.0 }", "Xe"),
        ("mass = { Ar = -1.0 }", "positive"),
        ('format = "no-such-format"', "no-such-format"),
    ],
)
def test_bad_structure_options_exit_2(tmp_path, capsys, system, message):
    atoms = bulk("Ar", "fcc", a=5.26, cubic=True).repeat(4)
    ase.io.write(tmp_path / "argon.xyz", atoms)
    assert main(["run", str(_config(tmp_path, "argon.xyz", system)), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.splitlines()) == 1
    assert not (tmp_path / "out.h5").exists()


def test_units_can_still_be_chosen(tmp_path):
    from md.config import load_config

    atoms = bulk("Ar", "fcc", a=5.26, cubic=True).repeat(4)
    ase.io.write(tmp_path / "argon.xyz", atoms)
    default = load_config(_config(tmp_path, "argon.xyz"))
    assert default.units.name == "metal"
    assert default.integrator.dt == 5.0 * ase.units.fs  # dt read in fs
    chosen = load_config(_config(tmp_path, "argon.xyz", units='units = "lj"'))
    assert chosen.units.name == "lj"
    assert chosen.integrator.dt == 5.0  # dt read in tau
