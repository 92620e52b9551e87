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

:func:`integrator_class` resolves a config's ``type``: a name in ``INTEGRATORS``, a
plug-in registered under the entry-point group ``leapmd.integrators``, or a
``module:attribute`` path (:mod:`md.plugins`); a plug-in is an
:class:`IntegratorBase` subclass, as the built-in integrators are.
"""

from md import plugins
from md._kernel_cache import kernel_cache
from md.errors import ConstraintError
from md.schema import Key, key_names

# Kernel modules are imported here so numba caches them per user (md._kernel_cache).
with kernel_cache():
    from integrators.base import ConvergenceError, Integrator, IntegratorBase
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


def integrator_class(name: str) -> type:
    """The integrator class a config's ``type = name`` names: a built-in
    (``INTEGRATORS``, which win over plug-ins of the same name), a plug-in under the
    entry-point group ``leapmd.integrators``, or ``module:attribute``.

    Raises :class:`md.errors.PluginError` naming the plug-in when it is missing, its import
    raises, it is not an :class:`IntegratorBase` subclass with ``step`` and ``describe``,
    or its constructor does not take its config keys.
    """
    return plugins.load(name, "integrators", INTEGRATORS, _integrator_problem)


def _integrator_problem(found) -> str | None:
    """What keeps ``found`` from serving as a config's integrator (None: nothing)."""
    if not (isinstance(found, type) and issubclass(found, IntegratorBase)):
        what = found.__name__ if isinstance(found, type) else f"{type(found).__name__} {found!r}"
        return f"{what} is not an integrator: subclass integrators.base.IntegratorBase"
    # a plug-in class (foreign): the methods the loop calls
    missing = [m for m in ("step", "describe") if not callable(getattr(found, m, None))]
    if missing:
        return f"{found.__name__} does not define {' and '.join(missing)}()"
    keys = found.CONFIG_KEYS
    if not isinstance(keys, tuple) or not all(isinstance(k, Key) for k in keys):
        return f"CONFIG_KEYS must be a tuple of md.schema.Key, got {keys!r}"
    supplied = ("kB",) if found.thermostat else ()  # the config adds kB (and seed, declared)
    return plugins.signature_problem(found, key_names(keys), supplied)


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
    "IntegratorBase",
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
    "integrator_class",
]
