"""Shared validation of user-facing numbers and index arrays (layer 0).

One set of checks for the whole package, so every "must be finite and > 0"
reads the same and rejects the same things (``True``, strings, NaN, inf).
Each returns the value converted to the type the engine uses, or raises
``ValueError`` with a message that starts with the name it was given.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

#: Largest step count, interval or other count the engine takes: exact in float64
#: (times are step * dt) and far inside int64 (the H5MD step arrays).
MAX_COUNT = 2**53
#: Largest seed: stored as a signed 64-bit integer in trajectories and checkpoints.
MAX_SEED = 2**63 - 1


def positive(value, name: str, allow_zero: bool = False) -> float:
    """Return ``value`` as a float if it is finite and > 0 (or >= 0), else raise ValueError.

    Examples
    --------
    >>> positive(2, "dt")
    2.0
    >>> positive(0.0, "skin", allow_zero=True)
    0.0
    >>> positive(float("nan"), "dt")
    Traceback (most recent call last):
    ...
    ValueError: dt must be finite and > 0, got nan
    """
    if isinstance(value, bool):
        raise ValueError(f"{name} must be a number, got {value!r}")
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(number) or number < 0 or (number == 0 and not allow_zero):
        rule = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name} must be finite and {rule}, got {value!r}")
    return number


def positive_array(value, name: str, allow_zero: bool = False, what: str = "type"):
    """Return a float64 scalar or 1-D array whose entries are finite and > 0 (or >= 0).

    ``what`` names what one entry belongs to in the message ("type", "bond type").
    """
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number or a list of numbers, got {value!r}") from None
    if array.ndim > 1 or array.size == 0:
        raise ValueError(f"{name} must be a number or a list with one number per {what}")
    ok = np.isfinite(array) & ((array >= 0) if allow_zero else (array > 0))
    if not np.all(ok):
        rule = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name} must be finite and {rule}, got {value!r}")
    return array


def finite_array(value, name: str, what: str = "type"):
    """Return a float64 scalar or 1-D array whose entries are finite (of either sign)."""
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number or a list of numbers, got {value!r}") from None
    if array.ndim > 1 or array.size == 0 or not np.all(np.isfinite(array)):
        raise ValueError(
            f"{name} must be a finite number or a list with one per {what}, got {value!r}"
        )
    return array


def positive_scalar(value, name: str, allow_zero: bool = False) -> float:
    """Like :func:`positive`, for values that may arrive as numpy scalars or 0-d arrays."""
    array = positive_array(value, name, allow_zero)
    if array.ndim != 0:
        raise ValueError(f"{name} must be a single number, got {value!r}")
    return float(array)


def count(value, name: str, minimum: int = 0, maximum: int = MAX_COUNT) -> int:
    """Return ``value`` as an int if it is an integer in [``minimum``, ``maximum``] (no bools).

    Examples
    --------
    >>> count(3, "chains", minimum=1)
    3
    >>> count(2.5, "chains", minimum=1)
    Traceback (most recent call last):
    ...
    ValueError: chains must be an integer >= 1, got 2.5
    """
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    if value > maximum:
        raise ValueError(f"{name} must be at most {maximum}, got {value!r}")
    return int(value)


def _integral(array: np.ndarray) -> bool:
    return bool(
        np.issubdtype(array.dtype, np.integer)
        or (np.issubdtype(array.dtype, np.floating) and np.all(array == np.round(array)))
    )


def bond_array(bonds, name: str = "bonds") -> NDArray[np.int64]:
    """Return bonds as a C-contiguous (B, 2) int64 copy, refusing negative and self bonds.

    Examples
    --------
    >>> bond_array([[0, 1], [1, 2]]).tolist()
    [[0, 1], [1, 2]]
    >>> bond_array([[0, 0]])
    Traceback (most recent call last):
    ...
    ValueError: bond 0 joins atom 0 to itself
    """
    array = np.asarray(bonds)
    if array.size == 0:
        array = array.reshape(0, 2)
    if array.ndim != 2 or array.shape[1] != 2:
        raise ValueError(f"{name} must have shape (B, 2), got {array.shape}")
    if array.size and not _integral(array):
        raise ValueError(f"{name} must be integer atom indices")
    array = np.array(array, dtype=np.int64, order="C", copy=True)
    if array.size and array.min() < 0:
        bad = int(np.flatnonzero((array < 0).any(axis=1))[0])
        raise ValueError(f"bond {bad} {tuple(array[bad].tolist())} has a negative atom index")
    same = np.flatnonzero(array[:, 0] == array[:, 1])
    if same.size:
        raise ValueError(f"bond {int(same[0])} joins atom {array[same[0], 0]} to itself")
    return array


def bond_type_array(bond_types, n_bonds: int, item: str = "bond") -> NDArray[np.int64]:
    """Return one non-negative integer type per bond (or per ``item``) as an int64 copy."""
    name = f"{item}_types"
    array = np.asarray(bond_types)
    if array.shape != (n_bonds,):
        raise ValueError(f"{name} must have shape ({n_bonds},) (one per {item}), got {array.shape}")
    if array.size and not _integral(array):
        raise ValueError(f"{name} must be integers")
    array = np.array(array, dtype=np.int64, order="C", copy=True)
    if array.size and array.min() < 0:
        raise ValueError(f"{name} must be non-negative")
    return array


def angle_array(angles, name: str = "angles") -> NDArray[np.int64]:
    """Return angles as a C-contiguous (A, 3) int64 copy of ``(i, j, k)`` triples.

    ``j`` is the vertex (LAMMPS's order: atom2 is the apex). Refuses
    negative indices and a triple that names one atom twice.

    Examples
    --------
    >>> angle_array([[0, 1, 2]]).tolist()
    [[0, 1, 2]]
    >>> angle_array([[0, 1, 0]])
    Traceback (most recent call last):
    ...
    ValueError: angle 0 (0, 1, 0) names atom 0 twice
    """
    array = np.asarray(angles)
    if array.size == 0:
        array = array.reshape(0, 3)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(
            f"{name} must have shape (A, 3): triples (i, j, k), j the vertex; "
            f"got shape {array.shape}"
        )
    if array.size and not _integral(array):
        raise ValueError(f"{name} must be integer atom indices")
    array = np.array(array, dtype=np.int64, order="C", copy=True)
    if array.size and array.min() < 0:
        bad = int(np.flatnonzero((array < 0).any(axis=1))[0])
        raise ValueError(f"angle {bad} {tuple(array[bad].tolist())} has a negative atom index")
    repeated = (
        (array[:, 0] == array[:, 1]) | (array[:, 1] == array[:, 2]) | (array[:, 0] == array[:, 2])
    )
    if repeated.any():
        bad = int(np.flatnonzero(repeated)[0])
        triple = array[bad].tolist()
        twice = next(a for a in triple if triple.count(a) > 1)
        raise ValueError(f"angle {bad} {tuple(triple)} names atom {twice} twice")
    return array


def read_index_file(path, width: int, key: str) -> NDArray[np.int64]:
    """Read a text table of ``width`` integer atom indices per line (``#`` comments).

    Every problem is reported with the file and line: ``key`` (the config
    key that named the file, e.g. ``angles_file``) starts the message.
    Blank and comment lines are skipped.
    """
    if not isinstance(path, str | Path):
        raise ValueError(f"{key} must be a path, got {path!r}")
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{key} not found: {path}")
    rows = []
    try:
        with open(path, encoding="utf-8") as handle:
            for number, line in enumerate(handle, start=1):
                text = line.split("#", 1)[0].strip()
                if not text:
                    continue
                words = text.split()
                try:
                    values = [int(word) for word in words]
                except ValueError:
                    values = []
                if len(words) != width or len(values) != width:
                    raise ValueError(
                        f"{key} {path}: line {number}: expected {width} integer atom indices, "
                        f"got {text!r}"
                    )
                if min(values) < 0:
                    raise ValueError(
                        f"{key} {path}: line {number}: negative atom index in {text!r}"
                    )
                rows.append(values)
    except (OSError, UnicodeDecodeError) as error:
        raise ValueError(f"{key} {path}: cannot read ({error})") from None
    return np.array(rows, dtype=np.int64).reshape(-1, width)


def read_bonds_file(path) -> NDArray[np.int64]:
    """Read a whitespace table of bonds, one ``i j`` pair of atom indices per line."""
    if not isinstance(path, str | Path):
        raise ValueError(f"bonds_file must be a path, got {path!r}")
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"bonds_file not found: {path}")
    try:
        table = np.loadtxt(path, dtype=np.float64, ndmin=2, comments="#")
    except ValueError as error:
        raise ValueError(f"bonds_file {path}: not a table of integers ({error})") from None
    if table.size == 0:
        return np.zeros((0, 2), dtype=np.int64)
    if table.shape[1] != 2:
        raise ValueError(f"bonds_file {path}: expected two columns (i j), got {table.shape[1]}")
    if not np.all(table == np.round(table)):
        raise ValueError(f"bonds_file {path}: atom indices must be integers")
    return table.astype(np.int64)
