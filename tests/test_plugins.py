"""Plug-ins from outside the package: a user's pair style, bond style and integrator named
in a TOML config by ``module:attribute`` (a module on PYTHONPATH) or by entry point (a
small plug-in package, ``examples/plugin_package``, installed into a temporary folder),
and run by ``md run``; bad plug-ins exit 2 with a message and write nothing.

The package is "installed" as pip would leave it for importlib.metadata: the package's
folder beside a ``.dist-info`` holding its METADATA and the entry points its
pyproject.toml declares (pip itself would need the wheel package to build it offline).
"""

from __future__ import annotations

import math
import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import h5py
import numpy as np
import pytest

import potentials
from integrators import integrator_class
from md.cli import main
from md.config import load_config
from md.errors import PluginError
from md.schema import REQUIRED
from md.state import State

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "examples" / "plugin_package"
SOURCES = PACKAGE / "leapmd_demo_plugin"

CONFIG = """\
units = "lj"
seed = 7

[system]
lattice = "fcc"
cells = 2
density = 0.5
temperature = 0.5

[[potentials]]
type = "{pair}"
a = 2.0
width = 0.8
cutoff = 1.8
{pair_extra}

[[potentials]]
type = "{bond}"
bonds = [[0, 1], [2, 3]]
k = 20.0
r0 = 1.1
c = 1.0

[integrator]
type = "{integrator}"
dt = 0.005

[run]
steps = 20
thermo_every = 10

[output]
path = "out.h5"
every = 10
"""
BY_PATH = {
    "pair": "user_pair:Gauss",
    "bond": "user_bond:AnharmonicBonds",
    "integrator": "user_integrator:PositionVerlet",
}
BY_ENTRY_POINT = {
    "pair": "demo_gauss",
    "bond": "demo_anharmonic",
    "integrator": "demo_position_verlet",
}


def _user_modules(folder: Path) -> Path:
    """The plug-ins as three loose files in ``folder``, outside the repository."""
    folder.mkdir(exist_ok=True)
    for source, name in (
        ("pairs", "user_pair"),
        ("bonds", "user_bond"),
        ("integrators", "user_integrator"),
    ):
        shutil.copy(SOURCES / f"{source}.py", folder / f"{name}.py")
    return folder


def _installed_package(target: Path) -> Path:
    """The plug-in package installed into ``target``: its folder and a .dist-info with the
    entry points of its pyproject.toml (what importlib.metadata reads)."""
    project = tomllib.loads((PACKAGE / "pyproject.toml").read_text())["project"]
    shutil.copytree(SOURCES, target / SOURCES.name)
    info = target / f"leapmd_demo_plugin-{project['version']}.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(
        f"Metadata-Version: 2.1\nName: {project['name']}\nVersion: {project['version']}\n"
    )
    lines = []
    for group, points in project["entry-points"].items():
        lines += [f"[{group}]", *(f"{name} = {value}" for name, value in points.items()), ""]
    (info / "entry_points.txt").write_text("\n".join(lines))
    return target


def _md_run(folder: Path, config: str, path: Path) -> subprocess.CompletedProcess:
    """``md run config`` in ``folder``, in a child process with ``path`` on its PYTHONPATH."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(path), str(ROOT)]))
    return subprocess.run(
        [sys.executable, "-m", "md.cli", "run", config, "--no-progress", "-q"],
        cwd=folder,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )


def _check_run(output: Path, result: subprocess.CompletedProcess) -> None:
    assert result.returncode == 0, result.stdout + result.stderr
    with h5py.File(output, "r") as h5:
        steps = h5["particles/trajectory/position/step"][:]
        total = h5["observables/total_energy/value"][:]
    assert list(steps) == [0, 10, 20]
    assert np.ptp(total) < 1e-3 * abs(total[0])  # position Verlet conserves energy


def test_user_pair_and_bond_terms_in_files_on_pythonpath_run_through_md_run(tmp_path):
    modules = _user_modules(tmp_path / "elsewhere")
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.toml").write_text(CONFIG.format(**BY_PATH, pair_extra=""))
    _check_run(run / "out.h5", _md_run(run, "config.toml", modules))


def test_the_same_plug_ins_run_through_their_entry_points(tmp_path):
    """The example config that names them by entry point, the package installed."""
    site = _installed_package(tmp_path / "site")
    config = PACKAGE / "entry_points.toml"
    _check_run(tmp_path / "demo_plugins.h5", _md_run(tmp_path, str(config), site))


# ---------------------------------------------------------------- in this process
@pytest.fixture
def plugin_path(tmp_path, monkeypatch):
    """The loose modules and the installed package importable in this process."""
    modules = _user_modules(tmp_path / "elsewhere")
    site = _installed_package(tmp_path / "site")
    monkeypatch.syspath_prepend(str(modules))
    monkeypatch.syspath_prepend(str(site))
    (modules / "broken_plugin.py").write_text("raise RuntimeError('the plug-in broke')\n")
    (modules / "wrong_signature.py").write_text(
        "from potentials import PairPotential\n"
        "from user_pair import GAUSS\n\n\n"
        "class Gauss(PairPotential):\n"
        "    PARAMETERS = ('a', 'width')\n\n"
        "    def __init__(self, a=1.0, w=1.0, cutoff=3.0, cutoff_mode='shift', r_on=None,\n"
        "                 pairs=None):\n"
        "        super().__init__(GAUSS, cutoff, cutoff_mode, r_on, pairs, a=a, width=w)\n"
    )
    (modules / "raising_plugin.py").write_text(
        "from integrators.base import IntegratorBase\n\n\n"
        "class Stuck(IntegratorBase):\n"
        "    def __init__(self, dt):\n"
        "        raise KeyError('no such table')\n\n"
        "    def step(self, state, forcefield):\n"
        "        pass\n\n"
        "    def describe(self):\n"
        "        return {}\n"
    )
    before = set(sys.modules)
    yield tmp_path
    for name in set(sys.modules) - before:
        if name.split(".")[0] in (
            "user_pair",
            "user_bond",
            "user_integrator",
            "broken_plugin",
            "wrong_signature",
            "raising_plugin",
            "leapmd_demo_plugin",
        ):
            del sys.modules[name]


def test_the_example_configs_name_the_same_plug_ins(plugin_path):
    by_path, by_entry = (load_config(PACKAGE / f"{n}.toml") for n in ("by_path", "entry_points"))
    assert [p.values for p in by_path.potentials] == [p.values for p in by_entry.potentials]
    for a, b in zip(by_path.potentials, by_entry.potentials, strict=True):
        assert potentials.potential_class(a.type) is potentials.potential_class(b.type)
    assert integrator_class(by_path.integrator.type) is integrator_class(by_entry.integrator.type)


def test_config_keys_of_a_style_that_declares_none_follow_from_its_constructor(plugin_path):
    from user_bond import AnharmonicBonds
    from user_pair import Gauss

    keys = {k.name: k for k in Gauss.CONFIG_KEYS}
    assert list(keys) == ["a", "width", "cutoff", "cutoff_mode", "r_on", "pairs"]
    assert (keys["a"].kind, keys["a"].default, keys["cutoff"].default) == ("number", 1.0, 3.0)
    bond_keys = {k.name: k.default for k in AnharmonicBonds.CONFIG_KEYS}
    assert bond_keys == {
        "bonds": None,
        "bonds_file": None,
        "k": 10.0,
        "r0": 1.0,
        "c": 0.0,
        "bond_types": None,
    }


def test_a_plug_in_resolves_by_path_and_by_entry_point_to_one_class(plugin_path):
    by_path = potentials.potential_class("leapmd_demo_plugin.pairs:Gauss")
    assert potentials.potential_class("demo_gauss") is by_path
    assert potentials.potential_class("lj") is potentials.LennardJones


def test_a_builtin_name_wins_over_an_entry_point_of_that_name(plugin_path, caplog):
    info = next((plugin_path / "site").glob("*.dist-info"))
    text = (info / "entry_points.txt").read_text()
    (info / "entry_points.txt").write_text(
        text.replace(
            "demo_anharmonic =",
            "spring = leapmd_demo_plugin.bonds:AnharmonicBonds\ndemo_anharmonic =",
        )
    )
    assert potentials.potential_class("spring") is potentials.HarmonicBonds
    potentials.potential_class("demo_anharmonic")  # a search of the entry points warns
    assert "shadowed" in caplog.text and "spring" in caplog.text


def test_a_plug_in_config_is_validated_like_a_builtin(plugin_path):
    config = plugin_path / "config.toml"
    config.write_text(CONFIG.format(**BY_PATH, pair_extra="depth = 1.0"))
    with pytest.raises(ValueError, match=r"\[potentials.0\] \(user_pair:Gauss\): unknown key"):
        load_config(config)
    config.write_text(CONFIG.format(**BY_PATH, pair_extra='cutoff_mode = "sharp"'))
    with pytest.raises(ValueError, match=r"\[potentials.0\] cutoff_mode: must be one of"):
        load_config(config)
    config.write_text(CONFIG.format(**BY_PATH, pair_extra=""))
    assert load_config(config).potentials[0].values["width"] == 0.8


BAD = [
    (
        "pair",
        "no_such_module:Gauss",
        "[potentials.0] type: plug-in 'no_such_module:Gauss': no module named 'no_such_module'",
    ),
    (
        "pair",
        "user_pair:Gaussian",
        "[potentials.0] type: plug-in 'user_pair:Gaussian': module user_pair",
    ),
    ("pair", "gaussian", "[potentials.0] type: must be one of 'lj'"),
    (
        "pair",
        "broken_plugin:Gauss",
        "[potentials.0] type: plug-in 'broken_plugin:Gauss': "
        "importing broken_plugin raised RuntimeError: the plug-in broke",
    ),
    (
        "pair",
        "user_pair:gauss_energy",
        "[potentials.0] type: plug-in 'user_pair:gauss_energy': is function",
    ),
    ("pair", "user_pair:GAUSS", "not a potential class"),
    (
        "pair",
        "wrong_signature:Gauss",
        "[potentials.0] type: plug-in 'wrong_signature:Gauss': its constructor Gauss(a=1.0, w=1.0",
    ),
    ("bond", "user_pair:Gauss", "does not apply to type = 'user_pair:Gauss'"),
    (
        "integrator",
        "user_bond:AnharmonicBonds",
        "[integrator] type: plug-in "
        "'user_bond:AnharmonicBonds': AnharmonicBonds is not an integrator",
    ),
    (
        "integrator",
        "raising_plugin:Stuck",
        "[integrator] (raising_plugin:Stuck): building it raised KeyError: 'no such table'",
    ),
]


@pytest.mark.parametrize(("section", "name", "message"), BAD, ids=[b[1] for b in BAD])
def test_a_bad_plug_in_exits_2_naming_it_and_writes_nothing(
    plugin_path, monkeypatch, capsys, section, name, message
):
    monkeypatch.chdir(plugin_path)
    types = dict(BY_PATH, **{section: name})
    (plugin_path / "config.toml").write_text(CONFIG.format(**types, pair_extra=""))
    assert main(["run", "config.toml", "--no-progress", "-q"]) == 2
    err = capsys.readouterr().err
    assert "config.toml: " + message in err or message in err, err
    assert "Traceback" not in err
    assert not list(plugin_path.glob("out.h5*"))


def test_a_plug_in_value_its_constructor_refuses_exits_2(plugin_path, monkeypatch, capsys):
    monkeypatch.chdir(plugin_path)
    text = CONFIG.format(**BY_PATH, pair_extra="").replace("width = 0.8", "width = -0.8")
    (plugin_path / "config.toml").write_text(text)
    assert main(["run", "config.toml", "--no-progress", "-q"]) == 2
    err = capsys.readouterr().err
    assert "config.toml: [potentials.0] (user_pair:Gauss): width" in err, err
    assert not list(plugin_path.glob("out.h5*"))


def test_errors_of_the_lookup_itself():
    with pytest.raises(PluginError, match="expected 'module:attribute'"):
        potentials.potential_class(":Gauss")
    with pytest.raises(PluginError, match="is float 3.14"):
        potentials.potential_class("math:pi")


# ---------------------------------------------------------------- physics
def test_the_plug_in_gaussian_matches_its_analytic_energy_and_gradient(plugin_path):
    from user_bond import ANHARMONIC
    from user_pair import GAUSS, Gauss

    a, width = 2.0, 0.8
    term = potentials.check_term(GAUSS, {"a": a, "inv_w2": 1.0 / width**2}, (0.2, 2.5))
    assert max(term.errors.values()) < 1e-7
    bond = potentials.check_term(ANHARMONIC, {"k": 20.0, "r0": 1.1, "c": 1.0}, (0.6, 1.6))
    assert max(bond.errors.values()) < 1e-7

    gauss = Gauss(a=a, width=width, cutoff=3.0, cutoff_mode="none")

    def energy_forces(x):
        state = State(positions=[[0.0, 0.0, 0.0], [x, 0.3, -0.2]], box=20.0, pbc=False)
        return gauss.energy_forces(state, None), state

    x, h = 0.7, 1e-6
    result, state = energy_forces(x)
    r = math.dist(*state.positions)
    assert result.energy == pytest.approx(a * math.exp(-((r / width) ** 2)), rel=1e-12)
    gradient = (energy_forces(x + h)[0].energy - energy_forces(x - h)[0].energy) / (2 * h)
    assert result.forces[1, 0] == pytest.approx(-gradient, rel=1e-7)
    np.testing.assert_allclose(result.forces.sum(axis=0), 0.0, atol=1e-14)


def test_the_ase_calculator_takes_a_plug_in_table_as_a_config_does(plugin_path):
    from ase import Atoms

    from md.calculator import MDCalculator

    table = {
        "type": "user_pair:Gauss",
        "a": 2.0,
        "width": 0.8,
        "cutoff": 3.0,
        "cutoff_mode": "none",
    }
    atoms = Atoms("Ar2", positions=[[0.0, 0.0, 0.0], [0.9, 0.0, 0.0]])
    atoms.calc = MDCalculator(potentials=[table])
    assert atoms.get_potential_energy() == pytest.approx(2.0 * math.exp(-((0.9 / 0.8) ** 2)))
    with pytest.raises(ValueError, match=r"potentials\[0\]: type plug-in 'user_pair:Gaussian'"):
        MDCalculator(potentials=[dict(table, type="user_pair:Gaussian")])


def test_an_angle_style_without_config_keys_reads_its_table(tmp_path):
    @potentials.angle_term(variable="cos")
    def bend(c, k, c0):
        return k * (c - c0) ** 2, 2.0 * k * (c - c0)

    class Bend(potentials.AnglePotential):
        def __init__(self, angles, k, c0=-1.0, angle_types=None):
            super().__init__(bend, angles, angle_types, k=k, c0=c0)

    keys = {k.name: k.default for k in Bend.CONFIG_KEYS}
    assert list(keys) == ["angles", "angles_file", "k", "c0", "angle_types"]
    assert keys["c0"] == -1.0 and keys["k"] is REQUIRED
    (tmp_path / "angles.txt").write_text("# i j k\n0 1 2\n1 2 3\n")
    built = Bend.from_config({"angles_file": str(tmp_path / "angles.txt"), "k": 2.0})
    assert built.angles.tolist() == [[0, 1, 2], [1, 2, 3]]
    with pytest.raises(ValueError, match="give exactly one of 'angles'"):
        Bend.from_config({"k": 2.0})
