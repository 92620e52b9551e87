"""Rigid bodies (issue 68): body data, force and torque, the rotational integrators."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from integrators.rigid import ROTATION_ORDERS, ROTATIONS, RigidNVE
from md.forcefield import ForceField
from md.rigid import RigidBodies, matrix_quaternions, quaternion_matrices
from md.simulation import Simulation
from md.state import State
from potentials.base import ForceResult
from potentials.lennard_jones import LennardJones


def _state(positions, masses=None, box=20.0, velocities=None):
    positions = np.asarray(positions, float)
    n = len(positions)
    return State(
        positions=positions,
        velocities=np.zeros((n, 3)) if velocities is None else velocities,
        masses=np.ones(n) if masses is None else masses,
        box=[box] * 3,
        pbc=[True] * 3,
    )


def _random_rotation(rng):
    q = rng.normal(size=4)
    return quaternion_matrices((q / np.linalg.norm(q))[None])[0]


# An asymmetric trimer (three distinct moments) and a linear dimer.
TRIMER = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.3, 0.8, 0.0]])
TRIMER_MASSES = np.array([1.0, 2.0, 3.0])


def test_quaternions_and_matrices_round_trip(rng):
    # Half turns about each axis take the branches where w is not the largest component.
    flips = [np.diag(d) for d in ([1.0, -1, -1], [-1.0, 1, -1], [-1.0, -1, 1])]
    matrices = np.array([*(_random_rotation(rng) for _ in range(40)), *flips])
    q = matrix_quaternions(matrices)
    assert np.allclose(quaternion_matrices(q), matrices, atol=1e-14)
    assert np.allclose(np.linalg.norm(q, axis=1), 1.0) and np.all(q[:, 0] >= 0)


def test_body_data_of_a_trimer(rng):
    a = _random_rotation(rng)
    positions = TRIMER @ a.T + [5.0, 19.5, 3.0]  # across the periodic boundary in y
    omega, centre_velocity = np.array([0.3, -0.2, 0.5]), np.array([0.1, 0.2, -0.3])
    com = (TRIMER_MASSES[:, None] * positions).sum(0) / TRIMER_MASSES.sum()
    velocities = centre_velocity + np.cross(omega, positions - com)
    state = _state(positions % 20.0, TRIMER_MASSES, velocities=velocities)
    bodies = RigidBodies.from_molecules(state, [1, 1, 1])
    d = positions - com
    inertia = sum(
        m * (np.dot(r, r) * np.eye(3) - np.outer(r, r))
        for m, r in zip(TRIMER_MASSES, d, strict=True)
    )
    assert np.allclose(bodies.moments[0], np.linalg.eigvalsh(inertia), rtol=1e-12)
    assert np.all(np.diff(bodies.moments[0]) > 0)
    assert np.allclose(bodies.momenta[0], TRIMER_MASSES.sum() * centre_velocity)
    assert np.allclose(bodies.angular_momenta[0], inertia @ omega)
    assert np.allclose(bodies.angular_velocities()[0], omega)
    wrapped = state.positions.copy()
    bodies.place(state)  # the same atoms, unwrapped onto one image
    shift = state.positions - wrapped
    assert np.allclose(shift, np.rint(shift / 20.0) * 20.0, atol=1e-12)
    assert np.allclose(state.velocities, velocities, atol=1e-13)
    translational, rotational = bodies.kinetic_energies(state)
    assert translational + rotational == pytest.approx(
        0.5 * np.sum(TRIMER_MASSES[:, None] * velocities**2), rel=1e-12
    )


def test_linear_dimer_and_free_atoms():
    state = _state([[0, 0, 0], [1, 1, 0], [5, 5, 5], [7, 7, 7]], velocities=np.ones((4, 3)))
    state.velocities[1] = [0, 0, 3]
    bodies = RigidBodies.from_molecules(state, [1, 1, 0, 0])
    assert bodies.linear.tolist() == [True]
    assert bodies.moments[0, 0] == 0.0
    assert bodies.free.tolist() == [2, 3]
    assert bodies.n_dof() == 3 * 2 + 5 - 3
    bodies.place(state)  # no spin about the axis
    axis = (state.positions[1] - state.positions[0]) / np.sqrt(2)
    assert np.dot(bodies.angular_momenta[0], axis) == pytest.approx(0.0, abs=1e-14)


@pytest.mark.parametrize(
    ("positions", "ids", "masses", "box", "message"),
    [
        ([[0, 0, 0], [1, 0, 0], [3, 0, 0]], [1, 1, 2], None, 20, "single atom"),
        ([[0, 0, 0], [1, 0, 0], [3, 0, 0]], [1, 1, 0], [1, 0, 1], 20, "mass 0"),
        ([[0, 0, 0], [1, 0, 0], [3, 0, 0]], [1, 1, 0], [1, -2, 1], 20, "mass -2"),
        ([[0, 0, 0], [3, 0, 0], [6, 0, 0]], [1, 1, 1], None, 10, "half the box"),
        ([[0, 0, 0], [1, 0, 0], [1, 0, 0]], [1, 1, 1], None, 20, "overlap"),
        ([[0, 0, 0], [1, 0, 0], [3, 0, 0]], [0, 0, 0], None, 20, "no rigid bodies"),
    ],
)
def test_bad_bodies_are_refused(positions, ids, masses, box, message):
    state = _state(positions, None, box)
    if masses is not None:  # State refuses them itself; a body's check must too
        state.masses[:] = masses
    with pytest.raises(ValueError, match=message):
        RigidBodies.from_molecules(state, ids)


def _two_trimers(rng):
    a, b = _random_rotation(rng), _random_rotation(rng)
    positions = np.concatenate([TRIMER @ a.T + 5.0, TRIMER @ b.T + [6.3, 5.4, 5.9]])
    return _state(positions, np.tile(TRIMER_MASSES, 2), box=12.0)


def test_torque_is_minus_the_energy_derivative_by_rotation(rng):
    """tau . e = -dE/dtheta for a small turn of body 0 about its centre around e."""
    state = _two_trimers(rng)
    bodies = RigidBodies.from_molecules(state, [1, 1, 1, 2, 2, 2])
    bodies.place(state)
    forcefield = ForceField([LennardJones(cutoff=3.0)], skin=0.3)
    force, torque = bodies.force_torque(forcefield.compute(state).forces)
    assert np.linalg.norm(torque[0]) > 1e-3  # a real torque to check
    assert np.allclose(force[0], -force[1])
    assert np.allclose(torque.sum(0), -np.cross(bodies.centres[0] - bodies.centres[1], force[0]))

    def energy(angle, axis):
        turned = state.copy()
        k = np.asarray(axis, float)
        c, s = np.cos(angle), np.sin(angle)
        cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        turn = np.eye(3) + s * cross + (1 - c) * cross @ cross
        atoms = np.arange(3)
        turned.positions[atoms] = (
            bodies.centres[0] + (state.positions[atoms] - bodies.centres[0]) @ turn.T
        )
        return ForceField([LennardJones(cutoff=3.0)], skin=0.3).compute(turned).energy

    h = 1e-5
    for axis in np.eye(3):
        derivative = (energy(h, axis) - energy(-h, axis)) / (2 * h)
        assert -derivative == pytest.approx(np.dot(torque[0], axis), rel=1e-6, abs=1e-8)
    # Failing check of the check: the torque about the origin instead of the centre.
    wrong = np.cross(state.positions[:3], forcefield.compute(state).forces[:3]).sum(0)
    assert not np.allclose(wrong, torque[0], rtol=1e-3)


class _NoForces:
    """A force source with no forces: free rotation."""

    def compute(self, state, virial=True):
        return ForceResult(0.0, np.zeros_like(state.positions), np.zeros((3, 3)))


def _top(rng):
    """An asymmetric top spinning near its intermediate axis (Dzhanibekov)."""
    state = _state(TRIMER + 5.0, TRIMER_MASSES)
    bodies = RigidBodies.from_molecules(state, [1, 1, 1])
    a = bodies.matrices()[0]
    omega_body = np.array([0.02, 3.0, 0.03])  # body frame: mostly about axis 2 of 3
    bodies.angular_momenta[0] = a @ (bodies.moments[0] * omega_body)
    bodies.place(state)
    return state, bodies


def _tumble(rotation, dt, t_end, rng):
    state, bodies = _top(rng)
    integrator = RigidNVE(dt, bodies, rotation)
    source = _NoForces()
    energies = []
    for _ in range(int(round(t_end / dt))):
        integrator.step(state, source)
        energies.append(sum(bodies.kinetic_energies(state)))
    return state, bodies, np.array(energies)


def test_free_top_tumbles_and_conserves(rng):
    state, bodies, energies = _tumble("no_squish", 0.01, 8.0, rng)
    start_state, start = _top(rng)
    assert np.allclose(bodies.angular_momenta, start.angular_momenta, rtol=1e-13)
    e0 = sum(start.kinetic_energies(start_state))
    assert np.max(np.abs(energies - e0)) / e0 < 1e-3
    # The intermediate axis flips over in this time (the Dzhanibekov effect).
    axis2 = np.array([a[:, 1] for a in [bodies.matrices()[0], start.matrices()[0]]])
    assert np.dot(axis2[0], axis2[1]) < 0


@functools.cache
def _reference_top():
    return _tumble("rk4", 0.001, 2.0, None)[0]


@pytest.mark.parametrize("rotation", sorted(ROTATIONS))
def test_rotational_orders_on_the_free_top(rotation, rng):
    reference = _reference_top()
    errors = []
    dts = (0.02, 0.01)
    for dt in dts:
        state, _, _ = _tumble(rotation, dt, 2.0, rng)
        errors.append(np.max(np.abs(state.positions - reference.positions)))
    order = np.log2(errors[0] / errors[1])
    assert order == pytest.approx(ROTATION_ORDERS[rotation], abs=0.3), (errors, order)


def _trimer_gas(rng, n_side=2, spacing=2.2):
    grid = np.array(
        [[i, j, k] for i in range(n_side) for j in range(n_side) for k in range(n_side)]
    )
    positions = []
    for corner in grid * spacing + 0.6:
        positions.append(TRIMER @ _random_rotation(rng).T + corner)
    positions = np.concatenate(positions)
    n = len(positions)
    state = _state(positions, np.tile(TRIMER_MASSES, n // 3), box=n_side * spacing)
    state.velocities[:] = rng.normal(scale=0.5, size=(n, 3))
    ids = np.repeat(np.arange(1, n // 3 + 1), 3)
    return state, ids


def test_nve_of_trimers_conserves_energy_to_second_order(rng):
    state0, ids = _trimer_gas(rng)
    drifts = []
    for dt in (0.002, 0.001):
        state = state0.copy()
        bodies = RigidBodies.from_molecules(state, ids)
        bodies.place(state)
        sim = Simulation(state, [LennardJones(cutoff=2.0)], RigidNVE(dt, bodies))
        e0 = sim.thermo()["total_energy"]
        energies = []
        for _ in range(int(round(0.2 / dt))):
            sim.run(1)
            energies.append(sim.thermo()["total_energy"])
        drifts.append(np.max(np.abs(np.array(energies) - e0)))
    order = np.log2(drifts[0] / drifts[1])
    assert 1.7 < order < 2.3, (drifts, order)


@pytest.mark.parametrize("bath", ["langevin", "bussi"])
def test_baths_on_bodies_reach_both_temperatures(rng, bath):
    """27 LJ trimers in a Langevin bath (from rest) or Bussi's (from T ~ 0.2) at T = 1.5:
    the translational and the rotational temperature (block means) both equal the target
    within 4 standard errors."""
    from integrators.rigid import RigidBussi, RigidLangevin

    state, ids = _trimer_gas(rng, n_side=3, spacing=2.4)
    state.velocities *= 0.6
    state.velocities -= np.average(state.velocities, axis=0, weights=state.masses)
    bodies = RigidBodies.from_molecules(state, ids)
    bodies.place(state)
    target = 1.5
    if bath == "langevin":
        state.velocities[:] = 0.0
        bodies.take_velocities(state)
        integrator = RigidLangevin(0.005, bodies, "no_squish", kT=target, friction=2.0, seed=5)
    else:
        integrator = RigidBussi(0.005, bodies, "no_squish", kT=target, tau=0.1, seed=5)
    sim = Simulation(state, [LennardJones(cutoff=2.0)], integrator)
    sim.run(200)  # relax
    rows = []
    for _ in range(1600):
        sim.run(1)
        rows.append(sim.thermo())
    for name in ("translational_temperature", "rotational_temperature"):
        blocks = np.array([r[name] for r in rows]).reshape(16, -1).mean(axis=1)
        error = blocks.std(ddof=1) / np.sqrt(len(blocks))
        assert abs(blocks.mean() - target) < 4 * error + 0.01, (name, blocks.mean(), error)
        assert error < 0.05 * target  # a test that can tell


def test_springs_join_bodies_to_each_other_and_to_free_atoms(rng):
    """Harmonic springs from a constituent of one trimer to one of another, and from a
    constituent to a free atom: NVE conserves energy to second order, and the bodies
    turn (the springs pull off their centres, so they exert torques)."""
    from potentials.springs import HarmonicBonds

    a, b = _random_rotation(rng), _random_rotation(rng)
    positions = np.concatenate(
        [TRIMER @ a.T + 4.0, TRIMER @ b.T + [6.0, 4.2, 4.1], [[4.2, 6.0, 4.0]]]
    )
    masses = np.concatenate([TRIMER_MASSES, TRIMER_MASSES, [1.0]])
    state0 = _state(positions, masses, box=20.0)
    state0.velocities[:] = rng.normal(scale=0.3, size=(7, 3))
    springs = [[2, 3], [0, 6]]
    errors = []
    for dt in (0.004, 0.002):
        state = state0.copy()
        bodies = RigidBodies.from_molecules(state, [1, 1, 1, 2, 2, 2, 0])
        bodies.place(state)
        start = bodies.angular_momenta.copy()
        sim = Simulation(state, [HarmonicBonds(springs, k=20.0, r0=1.5)], RigidNVE(dt, bodies))
        e0 = sim.thermo()["total_energy"]
        energies = []
        for _ in range(int(round(1.0 / dt))):
            sim.run(1)
            energies.append(sim.thermo()["total_energy"])
        errors.append(np.max(np.abs(np.array(energies) - e0)))
        assert not np.allclose(bodies.angular_momenta, start, atol=1e-2)
    order = np.log2(errors[0] / errors[1])
    assert 1.7 < order < 2.3, (errors, order)


def test_nose_hoover_chains_on_bodies(rng):
    """27 LJ trimers under Nose-Hoover chains at T = 1.5 from T ~ 0.5: the temperature's
    mean over the second half is the target within 5 %, and the conserved energy (with
    the chain's) departs from its start only by the integration error, of second order."""
    from integrators.rigid import RigidNoseHoover

    start, ids = _trimer_gas(rng, n_side=3, spacing=2.4)
    start.velocities -= np.average(start.velocities, axis=0, weights=start.masses)
    target = 1.5
    runs = {}
    for dt, steps in ((0.004, 1200), (0.002, 400)):
        state = start.copy()
        bodies = RigidBodies.from_molecules(state, ids)
        bodies.place(state)
        integrator = RigidNoseHoover(dt, bodies, "no_squish", kT=target, tau=0.1)
        sim = Simulation(state, [LennardJones(cutoff=2.0)], integrator)
        rows = [sim.thermo()]
        for _ in range(steps):
            sim.run(1)
            rows.append(sim.thermo())
        runs[dt] = rows
    temperatures = np.array([r["temperature"] for r in runs[0.004][600:]])
    assert abs(temperatures.mean() - target) < 0.05 * target, temperatures.mean()
    errors = []
    for dt, rows in runs.items():  # over the first 0.8 time units, while the bath heats
        conserved = np.array([r["conserved_energy"] for r in rows[: int(round(0.8 / dt)) + 1]])
        errors.append(np.max(np.abs(conserved - conserved[0])))
    heat = runs[0.002][-1]["total_energy"] - runs[0.002][0]["total_energy"]
    assert heat > 10.0 * errors[0]  # the bath did work, far more than the error
    order = np.log2(errors[0] / errors[1])
    assert 1.7 < order < 2.3, (errors, order)


def test_compiled_body_loops_match_their_definitions_and_python_twins(rng):
    """The compiled passes over bodies (placing constituents, summing force and torque, the
    four free-rotor steps) against numpy's definitions and their own Python twins (as
    ``NUMBA_DISABLE_JIT`` runs them)."""
    from integrators import _rigid_kernels as kernels
    from md import rigid

    parts = [TRIMER @ _random_rotation(rng).T + rng.uniform(2, 18, 3) for _ in range(6)]
    positions = np.concatenate([*parts, [[1.0, 1.0, 1.0], [1.0, 19.0, 5.0]]])
    state = _state(positions, np.concatenate([np.tile(TRIMER_MASSES, 6), [1.0, 1.0]]))
    bodies = RigidBodies.from_molecules(state, [*np.repeat(np.arange(1, 7), 3), 0, 0])
    bodies.angular_momenta[:] = rng.normal(size=(6, 3))
    bodies.momenta[:] = rng.normal(size=(6, 3))
    free_before = state.positions[-2:].copy()
    bodies.place(state)
    d = bodies.offsets()
    assert np.allclose(
        state.positions[bodies.members], bodies.centres[bodies.owner] + d, atol=1e-14
    )
    omega = bodies.angular_velocities()[bodies.owner]
    velocity = (bodies.momenta / bodies.masses[:, None])[bodies.owner] + np.cross(omega, d)
    assert np.allclose(state.velocities[bodies.members], velocity, atol=1e-14)
    assert np.array_equal(state.positions[-2:], free_before)  # free atoms untouched
    forces = rng.normal(size=(state.n_atoms, 3))
    force, torque = bodies.force_torque(forces)
    expected_force = np.zeros((6, 3))
    np.add.at(expected_force, bodies.owner, forces[bodies.members])
    expected_torque = np.zeros((6, 3))
    np.add.at(expected_torque, bodies.owner, np.cross(d, forces[bodies.members]))
    assert np.allclose(force, expected_force, atol=1e-14)
    assert np.allclose(torque, expected_torque, atol=1e-14)
    twin = np.empty((6, 3)), np.empty((6, 3))
    rigid._force_torque.py_func(
        bodies.members, bodies.starts, bodies.quaternions, bodies.body_positions, forces, *twin
    )
    assert np.allclose(twin[0], force, atol=1e-14) and np.allclose(twin[1], torque, atol=1e-14)
    args = (bodies.quaternions, bodies.angular_momenta, bodies.inverse_moments, 0.05)
    for name, kernel, extra in (
        (
            "no_squish",
            kernels._axis_turns,
            (np.array([2, 1, 0, 1, 2]), np.array([0.5, 0.5, 1, 0.5, 0.5]), False),
        ),
        (
            "dlm",
            kernels._axis_turns,
            (np.array([0, 1, 2, 1, 0]), np.array([0.5, 0.5, 1, 0.5, 0.5]), True),
        ),
        ("richardson", kernels._richardson, ()),
        ("rk4", kernels._rk4, ()),
    ):
        compiled = ROTATIONS[name](*args)
        python = np.empty((6, 4))
        kernel.py_func(*args, *extra, python)
        assert np.allclose(python, compiled, atol=1e-14), name
        assert np.allclose(np.linalg.norm(compiled, axis=1), 1.0, atol=1e-14)
        # a step of the free rotor keeps the energy L I^-1 L to the method's order
        after = np.einsum("bji,bj->bi", quaternion_matrices(compiled), bodies.angular_momenta)
        before = np.einsum("bji,bj->bi", bodies.matrices(), bodies.angular_momenta)
        energy = lambda body: np.sum(body**2 * bodies.inverse_moments, axis=1)  # noqa: E731
        assert np.allclose(energy(after), energy(before), rtol=1e-3), name
