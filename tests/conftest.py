"""Shared fixtures: a seeded random generator and small system factories.

The factories are fixtures returning functions, so a test builds as many
systems as it needs, all drawn from the test's own seeded ``rng``::

    def test_something(fcc_lattice, random_gas):
        crystal = fcc_lattice(cells=3, perturbation=0.05, temperature=1.0)
        gas = random_gas(64, box=6.0, pbc=[True, True, False])
"""

from __future__ import annotations

import numpy as np
import pytest

import md

SEED = 20240607
R_MIN_LJ = 2.0 ** (1.0 / 6.0)


@pytest.fixture
def rng() -> np.random.Generator:
    """A numpy Generator with a fixed seed (fresh for every test)."""
    return np.random.default_rng(SEED)


@pytest.fixture
def dimer():
    """Factory: two atoms ``r`` apart along x, centred in a cubic box.

    ``dimer(r=2**(1/6), box=10.0, pbc=False, masses=1.0, types=(0, 0))``
    """

    def make(r=R_MIN_LJ, box=10.0, pbc=False, masses=1.0, types=(0, 0)) -> md.State:
        box = np.broadcast_to(np.asarray(box, dtype=float), (3,)).copy()
        centre = 0.5 * box
        positions = np.array([centre - [0.5 * r, 0, 0], centre + [0.5 * r, 0, 0]])
        return md.State(positions=positions, masses=masses, box=box, pbc=pbc, types=list(types))

    return make


@pytest.fixture
def fcc_lattice(rng):
    """Factory: an fcc crystal, optionally perturbed and thermalised.

    ``fcc_lattice(cells=3, density=0.8442, perturbation=0.0, temperature=None,
    pbc=True, n_types=1)``: ``perturbation`` is the standard deviation of a
    Gaussian displacement of every coordinate [length]; ``temperature`` draws
    Maxwell-Boltzmann velocities (kB = 1); ``n_types`` > 1 assigns random types.
    """

    def make(
        cells=3, density=0.8442, perturbation=0.0, temperature=None, pbc=True, n_types=1
    ) -> md.State:
        state = md.lattice("fcc", cells, density=density, pbc=pbc)
        if perturbation:
            state.positions += rng.normal(scale=perturbation, size=state.positions.shape)
        if n_types > 1:
            state = _with_random_types(state, n_types, rng)
        if temperature is not None:
            md.maxwell_boltzmann(state, temperature, seed=rng)
        return state

    return make


@pytest.fixture
def random_gas(rng):
    """Factory: ``n_atoms`` random atoms with no pair closer than ``min_distance``.

    ``random_gas(n_atoms, box, pbc=True, min_distance=0.8, n_types=1,
    images=0, masses=1.0)``: atoms are placed uniformly in the box by random
    sequential insertion (minimum image along periodic axes). ``images`` > 0
    then moves every atom by a random number of box lengths in
    [-images, images] along each periodic axis, since the engine keeps
    positions unwrapped. ``n_types`` > 1 assigns random types (each occurs).
    """

    def make(n_atoms, box, pbc=True, min_distance=0.8, n_types=1, images=0, masses=1.0) -> md.State:
        box = np.broadcast_to(np.asarray(box, dtype=float), (3,)).copy()
        periodic = np.broadcast_to(np.asarray(pbc, dtype=bool), (3,)).copy()
        lengths = np.where(periodic, box, np.inf)
        positions = np.empty((n_atoms, 3))
        placed = 0
        for _ in range(1000 * n_atoms):
            trial = rng.uniform(0.0, box)
            d = positions[:placed] - trial
            d -= np.where(periodic, box, 0.0) * np.round(d / lengths)
            if placed == 0 or np.min(np.einsum("ij,ij->i", d, d)) >= min_distance**2:
                positions[placed] = trial
                placed += 1
                if placed == n_atoms:
                    break
        else:
            raise RuntimeError(f"could not place {n_atoms} atoms in box {box}")
        if images:
            shifts = rng.integers(-images, images + 1, size=positions.shape) * periodic
            positions += shifts * box
        state = md.State(positions=positions, masses=masses, box=box, pbc=periodic)
        if n_types > 1:
            state = _with_random_types(state, n_types, rng)
        return state

    return make


def _with_random_types(state: md.State, n_types: int, rng) -> md.State:
    types = rng.integers(0, n_types, size=state.n_atoms)
    types[:n_types] = np.arange(n_types)  # every type occurs
    return md.State(
        positions=state.positions,
        velocities=state.velocities,
        masses=state.masses,
        box=state.box,
        pbc=state.pbc,
        types=types,
    )
