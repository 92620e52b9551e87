"""The pair styles on the pair frame and user-written pair terms.

Formulas (LAMMPS's definitions) at chosen distances, Hessian blocks against
finite differences of the forces, the slot-frame kernels against the
atom-order ones in every cell shape, implicit Euler on Morse and on a user
term, Buckingham's collapse and bad input. The contract suite in
test_potentials.py covers forces = -grad E, Newton's third law, virials and
lists for every registered style; test_vs_lammps.py compares with LAMMPS.
"""

from __future__ import annotations

import importlib.util
import json
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from _configs import fcc_run

import md
from integrators import ImplicitEuler, VelocityVerlet
from md.errors import PairCollapseError, SimulationError
from md.forcefield import ForceField
from md.neighbors import NeighborList
from md.parallel import get_threads, set_threads
from potentials import (
    Buckingham,
    LennardJones,
    Mie,
    Morse,
    PairPotential,
    PairTerm,
    Soft,
    Table,
    Yukawa,
    pair_term,
)
from potentials.table import read_table

ROOT = Path(__file__).resolve().parents[1]
STEP = 1e-6
#: The styles whose every kernel path runs in the default suite; the others' slot-frame,
#: Hessian and md-run tests compile a term each and run with -m slow (their formulas,
#: contracts and LAMMPS comparisons stay in the default run where noted there).
DEFAULT_STYLES = {"morse", "table", "buckingham"}


def styles(names):
    """``names`` as parameters, those outside DEFAULT_STYLES marked slow."""
    return [
        pytest.param(name, marks=() if name in DEFAULT_STYLES else pytest.mark.slow)
        for name in names
    ]


def _example():
    spec = importlib.util.spec_from_file_location("wca_example", ROOT / "examples/wca_pair_term.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _dimer(potential, r, ti=0, tj=0):
    """(energy, force on atom 1 along +x) of two atoms r apart."""
    state = md.State(
        positions=[[0.0, 0.0, 0.0], [r, 0.0, 0.0]], box=50.0, pbc=False, types=[ti, tj]
    )
    result = potential.energy_forces(state, None)
    return result.energy, result.forces[1, 0]


# ------------------------------------------------------------------ formulas
def _morse(r, d0, a, r0):
    return d0 * (np.exp(-2 * a * (r - r0)) - 2 * np.exp(-a * (r - r0)))


def _mie(r, eps, sigma, n, m):
    c = n / (n - m) * (n / m) ** (m / (n - m))
    return c * eps * ((sigma / r) ** n - (sigma / r) ** m)


FORMULAS = {
    "morse": (
        Morse(d0=0.9, alpha=1.7, r0=1.3, cutoff=4.0, cutoff_mode="none"),
        lambda r: _morse(r, 0.9, 1.7, 1.3),
    ),
    "mie": (
        Mie(epsilon=1.2, sigma=1.1, n=14.0, m=7.5, cutoff=4.0, cutoff_mode="none"),
        lambda r: _mie(r, 1.2, 1.1, 14.0, 7.5),
    ),
    "buckingham": (
        Buckingham(a=900.0, rho=0.2, c=2.0, cutoff=4.0, cutoff_mode="none"),
        lambda r: 900.0 * np.exp(-r / 0.2) - 2.0 / r**6,
    ),
    "yukawa": (
        Yukawa(a=2.5, kappa=0.8, cutoff=4.0, cutoff_mode="none"),
        lambda r: 2.5 * np.exp(-0.8 * r) / r,
    ),
    "soft": (Soft(a=3.0, cutoff=4.0), lambda r: 3.0 * (1 + np.cos(np.pi * r / 4.0))),
}


@pytest.mark.parametrize("style", list(FORMULAS))
def test_energy_and_force_follow_the_lammps_formula(style):
    potential, u = FORMULAS[style]
    for r in (0.95, 1.2, 1.6, 2.3, 3.7):
        energy, force = _dimer(potential, r)
        assert energy == pytest.approx(u(r), rel=1e-12, abs=1e-14)
        h = 1e-6
        assert force == pytest.approx(-(u(r + h) - u(r - h)) / (2 * h), rel=1e-7, abs=1e-9)
    assert _dimer(potential, 4.0 + 1e-9) == (0.0, 0.0)


def test_known_values():
    assert _dimer(Morse(d0=0.7, alpha=2.0, r0=1.4, cutoff=3.0), 1.4)[0] == pytest.approx(
        -0.7 - _morse(3.0, 0.7, 2.0, 1.4), rel=1e-14
    )
    # Mie with n = 12, m = 6 is Lennard-Jones.
    mie = Mie(epsilon=0.8, sigma=1.2, n=12.0, m=6.0, cutoff=3.0, cutoff_mode="none")
    lj = LennardJones(epsilon=0.8, sigma=1.2, cutoff=3.0, cutoff_mode="none")
    for r in (1.1, 1.35, 2.0):
        assert _dimer(mie, r)[0] == pytest.approx(_dimer(lj, r)[0], rel=1e-12)
        assert _dimer(mie, r)[1] == pytest.approx(_dimer(lj, r)[1], rel=1e-12)
    # Soft: finite at full overlap (2 A, no force), zero with zero force at the cutoff.
    soft = Soft(a=1.5, cutoff=1.0)
    state = md.State(positions=[[1.0, 1.0, 1.0], [1.0, 1.0, 1.0]], box=5.0, pbc=False)
    result = soft.energy_forces(state, None)
    assert result.energy == 3.0 and np.all(result.forces == 0.0)
    energy, force = _dimer(soft, 1.0 - 1e-7)
    assert abs(energy) < 1e-12 and abs(force) < 1e-5


# ---------------------------------------------------------------- curvatures
def _numerical_hessian(potential, state):
    x0 = state.positions.copy()
    size = 3 * state.n_atoms
    hessian = np.empty((size, size))
    for k in range(size):
        state.positions[:] = x0
        state.positions.flat[k] += STEP
        plus = potential.energy_forces(state, None).forces.ravel()
        state.positions[:] = x0
        state.positions.flat[k] -= STEP
        minus = potential.energy_forces(state, None).forces.ravel()
        hessian[:, k] = -(plus - minus) / (2.0 * STEP)
    state.positions[:] = x0
    return hessian


HESSIAN_CASES = {
    "morse": lambda mode: Morse(d0=1.0, alpha=2.0, r0=1.1, cutoff=2.0, cutoff_mode=mode),
    "mie": lambda mode: Mie(
        epsilon=[1.0, 0.5], sigma=[1.0, 1.1], n=13.0, m=6.5, cutoff=2.0, cutoff_mode=mode
    ),
    "buckingham": lambda mode: Buckingham(a=2000.0, rho=0.15, c=1.0, cutoff=2.0, cutoff_mode=mode),
    "yukawa": lambda mode: Yukawa(a=[1.0, 2.0], kappa=1.3, cutoff=2.0, cutoff_mode=mode),
    "soft": lambda mode: Soft(a=[1.0, 2.0], cutoff=1.5, cutoff_mode=mode),
    "wca": lambda mode: _example().make_potential(),
}


@pytest.mark.parametrize("mode", ["none", "smooth"])
@pytest.mark.parametrize("style", styles(HESSIAN_CASES))
def test_hessian_blocks_match_differences_of_the_forces(style, mode, random_gas):
    potential = HESSIAN_CASES[style](mode)
    kinks = np.array([potential.pair_parameters(0, 0)[k] for k in ("cutoff", "r_on")])
    for _ in range(20):  # a system with no pair within 1e-3 of a kink
        state = random_gas(20, 4.6, n_types=2, min_distance=0.85)
        d = state.positions[:, None] - state.positions[None]
        d -= state.box * np.round(d / state.box)
        r = np.sqrt((d**2).sum(-1))[np.triu_indices(state.n_atoms, 1)]
        if np.min(np.abs(r[:, None] - kinks)) > 1e-3:
            break
    exact = potential.hessian(state, None).toarray()
    numeric = _numerical_hessian(potential, state)
    scale = np.abs(exact).max()
    np.testing.assert_allclose(exact, numeric, rtol=0, atol=1e-6 * scale)
    nl = NeighborList(potential.cutoff, 0.3)
    nl.update(state)
    listed = potential.hessian(state, nl).toarray()
    np.testing.assert_allclose(listed, exact, rtol=0, atol=1e-12 * scale)


def test_spline_table_hessian_is_the_jacobian_of_its_forces(tmp_path, random_gas):
    path = tmp_path / "t.table"
    r = np.linspace(0.5, 2.2, 400)
    e = np.exp(-3 * (r - 1.0)) - 2 * np.exp(-1.5 * (r - 1.0))
    f = 3 * (np.exp(-3 * (r - 1.0)) - np.exp(-1.5 * (r - 1.0)))
    path.write_text(
        "T\nN 400 R 0.5 2.2\n\n"
        + "".join(f"{k + 1} {r[k]:.17g} {e[k]:.17g} {f[k]:.17g}\n" for k in range(400))
    )
    potential = Table(path, "T", "spline", cutoff=2.0)
    state = random_gas(12, 3.2, min_distance=0.85)
    exact = potential.hessian(state, None).toarray()
    numeric = _numerical_hessian(potential, state)
    np.testing.assert_allclose(exact, numeric, rtol=0, atol=1e-6 * np.abs(exact).max())


# --------------------------------------------------------- frame vs atom order
@pytest.mark.parametrize("cell", ["orthorhombic", "tilted", "slab"])
@pytest.mark.parametrize(
    ("style", "threads"),
    [
        # each term and threaded variant compiles apart: Morse on one thread runs by default
        # (LJ's threaded slot-frame kernels: tests/test_parallel.py), the rest with -m slow
        pytest.param(*case, marks=() if case == ("morse", 1) else pytest.mark.slow)
        for case in [
            ("morse", 1),
            ("morse", 2),
            ("yukawa", 1),
            ("yukawa", 2),
            ("wca", 1),
            ("wca", 2),
        ]
    ],
)
def test_slot_frame_kernels_equal_the_atom_order_kernels(style, cell, threads, fcc_lattice):
    """The threaded slot-frame kernels (forces, virial, Hessian blocks) give the atom-order
    kernels' results to round-off in every cell shape, with one chunk or two."""
    builders = {
        "morse": lambda: Morse(
            d0=1.0, alpha=2.0, r0=1.1, cutoff=2.2, pairs={(0, 1): {"d0": 0.5, "cutoff": 1.9}}
        ),
        "yukawa": lambda: Yukawa(a=[1.0, 2.0], kappa=1.1, cutoff=2.2, cutoff_mode="smooth"),
        "wca": lambda: _example().make_potential(),
    }
    state = fcc_lattice(cells=8, perturbation=0.07, n_types=1 if style == "wca" else 2)
    if cell == "tilted":
        state.tilt = np.array([0.2, -0.15, 0.1]) * state.box[[0, 0, 1]]
    elif cell == "slab":
        state.pbc = np.array([True, True, False])
    potential = builders[style]()
    before = get_threads()
    try:
        set_threads(threads)
        forcefield = ForceField([potential], skin=0.3)
        fast = forcefield.compute(state, virial=True)
        assert forcefield.neighbor_list.frame.n_chunks == threads
        blocks = potential.hessian(state, forcefield.neighbor_list)
    finally:
        set_threads(before)
    reference = potential.energy_forces(state, forcefield.neighbor_list, per_atom=True)
    assert fast.energy == pytest.approx(reference.energy, rel=1e-12)
    np.testing.assert_allclose(
        fast.forces, reference.forces, rtol=0, atol=1e-11 * np.abs(reference.forces).max()
    )
    np.testing.assert_allclose(
        fast.virial, reference.virial, rtol=0, atol=1e-11 * np.abs(reference.virial).max()
    )
    exact = potential.hessian(state, None)
    assert abs(blocks - exact).max() <= 1e-11 * abs(exact).max()


# ---------------------------------------------------------------- user terms
def test_user_term_forces_are_minus_the_gradient_of_its_energy(random_gas):
    potential = _example().make_potential()
    state = random_gas(40, 4.0, min_distance=0.8, images=1)
    result = potential.energy_forces(state, None)
    assert result.energy > 0
    np.testing.assert_allclose(result.forces.sum(axis=0), 0.0, atol=1e-12 * state.n_atoms)
    for i in range(0, state.n_atoms, 7):
        for axis in range(3):
            moved = state.copy()
            moved.positions[i, axis] += STEP
            up = potential.energy_forces(moved, None).energy
            moved.positions[i, axis] -= 2 * STEP
            down = potential.energy_forces(moved, None).energy
            assert result.forces[i, axis] == pytest.approx(
                -(up - down) / (2 * STEP), rel=1e-6, abs=1e-6
            )


def test_wca_term_equals_shifted_lennard_jones_below_its_cutoff(random_gas):
    """The user's WCA is LJ truncated at 2^(1/6) sigma and shifted there (u(rc) = -eps)."""
    rc = 2 ** (1 / 6) * 1.1
    wca = _example().make_potential(epsilon=0.7, sigma=1.1)
    lj = LennardJones(epsilon=0.7, sigma=1.1, cutoff=rc, cutoff_mode="shift")
    state = random_gas(60, 4.5, min_distance=0.85)
    ours, theirs = wca.energy_forces(state, None), lj.energy_forces(state, None)
    assert ours.energy == pytest.approx(theirs.energy, rel=1e-11)
    np.testing.assert_allclose(ours.forces, theirs.forces, rtol=1e-10, atol=1e-12)


def test_user_term_through_the_ase_calculator():
    from md.calculator import MDCalculator

    potential = _example().make_potential(epsilon=0.01, sigma=3.0)
    state = md.lattice("fcc", 3, lattice_constant=4.6, shear=(0.2, 0.0, 0.1))
    state.positions += np.random.default_rng(2).normal(0, 0.1, state.positions.shape)
    atoms = state.to_ase()
    atoms.calc = MDCalculator([potential])
    result = ForceField([potential]).compute(state, virial=True)
    assert atoms.get_potential_energy() == pytest.approx(result.energy, rel=1e-12)
    assert np.abs(atoms.get_forces()).max() > 0
    stress = atoms.get_stress(voigt=False)
    np.testing.assert_allclose(
        np.trace(stress) / 3, -np.trace(result.virial) / 3 / state.volume, rtol=1e-10
    )


def test_a_term_without_curvature_is_refused_by_implicit_euler():
    @pair_term
    def gaussian(r2, epsilon, width):
        u = epsilon * math.exp(-r2 / (width * width))
        return u, 2.0 * u / (width * width)

    potential = PairPotential(gaussian, epsilon=1.0, width=0.8, cutoff=2.5)
    state = md.maxwell_boltzmann(md.lattice("fcc", 4, density=0.9), 0.5, seed=3)
    md.Simulation(state.copy(), [potential], VelocityVerlet(0.01)).run(3)  # explicit: fine
    with pytest.raises((TypeError, SimulationError), match="no curvature"):
        md.Simulation(state, [potential], ImplicitEuler(0.01)).run(1)


@pytest.mark.parametrize("name", [pytest.param("morse", marks=pytest.mark.slow), "wca"])
def test_implicit_euler_runs_on_the_frame(name):  # Morse's Hessian kernels compile: -m slow
    """Newton with the frame's Hessian converges, and the dynamics dissipates energy as
    implicit Euler must (never gains it)."""
    potential = (
        Morse(d0=1.0, alpha=3.0, r0=1.1, cutoff=2.3)
        if name == "morse"
        else _example().make_potential()
    )
    density = 0.9 if name == "wca" else 0.75
    state = md.maxwell_boltzmann(md.lattice("fcc", 4, density=density), 0.4, seed=5)
    integrator = ImplicitEuler(0.01)
    sim = md.Simulation(state, [potential], integrator)
    energies = [sim.thermo()["total_energy"]]
    for _ in range(10):
        sim.run(2)
        energies.append(sim.thermo()["total_energy"])
    assert np.all(np.diff(energies) <= 1e-9 * abs(energies[0]))
    assert energies[-1] < energies[0]
    assert integrator.statistics.get("newton_iterations", 1) > 0


def test_pair_term_checks_its_signature():
    def no_params(r2):
        return r2, r2

    term = PairTerm(no_params)
    assert term.parameters == ()
    with pytest.raises(TypeError, match="curvature takes"):
        PairTerm(lambda r2, a: (a, a), curvature=lambda r2, b: (b, b, b))
    with pytest.raises(TypeError, match="taken"):
        PairPotential(pair_term(lambda r2, cutoff: (r2, r2)), cutoff=1.0)


# ---------------------------------------------------------------- Buckingham
def test_buckingham_collapse_names_the_pair_and_the_step():
    buck = Buckingham(a=1000.0, rho=0.2, c=5.0, cutoff=3.0)
    barrier = buck.barrier(1000.0, 0.2, 5.0)
    state = md.State(
        positions=[[1, 1, 1], [1 + 0.9 * barrier, 1, 1], [4, 4, 4]],
        box=10.0,
        pbc=False,
        type_names=("O",),
    )
    state.step = 17
    with pytest.raises(PairCollapseError, match=r"atoms 0 and 1 \(types O-O\).*step 17"):
        buck.energy_forces(state, None)
    state.positions[1, 0] = 1 + 1.1 * barrier  # outside the barrier: repulsive, finite
    energy, force = buck.energy_forces(state, None).energy, buck.energy_forces(state, None).forces
    assert math.isfinite(energy) and force[1, 0] > 0
    # In a run it stops the simulation at the step it happened.
    state = md.State(
        positions=[[1, 1, 1], [1 + 1.3 * barrier, 1, 1]],
        box=10.0,
        pbc=False,
        velocities=[[3.0, 0, 0], [-3.0, 0, 0]],
    )
    with pytest.raises(SimulationError, match="atoms 0 and 1"):
        md.Simulation(state, [buck], VelocityVerlet(0.002)).run(200)


def test_buckingham_without_a_barrier_is_refused():
    with pytest.raises(ValueError, match="no repulsive barrier"):
        Buckingham(a=1.0, rho=0.1, c=10.0, cutoff=3.0)


# ---------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    ("build", "message"),
    [
        (lambda: Mie(n=6.0, m=6.0), "n .* must be larger than m"),
        (lambda: Mie(n=[12.0, 5.0], m=6.0, epsilon=[1, 1], sigma=[1, 1]), "larger than m"),
        (lambda: Buckingham(rho=0.0), "rho must be finite and > 0"),
        (lambda: Buckingham(rho=-1.0), "rho"),
        (lambda: Morse(alpha=0.0), "alpha"),
        (lambda: Morse(d0=[1.0, 2.0]), "d0 must be a number"),
        (lambda: Yukawa(kappa=-1.0), "kappa"),
        (lambda: Soft(a=1.0, mixing="arithmetic"), "mixing"),
        (lambda: Morse(pairs={(0, 1): {"epsilon": 1.0}}), "unknown pair parameter"),
    ],
)
def test_bad_parameters_are_refused(build, message):
    with pytest.raises(ValueError, match=message):
        build()


TABLE = "T\nN 4 R 0.5 2.0\n\n1 0.5 3.0 10.0\n2 1.0 0.0 1.0\n3 1.5 -0.5 0.2\n4 2.0 -0.1 0.05\n"


@pytest.mark.parametrize(
    ("text", "keyword", "message"),
    [
        (TABLE, "X", "no section named 'X'"),
        (TABLE.replace("N 4 R 0.5 2.0", "R 0.5 2.0"), "T", ":2: the parameter line does not set N"),
        (TABLE.replace("N 4", "N 5"), "T", ":7: section T ends after 4 of its N = 5 points"),
        (TABLE.replace("3 1.5 -0.5 0.2", "3 1.5 -0.5"), "T", ":6: expected 'index r energy force'"),
        (TABLE.replace("3 1.5 -0.5 0.2", "3 1.5 x 0.2"), "T", ":6: not numbers"),
        (
            TABLE.replace("N 4 R 0.5 2.0", "N 4").replace("3 1.5", "3 0.9"),
            "T",
            ":6: distances must increase",
        ),
        (TABLE.replace("R 0.5 2.0", "BITMAP 0.5 2.0"), "T", "BITMAP tables are not supported"),
    ],
)
def test_bad_table_files_name_the_file_and_line(text, keyword, message, tmp_path):
    path = tmp_path / "bad.table"
    path.write_text(text)
    with pytest.raises(ValueError, match=message) as error:
        Table(path, keyword)
    assert str(path) in str(error.value)


def test_table_missing_or_too_short_for_the_cutoff(tmp_path):
    with pytest.raises(ValueError, match="not found"):
        Table(tmp_path / "nowhere.table", "T")
    path = tmp_path / "t.table"
    path.write_text(TABLE)
    with pytest.raises(ValueError, match="covers r = 0.5 to 2.*cutoff 2.5"):
        Table(path, "T", cutoff=2.5)
    assert read_table(path, "T").r.tolist() == [0.5, 1.0, 1.5, 2.0]


def test_table_interpolates_a_smooth_function_closely(tmp_path):
    """A dense table of Morse reproduces Morse (energy and force) to interpolation accuracy;
    a pair below the table's first distance is an error naming it."""
    path = tmp_path / "m.table"
    n = 2000
    r = np.linspace(0.7, 2.5, n)
    e = _morse(r, 1.0, 2.0, 1.2)
    f = 2 * 2.0 * (np.exp(-4.0 * (r - 1.2)) - np.exp(-2.0 * (r - 1.2)))
    path.write_text(
        "M\nN 2000 R 0.7 2.5\n\n"
        + "".join(f"{k + 1} {r[k]:.17g} {e[k]:.17g} {f[k]:.17g}\n" for k in range(n))
    )
    morse = Morse(d0=1.0, alpha=2.0, r0=1.2, cutoff=2.5, cutoff_mode="none")
    for interpolation, tolerance in (("linear", 1e-4), ("spline", 1e-8)):
        table = Table(path, "M", interpolation)
        for x in (0.75, 1.0, 1.2, 1.77, 2.4):
            energy, force = _dimer(table, x)
            expected = _dimer(morse, x)
            assert energy == pytest.approx(expected[0], abs=tolerance)
            assert force == pytest.approx(expected[1], abs=tolerance * 10)
        with pytest.raises(PairCollapseError, match="below the table's first distance"):
            _dimer(table, 0.65)


# ---------------------------------------------------------------- kernel cache
_CACHE_CHILD = """
import json, md
from potentials import PairPotential, pair_term
from potentials._pair_codegen import kernels_for

@pair_term
def soft_wall(r2, k, width):
    gap = width - r2**0.5
    return 0.5 * k * gap * gap, k * gap / r2**0.5

state = md.lattice("fcc", 5, density=0.8)
potential = PairPotential(soft_wall, k=10.0, width=1.3, cutoff=1.3, cutoff_mode="none")
forcefield = md.ForceField([potential], skin=0.3)
result = forcefield.compute(state)
kernels = kernels_for(potential.term)
variants = [getattr(kernels, name) for name in dir(kernels) if name.startswith("frame_forces__")]
used = [kernel for kernel in variants if kernel.stats.cache_hits or kernel.stats.cache_misses]
print(json.dumps({"frame": forcefield.neighbor_list.frame is not None,
                  "hits": sum(sum(kernel.stats.cache_hits.values()) for kernel in used),
                  "misses": sum(sum(kernel.stats.cache_misses.values()) for kernel in used),
                  "file": kernels_for(potential.term).__file__, "energy": result.energy}))
"""


@pytest.mark.slow  # three processes compiling on an empty cache: over a minute
def test_frame_kernels_compile_once_and_load_from_the_cache_in_later_processes(tmp_path):
    """A user's term defined in a script: two processes compiling it at once both finish
    and leave one complete copy of the frame's kernels (no temporaries); a third process
    loads the compiled kernels from numba's cache, compiling none."""
    env = {
        "XDG_CACHE_HOME": str(tmp_path / "cache"),
        "PATH": "/usr/bin:/bin",
        "PYTHONPATH": str(ROOT),
    }

    def start():
        command = [sys.executable, "-c", _CACHE_CHILD]
        return subprocess.Popen(
            command,
            env=env,
            cwd=tmp_path,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )

    def report(process):
        out, err = process.communicate(timeout=1800)
        assert process.returncode == 0, err
        return json.loads(out.splitlines()[-1])

    together = [start(), start()]
    first, second = (report(process) for process in together)
    third = report(start())
    assert first["frame"] and first["energy"] > 0  # the slot-frame path, overlapping walls
    assert first["file"] == second["file"] == third["file"]
    # Python's own bytecode cache of the copy may sit beside it; nothing else may
    copies = [
        path
        for path in (tmp_path / "cache/leapmd/numba/pair_terms").iterdir()
        if path.name != "__pycache__"
    ]
    assert [path.name for path in copies] == [Path(first["file"]).name]
    template = (ROOT / "potentials/_pair_kernels.py").read_bytes()
    assert Path(first["file"]).read_bytes().startswith(template)  # and the variants after it
    assert first["energy"] == second["energy"] == third["energy"]
    # the first call runs the variants with and without the virial: two kernels, both loaded
    assert third["hits"] == 2 and third["misses"] == 0
    assert first["misses"] + first["hits"] == 2 and second["misses"] + second["hits"] == 2


def test_a_source_edited_while_a_process_runs_does_not_rename_its_kernels(monkeypatch, tmp_path):
    """The term's fingerprint and its template copy come from the frame's sources as this
    process imported them (the code it runs), not as the files read later: otherwise a
    source edited during a run got the old code's compiled kernels stored in the shared
    cache under the new code's fingerprint, where later processes loaded them (found: a
    kernel change that seemed to change nothing)."""
    from numba.core import config

    from potentials import _pair_codegen

    term = LennardJones(cutoff=2.5).term
    before = _pair_codegen._fingerprint(term)
    template = (ROOT / "potentials/_pair_kernels.py").read_bytes()
    monkeypatch.setattr(Path, "read_bytes", lambda self: b"# edited since")
    monkeypatch.setattr(Path, "read_text", lambda self, *a, **k: "# edited since")
    assert _pair_codegen._fingerprint(term) == before
    monkeypatch.setattr(config, "CACHE_DIR", str(tmp_path))
    copy = _pair_codegen._template_copy("edited_lj")
    monkeypatch.undo()
    assert copy.read_bytes().startswith(template)


# ---------------------------------------------------------------- vector exp
def test_vector_exp_is_within_its_stated_error_bound():
    """potentials.pair_math.exp, compiled as the pair loops compile it (fast-math flags):
    within 2e-14 relative of numpy's exp on [-707, 709.7827] (up to the largest double), the
    bound its docstring states (46 bits; the polynomial fit's own error is 1.64e-14), 0 below
    -708, inf above ln(DBL_MAX), NaN for NaN; ``math.exp`` itself in Python."""
    from numba import njit

    from potentials.pair_math import exp

    @njit(fastmath={"reassoc", "contract", "nsz", "arcp"}, error_model="numpy")
    def evaluate(x, out):
        for i in range(x.shape[0]):
            out[i] = exp(x[i])

    rng = np.random.default_rng(4)
    x = np.concatenate(
        [
            np.linspace(-707.0, 709.0, 500_001),
            rng.uniform(-60.0, 5.0, 500_000),
            np.linspace(709.0, 709.7827, 10_001),  # 2^k with k = 1024 from 709.44
            np.arange(-40, 41) * math.log(2.0),
        ]
    )
    out = np.empty_like(x)
    evaluate(x, out)
    relative = np.abs(out / np.exp(x) - 1.0)
    assert relative.max() <= 2e-14
    edges = np.array([-708.5, -1000.0, 709.9, np.inf, -np.inf, np.nan])
    evaluate(edges, out[:6])
    assert out[:3].tolist() == [0.0, 0.0, np.inf] and out[3] == np.inf and out[4] == 0.0
    assert np.isnan(out[5])
    assert exp(0.5) == math.exp(0.5)


def test_vector_sin_and_cos_are_within_their_stated_error_bound():
    """potentials.pair_math.sin and cos, compiled as the pair loops compile them: within
    4e-16 absolute of numpy's on |x| <= 1e5 (both from one reduction, as a pair term calls
    them), every quadrant and multiples of pi/2 included; NaN for inf and NaN; relative
    accuracy kept near 0 (sin x ~ x); ``math.sin`` and ``math.cos`` themselves in Python."""
    from numba import njit

    from potentials.pair_math import cos, sin

    @njit(fastmath={"reassoc", "contract", "nsz", "arcp"}, error_model="numpy")
    def evaluate(x, s, c):
        for i in range(x.shape[0]):
            s[i] = sin(x[i])
            c[i] = cos(x[i])

    rng = np.random.default_rng(5)
    x = np.concatenate(
        [
            np.linspace(-1e5, 1e5, 400_001),
            rng.uniform(-8.0, 8.0, 400_000),
            np.arange(-200, 201) * (0.5 * math.pi),
            np.arange(-64, 65) * 0.25,
        ]
    )
    s, c = np.empty_like(x), np.empty_like(x)
    evaluate(x, s, c)
    assert np.abs(s - np.sin(x)).max() <= 4e-16
    assert np.abs(c - np.cos(x)).max() <= 4e-16
    small = np.geomspace(1e-300, 0.7, 2001)
    ss, cs = np.empty_like(small), np.empty_like(small)
    evaluate(small, ss, cs)
    assert np.all(np.abs(ss / np.sin(small) - 1.0) <= 4e-16)
    edges = np.array([np.inf, -np.inf, np.nan])
    evaluate(edges, s[:3], c[:3])
    assert np.all(np.isnan(s[:3])) and np.all(np.isnan(c[:3]))
    assert sin(0.5) == math.sin(0.5) and cos(0.5) == math.cos(0.5)


def test_vector_log_is_within_its_stated_error_bound():
    """potentials.pair_math.log, compiled as the pair loops compile it: at most 1 ulp from
    numpy's log over the doubles (subnormals included, and near 1, where log is small);
    -inf at 0, NaN below 0 and for NaN, inf at inf; ``math.log`` itself in Python."""
    from numba import njit

    from potentials.pair_math import log

    @njit(fastmath={"reassoc", "contract", "nsz", "arcp"}, error_model="numpy")
    def evaluate(x, out):
        for i in range(x.shape[0]):
            out[i] = log(x[i])

    rng = np.random.default_rng(5)
    powers = 2.0 ** np.arange(-1074, 1024)  # subnormals to the largest power of two
    x = np.concatenate(
        [
            10.0 ** rng.uniform(-307.0, 308.0, 400_000),
            rng.uniform(0.5, 2.0, 300_000),
            1.0 + rng.uniform(-1e-8, 1e-8, 100_000),
            rng.uniform(1e-320, 2e-308, 10_000),
            powers,
        ]
    )
    out = np.empty_like(x)
    evaluate(x, out)
    exact = np.log(x)
    ulps = np.abs(out - exact) / np.spacing(np.abs(exact))
    assert ulps.max() <= 1.0
    edges = np.array([0.0, -1.0, np.inf, -np.inf, np.nan])
    evaluate(edges, out[:5])
    assert out[0] == -np.inf and np.isnan(out[1]) and out[2] == np.inf
    assert np.isnan(out[3]) and np.isnan(out[4])
    assert log(0.5) == math.log(0.5)


def test_reciprocal_is_ieee_division_in_a_fast_math_loop():
    """potentials.pair_math.reciprocal inside a loop compiled with the pair loops' fast-math
    flags: 1 / x to the bit (numpy's division), inf at +-0, 0 at inf, NaN for NaN; and the
    same in Python."""
    from numba import njit

    from potentials.pair_math import reciprocal

    @njit(fastmath={"reassoc", "contract", "nsz", "arcp"}, error_model="numpy")
    def evaluate(x, y, out):
        for i in range(x.shape[0]):
            out[i] = y[i] * reciprocal(x[i])  # LLVM may not fold this into y / x

    rng = np.random.default_rng(6)
    x = np.concatenate(
        [
            10.0 ** rng.uniform(-300.0, 300.0, 100_000),
            rng.uniform(0.5, 3.0, 100_000),
            np.array([0.0, -0.0, np.inf, -np.inf, np.nan]),
        ]
    )
    ones = np.ones_like(x)
    out = np.empty_like(x)
    evaluate(x, ones, out)
    with np.errstate(divide="ignore"):
        expected = 1.0 / x
    assert np.array_equal(out, expected, equal_nan=True)
    assert out[-5] == np.inf and out[-4] == -np.inf and out[-3] == 0.0
    assert [reciprocal(v) for v in (4.0, 0.0, -0.0)] == [0.25, math.inf, -math.inf]


# ---------------------------------------------------------------- configs and the CLI
GOOD = {
    "morse": 'type = "morse"\nd0 = 1.0\nalpha = 3.0\nr0 = 1.1\ncutoff = 2.2',
    "mie": 'type = "mie"\nepsilon = 1.0\nsigma = 1.0\nn = 13.0\nm = 6.5\ncutoff = 2.5',
    "buckingham": 'type = "buckingham"\na = 2000.0\nrho = 0.15\nc = 1.0\ncutoff = 2.5',
    "yukawa": 'type = "yukawa"\na = 1.0\nkappa = 1.5\ncutoff = 2.5',
    "soft": 'type = "soft"\na = 1.0\ncutoff = 1.1',
    "table": 'type = "table"\nfile = "pair.table"\nkeyword = "T"\ninterpolation = "spline"',
}


def _table_file(folder: Path) -> None:
    r = np.linspace(0.6, 2.3, 300)
    e = np.exp(-6.0 * (r - 1.1)) - 2.0 * np.exp(-3.0 * (r - 1.1))
    f = 6.0 * (np.exp(-6.0 * (r - 1.1)) - np.exp(-3.0 * (r - 1.1)))
    (folder / "pair.table").write_text(
        "# a Morse table\n\nT\nN 300 R 0.6 2.3\n\n"
        + "".join(f"{k + 1} {r[k]:.17g} {e[k]:.17g} {f[k]:.17g}\n" for k in range(300))
    )


@pytest.mark.parametrize("style", styles(GOOD))
def test_md_run_with_each_style(style, tmp_path, monkeypatch):
    from md.cli import main

    monkeypatch.chdir(tmp_path)
    folder = tmp_path / "in"
    folder.mkdir()
    _table_file(folder)  # the path in the config is relative to the config's folder
    config = folder / "run.toml"
    config.write_text(fcc_run(GOOD[style]))
    assert main(["run", str(config), "--no-progress", "-q", "-o", "out.h5"]) == 0
    assert (tmp_path / "out.h5").exists()


BAD = {
    "unknown key": ('type = "morse"\nd0 = 1.0\nalpha = 3.0\nr0 = 1.1\nepsilon = 1.0', "epsilon"),
    "mie n <= m": ('type = "mie"\nn = 6.0\nm = 8.0', "must be larger than m"),
    "rho <= 0": ('type = "buckingham"\na = 1.0\nrho = 0.0\nc = 1.0', "rho"),
    "unknown pair key": (
        'type = "yukawa"\na = 1.0\n[[potentials.pairs]]\ntypes = ["A", "A"]\nb = 2.0',
        "pairs\\[0\\]: unknown key",
    ),
    "table missing": ('type = "table"\nfile = "none.table"\nkeyword = "T"', "none.table not found"),
    "table keyword": ('type = "table"\nfile = "pair.table"\nkeyword = "X"', "no section named"),
    "table too short": (
        'type = "table"\nfile = "pair.table"\nkeyword = "T"\ncutoff = 3.0',
        "cutoff 3 must lie",
    ),
    "table malformed": (
        'type = "table"\nfile = "broken.table"\nkeyword = "T"',
        "broken.table:4: not numbers",
    ),
    "table unsorted": (
        'type = "table"\nfile = "unsorted.table"\nkeyword = "T"',
        "unsorted.table:5: distances must increase",
    ),
    "interpolation": (
        'type = "table"\nfile = "pair.table"\nkeyword = "T"\ninterpolation = "cubic"',
        "interpolation: must be one of 'linear', 'spline', got 'cubic'",
    ),
}


@pytest.mark.parametrize("case", list(BAD))
def test_md_run_refuses_bad_pair_input_with_exit_2_writing_nothing(
    case, tmp_path, monkeypatch, capsys
):
    from md.cli import main

    monkeypatch.chdir(tmp_path)
    _table_file(tmp_path)
    (tmp_path / "broken.table").write_text("T\nN 3\n\n1 1.0 x 0.0\n2 1.5 0.0 0.0\n3 2.0 0 0\n")
    (tmp_path / "unsorted.table").write_text("T\nN 3\n\n1 1.0 1 0.0\n2 0.9 0.0 0.0\n3 2 0 0\n")
    potential, message = BAD[case]
    config = tmp_path / "run.toml"
    text = fcc_run(potential)
    config.write_text(text.replace('lattice = "fcc"', 'lattice = "fcc"\ntype_name = "A"'))
    assert main(["run", str(config), "--no-progress", "-o", "out.h5"]) == 2
    error = capsys.readouterr().err
    assert "potentials.0" in error and re.search(message, error), error
    assert not (tmp_path / "out.h5").exists() and not list(tmp_path.glob("out.h5*"))
