"""Builders for bead-spring polymers: Kremer-Grest melts and single chains.

Each builder returns ``(state, bonds)``: a :class:`~md.state.State` with
unit masses and one bead type ``"M"``, and the (B, 2) bond list for
:class:`potentials.springs.FENEBonds` or :class:`~potentials.springs.HarmonicBonds`.
:func:`chain_angles` gives the matching (A, 3) angle list (consecutive
triples along each chain) for :mod:`potentials.angles`, which makes the
chains semiflexible.
Chains are grown as random walks of fixed step ``bond_length`` that reject
any step landing closer than ``min_distance`` to a bead already placed
(minimum image along periodic axes), so the structure starts free of
overlaps and the WCA repulsion stays finite. Positions are continuous
(unwrapped), like every State: bonded beads are ``bond_length`` apart in
plain coordinates.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from md._checks import count, positive
from md.state import State

#: Random directions tried at once for each new bead.
_TRIALS_PER_BATCH = 32
#: Batches of directions tried before a chain is abandoned as a dead end.
_BATCHES_PER_BEAD = 4
#: Dead ends one attempt at a chain backs out of before starting it afresh.
_BACKTRACKS_PER_CHAIN = 100
#: Attempts at growing one chain before giving up.
_ATTEMPTS_PER_CHAIN = 50
#: Largest excluded-volume fraction density * pi/6 * min_distance^3 that
#: growth is tried at. Random sequential addition of spheres jams at 0.38;
#: chains jam earlier (about 0.28 in trials: density 1.03 at min_distance 0.8).
_MAX_FRACTION = 0.275


def polymer_melt(
    n_chains: int,
    chain_length: int,
    density: float = 0.85,
    bond_length: float = 0.97,
    seed: int | np.random.Generator | None = None,
    box_shape: str = "cubic",
    min_distance: float = 0.8,
) -> tuple[State, NDArray[np.int64]]:
    """Build a Kremer-Grest style bead-spring polymer melt in a periodic cubic box.

    Parameters
    ----------
    n_chains : int
        Number of chains, >= 1.
    chain_length : int
        Beads per chain, >= 2.
    density : float
        Bead number density [1/length^3]; the box edge is
        ``(n_chains * chain_length / density) ** (1/3)``. 0.85 is the
        Kremer-Grest melt.
    bond_length : float
        Distance between bonded beads [length]; 0.97 is the mean bond
        length of a Kremer-Grest melt (FENE k = 30, r_max = 1.5, with WCA).
    seed : int, numpy Generator or None
        Random seed or generator for the walks.
    box_shape : {"cubic"}
        Only cubic boxes are built.
    min_distance : float
        No two beads that are not bonded to each other start closer than
        this [length].

    Returns
    -------
    state : State
        ``n_chains * chain_length`` beads at rest, chain by chain (bead ``b``
        of chain ``c`` is atom ``c * chain_length + b``), masses 1, type "M".
    bonds : ndarray of int64, shape (n_chains * (chain_length - 1), 2)
        Bonded pairs ``(i, i + 1)`` within each chain.

    Raises
    ------
    ValueError
        For invalid counts or lengths, a box shorter than twice the bond
        length, or a density too high to place the chains.

    Examples
    --------
    >>> state, bonds = polymer_melt(4, 10, seed=1)
    >>> state.n_atoms, bonds.shape
    (40, (36, 2))
    """
    n_chains = count(n_chains, "n_chains", 1)
    chain_length = count(chain_length, "chain_length", 2)
    density = positive(density, "density")
    bond_length = positive(bond_length, "bond_length")
    min_distance = positive(min_distance, "min_distance", allow_zero=True)
    if box_shape != "cubic":
        raise ValueError(f"box_shape must be 'cubic', got {box_shape!r}")
    fraction = density * np.pi / 6.0 * min_distance**3
    if fraction > _MAX_FRACTION:
        raise ValueError(
            f"density {density:g} is too high to place beads at least {min_distance:g} apart "
            f"by random growth (the excluded-volume fraction {fraction:.3g} exceeds "
            f"{_MAX_FRACTION}); lower the density or min_distance"
        )
    n_atoms = n_chains * chain_length
    edge = (n_atoms / density) ** (1.0 / 3.0)
    if edge <= 2.0 * bond_length:
        raise ValueError(
            f"the box edge {edge:.4g} for {n_atoms} beads at density {density:g} is not longer "
            f"than twice the bond length ({2 * bond_length:g}), so bonds have no unique minimum "
            "image; use more or longer chains"
        )
    box = np.full(3, edge)
    pbc = np.ones(3, dtype=bool)
    rng = np.random.default_rng(seed)
    positions = _grow(n_chains, chain_length, bond_length, min_distance, box, pbc, rng)
    return _result(positions, box, pbc, n_chains, chain_length)


def single_chain(
    n_beads: int,
    bond_length: float = 0.97,
    straight: bool = False,
    seed: int | np.random.Generator | None = None,
    box: ArrayLike | None = None,
    pbc: bool | ArrayLike = False,
    min_distance: float = 0.8,
) -> tuple[State, NDArray[np.int64]]:
    """Build one bead-spring chain, straight along x or a self-avoiding random walk.

    Parameters
    ----------
    n_beads : int
        Number of beads, >= 2.
    bond_length : float
        Distance between bonded beads [length].
    straight : bool
        Beads on a line along +x; otherwise a random walk in which no two
        beads that are not bonded to each other come closer than ``min_distance``.
    seed : int, numpy Generator or None
        Random seed or generator for the walk.
    box : float or sequence of 3 floats, optional
        Box edges [length]. By default a cube 5 longer than the chain's
        largest extent (so a periodic chain is 5 away from its images); the
        chain is centred in the box.
    pbc : bool or sequence of 3 bool
        Periodicity. Along periodic axes the self-avoidance uses the minimum
        image and every edge must exceed twice the bond length.
    min_distance : float
        Closest approach of beads that are not bonded to each other [length].

    Returns
    -------
    state : State
        The beads at rest, masses 1, type "M".
    bonds : ndarray of int64, shape (n_beads - 1, 2)
        ``(i, i + 1)`` for every bead but the last.

    Examples
    --------
    >>> state, bonds = single_chain(5, bond_length=1.0, straight=True)
    >>> state.positions[:, 0] - state.positions[0, 0]
    array([0., 1., 2., 3., 4.])
    """
    n_beads = count(n_beads, "n_beads", 2)
    bond_length = positive(bond_length, "bond_length")
    min_distance = positive(min_distance, "min_distance", allow_zero=True)
    pbc = np.broadcast_to(np.asarray(pbc, dtype=bool), (3,)).copy()
    rng = np.random.default_rng(seed)
    margin = 5.0
    if box is not None:
        box = np.broadcast_to(np.asarray(box, dtype=np.float64), (3,)).copy()
        if not np.all(np.isfinite(box) & (box > 0)):
            raise ValueError(f"box edges must be positive and finite, got {box.tolist()}")
        short = pbc & (box <= 2.0 * bond_length)
        if np.any(short):
            raise ValueError(
                f"periodic box edges {box[short].tolist()} must exceed twice the bond length "
                f"({2 * bond_length:g}) for bonds to have a unique minimum image"
            )
    if straight:
        positions = np.zeros((n_beads, 3))
        positions[:, 0] = bond_length * np.arange(n_beads)
        if bond_length < min_distance:
            raise ValueError(
                f"a straight chain with bond_length {bond_length:g} puts beads i and i + 2 "
                f"closer than min_distance {min_distance:g}"
            )
    else:
        # Open box while growing unless the caller fixed a periodic box.
        grow_box = box if box is not None else np.zeros(3)
        grow_pbc = pbc if box is not None else np.zeros(3, dtype=bool)
        positions = _grow(1, n_beads, bond_length, min_distance, grow_box, grow_pbc, rng)
    if box is None:
        extent = positions.max(axis=0) - positions.min(axis=0)
        box = np.full(3, float(extent.max()) + margin)
    centre = 0.5 * (positions.max(axis=0) + positions.min(axis=0))
    positions += 0.5 * box - centre
    if straight and np.any(pbc):
        # The straight line may meet its own periodic images.
        close = _closest_nonbonded(positions, box, pbc)
        if close < min_distance:
            raise ValueError(
                f"the straight chain of {n_beads} beads meets its periodic image "
                f"(closest non-bonded distance {close:.3g} < {min_distance:g}); "
                "enlarge the box along x"
            )
    return _result(positions, box, pbc, 1, n_beads)


# ------------------------------------------------------------------- helpers


def chain_angles(n_chains: int, chain_length: int) -> NDArray[np.int64]:
    """Return the angles of the chains the builders make: consecutive bead triples.

    Bead ``b`` of chain ``c`` is atom ``c * chain_length + b`` (as
    :func:`polymer_melt` and :func:`single_chain` number them); each chain
    of L beads has the L - 2 angles ``(i, i + 1, i + 2)``, the middle bead
    the vertex.

    Returns
    -------
    ndarray of int64, shape (n_chains * (chain_length - 2), 3)

    Examples
    --------
    >>> chain_angles(2, 4).tolist()
    [[0, 1, 2], [1, 2, 3], [4, 5, 6], [5, 6, 7]]
    """
    n_chains = count(n_chains, "n_chains", 1)
    chain_length = count(chain_length, "chain_length", 2)
    first = (np.arange(n_chains)[:, None] * chain_length + np.arange(chain_length - 2)).ravel()
    return np.stack([first, first + 1, first + 2], axis=1).astype(np.int64)


def _result(positions, box, pbc, n_chains: int, chain_length: int):
    state = State(positions=positions, masses=1.0, box=box, pbc=pbc, type_names=("M",))
    first = (np.arange(n_chains)[:, None] * chain_length + np.arange(chain_length - 1)).ravel()
    bonds = np.stack([first, first + 1], axis=1).astype(np.int64)
    return state, bonds


def _random_directions(rng: np.random.Generator, n: int) -> NDArray[np.float64]:
    """(n, 3) unit vectors uniform on the sphere."""
    v = rng.normal(size=(n, 3))
    norms = np.linalg.norm(v, axis=1, keepdims=True)
    norms[norms == 0] = 1.0
    return v / norms


class _Occupancy:
    """Beads placed so far, for overlap queries by minimum image.

    With a periodic cube at least three cells of ``cell_width`` wide, beads
    are binned in a cell grid and a query looks at the 27 cells around a
    point; otherwise it scans every bead.
    """

    def __init__(self, capacity: int, box, pbc, cell_width: float) -> None:
        self.positions = np.empty((capacity, 3))
        self.count = 0
        self.lengths = np.where(pbc, box, 0.0)
        self.inverse = np.where(pbc, 1.0 / np.where(pbc, box, 1.0), 0.0)
        n_cells = np.floor(np.where(pbc, box, 0.0) / cell_width).astype(int)
        self.use_cells = bool(np.all(pbc) and np.all(n_cells >= 3))
        if self.use_cells:
            self.n_cells = n_cells
            self.width = box / n_cells
            self.cells: dict[tuple[int, int, int], list[int]] = {}

    def _cell(self, point) -> NDArray[np.int64]:
        return np.floor(point / self.width).astype(np.int64) % self.n_cells

    def add(self, point) -> None:
        index = self.count
        self.positions[index] = point
        self.count += 1
        if self.use_cells:
            self.cells.setdefault(tuple(self._cell(point).tolist()), []).append(index)

    def truncate(self, count: int) -> None:
        """Forget every bead from index ``count`` on (an abandoned chain)."""
        if self.use_cells:
            for index in range(count, self.count):
                key = tuple(self._cell(self.positions[index]).tolist())
                self.cells[key].remove(index)
        self.count = count

    def near(self, point) -> NDArray[np.int64]:
        """Indices of beads that may lie within ``cell_width`` of ``point``."""
        if not self.use_cells:
            return np.arange(self.count)
        centre = self._cell(point)
        found: list[int] = []
        for offset in np.ndindex(3, 3, 3):
            key = tuple(((centre + np.array(offset) - 1) % self.n_cells).tolist())
            found.extend(self.cells.get(key, ()))
        return np.asarray(found, dtype=np.int64)

    def min_distance2(self, candidates, indices) -> NDArray[np.float64]:
        """Squared minimum-image distance of each candidate to the nearest listed bead."""
        if len(indices) == 0:
            return np.full(len(candidates), np.inf)
        d = candidates[:, None, :] - self.positions[indices][None, :, :]
        d -= self.lengths * np.rint(d * self.inverse)
        return np.einsum("ijk,ijk->ij", d, d).min(axis=1)


def _grow(n_chains, chain_length, bond_length, min_distance, box, pbc, rng):
    """Return (n_chains * chain_length, 3) continuous positions of self-avoiding walks."""
    n_atoms = n_chains * chain_length
    occupied = _Occupancy(n_atoms, box, pbc, cell_width=bond_length + min_distance)
    min2 = min_distance * min_distance
    lengths = np.where(pbc, box, 0.0)
    for chain in range(n_chains):
        first = chain * chain_length
        for _attempt in range(_ATTEMPTS_PER_CHAIN):
            if _grow_chain(occupied, first, chain_length, bond_length, min2, lengths, rng):
                break
            occupied.truncate(first)
        else:
            raise ValueError(
                f"could not grow chain {chain} of {n_chains} ({chain_length} beads, bond length "
                f"{bond_length:g}) without beads closer than {min_distance:g} after "
                f"{_ATTEMPTS_PER_CHAIN} attempts; the density is too high for random growth"
            )
    return occupied.positions[:n_atoms].copy()


def _grow_chain(occupied, first, chain_length, bond_length, min2, lengths, rng) -> bool:
    """Append one chain to ``occupied``; return False if it keeps meeting dead ends.

    At a dead end the walk backs up a few beads (more after repeated
    failures) and grows again from there.
    """
    # First bead: anywhere in the box (periodic axes), or at the origin (open).
    trials = rng.uniform(0.0, 1.0, size=(_TRIALS_PER_BATCH * _BATCHES_PER_BEAD, 3)) * lengths
    for trial in trials:
        if occupied.min_distance2(trial[None, :], occupied.near(trial))[0] >= min2:
            occupied.add(trial)
            break
    else:
        return False
    failures = 0
    bead = first + 1
    while bead < first + chain_length:
        previous = occupied.positions[bead - 1]
        # Every bead within min_distance of a trial lies within
        # bond_length + min_distance (one cell width) of the previous bead.
        near = occupied.near(previous)
        near = near[near != bead - 1]
        for _ in range(_BATCHES_PER_BEAD):
            trials = previous + bond_length * _random_directions(rng, _TRIALS_PER_BATCH)
            ok = occupied.min_distance2(trials, near) >= min2
            if ok.any():
                occupied.add(trials[int(np.argmax(ok))])
                bead += 1
                break
        else:
            failures += 1
            if failures > _BACKTRACKS_PER_CHAIN:
                return False
            back = min(bead - first - 1, int(rng.integers(1, 2 + failures)))
            if back == 0:
                return False
            bead -= back
            occupied.truncate(bead)
    return True


def _closest_nonbonded(positions, box, pbc) -> float:
    """Smallest minimum-image distance between beads of one chain not bonded to each other."""
    lengths = np.where(pbc, box, 0.0)
    inverse = np.where(pbc, 1.0 / np.where(pbc, box, 1.0), 0.0)
    n = len(positions)
    best = np.inf
    for i in range(n - 2):
        d = positions[i + 2 :] - positions[i]
        d -= lengths * np.rint(d * inverse)
        best = min(best, float(np.sqrt(np.einsum("ij,ij->i", d, d).min())))
    return best
