"""A pair call over a list of atom indices takes the short path between builds (issue 69).

A decomposed rank's local system is often too thin along a periodic axis for cells (the
576-atom melt's 6.7-sigma z edge holds four half-radius cells, five are needed), so its
list (``NeighborList.keep_owned``) is the O(N^2) one over atom indices and has no slot
frame (a serial list always has one: cells, or the small box's search). The pair frame
keeps the last such call (kernel, geometry, tables) as it keeps a slot-frame call, and
runs it again while the State's arrays, the list's arrays and the cell's values are the
same: no variant lookup, geometry or tables a step. Here with no MPI (the local system cut
by hand as the halo cuts it): the slow path is entered once per build, a call makes few
Python calls, and every result is bit for bit a fresh potential's (the slow path), after
moves, a changed cell and a rebuild; then on real ranks (slow-marked): a step between
builds enters no slow path and the trajectory is the one with the short path turned off.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest
from _mpi_support import needs_mpi, rank_zero_json

import md
from md.forcefield import ForceField
from potentials import LennardJones, PairPotential

CUTOFF, SKIN = 2.5, 0.3


def _rank_system(cells=(6, 6, 4), seed=0):
    """Rank 0's local system of the LJ melt on ``cells`` cut into two bricks along x: its
    owned atoms first, then every image within the list radius of the brick along x;
    open along x, periodic along y and z (as the halo lays it out). (State, ids, owned)."""
    state = md.lattice("fcc", cells, density=0.8442)
    rng = np.random.default_rng(seed)
    box = state.box
    wrapped = (state.positions + rng.uniform(-0.1, 0.1, state.positions.shape)) % box
    half, shell = box[0] / 2, CUTOFF + SKIN
    owned = np.flatnonzero(wrapped[:, 0] < half)
    positions, ids = [wrapped[owned]], [owned]
    for shift in (-1, 0, 1):
        moved = wrapped.copy()
        moved[:, 0] += shift * box[0]
        near = (moved[:, 0] >= -shell) & (moved[:, 0] < half + shell)
        if shift == 0:
            near &= wrapped[:, 0] >= half
        positions.append(moved[near])
        ids.append(np.flatnonzero(near))
    local = md.State(positions=np.concatenate(positions), box=box.copy(), pbc=[False, True, True])
    return local, np.concatenate(ids).astype(np.int64), len(owned)


@pytest.fixture
def slow_path_entries(monkeypatch):
    """Counts of the pair frame's slow path (``PairPotential._energy_forces``) by potential."""
    counts: dict[int, int] = {}
    slow = PairPotential._energy_forces

    def counted(self, *args, **kwargs):
        counts[id(self)] = counts.get(id(self), 0) + 1
        return slow(self, *args, **kwargs)

    monkeypatch.setattr(PairPotential, "_energy_forces", counted)
    return counts


def _fresh(state, neighbor_list, virial):
    """The slow path's result: a new potential's first call over the same list."""
    return LennardJones(cutoff=CUTOFF).energy_forces(state, neighbor_list, virial=virial)


def _assert_same_bits(result, expected):
    assert result.energy == expected.energy
    assert np.array_equal(result.forces, expected.forces)
    if expected.virial is None:
        assert result.virial is None
    else:
        assert np.array_equal(result.virial, expected.virial)


def test_a_rank_list_over_atom_indices_enters_the_slow_path_once_a_build(slow_path_entries):
    local, ids, n_owned = _rank_system()
    forcefield = ForceField([LennardJones(cutoff=CUTOFF)], SKIN, cache=False)
    neighbor_list = forcefield.neighbor_list
    neighbor_list.keep_owned(ids, n_owned)
    potential = forcefield.potentials[0]
    forcefield.compute(local, False, False)
    assert neighbor_list.frame is None  # (the case at hand: a list over atom indices)
    builds, entries = neighbor_list.n_builds, slow_path_entries[id(potential)]
    rng = np.random.default_rng(1)
    for step in range(12):
        local.positions += rng.uniform(-0.004, 0.004, local.positions.shape)  # (in place)
        virial = step % 3 == 0
        result = forcefield.compute(local, False, virial)
        _assert_same_bits(result, _fresh(local, neighbor_list, virial))
    assert neighbor_list.n_builds == builds  # no build among these calls
    # (before: every call took the slow path, 12 entries)
    assert slow_path_entries[id(potential)] == entries, slow_path_entries


def test_a_rank_pair_call_between_builds_makes_few_python_calls():
    local, ids, n_owned = _rank_system()
    forcefield = ForceField([LennardJones(cutoff=CUTOFF)], SKIN, cache=False)
    forcefield.neighbor_list.keep_owned(ids, n_owned)
    forcefield.compute(local, False, False)
    calls = [0]

    def profile(frame, event, arg):
        if event == "call":
            calls[0] += 1

    sys.setprofile(profile)
    try:
        for _ in range(10):
            local.positions[0, 1] += 1e-4
            forcefield.compute(local, False, False)
    finally:
        sys.setprofile(None)
    # the force field's call, its list check, the pair call (the list's arrays asked
    # for), the kernel, the result and its finite check: 15; before, 33 (the variant
    # lookup, the geometry, the tables, the slow path's wrappers at every call)
    assert calls[0] / 10 <= 22, calls


def test_the_kept_call_follows_the_cell_and_a_rebuild_to_the_bit(slow_path_entries):
    local, ids, n_owned = _rank_system()
    neighbor_list = md.neighbors.NeighborList(CUTOFF, SKIN)
    neighbor_list.keep_owned(ids, n_owned)
    neighbor_list.update(local)
    potential = LennardJones(cutoff=CUTOFF)
    potential.energy_forces(local, neighbor_list, virial=False)
    # the same list, the cell changed in place along a periodic axis: the kept geometry's
    # lengths are stale and must not serve
    local.box[1] *= 1.01
    _assert_same_bits(
        potential.energy_forces(local, neighbor_list), _fresh(local, neighbor_list, True)
    )
    # a rebuild (new arrays of the list): the new list's pairs, not the kept call's
    local.positions[: n_owned // 2] += 0.4
    neighbor_list.update(local)
    _assert_same_bits(
        potential.energy_forces(local, neighbor_list, virial=False),
        _fresh(local, neighbor_list, False),
    )
    # a new positions array (a rank's local arrays alternate between builds) is a new call
    moved = local.copy()
    _assert_same_bits(
        potential.energy_forces(moved, neighbor_list, virial=False),
        _fresh(moved, neighbor_list, False),
    )
    assert slow_path_entries[id(potential)] == 4, slow_path_entries


#: The 576-atom melt on 2 ranks (its local list over atom indices), rank 0 printing: the
#: slow path's entries and the Python calls from one step start to the next (spans without
#: a build), then the trajectory with the kept call against every call by the slow path.
RANKS = """\
import json, sys
import numpy as np
from mpi4py import MPI
import md
from integrators import VelocityVerlet
from potentials import LennardJones, PairPotential
from md.distributed import DistributedSimulation


def simulation():
    lattice = md.lattice("fcc", (6, 6, 4), density=0.8442)
    n = len(lattice.positions)
    velocities = np.random.default_rng(3).normal(0.0, 1.7, lattice.positions.shape)
    state = md.State(positions=lattice.positions, velocities=velocities,
                     masses=1.0 + 0.5 * (np.arange(n) % 3), box=lattice.box)
    return DistributedSimulation(state, [LennardJones(cutoff=2.5)], VelocityVerlet(dt=0.005),
                                 skin=0.3)


slow_path = PairPotential._energy_forces
entries = [0]


def counted(self, *args):
    entries[0] += 1
    return slow_path(self, *args)


PairPotential._energy_forces = counted
sim = simulation()
sim.run(30)
forcefield = sim.forcefield
calls, marks = [0], []
starts = forcefield.start_step


def start_step(*args):
    marks.append((calls[0], forcefield.n_builds, entries[0]))
    starts(*args)


def profile(frame, event, arg):
    if event == "call":
        calls[0] += 1


forcefield.start_step = start_step
sys.setprofile(profile)
sim.run(60)
sys.setprofile(None)
spans = [(b[0] - a[0] - 1, b[2] - a[2]) for a, b in zip(marks, marks[1:]) if a[1] == b[1]]
listed = forcefield.neighbor_list.frame is None


def trajectory(kept):
    if not kept:  # every pair call by the slow path (the code before the kept call)
        def direct(self, state, neighbors, per_atom=False, virial=True, precision="double"):
            return slow_path(self, state, neighbors, per_atom, virial, precision)
        PairPotential.energy_forces = direct
    sim = simulation()
    energies = []
    sim.attach(lambda s: energies.append(s.thermo()["total_energy"]), 20)
    sim.run(150)
    view = sim.global_view()  # (rank 0's; None on the others)
    if view is None:
        return None
    return view.state.positions, view.state.velocities, energies, sim.forcefield.n_builds


PairPotential._energy_forces = slow_path
kept, direct = trajectory(True), trajectory(False)
if MPI.COMM_WORLD.Get_rank() == 0:
    print(json.dumps({
        "calls": [s[0] for s in spans], "entries": [s[1] for s in spans], "atoms": listed,
        "positions": bool(np.array_equal(kept[0], direct[0])),
        "velocities": bool(np.array_equal(kept[1], direct[1])),
        "energies": kept[2] == direct[2], "builds": [kept[3], direct[3]],
    }))
"""


@needs_mpi
@pytest.mark.slow  # three 2-rank runs of the melt, ~20 s on 2 cores
def test_a_decomposed_step_between_builds_takes_the_short_pair_call(tmp_path):
    found = rank_zero_json(tmp_path, RANKS)
    assert found["atoms"], found  # (the rank's list is over atom indices: the case at hand)
    assert len(found["calls"]) >= 20, found
    # a slow-path entry only at the first call on a build's new local arrays, the span
    # after the build's (about every fifth here); before: one in every span
    entries = found["entries"]
    assert max(entries) <= 1 and sum(entries) <= 0.4 * len(entries), found
    # 41-46 a step between builds, 64-69 after one; before: 60-65 (the slow path each step)
    assert sorted(found["calls"])[len(found["calls"]) // 2] <= 60, found
    assert found["positions"] and found["velocities"] and found["energies"], found
    assert found["builds"][0] == found["builds"][1] > 3, found
