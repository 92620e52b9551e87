"""Time integrators on the :class:`integrators.base.Integrator` protocol.

``INTEGRATORS`` maps the names used in configs to the classes. The core are
velocity Verlet, leapfrog and implicit Euler; the rest of the classical family
serves comparison and teaching (``md integrators`` measures them all).
"""

from integrators.base import ConvergenceError, Integrator
from integrators.explicit_euler import ExplicitEuler, SymplecticEuler
from integrators.implicit_euler import ImplicitEuler, ImplicitMidpoint
from integrators.leapfrog import Leapfrog
from integrators.runge_kutta import RK4, RKF45
from integrators.stormer_verlet import StormerVerlet
from integrators.velocity_verlet import VelocityVerlet

INTEGRATORS = {
    "verlet": VelocityVerlet,
    "velocity_verlet": VelocityVerlet,
    "leapfrog": Leapfrog,
    "explicit_euler": ExplicitEuler,
    "symplectic_euler": SymplecticEuler,
    "stormer_verlet": StormerVerlet,
    "rk4": RK4,
    "rkf45": RKF45,
    "implicit_euler": ImplicitEuler,
    "implicit_midpoint": ImplicitMidpoint,
}

__all__ = [
    "INTEGRATORS",
    "RK4",
    "RKF45",
    "ConvergenceError",
    "ExplicitEuler",
    "ImplicitEuler",
    "ImplicitMidpoint",
    "Integrator",
    "Leapfrog",
    "StormerVerlet",
    "SymplecticEuler",
    "VelocityVerlet",
]
