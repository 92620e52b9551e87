"""The import rule of ARCHITECTURE.md, checked on the source with ``ast``.

Modules import only downward: layer 0 (data and shared helpers), then
``potentials`` and ``integrators`` (which see only layer 0 of ``md``), then
the engine, then files and runs, then the edges, the CLI, and on top the
console script's entry, which nothing imports. Within a layer of ``md`` the
modules are listed in order, and a module imports only those listed before
it. ``importlib.import_module("name")`` counts as an import of ``name``; one
of a name computed at run time only in the facade. No import cycles; imports
inside functions only for heavy optional dependencies, each with a one-line
reason. No module imports or reads another module's private names
(``from m import _x``, ``obj._x``, ``getattr(obj, "_x")``), and a private
module outside layer 0 is imported only within its own package (for ``md``,
which is one package over several layers: by the module it serves).

Each rule is a function from a module's source to the problems found, run on
every module of the tree and, by the ``test_checker_flags_*`` tests, on small
sources that break it, so a rule that stopped finding anything would fail.
"""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("md", "potentials", "integrators")
#: Top-level modules outside the packages (the console script's entry).
TOP_MODULES = ("md_command",)

#: Layer of each module (a name ending in ".*" covers a package). Within each layer of md
#: the order is the import order: a module imports only modules listed before it (those
#: under one ".*" entry import each other freely, acyclically).
LAYERS = {
    0: [
        "md._version",
        "md._kernel_cache",
        "md._memory",
        "md._simd",
        "md.box",
        "md.state",
        "md.units",
        "md.parallel",
        "md.errors",
        "md.thermo",
        "md._checks",
        "md.schema",
        "md.plugins",
        "md.interrupts",
        "md._files",
        "md.topology",
        "md.rigid",
    ],
    1: ["potentials.*", "integrators.*"],
    2: [
        "md.neighbors.*",
        "md.forcefield",
        "md.cuda.*",
        "md.simulation",
        "md.observers",
        "md.build",
        "md.polymers",
        "md.minimize",
        "md.distributed._domain_kernels",
        "md.distributed._mpi_kernels",
        "md.distributed._verlet_kernels",
        "md.distributed.grid",
        "md.distributed.ranks",
        "md.distributed.migration",
        "md.distributed.halo",
        "md.distributed.bonded",
        "md.distributed.balance",
        "md.distributed.forcefield",
        "md.distributed.views",
        "md.distributed.simulation",
        "md.distributed",
    ],
    3: [
        "md.trajectory.*",
        "md.checkpoint",
        "md.structure",
        "md.config",
        "md.rigid_setup",
        "md.assemble",
        "md.guards",
        "md.relax",
        "md.run",
    ],
    4: [
        "md.render",
        "md.analysis.*",
        "md.studies.*",
        "md.calculator",
        "md.validate",
        "md.convert",
        "md.notebook",
        "md.sweeps.*",
    ],
    5: ["md.cli.*"],
    6: ["md_command"],
}
#: What potentials/ and integrators/ may import besides layer 0 of md.
PLUGIN_IMPORTS = {
    "potentials": ("potentials",),
    "integrators": ("integrators", "potentials.base"),
}
#: The module each private module of md above layer 0 serves: the only one that imports it
#: (md is one package across layers, so "within its own package" says too little there).
PRIVATE_OWNERS: dict[str, str] = {}
#: Modules that import a module named at run time, with why (none of the project's).
RUNTIME_IMPORTS = {"md.plugins": "imports the plug-in module a config's type names"}
#: Project imports allowed inside functions, with why.
LATE_PROJECT_IMPORTS = {
    ("md", "md.sweeps"): "md.sweep() loads the Dask machinery on first use",
    ("md_command", "md.cli"): "inside the try that turns a Ctrl-C while md loads into a line",
    ("md.cuda", "md.cuda.engine"): "numba.cuda loads only for a run on the device",
}


def _modules() -> dict[str, Path]:
    found = {name: ROOT / f"{name}.py" for name in TOP_MODULES}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            found[".".join(parts)] = path
    return found


MODULES = _modules()


def _entry(module: str) -> tuple[int, int]:
    """(layer, position in the layer's list) of a module."""
    for layer, names in LAYERS.items():
        for position, name in enumerate(names):
            if module == name or (name.endswith(".*") and module.startswith(name[:-2])):
                return layer, position
    raise KeyError(module)


def layer_of(module: str) -> int:
    return _entry(module)[0]


def _is_private(module: str) -> bool:
    return module.split(".")[-1].startswith("_") and not module.endswith("__init__")


def _is_private_name(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


@dataclass(frozen=True)
class Import:
    """One import in a module: an ``import``/``from`` statement or an ``import_module`` call."""

    line: int
    target: str | None  # the module named; None for an import_module of a computed name
    late: bool  # inside a function
    names: tuple[str, ...] = ()  # ``from target import names`` (not submodules)


class _Imports(ast.NodeVisitor):
    """Collect the imports of one module's source."""

    def __init__(self, module: str, is_package: bool) -> None:
        self.module, self.is_package = module, is_package
        self.found: list[Import] = []
        self.depth = 0

    def visit_FunctionDef(self, node) -> None:
        self.depth += 1
        self.generic_visit(node)
        self.depth -= 1

    visit_AsyncFunctionDef = visit_FunctionDef
    visit_Lambda = visit_FunctionDef

    def visit_If(self, node) -> None:
        test = node.test
        if isinstance(test, ast.Name) and test.id == "TYPE_CHECKING":
            for child in node.orelse:  # annotations only: not imported at run time
                self.visit(child)
            return
        self.generic_visit(node)

    def visit_Import(self, node) -> None:
        for alias in node.names:
            self.found.append(Import(node.lineno, alias.name, self.depth > 0))

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
            self.found.append(Import(node.lineno, f"{target}.{name}", self.depth > 0))
        rest = tuple(n for n in names if n not in submodules)
        if rest:
            self.found.append(Import(node.lineno, target, self.depth > 0, rest))

    def visit_Call(self, node) -> None:
        """``importlib.import_module(...)``, ``import_module(...)``, ``__import__(...)``."""
        function = node.func
        called = (
            function.attr
            if isinstance(function, ast.Attribute)
            else function.id
            if isinstance(function, ast.Name)
            else None
        )
        if called in ("import_module", "__import__") and node.args:
            name = node.args[0]
            literal = isinstance(name, ast.Constant) and isinstance(name.value, str)
            absolute = literal and not name.value.startswith(".")
            target = name.value if absolute else None
            self.found.append(Import(node.lineno, target, self.depth > 0))
        self.generic_visit(node)


def imports_of(module: str, source: str, is_package: bool = False) -> list[Import]:
    visitor = _Imports(module, is_package)
    visitor.visit(ast.parse(source))
    return visitor.found


def _imports(module: str) -> list[Import]:
    path = MODULES[module]
    return imports_of(module, path.read_text(), path.name == "__init__.py")


def _project(target: str | None) -> str | None:
    """The project module an import names (or the nearest package), else None."""
    if target is None or target.split(".")[0] not in (*PACKAGES, *TOP_MODULES):
        return None
    while target and target not in MODULES:
        target = target.rpartition(".")[0]
    return target or None


def direction_problems(module: str, imports: list[Import]) -> list[str]:
    """Imports that go up a layer, or back in a layer's order, or cannot be told."""
    if module == "md":
        return []  # the facade reaches every layer (upper ones lazily)
    problems = []
    own_layer, own_position = _entry(module)
    root = module.split(".")[0]
    for found in imports:
        where = f"{module}:{found.line}"
        if found.target is None:
            if module in RUNTIME_IMPORTS:
                continue
            problems.append(f"{where} imports a module named at run time; name it in the source")
            continue
        imported = _project(found.target)
        if imported is None:
            continue
        if imported == "md":
            if not found.late:
                problems.append(f"{where} imports the md facade")
            continue
        if root in PLUGIN_IMPORTS:
            if not (imported.startswith(PLUGIN_IMPORTS[root]) or layer_of(imported) == 0):
                problems.append(f"{where}: {root}/ may import only layer 0 of md, not {imported}")
            continue
        if (module, imported) in LATE_PROJECT_IMPORTS:
            continue
        layer, position = _entry(imported)
        if layer > own_layer:
            problems.append(
                f"{module} (layer {own_layer}) imports {imported} (layer {layer}) at line "
                f"{found.line}: modules import only downward"
            )
        elif layer == own_layer and position > own_position and own_layer != 1:
            problems.append(
                f"{where} imports {imported}, listed after it in layer {layer}: within a "
                "layer a module imports only those listed before it (tests/test_layers.py)"
            )
    return problems


def _may_use_private_module(module: str, private: str) -> bool:
    """Whether ``module`` may import the private module ``private`` (outside layer 0)."""
    if private in PRIVATE_OWNERS:
        return module == PRIVATE_OWNERS[private]
    package = private.rpartition(".")[0]
    return package not in ("", "md") and (module == package or module.startswith(package + "."))


def private_import_problems(module: str, imports: list[Import]) -> list[str]:
    """Private modules above layer 0 used outside their package; private names imported
    from another module, except by a private module's own package (or owner)."""
    problems = []
    for found in imports:
        imported = _project(found.target)
        if imported is None or imported == module:
            continue
        where = f"{module}:{found.line}"
        serves = _is_private(imported) and layer_of(imported) != 0
        allowed = serves and _may_use_private_module(module, imported)
        if serves and not allowed:
            owner = PRIVATE_OWNERS.get(imported, f"the {imported.rpartition('.')[0]} package")
            problems.append(
                f"{where} imports the private module {imported}, which serves {owner} only; "
                "what others need is a public name of the module it serves"
            )
            continue
        private = [n for n in found.names if _is_private_name(n)]
        if private and not allowed:
            problems.append(f"{where} imports private {private} from {imported}")
    return problems


def _private_attribute(node: ast.AST) -> tuple[ast.AST, str] | None:
    """(object, name) for ``obj._name`` and ``getattr/hasattr/setattr/delattr(obj, "_name")``."""
    if isinstance(node, ast.Attribute):
        return node.value, node.attr
    if (
        isinstance(node, ast.Call)
        and isinstance(node.func, ast.Name)
        and node.func.id in ("getattr", "hasattr", "setattr", "delattr")
        and len(node.args) >= 2
        and isinstance(node.args[1], ast.Constant)
        and isinstance(node.args[1].value, str)
    ):
        return node.args[0], node.args[1].value
    return None


def private_attribute_problems(module: str, source: str) -> list[str]:
    """``obj._name`` (or its ``getattr`` spelling) only for private attributes that the same
    module sets itself, or on ``self``/``cls``."""
    tree = ast.parse(source)
    own = {  # private attributes this module assigns (self._x = ..., setattr(obj, "_x", ...))
        target.attr
        for node in ast.walk(tree)
        if isinstance(node, ast.Assign | ast.AnnAssign | ast.AugAssign)
        for target in (node.targets if isinstance(node, ast.Assign) else [node.target])
        if isinstance(target, ast.Attribute)
    }
    own |= {
        node.args[1].value
        for node in ast.walk(tree)
        if isinstance(node, ast.Call)
        and isinstance(node.func, ast.Name)
        and node.func.id == "setattr"
        and (found := _private_attribute(node)) is not None
    }
    own |= {n.name for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)}
    problems = []
    for node in ast.walk(tree):
        found = _private_attribute(node)
        if found is None:
            continue
        base, name = found
        if not _is_private_name(name) or name in own:
            continue
        if isinstance(base, ast.Name) and base.id in ("self", "cls", "sys", "os"):
            continue
        problems.append(f"{module}:{node.lineno}: .{name} on {ast.unparse(base)}")
    return problems


def late_import_problems(module: str, source: str, imports: list[Import]) -> list[str]:
    """Imports inside functions: no project module unless listed, and each with a reason."""
    lines = source.splitlines()
    problems = []
    for found in imports:
        if not found.late:
            continue
        imported = _project(found.target)
        where = f"{module}:{found.line}"
        if imported is not None and (module, imported) not in LATE_PROJECT_IMPORTS:
            problems.append(
                f"{where} imports {found.target} inside a function; project imports "
                "belong at the top of the module"
            )
        text = lines[found.line - 1]
        above = lines[found.line - 2].strip() if found.line > 1 else ""
        if "#" not in text and not above.startswith("#"):
            problems.append(
                f"{where}: an import inside a function needs a one-line reason "
                f"(a comment on its line or the line above): {text.strip()}"
            )
    return problems


def _source(module: str) -> str:
    return MODULES[module].read_text()


@pytest.mark.parametrize("module", sorted(MODULES))
def test_imports_go_only_downward_and_in_layer_order(module):
    assert not direction_problems(module, _imports(module))


def test_nothing_imports_the_cli():
    for module in MODULES:
        if module.startswith("md.cli") or module in TOP_MODULES:
            continue
        for found in _imports(module):
            assert not (_project(found.target) or "").startswith("md.cli"), f"{module}:{found.line}"


def test_the_console_entry_imports_only_the_standard_library_before_its_try():
    """``md_command`` must run before ``md`` loads (a Ctrl-C then is a line, not a traceback)."""
    for found in _imports("md_command"):
        if not found.late:
            assert found.target in sys.stdlib_module_names | {"__future__"}, found


def test_no_import_cycles():
    graph = {
        module: {
            _project(found.target)
            for found in _imports(module)
            if not found.late and _project(found.target) not in (None, module)
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
    problems = [p for m in MODULES for p in late_import_problems(m, _source(m), _imports(m))]
    assert not problems, "\n".join(problems)


def test_no_module_imports_another_modules_private_names_or_modules():
    problems = [p for m in MODULES for p in private_import_problems(m, _imports(m))]
    assert not problems, "\n".join(problems)


def test_no_module_reads_another_objects_private_attributes():
    problems = [p for m in MODULES for p in private_attribute_problems(m, _source(m))]
    assert not problems, "\n".join(problems)


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
    for private in PRIVATE_OWNERS:
        assert private in MODULES and PRIVATE_OWNERS[private] in MODULES


def test_late_exemptions_are_still_needed():
    """An exemption for a late import that no longer exists would hide a new one."""
    for module, imported in LATE_PROJECT_IMPORTS:
        assert any(f.late and _project(f.target) == imported for f in _imports(module)), (
            module,
            imported,
        )


def _doc_spellings(entry: str) -> list[str]:
    """How ARCHITECTURE.md may name an entry of LAYERS: ``md/box.py`` for a module, and a
    family ``md/analysis/*`` for a package (``md.analysis.*``) or any module inside one."""
    parts = entry.removesuffix(".*").split(".")
    if entry.endswith(".*"):
        return ["/".join(parts) + "/*"]
    spellings = ["/".join(parts) + ".py"]
    if entry in MODULES and MODULES[entry].name == "__init__.py":
        spellings.append("/".join(parts) + "/*")
    spellings += ["/".join(parts[:k]) + "/*" for k in range(len(parts) - 1, 1, -1)]
    return spellings


def unnamed_modules(text: str, layers: dict[int, list[str]]) -> list[str]:
    """The entries of ``layers`` that ``text`` names in none of their spellings."""
    return [
        entry
        for entries in layers.values()
        for entry in entries
        if not any(
            re.search(rf"(?<![\w/.]){re.escape(s)}(?![\w])", text) for s in _doc_spellings(entry)
        )
    ]


def test_architecture_names_every_module_of_the_layer_table():
    text = (ROOT / "ARCHITECTURE.md").read_text()
    assert not unnamed_modules(text, LAYERS), "ARCHITECTURE.md does not name these modules"


def test_the_architecture_check_flags_an_unnamed_module():
    text = (ROOT / "ARCHITECTURE.md").read_text()
    assert unnamed_modules(text.replace("md/box.py", "md/box"), LAYERS) == ["md.box"]
    assert unnamed_modules(text.replace("md/neighbors/*", "md/neighbors"), LAYERS) == [
        "md.neighbors.*"
    ]
    family = {4: ["md.analysis.*", "md.distributed.grid", "md.distributed"]}
    assert not unnamed_modules("md/analysis/* md/distributed/*", family)
    assert unnamed_modules("md/analysis.py md/cli/run.py", {4: ["md.analysis.*", "md.run"]}) == [
        "md.analysis.*",
        "md.run",
    ]


# The checker on sources that break each rule: every pattern must be flagged.


def _direction(module: str, source: str) -> list[str]:
    return direction_problems(module, imports_of(module, source))


@pytest.mark.parametrize(
    "module, source",
    [
        ("md.neighbors", "from md.simulation import Simulation\n"),  # same layer, later
        ("md.neighbors", "import md.forcefield\n"),
        ("md.box", "from md.state import State\n"),  # layer 0 keeps an order too
        ("md.forcefield", "from md.run import prepare\n"),  # an upper layer
        ("md.simulation", "from md import neighbors, trajectory\n"),  # one of two upward
        ("md.forcefield", "import importlib\nrun = importlib.import_module('md.run')\n"),
        ("md.forcefield", "from importlib import import_module\nimport_module('md.config')\n"),
        ("md.forcefield", "mod = __import__('md.checkpoint')\n"),
        ("md.forcefield", "import importlib\nm = importlib.import_module('md.' + name)\n"),
        ("md.state", "from md import simulation\n"),
        ("potentials.springs", "from md.neighbors import NeighborList\n"),  # plug-ins: layer 0
        ("md.trajectory", "import md\n"),  # the facade, at the top of a module
    ],
)
def test_checker_flags_imports_against_the_order(module, source):
    assert _direction(module, source), source


def test_checker_lets_correct_imports_through():
    """The negative tests above fail for the right reason: the same modules importing
    downward, earlier in their layer, or outside the project are fine."""
    assert not _direction("md.simulation", "from md.forcefield import ForceField\n")
    assert not _direction("md.simulation", "import importlib\nimportlib.import_module('numpy')\n")
    assert not _direction("md.state", "from md.box import min_image\n")
    assert not _direction("md.run", "from md.neighbors import NeighborList\n")
    assert not _direction("integrators.langevin", "from potentials.base import Potential\n")


@pytest.mark.parametrize(
    "module, source",
    [
        ("md.simulation", "from md.neighbors._build_kernels import _max_displacement2\n"),
        ("md.simulation", "from md.neighbors._cell_kernels import MAX_SLOTS\n"),  # private
        ("md.run", "import md.neighbors._cell_kernels\n"),
        ("md.forcefield", "from md.neighbors import _cell_kernels\n"),
        ("md.simulation", "from md.neighbors import _MAX_CELLS_PER_ATOM\n"),
        ("md.forcefield", "from md._checks import _private_helper\n"),  # layer 0: public only
        ("potentials.springs", "from integrators._kernels import kick\n"),  # another package
        ("md.minimize", "from integrators._newton import IncrementalSolver\n"),
        ("potentials.lennard_jones", "from potentials.springs import _spring_kernel\n"),
    ],
)
def test_checker_flags_private_names_and_modules(module, source):
    assert private_import_problems(module, imports_of(module, source)), source


def test_checker_lets_a_package_use_its_own_private_modules():
    for module, source in [
        ("md.neighbors.lists", "from md.neighbors._cell_kernels import _brute_force_pairs\n"),
        ("md.neighbors._build_kernels", "from md.neighbors._cell_kernels import MAX_SLOTS\n"),
        ("integrators.langevin", "from integrators._kernels import _drift\n"),
        ("potentials.springs", "from potentials._kernels import _add_half_pair_virial\n"),
        ("md.run", "from md._files import atomic_path\n"),
    ]:
        assert not private_import_problems(module, imports_of(module, source)), source


@pytest.mark.parametrize(
    "source",
    [
        "def f(neighbors):\n    return neighbors._cache\n",
        "def f(ff):\n    return getattr(ff, '_cache')\n",
        "def f(ff):\n    return getattr(ff, '_cache', None)\n",
        "def f(ff):\n    return hasattr(ff, '_cache')\n",
        "def f(ff):\n    delattr(ff, '_cache')\n",
    ],
)
def test_checker_flags_private_attributes_of_other_objects(source):
    assert private_attribute_problems("md.forcefield", source), source


def test_checker_lets_a_module_read_what_it_sets():
    for source in [
        "class A:\n    def f(self):\n        return self._x\n",
        "def f(a, b):\n    a._x = 1\n    return b._x\n",
        "def f(a, b):\n    setattr(a, '_x', 1)\n    return getattr(b, '_x', None)\n",
        "def f(a):\n    return getattr(a, '__name__'), a.__class__\n",
    ]:
        assert not private_attribute_problems("md.forcefield", source), source


@pytest.mark.parametrize(
    "source",
    [
        "def f():\n    from md.neighbors import NeighborList\n    return NeighborList\n",
        "def f():\n    import scipy\n    return scipy\n",  # no reason given
        "import importlib\ndef f():\n    return importlib.import_module('scipy')\n",
    ],
)
def test_checker_flags_unexplained_or_project_imports_in_functions(source):
    imports = imports_of("md.forcefield", source)
    assert late_import_problems("md.forcefield", source, imports), source


def test_checker_lets_an_explained_optional_import_through():
    source = "def f():\n    import scipy  # heavy: only for this analysis\n    return scipy\n"
    assert not late_import_problems("md.analysis", source, imports_of("md.analysis", source))
