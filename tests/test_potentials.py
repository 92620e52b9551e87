"""Potentials: a contract every registered potential must meet, then Lennard-Jones physics.

The contract suite runs over ``potentials.POTENTIALS``: a new registry entry
needs a factory in ``FACTORIES`` below, or its contract tests fail.
"""

from __future__ import annotations

import functools
import tempfile
from pathlib import Path

import ase.calculators.lj
import numpy as np
import pytest

import md
from md.neighbors import NeighborList
from md.thermo import pressure
from potentials import (
    POTENTIALS,
    Buckingham,
    CosineAngles,
    FENEBonds,
    HarmonicAngles,
    HarmonicBonds,
    LennardJones,
    Mie,
    Morse,
    Soft,
    Table,
    Yukawa,
)

R_MIN = 2.0 ** (1.0 / 6.0)
FD_STEP = 1e-6  # central-difference step [length]
KINK_MARGIN = 1e-3  # no pair this close to a cutoff or switching onset in FD checks


# ------------------------------------------------------------------ factories


def _lj(cutoff_mode):
    """Two types, mixed and overridden pairs, three different pair cutoffs."""
    return LennardJones(
        epsilon=[1.0, 0.6],
        sigma=[1.0, 1.15],
        cutoff=2.4,
        cutoff_mode=cutoff_mode,
        pairs={(0, 1): {"epsilon": 0.8, "cutoff": 2.1}, (1, 1): {"cutoff": 2.45, "r_on": 1.9}},
    )


def _lj_kinks(potential, ti, tj):
    """Distances where a pair energy or its derivatives are not smooth (cutoff, r_on)."""
    p = potential.pair_parameters(ti, tj)
    return [p["cutoff"], p["r_on"]]


def _pair_variants(build):
    """One variant per cutoff mode of a pair style (``build(mode)``)."""
    return {mode: (lambda mode=mode: build(mode)) for mode in ("none", "shift", "smooth")}


#: Two-type pair styles for the contract: explicit pairs, per-pair cutoffs and r_on.
PAIRS = {(0, 1): {"cutoff": 2.1}, (1, 1): {"cutoff": 2.45, "r_on": 1.9}}


@functools.cache
def contract_table_file() -> Path:
    """A LAMMPS table file (Morse-like, two sections: R and RSQ spacing) in a temporary
    folder, for the table style's contract variants."""
    folder = Path(tempfile.mkdtemp(prefix="leapmd-table-"))
    path = folder / "contract.table"
    lines = ["# contract table", ""]
    for keyword, spacing in (("DENSE", "R"), ("SQUARED", "RSQ")):
        n, low, high = 3000, 0.5, 2.6
        i = np.arange(n)
        r = low + (high - low) * i / (n - 1)
        if spacing == "RSQ":
            r = np.sqrt(low**2 + (high**2 - low**2) * i / (n - 1))
        e = np.exp(-2.0 * (r - 1.1)) - 2.0 * np.exp(-(r - 1.1))
        f = 2.0 * (np.exp(-2.0 * (r - 1.1)) - np.exp(-(r - 1.1)))
        lines += [keyword, f"N {n} {spacing} {low} {high}", ""]
        lines += [f"{k + 1} {r[k]:.17g} {e[k]:.17g} {f[k]:.17g}" for k in range(n)]
        lines.append("")
    path.write_text("\n".join(lines))
    return path


def _contract_bonds():
    """Bonds among atoms 0..59 (every contract system has at least 60): a chain,
    cross-links, one bond listed twice. Random atoms are far apart, so the
    FENE factories use an r_max beyond every minimum-image distance (< 9)."""
    chain = [(i, i + 1) for i in range(59)]
    cross = [(0, 30), (7, 52), (44, 13), (21, 3), (59, 0), (25, 26)]
    return np.array(chain + cross)


def _bond_types(n_types):
    return np.arange(len(_contract_bonds())) % n_types


def _contract_angles():
    """Angles among atoms 0..59: consecutive triples, others across the system, one
    listed twice."""
    chain = [(i, i + 1, i + 2) for i in range(58)]
    cross = [(0, 30, 59), (7, 52, 13), (44, 13, 7), (21, 3, 40), (25, 26, 27)]
    return np.array(chain + cross)


def _angle_types(n_types):
    return np.arange(len(_contract_angles())) % n_types


def _no_kinks(potential, ti, tj):
    """Bond energies are smooth in the positions (within their range)."""
    return []


#: registry name -> {"variants": {id: zero-argument builder}, "kinks": f(potential, ti, tj)}
FACTORIES = {
    "morse": {
        "variants": _pair_variants(
            lambda mode: Morse(
                d0=0.8,
                alpha=2.5,
                r0=1.1,
                cutoff=2.4,
                cutoff_mode=mode,
                pairs={**PAIRS, (0, 1): {"cutoff": 2.1, "d0": 1.3}},
            )
        ),
        "kinks": _lj_kinks,
    },
    "mie": {
        "variants": _pair_variants(
            lambda mode: Mie(
                epsilon=[1.0, 0.6],
                sigma=[1.0, 1.15],
                n=[14.0, 12.0],
                m=6.5,
                cutoff=2.4,
                cutoff_mode=mode,
                pairs=PAIRS,
            )
        ),
        "kinks": _lj_kinks,
    },
    "buckingham": {
        "variants": _pair_variants(
            lambda mode: Buckingham(
                a=2000.0,
                rho=0.15,
                c=1.0,
                cutoff=2.4,
                cutoff_mode=mode,
                pairs={**PAIRS, (1, 1): {"cutoff": 2.45, "c": 1.5}},
            )
        ),
        "kinks": _lj_kinks,
    },
    "yukawa": {
        "variants": _pair_variants(
            lambda mode: Yukawa(a=[2.0, 1.0], kappa=1.5, cutoff=2.4, cutoff_mode=mode, pairs=PAIRS)
        ),
        "kinks": _lj_kinks,
    },
    "soft": {
        "variants": _pair_variants(
            lambda mode: Soft(
                a=[1.0, 3.0], cutoff=1.3, cutoff_mode=mode, pairs={(0, 1): {"cutoff": 1.1}}
            )
        ),
        "kinks": _lj_kinks,
    },
    "table": {
        "variants": {
            "spline-none": lambda: Table(
                contract_table_file(),
                "DENSE",
                "spline",
                cutoff=2.4,
                pairs={(0, 1): {"keyword": "SQUARED", "cutoff": 2.1}},
            ),
            "spline-shift": lambda: Table(
                contract_table_file(), "SQUARED", "spline", cutoff=2.45, cutoff_mode="shift"
            ),
        },
        "kinks": _lj_kinks,
    },
    "lj": {
        "variants": {mode: (lambda mode=mode: _lj(mode)) for mode in ("none", "shift", "smooth")},
        "kinks": _lj_kinks,
    },
    "spring": {
        "variants": {
            "uniform": lambda: HarmonicBonds(_contract_bonds(), k=2.5, r0=1.1),
            "typed": lambda: HarmonicBonds(
                _contract_bonds(), k=[1.0, 3.0, 0.5], r0=[0.0, 1.2, 2.0], bond_types=_bond_types(3)
            ),
        },
        "kinks": _no_kinks,
    },
    "fene": {
        "variants": {
            "uniform": lambda: FENEBonds(_contract_bonds(), k=7.0, r_max=10.0),
            "typed": lambda: FENEBonds(
                _contract_bonds(), k=[30.0, 5.0], r_max=[10.0, 14.0], bond_types=_bond_types(2)
            ),
        },
        "kinks": _no_kinks,
    },
    "angle_harmonic": {
        "variants": {
            "uniform": lambda: HarmonicAngles(_contract_angles(), k=2.5, theta0=109.5),
            "typed": lambda: HarmonicAngles(
                _contract_angles(),
                k=[1.0, 3.0, 0.5],
                theta0=[180.0, 75.0, 0.0],
                angle_types=_angle_types(3),
            ),
        },
        "kinks": _no_kinks,  # random triples are never within 0.06 degrees of 0 or 180
    },
    "angle_cosine": {
        "variants": {
            "uniform": lambda: CosineAngles(_contract_angles(), k=1.7),
            "typed": lambda: CosineAngles(
                _contract_angles(), k=[4.0, 0.25], angle_types=_angle_types(2)
            ),
        },
        "kinks": _no_kinks,
    },
}


def _contract_cases():
    for name in POTENTIALS:
        spec = FACTORIES.get(name)
        if spec is None:
            yield pytest.param((name, None), id=f"{name}-NO-FACTORY")
            continue
        # The pair styles beyond LJ, Morse and the table compile a term each on a cold
        # cache: their contracts run with -m slow.
        slow = name in ("mie", "buckingham", "yukawa", "soft")
        for variant in spec["variants"]:
            yield pytest.param(
                (name, variant), id=f"{name}-{variant}", marks=pytest.mark.slow if slow else ()
            )


CONTRACT_CASES = list(_contract_cases())


def test_every_registered_potential_has_a_factory():
    missing = sorted(set(POTENTIALS) - set(FACTORIES))
    assert not missing, f"add test factories for POTENTIALS entries {missing} in {__file__}"


@pytest.fixture(params=CONTRACT_CASES)
def case(request):
    name, variant = request.param
    if variant is None:
        pytest.fail(f"POTENTIALS[{name!r}] has no factory in tests/test_potentials.py FACTORIES")
    spec = FACTORIES[name]
    potential = spec["variants"][variant]()
    assert isinstance(potential, POTENTIALS[name])
    return potential, spec["kinks"]


PERIODIC_SYSTEMS = ["gas-periodic", "fcc-periodic"]
OPEN_SYSTEMS = ["cluster-open"]


def _build_system(name, random_gas, fcc_lattice):
    """Two-type test systems; every periodic edge exceeds twice the longest LJ cutoff."""
    if name == "gas-periodic":
        return random_gas(90, 6.5, n_types=2, min_distance=0.85, images=2)
    if name == "fcc-periodic":
        return fcc_lattice(cells=3, perturbation=0.06, n_types=2)
    return random_gas(60, 5.0, pbc=False, n_types=2, min_distance=0.85)


@pytest.fixture(params=PERIODIC_SYSTEMS + OPEN_SYSTEMS)
def system(request, random_gas, fcc_lattice):
    return _build_system(request.param, random_gas, fcc_lattice)


@pytest.fixture(params=PERIODIC_SYSTEMS)
def periodic_system(request, random_gas, fcc_lattice):
    return _build_system(request.param, random_gas, fcc_lattice)


@pytest.fixture(params=OPEN_SYSTEMS)
def open_system(request, random_gas, fcc_lattice):
    return _build_system(request.param, random_gas, fcc_lattice)


def _distances(state):
    d = state.positions[:, None, :] - state.positions[None, :, :]
    for axis in range(3):
        if state.pbc[axis]:
            d[..., axis] -= state.box[axis] * np.round(d[..., axis] / state.box[axis])
    r = np.sqrt(np.einsum("ijk,ijk->ij", d, d))
    np.fill_diagonal(r, np.inf)
    return r


def _near_kink(potential, kinks, state, margin):
    """(N, N) bool: pair (i, j) lies within ``margin`` of one of its kinks."""
    r = _distances(state)
    near = np.zeros(r.shape, dtype=bool)
    for ti in range(state.n_types):
        for tj in range(state.n_types):
            mask = (state.types[:, None] == ti) & (state.types[None, :] == tj)
            for kink in kinks(potential, ti, tj):
                near |= mask & (np.abs(r - kink) < margin)
    return near


def _scale(result):
    return max(1.0, float(np.abs(result.forces).max()))


def _energy(potential, state):
    return potential.energy_forces(state, None).energy


def _strained(state, factors):
    """Copy of ``state`` with positions and box scaled per axis by ``factors``."""
    out = state.copy()
    out.positions *= factors
    out.box *= factors
    return out


# ------------------------------------------------------------------- contract


def test_forces_match_central_differences(case, system):
    potential, kinks = case
    result = potential.energy_forces(system, None)
    clean = np.flatnonzero(~_near_kink(potential, kinks, system, KINK_MARGIN).any(axis=1))
    assert len(clean) >= 10, "too few atoms away from the kinks; change the system"
    checked = clean[:: max(1, len(clean) // 12)]
    numeric = np.zeros((len(checked), 3))
    for row, i in enumerate(checked):
        for axis in range(3):
            state = system.copy()
            state.positions[i, axis] += FD_STEP
            up = _energy(potential, state)
            state.positions[i, axis] -= 2 * FD_STEP
            down = _energy(potential, state)
            numeric[row, axis] = -(up - down) / (2 * FD_STEP)
    np.testing.assert_allclose(
        result.forces[checked], numeric, rtol=1e-6, atol=1e-6 * _scale(result)
    )


def test_forces_sum_to_zero(case, system):
    potential, _ = case
    result = potential.energy_forces(system, None)
    assert np.any(result.forces != 0.0)
    np.testing.assert_allclose(
        result.forces.sum(axis=0), 0.0, atol=1e-12 * system.n_atoms * _scale(result)
    )


def test_energy_is_translation_invariant(case, system, rng):
    potential, _ = case
    before = potential.energy_forces(system, None, per_atom=True)
    scale = max(1.0, float(np.abs(before.energies).sum()))
    moved = system.copy()
    moved.positions += [0.37, -1.3, 2.9]
    after = potential.energy_forces(moved, None)
    assert after.energy == pytest.approx(before.energy, rel=1e-12, abs=1e-12 * scale)
    np.testing.assert_allclose(after.forces, before.forces, rtol=1e-9, atol=1e-10 * _scale(before))
    if system.pbc.all():  # any atom may sit in any image of the box
        imaged = system.copy()
        imaged.positions += rng.integers(-3, 4, size=imaged.positions.shape) * imaged.box
        again = potential.energy_forces(imaged, None)
        assert again.energy == pytest.approx(before.energy, rel=1e-12, abs=1e-12 * scale)


def test_neighbor_list_result_equals_all_pairs(case, system, rng):
    potential, _ = case
    if potential.cutoff is None:
        pytest.skip("potential needs no neighbour list")
    skin = 0.3
    nl = NeighborList(potential.cutoff, skin)
    state = system.copy()
    for _ in range(3):  # the fresh list, then stale lists still within skin / 2
        nl.update(state)
        listed = potential.energy_forces(state, nl, per_atom=True)
        full = potential.energy_forces(state, None, per_atom=True)
        scale = max(1.0, float(np.abs(full.energies).sum()))
        assert listed.energy == pytest.approx(full.energy, rel=1e-12, abs=1e-12 * scale)
        np.testing.assert_allclose(
            listed.forces, full.forces, rtol=1e-12, atol=1e-12 * _scale(full)
        )
        np.testing.assert_allclose(
            listed.virial, full.virial, rtol=1e-12, atol=1e-12 * np.abs(full.virial).max()
        )
        np.testing.assert_allclose(listed.energies, full.energies, rtol=1e-12, atol=1e-12 * scale)
        directions = rng.normal(size=state.positions.shape)
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        state.positions += rng.uniform(0, 0.24 * skin, size=(state.n_atoms, 1)) * directions
    assert nl.n_builds <= 3


def test_per_atom_energies_sum_to_the_energy(case, system):
    potential, _ = case
    result = potential.energy_forces(system, None, per_atom=True)
    scale = max(1.0, float(np.abs(result.energies).sum()))
    assert result.energies.sum() == pytest.approx(result.energy, rel=1e-12, abs=1e-12 * scale)
    plain = potential.energy_forces(system, None)
    assert plain.energies is None
    assert plain.energy == result.energy


def test_per_atom_virials_sum_to_the_virial(case, system):
    potential, _ = case
    result = potential.energy_forces(system, None, per_atom=True)
    assert result.virials.shape == (system.n_atoms, 6)
    total = result.virials.sum(axis=0)
    voigt = result.virial[[0, 1, 2, 1, 0, 0], [0, 1, 2, 2, 2, 1]]  # xx yy zz yz xz xy
    scale = max(1.0, float(np.abs(result.virials).sum()))
    np.testing.assert_allclose(total, voigt, rtol=1e-12, atol=1e-12 * scale)
    assert potential.energy_forces(system, None).virials is None


def test_input_state_is_unchanged(case, system):
    potential, _ = case
    before = system.copy()
    potential.energy_forces(system, None, per_atom=True)
    if potential.cutoff is not None:
        nl = NeighborList(potential.cutoff, 0.3)
        nl.update(system)
        potential.energy_forces(system, nl, per_atom=True)
    for name in ("positions", "velocities", "masses", "box", "pbc", "types"):
        np.testing.assert_array_equal(getattr(system, name), getattr(before, name), err_msg=name)
    assert (system.step, system.time, system.type_names) == (0, 0.0, before.type_names)


def test_result_dtypes_and_shapes(case, system):
    potential, _ = case
    result = potential.energy_forces(system, None, per_atom=True)
    n = system.n_atoms
    assert np.isfinite(result.energy) and np.ndim(result.energy) == 0
    assert result.forces.shape == (n, 3) and result.forces.dtype == np.float64
    assert result.virial.shape == (3, 3) and result.virial.dtype == np.float64
    np.testing.assert_array_equal(result.virial, result.virial.T)  # pair virials are symmetric
    assert result.energies.shape == (n,) and result.energies.dtype == np.float64
    assert result.forces is not system.positions


def test_open_system_virial_is_sum_of_r_outer_f(case, open_system):
    """Without periodic images W = sum_i r_i (x) F_i, for any translation-invariant potential."""
    potential, _ = case
    result = potential.energy_forces(open_system, None)
    expected = np.einsum("ia,ib->ab", open_system.positions, result.forces)
    np.testing.assert_allclose(
        result.virial, expected, rtol=1e-10, atol=1e-10 * np.abs(expected).max()
    )


def test_diagonal_virial_is_minus_the_strain_derivative(case, system):
    """W_aa = -dE/d(eps_aa) under a uniaxial strain of positions and box."""
    potential, kinks = case
    h = 1e-6
    assert not _near_kink(potential, kinks, system, 10 * h * 3).any()
    virial = potential.energy_forces(system, None).virial
    for axis in range(3):
        up = np.ones(3)
        down = np.ones(3)
        up[axis] += h
        down[axis] -= h
        derivative = (
            _energy(potential, _strained(system, up)) - _energy(potential, _strained(system, down))
        ) / (2 * h)
        assert -derivative == pytest.approx(
            virial[axis, axis], rel=1e-6, abs=1e-6 * np.abs(virial).max()
        )


def test_virial_pressure_is_minus_dE_dV(case, periodic_system):
    """P = (2K + tr W) / (3V) with K = 0 equals -dE/dV under uniform scaling."""
    potential, kinks = case
    system = periodic_system
    relative = 1e-6  # dV / V
    assert not _near_kink(potential, kinks, system, 10 * relative).any()
    volume = system.volume
    result = potential.energy_forces(system, None)
    virial_pressure = pressure(0.0, result.virial, volume)
    bigger = _strained(system, (1 + relative) ** (1 / 3))
    smaller = _strained(system, (1 - relative) ** (1 / 3))
    assert bigger.volume == pytest.approx(volume * (1 + relative), rel=1e-14)
    numeric = -(_energy(potential, bigger) - _energy(potential, smaller)) / (2 * relative * volume)
    scale = np.abs(result.virial).max() / volume
    assert virial_pressure == pytest.approx(numeric, rel=1e-6, abs=1e-6 * scale)


# -------------------------------------------------------- Lennard-Jones values


def _lj_formula(r, epsilon, sigma):
    x6 = (sigma / r) ** 6
    return 4.0 * epsilon * (x6 * x6 - x6)


def _lj_force_formula(r, epsilon, sigma):
    """-du/dr."""
    x6 = (sigma / r) ** 6
    return 24.0 * epsilon * (2.0 * x6 * x6 - x6) / r


def _pair(potential, r, ti=0, tj=0):
    """(energy, force on the second atom along +x) of a dimer at distance r."""
    state = md.State(
        positions=[[0.0, 0.0, 0.0], [r, 0.0, 0.0]], box=50.0, pbc=False, types=[ti, tj]
    )
    result = potential.energy_forces(state, None)
    assert result.forces[0, 0] == -result.forces[1, 0]
    return result.energy, result.forces[1, 0]


def test_lj_minimum_is_minus_epsilon_at_two_to_the_sixth_sigma(dimer):
    epsilon, sigma = 0.7, 1.3
    lj = LennardJones(epsilon=epsilon, sigma=sigma, cutoff=10.0, cutoff_mode="none")
    result = lj.energy_forces(dimer(r=R_MIN * sigma, box=30.0), None, per_atom=True)
    assert result.energy == pytest.approx(-epsilon, rel=1e-14)
    np.testing.assert_allclose(result.forces, 0.0, atol=1e-13)
    np.testing.assert_allclose(result.energies, -0.5 * epsilon, rtol=1e-14)
    assert lj.pair_energy(R_MIN * sigma) == pytest.approx(-epsilon, rel=1e-14)
    # Repulsive inside the minimum, attractive outside, zero at r = sigma.
    assert _pair(lj, 0.99 * R_MIN * sigma)[1] > 0 > _pair(lj, 1.01 * R_MIN * sigma)[1]
    assert lj.pair_energy(sigma) == pytest.approx(0.0, abs=1e-14)


@pytest.mark.parametrize("r", [0.9, 1.0, 1.5, 2.2, 2.999])
def test_lj_values_and_forces_follow_the_formula(r):
    lj = LennardJones(epsilon=1.7, sigma=1.1, cutoff=3.0, cutoff_mode="none")
    energy, force = _pair(lj, r)
    assert energy == pytest.approx(_lj_formula(r, 1.7, 1.1), rel=1e-13)
    assert force == pytest.approx(_lj_force_formula(r, 1.7, 1.1), rel=1e-13)


def test_truncated_lj_is_zero_beyond_the_cutoff():
    lj = LennardJones(cutoff=2.5, cutoff_mode="none")
    assert _pair(lj, 2.5 - 1e-9)[0] == pytest.approx(_lj_formula(2.5, 1.0, 1.0), rel=1e-6)
    assert _pair(lj, 2.5 + 1e-9) == (0.0, 0.0)


def test_shifted_lj_energy_is_continuous_at_the_cutoff():
    rc = 2.5
    lj = LennardJones(epsilon=1.3, sigma=1.0, cutoff=rc, cutoff_mode="shift")
    below, force_below = _pair(lj, rc - 1e-9)
    assert abs(below) < 1e-8
    assert _pair(lj, rc + 1e-9) == (0.0, 0.0)
    # Below the cutoff: plain LJ minus u(rc), the force untouched (so it jumps at rc).
    for r in (1.0, 1.7, 2.4):
        energy, force = _pair(lj, r)
        shifted = _lj_formula(r, 1.3, 1.0) - _lj_formula(rc, 1.3, 1.0)
        assert energy == pytest.approx(shifted, rel=1e-13)
        assert force == pytest.approx(_lj_force_formula(r, 1.3, 1.0), rel=1e-13)
    assert force_below == pytest.approx(_lj_force_formula(rc, 1.3, 1.0), rel=1e-6)


@pytest.mark.parametrize("r_on", [None, 2.0])
def test_smooth_lj_energy_and_force_vanish_continuously_at_the_cutoff(r_on):
    rc = 2.5
    lj = LennardJones(epsilon=1.0, sigma=1.0, cutoff=rc, cutoff_mode="smooth", r_on=r_on)
    plain = LennardJones(epsilon=1.0, sigma=1.0, cutoff=rc, cutoff_mode="none")
    onset = lj.pair_parameters(0, 0)["r_on"]
    assert onset == (0.66 * rc if r_on is None else r_on)
    # Plain LJ below r_on.
    for r in np.linspace(0.9, onset - 1e-9, 7):
        assert _pair(lj, r) == pytest.approx(_pair(plain, r), rel=1e-14)
    # Continuous at r_on (energy and force).
    np.testing.assert_allclose(_pair(lj, onset + 1e-9), _pair(lj, onset - 1e-9), rtol=1e-7)
    # Switched tail: smaller in magnitude than plain LJ, same sign.
    for r in np.linspace(onset + 0.01, rc - 0.01, 5):
        energy, _ = _pair(lj, r)
        assert 0 < energy / _lj_formula(r, 1.0, 1.0) < 1
    # Near rc the switch goes as (rc - r)^2, so u ~ (rc - r)^2 and F ~ (rc - r).
    e1, f1 = _pair(lj, rc - 1e-4)
    e2, f2 = _pair(lj, rc - 2e-4)
    assert abs(e1) < 1e-7 and abs(f1) < 1e-3
    assert e2 / e1 == pytest.approx(4.0, rel=1e-3)
    assert f2 / f1 == pytest.approx(2.0, rel=1e-3)
    assert _pair(lj, rc + 1e-12) == (0.0, 0.0)


# ------------------------------------------------------------------ multi-type


@pytest.mark.parametrize(
    ("mixing", "sigma_01"),
    [("lorentz-berthelot", 1.5), ("geometric", np.sqrt(2.0))],
)
def test_mixing_rules(mixing, sigma_01):
    lj = LennardJones(
        epsilon=[1.0, 0.5], sigma=[1.0, 2.0], cutoff=6.0, cutoff_mode="none", mixing=mixing
    )
    epsilon_01 = np.sqrt(0.5)
    params = lj.pair_parameters(0, 1)
    assert params["epsilon"] == pytest.approx(epsilon_01, rel=1e-15)
    assert params["sigma"] == pytest.approx(sigma_01, rel=1e-15)
    for ti, tj, eps, sig in [(0, 0, 1.0, 1.0), (1, 1, 0.5, 2.0), (0, 1, epsilon_01, sigma_01)]:
        for r in (0.95 * sig, R_MIN * sig, 1.8 * sig):
            expected = _lj_formula(r, eps, sig)
            assert lj.pair_energy(r, ti, tj) == pytest.approx(expected, rel=1e-13)
            assert lj.pair_energy(r, tj, ti) == pytest.approx(expected, rel=1e-13)
        assert lj.pair_energy(R_MIN * sig, ti, tj) == pytest.approx(-eps, rel=1e-14)


def test_explicit_pair_parameters_override_mixing():
    base = {"epsilon": [1.0, 0.5], "sigma": [1.0, 2.0], "cutoff": 6.0, "cutoff_mode": "none"}
    lj = LennardJones(**base, pairs={(1, 0): {"epsilon": 0.3, "sigma": 1.1}})
    mixed = LennardJones(**base)
    for ti, tj in [(0, 1), (1, 0)]:
        assert lj.pair_energy(R_MIN * 1.1, ti, tj) == pytest.approx(-0.3, rel=1e-14)
    for t in (0, 1):
        for r in (1.0, 2.0, 3.0):
            assert lj.pair_energy(r, t, t) == mixed.pair_energy(r, t, t)


def test_pair_cutoffs():
    lj = LennardJones(
        epsilon=[1.0, 1.0],
        sigma=[1.0, 1.0],
        cutoff=2.5,
        cutoff_mode="shift",
        pairs={(0, 1): {"cutoff": 1.8}, (1, 1): {"cutoff": 3.0}},
    )
    assert lj.cutoff == 3.0  # the neighbour list must reach the longest pair cutoff
    assert lj.pair_energy(2.0, 0, 1) == 0.0
    assert lj.pair_energy(2.0, 0, 0) == pytest.approx(
        _lj_formula(2.0, 1, 1) - _lj_formula(2.5, 1, 1), rel=1e-13
    )
    assert lj.pair_energy(2.8, 0, 0) == 0.0
    assert lj.pair_energy(2.8, 1, 1) == pytest.approx(
        _lj_formula(2.8, 1, 1) - _lj_formula(3.0, 1, 1), rel=1e-13
    )
    # Each pair is shifted at its own cutoff.
    assert abs(lj.pair_energy(1.8 - 1e-9, 0, 1)) < 1e-7
    assert abs(lj.pair_energy(1.8 - 1e-9, 1, 0)) < 1e-7


def _reference_lj(state, params, shift):
    """Independent numpy all-pairs LJ; params[(ti, tj)] = (epsilon, sigma, cutoff)."""
    d = state.positions[:, None, :] - state.positions[None, :, :]
    for axis in range(3):
        if state.pbc[axis]:
            d[..., axis] -= state.box[axis] * np.round(d[..., axis] / state.box[axis])
    r = np.sqrt(np.einsum("ijk,ijk->ij", d, d))
    np.fill_diagonal(r, np.inf)
    n = state.n_atoms
    epsilon, sigma, cutoff = np.zeros((3, n, n))
    for (ti, tj), (eps, sig, rc) in params.items():
        for a, b in [(ti, tj), (tj, ti)]:
            mask = (state.types[:, None] == a) & (state.types[None, :] == b)
            epsilon[mask], sigma[mask], cutoff[mask] = eps, sig, rc
    inside = r < cutoff
    u = np.where(inside, _lj_formula(r, epsilon, sigma), 0.0)
    if shift:
        u -= np.where(inside, _lj_formula(cutoff, epsilon, sigma), 0.0)
    f_over_r = np.where(inside, _lj_force_formula(r, epsilon, sigma) / r, 0.0)
    forces = np.einsum("ij,ijk->ik", f_over_r, d)
    return 0.5 * u.sum(), forces


@pytest.mark.parametrize("mode", ["none", "shift"])
def test_multi_type_system_matches_an_independent_reference(mode, random_gas):
    state = random_gas(120, 7.0, n_types=3, min_distance=0.8, images=1)
    lj = LennardJones(
        epsilon=[1.0, 0.4, 2.0],
        sigma=[1.0, 1.3, 0.9],
        cutoff=2.6,
        cutoff_mode=mode,
        pairs={
            (0, 2): {"epsilon": 0.1, "cutoff": 2.0},
            (1, 2): {"sigma": 1.0},
            (2, 2): {"cutoff": 3.1},
        },
    )
    params = {
        (0, 0): (1.0, 1.0, 2.6),
        (1, 1): (0.4, 1.3, 2.6),
        (2, 2): (2.0, 0.9, 3.1),
        (0, 1): (np.sqrt(0.4), 1.15, 2.6),
        (0, 2): (0.1, 0.95, 2.0),
        (1, 2): (np.sqrt(0.8), 1.0, 2.6),
    }
    energy, forces = _reference_lj(state, params, shift=mode == "shift")
    nl = NeighborList(lj.cutoff, 0.3)
    nl.update(state)
    result = lj.energy_forces(state, nl)
    assert result.energy == pytest.approx(energy, rel=1e-12)
    np.testing.assert_allclose(result.forces, forces, rtol=1e-10, atol=1e-10 * np.abs(forces).max())


def _cell_matrix(state):
    """Rows a, b, c: the cell vectors (LAMMPS's convention: a = (lx, 0, 0), b = (xy, ly, 0),
    c = (xz, yz, lz))."""
    (lx, ly, lz), (xy, xz, yz) = state.box, state.tilt
    return np.array([[lx, 0.0, 0.0], [xy, ly, 0.0], [xz, yz, lz]])


def _numpy_lj(state, table, mode):
    """LJ written out in numpy, independent of the engine: every pair (i < j) at each of
    its periodic images (-1, 0, 1 cells along each periodic axis; positions wrapped
    first), the cutoff treatment of ``mode`` (the shift, or S(s) u(s) with
    S = (rc2 - s)^2 (rc2 + 2 s - 3 ro2) / (rc2 - ro2)^3 between ro2 and rc2).
    ``table[ti][tj]`` = (epsilon, sigma, cutoff, r_on). Returns energy, forces,
    virial (3, 3), per-atom energies and per-atom virials (xx, yy, zz, yz, xz, xy), and
    the (3N, 3N) Hessian."""
    h = _cell_matrix(state)
    fractional = np.linalg.solve(h.T, state.positions.T).T
    fractional -= np.floor(fractional) * state.pbc
    x = fractional @ h
    n = state.n_atoms
    energies, forces = np.zeros(n), np.zeros((n, 3))
    virials, hessian = np.zeros((n, 6)), np.zeros((3 * n, 3 * n))
    ranges = [(-1, 0, 1) if periodic else (0,) for periodic in state.pbc]
    shifts = np.array([[a, b, c] for a in ranges[0] for b in ranges[1] for c in ranges[2]]) @ h
    i, j = np.triu_indices(n, 1)
    d = (x[i] - x[j])[:, None, :] + shifts[None, :, :]  # (pairs, images, 3)
    i = np.repeat(i, len(shifts))
    j = np.repeat(j, len(shifts))
    d = d.reshape(-1, 3)
    s = np.einsum("ij,ij->i", d, d)
    eps, sigma, rc, ro = np.asarray(table)[state.types[i], state.types[j]].T
    keep = s < rc**2
    i, j, d, s, eps, sigma, rc2, ro2 = (v[keep] for v in (i, j, d, s, eps, sigma, rc**2, ro**2))
    c6, c12 = 4.0 * eps * sigma**6, 4.0 * eps * sigma**12
    # u(s) and its derivatives in s = r^2.
    g = c12 / s**6 - c6 / s**3
    g1 = -6.0 * c12 / s**7 + 3.0 * c6 / s**4
    g2 = 42.0 * c12 / s**8 - 12.0 * c6 / s**5
    if mode == "shift":
        g = g - (c12 / rc2**6 - c6 / rc2**3)
    elif mode == "smooth":
        den = (rc2 - ro2) ** 3
        on = s > ro2
        switch = np.where(on, (rc2 - s) ** 2 * (rc2 + 2.0 * s - 3.0 * ro2) / den, 1.0)
        d1 = np.where(on, 6.0 * (rc2 - s) * (ro2 - s) / den, 0.0)
        d2 = np.where(on, 6.0 * (2.0 * s - ro2 - rc2) / den, 0.0)
        g, g1, g2 = switch * g, d1 * g + switch * g1, d2 * g + 2.0 * d1 * g1 + switch * g2
    pair_forces = -2.0 * g1[:, None] * d  # on i; -grad_i u = -u'(s) 2 d
    np.add.at(forces, i, pair_forces)
    np.add.at(forces, j, -pair_forces)
    np.add.at(energies, i, 0.5 * g)
    np.add.at(energies, j, 0.5 * g)
    w = np.einsum("pa,pb->pab", pair_forces, d)
    voigt = w[:, [0, 1, 2, 2, 2, 1], [0, 1, 2, 1, 0, 0]]
    np.add.at(virials, i, 0.5 * voigt)
    np.add.at(virials, j, 0.5 * voigt)
    blocks = 2.0 * g1[:, None, None] * np.eye(3) + 4.0 * g2[:, None, None] * np.einsum(
        "pa,pb->pab", d, d
    )
    for a in range(3):
        for b in range(3):
            np.add.at(hessian, (3 * i + a, 3 * i + b), blocks[:, a, b])
            np.add.at(hessian, (3 * j + a, 3 * j + b), blocks[:, a, b])
            np.add.at(hessian, (3 * i + a, 3 * j + b), -blocks[:, a, b])
            np.add.at(hessian, (3 * j + a, 3 * i + b), -blocks[:, a, b])
    return g.sum(), forces, w.sum(axis=0), energies, virials, hessian


@pytest.mark.parametrize("cell", ["orthorhombic", "tilted", "slab"])
@pytest.mark.parametrize("mode", ["none", "shift", "smooth"])
def test_lj_equals_lj_written_out_in_numpy(mode, cell, fcc_lattice):
    """LJ on the pair frame against LJ written out in numpy (every image of every pair):
    three types mixed by Lorentz-Berthelot, an explicit unlike pair with its own cutoff
    and r_on, another like pair with its own cutoff; the energy, forces, virial (the
    threaded slot-frame kernel), the per-atom energies and virials (atom-order kernel)
    and the Hessian to 1e-12 of the largest value, in every cutoff mode and cell shape."""
    state = fcc_lattice(cells=5, perturbation=0.07, n_types=3)
    if cell == "tilted":
        state.tilt = np.array([0.2, -0.15, 0.1]) * state.box[[0, 0, 1]]
    elif cell == "slab":
        state.pbc = np.array([True, True, False])
    epsilon, sigma = [1.0, 0.4, 2.0], [1.0, 1.3, 0.9]
    lj = LennardJones(
        epsilon=epsilon,
        sigma=sigma,
        cutoff=2.6,
        cutoff_mode=mode,
        r_on=2.0,
        pairs={(0, 2): {"epsilon": 0.1, "cutoff": 2.2, "r_on": 1.7}, (1, 1): {"cutoff": 2.8}},
    )
    table = [
        [
            (np.sqrt(epsilon[a] * epsilon[b]), 0.5 * (sigma[a] + sigma[b]), 2.6, 2.0)
            for b in range(3)
        ]
        for a in range(3)
    ]
    table[0][2] = table[2][0] = (0.1, table[0][2][1], 2.2, 1.7)
    table[1][1] = (*table[1][1][:2], 2.8, 2.0)
    energy, forces, virial, energies, virials, hessian = _numpy_lj(state, table, mode)
    nl = NeighborList(lj.cutoff, 0.3)
    nl.update(state)
    assert nl.frame is not None  # the slot-frame kernel, not the atom-order one

    def close(ours, theirs):
        np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-12 * np.abs(theirs).max())

    fast = lj.energy_forces(state, nl, virial=True)
    per_atom = lj.energy_forces(state, nl, per_atom=True)
    for result in (fast, per_atom):
        assert result.energy == pytest.approx(energy, rel=1e-12)
        close(result.forces, forces)
        close(result.virial, virial)
    close(per_atom.energies, energies)
    close(per_atom.virials, virials)
    close(lj.hessian(state, nl).toarray(), hessian)


def test_lj_rejects_more_types_than_it_has_parameters(random_gas):
    lj = LennardJones(epsilon=[1.0, 1.0], sigma=[1.0, 1.0])
    with pytest.raises(ValueError, match="types"):
        lj.check(random_gas(10, 6.0, n_types=3))


@pytest.mark.parametrize(
    "kwargs",
    [
        {"cutoff_mode": "cubic"},
        {"mixing": "arithmetic"},
        {"sigma": 0.0},
        {"epsilon": -1.0},
        {"cutoff": 0.0},
        {"epsilon": [1.0, 1.0], "sigma": [1.0]},
        {"cutoff_mode": "smooth", "r_on": 3.0, "cutoff": 2.5},
        {"pairs": {(0, 1): {"radius": 1.0}}},
    ],
)
def test_lj_rejects_invalid_parameters(kwargs):
    with pytest.raises(ValueError):
        LennardJones(**kwargs)


def test_neighbor_list_shorter_than_the_cutoff_is_rejected(random_gas):
    state = random_gas(20, 7.0)
    lj = LennardJones(cutoff=2.5)
    nl = NeighborList(2.0, skin=0.3)
    nl.update(state)
    with pytest.raises(ValueError, match="cutoff"):
        lj.energy_forces(state, nl)


# ------------------------------------------------------------------------ ASE


def _ase_systems(fcc_lattice, sigma):
    density = 0.8442 / sigma**3
    crystal = fcc_lattice(cells=3, density=density, perturbation=0.05 * sigma)
    cluster = fcc_lattice(cells=3, density=density, perturbation=0.05 * sigma, pbc=False)
    return {"crystal": crystal, "cluster": cluster}


def _voigt(matrix):
    return np.array(
        [matrix[0, 0], matrix[1, 1], matrix[2, 2], matrix[1, 2], matrix[0, 2], matrix[0, 1]]
    )


@pytest.mark.parametrize("geometry", ["crystal", "cluster"])
@pytest.mark.parametrize(("mode", "r_on"), [("shift", None), ("smooth", None), ("smooth", 2.2)])
def test_lj_matches_ase(mode, r_on, geometry, fcc_lattice):
    sigma, epsilon = 1.1, 0.8
    rc = 2.5 * sigma
    state = _ase_systems(fcc_lattice, sigma)[geometry]
    lj = LennardJones(epsilon=epsilon, sigma=sigma, cutoff=rc, cutoff_mode=mode, r_on=r_on)
    atoms = state.to_ase()
    atoms.calc = ase.calculators.lj.LennardJones(
        sigma=sigma, epsilon=epsilon, rc=rc, ro=r_on, smooth=mode == "smooth"
    )
    nl = NeighborList(rc, 0.3)
    nl.update(state)
    ours = lj.energy_forces(state, nl, per_atom=True)
    assert ours.energy == pytest.approx(atoms.get_potential_energy(), rel=1e-11)
    forces = atoms.get_forces()
    np.testing.assert_allclose(ours.forces, forces, rtol=1e-9, atol=1e-10 * np.abs(forces).max())
    np.testing.assert_allclose(ours.energies, atoms.get_potential_energies(), rtol=1e-9, atol=1e-11)
    stress = atoms.get_stress()  # Voigt xx, yy, zz, yz, xz, xy
    np.testing.assert_allclose(
        _voigt(-ours.virial / state.volume), stress, rtol=1e-9, atol=1e-11 * np.abs(stress).max()
    )


def test_ase_stress_convention_is_the_strain_derivative(fcc_lattice):
    """ASE's stress is (1/V) dE/d(strain), so -W/V is its sign-correct counterpart."""
    state = fcc_lattice(cells=3, perturbation=0.05)
    atoms = state.to_ase()
    atoms.calc = ase.calculators.lj.LennardJones(sigma=1.0, epsilon=1.0, rc=2.5)
    stress = atoms.get_stress(voigt=False)
    volume = atoms.get_volume()
    h = 1e-6
    for a, b in [(0, 0), (2, 2), (0, 1), (1, 2)]:
        energies = []
        for sign in (1, -1):
            strain = np.zeros((3, 3))
            strain[a, b] += 0.5 * sign * h
            strain[b, a] += 0.5 * sign * h
            strained = atoms.copy()
            strained.calc = atoms.calc
            strained.set_cell(atoms.cell[:] @ (np.eye(3) + strain), scale_atoms=True)
            energies.append(strained.get_potential_energy())
        derivative = (energies[0] - energies[1]) / (2 * h)
        assert stress[a, b] == pytest.approx(derivative / volume, rel=1e-5, abs=1e-8)


# ------------------------------------------------------- the vectorised slot-frame kernel
FRAME_CASES = {
    "one-type-shift": dict(cutoff=2.5, cutoff_mode="shift"),
    "one-type-none": dict(cutoff=2.5, cutoff_mode="none"),
    "one-type-smooth": dict(cutoff=2.5, cutoff_mode="smooth", r_on=2.1),
    "three-types-shift": dict(
        epsilon=[1.0, 0.4, 2.0],
        sigma=[1.0, 1.3, 0.9],
        cutoff=2.6,
        cutoff_mode="shift",
        pairs={(0, 2): {"epsilon": 0.1, "cutoff": 2.0}, (2, 2): {"cutoff": 3.1}},
    ),
    "three-types-smooth": dict(
        epsilon=[1.0, 0.4, 2.0],
        sigma=[1.0, 1.3, 0.9],
        cutoff=2.6,
        cutoff_mode="smooth",
        r_on=2.0,
    ),
}


@pytest.mark.parametrize("cell", ["orthorhombic", "tilted", "slab"])
@pytest.mark.parametrize(
    ("params", "threads"),
    [
        # each threaded variant compiles apart: one type shifted runs by default, the rest -m slow
        pytest.param(
            params,
            threads,
            id=f"{name}-{threads}",
            marks=pytest.mark.slow if threads == 2 and name != "one-type-shift" else (),
        )
        for name, params in FRAME_CASES.items()
        for threads in (1, 2)
    ],
)
def test_vectorised_frame_kernel_equals_the_per_atom_kernel(params, cell, threads, fcc_lattice):
    """The slot-frame kernel (gathered partners, a vectorised pair loop, scattered forces,
    reordered sums) gives the energy, forces and virial of the per-atom-index kernel to
    round-off, with one chunk or two, and the same bits on every evaluation."""
    from md.forcefield import ForceField
    from md.parallel import get_threads, set_threads

    state = fcc_lattice(cells=9, perturbation=0.08, n_types=3 if "epsilon" in params else 1)
    if cell == "tilted":
        state.tilt = np.array([0.2, -0.15, 0.1]) * state.box[[0, 0, 1]]
    elif cell == "slab":
        state.pbc = np.array([True, True, False])
    lj = LennardJones(**params)
    before = get_threads()
    try:
        set_threads(threads)
        ff = ForceField([lj], skin=0.3)
        fast = ff.compute(state, virial=True)
        assert ff.neighbor_list.frame is not None and ff.neighbor_list.frame.n_chunks == threads
        ff.invalidate()
        again = ff.compute(state, virial=True)
    finally:
        set_threads(before)
    reference = lj.energy_forces(state, ff.neighbor_list, per_atom=True)
    assert fast.energy == pytest.approx(reference.energy, rel=1e-12)
    np.testing.assert_allclose(
        fast.forces, reference.forces, rtol=0, atol=1e-11 * np.abs(reference.forces).max()
    )
    np.testing.assert_allclose(
        fast.virial, reference.virial, rtol=0, atol=1e-11 * np.abs(reference.virial).max()
    )
    assert again.energy == fast.energy
    assert np.array_equal(again.forces, fast.forces) and np.array_equal(again.virial, fast.virial)
    ff.invalidate()
    assert np.array_equal(ff.compute(state, virial=False).forces, fast.forces)
