"""The pair frame's code generator: a module of kernels per pair term.

``potentials/_pair_kernels.py`` is a template: :func:`kernels_for` runs it once
per term (and precision) as a module of its own, with the term's functions
inlined into its loops through small generated adapters (:func:`_adapters`:
the term taking one tuple of parameters, that tuple read from a table column).
numba names a kernel's cache files after its source file and function and keys
them by signature and bytecode, which are the same for every term; so each
term's module is run from its own copy of the template.

The generated code, where it goes and how to see it
    Each copy is ``pair_terms/<term>_<hash>.py`` (``_mixed`` added for the
    mixed-precision copy, ``_lanes8``/``_lanes16`` for a fixed cluster width) in
    the kernel cache folder: ``NUMBA_CACHE_DIR`` where set, else
    ``md._kernel_cache.cache_directory()`` (a per-user folder). The hash is
    :func:`_fingerprint`: the bytes of the files in ``_FRAME_SOURCES`` (this
    module among them, as the adapters are written here) and the term's
    functions with all they reach. A copy is the template's text as this
    process imported it, followed by the variants (:func:`_variant_source`):
    one small ``@njit`` function per entry point and combination of its flags,
    ``<entry>__mode1_with_virial0`` and so on, each of which inlines its entry
    point with the flags as constants. Open the file to read what runs; the
    adapters are not in it (they are built in memory and set on the module
    before it runs), numba's compiled files sit beside it in its cache folder.

Why each variant inlines its entry point
    A variant that called its entry instead would run the entry's own
    compiled code in a process that compiled it, and a linked copy of it when
    loaded from the cache, which rounded differently: a mixed-precision run
    once differed with a cold and a warm cache (the note above the atom-order
    kernels in ``potentials/_pair_kernels.py``). Keep the inlining.

Clearing it
    Delete the ``pair_terms`` folder (or the whole kernel cache folder) at any
    time, between runs or while none is compiling: the next run writes the
    copies again and compiles afresh. An edited term or frame gets a new hash,
    so stale copies are never loaded, only left behind.
"""

from __future__ import annotations

import ast
import functools
import hashlib
import importlib.util
import inspect
import itertools
import logging
import sys
import textwrap
from collections.abc import Callable, Mapping
from pathlib import Path
from types import ModuleType

import numba
import numpy as np
from numba import njit

from md._kernel_cache import kernel_cache
from potentials._codegen import hash_value, identifier, template_copy
from potentials.base import check_precision_name
from potentials.pair_terms import PairTerm

#: Rows of the parameter table the frame owns; the term's parameters follow from TERM
#: (the same numbers as in ``_pair_kernels``).
RC2, RO2, SHIFT, INV_DEN, TERM = range(5)
_TEMPLATE = Path(__file__).with_name("_pair_kernels.py")
#: The files compiled into every term's kernels: the template, the modules whose kernels it
#: inlines, pair_math (functions terms call) and this module (the adapters it writes into
#: each copy: which function a precision's copy calls). Part of each term's fingerprint.
_FRAME_SOURCES = (
    _TEMPLATE,
    Path(__file__),
    Path(__file__).with_name("pair_math.py"),
    Path(__file__).with_name("_cluster_ir.py"),
    *(
        Path(importlib.util.find_spec(name).origin)
        for name in ("potentials._kernels", "md.box", "md._simd")
    ),
)
#: Those files as they were when this module was imported: the code this process runs
#: (the modules they define are loaded by then). Each term's fingerprint hashes them and
#: its copy of the template is written from them, never from the files as they are later:
#: a source edited while a process runs must not get the old code's kernels stored in the
#: shared cache under the new code's fingerprint (where every later process would load
#: them as the new code's).
_SOURCES = {path: path.read_bytes() for path in _FRAME_SOURCES}
#: The template's entry points (what the frame calls) and the arguments of theirs that
#: select a compiled variant: the cutoff mode, the virial flag, one atom type or several.
_ENTRIES = (
    "atom_forces",
    "atom_curvatures",
    "frame_forces",
    "frame_forces_threaded",
    "frame_verlet",
    "frame_curvatures",
    "frame_curvatures_threaded",
    "cluster_forces",
    "cluster_forces_threaded",
)
_FLAGS = {"mode": (0, 1, 2), "with_virial": (False, True), "single": (False, True)}
logger = logging.getLogger(__name__)

_LOADED: dict[tuple[str, str, int | None], ModuleType] = {}


def kernels_for(
    term: PairTerm, precision: str = "double", cluster_lanes: int | None = None
) -> ModuleType:
    """The frame's kernels with ``term`` inlined: ``_pair_kernels`` run as a module of its own.

    ``precision="mixed"`` gives a second copy whose term computes in float32
    (:func:`float32_version`), for the mixed-precision pair loop. ``cluster_lanes`` (8
    or 16) gives a copy whose cluster kernel has that vector width instead of the CPU's
    (``potentials._cluster_ir.cluster_row``), for benchmarks that compare the widths in
    one process; the engine uses the default, None.

    Loaded once per process and term. numba names a kernel's cache files after its
    source file and function, and keys them by signature and bytecode, which are the
    same for every term; so each term runs its own copy of the template, a file named
    after the term and a hash of everything its compiled kernels depend on
    (:func:`_fingerprint`), in ``pair_terms/`` of the per-user kernel cache folder.
    An unchanged term then loads its compiled kernels from numba's cache in every
    later process; an edited one gets a new copy and compiles afresh.
    """
    check_precision_name(precision)
    if cluster_lanes not in (None, 8, 16):
        raise ValueError(f"cluster_lanes must be 8, 16 or None, got {cluster_lanes!r}")
    key = _fingerprint(term)
    module = _LOADED.get((key, precision, cluster_lanes))
    if module is not None:
        return module
    stem = f"{identifier(term.name)}_{key[:20]}" + ("_mixed" if precision == "mixed" else "")
    extra = ""
    if cluster_lanes is not None:
        stem += f"_lanes{cluster_lanes}"
        extra = (
            "\n\n# The cluster kernel's width, fixed by kernels_for(cluster_lanes=...).\n"
            "_cluster_row = cluster_row(_pair, lambda: TERM + N_TERM, "
            f"lanes={cluster_lanes})\n"
        )
    name = f"potentials._pair_kernels_{stem}"
    spec = importlib.util.spec_from_file_location(name, _template_copy(stem, extra))
    module = importlib.util.module_from_spec(spec)
    module.__dict__.update(_adapters(term, precision))
    sys.modules[name] = module  # numba's parallel lowering looks kernels' modules up by name
    try:
        with kernel_cache():
            spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[name]
        raise
    _LOADED[key, precision, cluster_lanes] = module
    return module


def _template_copy(stem: str, extra: str = "") -> Path:
    """The template's copy for one term: ``pair_terms/STEM.py`` in the kernel cache folder
    (:func:`template_copy`)."""
    return template_copy(
        "pair_terms", stem, _SOURCES[_TEMPLATE] + _variant_source().encode() + extra.encode()
    )


@functools.cache
def _variant_source() -> str:
    """One small kernel per entry point and combination of its flags (``_FLAGS``),
    appended to each term's copy of the template: the entry point inlined (it is
    ``inline="always"``) with the flags as constants; a threaded entry's variant is
    ``parallel=True``, for its ``prange`` loops.

    numba then compiles each variant when it is first called, with one copy of the
    pair loop specialised to its flags (a few seconds), rather than all twelve at once;
    and a call from Python finds its compiled variant by the usual type match. (An entry
    point that asks for literal arguments, called from Python, retypes its arguments on
    every call: 13 times slower than the loop it runs on a small system.) Inlined, not
    called: a variant that called its entry would run the entry's own compiled code in
    a process that compiled it, and its linked copy when loaded from the cache, which
    rounded differently (see the template's note above its atom-order kernels).
    """
    tree = ast.parse(_SOURCES[_TEMPLATE].decode())
    arguments = {
        node.name: [arg.arg for arg in node.args.args]
        for node in tree.body
        if isinstance(node, ast.FunctionDef) and node.name in _ENTRIES
    }
    lines = ["", "", "# Variants, appended by potentials._pair_codegen._variant_source."]
    for entry in _ENTRIES:
        names = arguments[entry]
        flags = [name for name in names if name in _FLAGS]
        for values in itertools.product(*(_FLAGS[name] for name in flags)):
            fixed = dict(zip(flags, values, strict=True))
            passed = ", ".join(repr(fixed[name]) if name in fixed else name for name in names)
            parallel = ", parallel=True" if entry.endswith("_threaded") else ""
            lines += [
                "",
                "",
                f'@njit(cache=True{parallel}, error_model="numpy")',
                f"def {variant_name(entry, fixed)}({', '.join(names)}):",
                f"    return {entry}({passed})",
            ]
    return "\n".join(lines) + "\n"


def variant_name(entry: str, flags: Mapping[str, object]) -> str:
    return entry + "__" + "_".join(f"{name}{int(value)}" for name, value in flags.items())


def variant(kernels: ModuleType, entry: str, **flags):
    """The compiled variant of ``entry`` for these flags (given in the entry's order)."""
    return getattr(kernels, variant_name(entry, flags))


def _adapters(term: PairTerm, precision: str = "double") -> dict:
    """The names the template expects: the term's functions taking one tuple of parameters,
    and the tuple read from a table column. In mixed precision ``_pair_energy`` is the
    term's float32 version where that computes in float32 throughout
    (:func:`single_precision_term`), else the term itself, in double."""
    n = len(term.parameters)
    p = "".join(f"p[{i}], " for i in range(n))
    data = "data, " if term.uses_data else ""
    column = "".join(f"table[{TERM + i}, k], " for i in range(n))
    energy = (single_precision_term(term) if precision == "mixed" else None) or term.energy
    source = (
        f"def _pair_energy(r2, p, data):\n    return energy(r2, {data}{p})\n"
        f"def _pair_curvature(r2, p, data):\n    return curvature(r2, {data}{p})\n"
        f"def _column(table, k):\n    return ({column})\n"
    )
    options = {"inline": "always", "error_model": "numpy"}
    namespace = {
        "energy": njit(**options)(energy),
        "curvature": None if term.curvature is None else njit(**options)(term.curvature),
    }
    real = np.float32 if precision == "mixed" else np.float64
    exec(compile(source, f"<pair term {term.name}>", "exec"), namespace)  # noqa: S102
    adapters = {name: njit(**options)(namespace[name]) for name in ("_pair_energy", "_column")}
    adapters["_pair_curvature"] = njit(**options)(namespace["_pair_curvature"])
    adapters["N_TERM"] = n
    adapters["REAL"] = real
    return adapters


def single_precision_term(term: PairTerm) -> Callable | None:
    """The term's energy function for the mixed-precision loops, or None for its own.

    :func:`float32_version` of it if that, given float32 arguments, returns float32:
    its arithmetic then stays float32. A term that calls a helper computing in double
    (``pair_math.exp``: Morse, Buckingham, Yukawa) would convert to double and back
    around every call, which made Morse's force call 1.22 times double's; such a term
    runs as it is, in double, from r^2 and parameters rounded to float32 (1.0x).
    """
    single = float32_version(term.energy)
    if single is None:
        return None
    arguments = [np.float32(1.5)] + ([np.zeros(1)] if term.uses_data else [])
    arguments += [np.float32(1.0)] * len(term.parameters)
    try:
        compiled = njit(error_model="numpy")(single)
        compiled.compile(tuple(numba.typeof(a) for a in arguments))
    except Exception:  # noqa: BLE001 (numba's typing errors have no common base): use the term
        logger.debug("pair term %s: no float32 version", term.name, exc_info=True)
        return None
    returned = compiled.nopython_signatures[-1].return_type
    return single if str(returned) == "UniTuple(float32 x 2)" else None


#: Names whose value is a float constant, in ``math`` and numpy: float64 to numba.
_FLOAT_NAMES = {"inf", "pi", "e", "nan", "tau"}


def float32_version(function: Callable) -> Callable | None:
    """``function`` with its own float constants made float32, for mixed precision.

    numba types a literal such as ``12.0`` (and ``math.inf``, ``np.pi``) as float64,
    and float32 times float64 is float64: a pair term written for double would turn
    the mixed-precision loop back into double. So its source is parsed and every
    float literal, every ``inf``/``pi``/``e``/``nan`` read from a module and every
    global bound to a float wrapped in ``np.float32(...)``; integers (``r2 ** 3``)
    keep float32 as they are. Only the
    function's own body: helpers it calls (``pair_math.exp``) run in their own
    precision, as numba promotes their float32 arguments. Returns None where the
    source cannot be read or is not one ``def`` (a lambda, a function made by
    ``exec``); the double function then serves, correct and slower.
    """
    function = getattr(function, "py_func", function)
    try:
        source = textwrap.dedent(inspect.getsource(function))
        tree = ast.parse(source)
    except (OSError, TypeError, SyntaxError):
        return None
    if len(tree.body) != 1 or not isinstance(tree.body[0], ast.FunctionDef):
        return None
    definition = tree.body[0]
    definition.decorator_list = []
    floats = {
        name
        for name, value in function.__globals__.items()
        if isinstance(value, float | np.floating)
    }
    tree = ast.fix_missing_locations(_Float32Constants(floats).visit(tree))
    code = compile(tree, f"<float32 {function.__qualname__}>", "exec")
    namespace = dict(function.__globals__)
    if function.__closure__:
        namespace.update(
            zip(
                function.__code__.co_freevars,
                (cell.cell_contents for cell in function.__closure__),
                strict=True,
            )
        )
    namespace["_float32_"] = np.float32
    exec(code, namespace)  # noqa: S102
    made = namespace[definition.name]
    made.__defaults__ = function.__defaults__
    return made


class _Float32Constants(ast.NodeTransformer):
    """Wraps float literals, module float constants and the names in ``floats`` (globals
    bound to a float) in ``_float32_(...)``."""

    def __init__(self, floats: set[str]) -> None:
        self.floats = floats

    def visit_Name(self, node: ast.Name) -> ast.AST:
        if isinstance(node.ctx, ast.Load) and node.id in self.floats:
            return ast.Call(ast.Name("_float32_", ast.Load()), [node], [])
        return node

    def visit_Constant(self, node: ast.Constant) -> ast.AST:
        if isinstance(node.value, float):
            return ast.Call(ast.Name("_float32_", ast.Load()), [node], [])
        return node

    def visit_Attribute(self, node: ast.Attribute) -> ast.AST:
        if node.attr in _FLOAT_NAMES and isinstance(node.value, ast.Name):
            return ast.Call(ast.Name("_float32_", ast.Load()), [node], [])
        return self.generic_visit(node)


def _fingerprint(term: PairTerm) -> str:
    """A hash of everything the term's compiled kernels depend on: the frame's own sources
    (``_FRAME_SOURCES``, as imported: ``_SOURCES``) and the term's functions with all
    they reach through their globals, defaults and closures (helpers they call, wherever
    defined, and constants, which numba compiles in). A helper reached as an attribute
    (``module.helper``) is not followed."""
    digest = hashlib.sha256()
    for path in _FRAME_SOURCES:
        digest.update(_SOURCES[path])
    digest.update(_variant_source().encode())
    digest.update(repr((term.name, term.uses_data, term.parameters)).encode())
    seen: set = set()
    for function in (term.energy, term.curvature):
        hash_value(digest, function, seen)
    return digest.hexdigest()
