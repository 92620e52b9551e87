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
from md.checkpoint import restore
from potentials.base import ForceResult

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


def lj_config_text(
    *,
    seed: int = 5,
    cells: int = 3,
    density: float = 0.8442,
    temperature: float = 1.2,
    potential: str = "",
    integrator: str = 'type = "verlet"\ndt = 0.005',
    run: str | None = "steps = 40\nthermo_every = 10",
    output: str | None = 'path = "out.h5"\nevery = 10\nvelocities = true',
) -> str:
    """The TOML of a small fcc LJ run (lj units), for tests that write configs.

    ``potential`` adds keys to the LJ table (cutoff 2.5); ``integrator``,
    ``run`` and ``output`` are the bodies of those tables (None leaves the
    table out).
    """
    text = (
        f'units = "lj"\nseed = {seed}\n\n[system]\nlattice = "fcc"\ncells = {cells}\n'
        f"density = {density}\ntemperature = {temperature}\n\n"
        f'[[potentials]]\ntype = "lj"\ncutoff = 2.5\n{potential}\n[integrator]\n{integrator}\n'
    )
    if run is not None:
        text += f"\n[run]\n{run}\n"
    if output is not None:
        text += f"\n[output]\n{output}\n"
    return text


#: A small bead-spring melt (lj units, 4 chains of 8 with FENE bonds) writing polymer.h5.
POLYMER = """
units = "lj"
seed = 3
[system]
polymer = "melt"
chains = 4
chain_length = 8
density = 0.8
bond_length = 0.97
temperature = 1.0
[[potentials]]
type = "lj"
cutoff = 1.122462048309373
cutoff_mode = "shift"
[[potentials]]
type = "fene"
bonds = "system"
k = 30.0
r_max = 1.5
[integrator]
type = "verlet"
dt = 0.002
[run]
steps = 60
[output]
path = "polymer.h5"
every = 10
velocities = true
forces = true
"""


@pytest.fixture
def lj_config():
    """Factory: ``lj_config(**keys)`` is :func:`lj_config_text` (see there)."""
    return lj_config_text


class Tether:
    """Test-only external potential u = k/2 |r - anchor|^2 per atom (no cutoff).

    Anchors default to the origin. A harmonic oscillator per coordinate, with
    angular frequency sqrt(k / m): the integrators' analytic reference.
    """

    cutoff = None

    def __init__(self, k: float, anchors=0.0) -> None:
        self.k = k
        self.anchors = np.asarray(anchors, dtype=float)

    def energy_forces(self, state, neighbors, per_atom=False, virial=True) -> ForceResult:
        d = state.positions - self.anchors
        energies = 0.5 * self.k * np.einsum("ij,ij->i", d, d)
        forces = -self.k * d
        return ForceResult(
            energy=float(energies.sum()),
            forces=forces,
            virial=np.einsum("ia,ib->ab", d, forces),
            energies=energies if per_atom else None,
        )

    def check(self, state) -> None:
        pass

    def describe(self) -> dict:
        return {"type": "tether", "k": self.k}


def resumed_run(checkpoint, build, steps: int):
    """The simulation ``build(state)`` makes from ``checkpoint``'s state, restored from the
    checkpoint (integrator state, neighbour list) and run ``steps`` steps."""
    sim = build(checkpoint.state)
    restore(checkpoint, sim.integrator, sim.forcefield)
    sim.run(steps)
    return sim


def assert_same_end(sim, other) -> None:
    """Two runs ended at the same positions and velocities, bit for bit."""
    assert np.array_equal(sim.state.positions, other.state.positions)
    assert np.array_equal(sim.state.velocities, other.state.velocities)
