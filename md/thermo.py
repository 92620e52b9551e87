"""Kinetic energy, temperature and pressure from arrays (layer 0: numpy and one numba loop).

The engine calls these every thermo step; the trajectory analyses in
:mod:`md.analysis` build on them.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray


def kinetic_energy(velocities: NDArray[np.float64], masses: NDArray[np.float64]) -> float:
    """Return the total kinetic energy [energy].

    Parameters
    ----------
    velocities : ndarray of float64, shape (N, 3)
        Particle velocities [length/time].
    masses : ndarray of float64, shape (N,)
        Particle masses [mass].

    Examples
    --------
    >>> import numpy as np
    >>> kinetic_energy(np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]]), np.array([2.0, 1.0]))
    3.0
    """
    return 0.5 * float(np.einsum("i,ij,ij->", masses, velocities, velocities))


def degrees_of_freedom(n_atoms: int) -> int:
    """Return the kinetic degrees of freedom, 3N - 3.

    The three removed are the centre-of-mass momentum, which the velocity
    builders set to zero and the integrators conserve (the convention of
    LAMMPS's ``compute temp``). A single atom keeps its 3.

    Examples
    --------
    >>> degrees_of_freedom(100), degrees_of_freedom(1)
    (297, 3)
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

    Examples
    --------
    >>> import numpy as np
    >>> pressure(1.5, np.zeros((3, 3)), volume=1.0)
    1.0
    """
    if volume <= 0:
        return float("nan")
    return (2.0 * kinetic + float(np.trace(virial))) / (3.0 * volume)


#: Names of the pressure tensor's components in thermo rows and files.
PRESSURE_COMPONENTS = ("pxx", "pyy", "pzz", "pxy", "pxz", "pyz")
_COMPONENT_INDEX = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


def pressure_tensor(velocities, masses, virial, volume: float) -> NDArray[np.float64]:
    """Return the (3, 3) pressure tensor (sum_i m_i v_i v_i^T + W) / V [energy/length^3].

    Its trace over three is :func:`pressure`. All NaN for a zero volume.

    Examples
    --------
    >>> import numpy as np
    >>> p = pressure_tensor(np.array([[1.0, 0, 0]]), np.array([2.0]), np.zeros((3, 3)), 1.0)
    >>> p[0, 0], p[1, 1]
    (np.float64(2.0), np.float64(0.0))
    """
    if volume <= 0:
        return np.full((3, 3), np.nan)
    kinetic = kinetic_tensor(velocities, masses)
    return (kinetic + np.asarray(virial, dtype=np.float64)) / volume


def tensor_components(tensor) -> dict[str, float]:
    """The six independent components of a symmetric (3, 3) tensor, by name."""
    return {
        name: float(tensor[a, b])
        for name, (a, b) in zip(PRESSURE_COMPONENTS, _COMPONENT_INDEX, strict=True)
    }


@njit(cache=True, error_model="numpy")
def kinetic_tensor(velocities, masses) -> NDArray[np.float64]:
    """Return sum_i m_i v_i v_i^T, (3, 3) [energy], twice the kinetic energy tensor.

    One pass in one thread: numpy's einsum takes 40 times as long, and its
    matrix product goes to OpenBLAS, whose spinning threads then slow the
    force kernels' own.
    """
    out = np.zeros((3, 3))
    for i in range(velocities.shape[0]):
        m = masses[i]
        vx, vy, vz = velocities[i, 0], velocities[i, 1], velocities[i, 2]
        out[0, 0] += m * vx * vx
        out[1, 1] += m * vy * vy
        out[2, 2] += m * vz * vz
        out[0, 1] += m * vx * vy
        out[0, 2] += m * vx * vz
        out[1, 2] += m * vy * vz
    out[1, 0] = out[0, 1]
    out[2, 0] = out[0, 2]
    out[2, 1] = out[1, 2]
    return out
