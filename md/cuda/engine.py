"""The device state and one time step on it: what ``Simulation(device="cuda")`` runs.

:class:`DeviceEngine` holds positions, velocities, forces, masses, types and the
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
    SUM_THREADS,
    _bath,
    _cell_of,
    _cell_starts,
    _drift,
    _gather,
    _gather_rows,
    _kick,
    _kick_drift,
    _kinetic_sum,
    _langevin_sums,
    _moved,
    _reduce_columns,
    _relax,
    _remember,
    _scale,
    _scatter,
    _search_all,
    _search_cells,
    _sort_cells,
    _sum_observables,
    _synchronise,
    angle_kernel,
    bond_kernel,
    launch,
    noise_kernel,
    pair_kernel,
)
from md.errors import NonFiniteError
from potentials.base import ForceResult
from potentials.device_terms import bonded_function, kind_of, pair_function

logger = logging.getLogger(__name__)

#: Partners of room per atom in a first list (regrown to the largest row when one overflows).
FIRST_ROOM = 64
#: Builds of the list between sorts of the atoms by cell (and one at the first build).
SORT_EVERY = 10
#: The per-atom arrays a sort moves (forces and observables are computed after it).
_PER_ATOM = ("positions", "velocities", "inverse_masses", "masses", "types", "ids", "sigmas")
_PER_ATOM += ("half",)


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
        Neighbour-list builds on the device.
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
        types = np.zeros(n, np.int32) if state.types is None else state.types.astype(np.int32)
        a = {
            "positions": cuda.to_device(np.ascontiguousarray(state.positions)),
            "velocities": cuda.to_device(np.ascontiguousarray(state.velocities)),
            "forces": cuda.device_array((n, 3)),
            "inverse_masses": cuda.to_device(1.0 / state.masses),
            "masses": cuda.to_device(np.ascontiguousarray(state.masses)),
            "types": cuda.to_device(types),
            "lengths": cuda.to_device(lengths),
            "inverse": cuda.to_device(inverse),
            "tilt": cuda.to_device(tilt),
            "reference": cuda.device_array((n, 3)),
            "counts": cuda.device_array(n, np.int32),
            "neighbors": cuda.device_array((self.room, n), np.int32),
            "flag": cuda.to_device(np.zeros(1, np.int32)),
            "observables": cuda.device_array((n, N_OBSERVABLES)),
            "totals": cuda.device_array(N_OBSERVABLES),
            "tables": [cuda.to_device(table) for _, table, _, _, _ in self.pairs],
            "data": [cuda.to_device(data) for _, _, _, data, _ in self.pairs],
        }
        a["bonded"] = [
            tuple(cuda.to_device(x) for x in (items, item_types, table, *_by_atom(items, n)))
            for _, _, _, items, item_types, table in self.bonded
        ]
        self.n_atoms = n
        # blocks of the sums: a few thousand atoms each, at most SUM_BLOCKS
        self.sum_blocks = min(SUM_BLOCKS, max(1, n // (16 * SUM_THREADS)))
        a["partial"] = cuda.device_array((self.sum_blocks, N_OBSERVABLES))
        self.perm = np.arange(n)  # device row d holds the user's atom perm[d]
        self.n_cells = _cell_grid(state, self.radius)
        self.use_cells = self.n_cells is not None and min(self.n_cells) >= 3
        if self.n_cells is not None:  # cells for the search, or only for sorting
            n_cells = int(np.prod(self.n_cells))
            a["n_cells"] = cuda.to_device(np.asarray(self.n_cells, np.int64))
            a["box"] = cuda.to_device(np.ascontiguousarray(state.box, np.float64))
            a["cells"] = cuda.device_array(n, np.int32)
            a["cell_counts"] = cuda.device_array(n_cells, np.int32)
            a["cell_starts"] = cuda.device_array(n_cells + 1, np.int32)
            a["cursors"] = cuda.device_array(n_cells, np.int32)
            a["order"] = cuda.device_array(n, np.int32)
        if self.kind in ("Langevin", "Bussi"):
            saved = self.integrator.get_state()
            self.bath = (float(saved["reservoir"]), int(saved["steps"]), 0)
            a["kinetic"] = cuda.device_array(1)
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
        self.n_sorts = 0
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
        state.positions[self.perm] = a["positions"].copy_to_host()
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
        """One step of the integrator on the device; advances ``state.step`` and ``time``."""
        a, dt = self.arrays, self.integrator.dt
        grid = launch(self.n_atoms)
        args = (a["positions"], a["velocities"], a["forces"], a["inverse_masses"])
        mark = self._mark
        mark("start")
        if self.kind == "Leapfrog":
            kick_dt = 0.5 * dt if self.restarting else dt
            half = a["half"]
            _kick_drift[grid](a["positions"], half, a["forces"], a["inverse_masses"], kick_dt, dt)
            mark("integrate")
            self._update()
            mark("neighbors")
            self._forces()
            mark("forces")
            _synchronise[grid](a["velocities"], half, a["forces"], a["inverse_masses"], 0.5 * dt)
            mark("integrate")
            if self.restarting:
                self.integrator.statistics["restarts"] += 1
            self.restarting = False
            self.integrator.statistics["steps"] += 1
        elif self.kind == "Langevin":
            self._langevin_step(state, grid)
        else:
            if self.kind == "Bussi":
                self._bussi_rescale(grid)
            _kick_drift[grid](*args, 0.5 * dt, dt)
            mark("integrate")
            self._update()
            mark("neighbors")
            self._forces()
            mark("forces")
            _kick[grid](a["velocities"], a["forces"], a["inverse_masses"], 0.5 * dt)
            if self.kind == "Bussi":
                self._bussi_rescale(grid)
                reservoir, steps, done = self.bath
                self.bath = (reservoir, steps, done + 1)
            mark("integrate")
        self.integrator.end_step(state)

    def _bussi_rescale(self, grid) -> None:
        """Bussi's half-step rescaling: the kinetic energy summed on the device (eight
        bytes to the host), the factor from the integrator's own stream
        (``Bussi.rescale_factor``, as its CPU step), the velocities scaled on the device."""
        a, bussi = self.arrays, self.integrator
        blocks = self.sum_blocks
        _kinetic_sum[blocks, SUM_THREADS](a["velocities"], a["masses"], a["partial"])
        _reduce_columns[1, 32](a["partial"], blocks, 1, a["kinetic"], 0)
        kinetic = float(a["kinetic"].copy_to_host()[0])
        c = math.exp(-0.5 * bussi.dt / bussi.tau)
        alpha = bussi.rescale_factor(kinetic, bussi.degrees_of_freedom(self.n_atoms), c)
        if alpha != 1.0:
            _scale[grid](a["velocities"], alpha)

    def _langevin_step(self, state, grid) -> None:
        """BAOAB as ``integrators.langevin.Langevin.step``: the noise of counter (step,
        atom id) under the integrator's key, the same numbers as the CPU path's."""
        a, half = self.arrays, 0.5 * self.integrator.dt
        mark = self._mark
        velocities, noise, masses, sums = a["velocities"], a["noise"], a["masses"], a["sums"]
        _kick[grid](velocities, a["forces"], a["inverse_masses"], half)  # B
        _drift[grid](a["positions"], velocities, half)  # A
        step = np.uint64(state.step + 1)
        self.noise_kernel[grid](*self.key, step, a["ids"], a["sigmas"], noise)  # O
        blocks, partial = self.sum_blocks, a["partial"]
        _langevin_sums[blocks, SUM_THREADS](velocities, noise, masses, partial, True)
        _reduce_columns[1, 32](partial, blocks, 5, sums, 0)
        _relax[grid](velocities, noise, self.relax[0], sums, self.relax[1])
        _langevin_sums[blocks, SUM_THREADS](velocities, noise, masses, partial, False)
        _reduce_columns[1, 32](partial, blocks, 1, sums, 5)
        _bath[1, 1](sums)
        _drift[grid](a["positions"], velocities, half)  # A
        mark("integrate")
        self._update()
        mark("neighbors")
        self._forces()
        mark("forces")
        _kick[grid](velocities, a["forces"], a["inverse_masses"], half)  # B
        mark("integrate")
        reservoir, steps, done = self.bath
        self.bath = (reservoir, steps, done + 1)

    def timed_step(self, state) -> dict[str, float]:
        """:meth:`step`, timed by CUDA events between its kernels: milliseconds spent in
        the integrator's passes, the list's check (and rebuild) and the force kernels."""
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
        blocks = self.sum_blocks
        _sum_observables[blocks, SUM_THREADS](
            a["observables"], a["velocities"], a["masses"], a["partial"]
        )
        _reduce_columns[1, 32](a["partial"], blocks, N_OBSERVABLES, a["totals"], 0)
        return a["totals"].copy_to_host()

    def _update(self) -> None:
        """Rebuild the list if an atom moved more than half the skin (decided on the device:
        only the flag crosses)."""
        a = self.arrays
        flag = a["flag"]
        _moved[launch(self.n_atoms)](a["positions"], a["reference"], self.half_skin**2, flag)
        if flag.copy_to_host()[0]:
            self._build()

    def _bin(self) -> None:
        """The counting sort of the atoms by cell: ``order`` the device rows cell by cell."""
        a = self.arrays
        grid = launch(self.n_atoms)
        counts = a["cell_counts"]
        counts.copy_to_device(np.zeros(counts.shape[0], np.int32))
        _cell_of[grid](a["positions"], a["box"], a["n_cells"], a["cells"], counts)
        _cell_starts[1, 1](counts, a["cell_starts"], a["cursors"])
        _scatter[grid](a["cells"], a["cell_starts"], a["cursors"], a["order"])
        _sort_cells[launch(counts.shape[0])](a["cell_starts"], a["order"])

    def _sort(self) -> None:
        """Put the device's rows in cell order (atoms near in space near in memory, as
        HOOMD-blue sorts them): every per-atom array gathered on the device, the bonds' and
        angles' atom numbers and rows renumbered on the host. Invisible: :meth:`pull` and
        :meth:`result` give the user's order (``perm``)."""
        a = self.arrays
        self._bin()
        order = a["order"].copy_to_host().astype(np.int64)
        grid = launch(self.n_atoms)
        for name in _PER_ATOM:
            if name in a:
                moved = cuda.device_array_like(a[name])
                gather = _gather_rows if len(a[name].shape) == 2 else _gather
                gather[grid](a[name], a["order"], moved)
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

    def _build(self) -> None:
        a = self.arrays
        n, grid = self.n_atoms, launch(self.n_atoms)
        if self.n_cells is not None and self.n_builds % SORT_EVERY == 0:
            self._sort()
        while True:
            a["flag"].copy_to_device(np.zeros(1, np.int32))
            geometry = (a["positions"], a["lengths"], a["inverse"], a["tilt"])
            if self.use_cells:
                self._bin()
                _search_cells[grid](
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
                _search_all[grid](*geometry, self.radius**2, a["neighbors"], a["counts"])
            _remember[grid](a["positions"], a["reference"], a["counts"], self.room, a["flag"])
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
            kernel[grid](
                a["positions"],
                a["types"],
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
            kernel[grid](*geometry, *arrays, a["forces"], a["observables"])


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
