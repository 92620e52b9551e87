"""The simulation of a decomposed run (:class:`DistributedSimulation`): every rank
builds it from the whole system and keeps its brick's atoms; the loop, the thermo
row, the minimiser and the observers run on every rank together.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from integrators.base import Distributable, Restartable, constraints_of
from md.distributed.bonded import longest_arm
from md.distributed.forcefield import BOND_SKINS, DistributedForceField
from md.distributed.grid import Grid, check_grid, choose_grid
from md.distributed.ranks import agree, mpi_ranks
from md.distributed.views import ForceFieldView, Gathered, GlobalView, IntegratorView
from md.errors import SimulationError
from md.minimize import minimize
from md.parallel import global_max, using_reductions
from md.simulation import Simulation
from md.state import State
from potentials.base import Bonded, BondedAngles

#: Stop requests as numbers, for the reduction that makes every rank see them.
_STOPS = {"SIGINT": 1.0, "SIGTERM": 2.0}
#: No positions: no step start before the last one is known.
_NONE = np.empty((0, 3))


class DistributedSimulation(Simulation):
    """A Simulation whose system is shared by the ranks of an MPI run.

    Every rank builds it from the same whole-system ``state`` (as every rank
    of ``mpiexec -n P md run`` builds the config's system) and keeps the atoms
    of its brick: ``sim.state`` is then this rank's part (``state.ids`` its
    atoms' ids) and ``sim.forcefield`` a :class:`DistributedForceField`.
    :meth:`run`, :meth:`thermo` and the observers are collective: every rank
    calls them together. Observers run on rank 0 only, and see the whole
    system gathered there, in its original atom order (:meth:`global_view`).

    Parameters
    ----------
    state, potentials, integrator, skin, units, max_displacement, threads, precision
        As for :class:`md.simulation.Simulation`; ``state`` is the whole system.
    ranks : MPIRanks, optional
        The ranks (default: :func:`mpi_ranks`).
    decomposition : sequence of three ints, optional
        Bricks along a, b and c (default: chosen from the rank count and the
        cell, :func:`md.distributed.grid.choose_grid`).
    balance_every, balance_threshold
        Dynamic load balancing, off by default (see
        :class:`DistributedForceField`): a balanced run's trajectory depends on
        the ranks' timings, so it is no longer repeatable bit for bit.

    Raises
    ------
    ValueError
        If the integrator cannot run decomposed (RATTLE, constraints, the
        implicit methods), a potential lists atoms in a way the ranks cannot
        share, or the bricks would be thinner than the ghost shell (naming
        the largest decomposition that fits).
    """

    def __init__(
        self,
        state: State,
        potentials,
        integrator,
        skin: float = 0.3,
        units="lj",
        max_displacement: float | None = None,
        threads: int | None = None,
        ranks=None,
        decomposition=None,
        precision: str = "double",
        balance_every: int = 0,
        balance_threshold: float = 1.05,
    ) -> None:
        ranks = ranks if ranks is not None else mpi_ranks()
        if ranks is None:
            raise ValueError("a DistributedSimulation needs several MPI ranks (run under mpiexec)")
        super().__init__(
            state,
            potentials,
            integrator,
            skin=skin,
            units=units,
            max_displacement=max_displacement,
            threads=threads,
            precision=precision,
        )
        refuse_undistributable(integrator, self.forcefield.potentials)
        self.ranks = ranks
        whole = self.forcefield
        arm = longest_arm(whole.potentials, state)
        pairs = whole.neighbor_list.list_radius if whole.neighbor_list is not None else 0.0
        bonds = arm + BOND_SKINS * skin if arm > 0 else 0.0
        reach = max(pairs, bonds)
        what = "cutoff + skin" if pairs >= bonds else f"the longest bond + {BOND_SKINS:g} skins"
        if decomposition is None:
            shape = choose_grid(ranks.n_ranks, state.box, state.tilt, state.pbc, reach, what)
        else:
            shape = tuple(int(p) for p in decomposition)
            if math.prod(shape) != ranks.n_ranks:
                raise ValueError(
                    f"decomposition {list(shape)} has {math.prod(shape)} bricks "
                    f"for {ranks.n_ranks} ranks"
                )
            check_grid(shape, state.box, state.tilt, state.pbc, reach, what)
        self.forcefield = DistributedForceField(
            whole.potentials,
            skin,
            ranks,
            Grid(shape),
            arm,
            precision=precision,
            balance_every=balance_every,
            balance_threshold=balance_threshold,
        )
        self._masses = state.masses.copy() if ranks.rank == 0 else None
        self._types = state.types.copy() if ranks.rank == 0 else None
        self.state = self._part(state, self.forcefield.domain.owner_of(state))
        self.forcefield.rebuild(self.state, migrate=False)
        self.forcefield.migrate_pending = False
        self.forcefield.reserve(self.state)

    @property
    def rank(self) -> int:
        return self.ranks.rank

    @property
    def grid(self) -> Grid:
        """The bricks now (load balancing moves the planes between them)."""
        return self.forcefield.domain.grid

    def _part(self, state: State, owners: NDArray[np.int64], slots=None) -> State:
        """This rank's atoms of the whole system ``state`` (those ``owners`` gives it), in
        increasing id, or in the order of their ``slots`` (rows on the rank) if given."""
        mine = self._mine(owners, slots)
        return State(
            positions=state.positions[mine],
            velocities=state.velocities[mine],
            masses=state.masses[mine],
            box=state.box,
            pbc=state.pbc,
            types=state.types[mine],
            type_names=state.type_names,
            step=state.step,
            time=state.time,
            tilt=state.tilt,
            ids=mine,
        )

    def attach(self, observer, interval: int = 1) -> None:
        """As :meth:`Simulation.attach`; the observer runs on rank 0 with the whole system."""
        super().attach(Gathered(observer), interval)

    def observe(self, observer) -> None:
        """Call ``observer`` now as an attached one would be (rank 0, whole system;
        collective)."""
        self.forcefield.steps_end()
        Gathered(observer)(self)

    def run(self, n_steps: int) -> None:
        """As :meth:`Simulation.run`, on every rank together."""
        self.forcefield.steps_end(forget=True)  # (the state may have changed since)
        try:
            with using_reductions(self.ranks):
                super().run(n_steps)
        finally:
            self.forcefield.steps_end()

    def thermo(self) -> dict[str, float]:
        """As :meth:`Simulation.thermo`, over the whole system (collective)."""
        self.forcefield.steps_end()  # (an observer's row, after a step: its calls agree)
        with using_reductions(self.ranks):
            return super().thermo()

    def minimize(self, fmax: float, max_steps: int = 10_000, **options):
        """:func:`md.minimize.minimize` of the whole system (collective); atoms migrate
        between its steps as in a run. Returns its MinimizeResult."""
        self.forcefield.steps_end()
        with using_reductions(self.ranks):
            return minimize(
                self.state,
                self.forcefield,
                fmax,
                max_steps,
                between_steps=self.redistribute,
                **options,
            )

    # -------------------------------------------------------------- the loop
    def request_stop(self, reason: str = "stop requested") -> None:
        """As :meth:`Simulation.request_stop`; every rank stops after the same step (the
        request is shared at the next force evaluation)."""
        super().request_stop(reason)
        self.forcefield.stop_code = _STOPS.get(reason, 3.0)

    def _stopping(self) -> bool:
        """Start a step on every rank alike, from what the last force evaluation shared:
        stop when any rank was asked to; else migrate and rebuild when the coming step
        could outrun the list (or the last build, forced inside a step, kept owners)."""
        forcefield = self.forcefield
        if forcefield.stop_seen:
            names = {value: name for name, value in _STOPS.items()}
            self.stop_requested = names.get(forcefield.stop_seen, "stop requested")
            return True
        migrating = forcefield.ahead > 1.0 or forcefield.migrate_pending
        if migrating:
            dt = self.integrator.dt  # (every integrator has one: the Integrator protocol)
            self._guarded(lambda: self._migrate(dt=dt), self.state.step)
        forcefield.start_step(self.state.positions, migrating)
        forcefield.step_begins()  # the integrator's calls, decided alike on every rank
        return False

    def _migrate(self, carried: dict | None = None, dt: float | None = None) -> dict:
        """Migrate atoms (with the integrator's per-atom state and ``carried``) and rebuild
        (ahead of a step of ``dt``, see :meth:`DistributedForceField.rebuild`). Collective."""
        integrator = self.integrator
        keys = self.per_atom_keys()
        saved = integrator.get_state() if keys else {}
        extra = {key: np.asarray(saved[key]) for key in keys if saved.get(key) is not None}
        carried = {**extra, **(carried or {})}
        moved = self.forcefield.rebuild(self.state, migrate=True, carried=carried, dt=dt)
        if extra:
            saved.update({key: moved[key] for key in extra})
            integrator.set_state(saved)
        return moved

    def redistribute(self, velocities: NDArray[np.float64]) -> NDArray[np.float64]:
        """Between two steps of a minimiser (FIRE): migrate, with its ``velocities``, when
        the next step could outrun the list; return the velocities of the atoms now owned.
        Collective."""
        forcefield = self.forcefield
        migrating = forcefield.ahead > 1.0 or forcefield.migrate_pending
        if migrating:
            key = ("minimizer", "velocities")
            velocities = self._migrate({key: velocities})[key]
        forcefield.start_step(self.state.positions, migrating)
        return velocities

    def _notify(self, all_observers: bool) -> None:
        """As :meth:`Simulation._notify`; the observers' calls come after a step, so the
        use of held results is agreed among the ranks again."""
        self.forcefield.steps_end()
        super()._notify(all_observers)

    def _check_displacement(self, limit: float) -> None:
        """The blow-up guard, over every rank: all stop if any atom moved too far."""
        error = None
        try:
            super()._check_displacement(limit)
        except SimulationError as caught:
            error = caught
        if global_max(0.0 if error is None else 1.0, self.ranks):
            agree(self.ranks, error)

    def timing_summary(self) -> dict[str, float]:
        """As :meth:`Simulation.timing_summary`, with the time spent communicating as a
        section of its own (halo exchange, reverse pass, migration, reductions, gathers):
        the other sections leave it out, so the sections add up to at most the wall time."""
        return {**super().timing_summary(), "comm": self.ranks.clock.seconds}

    def _comm_seconds(self) -> float:
        return self.ranks.clock.seconds

    # ------------------------------------------------------------ whole system
    def per_atom_keys(self) -> tuple[str, ...]:
        """The keys of the integrator's saved state that are per-atom arrays (Distributable)."""
        integrator = self.integrator
        return tuple(integrator.per_atom_state) if isinstance(integrator, Distributable) else ()

    def global_view(
        self, forces: bool = False, thermo: bool = True, layout: bool = False
    ) -> GlobalView | None:
        """The whole system gathered on rank 0, in its atom order (collective): a
        :class:`GlobalView` there, None on the other ranks.

        With ``layout`` (a checkpoint's gather: :class:`md.distributed.views.LayoutUse`)
        each atom's row also carries what a resume needs beyond the state: its last list
        build's position, its rank and its last two step starts (7 numbers more an atom);
        without it (a trajectory frame) the view's ``forcefield`` has no build positions
        and its ``decomposition`` no owners, slots or step starts."""
        state = self.state
        self.forcefield.steps_end()
        row = self.thermo() if thermo else None
        columns = [state.ids[:, None].astype(np.float64), state.positions, state.velocities]
        if forces:
            columns.append(self.forcefield.compute(state).forces)
        keys = self.per_atom_keys()
        saved = self.integrator.get_state() if isinstance(self.integrator, Restartable) else None
        shapes = []
        for key in keys:
            value = None if saved is None else saved.get(key)
            if value is not None:
                value = np.asarray(value, dtype=np.float64)
                shapes.append((key, value.shape[1:]))
                columns.append(value.reshape(state.n_atoms, -1))
        if layout:
            missing = np.full_like(state.positions, np.nan)
            reference = self.forcefield.reference
            if reference is None or reference.shape != state.positions.shape:
                reference = missing
            # The build positions, the rank, and the last two step starts, from which the
            # next steps' look-ahead measures (the step that follows a resume then decides
            # to migrate as the uninterrupted one).
            columns += [reference, np.full((state.n_atoms, 1), float(self.rank))]
            for kept in (self.forcefield.step_start, self.forcefield.step_before):
                columns.append(kept if kept.shape == state.positions.shape else missing)
        rows = self.ranks.gather_rows(np.concatenate(columns, axis=1))
        if rows is None:
            return None
        n = rows.shape[0]
        whole = np.empty_like(rows)
        whole[rows[:, 0].astype(np.int64)] = rows
        gathered = State(
            positions=whole[:, 1:4],
            velocities=whole[:, 4:7],
            masses=self._masses,
            box=state.box,
            pbc=state.pbc,
            types=self._types,
            type_names=state.type_names,
            step=state.step,
            time=state.time,
            tilt=state.tilt,
        )
        start = 7  # after id, positions and velocities
        gathered_forces = None
        if forces:
            gathered_forces, start = whole[:, 7:10].copy(), 10
        if saved is not None:
            saved = dict(saved)
            for key, shape in shapes:
                size = int(np.prod(shape))
                saved[key] = whole[:, start : start + size].reshape((n, *shape)).copy()
                start += size
        decomposition = {
            "grid": list(self.grid.shape),
            "cuts": [list(planes) for planes in self.grid.cuts],
            "bond_reach": self.forcefield.bond_reach,
            "migrate_pending": self.forcefield.migrate_pending,
            "ahead": self.forcefield.ahead,
        }
        reference = None
        if layout:
            reference = whole[:, start : start + 3].copy()
            owners = whole[:, start + 3].astype(np.int64)
            starts = [whole[:, start + 4 + 3 * k : start + 7 + 3 * k].copy() for k in (0, 1)]
            # Each atom's row on its rank: the gathered rows come rank after rank, each
            # rank's in its own order (a resume on this grid restores it, for the same bits).
            ranks = rows[:, start + 3].astype(np.int64)
            slots = np.empty(n, dtype=np.int64)
            slots[rows[:, 0].astype(np.int64)] = np.arange(n) - np.searchsorted(ranks, ranks)
            decomposition.update(
                owners=owners,
                slots=slots,
                # None where unknown (a migration since, or no step yet): NaN rows, all or
                # none
                step_start=None if np.isnan(starts[0]).any() else starts[0],
                step_before=None if np.isnan(starts[1]).any() else starts[1],
            )
        return GlobalView(
            state=gathered,
            row=row,
            integrator=IntegratorView(self.integrator, saved),
            forcefield=ForceFieldView(
                self.forcefield, gathered_forces, row, reference, decomposition
            ),
            units=self.units,
        )

    def light_view(self, thermo: bool = True) -> GlobalView | None:
        """Step, time and (with ``thermo``) the thermo row of the whole system, without the
        atoms (collective): a :class:`GlobalView` on rank 0 whose ``state`` is rank 0's
        part, None on the other ranks."""
        row = self.thermo() if thermo else None
        if self.rank != 0:
            return None
        return GlobalView(
            state=self.state, row=row, integrator=self.integrator, forcefield=None, units=self.units
        )

    def resume(self, state: State, reference, reference_cell=None, layout=None) -> None:
        """Continue from a checkpoint: ``state`` is its whole system, ``reference`` the
        positions of its last list build (``reference_cell`` that build's box and tilt),
        ``layout`` the decomposition it was written with, if any. The integrator's saved
        state must already be restored (whole-system arrays): it is cut here. Collective.

        On the grid and rank count that wrote it, the owners, the ghost shell and the
        list are those of the uninterrupted run, so the run continues bit for bit; on
        another, atoms go to the bricks holding their build positions, and the run agrees
        with the uninterrupted one to round-off.
        """
        forcefield = self.forcefield
        same = (
            layout is not None
            and list(layout.get("grid", [])) == list(self.grid.shape)
            and len(layout.get("owners", ())) == state.n_atoms
        )
        at_build = state.copy()
        if reference is not None:
            at_build.positions[:] = reference
            if reference_cell is not None:
                box, tilt = reference_cell
                at_build.box = np.array(box, dtype=np.float64)
                at_build.tilt = np.array(tilt, dtype=np.float64)
        if same and layout.get("cuts") is not None:  # planes moved by load balancing
            forcefield.domain.set_grid(Grid(self.grid.shape, layout["cuts"]))
        owners = (
            np.asarray(layout["owners"], dtype=np.int64)
            if same
            else forcefield.domain.owner_of(at_build)
        )
        slots = layout.get("slots") if same else None  # (checkpoints before it: by id)
        self.state = self._part(state, owners, slots)
        part_at_build = self._part(at_build, owners, slots)
        if same:
            forcefield.bond_reach = float(layout.get("bond_reach", forcefield.bond_reach))
        forcefield.invalidate()
        forcefield.rebuild(part_at_build, migrate=False)
        # The step starts the checkpoint kept (else none known): the look-ahead of the
        # steps that follow, hence when atoms migrate, is that of the uninterrupted run.
        forcefield.step_start, forcefield.step_before = (
            _NONE if kept is None else self._part_rows(kept, owners, slots)
            for kept in (
                layout.get("step_start") if same else None,
                layout.get("step_before") if same else None,
            )
        )
        self._localize_integrator()
        forcefield.refresh(self.state)
        # What the uninterrupted run's next step start would have seen.
        forcefield.migrate_pending = bool(layout.get("migrate_pending", False)) if same else False
        forcefield.ahead = float(layout.get("ahead", 0.0)) if same else 0.0

    def _mine(self, owners: NDArray[np.int64], slots=None) -> NDArray[np.int64]:
        """The ids of this rank's atoms (those ``owners`` gives it), in increasing id, or in
        the order of their ``slots`` (rows on the rank) if given."""
        mine = np.flatnonzero(owners == self.ranks.rank)
        if slots is not None:
            mine = mine[np.argsort(np.asarray(slots)[mine], kind="stable")]
        return mine

    def _part_rows(self, rows: NDArray, owners: NDArray[np.int64], slots=None) -> NDArray:
        """This rank's rows of the whole-system per-atom ``rows``, in :meth:`_part`'s order."""
        return np.ascontiguousarray(np.asarray(rows, dtype=np.float64)[self._mine(owners, slots)])

    def _localize_integrator(self) -> None:
        """Cut the integrator's whole-system per-atom state down to this rank's atoms."""
        keys = self.per_atom_keys()
        if not keys:
            return
        saved = self.integrator.get_state()
        changed = False
        for key in keys:
            value = saved.get(key)
            if value is not None and len(value) != self.state.n_atoms:
                saved[key] = np.asarray(value)[self.state.ids]
                changed = True
        if changed:
            self.integrator.set_state(saved)


def refuse_undistributable(integrator, potentials) -> None:
    """Raise ValueError if the integrator or a potential cannot run decomposed over ranks."""
    name = integrator.describe().get("type", type(integrator).__name__)
    if constraints_of(integrator) is not None:
        raise ValueError(
            f"rigid bonds (the {name} integrator's constraints) do not run decomposed over MPI "
            "ranks: run this config on one rank (without mpiexec)"
        )
    if not (isinstance(integrator, Distributable) and integrator.distributed):
        raise ValueError(
            f"the {name} integrator does not run decomposed over MPI ranks (its step needs "
            "the whole system at once, as the implicit methods' solves and XPBD's sweeps over "
            "the bonds do): run this config on one rank (without mpiexec), or choose another "
            "integrator"
        )
    for potential in potentials:
        if potential.cutoff is None and not isinstance(potential, Bonded | BondedAngles):
            raise ValueError(
                f"potential {type(potential).__name__} has no cutoff and lists no atoms, so "
                "the ranks cannot share it: run on one rank"
            )
