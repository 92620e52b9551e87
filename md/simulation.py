"""The simulation loop: integrator, counters, observers."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from typing import Protocol, runtime_checkable

import numpy as np

from integrators.base import ThermoTerms, pair_groups_of
from md.box import cell_deformation
from md.cuda import device_engine
from md.errors import NonFiniteError, SimulationError
from md.forcefield import ForceField
from md.neighbors import max_displacement2
from md.parallel import global_sum, set_threads
from md.state import State
from md.thermo import (
    degrees_of_freedom,
    kinetic_energy,
    kinetic_tensor,
    pressure,
    tensor_components,
)
from md.units import UnitSystem, get_units
from potentials.base import Potential

logger = logging.getLogger(__name__)

Observer = Callable[["Simulation"], None]


@runtime_checkable
class VirialUse(Protocol):
    """Optional hook of an observer: ``uses_virial = False`` says it reads no pressure.

    On steps where only such observers run, the force field skips the
    virial (see :meth:`Simulation.attach`); an observer without the
    attribute is assumed to read it.
    """

    uses_virial: bool


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
    max_displacement : float, optional
        Blow-up guard [length]: a particle moving farther than this in one
        step stops the run with a :class:`SimulationError` (``md run`` uses
        the skin). None: no check. Kept as an attribute of that name. When
        the cell moved in the step (a barostat), the move is measured from
        the particle's old position carried along with the cell (the affine
        part, which grows with the box, is not counted); a cell move that
        changed the distances between neighbours (up to the neighbour-list
        radius apart) by more than the guard stops the run too, naming the
        box's strain.
    threads : int, optional
        Threads for the force and neighbour kernels, set process-wide through
        :func:`md.parallel.set_threads`; None leaves the setting as it is
        (every core unless set).
    precision : {"double", "mixed"}
        ``"mixed"`` computes the pair terms of the pair-kernel frame in
        float32 (r^2 rounded from double, parameters, u and f/r) with the pair
        forces, every sum, the positions, velocities and the integrator in
        double; bonded terms stay double. Forces agree with double to about
        3e-7 of the largest. Kept in the ForceField
        (``sim.forcefield.precision``).
    outer_skin : float, optional
        The cluster list's outer skin [length] (mixed precision): see
        :class:`md.neighbors.NeighborList`. None: its default, 5 x ``skin``.
    neighbor_every, neighbor_check : int, bool
        Look at the neighbour list only every ``neighbor_every`` steps, and at a
        look rebuild it only if an atom moved more than half the skin
        (``neighbor_check``) or always (False): LAMMPS's ``neigh_modify every N
        check yes/no``, GROMACS's ``nstlist``. The defaults, 1 and True, are exact;
        anything else can miss pairs between looks (the energy drifts): see
        :class:`md.neighbors.NeighborList`.
    device : {"cpu", "cuda"}
        ``"cuda"`` runs the steps on an NVIDIA GPU (:mod:`md.cuda`): the state stays on
        the device during :meth:`run` and comes back for the observers only on the
        steps they run. What is not ported (see :func:`md.cuda.refusal`) raises
        :class:`md.errors.DeviceError` here. ``max_displacement`` is not checked there.

    Attributes
    ----------
    stop_requested : str or None
        Set by :meth:`request_stop` (e.g. from a signal handler); :meth:`run`
        then returns after the step in progress.

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
        max_displacement: float | None = None,
        threads: int | None = None,
        precision: str = "double",
        outer_skin: float | None = None,
        neighbor_every: int = 1,
        neighbor_check: bool = True,
        device: str = "cpu",
    ) -> None:
        if threads is not None:
            set_threads(threads)
        self.state = state
        self.forcefield = ForceField(
            potentials,
            skin=skin,
            precision=precision,
            outer_skin=outer_skin,
            neighbor_every=neighbor_every,
            neighbor_check=neighbor_check,
        )
        self.forcefield.check(state)
        groups = pair_groups_of(integrator)  # rigid bodies: their inner pairs never listed
        if groups is not None:
            if groups.shape != (state.n_atoms,):
                raise ValueError(
                    f"the integrator's pair groups are {groups.shape[0]} for {state.n_atoms} atoms"
                )
            if device != "cpu":
                raise ValueError(
                    f"pair exclusions (rigid bodies) run on the CPU only, not {device!r}"
                )
            self.forcefield.exclude_groups(groups)
        self.integrator = integrator
        self.device = device
        self._engine = device_engine(
            device,
            state,
            self.forcefield,
            integrator,
            neighbor_every=neighbor_every,
            neighbor_check=neighbor_check,
        )
        self.units = get_units(units)
        self.timings = {"integrate": 0.0, "output": 0.0}
        self._observers: list[tuple[Observer, int]] = []
        self._virial_intervals: list[int] = []
        self._observed_start = False
        if max_displacement is not None and not max_displacement > 0:
            raise ValueError(f"max_displacement must be positive, got {max_displacement!r}")
        self.max_displacement = max_displacement
        self.stop_requested: str | None = None
        self._previous = np.empty((0, 3))
        self._previous_cell = (b"", b"")  # box and tilt before the step, as bytes
        self._mapped = np.empty((0, 3))  # the step's start carried along with the cell

    @property
    def potentials(self) -> list[Potential]:
        return self.forcefield.potentials

    def attach(self, observer: Observer, interval: int = 1) -> None:
        """Call ``observer(sim)`` after every step divisible by ``interval``.

        Observers read ``sim.state`` and never write it; those that keep data
        copy it. A fresh run (step 0) also calls them once before the first
        step; a continued run does not, so no frame is written twice.

        Integrators ask for forces without the virial (it costs a quarter of
        the pair time); on steps where an observer will be called the force
        field computes it anyway, so ``sim.thermo()`` there costs no second
        evaluation. An observer with ``uses_virial = False`` (a progress bar,
        a checkpoint) does not ask for this.
        """
        if isinstance(interval, bool) or not isinstance(interval, int | np.integer) or interval < 1:
            raise ValueError(f"observer interval must be a positive integer, got {interval!r}")
        self._observers.append((observer, int(interval)))
        if not isinstance(observer, VirialUse) or observer.uses_virial:
            self._virial_intervals.append(int(interval))

    def request_stop(self, reason: str = "stop requested") -> None:
        """Ask :meth:`run` to return once the step in progress is complete.

        Safe to call from a signal handler: it only sets ``stop_requested``.
        """
        self.stop_requested = reason

    def skip_initial_observation(self) -> None:
        """Do not call observers before the first step (a run resumed from step 0)."""
        self._observed_start = True

    def run(self, n_steps: int) -> None:
        """Advance ``n_steps`` steps, or fewer if :meth:`request_stop` is called.

        Raises
        ------
        SimulationError
            If the energy or positions become NaN or infinite, or a particle
            moves farther than ``max_displacement`` in one step; the state is
            left at the failing step and observers have seen every step
            before it.

        Notes
        -----
        The run leaves the process's memory allocator as it is. The implicit
        integrators free and allocate arrays of 3N doubles every step, which
        glibc's defaults return to the kernel and page-fault in again (an
        implicit Euler step on 32000 atoms took 1.8 times as long, see
        :mod:`md._memory`); ``md run`` avoids this with
        :func:`md.keep_freed_memory`, which a program may call once itself.
        """
        if isinstance(n_steps, bool) or not isinstance(n_steps, int | np.integer) or n_steps < 0:
            raise ValueError(f"n_steps must be a non-negative integer, got {n_steps!r}")
        if self._engine is not None:
            return self._run_on_device(int(n_steps))
        state = self.state
        if state.step == 0 and not self._observed_start:
            self._guarded(
                lambda: self.forcefield.compute(state),
                state.step,
                hint="the starting configuration cannot be evaluated",
            )
            self._notify(all_observers=True)
            self._observed_start = True
        # The loop's per-step work in locals: a small box's step is tens of microseconds,
        # of which each attribute chain and call here would be a visible part.
        forcefield, integrator = self.forcefield, self.integrator
        intervals, timings = self._virial_intervals, self.timings
        clock = time.perf_counter
        # A run of this class (not a decomposed one, which overrides both) asks neither
        # per step: no stop to agree on beyond stop_requested, no communication to time.
        own = type(self)
        comm = None if own._comm_seconds is Simulation._comm_seconds else self._comm_seconds
        stopping = None if own._stopping is Simulation._stopping else self._stopping
        if not intervals:
            forcefield.virial_wanted = False
        for _ in range(int(n_steps)):
            if stopping is None:
                if self.stop_requested is not None:
                    break
            elif stopping():
                break
            spent = forcefield.timings  # _timed_elsewhere, inline
            before = spent["neighbor"] + spent["force"] + (0.0 if comm is None else comm())
            start = clock()
            limit = self.max_displacement
            if limit is not None:
                if self._previous.shape != state.positions.shape:
                    self._previous = np.empty_like(state.positions)
                np.copyto(self._previous, state.positions)
                self._previous_cell = (state.box.tobytes(), state.tilt.tobytes())
            upcoming = state.step + 1
            if intervals:
                forcefield.virial_wanted = any(upcoming % k == 0 for k in intervals)
            try:
                integrator.step(state, forcefield)
            except NonFiniteError as error:  # as _guarded, without a closure per step
                hint = "the dynamics blew up (is dt too large?)"
                raise SimulationError(upcoming, f"{error}; {hint}") from error
            if limit is not None:
                self._check_displacement(limit)
            elapsed = clock() - start
            spent = forcefield.timings
            elsewhere = spent["neighbor"] + spent["force"] + (0.0 if comm is None else comm())
            timings["integrate"] += elapsed - (elsewhere - before)
            if self._observers:
                self._notify(all_observers=False)
        self.forcefield.virial_wanted = False

    def _run_on_device(self, n_steps: int) -> None:
        """:meth:`run` on the device: the state comes back only before observers run."""
        state, engine = self.state, self._engine
        start = time.perf_counter()
        hint = "the starting configuration cannot be evaluated"
        self._guarded(lambda: engine.start(state), state.step, hint=hint)
        self.timings["integrate"] += time.perf_counter() - start
        try:
            if state.step == 0 and not self._observed_start:
                self._guarded(lambda: engine.pull(state), state.step, hint=hint)
                self._notify(all_observers=True)
                self._observed_start = True
            intervals = [interval for _, interval in self._observers]
            for _ in range(n_steps):
                if self._stopping():
                    break
                start = time.perf_counter()
                engine.step(state)
                if any(state.step % k == 0 for k in intervals):
                    self._guarded(lambda: engine.pull(state), state.step)
                    self.timings["integrate"] += time.perf_counter() - start
                    self._notify(all_observers=False)
                else:
                    self.timings["integrate"] += time.perf_counter() - start
        finally:
            self._guarded(lambda: engine.finish(state), state.step)

    def _stopping(self) -> bool:
        """Whether :meth:`run` stops before the next step (a decomposed run also agrees on
        it across ranks and moves atoms between them here)."""
        return self.stop_requested is not None

    def _check_displacement(self, limit: float) -> None:
        """Raise SimulationError if a particle moved farther than ``limit`` this step.

        If the cell changed (a barostat), each particle's old position is first
        carried along with the cell (``r M``, M the cell's deformation), so only
        the motion relative to the deformed cell counts; a deformation that by
        itself moved neighbours (up to the list radius apart) by more than
        ``limit`` relative to each other is reported as the barostat's doing.
        """
        state = self.state
        previous = self._previous
        if self._previous_cell != (state.box.tobytes(), state.tilt.tobytes()):
            box, tilt = (np.frombuffer(b, dtype=np.float64) for b in self._previous_cell)
            deformation = cell_deformation(box, tilt, state.box, state.tilt, state.pbc)
            self._check_cell_move(deformation, limit)
            if self._mapped.shape != previous.shape:
                self._mapped = np.empty_like(previous)
            previous = np.matmul(previous, deformation, out=self._mapped)
        moved2 = max_displacement2(state.positions, previous)
        if moved2 <= limit * limit:
            return
        step = state.step
        if not np.isfinite(moved2):
            raise SimulationError(
                step, "positions became NaN or infinite; the dynamics blew up (is dt too large?)"
            )
        distances = np.linalg.norm(state.positions - previous, axis=1)
        atom = int(np.argmax(distances))
        named = atom if state.ids is None else int(state.ids[atom])
        relative = " relative to the moving cell" if previous is not self._previous else ""
        raise SimulationError(
            step,
            f"atom {named} moved {distances[atom]:.4g} in one step{relative}, more than the "
            f"neighbour-list skin {limit:g}; the dynamics is blowing up "
            "(time step too large, or overlapping atoms?)",
        )

    def _check_cell_move(self, deformation, limit: float) -> None:
        """Raise SimulationError if the cell's deformation alone moved neighbours apart by
        more than ``limit`` (the strain times the neighbour-list radius)."""
        if not np.all(np.isfinite(deformation)):
            raise SimulationError(self.state.step, "the box became NaN or infinite")
        strain = float(np.linalg.norm(deformation - np.eye(3), ord=2))
        nl = self.forcefield.neighbor_list
        if nl is None or strain * nl.list_radius <= limit:
            return
        raise SimulationError(
            self.state.step,
            f"the barostat moved the box by {100 * strain:.3g}% in one step, which changes "
            f"the distance between neighbours {nl.list_radius:g} apart by "
            f"{strain * nl.list_radius:.3g}, more than the neighbour-list skin {limit:g}: the "
            "pressure coupling is far too strong; use a larger [barostat] tau",
        )

    @property
    def device_engine(self):
        """The engine that runs the steps on the device (a
        :class:`md.cuda.engine.DeviceEngine`: its list builds, sorts and launches), or None
        for ``device="cpu"``."""
        return self._engine

    def thermo(self) -> dict[str, float]:
        """Return potential, kinetic and total energy, temperature and pressure now.

        Energies in [energy], temperature in [temperature] (kB of ``units``),
        pressure and its tensor's components ``pxx`` ... ``pyz`` in
        [energy/length^3], ``volume`` [length^3] and the mass ``density``
        [mass/length^3]; also ``step`` and ``time``. With a
        thermostat, also ``conserved_energy`` (total plus the heat bath's
        energy); with rigid bonds, the temperature counts one degree of
        freedom fewer per bond and the pressure includes the constraint virial; with
        rigid bodies, their degrees of freedom and virial, and the
        ``translational_temperature`` and ``rotational_temperature``.
        """
        state = self.state
        engine = self._engine
        result = engine.result() if engine and engine.active else self.forcefield.compute(state)
        # Sums over atoms go through global_sum: over every rank in a decomposed run.
        kinetic = global_sum(kinetic_energy(state.velocities, state.masses))
        # Thermostats and constrained integrators (integrators/_thermostat.py) give their
        # degrees of freedom, the constraint virial and the heat bath's energy.
        integrator = self.integrator
        terms = (
            integrator.thermo_terms(state, result) if isinstance(integrator, ThermoTerms) else {}
        )
        n_dof = terms.get("n_dof", degrees_of_freedom(global_sum(state.n_atoms)))
        kinetic_temperature = 2.0 * kinetic / (n_dof * self.units.kB) if n_dof > 0 else 0.0
        virial = result.virial + terms["virial"] if "virial" in terms else result.virial
        volume = state.volume
        if volume > 0:
            tensor = (global_sum(kinetic_tensor(state.velocities, state.masses)) + virial) / volume
        else:
            tensor = np.full((3, 3), np.nan)
        mass = global_sum(float(np.sum(state.masses)))
        row = {
            "step": state.step,
            "time": state.time,
            "potential_energy": result.energy,
            "kinetic_energy": kinetic,
            "total_energy": result.energy + kinetic,
            "temperature": kinetic_temperature,
            "pressure": pressure(kinetic, virial, volume),
            "volume": volume,
            "density": mass / volume if volume > 0 else float("nan"),
            **tensor_components(tensor),
        }
        if "reservoir_energy" in terms:
            row["conserved_energy"] = row["total_energy"] + terms["reservoir_energy"]
        for name, (energy, n) in terms.get("kinetic_split", {}).items():  # rigid bodies
            row[f"{name}_temperature"] = 2.0 * energy / (n * self.units.kB) if n > 0 else 0.0
        return row

    def timing_summary(self) -> dict[str, float]:
        """Wall time [s] spent in force kernels, neighbour lists, integration and output."""
        return {
            "force": self.forcefield.timings["force"],
            "neighbor": self.forcefield.timings["neighbor"],
            "integrate": self.timings["integrate"],
            "output": self.timings["output"],
        }

    def _timed_elsewhere(self) -> float:
        """Seconds counted so far in the force field's sections and in communication, which
        the integrate and output sections leave out (so no time is counted twice)."""
        timings = self.forcefield.timings
        return timings["neighbor"] + timings["force"] + self._comm_seconds()

    def _comm_seconds(self) -> float:
        """Seconds spent communicating with other ranks (none in a one-process run)."""
        return 0.0

    def _notify(self, all_observers: bool) -> None:
        before = self._timed_elsewhere()
        start = time.perf_counter()
        step = self.state.step
        for observer, interval in self._observers:
            if all_observers or step % interval == 0:
                observer(self)
        elapsed = time.perf_counter() - start
        self.timings["output"] += elapsed - (self._timed_elsewhere() - before)

    @staticmethod
    def _guarded(action, step: int, hint: str = "the dynamics blew up (is dt too large?)"):
        try:
            return action()
        except NonFiniteError as error:
            raise SimulationError(step, f"{error}; {hint}") from error
