"""The cluster-pair list (GROMACS's layout) and the mixed-precision cluster kernels.

The list is checked against an O(N^2) minimum-image search: every atom pair
within the list radius lies in exactly one listed cluster pair at the image
that brings it within reach, before and after the pruning that the first force
call drives; the kernels against the double-precision slot frame (forces,
energy, virial to float32 round-off, and not equal to them), on several types,
cutoff modes, pair terms, thread counts, unwrapped positions and sparse columns.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import md
from integrators import VelocityVerlet
from md.forcefield import ForceField
from md.neighbors import ClusterFrame, NeighborList
from md.neighbors._cluster_grid import CLUSTER, FILLER, cluster_grid, column_counts
from md.neighbors._cluster_prune import cluster_positions
from md.neighbors._cluster_search import balanced_chunks, chunk_windows, row_reach, search_pairs
from md.parallel import get_threads, set_threads
from potentials import LennardJones, Morse, PairPotential, pair_term

EPS32 = float(np.finfo(np.float32).eps)


def reference_pairs(state, radius):
    """Set of (i, j), i < j, closer than ``radius`` by minimum image."""
    d = state.positions[:, None, :] - state.positions[None, :, :]
    d -= state.box * np.round(d / state.box)
    r2 = np.einsum("ijk,ijk->ij", d, d)
    i, j = np.nonzero(np.triu(r2 < radius * radius, k=1))
    return set(zip(i.tolist(), j.tolist(), strict=True))


def relative_positions(state, clusters):
    """(clusters, 4, 3) positions relative to the slots' origins in the i and the j role,
    fillers where the kernels put them (apart in x, +-FILLER in z: two never meet)."""
    rel = state.positions[np.maximum(clusters.atom, 0)] - clusters.origin
    filler = clusters.atom < 0
    rel[filler] = 0.0
    rel[filler, 0] = 10.0 * (np.nonzero(filler)[0] % CLUSTER)
    rel_i, rel_j = rel.copy(), rel.copy()
    rel_i[filler, 2], rel_j[filler, 2] = FILLER, -FILLER
    return rel_i.reshape(-1, CLUSTER, 3), rel_j.reshape(-1, CLUSTER, 3)


def listed_atom_pairs(state, clusters, radius):
    """The atom pairs within ``radius`` of every listed cluster pair, from the list's own
    geometry (relative positions and offsets), as a list (so that a pair listed twice
    shows), each (min, max)."""
    rel_i, rel_j = relative_positions(state, clusters)
    atoms = clusters.atom.reshape(-1, CLUSTER)
    found = []
    for ci in range(clusters.n_clusters):
        for k in range(clusters.starts[ci], clusters.starts[ci + 1]):
            cj = clusters.partners[k]
            d = rel_i[ci][:, None, :] - rel_j[cj][None, :, :] + clusters.offsets[k].astype(float)
            close = np.einsum("abk,abk->ab", d, d) < radius * radius
            if k == clusters.starts[ci]:
                assert cj == ci and not clusters.offsets[k].any(), "a row starts with itself"
                close = np.triu(close, k=1)
            for a, b in zip(*np.nonzero(close), strict=True):
                i, j = atoms[ci, a], atoms[cj, b]
                assert i >= 0 and j >= 0, "a filler came within reach"
                found.append((min(i, j), max(i, j)))
    return found


def assert_covers(state, clusters, radius):
    found = listed_atom_pairs(state, clusters, radius)
    assert len(found) == len(set(found)), "an atom pair is listed twice"
    expected = reference_pairs(state, radius)
    missing, extra = expected - set(found), set(found) - expected
    assert not missing and not extra, (sorted(missing)[:5], sorted(extra)[:5])


SYSTEMS = {
    "liquid-like lattice": dict(cells=6, perturbation=0.15),
    "two types": dict(cells=6, perturbation=0.1, n_types=2),
}


@pytest.mark.parametrize("system", SYSTEMS.values(), ids=SYSTEMS.keys())
def test_cluster_list_holds_every_pair_within_the_radius_once(system, fcc_lattice, rng):
    state = fcc_lattice(**system)
    state.positions += rng.integers(-2, 3, size=state.positions.shape) * state.box  # unwrapped
    nl = NeighborList(2.5, 0.3, clusters=True)
    assert nl.update(state)
    clusters = nl.clusters
    assert clusters is not None
    assert_covers(state, clusters, nl.list_radius)
    # every atom in one slot, fillers only at the end of a column's last cluster
    assert sorted(clusters.atom[clusters.atom >= 0].tolist()) == list(range(state.n_atoms))


@pytest.mark.parametrize(
    ("n_atoms", "box"),
    [(60, 12.0), (300, (11.0, 12.5, 14.0)), (120, (8.0, 8.0, 30.0))],
    ids=["sparse gas: tall clusters", "uneven edges", "long z: images of a tall cluster"],
)
def test_sparse_columns_and_their_images_are_searched_exactly(n_atoms, box, random_gas):
    """Few atoms per column: clusters span much of the box in z, and a cluster meets
    images of itself and of its column's other clusters."""
    state = random_gas(n_atoms, box, min_distance=0.6, images=2)
    nl = NeighborList(1.5, 0.3, clusters=True)
    nl.update(state)
    assert nl.clusters is not None
    assert_covers(state, nl.clusters, nl.list_radius)


def candidates(state, radius, chunks, room=256):
    """The search's candidates: its atom check with a reach that keeps every pair (the
    variant the engine compiles; None for the positions would compile another)."""
    ncx, ncy = column_counts(state.box, state.n_atoms, radius)
    first, atom, origin, lower, upper = cluster_grid(state.positions, state.box, ncx, ncy)
    xi = np.empty(3 * len(atom), np.float32)
    xj = np.empty(3 * len(atom), np.float32)
    cluster_positions(state.positions, atom, origin, xi, xj)
    return search_pairs(
        state.box, ncx, ncy, first, lower, upper, radius, chunks, room, xi, xj, np.float32(1e30)
    )


def test_the_list_keeps_exactly_the_candidates_with_an_atom_pair_within_reach(fcc_lattice):
    """The build prunes the search's candidates atom by atom (GROMACS's pruning): the kept
    pairs are those of the candidates with an atom pair within the list radius (a row's
    first pair, the cluster with itself, always), to float32's rounding at the edge (no
    outer list: the search's own check)."""
    state = fcc_lattice(cells=6, perturbation=0.1)
    nl = NeighborList(2.5, 0.3, clusters=True, outer_skin=0.3)
    nl.update(state)
    clusters = nl.clusters
    radius = nl.list_radius
    starts, partners, offsets = candidates(state, radius, 1)
    assert 0.4 * len(partners) < clusters.n_pairs < len(partners)
    rel_i, rel_j = relative_positions(state, clusters)

    def closest(ci, cj, offset):
        d = rel_i[ci][:, None, :] - rel_j[cj][None, :, :] + offset.astype(float)
        r2 = np.einsum("abk,abk->ab", d, d)
        return np.sqrt(
            np.triu(r2, k=1)[np.triu_indices(4, 1)].min()
            if ci == cj and not offset.any()
            else r2.min()
        )

    kept = {
        (ci, int(cj), tuple(o))
        for ci in range(clusters.n_clusters)
        for cj, o in zip(
            clusters.partners[clusters.starts[ci] : clusters.starts[ci + 1]],
            clusters.offsets[clusters.starts[ci] : clusters.starts[ci + 1]],
            strict=True,
        )
    }
    for ci in range(len(starts) - 1):
        for k in range(starts[ci], starts[ci + 1]):
            key = (ci, int(partners[k]), tuple(offsets[k]))
            if k == starts[ci]:
                assert key in kept
                continue
            distance = closest(ci, partners[k], offsets[k])
            if abs(distance - radius) > 1e-4:
                assert (key in kept) == (distance < radius), (key, distance)


def closest_distances(state, clusters, rows=None):
    """Per listed cluster pair, its closest atom pair's distance (the cluster with itself:
    its distinct atoms), from the list's own geometry."""
    rel_i, rel_j = relative_positions(state, clusters)
    distances = np.empty(clusters.n_pairs)
    for ci in range(clusters.n_clusters) if rows is None else rows:
        for k in range(clusters.starts[ci], clusters.starts[ci + 1]):
            d = rel_i[ci][:, None, :] - rel_j[clusters.partners[k]][None, :, :]
            d += clusters.offsets[k].astype(float)
            r2 = np.einsum("abk,abk->ab", d, d)
            if k == clusters.starts[ci]:
                r2 = r2[np.triu_indices(CLUSTER, 1)]
            distances[k] = np.sqrt(r2.min())
    return distances


def rows_of(clusters):
    return [
        [
            (int(j), tuple(o.tolist()))
            for j, o in zip(
                clusters.partners[clusters.starts[c] : clusters.starts[c + 1]],
                clusters.offsets[clusters.starts[c] : clusters.starts[c + 1]],
                strict=True,
            )
        ]
        for c in range(clusters.n_clusters)
    ]


def moved_by(state, rng, largest):
    """``state`` with every atom moved in a random direction, the farthest by ``largest``."""
    moved = state.copy()
    step = rng.normal(size=state.positions.shape)
    step /= np.linalg.norm(step, axis=1)[:, None]
    moved.positions += step * rng.uniform(0.0, largest, size=(state.n_atoms, 1))
    moved.positions[0] = state.positions[0] + step[0] * largest
    return moved


@pytest.mark.parametrize("threads", [1, 2])
def test_a_prune_keeps_exactly_the_outer_pairs_within_the_list_radius(threads, fcc_lattice, rng):
    """GROMACS's dynamic pruning: the search lists the pairs within cutoff + outer_skin;
    once an atom has moved past skin / 2, the list the kernels read becomes the outer
    pairs with an atom pair within cutoff + skin at the new positions, each row in its
    order (to float32's rounding at the edge), on one thread or two."""
    state = fcc_lattice(cells=8, perturbation=0.1)
    before = get_threads()
    try:
        set_threads(threads)
        nl = NeighborList(2.5, 0.3, clusters=True, outer_skin=1.2)
        nl.update(state)
        outer = nl.outer_clusters
        assert outer is not None and outer.n_pairs > 1.3 * nl.clusters.n_pairs
        moved = moved_by(state, rng, 0.3)  # past skin / 2, within (outer - skin) / 2
        assert not nl.update(moved)
        assert (nl.n_builds, nl.n_prunes) == (1, 1)
        np.testing.assert_array_equal(nl.pruned_positions, moved.positions)
        np.testing.assert_array_equal(nl.reference_positions, state.positions)
        assert len(nl.clusters.bounds) - 1 == threads
    finally:
        set_threads(before)
    distances = closest_distances(moved, outer)
    radius = nl.list_radius
    expected = [
        [
            pair
            for k, pair in zip(range(outer.starts[c], outer.starts[c + 1]), row, strict=True)
            if k == outer.starts[c] or distances[k] < radius + 1e-4
        ]
        for c, row in enumerate(rows_of(outer))
    ]
    kept = rows_of(nl.clusters)
    uncertain = {
        (c, pair)
        for c, row in enumerate(rows_of(outer))
        for k, pair in zip(range(outer.starts[c], outer.starts[c + 1]), row, strict=True)
        if abs(distances[k] - radius) <= 1e-4
    }
    for c in range(outer.n_clusters):
        assert kept[c][0] == (c, (0.0, 0.0, 0.0))
        assert [p for p in kept[c] if (c, p) not in uncertain] == [
            p for p in expected[c] if (c, p) not in uncertain
        ]
    assert_covers(moved, nl.clusters, radius)  # every pair within reach, once


def test_pruning_misses_no_pair_within_the_cutoff_until_the_next_search(fcc_lattice, rng):
    """A random walk, the list updated every step: each step every atom pair within the
    cutoff lies in exactly one cluster pair of the list the kernels read; the walk takes
    the list through prunes and searches (an atom past skin / 2 since the last prune:
    prune; past (outer_skin - skin) / 2 since the search: search)."""
    state = fcc_lattice(cells=6, perturbation=0.1)
    nl = NeighborList(2.5, 0.2, clusters=True, outer_skin=0.8)
    nl.update(state)
    for _ in range(14):
        state = moved_by(state, rng, 0.07)
        nl.update(state)
        assert_covers(state, nl.clusters, nl.cutoff)
    assert nl.n_builds >= 2 and nl.n_prunes >= 3, (nl.n_builds, nl.n_prunes)


def test_the_verdict_prunes_then_searches(fcc_lattice):
    """One atom moved: up to skin / 2 nothing; past it a prune (the list's pruned
    positions move on, the search's stay); when a prune is due and the atom is past
    (outer_skin - skin) / 2 from the search, a new search; a list without an outer one
    (outer_skin <= skin) searches at skin / 2."""
    state = fcc_lattice(cells=6, perturbation=0.05)
    nl = NeighborList(2.5, 0.3, clusters=True, outer_skin=1.1)  # prune past 0.15, search 0.4
    nl.update(state)
    for distance, builds, prunes in [
        (0.14, 1, 0),
        (0.16, 1, 1),
        (0.30, 1, 1),
        (0.32, 1, 2),
        (0.41, 1, 2),
        (0.48, 2, 2),
    ]:
        moved = state.copy()
        moved.positions[7, 0] += distance
        nl.update(moved)
        assert (nl.n_builds, nl.n_prunes) == (builds, prunes), distance
    plain = NeighborList(2.5, 0.3, clusters=True, outer_skin=0.3)
    plain.update(state)
    assert plain.pruned_positions is None
    moved = state.copy()
    moved.positions[7, 0] += 0.16
    assert plain.update(moved) and plain.n_prunes == 0


def test_a_box_too_small_for_the_outer_list_searches_at_the_list_radius(fcc_lattice):
    state = fcc_lattice(cells=5, perturbation=0.05)  # edge 8.4: > 2 x 2.8, < 2 x 4.3
    nl = NeighborList(2.5, 0.3, clusters=True, outer_skin=1.8)
    nl.update(state)
    assert nl.clusters is not None and nl.pruned_positions is None
    assert_covers(state, nl.clusters, nl.list_radius)


@pytest.mark.parametrize(("cells", "outer"), [(5, False), (6, True)])
def test_no_outer_list_where_it_needs_many_narrower_columns(cells, outer, fcc_lattice):
    """A box just over twice the outer radius (500 atoms, edge 8.40 against 2 x 4.0) would
    need 23 x 23 columns for 125 clusters, so that no column meets two images of another:
    its search took 4 ms against 0.2 at the list radius (5 x 5 columns). Such a box
    searches at the list radius, without pruning; 864 atoms (edge 10.1, 7 x 7 columns
    against the density's 6 x 6) keep the outer list. Both lists hold every pair."""
    state = fcc_lattice(cells=cells, perturbation=0.05)
    nl = NeighborList(2.5, 0.3, clusters=True)  # outer skin 1.5: radius 4.0
    nl.update(state)
    assert (nl.outer_clusters is not None) == outer
    assert nl.clusters is not None and (nl.pruned_positions is not None) == outer
    assert_covers(state, nl.clusters, nl.list_radius)


def test_rebuild_at_a_checkpoints_positions_gives_the_same_pruned_list(fcc_lattice, rng):
    state = fcc_lattice(cells=6, perturbation=0.1)
    nl = NeighborList(2.5, 0.3, clusters=True)
    nl.update(state)
    now = moved_by(state, rng, 0.2)
    nl.update(now)
    assert nl.n_prunes == 1
    again = NeighborList(2.5, 0.3, clusters=True)
    again.rebuild_at(now, nl.reference_positions, pruned=nl.pruned_positions)
    assert rows_of(again.clusters) == rows_of(nl.clusters)
    with pytest.raises(ValueError, match="pruned positions have shape"):
        again.rebuild_at(now, nl.reference_positions, pruned=nl.pruned_positions[:-1])


@pytest.mark.parametrize("outer", [-0.1, math.nan, math.inf])
def test_a_bad_outer_skin_is_refused(outer):
    with pytest.raises(ValueError, match="outer_skin must be >= 0 and finite"):
        NeighborList(2.5, 0.3, clusters=True, outer_skin=outer)


@pytest.mark.parametrize("cell", ["small", "tilted", "open axis", "decomposed rank"])
def test_cells_the_cluster_search_does_not_serve_get_the_slot_frame(cell, fcc_lattice):
    state = fcc_lattice(
        cells=3 if cell == "small" else 6,
        perturbation=0.05,
        pbc=(True, True, False) if cell == "open axis" else True,
    )
    if cell == "tilted":
        state.tilt = np.array([0.5, 0.0, 0.0])
    nl = NeighborList(2.5, 0.3, clusters=True)
    if cell == "decomposed rank":
        nl.keep_owned(np.arange(state.n_atoms), state.n_atoms)
    nl.update(state)
    assert nl.clusters is None
    assert nl.frame is not None  # (the small box: the search over its images)


def test_a_cell_change_rebuilds_the_clusters(fcc_lattice):
    """Offsets and origins hold the build's box lengths: a barostat's step rebuilds."""
    state = fcc_lattice(cells=6, perturbation=0.05)
    nl = NeighborList(2.5, 0.3, clusters=True)
    nl.update(state)
    assert not nl.update(state)
    state.box = state.box * 1.001
    state.positions *= 1.001
    assert nl.update(state)
    assert_covers(state, nl.clusters, nl.list_radius)


def test_the_slot_list_is_built_on_demand_at_the_build_positions(fcc_lattice, rng):
    """Per-atom results read the atom-order list: after a cluster build it comes from the
    positions of the build, so it holds what a slot build there would have held."""
    state = fcc_lattice(cells=6, perturbation=0.05)
    nl = NeighborList(2.5, 0.3, clusters=True)
    nl.update(state)
    at_build = state.copy()
    state.positions += rng.normal(scale=0.02, size=state.positions.shape)
    assert not nl.update(state)
    plain = NeighborList(2.5, 0.3)
    plain.update(at_build)
    np.testing.assert_array_equal(nl.pairs(), plain.pairs())
    mixed = ForceField([LennardJones(cutoff=2.5)], precision="mixed")
    result = mixed.compute(state, per_atom=True)
    double = ForceField([LennardJones(cutoff=2.5)]).compute(state, per_atom=True)
    assert np.abs(result.energies - double.energies).max() < 1e-5


def _relative_error(mixed, double):
    return np.abs(mixed - double).max() / np.abs(double).max()


POTENTIALS = {
    "lj-none": lambda: LennardJones(cutoff=2.5, cutoff_mode="none"),
    "lj-shift": lambda: LennardJones(cutoff=2.5),
    "lj-smooth": lambda: LennardJones(cutoff=2.5, cutoff_mode="smooth"),
    "lj-two-types": lambda: LennardJones(
        epsilon=[1.0, 0.7],
        sigma=[1.0, 0.9],
        cutoff=2.5,
        pairs={(0, 1): {"epsilon": 0.5, "cutoff": 2.1}},
    ),
    "morse (double term)": lambda: Morse(d0=1.0, alpha=2.0, r0=1.1, cutoff=2.5),
}
#: each other case compiles its own kernels (~17 s); two threads run in the default suite
#: in test_two_terms_in_one_process_each_run_their_own_pair_function
DEFAULT = {("lj-shift", 1)}


def _kernel_cases():
    return [
        pytest.param(name, threads, marks=() if (name, threads) in DEFAULT else pytest.mark.slow)
        for name in POTENTIALS
        for threads in (1, 2)
    ]


@pytest.mark.parametrize(("name", "threads"), _kernel_cases())
def test_cluster_kernels_equal_the_double_frame_to_float32_round_off(
    name, threads, fcc_lattice, rng
):
    state = fcc_lattice(cells=8, perturbation=0.08, n_types=2 if "two" in name else 1)
    state.positions += rng.integers(-3, 4, size=state.positions.shape) * state.box
    potential = POTENTIALS[name]()
    before = get_threads()
    try:
        set_threads(threads)
        double = ForceField([potential]).compute(state, virial=True)
        field = ForceField([potential], precision="mixed")
        results = [field.compute(state, virial=True)]
        field.invalidate()
        results.append(field.compute(state, virial=False))  # the other variant
        clusters = field.neighbor_list.clusters
        assert clusters is not None and len(clusters.bounds) - 1 == threads
    finally:
        set_threads(before)
    for mixed in results:
        error = _relative_error(mixed.forces, double.forces)
        assert 1e-3 * EPS32 < error < 200 * EPS32, error  # float32 lanes, double sums
        assert abs(mixed.energy - double.energy) < 20 * EPS32 * abs(double.energy)
    assert _relative_error(results[0].virial, double.virial) < 20 * EPS32
    assert results[1].virial is None
    for mixed in results:
        # Newton's third law to float32 round-off: a pair's force enters the i sums and the
        # j sums in float32 lanes before each is added in double (random-walk accumulation)
        scale = np.sqrt(state.n_atoms) * np.abs(double.forces).max()
        assert np.abs(mixed.forces.sum(axis=0)).max() < 10 * EPS32 * scale
    # the virial's variant adds the same pair forces (LLVM may order the float32 lane sums
    # of the two compiled variants apart: equal to round-off, each repeatable on its own)
    assert _relative_error(results[0].forces, results[1].forces) < 10 * EPS32


def test_rows_of_every_length_give_the_double_forces(fcc_lattice):
    """A crystal slab beside a dilute gas of its lattice sites: rows of the cluster alone
    (evaluated before the row's loop, its lower triangle masked), of a few pairs and of
    more than a flush group of pairs (``potentials._cluster_ir._FLUSH``) all give the
    double frame's forces."""
    lattice = fcc_lattice(cells=8, perturbation=0.05)
    x = lattice.positions
    keep = (x[:, 0] < 0.4 * lattice.box[0]) | (np.arange(lattice.n_atoms) % 29 == 0)
    state = md.State(positions=x[keep], box=lattice.box)
    double = ForceField([LennardJones(cutoff=2.5)]).compute(state)
    field = ForceField([LennardJones(cutoff=2.5)], precision="mixed")
    mixed = field.compute(state)
    clusters = field.neighbor_list.clusters
    assert clusters is not None
    lengths = np.diff(clusters.starts)
    assert lengths.min() == 1 and lengths.max() > 17 and np.any((lengths > 1) & (lengths < 5))
    scale = np.abs(double.forces).max()
    assert np.abs(mixed.forces - double.forces).max() < 200 * EPS32 * scale
    assert abs(mixed.energy - double.energy) < 50 * EPS32 * abs(double.energy)


def test_the_cluster_kernel_gives_the_same_forces_on_every_call(fcc_lattice):
    """A fixed summation order: two evaluations of one state are bit for bit equal (what a
    checkpoint's bit-for-bit resume rests on)."""
    state = fcc_lattice(cells=6, perturbation=0.05)
    field = ForceField([LennardJones(cutoff=2.5)], precision="mixed")
    field.compute(state)
    field.invalidate()
    first = field.compute(state)
    field.invalidate()
    second = field.compute(state)
    assert np.array_equal(first.forces, second.forces) and first.energy == second.energy


def test_overlapping_atoms_give_an_infinite_energy_not_a_finite_one(fcc_lattice):
    state = fcc_lattice(cells=6, perturbation=0.05)
    state.positions[1] = state.positions[0]
    field = ForceField([LennardJones(cutoff=2.5)], precision="mixed")
    field.neighbor_list.update(state)
    result = LennardJones(cutoff=2.5).energy_forces(state, field.neighbor_list, precision="mixed")
    assert not np.isfinite(result.energy)


def test_a_mixed_melt_runs_on_the_cluster_list(fcc_lattice):
    """Simulation(precision="mixed") takes the cluster layout where the cell allows, and its
    short run follows the double run to float32 round-off's growth."""
    runs = {}
    for precision in ("double", "mixed"):
        state = md.build.maxwell_boltzmann(md.lattice("fcc", 6, density=0.8442), 1.0, seed=5)
        sim = md.Simulation(
            state, [LennardJones(cutoff=2.5)], VelocityVerlet(dt=0.005), precision=precision
        )
        sim.run(50)
        runs[precision] = sim
    assert runs["mixed"].forcefield.neighbor_list.clusters is not None
    assert runs["double"].forcefield.neighbor_list.clusters is None
    gap = np.abs(runs["mixed"].state.positions - runs["double"].state.positions).max()
    assert 0 < gap < 1e-3


def test_the_search_gives_one_list_on_any_number_of_chunks_and_grows_its_room(fcc_lattice):
    """Columns searched in chunks on the threads, rows copied together: the same list as
    one chunk; buffers too small for the rows ask for more room (None), not a short list."""
    state = fcc_lattice(cells=8, perturbation=0.1)
    lists = [candidates(state, 2.8, chunks) for chunks in (1, 2, 3)]
    for other in lists[1:]:
        for a, b in zip(lists[0], other, strict=True):
            np.testing.assert_array_equal(a, b)
    assert candidates(state, 2.8, 2, room=2) is None


@pair_term
def gaussian_bump(r2, height, width):
    """A user term (the frame's own example): not LJ, whose kernels a test ran before."""
    u = height * math.exp(-r2 / (width * width))
    return u, 2.0 * u / (width * width)


def test_two_terms_in_one_process_each_run_their_own_pair_function(fcc_lattice):
    """Each term's copy of the template compiles its own cluster kernels: numba's cache of
    compiled subroutines keys by code object, the same for every copy, and once handed a
    second term the first one's pair function (LJ's forces for a Gaussian; on any number
    of threads: one here, the threaded variants compile for half a minute)."""
    state = fcc_lattice(cells=8, perturbation=0.05)
    before = get_threads()
    try:
        set_threads(1)
        for potential in (
            LennardJones(cutoff=2.5),
            PairPotential(gaussian_bump, height=1.0, width=0.8, cutoff=2.5),
        ):
            double = ForceField([potential]).compute(state)
            field = ForceField([potential], precision="mixed")
            mixed = field.compute(state)
            assert len(field.neighbor_list.clusters.bounds) - 1 == 1
            assert _relative_error(mixed.forces, double.forces) < 200 * EPS32
            assert abs(mixed.energy - double.energy) < 20 * EPS32 * abs(double.energy)
    finally:
        set_threads(before)


def _row_kernel(term_module, lanes):
    """An i-cluster loop over ``cluster_row(..., lanes)`` of a term's float32 pair
    function: one type, no virial (the engine's kernels use 16 lanes where the CPU has
    AVX-512, else 8). Returns the energy and the largest j-lane pair count any row left."""
    from numba import njit

    from potentials._cluster_ir import cluster_row
    from potentials._kernels import cluster_j_remainders

    row = cluster_row(term_module._pair, lambda: term_module.TERM + term_module.N_TERM, lanes=lanes)

    @njit(error_model="numpy")
    def run(xi, xj, starts, partners, offsets, table, mode, data, cut2, out, j_sums, j_counts):
        out[:] = 0.0
        energy = 0.0
        most = 0
        for ci in range(len(starts) - 1):
            energy += row(
                xi,
                xj,
                offsets,
                partners,
                starts[ci],
                starts[ci + 1],
                ci,
                None,
                1,
                table,
                mode,
                data,
                cut2,
                out,
                j_sums,
                j_counts,
                0,
                None,
            )
            most = max(most, j_counts.max())
        cluster_j_remainders(j_sums, j_counts, out, 0)
        return energy, most

    return run


def _row_forces(state, potential, lanes):
    """The forces and energy of ``_row_kernel`` over the mixed ForceField's cluster list of
    ``state`` (atom order), the largest j-lane count after a row, and the j lanes and
    counts after the call."""
    from potentials._kernels import J_STRIDE
    from potentials._pair_codegen import kernels_for
    from potentials._pair_frame import CUTOFF_MODES

    field = ForceField([potential], precision="mixed")
    field.neighbor_list.update(state)
    clusters = field.neighbor_list.clusters
    assert clusters is not None
    xi = np.empty(12 * clusters.n_clusters, np.float32)
    xj = np.empty_like(xi)
    clusters.relative_positions(state.positions, xi, xj)
    module = kernels_for(potential.term, "mixed")
    table = potential.tables(1).astype(np.float32)
    cut2 = np.float32(table[module.RC2].max())
    mode = int(CUTOFF_MODES[potential.cutoff_mode])
    out = np.empty(12 * clusters.n_clusters)
    j_sums = np.zeros(J_STRIDE * clusters.n_clusters, np.float32)
    j_counts = np.zeros(clusters.n_clusters, np.int32)
    energy, most = _row_kernel(module, lanes)(
        xi,
        xj,
        clusters.starts,
        clusters.partners,
        clusters.offsets.reshape(-1),
        table,
        mode,
        potential.data,
        cut2,
        out,
        j_sums,
        j_counts,
    )
    forces = np.zeros((state.n_atoms, 3))
    slots = out.reshape(-1, 3, CLUSTER).transpose(0, 2, 1).reshape(-1, 3)
    real = clusters.atom >= 0
    np.add.at(forces, clusters.atom[real], slots[real])
    return energy, forces, most, j_sums, j_counts


def test_sixteen_lane_rows_give_the_eight_lane_forces(fcc_lattice):
    """``cluster_row(lanes=16)`` (a whole 4x4 cluster pair per vector: the kernels' width
    where the CPU has AVX-512) sums the same pair terms as ``lanes=8`` (AVX2's): forces
    and energy to float32 round-off of each other's and of double, whichever this CPU
    runs in the engine."""
    state = fcc_lattice(cells=6, perturbation=0.08)
    potential = LennardJones(cutoff=2.5)
    double = ForceField([potential]).compute(state)
    results = {lanes: _row_forces(state, potential, lanes)[:2] for lanes in (8, 16)}
    for energy, forces in results.values():
        assert _relative_error(forces, double.forces) < 200 * EPS32
        assert abs(energy - double.energy) < 20 * EPS32 * abs(double.energy)
    assert _relative_error(results[16][1], results[8][1]) < 20 * EPS32


@pytest.mark.parametrize("lanes", [8, 16])
def test_the_j_lanes_hold_a_bounded_number_of_pairs_and_are_left_zero(lanes, fcc_lattice):
    """A j cluster's forces are summed in float32 lanes for at most ``_J_FLUSH`` cluster
    pairs (then folded into its double forces at the end of the row that filled them), so
    their round-off does not grow with the neighbour count: at a 4 sigma cutoff some
    clusters are the partners of more than twice as many rows, yet every row leaves fewer
    than ``_J_FLUSH`` pairs in any cluster's lanes (a row folds those it filled). After
    the call the lanes and counts are zero again (the engine's scratch relies on it), and
    the forces are the double frame's to float32 round-off."""
    from potentials._cluster_ir import _J_FLUSH

    state = fcc_lattice(cells=7, perturbation=0.08)
    potential = LennardJones(cutoff=4.0)
    double = ForceField([potential]).compute(state)
    energy, forces, most, j_sums, j_counts = _row_forces(state, potential, lanes)
    partners = ForceField([potential], precision="mixed")
    partners.neighbor_list.update(state)
    rows_per_cluster = np.bincount(partners.neighbor_list.clusters.partners)
    assert rows_per_cluster.max() > 2 * _J_FLUSH  # the lanes fill more than once
    assert 0 < most < _J_FLUSH  # a row leaves none full: it folds those it filled
    assert not j_sums.any() and not j_counts.any()
    assert _relative_error(forces, double.forces) < 200 * EPS32
    assert abs(energy - double.energy) < 20 * EPS32 * abs(double.energy)


def test_the_threaded_slot_passes_give_the_serial_bits(fcc_lattice, rng):
    """The per-step passes around the kernel, split into runs on the threads (used from
    16000 slots a thread): the float32 relative positions and the chunks' sum into atom
    order equal the serial passes bit for bit, fillers included."""
    from md.neighbors._cluster_prune import cluster_positions_threaded
    from potentials._kernels import (
        _cluster_atom_forces,
        _cluster_atom_forces_threaded,
        cluster_sum_runs,
    )

    state = fcc_lattice(cells=6, perturbation=0.1)
    field = ForceField([LennardJones(cutoff=2.5)], precision="mixed")
    field.neighbor_list.update(state)
    clusters = field.neighbor_list.clusters
    assert (clusters.atom < 0).any(), "the test wants fillers"
    size = 12 * clusters.n_clusters
    serial = [np.full(size, np.nan, np.float32) for _ in range(2)]
    clusters.relative_positions(state.positions, *serial)
    for runs in (2, 3, 7):
        threaded = [np.full(size, np.nan, np.float32) for _ in range(2)]
        cluster_positions_threaded(state.positions, clusters.atom, clusters.origin, *threaded, runs)
        for a, b in zip(serial, threaded, strict=True):
            assert np.array_equal(a, b)
    windows = chunk_windows(
        row_reach(clusters.starts, clusters.partners), balanced_chunks(clusters.starts, 3)
    )
    buffers = rng.normal(size=12 * (windows[-1, 2] + windows[-1, 1] - windows[-1, 0]))
    expected = np.zeros((state.n_atoms, 3))
    _cluster_atom_forces(buffers, clusters.atom, windows, expected)
    for runs in (2, 5):
        forces = np.zeros((state.n_atoms, 3))
        first = cluster_sum_runs(windows, clusters.n_clusters, runs)
        _cluster_atom_forces_threaded(buffers, clusters.atom, windows, forces, first)
        assert np.array_equal(forces, expected)


def test_the_threaded_grid_gives_the_serial_arrays(fcc_lattice, rng):
    """``cluster_grid`` on the threads (the wrap in runs, the columns' sorts and the
    clusters' boxes in parallel) returns the arrays of one thread bit for bit, for atoms
    several box lengths out and equal heights in a column (a lattice's planes)."""
    state = fcc_lattice(cells=7)
    moved = state.positions + rng.normal(scale=0.2, size=state.positions.shape)
    moved += rng.integers(-3, 4, size=moved.shape) * state.box
    ncx, ncy = column_counts(state.box, state.n_atoms, 2.8)
    before = get_threads()
    for positions in (state.positions, moved):
        try:
            set_threads(1)
            serial = cluster_grid(positions, state.box, ncx, ncy)
        finally:
            set_threads(before)
        assert positions is state.positions or (serial[1] < 0).any(), "the test wants fillers"
        for runs in (1, 2, 3, 5):
            threaded = cluster_grid(positions, state.box, ncx, ncy, runs)
            for a, b in zip(serial, threaded, strict=True):
                assert a.dtype == b.dtype and np.array_equal(a, b)


def test_chunks_use_scratch_for_the_clusters_they_reach_and_the_sum_reads_only_that(
    fcc_lattice, rng
):
    """Every row's partners are its i cluster and clusters after it, and a chunk's rows
    reach only a layer of columns past its own clusters (the first chunk's: the far
    side of the periodic box too), so each chunk's forces and j lanes take room for
    that window only (``chunk_windows``), one window after another: on 2, 3, 5 and 8
    chunks the windows hold every pair and together less than chunks times the list
    (on this small lattice 1.6, 2.0, 3.0 and 3.8 times; the reach is a larger part of
    a small box). The sum into atom order reads each chunk's window and
    nothing else (garbage around the windows changes nothing)."""
    from potentials._kernels import _cluster_atom_forces

    state = fcc_lattice(cells=12, perturbation=0.1)
    state.positions += rng.integers(-2, 3, size=state.positions.shape) * state.box
    before = get_threads()
    try:
        set_threads(2)
        field = ForceField([LennardJones(cutoff=2.5)], precision="mixed")
        field.neighbor_list.update(state)
    finally:
        set_threads(before)
    clusters = field.neighbor_list.clusters
    n = clusters.n_clusters
    # the engine's windows, of a list pruned from the outer list (whose row reach they
    # take: a bound): they cover every pair, and are no smaller than the exact ones
    assert field.neighbor_list.outer_clusters is not None and len(clusters.bounds) == 3
    reach = row_reach(clusters.starts, clusters.partners)
    exact = chunk_windows(reach, clusters.bounds)
    assert np.all(clusters.windows[:, 1] >= exact[:, 1]) and clusters.windows[-1, 1] == n
    for ci in range(n):
        row = clusters.partners[clusters.starts[ci] : clusters.starts[ci + 1]]
        assert row[0] == ci and np.all(row >= ci)
    real = clusters.atom >= 0
    for chunks in (2, 3, 5, 8):
        bounds = balanced_chunks(clusters.starts, chunks)
        windows = chunk_windows(reach, bounds)
        assert np.array_equal(windows[:, 0], bounds[:-1]) and windows[-1, 1] == n
        sizes = windows[:, 1] - windows[:, 0]
        assert np.array_equal(windows[:, 2], np.concatenate([[0], np.cumsum(sizes)[:-1]]))
        for c in range(chunks):  # each window ends past the last cluster its rows reach
            reached = clusters.partners[clusters.starts[bounds[c]] : clusters.starts[bounds[c + 1]]]
            assert windows[c, 1] == max(bounds[c + 1], reached.max(initial=-1) + 1)
        total = int(sizes.sum())
        assert total < {2: 0.85, 3: 0.75, 5: 0.65, 8: 0.55}[chunks] * chunks * n, total / n
        # the sum alone, against the windows added into whole-list buffers by numpy
        buffers = np.full(12 * total + 24, np.nan)
        whole = np.zeros((chunks, 12 * n))
        for c, (first, end, place) in enumerate(windows):
            values = rng.normal(size=12 * (end - first))
            buffers[12 * place : 12 * (place + end - first)] = values
            whole[c, 12 * first : 12 * end] = values
        forces = np.empty((state.n_atoms, 3))
        _cluster_atom_forces(buffers, clusters.atom, windows, forces)
        slots = whole.sum(axis=0).reshape(-1, 3, CLUSTER).transpose(0, 2, 1).reshape(-1, 3)
        summed = np.zeros((state.n_atoms, 3))
        summed[clusters.atom[real]] = slots[real]
        assert np.isfinite(forces).all()
        assert np.allclose(forces, summed, rtol=1e-13, atol=1e-13)


class _Chunked:
    """A cluster list's arrays cut into another number of chunks, as a neighbour list
    hands them to the pair kernels."""

    def __init__(self, neighbors, chunks):
        c = neighbors.clusters
        self.clusters = ClusterFrame(c.atom, c.origin, c.starts, c.partners, c.offsets, chunks)
        self.list_radius = neighbors.list_radius


@pytest.mark.parametrize("name", ["lj-shift", pytest.param("lj-two-types", marks=pytest.mark.slow)])
def test_any_number_of_chunks_in_their_windows_gives_the_forces_of_one(name, fcc_lattice, rng):
    """The kernel over 1, 2, 3, 5 and 8 chunks, each in its own window of scratch (on
    this machine's threads, several chunks a thread): the forces, energy and virial of
    one chunk to float32 round-off and Newton's third law, and the same bits on a second
    call (the j lanes left zero by the first)."""
    state = fcc_lattice(cells=9, perturbation=0.08, n_types=2 if "two" in name else 1)
    state.positions += rng.integers(-2, 3, size=state.positions.shape) * state.box
    potential = POTENTIALS[name]()
    double = ForceField([potential]).compute(state, virial=True)
    field = ForceField([potential], precision="mixed")
    field.neighbor_list.update(state)
    results = {}
    for chunks in (1, 2, 3, 5, 8):
        neighbors = _Chunked(field.neighbor_list, chunks)
        results[chunks] = potential.energy_forces(state, neighbors, precision="mixed")
        again = potential.energy_forces(state, neighbors, precision="mixed")
        assert np.array_equal(again.forces, results[chunks].forces)
    scale = np.sqrt(state.n_atoms) * np.abs(double.forces).max()
    for result in results.values():
        assert _relative_error(result.forces, double.forces) < 200 * EPS32
        assert abs(result.energy - double.energy) < 20 * EPS32 * abs(double.energy)
        assert _relative_error(result.virial, double.virial) < 20 * EPS32
        assert np.abs(result.forces.sum(axis=0)).max() < 10 * EPS32 * scale
        assert _relative_error(result.forces, results[1].forces) < 20 * EPS32


_AVX2_ONLY = (
    "+64bit,+avx,+avx2,+bmi,+bmi2,+cmov,+cx16,+f16c,+fma,+lzcnt,+mmx,+movbe,+pclmul,+popcnt,"
    "+sahf,+sse,+sse2,+sse3,+sse4.1,+sse4.2,+ssse3,+xsave,-avx512f,-avx512bw,-avx512dq,"
    "-avx512vl,-avx512cd"
)


@pytest.mark.slow
@pytest.mark.skipif(not md._simd.PERMUTE, reason="an x86-64 CPU with AVX2 runs AVX2 code")
def test_kernels_compiled_for_avx2_keep_eight_lanes_and_the_forces(tmp_path):
    """Compiled for AVX2 alone (a child process, kernels compiled afresh) the cluster
    kernel takes 8 lanes (``md._simd.ZMM`` false; with AVX-512 the engine's own runs 16,
    see ``ZMM``), and its mixed forces equal double to float32 round-off."""
    import os
    import subprocess
    import sys

    script = """
import numpy as np
import md, md._simd
from md.forcefield import ForceField
from potentials import LennardJones
assert md._simd.PERMUTE and not md._simd.ZMM
state = md.lattice("fcc", 8, density=0.8442)
state.positions += np.random.default_rng(5).normal(scale=0.05, size=state.positions.shape)
double = ForceField([LennardJones(cutoff=2.5)]).compute(state)
field = ForceField([LennardJones(cutoff=2.5)], precision="mixed")
mixed = field.compute(state)
assert field.neighbor_list.clusters is not None
eps = float(np.finfo(np.float32).eps)
error = np.abs(mixed.forces - double.forces).max() / np.abs(double.forces).max()
assert 1e-3 * eps < error < 200 * eps, error
assert abs(mixed.energy - double.energy) < 20 * eps * abs(double.energy)
print("ok")
"""
    env = dict(
        os.environ,
        NUMBA_CPU_NAME="haswell",
        NUMBA_CPU_FEATURES=_AVX2_ONLY,
        NUMBA_CACHE_DIR=str(tmp_path / "numba"),
        XDG_CACHE_HOME=str(tmp_path),
    )
    done = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=900
    )
    assert done.returncode == 0 and done.stdout.strip().endswith("ok"), done.stderr[-3000:]


def test_the_wide_flag_follows_the_compiled_features():
    """``ZMM`` (16-lane cluster rows) is set exactly where numba compiles for AVX-512F."""
    features = md._simd._compiled_features()
    assert md._simd.ZMM == (
        md._simd.PERMUTE and "+avx512f" in features and "-evex512" not in features
    )


def test_a_kernel_module_of_either_width_and_no_other():
    """``kernels_for(..., cluster_lanes=...)`` (the benchmark's side-by-side widths) gives
    a module of its own per width, the default one the engine's; other widths are refused."""
    from potentials._pair_codegen import kernels_for

    term = LennardJones(cutoff=2.5).term
    default = kernels_for(term, "mixed")
    eight = kernels_for(term, "mixed", cluster_lanes=8)
    assert eight is not default and eight is kernels_for(term, "mixed", cluster_lanes=8)
    assert "_lanes8" in eight.__name__ and "_lanes" not in default.__name__
    with pytest.raises(ValueError, match="cluster_lanes must be 8, 16 or None"):
        kernels_for(term, "mixed", cluster_lanes=4)
