"""The device state and one time step on it: what ``Simulation(device="cuda")`` runs.

:class:`DeviceEngine` holds positions (with the types), velocities, forces, masses and the
neighbour list on the GPU for a whole :meth:`Simulation.run <md.simulation.Simulation.run>`
call: :meth:`start` uploads the host State (which a minimisation, a restored checkpoint or
the user may have changed between runs), :meth:`step` advances one step with nothing
crossing to the host but the list's rebuild flag (four bytes), :meth:`pull` copies
positions and velocities back for the observers (output, thermo, checkpoints), and
:meth:`result` gives the forces, energy and virial summed on the device.

Importing this module imports ``numba.cuda``; ``md.cuda.device_engine`` does so only for a
run that asks for the device.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numba import cuda

from integrators.langevin import noise_of_atom
from md.box import periodic_lengths, periodic_tilt
from md.cuda._kernels import (
    N_OBSERVABLES,
    SUM_BLOCKS,
    _cell_of,
    _cell_starts,
    _drift_check,
    _gather,
    _gather_rows,
    _kick,
    _kick_drift_check,
    _kick_scale_kinetic,
    _relax_bath,
    _remember,
    _scatter,
    _search_all,
    _search_cells,
    _sort_cells,
    _sum_observables,
    _synchronise,
    angle_kernel,
    bond_kernel,
    curve_ranks,
    launch,
    noise_kernel,
    pair_kernel,
    scan_threads,
    sum_threads,
)
from md.errors import NonFiniteError
from potentials.base import ForceResult
from potentials.device_terms import bonded_function, kind_of, pair_function

logger = logging.getLogger(__name__)

#: Partners of room per atom in a first list (regrown to the largest row when one overflows).
FIRST_ROOM = 64
#: Builds of the list between sorts of the atoms along the cells' Morton curve (and one at
#: the first build).
SORT_EVERY = 10
#: The per-atom arrays a sort moves (forces and observables are computed after it); the
#: positions carry the types in their fourth column.
_PER_ATOM = ("positions", "velocities", "inverse_masses", "masses", "ids", "sigmas", "half")


class DeviceEngine:
    """A force field's pair potentials and an integrator's step on the GPU.

    Parameters
    ----------
    state : State
        The system (its shape, types and box are fixed for the engine's life).
    forcefield : ForceField
        Its pair potentials, precision, cutoff and skin (checked by ``md.cuda.refusal``).
    integrator : VelocityVerlet or Leapfrog
        The step to run (its ``dt``; a leapfrog's half-step velocities are kept on the
        device and handed back with :meth:`pull` through its ``set_state``).

    Attributes
    ----------
    n_builds : int
        Neighbour-list builds on the device (over the engine's life: every run's).
    n_sorts : int
        Sorts of the device's rows along the cells' Morton curve (likewise).
    n_launches : int
        Kernel launches (likewise; a step's count is in docs/guide/gpu.md).
    sort_every : int
        Builds between sorts (:data:`SORT_EVERY`; the tests sort at every build).
    """

    def __init__(self, state, forcefield, integrator) -> None:
        self.forcefield = forcefield
        self.integrator = integrator
        self.kind = type(integrator).__name__
        nl = forcefield.neighbor_list
        self.radius = nl.cutoff + nl.skin
        self.half_skin = 0.5 * nl.skin
        n_types = max(state.n_types, 1)
        self.n_types = n_types
        self.pairs = [
            pair_function(p, n_types, forcefield.precision)
            for p in forcefield.potentials
            if kind_of(p) == "pair"
        ]
        self.bonded = [bonded_function(p) for p in forcefield.potentials if kind_of(p) != "pair"]
        self.kernels = None  # compiled on the first start
        self.active = False
        self.n_builds = 0
        self.n_sorts = 0
        self.n_launches = 0
        self.sort_every = SORT_EVERY
        self.room = FIRST_ROOM
        self.arrays: dict = {}
        self.events: list | None = None  # (name, CUDA event) while timed_step runs

    # ------------------------------------------------------------ the run's life
    def start(self, state) -> None:
        """Upload ``state`` and compute its forces on the device (start of a run)."""
        if self.kernels is None:
            self.kernels = [pair_kernel(pair, real) for pair, _, _, _, real in self.pairs]
            self.noise_kernel = noise_kernel(noise_of_atom) if self.kind == "Langevin" else None
            self.bonded_kernels = [
                (bond_kernel if kind == "bond" else angle_kernel)(term, params)
                for kind, term, params, _, _, _ in self.bonded
            ]
        n = state.n_atoms
        lengths, inverse = periodic_lengths(state.box, state.pbc)
        tilt = periodic_tilt(state.tilt, state.pbc)
        packed = np.empty((n, 4))  # the types in the fourth column (exact as doubles)
        packed[:, :3] = state.positions
        packed[:, 3] = 0.0 if state.types is None else state.types
        a = {
            "positions": cuda.to_device(packed),
            "velocities": cuda.to_device(np.ascontiguousarray(state.velocities)),
            "forces": cuda.device_array((n, 3)),
            "inverse_masses": cuda.to_device(1.0 / state.masses),
            "masses": cuda.to_device(np.ascontiguousarray(state.masses)),
            "lengths": cuda.to_device(lengths),
            "inverse": cuda.to_device(inverse),
            "tilt": cuda.to_device(tilt),
            "reference": cuda.device_array((n, 3)),
            "counts": cuda.device_array(n, np.int32),
            "neighbors": cuda.device_array((self.room, n), np.int32),
            "flag": cuda.to_device(np.zeros(1, np.int32)),
            "observables": cuda.device_array((n, N_OBSERVABLES)),
            "totals": cuda.device_array(N_OBSERVABLES),
            "counter": cuda.to_device(np.zeros(1, np.int32)),  # the sums' ticket
            "tables": [cuda.to_device(table) for _, table, _, _, _ in self.pairs],
            "data": [cuda.to_device(data) for _, _, _, data, _ in self.pairs],
        }
        a["bonded"] = [
            tuple(cuda.to_device(x) for x in (items, item_types, table, *_by_atom(items, n)))
            for _, _, _, items, item_types, table in self.bonded
        ]
        self.n_atoms = n
        # blocks of the sums (and the passes fused with them): a thread per atom, at most
        # SUM_BLOCKS blocks (then a few atoms a thread)
        self.sum_threads = sum_threads(n)
        self.sum_blocks = min(SUM_BLOCKS, (n + self.sum_threads - 1) // self.sum_threads)
        a["partial"] = cuda.device_array((self.sum_blocks, N_OBSERVABLES))
        self.perm = np.arange(n)  # device row d holds the user's atom perm[d]
        self.n_cells = _cell_grid(state, self.radius)
        self.use_cells = self.n_cells is not None and min(self.n_cells) >= 3
        if self.n_cells is not None:  # cells for the search, or only for sorting
            n_cells = int(np.prod(self.n_cells))
            a["n_cells"] = cuda.to_device(np.asarray(self.n_cells, np.int64))
            a["box"] = cuda.to_device(np.ascontiguousarray(state.box, np.float64))
            a["cells"] = cuda.device_array(n, np.int32)
            a["cell_counts"] = cuda.to_device(np.zeros(n_cells, np.int32))  # kept zeroed
            a["row_major"] = cuda.to_device(np.arange(n_cells, dtype=np.int32))
            a["curve"] = cuda.to_device(curve_ranks(self.n_cells))
            self.scan_threads = scan_threads(n_cells)
            a["cell_starts"] = cuda.device_array(n_cells + 1, np.int32)
            a["cursors"] = cuda.device_array(n_cells, np.int32)
            a["order"] = cuda.device_array(n, np.int32)
        if self.kind in ("Langevin", "Bussi"):
            saved = self.integrator.get_state()
            self.bath = (float(saved["reservoir"]), int(saved["steps"]), 0)
            a["kinetic"] = cuda.device_array(1)
            self.kinetic_ready = False  # a Bussi step leaves the next rescaling's sum here
        if self.kind == "Langevin":
            langevin = self.integrator
            c = math.exp(-langevin.friction * langevin.dt)
            sigmas = np.sqrt((1.0 - c * c) * langevin.kT / state.masses)
            ids = np.arange(n, dtype=np.int64) if state.ids is None else state.ids
            a["ids"] = cuda.to_device(np.ascontiguousarray(ids, dtype=np.int64))
            a["sigmas"] = cuda.to_device(sigmas)
            a["noise"] = cuda.device_array((n, 3))
            a["sums"] = cuda.to_device(np.zeros(7))
            self.relax = (c, bool(langevin.fix_com and n > 1))
            self.key = tuple(np.uint64(word) for word in langevin.key)
        if self.kind == "Leapfrog":
            saved = self.integrator.get_state()["half_velocities"]
            half = state.velocities if saved is None else saved
            a["half"] = cuda.to_device(np.ascontiguousarray(half))
            self.restarting = saved is None
        self.arrays = a
        self.active = True
        self._build()
        self._forces()

    def finish(self, state) -> None:
        """Copy the state back (end of a run); later calls compute on the CPU again."""
        if self.active:
            self.pull(state)
        self.active = False
        self.arrays = {}

    def pull(self, state) -> None:
        """Copy positions and velocities (and a leapfrog's half-step velocities) into
        ``state``'s arrays; NonFiniteError if they are no longer finite."""
        a = self.arrays
        state.positions[self.perm] = a["positions"].copy_to_host()[:, :3]
        state.velocities[self.perm] = a["velocities"].copy_to_host()
        if self.kind in ("Langevin", "Bussi"):  # the bath's energy and steps, as the CPU's
            reservoir, steps, done = self.bath
            saved = self.integrator.get_state()
            if self.kind == "Langevin":  # Bussi's is kept on the host (rescale_factor)
                saved["reservoir"] = reservoir + float(a["sums"].copy_to_host()[6])
            saved["steps"] = steps + done
            self.integrator.set_state(saved)
        if self.kind == "Leapfrog" and not self.restarting:
            saved = self.integrator.get_state()
            half = np.empty((self.n_atoms, 3))
            half[self.perm] = a["half"].copy_to_host()
            self.integrator.set_state({"half_velocities": half, "statistics": saved["statistics"]})
        if not (np.all(np.isfinite(state.positions)) and np.all(np.isfinite(state.velocities))):
            raise NonFiniteError("positions or velocities became NaN or infinite on the device")

    # ------------------------------------------------------------ one step
    def step(self, state) -> None:
        """One step of the integrator on the device; advances ``state.step`` and ``time``.

        Launches per step without a list rebuild (one pair potential, plus one per further
        potential): velocity Verlet and leapfrog 3, Bussi 4, Langevin 6; the host reads
        the rebuild flag (four bytes) and, for Bussi, two kinetic energies (eight bytes
        each)."""
        a, dt = self.arrays, self.integrator.dt
        grid = launch(self.n_atoms)
        go, mark = self._go, self._mark
        look = (a["reference"], self.half_skin**2, a["flag"])
        mark("start")
        if self.kind == "Leapfrog":
            kick_dt = 0.5 * dt if self.restarting else dt
            half, forces, inverse = a["half"], a["forces"], a["inverse_masses"]
            go(
                _kick_drift_check,
                grid,
                a["positions"],
                half,
                forces,
                inverse,
                1.0,
                kick_dt,
                dt,
                *look,
                True,
            )
            mark("integrate")
            self._update()
            mark("neighbors")
            self._forces()
            mark("forces")
            # the rows as they are now (a rebuild may have sorted them into new arrays)
            on_step = (a["velocities"], a["half"], a["forces"], a["inverse_masses"])
            go(_synchronise, grid, *on_step, 0.5 * dt)
            mark("integrate")
            if self.restarting:
                self.integrator.statistics["restarts"] += 1
            self.restarting = False
            self.integrator.statistics["steps"] += 1
        elif self.kind == "Langevin":
            self._langevin_step(state, grid, look)
        else:
            velocities, inverse = a["velocities"], a["inverse_masses"]
            alpha = self._bussi_factor() if self.kind == "Bussi" else 1.0
            kick = (a["forces"], inverse, alpha, 0.5 * dt, dt)
            go(_kick_drift_check, grid, a["positions"], velocities, *kick, *look, True)
            mark("integrate")
            self._update()
            mark("neighbors")
            self._forces()
            mark("forces")
            velocities, inverse = a["velocities"], a["inverse_masses"]  # as now (a sort)
            if self.kind == "Bussi":  # the kick and the sum of the second rescaling, then it
                sums = (self.sum_blocks, self.sum_threads)
                totals = (a["partial"], a["counter"], a["kinetic"])
                physics = (velocities, a["forces"], inverse, a["masses"])
                go(_kick_scale_kinetic, sums, *physics, 0.5 * dt, 1.0, *totals)
                self.kinetic_ready = True
                go(_kick_scale_kinetic, sums, *physics, 0.0, self._bussi_factor(), *totals)
                self.kinetic_ready = True  # the next step's first rescaling's sum
                reservoir, steps, done = self.bath
                self.bath = (reservoir, steps, done + 1)
            else:
                go(_kick, grid, velocities, a["forces"], inverse, 0.5 * dt)
            mark("integrate")
        self.integrator.end_step(state)

    def _bussi_factor(self) -> float:
        """Bussi's half-step rescaling factor: the kinetic energy summed on the device
        (eight bytes to the host; left by the pass before it, else summed here), the
        factor from the integrator's own stream (``Bussi.rescale_factor``, as its CPU
        step). The caller's next pass scales the velocities by it."""
        a, bussi = self.arrays, self.integrator
        if not self.kinetic_ready:
            sums = (self.sum_blocks, self.sum_threads)
            physics = (a["velocities"], a["velocities"], a["inverse_masses"], a["masses"])
            self._go(_kick_scale_kinetic, sums, *physics, 0.0, 1.0, *self._totals_of("kinetic"))
        self.kinetic_ready = False
        kinetic = float(a["kinetic"].copy_to_host()[0])
        c = math.exp(-0.5 * bussi.dt / bussi.tau)
        return bussi.rescale_factor(kinetic, bussi.degrees_of_freedom(self.n_atoms), c)

    def _totals_of(self, name: str) -> tuple:
        """The arguments a fused sum ends with: its blocks' rows, the ticket, the result."""
        a = self.arrays
        return a["partial"], a["counter"], a[name]

    def _langevin_step(self, state, grid, look) -> None:
        """BAOAB as ``integrators.langevin.Langevin.step``: the noise of counter (step,
        atom id) under the integrator's key, the same numbers as the CPU path's."""
        a, half = self.arrays, 0.5 * self.integrator.dt
        go, mark = self._go, self._mark
        velocities, noise, masses = a["velocities"], a["noise"], a["masses"]
        kick = (a["forces"], a["inverse_masses"], 1.0, half, half)
        go(_kick_drift_check, grid, a["positions"], velocities, *kick, *look, False)  # B, A
        step = np.uint64(state.step + 1)
        sums, totals = (self.sum_blocks, self.sum_threads), self._totals_of("sums")
        # O: the noise and its momentum, the velocities relaxed, the bath's energy booked
        go(
            self.noise_kernel,
            sums,
            *self.key,
            step,
            a["ids"],
            a["sigmas"],
            noise,
            velocities,
            masses,
            *totals,
        )
        go(_relax_bath, sums, velocities, noise, masses, *self.relax, *totals)
        go(_drift_check, grid, a["positions"], velocities, half, *look)  # A
        mark("integrate")
        self._update()
        mark("neighbors")
        self._forces()
        mark("forces")
        kick = (a["velocities"], a["forces"], a["inverse_masses"])  # as now (a sort)
        go(_kick, grid, *kick, half)  # B
        mark("integrate")
        reservoir, steps, done = self.bath
        self.bath = (reservoir, steps, done + 1)

    def timed_step(self, state) -> dict[str, float]:
        """:meth:`step`, timed by CUDA events between its kernels: milliseconds spent in
        the integrator's passes (the list's displacement check fused into them), the
        read of the rebuild flag with any rebuild, and the force kernels."""
        self.events = []
        try:
            self.step(state)
        finally:
            events, self.events = self.events, None
        events[-1][1].synchronize()
        split: dict[str, float] = {}
        for (_, before), (name, after) in zip(events, events[1:], strict=False):
            split[name] = split.get(name, 0.0) + before.elapsed_time(after)
        return split

    def _go(self, kernel, grid, *arguments) -> None:
        """Launch ``kernel`` over ``grid`` (counted in :attr:`n_launches`)."""
        kernel[grid](*arguments)
        self.n_launches += 1

    def _mark(self, name: str) -> None:
        """Record a CUDA event after the kernels so far (only in :meth:`timed_step`)."""
        if self.events is not None:
            event = cuda.event()
            event.record()
            self.events.append((name, event))

    def result(self) -> ForceResult:
        """Energy, forces and virial of the device's configuration (summed on the device)."""
        totals = self._totals()
        xx, yy, zz, yz, xz, xy = totals[1:7]
        virial = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
        forces = np.empty((self.n_atoms, 3))
        forces[self.perm] = self.arrays["forces"].copy_to_host()
        return ForceResult(energy=float(totals[0]), forces=forces, virial=virial)

    def kinetic_energy(self) -> float:
        return float(self._totals()[7])

    # ------------------------------------------------------------ helpers
    def _totals(self) -> np.ndarray:
        a = self.arrays
        sums = (self.sum_blocks, self.sum_threads)
        physics = (a["observables"], a["velocities"], a["masses"])
        self._go(_sum_observables, sums, *physics, *self._totals_of("totals"))
        return a["totals"].copy_to_host()

    def _update(self) -> None:
        """Rebuild the list if an atom moved more than half the skin (decided on the device,
        by the integrator's pass before: only the flag crosses)."""
        if self.arrays["flag"].copy_to_host()[0]:
            self._build()

    def _bin(self, rank: str = "row_major") -> None:
        """The counting sort of the atoms by cell: ``order`` the device rows cell by cell,
        the cells in row-major order (the search's) or along the Morton curve
        (``rank="curve"``, a sort's); the counts are left zeroed for the next one."""
        a, go = self.arrays, self._go
        grid = launch(self.n_atoms)
        counts = a["cell_counts"]
        go(_cell_of, grid, a["positions"], a["box"], a["n_cells"], a[rank], a["cells"], counts)
        go(_cell_starts, (1, self.scan_threads), counts, a["cell_starts"], a["cursors"])
        go(_scatter, grid, a["cells"], a["cell_starts"], a["cursors"], a["order"])
        go(_sort_cells, launch(counts.shape[0]), a["cell_starts"], a["order"])

    def _sort(self) -> None:
        """Put the device's rows in the order of their cells along a Morton curve (atoms near
        in space near in memory, as HOOMD-blue sorts them along a Hilbert curve), each
        cell's atoms in their former order: every per-atom array gathered on the device,
        the bonds' and angles' atom numbers and rows renumbered on the host. Invisible:
        :meth:`pull` and :meth:`result` give the user's order (``perm``)."""
        a = self.arrays
        self._bin("curve")
        order = a["order"].copy_to_host().astype(np.int64)
        grid = launch(self.n_atoms)
        for name in _PER_ATOM:
            if name in a:
                moved = cuda.device_array_like(a[name])
                gather = _gather_rows if len(a[name].shape) == 2 else _gather
                self._go(gather, grid, a[name], a["order"], moved)
                a[name] = moved
        self.perm = self.perm[order]
        row = np.empty(self.n_atoms, np.int64)
        row[self.perm] = np.arange(self.n_atoms)  # the device row of each user atom
        a["bonded"] = [
            tuple(
                cuda.to_device(x)
                for x in (row[items], item_types, table, *_by_atom(row[items], self.n_atoms))
            )
            for _, _, _, items, item_types, table in self.bonded
        ]
        self.n_sorts += 1
        self.kinetic_ready = False  # a sum over the rows in their new order, as a fresh one

    def _build(self) -> None:
        a = self.arrays
        n, grid = self.n_atoms, launch(self.n_atoms)
        if self.n_cells is not None and self.n_builds % self.sort_every == 0:
            self._sort()
        while True:
            a["flag"].copy_to_device(np.zeros(1, np.int32))
            geometry = (a["positions"], a["lengths"], a["inverse"], a["tilt"])
            if self.use_cells:
                self._bin()
                self._go(
                    _search_cells,
                    grid,
                    *geometry,
                    a["n_cells"],
                    a["cells"],
                    a["cell_starts"],
                    a["order"],
                    self.radius**2,
                    a["neighbors"],
                    a["counts"],
                )
            else:
                list_ = (a["neighbors"], a["counts"])
                self._go(_search_all, grid, *geometry, self.radius**2, *list_)
            remembered = (a["reference"], a["counts"], self.room, a["flag"])
            self._go(_remember, grid, a["positions"], *remembered)
            self.n_builds += 1
            if not a["flag"].copy_to_host()[0]:
                return
            self.room = int(a["counts"].copy_to_host().max()) + 8
            logger.debug("device neighbour list: room regrown to %d partners", self.room)
            a["neighbors"] = cuda.device_array((self.room, n), np.int32)

    def _forces(self) -> None:
        a = self.arrays
        grid = launch(self.n_atoms)
        for index, (kernel, (_, _, mode, _, _)) in enumerate(
            zip(self.kernels, self.pairs, strict=True)
        ):
            self._go(
                kernel,
                grid,
                a["positions"],
                self.n_types,
                a["neighbors"],
                a["counts"],
                a["lengths"],
                a["inverse"],
                a["tilt"],
                a["tables"][index],
                mode,
                a["data"][index],
                index > 0,
                a["forces"],
                a["observables"],
            )
        geometry = (a["positions"], a["lengths"], a["inverse"], a["tilt"])
        for kernel, arrays in zip(self.bonded_kernels, a["bonded"], strict=True):
            self._go(kernel, grid, *geometry, *arrays, a["forces"], a["observables"])


def _by_atom(items: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Each atom's tuples (bonds or angles) as CSR ``(starts, entries)``: an entry is
    ``width * t + place``, tuple t with the atom at ``place``, in tuple order per atom."""
    atoms = items.reshape(-1)
    codes = np.arange(atoms.shape[0], dtype=np.int64)  # = width * t + place, row-major
    order = np.argsort(atoms, kind="stable")
    starts = np.zeros(n + 1, np.int64)
    np.cumsum(np.bincount(atoms, minlength=n), out=starts[1:])
    return starts, np.ascontiguousarray(codes[order])


def _cell_grid(state, radius: float) -> tuple[int, int, int] | None:
    """The cells of at least ``radius`` along each axis of an orthorhombic cell periodic
    along every axis (the cell search serves where each has three or more; sorting by
    cell, wherever there are any); None for other cells."""
    if not (np.all(state.pbc) and np.all(state.tilt == 0.0)):
        return None
    return tuple(max(1, int(length // radius)) for length in state.box)
