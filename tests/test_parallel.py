"""The fast paths against the simple ones: slot frame vs atom order, threads vs serial.

The cell-built neighbour list sorts atoms by cell and stores each pair's
periodic image as a code; the LJ force kernel then runs over that slot frame
in one chunk per thread. Each of these must agree with the plain serial
kernel over atom indices with a minimum image per pair: forces and energies
to round-off, trajectories over hundreds of steps, and the serial path bit
for bit from run to run.
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_neighbors import assert_list_is_exact, reference_pairs

import md
import md.neighbors.lists
from integrators import VelocityVerlet
from md.neighbors import NeighborList
from md.parallel import get_threads, max_threads, set_threads
from potentials import LennardJones


class AtomOrderLJ(LennardJones):
    """LJ that always takes the serial atom-order kernel with a minimum image per pair."""

    def energy_forces(self, state, neighbors, per_atom=False, virial=True):
        result = super().energy_forces(state, neighbors, per_atom=True)
        if not per_atom:
            result.energies = result.virials = None
        return result


@pytest.fixture
def chunks(monkeypatch):
    """Factory: make lists and kernels split small systems into ``n`` chunks.

    Chunks run on numba's threads when there are several cores and one
    after another otherwise, so the chunked code is tested on any machine.
    """

    def use(n: int) -> None:
        monkeypatch.setattr(md.neighbors.lists, "_MIN_CHUNK_ATOMS", 16)
        monkeypatch.setattr(md.parallel, "get_threads", lambda: n)

    return use


def _liquid(cells=6, seed=3, n_types=1):
    """A disordered LJ liquid with positions unwrapped over several box lengths."""
    rng = np.random.default_rng(seed)
    state = md.maxwell_boltzmann(md.lattice("fcc", cells, density=0.8442), 2.0, seed=seed)
    state.positions += rng.normal(scale=0.08, size=state.positions.shape)
    state.positions += rng.integers(-3, 4, size=state.positions.shape) * state.box
    if n_types > 1:
        state.types[:] = rng.integers(0, n_types, size=state.n_atoms)
        state.type_names = [f"T{t}" for t in range(n_types)]
    return state


POTENTIALS = {
    "truncated": dict(cutoff=2.5, cutoff_mode="none"),
    "shifted": dict(cutoff=2.5, cutoff_mode="shift"),
    "smooth-two-types": dict(
        epsilon=[1.0, 0.6], sigma=[1.0, 0.9], cutoff=2.5, cutoff_mode="smooth", r_on=2.0
    ),
}


@pytest.mark.parametrize(
    ("params", "n_chunks"),
    [
        # each chunked (threaded) variant compiles apart: the shifted one runs by default
        pytest.param(
            params,
            n_chunks,
            id=f"{name}-{n_chunks}",
            marks=pytest.mark.slow if n_chunks == 3 and name != "shifted" else (),
        )
        for name, params in POTENTIALS.items()
        for n_chunks in (1, 3)
    ],
)
def test_slot_frame_kernel_equals_atom_order_kernel(params, n_chunks, chunks):
    chunks(n_chunks)
    n_types = len(params["sigma"]) if "sigma" in params else 1
    state = _liquid(n_types=n_types)
    nl = NeighborList(2.5, skin=0.3)
    nl.build(state)
    assert nl.order is not None and len(nl.bounds) == n_chunks + 1
    lj = LennardJones(**params)
    fast = lj.energy_forces(state, nl)
    slow = lj.energy_forces(state, nl, per_atom=True)  # atom order, minimum image
    everything = lj.energy_forces(state, None)  # every pair, no list
    scale = np.abs(slow.forces).max()
    np.testing.assert_allclose(fast.forces, slow.forces, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(fast.forces, everything.forces, rtol=0, atol=1e-12 * scale)
    assert fast.energy == pytest.approx(slow.energy, rel=1e-12)
    np.testing.assert_allclose(fast.virial, slow.virial, rtol=1e-12, atol=1e-9)
    # Newton's third law survives the chunked force buffers.
    np.testing.assert_allclose(fast.forces.sum(axis=0), 0.0, atol=1e-10 * scale)


def test_virial_can_be_skipped_and_is_then_computed_on_demand():
    state = _liquid(cells=5)
    forcefield = md.ForceField([LennardJones(cutoff=2.5)], skin=0.3)
    lean = forcefield.compute(state, virial=False)
    assert lean.virial is None
    evaluations = forcefield.n_evaluations
    full = forcefield.compute(state)  # needs the virial: evaluates again
    assert forcefield.n_evaluations == evaluations + 1 and full.virial is not None
    np.testing.assert_array_equal(lean.forces, full.forces)
    assert forcefield.compute(state, virial=False) is full  # a virial does no harm


@pytest.mark.parametrize("reach", [1, 2])
def test_cells_one_or_half_a_radius_wide_give_the_exact_list(reach, monkeypatch):
    monkeypatch.setattr(md.neighbors.lists, "_REACH", reach)
    for pbc in (True, False, (True, False, True)):
        state = _liquid(cells=6)
        state.pbc[:] = pbc
        nl = NeighborList(2.5, skin=0.3)
        nl.build(state)
        assert nl.used_cells
        assert_list_is_exact(nl, state)


@pytest.mark.parametrize("n_chunks", [2, 3, 5])
def test_chunked_build_gives_the_same_list_as_one_chunk(n_chunks, chunks):
    state = _liquid(cells=5)
    chunks(1)
    serial = NeighborList(2.5, skin=0.3)
    serial.build(state)
    chunks(n_chunks)
    chunked = NeighborList(2.5, skin=0.3)
    chunked.build(state)  # starts with a small buffer: every chunk overflows once
    assert len(chunked.bounds) == n_chunks + 1
    np.testing.assert_array_equal(chunked.order, serial.order)
    np.testing.assert_array_equal(chunked.slot_starts, serial.slot_starts)
    np.testing.assert_array_equal(chunked.slot_neighbors, serial.slot_neighbors)
    np.testing.assert_array_equal(chunked.codes, serial.codes)
    assert_list_is_exact(chunked, state)
    # Chunks of the force kernels hold about equal numbers of pairs.
    per_chunk = np.diff(chunked.slot_starts[chunked.bounds])
    assert per_chunk.sum() == chunked.n_pairs
    assert per_chunk.max() - per_chunk.min() <= 2 * np.diff(chunked.slot_starts).max()


@settings(max_examples=40, deadline=None, database=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n_atoms=st.integers(30, 250),
    edges_over_radius=st.tuples(*[st.floats(3.01, 6.0)] * 3),
    pbc=st.tuples(*[st.booleans()] * 3),
    skin=st.sampled_from([0.05, 0.3, 0.6]),
    n_chunks=st.integers(1, 4),
)
def test_no_pair_is_missed_and_every_image_is_right_after_moves_up_to_half_the_skin(
    seed, n_atoms, edges_over_radius, pbc, skin, n_chunks
):
    """Property: after any moves of at most skin/2, the list still holds every pair
    within the cutoff, and the slot frame gives each listed pair its minimum-image
    displacement (so no kernel needs a minimum image)."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(md.neighbors.lists, "_MIN_CHUNK_ATOMS", 8)
        patch.setattr(md.parallel, "get_threads", lambda: n_chunks)
        _check_moves(seed, n_atoms, edges_over_radius, pbc, skin)


def _check_moves(seed, n_atoms, edges_over_radius, pbc, skin):
    rng = np.random.default_rng(seed)
    cutoff = 1.0
    box = np.array(edges_over_radius) * (cutoff + skin)
    positions = rng.uniform(0.0, 1.0, size=(n_atoms, 3)) * box
    positions += rng.integers(-3, 4, size=positions.shape) * box * np.array(pbc)
    state = md.State(positions=positions, box=box, pbc=list(pbc))
    nl = NeighborList(cutoff, skin)
    nl.build(state)
    assert nl.used_cells and nl.order is not None
    for _ in range(3):
        directions = rng.normal(size=positions.shape)
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        most = 0.5 * skin * (1.0 - 1e-9)  # half the skin, less the rounding of |d|^2
        lengths = rng.uniform(0.0, most, size=(n_atoms, 1))
        lengths[rng.integers(n_atoms)] = most  # at least one atom moves the whole way
        state.positions[:] = positions + lengths * directions
        assert not nl.update(state)
        within = set(map(tuple, reference_pairs(state.positions, box, state.pbc, cutoff)))
        assert within <= set(map(tuple, nl.pairs()))
        # Frame displacements equal minimum-image displacements for every listed pair.
        frame = nl.frame_positions(state.positions)
        rows = np.repeat(np.arange(n_atoms), np.diff(nl.slot_starts))
        d_frame = frame[rows] - frame[nl.slot_neighbors] - nl.shifts[nl.codes]
        d = state.positions[nl.order[rows]] - state.positions[nl.order[nl.slot_neighbors]]
        d -= np.where(state.pbc, box, 0.0) * np.round(d / box)
        np.testing.assert_allclose(d_frame, d, rtol=0, atol=1e-9 * box.max())


def _trajectory(state, potential, steps, n_chunks, chunks):
    chunks(n_chunks)
    state = state.copy()
    sim = md.Simulation(state, [potential], VelocityVerlet(dt=0.005), skin=0.3)
    sim.run(steps)
    return state, sim


def test_slot_frame_trajectory_follows_the_atom_order_one(chunks):
    start = _liquid(cells=5, seed=8)
    fast, sim = _trajectory(start, LennardJones(cutoff=2.5), 300, 1, chunks)
    slow, _ = _trajectory(start, AtomOrderLJ(cutoff=2.5), 300, 1, chunks)
    assert sim.forcefield.neighbor_list.n_builds > 3  # the list was rebuilt on the way
    np.testing.assert_allclose(fast.positions, slow.positions, rtol=0, atol=1e-8)
    np.testing.assert_allclose(fast.velocities, slow.velocities, rtol=0, atol=1e-7)


def test_chunked_trajectory_follows_the_serial_one(chunks):
    start = _liquid(cells=5, seed=9)
    serial, _ = _trajectory(start, LennardJones(cutoff=2.5), 300, 1, chunks)
    chunked, sim = _trajectory(start, LennardJones(cutoff=2.5), 300, 3, chunks)
    assert len(sim.forcefield.neighbor_list.bounds) == 4
    np.testing.assert_allclose(chunked.positions, serial.positions, rtol=0, atol=1e-8)
    np.testing.assert_allclose(chunked.velocities, serial.velocities, rtol=0, atol=1e-7)


@pytest.mark.parametrize("n_chunks", [1, 3])
def test_runs_are_bit_for_bit_repeatable(n_chunks, chunks):
    start = _liquid(cells=5, seed=10)
    first, _ = _trajectory(start, LennardJones(cutoff=2.5), 200, n_chunks, chunks)
    second, _ = _trajectory(start, LennardJones(cutoff=2.5), 200, n_chunks, chunks)
    np.testing.assert_array_equal(first.positions, second.positions)
    np.testing.assert_array_equal(first.velocities, second.velocities)


@pytest.mark.skipif(max_threads() < 2, reason="one core: no second thread to compare with")
def test_two_threads_agree_with_one_on_a_real_system():
    """Through the public setting: 4000 atoms, two chunks of 2000 on two threads."""
    before = get_threads()
    try:
        state = _liquid(cells=10, seed=11)
        results = []
        for threads in (1, 2):
            set_threads(threads)
            nl = NeighborList(2.5, skin=0.3)
            nl.build(state)
            assert len(nl.bounds) == threads + 1
            results.append(LennardJones(cutoff=2.5).energy_forces(state, nl))
        serial, threaded = results
        assert threaded.energy == pytest.approx(serial.energy, rel=1e-13)
        scale = np.abs(serial.forces).max()
        np.testing.assert_allclose(threaded.forces, serial.forces, rtol=0, atol=1e-13 * scale)
    finally:
        set_threads(before)


def test_thread_setting_is_checked():
    before = get_threads()
    try:
        for bad in (0, -1, 1.5, True, max_threads() + 1):
            with pytest.raises(ValueError, match="threads"):
                set_threads(bad)
        assert get_threads() == before
    finally:
        set_threads(before)


def test_threaded_per_atom_passes_change_no_bits(monkeypatch):
    """The passes over atoms that run in chunks on large systems (kick, drift, the
    displacement check, the force cache's copy and comparison) give the same trajectory,
    bit for bit, as their serial forms: run here on 2000 atoms with the chunk sizes
    lowered so that two threads take part."""
    import integrators._kernels
    import md.parallel

    if max_threads() < 2:
        pytest.skip("needs two threads")
    before = get_threads()
    try:
        set_threads(2)
        runs = []
        for threaded in (False, True):
            if threaded:
                monkeypatch.setattr(integrators._kernels, "_MIN_CHUNK_ATOMS", 100)
                monkeypatch.setattr(md.neighbors.lists, "_MIN_PASS_ATOMS", 100)
                monkeypatch.setattr(md.parallel, "_MIN_CHUNK_VALUES", 100)
            assert (integrators._kernels._chunks(2048) == 2) is threaded
            assert (md.parallel._chunks(3 * 2048) == 2) is threaded
            state = _liquid(cells=8, seed=5)
            sim = md.Simulation(state, [LennardJones(cutoff=2.5)], VelocityVerlet(0.005), skin=0.3)
            sim.run(40)
            assert sim.forcefield.neighbor_list.n_builds > 2  # the displacement check acted
            runs.append((state.positions.copy(), state.velocities.copy()))
        np.testing.assert_array_equal(runs[1][0], runs[0][0])
        np.testing.assert_array_equal(runs[1][1], runs[0][1])
    finally:
        set_threads(before)


@pytest.mark.parametrize("where", [0, 700, 1500, 2999])
def test_chunked_comparison_and_copy(monkeypatch, where):
    """same_values finds a difference (or a NaN) in any chunk; copy_into copies every one."""
    import md.parallel

    monkeypatch.setattr(md.parallel, "_MIN_CHUNK_VALUES", 100)
    before = get_threads()
    try:
        set_threads(min(2, max_threads()))
        a = np.random.default_rng(where).normal(size=(1000, 3))
        b = np.empty_like(a)
        md.parallel.copy_into(b, a)
        np.testing.assert_array_equal(b, a)
        assert md.parallel.same_values(a, b)
        b.reshape(-1)[where] += 1e-15 * max(1.0, abs(a.reshape(-1)[where]))
        assert not md.parallel.same_values(a, b)
        b.reshape(-1)[where] = np.nan
        a.reshape(-1)[where] = np.nan
        assert not md.parallel.same_values(a, b)  # NaN equals nothing, as in np.array_equal
    finally:
        set_threads(before)
