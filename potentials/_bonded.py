"""What the bonded potentials (bonds, angles) share: the list of atom tuples they hold,
per-type parameter tables and the checks of their config tables. Imported only within
``potentials``."""

from __future__ import annotations

import copy
import hashlib
from collections.abc import Callable, Mapping

import numpy as np
from numpy.typing import ArrayLike

from md._checks import bond_type_array, finite_array, positive_array
from md.schema import Key, check_names


class ListedTuples:
    """A potential over a fixed list of atom tuples (bonds, angles) with a type per tuple.

    Holds the list and its types read-only (the checks made when they were set must stay
    true), the largest atom index they name, and what follows from them alone: the
    check against a state's atoms, the same potential over another list (one rank's
    share in a decomposed run) and the list's part of ``describe()``. Subclasses set
    ``ITEM``, the word for one tuple ("bond", "angle"), and expose the list under
    their own names.
    """

    cutoff = None  # bonded: no neighbour list needed
    #: What one tuple is called in messages and descriptions.
    ITEM: str

    def _setup_list(
        self, items: np.ndarray, item_types, params: dict[str, ArrayLike], nonnegative: bool = True
    ) -> None:
        """Hold ``items`` (checked already) with their types and per-type parameter tables
        (:func:`type_tables`: ``per_type`` and ``_tables``)."""
        types, self.per_type, self._tables = type_tables(
            params, item_types, len(items), self.ITEM, nonnegative
        )
        self._set_list(items, types)

    def _set_list(self, items: np.ndarray, types: np.ndarray) -> None:
        items.flags.writeable = False
        types.flags.writeable = False
        self._items = items
        self._types = types
        self._max_index = int(items.max()) if len(items) else -1

    def _with_list(self, items: np.ndarray, types: ArrayLike):
        """A copy over ``items`` (checked already) whose ``types`` index the same tables."""
        types = np.array(types, dtype=self._types.dtype, copy=True)
        if types.shape != (len(items),):
            raise ValueError(f"{len(items)} {self.ITEM}s but {types.shape} {self.ITEM} types")
        part = copy.copy(self)
        part._set_list(items, types)
        return part

    def _check_indices(self, n_atoms: int) -> None:
        """Raise ValueError naming the first tuple with an atom index >= ``n_atoms``."""
        if self._max_index >= n_atoms:
            bad = int(np.flatnonzero((self._items >= n_atoms).any(axis=1))[0])
            atoms = tuple(int(a) for a in self._items[bad])
            raise ValueError(
                f"{self.ITEM} {bad} {atoms} refers to atom {max(atoms)}, but the system has "
                f"{n_atoms} atoms (indices 0..{n_atoms - 1})"
            )

    def _list_description(self, style: str, **params) -> dict:
        """``describe()``'s dict: the style, ``params``, the tuple count, a hash of the list
        and, with per-type parameters, the type count."""
        digest = hashlib.sha256(np.ascontiguousarray(self._items, dtype="<i8").tobytes())
        out = {"type": style, **params, f"n_{self.ITEM}s": len(self._items)}
        out[f"{self.ITEM}s_sha256"] = digest.hexdigest()
        if self.per_type:
            out[f"n_{self.ITEM}_types"] = len(self._tables[0]) if self._tables else None
        return out


def type_tables(
    params: dict[str, ArrayLike], item_types, n_items: int, item: str, nonnegative: bool = True
) -> tuple[np.ndarray, bool, list[np.ndarray]]:
    """Check parameters given once or per type; return ``(types, per_type, tables)``.

    ``params`` maps names to a number or a list (one value per ``item`` type),
    each finite (and >= 0 if ``nonnegative``); ``item_types`` holds one type index per member (a
    bond, an angle) or is None when every parameter is a single number.
    ``tables`` holds one float64 array per parameter, one entry per type.
    """
    what = f"{item} type"
    given = {
        name: positive_array(value, name, allow_zero=True, what=what)
        if nonnegative
        else finite_array(value, name, what)
        for name, value in params.items()
    }
    per_type = [name for name, value in given.items() if value.ndim == 1]
    key = f"{item}_types"
    if item_types is None:
        if per_type:
            raise ValueError(
                f"{', '.join(per_type)} given per {item} type, so {key} "
                f"(one type index per {item}) is needed"
            )
        types = np.zeros(n_items, dtype=np.int64)
        n_types = 1
    else:
        types = bond_type_array(item_types, n_items, item)
        lengths = {len(given[name]) for name in per_type}
        if len(lengths) > 1:
            raise ValueError(
                f"per-type parameters must have one value per {item} type, got lengths "
                + ", ".join(f"{name}: {len(given[name])}" for name in per_type)
            )
        used = int(types.max()) + 1 if n_items else 1
        n_types = lengths.pop() if lengths else used
        if used > n_types:
            raise ValueError(
                f"{key} go up to {used - 1} but {', '.join(per_type)} "
                f"{'has' if len(per_type) == 1 else 'have'} values for {n_types} {item} types"
            )
    tables = [np.broadcast_to(value, (n_types,)).copy() for value in given.values()]
    return types, item_types is not None, tables


def bonded_keys(item: str, example: str, *parameters: Key) -> tuple[Key, ...]:
    """The config keys of a bonded potential: its members (``<item>s`` or
    ``<item>s_file``), their ``<item>_types``, and its ``parameters``."""
    members, file_key = f"{item}s", f"{item}s_file"
    return (
        Key(
            members,
            'list or "system"',
            None,
            doc=f'The {item}s, a list of `{example}` atom indices, or `"system"`: the {item}s '
            f"`[system]` made (a polymer) or read (a structure file). Give this or "
            f"`{file_key}`.",
        ),
        Key(
            file_key,
            "path",
            None,
            doc=f"A text file of {example.count(',') + 1} integer columns (`#` comments), "
            f"relative to the config. Give this or `{members}`.",
        ),
        *parameters,
        Key(
            f"{item}_types",
            "list of integers",
            None,
            doc=f"One type index per {item}, into per-type parameters given as lists.",
            default_doc=f'all {item}s one type (`"system"`: the file\'s types)',
        ),
    )


def config_values(
    params: Mapping, keys: tuple[Key, ...], item: str, read_file: Callable, example: str
) -> dict:
    """Check a bonded potential's config table; return constructor arguments.

    ``keys`` are the potential's declared keys (:func:`bonded_keys`): the
    members, given as ``<item>s`` (a list of index lists) or ``<item>s_file``
    (read by ``read_file(path)``), optional ``<item>_types``, and the
    parameters, each a number or a list. ``example`` shows one member in
    messages (``"[i, j]"``).
    """
    params = dict(params)
    members, file_key, types_key = f"{item}s", f"{item}s_file", f"{item}_types"
    check_names(params, keys)
    names = [k.name for k in keys if k.name not in (members, file_key, types_key)]
    if (members in params) == (file_key in params):
        raise ValueError(f"give exactly one of '{members}' (a list of {example}) and '{file_key}'")
    if file_key in params:
        params[members] = read_file(params.pop(file_key))
    for name in names:
        value = params.get(name)
        values = value if isinstance(value, list) else [value]
        if any(isinstance(v, bool) or not isinstance(v, int | float | None) for v in values):
            raise ValueError(f"{name}: expected a number or a list of numbers, got {value!r}")
    for name in (members, types_key):
        value = params.get(name)
        if value is None or isinstance(value, np.ndarray):
            continue
        if not isinstance(value, list):
            raise ValueError(f"{name}: expected a list, got {value!r}")
        flat = [v for row in value for v in (row if isinstance(row, list) else [row])]
        if any(isinstance(v, bool) or not isinstance(v, int) for v in flat):
            raise ValueError(f"{name}: expected integers, got {value!r}")
    return params


def symmetric(v: np.ndarray) -> np.ndarray:
    """The (3, 3) tensor of a virial stored as (xx, yy, zz, yz, xz, xy)."""
    xx, yy, zz, yz, xz, xy = v
    return np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
