"""The installed package is the one imported, and numba's cache stays out of it.

A non-editable install followed by an editable one (the README's two
commands in that order) used to leave ``site-packages/md/__pycache__`` full of
numba cache files, which pip does not remove: the folder then shadowed the
real package as a namespace package in every process started outside the
checkout. These tests fail if the package is shadowed, or if numba writes
our kernels' cache beside their sources again.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import md

ROOT = Path(__file__).resolve().parents[1]


def _child(code: str, cwd: Path, **env) -> subprocess.CompletedProcess:
    environment = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    environment.update(env)
    return subprocess.run(
        [sys.executable, "-c", code], cwd=cwd, env=environment, capture_output=True, text=True
    )


def test_a_process_outside_the_checkout_imports_the_real_packages(tmp_path):
    code = (
        "import json, md, potentials, integrators\n"
        "from integrators import VelocityVerlet\n"
        "print(json.dumps([md.__version__] + [m.__file__ for m in (md, potentials, integrators)]))"
    )
    result = _child(code, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    version, *files = json.loads(result.stdout)
    assert version == md.__version__
    # A namespace package (a leftover folder without __init__.py) has no __file__.
    assert all(f is not None and f.endswith("__init__.py") for f in files), files


@pytest.mark.slow  # keeps the default suite within its 10 minutes
def test_kernels_cache_per_user_not_beside_their_sources(tmp_path):
    cache = tmp_path / "xdg"
    code = (
        "import json, md, potentials, integrators\n"
        "from md.neighbors import _build_kernels\n"
        "from potentials._pair_codegen import kernels_for\n"
        "from integrators import _kernels\n"
        "lj = potentials.LennardJones(cutoff=2.5)\n"
        "pair = kernels_for(lj.term).frame_forces\n"
        "kernels = [_build_kernels._bin_atoms, pair, _kernels._kick]\n"
        "print(json.dumps([k._cache._cache_path for k in kernels]))\n"
        "s = md.lattice('fcc', 3, density=0.8)\n"
        "md.Simulation(s, [lj], integrators.VelocityVerlet(0.005)).run(2)\n"
    )
    result = _child(code, cwd=tmp_path, XDG_CACHE_HOME=str(cache))
    assert result.returncode == 0, result.stderr
    for path in json.loads(result.stdout):
        assert Path(path).is_relative_to(cache / "leapmd" / "numba"), path
        assert not Path(path).is_relative_to(ROOT)
    assert list(cache.rglob("*.nbi")), "the run compiled kernels but cached none"


def test_numba_cache_dir_set_by_the_user_wins_and_others_are_untouched(tmp_path):
    code = (
        "import json, md, numba\n"
        "from md.neighbors import _build_kernels\n"
        "from numba.core import config\n"
        "print(json.dumps([_build_kernels._bin_atoms._cache._cache_path, config.CACHE_DIR]))\n"
    )
    result = _child(code, cwd=tmp_path, NUMBA_CACHE_DIR=str(tmp_path / "mine"))
    assert result.returncode == 0, result.stderr
    path, setting = json.loads(result.stdout)
    assert Path(path).is_relative_to(tmp_path / "mine")
    assert setting == str(tmp_path / "mine")
    # Without it, numba's own setting is restored after our imports (other libraries
    # keep numba's default locations).
    result = _child(
        "import md, integrators\nfrom numba.core import config\nprint(repr(config.CACHE_DIR))",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "''"


def test_ci_runs_the_readme_commands_in_order():
    readme = (ROOT / "README.md").read_text()
    block = readme.split("```bash\n", 1)[1].split("```", 1)[0]
    commands = [line for line in block.splitlines() if line and not line.startswith("#")]
    assert len(commands) == 2 and "md run" in commands[0] and "pytest" in commands[1]
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    positions = [ci.index(command) for command in commands]  # verbatim lines
    assert positions == sorted(positions)


def test_every_package_is_listed_for_the_wheel():
    import tomllib

    listed = set(
        tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]
    )
    found = {
        ".".join(path.parent.relative_to(ROOT).parts)
        for top in ("md", "potentials", "integrators")
        for path in (ROOT / top).rglob("__init__.py")
    }
    assert found <= listed, f"missing from [tool.setuptools] packages: {sorted(found - listed)}"
