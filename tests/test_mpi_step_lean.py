"""A decomposed step between list builds with the local pair kernel called directly
(issue 69): ``DistributedForceField.verlet_step`` makes the local force field's one
compiled call itself (``ForceField.pair_call``: no ``compute``, list update, potential
or finite checks in Python between its two compiled calls), checks the local list in its
first compiled call and the forces' finiteness in its second.

The ranks are real (``mpiexec``, skipped without the ``[mpi]`` extra). The melt has 864
atoms, so that a rank's local system is wide enough for cells (a slot-frame list, whose
kept call is the one handed out; the smaller melts of the other MPI tests have lists over
atom indices). One launch runs it three ways: as it is (counted on rank 0 under a
profiler), with ``pair_call`` answering None (the path it replaced: the local
``compute`` every step), and with the direct call's forces made NaN at some steps (its
non-finite path: the local compute then says what, here nothing, and the step goes on).
The melt is also run with an atom's velocity made 20 times larger for a step (a list
outrun inside the step after direct calls), both ways. The last test checks
``ForceField.pair_call`` in one process.
"""

from __future__ import annotations

import numpy as np
import pytest
from _mpi_support import needs_mpi, rank_zero_json

import md
from md.forcefield import ForceField
from potentials import LennardJones, Morse

SCRIPT = """\
import json, sys
import numpy as np
import md
from integrators import VelocityVerlet
from potentials import LennardJones
from md.distributed import DistributedSimulation
from md.forcefield import ForceField

STEPS, KICK = 160, 90


def system():
    lattice = md.lattice("fcc", (6, 6, 6), density=0.8442)
    n = len(lattice.positions)
    velocities = np.random.default_rng(5).normal(0.0, 1.7, lattice.positions.shape)
    masses = 1.0 + 0.5 * (np.arange(n) % 3)
    return md.State(positions=lattice.positions, velocities=velocities, masses=masses,
                    box=lattice.box)


def simulation(state, kind):
    return kind(state, [LennardJones(cutoff=2.5)], VelocityVerlet(dt=0.005), skin=0.3)


def run(kick=False):
    sim = simulation(system(), DistributedSimulation)
    sim.run(20)
    forcefield = sim.forcefield
    calls, computes, marks, inside = [0], [0], [], [0]
    starts, rebuild = forcefield.start_step, forcefield.rebuild

    def counted_rebuild(state, migrate, *args, **kwargs):
        inside[0] += not migrate  # (a rebuild inside a step keeps the owners)
        return rebuild(state, migrate, *args, **kwargs)

    def start_step(*args):
        marks.append((calls[0], computes[0], forcefield.n_builds))
        if kick and sim.state.step in (KICK, KICK + 1):  # (one step 20 times as fast: a
            # move the look-ahead did not see, the list outrun inside it)
            sim.state.velocities[sim.state.ids == 7] *= 20.0 if sim.state.step == KICK else 0.05
        starts(*args)

    def profile(frame, event, arg):
        if event == "call":
            calls[0] += 1
            code = frame.f_code
            computes[0] += code.co_name == "compute" and code.co_filename.endswith(
                "md/forcefield.py")

    forcefield.start_step, forcefield.rebuild = start_step, counted_rebuild
    sys.setprofile(profile)
    sim.run(STEPS - 20)
    sys.setprofile(None)
    spans = [(a, b) for a, b in zip(marks, marks[1:]) if a[2] == b[2]]  # (no build)
    return sim, {
        "calls": [b[0] - a[0] - 1 for a, b in spans],
        "computes": sum(b[1] - a[1] for a, b in spans),
        "builds": forcefield.n_builds,
        "energy": sim.thermo()["total_energy"],
        "inside": inside[0],
    }


found, views = {}, {}
for name, kick in (("direct", False), ("direct kicked", True)):
    sim, found[name] = run(kick)
    views[name] = sim.global_view()
handed = getattr(ForceField, "pair_call", lambda self, state: None)  # (none before)
ForceField.pair_call = lambda self, state: None  # the local compute every step, as before
for name, kick in (("replaced", False), ("replaced kicked", True)):
    sim, found[name] = run(kick)
    views[name] = sim.global_view()
made = [0]


def poisoned(self, state):
    call = handed(self, state)
    if call is None:
        return None
    kernel = call[0]

    def kernel_with_nan(*arguments):
        kernel(*arguments)
        made[0] += 1
        if made[0] % 7 == 3:
            arguments[-1][5, 1] = np.nan

    return (kernel_with_nan, *call[1:])


ForceField.pair_call = poisoned
sim, found["poisoned"] = run()
views["poisoned"] = sim.global_view()
found["poisoned"]["made"] = made[0]
if sim.rank == 0:
    for name, like in (("replaced", "direct"), ("poisoned", "direct"),
                       ("replaced kicked", "direct kicked")):
        a, b = views[like].state, views[name].state
        found[name]["same"] = bool(
            np.array_equal(a.positions, b.positions)
            and np.array_equal(a.velocities, b.velocities)
            and found[like]["energy"] == found[name]["energy"]
        )
    found["serial"] = []
    for name, kick in (("direct", False), ("direct kicked", True)):
        serial = simulation(system(), md.Simulation)
        if kick:
            serial.run(KICK)
            serial.state.velocities[7] *= 20.0
            serial.run(1)
            serial.state.velocities[7] *= 0.05
        serial.run(STEPS - serial.state.step)
        a = views[name].state
        found["serial"].append(float(max(np.abs(a.positions - serial.state.positions).max(),
                                         np.abs(a.velocities - serial.state.velocities).max())))
    print(json.dumps(found))
"""


@pytest.fixture(scope="module")
def launched(tmp_path_factory) -> dict:
    """The one launch's findings (:data:`SCRIPT`, rank 0)."""
    return rank_zero_json(tmp_path_factory.mktemp("step_lean"), SCRIPT)


@needs_mpi
def test_a_step_between_builds_calls_the_local_pair_kernel_itself(launched):
    """Rank 0, from one step start to the next without a build: at most 18 Python calls
    (median: 17; 25 before, with the local ``compute`` between the two compiled calls); in
    the first step after a build, where the pair call is laid out again (the 90th
    percentile: a fifth of the steps), at most 45 (42; 53 with the local ``compute``
    there); the local ``compute`` made in hardly any step (every step before)."""
    found = launched["direct"]
    calls = sorted(found["calls"])
    assert len(calls) >= 60 and found["builds"] > 5, found
    assert calls[len(calls) // 2] <= 18, found
    assert calls[int(0.9 * len(calls))] <= 45, found
    assert found["computes"] <= 0.05 * len(calls), found


@needs_mpi
def test_the_direct_call_gives_the_bits_of_the_local_compute(launched):
    """The trajectory (positions, velocities, the final total energy, builds) is the same
    bits as with the local ``compute`` every step, and as with the direct call's forces made
    NaN now and then (the local compute then evaluates the step again: no message was sent
    for the poisoned one); within 1e-10 of the serial run."""
    direct, replaced, poisoned = launched["direct"], launched["replaced"], launched["poisoned"]
    assert replaced["same"] and poisoned["same"], launched
    assert direct["builds"] == replaced["builds"] == poisoned["builds"], launched
    assert replaced["computes"] >= len(replaced["calls"]), launched  # (no direct call there)
    assert poisoned["made"] >= 30, launched  # (the poisoned kernel ran: NaN 1 in 7)
    assert max(launched["serial"]) < 1e-10, launched


@needs_mpi
def test_a_list_outrun_after_direct_calls_rebuilds_as_the_local_compute(launched):
    """An atom's velocity made 20 times larger for a step (a move the look-ahead did not
    see): the step's reduction finds the list outrun and every rank rebuilds inside the
    step; the same bits as with the local ``compute`` every step, within 1e-10 of the
    serial run."""
    kicked, replaced = launched["direct kicked"], launched["replaced kicked"]
    assert replaced["same"] and kicked["builds"] == replaced["builds"], launched
    assert kicked["inside"] >= 1 and kicked["inside"] == replaced["inside"], launched
    assert kicked["computes"] <= 0.05 * len(kicked["calls"]), launched  # (direct calls)


def test_the_force_field_hands_out_the_call_compute_makes():
    """``ForceField.pair_call``: the kernel, its arguments and energies compute's kept call
    uses, with the list's reference and allowance: the same bits as ``compute`` at the
    first positions, after a move within the skin (the arrays changed in place) and for a
    state of new arrays (laid out again, not run); None before a call was kept, in mixed
    precision and for two potentials."""
    lattice = md.lattice("fcc", (4, 4, 4), density=0.8442)
    rng = np.random.default_rng(2)
    positions = lattice.positions + rng.normal(0.0, 0.02, lattice.positions.shape)
    state = md.State(positions=positions, masses=1.0, box=lattice.box)
    forcefield = ForceField([LennardJones(cutoff=2.5)], 0.3)
    assert forcefield.pair_call(state) is None  # (no call kept yet)
    for move in (0.0, 0.05):
        state.positions += rng.uniform(-move, move, state.positions.shape)
        result = forcefield.compute(state, virial=False)
        kernel, arguments, energies, reference, allowed2 = forcefield.pair_call(state)
        forces = np.full_like(state.positions, np.nan)
        kernel(*arguments, forces)
        assert np.array_equal(forces, result.forces) and float(energies[0]) == result.energy
        assert allowed2 == (0.5 * 0.3) ** 2
        assert np.abs(state.positions - reference).max() <= 0.05
    # a state of new arrays (the same values, as a decomposed rank's next build): laid out
    # afresh for them, without a force call, the same bits
    fresh = md.State(positions=state.positions.copy(), masses=1.0, box=lattice.box)
    kernel, arguments, energies, _, _ = forcefield.pair_call(fresh)
    assert arguments[0] is fresh.positions
    forces = np.full_like(state.positions, np.nan)
    kernel(*arguments, forces)
    assert np.array_equal(forces, result.forces) and float(energies[0]) == result.energy
    mixed = ForceField([LennardJones(cutoff=2.5)], 0.3, precision="mixed")
    mixed.compute(state, virial=False)
    two = ForceField([LennardJones(cutoff=2.5), Morse(cutoff=2.5)], 0.3)
    two.compute(state, virial=False)
    assert mixed.pair_call(state) is None and two.pair_call(state) is None
