"""The mixed-precision step on one and on two threads (issue 70: the cluster kernel's
chunks, the clusters only their own chunk writes, the pass that sums the shared ones)."""

from __future__ import annotations

import numpy as np
import pytest

import potentials._pair_frame
from integrators import VelocityVerlet
from md.forcefield import ForceField
from md.neighbors import ClusterFrame
from md.parallel import get_threads, max_threads, set_threads
from md.simulation import Simulation
from potentials import LennardJones

EPS32 = float(np.finfo(np.float32).eps)

needs_two = pytest.mark.skipif(max_threads() < 2, reason="numba offers one thread")


@pytest.fixture
def threads():
    """Set the thread count inside a test; the one before is restored after it."""
    before = get_threads()
    yield set_threads
    set_threads(before)


def _melt(fcc_lattice, cells=10):
    """The LJ melt's start (fcc at density 0.8442, T = 3; 4 cells^3 atoms), rattled."""
    return fcc_lattice(cells=cells, perturbation=0.05, temperature=3.0)


def _relative_error(a, b):
    return float(np.abs(a - b).max() / np.abs(b).max())


@needs_two
@pytest.mark.parametrize("n_threads", [1, 2])
def test_mixed_forces_on_one_and_two_threads_equal_double_and_sum_to_zero(
    n_threads, threads, fcc_lattice
):
    """On 1 and 2 threads (a chunk of the cluster list per thread) the mixed forces equal
    the double ones to float32 round-off, their sum vanishes (Newton's third law: each
    cluster pair's i and j forces cancel whichever chunk or pass writes them), the energy
    agrees, and a second call gives the same bits; also after MD steps, whose prunes
    make new lists and chunks."""
    state = _melt(fcc_lattice)
    threads(n_threads)
    for steps in (0, 30):
        if steps:
            sim = Simulation(
                state, [LennardJones(cutoff=2.5)], VelocityVerlet(0.005), precision="mixed"
            )
            sim.run(steps)
            state = sim.state
            assert sim.forcefield.neighbor_list.n_prunes > 0
        double = ForceField([LennardJones(cutoff=2.5)]).compute(state)
        field = ForceField([LennardJones(cutoff=2.5)], precision="mixed")
        mixed = field.compute(state)
        clusters = field.neighbor_list.clusters
        assert clusters is not None and len(clusters.bounds) - 1 == n_threads
        assert _relative_error(mixed.forces, double.forces) < 200 * EPS32
        assert abs(mixed.energy - double.energy) < 20 * EPS32 * abs(double.energy)
        scale = np.sqrt(state.n_atoms) * np.abs(double.forces).max()
        assert np.abs(mixed.forces.sum(axis=0)).max() < 10 * EPS32 * scale
        field.invalidate()
        assert np.array_equal(field.compute(state).forces, mixed.forces)


@needs_two
def test_the_two_threads_forces_differ_from_one_only_by_round_off(threads, fcc_lattice):
    """The two chunks' forces are the one chunk's to float32 round-off (only the order of
    the float32 and double sums differs), never a missed or doubled pair."""
    state = _melt(fcc_lattice)
    results = {}
    for n in (1, 2):
        threads(n)
        results[n] = ForceField([LennardJones(cutoff=2.5)], precision="mixed").compute(state)
    assert _relative_error(results[2].forces, results[1].forces) < 20 * EPS32
    assert results[2].forces is not results[1].forces


def _shared_by_numpy(clusters: ClusterFrame) -> np.ndarray:
    """The clusters some row of an earlier chunk than their own lists, from the pairs."""
    n = clusters.n_clusters
    rows = np.repeat(np.arange(n), np.diff(clusters.starts))
    first = np.full(n, n)
    np.minimum.at(first, clusters.partners, rows)
    own = np.searchsorted(clusters.bounds, np.arange(n), side="right") - 1
    return np.flatnonzero(first < clusters.bounds[own])


@needs_two
def test_the_shared_clusters_are_those_an_earlier_chunk_lists(threads, fcc_lattice):
    """``ClusterFrame.final`` / ``shared`` on 1, 2, 3 and 5 chunks: shared exactly where a
    row of an earlier chunk lists the cluster (the first chunk's clusters never), final
    everywhere else; on two chunks of the melt's list at most 0.6 of the clusters are
    shared (the layers each side of the chunks' boundary and across the periodic one)."""
    state = _melt(fcc_lattice)
    threads(2)
    field = ForceField([LennardJones(cutoff=2.5)], precision="mixed")
    field.neighbor_list.update(state)
    c = field.neighbor_list.clusters
    for chunks in (1, 2, 3, 5):
        frame = ClusterFrame(c.atom, c.origin, c.starts, c.partners, c.offsets, chunks)
        expected = _shared_by_numpy(frame)
        assert np.array_equal(frame.shared, expected)
        final = np.ones(frame.n_clusters, bool)
        final[expected] = False
        assert np.array_equal(frame.final.astype(bool), final)
        assert final[: frame.bounds[1]].all()
        if chunks == 2:
            assert 0 < len(expected) < 0.6 * frame.n_clusters


@needs_two
def test_on_two_threads_the_pass_after_the_kernel_sums_only_the_shared_atoms(
    threads, fcc_lattice, monkeypatch
):
    """On two chunks the kernel writes the forces of the clusters only its own chunk
    lists, and the pass that sums the chunks' buffers into atom order writes the rest
    alone: at most 0.6 of the atoms (every atom before: the pass summed every slot),
    and the forces are complete (checked against double above)."""
    written = []
    original = potentials._pair_frame.cluster_atom_forces

    def watched(*args):
        forces = args[-1]
        probe = np.full_like(forces, np.nan)
        original(*args[:-1], probe)
        written.append(int(np.isfinite(probe[:, 0]).sum()))
        original(*args)

    monkeypatch.setattr(potentials._pair_frame, "cluster_atom_forces", watched)
    state = _melt(fcc_lattice)
    threads(2)
    field = ForceField([LennardJones(cutoff=2.5)], precision="mixed")
    result = field.compute(state)
    assert len(field.neighbor_list.clusters.bounds) == 3 and written
    assert 0 < written[-1] <= 0.6 * state.n_atoms, written[-1] / state.n_atoms
    double = ForceField([LennardJones(cutoff=2.5)]).compute(state)
    assert _relative_error(result.forces, double.forces) < 200 * EPS32


def test_the_sum_passes_runs_hold_equal_work(fcc_lattice):
    """The threaded sum's runs (``cluster_sum_runs``) over the shared clusters of a
    two-chunk list: each run's slots read as many buffer values as the others' to one
    cluster (on two chunks every shared cluster reads both chunks' buffers), the runs
    cover the list once, in order. (Runs of equal slot counts over every slot, as the
    pass had, read 1.6 to 2 buffers a slot by where they fall: 0.53 of the work apart on
    the 32000-atom melt.)"""
    from potentials._kernels import cluster_sum_runs

    state = _melt(fcc_lattice)
    field = ForceField([LennardJones(cutoff=2.5)], precision="mixed")
    field.neighbor_list.update(state)
    c = field.neighbor_list.clusters
    frame = ClusterFrame(c.atom, c.origin, c.starts, c.partners, c.offsets, 2)
    shared, windows = frame.shared, frame.windows
    for runs in (2, 3, 4):
        offsets = cluster_sum_runs(len(shared), runs)
        assert offsets[0] == 0 and offsets[-1] == len(shared) and np.all(np.diff(offsets) >= 0)
        work = []
        for r in range(runs):
            run = shared[offsets[r] : offsets[r + 1]]
            chunk = np.searchsorted(windows[:, 0], run, side="right") - 1
            reads = sum(
                int((cl < windows[: k + 1, 1]).sum()) for cl, k in zip(run, chunk, strict=True)
            )
            work.append(reads)
        assert max(work) - min(work) <= 2 * 2, work  # one cluster, two buffers


@needs_two
def test_a_prune_in_two_chunks_moves_the_second_on_the_threads_to_the_same_list(
    threads, fcc_lattice
):
    """The prune of the melt's outer list in two chunks (the second chunk's kept pairs
    moved down to their place on the threads, where that place and theirs do not overlap:
    the prune keeps about half) gives the one-chunk prune's list bit for bit."""
    from md.neighbors._cluster_kernels import balanced_chunks, prune_pairs

    state = _melt(fcc_lattice)
    threads(2)
    field = ForceField([LennardJones(cutoff=2.5)], precision="mixed")
    neighbors = field.neighbor_list
    neighbors.update(state)
    outer = neighbors.outer_clusters
    assert outer is not None
    xi = np.empty(12 * outer.n_clusters, np.float32)
    xj = np.empty_like(xi)
    outer.relative_positions(state.positions + 0.05, xi, xj)
    reach2 = np.float32((neighbors.list_radius * (1.0 + 1e-5)) ** 2)
    found = {}
    for chunks in (1, 2):
        bounds = balanced_chunks(outer.starts, chunks)
        kept = (
            np.full(outer.n_clusters + 1, -1, np.int64),
            np.full(outer.n_pairs, -1, np.int32),
            np.full((outer.n_pairs, 3), np.nan, np.float32),
        )
        count = prune_pairs(
            outer.starts, outer.partners, outer.offsets, bounds, xi, xj, reach2, *kept
        )
        found[chunks] = (kept[0], kept[1][:count], kept[2][:count])
        if chunks == 2:  # the second chunk's pairs and their new place apart: the threaded move
            source, target = outer.starts[bounds[1]], kept[0][bounds[1]]
            assert target + (count - target) <= source
    assert 0.3 * outer.n_pairs < len(found[1][1]) < 0.7 * outer.n_pairs
    for a, b in zip(found[1], found[2], strict=True):
        assert np.array_equal(a, b)


@needs_two
@pytest.mark.parametrize("where", [0, -1])
def test_the_force_check_finds_a_non_finite_force_in_either_chunk(where, threads):
    """``md.parallel.all_finite`` (the force field's check of every force, in chunks on the
    threads from 96000 values): a NaN or an infinity at either end is found."""
    from md.parallel import all_finite

    threads(2)
    forces = np.ones((40000, 3))
    assert all_finite(forces)
    for bad in (np.nan, np.inf, -np.inf):
        forces[where, 1] = bad
        assert not all_finite(forces)
        forces[where, 1] = 1.0
