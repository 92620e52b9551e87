"""The mixed-precision step on one and on two threads (issue 70): the cluster kernel's
chunks against double, the sum of the chunks' buffers into atom order split by its work,
the prune's threaded move, the threaded check of the forces."""

from __future__ import annotations

import numpy as np
import pytest

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


def _work(windows, first, end):
    """The sum into atom order's work for clusters ``first`` to ``end``, counted cluster by
    cluster: one unit for its atoms' writes, one for each window holding it (read)."""
    clusters = np.arange(first, end)
    held = (windows[:, 0][None, :] <= clusters[:, None]) & (
        clusters[:, None] < windows[:, 1][None, :]
    )
    return int(held.sum()) + len(clusters)


@pytest.mark.parametrize("chunks", [2, 3])
def test_the_sum_into_atom_order_splits_its_work_evenly_between_its_runs(chunks, fcc_lattice):
    """The threaded sum of the chunks' buffers into atom order (``cluster_sum_runs``) on
    the melt's list in 2 and 3 chunks: its 2, 3 or 4 runs do the same work (a cluster's
    writes and a read of each window holding it) to within one cluster's each, whole
    clusters, in order, covering the list. A cluster is read from each chunk whose
    window holds it (in two chunks the second chunk's clusters from both buffers: the
    first chunk's window is the whole list), so runs of equal slot counts, as before,
    were apart by the reads (``even``: under 0.85 of the largest run's work in the
    smallest; on the 32000-atom melt 46 and 71 us)."""
    from potentials._kernels import cluster_sum_runs

    state = _melt(fcc_lattice)
    field = ForceField([LennardJones(cutoff=2.5)], precision="mixed")
    field.neighbor_list.update(state)
    c = field.neighbor_list.clusters
    frame = ClusterFrame(c.atom, c.origin, c.starts, c.partners, c.offsets, chunks)
    windows, n = frame.windows, frame.n_clusters
    assert windows[0, 1] == n  # the first chunk reaches across the periodic boundary
    for runs in (2, 3, 4):
        first = cluster_sum_runs(windows, n, runs)
        assert first[0] == 0 and first[-1] == n and np.all(np.diff(first) > 0)
        work = [_work(windows, first[r], first[r + 1]) for r in range(runs)]
        assert max(work) - min(work) <= 2 * (chunks + 1), work
        even = [_work(windows, r * n // runs, (r + 1) * n // runs) for r in range(runs)]
        assert min(even) < 0.85 * max(even), even


@needs_two
def test_a_prune_in_two_chunks_on_the_threads_gives_the_same_list(threads, fcc_lattice):
    """The prune of the melt's outer list in two chunks (each chunk's kept pairs copied
    straight to their place on the threads) gives the one-chunk prune's list bit for
    bit."""
    from md.neighbors._cluster_prune import prune_pairs
    from md.neighbors._cluster_search import balanced_chunks

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
        marks = np.empty(outer.n_pairs, np.uint8)
        count = prune_pairs(
            outer.starts, outer.partners, outer.offsets, bounds, xi, xj, reach2, *kept, marks
        )
        found[chunks] = (kept[0], kept[1][:count], kept[2][:count])
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


def test_a_mixed_call_over_the_same_list_runs_the_last_calls_kernel_again(fcc_lattice, monkeypatch):
    """The second mixed call over the same cluster list (the same State arrays, moved in
    place as an integrator moves them) runs the kernel prepared by the first, with no set-up
    (``_energy_forces`` not entered: about 25 us of Python a call), and gives what a fresh
    potential gives at the new positions, bit for bit; a new list (a prune) sets it up again;
    with and without the virial apart."""
    from potentials._pair_frame import PairPotential

    entered = []
    original = PairPotential._energy_forces

    def counted(self, *args, **kwargs):
        entered.append(1)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(PairPotential, "_energy_forces", counted)
    state = _melt(fcc_lattice, cells=6)
    field = ForceField([LennardJones(cutoff=2.5)], precision="mixed")
    neighbors = field.neighbor_list
    neighbors.update(state)
    lj = LennardJones(cutoff=2.5)
    for virial in (False, True):
        lj.energy_forces(state, neighbors, virial=virial, precision="mixed")
    before = len(entered)
    state.positions += 0.01  # in place, within the list's skin: the same list
    assert not neighbors.update(state) and neighbors.n_prunes == 0
    for virial in (False, True):
        again = lj.energy_forces(state, neighbors, virial=virial, precision="mixed")
        fresh = LennardJones(cutoff=2.5).energy_forces(
            state, neighbors, virial=virial, precision="mixed"
        )
        assert np.array_equal(again.forces, fresh.forces) and again.energy == fresh.energy
        assert (again.virial is None) == (not virial)
        if virial:
            assert np.array_equal(again.virial, fresh.virial)
    assert len(entered) == before + 2  # the two fresh potentials' calls only
    state.positions[0] += 0.2  # past half the skin: a prune, a new list
    neighbors.update(state)
    assert neighbors.n_prunes == 1
    pruned = lj.energy_forces(state, neighbors, virial=False, precision="mixed")
    assert len(entered) == before + 3
    double = ForceField([LennardJones(cutoff=2.5)]).compute(state)
    assert _relative_error(pruned.forces, double.forces) < 200 * EPS32
