"""The Potential protocol and the ForceResult it returns."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from md.neighbors import NeighborList
    from md.state import State


@dataclass
class ForceResult:
    """Energy, forces and virial of a configuration.

    Attributes
    ----------
    energy : float
        Potential energy [energy].
    forces : ndarray of float64, shape (N, 3)
        Forces [energy/length].
    virial : ndarray of float64, shape (3, 3), or None
        Pair virial W_ab = sum over interactions of r_ij,a F_ij,b [energy];
        its trace over 3 V is the configurational pressure. None when the
        caller said it needs no virial (``virial=False``), as integrators do
        between thermo outputs (LAMMPS's vflag).
    energies : ndarray of float64, shape (N,), optional
        Per-atom energies (each pair split half and half), when asked for.
    virials : ndarray of float64, shape (N, 6), optional
        Per-atom virials (each pair's r_ij (x) F_ij split half and half) as
        (xx, yy, zz, yz, xz, xy) [energy], when asked for and provided.
    """

    energy: float
    forces: NDArray[np.float64]
    virial: NDArray[np.float64] | None
    energies: NDArray[np.float64] | None = None
    virials: NDArray[np.float64] | None = None


class Potential(Protocol):
    """What the ForceField needs of a potential.

    ``cutoff`` is the interaction range, or None for potentials that need no
    neighbour list (bonded terms). ``energy_forces`` returns a new
    ForceResult and leaves the state untouched; ``neighbors`` is a list built
    with a radius of at least ``cutoff``. A potential whose ``energy_forces``
    also takes ``virial`` (bool, default True) may skip the virial when it
    is False; the ForceField passes it only to those that do.
    """

    cutoff: float | None

    def energy_forces(
        self, state: State, neighbors: NeighborList | None, per_atom: bool = False
    ) -> ForceResult: ...

    def check(self, state: State) -> None:
        """Raise ValueError if the potential cannot act on this state (types, sizes)."""
        ...

    def describe(self) -> dict:
        """Return the parameters as plain values, for trajectory metadata."""
        ...


@runtime_checkable
class SupportsHessian(Protocol):
    """Optional capability: the (3N, 3N) second derivative of the energy."""

    def hessian(self, state: State, neighbors: NeighborList | None) -> NDArray[np.float64]: ...
