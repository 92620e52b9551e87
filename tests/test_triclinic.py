"""Triclinic cells: geometry, neighbour lists, potentials and constraints in a sheared cell.

The references are independent of the engine's minimum image: an explicit
search over periodic images, the same periodic system described by an
orthorhombic box, and ASE's own Lennard-Jones calculator (tests/test_calculator.py).
"""

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import md
from md.box import (
    cell_matrix,
    minimum_image,
    perpendicular_widths,
    reduced_tilt,
    restricted_cell,
    wrap,
)
from md.forcefield import ForceField
from md.neighbors import NeighborList
from potentials.lennard_jones import LennardJones
from potentials.springs import HarmonicBonds


def rotation_matrix(seed):
    """A random proper rotation (QR of a Gaussian matrix, signs fixed)."""
    q, r = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def nearest_image_distances(positions, cell, reach=2):
    """(N, N) distance to the nearest periodic image, by trying every image shift.

    Positions are first folded into the cell through their fractional
    coordinates (numpy's inverse, not the engine's wrap).
    """
    fractional = positions @ np.linalg.inv(cell)
    positions = (fractional - np.floor(fractional)) @ cell
    d = positions[:, None, :] - positions[None, :, :]
    best = np.full(d.shape[:2], np.inf)
    for shift in itertools.product(range(-reach, reach + 1), repeat=3):
        best = np.minimum(best, np.linalg.norm(d + np.array(shift) @ cell, axis=2))
    return best


def random_cell(rng, edges=(9.0, 10.0, 11.0), fraction=0.5):
    """Edges and tilts with |xy|, |xz| <= fraction Lx and |yz| <= fraction Ly."""
    box = np.array(edges) * rng.uniform(0.9, 1.1, 3)
    tilt = rng.uniform(-fraction, fraction, 3) * box[[0, 0, 1]]
    return box, tilt


# ------------------------------------------------------------------ geometry
def test_restricted_cell_rotates_any_cell_into_lower_triangular_form():
    for seed in range(20):
        rng = np.random.default_rng(seed)
        lower = cell_matrix(*random_cell(rng))
        rotation = rotation_matrix(seed)
        user = lower @ rotation.T
        box, tilt, q = restricted_cell(user)
        np.testing.assert_allclose(q @ q.T, np.eye(3), atol=1e-14)
        assert np.linalg.det(q) == pytest.approx(1.0)
        np.testing.assert_allclose(cell_matrix(box, tilt), lower, atol=1e-12)
        np.testing.assert_allclose(user @ q, lower, atol=1e-12)


def test_restricted_cell_keeps_lower_triangular_cells_bit_for_bit():
    lower = np.array([[5.0, 0, 0], [1.3, 6.1, 0], [-0.7, 2.2, 7.3]])
    box, tilt, q = restricted_cell(lower)
    assert np.array_equal(q, np.eye(3))
    assert np.array_equal(cell_matrix(box, tilt), lower)


def test_left_handed_cell_keeps_its_lattice():
    cell = np.array([[5.0, 0, 0], [1.0, 6.0, 0], [0.5, 0.4, -7.0]])
    box, tilt, q = restricted_cell(cell)
    assert np.linalg.det(q) == pytest.approx(1.0)
    # Every vector of the new cell is an integer combination of the old one's.
    combination = np.linalg.solve(cell.T, (cell_matrix(box, tilt) @ q.T).T).T
    np.testing.assert_allclose(combination, np.round(combination), atol=1e-12)
    assert abs(np.linalg.det(np.round(combination))) == 1


def test_restricted_cell_refuses_degenerate_cells():
    with pytest.raises(ValueError, match="linearly dependent"):
        restricted_cell([[1.0, 1, 0], [0, 1, 1], [1, 2, 1]])
    with pytest.raises(ValueError, match=r"\(3, 3\)"):
        restricted_cell(np.eye(2))


def test_perpendicular_widths_are_face_distances():
    box, tilt = np.array([8.0, 9.0, 10.0]), np.array([3.0, -2.0, 4.0])
    h = cell_matrix(box, tilt)
    reciprocal = np.linalg.inv(h).T  # rows: reciprocal vectors, |b*_i| = 1 / width_i
    np.testing.assert_allclose(
        perpendicular_widths(box, tilt), 1 / np.linalg.norm(reciprocal, axis=1)
    )
    np.testing.assert_array_equal(perpendicular_widths(box), box)


@settings(max_examples=40, deadline=None, database=None)
@given(seed=st.integers(0, 2**31 - 1), fraction=st.sampled_from([0.0, 0.25, 0.5]))
def test_minimum_image_is_the_nearest_image(seed, fraction):
    rng = np.random.default_rng(seed)
    box, tilt = random_cell(rng, fraction=fraction)
    h = cell_matrix(box, tilt)
    positions = rng.random((40, 3)) @ h + rng.normal(0, 20, (40, 3))
    nearest = nearest_image_distances(positions, h)
    d = minimum_image(positions[:, None, :] - positions[None, :, :], box, [True] * 3, tilt)
    found = np.linalg.norm(d, axis=2)
    within = nearest < 0.5 * perpendicular_widths(box, tilt).min()
    np.testing.assert_allclose(found[within], nearest[within], atol=1e-9)


def test_wrap_puts_positions_in_the_cell_and_images_undo_it():
    rng = np.random.default_rng(3)
    box, tilt = random_cell(rng)
    h = cell_matrix(box, tilt)
    positions = rng.normal(0, 30, (500, 3))
    wrapped, images = wrap(positions, box, [True] * 3, tilt)
    fractional = wrapped @ np.linalg.inv(h)
    assert fractional.min() >= 0 and fractional.max() < 1
    np.testing.assert_allclose(wrapped + images @ h, positions, atol=1e-10)


def test_reduced_tilt_gives_the_same_lattice():
    box, tilt = np.array([6.0, 7.0, 8.0]), np.array([10.0, -9.0, 12.0])
    reduced = reduced_tilt(box, tilt, [True] * 3)
    assert abs(reduced[0]) <= 3 and abs(reduced[1]) <= 3 and abs(reduced[2]) <= 3.5
    old, new = cell_matrix(box, tilt), cell_matrix(box, reduced)
    combination = np.linalg.solve(old.T, new.T).T
    np.testing.assert_allclose(combination, np.round(combination), atol=1e-12)
    assert abs(np.linalg.det(np.round(combination))) == 1


# ------------------------------------------------------------------ state
def test_state_takes_a_lower_triangular_box_matrix():
    cell = [[5.0, 0, 0], [1.0, 6.0, 0], [0.5, -1.0, 7.0]]
    state = md.State(positions=np.zeros((1, 3)), box=cell)
    np.testing.assert_array_equal(state.box, [5, 6, 7])
    np.testing.assert_array_equal(state.tilt, [1.0, 0.5, -1.0])
    np.testing.assert_array_equal(state.cell, cell)
    assert state.volume == pytest.approx(abs(np.linalg.det(cell)))
    assert not state.is_orthorhombic
    assert np.array_equal(state.copy().tilt, state.tilt)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"box": [[5.0, 1.0, 0], [0, 6.0, 0], [0, 0, 7.0]]}, "lower triangular"),
        ({"box": [5.0, 6.0, 7.0], "tilt": [1.0, 0, 0], "pbc": [True, False, True]}, "xy"),
        ({"box": [5.0, 6.0, 7.0], "tilt": [0, np.nan, 0]}, "finite"),
    ],
)
def test_state_refuses_bad_cells(kwargs, message):
    with pytest.raises(ValueError, match=message):
        md.State(positions=np.zeros((1, 3)), **kwargs)


def test_from_ase_rotates_a_general_cell_and_keeps_distances():
    import ase

    rng = np.random.default_rng(1)
    lower = cell_matrix(*random_cell(rng))
    cell = lower @ rotation_matrix(4).T
    positions = rng.random((30, 3)) @ cell
    atoms = ase.Atoms("Ar30", positions=positions, cell=cell, pbc=True)
    atoms.set_velocities(rng.normal(size=(30, 3)))
    state = md.State.from_ase(atoms)
    np.testing.assert_allclose(state.cell, lower, atol=1e-12)
    np.testing.assert_allclose(
        nearest_image_distances(state.positions, state.cell, 1),
        nearest_image_distances(positions, cell, 1),
        atol=1e-10,
    )
    np.testing.assert_allclose(
        np.linalg.norm(state.velocities, axis=1), np.linalg.norm(atoms.get_velocities(), axis=1)
    )
    back = state.to_ase()
    np.testing.assert_allclose(back.cell.array, lower, atol=1e-12)


# ------------------------------------------------------------------ neighbour lists
def assert_list_matches_image_search(state, cutoff, skin):
    nl = NeighborList(cutoff, skin)
    nl.build(state)
    nearest = nearest_image_distances(state.positions, state.cell)
    i, j = np.nonzero(np.triu(nearest < nl.list_radius, k=1))
    expected = np.stack([i, j], axis=1)
    got = nl.pairs()
    assert len(np.unique(got, axis=0)) == len(got), "a pair is listed twice"
    np.testing.assert_array_equal(got, expected)
    return nl


@settings(max_examples=12, deadline=None, database=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    fraction=st.sampled_from([0.1, 0.3, 0.5]),
    skin=st.sampled_from([0.0, 0.4]),
)
def test_cell_list_misses_no_pair_in_random_cells(seed, fraction, skin):
    """Tilts up to half an edge (the flip limit): the cell search finds every pair."""
    rng = np.random.default_rng(seed)
    box, tilt = random_cell(rng, edges=(12.0, 13.0, 14.0), fraction=fraction)
    n = 250
    positions = rng.random((n, 3)) @ cell_matrix(box, tilt) + rng.normal(0, 10, (n, 3))
    state = md.State(positions=positions, box=box, tilt=tilt)
    nl = assert_list_matches_image_search(state, 2.0, skin)
    assert nl.used_cells
    # The slot frame: every listed pair's separation is its nearest image.
    frame = nl.frame_positions(state.positions)
    rows = np.repeat(np.arange(n), np.diff(nl.slot_starts))
    d = frame[rows] - frame[nl.slot_neighbors] - nl.shifts[nl.codes]
    nearest = nearest_image_distances(state.positions, state.cell)
    np.testing.assert_allclose(
        np.linalg.norm(d, axis=1), nearest[nl.order[rows], nl.order[nl.slot_neighbors]], atol=1e-9
    )


def _deformed(state, rng, strain, jitter):
    """``state`` under a random lower-triangular deformation (cell and positions) plus noise."""
    m = np.eye(3) + strain * np.tril(rng.uniform(-1.0, 1.0, (3, 3)))
    cell = state.cell @ m
    positions = state.positions @ m + rng.normal(0.0, jitter, state.positions.shape)
    return md.State(
        positions=positions,
        box=np.diag(cell).copy(),
        tilt=cell[[1, 2, 2], [0, 0, 1]],
        velocities=state.velocities,
    )


@settings(max_examples=30, deadline=None, database=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    fraction=st.sampled_from([0.0, 0.3]),
    strain=st.sampled_from([0.002, 0.01, 0.03, 0.08]),
    edges=st.sampled_from([(12.0, 13.0, 14.0), (7.0, 7.5, 8.0)]),
)
def test_a_list_kept_through_a_cell_deformation_misses_no_pair(seed, fraction, strain, edges):
    """A barostat's deformation: the list is kept only while every pair within the cutoff
    is listed, and its slot frame then gives each such pair's nearest-image separation."""
    rng = np.random.default_rng(seed)
    box, tilt = random_cell(rng, edges=edges, fraction=fraction)
    n = 250 if edges[0] > 10 else 60
    positions = rng.random((n, 3)) @ cell_matrix(box, tilt) + rng.normal(0, 10, (n, 3))
    cutoff = 2.0
    nl = NeighborList(cutoff, 0.4)
    nl.build(md.State(positions=positions, box=box, tilt=tilt))
    try:
        state = _deformed(md.State(positions=positions, box=box, tilt=tilt), rng, strain, 0.03)
        rebuilt = nl.update(state)
    except ValueError:  # the deformed cell is too narrow for the cutoff: refused, as it must
        return
    assert rebuilt == (nl.n_builds == 2) and nl.n_followed == (0 if rebuilt else 1)
    nearest = nearest_image_distances(state.positions, state.cell)
    i, j = np.nonzero(np.triu(nearest < cutoff, k=1))
    assert set(zip(i.tolist(), j.tolist(), strict=True)) <= set(map(tuple, nl.pairs().tolist()))
    if nl.order is not None:
        frame = nl.frame_positions(state.positions)
        rows = np.repeat(np.arange(n), np.diff(nl.slot_starts))
        d = np.linalg.norm(frame[rows] - frame[nl.slot_neighbors] - nl.shifts[nl.codes], axis=1)
        exact = nearest[nl.order[rows], nl.order[nl.slot_neighbors]]
        close = exact < cutoff
        np.testing.assert_allclose(d[close], exact[close], atol=1e-9)


def test_forces_through_a_followed_cell_equal_a_fresh_list():
    """Small deformations are followed (no rebuild) with exactly the forces of a new list;
    a large one rebuilds."""
    rng = np.random.default_rng(4)
    start = lj_liquid_in(np.array([10.0, 11.0, 12.0]), np.array([1.0, -2.0, 1.5]))
    lj = LennardJones(epsilon=1.0, sigma=1.0, cutoff=2.5)
    kept = ForceField([lj], skin=0.4)
    kept.compute(start)
    state = start
    for strain in (0.003, 0.003, 0.004, None):
        state = _deformed(state, rng, strain, 0.01) if strain else start.copy()  # and back
        result, fresh = kept.compute(state), ForceField([lj], skin=0.4).compute(state)
        assert result.energy == pytest.approx(fresh.energy, rel=1e-12)
        np.testing.assert_allclose(result.forces, fresh.forces, atol=1e-10)
        np.testing.assert_allclose(result.virial, fresh.virial, atol=1e-9)
    assert kept.neighbor_list.n_builds == 1 and kept.neighbor_list.n_followed == 4
    kept.compute(_deformed(state, rng, 0.01, 0.3))  # atoms moved more than the skin covers
    assert kept.neighbor_list.n_builds == 2


def test_small_triclinic_cell_uses_the_brute_force_search():
    rng = np.random.default_rng(0)
    box, tilt = np.array([7.0, 7.5, 8.0]), np.array([2.0, -1.5, 2.5])
    state = md.State(positions=rng.random((60, 3)) @ cell_matrix(box, tilt), box=box, tilt=tilt)
    nl = assert_list_matches_image_search(state, 2.5, 0.3)
    assert not nl.used_cells


def test_too_narrow_a_cell_is_refused_with_its_width_and_tilt():
    state = md.State(positions=np.zeros((2, 3)), box=[6.0, 6.0, 6.0], tilt=[5.0, 0, 0])
    with pytest.raises(ValueError, match=r"width across x is 4\.6.*xy = 5"):
        NeighborList(2.5, 0.3).build(state)


# ------------------------------------------------------------------ potentials
def lj_liquid_in(box, tilt, n=300, seed=0):
    rng = np.random.default_rng(seed)
    h = cell_matrix(box, tilt)
    grid = (np.stack(np.meshgrid(*[np.arange(7)] * 3, indexing="ij"), -1).reshape(-1, 3) + 0.5) / 7
    fractional = grid[rng.permutation(len(grid))[:n]] + rng.normal(0, 0.01, (n, 3))
    positions = fractional @ h + rng.integers(-2, 3, (n, 3)) @ h  # unwrapped on purpose
    return md.State(positions=positions, box=box, tilt=tilt, velocities=rng.normal(0, 1, (n, 3)))


def test_sheared_description_of_an_orthorhombic_system_gives_the_same_forces():
    """The cell (a, b + a, c + b) spans the same lattice as the box (a, b, c)."""
    box = np.array([10.0, 11.0, 12.0])
    ortho = lj_liquid_in(box, np.zeros(3))
    sheared = ortho.copy()
    sheared.tilt[:] = [box[0], 0.0, box[1]]  # b' = b + a, c' = c + b
    assert sheared.volume == pytest.approx(ortho.volume)
    lj = LennardJones(epsilon=1.0, sigma=1.0, cutoff=2.5)
    results = []
    for state in (ortho, sheared):
        ff = ForceField([lj], skin=0.3)
        results.append(ff.compute(state))
    assert results[1].energy == pytest.approx(results[0].energy, rel=1e-12)
    np.testing.assert_allclose(results[1].forces, results[0].forces, atol=1e-10)
    np.testing.assert_allclose(results[1].virial, results[0].virial, atol=1e-9)


def test_primitive_fcc_cell_has_the_energy_and_stress_of_the_cubic_cell():
    from ase.build import bulk

    lj = LennardJones(epsilon=1.0, sigma=1.0, cutoff=2.5)
    per_atom, pressures = [], []
    strain = np.eye(3) + np.array([[0.01, 0.02, 0], [0, -0.01, 0.015], [0, 0, 0.005]])
    for cubic, repeat in ((False, 8), (True, 4)):
        atoms = bulk("Ar", "fcc", a=1.56, cubic=cubic).repeat(repeat)
        atoms.set_cell(atoms.cell.array @ strain, scale_atoms=True)
        state = md.State.from_ase(atoms)
        result = ForceField([lj], skin=0.3).compute(state)
        assert np.abs(result.forces).max() < 1e-10
        per_atom.append(result.energy / state.n_atoms)
        # The virial per atom, rotated back to the common frame of atoms.cell.
        _, _, q = restricted_cell(atoms.cell.array)
        pressures.append(q @ result.virial @ q.T / state.n_atoms)
    assert per_atom[0] == pytest.approx(per_atom[1], rel=1e-12)
    np.testing.assert_allclose(pressures[0], pressures[1], atol=1e-10)


def test_lj_and_bond_forces_are_minus_the_energy_gradient_in_a_sheared_cell():
    box, tilt = np.array([10.0, 10.5, 11.0]), np.array([4.0, -3.5, 4.5])
    state = lj_liquid_in(box, tilt, n=120, seed=2)
    n = state.n_atoms
    bonds = np.array([[0, 1], [2, 3], [4, 5]])
    # Place each bond's partner across the cell from it: the bond spans the tilted boundary.
    for i, j in bonds:
        state.positions[j] = state.positions[i] + np.array([0.3, -0.6, 0.5]) + state.cell[2]
    potentials = [
        LennardJones(epsilon=1.0, sigma=1.0, cutoff=2.5, cutoff_mode="smooth"),
        HarmonicBonds(bonds=bonds, k=30.0, r0=0.9),
    ]
    all_pairs = sum((p.energy_forces(state, None).forces for p in potentials), np.zeros((n, 3)))
    for forces in (ForceField(potentials).compute(state).forces, all_pairs):
        np.testing.assert_allclose(forces.sum(axis=0), 0.0, atol=1e-9)  # Newton's third law
        h = 1e-6
        for atom in (0, 1, 7, n - 1):
            for axis in range(3):
                plus, minus = state.copy(), state.copy()
                plus.positions[atom, axis] += h
                minus.positions[atom, axis] -= h
                slope = (
                    ForceField(potentials).compute(plus).energy
                    - ForceField(potentials).compute(minus).energy
                ) / (2 * h)
                assert -slope == pytest.approx(forces[atom, axis], rel=1e-5, abs=1e-6)


def test_virial_is_the_energy_derivative_under_strain_in_a_sheared_cell():
    """W = -dU/d(strain) at fixed fractional coordinates, for all six components."""
    box, tilt = np.array([10.0, 10.5, 11.0]), np.array([3.0, -2.5, 4.0])
    state = lj_liquid_in(box, tilt, n=200, seed=5)
    lj = LennardJones(epsilon=1.0, sigma=1.0, cutoff=2.5, cutoff_mode="smooth")
    virial = ForceField([lj]).compute(state).virial

    def energy(strain):
        deformation = np.eye(3) + strain
        box_, tilt_, _ = restricted_cell(state.cell @ deformation)
        strained = md.State(positions=state.positions @ deformation, box=box_, tilt=tilt_)
        return ForceField([lj]).compute(strained).energy

    h = 1e-6
    for a, b in [(0, 0), (1, 1), (2, 2), (1, 0), (2, 0), (2, 1)]:
        strain = np.zeros((3, 3))
        strain[a, b] = h
        slope = (energy(strain) - energy(-strain)) / (2 * h)
        assert -slope == pytest.approx(virial[a, b], rel=1e-5, abs=1e-5)


def test_constraints_across_a_tilted_boundary_hold_their_length():
    from integrators.rattle import BondConstraints, Rattle

    box, tilt = np.array([9.0, 9.0, 9.0]), np.array([3.0, 2.0, -3.0])
    rng = np.random.default_rng(1)
    pairs = []
    positions = []
    for k in range(20):
        start = rng.random(3) @ cell_matrix(box, tilt)
        direction = rng.normal(size=3)
        positions += [
            start,
            start + direction / np.linalg.norm(direction) + cell_matrix(box, tilt)[2],
        ]
        pairs.append([2 * k, 2 * k + 1])
    state = md.State(
        positions=np.array(positions), box=box, tilt=tilt, velocities=rng.normal(0, 0.5, (40, 3))
    )
    constraints = BondConstraints(np.array(pairs), lengths=1.0)
    integrator = Rattle(0.002, constraints)
    ff = ForceField([LennardJones(epsilon=1.0, sigma=1.0, cutoff=2.0)])
    for _ in range(50):
        integrator.step(state, ff)
    np.testing.assert_allclose(constraints.errors(state), 0.0, atol=1e-7)
    lengths = np.linalg.norm(constraints.bond_vectors(state), axis=1)
    np.testing.assert_allclose(lengths, 1.0, atol=1e-6)
