"""The force field of one rank of a decomposed run (:class:`DistributedForceField`).

A rank evaluates its local system (owned atoms and ghosts, :mod:`md.distributed.halo`)
with an ordinary :class:`md.forcefield.ForceField`. Its neighbour list keeps only
the pairs whose designated atom it owns (the lower id when the ids' sum is even,
the higher when odd: :meth:`md.neighbors.NeighborList.keep_owned`, searched over the
owned atoms' rows only: no pair of two ghosts is a candidate, no ghost has a row for the
pair kernels to walk), so every pair is evaluated once in the whole run; each bond
(angle) is evaluated by the owner of its first atom (vertex), with its partners' nearest
copies. The ghosts' forces go back to their owners (newton on), and the energy and
virial are sums over the ranks. The list is rebuilt when the largest move of any atom
since the last build exceeds skin/2 (a global maximum); atoms migrate at rebuilds taken
between steps, and the ghosts and list are laid out where the step is expected to take
the atoms.
"""

from __future__ import annotations

import copy
import math
import time

import numpy as np
from numpy.typing import NDArray

from md.box import (
    cell_matrix,
    periodic_tilt,
)
from md.distributed._domain_kernels import (
    moved_since,
    predicted_positions,
)
from md.distributed._verlet_kernels import closing_kick, gather_reverse_kick, step_out
from md.distributed.balance import LoadBalance
from md.distributed.bonded import BondedShare
from md.distributed.grid import Grid
from md.distributed.halo import AGREED_STRAY, Domain
from md.distributed.ranks import agree, gather_folded
from md.errors import DecompositionError, NonFiniteError
from md.forcefield import ForceField
from md.neighbors import largest_displacement2
from md.parallel import chunk_count, copied, copy_into, global_max, same_values
from md.state import State
from md.topology import Topology
from potentials.base import ForceResult

#: A step starts with a rebuild (and migration) when some atom's next move could take it
#: past the list's limit (``moved_since`` of ``_domain_kernels`` bounds each atom's next
#: move from its last two) with this many times the last step's largest move to spare.
LOOKAHEAD = 0.05
#: Ghost shell beyond the longest bond, in skins: the bonds of the last build may
#: stretch by a skin before the next, plus the slack of a rebuild forced inside a step.
BOND_SKINS = 2.5
#: Fewest atoms per thread worth a chunk of their own in the displacement pass.
_MIN_PASS_ATOMS = 16_000
#: The identity, for a cell that has not changed since the build.
_IDENTITY = np.eye(3)
#: No positions: no step start before the last one is known.
_NONE = np.empty((0, 3))


class DistributedForceField:
    """The force field of one rank of a decomposed run (the interface of ForceField).

    ``compute(state)`` takes this rank's owned atoms (``state.ids``: their
    global ids) and returns their forces, with the energy and virial of the
    whole system; results are cached while the owned positions and the cell
    stay the same. It is collective: every rank calls it at the same point.

    Parameters
    ----------
    potentials : sequence of Potential
        The whole system's potentials (bonded ones over global atom ids).
    skin : float
        Neighbour-list skin [length].
    ranks : MPIRanks
    grid : Grid
    bond_reach : float
        The longest bond (or angle arm) of the starting state [length].
    precision : {"double", "mixed"}
        Of the local force field's pair loops (see :class:`md.forcefield.ForceField`).

    Attributes
    ----------
    local : ForceField
        The force field of the rank's local system (owned atoms and ghosts);
        its neighbour list is ``neighbor_list``.
    timings : dict
        Seconds in ``"neighbor"`` (the list's checks and rebuilds, bonded items
        found) and ``"force"`` (the local kernels). The time spent
        communicating (ghost positions out and forces back, migration, the
        ghost search's messages, reductions) is not in them: it is
        ``ranks.clock.seconds``, as its own section.
    migrate_pending : bool
        The last build kept owners (it was forced inside a step): the next
        step start migrates.
    balance_every, balance_threshold
        Dynamic load balancing (off where ``balance_every`` is 0): ``balance``, its
        :class:`md.distributed.balance.LoadBalance`, which the migrations ask.
    imbalance, balances
        The busiest rank's busy seconds over the mean at the last check; how many
        checks moved the planes.
    """

    def __init__(
        self,
        potentials,
        skin: float,
        ranks,
        grid: Grid,
        bond_reach: float,
        precision: str = "double",
        balance_every: int = 0,
        balance_threshold: float = 1.05,
    ) -> None:
        self.potentials = list(potentials)
        self.ranks = ranks
        self.skin = float(skin)
        # its results are this object's to keep (cached per owned positions, _cache)
        self.local = ForceField(self.potentials, skin, precision=precision, cache=False)
        self.precision = self.local.precision
        self.neighbor_list = self.local.neighbor_list
        self.domain = Domain(ranks, grid)
        self.timings = {"neighbor": 0.0, "force": 0.0}
        self.n_evaluations = 0
        self.n_subset_evaluations = 0
        self.n_builds = 0
        self.virial_wanted = False
        self.migrate_pending = False
        #: Set by the simulation at each step start: the look-ahead measures from there.
        self.step_start = np.empty((0, 3))
        #: The step start before that (empty when atoms migrated in between).
        self.step_before = np.empty((0, 3))
        #: A stop request of this rank (1 SIGINT, 2 SIGTERM, 3 other), shared at the next
        #: evaluation; ``stop_seen`` and ``ahead`` are the largest over the ranks there.
        self.stop_code = 0.0
        self.stop_seen = 0.0
        self.ahead = 0.0
        #: The bonded terms' items and this rank's share of them.
        self.bonded = BondedShare(self.potentials)
        self.bond_reach = float(bond_reach)
        self.reference: NDArray[np.float64] | None = None
        self._reference_memory = np.empty((0, 3))  # (reference is a view of its first rows)
        self._ahead: State | None = None  # (the state a build lays out a step ahead)
        self.reference_cell: tuple | None = None
        self._cell_bytes: tuple = ()
        self._cache: dict = {}
        self._exchanged: tuple | None = None
        # The loop's steps (see step_begins): whether a call is inside one, the cache keys
        # called in it so far, whether a step's first call finds the atoms where the last
        # step's evaluation left them on every rank (None: not known yet), and this
        # rank's observation of that, shared at the next reduction.
        self._in_step = False
        self._called: set = set()
        self.steady: bool | None = None
        self._steady_keys: frozenset = frozenset()
        self._evaluated_in_step: set = set()  # keys whose last evaluation was in a step
        self._reported: set = set()  # keys observed since the last reduction
        self._moved_report = -1.0  # -1: nothing observed since the last reduction
        #: The one reduction of an evaluation: error, energy, virial (9), list outrun,
        #: look-ahead, stop request, non-finite positions, the step's first calls' moves,
        #: and a step start's build's outcome (failed, longest bond: see rebuild).
        self._values = np.zeros(18)
        self._worst = np.zeros(7)
        self._totals = np.zeros(11)
        self._gathered = np.zeros((ranks.n_ranks, 18))  # (verlet_step's reduction)
        self._fused: tuple | None = None  # (what verlet_step keeps a build: _fused_step)
        self._build_outcome: tuple | None = None  # (longest bond, this rank's error)
        self.balance = LoadBalance(balance_every, balance_threshold)
        self.balance_every, self.balance_threshold = self.balance.every, self.balance.threshold

    @property
    def cutoff(self) -> float | None:
        return self.local.cutoff

    @property
    def imbalance(self) -> float:
        return self.balance.imbalance

    @property
    def balances(self) -> int:
        return self.balance.balances

    @property
    def reach(self) -> float:
        """The ghost shell a build needs: the list radius, or the longest bond plus skins."""
        cutoff = self.cutoff  # (a property: asked once)
        pairs = cutoff + self.skin if cutoff is not None else 0.0
        bonds = self.bond_reach + BOND_SKINS * self.skin if self.bonded.listed else 0.0
        return max(pairs, bonds)

    def check(self, state: State) -> None:
        """Nothing to check per rank: the whole system was checked before it was cut."""

    def invalidate(self) -> None:
        """Forget cached results (and which positions the ghosts hold, and the local pair
        call: a potential's parameters may have changed)."""
        self._cache.clear()
        self._fused = None
        self._exchanged = None
        self.steps_end(forget=True)

    def topology(self, extra=()) -> Topology:
        """The whole system's bonds and angles (as :meth:`ForceField.topology`)."""
        return ForceField(self.potentials).topology(extra)

    def hessian_operator(self, state: State):
        raise NotImplementedError("second derivatives are not available in a decomposed run")

    def hessian(self, state: State):
        raise NotImplementedError("second derivatives are not available in a decomposed run")

    # ------------------------------------------------------------------ results
    def compute(self, state: State, per_atom: bool = False, virial: bool = True) -> ForceResult:
        """Forces on ``state``'s (owned) atoms; energy and virial of the whole system."""
        return self._result(state, None, per_atom, virial)

    def compute_subset(self, state: State, which, virial: bool = False) -> ForceResult:
        """As :meth:`ForceField.compute_subset`, over the ranks."""
        which = tuple(int(i) for i in which)
        for i in which:
            if not 0 <= i < len(self.potentials):
                raise IndexError(
                    f"potential index {i} out of range (0..{len(self.potentials) - 1})"
                )
        return self._result(state, which, False, virial)

    def verlet_step(
        self, state: State, kick_dt: float, drift_dt: float, threaded: bool = False
    ) -> int:
        """As :meth:`md.ForceField.verlet_step` (2 done, 0 nothing done; collective): where
        the step's first call takes the held forces, in double precision without virial
        or bonded terms, on compiled sweeps and the build's cell, ``step_out`` (kick, drift,
        ``moved_since``, owned rows, ghosts sent, the local list's check), the local pair
        kernel's call (:meth:`md.ForceField.pair_call`, while the local list holds; else
        the local ``compute``), then ``gather_reverse_kick`` (the finite checks, the
        reduction, ghost forces back, closing kick); else as :meth:`_evaluate`. The same
        messages, bookkeeping and bits as :meth:`compute` and the kicks; the two compiled
        calls on the ranks' clock. What a build fixes is prepared once a build
        (:meth:`Domain.fused_arguments`; the pair call laid out at the build's first step)."""
        held, outcome = self._cache.get(None), self._build_outcome  # (a step start's build)
        positions, cell, fused = state.positions, self._cell_bytes, self._fused
        if (
            threaded
            or held is None
            or not (self._in_step and self.steady and None in self._steady_keys)
            or None in self._called
            or self.virial_wanted
            or (outcome is not None and outcome[1] is not None)  # (this rank's build failed)
            or (reference := self.reference) is None
            or reference.shape != positions.shape
            or (begin := self.step_start).shape != positions.shape
            or (key := held[0])[1:] != cell  # (the held forces' cell is the build's)
            or (state.box.tobytes(), state.tilt.tobytes()) != cell  # (the local cell's)
        ):
            return 0
        if fused is None or fused[0] is not reference:  # (the first step after a build)
            plain = not self.bonded.listed and self.precision == "double"
            fused = (reference, plain and self.domain.fused_arguments(state), None, True)
            self._fused = fused
        if not fused[1]:
            return 0  # (this build's layout has no fused step)
        out_tail, back_tail, local_state, n_owned, check = fused[1]
        pair = fused[2]  # (the local pair call: None not asked yet this build, False none)
        if pair is None or (pair and pair[6] != self.neighbor_list.n_builds):  # (rebuilt)
            pair = self._pair_call(local_state)  # (laid out before the step, not run)
            fused = self._fused = (reference, fused[1], pair, fused[3] and not pair)
        velocities, masses, clock = state.velocities, state.masses, self.ranks.clock
        with clock:  # (the kick, drift and displacement pass with the messages)
            code, moved2, step2, coming2, local2 = step_out(
                *(key[0], positions, velocities, held[1].forces, masses, kick_dt, drift_dt),
                *(reference, _IDENTITY, begin, self.step_before, *out_tail),
                _NONE if not pair else pair[3],
            )
        if code:
            if code < 0:  # (not the held forces' positions: nothing was done)
                return 0
            check(code)
        self._called.add(None)  # the step's first call, as _in_step_decision takes it
        if None in self._evaluated_in_step:
            self._moved_report = max(self._moved_report, 0.0)
            self._reported.add(None)
        self._exchanged = None  # the step's second call evaluates, as refresh and _attempt
        start = time.perf_counter()
        # The local compute's call made here while its list holds (the finite checks in
        # gather_reverse_kick), else the local compute (which rebuilds the list if it must)
        direct = pair and local2 <= pair[4]
        if direct:
            forces = np.empty(pair[5])
            pair[0](*pair[1], forces)
            error, result = None, ForceResult(float(pair[2][0]), forces, None)
        else:
            error, result = self._local_compute(local_state)
            if fused[3] and error is None:  # (none before the step: asked once after it)
                self._fused = (reference, fused[1], self._pair_call(local_state), False)
        self.timings["force"] += time.perf_counter() - start
        totals, worst = self._totals, self._worst
        forces = _NONE if result is None else result.forces
        while True:
            with clock:  # (the closing kick with the messages)
                code, done = gather_reverse_kick(
                    *(error is not None, 0.0 if result is None else result.energy, moved2),
                    *(step2, coming2, 0.5 * self.skin, LOOKAHEAD, self.domain.outgrown),
                    *(self.stop_code, self._moved_report),
                    *(0.0 if outcome is None else outcome[0], self._values, self._gathered),
                    *(totals, worst, forces, *back_tail, velocities, masses, kick_dt, direct),
                )
            if code != -2:
                break
            # a value of the direct call is not finite (no message sent): the local compute
            # says what, as it did before
            direct, (error, result) = False, self._local_compute(local_state)
            forces = _NONE if result is None else result.forces
        if code:
            check(code)
        if outcome is not None:
            self._settle_build(worst[6:4:-1])  # (another rank's failure raises here)
        if worst[3]:
            self._shared(worst)  # (raises on every rank)
        if worst[4] >= 0.0:  # (_shared's lines, a call fewer a step)
            self.steady = not worst[4]
            if self._reported != self._steady_keys:
                self._steady_keys = frozenset(self._reported)
            self._moved_report = -1.0
            self._reported.clear()
        self.ahead, self.stop_seen = float(worst[1]), float(worst[2])
        if done:  # (the local result is this step's own: the local force field keeps none)
            result.energy, result.forces = float(totals[1]), forces[:n_owned]
        else:  # not one rank's doing, or every rank's: all go on as _evaluate
            if worst[0]:  # some rank's list was outrun: all rebuild and evaluate again
                self.rebuild(state, migrate=False)
                error, result, totals, worst = self._attempt(state, None, False, False, False)
                if worst[0]:
                    self.rebuild(state, migrate=False)
            # (an error or a non-finite energy raises there, as in _evaluate)
            result = self._finish(error, result, totals, False, False)
            closing_kick(velocities, result.forces, masses, kick_dt)
        self._evaluated_in_step.add(None)
        self.n_evaluations += 1
        key[0][...] = positions  # (the key's copy: shaped as they are, step_out compared)
        self._cache[None] = (key, result)
        return 2

    def _pair_call(self, local_state: State) -> tuple | bool:
        """The local pair call (:meth:`md.ForceField.pair_call`) with the forces' shape and
        the local list's build it serves; False where there is none."""
        try:
            made = self.local.pair_call(local_state)
        except Exception:  # (the local compute raises it, shared with every rank)
            return False
        shape, built = (len(local_state.positions), 3), self.neighbor_list.n_builds
        return (*made, shape, built) if made else False

    def _local_compute(self, local_state: State) -> tuple:
        """(the error shared with every rank, or None; the local result without virial)."""
        try:
            return None, self.local.compute(local_state, False, False)
        except Exception as caught:  # shared with every rank by the caller's reduction
            return self._global_error(caught), None

    def _result(self, state: State, which, per_atom: bool, virial: bool) -> ForceResult:
        held = self._cache.get(which)
        same = held is not None and _same(held[0], state)
        available = held is not None and (
            (not per_atom or held[1].energies is not None)
            and (not virial or held[1].virial is not None)
        )
        usable = same and available
        if self._in_step:
            decided = self._in_step_decision(state, which, held, same, available)
        else:
            # A rank that can use its result does not compare its exchanged positions (a
            # full pass over them each step): "not exchanged" is always safe, it only sends
            # again. Decided together: a rank that owns no atoms sees its (no) positions
            # unchanged while the others' moved, and must still evaluate and exchange.
            exchanged = not usable and self._exchanged is not None and _same(self._exchanged, state)
            decided = self._all_ranks(usable, exchanged)
        usable, exchanged = decided
        if usable:
            return held[1]
        virial = virial or self.virial_wanted
        result = self._evaluate(state, which, per_atom, virial, exchanged)
        if self._in_step:
            self._evaluated_in_step.add(which)
        else:
            self._evaluated_in_step.discard(which)
        if which is None:
            self.n_evaluations += 1
        else:
            self.n_subset_evaluations += 1
        self._cache[which] = (_key(state, held[0] if held else None), result)
        return result

    def _in_step_decision(self, state: State, which, held, same: bool, available: bool):
        """(use the cached result, positions exchanged already) for a call inside a step of
        the loop, decided on every rank alike without a message.

        Every rank makes the same calls, so what no rank's positions decide is the same
        on all: the first call of a step for a cache key uses the result held when the
        ranks last found the atoms where the step before's evaluation for that key left
        them (``steady``: velocity Verlet's step-start call); every other call evaluates.
        Until that is known (and for keys it was not seen for), the first calls agree as
        calls outside a step do; each first call's observation (moved since an
        evaluation in the last step, or not) is shared at the next reduction."""
        first = which not in self._called
        self._called.add(which)
        if not first:
            return False, False
        usable = same and available
        if which in self._evaluated_in_step:  # (the same keys on every rank)
            self._moved_report = max(self._moved_report, 0.0 if same else 1.0)
            self._reported.add(which)
        if self.steady is None or which not in self._steady_keys:
            exchanged = not usable and self._exchanged is not None and _same(self._exchanged, state)
            return self._all_ranks(usable, exchanged)
        if not self.steady:
            return False, False
        cell = held is not None and (state.box.tobytes(), state.tilt.tobytes()) == held[0][1:]
        if not same and cell:  # (a cell that changed changed on every rank: all evaluate)
            now, then = state.positions, held[0][0]  # the same bits (NaN included)?
            if now.shape != then.shape or not same_values(now.view(np.int64), then.view(np.int64)):
                self._broken_promise(state)
            usable = available  # (the same bits, NaN where they were: as the other ranks)
        return usable, False

    def _broken_promise(self, state: State) -> None:
        """The atoms moved between the last step's evaluation and this step's first call,
        where the steps before did not: the other ranks took their held results, so this
        one cannot evaluate with them. End every rank, saying why (no rank is left
        waiting)."""
        self.ranks.abort(
            3,
            f"step {state.step}: the integrator moved atoms between its last force evaluation "
            "and the next step's first call, which its earlier steps did not; a decomposed "
            "run relies on that pattern holding (md.distributed.DistributedForceField."
            "step_begins): ending every rank",
        )

    def step_begins(self) -> None:
        """A step of the run's loop starts on every rank (after :meth:`start_step`); the
        calls until :meth:`steps_end` are the integrator's, made alike on every rank, and
        decided without a message of their own (see :meth:`_in_step_decision`): the step's
        only reduction is its evaluation's."""
        self._in_step = True
        self._called.clear()

    def steps_end(self, forget: bool = False) -> None:
        """The calls from now on are outside a step (thermo rows, observers, a minimiser):
        their use of held results is agreed by a reduction. ``forget``: what the steps
        showed (``steady``) is observed again (a run's start: its state may have been
        changed between runs)."""
        self._in_step = False
        self._settle_build()
        if forget:
            self.steady = None
            self._steady_keys = frozenset()
            self._evaluated_in_step.clear()
            self._reported.clear()
            self._moved_report = -1.0

    def _all_ranks(self, *flags: bool) -> tuple[bool, ...]:
        """Whether each of ``flags`` holds on every rank (one reduction; collective)."""
        failing = self.ranks.max(np.array([0.0 if flag else 1.0 for flag in flags]))
        return tuple(bool(value == 0.0) for value in failing)

    def _evaluate(
        self, state: State, which, per_atom: bool, virial: bool, exchanged: bool = False
    ) -> ForceResult:
        """Exchange, compute, share: one reduction carries the energy and virial, whether a
        rank failed or found its list outrun (then every rank rebuilds and evaluates again),
        and what the next step start needs (the look-ahead, a stop request)."""
        for _ in range(2):
            error, result, totals, worst = self._attempt(state, which, per_atom, virial, exchanged)
            exchanged = False  # a rebuild below lays the local system out anew
            if not worst[0]:
                break
            self.rebuild(state, migrate=False)  # some rank's list was outrun: all rebuild
        return self._finish(error, result, totals, per_atom, virial)

    def _attempt(self, state: State, which, per_atom: bool, virial: bool, exchanged: bool):
        """One try of :meth:`_evaluate`: (this rank's error, its local result, the sums, the
        largest values over the ranks)."""
        covered, ahead, finite = self.refresh(state, exchanged)
        start = time.perf_counter()
        error, result = None, None
        outcome = self._build_outcome
        try:
            if outcome is not None and outcome[1] is not None:
                pass  # this rank's list is not whole: the build's error is shared below
            elif which is None:
                result = self.local.compute(self.domain.local_state, per_atom, virial)
            else:
                result = self.local.compute_subset(self.domain.local_state, which, virial)
        except Exception as caught:  # shared with every rank below
            error = self._global_error(caught)
        middle = time.perf_counter()
        values = self._values
        values[:] = 0.0
        values[0] = error is not None
        if result is not None:
            values[1] = result.energy
            if virial and result.virial is not None:
                values[2:11] = np.asarray(result.virial).ravel()
        values[11] = not covered
        values[12] = ahead
        values[13] = self.stop_code
        values[14] = not finite
        values[15] = self._moved_report
        if outcome is not None:
            values[16:18] = (outcome[1] is not None, outcome[0])
        totals, worst = np.empty(11), self._worst
        gather_folded(self.ranks, values, 11, totals, worst)  # on the ranks' clock
        self.timings["force"] += middle - start
        self._settle_build(worst[6:4:-1])  # (a build's outcome waits on every rank or none)
        self._shared(worst)
        return error, result, totals, worst

    def _shared(self, worst: NDArray[np.float64]) -> None:
        """Take what the reduction's largest values (``worst``) say, alike on every rank."""
        if worst[4] >= 0.0:  # what the steps' first calls found, on every rank
            self.steady = not worst[4]
            if self._reported != self._steady_keys:
                self._steady_keys = frozenset(self._reported)
            self._moved_report = -1.0
            self._reported.clear()
        if worst[3]:
            raise NonFiniteError("particle positions are not finite")
        self.ahead, self.stop_seen = float(worst[1]), float(worst[2])

    def _finish(self, error, result, totals, per_atom: bool, virial: bool) -> ForceResult:
        """An evaluation's result from its last try (collective: errors raised alike)."""
        if totals[0]:
            agree(self.ranks, error)
        with self.ranks.clock:
            # The local result is this evaluation's own (the local force field keeps none):
            # the ghosts' rows are summed into it in place and the owned rows returned as they
            # are (a 10^6-atom rank saves two copies of its forces a step).
            forces = self.domain.reverse(np.asarray(result.forces, dtype=np.float64))
            energies = virials = None
            if per_atom:
                energies = self.domain.reverse(np.array(result.energies)[:, None])[:, 0].copy()
                if result.virials is not None:
                    virials = self.domain.reverse(np.array(result.virials)).copy()
        if not math.isfinite(totals[1]):
            raise NonFiniteError(f"potential energy is {totals[1]}")
        return ForceResult(
            energy=float(totals[1]),
            forces=forces,
            virial=totals[2:11].reshape(3, 3).copy() if virial else None,
            energies=energies,
            virials=virials,
        )

    def _global_error(self, error: Exception) -> Exception:
        """A bonded term's error, naming the whole system's bond (angle) and atoms."""
        return self.bonded.global_error(error, self.domain.local_ids)

    # ----------------------------------------------------------------- rebuilds
    def refresh(self, state: State, exchanged: bool = False) -> tuple[bool, float, bool]:
        """Bring the local system to ``state``'s positions (sending the ghosts') unless every
        rank found them ``exchanged`` already; return (whether this rank's list still
        covers the cutoff, the look-ahead ratio, whether its positions are finite).
        Collective; the first call builds."""
        if self.reference is None or self.reference.shape != state.positions.shape:
            self.rebuild(state, migrate=False)
            exchanged = False
        if exchanged:
            return True, self.ahead, True
        start, communicated = time.perf_counter(), self.ranks.clock.seconds
        mapping, allowed = self.allowance(state)
        begin = self.step_start if self.step_start.shape == state.positions.shape else None
        if mapping is None and begin is None:
            chunks = chunk_count(state.n_atoms, _MIN_PASS_ATOMS)
            moved2 = largest_displacement2(state.positions, self.reference, chunks)
            step2, coming2, copied = 0.0, moved2, False
        else:
            before = self.step_before if begin is not None else _NONE
            # the same pass writes the owned positions into the local system (not a message)
            owned = self.domain.owned_rows(state)
            moved2, step2, coming2 = moved_since(
                state.positions,
                self.reference,
                _IDENTITY if mapping is None else mapping,
                state.positions if begin is None else begin,
                before,
                owned,
            )
            copied = len(owned) > 0
        # the list's check and the owned rows of its local system; the ghosts' messages on
        # the ranks' clock
        self.domain.update(state, copied)
        self.timings["neighbor"] += (
            time.perf_counter() - start - (self.ranks.clock.seconds - communicated)
        )
        # Which positions the ghosts hold, for the agreement of calls outside a step (a
        # call at the same positions that cannot use its held result skips the messages).
        # A step's calls never ask (they evaluate, or take the held result): no copy there.
        self._exchanged = None if self._in_step else _key(state, self._exchanged)
        moved, step_move = math.sqrt(moved2), math.sqrt(step2)
        finite = math.isfinite(moved2)
        coming = math.sqrt(coming2) + LOOKAHEAD * step_move
        covered = moved <= allowed and self.domain.layout_holds(state)
        # (the look-ahead ratio: inf when nothing may move but something does)
        ratio = coming / allowed if allowed > 0 else (math.inf if coming > 0 else 0.0)
        return covered, ratio, finite

    def coming_positions(
        self, state: State, dt: float, out: NDArray | None = None, forces: NDArray | None = None
    ) -> NDArray[np.float64]:
        """Where the owned atoms are expected after a step of ``dt``: r + dt v + dt^2 a / 2
        (velocity Verlet's move) with the forces at hand (``forces``, known to be of these
        positions, else the cached ones), r + dt v without (in ``out``, else a new array)."""
        if forces is None:
            forces = self.cached_forces(state)
        if out is None:
            out = np.empty_like(state.positions)
        predicted_positions(
            state.positions,
            state.velocities,
            _NONE if forces is None else forces,
            state.masses,
            float(dt),
            out,
        )
        return out  # (the kernel returns none: boxing an array costs a Python call)

    def cached_forces(self, state: State) -> NDArray[np.float64] | None:
        """The forces on ``state``'s owned atoms if they are at hand (computed at these
        positions and cell), else None; nothing is computed."""
        held = self._cache.get(None)
        if held is not None and _same(held[0], state):
            return held[1].forces
        return None

    def start_step(self, positions: NDArray[np.float64], migrated: bool) -> None:
        """Note the owned ``positions`` at a step start, keeping the last step start's
        unless atoms ``migrated`` since (the look-ahead uses both)."""
        if migrated or self.step_start.shape != positions.shape:
            self.step_before = _NONE
        else:
            self.step_before, self.step_start = self.step_start, self.step_before
        self.step_start = copied(positions, self.step_start)

    def allowance(self, state: State) -> tuple[NDArray | None, float]:
        """(the cell's deformation since the build, None if unchanged; the largest move an
        atom may make before the list misses a pair within the cutoff) [length]."""
        cutoff = self.cutoff or 0.0
        if (state.box.tobytes(), state.tilt.tobytes()) == self._cell_bytes:
            return None, 0.5 * self.skin
        box0, tilt0 = self.reference_cell
        before = cell_matrix(np.where(state.pbc, box0, 1.0), periodic_tilt(tilt0, state.pbc))
        after = cell_matrix(
            np.where(state.pbc, state.box, 1.0), periodic_tilt(state.tilt, state.pbc)
        )
        mapping = np.linalg.solve(before, after)
        smallest = float(np.linalg.svd(mapping, compute_uv=False).min())
        return mapping, 0.5 * (smallest * (cutoff + self.skin) - cutoff)

    def reserve(self, state: State) -> None:
        """Map the memory the first migration writes ``state``'s arrays and the cached
        forces into, now rather than inside the run (see :meth:`Domain.reserve`)."""
        self.domain.reserve(state, {("cached", None): state.positions})

    def rebuild(
        self, state: State, migrate: bool, carried: dict | None = None, dt: float | None = None
    ) -> dict:
        """Rebuild the ghosts and the local list at ``state``; with ``migrate``, first move
        atoms (with ``carried`` per-atom arrays and the cached forces) to the ranks of their
        bricks. Collective. Returns the carried arrays, migrated.

        With ``dt``, the time step about to be taken (a step start's build), the ghosts and
        the list are laid out where that step is expected to take the atoms
        (:meth:`coming_positions`), so that the list lasts as many steps as a single
        process's (built where the atoms are, it would lose a step's worth of skin; any
        build position is valid: the list is checked against it at every evaluation), and
        the step's evaluation shares the build's outcome (a rank's failure, the longest
        bond) in its reduction: a rank whose build failed evaluates nothing there.

        Its time goes to ``timings["neighbor"]``, less the migration's and the ghost
        search's (on the ranks' clock)."""
        start, communicated = time.perf_counter(), self.ranks.clock.seconds
        carried = dict(carried or {})
        if migrate:
            # Results of the current positions travel with their atoms; older ones (a
            # minimiser migrates after moving the atoms, before evaluating) are dropped.
            kept, cached = {}, {}
            for which, held in self._cache.items():
                if _same(held[0], state):
                    kept[which] = held
                    cached[("cached", which)] = held[1].forces
            self._cache = kept
            if self.balance_every:  # (a brick keeps room for the shell and the strays)
                self.balance.check(state, self.domain, self.ranks, self.reach + self.skin)
            with self.ranks.clock:
                # (the cached forces are the evaluations' own arrays: they move in them)
                moved = self.domain.migrate(state, {**carried, **cached}, spent=tuple(cached))
            for name in carried:  # (a loop: a comprehension is a Python call of its own)
                carried[name] = moved[name]
            for which, (held, result) in list(self._cache.items()):
                result.forces = moved[("cached", which)]
                result.energies = result.virials = None
                self._cache[which] = (_key(state, held), result)  # (in its memory if it fits)
        self.migrate_pending = not migrate
        # The build positions go where the last build's were (that list is done with): a
        # fresh 10^6-atom array cost its page faults at every build (the predicted
        # positions 5 -> 19 ms a build on the Zen 4 VM). No reference until it is whole.
        self.reference = None
        memory = self._reference_memory
        n = len(state.positions)  # (State.n_atoms is a property: a Python call each)
        if memory.shape[0] < n:
            memory = np.empty((n + n // 8 + 16, 3))
            self._reference_memory = memory
        reference = memory[:n]
        at = state
        if dt is not None and state.velocities is not None:
            at = self._ahead  # (a shallow copy of the state, kept: copy.copy took ~8 us)
            if at is None:
                at = self._ahead = copy.copy(state)
            at.__dict__.update(state.__dict__)
            held = self._cache.get(None) if migrate else None  # (a migration's: of state)
            forces = None if held is None else held[1].forces
            at.positions = self.coming_positions(state, dt, reference, forces)
        self._settle_build()
        reach = self.reach
        # (a step start's build: atoms just migrated, laid out a step ahead; AGREED_STRAY)
        agreed = AGREED_STRAY * self.skin if migrate and dt is not None and self.skin else None
        error, longest = self.domain.build(at, reach, agreed), 0.0  # ghosts on the ranks' clock
        try:
            longest = self._localize_bonded()
            nl = self.local.neighbor_list
            if nl is not None:
                nl.keep_owned(self.domain.local_ids, self.domain.n_owned)
                nl.build(self.domain.local_state)
        except (NonFiniteError, ValueError) as caught:  # shared with every rank
            error = caught if error is None else error
        self._build_outcome = (longest, error)
        if dt is None:
            self._settle_build()
        if at is state:
            copy_into(reference, state.positions)
        self.reference = reference
        cell = (state.box.tobytes(), state.tilt.tobytes())
        if cell != self._cell_bytes or self.reference_cell is None:  # (else the same values)
            self.reference_cell = (state.box.copy(), state.tilt.copy())
            self._cell_bytes = cell
        # Built where the atoms are: the local system holds their positions. Built ahead of
        # them: the next evaluation sends positions on every rank (a rank whose atoms reach
        # their predicted positions to the last bit must not skip a collective exchange).
        self._exchanged = _key(state, self._exchanged) if at is state else None
        self.ahead = 0.0
        self.n_builds += 1
        elapsed = time.perf_counter() - start
        self.timings["neighbor"] += elapsed - (self.ranks.clock.seconds - communicated)
        return carried

    def _settle_build(self, shared=None) -> None:
        """Share a waiting build's outcome (its own reduction, unless ``shared``: the longest
        bond and whether a rank failed, from an evaluation's) and raise its error on every
        rank alike, else keep the longest bond. Collective: all ranks hold one or none."""
        outcome, self._build_outcome = self._build_outcome, None
        if outcome is None:
            return
        longest, error = outcome
        if shared is None:
            shared = global_max(np.array([longest, error is not None], dtype=float), self.ranks)
        longest, failed = float(shared[0]), bool(shared[1])
        if failed:
            agree(self.ranks, error)
        if self.bonded.listed:
            reach = self.reach  # (the build's: bond_reach changes only here)
            if longest > reach:
                raise DecompositionError(
                    f"a bond is {longest:.4g} long, beyond the ghost shell ({reach:.4g}) of "
                    "the last build; bonds must not stretch that fast"
                )
            self.bond_reach = longest

    def _localize_bonded(self) -> float:
        """Give the local force field this rank's bonds and angles over local indices;
        return the longest bond (angle arm) among them [length]."""
        return self.bonded.localize(self.domain, self.potentials, self.local.potentials)


def _key(state: State, old: tuple | None = None) -> tuple:
    """What a result depends on: the owned positions (copied, into ``old``'s array when it
    fits) and the cell."""
    positions = copied(state.positions, _NONE if old is None else old[0])
    return positions, state.box.tobytes(), state.tilt.tobytes()


def _same(key: tuple, state: State) -> bool:
    positions, box, tilt = key
    return (
        positions.shape == state.positions.shape
        and box == state.box.tobytes()
        and tilt == state.tilt.tobytes()
        and same_values(positions, state.positions)
    )
