"""The config reference against the config parser: every key documented is accepted, and
every key accepted is documented.

The page is rendered as the Sphinx build renders it (``docs/_ext/config_reference.py``),
and its keys are read back from the page's text: per section, per plug-in ``type``, and
for ``[system]`` per kind of system. Then ``md.config.parse_config`` is probed with one
key at a time, added to a small valid config: a key the page lists there must not be
refused, and every candidate key the page does not list there must be refused as
unknown or not applying. The candidates are every key named anywhere on the page, every
constructor argument of the plug-ins, the keys of the example configs, and a made-up one.
Two more tests show the check failing on a page that lacks a key or lists one too many.
"""

from __future__ import annotations

import importlib.util
import inspect
import re
import tomllib
from collections import defaultdict
from pathlib import Path

import pytest

from integrators import INTEGRATORS
from integrators.barostats import BAROSTAT_KEYS, Barostat
from integrators.rattle import BondConstraints
from md.config import SYSTEM_KINDS, parse_config, sections
from md.errors import ConfigError
from md.schema import KINDS, REQUIRED, Key, Varies
from md.units import UNIT_SYSTEMS
from potentials import POTENTIALS

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location(
    "config_reference", ROOT / "docs" / "_ext" / "config_reference.py"
)
reference = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(reference)

LABELS = {label: kind for kind, label in SYSTEM_KINDS.items()}
#: A small valid config of each kind of system, to which probed keys are added.
SYSTEMS = {
    "lattice": {"lattice": "fcc", "cells": 2, "density": 0.8},
    "melt": {"polymer": "melt", "chains": 2, "chain_length": 4, "density": 0.5},
    "chain": {"polymer": "chain", "chain_length": 4},
    "structure": {"structure": "s.xyz"},
}
#: Messages of the parser that refuse a key as not belonging where it is.
REFUSALS = ("unknown key", "does not apply", "needs exactly one of 'lattice'")
MADE_UP = "no_such_key"


# ------------------------------------------------------------------ the page
def documented(page: str) -> dict[tuple[str, str | None], dict[str, tuple[str, str, str]]]:
    """``{(section, type or kind): {key: (type, default, meaning)}}`` read from a page's rows.

    Sections are the ``##`` headings (``[run]`` -> run, ``[[potentials]]`` ->
    potentials, "Top level" -> ""), plug-in types the ``"names"`` of ``###``
    headings, and ``[system]``'s rows go to each kind of system their "applies
    to" column names.
    """
    found: dict = defaultdict(dict)
    section, types = None, [None]
    for line in page.splitlines():
        if line.startswith("## "):
            title = line[3:].strip().strip("`")
            section = (
                ""
                if title == "Top level"
                else (title.strip("[]") if title.startswith("[") else None)
            )
            types = [None]
        elif line.startswith("### ") and section is not None:
            types = re.findall(r'"(\w+)"', line)
        elif section is not None and (row := re.match(r"\| `(\w+)` \|(.*)\|$", line)):
            cells = [c.strip() for c in row.group(2).split(" | ")]
            if section == "system":
                applies, cells = cells[0], cells[1:]
                kinds = (
                    list(SYSTEMS)
                    if applies == "all"
                    else [LABELS[label] for label in re.split(r", (?=a |polymer)", applies)]
                )
            else:
                kinds = types
            for kind in kinds:
                found[(section, kind)][row.group(1)] = (cells[0], cells[1], cells[-1])
    return dict(found)


def sample(cells: tuple[str, str, str]) -> object:
    """A value of the kind a row's type column names (a string: the first of its choices)."""
    kind, meaning = cells[0].split(" >")[0], cells[2]
    choices = re.search(r'One of `"([^"]+)"`', meaning)
    if kind == "string" and choices:
        return choices.group(1)
    values = {
        "number": 1.0,
        "integer": 2,
        "string": "x",
        "boolean": True,
        "path": "bonds.txt",
        "output path": "out.h5",
        "table": {},
        "number or list": 1.0,
        "number or table": 1.0,
        "number, list or table": 1.0,
        'list or "system"': "system",
        "list of integers": [0],
        "list of positions": [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]],
        "list of tables": [],
        "integer or list of integers": 3,
        '"bonded" or list of integers': "bonded",
        "integer or list of three": 2,
        "number or list of three": 0.0,
        "boolean or list of three": True,
    }
    return values[kind]


# ------------------------------------------------------------------ the parser
def base_config(section: str, kind: str | None, keys: dict) -> dict:
    """A valid config in which ``section`` (of plug-in type or system kind ``kind``) holds
    its required keys (from the page), with ``keys`` as the section's table."""

    def required(of) -> dict:
        return {
            name: sample(cells)
            for name, cells in PAGE_KEYS.get(of, {}).items()
            if cells[1] == "required"
        }

    config = {
        "units": "lj",
        "system": dict(SYSTEMS["lattice"]),
        "potentials": [{"type": "lj"}],
        "integrator": {"type": "verlet", "dt": 0.005},
    }
    table = dict(keys)
    if section == "":
        config.update(table)
    elif section == "system":
        config["system"] = {
            **SYSTEMS[kind],
            **{k: v for k, v in table.items() if k not in SYSTEMS[kind]},
        }
    elif section == "potentials":
        config["potentials"] = [{"type": kind, **required(("potentials", kind)), **table}]
    elif section == "integrator":
        config["integrator"] = {"type": kind, **required(("integrator", kind)), **table}
    elif section == "integrator.constraints":
        config["integrator"] = {"type": "rattle", "dt": 0.005, "constraints": table}
    elif section == "barostat":
        config["integrator"] = {
            "type": "nose_hoover_chain",
            "dt": 0.005,
            "temperature": 1.0,
            "tau": 0.5,
        }
        config["barostat"] = {"type": kind, **required(("barostat", kind)), **table}
    else:
        config[section] = table
    return config


def accepted(section: str, kind: str | None, name: str, value) -> bool:
    """Whether the parser takes ``name`` in ``section`` (of type or system kind ``kind``)."""
    config = base_config(section, kind, {name: value})
    try:
        parse_config(config, source="probe.toml", base=FOLDER)
    except ConfigError as error:
        message = str(error)
        return not (any(r in message for r in REFUSALS) and name in message)
    return True


def mismatches(page: str) -> list[str]:
    """Where the page and the parser disagree, one line each (empty: they agree)."""
    keys = documented(page)
    anywhere = {name: cells for table in keys.values() for name, cells in table.items()}
    candidates = set(anywhere) | CONSTRUCTOR_KEYS | EXAMPLE_KEYS | DECLARED_KEYS | {MADE_UP}
    problems = []
    for (section, kind), table in keys.items():
        for name in sorted(candidates - {"type"}):
            if section == "" and name in SECTION_NAMES:
                continue  # the tables themselves, documented as sections
            listed = name in table
            cells = table[name] if listed else anywhere.get(name)
            value = sample(cells) if cells else 1.0
            if accepted(section, kind, name, value) != listed:
                where = f"[{section}]" + (f" ({kind})" if kind else "")
                problems.append(
                    f"{where} {name}: "
                    + ("documented but refused" if listed else "accepted but not documented")
                )
    return problems


def _constructor_keys() -> set[str]:
    names = set()
    for cls in [*POTENTIALS.values(), *INTEGRATORS.values(), Barostat, BondConstraints]:
        names |= set(inspect.signature(cls.__init__).parameters) - {"self"}
    return names


def _example_keys() -> set[str]:
    names = set()

    def walk(value) -> None:
        if isinstance(value, dict):
            names.update(value)
            for item in value.values():
                walk(item)
        elif isinstance(value, list):
            for item in value:
                walk(item)

    for path in (ROOT / "examples").glob("*.toml"):
        walk(tomllib.loads(path.read_text()))
    return names


PAGE = reference.render()
PAGE_KEYS = documented(PAGE)
SECTION_NAMES = {s.name for s in sections() if s.name and "." not in s.name}
CONSTRUCTOR_KEYS = _constructor_keys()
DECLARED_KEYS = {
    k.name
    for s in sections()
    for k in (*s.keys, *(k for keys in (s.types or {}).values() for k in keys))
}
EXAMPLE_KEYS = _example_keys()
FOLDER = None  # set by the fixture: where s.xyz and bonds.txt exist


@pytest.fixture(autouse=True)
def folder(tmp_path):
    global FOLDER
    (tmp_path / "s.xyz").write_text(
        '2\nLattice="10 0 0 0 10 0 0 0 10" Properties=species:S:1:pos:R:3 pbc="T T T"\n'
        "Ar 0 0 0\nAr 3 3 3\n"
    )
    (tmp_path / "bonds.txt").write_text("0 1\n")
    FOLDER = tmp_path
    yield
    FOLDER = None


# ------------------------------------------------------------------ the tests
def test_the_page_lists_every_section_and_plug_in_type():
    kinds = {kind for (section, kind) in PAGE_KEYS if section == "system"}
    assert kinds == set(SYSTEMS)
    for section, registry in (
        ("potentials", POTENTIALS),
        ("integrator", INTEGRATORS),
        ("barostat", BAROSTAT_KEYS),
    ):
        assert {kind for (s, kind) in PAGE_KEYS if s == section} == set(registry)
    for name in ("", "integrator.constraints", "minimize", "run", "output"):
        assert (name, None) in PAGE_KEYS
    assert PAGE_KEYS[("run", None)]["steps"][:2] == ("integer >= 0", "`1000`")
    assert PAGE_KEYS[("integrator", "langevin")]["friction"][1] == "required"


def test_keys_documented_and_keys_accepted_are_the_same():
    assert mismatches(PAGE) == []


def test_the_check_fails_on_a_page_without_a_key():
    row = next(line for line in PAGE.splitlines() if line.startswith("| `skin` |"))
    assert "[run] skin: accepted but not documented" in mismatches(PAGE.replace(row + "\n", ""))


def test_the_check_fails_on_a_page_with_a_key_too_many():
    row = next(line for line in PAGE.splitlines() if line.startswith("| `skin` |"))
    extra = row.replace("`skin`", "`skim`")
    assert mismatches(PAGE.replace(row, row + "\n" + extra)) == [
        "[run] skim: documented but refused"
    ]


def test_a_made_up_key_is_refused_everywhere():
    for section, kind in PAGE_KEYS:
        assert not accepted(section, kind, MADE_UP, 1.0), (section, kind)


# ------------------------------------------------------------------ declarations
def _parameters(cls, leave_out=("self",)):
    return {
        n: p for n, p in inspect.signature(cls.__init__).parameters.items() if n not in leave_out
    }


def _same_default(key: Key, parameter: inspect.Parameter) -> bool:
    if parameter.default is inspect.Parameter.empty:
        return key.default is REQUIRED
    return key.default == parameter.default


@pytest.mark.parametrize("name", sorted(INTEGRATORS))
def test_an_integrator_declares_each_constructor_argument_with_its_default(name):
    """kB is left out: the config gives it from the unit system."""
    cls = INTEGRATORS[name]
    parameters = _parameters(cls, ("self", "kB"))
    assert [k.name for k in cls.CONFIG_KEYS] == list(parameters)
    for key in cls.CONFIG_KEYS:
        assert _same_default(key, parameters[key.name]), (name, key.name)


@pytest.mark.parametrize("name", sorted(POTENTIALS))
def test_a_potential_declares_each_constructor_argument_with_its_default(name):
    """A key without a default (None) may stand for an argument the config can give
    another way (``bonds`` or ``bonds_file``)."""
    cls = POTENTIALS[name]
    declared = {k.name: k for k in cls.CONFIG_KEYS}
    for parameter in _parameters(cls).values():
        assert parameter.name in declared, (name, parameter.name)
        key = declared[parameter.name]
        if key.default is not None:
            assert _same_default(key, parameter), (name, key.name)


def test_barostat_and_constraint_keys_match_their_constructors():
    parameters = _parameters(Barostat, ("self", "kind"))
    assert {k.name for keys in BAROSTAT_KEYS.values() for k in keys} == set(parameters)
    for keys in BAROSTAT_KEYS.values():
        for key in keys:
            if not isinstance(key.default, Varies) and key.default is not None:
                assert _same_default(key, parameters[key.name]), key.name
    declared = {k.name: k for k in BondConstraints.CONFIG_KEYS}
    for parameter in _parameters(BondConstraints).values():
        assert parameter.name in declared
        if parameter.default is not inspect.Parameter.empty:
            assert declared[parameter.name].default == parameter.default


def test_every_declared_unit_and_kind_is_known():
    every = [
        k
        for s in sections()
        for k in (*s.keys, *(k for keys in (s.types or {}).values() for k in keys))
    ]
    assert len(every) > 80
    for key in every:
        assert key.kind in KINDS
        assert key.unit is None or all(key.unit in u.config_units for u in UNIT_SYSTEMS.values())
        assert key.doc, key.name
    with pytest.raises(ValueError, match="unknown kind"):
        Key("x", "numbr")
