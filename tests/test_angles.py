"""Angle potentials (angle_harmonic, angle_cosine): formulas, derivatives, singular
geometries, the Hessian, topology in files, configs, bad input, and the physics of a
semiflexible chain.

The registry's contract suite (tests/test_potentials.py) already checks both forms
for central-difference forces, zero net force, translation invariance, per-atom sums,
virial against strain derivatives and dtypes; LAMMPS comparisons are in
tests/test_vs_lammps.py. Here: what is particular to angles.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest
import scipy.sparse

import md
from integrators.implicit_euler import ImplicitEuler
from md.analysis import block_average
from md.box import minimum_image
from md.cli import main
from md.config import build_system, load_config
from md.errors import NonFiniteError
from md.polymers import chain_angles, single_chain
from md.structure import read_structure
from md.thermo import kinetic_energy
from md.topology import Topology
from md.trajectory import open_trajectory, read_topology, read_trajectory
from potentials import (
    POTENTIALS,
    AngleCollapseError,
    CosineAngles,
    FENEBonds,
    HarmonicAngles,
    HarmonicBonds,
)
from potentials.angles import SMALL, angle_values
from potentials.base import ForceResult

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "semiflexible_chains.toml"
FD_STEP = 1e-6


def _triple(theta_degrees, arms=(1.0, 1.3), box=20.0, pbc=False):
    """Atoms i, j (the vertex), k with the angle i-j-k = theta, in the xy plane."""
    theta = np.radians(theta_degrees)
    centre = np.full(3, 0.5 * box) if not pbc else np.zeros(3)
    positions = centre + np.array(
        [
            [arms[0], 0.0, 0.0],
            [0.0, 0.0, 0.0],
            [arms[1] * np.cos(theta), arms[1] * np.sin(theta), 0.0],
        ]
    )
    return md.State(positions=positions, box=box, pbc=pbc)


def _numeric_forces(potential, state, h=FD_STEP):
    out = np.zeros_like(state.positions)
    for i in range(state.n_atoms):
        for axis in range(3):
            moved = state.copy()
            moved.positions[i, axis] += h
            up = potential.energy_forces(moved).energy
            moved.positions[i, axis] -= 2 * h
            out[i, axis] = -(up - potential.energy_forces(moved).energy) / (2 * h)
    return out


def _numeric_hessian(potential, state, h=FD_STEP):
    size = 3 * state.n_atoms
    out = np.zeros((size, size))
    for column in range(size):
        moved = state.copy()
        moved.positions.reshape(-1)[column] += h
        up = potential.energy_forces(moved).forces.ravel()
        moved.positions.reshape(-1)[column] -= 2 * h
        out[:, column] = -(up - potential.energy_forces(moved).forces.ravel()) / (2 * h)
    return out


def _tilted_chains(rng):
    """Three chains of six beads as random walks in a tilted periodic cell, unwrapped
    across it by random lattice vectors, with typed angles."""
    state = md.State(
        positions=np.zeros((18, 3)), box=[4.2, 4.6, 4.4], pbc=True, tilt=[1.1, -0.8, 0.9]
    )
    positions = []
    for _ in range(3):
        bead = rng.uniform(0, 4, 3)
        for _ in range(6):
            positions.append(bead.copy())
            step = rng.normal(size=3)
            bead = bead + 0.95 * step / np.linalg.norm(step)
    state.positions[:] = np.array(positions) + rng.integers(-2, 3, (18, 3)) @ state.cell
    angles = chain_angles(3, 6)
    return state, angles, np.arange(len(angles)) % 2


# ------------------------------------------------------------------ formulas


@pytest.mark.parametrize("theta", [30.0, 90.0, 123.4, 170.0])
def test_energies_follow_the_lammps_formulas(theta):
    state = _triple(theta)
    harmonic = HarmonicAngles([[0, 1, 2]], k=2.5, theta0=110.0)
    cosine = CosineAngles([[0, 1, 2]], k=1.5)
    expected = 2.5 * (np.radians(theta) - np.radians(110.0)) ** 2  # no 1/2: LAMMPS's K
    assert harmonic.energy_forces(state).energy == pytest.approx(expected, rel=1e-13)
    assert cosine.energy_forces(state).energy == pytest.approx(
        1.5 * (1 + np.cos(np.radians(theta))), rel=1e-13, abs=1e-15
    )
    np.testing.assert_allclose(harmonic.angle_values(state), [theta], rtol=1e-12)


def test_force_on_an_end_is_the_torque_over_the_arm():
    """|F_i| = |dU/dtheta| / r_i, perpendicular to the arm, turning theta toward theta0."""
    state = _triple(100.0, arms=(1.7, 0.8))
    result = HarmonicAngles([[0, 1, 2]], k=3.0, theta0=120.0).energy_forces(state)
    torque = 2 * 3.0 * np.radians(100.0 - 120.0)
    assert np.linalg.norm(result.forces[0]) == pytest.approx(abs(torque) / 1.7, rel=1e-12)
    assert np.linalg.norm(result.forces[2]) == pytest.approx(abs(torque) / 0.8, rel=1e-12)
    assert result.forces[0] @ [1, 0, 0] == pytest.approx(0.0, abs=1e-14)  # perpendicular
    assert result.forces[0, 1] < 0  # atom 0 moves away from atom 2: theta opens to 120


@pytest.mark.parametrize(
    "potential",
    [
        HarmonicAngles(
            chain_angles(3, 6), k=[2.0, 0.7], theta0=[180.0, 100.0], angle_types=np.arange(12) % 2
        ),
        CosineAngles(chain_angles(3, 6), k=[1.5, 4.0], angle_types=np.arange(12) % 2),
    ],
    ids=["harmonic", "cosine"],
)
def test_forces_and_hessian_match_finite_differences_in_a_tilted_cell(potential, rng):
    state, _, _ = _tilted_chains(rng)
    result = potential.energy_forces(state)
    np.testing.assert_allclose(result.forces, _numeric_forces(potential, state), atol=2e-8)
    np.testing.assert_allclose(result.forces.sum(axis=0), 0.0, atol=1e-13)
    hessian = potential.hessian(state)
    assert scipy.sparse.issparse(hessian) and hessian.shape == (54, 54)
    dense = hessian.toarray()
    np.testing.assert_allclose(dense, dense.T, atol=1e-12)
    np.testing.assert_allclose(dense, _numeric_hessian(potential, state), atol=1e-7)
    # Zero row sums: a rigid translation costs nothing.
    np.testing.assert_allclose(dense.reshape(54, 18, 3).sum(axis=1), 0.0, atol=1e-12)


def test_per_atom_energies_and_virials_are_thirds(rng):
    state, angles, types = _tilted_chains(rng)
    single = HarmonicAngles(angles[:1], k=2.0, theta0=150.0)
    result = single.energy_forces(state, per_atom=True)
    i, j, k = angles[0]
    np.testing.assert_allclose(result.energies[[i, j, k]], result.energy / 3, rtol=1e-14)
    assert np.count_nonzero(result.energies) == 3
    voigt = result.virial[[0, 1, 2, 1, 0, 0], [0, 1, 2, 2, 2, 1]]
    np.testing.assert_allclose(result.virials[[i, j, k]], np.tile(voigt / 3, (3, 1)), rtol=1e-13)


def test_virial_is_arm_outer_force(rng):
    """W = x_ij (x) F_i + x_kj (x) F_k, symmetric, traceless (angles do not change with
    the volume)."""
    state = _triple(73.0, box=6.0, pbc=True)
    state.positions[0] += state.box * [1, 0, -2]  # an arm across the boundary
    result = CosineAngles([[0, 1, 2]], k=2.0).energy_forces(state)
    a = minimum_image(state.positions[0] - state.positions[1], state.box, state.pbc)
    b = minimum_image(state.positions[2] - state.positions[1], state.box, state.pbc)
    expected = np.outer(a, result.forces[0]) + np.outer(b, result.forces[2])
    np.testing.assert_allclose(result.virial, expected, atol=1e-14)
    np.testing.assert_allclose(result.virial, result.virial.T, atol=1e-14)
    assert np.trace(result.virial) == pytest.approx(0.0, abs=1e-14)


# ------------------------------------------------------------------ straight and folded


@pytest.mark.parametrize("theta", [180.0, 0.0])
@pytest.mark.parametrize(
    "potential",
    [
        HarmonicAngles([[0, 1, 2]], k=2.0, theta0=180.0),
        HarmonicAngles([[0, 1, 2]], k=2.0, theta0=120.0),
        HarmonicAngles([[0, 1, 2]], k=2.0, theta0=0.0),
        CosineAngles([[0, 1, 2]], k=2.0),
    ],
    ids=["harmonic-180", "harmonic-120", "harmonic-0", "cosine"],
)
def test_exactly_straight_or_folded_triples_give_finite_zero_forces(potential, theta):
    """At sin theta = 0 the gradient of cos theta vanishes: no NaN, no force (as LAMMPS)."""
    state = _triple(theta)
    result = potential.energy_forces(state, per_atom=True)
    assert np.isfinite(result.energy) and np.all(np.isfinite(result.energies))
    np.testing.assert_array_equal(np.isfinite(result.forces), True)
    np.testing.assert_allclose(result.forces, 0.0, atol=1e-12)
    assert np.all(np.isfinite(potential.hessian(state).toarray()))
    if isinstance(potential, CosineAngles):
        expected = 2.0 * (1 + np.cos(np.radians(theta)))
    else:
        expected = 2.0 * np.radians(theta - potential.theta0[0]) ** 2
    assert result.energy == pytest.approx(expected, rel=1e-14, abs=1e-15)


@pytest.mark.parametrize("theta", [179.9, 179.5, 0.1, 0.5])
@pytest.mark.parametrize("theta0", [180.0, 120.0, 0.0])
def test_near_straight_and_folded_forces_are_exact_where_sin_theta_exceeds_the_floor(theta, theta0):
    """sin(0.1 degrees) = 0.0017 > 0.001: no clamping; forces = -grad E and the Hessian is
    the derivative of the forces."""
    assert np.sin(np.radians(theta)) > SMALL
    state = _triple(theta)
    potential = HarmonicAngles([[0, 1, 2]], k=2.0, theta0=theta0)
    result = potential.energy_forces(state)
    # Derivatives grow as 1 / sin^3 theta here (truncation ~ h^2 / sin^3 theta) and
    # arccos loses digits (round-off ~ 1e-16 / (h sin theta)): h = 1e-7 between the two.
    numeric = _numeric_forces(potential, state, h=1e-7)
    scale = max(1.0, np.abs(result.forces).max())
    np.testing.assert_allclose(result.forces, numeric, rtol=1e-6, atol=1e-6 * scale)
    hessian = potential.hessian(state).toarray()
    np.testing.assert_allclose(
        hessian, _numeric_hessian(potential, state, h=1e-8), atol=1e-4 * np.abs(hessian).max()
    )


@pytest.mark.parametrize("theta", [179.99, 0.01])
def test_within_the_floor_forces_are_lammps_clamped_and_bounded(theta):
    """Where sin theta < 0.001 LAMMPS divides by 0.001 instead: the force is that of
    -dU/d(cos theta) = 2 K (theta - theta0) / 0.001, finite; the Hessian stays the
    derivative of those forces."""
    state = _triple(theta, arms=(1.0, 1.0))
    potential = HarmonicAngles([[0, 1, 2]], k=2.0, theta0=120.0)
    result = potential.energy_forces(state)
    c = np.cos(np.radians(theta))
    arm_a, arm_b = state.positions[[0, 2]] - state.positions[1]
    dc_dx = arm_b - c * arm_a  # unit arms: d cos theta / d x_i
    expected = 2.0 * 2.0 * np.radians(theta - 120.0) / SMALL * dc_dx
    np.testing.assert_allclose(result.forces[0], expected, rtol=1e-6, atol=1e-12)
    assert np.all(np.isfinite(result.forces))
    hessian = potential.hessian(state).toarray()
    np.testing.assert_allclose(
        hessian, _numeric_hessian(potential, state, h=1e-9), atol=1e-4 * np.abs(hessian).max()
    )


def test_a_zero_length_arm_raises_naming_the_angle():
    state = md.State(positions=[[0, 0, 0], [1, 0, 0], [2, 0, 0], [2, 0, 0]], box=10.0, pbc=False)
    potential = CosineAngles([[0, 1, 2], [1, 2, 3]], k=1.0)
    with pytest.raises(AngleCollapseError, match=r"angle 1 \(1, 2, 3\)") as caught:
        potential.energy_forces(state)
    assert caught.value.angle == 1 and caught.value.atoms == (1, 2, 3)
    assert isinstance(caught.value, NonFiniteError)
    with pytest.raises(AngleCollapseError):
        potential.hessian(state)
    assert np.isnan(angle_values(state, [[1, 2, 3]])[0])


# ------------------------------------------------------------------ construction


@pytest.mark.parametrize(
    ("build", "match"),
    [
        (lambda: HarmonicAngles([[0, 1, 2]], k=-1.0, theta0=90.0), "k must be finite and >= 0"),
        (lambda: HarmonicAngles([[0, 1, 2]], k=1.0, theta0=190.0), "theta0 must be between"),
        (lambda: HarmonicAngles([[0, 1, 2]], k=1.0, theta0=-5.0), "theta0 must be finite"),
        (lambda: CosineAngles([[0, 1, 2]], k=-0.5), "k must be finite and >= 0"),
        (lambda: CosineAngles([[0, 1, 2]], k=float("nan")), "k must be finite"),
        (lambda: CosineAngles([[0, 1, 1]], k=1.0), r"angle 0 \(0, 1, 1\) names atom 1 twice"),
        (lambda: CosineAngles([[0, 1]], k=1.0), r"shape \(A, 3\)"),
        (lambda: CosineAngles([[0, -1, 2]], k=1.0), "negative atom index"),
        (lambda: CosineAngles([[0, 1, 2]], k=[1.0, 2.0]), "angle_types"),
        (lambda: CosineAngles([[0, 1, 2]], k=[1.0], angle_types=[3]), "angle_types go up to 3"),
    ],
)
def test_invalid_parameters_are_refused(build, match):
    with pytest.raises(ValueError, match=match):
        build()


def test_check_refuses_atoms_that_do_not_exist():
    potential = CosineAngles([[0, 1, 2], [1, 2, 5]], k=1.0)
    state = _triple(90.0)
    with pytest.raises(ValueError, match=r"angle 1 \(1, 2, 5\) refers to atom 5.*3 atoms"):
        potential.check(state)
    with pytest.raises(ValueError, match="refers to atom 5"):
        potential.energy_forces(state)


def test_registry_and_describe():
    assert POTENTIALS["angle_harmonic"] is HarmonicAngles
    assert POTENTIALS["angle_cosine"] is CosineAngles
    described = HarmonicAngles(
        [[0, 1, 2], [1, 2, 3]], k=[1.0, 2.0], theta0=[180.0, 90.0], angle_types=[1, 0]
    ).describe()
    assert json.loads(json.dumps(described)) == described
    assert described["type"] == "angle_harmonic" and described["theta0"] == [180.0, 90.0]
    assert described["n_angles"] == 2 and described["n_angle_types"] == 2
    assert CosineAngles([[0, 1, 2]], k=3.0).describe()["k"] == 3.0


def test_from_config_reads_an_angles_file(tmp_path):
    path = tmp_path / "angles.txt"
    path.write_text("# i j k\n0 1 2\n\n1 2 3  # the second\n")
    potential = CosineAngles.from_config({"angles_file": str(path), "k": 2.0})
    np.testing.assert_array_equal(potential.angles, [[0, 1, 2], [1, 2, 3]])
    path.write_text("0 1 2\n1 2\n")
    with pytest.raises(ValueError, match=rf"angles_file {path}: line 2: expected 3 integer"):
        CosineAngles.from_config({"angles_file": str(path), "k": 2.0})
    path.write_text("0 1 2.5\n")
    with pytest.raises(ValueError, match="line 1: expected 3 integer atom indices"):
        CosineAngles.from_config({"angles_file": str(path), "k": 2.0})


@pytest.mark.parametrize(
    ("params", "match"),
    [
        ({"angles": [[0, 1, 2]], "k": 1.0, "theta0": 90.0, "stiff": 1}, "unknown key.*stiff"),
        ({"angles": [[0, 1, 2]], "k": 1.0}, "missing key.*theta0"),
        ({"k": 1.0, "theta0": 90.0}, "exactly one of 'angles'"),
        ({"angles": [[0, 1, 2.5]], "k": 1.0, "theta0": 90.0}, "angles: expected integers"),
        ({"angles": [[0, 1, 2]], "k": "stiff", "theta0": 90.0}, "k: expected a number"),
        ({"angles_file": "/nonexistent/a.txt", "k": 1.0, "theta0": 90.0}, "not found"),
    ],
)
def test_from_config_rejects_bad_tables(params, match):
    with pytest.raises(ValueError, match=match):
        HarmonicAngles.from_config(params)


def test_ase_calculator_takes_angles(rng):
    """Energy, forces, stress and per-atom energies through MDCalculator equal the engine's."""
    from md.calculator import MDCalculator  # the ASE adapter: only this test needs it

    state, angles, types = _tilted_chains(rng)
    potential = HarmonicAngles(angles, k=[2.0, 0.7], theta0=[180.0, 100.0], angle_types=types)
    ours = md.ForceField([potential]).compute(state, per_atom=True)
    atoms = state.to_ase()
    atoms.calc = MDCalculator([potential])
    assert atoms.get_potential_energy() == pytest.approx(ours.energy, rel=1e-12)
    np.testing.assert_allclose(atoms.get_potential_energies(), ours.energies, atol=1e-12)
    # ASE's cell is rotated from ours only if it is not lower triangular: here it is.
    np.testing.assert_allclose(atoms.get_forces(), ours.forces, atol=1e-12)
    voigt = (-ours.virial / state.volume)[[0, 1, 2, 1, 0, 0], [0, 1, 2, 2, 2, 1]]
    np.testing.assert_allclose(atoms.get_stress(), voigt, atol=1e-12)


# ------------------------------------------------------------------ implicit Euler


class _WithoutHessian:
    """An angle potential hidden behind a wrapper with no Hessian: fixed-point iteration."""

    cutoff = None

    def __init__(self, inner) -> None:
        self.inner = inner

    def energy_forces(self, state, neighbors=None, per_atom=False, virial=True) -> ForceResult:
        return self.inner.energy_forces(state, neighbors, per_atom, virial)

    def check(self, state) -> None:
        self.inner.check(state)

    def describe(self) -> dict:
        return self.inner.describe()


def test_implicit_euler_newton_with_angles_matches_fixed_point_iteration(rng):
    """Newton's steps use the angle Hessian; they must land where the Hessian-free
    fixed-point iteration does, and the energy falls step by step (backward Euler)."""
    state, bonds = single_chain(12, bond_length=1.0, seed=5)
    angles = chain_angles(1, 12)
    md.maxwell_boltzmann(state, 1.0, seed=rng)
    results = []
    for hidden in (False, True):
        bend = HarmonicAngles(angles, k=8.0, theta0=150.0)
        terms = [HarmonicBonds(bonds, k=50.0, r0=1.0), _WithoutHessian(bend) if hidden else bend]
        run = state.copy()
        forcefield = md.ForceField(terms)
        integrator = ImplicitEuler(dt=0.02, tol=1e-12)
        energies = []
        for _ in range(10):
            integrator.step(run, forcefield)
            energies.append(
                forcefield.compute(run).energy + kinetic_energy(run.velocities, run.masses)
            )
        assert np.all(np.diff(energies) < 0)
        results.append((run, integrator.statistics))
    (newton, stats), (fixed, _) = results
    assert stats["hessian_evaluations"] > 0
    np.testing.assert_allclose(newton.positions, fixed.positions, atol=1e-9)
    np.testing.assert_allclose(newton.velocities, fixed.velocities, atol=1e-7)


# ------------------------------------------------------------------ topology and files


def test_chain_angles_are_consecutive_triples():
    np.testing.assert_array_equal(chain_angles(2, 4), [[0, 1, 2], [1, 2, 3], [4, 5, 6], [5, 6, 7]])
    assert chain_angles(3, 2).shape == (0, 3)
    with pytest.raises(ValueError, match="chain_length"):
        chain_angles(1, 1)


def test_forcefield_topology_names_angles_by_style():
    bonds = [[0, 1], [1, 2], [2, 3]]
    forcefield = md.ForceField(
        [
            FENEBonds(bonds),
            CosineAngles([[0, 1, 2], [1, 2, 3]], k=2.0),
            HarmonicAngles([[0, 1, 2]], k=1.0, theta0=[90.0, 120.0], angle_types=[1]),
        ]
    )
    topology = forcefield.topology()
    assert topology.bond_type_names == ("fene",)
    assert topology.angle_type_names == ("angle_cosine", "angle_harmonic.0", "angle_harmonic.1")
    np.testing.assert_array_equal(topology.angle_types, [0, 0, 2])
    with pytest.raises(ValueError, match="also bond type names"):
        Topology.from_bonds(bonds, bond_type_names=["x"]).with_angles([[0, 1, 2]], None, ["x"])


#: The example shrunk for file tests: two chains of six beads (8 angles, 10 bonds).
SMALL_CHAINS = chain_angles(2, 6)


def _run_chain(tmp_path, extra="", name="chain.toml", steps=20):
    text = EXAMPLE.read_text().replace("steps = 12000", f"steps = {steps}")
    text = text.replace("chains = 20", "chains = 2").replace(
        "chain_length = 10", "chain_length = 6"
    )
    config = tmp_path / name
    config.write_text(text + extra)
    out = tmp_path / "chain.h5"
    code = main(["run", str(config), "-o", str(out), "--no-progress", "-q"])
    return code, out


def test_run_stores_angles_in_h5md_connectivity_and_mdanalysis_reads_them(tmp_path):
    code, out = _run_chain(tmp_path)
    assert code == 0
    with h5py.File(out, "r") as f:
        group = f["connectivity"]
        assert json.loads(group.attrs["angle_types"]) == ["angle_cosine"]
        stored = group["angle_cosine"]
        assert stored.dtype == np.int32 and stored.shape == (8, 3)
        np.testing.assert_array_equal(stored[()], SMALL_CHAINS)
        assert f[stored.attrs["particles_group"]].name == "/particles/trajectory"
        assert group["fene"].shape == (10, 2)
    topology = read_topology(out)
    np.testing.assert_array_equal(topology.angles, SMALL_CHAINS)
    assert topology.bond_type_names == ("fene",)
    universe = open_trajectory(out)  # MDAnalysis's own H5MD reader opens the file
    assert len(universe.angles) == 8 and len(universe.bonds) == 10
    assert set(universe.angles.types()) == {"angle_cosine"}
    np.testing.assert_allclose(
        universe.angles.values()[0],
        np.radians(angle_values(read_trajectory(out).state(-1), [[0, 1, 2]])[0]),
        rtol=1e-5,
    )
    # A structure read back from the trajectory keeps the angles: angles = "system".
    state, again = read_structure(out, units="lj")
    np.testing.assert_array_equal(again.angles, topology.angles)


def test_lammps_data_output_has_angles_and_reads_back(tmp_path, capsys):
    code, out = _run_chain(tmp_path)
    assert code == 0
    data = tmp_path / "chain.data"
    assert main(["convert", str(out), str(data)]) == 0
    text = data.read_text()
    assert "8 angles\n" in text and "1 angle types\n" in text
    assert "angle types 1=angle_cosine" in text.splitlines()[0]
    section = text.split("\nAngles\n\n", 1)[1].split("\n\n")[0].splitlines()
    rows = np.array([line.split() for line in section], dtype=int)
    np.testing.assert_array_equal(rows[:, 0], np.arange(1, 9))  # ids
    np.testing.assert_array_equal(rows[:, 2:] - 1, SMALL_CHAINS)
    state, topology = read_structure(data, units="lj")
    assert topology.angle_type_names == ("angle_cosine",)
    assert sorted(map(tuple, topology.angles.tolist())) == sorted(map(tuple, SMALL_CHAINS.tolist()))
    gsd = tmp_path / "chain.gsd"
    assert main(["convert", str(out), str(gsd)]) == 0
    _, from_gsd = read_structure(gsd, units="lj")
    np.testing.assert_array_equal(from_gsd.angles, SMALL_CHAINS)
    assert from_gsd.angle_type_names == ("angle_cosine",)


def test_config_angles_system_from_a_lammps_data_file(tmp_path):
    """A data file with angles is a structure whose angles = "system" takes them."""
    code, out = _run_chain(tmp_path)
    assert code == 0
    data = tmp_path / "chain.data"
    assert main(["convert", str(out), str(data)]) == 0
    config = tmp_path / "from_data.toml"
    config.write_text(
        'units = "lj"\n[system]\nstructure = "chain.data"\n'
        '[[potentials]]\ntype = "fene"\nbonds = "system"\n'
        '[[potentials]]\ntype = "angle_harmonic"\nangles = "system"\nk = 3.0\ntheta0 = 180.0\n'
        '[integrator]\ntype = "verlet"\ndt = 0.002\n[run]\nsteps = 5\n'
    )
    state, topology = build_system(load_config(config))
    assert sorted(map(tuple, topology.angles.tolist())) == sorted(map(tuple, SMALL_CHAINS.tolist()))
    assert main(["run", str(config), "-o", str(tmp_path / "again.h5"), "--no-progress", "-q"]) == 0
    assert read_topology(tmp_path / "again.h5").angle_type_names == ("angle_harmonic",)


def test_melt_config_builds_angles_along_every_chain(tmp_path):
    config = tmp_path / "melt.toml"
    config.write_text(
        'units = "lj"\nseed = 1\n[system]\npolymer = "melt"\nchains = 3\nchain_length = 5\n'
        "density = 0.3\n"
        '[[potentials]]\ntype = "angle_cosine"\nangles = "system"\nk = 1.0\n'
        '[integrator]\ntype = "verlet"\ndt = 0.002\n'
    )
    _, topology = build_system(load_config(config))
    np.testing.assert_array_equal(topology.angles, chain_angles(3, 5))


# ------------------------------------------------------------------ bad input (CLI)


def _refused(tmp_path, capsys, extra, *needles, files=None):
    for name, text in (files or {}).items():
        (tmp_path / name).write_text(text)
    code, out = _run_chain(tmp_path, extra, name="bad.toml")
    err = capsys.readouterr().err
    assert code == 2, err
    assert not out.exists() and not Path(str(out) + ".ckpt").exists()
    for needle in ("bad.toml", *needles):
        assert needle in err, (needle, err)
    return err


def test_cli_refuses_angles_naming_missing_atoms(tmp_path, capsys):
    extra = '[[potentials]]\ntype = "angle_cosine"\nangles = [[0, 1, 2], [10, 11, 12]]\nk = 1.0\n'
    _refused(tmp_path, capsys, extra, "[potentials.3]", "angle 1 (10, 11, 12)", "atom 12")


def test_cli_refuses_a_malformed_angles_file_naming_file_and_line(tmp_path, capsys):
    extra = '[[potentials]]\ntype = "angle_cosine"\nangles_file = "a.txt"\nk = 1.0\n'
    _refused(tmp_path, capsys, extra, "a.txt", "line 3", files={"a.txt": "0 1 2\n#\n1 2 x\n"})


@pytest.mark.parametrize(
    ("table", "needles"),
    [
        ('type = "angle_cosine"\nangles = "system"\nk = 1.0\nbend = 2\n', ["unknown key", "bend"]),
        ('type = "angle_cosine"\nangles = "system"\nk = -1.0\n', ["k must be finite and >= 0"]),
        ('type = "angle_harmonic"\nangles = "system"\nk = 1.0\ntheta0 = 200.0\n', ["theta0"]),
        ('type = "angle_harmonic"\nangles = "system"\nk = -3.0\ntheta0 = 90.0\n', ["k must"]),
        ('type = "angle_cosine"\nangles = [[0, 0, 1]]\nk = 1.0\n', ["names atom 0 twice"]),
    ],
)
def test_cli_refuses_bad_angle_tables(tmp_path, capsys, table, needles):
    _refused(tmp_path, capsys, "[[potentials]]\n" + table, "[potentials.3]", *needles)


def test_cli_refuses_system_angles_without_a_source(tmp_path, capsys):
    config = tmp_path / "lattice.toml"
    config.write_text(
        'units = "lj"\n[system]\nlattice = "fcc"\ncells = 3\ndensity = 0.8\n'
        '[[potentials]]\ntype = "angle_cosine"\nangles = "system"\nk = 1.0\n'
        '[integrator]\ntype = "verlet"\ndt = 0.002\n[output]\npath = "x.h5"\n'
    )
    assert main(["run", str(config), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert 'angles = "system" needs angles from [system]' in err and "lattice.toml" in err
    assert not (tmp_path / "x.h5").exists()


# ------------------------------------------------------------------ physics


def _mean_cosine(tmp_path, config, steps):
    """Run ``config`` through the CLI; return (block average of the mean cos theta per
    frame after the first 5 tau, the run's potentials, its mean temperature)."""
    out = tmp_path / "semiflexible.h5"
    code = main(["run", str(config), "-o", str(out), "--steps", str(steps), "--no-progress", "-q"])
    assert code == 0
    traj = read_trajectory(out)
    angles = traj.topology.angles
    assert len(angles) == 20 * 8  # every consecutive triple of the 20 chains of 10
    start = int(np.searchsorted(traj.times, 5.0))  # the random-walk start relaxes in a few tau
    cosines = np.cos(
        np.radians(
            np.array(
                [angle_values(traj.state(frame), angles) for frame in range(start, traj.n_frames)]
            )
        )
    )
    result = block_average(cosines.mean(axis=1), n_blocks=8)
    return result, traj.parameters["potentials"], traj.observables["temperature"][start:].mean()


#: What the isolated-angle expectation leaves out, as a bound on <cos theta>: the WCA
#: repulsion of beads i, i+2 (it acts only below 70 degrees, Boltzmann weight ~1e-3 at
#: K = 5), the chains' rare contacts, and the integrator's O(dt^2) bias in configurations
#: (about 0.003 at dt = 0.005: measured 0.014 at dt = 0.01 and 0.005 at dt = 0.005 from
#: long runs of a single chain).
SYSTEMATIC = 0.004


def test_semiflexible_chains_example_has_the_boltzmann_mean_angle(tmp_path):
    """The example (angle_cosine, K = 5, T = 1) run for 30 tau through the CLI:
    <cos theta> over its angles equals the isolated-angle expectation
    1/b - coth(b), b = K/kT, within four standard errors (block averages) plus
    SYSTEMATIC. -0.800 here; a missing bending term would give about 0 (a freely
    jointed chain), a factor 1/2 in the energy -0.61, theta measured the other way +0.8."""
    result, potentials, temperature = _mean_cosine(tmp_path, EXAMPLE, 6000)
    k = next(p["k"] for p in potentials if p["type"] == "angle_cosine")
    assert temperature == pytest.approx(1.0, abs=0.05)  # the T the expectation assumes
    b = k / 1.0
    expected = 1.0 / b - 1.0 / np.tanh(b)
    assert result.sem < 0.01
    assert abs(result.mean - expected) < 4 * result.sem + SYSTEMATIC, (result, expected)


@pytest.mark.slow
def test_harmonic_angles_give_the_boltzmann_mean_angle(tmp_path):
    """The example with angle_harmonic (K = 2.5, theta0 = 180) instead, for 60 tau:
    <cos theta> against the quadrature of sin(theta) exp(-K (theta - pi)^2 / kT)."""
    from scipy.integrate import quad  # scipy's quadrature: only this test needs it

    config = tmp_path / "harmonic.toml"
    config.write_text(
        EXAMPLE.read_text()
        .replace('type = "angle_cosine"      # or', 'type = "angle_harmonic"    # or')
        .replace("k = 5.0", "k = 2.5\ntheta0 = 180.0")
    )
    result, potentials, temperature = _mean_cosine(tmp_path, config, 12000)
    assert potentials[-1] | {"angles_sha256": ""} == {
        "type": "angle_harmonic",
        "k": 2.5,
        "theta0": 180.0,
        "n_angles": 160,
        "angles_sha256": "",
    }
    assert temperature == pytest.approx(1.0, abs=0.05)

    def weight(theta):
        return np.sin(theta) * np.exp(-2.5 * (theta - np.pi) ** 2)

    expected = quad(lambda t: np.cos(t) * weight(t), 0, np.pi)[0] / quad(weight, 0, np.pi)[0]
    assert abs(result.mean - expected) < 4 * result.sem + SYSTEMATIC, (result, expected)
