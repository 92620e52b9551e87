"""What observers of a decomposed run see: the whole system gathered on rank 0
(:class:`GlobalView` and the integrator's and force field's views in it), the
wrapper that gathers it for an observer (:class:`Gathered`), and the stand-in
for an observer that rank 0 holds (:class:`Elsewhere`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from md.distributed.ranks import agree
from md.parallel import global_max
from md.simulation import VirialUse
from md.state import State
from md.topology import Topology
from potentials.base import ForceResult

if TYPE_CHECKING:
    from md.distributed.simulation import DistributedSimulation


@runtime_checkable
class WholeSystemUse(Protocol):
    """Optional hook of an observer: ``whole_system = False`` says it reads only the step,
    time and thermo (a thermo table, a progress bar), so a decomposed run hands it those
    without gathering the atoms; an observer without the attribute gets the whole system."""

    whole_system: bool


@runtime_checkable
class ForcesUse(Protocol):
    """Optional hook of an observer: ``store_forces = True`` says it reads the forces (a
    trajectory writer storing them), so a decomposed run gathers them too; an observer
    without the attribute is handed none."""

    store_forces: bool


@runtime_checkable
class LayoutUse(Protocol):
    """Optional hook of an observer: ``store_layout = True`` says it records where a resume
    starts from (a checkpoint writer), so a decomposed run gathers with the atoms their
    last build positions, ranks and step starts (``DistributedSimulation.global_view``'s
    ``layout``); an observer without the attribute (a trajectory writer) is handed none."""

    store_layout: bool


@runtime_checkable
class Decomposed(Protocol):
    """What a force field seen by rank 0's observers of a decomposed run has beyond a
    ForceField's: ``decomposition``, the layout a checkpoint records (the grid, its cut
    planes, each atom's owner and row, and what the next step start would see)."""

    decomposition: dict


class Elsewhere:
    """The stand-in, on the other ranks, for an observer that rank 0 holds (a trajectory
    writer): it says what the gather for it needs, and is never called."""

    uses_virial = True

    def __init__(self, store_forces: bool = False) -> None:
        self.store_forces = bool(store_forces)

    def __call__(self, sim) -> None:
        raise RuntimeError("an observer held by rank 0 was called on another rank")


class Gathered:
    """An observer run on rank 0 with the whole system; the others take part in the gather."""

    def __init__(self, observer) -> None:
        self.observer = observer
        self.uses_virial = observer.uses_virial if isinstance(observer, VirialUse) else True
        #: False for an observer that reads only the step, time and thermo (a thermo
        #: table, a progress bar): it gets them without the atoms being gathered.
        self.whole_system = observer.whole_system if isinstance(observer, WholeSystemUse) else True
        #: True for an observer that records the run's layout (a checkpoint writer).
        self.layout = isinstance(observer, LayoutUse) and bool(observer.store_layout)

    def __call__(self, sim: DistributedSimulation) -> None:
        if self.whole_system:
            forces = isinstance(self.observer, ForcesUse) and bool(self.observer.store_forces)
            extra = {"layout": True} if self.layout else {}  # (the layout's columns)
            view = sim.global_view(forces=forces, thermo=self.uses_virial, **extra)
        else:
            view = sim.light_view(thermo=self.uses_virial)
        error = None
        if view is not None:
            try:
                self.observer(view)
            except Exception as caught:  # shared with every rank below
                error = caught
        if global_max(0.0 if error is None else 1.0, sim.ranks):
            agree(sim.ranks, error)


@dataclass
class GlobalView:
    """What an observer of a decomposed run sees on rank 0: the whole system, gathered.

    It offers what observers read of a :class:`md.simulation.Simulation`:
    ``state`` (the whole system in its atom order), ``thermo()`` (computed by
    every rank together before the gather), ``integrator`` (``describe``,
    ``get_state`` with whole-system per-atom arrays, and the rest of the
    integrator) and ``forcefield`` (``compute`` giving the gathered forces,
    ``neighbor_list.reference_positions``, ``topology``), and ``units``.
    """

    state: State
    row: dict | None
    integrator: object
    forcefield: object
    units: object

    def thermo(self) -> dict[str, float]:
        if self.row is None:
            raise RuntimeError("this observer said it reads no thermo (uses_virial = False)")
        return dict(self.row)


class IntegratorView:
    """The integrator, with ``get_state`` giving the whole system's per-atom arrays."""

    def __init__(self, integrator, saved) -> None:
        self._integrator = integrator
        self._saved = saved

    def get_state(self):
        return self._saved

    def __getattr__(self, name):
        # a proxy: every other attribute is the integrator's own (not a capability probe)
        return getattr(self._integrator, name)


@dataclass
class ListView:
    """The neighbour list's build, for checkpoints: positions and cell of the last build
    (a rank's list is never a pruned cluster list: no prune positions, no prunes)."""

    reference_positions: NDArray[np.float64] | None
    reference_cell: tuple | None
    n_builds: int
    pruned_positions: None = None
    n_prunes: int = 0
    built_step: None = None  # ranks always look at their lists: no step to count from


class ForceFieldView:
    """The force field as a rank-0 observer sees it (gathered forces, the build, topology)."""

    def __init__(self, forcefield, forces, row, reference, layout) -> None:
        self._forcefield = forcefield
        self._forces = forces
        self._energy = None if row is None else row["potential_energy"]
        complete = reference is not None and not np.isnan(reference).any()
        self.neighbor_list = ListView(
            reference if complete else None, forcefield.reference_cell, forcefield.n_builds
        )
        self.decomposition = layout
        self.precision = forcefield.precision  # what a checkpoint of the run records

    def compute(self, state: State, per_atom: bool = False, virial: bool = True) -> ForceResult:
        if self._forces is None:
            raise RuntimeError("forces were not gathered for this observer (store_forces)")
        return ForceResult(energy=self._energy, forces=self._forces, virial=None)

    def topology(self, extra=()) -> Topology:
        return self._forcefield.topology(extra)
