"""Matrix-free pair Hessians: products, diagonal, assembly, and the definite modification."""

from __future__ import annotations

import numpy as np
import pytest

import md
from potentials import FENEBonds, HarmonicBonds, LennardJones
from potentials.pair_hessian import HessianSum, PairHessian


def _bonded_gas(random_gas, rng, n_atoms=16):
    """A random periodic gas (min distance 0.8) with a chain of bonds through it."""
    state = random_gas(n_atoms, box=4.2, pbc=True, min_distance=0.8, images=1)
    state = md.State(
        positions=state.positions,
        masses=rng.uniform(0.5, 2.0, n_atoms),
        box=state.box,
        pbc=state.pbc,
    )
    bonds = [(i, i + 1) for i in range(n_atoms - 1)] + [(0, 5), (0, 5)]  # one bond listed twice
    return state, bonds


@pytest.mark.parametrize("mode", ["none", "shift", "smooth"])
def test_operator_equals_the_assembled_matrix(random_gas, rng, mode):
    state, bonds = _bonded_gas(random_gas, rng)
    forcefield = md.ForceField(
        [LennardJones(cutoff=1.8, cutoff_mode=mode), HarmonicBonds(bonds, k=50.0, r0=1.0)]
    )
    operator = forcefield.hessian_operator(state)
    dense = forcefield.hessian(state).toarray()
    np.testing.assert_allclose(dense, dense.T, atol=1e-12)
    for _ in range(3):
        x = rng.normal(size=3 * state.n_atoms)
        np.testing.assert_allclose(operator.matvec(x), dense @ x, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(operator.diagonal(), np.diag(dense), rtol=1e-12, atol=1e-12)
    assert operator.nnz >= np.count_nonzero(dense)


def test_fene_operator_equals_its_matrix(random_gas, rng):
    state, bonds = _bonded_gas(random_gas, rng)
    potential = FENEBonds(bonds, k=30.0, r_max=5.0)
    operator = potential.hessian_operator(state)
    dense = potential.hessian(state).toarray()
    x = rng.normal(size=3 * state.n_atoms)
    np.testing.assert_allclose(operator.matvec(x), dense @ x, rtol=1e-12, atol=1e-9)


def test_blocks_have_the_stored_eigenvalues(random_gas, rng):
    state, _ = _bonded_gas(random_gas, rng)
    hessian = LennardJones(cutoff=1.8).hessian_operator(state, None)
    for p in range(min(10, len(hessian.pair_i))):
        i, j = hessian.pair_i[p], hessian.pair_j[p]
        block = -hessian.tocsr()[3 * i : 3 * i + 3, 3 * j : 3 * j + 3].toarray()
        expected = sorted([hessian.transverse[p]] * 2 + [hessian.radial[p]])
        np.testing.assert_allclose(np.linalg.eigvalsh(block), expected, rtol=1e-10, atol=1e-10)


def test_clamped_to_zero_is_positive_semidefinite(random_gas, rng):
    state, _ = _bonded_gas(random_gas, rng)
    hessian = LennardJones(cutoff=1.8).hessian_operator(state, None)
    assert hessian.min_eigenvalue() < 0.0  # compressed pairs below 2^(1/6)
    projected = hessian.clamped(0.0).tocsr().toarray()
    assert np.linalg.eigvalsh(projected).min() > -1e-10
    assert np.linalg.eigvalsh(hessian.tocsr().toarray()).min() < -1e-3


def test_definite_makes_the_newton_matrix_positive_and_keeps_safe_pairs(random_gas, rng):
    state, bonds = _bonded_gas(random_gas, rng)
    bonded = HarmonicBonds(bonds, k=1e3, r0=1.2)  # every bond compressed: negative transverse
    operator = HessianSum(
        [LennardJones(cutoff=1.8).hessian_operator(state, None), bonded.hessian_operator(state)]
    )
    mass_diagonal = np.diag(np.repeat(state.masses, 3))
    for h2 in (1e-4, 1e-2, 1.0):
        exact = mass_diagonal + h2 * operator.tocsr().toarray()
        fixed = operator.definite(h2, state.masses)
        matrix = mass_diagonal + h2 * fixed.tocsr().toarray()
        assert np.linalg.eigvalsh(matrix).min() > 0.0
        if h2 >= 1e-2:
            assert np.linalg.eigvalsh(exact).min() < 0.0  # the exact one is indefinite
        # Only negative curvatures change, and only below the mass-share bound
        # a_i a_j / (h2 (a_i + a_j)) >= min(a) / (2 h2), a = m / (negative pairs of the atom).
        counts = np.zeros(state.n_atoms)
        for term in operator.terms:
            np.add.at(counts, term.pair_i[term.negative_pairs()], 1)
            np.add.at(counts, term.pair_j[term.negative_pairs()], 1)
        bound = np.min(state.masses / np.maximum(counts, 1)) / (2.0 * h2)
        for before, after in zip(operator.terms, fixed.terms, strict=True):
            changed = (before.transverse != after.transverse) | (before.radial != after.radial)
            assert np.all(before.negative_pairs()[changed])
            assert np.all(after.transverse >= before.transverse)
            assert np.all(after.radial >= before.radial)
            safe = np.minimum(before.transverse, before.radial) > -bound
            assert not np.any(changed & safe)
        if h2 == 1e-4:
            assert not any(np.any(b.transverse != a.transverse) for b, a in
                           zip(operator.terms, fixed.terms, strict=True))  # fmt: skip


def test_duplicate_pairs_are_summed_in_the_matrix():
    hessian = PairHessian(
        2, np.array([0, 0]), np.array([1, 1]), np.array([1.0, 2.0]), np.array([3.0, 4.0]),
        np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]), unique=False,
    )  # fmt: skip
    dense = hessian.tocsr().toarray()
    np.testing.assert_allclose(np.diag(dense), [7.0, 3.0, 3.0, 7.0, 3.0, 3.0])
    np.testing.assert_allclose(dense[0, 3], -7.0)


@pytest.mark.parametrize("mode", ["shift", "smooth"])
def test_threaded_hessian_equals_the_serial_one(fcc_lattice, rng, mode):
    """Curvatures, diagonal blocks and products split over two threads (chunks of rows and
    of pairs, summed in chunk order) equal the one-thread operator to round-off."""
    from md.neighbors import NeighborList
    from md.parallel import get_threads, set_threads

    state = fcc_lattice(cells=9, perturbation=0.08)  # 2916 atoms, ~10^5 listed pairs
    lj = LennardJones(cutoff=2.5, cutoff_mode=mode, r_on=2.0 if mode == "smooth" else None)
    nl = NeighborList(2.5, 0.3)
    nl.update(state)
    x = rng.normal(size=3 * state.n_atoms)
    before = get_threads()
    operators = {}
    try:
        for threads in (1, 2):
            set_threads(threads)
            operators[threads] = lj.hessian_operator(state, nl)
            operators[threads].product = operators[threads].matvec(x)
    finally:
        set_threads(before)
    one, two = operators[1], operators[2]
    assert one.n_chunks == 1 and two.n_chunks == 2
    np.testing.assert_array_equal(two.pair_i, one.pair_i)  # same pairs, same order
    np.testing.assert_array_equal(two.transverse, one.transverse)
    scale = np.abs(one.diagonal_blocks).max()
    np.testing.assert_allclose(two.diagonal_blocks, one.diagonal_blocks, rtol=0,
                               atol=1e-12 * scale)  # fmt: skip
    np.testing.assert_allclose(two.product, one.product, rtol=0,
                               atol=1e-12 * np.abs(one.product).max())  # fmt: skip
    np.testing.assert_allclose(two.product, one.tocsr() @ x, rtol=0,
                               atol=1e-11 * np.abs(one.product).max())  # fmt: skip


@pytest.mark.parametrize("chunks", [2, 3, 5])
def test_hessian_of_a_list_in_chunks_equals_the_one_chunk_one(fcc_lattice, chunks):
    """The curvature pass places each chunk's pairs from counts of every chunk but the
    last (counted in as many pieces as there are chunks) and gives the last chunk room
    for all its listed pairs: over a list split into 2, 3 or 5 chunks, the operator holds
    the same pairs, in the same order, as over a one-chunk list; its Jacobi diagonal
    (summed on its own, three entries per atom) equals the diagonal blocks' and the
    matrix's."""
    from md.neighbors import NeighborList, _balanced_bounds
    from md.parallel import get_threads, set_threads

    state = fcc_lattice(cells=9, perturbation=0.08)
    lj = LennardJones(cutoff=2.5, cutoff_mode="shift")
    before = get_threads()
    operators = []
    try:
        set_threads(1)
        nl = NeighborList(2.5, 0.3)
        nl.update(state)
        for count in (1, chunks):
            nl.bounds = _balanced_bounds(nl.slot_starts, count)  # the list's chunks
            assert nl.frame.n_chunks == count
            operators.append(lj.hessian_operator(state, nl))
    finally:
        set_threads(before)
    one, many = operators
    for name in ("pair_i", "pair_j", "transverse", "radial", "unit"):
        np.testing.assert_array_equal(getattr(many, name), getattr(one, name))
    diagonal = many.diagonal()
    np.testing.assert_allclose(diagonal, many.diagonal_blocks[:, :3].ravel(), rtol=1e-13)
    np.testing.assert_allclose(diagonal, one.tocsr().diagonal(), rtol=1e-12, atol=1e-12)
