"""Bonds and angles as data: which atoms are joined, by which named type (layer 0).

A :class:`Topology` is what files store and viewers draw: the H5MD
``connectivity`` group, LAMMPS data ``Bonds`` and ``Angles``, GSD ``bonds``
and ``angles``, MDAnalysis's ``u.bonds`` and ``u.angles``. It says nothing
about forces; the bonded potentials and the constraints own their own bond
and angle lists, and :func:`combine` joins them under the names of their
styles ("spring", "fene", "constraint", "angle_harmonic", "angle_cosine").
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from md._checks import angle_array, bond_array, bond_type_array


def _no_angles() -> NDArray[np.int64]:
    return np.zeros((0, 3), dtype=np.int64)


def _no_types() -> NDArray[np.int64]:
    return np.zeros(0, dtype=np.int64)


@dataclass(frozen=True)
class Topology:
    """Bonds as atom index pairs, each with a type index into ``bond_type_names``,
    and angles as atom index triples ``(i, j, k)`` (``j`` the vertex), each with a
    type index into ``angle_type_names``.

    Bond and angle type names are distinct (they name the datasets of one
    H5MD ``connectivity`` group).

    Examples
    --------
    >>> topology = Topology.from_bonds([[0, 1], [1, 2]])
    >>> topology.n_bonds, topology.bond_type_names
    (2, ('bond',))
    >>> topology.by_type()["bond"].tolist()
    [[0, 1], [1, 2]]
    >>> topology = topology.with_angles([[0, 1, 2]])
    >>> topology.n_angles, topology.angle_type_names
    (1, ('angle',))
    """

    bonds: NDArray[np.int64]
    bond_types: NDArray[np.int64]
    bond_type_names: tuple[str, ...]
    angles: NDArray[np.int64] = field(default_factory=_no_angles)
    angle_types: NDArray[np.int64] = field(default_factory=_no_types)
    angle_type_names: tuple[str, ...] = ()

    @classmethod
    def empty(cls) -> Topology:
        return cls(np.zeros((0, 2), dtype=np.int64), np.zeros(0, dtype=np.int64), ())

    @classmethod
    def from_bonds(
        cls,
        bonds: ArrayLike,
        bond_types: ArrayLike | None = None,
        bond_type_names: Sequence[str] | None = None,
    ) -> Topology:
        """Validate and build; types default to 0 and names to "bond" or "bond<k>"."""
        pairs = bond_array(bonds)
        types, names = _typed(len(pairs), bond_types, bond_type_names, "bond")
        return cls(pairs, types, names)

    def with_angles(
        self,
        angles: ArrayLike,
        angle_types: ArrayLike | None = None,
        angle_type_names: Sequence[str] | None = None,
    ) -> Topology:
        """Return a copy with these angles (replacing any); types default to 0 and
        names to "angle" or "angle<k>"."""
        triples = angle_array(angles)
        types, names = _typed(len(triples), angle_types, angle_type_names, "angle")
        clash = sorted(set(names) & set(self.bond_type_names))
        if clash:
            raise ValueError(f"angle type names {clash} are also bond type names")
        return replace(self, angles=triples, angle_types=types, angle_type_names=names)

    @property
    def n_bonds(self) -> int:
        return len(self.bonds)

    @property
    def n_angles(self) -> int:
        return len(self.angles)

    def __len__(self) -> int:
        return self.n_bonds

    def check(self, n_atoms: int, where: str = "bonds") -> None:
        """Raise ValueError if a bond or an angle names an atom index >= ``n_atoms``."""
        for item, members in (("bond", self.bonds), ("angle", self.angles)):
            if len(members) and int(members.max()) >= n_atoms:
                bad = int(np.flatnonzero((members >= n_atoms).any(axis=1))[0])
                raise ValueError(
                    f"{where}: {item} {bad} {tuple(members[bad].tolist())} names an atom beyond "
                    f"the {n_atoms} of the system"
                )

    def by_type(self) -> dict[str, NDArray[np.int64]]:
        """Return the bonds grouped by type name, in type order (empty types included)."""
        return {
            name: self.bonds[self.bond_types == index]
            for index, name in enumerate(self.bond_type_names)
        }

    def angles_by_type(self) -> dict[str, NDArray[np.int64]]:
        """Return the angles grouped by type name, in type order (empty types included)."""
        return {
            name: self.angles[self.angle_types == index]
            for index, name in enumerate(self.angle_type_names)
        }

    @classmethod
    def from_groups(
        cls, groups: dict[str, ArrayLike], angle_groups: dict[str, ArrayLike] | None = None
    ) -> Topology:
        """Inverse of :meth:`by_type` (and :meth:`angles_by_type`): one type per name,
        in the dicts' order."""
        bonds, types = _grouped([bond_array(pairs) for pairs in groups.values()], 2)
        topology = cls(bonds, types, tuple(groups))
        if angle_groups:
            parts = [angle_array(triples) for triples in angle_groups.values()]
            angles, types = _grouped(parts, 3)
            topology = topology.with_angles(angles, types, tuple(angle_groups))
        return topology


def combine(
    parts: Iterable[tuple[str, ArrayLike, ArrayLike | None]],
    angle_parts: Iterable[tuple[str, ArrayLike, ArrayLike | None]] = (),
) -> Topology:
    """Join bond lists ``(style, bonds, bond_types)`` (and angle lists ``(style, angles,
    angle_types)``) into one Topology.

    Each style's types become named types: ``style`` when the style has
    one type, ``style.<k>`` for its type k when it has several.

    Examples
    --------
    >>> topology = combine([("spring", [[0, 1]], None), ("fene", [[1, 2], [2, 3]], [0, 1])])
    >>> topology.bond_type_names
    ('spring', 'fene.0', 'fene.1')
    >>> topology.bond_types.tolist()
    [0, 1, 2]
    >>> combine([], [("angle_cosine", [[0, 1, 2]], None)]).angle_type_names
    ('angle_cosine',)
    """
    bonds, types, names = _joined(parts, bond_array, "bond", 2)
    topology = Topology(bonds, types, names)
    angles, types, names = _joined(angle_parts, angle_array, "angle", 3)
    if len(names):
        topology = topology.with_angles(angles, types, names)
    return topology


def _typed(n_items: int, item_types, type_names, item: str) -> tuple[NDArray, tuple]:
    """Checked type indices (default 0) and their names (default ``item`` or ``item<k>``)."""
    if item_types is None:
        types = np.zeros(n_items, dtype=np.int64)
    else:
        types = bond_type_array(item_types, n_items, item)
    n_types = int(types.max()) + 1 if len(types) else 0
    if type_names is None:
        return types, (item,) if n_types == 1 else tuple(f"{item}{t}" for t in range(n_types))
    names = tuple(str(name) for name in type_names)
    if len(names) < n_types:
        raise ValueError(
            f"{item} types go up to {n_types - 1} but only {len(names)} {item} type names are given"
        )
    if len(set(names)) != len(names):
        raise ValueError(f"{item} type names repeat: {list(names)}")
    return types, names


def _grouped(parts: list[NDArray], width: int) -> tuple[NDArray, NDArray]:
    """Concatenate per-type member lists; their type is their index in ``parts``."""
    if not parts:
        return np.zeros((0, width), dtype=np.int64), np.zeros(0, dtype=np.int64)
    types = [np.full(len(part), index, dtype=np.int64) for index, part in enumerate(parts)]
    return np.concatenate(parts), np.concatenate(types)


def _joined(parts, check, item: str, width: int) -> tuple[NDArray, NDArray, tuple]:
    """The members, type indices and type names of ``(style, members, types)`` parts."""
    members, types, names = [], [], []
    for style, listed, style_types in parts:
        listed = check(listed)
        if style_types is None:
            style_types = np.zeros(len(listed), dtype=np.int64)
        style_types = bond_type_array(style_types, len(listed), item)
        n_types = int(style_types.max()) + 1 if len(style_types) else 1
        offset = len(names)
        if n_types == 1:
            names.append(style)
        else:
            names.extend(f"{style}.{t}" for t in range(n_types))
        members.append(listed)
        types.append(style_types + offset)
    if not members:
        return np.zeros((0, width), dtype=np.int64), np.zeros(0, dtype=np.int64), ()
    if len(set(names)) != len(names):  # two potentials of one style: number them
        names = [f"{name}#{index}" for index, name in enumerate(names)]
    return np.concatenate(members), np.concatenate(types), tuple(names)


__all__ = ["Topology", "combine"]
