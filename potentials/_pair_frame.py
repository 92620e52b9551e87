"""The pair-kernel frame: everything a pair potential needs except its pair term.

A pair potential supplies a :class:`~potentials.pair_terms.PairTerm`: its
energy u and force over distance -u'(r)/r as a plain numba-compatible function
of r^2 and its parameters (and, optionally, u's first two derivatives with
respect to s = r^2, for Hessians). :class:`PairPotential` does the rest:
type-pair parameter tables (per-type values mixed, explicit pairs), the cutoff
modes (``none``, ``shift``, ``smooth`` with ``r_on``), the threaded slot-frame
kernels over a cell-built list and the atom-order kernels (minimum image,
per-atom energies and virials), the virial, orthorhombic and triclinic cells,
open axes, and the curvature passes that implicit integrators use.

The kernels live in ``potentials/_pair_kernels.py``, a template that
``potentials._pair_codegen.kernels_for`` runs once per term as a module of its
own with the term's functions inlined into its vectorised loops; numba caches
each term's kernels apart, keyed by a hash of the term's source (that module's
docstring says where the generated code goes and how to see and clear it).

At about 1100 lines this module is over the house's 800: nearly all of it is the one
class :class:`PairPotential` (tables, checks, the kernel calls of each path), whose
methods share its buffers and tables; the public term API is ``potentials.pair_terms``
and the code generator ``potentials._pair_codegen``.
"""

from __future__ import annotations

import functools
import inspect
import logging
import math
import operator
import re
import sys
from collections.abc import Callable, Mapping, Sequence

import numba
import numpy as np
import scipy.sparse as sp

from md._checks import positive_scalar
from md._memory import KeptArrays
from md.box import minimum_image, periodic_lengths, periodic_tilt
from md.errors import PairCollapseError
from md.schema import REQUIRED, Key, check_names, key_names
from md.state import State
from potentials._bonded import symmetric
from potentials._cluster_ir import slp_vectorising
from potentials._frame_call import frame_call, set_slots
from potentials._kernels import (
    J_STRIDE,
    _cluster_moments,
    _slot_types,
    cluster_atom_forces,
    zeros_on_lines,
)
from potentials._pair_codegen import (
    INV_DEN,
    RC2,
    RO2,
    SHIFT,
    TERM,
    kernels_for,
    variant,
)
from potentials._step_kernels import (
    cluster_runs,
    finish_forces,
    finish_step,
    kick_drift_slots,
    pass_chunks,
)
from potentials.base import PRECISIONS, ForceResult, check_precision_name
from potentials.pair_hessian import PairHessian
from potentials.pair_terms import HEADROOM, PairTerm, all_numbers

CUTOFF_MODES = {"none": 0, "shift": 1, "smooth": 2}
#: Mixing rules for per-type values: how a type pair's value follows from two types'.
MIXING_FUNCTIONS = {
    "geometric": lambda a, b: float(np.sqrt(a * b)),
    "arithmetic": lambda a, b: 0.5 * float(a + b),
}
logger = logging.getLogger(__name__)
_RESERVED = {"cutoff", "cutoff_mode", "r_on", "pairs", "mixing", "types", "type"}


def _compiling_the_term(method: Callable) -> Callable:
    """Wrap a method that runs the term's kernels: numba's error from compiling the term
    into them (the first call of each kernel compiles it) becomes a TypeError naming the
    term and what a term must be."""

    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        try:
            return method(self, *args, **kwargs)
        except numba.core.errors.NumbaError as error:
            raise TypeError(_compile_message(self.term, error)) from None

    return wrapper


def _compile_message(term: PairTerm, error: Exception) -> str:
    """What is wrong with a term numba cannot compile, with numba's first complaint."""
    plain = re.sub(r"\x1b\[[0-9;]*m", "", str(error))  # numba's highlighting
    lines = [line.strip() for line in plain.splitlines() if line.strip()]
    said = [line for line in lines if not line.startswith(("Failed in", "During:", "- "))]
    complaint = said[0] if said else type(error).__name__
    signature = ", ".join(("r2", *(("data",) if term.uses_data else ()), *term.parameters))
    curvature = ""
    if term.curvature is not None:
        curvature = f", and {term.curvature.__name__} a tuple of three (u, du_ds, d2u_ds2)"
    return (
        f"pair term {term.name}: numba cannot compile it into the pair kernels ({complaint}); "
        f"{term.energy.__name__}({signature}) must be numba-compatible Python (arithmetic, math "
        "and numpy functions, helpers decorated with numba.njit or register_jitable) that "
        "returns a tuple of two floats (u, f_over_r)" + curvature
    )


class PairPotential:
    r"""A pair potential on the pair-kernel frame, from a :class:`PairTerm` and its values.

    Parameters
    ----------
    term : PairTerm
        The pair term (see :func:`pair_term`).
    cutoff : float
        Pair cutoff [length] for every pair not overridden in ``pairs``.
    cutoff_mode : {"none", "shift", "smooth"}
        ``"none"``: truncated, energy and force jump at the cutoff.
        ``"shift"``: energy shifted by u(cutoff) so it is continuous there
        (LAMMPS's ``pair_modify shift yes``); the force still jumps.
        ``"smooth"``: u(r) is multiplied by the switching polynomial
        S(s) = (rc^2 - s)^2 (rc^2 + 2 s - 3 ro^2) / (rc^2 - ro^2)^3 in
        s = r^2 between ``r_on`` and the cutoff (1 below, 0 above), so energy
        and force are continuous (CHARMM's switch, ASE's LennardJones
        ``smooth=True``).
    r_on : float, optional
        Onset of switching for ``"smooth"`` [length]; defaults to 0.66 times
        each pair's cutoff.
    pairs : mapping, optional
        Values for chosen type pairs, overriding the others:
        ``{(ti, tj): {"cutoff": ..., "r_on": ..., name: value}}`` (any subset).
    mixing : str, optional
        Rule for unlike pairs of per-type values (the styles that mix say which).
    data : ndarray, optional
        The array a term with ``uses_data`` reads (tables).
    **values
        The term's parameters, one number each (the same for every pair), or,
        where the style mixes, one per type.

    Examples
    --------
    >>> from potentials.pair_terms import pair_term
    >>> @pair_term
    ... def harmonic_wall(r2, k, r0):
    ...     r = r2**0.5
    ...     return 0.5 * k * (r - r0) ** 2, -k * (r - r0) / r
    >>> wall = PairPotential(harmonic_wall, k=10.0, r0=1.0, cutoff=1.0, cutoff_mode="none")
    >>> round(wall.pair_energy(0.5), 12)
    1.25
    """

    #: Config ``type`` of a built-in style (None for a potential built from a user's term).
    style: str | None = None
    #: Mixing rules: rule name -> {parameter: "geometric" | "arithmetic"}; the parameters
    #: named there may be given per type. Empty: every parameter is one number or per pair.
    MIXING: Mapping[str, Mapping[str, str]] = {}
    #: Parameter checks: name -> "positive" | "nonnegative" (others: any finite number).
    LIMITS: Mapping[str, str] = {}
    #: The parameters users give (keywords, config keys), where a style converts them into
    #: its term's (LJ: epsilon, sigma -> c6, c12); None: the term's own.
    PARAMETERS: tuple[str, ...] | None = None
    #: The keys of a style's config table (:func:`pair_config_keys`; see :meth:`from_config`).
    CONFIG_KEYS: tuple[Key, ...] = ()
    #: The precisions :meth:`energy_forces` offers (``potentials.base.PRECISIONS``).
    PRECISIONS = PRECISIONS
    #: Whether ``CONFIG_KEYS`` was made from the constructor (:meth:`__init_subclass__`).
    _derived_keys = False

    def __init_subclass__(cls, **kwargs) -> None:
        """A style that declares no ``CONFIG_KEYS`` (a plug-in's, say) gets them from its
        constructor: its ``PARAMETERS`` (else its constructor's own arguments) as numbers
        (one per type where ``MIXING`` names them) with the constructor's defaults, then the
        frame's keys (:func:`pair_config_keys`), ``cutoff`` and ``cutoff_mode`` with the
        constructor's defaults."""
        super().__init_subclass__(**kwargs)
        if "CONFIG_KEYS" in cls.__dict__ or (cls.CONFIG_KEYS and not cls._derived_keys):
            return
        cls.CONFIG_KEYS = _derived_config_keys(cls)
        cls._derived_keys = True

    def __init__(
        self,
        term: PairTerm,
        cutoff: float,
        cutoff_mode: str = "shift",
        r_on: float | None = None,
        pairs: Mapping[tuple[int, int], Mapping[str, float]] | None = None,
        mixing: str | None = None,
        data: np.ndarray | None = None,
        **values,
    ) -> None:
        if not isinstance(term, PairTerm):
            raise TypeError(f"expected a PairTerm (see potentials.pair_term), got {term!r}")
        self.term = term
        self._run_variants: set = set()  # the slot-frame kernels this object has run
        self._frame_kernels: dict = {}  # the slot-frame variants found, by kernels and flags
        # The last double-precision slot-frame call without and with the virial: what it
        # depends on and (kernel, arguments but the forces, chunks). One serves a call
        # while the State's position and type arrays, its type names, this object's data
        # and cutoff mode are the same objects (the values are read at the call): a step
        # of a run then pays for its pair kernel, not for finding it again (about 4 us a
        # call at 108 atoms); see energy_forces
        self._frame_calls: list = [None, None]
        # The same for the last mixed-precision call over a cluster-pair list, its list
        # (a prune or a search makes a new one) one more object that must be the same: a
        # step then pays for the kernels and not for setting them up again (about 25 us
        # of Python a call at 32000 atoms, on the calling thread alone); see energy_forces
        self._cluster_calls: list = [None, None]
        # The cluster frame whose relative positions the list wrote at the State's present
        # positions (set by mixed_verlet_step's second call, after the list's prune or
        # search): the kernel's call over it reads them, not written again; else None
        self._made_frame = None
        # The last double-precision call over a list of atom indices (an O(N^2) build:
        # a decomposed rank's local system too thin along a periodic axis for cells; a
        # serial list has a slot frame): (positions, types, type names, data, cutoff
        # mode, the list's starts and neighbours, the cell's bytes, (kernel, its
        # geometry, types, table, mode, the empty per-atom arrays)). It serves a call
        # while those are the same objects (the cell the same values; positions read at
        # the call): a rank of the 576-atom melt took the whole set-up (variant lookup,
        # geometry, tables; about 20 Python calls) at every step; see energy_forces
        self._atom_call: tuple | None = None
        # verlet_step's compiled step for the kept call without the virial: (that call,
        # the kernel, its arguments after the reference and its bound and before the
        # forces: a FrameCall, the mode and single-type flag; energies; the call's
        # arguments, to see whether a new call differs only by its list's slots)
        self._verlet_call: tuple | None = None
        # (windows, runs) of mixed_verlet_step's sum into atom order: the runs of the
        # cluster list whose chunks' windows these are
        self._sum_runs: tuple | None = None
        label = self.style or term.name
        prefix = "" if self.style else f"pair term {term.name}: "  # a user's term is named
        if not isinstance(cutoff_mode, str) or cutoff_mode not in CUTOFF_MODES:
            raise ValueError(
                f"cutoff_mode must be one of {', '.join(CUTOFF_MODES)}, got {cutoff_mode!r}"
            )
        if (mixing is not None or self.MIXING) and (
            not isinstance(mixing, str) or mixing not in self.MIXING
        ):
            rules = ", ".join(self.MIXING) or "none (this style does not mix)"
            raise ValueError(f"mixing must be one of {rules}, got {mixing!r}")
        names = self.parameter_names()
        clash = _RESERVED.intersection(names)
        if clash:
            raise TypeError(f"pair term {term.name}: parameter names {sorted(clash)} are taken")
        unknown = set(values) - set(names)
        missing = [n for n in names if n not in values]
        if unknown:
            raise ValueError(f"{label}: unknown parameter(s) {sorted(unknown)}")
        if missing:
            raise ValueError(f"{label}: missing parameter(s) {missing}")
        self.mixing = mixing
        per_type = set(self.MIXING.get(mixing, {})) if mixing else set()
        self.values = {}
        for name in names:
            what = "a number or one number per type" if name in per_type else "a number"
            try:  # strings ("1.0") and bools numpy would take as numbers are refused
                array = (
                    np.asarray(values[name], dtype=np.float64)
                    if all_numbers(values[name])
                    else np.empty(0)
                )
            except (TypeError, ValueError):
                array = np.empty(0)  # not numbers: refused below
            if array.ndim > 1 or array.size == 0 or (array.ndim == 1 and name not in per_type):
                raise ValueError(f"{prefix}{name} must be {what}, got {values[name]!r}")
            if not np.all(np.isfinite(array)):
                raise ValueError(f"{name} must be finite, got {values[name]!r}")
            self.values[name] = array
        lengths = {a.size for a in self.values.values() if a.ndim == 1}
        if len(lengths) > 1:
            raise ValueError(
                f"{', '.join(sorted(per_type))}: the values given per type must all have one "
                f"value per type (got lists of {sorted(lengths)} values)"
            )
        self.n_types_fixed = lengths.pop() if lengths else None
        self.default_cutoff = positive_scalar(cutoff, "cutoff")
        self.cutoff_mode = cutoff_mode
        self.r_on = None if r_on is None else positive_scalar(r_on, "r_on")
        try:
            self.data = np.zeros(0) if data is None else np.ascontiguousarray(data, np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{label}: data must be an array of numbers, got {data!r}") from None
        self.pairs = {}
        allowed = set(names) | {"cutoff", "r_on"}
        if pairs is not None and not isinstance(pairs, Mapping):
            raise ValueError(f"{label}: pairs must map type pairs (i, j) to values, got {pairs!r}")
        for key, entry in (pairs or {}).items():
            ti, tj = _pair_types(key)
            if not isinstance(entry, Mapping):
                raise ValueError(f"pairs[{key!r}] must map parameter names to values, got {entry}")
            bad = set(entry) - allowed
            if bad:
                raise ValueError(f"unknown pair parameter(s) {sorted(bad)} for pair {key}")
            self.pairs[(min(ti, tj), max(ti, tj))] = dict(entry)
        # Validates every pair now, not at run time.
        self.tables(self.n_types_fixed or 1 + max((max(k) for k in self.pairs), default=0))
        self.cutoff = max(
            [self.default_cutoff] + [p["cutoff"] for p in self.pairs.values() if "cutoff" in p]
        )
        self._kernels = None

    @property
    def per_type_parameters(self) -> bool:
        """True with per-type values or explicit ``pairs`` (``TypedParameters``)."""
        return self.n_types_fixed is not None or bool(self.pairs)

    # ------------------------------------------------------------ per style
    def parameter_names(self) -> tuple[str, ...]:
        """The user-facing parameter names (``PARAMETERS``, else the term's)."""
        return self.term.parameters if self.PARAMETERS is None else self.PARAMETERS

    def coefficients(self, values: Mapping[str, float], ti: int, tj: int) -> tuple[float, ...]:
        """The term's parameters for one type pair from its (checked) values."""
        return tuple(np.float64(values[name]) for name in self.term.parameters)

    def check_pair(self, values: Mapping[str, float], ti: int, tj: int) -> None:
        """Raise ValueError if one pair's values are not allowed (beyond LIMITS)."""

    def cutoff_energy(self, coefficients: tuple, rc2: float) -> float:
        """u at the cutoff (the shift of ``"shift"``): the term evaluated there."""
        return self.term.energy_at(rc2, coefficients, self.data)[0]

    # ------------------------------------------------------------ tables
    def pair_parameters(self, ti: int, tj: int) -> dict[str, float]:
        """Return the parameter values, cutoff and r_on of the type pair (ti, tj)."""
        params = {}
        rules = self.MIXING.get(self.mixing, {}) if self.mixing else {}
        for name, array in self.values.items():
            if array.ndim == 0:
                params[name] = float(array)
                continue
            n = len(array)
            if ti >= n or tj >= n:
                raise ValueError(
                    f"{type(self).__name__} has parameters for {n} types, but type "
                    f"{max(ti, tj)} occurs"
                )
            params[name] = MIXING_FUNCTIONS[rules[name]](array[ti], array[tj])
        params.update(cutoff=self.default_cutoff, r_on=self.r_on)
        params.update(self.pairs.get((min(ti, tj), max(ti, tj)), {}))
        for name, rule in self.LIMITS.items():
            params[name] = positive_scalar(params[name], name, allow_zero=rule == "nonnegative")
        for name in self.values:
            value = params[name]
            if isinstance(value, bool) or not isinstance(value, int | float | np.floating):
                raise ValueError(f"{name} must be a number, got {value!r}")
            if not math.isfinite(value):
                raise ValueError(f"{name} must be finite, got {value!r} for pair ({ti}, {tj})")
            params[name] = float(value)
        params["cutoff"] = positive_scalar(params["cutoff"], "cutoff")
        if params["r_on"] is None:
            params["r_on"] = 0.66 * params["cutoff"]
        if self.cutoff_mode == "smooth" and not params["r_on"] < params["cutoff"]:
            raise ValueError(
                f"r_on ({params['r_on']:g}) must be smaller than the cutoff "
                f"({params['cutoff']:g}) for pair ({ti}, {tj})"
            )
        self.check_pair(params, ti, tj)
        return params

    def tables(self, n_types: int) -> np.ndarray:
        """The kernels' parameters: a (TERM + n, n_types * n_types) table, column
        ti * n_types + tj.

        Rows ``RC2`` and ``RO2`` (squared cutoff and switching start), ``SHIFT``
        (u at the cutoff), ``INV_DEN`` (1 / (rc^2 - ro^2)^3, the switching
        function's scale), then the term's n parameters.
        """
        n_term = len(self.term.parameters)
        table = np.zeros((TERM + n_term, n_types * n_types))
        for ti in range(n_types):
            for tj in range(n_types):
                p = self.pair_parameters(ti, tj)
                k = ti * n_types + tj
                with np.errstate(all="ignore"):
                    coefficients = self.coefficients(p, ti, tj)
                    table[TERM:, k] = coefficients
                    table[RC2, k] = np.float64(p["cutoff"]) ** 2
                    table[RO2, k] = np.float64(p["r_on"]) ** 2
                    table[SHIFT, k] = self.cutoff_energy(coefficients, table[RC2, k])
                    if table[RC2, k] > table[RO2, k]:
                        table[INV_DEN, k] = 1.0 / (table[RC2, k] - table[RO2, k]) ** 3
                self._check_column(p, ti, tj, table[:, k])
        return table

    def _check_column(self, values: Mapping, ti: int, tj: int, column: np.ndarray) -> None:
        """Raise ValueError unless a type pair's table column is finite and its term gives
        finite u and f/r below HEADROOM at the cutoff and just beyond it (the pair loops
        evaluate the term at every listed pair and mask those beyond the cutoff by a
        product, so a NaN or infinity there reaches the forces). The message names the
        value of the largest or smallest magnitude when one is beyond HEADROOM or the
        column overflowed, else the term and what it returned."""
        given = {name: values[name] for name in self.values}
        given["cutoff"] = values["cutoff"]
        if self.r_on is not None or "r_on" in self.pairs.get((min(ti, tj), max(ti, tj)), {}):
            given["r_on"] = values["r_on"]
        settings = np.concatenate((column[[RC2, RO2, INV_DEN]], column[TERM:]))
        coefficients = tuple(column[TERM:])
        problem = None
        if not np.all(np.isfinite(settings)):
            problem = "the pair's coefficients (or the cutoff's square) overflow"
        else:
            rc = math.sqrt(column[RC2])
            for r, where in ((rc, "the cutoff"), (1.001 * rc, "just beyond the cutoff")):
                with np.errstate(all="ignore"):
                    u, fr = self.term.energy_at(r * r, coefficients, self.data)
                if not (abs(u) <= HEADROOM and abs(fr) * r <= HEADROOM):
                    problem = (
                        f"at r = {r:g} ({where}) the pair term gives u = {u:g} and "
                        f"-u'(r) = {fr * r:g}"
                    )
                    break
            if not (problem or math.isfinite(column[SHIFT])):
                problem = f"the energy at the cutoff is {column[SHIFT]:g}"
        if problem is None:
            if self.term.curvature is not None:  # its shape (three numbers), for Hessians
                self.term.curvature_at(column[RC2], coefficients, self.data)
            return
        prefix = "" if self.style else f"pair term {self.term.name}: "
        shown = ", ".join(f"{name} = {value:g}" for name, value in given.items())
        nonzero = [name for name in given if given[name] != 0.0]
        extreme = max(nonzero, key=lambda name: abs(math.log10(abs(given[name]))), default=None)
        magnitude = 0.0 if extreme is None else abs(given[extreme])
        if extreme is not None and (
            not 1.0 / HEADROOM <= magnitude <= HEADROOM or not np.all(np.isfinite(settings))
        ):
            raise ValueError(
                f"{prefix}{extreme} = {given[extreme]:g} (type pair ({ti}, {tj}); {shown}) is "
                f"beyond what double precision can compute with: {problem}; the pair's energy "
                f"and force must be finite and below {HEADROOM:.3g} there"
            )
        raise ValueError(
            f"{prefix}with {shown} (type pair ({ti}, {tj})) {problem}: a pair term must return "
            "two finite numbers (u, f_over_r = -u'(r)/r) at and beyond its cutoff, below "
            f"{HEADROOM:.3g} in magnitude, so that sums over pairs stay finite"
        )

    def pair_energy(self, r: float, ti: int = 0, tj: int = 0) -> float:
        """Return the pair energy u(r) with the cutoff treatment applied [energy]."""
        positions = np.array([[0.0, 0.0, 0.0], [float(r), 0.0, 0.0]])
        state = State(
            positions=positions,
            box=[1.0, 1.0, 1.0],
            pbc=False,
            types=np.array([ti, tj]),
            type_names=None,
        )
        return self.energy_forces(state, None).energy

    # ------------------------------------------------------------ compute
    def check(self, state) -> None:
        if self.n_types_fixed is not None and state.n_types > self.n_types_fixed:
            raise ValueError(
                f"{type(self).__name__} has parameters for {self.n_types_fixed} types but the "
                f"system has {state.n_types} ({', '.join(state.type_names)})"
            )

    def check_precision(self, state, precision: str) -> None:
        """Raise ValueError if a parameter of ``state``'s type pairs cannot be held in
        ``precision`` (float32's range, for ``"mixed"``); the ForceField asks at set-up."""
        if precision == "mixed":
            self._cached_tables(max(state.n_types, self.n_types_fixed or 1), np.float32)

    def energy_forces(
        self,
        state,
        neighbors,
        per_atom: bool = False,
        virial: bool = True,
        precision: str = "double",
    ) -> ForceResult:
        """Return energy, forces, virial (and per-atom energies and virials) for ``state``.

        ``neighbors`` is a NeighborList with a radius >= ``cutoff``, or None
        for the O(N^2) all-pairs loop (small systems, tests). Over a list
        built by cells, the threaded slot-frame kernel runs (no minimum
        image, one chunk per thread); per-atom results and O(N^2) lists use
        the serial kernel over atom indices. ``virial=False`` skips the
        virial, leaving ``result.virial`` None.

        ``precision="mixed"`` computes the pair terms in float32 (r^2 taken in
        double and rounded once, parameters, u and f/r; see
        :func:`single_precision_term`), in the slot-frame and the atom-order
        kernels alike; the pair forces f/r * d, every sum and the results are
        float64: about 3e-7 of the largest force. Over a list that holds cluster
        pairs (``neighbors.clusters``: ``NeighborList(clusters=True)``, which a
        mixed-precision ForceField builds where the cell allows) it runs the
        cluster kernels instead (:mod:`potentials._cluster_ir`): float32
        separations and pair forces, eight pairs per vector, sums in double
        every few pairs; Newton's third law then holds to float32 round-off.
        """
        if precision == "double" and not per_atom and neighbors is not None:
            call = self._frame_calls[bool(virial)]
            if (  # _same_call, inline (a call fewer per step)
                call is not None
                and call[1] is state.positions
                and call[2] is state.types
                and call[3] is state.type_names
                and call[4] is self.data
                and call[5] == self.cutoff_mode
            ):
                frame = neighbors.frame
                if call[0] is not frame:  # the list was built again since
                    call = self._reslotted(call, neighbors, frame, bool(virial))
            else:
                call = None
            if call is not None:
                # the kernel of the last call, compiled then: nothing to compile here
                kernel, arguments, energies, virials, chunks = call[-1]
                forces = np.empty((len(arguments[0]), 3))
                kernel(*arguments, forces)
                result = ForceResult(
                    energy=float(energies.sum()) if chunks > 1 else float(energies[0]),
                    forces=forces,
                    virial=symmetric(virials.sum(axis=0)) if virial else None,
                )
                if not math.isfinite(result.energy):
                    self._explain_non_finite(state, neighbors)
                return result
            call = self._atom_call
            if (  # the last call over atom indices (see _atom_call), with the same list
                call is not None
                and call[0] is state.positions
                and call[1] is state.types
                and call[2] is state.type_names
                and call[3] is self.data
                and call[4] == self.cutoff_mode
                and (lists := neighbors.atom_lists())  # (starts, neighbors: one call)
                and lists[0] is call[5]
                and lists[1] is call[6]
                and call[7] == (state.box.tobytes(), state.tilt.tobytes(), state.pbc.tobytes())
            ):
                kernel, geometry, n_types, table, mode, energies, virials = call[-1]
                forces = np.zeros((len(geometry[0]), 3))
                total_virial = np.zeros(6)
                energy = kernel(
                    geometry,
                    n_types,
                    table,
                    mode,
                    self.data,
                    forces,
                    total_virial,
                    energies,
                    virials,
                )
                result = ForceResult(
                    energy=energy,
                    forces=forces,
                    virial=symmetric(total_virial) if virial else None,
                )
                if not math.isfinite(result.energy):
                    self._explain_non_finite(state, neighbors)
                return result
        if precision == "mixed" and not per_atom and neighbors is not None:
            call = self._cluster_calls[bool(virial)]
            if (
                call is not None
                and call[0] is getattr(neighbors, "clusters", None)
                and call[1] is state.positions
                and call[2] is state.types
                and call[3] is state.type_names
                and call[4] is self.data
                and call[5] == self.cutoff_mode
                and call[6] is neighbors
            ):
                # the kernel and arrays of the last call over this list: compiled then
                result = self._run_cluster_call(call[-1], state, bool(virial))
                if not math.isfinite(result.energy):
                    self._explain_non_finite(state, neighbors)
                return result
        return self._energy_forces(state, neighbors, per_atom, virial, precision)

    def verlet_step(self, state, neighbors, kicks, kick_dt, drift_dt, reference, allowed2):
        """A velocity Verlet step with this potential's forces in one compiled call, where
        the last slot-frame call without the virial serves ``state`` (as in
        :meth:`energy_forces`) on one chunk; None where it does not (nothing done).

        v += kick_dt kicks/m and x += drift_dt v; then, if no atom is farther than
        ``sqrt(allowed2)`` from ``reference`` (the list's half-skin rule, see
        :meth:`md.neighbors.NeighborList.exact_check`), the forces over ``neighbors``
        without the virial and v += kick_dt forces/m. ``kicks`` None: the step's second
        half alone (the forces and the last kick, after a rebuild of the list).
        Returns ``(code, result)``: code 0, the step done, ``result`` its ForceResult;
        1, only the first kick and the drift done, an atom moved too far or a coordinate
        is not finite (the caller refreshes the list, then evaluates and kicks); 2, the
        forces or energy not finite, the last kick not done; ``result`` None. The same
        bits as the separate kicks, list check and :meth:`energy_forces` (the template's
        ``frame_verlet``).
        """
        call = self._frame_calls[0]
        if (  # the conditions of energy_forces' kept call
            call is None
            or call[1] is not state.positions
            or call[2] is not state.types
            or call[3] is not state.type_names
            or call[4] is not self.data
            or call[5] != self.cutoff_mode
        ):
            return None
        frame = neighbors.frame
        if call[0] is not frame:  # the list was built again since
            call = self._reslotted(call, neighbors, frame, False)
            if call is None:
                return None
        fused = self._verlet_call
        if fused is None or fused[0] is not call:
            kernel, arguments, energies, virials, chunks = call[-1]
            if chunks != 1 or type(self).energy_forces is not PairPotential.energy_forces:
                return None  # (a subclass's own energy_forces is asked)
            # (positions, types, slots, n_types, table, mode, data, with_virial, single,
            # slot positions, slot types, buffers, energies, virials): the loop-invariant
            # arrays in one FrameCall (unboxed as one pointer), then the mode and the
            # single-type flag, in frame_verlet's order
            if fused is not None and _only_slots_differ(fused[4], arguments):
                set_slots(fused[2][0], arguments[2])  # the call moved onto a new list
                step, tail = fused[1], fused[2]
            else:
                packed = frame_call(*arguments[1:5], arguments[6], *arguments[9:])
                tail = (packed, arguments[5], arguments[8])
                flags = (arguments[5], arguments[8])  # the kernel's mode and single-type flag
                step = self._frame_kernels.get(("verlet", *flags))
                if step is None:
                    kernels = self._loaded("double")
                    step = variant(kernels, "frame_verlet", mode=flags[0], single=flags[1])
                    self._frame_kernels["verlet", *flags] = step
            fused = self._verlet_call = (call, step, tail, energies, arguments)
        _, step, tail, energies, _ = fused
        forces = np.empty((len(state.masses), 3))
        first_half = kicks is not None
        code = step(
            state.positions,
            state.velocities,
            state.masses,
            kicks if first_half else forces,  # (not read without the first half)
            kick_dt,
            drift_dt,
            reference if first_half else forces,
            allowed2,
            first_half,
            *tail,
            forces,
        )
        if code != 0:
            return code, None
        return 0, ForceResult(energy=float(energies[0]), forces=forces, virial=None)

    def kept_call(self, state, neighbors) -> tuple | None:
        """The compiled call :meth:`energy_forces` of ``state`` over ``neighbors`` makes in
        double precision without the virial, where the last slot-frame call serves it on
        one chunk (as :meth:`verlet_step` asks): ``(kernel, arguments, energies)``, where
        ``kernel(*arguments, forces)`` writes the forces into ``forces`` (N, 3; its
        contents are not read) and their energy into ``energies[0]``, the same bits as
        :meth:`energy_forces`, which would also check that the energy is finite. For a
        state of other arrays (a decomposed rank's next build) the call is laid out as
        the full path would lay it out, and kept, without being run (where that kernel
        has run in this object before). None where neither serves. Valid while the list
        is not built again and the state's arrays and this potential's parameters are
        the same."""
        if type(self).energy_forces is not PairPotential.energy_forces:
            return None
        call = self._frame_calls[0]
        if (  # the conditions of energy_forces' kept call
            call is None
            or call[1] is not state.positions
            or call[2] is not state.types
            or call[3] is not state.type_names
            or call[4] is not self.data
            or call[5] != self.cutoff_mode
        ):
            call = self._laid_call(state, neighbors)  # (new arrays: a decomposed rank's build)
        else:
            frame = neighbors.frame
            if call[0] is not frame:  # the list was built again since
                call = self._reslotted(call, neighbors, frame, False)
        if call is None:
            return None
        kernel, arguments, energies, _, chunks = call[-1]
        return (kernel, arguments, energies) if chunks == 1 else None

    def _laid_call(self, state, neighbors) -> tuple | None:
        """The slot-frame call without the virial that :meth:`energy_forces` of ``state``
        would lay out on its full path, laid out and kept (``_frame_calls``) without being
        run, where its kernel has run before in this object; None where it has not, or
        where ``neighbors`` has no slot frame."""
        frame = neighbors.frame
        if frame is None:
            return None
        self._check_radius(neighbors)
        n_types = max(state.n_types, self.n_types_fixed or 1)
        table = self._cached_tables(n_types, np.float64)
        mode = CUTOFF_MODES[self.cutoff_mode]
        self._last_frame_call = None
        self._frame_energy_forces(
            self._loaded("double"), state, frame, n_types, table, mode, False, run=False
        )
        if self._last_frame_call is None:
            return None
        self._atom_call = None  # (one kind of call kept, as energy_forces keeps them)
        call = (frame, state.positions, state.types, state.type_names, self.data)
        self._frame_calls[0] = (*call, self.cutoff_mode, self._last_frame_call)
        return self._frame_calls[0]

    def mixed_verlet_step(self, state, neighbors, kicks, kick_dt, drift_dt, held, allowed2, key):
        """A mixed-precision velocity Verlet step over a cluster-pair list in two compiled
        calls around the cluster kernel, where the last cluster call without the virial
        serves ``state`` (as in :meth:`energy_forces`); None where it does not (nothing
        done).

        First (``potentials._step_kernels``): v += kick_dt kicks/m, x += drift_dt v, x
        copied into ``key`` (N, 3: the force field's cache) and the largest squared
        distance from ``held`` (N, 3: where the list was last built or pruned), then,
        if that is at most ``allowed2`` (the list's half-skin rule, see
        :meth:`md.neighbors.NeighborList.cluster_check`), the float32 positions relative
        to the clusters' origins. Then the cluster kernel, and the second call: its
        chunks summed into atom order with the finite check on the way, and v += kick_dt
        forces/m. Returns ``(code, result)``: 0, the step done, ``result`` its
        ForceResult (no virial); 1, only the first kick and drift done (an atom moved
        too far, or a coordinate is not finite: the caller refreshes the list, then
        evaluates and kicks; ``key`` holds the new positions either way); 2, a force or
        the energy not finite, the last kick not done; ``result`` None. With code 1,
        ``result`` is the largest squared distance from ``held`` that the pass measured
        (what :meth:`md.neighbors.NeighborList.update` may take instead of measuring it
        again). The same bits as the separate kicks, list check and :meth:`energy_forces`.

        ``kicks`` None: the second call of a step whose list was refreshed after the
        first one's drift (``held``, ``allowed2`` and ``key`` unused): the forces by
        :meth:`energy_forces` (over the new list; the positions are those ``key``
        holds), the finite check and v += kick_dt forces/m; ``(0, result)``, or ``(2,
        None)`` where a value is not finite (nothing kicked). A cluster frame of
        ``neighbors`` other than the first call's was made by that refresh at ``state``'s
        positions: its relative positions (``ClusterFrame.relative``) are read as the list
        wrote them.
        """
        if kicks is None:
            if type(self).energy_forces is not PairPotential.energy_forces:
                return None
            # a frame other than the first call's: the list's prune or search made it at
            # state's positions, so its relative positions (ClusterFrame.relative) are
            # state's and the kernel reads them as they are (52 us a call at 32000 atoms)
            made = getattr(neighbors, "clusters", None)
            kept = self._cluster_calls[0]
            self._made_frame = made if kept is not None and kept[0] is not made else None
            try:
                result = self.energy_forces(state, neighbors, virial=False, precision="mixed")
            finally:
                self._made_frame = None
            energy = finish_forces(
                result.forces, result.energy, state.velocities, state.masses, kick_dt
            )
            if energy != energy:
                return 2, None
            return 0, result
        call = self._cluster_calls[0]
        if (  # the conditions of energy_forces' kept cluster call
            call is None
            or call[0] is not getattr(neighbors, "clusters", None)
            or call[1] is not state.positions
            or call[2] is not state.types
            or call[3] is not state.type_names
            or call[4] is not self.data
            or call[5] != self.cutoff_mode
            or call[6] is not neighbors
            or type(self).energy_forces is not PairPotential.energy_forces
        ):
            return None
        prepared = call[-1]
        clusters, scratch = prepared[3], prepared[2]
        atom = clusters.atom
        chunks = pass_chunks(state.n_atoms)
        moved2 = kick_drift_slots(
            state.positions,
            state.velocities,
            kicks,
            state.masses,
            kick_dt,
            drift_dt,
            held,
            allowed2,
            key,
            atom,
            clusters.origin,
            scratch[0],
            scratch[1],
            chunks,
        )
        if not moved2 <= allowed2:  # (NaN too: the list's update says what)
            return 1, moved2
        forces = np.empty((state.n_atoms, 3))
        self._cluster_kernel(prepared, state, False, forces)
        windows, runs = clusters.windows, self._sum_runs
        if runs is None or runs[0] is not windows:  # (found once per list)
            runs = self._sum_runs = (windows, cluster_runs(windows, len(atom)))
        energy = finish_step(
            scratch[3],
            atom,
            windows,
            forces,
            runs[1],
            scratch[6],
            state.velocities,
            state.masses,
            kick_dt,
            chunks,
        )
        if energy != energy:  # NaN: a force or the energy is not finite
            return 2, None
        return 0, ForceResult(energy=float(energy), forces=forces, virial=None)

    @_compiling_the_term
    def _energy_forces(self, state, neighbors, per_atom, virial, precision) -> ForceResult:
        """:meth:`energy_forces` where the last slot-frame call does not serve (see
        ``_frame_calls``): the kernel found (compiled on its first call) and run."""
        kernels = self._loaded(check_precision_name(precision))
        n = state.n_atoms
        n_types = max(state.n_types, self.n_types_fixed or 1)
        table = self._cached_tables(n_types, np.float32 if precision == "mixed" else np.float64)
        mode = CUTOFF_MODES[self.cutoff_mode]
        clusters = None
        if neighbors is not None and not per_atom and precision == "mixed":
            clusters = getattr(neighbors, "clusters", None)
        frame = None if neighbors is None or per_atom or clusters is not None else neighbors.frame
        if clusters is not None:
            self._check_radius(neighbors)
            result, prepared = self._cluster_energy_forces(
                kernels, state, clusters, n_types, table, mode, virial
            )
            self._cluster_calls[bool(virial)] = (
                clusters,
                state.positions,
                state.types,
                state.type_names,
                self.data,
                self.cutoff_mode,
                neighbors,
                prepared,
            )
        elif frame is not None:
            self._check_radius(neighbors)
            result = self._frame_energy_forces(kernels, state, frame, n_types, table, mode, virial)
            if precision == "double":
                self._atom_call = None  # (one kind of call kept: the list's)
                self._frame_calls[bool(virial)] = (
                    frame,
                    state.positions,
                    state.types,
                    state.type_names,
                    self.data,
                    self.cutoff_mode,
                    self._last_frame_call,
                )
        else:
            geometry = self._geometry(state, neighbors)
            forces = np.zeros((n, 3))
            total_virial = np.zeros(6)
            energies = np.zeros(n if per_atom else 0)
            virials = np.zeros((n if per_atom else 0, 6))
            kernel = variant(kernels, "atom_forces", mode=mode)
            energy = kernel(
                geometry, n_types, table, mode, self.data, forces, total_virial, energies, virials
            )
            if precision == "double" and neighbors is not None and not per_atom:
                # kept for the next calls over the same list (see _atom_call); the slot
                # frame's calls are dropped (a list over atom indices has no frame)
                self._frame_calls = [None, None]
                cell = (state.box.tobytes(), state.tilt.tobytes(), state.pbc.tobytes())
                self._atom_call = (
                    *(state.positions, state.types, state.type_names, self.data),
                    *(self.cutoff_mode, geometry[5], geometry[6], cell),
                    (kernel, geometry, n_types, table, mode, energies, virials),
                )
            result = ForceResult(
                energy=energy,
                forces=forces,
                virial=symmetric(total_virial) if virial or per_atom else None,
                energies=energies if per_atom else None,
                virials=virials if per_atom else None,
            )
        if not math.isfinite(result.energy):
            self._explain_non_finite(state, neighbors)
        return result

    def _cluster_energy_forces(self, kernels, state, clusters, n_types, table, mode, virial: bool):
        """Mixed precision over a cluster-pair list (``md.neighbors.ClusterFrame``): the
        relative positions in float32, the cluster kernel per chunk (on the threads when
        there are several), the chunks' forces summed into atom order, and the virial
        from the kernel's offset part plus the positions' part. Returns the result and
        the call prepared (``_run_cluster_call``), which the next call over the same list
        may run again."""
        n_clusters = clusters.n_clusters
        chunks = len(clusters.bounds) - 1
        # the chunks' forces and j lanes: room for each chunk's window (the clusters its
        # rows reach), not the whole list per chunk; the windows move with each prune, so
        # several chunks get a sixteenth more than they ask
        need = clusters.window_clusters
        scratch = getattr(self, "_cluster_scratch", None)
        remade = scratch is None or len(scratch[6]) != chunks or len(scratch[5]) < need
        if remade:
            room = need + need // 16 if chunks > 1 else need
            windows_scratch = (
                np.empty(12 * room),
                # the kernels' j lanes and their pair counts: zero, and left zero by each call
                zeros_on_lines(J_STRIDE * room, np.float32),
                np.zeros(room, np.int32),
                np.empty(chunks),
                np.empty((chunks, 9)),
            )
        else:
            windows_scratch = scratch[3:]
        if remade or scratch[0].shape[0] != 12 * n_clusters:
            # the per-cluster arrays, whose length follows each search's clusters: kept
            # from search to search (fresh ones cost page faults: md._memory.KeptArrays)
            kept = getattr(self, "_cluster_kept", None)
            if kept is None:
                kept = self._cluster_kept = KeptArrays()
            scratch = (
                kept.take("relative i", 12 * n_clusters, np.float32),
                kept.take("relative j", 12 * n_clusters, np.float32),
                kept.take("slot types", 4 * n_clusters, np.int32),
                *windows_scratch,
            )
            self._cluster_scratch = scratch
        relative = clusters.relative  # None, or the list's own buffers
        if relative is not None and all(
            x.dtype == np.float32 and x.shape == scratch[0].shape for x in relative
        ):
            # the list's own buffers for the relative positions (see ClusterFrame): the
            # kernel then reads those it wrote at its prune or search (see _made_frame)
            scratch = (*relative, *scratch[2:])
        single = n_types == 1
        entry = "cluster_forces_threaded" if chunks > 1 else "cluster_forces"
        lists = (
            clusters.starts,
            clusters.partners,
            clusters.offsets.reshape(-1),
            clusters.bounds,
            clusters.windows,
        )
        # as the slot frame's first call: both virial variants run once (they compile or
        # load before a run's loop), the one asked for last
        ran = (entry, mode, single)
        variants = [bool(virial)] if ran in self._run_variants else [not virial, bool(virial)]
        self._run_variants.add(ran)
        with slp_vectorising():  # the term's lanes (potentials._cluster_ir)
            for with_virial in variants:
                kernel = variant(
                    kernels, entry, mode=int(mode), with_virial=with_virial, single=single
                )
                prepared = (kernel, lists, scratch, clusters, n_types, table, int(mode), single)
                result = self._run_cluster_call(prepared, state, with_virial)
        return result, prepared

    def _run_cluster_call(self, prepared, state, virial: bool) -> ForceResult:
        """One call of the cluster kernel ``prepared`` by ``_cluster_energy_forces`` (the
        kernel's variant for ``virial``, its arrays): the relative positions, the kernel,
        the chunks' forces summed into atom order, the virial."""
        scratch, clusters = prepared[2], prepared[3]
        xi, xj, energies, virials = scratch[0], scratch[1], scratch[6], scratch[7]
        atom = clusters.atom
        made = self._made_frame
        if made is not clusters or made.relative is None or xi is not made.relative[0]:
            clusters.relative_positions(state.positions, xi, xj)
        forces = np.empty((state.n_atoms, 3))
        self._cluster_kernel(prepared, state, virial, forces)
        chunks = len(energies)
        if chunks > 1:  # one chunk writes the forces in atom order itself
            cluster_atom_forces(scratch[3], atom, clusters.windows, forces)
        total = None
        if virial:
            w = virials.sum(axis=0).reshape(3, 3) + _cluster_moments(atom, xi, forces)
            total = 0.5 * (w + w.T)
        return ForceResult(
            energy=float(energies.sum()) if chunks > 1 else float(energies[0]),
            forces=forces,
            virial=total,
        )

    def _cluster_kernel(self, prepared, state, virial: bool, forces) -> None:
        """The cluster kernel of ``prepared`` over its relative positions, as written: the
        chunks' forces into their buffers (one chunk: into ``forces``, in atom order),
        their energies and virials into the scratch's."""
        kernel, lists, scratch, clusters, n_types, table, mode, single = prepared
        xi, xj, slot_types, buffers, j_sums, j_counts, energies, virials = scratch
        atom = clusters.atom
        if not single:
            _slot_types(state.types, atom, slot_types)
        kernel(
            xi,
            xj,
            lists,
            slot_types,
            n_types,
            table,
            mode,
            self.data,
            virial,
            single,
            buffers,
            j_sums,
            j_counts,
            atom,
            forces,
            energies,
            virials,
        )

    def _frame_energy_forces(
        self, kernels, state, frame, n_types, table, mode, virial: bool, run: bool = True
    ):
        """The slot-frame call laid out (``_last_frame_call``) and run; without ``run``,
        laid out alone where its kernel has run before (else nothing: None either way)."""
        n = state.n_atoms
        chunks = frame.n_chunks
        scratch = getattr(self, "_scratch", None)
        if scratch is None or scratch[0].shape[0] != n or scratch[2].shape[0] != chunks:
            scratch = (
                np.empty((n, 3)),
                np.empty(n, dtype=state.types.dtype),
                np.empty((chunks, n, 3)),
                np.empty(chunks),
                np.empty((chunks, 6)),
            )
            self._scratch = scratch
        slot_positions, slot_types, buffers, energies, virials = scratch
        forces = np.empty((n, 3) if run else (0, 3))
        # One chunk stays off numba's thread pool: no wake-ups on a busy machine.
        entry = "frame_forces_threaded" if chunks > 1 else "frame_forces"
        arguments = (
            state.positions,
            state.types,
            _slots(frame),
            n_types,
            table,
            int(mode),
            self.data,
            bool(virial),
            n_types == 1,
            slot_positions,
            slot_types,
            buffers,
            energies,
            virials,
            forces,
        )
        # A run asks for forces with the virial (thermo steps) and without (the rest): this
        # object's first call for a kernel runs both variants (one force evaluation more,
        # once), so both compile (or load) before a run's loop starts rather than one in
        # the middle of its timing.
        ran = (entry, mode, n_types == 1, table.dtype.str)
        if not run:
            kernel = self._frame_kernels.get((kernels.__name__, *ran, bool(virial)))
            if ran in self._run_variants and kernel is not None:
                self._last_frame_call = (kernel, arguments[:-1], energies, virials, chunks)
            return None
        variants = [bool(virial)] if ran in self._run_variants else [not virial, bool(virial)]
        self._run_variants.add(ran)
        found = self._frame_kernels
        for with_virial in variants:
            key = (kernels.__name__, *ran, with_virial)  # variant(): a microsecond a call
            kernel = found.get(key)
            if kernel is None:
                kernel = found[key] = variant(
                    kernels, entry, mode=int(mode), with_virial=with_virial, single=n_types == 1
                )
            kernel(*arguments)
        self._last_frame_call = (kernel, arguments[:-1], energies, virials, chunks)
        return ForceResult(
            energy=float(energies.sum()) if chunks > 1 else float(energies[0]),
            forces=forces,
            virial=symmetric(virials.sum(axis=0)) if virial else None,
        )

    def _reslotted(self, call: tuple, neighbors, frame, virial: bool) -> tuple | None:
        """A slot-frame call of ``_frame_calls`` moved onto a new frame of the list (a
        rebuild: new slots and pairs, the same atoms), kept for the next calls; None
        where its kernel and scratch do not serve the frame (another chunk count, or no
        slot frame)."""
        kernel, arguments, energies, virials, chunks = call[-1]
        if frame is None or frame.n_chunks != chunks:
            return None
        self._check_radius(neighbors)
        arguments = (*arguments[:2], _slots(frame), *arguments[3:])
        call = (frame, *call[1:-1], (kernel, arguments, energies, virials, chunks))
        self._frame_calls[virial] = call
        return call

    def _explain_non_finite(self, state, neighbors) -> None:
        """Called when the energy is not finite; a style whose term has a forbidden inner
        region (Buckingham) raises an error naming the pair there. By default the
        caller's NonFiniteError (overlapping atoms) stands."""

    def hessian(self, state, neighbors) -> sp.csr_matrix:
        r"""Return the (3N, 3N) Hessian of the energy, :math:`\partial^2 U / \partial x \partial x`.

        Exact for every cutoff mode: inside the cutoff the second derivative
        of u(r) (``"none"``, ``"shift"``: the shift is a constant) or of
        S(s) u(s) (``"smooth"``); pairs beyond the cutoff contribute nothing
        (the jump of the truncated modes at the cutoff is not a derivative).
        Each pair adds a 3x3 block K to the (i, i) and (j, j) blocks and -K
        to (i, j) and (j, i), so every block row sums to zero (translation
        invariance) and the matrix is symmetric. Needs the term's curvature.

        Parameters
        ----------
        state : State
            The configuration; left untouched.
        neighbors : NeighborList or None
            A list with a radius >= ``cutoff``, or None for all pairs.

        Returns
        -------
        scipy.sparse.csr_matrix, shape (3N, 3N)
            Row and column 3 i + a is coordinate a of atom i [energy/length^2];
            canonical (sorted column indices, no duplicates), with every
            diagonal block stored.
        """
        return self.hessian_operator(state, neighbors).tocsr()

    @_compiling_the_term
    def hessian_operator(self, state, neighbors) -> PairHessian:
        """Return the Hessian as pair blocks, to apply without assembling it.

        The same matrix as :meth:`hessian` (arguments alike), as a
        :class:`potentials.pair_hessian.PairHessian`: one 3x3 block per pair
        inside the cutoff. Its ``matvec`` costs about a force evaluation,
        which is what a Newton-Krylov solver needs.
        """
        if self.term.curvature is None:
            raise TypeError(
                f"pair term {self.term.name} has no curvature, so its Hessian (which implicit "
                "integrators' Newton steps need) is not available: give the term one "
                "(PairTerm(..., curvature=...) or @term.with_curvature), or use an explicit "
                "integrator"
            )
        kernels = self._loaded()
        n = state.n_atoms
        n_types = max(state.n_types, self.n_types_fixed or 1)
        table = self._cached_tables(n_types)
        mode = CUTOFF_MODES[self.cutoff_mode]
        frame = None if neighbors is None else neighbors.frame
        if frame is not None:
            self._check_radius(neighbors)
            return self._frame_hessian(kernels, state, frame, n_types, table, mode)
        geometry = self._geometry(state, neighbors)
        listed = len(geometry[-1])  # room for every listed pair; those inside are kept
        pair_i = np.empty(listed, dtype=np.int64)
        pair_j = np.empty(listed, dtype=np.int64)
        transverse = np.empty(listed)
        radial = np.empty(listed)
        unit = np.empty((listed, 3))
        n_pairs = variant(kernels, "atom_curvatures", mode=mode)(
            geometry, n_types, table, mode, self.data, pair_i, pair_j, transverse, radial, unit
        )
        return PairHessian(
            n,
            pair_i[:n_pairs],
            pair_j[:n_pairs],
            transverse[:n_pairs],
            radial[:n_pairs],
            unit[:n_pairs],
        )

    def _frame_hessian(self, kernels, state, frame, n_types, table, mode) -> PairHessian:
        """``hessian_operator`` over a slot-frame list, in one threaded pass: each chunk
        writes the blocks of its pairs inside the cutoff from where its listed pairs
        start, so no pass counts them first; the operator takes each chunk's run as one
        of its pieces and skips the gaps the pairs beyond the cutoff leave. The Jacobi
        diagonal is summed when the solver asks for it."""
        n = state.n_atoms
        chunks = frame.n_chunks
        slot_positions = np.empty((n, 3))
        slot_types = np.empty(n, dtype=state.types.dtype)
        room = int(frame.starts[-1])  # every listed pair
        # The blocks go into buffers kept from the last call when nothing uses them any
        # more (the last operator is gone): fresh arrays of tens of MB cost page faults
        # that take as long as writing them.
        held = getattr(self, "_hessian_buffers", None)
        if held is None or held[0].shape[0] < room or not _unshared(held):
            size = int(room * 1.05) + 1024
            held = (
                np.empty(size, dtype=np.int32),
                np.empty(size, dtype=np.int32),
                np.empty(size),
                np.empty(size),
                np.empty((size, 3)),
            )
            self._hessian_buffers = held
        written = np.zeros(chunks, dtype=np.int64)
        # One chunk stays off numba's thread pool: no wake-ups on a busy machine.
        entry = "frame_curvatures_threaded" if chunks > 1 else "frame_curvatures"
        write = variant(kernels, entry, mode=int(mode), single=n_types == 1)
        write(
            state.positions,
            state.types,
            _slots(frame),
            n_types,
            table,
            int(mode),
            self.data,
            n_types == 1,
            slot_positions,
            slot_types,
            held,
            written,
        )
        first = frame.starts[frame.bounds[:-1]]
        return PairHessian(n, *held, pieces=np.column_stack((first, first + written)))

    def describe(self) -> dict:
        out = {"type": self.style or self.term.name}
        out.update({name: array.tolist() for name, array in self.values.items()})
        out.update(cutoff=self.default_cutoff, cutoff_mode=self.cutoff_mode)
        if self.mixing is not None:
            out["mixing"] = self.mixing
        if self.r_on is not None:
            out["r_on"] = self.r_on
        if self.pairs:
            out["pairs"] = {f"{i}-{j}": v for (i, j), v in self.pairs.items()}
        return out

    # ------------------------------------------------------------ config
    @classmethod
    def config_values(cls, params: dict, type_names: Sequence[str]) -> dict:
        """Turn a config table (type names resolved) into constructor keywords.

        Keys: the style's ``PARAMETERS`` (a number, or for those the style mixes
        a table ``{name = value}`` covering every type), ``cutoff``,
        ``cutoff_mode``, ``r_on``, ``mixing`` (styles that mix), and
        ``pairs``, a list of tables ``{types = [name, name], key = value, ...}``.
        """
        names = cls.PARAMETERS
        if names is None:  # the keys made from the constructor name them
            names = tuple(n for n in key_names(cls.CONFIG_KEYS) if n not in _RESERVED)
        params = dict(params)
        check_names(params, cls.CONFIG_KEYS)
        for key in names:
            value = params.get(key)
            if isinstance(value, Mapping):
                missing = [name for name in type_names if name not in value]
                extra = [name for name in value if name not in type_names]
                if missing or extra:
                    raise ValueError(
                        f"{key}: give one value per type {list(type_names)}"
                        + (f"; missing {missing}" if missing else "")
                        + (f"; unknown types {extra}" if extra else "")
                    )
                params[key] = [value[name] for name in type_names]
        keys = {*names, "cutoff", "r_on"}
        pairs = config_pairs(params.pop("pairs", None), type_names, keys, numbers=keys)
        for key in (*names, "cutoff", "r_on"):
            value = params.get(key)
            for v in value if isinstance(value, list) else [value]:
                if v is not None:
                    _number(key, v)
        return {**params, "pairs": pairs}

    @classmethod
    def from_config(cls, params: Mapping, type_names: Sequence[str]):
        """Build from a config table; per-type values are keyed by type name."""
        return cls(**cls.config_values(dict(params), type_names))

    # ------------------------------------------------------------ helpers
    def _loaded(self, precision: str = "double"):
        if self._kernels is None:
            self._kernels = {}
        if precision not in self._kernels:
            self._kernels[precision] = kernels_for(self.term, precision)
        return self._kernels[precision]

    def _geometry(self, state, neighbors):
        """(positions, types, lengths, inverse, tilt, starts, neighbors) over atom indices."""
        lengths, inverse = periodic_lengths(state.box, state.pbc)
        tilt = periodic_tilt(state.tilt, state.pbc)
        if neighbors is None:
            starts, partners = _all_pairs(state.n_atoms)
        else:
            self._check_radius(neighbors)
            starts, partners = neighbors.starts, neighbors.neighbors
        return (state.positions, state.types, lengths, inverse, tilt, starts, partners)

    def _check_radius(self, neighbors) -> None:
        if neighbors.list_radius < self.cutoff:
            raise ValueError(
                f"neighbour list radius {neighbors.list_radius:g} is below the "
                f"{self.style or self.term.name} cutoff {self.cutoff:g}"
            )

    def _cached_tables(self, n_types: int, dtype=np.float64):
        """The parameter table for ``n_types`` types (and its float32 copy, for mixed
        precision), made once."""
        cache = getattr(self, "_table_cache", None)
        if cache is None or cache[0] != n_types:
            cache = self._table_cache = (n_types, self.tables(n_types), {})
        if dtype == np.float64:
            return cache[1]
        if dtype not in cache[2]:
            cache[2][dtype] = self._narrowed(cache[1], dtype)
        return cache[2][dtype]

    def _narrowed(self, table: np.ndarray, dtype) -> np.ndarray:
        """``table`` in ``dtype`` (float32: mixed precision); ValueError naming the value if
        one would overflow or lose its digits below float32's normal range (a parameter in
        units where it is 1e-50, say: the pair loop would compute with 0 or inf)."""
        info = np.finfo(dtype)
        magnitude = np.abs(table)
        bad = (magnitude > info.max) | ((magnitude < info.tiny) & (magnitude > 0.0))
        if np.any(bad):
            row, column = (int(i[0]) for i in np.nonzero(bad))
            names = (
                "cutoff^2",
                "r_on^2",
                "the energy at the cutoff",
                "the switch's scale",
                *self.term.parameters,
            )
            raise ValueError(
                f"{self.style or self.term.name}: {names[row]} = {table[row, column]:g} (type-pair "
                f"column {column}) is outside {np.dtype(dtype).name}'s range "
                f"({info.tiny:.2g} to {info.max:.2g}); mixed precision cannot hold it: run in "
                "double precision or in units that bring it into range"
            )
        return table.astype(dtype)


#: Type numbers a ``pairs`` key may name: a table per parameter has this squared entries.
MAX_PAIR_TYPE = 1024


def _pair_types(key) -> tuple[int, int]:
    """The two type numbers of a ``pairs`` key, refused unless two integers in range."""
    try:
        ti, tj = (operator.index(t) for t in key)
    except (TypeError, ValueError):
        raise ValueError(f"pairs keys must be two type numbers (i, j), got {key!r}") from None
    if not (0 <= ti < MAX_PAIR_TYPE and 0 <= tj < MAX_PAIR_TYPE):
        raise ValueError(f"pair types must lie in 0 .. {MAX_PAIR_TYPE - 1}, got {key}")
    return ti, tj


def collapse_error(potential: PairPotential, state, neighbors, limit2: np.ndarray, reason: str):
    """The PairCollapseError for the closest pair inside its type pair's ``limit2`` (a squared
    distance per table column), or None if no pair is; ``reason`` says what lies inside."""
    n_types = max(state.n_types, potential.n_types_fixed or 1)
    starts, partners = potential._geometry(state, neighbors)[5:]
    i = np.repeat(np.arange(state.n_atoms), np.diff(starts))
    j = np.asarray(partners, dtype=np.int64)
    d = minimum_image(state.positions[i] - state.positions[j], state.box, state.pbc, state.tilt)
    r2 = np.einsum("ij,ij->i", d, d)
    columns = state.types[i] * n_types + state.types[j]
    inside = np.flatnonzero(r2 < limit2[columns])
    if not len(inside):
        return None
    worst = inside[np.argmin(r2[inside] / limit2[columns[inside]])]
    a, b = int(i[worst]), int(j[worst])
    names = state.type_names
    return PairCollapseError(
        potential.style or potential.term.name,
        a,
        b,
        (names[state.types[a]], names[state.types[b]]),
        float(np.sqrt(r2[worst])),
        float(np.sqrt(limit2[columns[worst]])),
        state.step,
        reason,
    )


def pair_config_keys(
    *parameters: Key,
    cutoff: float | None = 2.5,
    cutoff_mode: str = "shift",
    mixing: tuple[str, ...] = (),
    mixing_doc: str = "",
    pair_keys: tuple[str, ...] | None = None,
    cutoff_doc: str = "",
) -> tuple[Key, ...]:
    """A pair style's ``CONFIG_KEYS``: its own ``parameters``, then the keys the frame takes
    with the style's defaults: ``cutoff``, ``cutoff_mode``, ``r_on``, ``mixing`` (styles
    that mix: the rules, the first the default) and ``pairs``, whose tables take
    ``pair_keys`` (default: the parameters), ``cutoff`` and ``r_on``; ``cutoff_doc`` says
    what a ``cutoff`` default of None means."""
    mixed = (Key("mixing", "string", mixing[0], choices=mixing, doc=mixing_doc),) if mixing else ()
    names = ", ".join(f"`{name}`" for name in pair_keys or key_names(parameters))
    return (
        *parameters,
        Key(
            "cutoff",
            "number",
            cutoff,
            unit="length",
            doc="The pair cutoff, for every pair not given its own in `pairs`.",
            default_doc=cutoff_doc,
        ),
        Key(
            "cutoff_mode",
            "string",
            cutoff_mode,
            choices=tuple(CUTOFF_MODES),
            doc='`"none"`: truncated; `"shift"`: energy continuous at the cutoff (LAMMPS\'s '
            '`pair_modify shift yes`); `"smooth"`: energy and force switched off between '
            "`r_on` and the cutoff.",
        ),
        Key(
            "r_on",
            "number",
            None,
            unit="length",
            doc='Where switching starts with `cutoff_mode = "smooth"`.',
            default_doc="0.66 `cutoff` per pair",
        ),
        *mixed,
        Key(
            "pairs",
            "list of tables",
            None,
            doc="Single type pairs given their own values: `[[potentials.pairs]]` tables with "
            f"`types = [a, b]` and any of {names}, `cutoff`, `r_on`.",
        ),
    )


def _derived_config_keys(cls) -> tuple[Key, ...]:
    """The ``CONFIG_KEYS`` of a style that declares none, from its constructor's signature
    (see :meth:`PairPotential.__init_subclass__`)."""
    try:
        signature = inspect.signature(cls.__init__).parameters
    except (TypeError, ValueError):
        signature = {}
    names = cls.PARAMETERS
    if names is None:
        names = tuple(
            n
            for n, p in signature.items()
            if n not in (*_RESERVED, "self", "term", "data")
            and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)
        )

    def default(name: str, otherwise=REQUIRED):
        parameter = signature.get(name)
        if parameter is None or parameter.default is parameter.empty:
            return otherwise
        return parameter.default

    per_type = {name for rules in cls.MIXING.values() for name in rules}
    parameters = tuple(
        Key(
            name,
            "number, list or table" if name in per_type else "number",
            default(name),
            doc=f"A parameter of {cls.__name__}"
            + (" (one number, or per type, mixed by `mixing`)." if name in per_type else "."),
        )
        for name in names
    )
    return pair_config_keys(
        *parameters,
        cutoff=default("cutoff"),
        cutoff_mode=default("cutoff_mode", "shift"),
        mixing=tuple(cls.MIXING),
    )


def config_pairs(entries, type_names: Sequence[str], keys: set[str], numbers: set[str]) -> dict:
    """``[[potentials.pairs]]`` tables as ``{(ti, tj): {key: value}}``: each names two of the
    types (``types = [a, b]``) and any of ``keys``, those in ``numbers`` numbers; errors say
    which entry is wrong."""
    index = {name: i for i, name in enumerate(type_names)}
    pairs = {}
    if entries is not None and not isinstance(entries, list):
        raise ValueError(f"pairs must be an array of tables (types = [a, b], ...), got {entries!r}")
    for number, entry in enumerate(entries or []):
        if not isinstance(entry, Mapping) or "types" not in entry:
            raise ValueError(f"pairs[{number}] must be a table with 'types = [a, b]'")
        entry = dict(entry)
        types = entry.pop("types")
        if (
            not isinstance(types, list)
            or len(types) != 2
            or any(not isinstance(n, str) or n not in index for n in types)
        ):
            raise ValueError(
                f"pairs[{number}].types must name two of the types {list(type_names)}, "
                f"got {types!r}"
            )
        bad = set(entry) - keys
        if bad:
            raise ValueError(f"pairs[{number}]: unknown key(s) {', '.join(sorted(bad))}")
        for key in numbers.intersection(entry):
            _number(f"pairs[{number}].{key}", entry[key])
        pairs[(index[types[0]], index[types[1]])] = entry
    return pairs


def _number(key: str, value) -> None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"{key}: expected a number, got {value!r}")


def _slots(frame) -> tuple:
    return (
        frame.order,
        frame.images,
        frame.lengths,
        frame.shifts,
        frame.starts,
        frame.neighbors,
        frame.codes,
        frame.bounds,
        frame.tilt,
        frame.shifted,
    )


def _only_slots_differ(old: tuple, new: tuple) -> bool:
    """Whether two slot-frame calls' arguments (``_frame_energy_forces``' order) are the same
    objects and values but for the slots (index 2): a call moved onto a rebuilt list."""
    return (
        len(old) == len(new)
        and all(old[i] is new[i] for i in (0, 1, 4, 6, *range(9, len(new))))
        and old[3] == new[3]
        and old[5] == new[5]
        and old[7] == new[7]
        and old[8] == new[8]
        and type(old[2]) is type(new[2])
    )


def _unshared(buffers) -> bool:
    """Whether nothing but ``buffers`` refers to its arrays (no view, no operator built
    on them), by CPython's reference counts: each at most that of an array held only by
    a tuple and counted the same way (interpreters differ in what the count includes)."""
    probe = (np.empty(0),)
    baseline = max(sys.getrefcount(array) for array in probe)
    return all(sys.getrefcount(buffer) <= baseline for buffer in buffers)


def _all_pairs(n: int):
    """CSR half list of every pair, for neighbour-free evaluation."""
    counts = np.arange(n - 1, -1, -1, dtype=np.int64)
    starts = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(counts, out=starts[1:])
    neighbors = np.concatenate([np.arange(i + 1, n) for i in range(n)] or [np.zeros(0)])
    return starts, neighbors.astype(np.int32)
