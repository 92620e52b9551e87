"""The Verlet/cell neighbour list against an independent O(N^2) minimum-image search."""

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import md
from md.neighbors import NeighborList, max_displacement2


def reference_pairs(positions, box, pbc, radius):
    """Sorted (P, 2) array of every pair i < j closer than ``radius`` by minimum image."""
    d = positions[:, None, :] - positions[None, :, :]
    for axis in range(3):
        if pbc[axis]:
            d[..., axis] -= box[axis] * np.round(d[..., axis] / box[axis])
    r2 = np.einsum("ijk,ijk->ij", d, d)
    i, j = np.nonzero(np.triu(r2 < radius * radius, k=1))
    return np.stack([i, j], axis=1).astype(np.int64)


def assert_list_is_exact(nl, state):
    """The list holds exactly the pairs within cutoff + skin, each once, in valid CSR form."""
    n = state.n_atoms
    assert nl.starts.shape == (n + 1,) and nl.starts[0] == 0
    assert np.all(np.diff(nl.starts) >= 0) and nl.starts[-1] == len(nl.neighbors)
    assert nl.neighbors.dtype == np.int32
    rows = np.repeat(np.arange(n), np.diff(nl.starts))
    assert not np.any(rows == nl.neighbors), "an atom is listed as its own neighbour"
    expected = reference_pairs(state.positions, state.box, state.pbc, nl.list_radius)
    got = nl.pairs()
    assert len(np.unique(got, axis=0)) == len(got), "a pair is listed twice"
    missing = set(map(tuple, expected)) - set(map(tuple, got))
    extra = set(map(tuple, got)) - set(map(tuple, expected))
    assert not missing and not extra, f"missing {sorted(missing)[:5]}, extra {sorted(extra)[:5]}"
    np.testing.assert_array_equal(got, expected)


# Random gases: (n_atoms, box, pbc, cutoff, skin, uses cells)
GASES = {
    "periodic-just-over-2rc": (50, 5.05, True, 2.5, 0.3, False),
    "periodic-2-cells-5-half-cells": (40, 3.0 * 1.2 - 0.01, True, 1.0, 0.2, True),
    "periodic-4-half-cells": (40, 2.5 * 1.2 - 0.01, True, 1.0, 0.2, False),
    "periodic-3-cells": (25, 3.0 * 1.2 + 0.01, True, 1.0, 0.2, True),
    "periodic-many-cells": (400, (10.0, 8.5, 12.0), True, 1.0, 0.2, True),
    "periodic-one-thin-axis": (150, (10.0, 10.0, 2.3), True, 1.0, 0.1, False),
    "periodic-no-skin": (300, 9.0, True, 1.5, 0.0, True),
    "open": (200, 9.0, False, 1.3, 0.3, True),
    "open-thin-slab": (100, (12.0, 12.0, 0.5), False, 1.3, 0.3, True),
    "mixed-xz-periodic": (250, (9.0, 8.0, 7.0), (True, False, True), 1.2, 0.3, True),
    "mixed-y-periodic": (150, (7.0, 5.2, 6.0), (False, True, False), 1.2, 0.3, True),
    "mixed-short-periodic-axis": (60, (8.0, 3.0, 8.0), (False, True, False), 1.2, 0.3, False),
}


@pytest.mark.parametrize("case", GASES.values(), ids=GASES.keys())
def test_random_gas_matches_brute_force(case, random_gas):
    n_atoms, box, pbc, cutoff, skin, uses_cells = case
    state = random_gas(n_atoms, box, pbc=pbc, min_distance=0.5, images=3)
    nl = NeighborList(cutoff, skin)
    assert nl.update(state)
    assert nl.used_cells == uses_cells
    assert nl.n_pairs > 0
    assert_list_is_exact(nl, state)


@pytest.mark.parametrize(
    ("kind", "cells", "cutoff", "pbc"),
    [
        ("fcc", 4, 2.5, True),  # 6.7 box: two cells, O(N^2)
        ("fcc", 5, 2.5, True),  # 8.4 box: three cells
        ("fcc", 6, 1.4, True),
        ("bcc", 5, 1.9, (True, True, False)),
        ("sc", 6, 1.3, False),
    ],
)
def test_perturbed_lattice_matches_brute_force(kind, cells, cutoff, pbc, rng):
    state = md.lattice(kind, cells, density=0.8442, pbc=pbc)
    state.positions += rng.normal(scale=0.04, size=state.positions.shape)
    # Whole-box jumps along periodic axes: the engine keeps positions unwrapped.
    state.positions += rng.integers(-2, 3, size=state.positions.shape) * state.box * state.pbc
    nl = NeighborList(cutoff, skin=0.25)
    nl.update(state)
    assert_list_is_exact(nl, state)


def test_sparse_cluster_across_the_boundary_of_a_huge_box(rng):
    """A few atoms in a box of ~10^5 cells: the grid is coarsened, pairs across the edge kept."""
    positions = rng.uniform(-2.0, 2.0, size=(30, 3))  # straddles the periodic faces at 0
    state = md.State(positions=positions, box=50.0)
    nl = NeighborList(1.0, 0.2)
    nl.update(state)
    assert nl.used_cells
    assert_list_is_exact(nl, state)


@pytest.mark.parametrize("pbc", [True, False])
def test_crowded_cells_searched_in_several_blocks_match_brute_force(pbc, rng):
    """The search copies each cell's slots in blocks of GATHER_BLOCK: cells holding
    several blocks' worth (a dense random gas), partly filled blocks and empty cells all
    give the exact list, in a periodic and an open box."""
    from md.neighbors._cell_kernels import GATHER_BLOCK

    state = md.State(positions=rng.uniform(0.0, 6.0, size=(1500, 3)), box=6.0, pbc=pbc)
    state.positions[:100] = rng.uniform(0.0, 0.5, size=(100, 3))  # one very full corner
    nl = NeighborList(1.0, 0.2)
    nl.update(state)
    assert nl.used_cells
    # Cells are at least (cutoff + skin) / 2 = 0.6 wide, so the corner's 0.5-wide cube
    # meets at most 8 of them: one holds 13 or more atoms, over one block. With 1.4
    # atoms per cell elsewhere, many cells hold less than a block and some none.
    assert 100 > 8 * GATHER_BLOCK
    assert_list_is_exact(nl, state)


def _candidates(n, rng, first=5, pad=64):
    """Packed candidates at first..first+n-1 around the origin, ``pad`` entries past them
    set to pass the distance test, and the packed values of those within 0.8."""
    from md.neighbors._cell_kernels import _CODE_SHIFT

    size = first + n + pad
    xyz = rng.uniform(-1.0, 1.0, size=(3, size))
    xyz[:, first + n :] = 0.0  # past the last candidate: at the centre, would pass
    slots = rng.permutation(1000)[:size].astype(np.uint32)
    packed = slots | (rng.integers(0, 27, size=size).astype(np.uint32) << _CODE_SHIFT)
    r2_max = 0.64
    near = (xyz[:, first : first + n] ** 2).sum(axis=0) < r2_max
    wanted = packed[first : first + n][near]
    arrays = tuple(np.ascontiguousarray(row) for row in xyz) + (packed,)
    return arrays, r2_max, wanted


@pytest.mark.parametrize("n", [0, 1, 37, 63, 64, 65, 127, 128, 129, 200])
def test_keep_lists_exactly_the_near_candidates_at_every_word_edge(n, rng):
    """Near the end of a chunk's region the search tests candidates 64 at a time into
    bit masks (``_keep``): for counts at and around multiples of 64, the kept packed
    values equal a plain numpy selection, in order; the entries past the last candidate
    (set to pass the test) are never kept, and past the capacity the hits are counted
    but not written."""
    from md.neighbors._candidates import _keep

    first = 5
    arrays, r2_max, wanted = _candidates(n, rng, first)
    masks = np.empty(8, dtype=np.uint64)
    out = np.full(3 + n, 7, dtype=np.uint32)
    found = _keep(0.0, 0.0, 0.0, r2_max, *arrays, first, first + n, masks, 1, 2, 3 + n, out)
    assert found == len(wanted)
    assert np.array_equal(out[3 : 3 + found], wanted)
    assert np.all(out[:3] == 7) and np.all(out[3 + found :] == 7)
    # No room: counted, nothing written.
    out[:] = 7
    full = _keep(0.0, 0.0, 0.0, r2_max, *arrays, first, first + n, masks, 1, 2, 1 + found, out)
    assert full == found
    assert np.all(out == 7)


@pytest.mark.parametrize("path", ["scan", "permute-whole", "permute-blocks"])
@pytest.mark.parametrize("valid", [0, 1, 7, 8, 9, 37, 63, 64])
def test_near_pack_writes_the_kept_candidates_in_order_on_every_path(path, valid, rng):
    """The search's main path writes the kept candidates of up to 64 as it tests them:
    by AVX2 lane permutes (on x86 with AVX2; variants for whole words of 64 and for a
    word's blocks one by one) or by scanning a bit mask (every CPU). Each keeps exactly
    numpy's selection of the first ``valid`` candidates, in order, returns the new end,
    and writes nothing before ``at`` or beyond the 8 entries from the end."""
    from numba import njit

    import md._simd
    from md._simd import PERMUTATIONS
    from md.neighbors._candidates import (
        _near_pack_blocks,
        _near_pack_permute_whole,
        _near_pack_scan,
    )

    if path != "scan" and not md._simd.PERMUTE:
        pytest.skip("compiled for a CPU without AVX2: the permute path is not used")
    if path == "permute-whole" and valid != 64:
        pytest.skip("the whole-word variant takes exactly 64 candidates")
    pack = {
        "scan": _near_pack_scan,
        "permute-whole": _near_pack_permute_whole,
        "permute-blocks": _near_pack_blocks,
    }[path]

    @njit
    def call(x, y, z, packed, start, valid, out, at):
        return pack(0.0, 0.0, 0.0, 0.64, x, y, z, packed, start, valid, PERMUTATIONS, out, at)

    first = 5
    arrays, _, wanted = _candidates(valid, rng, first)
    out = np.full(3 + 64 + 8, 7, dtype=np.uint32)
    end = call(*arrays, first, valid, out, 3)
    assert end == 3 + len(wanted)
    assert np.array_equal(out[3:end], wanted)
    assert np.all(out[:3] == 7) and np.all(out[end + 8 :] == 7)


@pytest.mark.parametrize("n_atoms", [0, 1, 2])
def test_tiny_systems(n_atoms):
    state = md.State(positions=[[0.1, 0.2, 0.3], [0.9, 0.2, 0.3]][:n_atoms] or np.zeros((0, 3)))
    state.box[:] = 10.0
    nl = NeighborList(1.0, 0.1)
    nl.update(state)
    assert_list_is_exact(nl, state)
    assert nl.n_pairs == (1 if n_atoms == 2 else 0)


@settings(max_examples=60, deadline=None, database=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n_atoms=st.integers(2, 120),
    edges_over_radius=st.tuples(*[st.floats(2.05, 7.0)] * 3),
    pbc=st.tuples(*[st.booleans()] * 3),
    skin=st.sampled_from([0.0, 0.1, 0.4]),
)
def test_any_box_and_periodicity_matches_brute_force(seed, n_atoms, edges_over_radius, pbc, skin):
    generator = np.random.default_rng(seed)
    cutoff = 1.0
    box = np.array(edges_over_radius) * (cutoff + skin)
    box = np.maximum(box, 2.0 * cutoff * 1.001)
    positions = generator.uniform(-2.0, 3.0, size=(n_atoms, 3)) * box
    state = md.State(positions=positions, box=box, pbc=list(pbc))
    nl = NeighborList(cutoff, skin)
    nl.update(state)
    assert_list_is_exact(nl, state)


# --------------------------------------------------------------------- rebuild


def test_rebuild_exactly_when_an_atom_moves_more_than_half_the_skin(random_gas):
    state = random_gas(100, 6.0, min_distance=0.7)
    nl = NeighborList(cutoff=1.5, skin=0.4)
    assert nl.update(state) and nl.n_builds == 1
    assert not nl.update(state)

    # Every atom moves just under skin / 2 (in a random direction): no rebuild.
    reference = state.positions.copy()
    directions = np.random.default_rng(1).normal(size=reference.shape)
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    state.positions[:] = reference + 0.199 * directions
    assert not nl.update(state) and nl.n_builds == 1

    # Displacements count from the last build, not from the last update.
    state.positions[:] = reference + 0.1 * directions
    assert not nl.update(state)
    state.positions[7] = reference[7] + 0.201 * directions[7]
    assert nl.update(state) and nl.n_builds == 2
    assert_list_is_exact(nl, state)

    # The new reference is the rebuilt configuration.
    state.positions[7] += 0.19 * directions[7]
    assert not nl.update(state)
    state.positions[7] += 0.02 * directions[7]
    assert nl.update(state) and nl.n_builds == 3


def test_rebuild_when_box_periodicity_or_atom_count_changes(random_gas):
    state = random_gas(50, 7.0)
    nl = NeighborList(cutoff=1.5, skin=0.4)
    nl.update(state)
    state.box[0] = 7.05  # atoms kept in place: up to 0.05 from their scaled positions
    assert not nl.update(state) and nl.n_followed == 1  # within what the skin covers
    within = set(map(tuple, reference_pairs(state.positions, state.box, state.pbc, 1.5)))
    assert within <= set(map(tuple, nl.pairs()))
    state.box[0] = 7.6  # up to 0.6 away: beyond the half skin
    assert nl.update(state)
    assert_list_is_exact(nl, state)
    state.pbc[1] = False
    assert nl.update(state)
    assert_list_is_exact(nl, state)
    smaller = md.State(positions=state.positions[:-1], box=state.box, pbc=state.pbc)
    assert nl.update(smaller)
    assert_list_is_exact(nl, smaller)
    assert nl.n_builds == 4


@pytest.mark.parametrize("pbc", [True, False, (True, False, True)], ids=["pbc", "open", "mixed"])
def test_every_pair_within_cutoff_is_listed_until_the_rebuild(pbc, random_gas, rng):
    cutoff, skin = 1.6, 0.5
    state = random_gas(300, 7.0, pbc=pbc, min_distance=0.6, images=2)
    nl = NeighborList(cutoff, skin)
    nl.update(state)
    reference = state.positions.copy()
    for _ in range(20):
        directions = rng.normal(size=reference.shape)
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        lengths = rng.uniform(0.0, 0.4999 * skin, size=(len(directions), 1))
        state.positions[:] = reference + lengths * directions
        assert not nl.update(state)
        within = set(map(tuple, reference_pairs(state.positions, state.box, state.pbc, cutoff)))
        assert within <= set(map(tuple, nl.pairs()))
    assert nl.n_builds == 1


def test_worst_case_approach_stays_outside_the_cutoff():
    """Two atoms just beyond cutoff + skin approach head-on by just under skin / 2 each."""
    cutoff, skin = 2.0, 0.4
    gap = cutoff + skin + 1e-6
    state = md.State(positions=[[0.0, 0, 0], [gap, 0, 0]], box=10.0, pbc=False)
    nl = NeighborList(cutoff, skin)
    nl.update(state)
    assert nl.n_pairs == 0
    state.positions[0, 0] += 0.5 * skin - 1e-7
    state.positions[1, 0] -= 0.5 * skin - 1e-7
    assert not nl.update(state)
    assert state.positions[1, 0] - state.positions[0, 0] > cutoff
    state.positions[1, 0] -= 2e-7
    assert nl.update(state) and nl.n_pairs == 1


# ---------------------------------------------------------------------- errors


@pytest.mark.parametrize("edge", [5.0, 4.9, 1.0])
def test_cutoff_too_long_for_a_periodic_edge_raises(edge):
    state = md.State(positions=np.zeros((2, 3)) + [[0, 0, 0], [0.5, 0.5, 0.5]], box=[9, edge, 9])
    nl = NeighborList(cutoff=2.5, skin=0.3)
    with pytest.raises(ValueError, match="cutoff"):
        nl.update(state)
    with pytest.raises(ValueError, match="cutoff"):
        nl.check_box(state.box, state.pbc)


def test_more_atoms_than_the_packed_slots_hold_raises(monkeypatch, fcc_lattice):
    """The cell search packs slot and image code in 32 bits: a list of more atoms than that
    holds is refused with the limit in the message, not silently wrapped."""
    import md.neighbors.lists

    state = fcc_lattice(cells=5)  # 500 atoms
    monkeypatch.setattr(md.neighbors.lists, "MAX_SLOTS", 499)
    with pytest.raises(ValueError, match="at most 499 atoms per process, got 500"):
        NeighborList(2.5, 0.3).build(state)


def test_short_open_edge_is_fine():
    state = md.State(positions=[[0, 0, 0], [0.5, 0.5, 0.5]], box=[9, 1.0, 9], pbc=[1, 0, 1])
    nl = NeighborList(cutoff=2.5, skin=0.3)
    nl.update(state)
    assert nl.n_pairs == 1


@pytest.mark.parametrize(("cutoff", "skin"), [(0.0, 0.3), (-1.0, 0.3), (np.nan, 0.3), (1, -0.1)])
def test_invalid_cutoff_or_skin_raises(cutoff, skin):
    with pytest.raises(ValueError):
        NeighborList(cutoff, skin)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
@pytest.mark.parametrize("after_build", [False, True])
@pytest.mark.parametrize("box", [5.0, 12.0], ids=["brute-force", "cells"])
def test_non_finite_positions_raise(bad, after_build, box, random_gas):
    state = random_gas(40, box)
    nl = NeighborList(cutoff=1.2, skin=0.3)
    if after_build:
        nl.update(state)
    good = state.positions[13, 1]
    state.positions[13, 1] = bad
    with pytest.raises(md.NonFiniteError):
        nl.update(state)
    with pytest.raises(md.NonFiniteError):
        nl.build(state)
    # a failed build leaves a list that asks to be rebuilt, and the rebuild is exact
    state.positions[13, 1] = good
    assert nl.needs_rebuild(state) and nl.update(state)
    assert_list_is_exact(nl, state)
    assert not nl.update(state)


def test_open_cluster_spread_over_a_huge_extent():
    # Atoms that flew apart (a blown-up open system) must not overflow the cell grid.
    positions = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1e250, -1e250, 3e249]])
    state = md.State(positions=positions, box=10.0, pbc=False)
    nl = md.NeighborList(cutoff=2.5, skin=0.3)
    nl.build(state)
    assert nl.pairs().tolist() == [[0, 1]]


def test_a_list_that_switches_from_pair_search_to_cells_stays_exact():
    """A box that grows (a barostat, an ASE cell change) moves one list from the O(N^2)
    search, which had grown its buffers, to the cell search, which fills the pair and the
    image-code buffers side by side: both must have grown (a shorter code buffer was written
    past its end, corrupting memory)."""
    state = md.lattice("fcc", 4, density=0.95)  # 256 atoms; box 6.46 < 5 half-radius cells
    nl = NeighborList(2.5, skin=0.3)
    nl.update(state)
    assert not nl.used_cells
    assert_list_is_exact(nl, state)
    scale = (0.95 / 0.7) ** (1 / 3)  # box 7.15: room for the cells
    state.positions *= scale
    state.box = state.box * scale
    assert not nl.update(state)  # an affine expansion: the list is kept, in the new box
    nl.build(state)
    assert nl.used_cells
    assert_list_is_exact(nl, state)
    state.positions /= scale  # and back
    state.box = state.box / scale
    nl.build(state)
    assert not nl.used_cells
    assert_list_is_exact(nl, state)


def test_max_displacement_equals_numpy_and_flags_every_non_finite_coordinate(rng):
    """The rebuild check's largest squared displacement (an integer maximum over bit
    patterns) equals numpy's, and any NaN (either sign) or infinity, in any atom and
    coordinate, gives inf, serial and threaded."""
    from md.neighbors._build_kernels import (
        _largest_displacement2,
        _max_displacement2,
        _max_displacement2_threaded,
    )

    reference = rng.uniform(-5.0, 5.0, size=(1001, 3))
    positions = reference + rng.normal(scale=0.1, size=reference.shape)
    exact = ((positions - reference) ** 2).sum(axis=1).max()
    assert _max_displacement2(positions, reference) == exact
    assert max_displacement2(positions, reference) == exact  # the public name (Simulation's)
    assert _max_displacement2_threaded(positions, reference, 3) == exact
    for chunks in (1, 3):
        assert _largest_displacement2(positions, reference, chunks) == exact
    assert _max_displacement2(positions[:0], reference[:0]) == 0.0
    assert _max_displacement2(reference, reference) == 0.0
    for atom, axis in ((0, 0), (500, 1), (1000, 2)):
        for bad in (np.nan, -np.nan, np.inf, -np.inf):
            broken = positions.copy()
            broken[atom, axis] = bad
            assert _max_displacement2(broken, reference) == np.inf
            assert max_displacement2(broken, reference) == np.inf
            assert _max_displacement2_threaded(broken, reference, 3) == np.inf
            assert _largest_displacement2(broken, reference, 3) == np.inf


def test_list_back_in_its_build_cell_takes_the_build_lengths_again(random_gas):
    """A list that followed a barostat's small cell change and sees the build's cell
    again (the fast same-cell test of every step) returns to the build's lengths and
    shifts, without a rebuild, and its frame positions are the atoms' again."""
    state = random_gas(200, 7.0)
    nl = NeighborList(cutoff=1.5, skin=0.4)
    nl.update(state)
    lengths, shifts = nl.lengths.copy(), nl.shifts.copy()
    state.box[0] = 7.02
    assert not nl.update(state) and nl.n_followed == 1
    assert nl.lengths[0] == 7.02 and not np.array_equal(nl.shifts, shifts)
    state.box[0] = 7.0
    assert not nl.update(state) and nl.n_builds == 1
    assert np.array_equal(nl.lengths, lengths) and np.array_equal(nl.shifts, shifts)
    wrapped = md.box.wrap(state.positions[nl.order], state.box, state.pbc)[0]
    assert np.allclose(nl.frame_positions(state.positions), wrapped, rtol=0.0, atol=1e-12)
    assert_list_is_exact(nl, state)


@pytest.mark.parametrize("chunks", [2, 3, 5])
@pytest.mark.parametrize("shape", ["periodic", "open", "sheared"])
def test_threaded_binning_and_plane_order_equal_the_serial_ones(chunks, shape, rng):
    """The cell search's counting sort and its second (z, x, y) layout (with the slots'
    cells, tags and largest counts) run in chunks on threads; each gives exactly the
    serial result, atoms in index order within a cell."""
    from md.neighbors._build_kernels import _bin_atoms, _bin_atoms_threaded
    from md.neighbors._cell_kernels import GATHER_BLOCK, _slot_layout, _slot_layout_threaded

    n = 3000
    positions = rng.uniform(-3.0, 13.0, size=(n, 3))  # some outside the box
    pbc = np.array([shape != "open", True, True])
    box = np.array([10.0, 10.0, 10.0])
    tilt = np.array([1.5, -2.0, 0.5]) if shape == "sheared" else np.zeros(3)
    origin = np.array([positions[:, 0].min(), 0.0, 0.0]) if shape == "open" else np.zeros(3)
    n_cells = np.array([6, 7, 8])
    width = np.array(
        [(positions[:, 0].max() - origin[0]) / 6 if shape == "open" else 10 / 6, 10 / 7, 10 / 8]
    )

    def binned(threaded):
        out = (
            np.empty(n, dtype=np.int64),
            np.empty(int(np.prod(n_cells)) + 1, dtype=np.int64),
            np.empty(n, dtype=np.int64),
            np.zeros((3, n + GATHER_BLOCK)),
            np.empty((n, 3), dtype=np.int32),
        )
        arguments = (positions, origin, width, n_cells, pbc, box, tilt, *out)
        if threaded:
            _bin_atoms_threaded(*arguments, chunks)
        else:
            _bin_atoms(*arguments)
        return out

    serial, threaded = binned(False), binned(True)
    for a, b in zip(serial, threaded, strict=True):
        assert np.array_equal(a, b)
    cell_of, cell_starts, order = serial[0], serial[1], serial[2]
    assert np.all(np.diff(cell_of[order]) >= 0)  # grouped by cell
    for c in range(len(cell_starts) - 1):  # index order within a cell
        assert np.all(np.diff(order[cell_starts[c] : cell_starts[c + 1]]) > 0)
    slot_cell = np.full(n, -1, dtype=np.int64)
    layout = _slot_layout(serial[3], cell_starts, n_cells, slot_cell)
    threaded_cells = np.full(n, -1, dtype=np.int64)
    layout_threaded = _slot_layout_threaded(serial[3], cell_starts, n_cells, threaded_cells, chunks)
    assert np.array_equal(slot_cell, cell_of[order]) and np.array_equal(threaded_cells, slot_cell)
    (px, py, pz, slot, plane_starts), tags, most = layout
    for a, b in zip(layout[0], layout_threaded[0], strict=True):
        assert np.array_equal(a, b)
    assert np.array_equal(tags, layout_threaded[1]) and most == layout_threaded[2]
    # the (z, x, y) order: each cell's slots, in slot order, where that cell's turn comes
    nx, ny, nz = n_cells
    expected = [
        np.arange(cell_starts[(kx * ny + ky) * nz + kz], cell_starts[(kx * ny + ky) * nz + kz + 1])
        for kz in range(nz)
        for kx in range(nx)
        for ky in range(ny)
    ]
    assert np.array_equal(slot[:n], np.concatenate(expected))
    assert np.array_equal(np.diff(plane_starts), [len(e) for e in expected])
    assert np.array_equal(px[:n], serial[3][0, slot[:n]])
    assert np.array_equal(py[:n], serial[3][1, slot[:n]])
    assert np.array_equal(pz[:n], serial[3][2, slot[:n]])
    assert np.all(px[n:] == 0.0) and np.all(slot[n:] == 0)  # finite padding
    assert np.array_equal(tags & ((1 << 27) - 1), np.arange(len(tags)))
    assert np.all(tags >> 27 == 13)  # no image shift
    counts = np.diff(cell_starts)
    assert most == (counts.max(), counts.reshape(-1, nz).sum(axis=1).max())


def _pairs_within(state, radius):
    """Sorted (P, 2) pairs i < j closer than ``radius`` by the (tilted) minimum image."""
    d = state.positions[:, None] - state.positions[None]
    d = md.box.minimum_image(d, state.box, state.pbc, state.tilt)
    i, j = np.nonzero(np.triu((d**2).sum(axis=-1) < radius**2, k=1))
    return np.stack([i, j], axis=1).astype(np.int64)


@pytest.mark.parametrize("shape", ["periodic", "open", "sheared"])
def test_one_build_call_in_any_number_of_chunks_gives_the_same_list(shape, fcc_lattice):
    """``_cell_list`` (bin, search, join in one compiled call) gives the same slots,
    pairs and shifted-row flags in 1, 2, 3 or 5 search chunks, joined across real gaps
    between the chunks' regions; a buffer too small is reported as minus the largest
    chunk's count, and a buffer of that many per chunk then holds the list. The rows of its balanced
    chunks split the pairs as evenly as rows allow."""
    from md.neighbors._build_kernels import _cell_list

    state = fcc_lattice(cells=6, perturbation=0.1, pbc=shape != "open")
    if shape == "sheared":
        state.tilt[:] = (1.1, -0.7, 0.4)
    nl = NeighborList(cutoff=1.5, skin=0.3)
    nl.build(state)
    assert np.array_equal(nl.pairs(), _pairs_within(state, nl.list_radius))
    origin, width, n_cells, reach = nl._grid(state)
    r2 = nl.list_radius**2

    def build(chunks, size):
        neighbors, codes = np.full(size, -1, dtype=np.int32), np.full(size, 255, dtype=np.uint8)
        out = _cell_list(
            state.positions,
            origin,
            width,
            n_cells,
            reach,
            state.pbc,
            state.box,
            nl.tilt,
            r2,
            chunks,
            neighbors,
            codes,
        )
        return out, neighbors, codes

    (order, images, starts, bounds, count, shifted), neighbors, codes = build(1, 3 * nl.n_pairs)
    assert count == nl.n_pairs and np.array_equal(starts, nl.slot_starts)
    assert np.array_equal(neighbors[:count], nl.slot_neighbors)
    assert np.array_equal(codes[:count], nl.codes) and np.array_equal(order, nl.order)
    # each row's flag: set on every row with a pair with an image shift (a code other than
    # 13), and otherwise only near a periodic edge (on rows whose pairs happen not to cross)
    rows = np.repeat(np.arange(state.n_atoms), np.diff(starts))
    crossing = np.bincount(rows, weights=codes[:count] != 13, minlength=state.n_atoms) > 0
    assert np.array_equal(nl.frame.shifted, shifted) and np.all(shifted[crossing])
    assert crossing.any() == (shape != "open") and shifted.any() == (shape != "open")
    assert not shifted.all()
    for chunks in (2, 3, 5):
        small = build(chunks, nl.n_pairs // 2)[0][4]
        assert small < 0 and -small * chunks > nl.n_pairs // 2
        (o, i, s, b, c, sh), nb, cd = build(chunks, -small * chunks)
        assert c == count and np.array_equal(o, order) and np.array_equal(i, images)
        assert np.array_equal(s, starts) and np.array_equal(nb[:c], neighbors[:count])
        assert np.array_equal(cd[:c], codes[:count]) and np.array_equal(sh, shifted)
        (o, i, s, b, c, sh), nb, cd = build(chunks, 3 * nl.n_pairs)  # gaps between regions
        assert np.array_equal(s, starts) and np.array_equal(nb[:c], neighbors[:count])
        assert np.array_equal(cd[:c], codes[:count]) and np.array_equal(sh, shifted)
        assert b[0] == 0 and b[-1] == state.n_atoms and np.all(np.diff(b) >= 0)
        per_chunk = np.diff(s[b])
        assert per_chunk.max() - per_chunk.min() <= 2 * np.diff(s).max()


def test_balanced_bounds_start_each_chunk_at_the_first_row_past_its_share():
    """Chunk c starts at the first row starting at or after ceil(c P / chunks), never
    before the chunk ahead; empty rows, no pairs and one chunk included."""
    from md.neighbors._build_kernels import _balanced_bounds

    rng = np.random.default_rng(11)
    for _ in range(500):
        n = int(rng.integers(0, 40))
        rows = rng.integers(0, 6, n) * (rng.random(n) < 0.7)  # many empty rows
        starts = np.concatenate([[0], np.cumsum(rows)]).astype(np.int64)
        chunks = int(rng.integers(1, 8))
        targets = [-(-starts[-1] * c // chunks) for c in range(chunks + 1)]
        expected = [0] + [int(np.searchsorted(starts, t)) for t in targets[1:-1]] + [n]
        expected = np.maximum.accumulate(expected)
        assert np.array_equal(_balanced_bounds(starts, chunks), expected)


def test_one_list_rebuilt_in_cell_after_cell_stays_exact(random_gas):
    """A list keeps a build's cell data (grid, lengths, shifts) for the next build in the
    same periodic cell; rebuilt in other edges, another tilt, another periodicity, with
    fewer atoms and back in the first cell, it is exact every time."""
    from md.neighbors._build_kernels import _shift_table

    state = random_gas(300, 8.0, min_distance=0.6, images=2)
    nl = NeighborList(cutoff=1.2, skin=0.3)
    cells = [
        (np.array([8.0, 8.0, 8.0]), np.zeros(3), np.array([True, True, True])),
        (np.array([8.4, 7.6, 8.0]), np.zeros(3), np.array([True, True, True])),
        (np.array([8.4, 7.6, 8.0]), np.array([0.9, -0.5, 0.3]), np.array([True, True, True])),
        (np.array([8.4, 7.6, 8.0]), np.zeros(3), np.array([True, False, True])),
        (np.array([8.0, 8.0, 8.0]), np.zeros(3), np.array([True, True, True])),
    ]
    for box, tilt, pbc in cells * 2:
        trial = md.State(positions=state.positions, box=box, pbc=pbc, tilt=tilt)
        nl.build(trial)
        assert np.array_equal(nl.pairs(), _pairs_within(trial, nl.list_radius))
        assert np.array_equal(nl.lengths, np.where(pbc, box, 0.0))
        assert np.array_equal(nl.tilt, tilt)
        assert np.array_equal(nl.shifts, _shift_table(box, pbc, tilt))
    fewer = md.State(positions=state.positions[:-7], box=cells[0][0], pbc=cells[0][2])
    nl.build(fewer)
    assert_list_is_exact(nl, fewer)


def test_move_within_equals_a_copy_of_the_slice():
    """``move_within`` (memmove inside one array), the join of the chunks' regions: forward
    and backward overlapping moves and an empty one, every element type the list uses."""
    from numba import njit

    from md._simd import move_within

    @njit
    def move(array, to, start, count):
        move_within(array, to, start, count)

    for dtype in (np.int32, np.uint8, np.int64, np.float64):
        for to, start, count in ((3, 10, 50), (20, 10, 50), (0, 90, 10), (5, 5, 40), (7, 1, 0)):
            array = np.arange(100).astype(dtype)
            expected = array.copy()
            expected[to : to + count] = array[start : start + count].copy()
            move(array, to, start, count)
            assert np.array_equal(array, expected), (dtype, to, start, count)


#: A CPU without AVX2 (numba's target): the cell search's portable bit-scan path.
_NO_AVX2 = (
    "+64bit,+avx,+cmov,+cx16,+mmx,+pclmul,+popcnt,+sahf,+sse,+sse2,+sse3,+sse4.1,+sse4.2,"
    "+ssse3,+xsave,-avx2,-avx512f,-bmi,-bmi2,-fma"
)


@pytest.mark.slow
def test_cell_search_compiled_without_avx2_matches_brute_force(tmp_path):
    """On a CPU without AVX2 the search packs its hits by scanning bit masks instead of
    lane permutes: compiled for such a CPU (in a child process, kernels compiled afresh),
    crowded, sparse, periodic, open and sheared boxes still give the exact list."""
    import os
    import subprocess
    import sys

    script = """
import itertools

import numpy as np
import md._simd
from md.neighbors import NeighborList
import md
assert not md._simd.PERMUTE
rng = np.random.default_rng(3)
for pbc, tilt in ((True, None), (False, None), (True, [0.4, -0.3, 0.2])):
    state = md.State(positions=rng.uniform(0.0, 6.0, size=(1500, 3)), box=6.0, pbc=pbc)
    state.positions[:100] = rng.uniform(0.0, 0.5, size=(100, 3))  # over a word in a cell
    if tilt is not None:
        state.tilt = np.array(tilt)
    nl = NeighborList(1.0, 0.2)
    nl.update(state)
    assert nl.used_cells
    lengths = np.where(state.pbc, state.box, 0.0)
    got = set(map(tuple, nl.pairs()))
    h = md.box.cell_matrix(lengths, md.box.periodic_tilt(state.tilt, state.pbc))
    x = state.positions
    expected = set()
    for i in range(len(x)):
        d = x[i] - x[i + 1 :]
        if pbc:
            f = np.linalg.solve(h.T, d.T).T
            d = (f - np.round(f)) @ h
        near = np.nonzero((d * d).sum(axis=1) < 1.2 ** 2)[0]
        expected.update((i, i + 1 + j) for j in near)
    assert got == expected, (len(got), len(expected))
print("ok")
"""
    env = dict(
        os.environ,
        NUMBA_CPU_NAME="sandybridge",
        NUMBA_CPU_FEATURES=_NO_AVX2,
        NUMBA_CACHE_DIR=str(tmp_path / "numba"),
    )
    done = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=900
    )
    assert done.returncode == 0 and done.stdout.strip().endswith("ok"), done.stderr[-3000:]


def _designates(a, b):
    """md.neighbors._cell_kernels.designates for arrays: whether a (not b) is the pair's designated
    atom."""
    return (a < b) != ((a + b) % 2 == 1)


@pytest.mark.parametrize("owners", ["slab", "scattered"])
@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("shape", ["open", "periodic"])
def test_keep_owned_lists_each_pair_under_the_owner_of_its_designated_atom(
    shape, threads, owners, fcc_lattice
):
    """A rank's list (NeighborList.keep_owned): of every pair within the list radius, those
    whose designated atom is owned (the smaller id if the ids' sum is even, else the
    larger), after the cell search (which searches the owned atoms' rows only) and the
    O(N^2) one alike (one or two chunks). Owned atoms as a rank holds them (a slab, as the
    lattice orders them) or scattered. With ids in the lattice's order (all the slab's ids
    below the others') the rank keeps about half of the pairs across its faces, not all
    of them."""
    from md.parallel import get_threads, set_threads

    state = fcc_lattice(cells=7, perturbation=0.1, pbc=shape != "open")
    n = state.n_atoms
    rng = np.random.default_rng(5)
    if owners == "scattered":
        state.positions[:] = state.positions[rng.permutation(n)]
    ids = rng.permutation(n).astype(np.int64)
    n_owned = n // 2
    before = get_threads()
    set_threads(threads)
    try:
        whole = NeighborList(cutoff=1.5, skin=0.3)
        whole.build(state)
        mine = NeighborList(cutoff=1.5, skin=0.3)
        mine.keep_owned(ids, n_owned)
        mine.build(state)
    finally:
        set_threads(before)
    assert whole.used_cells and mine.used_cells
    pairs = whole.pairs()
    first, second = pairs[:, 0], pairs[:, 1]
    keep = np.where(_designates(ids[first], ids[second]), first < n_owned, second < n_owned)
    np.testing.assert_array_equal(mine.pairs(), pairs[keep])
    assert 0 < keep.sum() < len(pairs)
    # in slot space, each kept pair's image code gives its minimum-image separation
    rows = np.repeat(np.arange(n), np.diff(mine.slot_starts))
    q = mine.slot_neighbors.astype(np.int64)
    frame = mine.frame_positions(state.positions)
    shifts = mine.shifts[mine.codes] if len(mine.codes) else 0.0
    separations = md.box.minimum_image(
        state.positions[mine.order[rows]] - state.positions[mine.order[q]], state.box, state.pbc
    )
    np.testing.assert_allclose(frame[rows] - frame[q] - shifts, separations, atol=1e-9)
    # the O(N^2) search keeps the same pairs
    few = md.State(positions=rng.uniform(0.0, 4.0, (60, 3)), box=[4.0, 4.0, 4.0])
    alone = NeighborList(cutoff=1.5, skin=0.3)
    alone.build(few)
    small = NeighborList(cutoff=1.5, skin=0.3)
    small.keep_owned(ids[:60], 20)
    small.build(few)
    assert not small.used_cells
    expected = alone.pairs()
    a, b = expected[:, 0], expected[:, 1]
    rule = np.where(_designates(ids[:60][a], ids[:60][b]), a < 20, b < 20)
    np.testing.assert_array_equal(small.pairs(), expected[rule])
    # ids in lattice order: the slab's are all below the others', yet the pairs across its
    # faces are shared about evenly (the smaller id alone would keep every one of them)
    if owners == "slab":
        ordered = NeighborList(cutoff=1.5, skin=0.3)
        ordered.keep_owned(np.arange(n, dtype=np.int64), n_owned)
        ordered.build(state)
        across = (first < n_owned) != (second < n_owned)
        kept = ordered.pairs()
        kept_across = np.count_nonzero((kept[:, 0] < n_owned) != (kept[:, 1] < n_owned))
        assert 0.4 < kept_across / np.count_nonzero(across) < 0.6
    # ids that are not one per atom are refused by either search
    for listed, atoms in ((mine, state), (small, few)):
        listed.keep_owned(ids[:10], 5)
        with pytest.raises(ValueError, match=f"10 ids for {atoms.n_atoms} atoms"):
            listed.build(atoms)


# ------------------------------------------------------------ boxes under five cells


def images_within(state, radius):
    """Every (i, j, separation) with i < j and an image of j within ``radius`` of i: all
    shifts of -2 .. 2 cell vectors from the minimum image, so none is missed."""
    h = md.box.cell_matrix(np.where(state.pbc, state.box, 0.0), state.tilt)
    inverse = np.linalg.inv(md.box.cell_matrix(np.where(state.pbc, state.box, 1.0), state.tilt))
    shifts = (
        np.array(list(itertools.product(*[range(-2, 3) if p else range(1) for p in state.pbc]))) @ h
    )
    found = set()
    for i in range(state.n_atoms):
        d = state.positions[i] - state.positions[i + 1 :]
        d -= np.where(state.pbc, np.rint(d @ inverse), 0.0) @ h
        for shift in shifts:
            e = d - shift
            for k in np.flatnonzero(np.einsum("ij,ij->i", e, e) < radius * radius):
                found.add((i, i + 1 + int(k), tuple(np.round(e[k], 8))))
    return found


def listed_images(nl, state):
    """The slot list's entries as (i, j, separation), i < j, from its frame."""
    frame, at = nl.frame, nl.frame_positions(state.positions)
    entries = []
    for p in range(state.n_atoms):
        for k in range(frame.starts[p], frame.starts[p + 1]):
            q = frame.neighbors[k]
            d = at[p] - at[q] - frame.shifts[frame.codes[k]]
            i, j = int(frame.order[p]), int(frame.order[q])
            if i > j:
                i, j, d = j, i, -d
            entries.append((i, j, tuple(np.round(d, 8))))
    return entries


# (fcc cells, cutoff, skin, tilt, pbc): boxes with room for fewer than five half-radius cells
SMALL_BOXES = {
    "108-atoms-under-2-radii": (3, 2.5, 0.3, None, None),
    "256-atoms-2.4-radii": (4, 2.5, 0.3, None, None),
    "skin-near-the-edge": (3, 2.5, 1.5, None, None),
    "narrow-mixed-pbc": (2, 1.6, 0.3, None, (True, False, True)),
    "one-narrow-axis": ((6, 6, 2), 1.6, 0.3, None, None),
    "triclinic": (4, 2.4, 0.3, (0.8, -0.5, 0.6), None),
    "triclinic-mixed-pbc": (4, 2.4, 0.3, (0.8, 0.0, 0.0), (True, True, False)),
}


@pytest.mark.parametrize("case", SMALL_BOXES.values(), ids=SMALL_BOXES.keys())
def test_small_box_slot_list_holds_every_image_within_reach(case, rng):
    """A box under five half-radius cells along an axis gets the slot frame by an O(N^2)
    search over images (``_small_box_list``): every image of every pair within the list
    radius once, wherever the atoms lie (unwrapped by up to two box lengths); a pair with
    two such images (a box under twice the list radius) twice in the frame, once in the
    list over atom indices."""
    cells, cutoff, skin, tilt, pbc = case
    state = md.lattice("fcc", cells, density=0.8442, pbc=True if pbc is None else list(pbc))
    if tilt is not None:
        state.tilt = np.array(tilt)
    state.positions += rng.normal(scale=0.2, size=state.positions.shape)
    state.positions += rng.integers(-2, 3, size=state.positions.shape) * state.box * state.pbc
    nl = NeighborList(cutoff, skin)
    nl.update(state)
    assert not nl.used_cells and nl.order is not None
    entries = listed_images(nl, state)
    assert len(set(entries)) == len(entries)
    assert set(entries) == images_within(state, nl.list_radius)
    pairs = {(i, j) for i, j, _ in entries}
    assert (len(pairs) < len(entries)) == (np.min(state.box[state.pbc]) < 2 * nl.list_radius)
    rows = np.repeat(np.arange(state.n_atoms), np.diff(nl.starts))
    low, high = np.minimum(rows, nl.neighbors), np.maximum(rows, nl.neighbors)
    atom_pairs = set(zip(low.tolist(), high.tolist(), strict=True))
    assert len(atom_pairs) == len(nl.neighbors) and atom_pairs == pairs
    if tilt is None:
        assert_list_is_exact(nl, state)


@pytest.mark.parametrize("cells", [3, 4])
def test_small_box_forces_equal_the_minimum_image_ones(cells, rng):
    """LJ over the small-box slot frame (no minimum image, an entry per image) gives the
    energy, forces and virial of the kernel over atom indices with the minimum image."""
    from potentials import LennardJones

    state = md.maxwell_boltzmann(md.lattice("fcc", cells, density=0.8442), 1.5, seed=3)
    state.positions += rng.normal(scale=0.1, size=state.positions.shape)
    lj = LennardJones(epsilon=1.0, sigma=1.0, cutoff=2.5, cutoff_mode="shift")
    nl = NeighborList(2.5, 0.3)
    nl.update(state)
    assert nl.frame is not None
    framed = lj.energy_forces(state, nl)
    by_atom = lj.energy_forces(state, nl, per_atom=True)  # the atom list, minimum image
    assert framed.energy == pytest.approx(by_atom.energy, rel=1e-12)
    np.testing.assert_allclose(framed.forces, by_atom.forces, rtol=0, atol=1e-11)
    np.testing.assert_allclose(framed.virial, by_atom.virial, rtol=1e-12, atol=1e-11)
    assert by_atom.energies.sum() == pytest.approx(by_atom.energy, rel=1e-12)
