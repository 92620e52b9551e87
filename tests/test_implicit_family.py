"""BDF2, the trapezoidal rule, Gauss-Legendre 4 and XPBD: order, energy, symplecticity,
stiffness, checkpoints and refusals."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import numpy as np
import pytest
from test_checkpoint import assert_same_trajectory
from test_implicit import Tether, global_error, oscillator, oscillator_energies
from test_splitting import _jacobian, _small_cluster, _symplectic_defect

import md
from integrators import (
    BDF2,
    INTEGRATORS,
    XPBD,
    GaussLegendre4,
    ImplicitEuler,
    ImplicitMidpoint,
    Trapezoidal,
    VelocityVerlet,
    Yoshida6,
)
from integrators._newton import IncrementalSolver, new_statistics
from md.assemble import build_components
from md.checkpoint import CheckpointError, checkpoint_path, read_checkpoint, restore
from md.cli import main
from md.config import load_config
from md.polymers import single_chain
from md.studies import bond_oscillator
from potentials import FENEBonds, HarmonicBonds, LennardJones

ROOT = Path(__file__).resolve().parents[1]
STIFF = ROOT / "examples" / "implicit-stiff.toml"
NEW = (Trapezoidal, BDF2, GaussLegendre4)


# ------------------------------------------------------------------------ options


def test_registry_options_and_descriptions():
    assert INTEGRATORS["trapezoidal"] is Trapezoidal
    assert INTEGRATORS["bdf2"] is BDF2
    assert INTEGRATORS["gauss_legendre4"] is GaussLegendre4
    assert INTEGRATORS["xpbd"] is XPBD
    for cls, name in (
        (Trapezoidal, "trapezoidal"),
        (BDF2, "bdf2"),
        (GaussLegendre4, "gauss_legendre4"),
    ):
        integrator = cls(dt=0.01, tol=1e-9, max_iter=7, linear_solver="cg")
        assert integrator.describe() == {"type": name, "dt": 0.01, "tol": 1e-9, "max_iter": 7}
        assert integrator.order == (4 if cls is GaussLegendre4 else 2)
        for bad in (
            {"dt": 0.0},
            {"dt": 0.01, "tol": -1.0},
            {"dt": 0.01, "max_iter": 0},
            {"dt": 0.01, "linear_solver": "lu"},
        ):
            with pytest.raises(ValueError):
                cls(**bad)
    xpbd = XPBD(dt=0.05, iterations=7, tol=1e-6)
    assert xpbd.describe() == {"type": "xpbd", "dt": 0.05, "iterations": 7, "tol": 1e-6}
    assert XPBD(0.05, compliance=1e-4).describe()["compliance"] == 1e-4
    assert xpbd.order == 1 and xpbd.splits_forces
    for bad in (
        {"iterations": 0},
        {"tol": 0.0},
        {"compliance": 0.0},
        {"compliance": -1.0},
        {"compliance": float("inf")},
    ):
        with pytest.raises(ValueError):
            XPBD(0.05, **bad)


# -------------------------------------------------------------- order and energy


@pytest.mark.parametrize(("cls", "order"), [(Trapezoidal, 2), (BDF2, 2), (GaussLegendre4, 4)])
def test_global_order_on_the_oscillator(cls, order):
    steps = np.array([0.04, 0.02, 0.01, 0.005])
    errors = np.array([global_error(cls, dt) for dt in steps])
    slopes = np.diff(np.log(errors)) / np.diff(np.log(steps))
    assert np.all(np.abs(slopes - order) < 0.1), (slopes, errors)


@pytest.mark.slow
def test_md_integrators_measures_the_implicit_orders_from_three_points_or_more(tmp_path, capsys):
    """The issue's command on examples/integrators_lj.toml (108 atoms; ~2 CPU minutes):
    orders 1, 2, 2, 2, 4 within 0.15, each fitted from at least 3 points, and the
    figures written."""
    import csv

    names = ["implicit_euler", "implicit_midpoint", "bdf2", "trapezoidal", "gauss_legendre4"]
    out = tmp_path / "study"
    assert (
        main(
            [
                "integrators",
                str(ROOT / "examples" / "integrators_lj.toml"),
                "--integrators",
                ",".join(names),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    capsys.readouterr()
    with open(out / "integrators.csv", newline="") as handle:
        rows = {row["integrator"]: row for row in csv.DictReader(handle)}
    assert list(rows) == names
    for name, expected in zip(names, (1, 2, 2, 2, 4), strict=True):
        assert float(rows[name]["order"]) == pytest.approx(expected, abs=0.15), rows[name]
        assert int(rows[name]["fit_points"]) >= 3, rows[name]
    for figure in ("error_vs_dt.png", "work_precision.png"):
        assert (out / figure).stat().st_size > 10_000


def _lj_cluster():
    state = md.lattice("fcc", 2, density=1.0)
    state.pbc[:] = False
    state.box[:] = 50.0
    return md.maxwell_boltzmann(state, 0.3, seed=4)


def _final_positions(integrator, start, span=0.2):
    state = start.copy()
    md.Simulation(state, [LennardJones(cutoff=12.0)], integrator).run(round(span / integrator.dt))
    return state.positions


@pytest.mark.parametrize(
    ("cls", "order"),
    [(ImplicitMidpoint, 2), (Trapezoidal, 2), (BDF2, 2), (GaussLegendre4, 4)],
)
def test_global_order_on_a_lennard_jones_cluster(cls, order):
    """Nonlinear forces: every pair of successive dt gives the method's order (32 atoms,
    cutoff beyond the cluster, against Yoshida 6 at dt / 16)."""
    start = _lj_cluster()
    reference = _final_positions(Yoshida6(0.01 / 16), start)
    steps = np.array([0.01, 0.005, 0.0025])
    errors = np.array(
        [
            np.sqrt(np.mean((_final_positions(cls(dt, tol=1e-13), start) - reference) ** 2))
            for dt in steps
        ]
    )
    slopes = np.diff(np.log(errors)) / np.diff(np.log(steps))
    assert np.all(np.abs(slopes - order) < 0.15), (slopes, errors)


def _bdf2_started_by(first_step, state, forcefield, dt):
    """A BDF2 whose first step was ``first_step`` (taken on ``state``), as set_state gives it."""
    x0, v0 = state.positions.copy(), state.velocities.copy()
    first_step.step(state, forcefield)
    bdf2 = BDF2(dt, tol=first_step.tol, max_iter=first_step.max_iter)
    saved = {"last_displacement": state.positions - x0, "previous_velocities": v0}
    bdf2.set_state({"start_accelerations": None, "statistics": {}, **saved})
    return bdf2


def test_bdf2_sdirk2_start_beats_an_implicit_euler_start():
    """The docstring's justification, measured on the oscillator: with the first step
    taken by implicit Euler instead, BDF2's global error is larger at every dt (its
    O(dt^2) local error adds a second-order term of its own)."""
    for dt in (0.04, 0.02, 0.01):
        errors = []
        for euler_start in (False, True):
            state = oscillator()
            x0, v0 = state.positions.copy(), state.velocities.copy()
            forcefield = md.ForceField([Tether(1.0)])
            if euler_start:
                bdf2 = _bdf2_started_by(ImplicitEuler(dt, tol=1e-13), state, forcefield, dt)
            else:
                bdf2 = BDF2(dt, tol=1e-13)
            while state.step < round(1.0 / dt):
                bdf2.step(state, forcefield)
            t = state.time
            exact_x = x0 * np.cos(t) + v0 * np.sin(t)
            exact_v = -x0 * np.sin(t) + v0 * np.cos(t)
            errors.append(
                np.sqrt(
                    np.sum((state.positions - exact_x) ** 2 + (state.velocities - exact_v) ** 2)
                )
            )
        assert errors[0] < 0.5 * errors[1], (dt, errors)


def test_bdf2_sdirk2_start_damps_what_a_trapezoidal_start_leaves_ringing():
    """The L-stable start, measured on the stiff chain at 100 x Verlet's step: after a
    trapezoidal first step, the first BDF2 step's Newton solve does not converge; after
    the SDIRK2 start (the default), 20 steps run."""
    state, potentials, limit = _stiff_chain()
    forcefield = md.ForceField(potentials)
    bdf2 = _bdf2_started_by(Trapezoidal(100 * limit), state, forcefield, 100 * limit)
    with pytest.raises(md.ConvergenceError, match="step 2"):
        bdf2.step(state, forcefield)
    state, potentials, limit = _stiff_chain()
    bdf2 = BDF2(100 * limit)
    md.Simulation(state, potentials, bdf2).run(20)
    assert np.all(np.isfinite(state.positions))
    assert bdf2.statistics["steps"] == 20  # the start's two solves count as one step


def _bond_energy_kept(cls, omega_dt, n_steps):
    """Largest relative energy change of a zero-length harmonic bond over ``n_steps``
    (tol 1e-12), the energy sampled every tenth of the run."""
    state, potentials = bond_oscillator(omega_dt)
    state.velocities[:] = [[0.0, 0.03, 0.0], [0.0, -0.03, 0.0]]  # an ellipse, not a line
    forcefield = md.ForceField(potentials)
    integrator = cls(1.0, tol=1e-12)

    def energy():
        return forcefield.compute(state).energy + md.thermo.kinetic_energy(
            state.velocities, state.masses
        )

    start = energy()
    worst = 0.0
    for _ in range(10):
        for _ in range(n_steps // 10):
            integrator.step(state, forcefield)
        worst = max(worst, abs(energy() - start) / start)
    assert state.step == n_steps
    return worst


@pytest.mark.parametrize("cls", [Trapezoidal, GaussLegendre4])
def test_oscillator_energy_conserved_to_solver_tolerance(cls):
    """A zero-length harmonic bond at omega dt = 5 (2.5 x beyond velocity Verlet's
    limit): 1000 steps, the energy kept to 1e-11 relative (tol 1e-12)."""
    assert _bond_energy_kept(cls, 5.0, 1000) < 1e-11


@pytest.mark.slow
@pytest.mark.parametrize("cls", [Trapezoidal, GaussLegendre4])
@pytest.mark.parametrize("omega_dt", [0.5, 5.0])
def test_oscillator_energy_conserved_to_solver_tolerance_over_10_000_steps(cls, omega_dt):
    assert _bond_energy_kept(cls, omega_dt, 10_000) < 1e-10


def test_damping_methods_lose_oscillator_energy_by_their_factor():
    """BDF2's energy per step on the oscillator approaches |rho|^2 of its principal root."""
    k, dt = 1.0, 0.5
    state = oscillator()
    forcefield = md.ForceField([Tether(k)])
    integrator = BDF2(dt, tol=1e-13)
    energies = []
    for _ in range(200):
        integrator.step(state, forcefield)
        energies.append(oscillator_energies(state, k)[0])
    rho = abs(BDF2.amplification(np.sqrt(k) * dt)[0])
    # Over 100 steps the parasitic root (|rho| ~ 0.4) has died out; the energy of a
    # non-normal map still wobbles within a period, so compare over whole decades.
    ratio = (energies[-1] / energies[99]) ** (1.0 / 100)
    assert ratio == pytest.approx(rho**2, rel=1e-3)


# ------------------------------------------------------------ the shared solver


@pytest.mark.parametrize("cls", NEW)
def test_newton_methods_report_implicit_eulers_telemetry_and_agree_across_linear_solvers(cls):
    """The same counters as implicit Euler, counting real work (Hessians evaluated, linear
    iterations, more of them with an iterative solver than with LU), and the same
    trajectory from sparse LU and from the iterative solver to the Newton tolerance."""
    runs = {}
    for linear_solver in ("direct", "cg"):
        state = _lj_cluster()
        integrator = cls(0.005, tol=1e-10, linear_solver=linear_solver)
        md.Simulation(state, [LennardJones(cutoff=12.0)], integrator).run(5)
        stats = integrator.statistics
        assert set(stats) == set(ImplicitEuler(0.005).statistics), stats
        assert stats["steps"] == 5 and stats["newton_iterations"] >= 5, stats
        assert stats["hessian_evaluations"] >= 1 and stats["linear_iterations"] >= 1, stats
        runs[linear_solver] = (state, stats)
    assert runs["cg"][1]["linear_iterations"] > runs["direct"][1]["linear_iterations"]
    np.testing.assert_allclose(
        runs["cg"][0].positions, runs["direct"][0].positions, rtol=0, atol=1e-9
    )


@pytest.mark.parametrize("cls", NEW)
def test_convergence_failure_names_the_step_and_leaves_the_state(cls):
    state = _lj_cluster()
    sim = md.Simulation(state, [LennardJones(cutoff=12.0)], cls(0.005, tol=1e-10))
    sim.run(3)  # BDF2 has its history now
    integrator = cls(0.005, tol=1e-15, max_iter=1)
    integrator.set_state(sim.integrator.get_state())
    sim.integrator = integrator
    before = state.copy()
    with pytest.raises(md.ConvergenceError, match="step 4") as caught:
        sim.run(1)
    assert caught.value.step == 4 and caught.value.residual > 1e-15
    np.testing.assert_array_equal(state.positions, before.positions)
    np.testing.assert_array_equal(state.velocities, before.velocities)
    assert state.step == 3 and state.time == before.time


# ------------------------------------------------------------------ symplecticity


def test_gauss_legendre_preserves_the_symplectic_form():
    """J^T Omega J = Omega for one step on a 4-atom LJ cluster (the splittings' check),
    to the central differences' error; implicit Euler and BDF2's start fail it."""
    jacobian = _jacobian(GaussLegendre4(0.02, tol=1e-14), _small_cluster())
    assert _symplectic_defect(jacobian) < 1e-8
    assert np.linalg.det(jacobian) == pytest.approx(1.0, abs=1e-8)
    assert _symplectic_defect(_jacobian(ImplicitEuler(0.02, tol=1e-14), _small_cluster())) > 1e-4


# ---------------------------------------------------------------- stiff chains


def _stiff_chain():
    """State, potentials and velocity Verlet's linear stability limit 2 / omega_max of
    the chain of examples/implicit-stiff.toml."""
    config = load_config(STIFF)
    state, potentials, _ = build_components(config)
    return state, potentials, _verlet_limit(state, potentials)


def _verlet_limit(state, potentials):
    hessian = md.ForceField(potentials).hessian_operator(state).tocsr().toarray()
    scale = 1.0 / np.sqrt(np.repeat(state.masses, 3))
    omega_max = np.sqrt(np.linalg.eigvalsh(hessian * np.outer(scale, scale)).max())
    return 2.0 / omega_max


def test_stiff_example_is_what_it_says():
    """Bonds 1000 x the pair curvature at its range, and velocity Verlet's limit real:
    it runs at half the linear limit and blows up at 1.5 x."""
    state, potentials, limit = _stiff_chain()
    lj, springs = potentials
    sigma = 1.0
    curvature = 4.0 * (156.0 * sigma**12 / lj.cutoff**14 - 42.0 * sigma**6 / lj.cutoff**8)
    assert float(springs.k[0]) == pytest.approx(1000.0 * curvature, rel=1e-3)
    assert limit == pytest.approx(0.00458, rel=0.01)
    assert load_config(STIFF).integrator.dt == pytest.approx(100 * limit, rel=0.01)
    stable = md.Simulation(state.copy(), potentials, VelocityVerlet(0.5 * limit))
    start = stable.thermo()["total_energy"]
    stable.run(2000)
    assert abs(stable.thermo()["total_energy"] - start) < 0.02 * start
    with pytest.raises(md.SimulationError):
        md.Simulation(state.copy(), potentials, VelocityVerlet(1.5 * limit)).run(2000)


@pytest.mark.parametrize("cls", [ImplicitEuler, BDF2])
def test_damping_methods_stable_on_the_thermal_stiff_chain_at_100x_verlet(cls):
    """The chain at T = 0.5, 60 steps of 100 x Verlet's limit: no blow-up, energy never
    above its start, the bonds within 1% of their length."""
    state, potentials, limit = _stiff_chain()
    sim = md.Simulation(state, potentials, cls(100 * limit))
    start = sim.thermo()["total_energy"]
    for _ in range(6):
        sim.run(10)
        energy = sim.thermo()["total_energy"]
        assert np.isfinite(energy) and energy <= start * (1 + 1e-9)
    lengths = potentials[1].bond_lengths(state)
    np.testing.assert_allclose(lengths, 1.2, rtol=0.01)
    assert energy < 0.5 * start  # the bond vibrations were damped


def _linear_chain(n_beads=16, k=57150.0):
    """A chain on zero-length springs (exactly linear forces), stretched and moving."""
    rng = np.random.default_rng(2)
    positions = np.zeros((n_beads, 3))
    positions[:, 0] = 0.05 * np.arange(n_beads)
    state = md.State(
        positions=positions + rng.normal(scale=0.01, size=positions.shape),
        velocities=rng.normal(scale=0.3, size=positions.shape),
        box=[50.0] * 3,
        pbc=False,
    )
    bonds = np.column_stack([np.arange(n_beads - 1), np.arange(1, n_beads)])
    return state, [HarmonicBonds(bonds, k=k, r0=0.0)]


@pytest.mark.parametrize(
    "cls", [ImplicitMidpoint, Trapezoidal, GaussLegendre4, ImplicitEuler, BDF2, XPBD]
)
def test_every_implicit_method_stable_on_a_linear_stiff_chain_at_100x_verlet(cls):
    """Linear stiff forces, where A-stability is the whole story: at 100 x Verlet's limit
    the non-damping methods keep the energy (to 1e-9), the damping ones lose it."""
    state, potentials = _linear_chain()
    limit = _verlet_limit(state, potentials)
    verlet = md.Simulation(state.copy(), potentials, VelocityVerlet(1.05 * limit))
    energy = verlet.thermo()["total_energy"]
    verlet.run(500)  # its fastest mode grows 1.9-fold a step
    assert verlet.thermo()["total_energy"] > 1e10 * energy
    integrator = cls(100 * limit) if cls is XPBD else cls(100 * limit, tol=1e-10)
    sim = md.Simulation(state, potentials, integrator)
    start = sim.thermo()["total_energy"]
    sim.run(100)
    energy = sim.thermo()["total_energy"]
    if cls in (ImplicitMidpoint, Trapezoidal, GaussLegendre4):
        assert energy == pytest.approx(start, rel=1e-9)
    else:
        assert energy < 0.1 * start


@pytest.mark.slow
@pytest.mark.parametrize("cls", [ImplicitMidpoint, Trapezoidal, GaussLegendre4, XPBD])
def test_where_the_thermal_stiff_chain_defeats_a_method_at_100x_verlet(cls):
    """The limits the guide states, measured on the thermal stiff chain at 100 x Verlet's
    limit. Its bonds turn ~0.3 rad in a step: the methods that keep a linear
    oscillator's energy pump energy into the stiff bonds (Simo and Tarnow 1992), or
    their Newton solves stop converging. XPBD's pair forces are explicit, and two beads
    that touch (the WCA wall, omega dt ~ 5 at this step) blow it up."""
    state, potentials, limit = _stiff_chain()
    integrator = cls(100 * limit) if cls is XPBD else cls(100 * limit, max_iter=200)
    sim = md.Simulation(state, potentials, integrator)
    start = sim.thermo()["total_energy"]
    try:
        sim.run(60)
    except (md.ConvergenceError, md.SimulationError):
        return
    assert sim.thermo()["total_energy"] > 10 * start


# ------------------------------------------------------------------------- XPBD


def _bonded_chain(potential, n_beads=12, seed=1):
    state, bonds = single_chain(n_beads, bond_length=1.0, seed=seed)
    md.maxwell_boltzmann(state, 1.0, seed=seed)
    return state, potential(bonds)


BOND_LAWS = {
    "spring": lambda b: HarmonicBonds(b, k=500.0, r0=1.0),
    "fene": lambda b: FENEBonds(b, k=30.0, r_max=1.5),
}


def _collinear_chain(n_beads=10, seed=3):
    """A chain along x moving along x: its bonds never turn."""
    rng = np.random.default_rng(seed)
    positions = np.zeros((n_beads, 3))
    positions[:, 0] = np.arange(n_beads) + rng.normal(scale=0.05, size=n_beads)
    velocities = np.zeros((n_beads, 3))
    velocities[:, 0] = rng.normal(scale=1.0, size=n_beads)
    state = md.State(positions=positions, velocities=velocities, box=[100.0] * 3, pbc=False)
    return state, np.column_stack([np.arange(n_beads - 1), np.arange(1, n_beads)])


@pytest.mark.parametrize("law", sorted(BOND_LAWS))
def test_converged_xpbd_on_bonds_that_do_not_turn_is_implicit_euler(law):
    """Bonds that keep their direction: converged sweeps give implicit Euler's trajectory
    (each bond's equation lambda + dt^2 U'(r) = 0 is implicit Euler's along that line)."""
    runs = []
    for integrator in (XPBD(0.02, iterations=5000, tol=1e-14), ImplicitEuler(0.02, tol=1e-13)):
        state, bonds = _collinear_chain()
        md.Simulation(state, [BOND_LAWS[law](bonds)], integrator).run(20)
        runs.append(state)
    np.testing.assert_allclose(runs[0].positions, runs[1].positions, rtol=0, atol=1e-11)
    np.testing.assert_allclose(runs[0].velocities, runs[1].velocities, rtol=0, atol=1e-9)


@pytest.mark.parametrize("law", sorted(BOND_LAWS))
def test_converged_xpbd_on_turning_bonds_differs_from_implicit_euler_beyond_first_order(law):
    """Bonds that turn: XPBD moves each bond's atoms along its direction at the moment of
    its update (it leaves out the geometric stiffness, Macklin et al. 2016 eq. 11), so
    one step differs from implicit Euler's, but by O(dt^3) or less (measured: ~dt^4 for
    FENE, ~dt^5 for springs), below both methods' O(dt^2) local error."""
    differences = []
    for dt in (0.02, 0.01):
        ends = []
        for integrator in (XPBD(dt, iterations=5000, tol=1e-14), ImplicitEuler(dt, tol=1e-13)):
            state, potential = _bonded_chain(BOND_LAWS[law])
            integrator.step(state, md.ForceField([potential]))
            ends.append(state.positions)
        differences.append(np.abs(ends[0] - ends[1]).max())
    assert differences[1] > 0.0
    assert np.log2(differences[0] / differences[1]) > 3.0, differences


def test_xpbd_takes_pair_forces_explicitly_and_keeps_momentum():
    """One step is x~ = x + dt v + dt^2 a_pair(x), then implicit Euler on the bonds from
    x~ (the incremental solver with velocity v + dt a_pair; exact for a chain whose bonds
    keep their direction); linear momentum is kept to round-off over many steps of a
    turning chain."""
    dt = 0.01
    state, bonds = _collinear_chain()
    state.positions[:, 0] *= 1.3  # pairs within the LJ range: attractions act
    springs, lj = HarmonicBonds(bonds, k=2000.0, r0=1.3), LennardJones(cutoff=2.5)
    expected = state.copy()
    pair = md.ForceField([lj]).compute(expected).forces / expected.masses[:, None]
    assert np.abs(pair).max() > 0.1
    solver = IncrementalSolver(1e-13, 50, "direct", new_statistics())
    displacement = solver.solve(
        expected, md.ForceField([springs]), dt, "check", velocities=expected.velocities + dt * pair
    )
    md.Simulation(state, [lj, springs], XPBD(dt, iterations=5000, tol=1e-14)).run(1)
    np.testing.assert_allclose(state.positions, expected.positions, rtol=0, atol=1e-12)
    np.testing.assert_allclose(state.velocities, displacement / dt, rtol=0, atol=1e-9)

    state, springs = _bonded_chain(lambda b: HarmonicBonds(b, k=2000.0, r0=1.0), n_beads=16)
    xpbd = XPBD(dt)
    sim = md.Simulation(state, [lj, springs], xpbd)
    momentum = np.sum(state.masses[:, None] * state.velocities, axis=0)
    sim.run(300)
    after = np.sum(state.masses[:, None] * state.velocities, axis=0)
    np.testing.assert_allclose(after, momentum, rtol=0, atol=1e-12)
    stats = xpbd.statistics
    assert stats["steps"] == 300 and stats["sweeps"] >= 300


def test_xpbd_kernel_runs_as_python():
    """The sweeps kernel under NUMBA_DISABLE_JIT (its Python function) gives the compiled
    kernel's result: harmonic and FENE bonds across a periodic boundary."""
    from integrators.xpbd import _xpbd_sweeps

    rng = np.random.default_rng(7)
    n = 12
    positions = np.zeros((n, 3))
    positions[:, 0] = np.arange(n) * 0.9 - 1.0  # the chain crosses x = 0 of a 10-wide box
    positions += rng.normal(scale=0.1, size=positions.shape)
    positions %= 10.0
    bonds = np.column_stack([np.arange(n - 1), np.arange(1, n)]).astype(np.int64)
    forms = (np.arange(n - 1) % 2).astype(np.int64)  # harmonic, FENE, harmonic, ...
    stiffness = np.where(forms == 0, 500.0, 30.0)
    rest = np.where(forms == 0, 1.0, 1.5)
    lengths, inverse = np.full(3, 10.0), np.full(3, 0.1)
    results = []
    for kernel in (_xpbd_sweeps, _xpbd_sweeps.py_func):
        moved, displacement = positions.copy(), np.zeros_like(positions)
        multipliers = np.zeros(n - 1)
        out = kernel(
            moved,
            displacement,
            np.ones(n),
            lengths,
            inverse,
            np.zeros(3),
            bonds,
            forms,
            stiffness,
            rest,
            0.01**2,
            multipliers,
            40,
            1e-12,
        )
        results.append((out, moved, displacement, multipliers))
    (compiled, *arrays), (python, *python_arrays) = results
    assert compiled[0] == python[0] and compiled[2] == python[2] == 0
    assert compiled[1] == pytest.approx(python[1], rel=1e-9, abs=1e-15)
    assert np.abs(arrays[1]).max() > 1e-3  # the sweeps did move the atoms
    for a, b in zip(arrays, python_arrays, strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)


def test_xpbd_compliance_replaces_the_spring_constant():
    runs = []
    for k, compliance in ((500.0, 1.0 / 2000.0), (2000.0, None)):
        state, springs = _bonded_chain(lambda b, k=k: HarmonicBonds(b, k=k, r0=1.0))
        md.Simulation(state, [springs], XPBD(0.02, compliance=compliance)).run(10)
        runs.append(state.positions)
    np.testing.assert_array_equal(runs[0], runs[1])


def test_xpbd_with_few_sweeps_counts_its_unconverged_steps():
    state, potentials, limit = _stiff_chain()
    xpbd = XPBD(100 * limit, iterations=3)
    md.Simulation(state, potentials, xpbd).run(5)
    assert xpbd.statistics["unconverged_steps"] == 5
    assert xpbd.statistics["sweeps"] == 15
    assert np.all(np.isfinite(state.positions))


def test_xpbd_without_bonds_is_refused_by_name():
    state = md.lattice("fcc", 3, density=0.8)
    sim = md.Simulation(state, [LennardJones(cutoff=2.5)], XPBD(0.005))
    with pytest.raises(ValueError, match="xpbd found no bonds"):
        sim.run(1)


# ------------------------------------------------------------------ checkpoints

XPBD_CONFIG = """\
units = "lj"
seed = 4

[system]
polymer = "chain"
chain_length = 16
bond_length = 1.2
temperature = 0.5

[[potentials]]
type = "lj"
cutoff = 1.122462048309373
cutoff_mode = "shift"

[[potentials]]
type = "spring"
bonds = "system"
k = 5000.0
r0 = 1.2

[integrator]
{integrator}

[run]
steps = 60
thermo_every = 10
skin = 1.0

[output]
path = "out.h5"
every = 10
velocities = true
checkpoint_every = 20
"""


def _run(*args) -> int:
    return main(["run", *map(str, args), "--no-progress", "-q"])


@pytest.mark.parametrize(
    "integrator",
    [
        'type = "xpbd"\ndt = 0.02\niterations = 10',
        'type = "bdf2"\ndt = 0.02\ntol = 1e-8',
        'type = "gauss_legendre4"\ndt = 0.02\ntol = 1e-8',
        'type = "trapezoidal"\ndt = 0.02\ntol = 1e-8',
    ],
)
def test_resume_on_a_bonded_chain_is_bitwise_identical(tmp_path, monkeypatch, integrator):
    """Stop at 20, resume to 40, lose the tail after the step-20 checkpoint, resume to 60:
    the same trajectory, bit for bit, as the run in one go (BDF2's last displacement and
    velocities, the predictors' accelerations and the counters are in the checkpoint)."""
    monkeypatch.chdir(tmp_path)
    config = tmp_path / "run.toml"
    config.write_text(XPBD_CONFIG.format(integrator=integrator))
    assert _run(config, "-o", "full.h5") == 0
    assert _run(config, "-o", "cut.h5", "--steps", "20") == 0
    shutil.copy(checkpoint_path("cut.h5"), tmp_path / "at_20.ckpt")
    assert _run(config, "-o", "cut.h5", "--steps", "40", "--resume") == 0
    shutil.copy(tmp_path / "at_20.ckpt", checkpoint_path("cut.h5"))
    assert _run(config, "-o", "cut.h5", "--resume") == 0
    assert_same_trajectory("full.h5", "cut.h5")
    full, cut = (read_checkpoint(checkpoint_path(p)) for p in ("full.h5", "cut.h5"))
    assert repr(full.integrator_state) == repr(cut.integrator_state)


# -------------------------------------------------------------------- bad input


#: The config reader's refusal (md.schema checks the declared key before XPBD sees it).
COMPLIANCE_REFUSED = "[integrator] compliance: must be positive"


def _digests(folder: Path) -> dict:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in folder.iterdir()}


@pytest.mark.parametrize(
    ("integrator", "potentials", "message"),
    [
        ('type = "xpbd"\ndt = 0.02\ncompliance = 0.0', "bonds", COMPLIANCE_REFUSED),
        ('type = "xpbd"\ndt = 0.02\ncompliance = -1e-4', "bonds", COMPLIANCE_REFUSED),
        ('type = "xpbd"\ndt = 0.02', "lj only", "xpbd found no bonds"),
    ],
)
def test_bad_xpbd_input_exits_2_and_writes_nothing(
    tmp_path, monkeypatch, capsys, integrator, potentials, message
):
    monkeypatch.chdir(tmp_path)
    text = XPBD_CONFIG.format(integrator=integrator)
    if potentials == "lj only":
        text = text.replace(
            '[[potentials]]\ntype = "spring"\nbonds = "system"\nk = 5000.0\nr0 = 1.2\n', ""
        )
    (tmp_path / "run.toml").write_text(text)
    before = _digests(tmp_path)
    assert _run("run.toml") == 2
    err = capsys.readouterr().err
    assert message in err and "run.toml" in err, err
    assert _digests(tmp_path) == before  # nothing written


def test_bdf2_resumed_from_another_integrators_checkpoint_is_refused(tmp_path, monkeypatch, capsys):
    """From the CLI (exit 2, nothing touched), from Python (CheckpointError), and by BDF2's
    own set_state (a ValueError naming the missing history)."""
    monkeypatch.chdir(tmp_path)
    config = tmp_path / "run.toml"
    config.write_text(XPBD_CONFIG.format(integrator='type = "implicit_euler"\ndt = 0.02'))
    assert _run(config, "--steps", "20") == 0
    config.write_text(XPBD_CONFIG.format(integrator='type = "bdf2"\ndt = 0.02'))
    before = _digests(tmp_path)
    capsys.readouterr()
    assert _run(config, "--steps", "40", "--resume") == 2
    err = capsys.readouterr().err
    assert "integrator" in err and "bdf2" in err and "implicit_euler" in err, err
    assert _digests(tmp_path) == before

    saved = read_checkpoint(checkpoint_path("out.h5"))
    with pytest.raises(CheckpointError, match="implicit_euler"):
        restore(saved, BDF2(0.02))
    with pytest.raises(ValueError, match="not a BDF2 state.*last_displacement"):
        BDF2(0.02).set_state(saved.integrator_state)
