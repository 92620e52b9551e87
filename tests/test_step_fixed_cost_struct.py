"""Issue 69, the serial step's fixed cost: velocity Verlet's step in one compiled call, and
the ASE calculator's call with less Python around its force field.

While the exact list holds, a velocity Verlet step of one pair potential is one compiled
call (``ForceField.verlet_step``: the kicks, the drift, the list's half-skin check and the
pair forces, the template's ``frame_verlet``, the frame's arrays in one StructRef); a step
whose check asks for a rebuild builds the list after the drift and runs its second half as
a second such call; an observer's virial step or a value that is not finite take the
general path. What is tested: that the fused calls are what run (the separate kick, drift
and force kernels are not called), that they give the general path's numbers to the bit
(trajectories, list builds, the force cache, errors), and that the calculator's shorter
call gives a fresh calculator's results. No timings: those are
``benchmarks/small_boxes.py``'s."""

from __future__ import annotations

import sys
from collections import Counter

import numpy as np
import pytest
from ase.build import bulk

import md
from integrators import VelocityVerlet
from md.calculator import MDCalculator
from md.errors import SimulationError
from potentials import LennardJones

DT = 0.005
SKIN = 0.3


def melt(cells: int, seed: int = 11) -> md.State:
    """The LJ melt of benchmarks/small_boxes.py (fcc at rho* 0.8442, T* 3), unequal masses
    (1/m not exact in binary)."""
    state = md.maxwell_boltzmann(md.lattice("fcc", cells, density=0.8442), 3.0, seed=seed)
    state.masses = 1.0 + 0.37 * (np.arange(state.n_atoms) % 3)
    return state


def simulation(cells: int, fused: bool = True) -> md.Simulation:
    sim = md.Simulation(
        melt(cells), [LennardJones(cutoff=2.5, cutoff_mode="none")], VelocityVerlet(dt=DT), SKIN
    )
    if not fused:  # the general path: kicks, compute (list check, pair kernel), kick
        sim.forcefield.verlet_step = lambda *args: 0
    return sim


def profiled(action, repeats: int) -> Counter:
    """Python calls (numba dispatchers' included) during ``repeats`` calls of ``action``,
    by function name, and their total under ``"calls"``."""
    counts = Counter()

    def profile(frame, event, arg):
        if event == "call":
            counts[frame.f_code.co_name] += 1
            counts["calls"] += 1

    sys.setprofile(profile)
    try:
        for _ in range(repeats):
            action()
    finally:
        sys.setprofile(None)
    return counts


# ------------------------------------------------------------------- the fused step
@pytest.mark.parametrize("cells", [3, 5])  # 108 atoms (small-box list), 500 (cell search)
def test_a_verlet_step_is_one_compiled_call_while_the_list_holds(cells):
    """Over 100 steps with list builds among them, a step is one fused call (the kicks
    and drift, the list's check, the forces), two on the steps whose check asked for a
    rebuild (its second half after the build); the separate kick, drift and pair kernels
    are not called. A step that keeps its list made 18 Python calls before (numba's
    dispatchers included), 14 now."""
    sim = simulation(cells)
    sim.run(20)
    nl = sim.forcefield.neighbor_list
    builds, evaluations = nl.n_builds, sim.forcefield.n_evaluations
    counts, plain = Counter(), []
    for _ in range(100):
        before = nl.n_builds
        step = profiled(lambda: sim.run(1), 1)
        counts += step
        if nl.n_builds == before:
            plain.append(step["calls"])
    rebuilt = nl.n_builds - builds
    assert rebuilt > 5
    assert sim.forcefield.n_evaluations - evaluations == 100  # one evaluation a step
    fused = sum(n for name, n in counts.items() if name.startswith("frame_verlet__"))
    general = sum(n for name, n in counts.items() if name.startswith("frame_forces__"))
    assert fused == 100 + rebuilt
    assert general == 0
    assert counts["kick_drift_by_mass"] == counts["kick_by_mass"] == 0
    assert len(plain) == 100 - rebuilt
    assert max(plain) <= 15


@pytest.mark.parametrize("cells", [3, 4, 5])  # 108, 256, 500 atoms
def test_the_fused_step_is_the_general_paths_bit_for_bit(cells):
    """300 steps of the fused and of the general path, with virial steps (an observer
    every 25 steps) and builds among them: the same positions, velocities, list builds,
    energies and evaluation counts, to the bit."""
    runs = []
    for fused in (True, False):
        sim = simulation(cells, fused)
        energies = []
        sim.attach(lambda s, e=energies: e.append(s.thermo()["total_energy"]), 25)
        sim.run(300)
        runs.append((sim, energies))
    (fast, fast_energies), (general, general_energies) = runs
    assert fast.forcefield.neighbor_list.n_builds > 20
    assert fast.forcefield.neighbor_list.n_builds == general.forcefield.neighbor_list.n_builds
    assert fast.forcefield.n_evaluations == general.forcefield.n_evaluations
    assert np.array_equal(fast.state.positions, general.state.positions)
    assert np.array_equal(fast.state.velocities, general.state.velocities)
    assert fast_energies == general_energies


def test_the_fused_step_leaves_the_force_cache_a_compute_would():
    """After a fused step the force field serves the step's forces from its cache (no
    second evaluation), and they are a fresh force field's at those positions."""
    sim = simulation(4)
    sim.run(30)
    forcefield = sim.forcefield
    evaluations = forcefield.n_evaluations
    state = sim.state
    assert forcefield.verlet_step(state, 0.0, 0.0) == 2
    served = forcefield.compute(state, virial=False)
    assert forcefield.n_evaluations == evaluations + 1
    fresh = md.ForceField([LennardJones(cutoff=2.5, cutoff_mode="none")], skin=SKIN)
    expected = fresh.compute(state.copy(), virial=False)
    np.testing.assert_allclose(served.forces, expected.forces, rtol=0, atol=1e-12)
    assert served.energy == pytest.approx(expected.energy, rel=1e-14)


def test_the_fused_step_is_not_used_where_it_does_not_apply():
    """An observer's virial step, positions changed since the cached forces, and a list
    looked at only every few steps take the general path (verlet_step says 0 and does
    nothing)."""
    sim = simulation(3)
    sim.run(5)
    forcefield, state = sim.forcefield, sim.state
    before = state.positions.copy()
    forcefield.virial_wanted = True
    assert forcefield.verlet_step(state, 0.5 * DT, DT) == 0
    forcefield.virial_wanted = False
    assert np.array_equal(state.positions, before)
    state.positions[3, 0] += 1e-9  # the cached forces are not this state's
    assert forcefield.verlet_step(state, 0.5 * DT, DT) == 0
    assert state.positions[3, 0] == before[3, 0] + 1e-9
    every = md.Simulation(
        melt(3), [LennardJones(cutoff=2.5)], VelocityVerlet(dt=DT), SKIN, neighbor_every=2
    )
    every.run(5)
    assert every.forcefield.verlet_step(every.state, 0.5 * DT, DT) == 0


def overlap(sim: md.Simulation) -> None:
    """Two atoms on one place, at rest, the list built there: no atom moves, the forces
    are not finite."""
    state = sim.state
    state.positions[1] = state.positions[0]
    state.velocities[:] = 0.0
    sim.forcefield.neighbor_list.build(state)


def not_a_number(sim: md.Simulation) -> None:
    """A velocity that is not a number: the drift makes a position NaN."""
    sim.state.velocities[7, 2] = np.nan


@pytest.mark.parametrize("fused", [True, False])
@pytest.mark.parametrize("spoil", [overlap, not_a_number])
def test_a_non_finite_value_in_a_fused_step_is_the_general_paths_error(spoil, fused):
    """Forces that are not finite (the fused call's second half refuses to kick) or a
    position that is not (the list's check refuses it, the list's update says what):
    both paths stop with the same SimulationError at the same step and leave the same
    positions and velocities."""
    runs = []
    for path in (fused, False):
        sim = simulation(3, path)
        sim.run(5)
        spoil(sim)
        with pytest.raises(SimulationError) as raised:
            sim.run(3)
        runs.append((sim.state, raised.value))
    (state, error), (reference, expected) = runs
    assert error.step == expected.step == 6
    assert str(error) == str(expected)
    assert np.array_equal(state.positions, reference.positions, equal_nan=True)
    assert np.array_equal(state.velocities, reference.velocities, equal_nan=True)


# ----------------------------------------------------------------- the ASE calculator
def argon(cells: int) -> object:
    atoms = bulk("Ar", "fcc", a=5.26, cubic=True).repeat(cells)
    atoms.rattle(0.05, seed=3)
    return atoms


def calculator() -> MDCalculator:
    return MDCalculator([LennardJones(epsilon=0.0104, sigma=3.4, cutoff=8.5)], skin=0.5)


@pytest.mark.parametrize("cells", [2, 4])  # a 2x2x2 supercell inside (32 atoms), none (256)
def test_an_ase_call_makes_fewer_python_calls(cells):
    """An energy + forces pair of calls after a move (setting the positions included)
    made 57 Python calls before (the comparisons of the atoms made afresh at each call,
    the State brought up to the held copy by a second comparison of its cell), 34 now."""
    atoms = argon(cells)
    atoms.calc = calculator()
    atoms.get_forces()
    rng = np.random.default_rng(2)
    start = atoms.positions.copy()
    moves = iter([rng.uniform(-0.01, 0.01, size=start.shape) for _ in range(25)])

    def call():
        atoms.positions = start + next(moves)
        atoms.get_potential_energy()
        atoms.get_forces()

    for _ in range(5):
        call()
    assert profiled(call, 20)["calls"] / 20 <= 42


@pytest.mark.parametrize("cells", [2, 4])
def test_an_ase_call_after_a_move_is_a_fresh_calculators(cells):
    """Moves served by the short way (the supercell's copies written by one compiled
    pass, the State's cell taken as the held copy's): a fresh calculator's energy, forces
    and stress (to round-off: its list, built at these positions, sums in another
    order)."""
    atoms = argon(cells)
    atoms.calc = calculator()
    atoms.get_forces()
    rng = np.random.default_rng(5)
    for _ in range(4):
        atoms.positions += rng.uniform(-0.05, 0.05, size=atoms.positions.shape)
        energy, forces = atoms.get_potential_energy(), atoms.get_forces()
        stress = atoms.get_stress()
        fresh = atoms.copy()
        fresh.calc = calculator()
        assert energy == pytest.approx(fresh.get_potential_energy(), rel=1e-13)
        np.testing.assert_allclose(forces, fresh.get_forces(), rtol=0, atol=1e-13)
        np.testing.assert_allclose(stress, fresh.get_stress(), rtol=0, atol=1e-15)


def test_the_supercells_copies_are_numpys_broadcast_sum_bit_for_bit():
    """The compiled pass that writes a small cell's copies into the State adds each
    copy's shift as numpy's broadcast sum did (the positions of the old way, to the bit,
    -0.0 included)."""
    from md.calculator import _tile_into

    rng = np.random.default_rng(8)
    positions = rng.uniform(-3.0, 20.0, size=(37, 3))
    positions[4, 1] = -0.0
    shifts = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 10.1], [0.0, 7.3, 0.0], [5.2, 7.3, 10.1]])
    out = np.empty((4 * 37, 3))
    _tile_into(positions, shifts, out)
    expected = (positions[None, :, :] + shifts[:, None, :]).reshape(-1, 3)
    assert out.tobytes() == expected.tobytes()


def test_an_ase_call_sees_a_change_made_in_place_after_the_short_way():
    """The held copy's side of the comparison is made once: a change of the caller's
    numbers, charges or pbc made in place afterwards is still a change (ASE's way: a new
    copy, a fresh calculator's results)."""
    atoms = argon(2)
    atoms.calc = calculator()
    atoms.get_forces()
    atoms.positions[3] += 0.02
    atoms.get_forces()
    held = atoms.calc.atoms
    for change in (
        lambda: atoms.set_initial_charges(np.full(len(atoms), 0.2)),
        lambda: atoms.arrays["numbers"].__setitem__(0, 36),  # Kr: a second type
        lambda: atoms.pbc.__setitem__(2, False),
    ):
        atoms.positions[5] += 0.01
        change()
        forces = atoms.get_forces()
        fresh = atoms.copy()
        fresh.calc = calculator()
        assert np.array_equal(forces, fresh.get_forces())
        assert np.array_equal(atoms.calc.atoms.pbc, atoms.pbc)
    assert atoms.calc.atoms is not held
