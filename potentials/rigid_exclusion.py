"""Pairs inside one rigid body left out of the pair potentials, by subtraction.

The neighbour list has no exclusions; :class:`IntraBodyExclusion` evaluates the
given pair potentials over the pairs inside each body (a fixed half list, minimum
image as the frame applies it) and returns minus the result, so that the force
field's sum holds only the pairs between bodies and free atoms (as LAMMPS's
``neigh_modify exclude molecule/intra``, or OpenMM's exceptions, leave them out).
Forces inside a rigid body sum to no force and no torque on it, so this changes
the potential energy (by a constant) and the virial, never the motion; it keeps
the large, cancelling forces of close constituents out of the reported energy.
"""

from __future__ import annotations

import math

import numpy as np

from potentials.base import ForceResult


class _PairList:
    """A fixed half list in CSR form, as a pair frame reads a neighbour list (atom order)."""

    list_radius = math.inf
    frame = None
    clusters = None

    def __init__(self, starts, partners) -> None:
        self.starts = np.ascontiguousarray(starts, dtype=np.int64)
        self.neighbors = np.ascontiguousarray(partners, dtype=np.int32)


class IntraBodyExclusion:
    """Minus ``pair_potentials`` over the intra-body pairs ``(starts, partners)`` (see
    :meth:`md.rigid.RigidBodies.intra_pairs`); ``cutoff`` None (no neighbour list)."""

    cutoff = None

    def __init__(self, pair_potentials, starts, partners) -> None:
        self.pair_potentials = tuple(pair_potentials)
        self.pairs = _PairList(starts, partners)

    def check(self, state) -> None:
        for potential in self.pair_potentials:
            potential.check(state)

    def energy_forces(self, state, neighbors, per_atom: bool = False, virial: bool = True):
        n = state.n_atoms
        energy, forces = 0.0, np.zeros((n, 3))
        total_virial = np.zeros((3, 3)) if virial or per_atom else None
        energies = np.zeros(n) if per_atom else None
        virials = np.zeros((n, 6)) if per_atom else None
        for potential in self.pair_potentials:
            result = potential.energy_forces(state, self.pairs, per_atom, virial=virial)
            energy -= result.energy
            forces -= result.forces
            if total_virial is not None and result.virial is not None:
                total_virial -= result.virial
            if per_atom:
                energies -= result.energies
                if result.virials is not None:
                    virials -= result.virials
        return ForceResult(
            energy=energy, forces=forces, virial=total_virial, energies=energies, virials=virials
        )

    def describe(self) -> dict:
        return {"type": "intra_body_exclusion", "pairs": int(len(self.pairs.neighbors))}


__all__ = ["IntraBodyExclusion"]
