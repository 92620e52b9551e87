"""Config sections as typed records: what they hold, the units they convert, the
fingerprints checkpoints compare, and the messages for keys in the wrong place."""

from __future__ import annotations

import copy
import dataclasses
import json
import pickle
import tomllib
from pathlib import Path

import pytest

from md import units
from md.checkpoint import fingerprint_changes, physics_fingerprint
from md.config import (
    MinimizeConfig,
    OutputConfig,
    PluginEntry,
    RunConfig,
    SystemConfig,
    input_files,
    parse_config,
)
from md.errors import ConfigError

DATA = Path(__file__).parent / "data" / "config_fingerprints.json"

NPT = """
units = "metal"
seed = 11
[system]
lattice = "fcc"
cells = 3
lattice_constant = 5.26
[[potentials]]
type = "lj"
epsilon = 0.0104
sigma = 3.4
cutoff = 7
[integrator]
type = "langevin"
dt = 2
temperature = 90
friction = 0.01
[barostat]
type = "c_rescale"
pressure = 1
tau = 500
"""


def parse(text: str, **changes) -> object:
    data = tomllib.loads(text)
    for section, values in changes.items():
        data[section] = {**data.get(section, {}), **values}
    return parse_config(data, source="run.toml", text=text)


def test_sections_are_frozen_records_in_engine_units():
    config = parse(NPT)
    assert isinstance(config.system, SystemConfig) and isinstance(config.run, RunConfig)
    assert isinstance(config.output, OutputConfig) and config.minimize is None
    assert config.run == RunConfig() and config.output.path == Path("trajectory.h5")
    assert config.system.cells == (3, 3, 3) and config.system.type_name == "A"
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.run.steps = 5
    with pytest.raises(TypeError):
        config.integrator.values["dt"] = 1.0
    # Times, rates and pressures converted by the unit their key declares, bit for bit
    # as the config always has (checkpoints compare them).
    langevin = config.integrator
    assert (langevin.type, langevin.dt) == ("langevin", 2.0 * units.fs)
    assert langevin.get("friction") == 0.01 / units.fs
    assert langevin.get("temperature") == 90.0 and langevin.get("kB") == units.kB
    assert langevin.get("seed") == [11, 1]  # a stream apart from the velocity draw's
    barostat = config.barostat
    to_engine = 1.0 / units.eV_per_A3_in_bar
    assert barostat.values == {
        "pressure": 1.0 * to_engine,
        "tau": 500.0 * units.fs,
        "couple": "isotropic",
        "compressibility": 4.5e-5 / to_engine,
        "every": 10,
        "seed": [11, 2],
    }
    reduced = tomllib.loads(NPT)
    del reduced["units"]  # lj: the default is another, and nothing is converted
    assert parse_config(reduced).barostat.get("compressibility") == 0.1
    # Records travel (sweeps, processes) and compare by value.
    assert pickle.loads(pickle.dumps(config)) == config == copy.deepcopy(config)
    assert MinimizeConfig().fmax == 1e-2


def test_fingerprints_of_configs_written_before_the_records_are_unchanged(tmp_path, monkeypatch):
    """A checkpoint compares its fingerprint with the config's when a run resumes: configs
    fingerprinted by the code before the typed records (tests/data, written by it) still
    match, so their runs resume."""
    stored = json.loads(DATA.read_text())
    monkeypatch.chdir(tmp_path)
    for name, text in stored["files"].items():
        Path(name).write_text(text)
    assert len(stored["configs"]) >= 7
    for name, case in stored["configs"].items():
        config = parse_config(
            tomllib.loads(case["toml"]), source=f"{name}.toml", text=case["toml"], base="."
        )
        assert fingerprint_changes(case["fingerprint"], physics_fingerprint(config)) == [], name
        changed = dataclasses.replace(config, run=dataclasses.replace(config.run, skin=0.25))
        assert fingerprint_changes(case["fingerprint"], physics_fingerprint(changed)) == [
            f"run.skin: {config.run.skin} -> 0.25"
        ]


def test_input_files_are_the_paths_keys_name(tmp_path):
    (tmp_path / "b.txt").write_text("0 1\n")
    text = NPT.replace(
        '[integrator]\ntype = "langevin"',
        '[[potentials]]\ntype = "spring"\n'
        'bonds_file = "b.txt"\nk = 1\nr0 = 1\n[integrator]\ntype = "langevin"',
    )
    data = tomllib.loads(text)
    data["integrator"]["constraints"] = {"bonds_file": str(tmp_path / "b.txt")}
    config = parse_config(data, source="run.toml", base=tmp_path)
    assert input_files(config) == [tmp_path / "b.txt", tmp_path / "b.txt"]
    assert config.potentials[1].get("bonds_file") == str(tmp_path / "b.txt")


@pytest.mark.parametrize(
    ("section", "values", "message"),
    [
        (
            "integrator",
            {"type": "bussi", "tau": 100.0, "friction": 1.0},
            "run.toml: [integrator] friction: does not apply to type = 'bussi', which takes dt, "
            "temperature, tau, seed, constraints, fix_com",
        ),
        (
            "integrator",
            {"friction": None},
            "run.toml: missing required key [integrator] friction (type = 'langevin' needs it)",
        ),
        ("integrator", {"kB": 2.0}, "run.toml: [integrator] (langevin): unknown key(s): kB"),
        (
            "integrator",
            {"type": "verlet", "friction": None, "temperature": None},
            "run.toml: [integrator] (verlet) does not apply constraints; use one of rattle",
        ),
        ("barostat", {"every": 0}, "run.toml: [barostat] every: must be >= 1, got 0"),
        (
            "system",
            {"chains": 4},
            'run.toml: [system] chains: does not apply to a lattice (only to polymer = "melt")',
        ),
        (
            "system",
            {"straight": True, "chains": 4},
            "[system] chains, straight: does not apply "
            'to a lattice (only to polymer = "chain" or polymer = "melt")',
        ),
        ("run", {"ranks": 4}, "run.toml: unknown key(s) in [run]: ranks"),
        (
            "run",
            {"decomposition": [2, 0, 1]},
            "run.toml: [run] decomposition: must be positive integers, got [2, 0, 1]",
        ),
        (
            "run",
            {"decomposition": [2, 1]},
            "run.toml: [run] decomposition: expected int or a list of three, got [2, 1]",
        ),
    ],
)
def test_a_key_in_the_wrong_place_is_refused_naming_it(section, values, message):
    data = tomllib.loads(NPT)
    table = data.setdefault(section, {})
    for name, value in values.items():
        if value is None:
            table.pop(name)
        else:
            table[name] = value
    if "verlet" in values.values():
        data.pop("barostat")
        table["constraints"] = {"bonds": [[0, 1]]}
    with pytest.raises(ConfigError) as caught:
        parse_config(data, source="run.toml")
    assert message in str(caught.value)


def test_plugin_entries_build_what_they_name():
    from md.config import integrator_from_config

    entry = PluginEntry("nhc", {"dt": 0.01, "temperature": 1.0, "tau": 0.5, "chain_length": 2})
    chain = integrator_from_config(entry, "x.toml")
    assert (chain.dt, chain.chain_length, chain.tau) == (0.01, 2, 0.5)
    assert "tau" in entry and entry.get("seed") is None
