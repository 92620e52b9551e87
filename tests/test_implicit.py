"""Implicit Euler and implicit midpoint: analytic, order, stiffness and failure checks."""

from __future__ import annotations

import numpy as np
import pytest

import md
from integrators.base import ConvergenceError
from integrators.implicit_euler import ImplicitEuler, ImplicitMidpoint
from integrators.velocity_verlet import VelocityVerlet
from md.thermo import kinetic_energy
from potentials import LennardJones
from potentials.base import ForceResult

# ------------------------------------------------------------------ test-only potentials


class TetherWithoutHessian:
    """Every atom tied to the origin: U = k/2 sum |x_i|^2 (open boxes only), no Hessian."""

    cutoff = None

    def __init__(self, k: float) -> None:
        self.k = k

    def energy_forces(self, state, neighbors, per_atom=False, virial=True) -> ForceResult:
        x = state.positions
        return ForceResult(0.5 * self.k * float(np.sum(x * x)), -self.k * x, np.zeros((3, 3)))

    def check(self, state) -> None:
        pass

    def describe(self) -> dict:
        return {"type": "tether", "k": self.k}


class Tether(TetherWithoutHessian):
    """The tether with its Hessian k I (dense; the ForceField converts it)."""

    def hessian(self, state, neighbors):
        return self.k * np.eye(3 * state.n_atoms)


class ChainBonds:
    """Harmonic bonds between consecutive atoms: U = k/2 (r - r0)^2 per bond."""

    cutoff = None

    def __init__(self, k: float, r0: float) -> None:
        self.k, self.r0 = k, r0

    def _bonds(self, state):
        d = state.positions[:-1] - state.positions[1:]
        r = np.linalg.norm(d, axis=1)
        return d, r

    def energy_forces(self, state, neighbors, per_atom=False, virial=True) -> ForceResult:
        d, r = self._bonds(state)
        energy = 0.5 * self.k * float(np.sum((r - self.r0) ** 2))
        pair = (-self.k * (r - self.r0) / r)[:, None] * d  # force on the first atom of a bond
        forces = np.zeros_like(state.positions)
        forces[:-1] += pair
        forces[1:] -= pair
        return ForceResult(energy, forces, np.zeros((3, 3)))

    def check(self, state) -> None:
        pass

    def describe(self) -> dict:
        return {"type": "chain", "k": self.k, "r0": self.r0}

    def hessian(self, state, neighbors):
        d, r = self._bonds(state)
        n = state.n_atoms
        hessian = np.zeros((3 * n, 3 * n))
        for b in range(n - 1):
            unit = d[b] / r[b]
            ratio = self.r0 / r[b]
            block = self.k * ((1.0 - ratio) * np.eye(3) + ratio * np.outer(unit, unit))
            i, j = slice(3 * b, 3 * b + 3), slice(3 * b + 3, 3 * b + 6)
            hessian[i, i] += block
            hessian[j, j] += block
            hessian[i, j] -= block
            hessian[j, i] -= block
        return hessian


# ------------------------------------------------------------------------- helpers


def oscillator(masses=(1.0,)):
    """Atoms on tethers, in an open box, with x0 and v0 not parallel."""
    n = len(masses)
    positions = np.tile([1.0, 0.0, 0.2], (n, 1))
    velocities = np.tile([0.0, 0.5, -0.3], (n, 1))
    return md.State(
        positions=positions, velocities=velocities, masses=masses, box=[10.0] * 3, pbc=False
    )


def oscillator_energies(state, k):
    """Energy of each atom of the tethered oscillator."""
    return 0.5 * state.masses * np.sum(state.velocities**2, axis=1) + 0.5 * k * np.sum(
        state.positions**2, axis=1
    )


def total_energy(state, forcefield):
    return forcefield.compute(state).energy + kinetic_energy(state.velocities, state.masses)


def global_error(integrator_class, dt, span=1.0, k=1.0):
    """Phase-space error at time ``span`` against the exact oscillator solution."""
    state = oscillator()
    x0, v0 = state.positions.copy(), state.velocities.copy()
    forcefield = md.ForceField([Tether(k)])
    integrator = integrator_class(dt=dt, tol=1e-13)
    for _ in range(round(span / dt)):
        integrator.step(state, forcefield)
    omega = np.sqrt(k)
    t = state.time
    exact_x = x0 * np.cos(omega * t) + v0 / omega * np.sin(omega * t)
    exact_v = -x0 * omega * np.sin(omega * t) + v0 * np.cos(omega * t)
    return np.sqrt(np.sum((state.positions - exact_x) ** 2 + (state.velocities - exact_v) ** 2))


def chain(n_beads=10, seed=5):
    rng = np.random.default_rng(seed)
    positions = np.zeros((n_beads, 3))
    positions[:, 0] = np.arange(n_beads, dtype=float)
    positions += rng.normal(scale=0.02, size=positions.shape)
    velocities = rng.normal(scale=0.5, size=positions.shape)
    return md.State(
        positions=positions, velocities=velocities, masses=1.0, box=[50.0] * 3, pbc=False
    )


def lj_liquid(cells=4, temperature=1.0, seed=3):
    return md.maxwell_boltzmann(md.lattice("fcc", cells, density=0.8442), temperature, seed=seed)


# --------------------------------------------------------------------------- tests


def test_options_are_validated_and_described():
    integrator = ImplicitEuler(dt=0.01, tol=1e-9, max_iter=7, linear_solver="cg")
    assert integrator.describe() == {
        "type": "implicit_euler",
        "dt": 0.01,
        "tol": 1e-9,
        "max_iter": 7,
    }
    assert ImplicitMidpoint(dt=0.02).describe()["type"] == "implicit_midpoint"
    assert set(integrator.statistics) == {
        "steps",
        "newton_iterations",
        "linear_iterations",
        "line_search_backtracks",
        "fallbacks",
        "projections",
        "hessian_evaluations",
    }
    for bad in (
        {"dt": 0.0},
        {"dt": 0.01, "tol": 0.0},
        {"dt": 0.01, "tol": float("nan")},
        {"dt": 0.01, "max_iter": 0},
        {"dt": 0.01, "max_iter": 2.5},
        {"dt": 0.01, "linear_solver": "lu"},
    ):
        with pytest.raises(ValueError):
            ImplicitEuler(**bad)
    integrator.reset()


def test_implicit_euler_damps_oscillator_by_exact_factor():
    k, dt = 2.0, 0.3
    masses = np.array([1.0, 4.0])
    state = oscillator(masses)
    forcefield = md.ForceField([Tether(k)])
    integrator = ImplicitEuler(dt=dt, tol=1e-13)
    factor = 1.0 / (1.0 + (k / masses) * dt**2)  # omega^2 = k / m per atom
    energies = oscillator_energies(state, k)
    for n in range(1, 21):
        integrator.step(state, forcefield)
        new = oscillator_energies(state, k)
        np.testing.assert_allclose(new / energies, factor, rtol=1e-10)
        energies = new
        assert state.step == n
        assert state.time == pytest.approx(n * dt)
    # Linear forces: Newton is exact after one iteration per step.
    assert integrator.statistics["steps"] == 20
    assert integrator.statistics["newton_iterations"] <= 20


def test_implicit_euler_velocity_is_displacement_over_dt():
    state = oscillator()
    x0 = state.positions.copy()
    integrator = ImplicitEuler(dt=0.1, tol=1e-12)
    integrator.step(state, md.ForceField([Tether(1.0)]))
    np.testing.assert_allclose(state.velocities, (state.positions - x0) / 0.1, rtol=1e-12)
    # Backward Euler equation: v1 = v0 + dt F(x1) / m.
    np.testing.assert_allclose(state.velocities, [[0.0, 0.5, -0.3]] - 0.1 * state.positions)


@pytest.mark.parametrize(
    ("integrator_class", "order"), [(ImplicitEuler, 1.0), (ImplicitMidpoint, 2.0)]
)
def test_global_order(integrator_class, order):
    steps = np.array([0.04, 0.02, 0.01, 0.005])
    errors = np.array([global_error(integrator_class, dt) for dt in steps])
    slope = np.polyfit(np.log(steps), np.log(errors), 1)[0]
    assert abs(slope - order) < 0.15, (slope, errors)


def test_implicit_midpoint_conserves_oscillator_energy():
    k = 3.0
    state = oscillator((1.0, 2.0))
    forcefield = md.ForceField([Tether(k)])
    integrator = ImplicitMidpoint(dt=0.4, tol=1e-13)  # omega dt > 2: Verlet would be unstable
    start = oscillator_energies(state, k)
    for _ in range(200):
        integrator.step(state, forcefield)
    np.testing.assert_allclose(oscillator_energies(state, k), start, rtol=1e-10)
    assert state.step == 200 and state.time == pytest.approx(80.0)


def test_fixed_point_iteration_without_hessian_matches_newton():
    dt = 0.1
    with_newton, without = oscillator(), oscillator()
    newton = ImplicitEuler(dt=dt, tol=1e-12)
    fixed_point = ImplicitEuler(dt=dt, tol=1e-12)
    for _ in range(5):
        newton.step(with_newton, md.ForceField([Tether(1.0)]))
        fixed_point.step(without, md.ForceField([TetherWithoutHessian(1.0)]))
    np.testing.assert_allclose(without.positions, with_newton.positions, atol=1e-10)
    np.testing.assert_allclose(without.velocities, with_newton.velocities, atol=1e-10)


def test_stiff_chain_implicit_euler_stable_far_beyond_verlet_limit():
    k, r0 = 1e4, 1.0
    # Highest chain mode: omega_max < 2 sqrt(k / m) = 200, so Verlet needs dt < 0.01.
    verlet_limit = 2.0 / (2.0 * np.sqrt(k))
    sim = md.Simulation(chain(), [ChainBonds(k, r0)], VelocityVerlet(dt=2.0 * verlet_limit))
    with pytest.raises(md.SimulationError):
        sim.run(2000)

    state = chain()
    forcefield = md.ForceField([ChainBonds(k, r0)])
    integrator = ImplicitEuler(dt=25.0 * verlet_limit)
    energies = [total_energy(state, forcefield)]
    for _ in range(40):
        integrator.step(state, forcefield)
        energies.append(total_energy(state, forcefield))
    energies = np.array(energies)
    assert np.all(np.isfinite(state.positions))
    assert np.all(np.diff(energies) <= 1e-9 * abs(energies[0]))
    bonds = np.linalg.norm(np.diff(state.positions, axis=0), axis=1)
    np.testing.assert_allclose(bonds, r0, atol=0.01)
    stats = integrator.statistics
    assert stats["steps"] == 40
    assert stats["newton_iterations"] / stats["steps"] <= 6


def test_convergence_failure_names_step_and_restores_state():
    state = lj_liquid(cells=3)
    sim = md.Simulation(state, [LennardJones(cutoff=2.5)], ImplicitEuler(dt=0.005, tol=1e-8))
    sim.run(3)
    sim.integrator = ImplicitEuler(dt=0.005, tol=1e-14, max_iter=1)
    before = state.copy()
    with pytest.raises(ConvergenceError, match="step 4") as caught:
        sim.run(1)
    assert caught.value.step == 4
    assert caught.value.residual > 1e-14
    np.testing.assert_array_equal(state.positions, before.positions)
    np.testing.assert_array_equal(state.velocities, before.velocities)
    assert state.step == 3 and state.time == before.time
    assert sim.integrator.statistics["steps"] == 0


def test_chord_steps_reuse_the_hessian_and_reach_the_same_solution(monkeypatch):
    """While each full Newton step cuts the residual tenfold, CG reuses the last
    iteration's Hessian: fewer evaluations than iterations, and the same trajectory
    as evaluating it every iteration, to the solver's tolerance."""
    import integrators._newton as newton

    runs = {}
    for reduction in (newton._CHORD_REDUCTION, 0.0):  # 0: a fresh Hessian every iteration
        monkeypatch.setattr(newton, "_CHORD_REDUCTION", reduction)
        state = lj_liquid(cells=4)
        integrator = ImplicitEuler(0.005, tol=1e-10, linear_solver="cg")
        md.Simulation(state, [LennardJones(cutoff=2.5)], integrator).run(10)
        runs[reduction] = state, integrator.statistics
    (chord, chord_stats), (fresh, fresh_stats) = runs.values()
    assert fresh_stats["hessian_evaluations"] == fresh_stats["newton_iterations"]
    assert chord_stats["hessian_evaluations"] < chord_stats["newton_iterations"]
    assert chord_stats["hessian_evaluations"] >= chord_stats["steps"]  # never across steps
    np.testing.assert_allclose(chord.positions, fresh.positions, rtol=0, atol=1e-9)
    np.testing.assert_allclose(chord.velocities, fresh.velocities, rtol=0, atol=1e-7)


@pytest.mark.parametrize("integrator_class", [ImplicitEuler, ImplicitMidpoint])
def test_extrapolated_predictor_reaches_the_same_solution_in_fewer_iterations(integrator_class):
    """The predictor extrapolates the start accelerations of the last two steps to the
    end of the step: the same trajectory as the plain explicit prediction (reset before
    every step), to the solver's tolerance, with fewer Newton and CG iterations."""
    runs = []
    for forget in (False, True):
        state = lj_liquid(cells=4)
        integrator = integrator_class(0.005, tol=1e-10, linear_solver="cg")
        sim = md.Simulation(state, [LennardJones(cutoff=2.5)], integrator)
        for _ in range(20):
            if forget:
                integrator.reset()
            sim.run(1)
        runs.append((state, integrator.statistics))
    (extrapolated, fewer), (plain, more) = runs
    np.testing.assert_allclose(extrapolated.positions, plain.positions, rtol=0, atol=1e-9)
    np.testing.assert_allclose(extrapolated.velocities, plain.velocities, rtol=0, atol=1e-6)
    assert fewer["newton_iterations"] < more["newton_iterations"]
    assert fewer["linear_iterations"] < more["linear_iterations"]


@pytest.mark.parametrize("reach", [1.0, 0.5])
def test_extrapolation_weights_are_exact_for_quadratics(reach):
    """Weights for a(0), a(-1), a(-2) reproduce a(reach) for any polynomial of degree
    1 (one past step) or 2 (two)."""
    from integrators._newton import extrapolation_weights

    for n_history, coefficients in ((1, (0.3, -1.7, 0.0)), (2, (0.3, -1.7, 2.9))):

        def a(t, c=coefficients):
            return c[0] + c[1] * t + c[2] * t * t

        weights = extrapolation_weights(n_history, reach)
        assert weights[2] == 0.0 or n_history == 2
        estimate = sum(w * a(-k) for k, w in enumerate(weights))
        assert estimate == pytest.approx(a(reach), rel=1e-14, abs=1e-14)


def test_saved_predictor_history_is_checked():
    integrator = ImplicitEuler(0.005)
    assert integrator.get_state()["start_accelerations"] is None
    for bad, message in (
        (np.zeros(6), "shape"),
        (np.zeros((3, 6)), "shape"),
        (np.full((2, 6), np.nan), "finite"),
    ):
        with pytest.raises(ValueError, match=message):
            integrator.set_state({"start_accelerations": bad})
    integrator.set_state({"start_accelerations": np.ones((2, 6)), "statistics": {"steps": 4}})
    saved = integrator.get_state()
    np.testing.assert_array_equal(saved["start_accelerations"], np.ones((2, 6)))
    assert saved["statistics"]["steps"] == 4
    integrator.reset()
    assert integrator.get_state()["start_accelerations"] is None


def test_hessians_evaluated_within_a_step_reuse_the_last_ones_buffers(monkeypatch):
    """With a fresh Hessian every Newton iteration, each evaluation finds the last
    operator released by the solver (its preconditioner too), so the LJ blocks are
    written into the same buffers instead of tens of MB of new memory each time."""
    import integrators._newton as newton
    from md.forcefield import ForceField

    monkeypatch.setattr(newton, "_CHORD_REDUCTION", 0.0)  # no chord steps
    addresses = []
    evaluate = ForceField.hessian_operator

    def recorded(self, state):
        operator = evaluate(self, state)
        addresses.append(operator.terms[0].radial.__array_interface__["data"][0])
        return operator

    monkeypatch.setattr(ForceField, "hessian_operator", recorded)
    state = lj_liquid(cells=8)  # 2048 atoms: two chunks on two threads, one on one
    integrator = ImplicitEuler(0.005, tol=1e-10, linear_solver="cg")
    md.Simulation(state, [LennardJones(cutoff=2.5)], integrator).run(3)
    assert integrator.statistics["hessian_evaluations"] > integrator.statistics["steps"]
    # The reuse is opportunistic (reference counts: an operator kept alive a little
    # longer, e.g. by garbage awaiting the cycle collector in a long test session, makes
    # one evaluation allocate afresh, after which two sets of buffers may take turns), so
    # most evaluations, not all, find buffers an earlier one wrote.
    later = addresses[2:]
    reused = sum(a in addresses[1 : 2 + k] for k, a in enumerate(later))
    assert reused >= len(later) / 2, addresses


def test_cg_and_direct_solvers_agree():
    results = []
    for solver in ("direct", "cg"):
        state = lj_liquid(cells=3)
        sim = md.Simulation(
            state, [LennardJones(cutoff=2.5)], ImplicitEuler(0.005, 1e-11, linear_solver=solver)
        )
        sim.run(3)
        results.append(state)
        assert sim.integrator.statistics["linear_iterations"] >= 3
    np.testing.assert_allclose(results[0].positions, results[1].positions, atol=1e-11)
    np.testing.assert_allclose(results[0].velocities, results[1].velocities, atol=1e-8)


@pytest.mark.parametrize("integrator_class", [ImplicitEuler, ImplicitMidpoint])
def test_lj_liquid(integrator_class):
    state = lj_liquid(cells=4)
    integrator = integrator_class(dt=0.005)
    sim = md.Simulation(state, [LennardJones(cutoff=2.5)], integrator)
    energies = [sim.thermo()["total_energy"]]
    for _ in range(50):
        sim.run(1)
        energies.append(sim.thermo()["total_energy"])
    energies = np.array(energies)
    stats = integrator.statistics
    assert stats["steps"] == 50 and state.step == 50
    assert stats["newton_iterations"] / stats["steps"] <= 4
    # Momentum is conserved to solver tolerance (the CG solves are inexact).
    momentum = np.sum(state.masses[:, None] * state.velocities, axis=0)
    np.testing.assert_allclose(momentum, 0.0, atol=1e-5)
    if integrator_class is ImplicitEuler:
        # Backward Euler dissipates: the total energy falls step by step.
        assert np.all(np.diff(energies) < 0.0)
    else:
        assert np.max(np.abs(energies - energies[0])) < 1e-2 * abs(energies[0])


@pytest.mark.parametrize("chunks", [2, 3, 5])
def test_solver_vector_passes_in_chunks_equal_the_serial_ones(chunks):
    from integrators import _newton as newton

    rng = np.random.default_rng(7)
    n = 1001  # not a multiple of any chunk count
    vectors = [rng.normal(size=n) for _ in range(4)]
    masses = rng.uniform(0.5, 2.0, n)

    def run(serial, threaded, *args, mutable=()):
        """Both forms on copies of the arrays that the pass writes; their returns and
        those arrays."""
        outs = []
        for kernel, extra in ((serial, ()), (threaded, (chunks,))):
            copies = [a.copy() if k in mutable else a for k, a in enumerate(args)]
            outs.append((kernel(*copies, *extra), [copies[k] for k in mutable]))
        return outs

    def same(outs):
        (value_s, arrays_s), (value_t, arrays_t) = outs
        for a, b in zip(arrays_s, arrays_t, strict=True):
            np.testing.assert_array_equal(a, b)  # elementwise passes: no sums involved
        return value_s, value_t

    # incremental terms: kinetic sum to round-off, the largest |M^-1 grad| exactly
    s, t = same(
        run(
            newton._incremental_terms,
            newton._incremental_terms_threaded,
            vectors[0],
            vectors[1],
            masses,
            1.0 / masses,
            vectors[2],
            0.3,
            np.empty(n),
            mutable=(6,),
        )
    )
    assert t[0] == pytest.approx(s[0], rel=1e-13) and t[1] == s[1]
    s, t = same(
        run(
            newton._start_terms,
            newton._start_terms_threaded,
            vectors[0],
            vectors[1],
            1.0 / masses,
            0.1,
            0.01,
            np.empty(n),
            np.empty(n),
            np.empty(n),
            mutable=(5, 6, 7),
        )
    )
    assert t == s
    s, t = same(
        run(
            newton._cg_start,
            newton._cg_start_threaded,
            vectors[0],
            masses,
            np.empty(n),
            np.empty(n),
            np.empty(n),
            np.empty(n),
            mutable=(2, 3, 4, 5),
        )
    )
    np.testing.assert_allclose(t, s, rtol=1e-13)
    s, t = same(
        run(
            newton._cg_update,
            newton._cg_update_threaded,
            0.7,
            vectors[0],
            vectors[1],
            masses,
            vectors[2],
            vectors[3],
            np.empty(n),
            mutable=(4, 5, 6),
        )
    )
    np.testing.assert_allclose(t, s, rtol=1e-13)
    s, t = same(
        run(
            newton._add_scaled,
            newton._add_scaled_threaded,
            masses,
            vectors[0],
            0.2,
            vectors[1],
            mutable=(3,),
        )
    )
    np.testing.assert_array_equal(t[0], s[0])
    assert t[1] == pytest.approx(s[1], rel=1e-13)
    # The serial pass's own sum: the product it returns dotted with x.
    assert s[1] == pytest.approx(float(np.dot(vectors[0], s[0])), rel=1e-12)
    # A NaN in any chunk reaches the largest entry, whichever chunk it is in.
    for where in (0, n // 2, n - 1):
        forces = vectors[2].copy()
        forces[where] = np.nan
        _, largest = newton._incremental_terms_threaded(
            vectors[0], vectors[1], masses, 1.0 / masses, forces, 0.3, np.empty(n), chunks
        )
        assert np.isnan(largest)


def test_solves_with_vector_passes_on_threads_match_serial(monkeypatch):
    from integrators import _newton as newton
    from md.parallel import get_threads, max_threads, set_threads

    if max_threads() < 2:
        pytest.skip("needs 2 threads")
    monkeypatch.setattr(newton, "_MIN_CHUNK_ENTRIES", 64)  # threaded passes on a small system
    before = get_threads()
    results = []
    try:
        for threads in (1, 2):
            set_threads(threads)
            state = lj_liquid(cells=3)
            integrator = ImplicitEuler(0.005, tol=1e-10, linear_solver="cg")
            md.Simulation(state, [LennardJones(cutoff=2.5)], integrator).run(5)
            results.append(state)
    finally:
        set_threads(before)
    np.testing.assert_allclose(results[1].positions, results[0].positions, atol=1e-10)
    np.testing.assert_allclose(results[1].velocities, results[0].velocities, atol=1e-7)
