"""Time integrators on the :class:`integrators.base.Integrator` protocol.

``INTEGRATORS`` maps the names used in configs to the classes. The core are
velocity Verlet, leapfrog and implicit Euler; the rest of the classical family,
the implicit family (implicit midpoint, the trapezoidal rule, BDF2, two-stage
Gauss-Legendre, and XPBD for stiff bonds) and the higher-order symplectic
splittings (Yoshida 4 and 6, PEFRL, Blanes-Moan; :mod:`integrators.splitting`)
serve accuracy, comparison and
teaching (``md integrators`` measures them all). The thermostats (Langevin,
Bussi, Nose-Hoover chains, Berendsen) sample at a temperature; they and
:class:`Rattle` (velocity Verlet with SHAKE/RATTLE) take rigid-bond
``constraints``.
"""

from md._kernel_cache import kernel_cache
from md.errors import ConstraintError

# Kernel modules are imported here so numba caches them per user (md._kernel_cache).
with kernel_cache():
    from integrators.base import ConvergenceError, Integrator
    from integrators.bdf2 import BDF2
    from integrators.berendsen import Berendsen
    from integrators.bussi import Bussi
    from integrators.explicit_euler import ExplicitEuler, SymplecticEuler
    from integrators.gauss_legendre import GaussLegendre4
    from integrators.implicit_euler import ImplicitEuler, ImplicitMidpoint
    from integrators.langevin import Langevin
    from integrators.leapfrog import Leapfrog
    from integrators.nose_hoover import NoseHooverChain
    from integrators.rattle import BondConstraints, Rattle
    from integrators.respa import RESPA
    from integrators.runge_kutta import RK4, RKF45
    from integrators.splitting import (
        PEFRL,
        BlanesMoan,
        BlanesMoanRKN,
        Splitting,
        Yoshida4,
        Yoshida6,
    )
    from integrators.stormer_verlet import StormerVerlet
    from integrators.trapezoidal import Trapezoidal
    from integrators.velocity_verlet import VelocityVerlet
    from integrators.xpbd import XPBD

INTEGRATORS = {
    "verlet": VelocityVerlet,
    "velocity_verlet": VelocityVerlet,
    "leapfrog": Leapfrog,
    "explicit_euler": ExplicitEuler,
    "symplectic_euler": SymplecticEuler,
    "stormer_verlet": StormerVerlet,
    "yoshida4": Yoshida4,
    "forest_ruth": Yoshida4,
    "yoshida6": Yoshida6,
    "pefrl": PEFRL,
    "blanes_moan": BlanesMoan,
    "blanes_moan_rkn": BlanesMoanRKN,
    "respa": RESPA,
    "rk4": RK4,
    "rkf45": RKF45,
    "implicit_euler": ImplicitEuler,
    "implicit_midpoint": ImplicitMidpoint,
    "trapezoidal": Trapezoidal,
    "bdf2": BDF2,
    "gauss_legendre4": GaussLegendre4,
    "xpbd": XPBD,
    "rattle": Rattle,
    "langevin": Langevin,
    "bussi": Bussi,
    "nose_hoover_chain": NoseHooverChain,
    "nhc": NoseHooverChain,
    "berendsen": Berendsen,
}

__all__ = [
    "BDF2",
    "INTEGRATORS",
    "RESPA",
    "RK4",
    "RKF45",
    "Berendsen",
    "BlanesMoan",
    "BlanesMoanRKN",
    "BondConstraints",
    "Bussi",
    "ConstraintError",
    "ConvergenceError",
    "ExplicitEuler",
    "GaussLegendre4",
    "ImplicitEuler",
    "ImplicitMidpoint",
    "Integrator",
    "Langevin",
    "Leapfrog",
    "NoseHooverChain",
    "PEFRL",
    "Rattle",
    "Splitting",
    "StormerVerlet",
    "SymplecticEuler",
    "Trapezoidal",
    "VelocityVerlet",
    "XPBD",
    "Yoshida4",
    "Yoshida6",
]
