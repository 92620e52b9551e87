"""ForceField: potentials summed over one neighbour list, with a result cache."""

from __future__ import annotations

import math
import time
from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp

from md.errors import NonFiniteError
from md.neighbors import NeighborList
from md.parallel import all_finite, copy_into, same_values
from md.state import State
from md.topology import Topology, combine
from potentials.base import (
    Bonded,
    BondedAngles,
    ForceResult,
    Potential,
    SupportsHessian,
    SupportsHessianOperator,
    SupportsKeptCall,
    SupportsMixedVerletStep,
    SupportsPrecision,
    SupportsVerletStep,
    check_precision_name,
)
from potentials.pair_hessian import HessianSum


class ForceField:
    """Sum of potentials evaluated over one shared neighbour list.

    The list is built at the largest potential cutoff plus ``skin``; each
    pair kernel still tests its own cutoff. :meth:`compute` returns the
    cached result while positions, box, periodicity and types equal those of the last
    call, so velocity Verlet costs one evaluation per step without managing
    a cache itself.

    Parameters
    ----------
    potentials : sequence of Potential
        Terms to sum.
    skin : float
        Neighbour-list skin [length].
    precision : {"double", "mixed"}
        ``"mixed"``: the pair potentials that offer it (``PRECISIONS`` lists
        ``"mixed"``: those of the pair-kernel frame) run their pair loop in
        float32, with double sums and results; the others (bonds, angles)
        stay double. The neighbour list is then built in the cluster-pair
        layout where the cell allows (:class:`md.neighbors.NeighborList`'s
        ``clusters``), whose kernels compute eight atom pairs per vector. See
        :meth:`potentials.PairPotential.energy_forces`.
    outer_skin : float, optional
        The cluster list's outer skin [length], passed to the
        :class:`~md.neighbors.NeighborList` (None: its default, 5 x ``skin``).
    neighbor_every, neighbor_check : int, bool
        The list's ``every`` and ``check`` (LAMMPS's ``neigh_modify``): 1 and True,
        the defaults, keep it exact; see :class:`~md.neighbors.NeighborList`.
    cache : bool
        Keep the last result (and a copy of the positions it belongs to) for a call at
        the same positions (the default). A caller that keeps its own, such as a
        decomposed run's ranks, turns it off: every call evaluates, and no positions
        are copied (a 10^6-atom rank copied 24 MB a step for a result it never asked
        for again).

    Attributes
    ----------
    timings : dict
        Accumulated wall time [s] in ``"neighbor"`` (list updates) and
        ``"force"`` (potential kernels).
    n_evaluations : int
        Number of evaluations that were not served from the cache.
    virial_wanted : bool
        Compute the virial even when a caller says it needs none; the
        Simulation sets it for steps whose end an observer will see.
    """

    def __init__(
        self,
        potentials: Sequence[Potential],
        skin: float = 0.3,
        precision: str = "double",
        outer_skin: float | None = None,
        neighbor_every: int = 1,
        neighbor_check: bool = True,
        cache: bool = True,
    ) -> None:
        self.potentials = list(potentials)
        if not self.potentials:
            raise ValueError("a ForceField needs at least one potential")
        self.precision = check_precision_name(precision)
        cutoffs = [p.cutoff for p in self.potentials if p.cutoff is not None]
        # mixed precision: the cluster-pair layout, whose kernels compute in float32 lanes
        clusters = self.precision == "mixed"
        self.neighbor_list = (
            NeighborList(
                max(cutoffs),
                skin,
                clusters,
                outer_skin=outer_skin,
                every=neighbor_every,
                check=neighbor_check,
            )
            if cutoffs
            else None
        )
        self.timings = {"neighbor": 0.0, "force": 0.0}
        self.n_evaluations = 0
        self.virial_wanted = False
        self._cached: ForceResult | None = None
        self._key: tuple[np.ndarray, ...] | None = None
        self._subsets: dict[tuple[int, ...], tuple[tuple, ForceResult]] = {}
        self.n_subset_evaluations = 0
        self.cache = bool(cache)

    @property
    def cutoff(self) -> float | None:
        return None if self.neighbor_list is None else self.neighbor_list.cutoff

    def check(self, state: State) -> None:
        """Raise ValueError if the potentials cannot act on ``state`` (types, box)."""
        for potential in self.potentials:
            potential.check(state)
            if self._options(potential):  # a precision it offers: can it hold the values?
                potential.check_precision(state, self.precision)
        if self.neighbor_list is not None:
            self.neighbor_list.check_box(state.box, state.pbc, state.tilt)

    def exclude_groups(self, groups) -> None:
        """Leave out of the neighbour list every pair of two atoms in one group (``groups``
        (N,), -1 for none; None: every pair again): see
        :meth:`md.neighbors.NeighborList.exclude_groups`. Potentials without a cutoff
        (bonds, angles) are not affected."""
        if self.neighbor_list is not None:
            self.neighbor_list.exclude_groups(groups)
        self.invalidate()

    def invalidate(self) -> None:
        """Forget the cached results (after changing a potential's parameters)."""
        self._cached = None
        self._key = None
        self._subsets.clear()

    def compute(self, state: State, per_atom: bool = False, virial: bool = True) -> ForceResult:
        """Return the total energy, forces and virial of ``state``.

        ``virial=False`` (integrators) lets potentials skip the virial, which
        costs about a quarter of the LJ pair time; the result's ``virial`` is
        then None, and a later call at the same positions that needs it
        evaluates again.

        Raises
        ------
        NonFiniteError
            If a position, the energy, a force or the virial is NaN or infinite.
        """
        cached = self._cached
        key = self._key
        fresh = None  # a small system's key of ``state`` as it is now, once made
        if cached is not None:
            if key[3] is not None and state.positions.size <= _BYTES_KEY_VALUES:
                # bytes against bytes (see _key_of): the key made for the comparison is
                # the one a fresh evaluation keeps (the evaluation changes none of it)
                fresh = self._key_of(state)
                same = fresh == key
            else:
                same = self._same_key(key, state)
            if same and (
                (not per_atom or cached.energies is not None)
                and (not virial or cached.virial is not None)
            ):
                return cached
        virial = virial or self.virial_wanted  # a fresh evaluation includes it if wanted
        total = self._evaluate(state, self.potentials, per_atom, virial)
        self.n_evaluations += 1
        if self.cache:
            self._cached = total
            self._key = fresh if fresh is not None else self._key_of(state, key)
        return total

    def verlet_step(
        self, state: State, kick_dt: float, drift_dt: float, threaded: bool = False
    ) -> int:
        """Velocity Verlet's step in one compiled call where it can be: return 0, 1 or 2.

        For one double-precision pair potential with a ``verlet_step`` method (the pair
        frame's: :meth:`potentials.PairPotential.verlet_step`) over the exact list while it
        holds, with no virial wanted and the forces of ``state`` cached (the last step's):
        v += kick_dt f/m with those forces, x += drift_dt v, the new forces, v += kick_dt
        f/m, and the new forces cached as :meth:`compute` would (counted in
        ``n_evaluations``, the calls' time in ``timings["force"]``): 2. When an atom moved
        more than half the skin, the list is rebuilt after the drift (its time in
        ``timings["neighbor"]``) and the forces and the last kick are a second compiled
        call: 2 too. 1: only the first kick and the drift were done (a value is not
        finite, or the rebuilt list is not one this call serves): :meth:`compute` and the
        last kick are the caller's, as in a step without this call. 0: nothing done (any
        other case, a subclass that overrides :meth:`compute` too): the caller makes the
        whole step. The same bits as the step made of :meth:`compute` and the kicks.

        In mixed precision over the exact cluster-pair list, the same with the pair
        potential's ``mixed_verlet_step`` (:meth:`potentials.PairPotential.mixed_verlet_step`:
        two threaded passes over the atoms around the cluster kernel, the first also
        writing this cache's copy of the positions), for a system of any size whose
        cache holds arrays (over 1000 atoms); where the pass finds an atom past the list's
        rule, the list's update takes the displacement it measured, and the forces and the
        last kick are the potential's second call (the positions not copied again): 2.
        ``threaded``: the caller's own passes would
        run on the threads (velocity Verlet's, from 32000 atoms): the double step, one
        serial call, is then not made (0).
        """
        potentials = self.potentials
        neighbor_list = self.neighbor_list
        cached, key = self._cached, self._key
        if (
            cached is None
            or len(potentials) != 1
            or self.virial_wanted
            or neighbor_list is None
            or type(self).compute is not ForceField.compute  # a subclass's compute is asked
        ):
            return 0
        if self.precision == "mixed":
            return self._mixed_verlet_step(state, kick_dt, drift_dt)
        if self.precision != "double" or threaded:
            return 0
        potential = potentials[0]
        fuses = _STEPS_VERLET.get(type(potential))
        if fuses is None:
            fuses = _STEPS_VERLET[type(potential)] = isinstance(potential, SupportsVerletStep)
        if not fuses or potential.cutoff is None:
            return 0
        step = potential.verlet_step
        check = neighbor_list.exact_check(state)
        if check is None or not self._same_key(key, state):  # the cached forces are state's
            return 0
        timings, clock = self.timings, time.perf_counter
        start = clock()
        served = step(state, neighbor_list, cached.forces, kick_dt, drift_dt, *check)
        if served is None:
            return 0
        code, result = served
        if code == 1:  # kicked and drifted, and an atom moved too far: the list's build
            middle = clock()
            timings["force"] += middle - start
            if not neighbor_list.update(state):
                return 1  # (not the list's verdict: compute and the last kick decide)
            start = clock()
            timings["neighbor"] += start - middle
            served = step(state, neighbor_list, None, kick_dt, drift_dt, None, 0.0)
            if served is None:
                return 1
            code, result = served
        timings["force"] += clock() - start
        if code != 0:
            return 1  # a value not finite: compute says what
        self.n_evaluations += 1
        if key[3] is not None:  # bytes: only the positions moved since the key matched
            self._key = (state.positions.tobytes(), *key[1:])
        else:
            self._key = self._key_of(state, key)
        self._cached = result
        return 2

    def pair_call(self, state: State) -> tuple | None:
        """The one compiled call :meth:`compute` of ``state`` without the virial makes while
        its list holds, for a caller that makes it itself (a decomposed rank's step):
        ``(kernel, arguments, energies, reference, allowed2)`` where this force field is
        one double-precision potential that hands its call out
        (:class:`potentials.base.SupportsKeptCall`) over the exact list in its build's
        cell (:meth:`md.neighbors.NeighborList.exact_check`); None otherwise.
        ``kernel(*arguments, forces)`` writes the forces (N, 3) and their energy into
        ``energies[0]``, the same bits as :meth:`compute`, for positions none of which is
        farther than ``sqrt(allowed2)`` from ``reference`` (else :meth:`compute` rebuilds
        the list first); valid until the list is built again (``neighbor_list.n_builds``)
        or a potential's parameters change. The finite checks are the caller's; nothing
        is cached or timed."""
        potentials, neighbor_list = self.potentials, self.neighbor_list
        if (
            len(potentials) != 1
            or self.precision != "double"
            or neighbor_list is None
            or potentials[0].cutoff is None
            or type(self).compute is not ForceField.compute  # a subclass's compute is asked
        ):
            return None
        potential = potentials[0]
        kept = _KEPT_CALLS.get(type(potential))
        if kept is None:
            kept = _KEPT_CALLS[type(potential)] = isinstance(potential, SupportsKeptCall)
        check = neighbor_list.exact_check(state) if kept else None
        call = None if check is None else potential.kept_call(state, neighbor_list)
        return None if call is None else (*call, *check)

    def _mixed_verlet_step(self, state: State, kick_dt: float, drift_dt: float) -> int:
        """:meth:`verlet_step` in mixed precision (its conditions but the precision met)."""
        key = self._key
        potential = self.potentials[0]
        step = _MIXED_STEPS.get(type(potential), False)
        if step is False:
            fused = isinstance(potential, SupportsMixedVerletStep)
            step = _MIXED_STEPS[type(potential)] = (
                type(potential).mixed_verlet_step if fused else None
            )
        if step is None or key[3] is not None or potential.cutoff is None:
            return 0  # (a small system's key is bytes: nothing to write the positions into)
        neighbor_list = self.neighbor_list
        check = neighbor_list.cluster_check(state)
        if check is None or not self._same_key(key, state):  # the cached forces are state's
            return 0
        clock = time.perf_counter
        start = clock()
        served = step(
            potential,
            state,
            neighbor_list,
            self._cached.forces,
            kick_dt,
            drift_dt,
            *check,
            key[0],
        )
        timings = self.timings
        middle = clock()
        timings["force"] += middle - start
        if served is None:
            return 0
        code, result = served
        if code == 1 and math.isfinite(result):
            # kicked and drifted, and an atom moved past the list's rule: its prune or
            # search, measured from the pass's own displacement (not measured again),
            # then the forces and the last kick in the potential's second call (the
            # positions are already in key[0]: not copied again)
            neighbor_list.update(state, result)
            start = clock()
            timings["neighbor"] += start - middle
            served = step(potential, state, neighbor_list, None, kick_dt, drift_dt, None, 0.0, None)
            timings["force"] += clock() - start
            code, result = (1, None) if served is None else served
        if code != 0:  # kicked and drifted: the list's update, compute and the kick are the
            self._cached = None  # caller's (compute says what is not finite); key[0] moved on
            return 1
        self.n_evaluations += 1
        self._cached = result  # key[0] holds the positions now; cell and types are the same
        return 2

    def _evaluate(self, state: State, potentials, per_atom: bool, virial: bool) -> ForceResult:
        """Sum ``potentials`` over the shared neighbour list (refreshed if one of them needs
        it), timing the list and the kernels; NonFiniteError for non-finite input, energy, forces
        or virial."""
        start = time.perf_counter()
        neighbor_list = self.neighbor_list
        # (one potential, the common case, asked directly: no generator per evaluation)
        listed = (
            potentials[0].cutoff is not None
            if len(potentials) == 1
            else any(p.cutoff is not None for p in potentials)
        )
        if neighbor_list is not None and listed:
            neighbor_list.update(state)
        elif not np.all(np.isfinite(state.positions)):
            raise NonFiniteError("particle positions are not finite")
        middle = time.perf_counter()
        if len(potentials) == 1 and self.precision == "double":
            p = potentials[0]
            results = [
                p.energy_forces(
                    state, neighbor_list if p.cutoff is not None else None, per_atom, virial=virial
                )
            ]
        else:
            results = [
                p.energy_forces(
                    state,
                    neighbor_list if p.cutoff is not None else None,
                    per_atom,
                    virial=virial,
                    **self._options(p),
                )
                for p in potentials
            ]
        total = results[0] if len(results) == 1 else _sum_results(results, per_atom)
        timings = self.timings
        timings["neighbor"] += middle - start
        timings["force"] += time.perf_counter() - middle
        # The energy, then every force and the virial: compiled passes over the forces
        # (no NaN or infinity among them), not numpy's sum (a microsecond a call at 108
        # atoms, on every step). Not a BLAS dot: OpenBLAS's threads (np.vdot) spin after
        # the call and took the cores from numba's threaded kernels (the 32000-atom melt
        # on 2 threads 5.5x slower).
        if not (
            math.isfinite(total.energy)
            and all_finite(total.forces)
            and (total.virial is None or math.isfinite(np.sum(total.virial)))
        ):
            _refuse_non_finite(total, potentials, results)
        return total

    def _options(self, potential) -> dict:
        """What ``potential`` is asked for beyond the protocol: ``precision`` when it is
        not double and the potential lists it in its ``PRECISIONS`` (others, such as
        bonds, are not asked: they run double). A run's potentials may be objects this
        force field was not built with (a decomposed run's local bonded terms). Whether a
        class meets ``SupportsPrecision`` is asked once, of its first instance here:
        ``isinstance`` with a runtime-checkable protocol took 9.5 us a call (Python 3.11),
        at every evaluation, on the calling thread alone."""
        if self.precision == "double":
            return {}
        offers = _OFFERS_PRECISIONS.get(type(potential))
        if offers is None:
            offers = _OFFERS_PRECISIONS[type(potential)] = isinstance(potential, SupportsPrecision)
        if offers and self.precision in potential.PRECISIONS:
            return {"precision": self.precision}
        return {}

    def compute_subset(self, state: State, which, virial: bool = False) -> ForceResult:
        """Return the energy and forces of the potentials ``which`` (indices) alone.

        For multiple time stepping (RESPA): the fast and the slow forces are
        evaluated apart over the one shared neighbour list, each cached while
        the positions stay the same. Counted in ``n_subset_evaluations``, not
        in ``n_evaluations``.

        Raises
        ------
        IndexError
            If an index names no potential.
        NonFiniteError
            If a position, the energy, a force or the virial is NaN or infinite.
        """
        which = tuple(int(i) for i in which)
        for i in which:
            if not 0 <= i < len(self.potentials):
                raise IndexError(
                    f"potential index {i} out of range (0..{len(self.potentials) - 1})"
                )
        held = self._subsets.get(which)
        if (
            held is not None
            and self._same_key(held[0], state)
            and (not virial or held[1].virial is not None)
        ):
            return held[1]
        total = self._evaluate(state, [self.potentials[i] for i in which], False, virial)
        self.n_subset_evaluations += 1
        if self.cache:
            self._subsets[which] = (self._key_of(state, held[0] if held else None), total)
        return total

    def hessian(self, state: State) -> sp.csr_matrix:
        """Return the (3N, 3N) Hessian of the total energy, the sum of the potentials'.

        Refreshes the neighbour list as :meth:`compute` does; not cached. The
        time is counted in ``timings["neighbor"]`` and ``timings["force"]``.
        Row and column 3 i + a is coordinate a of atom i [energy/length^2].

        Raises
        ------
        TypeError
            If a potential has no ``hessian`` method.
        NonFiniteError
            If a position is NaN or infinite.
        """
        return self.hessian_operator(state).tocsr()

    def hessian_operator(self, state: State) -> HessianSum:
        """Return the Hessian of the total energy as an operator, unassembled.

        A :class:`potentials.pair_hessian.HessianSum` with ``matvec``,
        ``diagonal``, ``nnz`` and ``tocsr``: potentials with a
        ``hessian_operator`` method (pair blocks, applied at about the cost of
        a force evaluation) contribute that, the others their sparse matrix.
        Errors and timings as for :meth:`hessian`.
        """
        for potential in self.potentials:
            if not isinstance(potential, SupportsHessian):
                raise TypeError(
                    f"potential {type(potential).__name__} has no hessian() method, "
                    "so the force field cannot provide second derivatives"
                )
        start = time.perf_counter()
        if self.neighbor_list is not None:
            self.neighbor_list.update(state)
        elif not np.all(np.isfinite(state.positions)):
            raise NonFiniteError("particle positions are not finite")
        middle = time.perf_counter()
        terms = []
        for potential in self.potentials:
            neighbors = self.neighbor_list if potential.cutoff is not None else None
            if isinstance(potential, SupportsHessianOperator):
                terms.append(potential.hessian_operator(state, neighbors))
            else:
                terms.append(sp.csr_matrix(potential.hessian(state, neighbors)))
        self.timings["neighbor"] += middle - start
        self.timings["force"] += time.perf_counter() - middle
        return HessianSum(terms)

    def topology(self, extra=()) -> Topology:
        """Return the bonds and angles of the bonded potentials (and ``extra`` parts) as
        one Topology.

        ``extra`` holds further ``(style, bonds, bond_types)`` parts, such as
        an integrator's constraints. Type names are the potentials'
        ``bond_style`` and ``angle_style`` (see :func:`md.topology.combine`).
        """
        parts = [
            (potential.bond_style, potential.bonds, potential.bond_types)
            for potential in self.potentials
            if isinstance(potential, Bonded)
        ]
        angle_parts = [
            (potential.angle_style, potential.angles, potential.angle_types)
            for potential in self.potentials
            if isinstance(potential, BondedAngles)
        ]
        return combine([*parts, *extra], angle_parts)

    @staticmethod
    def _key_of(state: State, old: tuple | None = None) -> tuple:
        """The inputs a result depends on, copied: positions, the cell's bytes (box, tilt
        and pbc) and types; positions and types into ``old``'s arrays where they fit (no
        fresh allocation per evaluation: at 10^6 atoms its page faults cost more than the
        copy). Up to ``_BYTES_KEY_VALUES`` coordinates, positions and types are held as
        their bytes (with shape and dtype) instead: a small system's copy and comparison
        then cost a fraction of a microsecond, not two."""
        positions, types = state.positions, state.types
        if positions.size <= _BYTES_KEY_VALUES:
            held = (positions.shape, positions.dtype, types.shape, types.dtype)
            box, tilt, pbc = state.box, state.tilt, state.pbc
            if type(box) is np.ndarray and type(tilt) is np.ndarray and type(pbc) is np.ndarray:
                cell = box.tobytes() + tilt.tobytes() + pbc.tobytes()  # _cell_bytes, inline
            else:
                cell = _cell_bytes(state)
            return (positions.tobytes(), cell, types.tobytes(), held)
        if (
            old is not None
            and old[3] is None
            and old[0].shape == positions.shape
            and old[2].shape == types.shape
        ):
            copy_into(old[0], np.ascontiguousarray(positions, dtype=old[0].dtype))
            np.copyto(old[2], types)
            held_positions, held_types = old[0], old[2]
        else:
            held_positions, held_types = positions.copy(), types.copy()
        return (held_positions, _cell_bytes(state), held_types, None)

    def _same_key(self, key: tuple, state: State) -> bool:
        positions, cell, types, held = key
        # The cell compared by its bytes: the same bits give the same result, and a
        # comparison of three-value arrays costs ~5 us in np.array_equal (three a step).
        # Positions first: after a step they differ, at the first value compared.
        if held is not None:  # a small system's bytes (see _key_of)
            now = state.positions
            return (
                positions == now.tobytes()
                and held[0] == now.shape
                and held[1] == now.dtype
                and cell == _cell_bytes(state)
                and types == state.types.tobytes()
                and held[2] == state.types.shape
                and held[3] == state.types.dtype
            )
        return (
            positions.shape == state.positions.shape
            and types.shape == state.types.shape
            and same_values(positions, state.positions)
            and cell == _cell_bytes(state)
            and same_values(types, state.types)
        )

    def _matches(self, state: State) -> bool:
        return self._same_key(self._key, state)


#: Most coordinates (3 N) whose force cache holds positions as bytes (see
#: ``ForceField._key_of``): beyond, copying them into bytes at every comparison costs more
#: than the compiled comparison of held arrays (4000 atoms: 4.0 us against 2.6).
_BYTES_KEY_VALUES = 3000
#: Per potential class, whether it meets ``SupportsPrecision`` (``ForceField._options``).
_OFFERS_PRECISIONS: dict[type, bool] = {}
#: Per potential class, whether it meets ``SupportsKeptCall`` (``ForceField.pair_call``).
_KEPT_CALLS: dict[type, bool] = {}
#: Per potential class, whether it meets ``SupportsVerletStep`` (``ForceField.verlet_step``).
_STEPS_VERLET: dict[type, bool] = {}
#: Per potential class, its ``mixed_verlet_step`` or None (``ForceField._mixed_verlet_step``).
_MIXED_STEPS: dict[type, object] = {}


def _cell_bytes(state: State) -> bytes:
    """The bytes of ``state``'s box, tilt and pbc: one comparison of a result's cell. Taken
    as the arrays hold them (a State's are float64, float64 and bool; another dtype only
    makes a cell look changed, and the result is computed again); values that are not
    arrays are converted first."""
    box, tilt, pbc = state.box, state.tilt, state.pbc
    if type(box) is np.ndarray and type(tilt) is np.ndarray and type(pbc) is np.ndarray:
        return box.tobytes() + tilt.tobytes() + pbc.tobytes()
    return (
        np.asarray(box, dtype=np.float64).tobytes()
        + np.asarray(tilt, dtype=np.float64).tobytes()
        + np.asarray(pbc, dtype=bool).tobytes()
    )


def _refuse_non_finite(total: ForceResult, potentials, results: list[ForceResult]) -> None:
    """Raise NonFiniteError naming what is not finite in ``total`` (the energy, a force or
    the virial) and the potential it came from; return if all of it is finite."""
    if not math.isfinite(total.energy):
        raise NonFiniteError(f"potential energy is {total.energy}")
    for field in ("forces", "virial"):
        values = getattr(total, field)  # the ForceResult field named by the loop
        if values is None or np.all(np.isfinite(values)):
            continue
        culprits = [
            potential
            for potential, result in zip(potentials, results, strict=True)
            if not np.all(np.isfinite(getattr(result, field)))
        ]
        culprit = culprits[0] if culprits else potentials[0]
        if field == "forces":
            atom = int(np.flatnonzero(~np.isfinite(values).all(axis=1))[0])
            found = f"the force on atom {atom} is {values[atom].tolist()}"
        else:
            found = f"the virial is {np.asarray(values).tolist()}"
        raise NonFiniteError(
            f"{found} while the potential energy ({total.energy:g}) is finite "
            f"({_name(culprit)}): forces and virial must be finite too (a parameter beyond "
            "double precision, or a potential whose force is not defined there?)"
        )


def _name(potential) -> str:
    """A potential's name for messages: its config type where it has one, else its class."""
    try:
        kind = potential.describe().get("type")
    except Exception:  # noqa: BLE001 (describe is optional in the Potential protocol)
        kind = None
    return f"potential {kind or type(potential).__name__}"


def _sum_results(results: list[ForceResult], per_atom: bool) -> ForceResult:
    return ForceResult(
        energy=sum(r.energy for r in results),
        forces=np.sum([r.forces for r in results], axis=0),
        virial=(
            np.sum([r.virial for r in results], axis=0)
            if all(r.virial is not None for r in results)
            else None
        ),
        energies=np.sum([r.energies for r in results], axis=0) if per_atom else None,
        virials=(
            np.sum([r.virials for r in results], axis=0)
            if per_atom and all(r.virials is not None for r in results)
            else None
        ),
    )
