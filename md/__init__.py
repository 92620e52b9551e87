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
"""

from md.build import lattice, maxwell_boltzmann
from md.forcefield import ForceField
from md.neighbors import NeighborList, NonFiniteError
from md.simulation import Simulation, SimulationError
from md.state import State
from md.units import UNIT_SYSTEMS, UnitSystem, get_units

__version__ = "0.1.0"


def open_trajectory(path, **kwargs):
    """Open an H5MD trajectory we wrote as an MDAnalysis Universe (see md.trajectory)."""
    from md.trajectory import open_trajectory as _open

    return _open(path, **kwargs)


def __getattr__(name):
    # md.sweep (parameter sweeps on Dask) is imported on first use, so that
    # ``import md`` stays light and never imports Dask. The module is callable:
    # md.sweep(config, vary=..., ...) calls md.sweep.sweep.
    if name == "sweep":
        import importlib

        return importlib.import_module("md.sweep")
    raise AttributeError(f"module 'md' has no attribute {name!r}")


__all__ = [
    "UNIT_SYSTEMS",
    "ForceField",
    "NeighborList",
    "NonFiniteError",
    "Simulation",
    "SimulationError",
    "State",
    "UnitSystem",
    "get_units",
    "lattice",
    "maxwell_boltzmann",
    "open_trajectory",
    "sweep",
]
