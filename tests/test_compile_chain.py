"""The kernels' call chains compile each body once: a threaded kernel's ``prange`` index is
not passed bare to a compiled (not inlined) function.

numba types a ``prange`` loop twice: with the function (its index an int64, as ``range``
gives) and again as the outlined parallel body (its index a uint64). A compiled callee
given the bare index is then compiled for both, its LLVM optimised twice over: the pair
frame's chunk kernel and the cell search's chunk were, 3 s and 1.4 s CPU per variant
(benchmarks/README.md, "Cold compile time"). The kernels pass ``np.int64(index)``. Read
from the sources (no compilation): a callee is flagged unless it is ``inline="always"``.
"""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest
from numba.core.registry import CPUDispatcher

ROOT = Path(__file__).resolve().parents[1]
#: Every module of the packages with a threaded loop.
FILES = tuple(
    path.relative_to(ROOT).as_posix()
    for package in ("md", "potentials", "integrators")
    for path in sorted((ROOT / package).rglob("*.py"))
    if "prange" in path.read_text()
)


def _inlined_defs(tree: ast.Module) -> dict[str, bool]:
    """The module's own ``@njit`` functions: whether each is ``inline="always"``."""
    found = {}
    for node in tree.body:
        if not isinstance(node, ast.FunctionDef):
            continue
        for decorator in node.decorator_list:
            if getattr(decorator, "id", "") == "njit":
                found[node.name] = False
            elif isinstance(decorator, ast.Call) and getattr(decorator.func, "id", "") == "njit":
                found[node.name] = any(
                    k.arg == "inline" and getattr(k.value, "value", None) == "always"
                    for k in decorator.keywords
                )
    return found


def _compiled_callees(tree: ast.Module) -> set[str]:
    """The names of compiled functions, not inlined, that the module defines or imports."""
    names = {name for name, inlined in _inlined_defs(tree).items() if not inlined}
    for node in tree.body:
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            module = importlib.import_module(node.module)
            for alias in node.names:
                value = getattr(module, alias.name, None)
                if isinstance(value, CPUDispatcher) and value.targetoptions.get("inline") != (
                    "always"
                ):
                    names.add(alias.asname or alias.name)
    return names


def _bare_prange_indices(source: str) -> list[str]:
    """``callee(index)`` calls in ``prange`` loops that pass the loop's index bare to a
    compiled callee: 'line: callee(index)' for each."""
    tree = ast.parse(source)
    compiled = _compiled_callees(tree)
    found = []
    for loop in ast.walk(tree):
        if not (
            isinstance(loop, ast.For)
            and isinstance(loop.iter, ast.Call)
            and getattr(loop.iter.func, "id", "") == "prange"
            and isinstance(loop.target, ast.Name)
        ):
            continue
        index = loop.target.id
        for call in ast.walk(loop):
            if isinstance(call, ast.Call) and getattr(call.func, "id", "") in compiled:
                if any(isinstance(a, ast.Name) and a.id == index for a in call.args):
                    found.append(f"{call.lineno}: {call.func.id}({index})")
    return found


@pytest.mark.parametrize("path", FILES)
def test_no_prange_index_reaches_a_compiled_callee_bare(path):
    assert _bare_prange_indices((ROOT / path).read_text()) == []


def test_the_check_finds_a_bare_index():
    """The check itself: a compiled callee given the index bare is found, one given it
    converted or an inlined one is not."""
    source = (
        "from numba import njit, prange\n"
        "@njit\n"
        "def body(c, x):\n    x[c] = 1.0\n"
        "@njit(inline='always')\n"
        "def light(c, x):\n    x[c] = 2.0\n"
        "@njit(parallel=True)\n"
        "def run(x):\n"
        "    for c in prange(x.shape[0]):\n"
        "        body(c, x)\n"
        "        body(np.int64(c), x)\n"
        "        light(c, x)\n"
    )
    assert _bare_prange_indices(source) == ["11: body(c)"]
