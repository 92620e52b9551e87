"""The Integrator protocol, its capability flags, and the checks integrators share."""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar, Protocol, runtime_checkable

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
    ``distributed``
        It runs on one rank's atoms in a run decomposed over MPI ranks
        (:mod:`md.distributed`): its sums over atoms go through
        :func:`md.parallel.global_sum`, and its private per-atom arrays, named
        in ``per_atom_state`` (keys of ``get_state()``), move with their atoms.
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
    distributed: ClassVar[bool]
    per_atom_state: ClassVar[tuple[str, ...]]

    def step(self, state: State, forcefield: ForceField) -> None: ...

    def reset(self) -> None: ...

    def describe(self) -> dict: ...


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
    distributed: ClassVar[bool] = False
    per_atom_state: ClassVar[tuple[str, ...]] = ()

    def reset(self) -> None:
        """Drop private history (nothing, for a one-step method)."""


def check_dt(dt: float) -> float:
    """Return ``dt`` as a float, or raise ValueError if it is not finite and > 0."""
    return positive(dt, "dt")


__all__ = ["ConvergenceError", "Integrator", "IntegratorBase", "check_dt"]
