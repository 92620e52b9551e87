"""Config to objects: the system, potentials, integrator and Simulation a config describes.

What ``md run`` (:mod:`md.run`), ``md minimize``, the integrator studies
(:mod:`md.studies`) and the sweeps (:mod:`md.sweeps`) build from a parsed
:class:`md.config.Config`, in one place, so each builds the run the command
line would. Raises :class:`md.errors.ConfigError` naming the file and table
for anything that cannot be built; writes nothing.
"""

from __future__ import annotations

import math
from pathlib import Path

from integrators.barostats import Barostat, pressure_control
from integrators.base import ForceSplit, constraints_of
from md.checkpoint import restore
from md.config import Config, build_system, integrator_from_config, potential_from_config
from md.distributed import DistributedSimulation, ranks_per_node
from md.errors import ConfigError, ConvergenceError, DeviceError, NonFiniteError
from md.parallel import max_threads, set_threads
from md.rigid_setup import rigid_components
from md.simulation import Simulation
from md.state import State
from md.topology import Topology
from potentials.base import BondedAngles


def run_topology(sim: Simulation) -> Topology:
    """The bonds and angles a run's trajectory stores: its bonded potentials' and its
    constraints'."""
    constraints = constraints_of(sim.integrator)
    extra = [] if constraints is None else [("constraint", constraints.bonds, None)]
    return sim.forcefield.topology(extra=extra)


def build_components(config: Config, state: State | None = None):
    """Build the system, potentials and integrator; return ``(state, potentials, integrator)``.

    ``state`` replaces the built system (a checkpoint's). Constraints, if
    any, are bound to it, moving it onto the bond lengths. Raises
    ConfigError naming the file and section for anything that cannot be built.
    """
    fresh = state is None
    built, bonds = build_system(config)
    if state is not None and state.n_atoms != built.n_atoms:
        raise ConfigError(
            f"{config.source}: the state holds {state.n_atoms} atoms, the config builds "
            f"{built.n_atoms}"
        )
    state = built if state is None else state
    potentials = build_potentials(config, state.type_names, bonds)
    for index, potential in enumerate(potentials):
        if not isinstance(potential, BondedAngles):
            continue  # the others are checked with the force field (Simulation)
        try:  # angles name atoms: say which table names one the system lacks
            potential.check(state)
        except ValueError as error:
            kind = config.potentials[index].type
            raise ConfigError(f"{config.source}: [potentials.{index}] ({kind}): {error}") from None
    integrator = integrator_from_config(config.integrator, config.source, bonds)
    if config.rigid is not None:  # velocity Verlet over bodies (md.rigid_setup)
        integrator, potentials = rigid_components(
            config, integrator, state, bonds, potentials, fresh
        )
    if config.barostat is not None:
        try:
            barostat = Barostat(config.barostat.type, **config.barostat.values)
            barostat.check(state.pbc)
            integrator = pressure_control(integrator, barostat)
        except ValueError as error:
            raise ConfigError(f"{config.source}: [barostat]: {error}") from None
    constraints = constraints_of(integrator)
    if constraints is not None:  # start on the bond lengths, so step 0 is reported there
        try:
            constraints.bind(state, integrator.dt)
        except (ValueError, ConvergenceError) as error:
            raise ConfigError(f"{config.source}: [integrator.constraints]: {error}") from None
    return state, potentials, integrator


def build_potentials(config: Config, type_names, bonds=None) -> list:
    """Fresh potentials from the config's ``[[potentials]]``, as ``md run`` builds them.

    ``bonds`` is the system's topology (``build_system``'s second value), which
    ``bonds = "system"`` takes. Raises ConfigError naming the table.
    """
    return [
        potential_from_config(entry, type_names, config.source, index, bonds)
        for index, entry in enumerate(config.potentials)
    ]


def build_simulation(config: Config, checkpoint, saved_path: Path, threads, ranks=None):
    """The Simulation ``md run`` runs: built from the config (or ``checkpoint``'s state,
    restored into it), on ``ranks`` a DistributedSimulation, its first forces evaluated.

    Raises ConfigError naming the file and table (``--resume`` and ``saved_path`` for a
    checkpoint that does not fit the config) for anything that cannot be built.
    """
    shape = config.run.decomposition
    if ranks is None and shape is not None and math.prod(shape) != 1:
        raise ConfigError(
            f"{config.source}: [run] decomposition {list(shape)} has {math.prod(shape)} bricks, "
            f"but this run is one process: start it under MPI (mpiexec -n {math.prod(shape)} "
            "md run ...), or drop the key"
        )
    if ranks is not None and config.rigid is not None:
        raise ConfigError(
            f"{config.source}: [rigid]: rigid bodies do not run decomposed over MPI ranks "
            "(yet); run this config in one process, without mpiexec"
        )
    if checkpoint is not None:
        try:
            state, potentials, integrator = build_components(config, checkpoint.state)
        except ConfigError as error:
            raise ConfigError(f"--resume: checkpoint {saved_path}: {error}") from None
    else:
        state, potentials, integrator = build_components(config)
    # Blow-up guard: nobody moves farther than the skin in one step, nor than a tenth
    # of the longest cutoff (a tiny skin only means frequent rebuilds). Adaptive
    # integrators take long output steps on purpose.
    cutoffs = [p.cutoff for p in potentials if p.cutoff is not None]
    guard = max([config.run.skin, *(0.1 * c for c in cutoffs)])
    guard = guard if guard > 0 and not integrator.adaptive else None
    set_run_threads(config, threads, ranks)
    try:
        if ranks is None:
            sim = Simulation(
                state,
                potentials,
                integrator,
                skin=config.run.skin,
                units=config.units,
                max_displacement=guard,
                precision=config.run.precision,
                outer_skin=config.run.outer_skin,
                neighbor_every=config.run.neighbor_every,
                neighbor_check=config.run.neighbor_check,
                device=config.run.device,
            )
        else:
            if config.run.device != "cpu":
                raise DeviceError(
                    f'[run] device = "{config.run.device}": a run over MPI ranks does not run '
                    "on the device; run it as one process (without mpiexec)"
                )
            if (config.run.neighbor_every, config.run.neighbor_check) != (1, True):
                raise ValueError(
                    "[run] neighbor_every and neighbor_check: a run decomposed over MPI ranks "
                    "looks at its neighbour lists at every step; run this config on one rank "
                    "(without mpiexec), or leave them at 1 and true"
                )
            sim = DistributedSimulation(
                state,
                potentials,
                integrator,
                skin=config.run.skin,
                units=config.units,
                max_displacement=guard,
                ranks=ranks,
                decomposition=config.run.decomposition,
                precision=config.run.precision,
                balance_every=config.run.balance_every,
                balance_threshold=config.run.balance_threshold,
            )
    except ValueError as error:
        where = (
            f"{config.source}: [run] decomposition"
            if "decomposition" in str(error)
            else (config.source)
        )
        raise ConfigError(f"{where}: {error}") from None
    if isinstance(integrator, ForceSplit):  # RESPA: both kinds of potential must be there
        try:
            integrator.split(sim.forcefield)
        except ValueError as error:
            raise ConfigError(
                f"{config.source}: [integrator] ({integrator.describe()['type']}): {error}"
            ) from None
    if checkpoint is not None:
        if ranks is None:
            restore(checkpoint, integrator, sim.forcefield)
        else:  # the integrator's whole-system state, then the ranks' parts and lists
            restore(checkpoint, integrator)
            sim.resume(
                checkpoint.state,
                checkpoint.neighbor_reference,
                checkpoint.neighbor_cell,
                checkpoint.decomposition,
            )
        if checkpoint.n_frames:  # else frame 0 was never kept: write it again
            sim.skip_initial_observation()
    try:
        sim.forcefield.compute(sim.state)
    except NonFiniteError as error:
        raise ConfigError(
            f"{config.source}: the initial configuration cannot be evaluated: {error} "
            "(overlapping atoms, a stretched bond, or a parameter beyond double precision?)"
        ) from None
    return sim


def set_run_threads(config: Config, threads: int | None, ranks=None) -> None:
    """Set the kernel threads: ``threads`` (``--threads``) or the config's ``[run] threads``;
    with neither, in a decomposed run, a node's cores shared by its ranks."""
    where = "--threads" if threads is not None else f"{config.source}: [run] threads"
    threads = threads if threads is not None else config.run.threads
    if threads is None and ranks is not None:
        threads = max(1, max_threads() // ranks_per_node(ranks))
    try:
        set_threads(threads)
    except ValueError as error:
        raise ConfigError(f"{where}: {error}") from None


__all__ = [
    "build_components",
    "build_potentials",
    "build_simulation",
    "run_topology",
    "set_run_threads",
]
