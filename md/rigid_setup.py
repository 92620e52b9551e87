"""A config's ``[rigid]`` table to bodies and their integrator (layer 3).

:func:`body_ids` finds the molecule id of every atom: a LAMMPS data file's
molecule column (atom styles ``full``, ``molecular``, ``bond``, ``angle``), as
LAMMPS's ``fix rigid ... molecule`` takes it, else the bonded clusters of the
system's topology. :func:`rigid_components` builds the
:class:`md.rigid.RigidBodies` and wraps the config's velocity Verlet into
:class:`integrators.rigid.RigidNVE`, which leaves the pairs inside bodies out of the
neighbour list (``[rigid] exclude``; :meth:`md.neighbors.NeighborList.exclude_groups`). Both raise
:class:`md.errors.ConfigError` naming the file and key, before anything is written.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from integrators import Bussi, Langevin, NoseHooverChain
from integrators.rigid import RigidBussi, RigidLangevin, RigidNoseHoover, RigidNVE
from md.config import Config
from md.errors import ConfigError
from md.rigid import RigidBodies, molecules_from_bonds
from md.state import State
from md.structure import structure_kind
from md.topology import Topology

#: LAMMPS atom styles whose second column is the molecule id.
_MOLECULE_STYLES = ("full", "molecular", "bond", "angle")


def lammps_molecule_ids(path) -> np.ndarray | None:
    """The molecule column of a LAMMPS data file's Atoms section, ordered by atom id (as
    the structure reader orders atoms), or None for a style without one."""
    path = Path(path)
    ids, molecules = [], []
    style, in_atoms = None, False
    with open(path, errors="replace") as handle:
        for line in handle:
            text = line.split("#", 1)[0].strip()
            if text and text[0].isalpha():
                in_atoms = text.split()[0] == "Atoms"
                if in_atoms:
                    hint = line.split("#", 1)[1].split() if "#" in line else []
                    style = hint[0] if hint else None
                continue
            if in_atoms and text:
                words = text.split()
                ids.append(int(words[0]))
                molecules.append(int(words[1]) if len(words) > 1 else 0)
    if style not in _MOLECULE_STYLES or not ids:
        return None
    return np.asarray(molecules, dtype=np.int64)[np.argsort(ids, kind="stable")]


def body_ids(config: Config, state: State, topology: Topology | None) -> np.ndarray:
    """Molecule ids of the atoms: ``[rigid] bodies = "template"``'s copies in order, else
    the molecules (``bodies = "molecules"``)."""
    if config.rigid.template is not None:  # md.rigid.bodies_on_sites: K atoms per site
        size = len(config.rigid.template)
        return np.repeat(np.arange(1, state.n_atoms // size + 1), size)
    structure = config.system.structure
    if structure is not None and structure_kind(structure, config.system.format) == ("lammps-data"):
        try:
            found = lammps_molecule_ids(structure)
        except (OSError, ValueError) as error:
            raise ConfigError(
                f"{config.source}: [rigid] bodies: cannot read molecule ids from {structure} "
                f"({error})"
            ) from None
        if found is not None:
            if len(found) != state.n_atoms:
                raise ConfigError(
                    f"{config.source}: [rigid] bodies: {structure} lists {len(found)} molecule "
                    f"ids for {state.n_atoms} atoms"
                )
            return found
    bonds = np.zeros((0, 2), dtype=np.int64) if topology is None else topology.bonds
    return molecules_from_bonds(bonds, state.n_atoms)


def rigid_components(
    config: Config, integrator, state: State, topology: Topology | None, potentials, fresh: bool
):
    """Return ``(integrator, potentials)``: the config's velocity Verlet made
    :class:`RigidNVE` over its bodies (Langevin :class:`RigidLangevin`, Bussi
    :class:`RigidBussi`, Nose-Hoover chains :class:`RigidNoseHoover`), which with
    ``[rigid] exclude`` leaves the pairs inside bodies out of the neighbour list, and the
    potentials as they were. On a fresh
    run (``fresh``) the constituents are placed rigidly at once, so step 0 is reported
    there (a resumed state is already placed; its
    bodies come from the checkpoint)."""
    # The GPU path (md.cuda) does not move bodies yet.
    device = config.run.device
    if device != "cpu":
        raise ConfigError(
            f"{config.source}: [rigid]: rigid bodies run on the CPU only (yet); set [run] "
            f"device = 'cpu' (got {device!r})"
        )
    ids = body_ids(config, state, topology)
    try:
        bodies = RigidBodies.from_molecules(state, ids)
    except ValueError as error:
        raise ConfigError(f"{config.source}: [rigid] bodies: {error}") from None
    rotation = config.rigid.rotation
    exclude = config.rigid.exclude
    if isinstance(integrator, Langevin):  # its bath on the bodies' momenta
        rigid = RigidLangevin(
            integrator.dt,
            bodies,
            rotation,
            kT=integrator.kT,
            friction=integrator.friction,
            seed=integrator.seed,
            exclude=exclude,
        )
    elif isinstance(integrator, Bussi):  # its rescaling on every momentum
        rigid = RigidBussi(
            integrator.dt,
            bodies,
            rotation,
            kT=integrator.kT,
            tau=integrator.tau,
            seed=integrator.seed,
            exclude=exclude,
        )
    elif isinstance(integrator, NoseHooverChain):  # its chain on every momentum
        rigid = RigidNoseHoover(
            integrator.dt,
            bodies,
            rotation,
            kT=integrator.kT,
            tau=integrator.tau,
            chain_length=integrator.chain_length,
            n_substeps=integrator.n_substeps,
            exclude=exclude,
        )
    else:
        rigid = RigidNVE(integrator.dt, bodies, rotation, exclude)
    if fresh:
        bodies.place(state)
    return rigid, potentials


__all__ = ["body_ids", "lammps_molecule_ids", "rigid_components"]
