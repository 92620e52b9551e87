"""The frames' plain term functions, for another compiler target (the GPU path).

A pair potential's energy and force come from its term with the frame's cutoff treatment
(``_pair_kernels.pair``: the term for a type-pair column of the parameter table, then the
cutoff mode). Those are plain Python functions decorated with ``numba.njit``; a CUDA
kernel (``md.cuda``) compiles the same functions as device functions, so the physics is
written once. :func:`retarget` rebuilds a function with every compiled function it calls
(a global that is a numba dispatcher) compiled by the caller's ``compile`` instead, all
the way down; :func:`pair_function` gives a pair potential's entry point with what it
reads (the table, the cutoff mode, the data array).

What is followed: functions reached as globals or closures (``pair`` -> ``_terms`` -> the
term's ``_pair_energy`` adapter -> the term -> ``pair_math.exp``), numba's and plain
Python ones alike (a plain one, such as ``pair_math``'s CPU overloads, by its Python body).
A helper reached as a module attribute (``module.helper``) is left to the target compiler.
"""

from __future__ import annotations

import dis
import functools
import types
from collections.abc import Callable, Mapping

import numpy as np

from potentials._bonded_frame import AnglePotential, BondPotential, _adapters
from potentials._pair_codegen import kernels_for
from potentials._pair_frame import CUTOFF_MODES, PairPotential

__all__ = ["bonded_function", "compilable", "kind_of", "pair_function", "retarget"]


def kind_of(potential) -> str | None:
    """``"pair"`` for a pair potential of the frame (:func:`pair_function` serves it),
    ``"bond"`` or ``"angle"`` for one of the bonded frame (:func:`bonded_function`), else
    None."""
    for kind, frame in (("pair", PairPotential), ("bond", BondPotential)):
        if isinstance(potential, frame):
            return kind
    return "angle" if isinstance(potential, AnglePotential) else None


def compilable(potential) -> bool:
    """Whether this module gives ``potential``'s functions for another target."""
    return kind_of(potential) is not None


def retarget(
    function: Callable,
    compile: Callable,
    substitutes: Mapping[str, object] | None = None,
    _done: dict | None = None,
) -> Callable:
    """``compile`` applied to ``function``'s plain Python source, its callees retargeted too.

    ``function`` is a numba dispatcher or a plain function; every global it reads that is a
    dispatcher (has ``py_func``) is replaced, in a copy of its globals, by that callee
    retargeted. ``substitutes`` maps numpy function names to what the target offers instead
    (the CUDA target has no ``np.rint``: libdevice's ``rint``, the same rounding): a global
    bound to numpy is then read through a copy of the module with those names replaced.
    Returns ``compile(copy)``. Each callee is compiled once per call tree.
    """
    done = {} if _done is None else _done
    plain = getattr(function, "py_func", function)  # a numba dispatcher: its Python function
    if plain in done:
        return done[plain]
    namespace = dict(plain.__globals__)
    for name in _global_names(plain.__code__):
        value = namespace.get(name)
        if value is np and substitutes:
            namespace[name] = _numpy_with(tuple(sorted(substitutes.items())))
        elif _callee(value):
            namespace[name] = retarget(value, compile, substitutes, done)
    closure = plain.__closure__
    if closure:
        cells = []
        for cell in closure:
            value = cell.cell_contents
            if _callee(value):
                value = retarget(value, compile, substitutes, done)
            cells.append(types.CellType(value))
        closure = tuple(cells)
    copy = types.FunctionType(
        plain.__code__, namespace, plain.__name__, plain.__defaults__, closure
    )
    copy.__qualname__ = plain.__qualname__
    done[plain] = compiled = compile(copy)
    return compiled


def _global_names(code) -> set[str]:
    """The names ``code`` reads as globals (``co_names`` also holds attribute names), in
    nested code objects (comprehensions) too."""
    names = {i.argval for i in dis.get_instructions(code) if i.opname == "LOAD_GLOBAL"}
    for constant in code.co_consts:
        if isinstance(constant, types.CodeType):
            names |= _global_names(constant)
    return names


def _callee(value) -> bool:
    """Whether ``retarget`` follows ``value``: a numba dispatcher, or a plain function of
    ours (``pair_math.exp``, whose compiled form is a CPU overload: on another target its
    Python body, ``math.exp``, is compiled instead)."""
    if hasattr(value, "py_func") and not isinstance(value, type):  # a dispatcher, any kind
        return True
    return isinstance(value, types.FunctionType) and not value.__module__.startswith(
        ("numba", "numpy", "math")
    )


@functools.cache
def _numpy_with(substitutes: tuple) -> types.ModuleType:
    """A copy of the numpy module with ``substitutes`` ((name, value) pairs) set in it."""
    module = types.ModuleType("numpy")
    module.__dict__.update(np.__dict__)
    module.__dict__.update(dict(substitutes))
    return module


def pair_function(potential: PairPotential, n_types: int, precision: str = "double"):
    """``(pair, table, mode, data, real)`` of a pair potential for another target.

    ``pair(r2, k, table, mode, data) -> (u, f_over_r)`` is the frame's own function
    (the term for column ``k``, the cutoff treatment of ``mode``), as a numba dispatcher
    to give :func:`retarget`; ``table`` the potential's parameter table for ``n_types``
    types (float32 in mixed precision, as the CPU's mixed loops read it), ``mode`` the
    cutoff mode's number, ``data`` the data array (tables), ``real`` the type r^2 is
    rounded to before the call (float32 in mixed precision).
    """
    if not isinstance(potential, PairPotential):
        raise TypeError(f"expected a PairPotential, got {type(potential).__name__}")
    kernels = kernels_for(potential.term, precision)
    real = np.float32 if precision == "mixed" else np.float64
    table = np.ascontiguousarray(potential.tables(n_types).astype(real))
    data = np.ascontiguousarray(potential.data, dtype=np.float64)
    return kernels.pair, table, CUTOFF_MODES[potential.cutoff_mode], data, real


def bonded_function(potential: BondPotential | AnglePotential):
    """``(kind, term, params, items, item_types, table)`` of a bond or angle potential.

    ``kind`` is ``"bond"`` or ``"angle"``; ``term`` the frame's adapter of its term
    (``bond(r2, p) -> (u, u'(r) / r)`` or ``angle(c, p) -> (u, du/dc)``, the functions
    its CPU loops inline) and ``params(table, t) -> p`` the parameters of type t, both
    numba dispatchers to give :func:`retarget`; ``items`` the (B, 2) bonds or (A, 3)
    angles (vertex in the middle), ``item_types`` their types, ``table`` the (P, T)
    parameter table.
    """
    if not isinstance(potential, BondPotential | AnglePotential):
        raise TypeError(f"expected a BondPotential or AnglePotential, got {potential!r}")
    kind = "bond" if isinstance(potential, BondPotential) else "angle"
    adapters = _adapters(potential.term)
    items = potential.bonds if kind == "bond" else potential.angles
    types_ = potential.bond_types if kind == "bond" else potential.angle_types
    table = np.ascontiguousarray(potential.parameter_table, dtype=np.float64)
    if table.shape[0] == 0:  # a term without parameters: one row the adapter ignores
        table = np.zeros((1, max(table.shape[1], 1)))
    return (
        kind,
        adapters[f"_{kind}"],
        adapters["_params"],
        np.ascontiguousarray(items, dtype=np.int64),
        np.ascontiguousarray(types_, dtype=np.int64),
        table,
    )
