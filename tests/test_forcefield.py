"""ForceField: its result cache (positions, box, types and periodicity; an integrator
stepping without a Simulation uses it too) and the sum of several potentials over one
neighbour list."""

from __future__ import annotations

import numpy as np
import pytest

import md
from integrators import VelocityVerlet
from potentials import LennardJones


def test_integrator_alone_uses_the_cache(fcc_lattice):
    state = fcc_lattice(cells=3, temperature=1.0)
    forcefield = md.ForceField([LennardJones(cutoff=2.5)])
    integrator = VelocityVerlet(dt=0.005)
    integrator.step(state, forcefield)
    assert forcefield.n_evaluations == 2
    for _ in range(9):
        integrator.step(state, forcefield)
    assert forcefield.n_evaluations == 11
    assert state.step == 10 and state.time == pytest.approx(0.05, rel=1e-14)


def test_force_cache_follows_positions_box_and_types(random_gas):
    state = random_gas(30, 6.0, n_types=2)
    lj = LennardJones(epsilon=[1.0, 0.5], sigma=[1.0, 1.2], cutoff=2.5)
    forcefield = md.ForceField([lj])
    first = forcefield.compute(state)
    assert forcefield.compute(state) is first
    state.positions[0, 0] += 1e-3
    # (the list's slot frame and the all-pairs loop sum in different orders)
    assert forcefield.compute(state).energy == pytest.approx(
        lj.energy_forces(state, None).energy, rel=1e-13
    )
    state.box[:] = 6.5
    assert forcefield.compute(state).energy == pytest.approx(lj.energy_forces(state, None).energy)
    state.types[:] = 1 - state.types
    assert forcefield.compute(state).energy == pytest.approx(lj.energy_forces(state, None).energy)
    assert forcefield.n_evaluations == 4


def test_a_force_field_without_cache_evaluates_every_call_and_copies_nothing(random_gas):
    """cache=False (a decomposed run's local force field, whose caller keeps the results):
    each call evaluates, subsets too, the results equal the cached field's, and no call
    allocates a copy of the positions (tracemalloc: the cached field's first call does)."""
    import tracemalloc

    state = random_gas(3000, 30.0, n_types=2)
    lj = LennardJones(epsilon=[1.0, 0.5], sigma=[1.0, 1.2], cutoff=2.5)
    cached, plain = md.ForceField([lj]), md.ForceField([lj], cache=False)
    expected = cached.compute(state)
    first, second = plain.compute(state), plain.compute(state)
    assert first is not second and plain.n_evaluations == 2
    np.testing.assert_array_equal(first.forces, expected.forces)
    assert first.energy == expected.energy
    plain.compute_subset(state, [0])
    plain.compute_subset(state, [0])
    assert plain.n_subset_evaluations == 2
    assert cached.compute(state) is expected  # (the default keeps it)

    def largest_allocation(forcefield):
        tracemalloc.start()
        try:
            forcefield.compute(state)
            snapshot = tracemalloc.take_snapshot()
        finally:
            tracemalloc.stop()
        return max(
            (
                stat.size
                for stat in snapshot.statistics("lineno")
                if "forcefield.py" in stat.traceback[0].filename
            ),
            default=0,
        )

    state.positions[0, 0] += 1e-3
    fresh = md.ForceField([lj])
    assert largest_allocation(fresh) >= state.positions.nbytes  # its key: a copy
    assert largest_allocation(plain) < state.positions.nbytes / 8


def test_force_field_sums_its_potentials(random_gas):
    state = random_gas(60, 7.0, n_types=2)
    short = LennardJones(epsilon=[1.0, 0.5], sigma=[1.0, 1.2], cutoff=2.0)
    long = LennardJones(epsilon=0.3, sigma=0.9, cutoff=3.2, cutoff_mode="smooth")
    forcefield = md.ForceField([short, long], skin=0.2)
    assert forcefield.cutoff == 3.2  # one list, at the longest cutoff
    total = forcefield.compute(state)
    assert total.energies is None
    with_energies = forcefield.compute(state, per_atom=True)  # recomputed for energies
    assert forcefield.n_evaluations == 2
    parts = [p.energy_forces(state, None, per_atom=True) for p in (short, long)]
    assert with_energies.energy == pytest.approx(sum(r.energy for r in parts), rel=1e-12)
    np.testing.assert_allclose(with_energies.forces, parts[0].forces + parts[1].forces, atol=1e-11)
    np.testing.assert_allclose(with_energies.virial, parts[0].virial + parts[1].virial, atol=1e-11)
    np.testing.assert_allclose(
        with_energies.energies, parts[0].energies + parts[1].energies, atol=1e-12
    )


def test_force_cache_follows_periodicity():
    state = md.State(positions=[[0.2, 0.0, 0.0], [5.6, 0.0, 0.0]], box=6.0, pbc=True)
    forcefield = md.ForceField([LennardJones(cutoff=2.5)])
    assert forcefield.compute(state).energy > 1.0  # 0.6 apart through the x face
    state.pbc[:] = False  # now 5.4 apart: beyond the cutoff
    assert forcefield.compute(state).energy == 0.0
