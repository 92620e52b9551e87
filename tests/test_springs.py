"""Bonded potentials (harmonic springs, FENE) and the bead-spring polymer builders."""

from __future__ import annotations

import json

import numpy as np
import pytest
import scipy.sparse

import md
from integrators import VelocityVerlet
from md.box import minimum_image
from md.polymers import polymer_melt, single_chain
from md.thermo import pressure
from potentials import POTENTIALS, FENEBonds, HarmonicBonds, LennardJones, SupportsHessian
from potentials.springs import BondStretchError

FD_STEP = 1e-6  # central-difference step [length]
WCA_CUTOFF = 2.0 ** (1.0 / 6.0)


def _harmonic_formula(r, k, r0):
    return 0.5 * k * (r - r0) ** 2


def _fene_formula(r, k, r_max):
    return -0.5 * k * r_max**2 * np.log(1.0 - (r / r_max) ** 2)


def _bond_vectors(state, bonds):
    d = state.positions[bonds[:, 0]] - state.positions[bonds[:, 1]]
    return minimum_image(d, state.box, state.pbc)


def _bond_lengths(state, bonds):
    return np.linalg.norm(_bond_vectors(state, bonds), axis=1)


def _energy(potential, state):
    return potential.energy_forces(state, None).energy


def _numeric_forces(potential, state):
    forces = np.zeros_like(state.positions)
    for i in range(state.n_atoms):
        for axis in range(3):
            moved = state.copy()
            moved.positions[i, axis] += FD_STEP
            up = _energy(potential, moved)
            moved.positions[i, axis] -= 2 * FD_STEP
            down = _energy(potential, moved)
            forces[i, axis] = -(up - down) / (2 * FD_STEP)
    return forces


def _numeric_hessian(potential, state):
    n = state.n_atoms
    hessian = np.zeros((3 * n, 3 * n))
    for i in range(n):
        for axis in range(3):
            moved = state.copy()
            moved.positions[i, axis] += FD_STEP
            up = potential.energy_forces(moved, None).forces
            moved.positions[i, axis] -= 2 * FD_STEP
            down = potential.energy_forces(moved, None).forces
            hessian[:, 3 * i + axis] = -(up - down).ravel() / (2 * FD_STEP)
    return hessian


@pytest.fixture
def wiggly_chain(rng):
    """Factory: a random-walk chain of ``n`` beads with bond lengths in [0.8, 1.2].

    In a periodic box of edge 5 by default; positions are moved by random
    box images, so bonds cross the boundary and rely on the minimum image.
    """

    def make(n=8, box=5.0, pbc=True):
        steps = rng.normal(size=(n - 1, 3))
        steps *= rng.uniform(0.8, 1.2, size=(n - 1, 1)) / np.linalg.norm(steps, axis=1)[:, None]
        positions = np.vstack([np.zeros(3), np.cumsum(steps, axis=0)]) + rng.uniform(0, box, 3)
        if np.all(pbc):
            positions += rng.integers(-2, 3, size=positions.shape) * box
        state = md.State(positions=positions, box=box, pbc=pbc)
        bonds = np.stack([np.arange(n - 1), np.arange(1, n)], axis=1)
        return state, bonds

    return make


def _potentials(bonds):
    """Every bond potential form, including per-type parameters."""
    types = np.arange(len(bonds)) % 2
    return {
        "harmonic": HarmonicBonds(bonds, k=3.0, r0=0.9),
        "harmonic-r0-zero": HarmonicBonds(bonds, k=1.5, r0=0.0),
        "harmonic-typed": HarmonicBonds(bonds, k=[2.0, 5.0], r0=[1.2, 0.7], bond_types=types),
        "fene": FENEBonds(bonds),
        "fene-typed": FENEBonds(bonds, k=[30.0, 10.0], r_max=[1.5, 2.0], bond_types=types),
    }


FORMS = list(_potentials(np.array([[0, 1]])))


# ------------------------------------------------------------- analytic values


@pytest.mark.parametrize("r", [0.3, 0.97, 1.0, 1.4])
def test_dimer_energy_and_force_follow_the_formulas(dimer, r):
    state = dimer(r=r)
    bonds = [[0, 1]]
    harmonic = HarmonicBonds(bonds, k=4.0, r0=1.1).energy_forces(state, None)
    assert harmonic.energy == pytest.approx(_harmonic_formula(r, 4.0, 1.1), rel=1e-14, abs=1e-15)
    # Force on atom 1 (at larger x) along +x is -dU/dr.
    assert harmonic.forces[1, 0] == pytest.approx(-4.0 * (r - 1.1), rel=1e-13)
    fene = FENEBonds(bonds, k=30.0, r_max=1.5).energy_forces(state, None)
    assert fene.energy == pytest.approx(_fene_formula(r, 30.0, 1.5), rel=1e-13)
    assert fene.forces[1, 0] == pytest.approx(-30.0 * r / (1 - (r / 1.5) ** 2), rel=1e-13)
    for result in (harmonic, fene):
        np.testing.assert_allclose(result.forces[0], -result.forces[1], rtol=0, atol=0)
        np.testing.assert_array_equal(result.forces[:, 1:], 0.0)


def test_chain_energy_is_the_sum_over_bonds(wiggly_chain):
    state, bonds = wiggly_chain(n=12)
    r = _bond_lengths(state, bonds)
    types = np.arange(len(bonds)) % 2
    cases = [
        (HarmonicBonds(bonds, k=3.0, r0=0.9), _harmonic_formula(r, 3.0, 0.9)),
        (
            HarmonicBonds(bonds, k=[2.0, 5.0], r0=[1.2, 0.7], bond_types=types),
            _harmonic_formula(r, np.array([2.0, 5.0])[types], np.array([1.2, 0.7])[types]),
        ),
        (FENEBonds(bonds), _fene_formula(r, 30.0, 1.5)),
        (
            FENEBonds(bonds, k=[30.0, 10.0], r_max=[1.5, 2.0], bond_types=types),
            _fene_formula(r, np.array([30.0, 10.0])[types], np.array([1.5, 2.0])[types]),
        ),
    ]
    for potential, per_bond in cases:
        assert potential.energy_forces(state, None).energy == pytest.approx(
            per_bond.sum(), rel=1e-13
        )
        np.testing.assert_allclose(potential.bond_lengths(state), r, rtol=1e-14)


def test_kremer_grest_bond_minimum():
    """FENE(k=30, r_max=1.5) + WCA has its minimum at r = 0.961 sigma."""
    fene = FENEBonds([[0, 1]])
    wca = LennardJones(epsilon=1.0, sigma=1.0, cutoff=WCA_CUTOFF, cutoff_mode="shift")
    r = np.linspace(0.9, 1.05, 1501)
    total = [
        _energy(fene, s) + _energy(wca, s)
        for s in (md.State(positions=[[0, 0, 0], [x, 0, 0]], box=10.0, pbc=False) for x in r)
    ]
    assert r[int(np.argmin(total))] == pytest.approx(0.961, abs=0.001)


# ------------------------------------------------------------ forces, virial


@pytest.mark.parametrize("form", FORMS)
@pytest.mark.parametrize("pbc", [True, False], ids=["periodic", "open"])
def test_forces_match_central_differences(form, pbc, wiggly_chain):
    state, bonds = wiggly_chain(n=8, pbc=pbc)
    potential = _potentials(bonds)[form]
    result = potential.energy_forces(state, None)
    numeric = _numeric_forces(potential, state)
    scale = max(1.0, np.abs(result.forces).max())
    np.testing.assert_allclose(result.forces, numeric, rtol=1e-6, atol=1e-7 * scale)
    np.testing.assert_allclose(result.forces.sum(axis=0), 0.0, atol=1e-12 * scale)


@pytest.mark.parametrize("form", FORMS)
def test_virial_pressure_is_minus_dE_dV(form):
    state, bonds = polymer_melt(4, 8, seed=5)
    # Move the beads off the fixed bond length so every form has stretched bonds.
    state.positions += np.random.default_rng(5).normal(scale=0.05, size=state.positions.shape)
    potential = _potentials(bonds)[form]
    result = potential.energy_forces(state, None)
    relative = 1e-6
    volume = state.volume
    energies = []
    for factor in (1 + relative, 1 - relative):
        scaled = state.copy()
        scaled.positions *= factor ** (1 / 3)
        scaled.box *= factor ** (1 / 3)
        energies.append(_energy(potential, scaled))
    numeric = -(energies[0] - energies[1]) / (2 * relative * volume)
    assert pressure(0.0, result.virial, volume) == pytest.approx(
        numeric, rel=1e-6, abs=1e-8 * np.abs(result.virial).max() / volume
    )
    np.testing.assert_array_equal(result.virial, result.virial.T)
    # sum over bonds of r_ij (x) F_ij
    d = _bond_vectors(state, bonds)
    np.testing.assert_allclose(
        result.virial,
        np.einsum("ba,bc->ac", d, _pair_forces(potential, d)),
        rtol=1e-12,
        atol=1e-12 * np.abs(result.virial).max(),
    )


def _pair_forces(potential, d):
    """(B, 3) force on the first atom of each bond, from the formulas."""
    r = np.linalg.norm(d, axis=1)
    t = potential.bond_types
    if isinstance(potential, HarmonicBonds):
        du = potential.k[t] * (r - potential.r0[t])
    else:
        du = potential.k[t] * r / (1 - (r / potential.r_max[t]) ** 2)
    return -(du / r)[:, None] * d


@pytest.mark.parametrize("form", FORMS)
def test_per_atom_energies_sum_to_the_energy(form, wiggly_chain):
    state, bonds = wiggly_chain(n=10)
    potential = _potentials(bonds)[form]
    result = potential.energy_forces(state, None, per_atom=True)
    assert result.energies.sum() == pytest.approx(result.energy, rel=1e-13)
    # End beads carry half of one bond, inner beads half of two.
    per_bond = _per_bond_energies(potential, state, bonds)
    assert result.energies[0] == pytest.approx(0.5 * per_bond[0], rel=1e-13)
    assert result.energies[4] == pytest.approx(0.5 * (per_bond[3] + per_bond[4]), rel=1e-13)


def _per_bond_energies(potential, state, bonds):
    r = _bond_lengths(state, bonds)
    t = potential.bond_types
    if isinstance(potential, HarmonicBonds):
        return _harmonic_formula(r, potential.k[t], potential.r0[t])
    return _fene_formula(r, potential.k[t], potential.r_max[t])


@pytest.mark.parametrize("potential_class", [HarmonicBonds, FENEBonds])
def test_bonds_across_the_boundary_use_the_minimum_image(potential_class):
    box = 6.0
    # 0.5 apart through the x = 0 face; plain difference 5.5.
    state = md.State(positions=[[0.2, 1.0, 1.0], [5.7, 1.0, 1.0]], box=box)
    params = {"k": 2.0, "r0": 1.0} if potential_class is HarmonicBonds else {}
    potential = potential_class([[0, 1]], **params)
    result = potential.energy_forces(state, None)
    near = md.State(positions=[[0.2, 1.0, 1.0], [-0.3, 1.0, 1.0]], box=box)
    expected = potential.energy_forces(near, None)
    assert result.energy == pytest.approx(expected.energy, rel=1e-13)
    np.testing.assert_allclose(result.forces, expected.forces, rtol=1e-12)
    np.testing.assert_allclose(result.virial, expected.virial, rtol=1e-12)
    # Unwrapped positions several images away give the same result.
    far = state.copy()
    far.positions[1] += [-3 * box, 2 * box, box]
    again = potential.energy_forces(far, None)
    assert again.energy == pytest.approx(expected.energy, rel=1e-12)
    np.testing.assert_allclose(again.forces, expected.forces, rtol=1e-10)
    # Along an open axis there is no image: the bond is 5.5 long.
    open_x = md.State(positions=state.positions, box=box, pbc=[False, True, True])
    if potential_class is HarmonicBonds:
        assert _energy(potential, open_x) == pytest.approx(_harmonic_formula(5.5, 2.0, 1.0))
    else:
        with pytest.raises(BondStretchError):
            potential.energy_forces(open_x, None)


def test_no_bonds_gives_zero(dimer):
    for potential in (HarmonicBonds(np.zeros((0, 2), int), k=1.0, r0=1.0), FENEBonds([])):
        result = potential.energy_forces(dimer(), None, per_atom=True)
        assert result.energy == 0.0
        np.testing.assert_array_equal(result.forces, 0.0)
        np.testing.assert_array_equal(result.energies, 0.0)
        assert potential.hessian(dimer(), None).count_nonzero() == 0


# -------------------------------------------------------------------- Hessian


@pytest.mark.parametrize("form", FORMS)
@pytest.mark.parametrize("pbc", [True, False], ids=["periodic", "open"])
def test_hessian_matches_central_differences_of_the_forces(form, pbc, rng):
    # A chain of bonds 0.9 to 1.0 long, a cross-link (0, 2) 1.2 long and a
    # repeated bond: blocks of several bonds must add up.
    positions = [
        [0.0, 0.0, 0.0],
        [0.9, 0.2, 0.0],
        [0.6, 1.0, 0.3],
        [1.5, 1.3, 0.1],
        [1.8, 2.1, -0.4],
        [2.6, 2.5, -0.1],
    ] + rng.normal(scale=0.03, size=(6, 3))
    box = 5.0
    if pbc:  # near the faces, in random images
        positions += [4.0, 3.5, 0.3] + rng.integers(-2, 3, size=(6, 3)) * box
    state = md.State(positions=positions, box=box, pbc=pbc)
    bonds = np.array([[0, 1], [1, 2], [2, 3], [3, 4], [4, 5], [0, 2], [4, 5]])
    potential = _potentials(bonds)[form]
    assert isinstance(potential, SupportsHessian)
    hessian = potential.hessian(state, None)
    assert scipy.sparse.issparse(hessian) and hessian.format == "csr"
    assert hessian.shape == (3 * state.n_atoms, 3 * state.n_atoms)
    dense = hessian.toarray()
    numeric = _numeric_hessian(potential, state)
    scale = max(1.0, np.abs(dense).max())
    np.testing.assert_allclose(dense, numeric, rtol=1e-6, atol=1e-6 * scale)
    np.testing.assert_allclose(dense, dense.T, rtol=0, atol=1e-14 * scale)
    # Translations are zero modes: every row sums to zero per axis.
    np.testing.assert_allclose(
        dense.reshape(-1, state.n_atoms, 3).sum(axis=1), 0, atol=1e-12 * scale
    )


def test_hessian_is_sparse(wiggly_chain):
    state, bonds = wiggly_chain(n=40)
    hessian = HarmonicBonds(bonds, k=1.0, r0=1.0).hessian(state, None)
    # Diagonal blocks for 40 atoms and two off-diagonal blocks per bond.
    assert hessian.nnz == 9 * (40 + 2 * 39)


def test_hessian_of_a_relaxed_spring_is_rank_one(dimer):
    """At r = r0 only the bond direction is stiff: K = k rhat rhat^T."""
    hessian = HarmonicBonds([[0, 1]], k=4.0, r0=1.3).hessian(dimer(r=1.3), None).toarray()
    expected_block = np.zeros((3, 3))
    expected_block[0, 0] = 4.0
    np.testing.assert_allclose(hessian[:3, :3], expected_block, atol=1e-14)
    np.testing.assert_allclose(hessian[:3, 3:], -expected_block, atol=1e-14)


# ---------------------------------------------------------------- FENE range


def test_overstretched_fene_bond_raises_naming_the_bond(wiggly_chain):
    state, bonds = wiggly_chain(n=6, pbc=False)
    fene = FENEBonds(bonds, r_max=1.5)
    fene.energy_forces(state, None)
    state.positions[4:] += [0.0, 0.0, 1.2]  # bond 3 = (3, 4) now longer than 1.5
    length = float(_bond_lengths(state, bonds)[3])
    assert length >= 1.5
    with pytest.raises(BondStretchError, match=r"bond 3 between atoms 3 and 4") as info:
        fene.energy_forces(state, None)
    error = info.value
    assert (error.bond, error.i, error.j, error.r_max) == (3, 3, 4, 1.5)
    assert error.length == pytest.approx(length, rel=1e-12)
    assert f"{length:.6g}" in str(error) and "r_max = 1.5" in str(error)
    assert isinstance(error, md.NonFiniteError)
    with pytest.raises(BondStretchError, match="bond 3"):
        fene.hessian(state, None)


def test_fene_bond_at_exactly_r_max_raises(dimer):
    with pytest.raises(BondStretchError, match="bond 0 between atoms 0 and 1"):
        FENEBonds([[0, 1]], r_max=1.5).energy_forces(dimer(r=1.5), None)


def test_overstretched_bond_during_a_run_is_a_simulation_error():
    state = md.State(
        positions=[[0, 0, 0], [1.4, 0, 0]], velocities=[[-5, 0, 0], [5, 0, 0]], box=10.0
    )
    sim = md.Simulation(state, [FENEBonds([[0, 1]], k=1.0)], VelocityVerlet(dt=0.01))
    with pytest.raises(md.SimulationError, match="FENE bond 0") as info:
        sim.run(100)
    assert isinstance(info.value.__cause__, BondStretchError)
    assert info.value.step >= 1


# ------------------------------------------------------------------ validation


def test_check_refuses_out_of_range_indices(dimer):
    state = dimer()
    for potential in (HarmonicBonds([[0, 1], [1, 2]], k=1.0, r0=1.0), FENEBonds([[0, 1], [2, 1]])):
        with pytest.raises(ValueError, match=r"bond 1 .* atom 2, but the system has 2 atoms"):
            potential.check(state)
        with pytest.raises(ValueError, match="bond 1"):
            potential.energy_forces(state, None)
        with pytest.raises(ValueError, match="bond 1"):
            potential.hessian(state, None)
    HarmonicBonds([[0, 1]], k=1.0, r0=1.0).check(state)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"bonds": [[0, 0]]}, "itself"),
        ({"bonds": [[0, -1]]}, "negative"),
        ({"bonds": [[0, 1, 2]]}, "shape"),
        ({"bonds": [[0.5, 1]]}, "integer"),
        ({"k": -1.0}, "k"),
        ({"k": np.nan}, "k"),
        ({"r0": -0.5}, "r0"),
        ({"r0": np.inf}, "r0"),
        ({"k": [1.0, 2.0]}, "bond_types"),
        ({"k": [1.0, 2.0], "bond_types": [0, 2]}, "bond_types go up to 2"),
        ({"k": [1.0, 2.0], "r0": [1.0, 1.0, 1.0], "bond_types": [0, 1]}, "one value per"),
        ({"bond_types": [0]}, "shape"),
        ({"bond_types": [0, -1]}, "non-negative"),
    ],
)
def test_harmonic_rejects_invalid_parameters(kwargs, match):
    params = {"bonds": [[0, 1], [1, 2]], "k": 1.0, "r0": 1.0, **kwargs}
    with pytest.raises(ValueError, match=match):
        HarmonicBonds(**params)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [({"r_max": 0.0}, "r_max"), ({"r_max": -1.0}, "r_max"), ({"k": -30.0}, "k")],
)
def test_fene_rejects_invalid_parameters(kwargs, match):
    with pytest.raises(ValueError, match=match):
        FENEBonds([[0, 1]], **kwargs)


def test_bond_list_is_owned_and_read_only():
    bonds = np.array([[0, 1], [1, 2]])
    springs = HarmonicBonds(bonds, k=1.0, r0=1.0)
    bonds[0, 1] = 0  # the caller's array, not the potential's
    assert springs.bonds[0, 1] == 1
    with pytest.raises(ValueError):
        springs.bonds[0, 0] = 5


def test_scalar_parameters_broadcast_over_bond_types():
    springs = HarmonicBonds([[0, 1], [1, 2]], k=[1.0, 2.0], r0=0.5, bond_types=[1, 0])
    np.testing.assert_array_equal(springs.r0, [0.5, 0.5])


# ---------------------------------------------------------------------- config


def test_registry_entries():
    assert POTENTIALS["spring"] is HarmonicBonds
    assert POTENTIALS["fene"] is FENEBonds
    for cls in (HarmonicBonds, FENEBonds):
        assert cls([[0, 1]], k=1.0, **({"r0": 1.0} if cls is HarmonicBonds else {})).cutoff is None


def test_from_config_with_inline_bonds(dimer):
    springs = HarmonicBonds.from_config({"bonds": [[0, 1]], "k": 3.0, "r0": 0.5}, ("A",))
    assert springs.energy_forces(dimer(r=1.0), None).energy == pytest.approx(0.375)
    fene = POTENTIALS["fene"].from_config({"bonds": [[0, 1]]}, ("A",))
    assert (float(fene.k[0]), float(fene.r_max[0])) == (30.0, 1.5)
    typed = FENEBonds.from_config(
        {"bonds": [[0, 1], [1, 2]], "k": [30.0, 20.0], "r_max": 2.0, "bond_types": [1, 0]},
        ("A",),
    )
    np.testing.assert_array_equal(typed.k[typed.bond_types], [20.0, 30.0])


def test_from_config_reads_a_bonds_file(tmp_path):
    path = tmp_path / "bonds.txt"
    path.write_text("# i j\n0 1\n1 2\n\n2 3\n")
    springs = HarmonicBonds.from_config({"bonds_file": str(path), "k": 1.0, "r0": 1.0}, ("M",))
    np.testing.assert_array_equal(springs.bonds, [[0, 1], [1, 2], [2, 3]])
    single = tmp_path / "one.txt"
    single.write_text("4 7\n")
    np.testing.assert_array_equal(FENEBonds.from_config({"bonds_file": single}, ()).bonds, [[4, 7]])


@pytest.mark.parametrize(
    ("params", "match"),
    [
        ({"bonds": [[0, 1]], "k": 1.0, "r0": 1.0, "stiffness": 2.0}, "unknown key.*stiffness"),
        ({"k": 1.0, "r0": 1.0}, "exactly one of 'bonds'"),
        ({"bonds": [[0, 1]], "bonds_file": "b.txt", "k": 1.0, "r0": 1.0}, "exactly one"),
        ({"bonds_file": "/nonexistent/bonds.txt", "k": 1.0, "r0": 1.0}, "not found"),
        ({"bonds": [[0, 1]], "k": "stiff", "r0": 1.0}, "k: expected a number"),
        ({"bonds": [[0, 1]], "k": True, "r0": 1.0}, "k: expected a number"),
        ({"bonds": [[0, 1.5]], "k": 1.0, "r0": 1.0}, "bonds: expected integers"),
        ({"bonds": [[0, 1]], "k": 1.0}, "missing key.*r0"),
    ],
)
def test_from_config_rejects_bad_tables(params, match):
    with pytest.raises(ValueError, match=match):
        HarmonicBonds.from_config(params, ("A",))


def test_from_config_rejects_a_bad_bonds_file(tmp_path):
    path = tmp_path / "bonds.txt"
    path.write_text("0 1 2\n")
    with pytest.raises(ValueError, match="two columns"):
        FENEBonds.from_config({"bonds_file": str(path)}, ())
    path.write_text("0 x\n")
    with pytest.raises(ValueError, match="integers"):
        FENEBonds.from_config({"bonds_file": str(path)}, ())
    with pytest.raises(ValueError, match="unknown key.*r0"):
        FENEBonds.from_config({"bonds": [[0, 1]], "r0": 1.0}, ())


def test_describe_is_plain_json():
    bonds = [[0, 1], [1, 2]]
    described = [
        HarmonicBonds(bonds, k=1.0, r0=0.5).describe(),
        FENEBonds(bonds, k=[30.0, 20.0], r_max=1.5, bond_types=[0, 1]).describe(),
    ]
    assert json.loads(json.dumps(described)) == described
    assert described[0]["type"] == "spring" and described[0]["n_bonds"] == 2
    assert described[1]["type"] == "fene" and described[1]["k"] == [30.0, 20.0]
    assert HarmonicBonds(bonds[::-1], k=1.0, r0=0.5).describe() != described[0]


# -------------------------------------------------------------------- builders


def _closest_pair(state):
    d = minimum_image(
        state.positions[:, None, :] - state.positions[None, :, :], state.box, state.pbc
    )
    r = np.linalg.norm(d, axis=2)
    np.fill_diagonal(r, np.inf)
    return r


@pytest.mark.parametrize(("n_chains", "chain_length", "density"), [(10, 20, 0.85), (3, 7, 0.5)])
def test_polymer_melt(n_chains, chain_length, density):
    state, bonds = polymer_melt(n_chains, chain_length, density=density, seed=7)
    n = n_chains * chain_length
    assert state.n_atoms == n
    assert state.pbc.all() and np.all(state.box == state.box[0])
    assert n / state.volume == pytest.approx(density, rel=1e-12)
    np.testing.assert_array_equal(state.masses, 1.0)
    assert state.type_names == ("M",) and np.all(state.types == 0)
    np.testing.assert_array_equal(state.velocities, 0.0)
    assert bonds.shape == (n_chains * (chain_length - 1), 2) and bonds.dtype == np.int64
    np.testing.assert_array_equal(bonds[:, 1] - bonds[:, 0], 1)
    assert np.all(bonds[:, 1] % chain_length != 0)  # no bond joins two chains
    np.testing.assert_allclose(_bond_lengths(state, bonds), 0.97, rtol=1e-12)
    # Unwrapped: bonded beads are 0.97 apart in plain coordinates too.
    plain = np.linalg.norm(state.positions[bonds[:, 0]] - state.positions[bonds[:, 1]], axis=1)
    np.testing.assert_allclose(plain, 0.97, rtol=1e-12)
    r = _closest_pair(state)
    r[bonds[:, 0], bonds[:, 1]] = np.inf
    r[bonds[:, 1], bonds[:, 0]] = np.inf
    assert r.min() >= 0.8
    FENEBonds(bonds).check(state)


def test_polymer_melt_is_reproducible_with_a_seed():
    a, bonds_a = polymer_melt(3, 10, seed=11)
    b, bonds_b = polymer_melt(3, 10, seed=11)
    c, _ = polymer_melt(3, 10, seed=12)
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(bonds_a, bonds_b)
    assert not np.array_equal(a.positions, c.positions)


def test_polymer_melt_bond_length_and_threshold():
    state, bonds = polymer_melt(5, 10, density=0.6, bond_length=1.1, min_distance=0.9, seed=2)
    np.testing.assert_allclose(_bond_lengths(state, bonds), 1.1, rtol=1e-12)
    r = _closest_pair(state)
    r[bonds[:, 0], bonds[:, 1]] = r[bonds[:, 1], bonds[:, 0]] = np.inf
    assert r.min() >= 0.9


@pytest.mark.parametrize(
    ("args", "kwargs", "match"),
    [
        ((0, 10), {}, "n_chains"),
        ((5, 1), {}, "chain_length"),
        ((5, 2.5), {}, "chain_length"),
        ((5, 10), {"density": 2.0}, "density 2 is too high"),
        ((5, 10), {"density": -1.0}, "density"),
        ((5, 10), {"bond_length": 0.0}, "bond_length"),
        ((1, 2), {}, "twice the bond length"),
        ((5, 10), {"box_shape": "slab"}, "box_shape"),
    ],
)
def test_polymer_melt_rejects_impossible_inputs(args, kwargs, match):
    with pytest.raises(ValueError, match=match):
        polymer_melt(*args, **kwargs)


@pytest.mark.parametrize("straight", [True, False])
def test_single_chain(straight):
    state, bonds = single_chain(30, bond_length=0.9, straight=straight, seed=3)
    assert state.n_atoms == 30 and not state.pbc.any()
    np.testing.assert_array_equal(bonds, np.stack([np.arange(29), np.arange(1, 30)], axis=1))
    np.testing.assert_allclose(_bond_lengths(state, bonds), 0.9, rtol=1e-12)
    r = _closest_pair(state)
    r[bonds[:, 0], bonds[:, 1]] = r[bonds[:, 1], bonds[:, 0]] = np.inf
    assert r.min() >= 0.8
    # Inside its box, with room to spare.
    assert np.all(state.positions > 0) and np.all(state.positions < state.box)
    if straight:
        np.testing.assert_array_equal(state.positions[:, 1:], state.positions[:1, 1:].repeat(30, 0))


def test_single_chain_in_a_periodic_box():
    state, bonds = single_chain(50, seed=4, box=6.0, pbc=True)
    assert state.pbc.all() and np.all(state.box == 6.0)
    np.testing.assert_allclose(_bond_lengths(state, bonds), 0.97, rtol=1e-12)
    r = _closest_pair(state)
    r[bonds[:, 0], bonds[:, 1]] = r[bonds[:, 1], bonds[:, 0]] = np.inf
    assert r.min() >= 0.8


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"n_beads": 1}, "n_beads"),
        ({"n_beads": 5, "bond_length": -1.0}, "bond_length"),
        ({"n_beads": 5, "box": 1.5, "pbc": True}, "twice the bond length"),
        ({"n_beads": 12, "straight": True, "box": 10.0, "pbc": True}, "periodic image"),
        ({"n_beads": 5, "straight": True, "bond_length": 0.3}, "min_distance"),
    ],
)
def test_single_chain_rejects_impossible_inputs(kwargs, match):
    with pytest.raises(ValueError, match=match):
        single_chain(**kwargs)


# ----------------------------------------------------------------- dynamics


def _nve_total_energies(state, potentials, dt, n_steps):
    sim = md.Simulation(state, potentials, VelocityVerlet(dt=dt))
    totals = [sim.thermo()["total_energy"]]
    kinetic = []

    def record(sim):
        thermo = sim.thermo()
        totals.append(thermo["total_energy"])
        kinetic.append(thermo["kinetic_energy"])

    sim.attach(record, interval=10)
    sim.run(n_steps)
    assert len(totals) == n_steps // 10 + 1
    return np.array(totals), float(np.mean(kinetic))


def test_kremer_grest_melt_conserves_energy_in_nve():
    state, bonds = polymer_melt(8, 10, seed=1)
    md.maxwell_boltzmann(state, 1.0, seed=2)
    potentials = [
        FENEBonds(bonds, k=30.0, r_max=1.5),
        LennardJones(epsilon=1.0, sigma=1.0, cutoff=WCA_CUTOFF, cutoff_mode="shift"),
    ]
    # Soft start: the grown melt has beads 0.8 apart (WCA energy ~44 each).
    # Let them separate with a small step, rescaling to T = 1 now and then.
    warmup = md.Simulation(state, potentials, VelocityVerlet(dt=0.002))
    for _ in range(5):
        warmup.run(200)
        state.velocities *= np.sqrt(1.0 / warmup.thermo()["temperature"])
    start = state.copy()
    totals, kinetic = _nve_total_energies(state, potentials, dt=0.005, n_steps=1000)
    assert kinetic > 0.5 * state.n_atoms  # T stays of order 1: it really moved
    assert np.std(totals) / abs(np.mean(totals)) < 1e-3
    # The FENE energy (~18 per bond) dominates the total: also compare with K.
    assert np.std(totals) / kinetic < 2e-3
    assert abs(totals[-1] - totals[0]) / kinetic < 5e-3
    np.testing.assert_array_less(potentials[0].bond_lengths(state), 1.5)
    # Verlet's energy fluctuation scales as dt^2.
    finer, _ = _nve_total_energies(start, potentials, dt=0.0025, n_steps=2000)
    assert np.std(totals) / np.std(finer) > 2.5
