"""The simulation loop: integrator, counters, observers."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence

import numpy as np

from md.analysis import kinetic_energy, pressure, temperature
from md.forcefield import ForceField
from md.neighbors import NonFiniteError
from md.state import State
from md.units import UnitSystem, get_units
from potentials.base import Potential

logger = logging.getLogger(__name__)

Observer = Callable[["Simulation"], None]


class SimulationError(RuntimeError):
    """The dynamics broke down (NaN or infinite energy or positions) at ``step``."""

    def __init__(self, step: int, message: str) -> None:
        self.step = step
        super().__init__(f"step {step}: {message}")


class Simulation:
    """A state, its force field and an integrator, advanced by :meth:`run`.

    Parameters
    ----------
    state : State
        The system; advanced in place (``sim.state`` is the same object).
    potentials : sequence of Potential
        Interaction terms, summed by a :class:`~md.forcefield.ForceField`.
    integrator : Integrator
        Carries its own time step, e.g. ``VelocityVerlet(dt=0.005)``.
    skin : float
        Neighbour-list skin [length].
    units : {"lj", "metal"} or UnitSystem
        Only used for kB in the temperature; the dynamics is unit-agnostic.

    Examples
    --------
    >>> from md.build import lattice, maxwell_boltzmann
    >>> from potentials import LennardJones
    >>> from integrators import VelocityVerlet
    >>> state = maxwell_boltzmann(lattice("fcc", 4, density=0.8442), 1.0, seed=1)
    >>> sim = Simulation(state, [LennardJones(cutoff=2.5)], VelocityVerlet(dt=0.005))
    >>> sim.run(10)
    >>> sim.state.step
    10
    """

    def __init__(
        self,
        state: State,
        potentials: Sequence[Potential],
        integrator,
        skin: float = 0.3,
        units: str | UnitSystem = "lj",
    ) -> None:
        self.state = state
        self.forcefield = ForceField(potentials, skin=skin)
        self.forcefield.check(state)
        self.integrator = integrator
        self.units = get_units(units)
        self.timings = {"integrate": 0.0, "output": 0.0}
        self._observers: list[tuple[Observer, int]] = []
        self._observed_start = False

    @property
    def potentials(self) -> list[Potential]:
        return self.forcefield.potentials

    def attach(self, observer: Observer, interval: int = 1) -> None:
        """Call ``observer(sim)`` after every step divisible by ``interval``.

        Observers read ``sim.state`` and never write it; those that keep data
        copy it. A fresh run (step 0) also calls them once before the first
        step; a continued run does not, so no frame is written twice.
        """
        if isinstance(interval, bool) or not isinstance(interval, int | np.integer) or interval < 1:
            raise ValueError(f"observer interval must be a positive integer, got {interval!r}")
        self._observers.append((observer, int(interval)))

    def run(self, n_steps: int) -> None:
        """Advance ``n_steps`` steps.

        Raises
        ------
        SimulationError
            If the energy or positions become NaN or infinite; the state is
            left at the failing step and observers have seen every step
            before it.
        """
        if isinstance(n_steps, bool) or not isinstance(n_steps, int | np.integer) or n_steps < 0:
            raise ValueError(f"n_steps must be a non-negative integer, got {n_steps!r}")
        state = self.state
        if state.step == 0 and not self._observed_start:
            self._guarded(lambda: self.forcefield.compute(state), state.step)
            self._notify(all_observers=True)
            self._observed_start = True
        forcefield_timings = self.forcefield.timings
        for _ in range(int(n_steps)):
            before = forcefield_timings["neighbor"] + forcefield_timings["force"]
            start = time.perf_counter()
            self._guarded(lambda: self.integrator.step(state, self.forcefield), state.step + 1)
            elapsed = time.perf_counter() - start
            spent_in_forces = forcefield_timings["neighbor"] + forcefield_timings["force"] - before
            self.timings["integrate"] += elapsed - spent_in_forces
            if self._observers:
                self._notify(all_observers=False)

    def thermo(self) -> dict[str, float]:
        """Return potential, kinetic and total energy, temperature and pressure now.

        Energies in [energy], temperature in [temperature] (kB of ``units``),
        pressure in [energy/length^3]; also ``step`` and ``time``.
        """
        state = self.state
        result = self.forcefield.compute(state)
        kinetic = kinetic_energy(state.velocities, state.masses)
        return {
            "step": state.step,
            "time": state.time,
            "potential_energy": result.energy,
            "kinetic_energy": kinetic,
            "total_energy": result.energy + kinetic,
            "temperature": temperature(state.velocities, state.masses, self.units.kB),
            "pressure": pressure(kinetic, result.virial, state.volume),
        }

    def timing_summary(self) -> dict[str, float]:
        """Wall time [s] spent in force kernels, neighbour lists, integration and output."""
        return {
            "force": self.forcefield.timings["force"],
            "neighbor": self.forcefield.timings["neighbor"],
            "integrate": self.timings["integrate"],
            "output": self.timings["output"],
        }

    def _notify(self, all_observers: bool) -> None:
        start = time.perf_counter()
        step = self.state.step
        for observer, interval in self._observers:
            if all_observers or step % interval == 0:
                observer(self)
        self.timings["output"] += time.perf_counter() - start

    @staticmethod
    def _guarded(action, step: int):
        try:
            return action()
        except NonFiniteError as error:
            raise SimulationError(
                step, f"{error}; the dynamics blew up (is dt too large?)"
            ) from error
