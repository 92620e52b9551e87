"""The bonded frame: a user's bond or angle term, written in a few lines, gets the loops,
per-type parameters, virial, per-atom values and Hessians of the built-in styles, which
are terms on the same frame (``potentials._bonded_frame``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from md.errors import NonFiniteError
from md.polymers import chain_angles, polymer_melt
from md.state import State
from potentials import (
    AnglePotential,
    BondPotential,
    CosineAngles,
    FENEBonds,
    HarmonicAngles,
    HarmonicBonds,
    angle_term,
    bond_term,
)
from potentials.base import SupportsBondLaw, SupportsHessian


# --------------------------------------------------------------- user terms
@bond_term
def morse(r, d0, alpha, r0):
    e = math.exp(-alpha * (r - r0))
    return d0 * (1.0 - e) ** 2, 2.0 * alpha * d0 * (1.0 - e) * e


@morse.with_curvature
def morse_curvature(r, d0, alpha, r0):
    e = math.exp(-alpha * (r - r0))
    return (
        d0 * (1.0 - e) ** 2,
        2.0 * alpha * d0 * (1.0 - e) * e,
        2.0 * alpha**2 * d0 * e * (2.0 * e - 1.0),
    )


@angle_term(variable="cos")
def cosine_squared(c, k, c0):
    return k * (c - c0) ** 2, 2.0 * k * (c - c0)


@cosine_squared.with_curvature
def cosine_squared_curvature(c, k, c0):
    return k * (c - c0) ** 2, 2.0 * k * (c - c0), 2.0 * k


# The built-in formulas as a user writes them, in r and theta.
@bond_term
def my_harmonic(r, k, r0):
    return 0.5 * k * (r - r0) ** 2, k * (r - r0)


@my_harmonic.with_curvature
def my_harmonic_curvature(r, k, r0):
    return 0.5 * k * (r - r0) ** 2, k * (r - r0), k


@bond_term
def my_fene(r, k, r_max):
    x = (r / r_max) ** 2
    return -0.5 * k * r_max**2 * math.log(1.0 - x), k * r / (1.0 - x)


@angle_term
def my_harmonic_angle(theta, k, theta0):
    return k * (theta - theta0) ** 2, 2.0 * k * (theta - theta0)


@my_harmonic_angle.with_curvature
def my_harmonic_angle_curvature(theta, k, theta0):
    return k * (theta - theta0) ** 2, 2.0 * k * (theta - theta0), 2.0 * k


@angle_term(variable="cos")
def my_cosine(c, k):
    return k * (1.0 + c), k


@pytest.fixture(scope="module")
def chains():
    """Two chains of eight beads in an open box, jiggled, with their bonds and angles."""
    rng = np.random.default_rng(5)
    steps = rng.normal(size=(16, 3))
    steps *= 1.0 / np.linalg.norm(steps, axis=1)[:, None]
    positions = np.concatenate([np.cumsum(steps[:8], axis=0), np.cumsum(steps[8:], axis=0) + 3.0])
    state = State(positions=positions, box=40.0, pbc=False)
    first = np.concatenate([np.arange(7), 8 + np.arange(7)])
    return state, np.stack([first, first + 1], axis=1), chain_angles(2, 8)


def _energy(potential, state, positions):
    moved = state.copy()
    moved.positions[:] = positions
    return potential.energy_forces(moved).energy


def _numerical_forces(potential, state, h=1e-6):
    x = state.positions.copy()
    forces = np.zeros_like(x)
    for index in np.ndindex(x.shape):
        up, down = x.copy(), x.copy()
        up[index] += h
        down[index] -= h
        forces[index] = -(_energy(potential, state, up) - _energy(potential, state, down)) / (2 * h)
    return forces


def _user_potentials(bonds, angles):
    types = np.arange(len(bonds)) % 2
    return [
        BondPotential(morse, bonds, types, d0=[1.0, 2.0], alpha=[1.5, 2.5], r0=[0.9, 1.1]),
        AnglePotential(cosine_squared, angles, k=3.0, c0=-0.5),
        AnglePotential(my_harmonic_angle, angles, k=2.0, theta0=math.radians(100.0)),
    ]


@pytest.mark.parametrize("which", [0, 1, 2])
def test_user_terms_forces_are_minus_the_energy_gradient(chains, which):
    state, bonds, angles = chains
    potential = _user_potentials(bonds, angles)[which]
    result = potential.energy_forces(state, per_atom=True)
    assert result.energy > 0.0
    np.testing.assert_allclose(result.forces, _numerical_forces(potential, state), atol=2e-6)
    # Newton's third law, and an open box's virial is sum x_i (x) F_i.
    np.testing.assert_allclose(result.forces.sum(axis=0), 0.0, atol=1e-12)
    np.testing.assert_allclose(result.virial, state.positions.T @ result.forces, atol=1e-10)
    np.testing.assert_allclose(result.energies.sum(), result.energy, rtol=1e-12)
    np.testing.assert_allclose(result.virials.sum(axis=0)[:3], np.diag(result.virial), atol=1e-10)


@pytest.mark.parametrize("which", [0, 1, 2])
def test_user_terms_hessian_is_the_force_derivative(chains, which):
    state, bonds, angles = chains
    potential = _user_potentials(bonds, angles)[which]
    assert isinstance(potential, SupportsHessian)
    hessian = potential.hessian(state).toarray()
    h = 1e-6
    numerical = np.zeros_like(hessian)
    for column in range(3 * state.n_atoms):
        up, down = state.copy(), state.copy()
        up.positions.reshape(-1)[column] += h
        down.positions.reshape(-1)[column] -= h
        df = potential.energy_forces(up).forces - potential.energy_forces(down).forces
        numerical[:, column] = -df.reshape(-1) / (2 * h)
    np.testing.assert_allclose(hessian, hessian.T, atol=1e-10)
    np.testing.assert_allclose(hessian, numerical, atol=1e-5)


def test_a_bond_across_the_periodic_boundary_takes_the_minimum_image():
    box = 5.0
    inside = State(positions=[[2.0, 2.0, 2.0], [3.2, 2.0, 2.0]], box=box)
    across = State(positions=[[4.6, 2.0, 2.0], [0.8, 2.0, 2.0]], box=box)  # 1.2 apart
    potential = BondPotential(morse, [[0, 1]], d0=1.0, alpha=2.0, r0=1.0)
    a, b = potential.energy_forces(inside), potential.energy_forces(across)
    assert a.energy == pytest.approx(b.energy, rel=1e-14)
    np.testing.assert_allclose(a.forces, b.forces, rtol=1e-12)
    np.testing.assert_allclose(a.virial, b.virial, rtol=1e-12)


def test_built_in_styles_equal_the_same_formula_written_as_a_user_term():
    state, bonds = polymer_melt(3, 6, density=0.8, seed=2)
    state.positions[:] += np.random.default_rng(3).normal(scale=0.05, size=state.positions.shape)
    angles = chain_angles(3, 6)
    pairs = [
        (
            HarmonicBonds(bonds, k=[80.0, 40.0], r0=[0.9, 1.0], bond_types=np.arange(15) % 2),
            BondPotential(my_harmonic, bonds, np.arange(15) % 2, k=[80.0, 40.0], r0=[0.9, 1.0]),
        ),
        (FENEBonds(bonds), BondPotential(my_fene, bonds, k=30.0, r_max=1.5)),
        (
            HarmonicAngles(angles, k=4.0, theta0=120.0),
            AnglePotential(my_harmonic_angle, angles, k=4.0, theta0=math.radians(120.0)),
        ),
        (CosineAngles(angles, k=1.5), AnglePotential(my_cosine, angles, k=1.5)),
    ]
    for built_in, user in pairs:
        ours, theirs = (
            built_in.energy_forces(state, per_atom=True),
            user.energy_forces(state, per_atom=True),
        )
        assert ours.energy == pytest.approx(theirs.energy, rel=1e-12)
        np.testing.assert_allclose(ours.forces, theirs.forces, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(ours.virial, theirs.virial, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(ours.energies, theirs.energies, rtol=1e-9, atol=1e-12)
    for built_in, user in (pairs[0], pairs[2]):
        np.testing.assert_allclose(
            built_in.hessian(state).toarray(), user.hessian(state).toarray(), rtol=1e-9, atol=1e-8
        )


def test_a_user_bond_potential_describes_itself_and_offers_no_bond_law(chains):
    _, bonds, _ = chains
    potential = BondPotential(morse, bonds, d0=1.0, alpha=2.0, r0=1.0)
    described = potential.describe()
    assert (described["type"], described["term"], described["d0"]) == ("bond_term", "morse", 1.0)
    assert described["n_bonds"] == len(bonds)
    # XPBD and RATTLE move bonds by their law: a user's term has none to give.
    assert not isinstance(potential, SupportsBondLaw)
    assert isinstance(HarmonicBonds(bonds, k=1.0, r0=1.0), SupportsBondLaw)
    part = potential.with_bonds(bonds[:3], [0, 0, 0])
    assert part.n_bonds == 3 and part.term is morse
    # Trajectories store the bonds and angles, their types named after the terms.
    from md.forcefield import ForceField

    bend = AnglePotential(cosine_squared, chain_angles(2, 8), k=1.0, c0=0.0)
    topology = ForceField([potential, bend, HarmonicBonds(bonds, k=1.0, r0=1.0)]).topology()
    assert set(topology.bond_type_names) == {"morse", "spring"}
    assert list(topology.angle_type_names) == ["cosine_squared"]


def test_a_term_returning_the_wrong_count_is_named():
    @bond_term
    def three_values(r, k):
        return k * r, k, 0.0

    with pytest.raises(
        TypeError,
        match=r"bond term three_values: three_values\(r, k\) must "
        r"return a tuple of two numbers \(u, du_dr\), got 3",
    ):
        BondPotential(three_values, [[0, 1]], k=1.0)

    @angle_term
    def not_a_tuple(theta, k):
        return k * theta

    with pytest.raises(TypeError, match="angle term not_a_tuple: .* two numbers"):
        AnglePotential(not_a_tuple, [[0, 1, 2]], k=1.0)


def test_bad_parameters_are_named_with_the_term():
    with pytest.raises(ValueError, match="bond term morse: d0 must be a number"):
        BondPotential(morse, [[0, 1]], d0="deep", alpha=1.0, r0=1.0)
    with pytest.raises(
        TypeError,
        match=r"bond term morse takes the parameters \(d0, alpha, r0\); "
        "missing: r0; unknown: rzero",
    ):
        BondPotential(morse, [[0, 1]], d0=1.0, alpha=1.0, rzero=1.0)
    with pytest.raises(TypeError, match="expected a angle term"):
        AnglePotential(morse, [[0, 1, 2]], d0=1.0, alpha=1.0, r0=1.0)
    # A user's parameters may be negative (the built-in styles' may not).
    AnglePotential(cosine_squared, [[0, 1, 2]], k=1.0, c0=-0.5)
    with pytest.raises(ValueError, match="c0 must be a finite number"):
        AnglePotential(cosine_squared, [[0, 1, 2]], k=1.0, c0=math.inf)


def test_a_term_numba_cannot_compile_is_named():
    @bond_term
    def uses_a_dict(r, k):
        table = {"k": k}
        return table["k"] * r, str(k)

    with pytest.raises(TypeError):  # caught in Python already: a str is not a number
        BondPotential(uses_a_dict, [[0, 1]], k=1.0)

    def helper(r):  # a plain Python function: numba cannot call it
        return r

    @bond_term
    def calls_python(r, k):
        return k * helper(r), k

    state = State(positions=[[0, 0, 0], [1.2, 0, 0]], box=10.0, pbc=False)
    potential = BondPotential(calls_python, [[0, 1]], k=1.0)
    with pytest.raises(TypeError, match="bond term calls_python: numba cannot compile it"):
        potential.energy_forces(state)


def test_hessian_without_curvature_and_non_finite_energy_are_named():
    @bond_term
    def short_range(r, k, r_max):
        return -k * math.log(1.0 - r / r_max) if r < r_max else math.inf, k / (r_max - r)

    potential = BondPotential(short_range, [[0, 1]], k=1.0, r_max=1.5)
    near = State(positions=[[0, 0, 0], [1.0, 0, 0]], box=10.0, pbc=False)
    far = State(positions=[[0, 0, 0], [2.0, 0, 0]], box=10.0, pbc=False)
    assert np.isfinite(potential.energy_forces(near).energy)
    with pytest.raises(
        NonFiniteError,
        match=r"bond term short_range: bond 0 between atoms 0 and 1 "
        r"\(length 2.0\) has a non-finite energy",
    ):
        potential.energy_forces(far)
    with pytest.raises(TypeError, match="bond term short_range has no curvature"):
        potential.hessian(near)


def test_user_terms_run_in_a_simulation_with_explicit_and_implicit_steps(chains):
    """Velocity Verlet conserves the energy of chains held by user terms; implicit Euler
    (Newton's method on the terms' Hessians) runs them too."""
    import md
    from integrators.implicit_euler import ImplicitEuler
    from integrators.velocity_verlet import VelocityVerlet

    state, bonds, angles = chains
    start = state.copy()
    start.velocities[:] = np.random.default_rng(8).normal(scale=0.3, size=start.positions.shape)
    potentials = _user_potentials(bonds, angles)
    sim = md.Simulation(start.copy(), potentials, VelocityVerlet(dt=0.002))
    before = sim.thermo()["total_energy"]
    sim.run(300)
    after = sim.thermo()["total_energy"]
    assert abs(after - before) < 1e-3 * abs(before)
    implicit = md.Simulation(start.copy(), potentials, ImplicitEuler(dt=0.01, tol=1e-10))
    implicit.run(5)
    assert np.all(np.isfinite(implicit.state.positions))


_DISABLE_JIT_RUN = """
import json, math
import numpy as np
from md.polymers import chain_angles, polymer_melt
from potentials import (BondPotential, CosineAngles, FENEBonds, HarmonicAngles,
                        HarmonicBonds, bond_term)

@bond_term
def morse(r, d0, alpha, r0):
    e = math.exp(-alpha * (r - r0))
    return d0 * (1.0 - e) ** 2, 2.0 * alpha * d0 * (1.0 - e) * e

state, bonds = polymer_melt(3, 6, density=0.8, seed=2, box_shape="cubic")
state.positions[:] += np.random.default_rng(3).normal(scale=0.05, size=state.positions.shape)
angles = chain_angles(3, 6)
results = {}
for name, potential in [("fene", FENEBonds(bonds)), ("spring", HarmonicBonds(bonds, k=9.0, r0=1.0)),
                        ("cosine", CosineAngles(angles, k=1.5)),
                        ("harmonic", HarmonicAngles(angles, k=2.0, theta0=150.0)),
                        ("morse", BondPotential(morse, bonds, d0=1.0, alpha=2.0, r0=1.0))]:
    result = potential.energy_forces(state, per_atom=True)
    results[name] = [result.energy, result.forces.tolist(), result.virial.tolist(),
                     result.energies.tolist(), result.virials.tolist(),
                     None if name == "morse" else potential.hessian(state).toarray().tolist()]
print(json.dumps(results))
"""


def test_the_bonded_frame_runs_under_disable_jit_as_compiled():
    """With numba off (a debugger, coverage) the template's loops run as Python and give
    the compiled results, for the built-in styles and a user's term."""
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    def run(disable: str) -> dict:
        root = str(Path(__file__).resolve().parents[1])
        paths = os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")]))
        env = {**os.environ, "NUMBA_DISABLE_JIT": disable, "PYTHONPATH": paths}
        done = subprocess.run(
            [sys.executable, "-c", _DISABLE_JIT_RUN],
            env=env,
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert done.returncode == 0, done.stderr
        return json.loads(done.stdout.strip().splitlines()[-1])

    compiled, python = run("0"), run("1")
    for name, reference in compiled.items():
        for ours, theirs in zip(python[name], reference, strict=True):
            if theirs is not None:
                scale = np.abs(theirs).max()
                np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-12 * scale, err_msg=name)
