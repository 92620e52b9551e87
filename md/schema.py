"""Declared config keys: each key a config accepts, with its type, default, unit and meaning.

A key is declared once, as a :class:`Key`, by whoever owns it:

- the fixed sections of a config (``[system]``, ``[run]``, ``[output]``,
  ``[minimize]``) are frozen dataclasses in :mod:`md.config` whose fields are
  made by :func:`key`: the field is the record's attribute, its metadata the
  declaration;
- a plug-in (a potential, an integrator, a barostat type) lists its keys in a
  ``CONFIG_KEYS`` tuple beside its constructor, so a new plug-in declares its
  keys once.

:mod:`md.config` reads configs with these declarations (a key not declared is
refused; a value of the wrong kind too; times, rates and pressures are
converted by their declared unit), and the manual's config reference is
generated from them. Plug-ins check their own values' ranges in their
constructors; a declared ``positive``/``minimum`` is checked when the config
is read. For example:

>>> steps = Key("steps", "integer", 1000, unit="steps", doc="time steps to run", minimum=0)
>>> steps.check(40)
40
>>> steps.check(-1)
Traceback (most recent call last):
    ...
ValueError: must be >= 0, got -1
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

from md._checks import MAX_COUNT


class _Required:
    """The default of a key that must be given."""

    def __repr__(self) -> str:
        return "REQUIRED"

    def __reduce__(self) -> str:
        return "REQUIRED"


#: The default of a key that has none: the config must give it.
REQUIRED = _Required()


class Varies:
    """A default that depends on the case: the unit system or ``[system]``'s kind.

    Cases are named by unit system (``lj``, ``metal``) or by the kind of
    system (``lattice``, ``melt``, ``chain``, ``structure``; see
    :data:`md.config.SYSTEM_KINDS`); a case may be :data:`REQUIRED`.

    Examples
    --------
    >>> Varies(lj=0.1, metal=4.5e-5).pick("metal")
    4.5e-05
    """

    def __init__(self, **cases: Any) -> None:
        self.cases: dict[str, Any] = dict(cases)

    def pick(self, case: str | None) -> Any:
        """The default in ``case`` (None where the case names none)."""
        return self.cases.get(case)

    def __eq__(self, other) -> bool:
        return isinstance(other, Varies) and other.cases == self.cases

    def __hash__(self) -> int:
        return hash(tuple(self.cases))

    def __repr__(self) -> str:
        return f"Varies({', '.join(f'{k}={v!r}' for k, v in self.cases.items())})"


def _number(key: Key, value):
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"expected a number, got {value!r}")
    if not math.isfinite(value):
        raise ValueError(f"must be finite, got {value!r}")
    if key.positive and not value > 0:
        raise ValueError(f"must be positive, got {value!r}")
    if key.minimum is not None and value < key.minimum:
        raise ValueError(f"must be >= {key.minimum}, got {value!r}")
    return float(value)


def _integer(key: Key, value):
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"expected an integer, got {value!r}")
    if key.minimum is not None and value < key.minimum:
        raise ValueError(f"must be >= {key.minimum}, got {value!r}")
    maximum = MAX_COUNT if key.maximum is None else key.maximum
    if value > maximum:
        raise ValueError(f"must be at most {maximum}, got {value!r}")
    return int(value)


def _string(key: Key, value):
    if not isinstance(value, str):
        raise ValueError(f"expected a string, got {value!r}")
    if key.choices is not None and value not in key.choices:
        raise ValueError(f"must be one of {', '.join(map(repr, key.choices))}, got {value!r}")
    return value


def _boolean(key: Key, value):
    if not isinstance(value, bool):
        raise ValueError(f"expected true or false, got {value!r}")
    return value


def _table(key: Key, value):
    if not isinstance(value, dict):
        raise ValueError(f"expected a table, got {value!r}")
    return value


def _triple(kind: type):
    def check(key: Key, value):
        values = value if isinstance(value, list) else [value] * 3
        if len(values) != 3 or not all(_is_kind(v, kind) for v in values):
            raise ValueError(f"expected {kind.__name__} or a list of three, got {value!r}")
        return tuple(values)

    return check


def _is_kind(value, kind: type) -> bool:
    if kind is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if kind is float:
        return isinstance(value, int | float) and not isinstance(value, bool)
    return isinstance(value, kind)


#: The kinds of value a key may declare, and how each is checked when a config is read.
#: A kind checked as None is described only: the plug-in that owns the key checks it.
KINDS = {
    "number": _number,
    "integer": _integer,
    "string": _string,
    "boolean": _boolean,
    "path": _string,  # a file, relative to the config's folder
    "output path": _string,  # a file written, relative to the working directory
    "table": _table,
    "integer or list of three": _triple(int),
    "number or list of three": _triple(float),
    "boolean or list of three": _triple(bool),
    "number or list": None,  # one value, or one per bond or angle type
    "number, list or table": None,  # one value, one per type, or {type name = value}
    "number or table": None,  # one value, or {type name = value}
    'list or "system"': None,  # index lists, or the [system]'s own
    "list of integers": None,
    "list of positions": None,  # [[x, y, z], ...]: a rigid body's template
    "list of tables": None,
    "integer or list of integers": None,  # a seed or a seed sequence
    '"bonded" or list of integers': None,
}


@dataclasses.dataclass(frozen=True)
class Key:
    """One config key: its name, kind of value, default, unit and meaning.

    Parameters
    ----------
    name : str
        The key as written in the config.
    kind : str
        One of :data:`KINDS` (``"number"``, ``"integer"``, ``"string"``, ...).
    default : object
        The value when the key is not given, in config units; :data:`REQUIRED`
        when it must be given; a :class:`Varies` when it depends on the
        unit system or the kind of system.
    unit : str, optional
        The quantity (``"time"``, ``"length"``, ``"pressure"``, ...; see
        ``md.units.UnitSystem.config_units``): the reference shows it in
        each unit system, and the config converts times, rates, pressures
        and compressibilities into engine units.
    doc : str
        The meaning, one or two sentences (MyST markdown).
    choices : tuple, optional
        The values a string key accepts.
    positive, minimum, maximum
        Range checked when the config is read (integers are at most 2^53
        unless ``maximum`` says otherwise).
    when : tuple of str, optional
        The kinds of ``[system]`` the key applies to (None: every kind).
    default_doc : str
        What the reference shows as the default where ``default`` alone
        does not say it (a builder's or a file's own value).
    """

    name: str
    kind: str
    default: Any = REQUIRED
    unit: str | None = None
    doc: str = ""
    choices: tuple | None = None
    positive: bool = False
    minimum: float | None = None
    maximum: int | None = None
    when: tuple[str, ...] | None = None
    default_doc: str = ""

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"key {self.name!r}: unknown kind {self.kind!r}; known: {list(KINDS)}")

    @property
    def required(self) -> bool:
        """True when the key must be given (in every case its default names)."""
        return self.default is REQUIRED

    def default_in(self, case: str | None = None) -> Any:
        """The default in ``case`` (a unit system or kind of system): REQUIRED, a value or None."""
        return self.default.pick(case) if isinstance(self.default, Varies) else self.default

    def check(self, value):
        """Return ``value`` checked (numbers as float); raise ValueError saying what is wrong.

        The message does not name the key; the reader adds where it was.
        Kinds that are described only (see :data:`KINDS`) pass unchanged.
        """
        checker = KINDS[self.kind]
        return value if checker is None else checker(self, value)

    def applies(self, case: str | None) -> bool:
        """True if the key applies to the kind of system ``case`` (always, without ``when``)."""
        return self.when is None or case in self.when


_UNSET = object()


def key(
    default: Any = REQUIRED, kind: str = "number", *, unset: Any = _UNSET, **declared: Any
) -> Any:
    """A dataclass field that declares a config key (its name is the field's).

    ``default`` is the key's default (see :class:`Key`); ``unset`` is the
    value the record holds where the key does not apply or has no default
    (``REQUIRED`` and :class:`Varies` defaults need one). The other keywords
    are :class:`Key`'s.
    """
    held = default if unset is _UNSET else unset
    if held is REQUIRED or isinstance(held, Varies):
        raise ValueError("a required or varying key needs unset=, the value its field holds")
    declaration = Key("", kind, default, **declared)
    return dataclasses.field(default=held, metadata={"key": declaration})


def section_keys(record) -> tuple[Key, ...]:
    """The keys a record class (or instance) made with :func:`key` fields declares."""
    return tuple(
        dataclasses.replace(f.metadata["key"], name=f.name)
        for f in dataclasses.fields(record)
        if "key" in f.metadata
    )


def key_names(keys) -> tuple[str, ...]:
    """The names of ``keys``, in declaration order."""
    return tuple(k.name for k in keys)


def check_names(params: Mapping, keys) -> None:
    """Raise ValueError naming keys of ``params`` that ``keys`` does not declare, or
    declared required keys missing from it (the check a plug-in's ``from_config`` makes)."""
    names = key_names(keys)
    unknown = set(params) - set(names)
    if unknown:
        raise ValueError(
            f"unknown key(s): {', '.join(sorted(unknown))} (allowed: {', '.join(sorted(names))})"
        )
    missing = [k.name for k in keys if k.required and k.name not in params]
    if missing:
        raise ValueError(f"missing key(s): {', '.join(missing)}")


__all__ = [
    "KINDS",
    "REQUIRED",
    "Key",
    "Varies",
    "check_names",
    "key",
    "key_names",
    "section_keys",
]
