"""A rank's owned-row search tests the designated-atom rule in its vector distance test
(issue 69).

``NeighborList.keep_owned``'s cell search (``md.neighbors._owned_kernels``) kept an owned
row's ghost partners by the rule (``_cell_kernels.designates``) in a scalar pass after the
distance test, one partner at a time; now the ghosts' global ids are copied beside their
coordinates and the rule is part of each 8-lane test (``_near_pack_designated``), so only
a row that meets the end of its chunk's buffer checks partners afterwards
(``NeighborList.ghost_rule_checks``). The list is the same: checked here against brute
force on a rank cut by hand, and the packer against numpy on every path.
"""

from __future__ import annotations

import numpy as np
import pytest

import md
from md.neighbors import NeighborList

CUTOFF, SKIN = 1.5, 0.3
RADIUS = CUTOFF + SKIN


def _slab_rank(cells=(8, 6, 6)):
    """Rank 0 of a perturbed fcc melt cut in two slabs along x: owned atoms (x in the lower
    half) first, then every image of another atom within a list radius of the slab along
    x (open), periodic along y and z; (State, global ids, owned count)."""
    state = md.lattice("fcc", cells, density=0.8442)
    rng = np.random.default_rng(11)
    box = state.box
    wrapped = (state.positions + rng.uniform(-0.1, 0.1, state.positions.shape)) % box
    high = box[0] / 2
    inside = wrapped[:, 0] < high
    positions, ids = [wrapped[inside]], [np.flatnonzero(inside)]
    for shift in (-1, 0, 1):
        moved = wrapped.copy()
        moved[:, 0] += shift * box[0]
        near = (moved[:, 0] >= -RADIUS) & (moved[:, 0] < high + RADIUS)
        if shift == 0:
            near &= ~inside
        positions.append(moved[near])
        ids.append(np.flatnonzero(near))
    local = md.State(
        positions=np.concatenate(positions), box=box.copy(), pbc=np.array([False, True, True])
    )
    return local, np.concatenate(ids).astype(np.int64), int(inside.sum())


def _designates(a, b):
    return (a < b) != ((a + b) % 2 == 1)


def test_a_slab_rank_lists_its_brute_force_pairs_with_no_rule_pass():
    """The rank's list is exactly brute force's pairs it owns (an owned atom with a later
    owned one, or with a ghost whose pair designates it), and no ghost partner went through
    the rule after the distance test (the scalar pass read every ghost partner within reach
    before: about 1100 on this rank)."""
    local, ids, n_owned = _slab_rank()
    nl = NeighborList(CUTOFF, SKIN)
    nl.keep_owned(ids, n_owned)
    nl.build(local)
    nl.build(local)  # the buffers sized by the first build: no row meets a region's end
    assert nl.used_cells
    d = local.positions[:, None] - local.positions[None]
    d = md.box.minimum_image(d, local.box, local.pbc, local.tilt)
    i, j = np.nonzero(np.triu((d**2).sum(axis=-1) < RADIUS**2, k=1))
    own = (i < n_owned) & ((j < n_owned) | _designates(ids[i], ids[j]))
    np.testing.assert_array_equal(nl.pairs(), np.stack([i, j], axis=1)[own])
    owned_ghost = int(np.sum((i < n_owned) & (j >= n_owned)))
    dropped = owned_ghost - int(np.sum(own & (j >= n_owned)))
    assert dropped > 0.3 * owned_ghost  # (the rule drops about half of them)
    assert owned_ghost <= nl.ghost_candidates
    assert nl.ghost_rule_checks == 0


def test_rows_at_a_buffer_end_check_the_rule_after_the_test(monkeypatch):
    """A buffer grown to just the list's length (no head room): the rows near its end take
    the counting path (``_keep``), which checks the rule after the test; the list is still
    the one a roomy buffer gives."""
    import md.neighbors.lists

    local, ids, n_owned = _slab_rank((6, 5, 5))
    sized = NeighborList(CUTOFF, SKIN)
    sized.keep_owned(ids, n_owned)
    sized.build(local)
    sized.build(local)
    assert sized.ghost_rule_checks == 0
    listed = len(sized.slot_neighbors)
    monkeypatch.setattr(md.neighbors.lists, "_grown", lambda count: listed + 8)
    tight = NeighborList(CUTOFF, SKIN)
    tight.keep_owned(ids, n_owned)
    tight.build(local)  # overruns the first buffer, then fills the grown one
    np.testing.assert_array_equal(tight.pairs(), sized.pairs())
    assert 0 < tight.ghost_rule_checks <= tight.ghost_candidates


@pytest.mark.parametrize("path", ["scan", "permute-whole", "permute-blocks", "twin"])
@pytest.mark.parametrize("valid", [0, 1, 7, 8, 9, 37, 63, 64])
def test_near_pack_designated_keeps_near_designated_candidates_in_order(path, valid):
    """On every path the designated packer writes exactly numpy's selection of the first
    ``valid`` candidates that are near and whose pair with the row's atom designates it, in
    order, and nothing before ``at`` or past the 8 entries after the end."""
    from numba import njit

    import md._simd
    from md._simd import PERMUTATIONS
    from md.neighbors._candidates import (
        _designated_packer,
        _near_pack_designated_blocks,
        _near_pack_designated_permute_whole,
        _near_pack_designated_scan,
    )

    if path.startswith("permute") and not md._simd.PERMUTE:
        pytest.skip("compiled for a CPU without AVX2: the permute path is not used")
    if path in ("permute-whole", "twin") and valid != 64:
        pytest.skip("the whole-word variant takes exactly 64 candidates")
    rng = np.random.default_rng(valid)
    first, own_id = 5, 1000
    n = first + 64 + 64
    x, y, z = (rng.uniform(-1.0, 1.0, n) for _ in range(3))
    packed = np.arange(n, dtype=np.uint32) + 100
    ids = rng.integers(0, 2000, n).astype(np.int64)
    lanes = slice(first, first + valid)
    near = x[lanes] ** 2 + y[lanes] ** 2 + z[lanes] ** 2 < 0.64
    wanted = packed[lanes][near & _designates(own_id, ids[lanes])]
    assert 0 < len(wanted) < valid or valid < 16  # (the larger words: both kinds)
    out = np.full(3 + 64 + 8, 7, dtype=np.uint32)
    args = (0.0, 0.0, 0.0, 0.64, x, y, z, packed, ids, own_id, first, valid, PERMUTATIONS, out, 3)
    if path == "twin":
        end = _designated_packer(8, whole=True).python_twin(*args)
    else:
        pack = {
            "scan": _near_pack_designated_scan,
            "permute-whole": _near_pack_designated_permute_whole,
            "permute-blocks": _near_pack_designated_blocks,
        }[path]

        @njit
        def call(x, y, z, packed, ids, own_id, start, valid, out, at):
            table = PERMUTATIONS
            return pack(
                0.0, 0.0, 0.0, 0.64, x, y, z, packed, ids, own_id, start, valid, table, out, at
            )

        end = call(x, y, z, packed, ids, own_id, first, valid, out, 3)
    assert end == 3 + len(wanted)
    assert np.array_equal(out[3:end], wanted)
    assert np.all(out[:3] == 7) and np.all(out[end + 8 :] == 7)
