"""Thermodynamic quantities from plain arrays.

Trajectory analyses (RDF, MSD, VACF through MDAnalysis) build on these in a
later layer; everything here is pure numpy and unit-agnostic.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def kinetic_energy(velocities: NDArray[np.float64], masses: NDArray[np.float64]) -> float:
    """Return the total kinetic energy [energy].

    Parameters
    ----------
    velocities : ndarray of float64, shape (N, 3)
        Particle velocities [length/time].
    masses : ndarray of float64, shape (N,)
        Particle masses [mass].
    """
    return 0.5 * float(np.einsum("i,ij,ij->", masses, velocities, velocities))


def degrees_of_freedom(n_atoms: int) -> int:
    """Return the kinetic degrees of freedom, 3N - 3.

    The three removed are the centre-of-mass momentum, which the velocity
    builders set to zero and the integrators conserve (the convention of
    LAMMPS's ``compute temp``). A single atom keeps its 3.
    """
    return 3 * n_atoms - 3 if n_atoms > 1 else 3 * n_atoms


def temperature(velocities, masses, kB: float = 1.0) -> float:
    """Return the kinetic temperature 2 K / (n_dof kB) [temperature]."""
    n_dof = degrees_of_freedom(len(masses))
    if n_dof == 0:
        return 0.0
    return 2.0 * kinetic_energy(velocities, masses) / (n_dof * kB)


def pressure(kinetic: float, virial: NDArray[np.float64], volume: float) -> float:
    """Return the pressure (2 K + tr W) / (3 V) [energy/length^3].

    ``virial`` is the (3, 3) pair virial W_ab = sum over pairs of r_ij,a F_ij,b
    (positive for repulsion). The kinetic term uses all 3N velocity
    components, as the virial theorem does. NaN for a zero volume (open box).
    """
    if volume <= 0:
        return float("nan")
    return (2.0 * kinetic + float(np.trace(virial))) / (3.0 * volume)
