"""The import rule of ARCHITECTURE.md, checked on the source with ``ast``.

Modules import only downward: layer 0 (data and shared helpers), then
``potentials`` and ``integrators`` (which see only layer 0 of ``md``), then
the engine, then files and runs, then the edges, and the CLI on top, which
nothing imports. No import cycles; imports inside functions only for heavy
optional dependencies, each with a one-line reason; no module reads another
module's private names.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("md", "potentials", "integrators")

#: Layer of each module (a name ending in ".*" covers a package).
LAYERS = {
    0: [
        "md._version",
        "md._kernel_cache",
        "md._memory",
        "md._simd",
        "md.state",
        "md.box",
        "md.units",
        "md.parallel",
        "md.errors",
        "md.thermo",
        "md._checks",
        "md._files",
        "md.topology",
        "md.interrupts",
    ],
    1: ["potentials.*", "integrators.*"],
    2: [
        "md.neighbors",
        "md._cell_kernels",
        "md.forcefield",
        "md.simulation",
        "md.observers",
        "md.build",
        "md.polymers",
        "md.minimize",
    ],
    3: ["md.trajectory", "md.checkpoint", "md.structure", "md.config", "md.run"],
    4: [
        "md.analysis",
        "md.analysis_output",
        "md.integrator_study",
        "md.calculator",
        "md.validate",
        "md.convert",
        "md.render",
        "md.notebook",
        "md.sweeps.*",
    ],
    5: ["md.cli.*"],
}
#: What potentials/ and integrators/ may import besides layer 0 of md.
PLUGIN_IMPORTS = {
    "potentials": ("potentials",),
    "integrators": ("integrators", "potentials.base"),
}
#: Project imports allowed inside functions, with why.
LATE_PROJECT_IMPORTS = {
    ("md", "md.sweeps"): "md.sweep() loads the Dask machinery on first use",
    ("md.cli.sweep_child", "md.cli"): "imported after the child has set PR_SET_PDEATHSIG",
}


def _modules() -> dict[str, Path]:
    found = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            found[".".join(parts)] = path
    return found


MODULES = _modules()


def layer_of(module: str) -> int:
    for layer, names in LAYERS.items():
        for name in names:
            if module == name or (name.endswith(".*") and module.startswith(name[:-2])):
                return layer
    raise KeyError(module)


class _Imports(ast.NodeVisitor):
    """Collect (line, imported module, inside a function, names) of one file."""

    def __init__(self, module: str, is_package: bool) -> None:
        self.module, self.is_package = module, is_package
        self.found: list[tuple[int, str, bool, list[str]]] = []
        self.depth = 0

    def visit_FunctionDef(self, node) -> None:
        self.depth += 1
        self.generic_visit(node)
        self.depth -= 1

    visit_AsyncFunctionDef = visit_FunctionDef

    def visit_If(self, node) -> None:
        test = node.test
        if isinstance(test, ast.Name) and test.id == "TYPE_CHECKING":
            for child in node.orelse:  # annotations only: not imported at run time
                self.visit(child)
            return
        self.generic_visit(node)

    def visit_Import(self, node) -> None:
        for alias in node.names:
            self.found.append((node.lineno, alias.name, self.depth > 0, []))

    def visit_ImportFrom(self, node) -> None:
        if node.level:
            base = self.module.split(".")
            if not self.is_package:
                base = base[:-1]
            base = base[: len(base) - node.level + 1]
            target = ".".join(base + ([node.module] if node.module else []))
        else:
            target = node.module
        names = [a.name for a in node.names]
        # "from md import x" may name a submodule: record it as such.
        submodules = [n for n in names if f"{target}.{n}" in MODULES]
        for name in submodules:
            self.found.append((node.lineno, f"{target}.{name}", self.depth > 0, []))
        if len(submodules) < len(names):
            self.found.append((node.lineno, target, self.depth > 0, names))


def _imports(module: str) -> list[tuple[int, str, bool, list[str]]]:
    path = MODULES[module]
    visitor = _Imports(module, path.name == "__init__.py")
    visitor.visit(ast.parse(path.read_text(), filename=str(path)))
    return visitor.found


def _project(target: str) -> str | None:
    """The project module an import names (or the nearest package), else None."""
    if target.split(".")[0] not in PACKAGES:
        return None
    while target and target not in MODULES:
        target = target.rpartition(".")[0]
    return target or None


@pytest.mark.parametrize("module", sorted(m for m in MODULES if m != "md"))
def test_imports_go_only_downward(module):
    own = layer_of(module)
    root = module.split(".")[0]
    for line, target, late, _ in _imports(module):
        imported = _project(target)
        if imported is None or imported == "md":
            assert imported is None or late, f"{module}:{line} imports the md facade"
            continue
        if root in PLUGIN_IMPORTS:
            allowed = imported.startswith(PLUGIN_IMPORTS[root]) or layer_of(imported) == 0
            assert allowed, f"{module}:{line}: {root}/ may import only layer 0 of md, not {target}"
            continue
        if (module, imported) in LATE_PROJECT_IMPORTS:
            continue
        assert layer_of(imported) <= own, (
            f"{module} (layer {own}) imports {imported} (layer {layer_of(imported)}) at line "
            f"{line}: modules import only downward"
        )


def test_nothing_imports_the_cli():
    for module in MODULES:
        if module.startswith("md.cli"):
            continue
        for line, target, _, _ in _imports(module):
            assert not (_project(target) or "").startswith("md.cli"), f"{module}:{line}"


def test_no_import_cycles():
    graph = {
        module: {
            _project(target)
            for _, target, late, _ in _imports(module)
            if not late and _project(target) not in (None, module)
        }
        for module in MODULES
    }
    # A package's __init__ is imported before its submodules: an edge to it is
    # part of importing anything below it, not a cycle of its own.
    state: dict[str, int] = {}

    def visit(node, path):
        state[node] = 1
        for nxt in sorted(graph[node]):
            if nxt in (path[0].rpartition(".")[0],) or node.startswith(nxt + "."):
                continue
            if state.get(nxt) == 1:
                raise AssertionError("import cycle: " + " -> ".join([*path, nxt]))
            if nxt not in state:
                visit(nxt, [*path, nxt])
        state[node] = 2

    for module in sorted(graph):
        if module not in state:
            visit(module, [module])


def test_imports_inside_functions_are_heavy_optional_and_explained():
    for module, path in MODULES.items():
        lines = path.read_text().splitlines()
        for line, target, late, _ in _imports(module):
            if not late:
                continue
            imported = _project(target)
            if imported is not None:
                assert (module, imported) in LATE_PROJECT_IMPORTS, (
                    f"{module}:{line} imports {target} inside a function; project imports "
                    "belong at the top of the module"
                )
            text, above = lines[line - 1], lines[line - 2].strip()
            assert "#" in text or above.startswith("#"), (
                f"{module}:{line}: an import inside a function needs a one-line reason "
                f"(a comment on its line or the line above): {text.strip()}"
            )


def test_no_module_imports_another_modules_private_names():
    for module in MODULES:
        for line, target, _, names in _imports(module):
            imported = _project(target)
            if imported is None or imported.split(".")[-1].startswith("_"):
                continue  # a private shared module (md._checks) is there for its siblings
            private = [n for n in names if n.startswith("_") and not n.startswith("__")]
            assert not private, f"{module}:{line} imports private {private} from {target}"


def test_no_module_reads_another_objects_private_attributes():
    """``obj._name`` only for private attributes that the same module sets itself."""
    offenders = []
    for module, path in MODULES.items():
        tree = ast.parse(path.read_text())
        own = {  # private attributes this module assigns (self._x = ..., obj._x = ...)
            target.attr
            for node in ast.walk(tree)
            if isinstance(node, ast.Assign | ast.AnnAssign | ast.AugAssign)
            for target in (node.targets if isinstance(node, ast.Assign) else [node.target])
            if isinstance(target, ast.Attribute)
        }
        own |= {n.name for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)}
        for node in ast.walk(tree):
            if not isinstance(node, ast.Attribute):
                continue
            name = node.attr
            if not name.startswith("_") or name.startswith("__") or name in own:
                continue
            base = node.value
            if isinstance(base, ast.Name) and base.id in ("self", "cls", "sys", "os"):
                continue
            offenders.append(f"{module}:{node.lineno}: .{name} on {ast.unparse(base)}")
    assert not offenders, "\n".join(offenders)


def test_importing_md_stays_light():
    code = (
        "import sys, md, potentials, integrators\n"
        "heavy = [m for m in ('md.cli', 'md.sweeps', 'distributed', 'dask', 'matplotlib',"
        " 'MDAnalysis') if m in sys.modules]\n"
        "assert not heavy, heavy\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


def test_every_module_has_a_layer():
    for module in MODULES:
        if module != "md":
            layer_of(module)
