"""MDCalculator: ASE's LennardJones reproduced, derivatives, caching, and ASE's own drivers."""

from __future__ import annotations

import contextlib

import ase
import ase.units
import numpy as np
import pytest
from ase.build import bulk
from ase.calculators.calculator import PropertyNotImplementedError
from ase.calculators.fd import calculate_numerical_forces, calculate_numerical_stress
from ase.calculators.lj import LennardJones as AseLennardJones
from scipy.optimize import minimize_scalar

from md.calculator import MDCalculator
from md.thermo import temperature
from md.validate import argon_liquid
from potentials import LennardJones

EPSILON, SIGMA, CUTOFF = 0.0104, 3.40, 8.5  # argon, eV and Angstrom


def argon(cells=4, a=5.26, rattle=0.05, seed=1) -> ase.Atoms:
    atoms = bulk("Ar", "fcc", a=a, cubic=True).repeat(cells)
    if rattle:
        atoms.rattle(rattle, seed=seed)
    return atoms


def ours(mode="shift", r_on=None, cutoff=CUTOFF, **kwargs) -> MDCalculator:
    lj = LennardJones(epsilon=EPSILON, sigma=SIGMA, cutoff=cutoff, cutoff_mode=mode, r_on=r_on)
    return MDCalculator([lj], **kwargs)


def theirs(mode="shift", r_on=None, cutoff=CUTOFF) -> AseLennardJones:
    return AseLennardJones(
        epsilon=EPSILON, sigma=SIGMA, rc=cutoff, ro=r_on, smooth=mode == "smooth"
    )


def liquid() -> ase.Atoms:
    state, _ = argon_liquid(n_atoms=200, temperature=100.0, seed=3, n_equilibrate=100)
    return state.to_ase()


def geometries() -> dict:
    crystal = argon()
    cluster = argon(cells=3, rattle=0.1)
    cluster.pbc = False
    cluster.cell = np.zeros((3, 3))  # no cell at all: an isolated cluster
    slab = argon(rattle=0.08)
    slab.pbc = [True, True, False]  # open along z, the cell still has a volume
    slab.positions[:, 2] *= 1.2
    wire = argon(rattle=0.08)
    wire.pbc = [False, True, False]
    wire.cell = np.diag([0.0, wire.cell[1, 1], 0.0])  # open axes of zero length
    small = argon(cells=1, rattle=0.1)  # 5.26 A < 2 * cutoff: replicated internally
    mixed_small = argon(cells=(1, 2, 4), rattle=0.1)
    mixed_small.pbc = [True, False, True]
    return {
        "crystal": crystal,
        "liquid": liquid(),
        "cluster": cluster,
        "slab": slab,
        "wire": wire,
        "small cell": small,
        "small mixed": mixed_small,
    }


GEOMETRIES = geometries()


def _close(actual, expected, rtol=1e-10):
    """Agreement to ``rtol`` relative to the largest entry of ``expected``."""
    scale = np.abs(expected).max()
    np.testing.assert_allclose(actual, expected, rtol=0, atol=rtol * scale)


@pytest.mark.parametrize("name", GEOMETRIES)
@pytest.mark.parametrize(("mode", "r_on"), [("shift", None), ("smooth", None), ("smooth", 7.0)])
def test_matches_ase_lennard_jones(name, mode, r_on):
    reference = GEOMETRIES[name].copy()
    reference.calc = theirs(mode, r_on)
    for sort_atoms in (False, True):  # internal spatial order: the same results
        atoms = GEOMETRIES[name].copy()
        atoms.calc = ours(mode, r_on, sort_atoms=sort_atoms)
        assert atoms.get_potential_energy() == pytest.approx(
            reference.get_potential_energy(), rel=1e-10, abs=0
        )
        assert atoms.get_potential_energy(force_consistent=True) == atoms.get_potential_energy()
        _close(atoms.get_forces(), reference.get_forces())
        _close(atoms.get_potential_energies(), reference.get_potential_energies())
        if atoms.cell.rank == 3:
            _close(atoms.get_stress(), reference.get_stress())
            _close(atoms.get_stresses(), reference.get_stresses())
            assert atoms.get_stresses().shape == (len(atoms), 6)
            np.testing.assert_allclose(
                atoms.get_stresses().sum(axis=0), atoms.get_stress(), rtol=0, atol=1e-14
            )
        else:  # no volume, no stress: as ASE's own calculator
            for getter in (atoms.get_stress, atoms.get_stresses):
                with pytest.raises(PropertyNotImplementedError):
                    getter()


def _any_pbc_geometries() -> dict:
    """Tilted and rotated cells under every pbc, some narrow along a periodic axis."""
    rng = np.random.default_rng(7)
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    rotation = q * np.sign(np.diag(r))
    cases = {}
    for pbc in [
        (False, False, False),
        (True, False, False),
        (False, True, False),
        (False, False, True),
        (True, True, False),
        (True, False, True),
        (False, True, True),
    ]:
        for narrow in (False, True):  # narrow: 5.26 A periodic edges, replicated inside
            atoms = argon(cells=(1, 2, 3) if narrow else 3, rattle=0.08, seed=len(cases))
            cell = atoms.cell.array.copy()
            cell[1, 0] += 0.3 * cell[1, 1]
            cell[2, :2] += [0.2 * cell[2, 2], -0.25 * cell[2, 2]]
            atoms.set_cell(cell, scale_atoms=True)
            atoms.pbc = pbc
            cases[f"tilted {pbc}{' narrow' if narrow else ''}"] = atoms
            turned = atoms.copy()
            turned.set_cell(atoms.cell.array @ rotation.T, scale_atoms=True)
            cases[f"rotated {pbc}{' narrow' if narrow else ''}"] = turned
    return cases


ANY_PBC = _any_pbc_geometries()


@pytest.mark.parametrize("name", ANY_PBC)
def test_any_pbc_with_a_tilted_or_rotated_cell_matches_ase(name):
    """Was refused ("tilted between axes x and y ... must then both be periodic")."""
    reference = ANY_PBC[name].copy()
    reference.calc = theirs()
    atoms = ANY_PBC[name].copy()
    atoms.calc = ours()
    assert atoms.get_potential_energy() == pytest.approx(
        reference.get_potential_energy(), rel=1e-10, abs=0
    )
    _close(atoms.get_forces(), reference.get_forces())
    _close(atoms.get_potential_energies(), reference.get_potential_energies())
    _close(atoms.get_stress(), reference.get_stress())  # the cell has a volume: a stress
    _close(atoms.get_stresses(), reference.get_stresses())


@pytest.mark.parametrize("sort_atoms", [False, True])
@pytest.mark.parametrize("pbc", [True, False])
def test_zero_atoms_give_zero_energy_and_no_forces(sort_atoms, pbc):
    """Was a raw numpy error (a minimum of an empty array)."""
    for cell in ([20.0, 20.0, 20.0], [5.0, 5.0, 5.0], [[20, 0, 0], [5, 20, 0], [0, 0, 20]]):
        atoms = ase.Atoms(cell=cell, pbc=pbc)
        atoms.calc = ours(sort_atoms=sort_atoms)
        reference = atoms.copy()
        reference.calc = theirs()
        assert atoms.get_potential_energy() == reference.get_potential_energy() == 0.0
        assert atoms.get_forces().shape == (0, 3)
        assert atoms.get_potential_energies().shape == (0,)
        np.testing.assert_array_equal(atoms.get_stress(), reference.get_stress())


def test_stress_sign_is_ase_convention():
    """Compressed argon pushes outwards: negative stress (positive pressure), and vice versa."""
    compressed, stretched = argon(a=4.9, rattle=0), argon(a=5.6, rattle=0)
    for atoms in (compressed, stretched):
        atoms.calc = ours()
    assert np.all(compressed.get_stress()[:3] < 0)
    assert np.all(stretched.get_stress()[:3] > 0)


@pytest.mark.parametrize("mode", ["shift", "smooth"])
def test_forces_match_ase_numerical_forces(mode):
    atoms = argon(cells=2, rattle=0.15, seed=4)  # 32 atoms, replicated internally
    atoms.calc = ours(mode)
    analytic = atoms.get_forces()
    numerical = calculate_numerical_forces(atoms, eps=1e-5)
    np.testing.assert_allclose(analytic, numerical, rtol=0, atol=1e-6 * np.abs(analytic).max())


@pytest.mark.parametrize("mode", ["shift", "smooth"])
def test_stress_matches_numerical_strain_derivative(mode):
    """All six components against ASE's finite differences on our own calculator: the
    sheared cells those differences make are evaluated as they are."""
    atoms = argon(cells=2, rattle=0.15, seed=5)
    atoms.calc = ours(mode)
    analytic = atoms.get_stress()
    probe = atoms.copy()
    probe.calc = ours(mode)
    numerical = calculate_numerical_stress(probe, eps=1e-6)
    np.testing.assert_allclose(analytic, numerical, rtol=0, atol=1e-6 * np.abs(analytic).max())


def _random_triclinic_argon(seed, scale=1.0, n=48):
    """Argon at liquid density in a random, rotated triclinic cell, overlaps relaxed away."""
    from ase.optimize import FIRE

    rng = np.random.default_rng(seed)
    lower = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    lower[[1, 2, 2], [0, 0, 1]] = rng.uniform(-0.5, 0.5, 3)
    lower *= (n * 39.95 / 1.4 / 0.6022) ** (1 / 3) * scale  # 1.4 g/cm^3
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    cell = lower @ (q * np.sign(np.diag(r))).T
    atoms = ase.Atoms(f"Ar{n}", scaled_positions=rng.random((n, 3)), cell=cell, pbc=True)
    atoms.calc = theirs("shift", cutoff=6.0)
    FIRE(atoms, logfile=None).run(fmax=0.5, steps=200)
    return atoms


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("mode", ["shift", "smooth"])
def test_triclinic_cells_match_ase(seed, mode):
    """Random rotated triclinic cells, some narrower than twice the cutoff (replicated
    internally): energy, forces, stress, per-atom energies and stresses equal ASE's."""
    atoms = _random_triclinic_argon(seed, scale=1.0 if seed < 2 else 0.7)
    reference = atoms.copy()
    reference.calc = theirs(mode, cutoff=8.5)
    atoms.calc = ours(mode, cutoff=8.5)
    scale = np.abs(reference.get_forces()).max()
    assert atoms.get_potential_energy() == pytest.approx(
        reference.get_potential_energy(), rel=1e-10
    )
    np.testing.assert_allclose(atoms.get_forces(), reference.get_forces(), atol=1e-10 * scale)
    stress = reference.get_stress()
    np.testing.assert_allclose(atoms.get_stress(), stress, atol=1e-10 * np.abs(stress).max())
    np.testing.assert_allclose(
        atoms.get_potential_energies(), reference.get_potential_energies(), atol=1e-10
    )
    np.testing.assert_allclose(
        atoms.get_stresses(), reference.get_stresses(), atol=1e-10 * np.abs(stress).max()
    )
    numerical = calculate_numerical_stress(atoms, eps=1e-6)
    np.testing.assert_allclose(atoms.get_stress(), numerical, atol=1e-6 * np.abs(stress).max())


def test_one_evaluation_serves_energy_forces_and_stress():
    """Energy and forces share an evaluation without the virial (what MD asks for);
    a stress asked for first serves all three, a stress asked for later costs one
    more evaluation, with the virial."""
    atoms = argon()
    calc = ours()
    atoms.calc = calc
    atoms.get_stress()
    atoms.get_potential_energy()
    atoms.get_forces()
    assert calc.forcefield.n_evaluations == 1
    atoms.positions[0, 0] += 0.01
    forces = atoms.get_forces()
    atoms.get_potential_energy()
    assert calc.forcefield.n_evaluations == 2
    stress = atoms.get_stress()
    assert calc.forcefield.n_evaluations == 3
    np.testing.assert_array_equal(atoms.get_forces(), forces)
    np.testing.assert_array_equal(atoms.get_stress(), stress)
    assert calc.forcefield.n_evaluations == 3
    atoms.get_potential_energies()  # per-atom energies need one more pass ...
    atoms.get_stresses()  # ... which per-atom stresses share
    atoms.get_forces()
    assert calc.forcefield.n_evaluations == 4


def test_neighbour_list_is_kept_and_rebuilt_only_when_needed():
    atoms = argon()
    calc = ours(skin=1.0)
    atoms.calc = calc
    atoms.get_forces()
    builds = calc.forcefield.neighbor_list.n_builds
    for _ in range(5):  # small moves stay within the skin
        atoms.positions += 0.05
        atoms.get_forces()
    assert calc.forcefield.neighbor_list.n_builds == builds
    atoms.positions[3] += 0.6  # beyond skin / 2
    atoms.get_forces()
    assert calc.forcefield.neighbor_list.n_builds == builds + 1
    atoms.set_cell(atoms.cell[:] * 1.001, scale_atoms=True)  # a small cell step: followed
    atoms.get_forces()
    assert calc.forcefield.neighbor_list.n_builds == builds + 1
    assert calc.forcefield.neighbor_list.n_followed == 1
    atoms.set_cell(atoms.cell[:] * 1.3, scale_atoms=False)  # atoms far from the scaled cell's
    atoms.get_forces()
    assert calc.forcefield.neighbor_list.n_builds == builds + 2
    atoms.numbers[0] = 36  # a Kr among the Ar (type-blind parameters: allowed)
    atoms.get_forces()
    assert calc.forcefield.neighbor_list.n_builds == builds + 3
    atoms += ase.Atoms("Ar", positions=[[1.3, 1.3, 1.3]])
    atoms.get_forces()
    assert calc.forcefield.neighbor_list.n_builds == builds + 4


def test_per_type_parameters_keyed_by_chemical_symbol():
    """An Ar/Kr mixture from symbol-keyed tables, from numbers or tags, against a numpy
    all-pairs sum with Lorentz-Berthelot mixing (open cluster, no cutoff effects)."""
    rng = np.random.default_rng(7)
    atoms = argon(cells=2, rattle=0.1)
    atoms.pbc = False
    atoms.cell = np.zeros((3, 3))
    kr = rng.choice(len(atoms), size=12, replace=False)
    atoms.numbers[kr] = 36
    epsilon, sigma = {"Ar": 0.0104, "Kr": 0.0140}, {"Ar": 3.40, "Kr": 3.65}
    table = {"type": "lj", "epsilon": epsilon, "sigma": sigma, "cutoff": 40.0}
    table["cutoff_mode"] = "none"
    atoms.calc = MDCalculator([table])
    assert atoms.calc.type_names == ("Ar", "Kr")
    symbols = atoms.get_chemical_symbols()
    eps = np.array([epsilon[s] for s in symbols])
    sig = np.array([sigma[s] for s in symbols])
    i, j = np.triu_indices(len(atoms), 1)
    r = np.linalg.norm(atoms.positions[i] - atoms.positions[j], axis=1)
    s6 = (0.5 * (sig[i] + sig[j]) / r) ** 6
    expected = np.sum(4 * np.sqrt(eps[i] * eps[j]) * (s6 * s6 - s6))
    assert atoms.get_potential_energy() == pytest.approx(expected, rel=1e-12)
    # the same through tags, with parameters in the opposite order
    tagged = atoms.copy()
    tagged.set_tags(np.where(atoms.numbers == 36, 0, 1))
    lj = LennardJones(epsilon=[0.0140, 0.0104], sigma=[3.65, 3.40], cutoff=40.0, cutoff_mode="none")
    tagged.calc = MDCalculator([lj], types_from="tags", type_names=["Kr", "Ar"])
    assert tagged.get_potential_energy() == pytest.approx(expected, rel=1e-12)
    np.testing.assert_allclose(tagged.get_forces(), atoms.get_forces(), rtol=0, atol=1e-14)
    tags = tagged.get_tags()  # a changed tag is a changed type, although ASE does not track tags
    tags[kr[0]] = 1
    tagged.set_tags(tags)
    assert tagged.get_potential_energy() != pytest.approx(expected, rel=1e-12)


def test_bad_input_is_named():
    lj2 = LennardJones(epsilon=[0.0104, 0.014], sigma=[3.40, 3.65], cutoff=CUTOFF)
    with pytest.raises(ValueError, match="type_names"):
        MDCalculator([lj2])
    atoms = argon(cells=1)
    atoms.numbers[0] = 54
    atoms.calc = MDCalculator([lj2], type_names=["Ar", "Kr"])
    with pytest.raises(ValueError, match="atom 0 is Xe"):
        atoms.get_potential_energy()
    flat = ase.Atoms("Ar2", positions=[[0, 0, 0], [3.7, 0, 0]], pbc=True, cell=[20, 20, 0])
    flat.calc = ours()
    with pytest.raises(ValueError, match="periodic along z"):
        flat.get_forces()
    with pytest.raises(ValueError, match="types_from"):
        ours(types_from="charges")


# ----------------------------------------------------------- ASE's own drivers
def _fcc_lattice_energy(a: float, mode: str) -> float:
    """Energy per atom of a perfect fcc crystal, by direct lattice sum (numpy)."""
    n = int(np.ceil(CUTOFF / a)) + 1
    steps = np.arange(-n, n + 1)
    cells = np.stack(np.meshgrid(steps, steps, steps, indexing="ij"), -1).reshape(-1, 1, 3)
    basis = np.array([[0, 0, 0], [0.5, 0.5, 0], [0.5, 0, 0.5], [0, 0.5, 0.5]])
    r = np.linalg.norm((cells + basis).reshape(-1, 3) * a, axis=1)
    r = r[(r > 0) & (r < CUTOFF)]
    u = 4 * EPSILON * ((SIGMA / r) ** 12 - (SIGMA / r) ** 6)
    if mode == "shift":
        u -= 4 * EPSILON * ((SIGMA / CUTOFF) ** 12 - (SIGMA / CUTOFF) ** 6)
    else:  # smooth: (rc^2 - r^2)^2 (rc^2 + 2 r^2 - 3 ro^2) / (rc^2 - ro^2)^3 beyond ro
        rc2, ro2, s = CUTOFF**2, (0.66 * CUTOFF) ** 2, r * r
        u *= np.where(s < ro2, 1.0, (rc2 - s) ** 2 * (rc2 + 2 * s - 3 * ro2) / (rc2 - ro2) ** 3)
    return 0.5 * float(u.sum())


def _one_blas_thread():
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api="blas")


@pytest.mark.parametrize("mode", ["shift", "smooth"])
@pytest.mark.parametrize(
    "driver", ["FrechetCellFilter+BFGS", "FrechetCellFilter+FIRE", "UnitCellFilter+FIRE"]
)
def test_cell_relaxation_reaches_the_lattice_constant(mode, driver):
    """A perturbed, strained fcc cell relaxes to the lattice constant that minimises the
    lattice sum for this cutoff (with no cutoff it would be 2^(1/6) sigma sqrt(2) times
    0.9712; the truncation moves it)."""
    from ase.filters import FrechetCellFilter, UnitCellFilter
    from ase.optimize import BFGS, FIRE

    best = minimize_scalar(
        _fcc_lattice_energy,
        args=(mode,),
        bounds=(5.0, 5.6),
        method="bounded",
        options={"xatol": 1e-12},
    )
    atoms = argon(cells=1, a=5.35, rattle=0.05, seed=9)
    # Sheared and strained: all six strain components relax.
    deformation = np.array([[1.0, 0.03, -0.02], [0.0, 0.98, 0.04], [0.0, 0.0, 1.02]])
    atoms.set_cell(atoms.cell.array @ deformation, scale_atoms=True)
    atoms.calc = ours(mode)
    cell_filter, optimizer = driver.split("+")
    kind = {"FrechetCellFilter": FrechetCellFilter, "UnitCellFilter": UnitCellFilter}
    optimizer = {"BFGS": BFGS, "FIRE": FIRE}[optimizer]
    relax = optimizer(kind[cell_filter](atoms), logfile=None)
    with _one_blas_thread():  # FrechetCellFilter's 3x3 LAPACK calls crawl on a busy machine
        assert relax.run(fmax=1e-7, steps=3000)
    # Back to a cube of the lattice constant: edge lengths a, angles 90 degrees.
    np.testing.assert_allclose(atoms.cell.cellpar(), [best.x] * 3 + [90.0] * 3, rtol=1e-6)
    assert atoms.get_potential_energy() / len(atoms) == pytest.approx(best.fun, rel=1e-9)
    np.testing.assert_allclose(atoms.get_stress(), 0.0, atol=1e-8)


def test_fire_finds_the_lj13_icosahedron():
    """The 13-atom LJ cluster minimum is -44.326801 epsilon (Wales & Doye, 1997)."""
    from ase.cluster import Icosahedron
    from ase.optimize import FIRE

    cluster = Icosahedron("Ar", noshells=2, latticeconstant=5.26)
    cluster.rattle(0.1, seed=2)
    lj = LennardJones(epsilon=1.0, sigma=SIGMA, cutoff=30.0, cutoff_mode="none")
    cluster.calc = MDCalculator([lj])
    assert FIRE(cluster, logfile=None).run(fmax=1e-8, steps=5000)
    assert cluster.get_potential_energy() == pytest.approx(-44.326801, abs=2e-6)


def test_bfgs_relaxes_positions_back_to_the_lattice():
    from ase.optimize import BFGS

    atoms = argon(cells=2, rattle=0.1, seed=6)
    perfect = argon(cells=2, rattle=0)
    perfect.calc = ours()
    atoms.calc = ours()
    with _one_blas_thread():
        assert BFGS(atoms, logfile=None).run(fmax=1e-6, steps=500)
    assert atoms.get_potential_energy() == pytest.approx(perfect.get_potential_energy(), rel=1e-9)


def test_ase_velocity_verlet_conserves_energy():
    from ase.md.verlet import VelocityVerlet

    atoms = liquid()
    atoms.calc = ours()
    dyn = VelocityVerlet(atoms, timestep=5 * ase.units.fs)
    energies = []
    dyn.attach(lambda: energies.append(atoms.get_total_energy()), interval=1)
    dyn.run(200)
    kinetic = atoms.get_kinetic_energy()
    assert np.ptp(energies) < 2e-3 * kinetic
    assert atoms.calc.forcefield.n_evaluations == 201  # one per step, plus the start
    assert atoms.calc.forcefield.neighbor_list.n_builds < 40


def test_ase_langevin_reaches_the_target_temperature():
    """With ASE's FixCom constraint both ASE's get_temperature and ours count 3N - 3."""
    from ase.constraints import FixCom
    from ase.md.langevin import Langevin

    target = 40.0
    atoms = argon(cells=4, rattle=0.02)
    atoms.calc = ours()
    atoms.set_constraint(FixCom())
    rng = np.random.default_rng(11)
    friction = 0.05 / ase.units.fs
    dyn = Langevin(
        atoms, 5 * ase.units.fs, temperature_K=target, friction=friction, fixcm=False, rng=rng
    )
    dyn.run(200)
    samples = []
    dyn.attach(lambda: samples.append(atoms.get_temperature()), interval=1)
    dyn.run(800)
    ours_now = temperature(atoms.get_velocities(), atoms.get_masses(), ase.units.kB)
    assert atoms.get_temperature() == pytest.approx(ours_now, rel=1e-12)
    assert np.mean(samples) == pytest.approx(target, rel=0.03)


@pytest.mark.parametrize("cells", [4, (1, 2, 3)])
def test_spatial_sorting_changes_only_the_summation_order(cells):
    """Atoms held in cell order internally (re-sorted at every list rebuild) give the same
    trajectory as unsorted ones, to round-off; small cells are replicated and sorted too."""
    from ase.md.verlet import VelocityVerlet

    start = liquid() if cells == 4 else argon(cells=cells, rattle=0.1)
    runs = {}
    for sort in (False, True):
        atoms = start.copy()
        atoms.set_momenta(start.get_momenta())
        atoms.calc = ours(skin=0.3, sort_atoms=sort)
        dyn = VelocityVerlet(atoms, timestep=5 * ase.units.fs)
        dyn.run(100)
        runs[sort] = atoms
        assert atoms.calc.forcefield.neighbor_list.n_builds > 2  # re-sorted along the way
        _close(atoms.get_stresses(), runs[False].get_stresses(), rtol=1e-9)
        _close(atoms.get_potential_energies(), runs[False].get_potential_energies(), rtol=1e-9)
    assert runs[True].calc._order is not None and runs[False].calc._order is None
    np.testing.assert_allclose(runs[True].positions, runs[False].positions, atol=1e-9)
    _close(runs[True].get_forces(), runs[False].get_forces(), rtol=1e-8)
    assert runs[True].get_potential_energy() == pytest.approx(
        runs[False].get_potential_energy(), rel=1e-11
    )


def test_bonded_terms_keep_atom_indices():
    """Springs name atoms by index: the calculator neither sorts nor replicates them, and
    spring forces are the analytic -k (r - r0) along each bond."""
    from potentials import HarmonicBonds

    atoms = argon(cells=4, rattle=0.1)
    bonds = np.array([[0, 5], [7, 200], [100, 101]])
    springs = HarmonicBonds(bonds, k=0.5, r0=3.0)
    lj = LennardJones(epsilon=EPSILON, sigma=SIGMA, cutoff=CUTOFF)
    atoms.calc = MDCalculator([lj, springs], sort_atoms=True)
    alone = atoms.copy()
    alone.calc = MDCalculator([lj])
    spring_forces = atoms.get_forces() - alone.get_forces()
    expected = np.zeros_like(spring_forces)
    for i, j in bonds:
        d = atoms.get_distance(i, j, mic=True, vector=True)  # from i to j
        r = np.linalg.norm(d)
        expected[i] += 0.5 * (r - 3.0) * d / r
        expected[j] -= 0.5 * (r - 3.0) * d / r
    np.testing.assert_allclose(spring_forces, expected, rtol=0, atol=1e-12)
    assert atoms.calc._order is None
    small = argon(cells=1)
    small.calc = MDCalculator([lj, HarmonicBonds([[0, 1]], k=0.5, r0=3.0)])
    with pytest.raises(ValueError, match="cannot replicate"):
        small.get_forces()


def test_mixed_precision_forces_equal_double_ones_to_float32_round_off():
    """precision="mixed" reaches the pair frame: forces, energy and stress within float32
    round-off of double's, and not equal to them (the float32 path really ran)."""
    atoms = argon(cells=4, rattle=0.1)
    atoms.calc = ours()
    forces, energy, stress = (atoms.get_forces(), atoms.get_potential_energy(), atoms.get_stress())
    mixed = atoms.copy()
    mixed.calc = ours(precision="mixed")
    scale = np.abs(forces).max()
    gap = np.abs(mixed.get_forces() - forces).max() / scale
    assert 0 < gap < 1e-5, gap
    assert mixed.get_potential_energy() == pytest.approx(energy, rel=1e-6)
    np.testing.assert_allclose(mixed.get_stress(), stress, rtol=0, atol=1e-6 * np.abs(stress).max())
    assert mixed.calc.forcefield.precision == "mixed"


def test_an_unknown_precision_is_refused_naming_it():
    with pytest.raises(ValueError, match="half"):
        ours(precision="half")


def test_an_evaluation_copies_the_atoms_once_and_keeps_an_equal_copy(monkeypatch):
    """ASE's get_property copies the atoms before calculate; calculate keeps that copy
    rather than make a second (ASE's Calculator.calculate would), and copies the atoms
    itself when it is called directly on atoms that differ from the copy it holds."""
    atoms = argon(cells=3)
    atoms.calc = ours()
    atoms.get_forces()
    copies = []
    original = ase.Atoms.copy

    def counted(self):
        copies.append(self)
        return original(self)

    monkeypatch.setattr(ase.Atoms, "copy", counted)
    atoms.positions += 0.01
    forces = atoms.get_forces()
    assert len(copies) <= 1  # none: positions alone changed (tests/test_step_overhead.py)
    assert atoms.calc.atoms is not atoms
    assert np.array_equal(atoms.calc.atoms.positions, atoms.positions)
    fresh = atoms.copy()
    fresh.calc = ours()
    np.testing.assert_allclose(forces, fresh.get_forces(), rtol=0, atol=1e-12)
    # a direct call after the atoms changed behind a check_state: a copy of the new atoms
    atoms.calc.check_state(atoms)
    atoms.positions += 0.01
    copies.clear()
    atoms.calc.calculate(atoms, ["energy", "forces"])
    assert len(copies) == 1
    assert np.array_equal(atoms.calc.atoms.positions, atoms.positions)
