"""Messages that said the wrong thing (issue 33 item 17): each names the real problem, the
file and the key, and md run exits 2 before writing anything."""

from __future__ import annotations

import ase
import ase.io
import numpy as np
import pytest

import md
from md.cli import main
from md.structure import read_structure
from md.trajectory import read_trajectory

QUIET = ("--no-progress", "-q")

RUN = """
units = "{units}"
[system]
{system}
[[potentials]]
type = "lj"
cutoff = 2.5
[integrator]
{integrator}
[run]
steps = 10
[output]
path = "out.h5"
"""
VERLET = 'type = "verlet"\ndt = 0.005'

DATA = """LAMMPS data file

2 atoms
1 bonds
1 atom types
1 bond types

0 10 xlo xhi
0 10 ylo yhi
0 10 zlo zhi
{masses}
Atoms # full

1 1 1 0 1 1 1
2 1 1 0 2.2 1 1

Bonds

1 1 1 {partner}
"""


@pytest.fixture(autouse=True)
def in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)


def _run(capsys, system, integrator=VERLET, units="lj"):
    with open("run.toml", "w") as handle:
        handle.write(RUN.format(units=units, system=system, integrator=integrator))
    code = main(["run", "run.toml", *QUIET])
    return code, capsys.readouterr().err


# ---------------------------------------------------------------------- mass 0
def test_a_zero_mass_in_a_structure_file_is_named_as_such(tmp_path, capsys):
    """Was "velocities of atom 0 are not finite: [nan nan nan]" (momenta / 0)."""
    atoms = ase.Atoms("Ar2", positions=[[0, 0, 0], [3.8, 0, 0]], cell=[20, 20, 20], pbc=True)
    atoms.set_masses([0.0, 39.95])
    ase.io.write("zero.extxyz", atoms)
    code, err = _run(capsys, 'structure = "zero.extxyz"', units="metal")
    assert code == 2
    assert "zero.extxyz: masses must be positive; atom 0 has mass 0.0" in err
    assert "not finite" not in err
    (tmp_path / "zero.data").write_text(DATA.format(masses="\nMasses\n\n1 0.0\n", partner=2))
    code, err = _run(capsys, 'structure = "zero.data"')
    assert code == 2 and "zero.data: masses must be positive; atom 0 has mass 0.0" in err
    with pytest.raises(ValueError, match="masses must be positive; atom 0 has mass 0.0"):
        md.State.from_ase(atoms)
    assert not (tmp_path / "out.h5").exists()


# ------------------------------------------------------------ ASE reader errors
def test_a_bare_ase_reader_error_is_named_with_the_file_and_what_failed(tmp_path):
    """Was "cannot read b.data as a LAMMPS data file with atom_style full (64)"."""
    (tmp_path / "b.data").write_text(DATA.format(masses="\nMasses\n\n1 1.0\n", partner=64))
    with pytest.raises(ValueError) as raised:
        read_structure("b.data", units="lj")
    message = str(raised.value)
    assert message.startswith(
        "cannot read b.data as a LAMMPS data file with atom_style full: "
        "ASE's reader failed (KeyError 64)"
    )
    assert "an atom id in Bonds, Angles or Velocities missing from Atoms" in message


# ------------------------------------------------------------ data without Masses
@pytest.mark.parametrize(("mass", "expected"), [("2.0", [2.0, 2.0]), ('{"1" = 3.0}', [3.0, 3.0])])
def test_a_data_file_without_masses_takes_the_configs_mass(tmp_path, capsys, mass, expected):
    """Was refused ("no Masses section") although [system] mass gives them."""
    (tmp_path / "plain.data").write_text(DATA.format(masses="", partner=2))
    code, err = _run(capsys, f'structure = "plain.data"\nmass = {mass}')
    assert code == 0, err
    np.testing.assert_array_equal(read_trajectory("out.h5").masses, expected)


@pytest.mark.parametrize(
    ("mass", "message"),
    [
        (
            None,
            "plain.data: no Masses section; add one (masses per atom type) or give the masses "
            "([system] mass)",
        ),
        (
            '{"Ar" = 3.0}',
            "plain.data: no Masses section, and the masses given name no mass for "
            "type(s) 1 (the file's types: 1)",
        ),
    ],
)
def test_a_data_file_without_masses_and_no_mass_for_a_type_is_refused(
    tmp_path, capsys, mass, message
):
    (tmp_path / "plain.data").write_text(DATA.format(masses="", partner=2))
    system = 'structure = "plain.data"' + (f"\nmass = {mass}" if mass else "")
    code, err = _run(capsys, system)
    assert code == 2 and message in err
    assert not (tmp_path / "out.h5").exists()


# ------------------------------------------------------------ thermostat keys
@pytest.mark.parametrize(
    ("integrator", "message"),
    [
        (
            'type = "langevin"\ndt = 0.005\ntemperature = 1.0',
            "missing required key [integrator] friction (type = 'langevin' needs it)",
        ),
        (
            'type = "bussi"\ndt = 0.005\ntemperature = 1.0',
            "missing required key [integrator] tau (type = 'bussi' needs it)",
        ),
        (
            'type = "nose_hoover_chain"\ndt = 0.005\ntemperature = 1.0',
            "missing required key [integrator] tau (type = 'nose_hoover_chain' needs it)",
        ),
        (
            'type = "berendsen"\ndt = 0.005\ntemperature = 1.0',
            "missing required key [integrator] tau (type = 'berendsen' needs it)",
        ),
        (
            'type = "bussi"\ndt = 0.005\ntemperature = 1.0\ntau = 0.5\nfriction = 1.0',
            "[integrator] friction: does not apply to type = 'bussi', which takes dt, "
            "temperature, tau",
        ),
    ],
)
def test_a_missing_or_foreign_thermostat_key_is_named(tmp_path, capsys, integrator, message):
    """Was Python's "Langevin.__init__() missing 1 required positional argument: 'friction'"."""
    system = 'lattice = "fcc"\ncells = 3\ndensity = 0.8442\ntemperature = 1.0'
    code, err = _run(capsys, system, integrator)
    assert code == 2 and f"run.toml: {message}" in err
    assert "__init__" not in err and "positional argument" not in err
    assert not (tmp_path / "out.h5").exists()
