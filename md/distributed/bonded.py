"""A decomposed run's bonded terms (:class:`BondedShare`): each bond (angle) is evaluated
by the rank that owns its first atom (vertex), with its partners' nearest copies among the
rank's owned atoms and ghosts; their errors name the whole system's items and atoms.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from md.box import minimum_image, periodic_lengths, periodic_tilt
from md.distributed._domain_kernels import anchored_items, nearest_copies
from md.errors import AngleCollapseError, DecompositionError
from md.state import State
from potentials.base import Bonded, BondedAngles
from potentials.springs import BondStretchError


@dataclass
class _Bonded:
    """A bonded potential's items indexed by their anchor atom's id (a bond's first atom,
    an angle's vertex), and the items this rank evaluated at the last build."""

    index: int  # in the force field's list
    items: NDArray[np.int64]  # (B, 2) bonds or (A, 3) angles, global ids
    types: NDArray[np.int64]
    anchor: int  # column of the anchor atom
    order: NDArray[np.int64]  # items sorted by anchor id
    starts: NDArray[np.int64]  # CSR offsets into order, by anchor id
    local: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, dtype=np.int64))


def _index_bonded(index: int, potential) -> _Bonded | None:
    """A bonded potential's items by anchor (None for a potential that lists no atoms)."""
    if isinstance(potential, Bonded):
        items, types, anchor = potential.bonds, potential.bond_types, 0
    elif isinstance(potential, BondedAngles):
        items, types, anchor = potential.angles, potential.angle_types, 1
    else:
        return None
    items = np.asarray(items, dtype=np.int64)
    order = np.argsort(items[:, anchor], kind="stable")
    n_ids = int(items.max()) + 2 if len(items) else 1
    starts = np.searchsorted(items[order, anchor], np.arange(n_ids)).astype(np.int64)
    return _Bonded(index, items, np.asarray(types, dtype=np.int64), anchor, order, starts)


def longest_arm(potentials, state: State) -> float:
    """The longest bond, or angle arm from its vertex, of ``potentials`` in ``state``
    (minimum image; 0 without bonds) [length]."""
    longest = 0.0
    for potential in potentials:
        bonded = _index_bonded(0, potential)
        if bonded is None or not len(bonded.items):
            continue
        anchors = bonded.items[:, bonded.anchor]
        for column in range(bonded.items.shape[1]):
            if column == bonded.anchor:
                continue
            d = state.positions[bonded.items[:, column]] - state.positions[anchors]
            d = minimum_image(d, state.box, state.pbc, state.tilt)
            longest = max(longest, float(np.sqrt((d * d).sum(axis=1)).max()))
    return longest


class BondedShare:
    """The bonded potentials among ``potentials`` (a run's whole-system list), their items
    indexed by anchor atom; ``listed``: whether there is any."""

    def __init__(self, potentials) -> None:
        indexed = [_index_bonded(i, p) for i, p in enumerate(potentials)]
        self._bonded = [b for b in indexed if b is not None]
        self.listed = bool(self._bonded)

    def localize(self, domain, potentials, local_potentials: list) -> float:
        """Put into ``local_potentials`` (the rank's force field's list, parallel to
        ``potentials``) this rank's bonds and angles over the local indices of ``domain``'s
        last build; return the longest bond (angle arm) among them [length]."""
        if not self._bonded:
            return 0.0  # (the id sort below: 5-7 ms a build for a 10^6-atom rank)
        ids = domain.local_ids
        local = domain.local_state
        positions = local.positions
        lengths, inverse = periodic_lengths(local.box, local.pbc)
        tilt = periodic_tilt(local.tilt, local.pbc)
        by_id = np.argsort(ids, kind="stable")
        sorted_ids = np.ascontiguousarray(ids[by_id])
        longest = 0.0
        for bonded in self._bonded:
            chosen, anchors = anchored_items(ids[: domain.n_owned], bonded.starts, bonded.order)
            items = bonded.items[chosen]
            local = np.empty_like(items)
            for column in range(items.shape[1]):
                if column == bonded.anchor:
                    local[:, column] = anchors
                    continue
                found = np.empty(len(items), dtype=np.int64)
                distances = np.empty(len(items))
                partners = np.ascontiguousarray(items[:, column])
                nearest_copies(
                    anchors,
                    partners,
                    sorted_ids,
                    by_id,
                    positions,
                    lengths,
                    inverse,
                    tilt,
                    found,
                    distances,
                )
                if len(found) and found.min() < 0:
                    raise DecompositionError(
                        "a bonded atom has no copy on its partner's rank: a bond is longer "
                        "than the ghost shell"
                    )
                local[:, column] = found
                if len(distances):
                    longest = max(longest, float(distances.max()))
            bonded.local = chosen
            potential = potentials[bonded.index]
            types = bonded.types[chosen]
            if isinstance(potential, Bonded):
                part = potential.with_bonds(local, types)
            else:
                part = potential.with_angles(local, types)
            local_potentials[bonded.index] = part
        return longest

    def global_error(self, error: Exception, ids: NDArray[np.int64]) -> Exception:
        """A bonded term's ``error`` over local indices (``ids``: each local atom's global
        id), naming the whole system's bond (angle) and atoms; other errors as they are."""
        if isinstance(error, BondStretchError):
            bond = self._global_item(2, error.bond)
            return BondStretchError(
                bond, int(ids[error.i]), int(ids[error.j]), error.length, error.r_max
            )
        if isinstance(error, AngleCollapseError):
            angle = self._global_item(3, error.angle)
            return AngleCollapseError(angle, tuple(int(ids[a]) for a in error.atoms))
        return error

    def _global_item(self, width: int, local: int) -> int:
        for bonded in self._bonded:
            if bonded.items.shape[1] == width and local < len(bonded.local):
                return int(bonded.local[local])
        return local
