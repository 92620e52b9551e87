"""Plug-ins from outside the package: the classes a config's ``type`` may name.

A config's ``type = "..."`` names a built-in (``potentials.POTENTIALS``,
``integrators.INTEGRATORS``), a plug-in registered by an installed
distribution under an entry-point group (as pytest and ASE-style projects
register theirs)::

    [project.entry-points."leapmd.potentials"]
    gauss = "mypkg.pairs:Gauss"

or, for quick work, a ``module:attribute`` path to any module Python can
import (``type = "mypkg.pairs:Gauss"``, the module on ``PYTHONPATH``). A
built-in name always means the built-in: an entry point of the same name is
shadowed (a warning says so when entry points are searched), and reaches
its class only by its ``module:attribute`` path.

:func:`load` finds the object and hands it to the registry's own check of
its kind and signature (``potentials.potential_class``,
``integrators.integrator_class``); every failure, an import that raises
included, is a :class:`md.errors.PluginError` naming the plug-in and what is
wrong, which the config turns into a ``ConfigError`` naming the file and key.
Naming a module in a config imports it, running its code, as naming a
plug-in to pytest does.
"""

from __future__ import annotations

import importlib
import inspect
import logging
from collections.abc import Callable, Iterable, Mapping
from importlib.metadata import entry_points

from md.errors import PluginError

#: Entry-point group of each registry kind.
GROUPS = {"potentials": "leapmd.potentials", "integrators": "leapmd.integrators"}
logger = logging.getLogger(__name__)
#: The shadowed entry points warned about, per group.
_WARNED: set[tuple[str, tuple[str, ...]]] = set()


def load(
    name: str, kind: str, builtins: Mapping[str, object], check: Callable[[object], str | None]
) -> object:
    """The object a config's ``type = name`` names, for registry ``kind``.

    ``builtins`` first, then ``module:attribute``, then the entry points of
    ``GROUPS[kind]``; ``check(obj)`` returns what is wrong with a plug-in found
    (None: nothing). Raises :class:`PluginError` naming the plug-in.
    """
    if not isinstance(name, str):
        raise PluginError(f"expected a string, got {name!r}")
    if name in builtins:
        return builtins[name]
    if ":" in name:
        found = _attribute(name)
        label = f"plug-in {name!r}"
    else:
        found, label = _entry_point(name, kind, builtins)
    try:
        problem = check(found)
    except Exception as error:  # noqa: BLE001 (reading the user's class may raise anything)
        problem = f"reading it raised {type(error).__name__}: {error}"
    if problem:
        raise PluginError(f"{label}: {problem}")
    return found


def plugin_names(kind: str) -> tuple[str, ...]:
    """The names registered under ``GROUPS[kind]`` by installed distributions, sorted."""
    return tuple(sorted({point.name for point in entry_points(group=GROUPS[kind])}))


def signature_problem(cls: type, given: Iterable[str], supplied: Iterable[str] = ()) -> str | None:
    """What keeps ``cls(**values)`` from taking the keywords ``given`` (the config keys it
    declares) and ``supplied`` (those the config adds): a keyword its constructor does not
    take, or a required constructor argument neither holds. None if it fits."""
    try:
        parameters = inspect.signature(cls).parameters
    except (TypeError, ValueError):
        return None  # no signature to read (a builtin's): the constructor itself decides
    given, supplied = tuple(given), tuple(supplied)
    takes_any = any(p.kind is p.VAR_KEYWORD for p in parameters.values())
    keywords = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    named = {n for n, p in parameters.items() if p.kind in keywords}
    refused = [n for n in (*given, *supplied) if n not in named and not takes_any]
    required = [
        n
        for n, p in parameters.items()
        if n in named and p.default is p.empty and n not in given and n not in supplied
    ]
    signature = f"{cls.__name__}{inspect.signature(cls)}"
    if refused:
        return (
            f"its constructor {signature} does not take {', '.join(refused)}, which its "
            "config keys (CONFIG_KEYS) pass"
        )
    if required:
        return (
            f"its constructor {signature} requires {', '.join(required)}, which is not "
            "among its config keys (CONFIG_KEYS)"
        )
    return None


def _attribute(name: str) -> object:
    """``module:attribute`` (the attribute may be dotted) imported."""
    module_name, _, attribute = name.partition(":")
    if not module_name or not attribute:
        raise PluginError(f"plug-in {name!r}: expected 'module:attribute' (mypkg.pairs:Gauss)")
    module = _import(module_name, f"plug-in {name!r}")
    found = module
    for part in attribute.split("."):  # the path a user wrote, in a foreign module
        if not hasattr(found, part):
            raise PluginError(
                f"plug-in {name!r}: module {module_name} ({_file(module)}) has no "
                f"attribute {attribute!r}"
            )
        found = getattr(found, part)
    return found


def _import(module_name: str, label: str):
    try:
        return importlib.import_module(module_name)  # the user's module, named in a config
    except ModuleNotFoundError as error:
        if error.name and module_name.startswith(error.name):
            raise PluginError(
                f"{label}: no module named {error.name!r} (is it installed, or "
                "its folder on PYTHONPATH?)"
            ) from None
        raise PluginError(f"{label}: importing {module_name} raised {error!r}") from None
    except Exception as error:  # noqa: BLE001 (the user's module may raise anything)
        raise PluginError(
            f"{label}: importing {module_name} raised {type(error).__name__}: {error}"
        ) from None


def _entry_point(name: str, kind: str, builtins: Mapping[str, object]) -> tuple[object, str]:
    group = GROUPS[kind]
    points = entry_points(group=group)
    shadowed = tuple(sorted({p.name for p in points if p.name in builtins}))
    if shadowed and (group, shadowed) not in _WARNED:  # once per process
        _WARNED.add((group, shadowed))
        logger.warning(
            "entry point(s) %s of %s are shadowed by the built-ins of those names; "
            "name them by module:attribute",
            ", ".join(shadowed),
            group,
        )
    matches = [p for p in points if p.name == name]
    if not matches:
        known = [*builtins, *(n for n in plugin_names(kind) if n not in builtins)]
        raise PluginError(
            f"must be one of {', '.join(map(repr, known))} (or a plug-in: a name registered "
            f"under the entry-point group {group!r}, or 'module:attribute'), got {name!r}"
        )
    values = sorted({p.value for p in matches})
    if len(values) > 1:
        raise PluginError(
            f"type {name!r}: several plug-ins registered under {group!r} "
            f"claim the name ({', '.join(values)}); name one by "
            "module:attribute"
        )
    point = matches[0]
    label = f"plug-in {name!r} (entry point {point.value} in {group})"
    _import(point.module, label)
    try:
        return point.load(), label
    except AttributeError as error:
        raise PluginError(f"{label}: {error}") from None
    except Exception as error:  # noqa: BLE001 (the user's module may raise anything)
        raise PluginError(f"{label}: loading it raised {type(error).__name__}: {error}") from None


def _file(module) -> str:
    return getattr(module, "__file__", None) or "built in"  # built-in modules have none


__all__ = ["GROUPS", "load", "plugin_names", "signature_problem"]
