"""The bonded frame: everything a bond or angle potential needs except its bonded term.

A bonded term is the energy u and its derivative as a plain numba-compatible
function of one variable and the term's parameters: a :class:`BondTerm` of the
bond length r (or of r^2), an :class:`AngleTerm` of the angle theta (or of
cos theta), as OpenMM's ``CustomBondForce`` and ``CustomAngleForce`` separate the
expression from the kernel. :class:`BondPotential` and :class:`AnglePotential`
do the rest: the list of bonds or angles and their types, per-type parameter
tables, the loops (minimum image, triclinic cells, open axes), energy, forces,
virial, per-atom energies and virials, and Hessians where the term gives its
second derivative. ``potentials.springs`` and ``potentials.angles`` are its styles.

The loops live in ``potentials/_bonded_kernels.py``, a template executed once
per term as a module of its own (:func:`kernels_for`) with the term inlined; numba
caches each term's loops apart, keyed by a hash of the term's code (as the pair
frame does, ``potentials._pair_codegen``).
"""

from __future__ import annotations

import functools
import hashlib
import importlib.util
import inspect
import math
import re
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType

import numba
import numpy as np
import scipy.sparse
from numba import njit
from numpy.typing import ArrayLike, NDArray

from md._checks import angle_array, bond_array, read_bonds_file, read_index_file
from md._kernel_cache import kernel_cache
from md.box import minimum_image, periodic_lengths, periodic_tilt
from md.errors import AngleCollapseError, NonFiniteError
from md.schema import REQUIRED, Key
from potentials._bonded import ListedTuples, bonded_keys, config_values, symmetric
from potentials._codegen import hash_value, identifier, template_copy
from potentials.base import ForceResult
from potentials.pair_hessian import PairHessian
from potentials.pair_terms import is_number, shown

#: Floor on sin(theta) where an angle term of theta divides by it (du/dc = -u'(theta) /
#: sin theta): LAMMPS's SMALL in angle_harmonic.cpp.
SMALL = 0.001

_TEMPLATE = Path(__file__).with_name("_bonded_kernels.py")
#: The files compiled into every term's loops (part of each term's fingerprint), read
#: when this module is imported: the code this process runs (see ``_pair_codegen._SOURCES``).
_SOURCES = {
    path: path.read_bytes()
    for path in (
        _TEMPLATE,
        Path(__file__),
        *(
            Path(importlib.util.find_spec(name).origin)
            for name in ("potentials._kernels", "md.box", "md._simd")
        ),
    )
}

#: Per kind and variable: the argument's name, what energy returns, what curvature returns.
_FORMS = {
    ("bond", "r"): ("r", ("u", "du_dr"), ("u", "du_dr", "d2u_dr2")),
    ("bond", "r2"): ("r2", ("u", "du_dr_over_r"), ("u", "du_dr_over_r", "d2u_dr2")),
    ("angle", "theta"): ("theta", ("u", "du_dtheta"), ("u", "du_dtheta", "d2u_dtheta2")),
    ("angle", "cos"): ("c", ("u", "du_dc"), ("u", "du_dc", "d2u_dc2")),
}
#: Where :meth:`BondedTerm.check` evaluates a term in Python: r = 1, theta = 2 radians.
_PROBE = {"r": 1.0, "r2": 1.0, "theta": 2.0, "cos": math.cos(2.0)}


@dataclass(eq=False)
class BondedTerm:
    """A bonded term: plain functions of one variable and the parameters, for the frame.

    Parameters
    ----------
    energy : callable
        ``energy(x, *params) -> (u, du_dx)``, x the term's ``variable``.
        numba-compatible Python (arithmetic, ``math``/``numpy`` functions, helpers
        decorated with ``numba.njit`` or ``register_jitable``).
    curvature : callable, optional
        ``curvature(x, *params) -> (u, du_dx, d2u_dx2)``, for Hessians (implicit
        integrators' Newton steps); without it they are refused.
    name : str, optional
        A name for messages and the kernel cache (default: the function's).
    variable : str
        What x is (see :class:`BondTerm`, :class:`AngleTerm`).

    Attributes
    ----------
    parameters : tuple of str
        The parameter names, from ``energy``'s signature.
    """

    energy: Callable
    curvature: Callable | None = None
    name: str = ""
    variable: str = ""
    parameters: tuple[str, ...] = field(init=False)
    #: "bond" or "angle".
    KIND = ""

    def __post_init__(self) -> None:
        self.variable = self.variable or next(v for k, v in _FORMS if k == self.KIND)
        if (self.KIND, self.variable) not in _FORMS:
            known = ", ".join(repr(v) for k, v in _FORMS if k == self.KIND)
            raise ValueError(
                f"{self.KIND} term variable must be one of {known}, got {self.variable!r}"
            )
        names = list(inspect.signature(self.energy).parameters)
        self.name = self.name or self.energy.__name__
        if not names:
            raise TypeError(
                f"{self.KIND} term {self.name} must take {self._form[0]} as its first argument"
            )
        self.parameters = tuple(names[1:])
        if self.curvature is not None:
            theirs = tuple(list(inspect.signature(self.curvature).parameters)[1:])
            if theirs != self.parameters:
                raise TypeError(
                    f"{self.KIND} term {self.name}: curvature takes {theirs}, "
                    f"energy {self.parameters}"
                )

    @property
    def _form(self) -> tuple:
        return _FORMS[self.KIND, self.variable]

    def with_curvature(self, curvature: Callable) -> Callable:
        """Attach ``curvature`` (a decorator: ``@term.with_curvature``); returns it."""
        self.curvature = curvature
        self.__post_init__()
        return curvature

    def energy_at(self, x: float, params) -> tuple[float, float]:
        """(u, du/dx) evaluated in Python; TypeError naming the term unless two numbers."""
        return self._evaluate(self.energy, x, params, self._form[1])

    def curvature_at(self, x: float, params) -> tuple[float, float, float]:
        """(u, du/dx, d2u/dx2) evaluated in Python; TypeError unless three numbers."""
        return self._evaluate(self.curvature, x, params, self._form[2])

    def check(self, tables: list[np.ndarray]) -> None:
        """Evaluate the term (and its curvature) in Python for each type's parameters
        (``tables``: one array per parameter) at r = 1 or theta = 2 radians: a TypeError
        naming the term if it does not return what it must."""
        for values in zip(*tables, strict=True) if tables else [()]:
            self.energy_at(_PROBE[self.variable], values)
            if self.curvature is not None:
                self.curvature_at(_PROBE[self.variable], values)

    def signature(self) -> str:
        return ", ".join((self._form[0], *self.parameters))

    def _evaluate(self, function: Callable, x: float, params, names) -> tuple:
        function = getattr(function, "py_func", function)
        try:
            with np.errstate(all="ignore"):
                returned = function(np.float64(x), *(np.float64(p) for p in params))
        except (OverflowError, ZeroDivisionError, ValueError):  # inf, NaN when compiled
            return (math.nan,) * len(names)
        if not (
            isinstance(returned, tuple)
            and len(returned) == len(names)
            and all(map(is_number, returned))
        ):
            got = (
                f"{len(returned)} values ({', '.join(map(shown, returned))})"
                if isinstance(returned, tuple)
                else shown(returned)
            )
            count = {2: "two", 3: "three"}[len(names)]
            raise TypeError(
                f"{self.KIND} term {self.name}: {function.__name__}({self.signature()}) must "
                f"return a tuple of {count} numbers ({', '.join(names)}), got {got}"
            )
        return tuple(float(value) for value in returned)


class BondTerm(BondedTerm):
    """A bond term: u and its derivative as plain functions of the bond length.

    ``variable="r"`` (the default): ``energy(r, *params) -> (u, du_dr)`` and
    ``curvature(r, *params) -> (u, du_dr, d2u_dr2)``; the frame divides du/dr by r
    (a bond of zero length gets no force). ``variable="r2"``: they take r^2 and
    return du/dr / r in place of du/dr, which spares a square root and a division
    where the formula allows (FENE). A term whose energy is not finite at a bond
    (beyond its range) makes the potential raise :class:`md.errors.NonFiniteError`
    naming the bond.

    Examples
    --------
    >>> import math
    >>> @bond_term
    ... def morse(r, d0, alpha, r0):
    ...     e = math.exp(-alpha * (r - r0))
    ...     return d0 * (1.0 - e) ** 2, 2.0 * alpha * d0 * (1.0 - e) * e
    >>> morse.parameters
    ('d0', 'alpha', 'r0')
    >>> bonds = BondPotential(morse, [[0, 1]], d0=1.0, alpha=2.0, r0=1.0)
    """

    KIND = "bond"


class AngleTerm(BondedTerm):
    """An angle term: u and its derivative as plain functions of the angle.

    ``variable="theta"`` (the default): ``energy(theta, *params) -> (u, du_dtheta)``
    and ``curvature(theta, *params) -> (u, du_dtheta, d2u_dtheta2)``, theta in
    radians (0 to pi); the frame divides by sin theta floored at ``SMALL``, as
    LAMMPS does, so forces stay finite at straight and folded triples.
    ``variable="cos"``: they take c = cos theta and return derivatives in c, which
    needs no floor (a cosine series is exact everywhere).
    """

    KIND = "angle"


def bond_term(energy: Callable | None = None, *, name: str = "", variable: str = "r"):
    """Decorator: turn ``energy(r, *params) -> (u, du_dr)`` into a :class:`BondTerm`."""

    def wrap(function: Callable) -> BondTerm:
        return BondTerm(function, name=name, variable=variable)

    return wrap if energy is None else wrap(energy)


def angle_term(energy: Callable | None = None, *, name: str = "", variable: str = "theta"):
    """Decorator: turn ``energy(theta, *params) -> (u, du_dtheta)`` into an :class:`AngleTerm`.

    Examples
    --------
    >>> import math
    >>> @angle_term(variable="cos")
    ... def cosine_squared(c, k, c0):
    ...     return k * (c - c0) ** 2, 2.0 * k * (c - c0)
    >>> bend = AnglePotential(cosine_squared, [[0, 1, 2]], k=1.0, c0=-0.5)
    """

    def wrap(function: Callable) -> AngleTerm:
        return AngleTerm(function, name=name, variable=variable)

    return wrap if energy is None else wrap(energy)


# ------------------------------------------------------------------ kernels per term
#: How each variable's functions become the template's: the frame's r^2 or cos theta in,
#: u'(r) / r or du/dc out (``P`` stands for the parameters).
_ADAPTERS = {
    "r": """
def _bond(r2, p):
    r = np.sqrt(r2)
    u, du = energy(r, P)
    return u, (du / r if r > 0.0 else 0.0)
def _bond_curvature(r2, p):
    r = np.sqrt(r2)
    u, du, d2u = curvature(r, P)
    return u, (du / r if r > 0.0 else d2u), d2u
""",
    "r2": """
def _bond(r2, p):
    return energy(r2, P)
def _bond_curvature(r2, p):
    return curvature(r2, P)
""",
    "theta": """
def _angle(c, p):
    s = max(np.sqrt(1.0 - c * c), SMALL)
    u, du = energy(np.arccos(c), P)
    return u, -du / s
def _angle_curvature(c, p):
    exact = np.sqrt(1.0 - c * c)
    s = max(exact, SMALL)
    u, du, d2u = curvature(np.arccos(c), P)
    d1 = -du / s
    if exact >= SMALL:
        d2 = (d2u + c * d1) / (s * s)
    elif exact > 0.0:
        d2 = d2u / (exact * SMALL)  # only theta varies: d theta / dc = -1 / sin theta
    else:
        d2 = 0.0  # the gradient of c vanishes here, so d2u/dc2 does not enter
    return u, d1, d2
""",
    "cos": """
def _angle(c, p):
    return energy(c, P)
def _angle_curvature(c, p):
    return curvature(c, P)
""",
}
_LOADED: dict[str, ModuleType] = {}


def kernels_for(term: BondedTerm) -> ModuleType:
    """The frame's loops with ``term`` inlined: ``_bonded_kernels`` run as a module of its own.

    Loaded once per process and term, from a copy of the template named after the term
    and a hash of everything its compiled loops depend on, in ``bonded_terms/`` of the
    per-user kernel cache folder: an unchanged term loads its loops from numba's cache
    in every later process, an edited one compiles afresh.
    """
    key = _fingerprint(term)
    module = _LOADED.get(key)
    if module is not None:
        return module
    stem = f"{identifier(term.name)}_{key[:20]}"
    name = f"potentials._bonded_kernels_{stem}"
    path = template_copy("bonded_terms", stem, _SOURCES[_TEMPLATE])
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    module.__dict__.update(_adapters(term))
    sys.modules[name] = module
    try:
        with kernel_cache():
            spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[name]
        raise
    _LOADED[key] = module
    return module


def _adapters(term: BondedTerm) -> dict:
    """The names the template expects, for ``term`` (see its docstring)."""
    p = ", ".join(f"p[{i}]" for i in range(len(term.parameters)))
    column = "".join(f"table[{i}, t], " for i in range(len(term.parameters)))
    source = f"def _params(table, t):\n    return ({column})\n" + _ADAPTERS[term.variable].replace(
        "P)", f"{p})" if p else ")"
    )
    options = {"inline": "always", "error_model": "numpy"}
    namespace = {"np": np, "SMALL": SMALL}
    for role in ("energy", "curvature"):
        function = getattr(term, role)
        function = getattr(function, "py_func", function)
        namespace[role] = None if function is None else njit(**options)(function)
    exec(compile(source, f"<{term.KIND} term {term.name}>", "exec"), namespace)  # noqa: S102
    names = ["_params", f"_{term.KIND}"]
    adapters = {name: njit(**options)(namespace[name]) for name in names}
    curvature = f"_{term.KIND}_curvature"
    adapters[curvature] = None if term.curvature is None else njit(**options)(namespace[curvature])
    return adapters


def _fingerprint(term: BondedTerm) -> str:
    """A hash of the frame's sources and the term's functions with all they reach
    (``_codegen.hash_value``)."""
    digest = hashlib.sha256()
    for text in _SOURCES.values():
        digest.update(text)
    digest.update(repr((term.KIND, term.variable, term.name, term.parameters)).encode())
    seen: set = set()
    for function in (term.energy, term.curvature):
        hash_value(digest, function, seen)
    return digest.hexdigest()


def _compiling_the_term(method: Callable) -> Callable:
    """Wrap a method that runs the term's loops: numba's error from compiling the term
    becomes a TypeError naming the term and what a term must be."""

    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        try:
            return method(self, *args, **kwargs)
        except numba.core.errors.NumbaError as error:
            term = self.term
            plain = re.sub(r"\x1b\[[0-9;]*m", "", str(error))
            lines = [line.strip() for line in plain.splitlines() if line.strip()]
            said = [line for line in lines if not line.startswith(("Failed in", "During:", "- "))]
            returns = ", ".join(term._form[1])
            raise TypeError(
                f"{term.KIND} term {term.name}: numba cannot compile it into the bonded loops "
                f"({said[0] if said else type(error).__name__}); "
                f"{term.energy.__name__}({term.signature()}) must be numba-compatible Python "
                f"that returns a tuple of two floats ({returns})"
            ) from None

    return wrapper


# ------------------------------------------------------------------ the potentials
class _TermPotential(ListedTuples):
    """What bond and angle potentials share: a term, its per-type tables, its loops, and
    a config table's reading (``CONFIG_KEYS``, :meth:`from_config`)."""

    term: BondedTerm
    #: Whether the parameters must be >= 0 (the built-in styles') or only finite.
    NONNEGATIVE = False
    #: The keys of a style's config table (:func:`bond_config_keys`, :func:`angle_config_keys`).
    CONFIG_KEYS: tuple[Key, ...] = ()
    #: One member as a config writes it, for messages (``"[i, j]"``).
    EXAMPLE = ""
    #: The word for one member (``BondPotential``: "bond"); empty on this shared base.
    ITEM = ""
    #: Whether ``CONFIG_KEYS`` was made from the constructor (:meth:`__init_subclass__`).
    _derived_keys = False

    def __init_subclass__(cls, **kwargs) -> None:
        """A style that declares no ``CONFIG_KEYS`` (a plug-in's, say) and whose constructor
        takes no ``term`` gets them from its constructor: the members (``bonds`` or
        ``bonds_file``; ``angles`` or ``angles_file``), their types, and each other argument
        as a parameter, a number or one per type, with the constructor's default."""
        super().__init_subclass__(**kwargs)
        if "CONFIG_KEYS" in cls.__dict__ or (cls.CONFIG_KEYS and not cls._derived_keys):
            return
        try:
            signature = inspect.signature(cls.__init__).parameters
        except (TypeError, ValueError):
            return
        item = cls.ITEM
        own = ("self", f"{item}s", f"{item}_types")
        if "term" in signature or not item:
            return  # the frame's own classes, built from a term
        parameters = tuple(
            Key(
                name,
                "number or list",
                REQUIRED if p.default is p.empty else p.default,
                doc=f"A parameter of {cls.__name__}: one for all {item}s, or one per {item} type.",
            )
            for name, p in signature.items()
            if name not in own and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)
        )
        cls.CONFIG_KEYS = bonded_keys(item, cls.EXAMPLE, *parameters)
        cls._derived_keys = True

    @classmethod
    def from_config(cls, params: Mapping, type_names=()):
        """Build from a config table: the members (``<item>s``, a list of atom index lists,
        or ``<item>s_file``, a text file of them), optional ``<item>_types`` and the
        parameters, each a number or a list per type. ``type_names`` is unused: bonds and
        angles name atoms, not types."""
        return cls(**config_values(params, cls.CONFIG_KEYS, cls.ITEM, cls._read_file, cls.EXAMPLE))

    @staticmethod
    def _read_file(path) -> np.ndarray:
        raise NotImplementedError

    def _setup_term(
        self, term: BondedTerm, items: np.ndarray, item_types, values: Mapping[str, ArrayLike]
    ) -> None:
        if not isinstance(term, BondedTerm) or term.KIND != self.ITEM:
            raise TypeError(f"expected a {self.ITEM} term ({self.ITEM}_term), got {term!r}")
        given, wanted = set(values), set(term.parameters)
        if given != wanted:
            missing = ", ".join(sorted(wanted - given)) or "none"
            unknown = ", ".join(sorted(given - wanted)) or "none"
            raise TypeError(
                f"{self.ITEM} term {term.name} takes the parameters "
                f"({', '.join(term.parameters)}); missing: {missing}; "
                f"unknown: {unknown}"
            )
        ordered = {name: values[name] for name in term.parameters}
        self._setup_list(items, item_types, ordered, nonnegative=self.NONNEGATIVE)
        self.term = term
        n_types = len(self._tables[0]) if self._tables else int(self._types.max(initial=0)) + 1
        self._table = np.array(self._tables) if self._tables else np.zeros((0, n_types))
        term.check(self._tables)
        self._kernels = None

    def _user_setup(
        self,
        term: BondedTerm,
        to_array: Callable,
        items,
        item_types,
        values: Mapping[str, ArrayLike],
    ) -> None:
        """:meth:`_setup_term` for a user's term: messages name the term, and the style
        (the type name in topology) is the term's name unless a subclass names one."""
        try:
            self._setup_term(term, to_array(items), item_types, values)
        except ValueError as error:
            raise ValueError(f"{self.ITEM} term {getattr(term, 'name', term)}: {error}") from None
        style = f"{self.ITEM}_style"
        if getattr(type(self), style) == f"{self.ITEM}_term":
            setattr(self, style, term.name)

    @property
    def parameter_table(self) -> np.ndarray:
        """The loops' (P, T) parameter table: the term's parameters of type t in column t."""
        return self._table

    def _loops(self) -> ModuleType:
        if self._kernels is None:
            self._kernels = kernels_for(self.term)
        return self._kernels

    def _geometry(self, state) -> tuple:
        self._check_indices(state.n_atoms)
        lengths, inverse = periodic_lengths(state.box, state.pbc)
        return (
            state.positions,
            lengths,
            inverse,
            periodic_tilt(state.tilt, state.pbc),
            self._items,
            self._types,
            self._table,
        )

    @_compiling_the_term
    def energy_forces(
        self, state, neighbors=None, per_atom: bool = False, virial: bool = True
    ) -> ForceResult:
        """Return energy, forces, virial (and per-atom energies and virials) for ``state``.

        ``neighbors`` is ignored (the tuples are listed explicitly).
        """
        geometry = self._geometry(state)
        n = state.n_atoms
        forces = np.zeros((n, 3))
        total = np.zeros(6)
        energies = np.zeros(n if per_atom else 0)
        virials = np.zeros((n if per_atom else 0, 6))
        loop = getattr(self._loops(), f"{self.ITEM}_forces")
        energy, bad = loop(*geometry, forces, total, energies, virials)
        if bad >= 0:
            self._raise_bad(state, bad)
        return ForceResult(
            energy=energy,
            forces=forces,
            virial=symmetric(total),
            energies=energies if per_atom else None,
            virials=virials if per_atom else None,
        )

    def _check_curvature(self) -> None:
        if self.term.curvature is None:
            raise TypeError(
                f"{self.ITEM} term {self.term.name} has no curvature (u and its first two "
                f"derivatives), so no Hessian: give it one with @{self.term.name}"
                ".with_curvature"
            )

    def _raise_bad(self, state, bad: int):
        raise NotImplementedError

    def describe(self) -> dict:
        """The style (a user's term: ``{ITEM}_term`` and the term's name), each parameter
        (a number, or a list per type), the tuple count and a hash of the list."""
        style = getattr(type(self), f"{self.ITEM}_style")
        extra = {"term": self.term.name} if style == f"{self.ITEM}_term" else {}
        return self._list_description(style, **extra, **self._described_values())

    def _described_values(self) -> dict:
        """Each parameter as given: a number, or a list per type."""
        return {
            name: table.tolist() if self.per_type else float(table[0])
            for name, table in zip(self.term.parameters, self._tables, strict=True)
        }


class BondPotential(_TermPotential):
    r"""A bond potential on the bonded frame, from a :class:`BondTerm` and its values.

    Parameters
    ----------
    term : BondTerm
        The bond's energy as a function of its length (:func:`bond_term`).
    bonds : array_like of int, shape (B, 2)
        Atom index pairs ``(i, j)``, ``i != j``; a pair listed twice counts twice.
    bond_types : array_like of int, shape (B,), optional
        Type index of each bond into per-type parameters.
    **values : float or sequence of float
        The term's parameters by name, each finite: one value for every bond, or one
        per bond type (then ``bond_types`` is required).

    Bond vectors use the minimum image along periodic axes (:mod:`md.box`); each bond
    must stay shorter than half the box edge. No neighbour list (``cutoff = None``).
    """

    ITEM = "bond"
    EXAMPLE = "[i, j]"
    #: Name of the bond style: the built-in styles' config type, the bond type name in
    #: files; a user's term's name (``describe()`` says ``"bond_term"`` and the name).
    bond_style = "bond_term"
    _read_file = staticmethod(read_bonds_file)

    def __init__(
        self,
        term: BondTerm,
        bonds: ArrayLike,
        bond_types: ArrayLike | None = None,
        **values: float | ArrayLike,
    ) -> None:
        self._user_setup(term, bond_array, bonds, bond_types, values)

    @property
    def bonds(self) -> NDArray[np.int64]:
        """The (B, 2) atom indices of the bonds (read-only)."""
        return self._items

    @property
    def bond_types(self) -> NDArray[np.int64]:
        """The (B,) type index of each bond (read-only)."""
        return self._types

    @property
    def n_bonds(self) -> int:
        return len(self._items)

    def with_bonds(self, bonds: ArrayLike, bond_types: ArrayLike) -> BondPotential:
        """The same potential over another bond list, whose ``bond_types`` index the same
        per-type parameters: one rank's share of the bonds, over its local atoms, in a run
        decomposed over MPI ranks (:mod:`md.distributed`)."""
        return self._with_list(bond_array(bonds), bond_types)

    def check(self, state) -> None:
        """Raise ValueError if a bond names an atom the state does not have."""
        if self.n_bonds and np.any(self.bonds[:, 0] == self.bonds[:, 1]):
            bad = int(np.flatnonzero(self.bonds[:, 0] == self.bonds[:, 1])[0])
            raise ValueError(f"bond {bad} joins atom {self.bonds[bad, 0]} to itself")
        self._check_indices(state.n_atoms)

    def hessian(self, state, neighbors=None) -> scipy.sparse.csr_matrix:
        """Return the (3N, 3N) Hessian d^2 U / dx_ia dx_jb as a sparse CSR matrix.

        Row and column ``3 * i + a`` belong to atom ``i``, axis ``a``
        [energy/length^2].
        """
        return self.hessian_operator(state, neighbors).tocsr()

    @_compiling_the_term
    def hessian_operator(self, state, neighbors=None) -> PairHessian:
        """Return the Hessian as one pair block per bond (:class:`PairHessian`).

        Bond b's block is K = u'' e e^T + (u'/r) (I - e e^T) along its unit
        vector e; a zero-length bond gets K = (u'/r) I.
        """
        self._check_curvature()
        geometry = self._geometry(state)
        transverse = np.empty(self.n_bonds)
        radial = np.empty(self.n_bonds)
        unit = np.empty((self.n_bonds, 3))
        bad = self._loops().bond_curvatures(*geometry, transverse, radial, unit)
        if bad >= 0:
            self._raise_bad(state, bad)
        bonds = self.bonds.astype(np.int64)
        return PairHessian(
            state.n_atoms,
            bonds[:, 0].copy(),
            bonds[:, 1].copy(),
            transverse,
            radial,
            unit,
            unique=False,
        )

    def bond_lengths(self, state) -> NDArray[np.float64]:
        """Return the (B,) bond lengths in ``state`` (minimum image) [length]."""
        self._check_indices(state.n_atoms)
        d = state.positions[self.bonds[:, 0]] - state.positions[self.bonds[:, 1]]
        return np.linalg.norm(minimum_image(d, state.box, state.pbc, state.tilt), axis=1)

    def _raise_bad(self, state, bad: int):
        i, j = (int(a) for a in self.bonds[bad])
        raise NonFiniteError(
            f"bond term {self.term.name}: bond {bad} between atoms {i} and {j} (length "
            f"{self._length(state, bad)!r}) has a non-finite energy"
        )

    def _length(self, state, bond: int) -> float:
        """The length of bond ``bond`` in ``state`` (minimum image)."""
        i, j = self.bonds[bond]
        d = minimum_image(state.positions[i] - state.positions[j], state.box, state.pbc, state.tilt)
        return float(np.linalg.norm(d))


class AnglePotential(_TermPotential):
    r"""An angle potential on the bonded frame, from an :class:`AngleTerm` and its values.

    Parameters
    ----------
    term : AngleTerm
        The angle's energy as a function of theta or cos theta (:func:`angle_term`).
    angles : array_like of int, shape (A, 3)
        Atom index triples ``(i, j, k)``, ``j`` the vertex, three distinct atoms.
    angle_types : array_like of int, shape (A,), optional
        Type index of each angle into per-type parameters.
    **values : float or sequence of float
        The term's parameters by name, each finite: one value for every angle, or one
        per angle type (then ``angle_types`` is required).

    An angle with an arm of zero length raises :class:`md.errors.AngleCollapseError`.
    Each angle's energy and virial go a third to each of its atoms in per-atom
    results (LAMMPS's split).
    """

    ITEM = "angle"
    EXAMPLE = "[i, j, k]"
    #: Name of the angle style: its config type, and the angle type name in files (a
    #: user's term's name; ``describe()`` says ``"angle_term"`` and the name).
    angle_style = "angle_term"

    @staticmethod
    def _read_file(path) -> np.ndarray:
        return read_index_file(path, 3, "angles_file")

    def __init__(
        self,
        term: AngleTerm,
        angles: ArrayLike,
        angle_types: ArrayLike | None = None,
        **values: float | ArrayLike,
    ) -> None:
        self._user_setup(term, angle_array, angles, angle_types, values)

    @property
    def angles(self) -> NDArray[np.int64]:
        """The (A, 3) atom indices of the angles, vertex in the middle (read-only)."""
        return self._items

    @property
    def angle_types(self) -> NDArray[np.int64]:
        """The (A,) type index of each angle (read-only)."""
        return self._types

    @property
    def n_angles(self) -> int:
        return len(self._items)

    def with_angles(self, angles: ArrayLike, angle_types: ArrayLike) -> AnglePotential:
        """The same potential over another angle list, whose ``angle_types`` index the same
        per-type parameters: one rank's share of the angles, over its local atoms, in a run
        decomposed over MPI ranks (:mod:`md.distributed`)."""
        return self._with_list(angle_array(angles), angle_types)

    def check(self, state) -> None:
        """Raise ValueError if an angle names an atom the state does not have."""
        self._check_indices(state.n_atoms)

    @_compiling_the_term
    def hessian(self, state, neighbors=None) -> scipy.sparse.csr_matrix:
        """Return the (3N, 3N) Hessian d^2 U / dx_ia dx_jb as a sparse CSR matrix.

        Row and column ``3 * i + a`` belong to atom ``i``, axis ``a``
        [energy/length^2]: the derivative of the forces as computed (with the
        floor on sin theta of a term of theta), one dense 9x9 block per angle.
        The blocks are not positive definite in general (bending has negative
        curvature away from its minimum); the implicit integrators' Newton
        solver copes with that by its shifts.
        """
        self._check_curvature()
        geometry = self._geometry(state)
        blocks = np.empty((self.n_angles, 9, 9))
        bad = self._loops().angle_hessian_blocks(*geometry, blocks)
        if bad >= 0:
            self._raise_bad(state, bad)
        index = (3 * self.angles[:, :, None] + np.arange(3)).reshape(-1, 9)
        rows = np.broadcast_to(index[:, :, None], blocks.shape)
        columns = np.broadcast_to(index[:, None, :], blocks.shape)
        size = 3 * state.n_atoms
        return scipy.sparse.coo_matrix(
            (blocks.ravel(), (rows.ravel(), columns.ravel())), shape=(size, size)
        ).tocsr()

    def angle_values(self, state) -> NDArray[np.float64]:
        """Return the (A,) angles theta in ``state`` (minimum image) [degrees]."""
        self._check_indices(state.n_atoms)
        return angle_values(state, self.angles)

    def _raise_bad(self, state, bad: int):
        raise AngleCollapseError(bad, tuple(int(a) for a in self.angles[bad]))


def bond_config_keys(*parameters: Key) -> tuple[Key, ...]:
    """A bond style's ``CONFIG_KEYS``: ``bonds`` or ``bonds_file``, its ``parameters``
    (:class:`md.schema.Key`, kind ``"number or list"``: one per bond type) and
    ``bond_types``; :meth:`BondPotential.from_config` reads them."""
    return bonded_keys("bond", BondPotential.EXAMPLE, *parameters)


def angle_config_keys(*parameters: Key) -> tuple[Key, ...]:
    """An angle style's ``CONFIG_KEYS``: ``angles`` or ``angles_file``, its ``parameters``
    and ``angle_types``; :meth:`AnglePotential.from_config` reads them."""
    return bonded_keys("angle", AnglePotential.EXAMPLE, *parameters)


def angle_values(state, angles: ArrayLike) -> NDArray[np.float64]:
    """Return the angles theta of the triples ``angles`` (``j`` the vertex) [degrees].

    Minimum image along the state's periodic axes; cos theta clamped to
    [-1, 1]. An arm of zero length gives NaN.

    Examples
    --------
    >>> from md.state import State
    >>> state = State(positions=[[1, 0, 0], [0, 0, 0], [-1, 0, 0]], box=10.0, pbc=False)
    >>> angle_values(state, [[0, 1, 2]]).tolist()
    [180.0]
    """
    angles = angle_array(angles)
    positions = state.positions
    a = minimum_image(
        positions[angles[:, 0]] - positions[angles[:, 1]], state.box, state.pbc, state.tilt
    )
    b = minimum_image(
        positions[angles[:, 2]] - positions[angles[:, 1]], state.box, state.pbc, state.tilt
    )
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.einsum("ij,ij->i", a, b) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))
