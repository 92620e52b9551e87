"""The Integrator protocol, its capability flags, and the checks integrators share."""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from md._checks import positive
from md.errors import ConvergenceError

if TYPE_CHECKING:  # annotations only: integrators import nothing above layer 0 of md
    from md.forcefield import ForceField
    from md.state import State


@runtime_checkable
class Integrator(Protocol):
    """Advance a State by one time step.

    ``step`` updates ``state.positions`` and ``state.velocities`` in place and
    advances ``state.step`` by one and ``state.time`` by ``dt``; it asks the
    force field for forces with ``forcefield.compute(state, virial=False)``.
    Anything staggered (half-step velocities, solver history, a random
    generator) stays private to the integrator; ``reset`` drops it, and
    ``get_state()``/``set_state(saved)`` (optional) expose it as plain data so
    that checkpoints restart it exactly.

    Capability flags are class attributes, read by the config, the CLI and
    the integrator study; :class:`IntegratorBase` gives their defaults:

    ``thermostat``
        It controls the temperature (takes ``temperature`` and ``seed``) and
        reports a conserved quantity through ``thermo_terms``.
    ``stochastic``
        It draws random numbers (a ``seed`` makes runs repeatable).
    ``canonical``
        It samples the canonical ensemble (False: Berendsen).
    ``supports_constraints`` / ``requires_constraints``
        It takes ``constraints=`` (bond constraints); it cannot run without them.
    ``adaptive``
        It chooses its own substeps inside one output step, so it has no fixed
        order in ``dt`` and no per-step displacement bound.
    ``splits_forces``
        It evaluates groups of potentials apart (multiple time stepping), so
        it needs a force field with both kinds; ``md integrators`` measures
        it only when named.
    ``order``
        The global order of accuracy in ``dt`` the method is built for (None:
        adaptive, stochastic or thermostatted), which ``md integrators``
        measures and the tests check.
    """

    dt: float
    thermostat: ClassVar[bool]
    stochastic: ClassVar[bool]
    canonical: ClassVar[bool]
    supports_constraints: ClassVar[bool]
    requires_constraints: ClassVar[bool]
    adaptive: ClassVar[bool]
    splits_forces: ClassVar[bool]
    order: ClassVar[int | None]

    def step(self, state: State, forcefield: ForceField) -> None: ...

    def reset(self) -> None: ...

    def describe(self) -> dict: ...


@runtime_checkable
class SupportsAmplification(Protocol):
    """Optional capability: the method's amplification on the harmonic oscillator.

    ``amplification(omega_dt)`` returns the roots of the characteristic
    polynomial of the method applied to x'' = -omega^2 x with step dt, as
    :func:`amplification_roots` orders them: the principal root first (the
    one that follows the exact e^(i omega dt) as omega dt -> 0; for the
    methods here, the one of largest modulus). Its modulus is the amplitude
    ratio per step, below 1 for a method that damps; its argument the phase
    per step, omega dt when exact. A one-step method has two roots (the
    conjugate pair), a k-step method 2k.
    """

    @staticmethod
    def amplification(omega_dt: float) -> NDArray[np.complex128]: ...


def amplification_roots(*polynomials) -> NDArray[np.complex128]:
    """Return the roots of the product of ``polynomials`` (coefficients, highest
    power first), the largest modulus first and of a conjugate pair the one with
    the non-negative imaginary part first."""
    roots = np.concatenate([np.roots(np.asarray(p, dtype=np.complex128)) for p in polynomials])
    order = np.lexsort((-roots.imag, -np.round(np.abs(roots), 12)))
    return roots[order]


class IntegratorBase:
    """Defaults of the capability flags; every integrator in the registry derives from it."""

    thermostat: ClassVar[bool] = False
    stochastic: ClassVar[bool] = False
    canonical: ClassVar[bool] = True
    supports_constraints: ClassVar[bool] = False
    requires_constraints: ClassVar[bool] = False
    adaptive: ClassVar[bool] = False
    splits_forces: ClassVar[bool] = False
    order: ClassVar[int | None] = None

    def reset(self) -> None:
        """Drop private history (nothing, for a one-step method)."""


def check_dt(dt: float) -> float:
    """Return ``dt`` as a float, or raise ValueError if it is not finite and > 0."""
    return positive(dt, "dt")


__all__ = [
    "ConvergenceError",
    "Integrator",
    "IntegratorBase",
    "SupportsAmplification",
    "amplification_roots",
    "check_dt",
]
