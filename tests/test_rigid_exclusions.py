"""Pairs inside one rigid body left out of the neighbour list (issue 68).

``NeighborList.exclude_groups`` drops, after each build, the pairs of two atoms of
one body; :class:`integrators.rigid.RigidNVE` (``exclude``, the default, as ``[rigid]
exclude``) hands its bodies to the Simulation's force field. Checked here: every list
path a rigid run can take (the cell search, serial and threaded; the small-box search;
the O(N^2) one) equals the brute-force pairs less the intra-body ones; mixed precision
(no cluster layout then) agrees with double; the energy is the pairs' between bodies
alone, with the bodies' forces, torques and virial unchanged, even for constituents so
close that subtracting their pairs lost the rest; the configs pass it on; LAMMPS with
``neigh_modify exclude`` gives the same trajectory and energies.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_rigid import TRIMER, TRIMER_MASSES, _random_rotation, _state
from test_rigid_vs_lammps import PEERS, SHAPES, STEPS, _bodies, _lammps, _ours

from integrators.rigid import RigidNVE
from md.assemble import build_simulation
from md.box import minimum_image
from md.config import load_config
from md.forcefield import ForceField
from md.neighbors import NeighborList
from md.parallel import get_threads, set_threads
from md.rigid import RigidBodies
from md.simulation import Simulation
from md.state import State
from potentials.lennard_jones import LennardJones


def _trimers(rng, n_bodies: int, edge: float, n_free: int = 0) -> tuple[State, np.ndarray]:
    """``n_bodies`` trimers turned at random and ``n_free`` free atoms on the sites of a
    cubic grid in a periodic cube (shuffled); returns the state and each atom's body (-1:
    free)."""
    k = int(np.ceil((n_bodies + n_free) ** (1 / 3)))
    sites = np.stack(np.meshgrid(*[np.arange(k)] * 3, indexing="ij"), -1).reshape(-1, 3)
    sites = rng.permutation(sites)[: n_bodies + n_free] * (edge / k)
    parts = [TRIMER @ _random_rotation(rng).T + c for c in sites[:n_bodies]]
    positions = np.concatenate([*parts, sites[n_bodies:]]) % edge
    groups = np.concatenate([np.repeat(np.arange(n_bodies), 3), -np.ones(n_free, np.int64)])
    masses = np.concatenate([np.tile(TRIMER_MASSES, n_bodies), np.ones(n_free)])
    state = State(
        positions=positions,
        velocities=np.zeros_like(positions),
        masses=masses,
        box=[edge] * 3,
        pbc=[True] * 3,
    )
    return state, groups


def _reference_pairs(state: State, radius: float, groups: np.ndarray) -> set:
    """Every pair within ``radius`` (minimum image), less those of two atoms of one body."""
    n = state.n_atoms
    i, j = np.triu_indices(n, 1)
    d = minimum_image(state.positions[i] - state.positions[j], state.box, state.pbc)
    near = np.einsum("ij,ij->i", d, d) < radius**2
    inner = (groups[i] == groups[j]) & (groups[i] >= 0)
    return set(zip(i[near & ~inner].tolist(), j[near & ~inner].tolist(), strict=True))


@pytest.fixture
def two_threads():
    before = get_threads()
    set_threads(min(2, before))
    yield
    set_threads(before)


@pytest.mark.parametrize(
    "path, n_bodies, edge, n_free",
    [
        ("cells", 200, 14.0, 100),  # five or more cells a side: the cell search
        ("threaded cells", 700, 18.0, 0),  # 2100 atoms: two chunks on two threads
        ("small box", 20, 6.0, 10),  # under five cells: the small-box search (slot frame)
        ("atom order", 8, 2.5, 4),  # narrower than the list radius: O(N^2) over atoms
    ],
)
def test_list_is_brute_force_less_the_pairs_inside_bodies(
    path, n_bodies, edge, n_free, rng, two_threads
):
    state, groups = _trimers(rng, n_bodies, edge, n_free)
    # the O(N^2) search over atoms: a box narrower than the list radius (yet twice the cutoff)
    cutoff, skin = (1.0, 1.6) if path == "atom order" else (2.5, 0.3)
    nl = NeighborList(cutoff, skin)
    nl.update(state)
    everything = len(nl.pairs())
    nl.exclude_groups(groups)
    assert nl.update(state)  # new groups: built again
    listed = nl.pairs()
    expected = _reference_pairs(state, nl.list_radius, groups)
    assert set(map(tuple, listed.tolist())) == expected
    assert len(listed) == len(expected) < everything  # each once, the inner pairs gone
    if path == "atom order":
        assert nl.frame is None and not nl.used_cells
    else:
        assert nl.frame is not None and nl.used_cells == (path != "small box")
    if path == "threaded cells":
        assert get_threads() < 2 or len(nl.bounds) == 3
    # the chunks' bounds still balance the pairs that are left and cover every row
    assert nl.bounds[0] == 0 and nl.bounds[-1] == state.n_atoms
    assert nl.slot_starts[-1] == len(nl.slot_neighbors) == nl.n_pairs
    # the pair kernels over this list give the brute force's energy over those pairs
    lj = LennardJones(cutoff=cutoff)
    i, j = np.array(sorted(expected)).T
    d = minimum_image(state.positions[i] - state.positions[j], state.box, state.pbc)
    energy = sum(lj.pair_energy(float(r)) for r in np.linalg.norm(d, axis=1))
    assert lj.energy_forces(state, nl).energy == pytest.approx(energy, rel=1e-10, abs=1e-10)
    nl.exclude_groups(None)
    nl.update(state)
    assert len(nl.pairs()) == everything


def test_groups_must_fit_the_atoms(rng):
    state, groups = _trimers(rng, 10, 8.0)
    nl = NeighborList(2.5, 0.3)
    nl.exclude_groups(groups[:-1])
    with pytest.raises(ValueError, match="29 groups for 30 atoms"):
        nl.update(state)
    with pytest.raises(ValueError, match="one per atom"):
        nl.exclude_groups(groups.reshape(-1, 3))


def test_mixed_precision_leaves_them_out_in_the_slot_frame(rng):
    """The cluster-pair layout holds 4 x 4 blocks, so a list with groups is built in the
    slot frame; mixed precision then gives double's energy and forces to float32's
    round-off, without the pairs inside bodies."""
    state, groups = _trimers(rng, 300, 16.0, 50)
    results = {}
    for precision in ("double", "mixed"):
        field = ForceField([LennardJones(cutoff=2.5)], precision=precision)
        field.exclude_groups(groups)
        results[precision] = field.compute(state)
        assert field.neighbor_list.clusters is None
    double, mixed = results["double"], results["mixed"]
    assert mixed.energy == pytest.approx(double.energy, rel=1e-5)
    scale = np.max(np.abs(double.forces))
    assert np.max(np.abs(mixed.forces - double.forces)) < 1e-5 * scale
    whole = ForceField([LennardJones(cutoff=2.5)], precision="mixed")
    lj = LennardJones(cutoff=2.5)
    inner = sum(
        lj.pair_energy(float(np.linalg.norm(TRIMER[i] - TRIMER[j])))
        for i, j in ((0, 1), (0, 2), (1, 2))
    )
    assert whole.compute(state).energy - double.energy == pytest.approx(300 * inner, rel=1e-2)
    assert whole.neighbor_list.clusters is not None  # without groups: the cluster layout


def test_energy_is_between_bodies_and_their_motion_unchanged(rng):
    """Constituents 0.01 apart inside a body (LJ energy 4e24): left out of the list, the
    energy is the pairs' between the bodies alone to round-off, and the bodies' forces,
    torques and rigid-body virial are those with the inner pairs (which cancel on each
    body). Subtracting the inner pairs from the sum of all lost everything else there."""
    close = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.3, 0.8, 0.0]])
    a, b = _random_rotation(rng), _random_rotation(rng)
    positions = np.concatenate([close @ a.T + 5.0, TRIMER @ b.T + [6.3, 5.4, 5.9]])
    state = _state(positions, np.tile(TRIMER_MASSES, 2), box=12.0)
    bodies = RigidBodies.from_molecules(state, [1, 1, 1, 2, 2, 2])
    lj = LennardJones(cutoff=3.0)
    between = sum(
        lj.pair_energy(float(np.linalg.norm(positions[i] - positions[j])))
        for i in range(3)
        for j in range(3, 6)
    )
    sims = {
        exclude: Simulation(
            state.copy(), [LennardJones(cutoff=3.0)], RigidNVE(0.001, bodies, exclude=exclude)
        )
        for exclude in (True, False)
    }
    inter = sims[True].forcefield.compute(sims[True].state)
    full = sims[False].forcefield.compute(sims[False].state)
    assert inter.energy == pytest.approx(between, rel=1e-12)
    assert sims[True].thermo()["potential_energy"] == pytest.approx(between, rel=1e-12)
    assert full.energy > 1e24
    inner = sum(
        lj.pair_energy(float(np.linalg.norm(positions[i] - positions[j])))
        for body in (0, 3)
        for i, j in ((body, body + 1), (body, body + 2), (body + 1, body + 2))
    )
    assert abs(full.energy - inner - between) > 1.0  # what the subtraction gave
    force, torque = bodies.force_torque(inter.forces)
    # the full forces carry 1e27 inside the first body, cancelling to its round-off
    full_force, full_torque = bodies.force_torque(full.forces)
    assert np.allclose(full_force[1], force[1], atol=1e-10)
    assert np.allclose(full_torque[1], torque[1], atol=1e-10)
    assert np.allclose(force[0], -force[1], atol=1e-10)
    # the second body, all of whose pairs are well apart: the virial with and without
    # the inner pairs, on two bodies of normal trimers
    c = np.concatenate([TRIMER @ a.T + 5.0, TRIMER @ b.T + [6.3, 5.4, 5.9]])
    plain = _state(c, np.tile(TRIMER_MASSES, 2), box=12.0)
    pair_bodies = RigidBodies.from_molecules(plain, [1, 1, 1, 2, 2, 2])
    results = []
    for exclude in (True, False):
        field = ForceField([LennardJones(cutoff=3.0)])
        if exclude:
            field.exclude_groups(pair_bodies.body_of)
        results.append(field.compute(plain))
    for result in results:
        f, t = pair_bodies.force_torque(result.forces)
        f0, t0 = pair_bodies.force_torque(results[0].forces)
        assert np.allclose(f, f0, atol=1e-10) and np.allclose(t, t0, atol=1e-10)
    virials = [pair_bodies.virial_correction(plain, r.forces) + r.virial for r in results]
    assert virials[0] == pytest.approx(virials[1], abs=1e-10)


CONFIG = """units = "lj"
seed = 11
[system]
polymer = "melt"
chains = 12
chain_length = 3
density = 0.05
bond_length = 1.0
temperature = 1.0
[[potentials]]
type = "lj"
cutoff = 2.5
[integrator]
dt = 0.002
TYPE
[rigid]
exclude = EXCLUDE
[run]
steps = 10
"""


@pytest.mark.parametrize(
    "kind", ['type = "velocity_verlet"', 'type = "langevin"\ntemperature = 1.0\nfriction = 1.0']
)
def test_configs_hand_the_bodies_to_the_list(tmp_path, kind):
    """``[rigid] exclude`` (true by default) reaches the neighbour list, also with a
    thermostat; the energies differ by the inner pairs' alone, which move nothing."""
    energies = {}
    for exclude in ("true", "false"):
        path = tmp_path / f"{exclude}.toml"
        text = CONFIG.replace("TYPE", kind).replace("EXCLUDE", exclude)
        path.write_text(text)
        sim = build_simulation(load_config(path), None, tmp_path / "x", None)
        groups = sim.forcefield.neighbor_list.excluded_groups
        energies[exclude] = sim.thermo()["potential_energy"]
        if exclude == "true":
            assert groups is not None and np.array_equal(groups, np.repeat(np.arange(12), 3))
            state = sim.state.copy()
        else:
            assert groups is None
    inner = 0.0
    lj = LennardJones(cutoff=2.5)
    for body in range(12):
        x = state.positions[3 * body : 3 * body + 3]
        for i, j in ((0, 1), (0, 2), (1, 2)):
            d = minimum_image(x[i] - x[j], state.box, state.pbc)
            inner += lj.pair_energy(float(np.linalg.norm(d)))
    assert energies["false"] - energies["true"] == pytest.approx(inner, rel=1e-9)


@pytest.mark.parametrize("rotation", sorted(PEERS))
@pytest.mark.parametrize("shape", sorted(SHAPES))
def test_lammps_with_neigh_modify_exclude(shape, rotation):
    """Both codes without the pairs inside bodies (LAMMPS: ``neigh_modify exclude group
    bi bi``): the same trajectory to 1e-8 of the box and the same potential energy, which
    then holds the pairs between bodies alone, every 20 steps to 1e-8 relative."""
    start = _bodies(shape)
    size = len(SHAPES[shape][1])
    theirs = _lammps(start, STEPS, size, PEERS[rotation], exclude=True)
    with_inner = _lammps(start, 0, size, PEERS[rotation])
    state, row = _ours(start, STEPS, size, rotation, exclude=True)
    gap = minimum_image(state.positions - theirs["positions"], state.box, state.pbc)
    assert np.max(np.abs(gap)) < 1e-8 * state.box[0], np.max(np.abs(gap))
    np.testing.assert_allclose(row["series"], theirs["series"], rtol=1e-8)
    # LAMMPS's own energy at the start without the exclusion holds the inner pairs
    assert abs(with_inner["series"][0, 0] - theirs["series"][0, 0]) > 1e-3


def test_the_filter_runs_without_the_compiler(rng):
    """The kernel's Python twin (``NUMBA_DISABLE_JIT``) drops the same pairs, codes along."""
    from md.neighbors._exclusion_kernels import _drop_grouped_pairs

    n = 40
    groups = rng.integers(-1, 6, size=n)
    rows = [np.sort(rng.choice(n, size=rng.integers(0, 12), replace=False)) for _ in range(n)]
    starts = np.concatenate([[0], np.cumsum([len(r) for r in rows])]).astype(np.int64)
    neighbors = np.concatenate(rows).astype(np.int32)
    codes = rng.integers(0, 27, size=len(neighbors)).astype(np.uint8)
    order = rng.permutation(n).astype(np.int64)
    results = []
    for kernel in (_drop_grouped_pairs, _drop_grouped_pairs.py_func):
        s, nb, c = starts.copy(), neighbors.copy(), codes.copy()
        count = kernel(order, s, nb, c, groups)
        results.append((s, nb[:count], c[:count]))
    kept = [
        (p, q, code)
        for p in range(n)
        for q, code in zip(
            neighbors[starts[p] : starts[p + 1]], codes[starts[p] : starts[p + 1]], strict=True
        )
        if groups[order[p]] < 0 or groups[order[p]] != groups[order[q]]
    ]
    for s, nb, c in results:
        listed = [
            (p, q, code)
            for p in range(n)
            for q, code in zip(nb[s[p] : s[p + 1]], c[s[p] : s[p + 1]], strict=True)
        ]
        assert listed == kept
    assert 0 < len(kept) < len(neighbors)


def test_a_barostat_passes_the_bodies_on(rng):
    """Under a barostat (``inner``) the Simulation still finds the bodies' groups."""
    from integrators.barostats import Barostat, pressure_control
    from integrators.base import Wraps, pair_groups_of
    from integrators.rigid import RigidBussi

    state, groups = _trimers(rng, 27, 9.0)
    bodies = RigidBodies.from_molecules(state, groups + 1)
    barostat = Barostat("c_rescale", pressure=1.0, tau=1.0, compressibility=0.1)
    wrapped = pressure_control(RigidBussi(0.002, bodies, kT=1.0, tau=0.5, seed=1), barostat)
    assert isinstance(wrapped, Wraps)  # the groups are its inner integrator's
    assert np.array_equal(pair_groups_of(wrapped), groups)
    sim = Simulation(state, [LennardJones(cutoff=2.5)], wrapped)
    assert np.array_equal(sim.forcefield.neighbor_list.excluded_groups, groups)
    plain = RigidBussi(0.002, bodies, kT=1.0, tau=0.5, seed=1, exclude=False)
    assert pair_groups_of(pressure_control(plain, barostat)) is None
