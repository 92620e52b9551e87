"""The Integrator protocol, its capability flags, its optional hooks, and what integrators share.

The optional hooks are small ``runtime_checkable`` protocols; the engine
asks ``isinstance(integrator, Hook)`` before it calls one, so an integrator
that leaves a hook out is simply not asked:

======================  ==========================================  ==============================
protocol                members                                     used by
======================  ==========================================  ==============================
:class:`Constrained`    ``constraints`` (BondConstraints or None)   md.assemble (bind, topology),
                                                                    barostats
:class:`ThermoTerms`    ``thermo_terms(state, result)``             Simulation.thermo
:class:`Statistics`     ``statistics`` (dict of counters)           md run's summary, barostats
:class:`Restartable`    ``get_state()``, ``set_state(saved)``       checkpoints
:class:`ForceSplit`     ``split(forcefield)``                       md.assemble (RESPA/XPBD check)
:class:`SupportsAm-     ``amplification(omega_dt)`` (static)        md.studies (damping theory)
plification`
:class:`Distributable`  ``distributed``, ``per_atom_state``         md.distributed
:class:`DeclaresOrder`  ``order`` (of an integrator or a factory)   md.studies.integrator_study
:class:`DeclaresAdap-   ``adaptive`` (the same)                     md.studies.integrator_study
tive`
======================  ==========================================  ==============================

:class:`IntegratorBase` gives the flags' defaults, ``constraints = None``
(so every integrator in the registry is :class:`Constrained`) and
:meth:`IntegratorBase.end_step`, the bookkeeping that closes every step.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from md._checks import positive
from md.errors import ConvergenceError
from md.schema import REQUIRED, Key

if TYPE_CHECKING:  # annotations only: integrators import nothing above layer 0 of md
    from integrators.rattle import BondConstraints
    from md.state import State
    from potentials.base import ForceResult, ForceSource


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
    ``distributed`` (optional: False when absent, see :class:`Distributable`)
        It runs on one rank's atoms in a run decomposed over MPI ranks
        (:mod:`md.distributed`): its sums over atoms go through
        :func:`md.parallel.global_sum`, and its private per-atom arrays, named
        in ``per_atom_state`` (keys of ``get_state()``), move with their atoms.

    ``CONFIG_KEYS`` (a tuple of :class:`md.schema.Key`) declares the keys its
    ``[integrator]`` table takes: one per constructor argument but ``kB``,
    which the config supplies from its unit system.
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

    def step(self, state: State, forcefield: ForceSource) -> None: ...

    def reset(self) -> None: ...

    def describe(self) -> dict: ...


@runtime_checkable
class Constrained(Protocol):
    """Optional hook: the integrator's rigid bonds (None when it has none).

    ``md.run`` binds them to the starting state (moving it onto the bond
    lengths) and stores their bonds in the trajectory's topology; a
    barostat passes on its inner integrator's.
    """

    constraints: BondConstraints | None


@runtime_checkable
class ThermoTerms(Protocol):
    """Optional hook: what the integrator adds to ``Simulation.thermo()``.

    ``thermo_terms(state, result)`` returns a dict with any of ``n_dof``
    (degrees of freedom of the kinetic temperature), ``virial`` (a (3, 3)
    constraint virial added to the pair virial) and ``reservoir_energy``
    (a heat bath's or barostat's energy, giving ``conserved_energy``).
    """

    def thermo_terms(self, state: State, result: ForceResult) -> dict: ...


@runtime_checkable
class ScalesCell(Protocol):
    """Optional hook: how a barostat's move applies to the integrator's particles, where
    moving every position would be wrong (rigid bodies: their centres move, their shapes
    do not). ``scale_cell(state, mu, velocities)`` moves the cell and the positions by
    ``mu`` (a scale factor, or a (3, 3) deformation r -> r mu), and with ``velocities``
    the momenta by its inverse (v -> v mu^-T)."""

    def scale_cell(self, state: State, mu, velocities: bool) -> None: ...


@runtime_checkable
class Wraps(Protocol):
    """Optional hook: an integrator that moves the particles through another one, its
    ``inner`` (a barostat around the integrator that steps the particles)."""

    inner: Integrator


@runtime_checkable
class GroupsPairs(Protocol):
    """Optional hook: atoms whose pairs the neighbour list leaves out, ``pair_groups``
    (N,) int64, each atom's group or -1, or None. Two atoms of one group >= 0 (a rigid
    body) are never listed as a pair (LAMMPS's ``neigh_modify exclude molecule/intra``);
    :class:`md.simulation.Simulation` hands them to its force field."""

    pair_groups: NDArray[np.int64] | None


@runtime_checkable
class Statistics(Protocol):
    """Optional hook: cumulative counters (``steps``, solver iterations, ...) as a dict."""

    statistics: dict


@runtime_checkable
class Restartable(Protocol):
    """Optional hook: private state (history, random generator) as plain data.

    ``get_state()`` returns it (or None: nothing to keep) for a checkpoint;
    ``set_state(saved)`` takes it back, so a resumed run continues bit for
    bit. The two come together: a checkpoint holding private state cannot
    be resumed by an integrator without ``set_state``.
    """

    def get_state(self) -> dict | None: ...

    def set_state(self, saved: dict) -> None: ...


@runtime_checkable
class ForceSplit(Protocol):
    """Optional hook of an integrator with ``splits_forces``: its groups of potentials.

    ``split(forcefield)`` returns ``(fast, slow)``, tuples of indices into
    ``forcefield.potentials``, or raises ValueError when one group is empty;
    ``md.run`` calls it before the run so that a config without, say, bonds
    is refused up front.
    """

    def split(self, forcefield: ForceSource) -> tuple[tuple[int, ...], tuple[int, ...]]: ...


@runtime_checkable
class SupportsAmplification(Protocol):
    """Optional hook: the method's amplification on the harmonic oscillator.

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


#: The time step, a key of every integrator's config table.
DT = Key("dt", "number", REQUIRED, unit="time", positive=True, doc="The time step.")


@runtime_checkable
class Distributable(Protocol):
    """Optional flags: whether the integrator runs decomposed over MPI ranks.

    ``distributed`` True says it runs on one rank's atoms (its sums over atoms go
    through :func:`md.parallel.global_sum`); ``per_atom_state`` names the keys of
    ``get_state()`` that are per-atom arrays, which move with their atoms. The two
    come together (:class:`IntegratorBase` gives both); an integrator without them
    is not run decomposed.
    """

    distributed: bool
    per_atom_state: tuple[str, ...]


@runtime_checkable
class DeclaresOrder(Protocol):
    """Optional flag of an integrator, or of a factory of integrators (a class, or a
    ``functools.partial`` given one): ``order``, the global order in ``dt`` it is built
    for (None: none to measure). A plain function that makes integrators has none."""

    order: int | None


@runtime_checkable
class DeclaresAdaptive(Protocol):
    """Optional flag of an integrator or a factory of them: ``adaptive``, True when it
    chooses its own substeps (absent: a fixed-step method)."""

    adaptive: bool


class IntegratorBase:
    """Defaults of the capability flags, and the step's bookkeeping.

    Every integrator in the registry derives from it. ``constraints`` is
    None (no rigid bonds) unless the integrator sets it. ``CONFIG_KEYS`` is
    ``(DT,)``: an integrator with more constructor arguments declares them
    too (a test compares the declaration with the signature).
    """

    CONFIG_KEYS: ClassVar[tuple[Key, ...]] = (DT,)
    dt: float
    constraints: BondConstraints | None = None
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

    def end_step(self, state: State) -> None:
        """Close a step: advance ``state.step`` by one and ``state.time`` by ``dt``.

        Every integrator calls it last in ``step``, once positions and
        velocities hold the new point, so the counters move only for a step
        that was taken.
        """
        state.step += 1
        state.time += self.dt


def constraints_of(integrator) -> BondConstraints | None:
    """The integrator's rigid bonds, or None (none, or no :class:`Constrained` hook)."""
    return integrator.constraints if isinstance(integrator, Constrained) else None


def pair_groups_of(integrator) -> NDArray[np.int64] | None:
    """The integrator's :class:`GroupsPairs` groups (also under a barostat's ``inner``),
    or None."""
    while not isinstance(integrator, GroupsPairs):
        if not isinstance(integrator, Wraps):
            return None
        integrator = integrator.inner
    return integrator.pair_groups


def check_dt(dt: float) -> float:
    """Return ``dt`` as a float, or raise ValueError if it is not finite and > 0."""
    return positive(dt, "dt")


__all__ = [
    "DT",
    "Constrained",
    "ConvergenceError",
    "DeclaresAdaptive",
    "DeclaresOrder",
    "Distributable",
    "ForceSplit",
    "GroupsPairs",
    "Integrator",
    "IntegratorBase",
    "Restartable",
    "ScalesCell",
    "Statistics",
    "SupportsAmplification",
    "ThermoTerms",
    "Wraps",
    "amplification_roots",
    "check_dt",
    "constraints_of",
    "pair_groups_of",
]
