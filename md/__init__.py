"""leapmd: a readable, fast molecular dynamics engine (Python + numba).

The Python API::

    import md
    from potentials import LennardJones
    from integrators import VelocityVerlet

    state = md.lattice("fcc", 10, density=0.8442)
    md.maxwell_boltzmann(state, temperature=1.0, seed=1)
    sim = md.Simulation(state, [LennardJones(cutoff=2.5)], VelocityVerlet(dt=0.005))
    sim.run(1000)
    sim.thermo()

    sim, summary = md.run_config("examples/lj_small.toml", steps=100)   # what `md run` does
    md.show("lj_small.h5")        # in Jupyter, with nglview installed: a 3-D view

The package is layered; each module imports only from layers below it (see
ARCHITECTURE.md). This facade re-exports the public names; it is the only
module allowed to reach every layer. Importing it changes nothing process-wide
(no signal handlers, excepthook or allocator settings): those belong to the
``md`` command's entry (:func:`md.cli.main`, ``md_command``).
"""

from md._kernel_cache import kernel_cache
from md._memory import keep_freed_memory

# Kernel modules are imported here so numba caches them per user (md._kernel_cache).
with kernel_cache():
    from md._version import __version__
    from md.build import lattice, maxwell_boltzmann
    from md.errors import (
        CheckpointError,
        ConfigError,
        ConvergenceError,
        NonFiniteError,
        SimulationError,
        TrajectoryError,
    )
    from md.forcefield import ForceField
    from md.neighbors import NeighborList
    from md.simulation import Simulation
    from md.state import State
    from md.units import UNIT_SYSTEMS, UnitSystem, get_units


#: Names from the upper layers, resolved on first access: ``md.config`` and ``md.run``
#: import the integrator registry, so loading them here would make ``import
#: integrators`` (which imports layer 0 of md, hence this file) circular; ``show``
#: lives at the edge layer with the notebook tools.
_LAZY = {"run_config": "md.run", "open_trajectory": "md.trajectory", "show": "md.notebook"}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib  # resolves the upper-layer names listed in _LAZY

        # the facade alone may import a computed name: one of _LAZY's upper-layer modules
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'md' has no attribute {name!r}")


def sweep(config, vary=None, replicas: int = 1, out=None, **options):
    """Run a parameter sweep on Dask; see :func:`md.sweeps.sweep` for the arguments."""
    from md.sweeps import sweep as run_sweep  # Dask machinery: loaded on first use

    return run_sweep(config, vary=vary, replicas=replicas, out=out, **options)


__all__ = [
    "UNIT_SYSTEMS",
    "CheckpointError",
    "ConfigError",
    "ConvergenceError",
    "ForceField",
    "NeighborList",
    "NonFiniteError",
    "Simulation",
    "SimulationError",
    "State",
    "TrajectoryError",
    "UnitSystem",
    "__version__",
    "get_units",
    "keep_freed_memory",
    "lattice",
    "maxwell_boltzmann",
    "open_trajectory",
    "run_config",
    "show",
    "sweep",
]
