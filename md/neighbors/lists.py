"""Verlet neighbour lists built from cell lists.

A note on its length (about 1300 lines, over the 800 where a module is split): nearly
all of it is one class, :class:`NeighborList` (its state, the rebuild verdict, the
brute-force, cell and cluster builds and the prune share its buffers and reference
positions); :class:`SlotFrame` and :class:`ClusterFrame` are what it hands the pair
kernels. The kernels are the package's private modules (``_cell_kernels`` and
``_candidates``: the search; ``_build_kernels``: the build around it;
``_small_box_kernels``: the build of a box too narrow for the cells;
``_cluster_grid``, ``_cluster_search``, ``_cluster_prune``: the cluster-pair list's grid,
search and prune; ``_exclusion_kernels``: the pairs of one
group left out, :meth:`NeighborList.exclude_groups`; ``_owned_kernels``: the list of a
rank of a decomposed run, :meth:`NeighborList.keep_owned`).
"""

from __future__ import annotations

import contextlib
import logging
import math
from dataclasses import dataclass

import numpy as np
from numba.core import config as numba_config
from numpy.typing import NDArray

from md import parallel
from md._memory import KeptArrays
from md.box import (
    TILT_NAMES,
    cell_matrix,
    is_orthorhombic,
    periodic_lengths,
    periodic_tilt,
    perpendicular_widths,
)
from md.errors import NonFiniteError
from md.neighbors._build_kernels import (
    _atom_space_list,
    _balanced_bounds,
    _cell_grid,
    _cell_list,
    _largest_coordinates,
    _largest_displacement2,
    _max_displacement2,
    _shift_table,
)
from md.neighbors._cell_kernels import MAX_SLOTS, _brute_force_pairs
from md.neighbors._cluster_grid import cluster_grid, column_counts
from md.neighbors._cluster_prune import cluster_positions, cluster_positions_threaded, prune_pairs
from md.neighbors._cluster_search import balanced_chunks, chunk_windows, row_reach, search_pairs
from md.neighbors._exclusion_kernels import _drop_grouped_pairs
from md.neighbors._owned_kernels import _owned_brute_force_pairs, _owned_cell_list
from md.neighbors._small_box_kernels import _drop_repeats, _small_box_list
from md.parallel import chunk_count
from md.state import State

logger = logging.getLogger(__name__)

#: Most cells per atom the grid may have (sparse or open systems get wider cells).
_MAX_CELLS_PER_ATOM = 4
#: Cells per list radius: partners lie within this many cells along each axis.
_REACH = 2
#: Farthest a position may lie from the box, in box lengths (slot images are int32).
_MAX_IMAGES = 2.0e9
#: Fewest atoms per thread worth a chunk of their own.
_MIN_CHUNK_ATOMS = 1000
#: Fewest atoms per thread worth a chunk of their own in a memory-bound pass over them
#: (the per-step displacement check: 32000 atoms took 26 us on one thread, 17.5 on two,
#: on a 2-core Zen 5).
_MIN_PASS_ATOMS = 16_000
#: Head room of the pair buffer over the count that did not fit.
_GROWTH = 1.05
#: The verdict of :meth:`NeighborList._verdict` that asks for the cluster list to be pruned.
_PRUNE = "prune"
#: The outer cluster list's skin in skins, by default (see ``outer_skin``).
_OUTER_SKINS = 5.0


@dataclass(frozen=True)
class SlotFrame:
    """The neighbour list as a pair kernel reads it: the slot frame of one build.

    Slot p holds atom ``order[p]``, at ``positions[order[p]] + images[p] @ h``
    (wrapped into the box at the build; h is the cell matrix of ``lengths``
    and ``tilt``, so an orthorhombic box adds ``images[p] * lengths``); the partners of slot p are
    ``neighbors[starts[p]:starts[p + 1]]``, and pair k is separated by
    ``frame[p] - frame[q] - shifts[codes[k]]``, with no minimum image. Chunk c
    (one per thread) covers slots ``bounds[c]`` to ``bounds[c + 1]``.

    Attributes
    ----------
    order : ndarray of int64, shape (N,)
    images : ndarray of int32, shape (N, 3)
    lengths : ndarray of float64, shape (3,)
        Periodic box lengths at the build (zero along open axes) [length].
    shifts : ndarray of float64, shape (27, 3)
        Image shift of each code [length].
    starts : ndarray of int64, shape (N + 1,)
    neighbors : ndarray of int32, shape (P,)
    codes : ndarray of uint8, shape (P,)
    bounds : ndarray of int64, shape (C + 1,)
    tilt : ndarray of float64, shape (3,)
        Tilt factors (xy, xz, yz) at the build (zeros: orthorhombic) [length].
    shifted : ndarray of bool, shape (N,)
        Whether row p may have a pair with an image shift (a code other than
        13, the zero shift): set for every row that has one (and some that
        do not); the pair kernels gather the other rows' partners without
        their codes.
    """

    order: NDArray[np.int64]
    images: NDArray[np.int32]
    lengths: NDArray[np.float64]
    shifts: NDArray[np.float64]
    starts: NDArray[np.int64]
    neighbors: NDArray[np.int32]
    codes: NDArray[np.uint8]
    bounds: NDArray[np.int64]
    tilt: NDArray[np.float64]
    shifted: NDArray[np.bool_]

    @property
    def n_chunks(self) -> int:
        return len(self.bounds) - 1


class ClusterFrame:
    """The neighbour list in GROMACS's cluster-pair layout, as the cluster kernels read it.

    Built by :class:`NeighborList` with ``clusters=True`` (see
    :mod:`md.neighbors._cluster_grid` and ``_cluster_search`` for the grid and the
    search). Slot s holds atom
    ``atom[s]`` (-1: a filler), in cluster s // 4; its position relative to its
    cluster is ``positions[atom[s]] - origin[s]`` (:meth:`relative_positions`). I
    cluster c's partners are ``partners[starts[c]:starts[c + 1]]``, the first of
    them c itself; pair k's atoms are separated by ``x_rel[c, a] - x_rel[j, b] +
    offsets[k]`` (float32). Chunk t (one per thread) covers i clusters
    ``bounds[t]`` to ``bounds[t + 1]``, with about equal pair counts; its rows reach
    clusters ``windows[t, 0]`` (= ``bounds[t]``) to at most ``windows[t, 1]``, and its
    part of the kernels' per-chunk scratch starts at cluster ``windows[t, 2]`` of it
    (:func:`md.neighbors._cluster_search.chunk_windows`; ``window_clusters`` in all). A pruned
    list takes ``reach`` (per row, one past its last partner) from its outer list: a
    bound that costs no pass over the pairs at each prune.

    ``relative``: None, or the float32 buffers ``(xi, xj)`` into which the list wrote the
    slots' relative positions (as :meth:`relative_positions` writes them) at the positions
    it made this frame at (a search's or a prune's, :attr:`NeighborList.pruned_positions`),
    its own scratch, which it writes again only at its next prune or search (a new frame).
    A kernel over this frame may take them as its buffers for the relative positions: at
    the making's positions they are written already; whoever writes its own positions
    there (as the kernels' passes do) makes them that reader's.

    The list holds the cluster pairs that had an atom pair within the list radius
    at the build: the search's candidates (see :func:`md.neighbors._cluster_search.search_pairs`)
    checked atom by atom in 8-lane vectors (GROMACS's pruning), about half of them on the LJ melt.
    """

    def __init__(
        self, atom, origin, starts, partners, offsets, chunks: int, reach=None, relative=None
    ):
        self.atom = atom
        self.origin = origin
        self.starts = starts
        self.partners = partners
        self.offsets = offsets
        self.relative = relative
        self.bounds = balanced_chunks(starts, int(chunks))
        self._reach = reach
        self._windows = None

    @property
    def reach(self) -> NDArray[np.int64]:
        """Per i cluster, one past the last cluster its row reaches, or a bound on it
        (the search's, from its windows; else found on first use:
        :func:`md.neighbors._cluster_search.row_reach`)."""
        if self._reach is None:
            self._reach = row_reach(self.starts, self.partners)
        return self._reach

    @property
    def windows(self) -> NDArray[np.int64]:
        """Each chunk's window (first, end, place), found on first use: one chunk's is
        the whole list, with no pass over it."""
        if self._windows is None:
            if len(self.bounds) == 2:
                self._windows = np.array([[0, self.n_clusters, 0]], np.int64)
            else:
                self._windows = chunk_windows(self.reach, self.bounds)
        return self._windows

    @property
    def window_clusters(self) -> int:
        """The chunks' windows' clusters together: the per-chunk scratch's length."""
        first, end, place = self.windows[-1]
        return int(place + end - first)

    @property
    def n_clusters(self) -> int:
        return len(self.starts) - 1

    @property
    def n_pairs(self) -> int:
        """Cluster pairs listed."""
        return int(self.starts[-1])

    def relative_positions(
        self, positions: NDArray[np.float64], xi: NDArray[np.float32], xj: NDArray[np.float32]
    ) -> None:
        """Write the slots' positions relative to their origins into ``xi`` and ``xj``
        (float32, 12 per cluster: x0..x3, y0..y3, z0..z3), in the i and the j role (they
        differ in where the fillers sit: far apart, never within reach of anything), on the
        threads when there are enough slots."""
        _relative_positions(positions, self.atom, self.origin, xi, xj)


def _relative_positions(positions, atom, origin, xi, xj) -> None:
    """:meth:`ClusterFrame.relative_positions` of the slots ``atom``/``origin``, on the
    threads when there are enough slots (the same values on any number)."""
    chunks = chunk_count(len(atom), _MIN_PASS_ATOMS)
    if chunks == 1:
        cluster_positions(positions, atom, origin, xi, xj)
    else:
        cluster_positions_threaded(positions, atom, origin, xi, xj, chunks)


def max_displacement2(positions: NDArray[np.float64], reference: NDArray[np.float64]) -> float:
    """Largest squared distance of any atom from its place in ``reference`` [length^2].

    inf if any position is not finite (``reference`` must be). One serial pass,
    the kernel of the list's own rebuild test; :class:`md.simulation.Simulation`'s
    blow-up guard (``max_displacement``) uses it.
    """
    return _max_displacement2(positions, reference)


def largest_displacement2(
    positions: NDArray[np.float64], reference: NDArray[np.float64], chunks: int
) -> float:
    """As :func:`max_displacement2`, in ``chunks`` chunks on the threads when ``chunks`` > 1
    (the list's own rebuild test; :mod:`md.distributed` asks it for a rank's atoms)."""
    return _largest_displacement2(positions, reference, chunks)


def _square(length: float) -> float:
    """length**2, or inf where that overflows (a huge skin: every pair is listed)."""
    with np.errstate(over="ignore"):
        return float(np.square(np.float64(length)))


class NeighborList:
    """Half Verlet list with a skin, built by cell search and rebuilt on displacement.

    The list holds every pair closer than ``cutoff + skin`` at the last build.
    :meth:`update` rebuilds it when any particle has moved more than
    ``skin / 2`` since then, or when the box, periodicity or particle count
    changed; until then no pair can have come within ``cutoff`` unseen.

    Cells are half of ``cutoff + skin`` wide and atoms are grouped by a
    counting sort (no per-cell capacity). The cell search works in the
    *slot* frame: slot p holds atom ``order[p]``, atoms sorted by cell so
    that neighbours sit close together in memory, each wrapped into the box
    at the build. A pair's periodic image is then fixed until the next build
    and is stored as a code per pair, so the force kernels need no minimum
    image: the position of slot p is ``positions[order[p]] + images[p] * L``
    (:meth:`frame_positions`) and a pair (p, q) is separated by
    ``frame[p] - frame[q] - shifts[code]``.
    The search runs on :func:`md.parallel.get_threads` threads (one chunk of
    slots each) and gives the same list on any number of threads.

    When a periodic axis has room for fewer than five cells (a box under 2.5 list
    radii wide: the LJ liquid below about 500 atoms), an O(N^2) search over the
    periodic images builds the same slot frame instead (slots in atom order, wrapped
    into the cell; ``md.neighbors._small_box_kernels``), so small boxes
    run the pair kernels' fast path too. In a cell narrower than twice the list
    radius a pair may have two images within reach: the slot list then holds each
    (:attr:`n_pairs` counts them; at most one is within the cutoff), the list over
    atom indices each pair once. Where that search does not serve (a periodic width
    under the list radius, or :meth:`keep_owned`), the O(N^2) search over atom
    indices is used: ``order`` is None and kernels apply the minimum image per pair.

    Parameters
    ----------
    cutoff : float
        Interaction cutoff [length]; twice it must be shorter than every
        periodic box edge (the minimum-image convention).
    skin : float
        Extra list radius [length], >= 0.
    clusters : bool
        Build the list in GROMACS's cluster-pair layout (:class:`ClusterFrame`,
        read by the pair potentials' mixed-precision cluster kernels) where the
        cell allows it: periodic along every axis and orthorhombic, every edge
        longer than twice the list radius (else, on one rank of a decomposed
        run and under ``NUMBA_DISABLE_JIT``, the slot frame is built as usual;
        a sparse system gets columns narrower than its density asks, so that no
        column meets two images of another). The slot list is then built only if something asks for
        it (``frame``, ``starts``, ``pairs()``: per-atom results, Hessians), at
        the positions of the last build or prune.
    outer_skin : float or None
        With ``clusters``, GROMACS's dynamic pruning: the cluster search lists the
        pairs within ``cutoff + outer_skin`` (the outer list), and the list the
        kernels read is that one pruned to the pairs within ``cutoff + skin``
        (one atom-by-atom pass over the outer list, much cheaper than a search).
        When an atom has moved more than ``skin / 2`` since the last prune, the
        outer list is pruned again if no atom moved more than ``(outer_skin -
        skin) / 2`` since the search (every pair then within ``cutoff + skin`` is
        still in it), else searched again: exact, as the plain skin rule is.
        None: ``5 * skin`` (a search about a quarter as often as without). ``outer_skin
        <= skin``, or a box shorter than twice the outer radius, searches at
        ``cutoff + skin`` and never prunes.
    every : int
        Look at the list only every ``every`` steps (LAMMPS's ``neigh_modify every``):
        between looks it is kept whatever the atoms did, counted from the step of its
        build (``state.step`` at the evaluation), so a rebuild comes at the first
        evaluation at least ``every`` steps after it. 1 (the default): at every step.
    check : bool
        At a look, rebuild only if an atom has moved more than ``skin / 2`` since
        the build (LAMMPS's ``check yes``, the default); False: rebuild at every look
        (``check no``; with ``every``, GROMACS's fixed ``nstlist``). Only ``every=1``
        with ``check`` is exact: otherwise a pair that comes within the cutoff
        between two looks is missed until the next build, the energy drifts, and the
        cluster list is searched at the list radius with no outer list (its prunes
        serve the exact rule).

    Attributes
    ----------
    starts : ndarray of int64, shape (N + 1,)
        CSR row offsets into ``neighbors``, over atom indices.
    neighbors : ndarray of int32, shape (P,)
        ``neighbors[starts[i]:starts[i + 1]]`` are the partners of atom i;
        every pair within ``cutoff + skin`` appears exactly once, under
        either of its atoms (the O(N^2) searches put it under the lower
        index). Derived from the slot list on first use after a build.
    order : ndarray of int64, shape (N,), or None
        Atom in each slot (None after an O(N^2) build over atom indices).
    images : ndarray of int32, shape (N, 3)
        Per slot, the box lengths the build added to the atom's position to
        wrap it (zero along open axes).
    lengths : ndarray of float64, shape (3,)
        The periodic box lengths at the build (zero along open axes).
    slot_starts, slot_neighbors, codes : ndarray
        The list over slots: CSR offsets (N + 1,), partner slots (P,) int32
        and image codes (P,) uint8 naming rows of ``shifts``.
    shifts : ndarray of float64, shape (27, 3)
        Image shift of each code [length].
    bounds : ndarray of int64
        Slot ranges of the chunks the force kernels split the work into,
        balanced by pair count, one per thread.
    n_builds : int
        Number of builds so far (cluster searches, with ``clusters``).
    n_prunes : int
        Number of times the outer cluster list was pruned again between searches.
    n_bounded_prunes : int
        Of those, the prunes chosen over a search without measuring the atoms' distance
        from the search: their distance from the last prune plus that prune's bound on
        its own already lay within the prune distance.
    n_late_looks : int
        Looks of a list that is not :attr:`exact` at which an atom had moved more
        than ``skin / 2`` since the build: the list may have missed pairs within
        the cutoff before the look (LAMMPS's "dangerous builds"). The first is
        logged as a warning. Always 0 for the exact list.
    n_followed : int
        Number of times the list was kept through a change of the cell.

    Examples
    --------
    >>> from md.build import lattice
    >>> s = lattice("fcc", 4, density=0.8442)
    >>> nl = NeighborList(cutoff=2.5, skin=0.3)
    >>> nl.update(s)
    True
    >>> nl.update(s)
    False
    """

    def __init__(
        self,
        cutoff: float,
        skin: float = 0.3,
        clusters: bool = False,
        outer_skin: float | None = None,
        every: int = 1,
        check: bool = True,
    ) -> None:
        if not (np.isfinite(cutoff) and cutoff > 0):
            raise ValueError(f"neighbour list cutoff must be positive and finite, got {cutoff}")
        if not (np.isfinite(skin) and skin >= 0):
            raise ValueError(f"skin must be >= 0 and finite, got {skin}")
        if isinstance(every, bool) or not isinstance(every, int | np.integer) or every < 1:
            raise ValueError(f"neighbour list 'every' must be an integer >= 1, got {every!r}")
        if not isinstance(check, bool | np.bool_):
            raise ValueError(f"neighbour list 'check' must be True or False, got {check!r}")
        self.every = int(every)
        self.check = bool(check)
        self._built_step: int | None = None  # state.step at the last build
        # (step, positions) of a resume: evaluations there are not looks (see rebuild_at)
        self._resumed_at: tuple[int, NDArray[np.float64]] | None = None
        if outer_skin is None:
            outer_skin = _OUTER_SKINS * skin
        if not (np.isfinite(outer_skin) and outer_skin >= 0):
            raise ValueError(f"outer_skin must be >= 0 and finite, got {outer_skin}")
        self.cutoff = float(cutoff)
        self.skin = float(skin)
        self.outer_skin = float(outer_skin)
        self.clusters_wanted = bool(clusters)
        self._clusters: ClusterFrame | None = None
        self._outer: ClusterFrame | None = None  # the searched list, when pruned
        self._pruned_at: NDArray[np.float64] | None = None  # positions at its last prune
        # A bound on every atom's distance between _pruned_at and the search's positions
        # (0 at a search, inf where unknown): with the distance since the prune it bounds
        # the distance from the search, which then need not be measured (see update)
        self._pruned_from_search = math.inf
        self._prune_distance = 0.5 * (float(outer_skin) - float(skin))
        # Squared half of what the outer list has over the inner one: the farthest an atom
        # may have moved since the search for a prune to find every pair.
        self._prune_distance2 = _square(0.5 * (self.outer_skin - self.skin))
        self.n_prunes = 0
        self.n_bounded_prunes = 0
        # The cluster grid's, search's and prunes' arrays, kept from build to build (see
        # _build_clusters): the lists handed out are views of them, valid while current
        self._kept = KeptArrays()
        self._prune_relative = None  # the search's relative positions, for its prunes
        self._slots_pending = False  # a cluster build: the slot list on first use
        # (n_builds, n_prunes, n_followed, frame) of the last ``frame`` handed out: the
        # same SlotFrame until one of the counters moves (a frozen dataclass costs about a
        # microsecond to make, and a pair kernel asks for it at every evaluation)
        self._frame_memo: tuple | None = None
        self._pass_chunks = 1  # chunks of the displacement check (counted at each build)
        self._cluster_room = 64  # pairs of room per cluster in the search's buffers
        # Squared half skin; inf (never rebuild for motion) rather than an overflow.
        self._rebuild_distance2 = _square(0.5 * self.skin)
        # Squared list radius, once: _square's errstate costs microseconds a build.
        self._list_radius2 = _square(self.cutoff + self.skin)
        self.n_builds = 0
        self.n_late_looks = 0
        self.n_followed = 0
        self.used_cells = False
        self.order: NDArray[np.int64] | None = None
        self.images = np.zeros((0, 3), dtype=np.int32)
        self.lengths = np.zeros(3)
        self.tilt = np.zeros(3)
        self.slot_starts = np.zeros(1, dtype=np.int64)
        self.slot_neighbors = np.zeros(0, dtype=np.int32)
        self.codes = np.zeros(0, dtype=np.uint8)
        self.shifted_rows = np.zeros(0, dtype=np.bool_)  # per slot row (cell search)
        self.shifts = np.zeros((27, 3))
        self.bounds = np.zeros(2, dtype=np.int64)
        self._neighbor_buffer = np.zeros(1024, dtype=np.int32)
        self._code_buffer = np.zeros(1024, dtype=np.uint8)
        self._atom_list: tuple[NDArray[np.int64], NDArray[np.int32]] | None = None
        self._repeats = False  # a pair listed once per image (a cell under 2 list radii)
        self._small_memo = None  # (cell key, verdict) of _small_box_serves
        self._reference: NDArray[np.float64] | None = None
        self._box: NDArray[np.float64] | None = None
        self._tilt: NDArray[np.float64] | None = None
        self._pbc: NDArray[np.bool_] | None = None
        self._cell_bytes: tuple[bytes, ...] = ()  # box, tilt and pbc at the build
        self._cell_memo = None  # (key, cell data, periodic, {atoms: grid}) of _cell_data
        self._build_cell = None  # periodic lengths and tilt at the build
        self._followed_at_build = 0
        self._owned: tuple[NDArray[np.int64], int] | None = None
        self._listed_rows = 0  # rows of the last build that may hold pairs (see build)
        self._groups: NDArray[np.int64] | None = None  # see exclude_groups
        self._ghost_tests = np.zeros(1, dtype=np.int64)  # per search chunk: ghost_candidates

    def keep_owned(self, ids: NDArray[np.int64] | None, n_owned: int = 0) -> None:
        """From the next build on, list only the pairs this rank of a decomposed run evaluates.

        The State is one rank's atoms, ``0 .. n_owned - 1``, followed by ghost
        copies of atoms other ranks own (and periodic images); ``ids`` (N,) are
        their global ids. Of each pair the rank that owns its designated atom
        keeps it (the smaller id when the ids' sum is even, the larger when it is
        odd: ``md.neighbors._cell_kernels.designates``, which shares the pairs across a
        brick's face about evenly between its two ranks), so every pair of the
        whole system is listed on exactly one rank and pairs of two ghosts on
        none (:mod:`md.distributed` sends the ghosts' forces back to their
        owners). None lists every pair again.

        The search applies the rule itself (``md.neighbors._owned_kernels``): only
        the owned atoms have rows (slots ``0 .. n_owned - 1``, the owned atoms by
        cell; the ghosts' slots follow, their rows empty), each with its owned
        partners by the half rule and the ghosts around it that the rule gives it,
        so no pair of two ghosts is a candidate, and :attr:`bounds` (the pair
        kernels' chunks) ends at the last owned slot: a ghost costs the force call
        its position and force, no row. The O(N^2) search of a small local system
        lists the same pairs over atom indices, under their owned atoms.
        """
        self._owned = (
            None if ids is None else (np.ascontiguousarray(ids, dtype=np.int64), int(n_owned))
        )

    @property
    def ghost_candidates(self) -> int:
        """Ghosts the last cell search of a :meth:`keep_owned` list tested against an owned
        row (one per row and ghost; 0 for other searches): a diagnostic of the search's
        work, the ghosts whose segment of the shell (``_owned_kernels``) lies within the
        list radius of the row."""
        return int(self._ghost_tests.sum())

    def exclude_groups(self, groups: NDArray[np.int64] | None) -> None:
        """From the next build on (the next :meth:`update` builds), leave out every pair of
        two atoms in one group: ``groups`` (N,) has each atom's group, -1 for none (a
        rigid body's index, -1 for a free atom), as LAMMPS's ``neigh_modify exclude
        molecule/intra`` leaves out the pairs within a molecule. Each build drops them in
        one pass over the list it built (``md.neighbors._exclusion_kernels``). The
        cluster-pair layout holds whole 4 x 4 blocks of pairs, so a list with groups is
        built in the slot frame instead (``clusters`` then stays None; mixed precision
        runs its slot-frame kernels). None lists every pair again.
        """
        if groups is not None:
            groups = np.ascontiguousarray(groups, dtype=np.int64)
            if groups.ndim != 1:
                raise ValueError(f"exclusion groups must be one per atom, got shape {groups.shape}")
        self._groups = groups
        self._reference = None  # build at the next update

    @property
    def excluded_groups(self) -> NDArray[np.int64] | None:
        """:meth:`exclude_groups`'s groups (a copy), or None."""
        return None if self._groups is None else self._groups.copy()

    @property
    def list_radius(self) -> float:
        return self.cutoff + self.skin

    @property
    def exact(self) -> bool:
        """Whether the list is looked at every step with the displacement check, so that
        no pair within the cutoff is ever missed (``every == 1`` and ``check``)."""
        return self.every == 1 and self.check

    @property
    def built_step(self) -> int | None:
        """``state.step`` of the last build (None before the first)."""
        return self._built_step

    @contextlib.contextmanager
    def exactly(self):
        """Within the block, look at the list at every evaluation with the check
        (``every=1``, ``check=True``), whatever the list was made with: for work whose
        evaluations do not advance ``state.step`` (a minimisation)."""
        every, check = self.every, self.check
        self.every, self.check = 1, True
        try:
            yield self
        finally:
            self.every, self.check = every, check

    @property
    def n_pairs(self) -> int:
        self._slot_list()
        return int(self.slot_starts[-1])

    @property
    def clusters(self) -> ClusterFrame | None:
        """The cluster-pair list of the last build, or None (not asked for, or a cell it
        does not serve: see ``clusters`` in the class docstring). Its arrays are this
        list's kept buffers: valid while it is the current list; the next search (or,
        for a pruned list, prune) writes over them (copy them to keep them longer)."""
        return self._clusters

    @property
    def frame(self) -> SlotFrame | None:
        """The slot frame of the last build (None after an O(N^2) build over atom indices:
        use ``starts``)."""
        if self._slots_pending:
            self._slot_list()
        memo = self._frame_memo
        if (
            memo is not None
            and memo[0] == self.n_builds
            and memo[1] == self.n_prunes
            and memo[2] == self.n_followed
            and memo[3] is self.bounds  # the chunks may be set again between builds
        ):
            return memo[4]
        if self.order is None:
            return None
        frame = SlotFrame(
            self.order,
            self.images,
            self.lengths,
            self.shifts,
            self.slot_starts,
            self.slot_neighbors,
            self.codes,
            self.bounds,
            self.tilt,
            self.shifted_rows,
        )
        self._frame_memo = (self.n_builds, self.n_prunes, self.n_followed, self.bounds, frame)
        return frame

    @property
    def reference_positions(self) -> NDArray[np.float64] | None:
        """Positions at the last build (a copy), or None before the first."""
        return None if self._reference is None else self._reference.copy()

    @property
    def reference_cell(self) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
        """Edge lengths and tilt of the cell at the last build (copies), or None."""
        if self._reference is None:
            return None
        return self._box.copy(), self._tilt.copy()

    def rebuild_at(
        self,
        state: State,
        positions: NDArray[np.float64],
        box=None,
        tilt=None,
        pruned=None,
        step=None,
    ) -> None:
        """Build the list as it was built at ``positions`` (a checkpoint's), for ``state``.

        ``box`` and ``tilt`` are the cell of that build (default: ``state``'s);
        the list then follows the cell to ``state``'s, as it had in the run;
        ``pruned``, the positions of the cluster list's last prune
        (:attr:`pruned_positions`), prunes it there; ``step``, the step of that build
        (:attr:`built_step`; default: ``state``'s), from which ``every`` counts. A
        resumed run so has the same list, hence the same force summation order, as
        the run that was never interrupted. (A list looked at every ``every`` steps
        does not look at ``state``'s positions again at ``state``'s step: the run
        evaluated them within the step before, as a step ends, and looked there.)
        """
        at_build = state.copy()
        at_build.positions[:] = positions
        if step is not None:
            at_build.step = int(step)
        if box is not None:
            at_build.box = np.array(box, dtype=np.float64)
            at_build.tilt = np.zeros(3) if tilt is None else np.array(tilt, dtype=np.float64)
        self.build(at_build)
        if pruned is not None and self._outer is not None:
            pruned = np.asarray(pruned, dtype=np.float64)
            if pruned.shape != state.positions.shape:
                raise ValueError(
                    f"pruned positions have shape {pruned.shape}, the state {state.positions.shape}"
                )
            self._prune(pruned)
        if not self.exact:
            self._resumed_at = (int(state.step), state.positions.copy())
        self.update(state)

    @property
    def outer_clusters(self) -> ClusterFrame | None:
        """The outer cluster list of the last search (``outer_skin``), or None where the
        list is not pruned."""
        return self._outer

    @property
    def pruned_positions(self) -> NDArray[np.float64] | None:
        """Positions at the last prune of the cluster list (a copy; the search's own
        positions if none since), or None where the list is not pruned."""
        return None if self._outer is None else self._pruned_at.copy()

    @property
    def starts(self) -> NDArray[np.int64]:
        return self._atom_space()[0]

    @property
    def neighbors(self) -> NDArray[np.int32]:
        return self._atom_space()[1]

    def atom_lists(self) -> tuple[NDArray[np.int64], NDArray[np.int32]]:
        """(``starts``, ``neighbors``) in one Python call where they are at hand (the pair
        frame's kept call over atom indices checks both at every call: six calls a step)."""
        if self._slots_pending or (self.order is not None and self._atom_list is None):
            return self._atom_space()
        return (self.slot_starts, self.slot_neighbors) if self.order is None else self._atom_list

    def check_box(self, box: NDArray[np.float64], pbc: NDArray[np.bool_], tilt=None) -> None:
        """Raise ValueError if the cutoff breaks the minimum-image convention.

        An orthorhombic box needs every periodic edge longer than twice the
        cutoff. A tilted cell needs every perpendicular width (the distance
        between opposite faces) longer than twice the list radius, cutoff plus
        skin: only then does the minimum image find every listed pair.
        """
        if not is_orthorhombic(periodic_tilt(tilt, pbc)):
            widths = perpendicular_widths(box, tilt)
            too_narrow = pbc & (widths <= 2.0 * self.list_radius)
            if np.any(too_narrow):
                axis = int(np.argmax(too_narrow))
                tilts = ", ".join(f"{n} = {t:g}" for n, t in zip(TILT_NAMES, tilt, strict=True))
                raise ValueError(
                    f"cutoff + skin = {self.list_radius:g} is too long for the cell: its width "
                    f"across {'xyz'[axis]} is {widths[axis]:g} (edges {box.tolist()}, tilt "
                    f"{tilts}), and the minimum-image convention needs every perpendicular "
                    f"width longer than 2 * (cutoff + skin) = {2 * self.list_radius:g}; "
                    "use a larger cell or smaller tilt factors"
                )
            return
        too_short = pbc & (box <= 2.0 * self.cutoff)
        if np.any(too_short):
            axis = "xyz"[int(np.argmax(too_short))]
            raise ValueError(
                f"cutoff {self.cutoff:g} is too long for the box: the periodic edge "
                f"along {axis} is {box[np.argmax(too_short)]:g}, and the minimum-image "
                f"convention needs every periodic edge longer than 2 * cutoff = "
                f"{2 * self.cutoff:g}"
            )

    def needs_rebuild(self, state: State) -> bool:
        """Return True if the list no longer covers every pair within the cutoff.

        A cell that changed since the build (a barostat) is followed, not
        rebuilt for, while the list still covers it (see :meth:`update`).
        """
        return self._verdict(state) is True

    def exact_check(self, state: State) -> tuple | None:
        """``(reference, allowed2)`` when :meth:`update` of ``state`` would apply the half-skin
        rule alone, in one pass (the exact list in its build's own cell, which it never
        left, of a system checked on one chunk): the list holds while no atom is farther
        than ``sqrt(allowed2)`` from its place in ``reference`` (N, 3), else it is to be
        rebuilt. None otherwise (then only :meth:`update` decides). A fused step (velocity
        Verlet's, ``PairPotential.verlet_step``) checks this itself and calls
        :meth:`update` only when an atom moved farther."""
        reference = self._reference
        if (
            self.every == 1
            and self.check
            and self._outer is None
            and reference is not None
            and self._pass_chunks == 1
            and reference.shape == state.positions.shape
            and self.n_followed == self._followed_at_build
            and (state.box.tobytes(), state.tilt.tobytes(), state.pbc.tobytes()) == self._cell_bytes
        ):
            return reference, self._rebuild_distance2
        return None

    def cluster_check(self, state: State) -> tuple | None:
        """``(held, allowed2)`` when :meth:`update` of ``state`` would keep the exact cluster
        list, as it stands, for as long as no atom is farther than ``sqrt(allowed2)`` from
        its place in ``held`` (N, 3: the positions of the last prune, or of the search
        where the list is not pruned), and otherwise prune or search again: the exact
        cluster list in its build's own cell, which it never left. None otherwise (then
        only :meth:`update` decides). The mixed-precision fused step
        (``PairPotential.mixed_verlet_step``) checks this in its pass over the atoms and
        calls :meth:`update` only when an atom moved farther."""
        reference = self._reference
        if (
            self._clusters is None
            or not self.exact
            or reference is None
            or reference.shape != state.positions.shape
            or self.n_followed != self._followed_at_build
            or (state.box.tobytes(), state.tilt.tobytes(), state.pbc.tobytes()) != self._cell_bytes
        ):
            return None
        held = reference if self._outer is None else self._pruned_at
        return held, self._rebuild_distance2

    def update(self, state: State, moved2: float | None = None) -> bool:
        """Rebuild the list if needed; return True if it was rebuilt.

        When the cell changed within what the list covers (a barostat's small
        deformation), the pairs, slots and image codes are kept and the cell
        is followed: ``lengths``, ``tilt`` and ``shifts`` become the new
        cell's, so slot positions and image shifts are those of the new cell.

        ``moved2``: the largest squared distance of ``state``'s atoms from the ``held``
        positions of :meth:`cluster_check` (of the same state, list and cell), measured
        by the caller's own pass (the mixed-precision fused step's), so that this
        update does not measure it again; ignored unless the half-skin rule alone
        decides (as :meth:`cluster_check` says).
        """
        reference = self._reference
        if (
            self.every == 1
            and self.check
            and reference is not None
            and reference.shape == state.positions.shape
            and self.n_followed == self._followed_at_build
            and (state.box.tobytes(), state.tilt.tobytes(), state.pbc.tobytes()) == self._cell_bytes
        ):
            # The exact list in the build's own cell, which it never left (every step of
            # an NVE or NVT run): the half-skin rule alone, as _verdict applies it, with
            # the chunks counted at the build (the largest displacement is the same on
            # any number of them); with an outer cluster list, measured from its last
            # prune, then (past half the skin) from the search to choose a prune or a
            # search, as _verdict would.
            outer = self._outer is not None
            if moved2 is None or self._clusters is None:
                since = self._pruned_at if outer else reference
                moved2 = _largest_displacement2(state.positions, since, self._pass_chunks)
            if moved2 <= self._rebuild_distance2:
                return False
            if not math.isfinite(moved2):
                raise NonFiniteError("particle positions are not finite")
            if outer:
                # No atom is farther from the search's positions than its distance from
                # the last prune's plus theirs from the search's (a bound, widened by far
                # more than rounding): within the prune distance, the measure it spares
                # would choose the prune as well (the same lists)
                bound = math.sqrt(moved2) + self._pruned_from_search
                if bound * (1.0 + 1e-9) <= self._prune_distance:
                    self.n_bounded_prunes += 1
                    self._prune(state.positions, bound)
                    return False
                moved2 = _largest_displacement2(state.positions, reference, self._pass_chunks)
                if moved2 <= self._prune_distance2:
                    self._prune(state.positions, math.sqrt(moved2))
                    return False
            self.build(state)
            return True
        verdict = self._verdict(state)
        if verdict is True:
            self.build(state)
            return True
        if verdict is _PRUNE:
            self._prune(state.positions)
            return False
        if verdict is None:  # the build's own cell
            if self.n_followed == self._followed_at_build:
                return False  # never left it: nothing to restore
            verdict = self._build_cell
        lengths, tilt = verdict  # also the build's own cell, back from following another
        if not (np.array_equal(lengths, self.lengths) and np.array_equal(tilt, self.tilt)):
            self.lengths, self.tilt = lengths, tilt
            if self.order is not None:
                self.shifts = _shift_table(state.box, state.pbc, tilt)
            self.n_followed += 1
        return False

    def _verdict(self, state: State):
        """True: rebuild; None: the list holds and ``state``'s cell is the build's;
        ``_PRUNE``: prune the outer cluster list again (``outer_skin``); else the
        list holds in the cell of ``state``, whose periodic lengths and tilt are
        returned.

        With the cells H0 at the build and H now (rows: cell vectors), the
        build's positions mapped affinely are r0 M, M = H0^-1 H. A pair not
        listed was farther than rc + skin apart at the build, so at least
        s (rc + skin) apart after the mapping (s: the smallest singular value
        of M), and at least s (rc + skin) - 2 d now, where d is the largest
        distance of an atom from its mapped position. Nothing within the
        cutoff rc is missed while d <= (s (rc + skin) - rc) / 2; with M = 1
        this is the usual half-skin rule.
        """
        if self._reference is None or self._reference.shape != state.positions.shape:
            return True
        pbc = state.pbc
        # Byte equality first (each step: the fast test of an unchanged cell), then values.
        same_cell = (state.box.tobytes(), state.tilt.tobytes(), pbc.tobytes()) == self._cell_bytes
        if not same_cell:
            if not np.array_equal(self._pbc, pbc):
                return True
            same_cell = np.array_equal(self._box, state.box) and np.array_equal(
                self._tilt, state.tilt
            )
            if not same_cell and self._clusters is not None:
                return True  # cluster offsets and origins hold the build's box lengths
        if same_cell and not self.exact:
            if self._resumed_at is not None:
                step, positions = self._resumed_at
                if state.step == step and np.array_equal(state.positions, positions):
                    return None  # the resume's own positions, looked at before the checkpoint
                self._resumed_at = None
            since = state.step - self._built_step
            if 0 <= since < self.every:
                return None  # not a look: kept whatever the atoms did
            if not self.check:
                self._note_late_look(state)  # one pass per look, to say what was missed
                return True
        chunks = chunk_count(len(self._reference), _MIN_PASS_ATOMS)
        if same_cell and self._outer is not None:
            moved2 = _largest_displacement2(state.positions, self._pruned_at, chunks)
            if not math.isfinite(moved2):
                raise NonFiniteError("particle positions are not finite")
            if moved2 <= self._rebuild_distance2:
                return None
            moved2 = _largest_displacement2(state.positions, self._reference, chunks)
            return _PRUNE if moved2 <= self._prune_distance2 else True
        if same_cell:
            reference, allowed2 = self._reference, self._rebuild_distance2
        else:
            try:
                self.check_box(state.box, pbc, state.tilt)
            except ValueError:
                return True  # the build raises it
            before = cell_matrix(np.where(pbc, self._box, 1.0), periodic_tilt(self._tilt, pbc))
            after = cell_matrix(np.where(pbc, state.box, 1.0), periodic_tilt(state.tilt, pbc))
            m = np.linalg.solve(before, after)
            smallest = float(np.linalg.svd(m, compute_uv=False).min())
            allowed = 0.5 * (smallest * self.list_radius - self.cutoff)
            if not allowed > 0:
                return True
            reference, allowed2 = self._reference @ m, _square(allowed)
        moved2 = _largest_displacement2(state.positions, reference, chunks)
        if not math.isfinite(moved2):
            raise NonFiniteError("particle positions are not finite")
        if moved2 > allowed2:
            if same_cell and not self.exact:  # a look found the list stale already
                self._count_late_look(state, moved2)
            return True
        if same_cell:
            return None
        return periodic_lengths(state.box, pbc)[0], periodic_tilt(state.tilt, pbc)

    def _note_late_look(self, state: State) -> None:
        """At a look of a list rebuilt there unchecked (``check=False``): count it in
        :attr:`n_late_looks` if an atom moved more than ``skin / 2`` since the build."""
        chunks = chunk_count(len(self._reference), _MIN_PASS_ATOMS)
        moved2 = _largest_displacement2(state.positions, self._reference, chunks)
        if moved2 > self._rebuild_distance2:  # NaN: the build raises it
            self._count_late_look(state, moved2)

    def _count_late_look(self, state: State, moved2: float) -> None:
        """A look (``every > 1`` or no check) found an atom more than ``skin / 2`` from
        where the list was built: pairs may have come within the cutoff unseen since.
        Counted; the first one of the list is logged as a warning."""
        self.n_late_looks += 1
        if self.n_late_looks > 1:
            return
        logger.warning(
            "neighbour list looked at every %d steps%s: at step %d an atom had moved %.4g "
            "since the build at step %d, more than skin/2 = %.4g, so pairs within the "
            "cutoff may have been missed meanwhile (the energy drifts); a larger skin or a "
            "smaller neighbor_every avoids it (further such looks are only counted)",
            self.every,
            "" if self.check else " without the check",
            int(state.step),
            math.sqrt(moved2),
            self._built_step,
            0.5 * self.skin,
        )

    def build(self, state: State) -> None:
        """Build the list from scratch for ``state``."""
        positions = state.positions
        n = positions.shape[0]
        # The old reference's memory takes the new one (no list is valid until this
        # build completes: an error on the way leaves one that asks to be rebuilt).
        reference, self._reference = self._reference, None
        if reference is None or reference.shape != positions.shape:
            reference = np.empty_like(positions)
        largest = _largest_coordinates(positions, reference)  # inf if any is not finite
        if not all(map(math.isfinite, largest)):
            raise NonFiniteError("particle positions are not finite")
        lengths, tilt, grid, shifts, limits = self._cell_data(state)
        if largest[0] > limits[0] or largest[1] > limits[1] or largest[2] > limits[2]:
            raise NonFiniteError(
                f"particle positions lie more than {_MAX_IMAGES:g} box lengths from the box"
            )
        self._frame_memo = None  # a build that fails leaves no frame behind
        # Drop the old list first, so it and the new one are never held together.
        self.order, self._atom_list, self._clusters, self._outer = None, None, None, None
        self._repeats = False
        self._prune_relative = None
        self.images = self.slot_neighbors = self.codes = self.slot_starts = None
        self.shifted_rows = None
        self._slots_pending = False
        self._ghost_tests.fill(0)
        self.lengths = lengths
        self.tilt = tilt
        self.used_cells = grid is not None
        # the rows that may hold pairs: a rank's owned atoms (keep_owned), else every atom
        self._listed_rows = n if self._owned is None else self._owned_ids(n)[1]
        threads = parallel.get_threads()  # (chunk_count's, once: 2 Python calls fewer)
        chunks = max(1, min(threads, n // _MIN_CHUNK_ATOMS))
        # (a rank's list, keep_owned, is never a cluster one: not asked)
        columns = None if grid is None or self._owned is not None else self._cluster_columns(state)
        if columns is not None:
            self._build_clusters(state, columns, chunks)
            if self._prune_relative is not None:  # the search's, at these positions
                self._clusters.relative = self._prune_relative
            self.shifts = shifts
            self._slots_pending = True
        elif grid is None and self._small_box_serves(state):
            self._build_small_box(state, chunks)
            self.shifts = shifts
        elif grid is None:
            self._build_brute_force(state)
            self.bounds = _balanced_bounds(self.slot_starts[: self._listed_rows + 1], chunks)
        elif n > MAX_SLOTS:
            raise ValueError(
                f"the cell search lists at most {MAX_SLOTS} atoms per process, got {n}"
            )
        else:
            self._build_cells(state, grid, chunks)
            self.shifts = shifts
        if self._groups is not None:
            self._drop_grouped(chunks)
        self._reference = reference
        cell_bytes = (state.box.tobytes(), state.tilt.tobytes(), state.pbc.tobytes())
        if cell_bytes != self._cell_bytes:  # (else the copies held are of the same bits)
            self._box = state.box.copy()
            self._tilt = state.tilt.copy()
            self._pbc = state.pbc.copy()
            self._cell_bytes = cell_bytes
        self._build_cell = (self.lengths, self.tilt)
        self._followed_at_build = self.n_followed
        self._built_step = int(state.step)
        self._resumed_at = None
        self._pass_chunks = max(1, min(threads, n // _MIN_PASS_ATOMS))
        self.n_builds += 1

    def _cell_data(self, state: State):
        """(lengths, tilt, grid, shifts, limits) of a build in ``state``'s cell, after
        ``check_box``; ``limits``: the farthest a coordinate may lie from the origin
        along each axis (floats; inf along open axes).

        Kept for the next build while the cell is unchanged (whatever the atom count, which
        a decomposed rank's local system changes at every build): a build in a run then
        skips some thirty small numpy calls, each slow in a run, where the pair kernels
        have evicted the interpreter's data from the caches. Along an open axis the
        grid spans the atoms, so a cell with one (a rank of a decomposed run, open along
        its cut axes) finds its grid again at each build, in one compiled call
        (``_cell_grid``: the numpy of ``_grid`` took 21 of a 1080-atom rank's 144 us a
        build).
        """
        key = (
            state.box.tobytes(),
            state.tilt.tobytes(),
            state.pbc.tobytes(),
            self.cutoff,
            self.skin,
        )
        memo = self._cell_memo
        if memo is None or memo[0] != key:
            self.check_box(state.box, state.pbc, state.tilt)
            lengths, _ = periodic_lengths(state.box, state.pbc)
            tilt = periodic_tilt(state.tilt, state.pbc)
            limits = tuple(
                _MAX_IMAGES * x if periodic else math.inf
                for x, periodic in zip(lengths.tolist(), state.pbc.tolist(), strict=True)
            )
            across = perpendicular_widths(state.box, tilt)
            shifts = _shift_table(state.box, state.pbc, tilt)
            memo = (key, (lengths, tilt, across, shifts, limits), bool(np.all(state.pbc)), {})
            self._cell_memo = memo
        lengths, tilt, across, shifts, limits = memo[1]
        grids = memo[3]  # a periodic cell's grid per atom count (the most cells it may have)
        n = state.positions.shape[0]  # (State.n_atoms is a property: a Python call each)
        grid = grids.get(n, False)
        if grid is False:
            grid = self._grid(state, across)
            if memo[2]:
                if len(grids) > 8:  # (a rank's count changes at every build)
                    grids.clear()
                grids[n] = grid
        return lengths, tilt, grid, shifts, limits

    def _cluster_columns(self, state: State) -> tuple[int, int] | None:
        """(ncx, ncy) of a cluster build of ``state``, or None where the slot frame serves."""
        if (
            not self.clusters_wanted
            or self._owned is not None
            or self._groups is not None  # whole blocks of pairs: exclusions need the slot frame
            or numba_config.DISABLE_JIT
        ):
            return None
        box = state.box
        if not (np.all(state.pbc) and is_orthorhombic(state.tilt)) or np.any(
            box <= 2 * self.list_radius
        ):
            return None
        return column_counts(box, state.n_atoms, self._search_radius(box, state.n_atoms))

    def _search_radius(self, box: NDArray[np.float64], n_atoms: int) -> float:
        """The radius of a cluster search in ``box``: the outer list's where the list is
        exact and the box wider than twice it (pruning on), else the list radius. Not the
        outer one either where it needs more than twice the columns the density asks for
        (:func:`md.neighbors._cluster_grid.column_counts`: a box just over twice the radius wide,
        such as 500 atoms of the LJ melt at 4.0 sigma, needed 23 x 23 columns for 125
        clusters, and its search took 4 ms against 0.2 at the list radius)."""
        outer = self.cutoff + self.outer_skin
        if self.exact and self.outer_skin > self.skin and np.all(box > 2 * outer):
            natural = column_counts(box, n_atoms, 0.0)
            needed = column_counts(box, n_atoms, outer)
            if all(k <= 2 * m for k, m in zip(needed, natural, strict=True)):
                return outer
        return self.list_radius

    def _build_clusters(self, state: State, columns: tuple[int, int], chunks: int) -> None:
        """The cluster grid, search and (with an outer list) the search's own prune, into
        the arrays this list keeps from build to build (``self._kept``): a build writes
        over the last one's lists (no longer current: dropped by ``build``) and so needs
        no fresh memory; with glibc's own malloc thresholds fresh arrays cost page faults
        at each search (:mod:`md._memory`; ``benchmarks/cluster_pruning.py`` counts them)."""
        ncx, ncy = columns
        kept = self._kept
        first, atom, origin, lower, upper = cluster_grid(
            state.positions, state.box, ncx, ncy, chunks, kept
        )
        radius = self._search_radius(state.box, state.n_atoms)
        # the pairs with an atom pair within reach, checked in float32: the radius widened
        # by 1e-5 so that rounding can only keep a pair more, never drop one
        xi = kept.take("relative i", 3 * len(atom), np.float32)
        xj = kept.take("relative j", 3 * len(atom), np.float32)
        _relative_positions(state.positions, atom, origin, xi, xj)  # as a prune's: threaded
        reach2 = np.float32((radius * (1.0 + 1e-5)) ** 2)
        # an outer list: pruned to the list radius in the same pass (the search's own prune)
        inner2 = self._prune_reach2() if radius > self.list_radius else None
        while True:
            found = search_pairs(
                state.box,
                ncx,
                ncy,
                first,
                lower,
                upper,
                radius,
                chunks,
                self._cluster_room,
                xi,
                xj,
                reach2,
                inner2,
                with_reach=True,
                kept=kept,
            )
            if found is not None:
                break
            self._cluster_room *= 2  # a dense or sparse system: rows longer than foreseen
        reach = found[-1]  # the rows' reach from the search's windows: no pass over the pairs
        frame = ClusterFrame(atom, origin, *found[:3], chunks, reach=reach)
        if inner2 is None:
            self._clusters, self._pruned_at = frame, None
            return
        self._outer = frame
        self._clusters = ClusterFrame(atom, origin, *found[3:6], chunks, reach=reach)
        self._prune_relative = (xi, xj)  # the prunes' to write over (see _prune)
        self._keep_pruned_at(state.positions)

    def _keep_pruned_at(self, positions: NDArray[np.float64], from_search: float = 0.0) -> None:
        """Keep ``positions`` as the last prune's, no atom farther than ``from_search``
        from where the search found it (0: the search's own positions)."""
        if self._pruned_at is None or self._pruned_at.shape != positions.shape:
            self._pruned_at = np.empty_like(positions)
        self._pruned_at[:] = positions
        self._pruned_from_search = from_search

    def _prune_reach2(self) -> np.float32:
        """The squared list radius of the prune's float32 check, widened by 1e-5 (as the
        search's) so that rounding can only keep a pair more, never drop one."""
        return np.float32((self.list_radius * (1.0 + 1e-5)) ** 2)

    def _prune(self, positions: NDArray[np.float64], from_search: float = math.inf) -> None:
        """The outer cluster list pruned to the pairs with an atom pair within the list
        radius at ``positions`` (checked in float32, the radius widened by 1e-5 as the
        search's is) becomes the list the kernels read; the slot list is built again
        on demand, at these positions. (The search prunes its own list as it writes it:
        ``search_pairs`` with ``inner2``.) ``from_search``: a bound on any atom's distance
        from its place at the search (inf: not known)."""
        self._frame_memo = None
        outer = self._outer
        n, size = outer.n_clusters, outer.n_pairs
        # One set of buffers kept from search to search (the relative positions: the
        # search's own), written over by each prune: a pruned list's arrays hold until
        # the next prune (copy them to keep them longer).
        kept = self._kept
        starts = kept.take("prune starts", n + 1, np.int64)
        partners = kept.take("prune partners", size, np.int32)
        offsets = kept.take("prune offsets", size, np.float32, (3,))
        marks = kept.take("prune marks", size, np.uint8)  # each outer pair's verdict
        xi, xj = self._prune_relative or (
            kept.take("relative i", 12 * n, np.float32),
            kept.take("relative j", 12 * n, np.float32),
        )
        outer.relative_positions(positions, xi, xj)
        reach2 = self._prune_reach2()
        kept = prune_pairs(
            outer.starts,
            outer.partners,
            outer.offsets,
            outer.bounds,
            xi,
            xj,
            reach2,
            starts,
            partners,
            offsets,
            marks,
        )
        chunks = len(outer.bounds) - 1
        self._clusters = ClusterFrame(
            outer.atom,
            outer.origin,
            starts,
            partners[:kept],
            offsets[:kept],
            chunks,
            reach=outer.reach if chunks > 1 else None,
            relative=(xi, xj),
        )
        self._keep_pruned_at(positions, from_search)
        if self._reference is not None:  # a prune between searches (not the search's own)
            self.n_prunes += 1
            self.order, self._atom_list = None, None
            self.images = self.slot_neighbors = self.codes = self.slot_starts = None
            self.shifted_rows = None
            self._slots_pending = True

    def _slot_list(self) -> None:
        """After a cluster build or prune, build the slot list at its positions and the
        build's cell (once): what the frame's kernels, per-atom results and ``pairs()``
        read."""
        if not self._slots_pending:
            return
        self._slots_pending = False
        self._frame_memo = None
        at = self._reference if self._pruned_at is None else self._pruned_at
        at_build = State(
            positions=at.copy(), box=self._box.copy(), pbc=self._pbc.copy(), tilt=self._tilt.copy()
        )
        lengths, tilt = self.lengths, self.tilt  # the cell followed since, if any
        _, _, grid, _, _ = self._cell_data(at_build)
        self._build_cells(at_build, grid, chunk_count(at_build.n_atoms, _MIN_CHUNK_ATOMS))
        self.lengths, self.tilt = lengths, tilt

    def _build_brute_force(self, state: State) -> None:
        positions = state.positions
        n = positions.shape[0]
        lengths, inverse = periodic_lengths(state.box, state.pbc)
        starts = np.zeros(n + 1, dtype=np.int64)
        r2_max = self._list_radius2
        while True:
            if self._owned is None:
                count = _brute_force_pairs(
                    positions, lengths, inverse, self.tilt, r2_max, starts, self._neighbor_buffer
                )
            else:  # a rank's: the owned rows only
                count = _owned_brute_force_pairs(
                    positions,
                    self._listed_rows,
                    self._owned[0],
                    lengths,
                    inverse,
                    self.tilt,
                    r2_max,
                    starts,
                    self._neighbor_buffer,
                )
            if count <= self._neighbor_buffer.shape[0]:
                break
            # Both buffers grow together: the cell search fills them side by side, and
            # a code buffer left shorter would be written past its end after a switch
            # from this search to cells (a box that grew under a barostat).
            self._neighbor_buffer = np.empty(_grown(count), dtype=np.int32)
            self._code_buffer = np.empty(_grown(count), dtype=np.uint8)
        self.order = None
        self.shifted_rows = np.zeros(0, dtype=np.bool_)
        self.images = np.zeros((n, 3), dtype=np.int32)
        self.slot_starts = starts
        self.slot_neighbors = self._neighbor_buffer[:count]
        self.codes = np.zeros(0, dtype=np.uint8)
        self.shifts = np.zeros((27, 3))

    def _small_box_serves(self, state: State) -> bool:
        """Whether the slot-frame O(N^2) search (``_small_box_list``) builds the list of a
        cell the cell search cannot: every periodic perpendicular width longer than the
        list radius (so shifts of one cell vector find every image within reach) and a
        list of every pair (no :meth:`keep_owned`). Kept for the next build in the same cell."""
        if self._owned is not None or state.n_atoms < 2:
            return False
        key = (state.box.tobytes(), state.tilt.tobytes(), state.pbc.tobytes())
        if self._small_memo is None or self._small_memo[0] != key:
            widths = perpendicular_widths(state.box, periodic_tilt(state.tilt, state.pbc))
            self._small_memo = (key, bool(np.all(widths[state.pbc] > self.list_radius)))
        return self._small_memo[1]

    def _build_small_box(self, state: State, chunks: int) -> None:
        r2_max = self._list_radius2
        while True:
            order, images, starts, bounds, count, shifted, repeats = _small_box_list(
                state.positions,
                state.pbc,
                state.box,
                self.tilt,
                r2_max,
                chunks,
                self._neighbor_buffer,
                self._code_buffer,
            )
            if count >= 0:
                break
            self._neighbor_buffer = np.empty(_grown(-count), dtype=np.int32)
            self._code_buffer = np.empty(_grown(-count), dtype=np.uint8)
        self.order = order
        self.images = images
        self.slot_starts = starts
        self.slot_neighbors = self._neighbor_buffer[:count]
        self.codes = self._code_buffer[:count]
        self.shifted_rows = shifted
        self.bounds = bounds
        self._repeats = bool(repeats)

    def _build_cells(self, state: State, grid, chunks: int) -> None:
        origin, width, n_cells, reach = grid
        r2_max = self._list_radius2
        while True:
            if self._owned is None:
                found = _cell_list(
                    state.positions,
                    origin,
                    width,
                    n_cells,
                    reach,
                    state.pbc,
                    state.box,
                    self.tilt,
                    r2_max,
                    chunks,
                    self._neighbor_buffer,
                    self._code_buffer,
                )
            else:  # a rank's: owned rows only, no pair of two ghosts searched
                if self._ghost_tests.shape[0] < chunks:
                    self._ghost_tests = np.zeros(chunks, dtype=np.int64)
                found = _owned_cell_list(
                    state.positions,
                    self._listed_rows,
                    self._owned[0],
                    origin,
                    width,
                    n_cells,
                    reach,
                    state.pbc,
                    state.box,
                    self.tilt,
                    r2_max,
                    chunks,
                    self._neighbor_buffer,
                    self._code_buffer,
                    self._ghost_tests,
                )
            order, images, starts, bounds, count, shifted = found
            if count >= 0:
                break
            size = _grown(-count * chunks)
            self._neighbor_buffer = np.empty(size, dtype=np.int32)
            self._code_buffer = np.empty(size, dtype=np.uint8)
        self.order = order
        self.images = images
        self.slot_starts = starts
        self.slot_neighbors = self._neighbor_buffer[:count]
        self.codes = self._code_buffer[:count]
        self.shifted_rows = shifted
        self.bounds = bounds

    def _owned_ids(self, n_atoms: int) -> tuple[NDArray[np.int64], int]:
        """:meth:`keep_owned`'s ids and owned count, checked against ``n_atoms``."""
        ids, n_owned = self._owned
        if ids.shape[0] != n_atoms:
            raise ValueError(f"keep_owned was given {ids.shape[0]} ids for {n_atoms} atoms")
        if not 0 <= n_owned <= n_atoms:
            raise ValueError(f"keep_owned was given {n_owned} owned atoms of {n_atoms}")
        return ids, n_owned

    def _drop_grouped(self, chunks: int) -> None:
        """Apply :meth:`exclude_groups` to the list just built."""
        n = len(self.slot_starts) - 1
        if self._groups.shape[0] != n:
            raise ValueError(
                f"exclude_groups was given {self._groups.shape[0]} groups for {n} atoms"
            )
        order = self.order if self.order is not None else np.zeros(0, dtype=np.int64)
        count = _drop_grouped_pairs(
            order, self.slot_starts, self.slot_neighbors, self.codes, self._groups
        )
        self.slot_neighbors = self.slot_neighbors[:count]
        self.codes = self.codes[:count] if len(self.codes) else self.codes
        self.bounds = _balanced_bounds(self.slot_starts[: self._listed_rows + 1], chunks)

    def frame_positions(self, positions: NDArray[np.float64]) -> NDArray[np.float64]:
        """Positions of the slots, ``positions[order] + images @ h`` (numpy; for tests)."""
        self._slot_list()
        if self.order is None:
            return positions.copy()
        return positions[self.order] + self.images @ cell_matrix(self.lengths, self.tilt)

    def _atom_space(self) -> tuple[NDArray[np.int64], NDArray[np.int32]]:
        """The list over atom indices (cached until the next build)."""
        self._slot_list()
        if self.order is None:
            return self.slot_starts, self.slot_neighbors
        if self._atom_list is None:
            n = len(self.order)
            starts = np.empty(n + 1, dtype=np.int64)
            neighbors = np.empty(self.n_pairs, dtype=np.int32)
            _atom_space_list(self.order, self.slot_starts, self.slot_neighbors, starts, neighbors)
            if self._repeats:  # once per pair: the minimum image finds the nearest
                neighbors = neighbors[: _drop_repeats(starts, neighbors)]
            self._atom_list = (starts, neighbors)
        return self._atom_list

    def pairs(self) -> NDArray[np.int64]:
        """Return the listed pairs as a sorted (P, 2) array of (i, j) with i < j."""
        rows = np.repeat(np.arange(len(self.starts) - 1), np.diff(self.starts))
        cols = self.neighbors.astype(np.int64)
        pairs = np.stack([np.minimum(rows, cols), np.maximum(rows, cols)], axis=1)
        return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]

    def _grid(self, state: State, across=None):
        """Return (origin, width, n_cells, reach) of the cell grid, or None for O(N^2) search.

        Cells are the list radius / ``_REACH`` wide and every periodic axis
        needs 2 ``_REACH`` + 1 of them. Half-radius cells (reach 2), scanned
        in z columns, hold about 40% fewer candidates than radius-wide ones.
        Cells are binned in sheared-back coordinates, where the cell is the box
        of edges ``box``; their count along a periodic axis comes from the
        perpendicular width (``across``, found from the cell if not given), so
        each slab of cells is radius / reach thick; along an open axis the grid
        spans the atoms (``_cell_grid``).
        """
        n = state.positions.shape[0]
        if n < 2:
            return None
        if across is None:
            across = perpendicular_widths(state.box, periodic_tilt(state.tilt, state.pbc))
        box = state.box  # (a State's is float64; a writable array: the kernel's one signature)
        if box.dtype != np.float64 or not box.flags.writeable:
            box = box.astype(np.float64)
        origin, width, n_cells, fits = _cell_grid(
            state.positions,
            state.pbc,
            box,
            across,
            self.cutoff + self.skin,  # (list_radius, without its property's call)
            _REACH,
            _MAX_CELLS_PER_ATOM * n + 27,
        )
        return (origin, width, n_cells, _REACH) if fits else None


def _grown(count: int) -> int:
    """Buffer size for ``count`` pairs with head room for the next builds."""
    return int(count * _GROWTH) + 1024
