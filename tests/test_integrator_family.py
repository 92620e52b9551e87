"""Leapfrog, Euler (explicit, symplectic), Stormer-Verlet, RK4 and RKF45.

Accuracy is measured on a harmonic oscillator (one particle tethered to the
origin in an open box, three independent axes) against its analytic
solution; leapfrog is also checked against velocity Verlet on an LJ crystal.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import md
from conftest import Tether
from integrators.base import ConvergenceError
from integrators.explicit_euler import ExplicitEuler, SymplecticEuler
from integrators.leapfrog import Leapfrog
from integrators.runge_kutta import RK4, RKF45
from integrators.stormer_verlet import StormerVerlet
from integrators.velocity_verlet import VelocityVerlet
from potentials import ForceResult, LennardJones

K, MASS = 4.0, 1.0
OMEGA = math.sqrt(K / MASS)  # period pi
X0 = np.array([1.0, -0.5, 0.25])
V0 = np.array([0.5, 0.3, -0.2])
FINAL_TIME = 2.0

ALL = [ExplicitEuler, SymplecticEuler, Leapfrog, StormerVerlet, RK4, RKF45]
IDS = [cls.__name__ for cls in ALL]


def _oscillator():
    state = md.State(positions=[X0], velocities=[V0], masses=MASS, box=10.0, pbc=False)
    return state, md.ForceField([Tether(K)])


def _exact(t):
    return X0 * np.cos(OMEGA * t) + V0 / OMEGA * np.sin(OMEGA * t)


def _energy(state):
    x, v = state.positions[0], state.velocities[0]
    return 0.5 * MASS * v @ v + 0.5 * K * x @ x


def _final_error(integrator, n_steps):
    state, forcefield = _oscillator()
    for _ in range(n_steps):
        integrator.step(state, forcefield)
    assert state.time == pytest.approx(FINAL_TIME, rel=1e-12)
    return np.abs(state.positions[0] - _exact(FINAL_TIME)).max()


def _lj_crystal(seed=3):
    state = md.lattice("fcc", 3, density=0.8442)
    return md.maxwell_boltzmann(state, 1.5, seed=seed)


# ----------------------------------------------------------- order of accuracy


@pytest.mark.parametrize(
    ("cls", "order", "largest_dt"),
    [
        (ExplicitEuler, 1, 0.01),
        (SymplecticEuler, 1, 0.01),
        (Leapfrog, 2, 0.05),
        (StormerVerlet, 2, 0.05),
        (RK4, 4, 0.05),
    ],
    ids=lambda p: getattr(p, "__name__", None),
)
def test_global_order_of_accuracy(cls, order, largest_dt):
    """Slope of log(final position error) against log(dt) over four halvings."""
    dts = largest_dt / 2.0 ** np.arange(5)
    errors = [_final_error(cls(dt=dt), round(FINAL_TIME / dt)) for dt in dts]
    slope = np.polyfit(np.log(dts), np.log(errors), 1)[0]
    assert abs(slope - order) < 0.15, f"{cls.__name__}: measured order {slope:.3f}"


@pytest.mark.parametrize("tol", [1e-6, 1e-9])
def test_rkf45_error_is_within_its_tolerance(tol):
    error = _final_error(RKF45(dt=0.1, tol=tol), round(FINAL_TIME / 0.1))
    assert error <= 10 * tol


def test_rkf45_error_falls_with_the_tolerance():
    errors = [_final_error(RKF45(dt=0.1, tol=tol), 20) for tol in (1e-5, 1e-7, 1e-9, 1e-11)]
    assert all(b < a for a, b in zip(errors, errors[1:], strict=False))
    assert errors[-1] < 1e-4 * errors[0]


# -------------------------------------------------- one step, written by hand


def _reference_step(name, x, v, dt):
    """One step of each scheme on x'' = -w^2 x, written out with numpy."""
    w2 = OMEGA**2
    if name == "ExplicitEuler":
        return x + dt * v, v - dt * w2 * x
    if name == "SymplecticEuler":
        v = v - dt * w2 * x
        return x + dt * v, v
    if name == "StormerVerlet":
        half = x + 0.5 * dt * v
        v = v - dt * w2 * half
        return half + 0.5 * dt * v, v
    if name == "Leapfrog":  # velocity Verlet in exact arithmetic
        v = v - 0.5 * dt * w2 * x
        x = x + dt * v
        return x, v - 0.5 * dt * w2 * x
    if name == "RK4":  # the degree-4 Taylor polynomial of exp(dt A)
        a = np.array([[0.0, 1.0], [-w2, 0.0]]) * dt
        m = np.eye(2) + a + a @ a / 2 + a @ a @ a / 6 + a @ a @ a @ a / 24
        return m[0, 0] * x + m[0, 1] * v, m[1, 0] * x + m[1, 1] * v
    raise KeyError(name)


@pytest.mark.parametrize("cls", [ExplicitEuler, SymplecticEuler, StormerVerlet, Leapfrog, RK4])
def test_steps_follow_the_scheme_written_by_hand(cls):
    dt = 0.07
    state, forcefield = _oscillator()
    integrator = cls(dt=dt)
    x, v = X0.copy(), V0.copy()
    for _ in range(50):
        integrator.step(state, forcefield)
        x, v = _reference_step(cls.__name__, x, v, dt)
    np.testing.assert_allclose(state.positions[0], x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(state.velocities[0], v, rtol=0, atol=1e-12)


# ------------------------------------------------------------ energy behaviour


def test_explicit_euler_energy_grows_monotonically():
    """On the oscillator the energy is multiplied by exactly 1 + (w dt)^2 each step."""
    dt = 0.02
    state, forcefield = _oscillator()
    integrator = ExplicitEuler(dt=dt)
    energies = [_energy(state)]
    for _ in range(300):
        integrator.step(state, forcefield)
        energies.append(_energy(state))
    energies = np.array(energies)
    assert np.all(np.diff(energies) > 0)
    np.testing.assert_allclose(energies[1:] / energies[:-1], 1 + (OMEGA * dt) ** 2, rtol=1e-12)


@pytest.mark.parametrize(
    ("cls", "bound"), [(SymplecticEuler, 0.1), (StormerVerlet, 5e-3), (Leapfrog, 5e-3)]
)
def test_symplectic_energy_is_bounded_without_drift(cls, bound):
    """20 periods at w dt ~ 0.1: a bounded wobble, O(dt) or O(dt^2), and no trend.

    dt = pi / 64 puts 32 steps in every energy oscillation, so means over
    whole oscillations compare cleanly: the late mean equals the early one
    to 1e-3 of the wobble (RK4, dissipative, would miss by a factor 10^4).
    """
    dt = math.pi / 64
    state, forcefield = _oscillator()
    integrator = cls(dt=dt)
    e0 = _energy(state)
    energies = [e0]
    for _ in range(20 * 64):
        integrator.step(state, forcefield)
        energies.append(_energy(state))
    relative = (np.array(energies) - e0) / e0
    assert np.abs(relative).max() < bound
    window = 128  # two periods, four energy oscillations
    early, late = relative[:window], relative[-window:]
    assert abs(late.mean() - early.mean()) < 1e-3 * np.ptp(early)
    assert np.ptp(late) < 1.01 * np.ptp(early)


# ------------------------------------------------- leapfrog and velocity Verlet


def test_leapfrog_matches_velocity_verlet_on_lj():
    """Same start: positions agree to ~1e-12 and velocities to round-off over 300 steps.

    The two are the same scheme in exact arithmetic (leapfrog's synchronised
    velocity is v(t + dt/2) + dt/2 a(t + dt)); only round-off separates them,
    amplified by the chaos of the liquid, and the first step is bitwise equal.
    """
    start = _lj_crystal()
    a, b = start.copy(), start.copy()
    fa, fb = md.ForceField([LennardJones(cutoff=2.5)]), md.ForceField([LennardJones(cutoff=2.5)])
    leapfrog, verlet = Leapfrog(dt=0.005), VelocityVerlet(dt=0.005)
    leapfrog.step(a, fa)
    verlet.step(b, fb)
    assert np.array_equal(a.positions, b.positions)
    assert np.array_equal(a.velocities, b.velocities)
    for _ in range(299):
        leapfrog.step(a, fa)
        verlet.step(b, fb)
    assert np.abs(a.positions - start.positions).max() > 0.1  # it really went somewhere
    np.testing.assert_allclose(a.positions, b.positions, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.velocities, b.velocities, rtol=0, atol=1e-11)
    assert (a.step, a.time) == (b.step, b.time)
    assert leapfrog.statistics == {"steps": 300, "restarts": 1}


@pytest.mark.parametrize("flip", ["in_place", "replaced", "reset"])
def test_leapfrog_time_reversibility(flip):
    """Forward 200 steps, reverse the velocities, 200 back: the start to ~1e-10.

    Leapfrog notices the velocities changed (in place or as a new array) and
    restarts its half-step velocities from them; ``reset`` does so explicitly.
    """
    state = _lj_crystal(seed=11)
    start_positions, start_velocities = state.positions.copy(), state.velocities.copy()
    forcefield = md.ForceField([LennardJones(cutoff=2.5)])
    integrator = Leapfrog(dt=0.005)
    for _ in range(200):
        integrator.step(state, forcefield)
    assert np.abs(state.positions - start_positions).max() > 0.1
    if flip == "replaced":
        state.velocities = -state.velocities
    else:
        state.velocities *= -1.0
        if flip == "reset":
            integrator.reset()
    for _ in range(200):
        integrator.step(state, forcefield)
    np.testing.assert_allclose(state.positions, start_positions, rtol=0, atol=1e-10)
    np.testing.assert_allclose(state.velocities, -start_velocities, rtol=0, atol=1e-9)
    assert integrator.statistics["restarts"] == 2


def test_leapfrog_restarts_on_another_state():
    """Switching to another State (or editing positions) re-initialises from its velocities."""
    forcefield = md.ForceField([Tether(K)])
    first, _ = _oscillator()
    integrator = Leapfrog(dt=0.05)
    for _ in range(7):
        integrator.step(first, forcefield)
    second, _ = _oscillator()
    fresh, _ = _oscillator()
    for _ in range(5):
        integrator.step(second, forcefield)
    reference = Leapfrog(dt=0.05)
    for _ in range(5):
        reference.step(fresh, forcefield)
    np.testing.assert_array_equal(second.positions, fresh.positions)
    np.testing.assert_array_equal(second.velocities, fresh.velocities)
    assert integrator.statistics["restarts"] == 2

    second.positions[0, 0] += 0.1  # an external edit, same arrays, same step
    integrator.step(second, forcefield)
    assert integrator.statistics["restarts"] == 3


# --------------------------------------------------------------- RKF45 control


def test_rkf45_lands_on_the_output_times_and_counts_substeps():
    state, forcefield = _oscillator()
    integrator = RKF45(dt=0.25, tol=1e-8)
    for n in range(1, 9):
        integrator.step(state, forcefield)
        assert state.step == n
        assert state.time == pytest.approx(0.25 * n, rel=1e-14)
        np.testing.assert_allclose(state.positions[0], _exact(state.time), atol=1e-7)
    stats = integrator.statistics
    assert stats["steps"] == 8
    assert stats["accepted"] > 8  # dt = 0.25 is too long for tol 1e-8 in one go
    assert stats["substeps"] == stats["accepted"] + stats["rejected"]
    # Six forces per accepted substep; a rejected one reuses its first stage.
    assert forcefield.n_evaluations == 6 * stats["accepted"] + 5 * stats["rejected"]


def test_rkf45_keeps_its_substep_between_calls_and_reset_forgets_it():
    state, forcefield = _oscillator()
    integrator = RKF45(dt=1.0, tol=1e-8)
    integrator.step(state, forcefield)
    rejected = integrator.statistics["rejected"]
    assert rejected >= 1  # it first tried the whole dt
    for _ in range(3):
        integrator.step(state, forcefield)
    assert integrator.statistics["rejected"] == rejected  # started from the adapted size
    integrator.reset()
    integrator.step(state, forcefield)
    assert integrator.statistics["rejected"] > rejected


class FencedTether(Tether):
    """The tether, with an infinite energy beyond radius 1.5 (the orbit stays within 1.16)."""

    def __init__(self, k: float) -> None:
        super().__init__(k)
        self.outside = 0

    def energy_forces(self, state, neighbors, per_atom=False, virial=True) -> ForceResult:
        result = super().energy_forces(state, neighbors, per_atom)
        if np.linalg.norm(state.positions[0]) > 1.5:
            self.outside += 1
            return ForceResult(energy=math.inf, forces=result.forces, virial=result.virial)
        return result


def test_rkf45_rejects_a_substep_whose_stage_forces_are_not_finite():
    """A too-long trial substep sends a stage through the fence: rejected, not fatal."""
    state = md.State(positions=[X0], velocities=[V0], masses=MASS, box=10.0, pbc=False)
    fence = FencedTether(K)
    integrator = RKF45(dt=3.0, tol=1e-8)
    integrator.step(state, md.ForceField([fence]))
    assert fence.outside >= 1
    assert integrator.statistics["rejected"] >= 1
    assert np.abs(state.positions[0] - _exact(3.0)).max() < 1e-7


@pytest.mark.parametrize(
    "options", [{"dt_min": 0.5}, {"max_substeps": 3}], ids=["dt_min", "max_substeps"]
)
def test_rkf45_raises_convergence_error_and_leaves_the_state(options):
    state, forcefield = _oscillator()
    state.step, state.time = 4, 2.0
    integrator = RKF45(dt=1.0, tol=1e-12, **options)
    with pytest.raises(ConvergenceError) as caught:
        integrator.step(state, forcefield)
    assert caught.value.step == 5
    assert "step 5" in str(caught.value)
    np.testing.assert_array_equal(state.positions[0], X0)
    np.testing.assert_array_equal(state.velocities[0], V0)
    assert (state.step, state.time) == (4, 2.0)


# ------------------------------------------------------------------ bookkeeping


@pytest.mark.parametrize(
    ("cls", "per_step"),
    [(ExplicitEuler, 1), (SymplecticEuler, 1), (Leapfrog, 1), (StormerVerlet, 1), (RK4, 4)],
)
def test_force_evaluations_per_step(cls, per_step):
    state = _lj_crystal()
    forcefield = md.ForceField([LennardJones(cutoff=2.5)])
    integrator = cls(dt=0.002)
    for _ in range(5):
        integrator.step(state, forcefield)
    before = forcefield.n_evaluations
    for _ in range(10):
        integrator.step(state, forcefield)
    assert forcefield.n_evaluations - before == 10 * per_step


@pytest.mark.parametrize("cls", ALL, ids=IDS)
def test_each_step_advances_step_and_time(cls):
    dt = 0.03
    state, forcefield = _oscillator()
    state.step, state.time = 10, 1.5
    integrator = cls(dt=dt)
    for _ in range(7):
        integrator.step(state, forcefield)
    assert state.step == 17
    assert state.time == pytest.approx(1.5 + 7 * dt, rel=1e-14)
    assert integrator.statistics["steps"] == 7
    description = integrator.describe()
    assert description["dt"] == dt and isinstance(description["type"], str)
    integrator.reset()  # always allowed


@pytest.mark.parametrize("cls", ALL, ids=IDS)
@pytest.mark.parametrize("dt", [0.0, -0.001, np.nan, np.inf, "fast"])
def test_invalid_dt_raises(cls, dt):
    with pytest.raises(ValueError, match="dt"):
        cls(dt=dt)


@pytest.mark.parametrize(
    "options",
    [{"tol": 0.0}, {"tol": -1e-8}, {"dt_min": 0.0}, {"max_substeps": 0}, {"max_substeps": 2.5}],
)
def test_rkf45_invalid_options_raise(options):
    with pytest.raises(ValueError, match=next(iter(options))):
        RKF45(dt=0.01, **options)


def test_describe_names_every_integrator():
    names = {cls(dt=0.01).describe()["type"] for cls in ALL}
    assert names == {
        "explicit_euler",
        "symplectic_euler",
        "leapfrog",
        "stormer_verlet",
        "rk4",
        "rkf45",
    }
    assert RKF45(dt=0.01, tol=1e-6, dt_min=1e-5, max_substeps=50).describe() == {
        "type": "rkf45",
        "dt": 0.01,
        "tol": 1e-6,
        "dt_min": 1e-5,
        "max_substeps": 50,
    }


@pytest.mark.parametrize("cls", ALL, ids=IDS)
def test_runs_inside_a_simulation(cls):
    """The Simulation loop drives every integrator; observers see every step."""
    integrator = RKF45(dt=0.005, tol=1e-6) if cls is RKF45 else cls(dt=0.002)
    sim = md.Simulation(_lj_crystal(), [LennardJones(cutoff=2.5)], integrator)
    steps = []
    sim.attach(lambda s: steps.append(s.state.step))
    sim.run(10)
    assert steps == list(range(11))
    assert math.isfinite(sim.thermo()["total_energy"])
