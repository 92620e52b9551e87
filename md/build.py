"""Builders: lattices and thermal velocities."""

from __future__ import annotations

import numpy as np

from md.box import cell_matrix
from md.state import State
from md.thermo import degrees_of_freedom, kinetic_energy

#: Fractional coordinates of the conventional cubic cell's basis.
LATTICE_BASES: dict[str, np.ndarray] = {
    "sc": np.array([[0.0, 0.0, 0.0]]),
    "bcc": np.array([[0.0, 0.0, 0.0], [0.5, 0.5, 0.5]]),
    "fcc": np.array([[0.0, 0.0, 0.0], [0.5, 0.5, 0.0], [0.5, 0.0, 0.5], [0.0, 0.5, 0.5]]),
}


def lattice(
    kind: str,
    cells,
    density: float | None = None,
    lattice_constant: float | None = None,
    mass: float = 1.0,
    pbc=True,
    type_name: str = "A",
    shear=None,
) -> State:
    """Return a State of atoms on a cubic lattice, at rest, in a cubic or sheared cell.

    Parameters
    ----------
    kind : {"sc", "bcc", "fcc"}
        Lattice type.
    cells : int or sequence of 3 ints
        Number of conventional unit cells along x, y, z.
    density : float, optional
        Number density [1/length^3] (reduced density in LJ units); fixes the
        lattice constant as (atoms per cell / density)^(1/3).
    lattice_constant : float, optional
        Cubic cell edge [length]; give exactly one of this and ``density``.
    mass : float
        Mass of every atom [mass].
    shear : sequence of 3 floats, optional
        Shear the crystal and its cell homogeneously by the dimensionless tilt
        factors (xy, xz, yz) of HOOMD-blue's box: the cell vectors become
        (Lx, 0, 0), (xy Ly, Ly, 0) and (xz Lz, yz Lz, Lz), and every site moves
        with the cell (fractional coordinates are kept). The volume, hence the
        density, is unchanged; the crystal is strained. Needs periodic axes
        where it tilts.

    Examples
    --------
    >>> s = lattice("fcc", 2, density=0.8442)
    >>> s.n_atoms
    32
    """
    if kind not in LATTICE_BASES:
        raise ValueError(f"unknown lattice {kind!r} (known: {', '.join(LATTICE_BASES)})")
    basis = LATTICE_BASES[kind]
    n_cells = np.broadcast_to(np.asarray(cells), (3,))
    if not np.issubdtype(n_cells.dtype, np.integer) or np.any(n_cells < 1):
        raise ValueError(f"cells must be positive integers, got {cells!r}")
    if (density is None) == (lattice_constant is None):
        raise ValueError("give exactly one of density and lattice_constant")
    if density is not None:
        if not (np.isfinite(density) and density > 0):
            raise ValueError(f"density must be positive and finite, got {density}")
        with np.errstate(over="ignore"):
            a = float((len(basis) / np.float64(density)) ** (1.0 / 3.0))
    else:
        if not (np.isfinite(lattice_constant) and lattice_constant > 0):
            raise ValueError(
                f"lattice_constant must be positive and finite, got {lattice_constant}"
            )
        a = float(lattice_constant)
    with np.errstate(over="ignore"):
        edges = n_cells * np.float64(a)
    if not (np.isfinite(a) and np.all(np.isfinite(edges)) and a > 0):
        given = f"density {density!r}" if density is not None else f"lattice_constant {a!r}"
        raise ValueError(f"{given} makes a box beyond double precision (edges {edges.tolist()})")
    grid = np.stack(np.meshgrid(*(np.arange(n) for n in n_cells), indexing="ij"), axis=-1).reshape(
        -1, 1, 3
    )
    positions = ((grid + basis[None, :, :]) * a).reshape(-1, 3)
    tilt = np.zeros(3)
    if shear is not None:
        factors = np.asarray(shear, dtype=np.float64)
        if factors.shape != (3,) or not np.all(np.isfinite(factors)):
            raise ValueError(f"shear must be three finite numbers (xy, xz, yz), got {shear!r}")
        tilt = factors * edges[[1, 2, 2]]
        # Fractional coordinates kept: r -> r diag(L)^-1 H, with H the sheared cell.
        positions = positions / edges @ cell_matrix(edges, tilt)
    return State(
        positions=positions,
        masses=mass,
        box=edges,
        pbc=pbc,
        type_names=(type_name,),
        tilt=tilt,
    )


def maxwell_boltzmann(
    state: State, temperature: float, seed=None, kB: float = 1.0, exact: bool = True
) -> State:
    """Draw Maxwell-Boltzmann velocities in place; return the state.

    The centre-of-mass momentum is removed, and with ``exact`` the velocities
    are scaled so the kinetic temperature (3N - 3 degrees of freedom) equals
    ``temperature`` exactly, as LAMMPS's ``velocity create`` does. A single
    atom keeps its momentum (removing it would leave the atom at rest) and
    its 3 degrees of freedom (:func:`md.thermo.degrees_of_freedom`), so it
    too starts at exactly ``temperature``.

    Parameters
    ----------
    temperature : float
        Target temperature [temperature]; 0 gives velocities at rest.
    seed : int or numpy.random.Generator, optional
        Seed (or generator) for reproducible draws.
    kB : float
        Boltzmann constant in the engine units (1 for reduced units).
    """
    if not (np.isfinite(temperature) and temperature >= 0):
        raise ValueError(f"temperature must be finite and >= 0, got {temperature}")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    masses = state.masses
    sigma = np.sqrt(kB * temperature / masses)[:, None]
    velocities = rng.standard_normal((state.n_atoms, 3)) * sigma
    if state.n_atoms > 1:
        momentum = (masses[:, None] * velocities).sum(axis=0)
        velocities -= momentum / masses.sum()
    if exact:
        kinetic = kinetic_energy(velocities, masses)
        if kinetic > 0:
            target = 0.5 * degrees_of_freedom(state.n_atoms) * kB * temperature
            velocities *= np.sqrt(target / kinetic)
    state.velocities[:] = velocities
    return state
