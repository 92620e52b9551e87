"""The frames' plain term functions, for another compiler target (the GPU path).

A pair potential's energy and force come from its term with the frame's cutoff treatment
(``_pair_kernels.pair``: the term for a type-pair column of the parameter table, then the
cutoff mode). Those are plain Python functions decorated with ``numba.njit``; a CUDA
kernel (``md.cuda``) compiles the same functions as device functions, so the physics is
written once. :func:`retarget` rebuilds a function with every compiled function it calls
(a global that is a numba dispatcher) compiled by the caller's ``compile`` instead, all
the way down; :func:`pair_function` gives a pair potential's entry point with what it
reads (the table, the cutoff mode, the data array).

What is followed: functions reached as globals (``pair`` -> ``_terms`` -> the term's
``_pair_energy`` adapter -> the term). A helper reached as a module attribute
(``pair_math.exp``) is left to the target compiler as it is.
"""

from __future__ import annotations

import types
from collections.abc import Callable

import numpy as np

from potentials._pair_codegen import kernels_for
from potentials._pair_frame import CUTOFF_MODES, PairPotential

__all__ = ["pair_function", "retarget"]


def retarget(function: Callable, compile: Callable, _done: dict | None = None) -> Callable:
    """``compile`` applied to ``function``'s plain Python source, its callees retargeted too.

    ``function`` is a numba dispatcher or a plain function; every global it reads that is a
    dispatcher (has ``py_func``) is replaced, in a copy of its globals, by that callee
    retargeted. Returns ``compile(copy)``. Each callee is compiled once per call tree.
    """
    done = {} if _done is None else _done
    plain = getattr(function, "py_func", function)
    if plain in done:
        return done[plain]
    namespace = dict(plain.__globals__)
    for name in plain.__code__.co_names:
        value = namespace.get(name)
        if value is not None and hasattr(value, "py_func") and not isinstance(value, type):
            namespace[name] = retarget(value, compile, done)
    closure = plain.__closure__
    if closure:
        cells = []
        for cell in closure:
            value = cell.cell_contents
            if hasattr(value, "py_func") and not isinstance(value, type):
                value = retarget(value, compile, done)
            cells.append(types.CellType(value))
        closure = tuple(cells)
    copy = types.FunctionType(
        plain.__code__, namespace, plain.__name__, plain.__defaults__, closure
    )
    copy.__qualname__ = plain.__qualname__
    done[plain] = compiled = compile(copy)
    return compiled


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
