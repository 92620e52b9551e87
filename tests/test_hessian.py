"""Analytic Hessians: LennardJones.hessian and ForceField.hessian."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

import md
from md.box import minimum_image
from potentials import LennardJones

STEP = 1e-6


def _numerical_hessian(potential, state, neighbors=None):
    """Central differences of the forces: H[:, k] = -(F(x + h e_k) - F(x - h e_k)) / 2h."""
    x0 = state.positions.copy()
    size = 3 * state.n_atoms
    hessian = np.empty((size, size))
    for k in range(size):
        state.positions[:] = x0
        state.positions.flat[k] += STEP
        plus = potential.energy_forces(state, neighbors).forces.ravel()
        state.positions[:] = x0
        state.positions.flat[k] -= STEP
        minus = potential.energy_forces(state, neighbors).forces.ravel()
        hessian[:, k] = -(plus - minus) / (2.0 * STEP)
    state.positions[:] = x0
    return hessian


def _pair_distances(state):
    i, j = np.triu_indices(state.n_atoms, 1)
    d = minimum_image(state.positions[i] - state.positions[j], state.box, state.pbc)
    return np.linalg.norm(d, axis=1)


def _away_from(r, edges, margin=1e-3):
    return all(np.min(np.abs(r - edge)) > margin for edge in edges)


def _system(random_gas, pbc, n_types, rng):
    """A small gas whose pair distances keep clear of the cutoff and switching onset."""
    for _ in range(50):
        state = random_gas(14, box=5.5, pbc=pbc, min_distance=0.85, n_types=n_types, images=1)
        r = _pair_distances(state)
        if _away_from(r, [2.0, 2.2, 1.9, 1.2, 0.66 * 2.0, 0.66 * 2.2]):
            return state
    raise RuntimeError("no configuration clear of the cutoffs")


POTENTIALS = {
    "none": lambda: LennardJones(cutoff=2.0, cutoff_mode="none"),
    "shift": lambda: LennardJones(cutoff=2.0, cutoff_mode="shift"),
    "smooth": lambda: LennardJones(cutoff=2.0, cutoff_mode="smooth"),
    "smooth-r_on": lambda: LennardJones(cutoff=2.0, cutoff_mode="smooth", r_on=1.2),
    "multi-type": lambda: LennardJones(
        epsilon=[1.0, 0.5],
        sigma=[1.0, 0.9],
        cutoff=2.0,
        cutoff_mode="smooth",
        pairs={(0, 1): {"cutoff": 2.2, "r_on": 1.9}},
    ),
    "multi-type-shift": lambda: LennardJones(
        epsilon=[1.0, 0.7], sigma=[1.0, 1.1], cutoff=2.0, mixing="geometric"
    ),
}


@pytest.mark.parametrize(
    "pbc", [True, False, [True, False, True]], ids=["periodic", "open", "slab"]
)
@pytest.mark.parametrize("name", list(POTENTIALS))
def test_lj_hessian_matches_force_differences(name, pbc, random_gas, rng):
    potential = POTENTIALS[name]()
    state = _system(random_gas, pbc, 2 if name.startswith("multi") else 1, rng)
    hessian = potential.hessian(state, None)
    assert sp.issparse(hessian) and hessian.shape == (3 * state.n_atoms, 3 * state.n_atoms)
    dense = hessian.toarray()
    numerical = _numerical_hessian(potential, state)
    scale = np.max(np.abs(dense))
    assert scale > 1.0  # the system interacts
    np.testing.assert_allclose(dense, numerical, atol=1e-6 * scale, rtol=0)
    np.testing.assert_allclose(dense, dense.T, atol=1e-12 * scale, rtol=0)
    # Translation invariance: every row sums to zero (per Cartesian component).
    row_sums = dense.reshape(-1, state.n_atoms, 3).sum(axis=1)
    np.testing.assert_allclose(row_sums, 0.0, atol=1e-11 * scale)


@pytest.mark.parametrize("cell", ["orthorhombic", "tilted", "slab"])
@pytest.mark.parametrize("n_types", [1, 2])
@pytest.mark.parametrize(
    ("mode", "threads"),
    [
        # each threaded variant compiles apart: the shifted ones run by default, the rest -m slow
        pytest.param(
            mode,
            threads,
            id=f"{mode}-{threads}",
            marks=pytest.mark.slow if threads == 2 and mode != "shift" else (),
        )
        for mode in ("none", "shift", "smooth")
        for threads in (1, 2)
    ],
)
def test_lj_hessian_neighbor_list_equals_all_pairs(mode, n_types, cell, threads, fcc_lattice):
    """The slot-frame curvature kernel (chunks counted, then written, on one thread or two)
    assembles the all-pairs minimum-image Hessian, in any cell, with one type or two."""
    from md.parallel import get_threads, set_threads

    state = fcc_lattice(cells=8, perturbation=0.05, n_types=n_types)  # 2048 atoms: 2 chunks
    if cell == "tilted":
        state.tilt = np.array([0.2, -0.15, 0.1]) * state.box[[0, 0, 1]]
    elif cell == "slab":
        state.pbc = np.array([True, True, False])
    params = dict(epsilon=[1.0, 0.8], sigma=[1.0, 0.95], pairs={(0, 1): {"cutoff": 2.2}})
    potential = LennardJones(cutoff=2.5, cutoff_mode=mode, **(params if n_types == 2 else {}))
    before = get_threads()
    try:
        set_threads(threads)
        neighbors = md.NeighborList(potential.cutoff, skin=0.3)
        neighbors.update(state)
        assert neighbors.used_cells and neighbors.frame.n_chunks == threads
        listed = potential.hessian(state, neighbors)
    finally:
        set_threads(before)
    reference = potential.hessian(state, None)
    assert abs(listed - reference).max() <= 1e-12 * abs(reference).max()
    assert listed.nnz == reference.nnz
    # Canonical CSR: sorted, unique column indices in every row.
    canonical = listed.copy()
    canonical.has_canonical_format = False
    canonical.sum_duplicates()
    np.testing.assert_array_equal(canonical.indices, listed.indices)
    np.testing.assert_array_equal(canonical.data, listed.data)


def test_lj_hessian_of_dimer_matches_pair_curvature(dimer):
    # Along the bond the curvature is u''(r); across it u'(r) / r (zero at the minimum).
    potential = LennardJones(cutoff=2.5, cutoff_mode="none")
    r = 1.3
    state = dimer(r=r)
    block = potential.hessian(state, None).toarray()[:3, :3]
    u2 = 4.0 * (156.0 / r**14 - 42.0 / r**8)
    u1 = 4.0 * (-12.0 / r**13 + 6.0 / r**7)
    np.testing.assert_allclose(np.diag(block), [u2, u1 / r, u1 / r], rtol=1e-12)
    # A pair beyond the cutoff contributes nothing.
    assert abs(potential.hessian(dimer(r=2.6), None)).max() == 0.0


def test_lj_hessian_leaves_state_unchanged(fcc_lattice):
    state = fcc_lattice(cells=2, perturbation=0.05)
    before = state.copy()
    LennardJones(cutoff=1.5).hessian(state, None)
    np.testing.assert_array_equal(state.positions, before.positions)


class _NoHessian:
    """U = k/2 |x|^2 per atom, without a Hessian (test-only; needs no neighbour list)."""

    cutoff = None

    def __init__(self, k):
        self.k = k

    def energy_forces(self, state, neighbors, per_atom=False, virial=True):
        from potentials.base import ForceResult

        x = state.positions
        return ForceResult(0.5 * self.k * np.sum(x * x), -self.k * x, np.zeros((3, 3)))

    def check(self, state):
        pass

    def describe(self):
        return {"type": "tether", "k": self.k}


class _Tether(_NoHessian):
    """The same with its Hessian k I, returned dense (the ForceField converts it)."""

    def hessian(self, state, neighbors):
        return self.k * np.eye(3 * state.n_atoms)


def test_forcefield_hessian_sums_potentials(fcc_lattice):
    state = fcc_lattice(cells=3, perturbation=0.05)
    lj = LennardJones(cutoff=2.5, cutoff_mode="smooth")
    forcefield = md.ForceField([lj, _Tether(3.0)])
    total = forcefield.hessian(state)
    assert sp.isspmatrix_csr(total) or isinstance(total, sp.csr_array)
    expected = lj.hessian(state, None).toarray() + 3.0 * np.eye(3 * state.n_atoms)
    np.testing.assert_allclose(total.toarray(), expected, atol=1e-10)
    assert forcefield.neighbor_list.n_builds == 1


def test_forcefield_hessian_refreshes_neighbor_list(fcc_lattice):
    state = fcc_lattice(cells=4, perturbation=0.02)
    lj = LennardJones(cutoff=2.5)
    forcefield = md.ForceField([lj], skin=0.3)
    forcefield.compute(state)
    state.positions += np.array([0.3, 0.0, 0.0]) * (np.arange(state.n_atoms) % 2)[:, None]
    total = forcefield.hessian(state)
    assert forcefield.neighbor_list.n_builds == 2
    assert abs(total - lj.hessian(state, None)).max() <= 1e-10


def test_forcefield_hessian_names_potential_without_one(fcc_lattice):
    state = fcc_lattice(cells=2)
    forcefield = md.ForceField([LennardJones(cutoff=1.5), _NoHessian(1.0)])
    with pytest.raises(TypeError, match="_NoHessian"):
        forcefield.hessian(state)


def test_lj_hessian_operator_survives_the_next_one(fcc_lattice):
    """The slot-frame Hessian reuses its buffers only once nothing refers to them: an
    operator (or a view of its arrays) kept by the caller is never overwritten by the
    next call, and an operator rebuilt at the same positions equals the first."""
    state = fcc_lattice(cells=6, perturbation=0.05)
    potential = LennardJones(cutoff=2.5)
    neighbors = md.NeighborList(potential.cutoff, skin=0.3)
    neighbors.update(state)
    first = potential.hessian_operator(state, neighbors)
    kept = (first.pair_i.copy(), first.transverse.copy(), first.radial.copy(), first.unit.copy())
    view = first.radial[:10]
    original = state.positions.copy()
    state.positions += 0.01
    second = potential.hessian_operator(state, neighbors)
    assert not np.shares_memory(second.radial, first.radial)
    np.testing.assert_array_equal(first.pair_i, kept[0])
    np.testing.assert_array_equal(first.transverse, kept[1])
    np.testing.assert_array_equal(first.unit, kept[3])
    del first
    state.positions[:] = original
    third = potential.hessian_operator(state, neighbors)  # a view of the first's arrays lives
    assert not np.shares_memory(third.radial, view)
    np.testing.assert_array_equal(view, kept[2][:10])
    np.testing.assert_array_equal(third.radial, kept[2])
    np.testing.assert_array_equal(third.transverse, kept[1])
    del view
    fourth = potential.hessian_operator(state, neighbors)  # now the buffers are free again
    np.testing.assert_array_equal(fourth.radial, kept[2])
