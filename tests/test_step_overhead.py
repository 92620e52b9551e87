"""Issue 69, the serial step: what a step and an ASE call do besides their kernels.

A small box's step is tens of microseconds, so the Python around its kernels (finding the
kernel again, the force cache's key, the list's check, ASE's copies) is a large part of
it. What is tested here: the work that was removed stays removed (Python calls per step,
no copy of the atoms per ASE call, one slot frame per list), and the shortcuts that
replaced it give the numbers of the general path, bit for bit (trajectories, the steps
the list is rebuilt on, the force cache, the calculator's results). No timings: those
are ``benchmarks/small_boxes.py``'s.
"""

from __future__ import annotations

import sys
from collections import Counter

import ase
import numpy as np
import pytest
from ase.build import bulk

import md
from integrators import Langevin, Leapfrog, VelocityVerlet
from md.calculator import MDCalculator
from md.neighbors import NeighborList
from potentials import LennardJones

DT = 0.005
SKIN = 0.3


def melt(cells: int, seed: int = 5) -> md.State:
    """The LJ melt of benchmarks/small_boxes.py: fcc at rho* 0.8442, T* 3."""
    return md.maxwell_boltzmann(md.lattice("fcc", cells, density=0.8442), 3.0, seed=seed)


def lj() -> LennardJones:
    return LennardJones(cutoff=2.5, cutoff_mode="none")


INTEGRATORS = {
    "verlet": lambda: VelocityVerlet(dt=DT),
    "leapfrog": lambda: Leapfrog(dt=DT),
    "langevin": lambda: Langevin(dt=DT, temperature=1.5, friction=1.0, seed=3),
}


def python_calls(action, repeats: int) -> float:
    """Python function calls (profile "call" events, numba dispatchers' included) per call
    of ``action``."""
    counts = Counter()

    def profile(frame, event, arg):
        counts[event] += 1

    sys.setprofile(profile)
    try:
        for _ in range(repeats):
            action()
    finally:
        sys.setprofile(None)
    return counts["call"] / repeats


class Copying:
    """A potential that hands its inner one a copy of the State at every call: new
    position and type arrays each time, so no call is served by what the last one set
    up (the general path of the pair frame)."""

    def __init__(self, inner) -> None:
        self.inner = inner
        self.cutoff = inner.cutoff

    def check(self, state) -> None:
        self.inner.check(state)

    def energy_forces(self, state, neighbors, per_atom=False, virial=True):
        return self.inner.energy_forces(state.copy(), neighbors, per_atom, virial=virial)


# ------------------------------------------------------------------ the step's Python
@pytest.mark.parametrize(("name", "most"), [("verlet", 50), ("leapfrog", 60)])
def test_a_step_of_a_small_box_makes_few_python_calls(name, most):
    """A step of the 108-atom melt, averaged over 100 steps (13 list builds among them),
    made 73 Python calls (velocity Verlet; leapfrog 80) before issue 69's work and 29
    (39) after: the pair kernel's call set up once per list, the force cache keyed by
    bytes, the list's check direct."""
    sim = md.Simulation(melt(3), [lj()], INTEGRATORS[name](), skin=SKIN)
    sim.run(20)
    builds = sim.forcefield.neighbor_list.n_builds
    calls = python_calls(lambda: sim.run(1), 100)
    assert sim.forcefield.neighbor_list.n_builds > builds  # builds counted in the average
    assert calls <= most


# ------------------------------------------------------------- the same numbers
@pytest.mark.parametrize("cells", [3, 5])  # 108 atoms (no cell search), 500 (cells)
@pytest.mark.parametrize("name", sorted(INTEGRATORS))
def test_the_trajectory_is_the_general_paths_bit_for_bit(cells, name):
    """The pair frame's kept call (kernel, arguments) against a potential that is never
    served by it, for 150 steps with list builds among them: the same positions and
    velocities to the bit."""
    runs = []
    for potential in (lj(), Copying(lj())):
        sim = md.Simulation(melt(cells), [potential], INTEGRATORS[name](), skin=SKIN)
        sim.attach(lambda s: s.thermo(), 25)  # virial steps among the others
        sim.run(150)
        runs.append(sim)
    fast, general = runs
    assert fast.forcefield.neighbor_list.n_builds > 5
    assert fast.forcefield.neighbor_list.n_builds == general.forcefield.neighbor_list.n_builds
    assert np.array_equal(fast.state.positions, general.state.positions)
    assert np.array_equal(fast.state.velocities, general.state.velocities)
    assert fast.thermo()["potential_energy"] == general.thermo()["potential_energy"]


@pytest.mark.parametrize("cells", [3, 5])
def test_the_list_is_rebuilt_on_exactly_the_steps_the_half_skin_rule_names(cells):
    """After every step, the list was rebuilt if and only if an atom had moved more than
    skin / 2 from its place at the previous build (numpy's own measure here)."""
    sim = md.Simulation(melt(cells), [lj()], VelocityVerlet(dt=DT), skin=SKIN)
    sim.run(1)
    nl = sim.forcefield.neighbor_list
    reference, builds, rebuilt_steps = nl.reference_positions, nl.n_builds, []
    for _ in range(120):
        sim.run(1)
        moved = np.max(np.sum((sim.state.positions - reference) ** 2, axis=1))
        rebuilt = nl.n_builds > builds
        assert rebuilt == (moved > (0.5 * SKIN) ** 2), sim.state.step
        if rebuilt:
            reference, builds = nl.reference_positions, nl.n_builds
            rebuilt_steps.append(sim.state.step)
            assert np.array_equal(reference, sim.state.positions)
    assert len(rebuilt_steps) > 5


def test_the_slot_frame_is_kept_until_the_list_changes():
    """One SlotFrame per list (it was made afresh at every evaluation): the same object
    while the list holds, a new one after a build and after the list followed a cell
    change, each with the list's arrays of the moment."""
    state = melt(5)
    nl = NeighborList(2.5, SKIN)
    nl.update(state)
    frame = nl.frame
    assert nl.frame is frame
    state.positions += 0.01  # within the skin: no rebuild
    assert not nl.update(state)
    assert nl.frame is frame
    nl.build(state)
    rebuilt = nl.frame
    assert rebuilt is not frame
    assert rebuilt.starts is nl.slot_starts and rebuilt.order is nl.order
    scale = 1.0005  # a barostat's small move: the list follows the cell
    state.box *= scale
    state.positions *= scale
    assert not nl.update(state)
    assert nl.n_followed == 1
    followed = nl.frame
    assert followed is not rebuilt
    assert np.array_equal(followed.lengths, state.box)
    assert nl.frame is followed


@pytest.mark.parametrize("cells", [3, 7])  # 108 atoms (key as bytes), 1372 (as arrays)
def test_the_force_cache_sees_every_change_made_in_place(cells):
    """The force cache's key (bytes of positions and types for a small system, copies
    of them for a larger one) catches a change of one coordinate's last bit, of the
    box, the tilt, pbc and a type, each made in place, and serves the same values."""
    state = melt(cells)
    state.types[:] = np.arange(state.n_atoms) % 2
    state.type_names = ("A", "B")
    potential = LennardJones(epsilon=[1.0, 0.9], sigma=[1.0, 0.95], cutoff=2.5)
    forcefield = md.ForceField([potential], skin=SKIN)
    first = forcefield.compute(state, virial=False)
    assert forcefield.compute(state, virial=False) is first
    evaluations = forcefield.n_evaluations
    changes = [
        lambda: state.positions.__setitem__((7, 1), np.nextafter(state.positions[7, 1], 9.0)),
        lambda: state.box.__setitem__(2, state.box[2] * (1 + 1e-12)),
        lambda: state.tilt.__setitem__(0, -0.0),  # the same value in other bits
        lambda: state.types.__setitem__(3, 1 - state.types[3]),
        lambda: state.pbc.__setitem__(2, False),
    ]
    for change in changes:
        change()
        result = forcefield.compute(state, virial=False)
        evaluations += 1
        assert forcefield.n_evaluations == evaluations
        fresh = md.ForceField([potential], skin=SKIN).compute(state.copy(), virial=False)
        np.testing.assert_allclose(result.forces, fresh.forces, rtol=0, atol=1e-11)
        assert forcefield.compute(state, virial=False) is result  # then cached again
    assert forcefield.n_evaluations == evaluations


# ----------------------------------------------------------------- the ASE calculator
def argon(cells: int = 3) -> ase.Atoms:
    atoms = bulk("Ar", "fcc", a=5.26, cubic=True).repeat(cells)
    atoms.rattle(0.05, seed=1)
    return atoms


def calculator() -> MDCalculator:
    return MDCalculator([LennardJones(epsilon=0.0104, sigma=3.4, cutoff=8.5)], skin=0.5)


def test_an_ase_call_after_a_move_copies_no_atoms(monkeypatch):
    """When only positions changed, the calculator copies them into the atoms it holds
    (ASE's calculate copies the whole Atoms, about 10 us): no Atoms.copy, the held
    atoms still a copy equal to the caller's, and the results those of a fresh
    calculator."""
    atoms = argon()
    atoms.calc = calculator()
    atoms.get_forces()
    held = atoms.calc.atoms
    copies = []
    original = ase.Atoms.copy

    def counted(self):
        copies.append(self)
        return original(self)

    monkeypatch.setattr(ase.Atoms, "copy", counted)
    rng = np.random.default_rng(4)
    for _ in range(3):
        atoms.positions += rng.uniform(-0.02, 0.02, size=atoms.positions.shape)
        energy, forces = atoms.get_potential_energy(), atoms.get_forces()
        assert atoms.calc.atoms is held and held is not atoms
        assert np.array_equal(held.positions, atoms.positions)
    assert not copies
    monkeypatch.setattr(ase.Atoms, "copy", original)
    fresh = atoms.copy()
    fresh.calc = calculator()
    assert energy == pytest.approx(fresh.get_potential_energy(), abs=1e-12)
    np.testing.assert_allclose(forces, fresh.get_forces(), rtol=0, atol=1e-12)


def test_an_ase_call_within_ases_tolerance_is_not_a_change():
    """Positions within 1e-15 of the held ones (ASE's check_state tolerance) are no
    change: no evaluation, the same results; a larger move is one."""
    atoms = argon()
    atoms.calc = calculator()
    atoms.get_forces()
    forcefield = atoms.calc.forcefield
    evaluations = forcefield.n_evaluations
    energy = atoms.get_potential_energy()
    atoms.positions[0, 0] += 5e-16
    assert atoms.get_potential_energy() == energy
    assert atoms.calc.get_property("forces", atoms, allow_calculation=False) is not None
    assert forcefield.n_evaluations == evaluations
    atoms.positions[0, 0] += 1e-9
    assert atoms.calc.get_property("energy", atoms, allow_calculation=False) is None
    atoms.get_forces()
    assert forcefield.n_evaluations == evaluations + 1


def test_an_ase_call_after_another_change_takes_ases_way():
    """A move together with a change of the cell, or of the initial charges (which ASE
    compares too), is evaluated from a fresh copy of the atoms (ASE's way), with a fresh
    calculator's results."""
    atoms = argon()
    atoms.calc = calculator()
    atoms.get_forces()
    for change in (
        lambda: atoms.set_cell(atoms.cell * 1.01, scale_atoms=True),
        lambda: atoms.set_initial_charges(np.full(len(atoms), 0.1)),
    ):
        held = atoms.calc.atoms
        atoms.positions[0] += 0.05
        change()
        forces = atoms.get_forces()
        assert atoms.calc.atoms is not held
        assert np.array_equal(atoms.calc.atoms.get_initial_charges(), atoms.get_initial_charges())
        assert np.array_equal(atoms.calc.atoms.cell, atoms.cell)
        fresh = atoms.copy()
        fresh.calc = calculator()
        np.testing.assert_allclose(forces, fresh.get_forces(), rtol=0, atol=1e-12)


def test_an_ase_call_makes_few_python_calls():
    """An energy + forces call after a move made 134 Python calls before issue 69's work
    (Atoms.copy's among them) and 62 after."""
    atoms = argon()
    atoms.calc = calculator()
    atoms.get_forces()
    rng = np.random.default_rng(2)
    moves = [rng.uniform(-0.01, 0.01, size=atoms.positions.shape) for _ in range(20)]
    start = atoms.positions.copy()
    it = iter(moves)

    def call():
        atoms.positions = start + next(it)
        atoms.get_potential_energy()
        atoms.get_forces()

    for _ in range(5):  # the first calls load their kernels
        call()
    assert python_calls(call, 15) <= 80
