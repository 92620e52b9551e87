"""Time integrators on the :class:`integrators.base.Integrator` protocol.

``INTEGRATORS`` maps the names used in configs to the classes.
"""

from integrators.base import ConvergenceError, Integrator
from integrators.velocity_verlet import VelocityVerlet

INTEGRATORS = {"verlet": VelocityVerlet, "velocity_verlet": VelocityVerlet}

__all__ = ["INTEGRATORS", "ConvergenceError", "Integrator", "VelocityVerlet"]
