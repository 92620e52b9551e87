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
            assert not any(
                np.any(b.transverse != a.transverse)
                for b, a in zip(operator.terms, fixed.terms, strict=True)
            )


def test_pieces_skip_the_entries_between_them(rng):
    """An operator whose pairs lie in runs of longer arrays (the gaps hold NaN here)
    equals the one built from just those pairs: products, diagonal, blocks, matrix,
    eigenvalue bounds and the clamped operator; malformed runs are refused."""
    n_atoms, n_pairs = 30, 200
    pair_i = rng.integers(0, n_atoms, n_pairs)
    pair_j = (pair_i + rng.integers(1, n_atoms, n_pairs)) % n_atoms
    transverse, radial = rng.normal(size=n_pairs), rng.normal(size=n_pairs)
    unit = rng.normal(size=(n_pairs, 3))
    unit /= np.linalg.norm(unit, axis=1)[:, None]
    compact = PairHessian(n_atoms, pair_i, pair_j, transverse, radial, unit, unique=False)
    runs = [(0, 70), (70, 120), (120, 200)]
    gaps = [5, 0, 17]  # entries left before each run
    pieces, stored = [], [[] for _ in range(5)]
    at = 0
    for (first, last), gap in zip(runs, gaps, strict=True):
        for k, array in enumerate((pair_i, pair_j, transverse, radial, unit)):
            filler = np.full((gap,) + array.shape[1:], -1 if k < 2 else np.nan, array.dtype)
            stored[k] += [filler, array[first:last]]
        pieces.append((at + gap, at + gap + last - first))
        at += gap + last - first
    stored = [np.concatenate(parts) for parts in stored]
    gapped = PairHessian(n_atoms, *stored, unique=False, pieces=pieces)
    assert gapped.n_chunks == 3 and gapped.n_pairs == n_pairs
    for name in ("pair_i", "pair_j", "transverse", "radial", "unit"):
        np.testing.assert_array_equal(getattr(gapped, name), getattr(compact, name))
    x = rng.normal(size=3 * n_atoms)
    np.testing.assert_allclose(gapped.matvec(x), compact.tocsr() @ x, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(
        gapped.diagonal(), compact.tocsr().diagonal(), rtol=1e-12, atol=1e-12
    )
    np.testing.assert_allclose(
        gapped.diagonal_blocks, compact.diagonal_blocks, rtol=1e-12, atol=1e-12
    )
    np.testing.assert_allclose(
        gapped.tocsr().toarray(), compact.tocsr().toarray(), rtol=1e-12, atol=1e-12
    )
    assert gapped.nnz == compact.nnz
    assert gapped.min_eigenvalue() == compact.min_eigenvalue()
    np.testing.assert_array_equal(gapped.negative_pairs(), compact.negative_pairs())
    np.testing.assert_array_equal(gapped.clamped(0.0).radial, compact.clamped(0.0).radial)
    for bad in ([(0, 70), (60, 120)], [(5, 3)], [(0, len(stored[0]) + 1)], []):
        with pytest.raises(ValueError, match="pieces"):
            PairHessian(n_atoms, *stored, pieces=bad)
    with pytest.raises(ValueError, match="differ in length"):
        PairHessian(n_atoms, pair_i, pair_j[:-1], transverse, radial, unit)


def test_duplicate_pairs_are_summed_in_the_matrix():
    hessian = PairHessian(
        2,
        np.array([0, 0]),
        np.array([1, 1]),
        np.array([1.0, 2.0]),
        np.array([3.0, 4.0]),
        np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]),
        unique=False,
    )
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
    x = rng.normal(size=3 * state.n_atoms)
    before = get_threads()
    operators = {}
    try:
        for threads in (1, 2):
            set_threads(threads)
            nl = NeighborList(2.5, 0.3)  # its chunks (one per thread) are the operator's
            nl.update(state)
            operators[threads] = lj.hessian_operator(state, nl)
            operators[threads].product = operators[threads].matvec(x)
    finally:
        set_threads(before)
    one, two = operators[1], operators[2]
    assert one.n_chunks == 1 and two.n_chunks == 2
    np.testing.assert_array_equal(two.pair_i, one.pair_i)  # same pairs, same order
    np.testing.assert_array_equal(two.transverse, one.transverse)
    scale = np.abs(one.diagonal_blocks).max()
    np.testing.assert_allclose(two.diagonal_blocks, one.diagonal_blocks, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(
        two.product, one.product, rtol=0, atol=1e-12 * np.abs(one.product).max()
    )
    np.testing.assert_allclose(
        two.product, one.tocsr() @ x, rtol=0, atol=1e-11 * np.abs(one.product).max()
    )


@pytest.mark.parametrize("chunks", [2, 3, 5])
def test_hessian_of_a_list_in_chunks_equals_the_one_chunk_one(fcc_lattice, chunks):
    """The curvature pass writes each chunk's pairs from where its listed pairs start,
    leaving gaps where the pairs beyond the cutoff were: over a list split into 2, 3 or 5
    chunks, the operator holds the same pairs, in the same order, as over a one-chunk
    list, one piece per chunk; its products and Jacobi diagonal (summed on its own, three
    entries per atom) equal the diagonal blocks' and the matrix's."""
    from md.neighbors import NeighborList
    from md.neighbors._build_kernels import _balanced_bounds
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
    assert many.n_chunks == chunks and many.n_pairs == one.n_pairs
    assert many.pieces[-1, 1] - many.pieces[0, 0] > many.n_pairs  # gaps between the pieces
    for name in ("pair_i", "pair_j", "transverse", "radial", "unit"):
        np.testing.assert_array_equal(getattr(many, name), getattr(one, name))
    x = np.random.default_rng(3).normal(size=3 * state.n_atoms)
    product = one.matvec(x)
    np.testing.assert_allclose(many.matvec(x), product, rtol=0, atol=1e-12 * np.abs(product).max())
    diagonal = many.diagonal()
    np.testing.assert_allclose(diagonal, many.diagonal_blocks[:, :3].ravel(), rtol=1e-13)
    np.testing.assert_allclose(diagonal, one.tocsr().diagonal(), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("dtype", [np.int32, np.int64, np.float32, np.float64])
def test_stream_store_writes_what_a_plain_store_does(dtype):
    """The non-temporal store the Hessian pass writes its blocks with: the same values
    at the same places, later stores to one place winning, nothing else touched."""
    from numba import njit

    from md._simd import store_fence, stream_store

    @njit
    def write(out, places, values):
        for k in range(places.shape[0]):
            stream_store(out, np.uint64(places[k]), values[k])
        store_fence()

    rng = np.random.default_rng(5)
    places = rng.integers(0, 500, 2000)
    values = (rng.normal(size=2000) * 1000).astype(dtype)
    out = np.full(500, 3, dtype=dtype)
    expected = out.copy()
    for place, value in zip(places, values, strict=True):
        expected[place] = value
    write(out, places, values)
    np.testing.assert_array_equal(out, expected)
