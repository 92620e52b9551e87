"""State validation, copies, ASE round trips, lattice builders and thermal velocities."""

import ase
import ase.units
import numpy as np
import pytest

import md
from md.thermo import temperature

TWO_ATOMS = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])


def _state(**overrides):
    kwargs = {"positions": TWO_ATOMS, "box": [5.0, 5.0, 5.0]}
    kwargs.update(overrides)
    return md.State(**kwargs)


# ----------------------------------------------------------------- validation


@pytest.mark.parametrize(
    ("overrides", "named"),
    [
        ({"positions": np.zeros((2, 2))}, "positions"),
        ({"positions": np.zeros(3)}, "positions"),
        ({"positions": np.zeros((2, 3, 1))}, "positions"),
        ({"velocities": np.zeros((3, 3))}, "velocities"),
        ({"velocities": np.zeros((2, 2))}, "velocities"),
        ({"types": [0, 0, 0]}, "types"),
    ],
    ids=["positions-2d", "positions-1d", "positions-3d", "velocities-n", "velocities-2", "types"],
)
def test_wrong_shapes_raise_naming_the_field(overrides, named):
    with pytest.raises(ValueError, match=named):
        _state(**overrides)


@pytest.mark.parametrize(
    ("overrides", "named"),
    [
        ({"masses": [1.0, 2.0, 3.0]}, "masses"),
        ({"box": [5.0, 5.0]}, "box"),
        ({"pbc": [True, False]}, "pbc"),
    ],
    ids=["masses", "box", "pbc"],
)
def test_wrong_shapes_of_broadcast_fields_raise_naming_the_field(overrides, named):
    with pytest.raises(ValueError, match=named):
        _state(**overrides)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("field", ["positions", "velocities"])
def test_non_finite_positions_and_velocities_raise(field, bad):
    values = np.zeros((2, 3)) if field == "velocities" else TWO_ATOMS.copy()
    values[1, 2] = bad
    with pytest.raises(ValueError, match=f"{field} of atom 1"):
        _state(**{field: values})


@pytest.mark.parametrize("mass", [0.0, -1.0, np.nan])
def test_non_positive_masses_raise(mass):
    with pytest.raises(ValueError, match="mass"):
        _state(masses=[1.0, mass])


@pytest.mark.parametrize(
    ("box", "pbc"),
    [
        ([0.0, 5.0, 5.0], True),
        ([5.0, 5.0, 0.0], [False, False, True]),
        ([5.0, -1.0, 5.0], True),
        ([5.0, -1.0, 5.0], False),
        ([5.0, np.nan, 5.0], True),
        ([5.0, np.inf, 5.0], True),
    ],
)
def test_invalid_box_raises(box, pbc):
    with pytest.raises(ValueError, match="box"):
        _state(box=box, pbc=pbc)


def test_zero_box_edge_is_allowed_along_an_open_axis():
    state = _state(box=[5.0, 0.0, 5.0], pbc=[True, False, True])
    assert state.box.tolist() == [5.0, 0.0, 5.0]


@pytest.mark.parametrize(
    "overrides",
    [{"types": [0, -1]}, {"types": [0, 2], "type_names": ("A", "B")}],
    ids=["negative", "beyond-names"],
)
def test_invalid_types_raise(overrides):
    with pytest.raises(ValueError, match="type"):
        _state(**overrides)


def test_fields_are_coerced_to_contiguous_float64():
    state = _state(positions=[[0, 0, 0], [1, 2, 3]], masses=2, box=4, pbc=[1, 0, 1], types=[0, 1])
    assert state.positions.dtype == np.float64 and state.positions.flags.c_contiguous
    assert state.velocities.shape == (2, 3) and not state.velocities.any()
    assert state.masses.tolist() == [2.0, 2.0]
    assert state.box.tolist() == [4.0, 4.0, 4.0]
    assert state.pbc.dtype == bool and state.pbc.tolist() == [True, False, True]
    assert state.types.dtype == np.int32
    assert state.n_types == 2 and state.volume == 64.0


# ----------------------------------------------------------------------- copy


def test_copy_is_independent(fcc_lattice):
    original = fcc_lattice(cells=2, perturbation=0.05, temperature=1.0, n_types=2)
    original.step, original.time = 7, 0.035
    snapshot = {k: np.copy(getattr(original, k)) for k in ("positions", "velocities", "masses")}
    snapshot.update(box=original.box.copy(), pbc=original.pbc.copy(), types=original.types.copy())

    clone = original.copy()
    for name, value in snapshot.items():
        np.testing.assert_array_equal(getattr(clone, name), value)
    assert (clone.step, clone.time, clone.type_names) == (7, 0.035, original.type_names)

    clone.positions += 1.0
    clone.velocities *= -1.0
    clone.box[0] = 99.0
    clone.pbc[1] = False
    clone.types[0] = 1 - clone.types[0]
    clone.step += 1
    for name, value in snapshot.items():
        np.testing.assert_array_equal(getattr(original, name), value)
    assert original.step == 7
    assert not np.shares_memory(clone.masses, original.masses)


def test_masses_are_owned_and_writable():
    masses = np.array([1.0, 2.0])
    state = _state(masses=masses)
    masses[0] = -3.0  # must not reach the state, which validated positive masses
    assert state.masses[0] == 1.0
    state.masses[1] = 4.0  # e.g. reassigning the mass of one species
    assert state.masses.tolist() == [1.0, 4.0]


# ------------------------------------------------------------------------ ASE


def _ase_atoms(rng):
    symbols = ["Cu", "Ar", "Cu", "H", "Ar"]
    atoms = ase.Atoms(
        symbols=symbols,
        positions=rng.uniform(-2.0, 9.0, size=(5, 3)),
        cell=np.diag([7.0, 8.0, 9.0]),
        pbc=[True, False, True],
    )
    atoms.set_masses([63.5, 40.0, 60.0, 1.008, 39.0])
    atoms.set_velocities(rng.normal(size=(5, 3)))
    return atoms


def test_from_ase_copies_everything(rng):
    atoms = _ase_atoms(rng)
    state = md.State.from_ase(atoms)
    np.testing.assert_array_equal(state.positions, atoms.positions)
    np.testing.assert_allclose(state.velocities, atoms.get_velocities(), rtol=1e-14)
    np.testing.assert_array_equal(state.masses, atoms.get_masses())
    np.testing.assert_array_equal(state.box, [7.0, 8.0, 9.0])
    np.testing.assert_array_equal(state.pbc, [True, False, True])
    # Types numbered by increasing atomic number: H < Ar < Cu.
    assert state.type_names == ("H", "Ar", "Cu")
    np.testing.assert_array_equal(state.types, [2, 1, 2, 0, 1])


def test_ase_round_trip(rng):
    atoms = _ase_atoms(rng)
    back = md.State.from_ase(atoms).to_ase()
    np.testing.assert_array_equal(back.numbers, atoms.numbers)
    np.testing.assert_array_equal(back.positions, atoms.positions)
    np.testing.assert_allclose(back.get_velocities(), atoms.get_velocities(), rtol=1e-14)
    np.testing.assert_array_equal(back.get_masses(), atoms.get_masses())
    np.testing.assert_array_equal(back.cell[:], atoms.cell[:])
    np.testing.assert_array_equal(back.pbc, atoms.pbc)


def test_state_round_trip_through_ase(fcc_lattice):
    state = fcc_lattice(cells=2, perturbation=0.1, temperature=2.0)
    back = md.State.from_ase(state.to_ase())
    np.testing.assert_array_equal(back.positions, state.positions)
    np.testing.assert_allclose(back.velocities, state.velocities, rtol=1e-14, atol=1e-15)
    np.testing.assert_array_equal(back.masses, state.masses)
    np.testing.assert_array_equal(back.box, state.box)
    np.testing.assert_array_equal(back.pbc, state.pbc)


def test_non_chemical_type_names_become_dummies_with_tags():
    state = _state(types=[1, 0], type_names=("LJ1", "LJ2"))
    atoms = state.to_ase()
    assert atoms.get_chemical_symbols() == ["X", "X"]
    np.testing.assert_array_equal(atoms.get_tags(), [1, 0])


def test_from_ase_takes_a_lower_triangular_cell_as_it_is():
    atoms = ase.Atoms("Ar2", positions=TWO_ATOMS, cell=[[5, 0, 0], [1, 5, 0], [0, 0, 5]], pbc=True)
    state = md.State.from_ase(atoms)
    np.testing.assert_array_equal(state.positions, atoms.positions)
    np.testing.assert_array_equal(state.tilt, [1.0, 0.0, 0.0])


def test_from_ase_refuses_a_tilt_along_an_open_axis():
    cell = [[5, 0, 0], [1, 5, 0], [0, 0, 5]]
    atoms = ase.Atoms("Ar2", positions=TWO_ATOMS, cell=cell, pbc=[True, False, True])
    with pytest.raises(ValueError, match="xy"):
        md.State.from_ase(atoms)


# ------------------------------------------------------------------- lattices


def _min_image_distances(state):
    d = state.positions[:, None, :] - state.positions[None, :, :]
    d -= state.box * np.round(d / state.box)
    r = np.sqrt(np.einsum("ijk,ijk->ij", d, d))
    return r[~np.eye(state.n_atoms, dtype=bool)].reshape(state.n_atoms, -1)


@pytest.mark.parametrize(
    ("kind", "per_cell", "nn_over_a", "coordination"),
    [("sc", 1, 1.0, 6), ("bcc", 2, np.sqrt(3.0) / 2.0, 8), ("fcc", 4, np.sqrt(0.5), 12)],
)
def test_lattice_counts_density_and_neighbours(kind, per_cell, nn_over_a, coordination):
    cells = (3, 4, 5)
    density = 0.7
    state = md.lattice(kind, cells, density=density)
    assert state.n_atoms == per_cell * 60
    assert state.n_atoms / state.volume == pytest.approx(density, rel=1e-12)
    a = state.box / cells
    np.testing.assert_allclose(a, a[0], rtol=1e-12)  # cubic cells
    distances = _min_image_distances(state)
    nearest = distances.min(axis=1)
    np.testing.assert_allclose(nearest, nn_over_a * a[0], rtol=1e-12)
    # Every atom has the full shell of the ideal lattice.
    counts = (distances < nearest[:, None] * (1 + 1e-9)).sum(axis=1)
    assert np.all(counts == coordination)
    assert not state.velocities.any()
    assert np.all(state.pbc)


def test_lattice_constant_sets_the_box():
    state = md.lattice("bcc", 2, lattice_constant=3.3, mass=39.9, pbc=False)
    np.testing.assert_allclose(state.box, 6.6)
    assert state.n_atoms == 16
    assert np.all(state.masses == 39.9)
    assert not state.pbc.any()


@pytest.mark.parametrize(
    ("args", "kwargs", "named"),
    [
        (("hcp", 2), {"density": 1.0}, "hcp"),
        (("fcc", 2), {}, "exactly one"),
        (("fcc", 2), {"density": 1.0, "lattice_constant": 1.0}, "exactly one"),
        (("fcc", 2.5), {"density": 1.0}, "cells"),
        (("fcc", 0), {"density": 1.0}, "cells"),
        (("fcc", 2), {"density": -1.0}, "density"),
        (("fcc", 2), {"lattice_constant": 0.0}, "lattice_constant"),
    ],
)
def test_lattice_rejects_bad_arguments(args, kwargs, named):
    with pytest.raises(ValueError, match=named):
        md.lattice(*args, **kwargs)


# ---------------------------------------------------------- Maxwell-Boltzmann


def _mixed_mass_state(n=400):
    masses = np.where(np.arange(n) % 2 == 0, 1.0, 4.0)
    positions = np.arange(3 * n, dtype=float).reshape(n, 3)
    return md.State(positions=positions, masses=masses, box=1.0, pbc=False)


def test_maxwell_boltzmann_zero_momentum_and_exact_temperature():
    state = md.maxwell_boltzmann(_mixed_mass_state(), 1.7, seed=3)
    momentum = (state.masses[:, None] * state.velocities).sum(axis=0)
    scale = np.abs(state.masses[:, None] * state.velocities).sum()
    np.testing.assert_allclose(momentum, 0.0, atol=1e-14 * scale)
    kinetic = 0.5 * np.sum(state.masses[:, None] * state.velocities**2)
    assert 2.0 * kinetic / (3 * state.n_atoms - 3) == pytest.approx(1.7, rel=1e-12)
    assert temperature(state.velocities, state.masses) == pytest.approx(1.7, rel=1e-12)


def test_maxwell_boltzmann_in_metal_units():
    state = md.lattice("fcc", 3, lattice_constant=5.26, mass=39.948)
    md.maxwell_boltzmann(state, 300.0, seed=5, kB=ase.units.kB)
    atoms = state.to_ase()
    # ASE counts 3N degrees of freedom; ours are 3N - 3.
    n = state.n_atoms
    ase_temperature = atoms.get_temperature()
    assert ase_temperature * 3 * n / (3 * n - 3) == pytest.approx(300.0, rel=1e-10)


def test_maxwell_boltzmann_variance_scales_with_inverse_mass():
    state = md.maxwell_boltzmann(_mixed_mass_state(4000), 2.0, seed=11, exact=False)
    light = state.velocities[state.masses == 1.0]
    heavy = state.velocities[state.masses == 4.0]
    # <v_a^2> = kT / m per component; 6000 samples each give ~2 % scatter.
    assert np.mean(light**2) == pytest.approx(2.0, rel=0.08)
    assert np.mean(heavy**2) == pytest.approx(0.5, rel=0.08)


def test_maxwell_boltzmann_is_reproducible_with_a_seed():
    first = md.maxwell_boltzmann(_mixed_mass_state(), 1.0, seed=42).velocities
    again = md.maxwell_boltzmann(_mixed_mass_state(), 1.0, seed=42).velocities
    other = md.maxwell_boltzmann(_mixed_mass_state(), 1.0, seed=43).velocities
    np.testing.assert_array_equal(first, again)
    assert not np.allclose(first, other)
    # A Generator is accepted as the seed and advanced.
    generator = np.random.default_rng(42)
    from_generator = md.maxwell_boltzmann(_mixed_mass_state(), 1.0, seed=generator).velocities
    np.testing.assert_array_equal(from_generator, first)
    second = md.maxwell_boltzmann(_mixed_mass_state(), 1.0, seed=generator).velocities
    assert not np.allclose(second, first)


def test_maxwell_boltzmann_zero_temperature_is_at_rest_and_negative_raises():
    state = md.maxwell_boltzmann(_mixed_mass_state(10), 0.0, seed=1)
    assert not state.velocities.any()
    with pytest.raises(ValueError, match="temperature"):
        md.maxwell_boltzmann(state, -1.0, seed=1)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_one_atom_starts_at_the_temperature_asked_for(tmp_path, capsys, seed):
    """Was the raw draw (T = 0.82 for T = 1): a single atom keeps its momentum and its
    three degrees of freedom, and is scaled to the temperature like any system."""
    from md.cli import main

    state = md.State(positions=np.zeros((1, 3)), box=10.0, pbc=False)
    md.maxwell_boltzmann(state, 1.0, seed=seed)
    assert md.thermo.temperature(state.velocities, state.masses) == pytest.approx(1.0, rel=1e-12)
    (tmp_path / "one.toml").write_text(
        f'units = "lj"\nseed = {seed}\n[system]\nlattice = "sc"\ncells = 1\ndensity = 0.01\n'
        'temperature = 1.0\npbc = false\n[[potentials]]\ntype = "lj"\ncutoff = 2.5\n'
        '[integrator]\ntype = "verlet"\ndt = 0.005\n[run]\nsteps = 2\nthermo_every = 1\n'
        f'[output]\npath = "{tmp_path / "one.h5"}"\n'
    )
    assert main(["run", str(tmp_path / "one.toml"), "--no-progress"]) == 0
    first = capsys.readouterr().out.splitlines()[2].split()  # the step-0 row
    assert first[0] == "0" and float(first[2]) == pytest.approx(1.0, rel=1e-5)


def test_positions_and_velocities_are_owned():
    positions = np.zeros((2, 3))
    positions[1, 0] = 1.5
    velocities = np.ones((2, 3))
    state = md.State(positions=positions, velocities=velocities, box=5.0)
    state.positions += 1.0
    state.velocities *= 2.0
    assert positions[0, 0] == 0.0 and velocities[0, 0] == 1.0
    assert not np.shares_memory(state.positions, positions)
    assert not np.shares_memory(state.velocities, velocities)
