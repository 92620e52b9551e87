"""The kernel cache's dependency stamp: a cached kernel is compiled afresh after an
edit of a helper module it calls, and still loads from the cache when nothing changed."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from numba.core import caching, config

import md._kernel_cache as kernel_cache_module
from md._kernel_cache import dependency_stamp, kernel_cache, module_dependencies

#: The child: imports pkg.a inside kernel_cache(roots=[pkg]) ("ours") or plainly
#: ("numba", numba's own locators), calls the kernel and reports what it got.
#: md._kernel_cache needs only numba, so the child loads that file alone (quick).
CHILD = """
import contextlib, importlib.util, json, sys
folder, mode, module_path = sys.argv[1:4]
sys.path.insert(0, folder)
if mode == "ours":
    spec = importlib.util.spec_from_file_location("leapmd_kernel_cache", module_path)
    kc = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(kc)
    block = kc.kernel_cache(roots=[folder + "/pkg"])
else:
    block = contextlib.nullcontext()
with block:
    import pkg.a
value = pkg.a.kernel(1.0)
stats = pkg.a.kernel.stats
print(json.dumps({"value": value, "hits": sum(stats.cache_hits.values()),
                  "misses": sum(stats.cache_misses.values())}))
"""

KERNEL = """
from numba import njit

from .b import helper


@njit(cache=True)
def kernel(x):
    return helper(x) + 1.0
"""

HELPER = """
from numba import njit


@njit
def helper(x):
    return x * {factor}
"""


def _package(folder: Path) -> Path:
    pkg = folder / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text(KERNEL)
    (pkg / "b.py").write_text(HELPER.format(factor="2.0"))
    (folder / "child.py").write_text(CHILD)
    return pkg


def _edit_helper(pkg: Path) -> None:
    helper = pkg / "b.py"
    before = helper.stat().st_mtime_ns
    helper.write_text(HELPER.format(factor="3.0"))
    os.utime(helper, ns=(before + 10**9, before + 10**9))  # a later time on any filesystem


def _run(folder: Path, mode: str) -> dict:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(folder / f"cache_{mode}")}
    env.pop("NUMBA_DISABLE_JIT", None)
    done = subprocess.run(
        [sys.executable, str(folder / "child.py"), str(folder), mode, kernel_cache_module.__file__],
        env=env,
        capture_output=True,
        text=True,
        check=False,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_numba_alone_keeps_the_old_helper(tmp_path):
    """The defect being fixed: numba's own locator loads the caller with the old helper."""
    pkg = _package(tmp_path)
    assert _run(tmp_path, "numba")["value"] == 3.0
    _edit_helper(pkg)
    stale = _run(tmp_path, "numba")
    assert stale["hits"] == 1  # loaded from the cache ...
    assert stale["value"] == 3.0  # ... with 1 * 2 + 1, though b.py now says 1 * 3 + 1


def test_edited_helper_recompiles_and_unchanged_files_load_from_the_cache(tmp_path):
    pkg = _package(tmp_path)
    first = _run(tmp_path, "ours")
    assert (first["value"], first["misses"], first["hits"]) == (3.0, 1, 0)
    _edit_helper(pkg)
    edited = _run(tmp_path, "ours")
    assert edited["value"] == 4.0  # the new helper: compiled afresh
    assert (edited["misses"], edited["hits"]) == (1, 0)
    again = _run(tmp_path, "ours")
    assert again["value"] == 4.0
    assert (again["misses"], again["hits"]) == (0, 1)  # nothing edited: from the cache


def test_module_dependencies_follows_imports_within_the_roots(tmp_path):
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    other = tmp_path / "other"
    other.mkdir()
    files = {
        pkg / "__init__.py": "from pkg.c import name  # the facade\n",
        pkg
        / "a.py": "import os\nfrom numba import njit\n\nfrom .sub import d\nfrom pkg.b import (\n"
        "    one,  # a comment\n    two as three,\n)\n",
        pkg / "b.py": "def f():\n    import pkg.sub.e as e  # inside a function\n",
        pkg / "c.py": "name = 1\n",
        pkg / "sub" / "__init__.py": "",
        pkg / "sub" / "d.py": "from .. import c\nfrom other import x\n",
        pkg / "sub" / "e.py": "from pkg import a  # a cycle\n",
        other / "__init__.py": "",
    }
    for path, text in files.items():
        path.write_text(text)
    found = module_dependencies(pkg / "a.py", [pkg])
    names = sorted(os.path.relpath(path, tmp_path) for path in found)
    assert names == ["pkg/b.py", "pkg/c.py", "pkg/sub/d.py", "pkg/sub/e.py"]
    # only submodules taken from pkg and pkg.sub: neither __init__ is a dependency
    assert module_dependencies(pkg / "c.py", [pkg]) == []
    stamp = dependency_stamp(pkg / "sub" / "d.py", [pkg])
    assert [entry[0] for entry in stamp] == ["pkg/c.py"]
    assert stamp[0][1:] == (os.stat(pkg / "c.py").st_mtime_ns, len(files[pkg / "c.py"]))


def test_the_block_picks_the_per_user_folder_and_leaves_numba_as_it_was(tmp_path, monkeypatch):
    pkg = _package(tmp_path)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    monkeypatch.setattr(config, "CACHE_DIR", "")
    monkeypatch.syspath_prepend(str(tmp_path))
    locators = list(caching.CacheImpl._locator_classes)
    with kernel_cache(roots=[pkg]):
        assert caching.CacheImpl._locator_classes[0] not in locators
        with kernel_cache(roots=[pkg]):
            pass
        assert caching.CacheImpl._locator_classes[0] not in locators  # still the outer block's
        import pkg.a as kernels
    try:
        assert caching.CacheImpl._locator_classes == locators
        assert config.CACHE_DIR == ""
        assert kernels.kernel(np.float64(1.0)) == 3.0
        index = list((tmp_path / "xdg" / "leapmd" / "numba").glob("*/a.kernel-*.nbi"))
        assert len(index) == 1
    finally:
        for name in ("pkg.a", "pkg.b", "pkg"):
            sys.modules.pop(name, None)


def test_without_numbas_internals_numba_serves_as_before(monkeypatch, caplog):
    monkeypatch.delattr(caching.CacheImpl, "_locator_classes")
    monkeypatch.setattr(config, "CACHE_DIR", "")
    kernel_cache_module._numba_caching.cache_clear()
    caplog.set_level(logging.DEBUG, logger="md._kernel_cache")
    try:
        with kernel_cache():
            assert config.CACHE_DIR == str(kernel_cache_module.cache_directory())
        with kernel_cache():
            pass
        assert caplog.text.count("stamps only each kernel's own file") == 1
    finally:
        monkeypatch.undo()
        kernel_cache_module._numba_caching.cache_clear()
