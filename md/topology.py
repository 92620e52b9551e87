"""Bonds as data: which atom pairs are joined, and by which named bond type (layer 0).

A :class:`Topology` is what files store and viewers draw: the H5MD
``connectivity`` group, LAMMPS data ``Bonds``, GSD ``bonds``, MDAnalysis's
``u.bonds``. It says nothing about forces; the bonded potentials and the
constraints own their own bond lists, and :func:`combine` joins them under
the names of their styles ("spring", "fene", "constraint").
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from md._checks import bond_array, bond_type_array


@dataclass(frozen=True)
class Topology:
    """Bonds as atom index pairs, each with a type index into ``bond_type_names``.

    Examples
    --------
    >>> topology = Topology.from_bonds([[0, 1], [1, 2]])
    >>> topology.n_bonds, topology.bond_type_names
    (2, ('bond',))
    >>> topology.by_type()["bond"].tolist()
    [[0, 1], [1, 2]]
    """

    bonds: NDArray[np.int64]
    bond_types: NDArray[np.int64]
    bond_type_names: tuple[str, ...]

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
        if bond_types is None:
            types = np.zeros(len(pairs), dtype=np.int64)
        else:
            types = bond_type_array(bond_types, len(pairs))
        n_types = int(types.max()) + 1 if len(types) else 0
        if bond_type_names is None:
            names = ("bond",) if n_types == 1 else tuple(f"bond{t}" for t in range(n_types))
        else:
            names = tuple(str(name) for name in bond_type_names)
            if len(names) < n_types:
                raise ValueError(
                    f"bond types go up to {n_types - 1} but only {len(names)} bond type names "
                    "are given"
                )
            if len(set(names)) != len(names):
                raise ValueError(f"bond type names repeat: {list(names)}")
        return cls(pairs, types, names)

    @property
    def n_bonds(self) -> int:
        return len(self.bonds)

    def __len__(self) -> int:
        return self.n_bonds

    def check(self, n_atoms: int, where: str = "bonds") -> None:
        """Raise ValueError if a bond names an atom index >= ``n_atoms``."""
        if self.n_bonds and int(self.bonds.max()) >= n_atoms:
            bad = int(np.flatnonzero((self.bonds >= n_atoms).any(axis=1))[0])
            raise ValueError(
                f"{where}: bond {bad} {tuple(self.bonds[bad].tolist())} names an atom beyond "
                f"the {n_atoms} of the system"
            )

    def by_type(self) -> dict[str, NDArray[np.int64]]:
        """Return the bonds grouped by type name, in type order (empty types included)."""
        return {
            name: self.bonds[self.bond_types == index]
            for index, name in enumerate(self.bond_type_names)
        }

    @classmethod
    def from_groups(cls, groups: dict[str, ArrayLike]) -> Topology:
        """Inverse of :meth:`by_type`: one bond type per name, in the dict's order."""
        parts = [bond_array(pairs) for pairs in groups.values()]
        bonds = np.concatenate(parts) if parts else np.zeros((0, 2), dtype=np.int64)
        types = np.concatenate(
            [np.full(len(part), index, dtype=np.int64) for index, part in enumerate(parts)]
        ) if parts else np.zeros(0, dtype=np.int64)  # fmt: skip
        return cls(bonds, types, tuple(groups))


def combine(parts: Iterable[tuple[str, ArrayLike, ArrayLike | None]]) -> Topology:
    """Join bond lists ``(style, bonds, bond_types)`` into one Topology.

    Each style's types become named bond types: ``style`` when the style has
    one type, ``style.<k>`` for its type k when it has several.

    Examples
    --------
    >>> topology = combine([("spring", [[0, 1]], None), ("fene", [[1, 2], [2, 3]], [0, 1])])
    >>> topology.bond_type_names
    ('spring', 'fene.0', 'fene.1')
    >>> topology.bond_types.tolist()
    [0, 1, 2]
    """
    bonds, types, names = [], [], []
    for style, pairs, style_types in parts:
        pairs = bond_array(pairs)
        if style_types is None:
            style_types = np.zeros(len(pairs), dtype=np.int64)
        style_types = bond_type_array(style_types, len(pairs))
        n_types = int(style_types.max()) + 1 if len(style_types) else 1
        offset = len(names)
        if n_types == 1:
            names.append(style)
        else:
            names.extend(f"{style}.{t}" for t in range(n_types))
        bonds.append(pairs)
        types.append(style_types + offset)
    if not bonds:
        return Topology.empty()
    if len(set(names)) != len(names):  # two potentials of one style: number them
        names = [f"{name}#{index}" for index, name in enumerate(names)]
    return Topology(np.concatenate(bonds), np.concatenate(types), tuple(names))


__all__ = ["Topology", "combine"]
