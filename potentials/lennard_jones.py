"""Lennard-Jones pair potential with per-type parameters and three cutoff modes."""

from __future__ import annotations

import sys
from collections.abc import Mapping, Sequence

import numpy as np
import scipy.sparse as sp
from numba import njit, prange

from md._checks import positive_array, positive_scalar
from md._simd import store_fence, stream_store
from md.box import min_image, periodic_lengths, periodic_tilt, separation
from md.schema import Key, check_names
from md.state import State
from potentials._kernels import _add_half_pair_virial
from potentials.base import ForceResult
from potentials.pair_hessian import PairHessian

CUTOFF_MODES = {"none": 0, "shift": 1, "smooth": 2}
MIXING_RULES = ("lorentz-berthelot", "geometric")
#: Rows of the kernel's parameter table, one column per type pair.
C6, C12, RC2, RO2, SHIFT, INV_DEN = range(6)


class LennardJones:
    r"""Lennard-Jones potential :math:`u(r) = 4\epsilon[(\sigma/r)^{12} - (\sigma/r)^6]`.

    Parameters
    ----------
    epsilon, sigma : float or sequence of float
        Well depth [energy] and size [length]; one value for every type, or
        one per type (index = type) mixed into pair values by ``mixing``.
    cutoff : float
        Pair cutoff [length] for every pair not overridden in ``pairs``.
    cutoff_mode : {"none", "shift", "smooth"}
        ``"none"``: truncated, energy and force jump at the cutoff.
        ``"shift"``: energy shifted by u(cutoff) so it is continuous there;
        the force still jumps (ASE's LennardJones default).
        ``"smooth"``: u(r) is multiplied by the switching polynomial
        S(s) = (rc^2 - s)^2 (rc^2 + 2 s - 3 ro^2) / (rc^2 - ro^2)^3 in
        s = r^2 between ``r_on`` and the cutoff (1 below, 0 above), so energy
        and force are continuous; the same function ASE's ``smooth=True``
        uses, so results compare directly.
    r_on : float, optional
        Onset of switching for ``"smooth"`` [length]; defaults to 0.66 times
        each pair's cutoff (ASE's default).
    pairs : mapping, optional
        Explicit pair parameters overriding mixing:
        ``{(ti, tj): {"epsilon": ..., "sigma": ..., "cutoff": ..., "r_on": ...}}``
        (any subset of the keys).
    mixing : {"lorentz-berthelot", "geometric"}
        Rule for unlike pairs: epsilon_ij = sqrt(epsilon_i epsilon_j) in both;
        sigma_ij = (sigma_i + sigma_j) / 2 (Lorentz-Berthelot) or
        sqrt(sigma_i sigma_j) (geometric).

    Examples
    --------
    >>> lj = LennardJones(epsilon=1.0, sigma=1.0, cutoff=2.5)
    >>> abs(lj.pair_energy(2.5 - 1e-9)) < 1e-8  # shifted: continuous at the cutoff
    True
    """

    #: The keys of its config table (see :meth:`from_config`).
    CONFIG_KEYS = (
        Key("epsilon", "number, list or table", 1.0, unit="energy",
            doc="The well depth: one number, or per type (`{Ar = 0.0104, Kr = 0.014}`, "
                "covering every type), mixed by `mixing`."),
        Key("sigma", "number, list or table", 1.0, unit="length",
            doc="The size, given as `epsilon` is."),
        Key("cutoff", "number", 2.5, unit="length", doc="The pair cutoff."),
        Key("cutoff_mode", "string", "shift", choices=tuple(CUTOFF_MODES),
            doc='`"none"`: truncated; `"shift"`: energy continuous at the cutoff (ASE\'s '
                'default); `"smooth"`: energy and force switched off between `r_on` and the '
                "cutoff (ASE's `smooth=True`)."),
        Key("r_on", "number", None, unit="length",
            doc='Where switching starts with `cutoff_mode = "smooth"`.',
            default_doc="0.66 `cutoff` per pair"),
        Key("mixing", "string", "lorentz-berthelot", choices=MIXING_RULES,
            doc="The rule for unlike pairs of per-type values: epsilon geometric; sigma "
                "arithmetic (`lorentz-berthelot`) or geometric."),
        Key("pairs", "list of tables", None,
            doc="Single pairs set apart from mixing: `[[potentials.pairs]]` tables with "
                "`types = [a, b]` and any of `epsilon`, `sigma`, `cutoff`, `r_on`."),
    )  # fmt: skip

    def __init__(
        self,
        epsilon: float | Sequence[float] = 1.0,
        sigma: float | Sequence[float] = 1.0,
        cutoff: float = 2.5,
        cutoff_mode: str = "shift",
        r_on: float | None = None,
        pairs: Mapping[tuple[int, int], Mapping[str, float]] | None = None,
        mixing: str = "lorentz-berthelot",
    ) -> None:
        if cutoff_mode not in CUTOFF_MODES:
            raise ValueError(
                f"cutoff_mode must be one of {', '.join(CUTOFF_MODES)}, got {cutoff_mode!r}"
            )
        if mixing not in MIXING_RULES:
            raise ValueError(f"mixing must be one of {', '.join(MIXING_RULES)}, got {mixing!r}")
        self.epsilon = positive_array(epsilon, "epsilon", allow_zero=True)
        self.sigma = positive_array(sigma, "sigma")
        if self.epsilon.ndim != self.sigma.ndim or (
            self.epsilon.ndim == 1 and len(self.epsilon) != len(self.sigma)
        ):
            raise ValueError(
                "epsilon and sigma must both be scalars or both have one value per type "
                f"(got {self.epsilon.size} and {self.sigma.size})"
            )
        self.default_cutoff = positive_scalar(cutoff, "cutoff")
        self.cutoff_mode = cutoff_mode
        self.r_on = None if r_on is None else positive_scalar(r_on, "r_on")
        self.mixing = mixing
        self.pairs = {}
        for key, values in (pairs or {}).items():
            ti, tj = (int(t) for t in key)
            if ti < 0 or tj < 0:
                raise ValueError(f"pair types must be non-negative, got {key}")
            unknown = set(values) - {"epsilon", "sigma", "cutoff", "r_on"}
            if unknown:
                raise ValueError(f"unknown pair parameter(s) {sorted(unknown)} for pair {key}")
            self.pairs[(min(ti, tj), max(ti, tj))] = dict(values)
        self.n_types_fixed = len(self.sigma) if self.sigma.ndim == 1 else None
        # Validates every pair (r_on < cutoff, positive values) now, not at run time.
        self.tables(self.n_types_fixed or 1 + max((max(k) for k in self.pairs), default=0))
        self.cutoff = max(
            [self.default_cutoff] + [p["cutoff"] for p in self.pairs.values() if "cutoff" in p]
        )

    @property
    def per_type_parameters(self) -> bool:
        """True with per-type epsilon and sigma or explicit ``pairs`` (``TypedParameters``)."""
        return self.n_types_fixed is not None or bool(self.pairs)

    @classmethod
    def from_config(cls, params: Mapping, type_names: Sequence[str]) -> LennardJones:
        """Build from a config table; per-type values are keyed by type name.

        Keys: ``epsilon``, ``sigma`` (a number, or a table ``{name = value}``
        covering every type), ``cutoff``, ``cutoff_mode``, ``r_on``,
        ``mixing``, and ``pairs``, a list of tables
        ``{types = [name, name], epsilon, sigma, cutoff, r_on}``.
        """
        params = dict(params)
        check_names(params, cls.CONFIG_KEYS)
        index = {name: i for i, name in enumerate(type_names)}
        for key in ("epsilon", "sigma"):
            value = params.get(key)
            if isinstance(value, Mapping):
                missing = [name for name in type_names if name not in value]
                extra = [name for name in value if name not in index]
                if missing or extra:
                    raise ValueError(
                        f"{key}: give one value per type {list(type_names)}"
                        + (f"; missing {missing}" if missing else "")
                        + (f"; unknown types {extra}" if extra else "")
                    )
                params[key] = [value[name] for name in type_names]
        pairs = {}
        for number, entry in enumerate(params.pop("pairs", None) or []):
            if not isinstance(entry, Mapping) or "types" not in entry:
                raise ValueError(f"pairs[{number}] must be a table with 'types = [a, b]'")
            entry = dict(entry)
            names = entry.pop("types")
            if not isinstance(names, list) or len(names) != 2 or any(n not in index for n in names):
                raise ValueError(
                    f"pairs[{number}].types must name two of the types {list(type_names)}, "
                    f"got {names!r}"
                )
            pairs[(index[names[0]], index[names[1]])] = entry
        for key in ("epsilon", "sigma", "cutoff", "r_on"):
            value = params.get(key)
            values = value if isinstance(value, list) else [value]
            if any(isinstance(v, bool) or not isinstance(v, int | float | None) for v in values):
                raise ValueError(f"{key}: expected a number, got {value!r}")
        return cls(**params, pairs=pairs)

    # ------------------------------------------------------------------ tables
    def pair_parameters(self, ti: int, tj: int) -> dict[str, float]:
        """Return epsilon, sigma, cutoff and r_on for the type pair (ti, tj)."""
        if self.sigma.ndim == 0:
            eps, sig = float(self.epsilon), float(self.sigma)
        else:
            n = len(self.sigma)
            if ti >= n or tj >= n:
                raise ValueError(
                    f"LennardJones has parameters for {n} types, but type {max(ti, tj)} occurs"
                )
            eps = float(np.sqrt(self.epsilon[ti] * self.epsilon[tj]))
            if self.mixing == "lorentz-berthelot":
                sig = 0.5 * float(self.sigma[ti] + self.sigma[tj])
            else:
                sig = float(np.sqrt(self.sigma[ti] * self.sigma[tj]))
        params = {"epsilon": eps, "sigma": sig, "cutoff": self.default_cutoff, "r_on": self.r_on}
        params.update(self.pairs.get((min(ti, tj), max(ti, tj)), {}))
        params["epsilon"] = float(positive_scalar(params["epsilon"], "epsilon", allow_zero=True))
        params["sigma"] = float(positive_scalar(params["sigma"], "sigma"))
        params["cutoff"] = float(positive_scalar(params["cutoff"], "cutoff"))
        if params["r_on"] is None:
            params["r_on"] = 0.66 * params["cutoff"]
        if self.cutoff_mode == "smooth" and not params["r_on"] < params["cutoff"]:
            raise ValueError(
                f"r_on ({params['r_on']:g}) must be smaller than the cutoff "
                f"({params['cutoff']:g}) for pair ({ti}, {tj})"
            )
        return params

    def tables(self, n_types: int) -> np.ndarray:
        """The kernel's parameters: a (6, n_types * n_types) table, column ti * n_types + tj.

        Rows ``C6``, ``C12`` (4 eps sigma^6, 4 eps sigma^12), ``RC2`` and ``RO2``
        (squared cutoff and switching start), ``SHIFT`` (u at the cutoff) and
        ``INV_DEN`` (1 / (rc^2 - ro^2)^3, the switching function's scale).
        """
        size = n_types * n_types
        table = np.zeros((6, size))
        c6, c12, rc2, ro2, shift, inv_den = table
        for ti in range(n_types):
            for tj in range(n_types):
                p = {k: np.float64(v) for k, v in self.pair_parameters(ti, tj).items()}
                k = ti * n_types + tj
                with np.errstate(over="ignore", under="ignore"):
                    s6 = p["sigma"] ** 6
                    c6[k] = 4.0 * p["epsilon"] * s6
                    c12[k] = 4.0 * p["epsilon"] * s6 * s6
                    rc2[k] = p["cutoff"] ** 2
                    ro2[k] = p["r_on"] ** 2
                    inv_rc6 = 1.0 / rc2[k] ** 3
                    shift[k] = c12[k] * inv_rc6 * inv_rc6 - c6[k] * inv_rc6
                    if rc2[k] > ro2[k]:
                        inv_den[k] = 1.0 / (rc2[k] - ro2[k]) ** 3
                if not np.all(np.isfinite(table[:, k])):
                    raise ValueError(
                        f"epsilon {p['epsilon']:g}, sigma {p['sigma']:g}, cutoff {p['cutoff']:g}"
                        f" (r_on {p['r_on']:g}) of type pair ({ti}, {tj}) are beyond double "
                        "precision: 4 epsilon sigma^12 and the cutoff's powers must be finite"
                    )
        return table

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

    # ----------------------------------------------------------------- compute
    def check(self, state) -> None:
        if self.n_types_fixed is not None and state.n_types > self.n_types_fixed:
            raise ValueError(
                f"LennardJones has parameters for {self.n_types_fixed} types but the system "
                f"has {state.n_types} ({', '.join(state.type_names)})"
            )

    def energy_forces(
        self, state, neighbors, per_atom: bool = False, virial: bool = True
    ) -> ForceResult:
        """Return energy, forces, virial (and per-atom energies) for ``state``.

        ``neighbors`` is a NeighborList with a radius >= ``cutoff``, or None
        for the O(N^2) all-pairs loop (small systems, tests). Over a list
        built by cells, the threaded slot-frame kernel runs (no minimum
        image, one chunk per thread); per-atom results and O(N^2) lists use
        the serial kernel over atom indices. ``virial=False`` skips the
        virial (a quarter of the pair time), leaving ``result.virial`` None.
        """
        n = state.n_atoms
        n_types = max(state.n_types, self.n_types_fixed or 1)
        table = self._cached_tables(n_types)
        mode = CUTOFF_MODES[self.cutoff_mode]
        frame = None if neighbors is None or per_atom else neighbors.frame
        if frame is not None:
            self._check_radius(neighbors)
            return self._frame_energy_forces(state, frame, n_types, table, mode, virial)
        lengths, inverse = periodic_lengths(state.box, state.pbc)
        starts, neighbor_array = self._pair_list(n, neighbors)
        forces = np.zeros((n, 3))
        total_virial = np.zeros(6)
        energies = np.zeros(n if per_atom else 0)
        virials = np.zeros((n if per_atom else 0, 6))
        tilt = periodic_tilt(state.tilt, state.pbc)
        geometry = (state.positions, state.types, lengths, inverse, tilt, starts, neighbor_array)
        energy = _lj_energy_forces(
            geometry, n_types, table, mode, forces, total_virial, energies, virials
        )
        return ForceResult(
            energy=energy,
            forces=forces,
            virial=_symmetric(total_virial) if virial or per_atom else None,
            energies=energies if per_atom else None,
            virials=virials if per_atom else None,
        )

    def _frame_energy_forces(self, state, frame, n_types, table, mode, virial: bool):
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
        forces = np.empty((n, 3))
        # One chunk stays off numba's thread pool: no wake-ups on a busy machine.
        kernel = _lj_frame_forces_threaded if chunks > 1 else _lj_frame_forces
        slots = (
            frame.order, frame.images, frame.lengths, frame.shifts, frame.starts, frame.neighbors,
            frame.codes, frame.bounds, frame.tilt,
        )  # fmt: skip
        kernel(
            state.positions, state.types, slots, n_types, table, mode, virial,
            slot_positions, slot_types, buffers, energies, virials, forces,
        )  # fmt: skip
        return ForceResult(
            energy=float(energies.sum()) if chunks > 1 else float(energies[0]),
            forces=forces,
            virial=_symmetric(virials.sum(axis=0)) if virial else None,
        )

    def hessian(self, state, neighbors) -> sp.csr_matrix:
        r"""Return the (3N, 3N) Hessian of the energy, :math:`\partial^2 U / \partial x \partial x`.

        Exact for every cutoff mode: inside the cutoff the second derivative
        of u(r) (``"none"``, ``"shift"``: the shift is a constant) or of
        S(s) u(s) (``"smooth"``); pairs beyond the cutoff contribute nothing
        (the jump of the truncated modes at the cutoff is not a derivative).
        Each pair adds a 3x3 block K to the (i, i) and (j, j) blocks and -K
        to (i, j) and (j, i), so every block row sums to zero (translation
        invariance) and the matrix is symmetric.

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

    def hessian_operator(self, state, neighbors) -> PairHessian:
        """Return the Hessian as pair blocks, to apply without assembling it.

        The same matrix as :meth:`hessian` (arguments alike), as a
        :class:`potentials.pair_hessian.PairHessian`: one 3x3 block per pair
        inside the cutoff. Its ``matvec`` costs about a force evaluation,
        which is what a Newton-Krylov solver needs.
        """
        n = state.n_atoms
        n_types = max(state.n_types, self.n_types_fixed or 1)
        table = self._cached_tables(n_types)
        frame = None if neighbors is None else neighbors.frame
        if frame is not None:
            self._check_radius(neighbors)
            return self._frame_hessian(state, frame, n_types, table)
        lengths, inverse = periodic_lengths(state.box, state.pbc)
        starts, neighbor_array = self._pair_list(n, neighbors)
        tilt = periodic_tilt(state.tilt, state.pbc)
        geometry = (state.positions, state.types, lengths, inverse, tilt, starts, neighbor_array)
        listed = len(neighbor_array)  # room for every listed pair; those inside are kept
        pair_i = np.empty(listed, dtype=np.int64)
        pair_j = np.empty(listed, dtype=np.int64)
        transverse = np.empty(listed)
        radial = np.empty(listed)
        unit = np.empty((listed, 3))
        n_pairs = _lj_pair_curvatures(
            geometry, n_types, table, CUTOFF_MODES[self.cutoff_mode],
            pair_i, pair_j, transverse, radial, unit,
        )  # fmt: skip
        return PairHessian(
            n, pair_i[:n_pairs], pair_j[:n_pairs], transverse[:n_pairs], radial[:n_pairs],
            unit[:n_pairs],
        )  # fmt: skip

    def _frame_hessian(self, state, frame, n_types, table) -> PairHessian:
        """``hessian_operator`` over a slot-frame list, in one threaded pass: each chunk
        writes the blocks of its pairs inside the cutoff from where its listed pairs
        start, so no pass counts them first; the operator takes each chunk's run as one
        of its pieces and skips the gaps the pairs beyond the cutoff leave. The Jacobi
        diagonal is summed when the solver asks for it."""
        n = state.n_atoms
        chunks = frame.n_chunks
        slot_positions = np.empty((n, 3))
        slot_types = np.empty(n, dtype=state.types.dtype)
        slots = (
            frame.order, frame.images, frame.lengths, frame.shifts, frame.starts, frame.neighbors,
            frame.codes, frame.bounds, frame.tilt,
        )  # fmt: skip
        room = int(frame.starts[-1])  # every listed pair
        # The blocks go into buffers kept from the last call when nothing uses them any
        # more (the last operator is gone): fresh arrays of tens of MB cost page faults
        # that take as long as writing them.
        held = getattr(self, "_hessian_buffers", None)
        if held is None or held[0].shape[0] < room or not _unshared(held):
            size = int(room * 1.05) + 1024
            held = (
                np.empty(size, dtype=np.int32), np.empty(size, dtype=np.int32), np.empty(size),
                np.empty(size), np.empty((size, 3)),
            )  # fmt: skip
            self._hessian_buffers = held
        written = np.zeros(chunks, dtype=np.int64)
        # One chunk stays off numba's thread pool: no wake-ups on a busy machine.
        write = _lj_frame_curvatures_threaded if chunks > 1 else _lj_frame_curvatures
        write(state.positions, state.types, slots, n_types, table,
              CUTOFF_MODES[self.cutoff_mode], slot_positions, slot_types, held,
              written)  # fmt: skip
        first = frame.starts[frame.bounds[:-1]]
        return PairHessian(n, *held, pieces=np.column_stack((first, first + written)))

    def describe(self) -> dict:
        out = {
            "type": "lj",
            "epsilon": self.epsilon.tolist(),
            "sigma": self.sigma.tolist(),
            "cutoff": self.default_cutoff,
            "cutoff_mode": self.cutoff_mode,
            "mixing": self.mixing,
        }
        if self.r_on is not None:
            out["r_on"] = self.r_on
        if self.pairs:
            out["pairs"] = {f"{i}-{j}": v for (i, j), v in self.pairs.items()}
        return out

    def _pair_list(self, n: int, neighbors):
        """Return (starts, neighbors) of the half list to loop over (all pairs for None)."""
        if neighbors is None:
            return _all_pairs(n)
        self._check_radius(neighbors)
        return neighbors.starts, neighbors.neighbors

    def _check_radius(self, neighbors) -> None:
        if neighbors.list_radius < self.cutoff:
            raise ValueError(
                f"neighbour list radius {neighbors.list_radius:g} is below the LJ cutoff "
                f"{self.cutoff:g}"
            )

    def _cached_tables(self, n_types: int):
        cache = getattr(self, "_table_cache", None)
        if cache is None or cache[0] != n_types:
            self._table_cache = (n_types, self.tables(n_types))
        return self._table_cache[1]


def _unshared(buffers) -> bool:
    """Whether nothing but ``buffers`` refers to its arrays (no view, no operator built
    on them), by CPython's reference counts: each at most that of an array held only by
    a tuple and counted the same way (interpreters differ in what the count includes)."""
    probe = (np.empty(0),)
    baseline = max(sys.getrefcount(array) for array in probe)
    return all(sys.getrefcount(buffer) <= baseline for buffer in buffers)


def _symmetric(v: np.ndarray) -> np.ndarray:
    xx, yy, zz, yz, xz, xy = v
    return np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])


def _all_pairs(n: int):
    """CSR half list of every pair, for neighbour-free evaluation."""
    counts = np.arange(n - 1, -1, -1, dtype=np.int64)
    starts = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(counts, out=starts[1:])
    neighbors = np.concatenate([np.arange(i + 1, n) for i in range(n)] or [np.zeros(0)])
    return starts, neighbors.astype(np.int32)


@njit(cache=True, inline="always", error_model="numpy")
def _lj_pair(r2, k, table, mode):
    """Return (u, f/r) of one pair at squared distance r2, type-pair column k of ``table``.

    f/r is -du/dr / r, so the force on the first atom is (f/r) d. Both are 0
    at or beyond the cutoff. ``table`` is :meth:`LennardJones.tables`; mode:
    0 truncated, 1 shifted, 2 smooth. Branch-free past the cutoff: a third
    of the listed pairs lie in the skin, and a mispredicted branch costs
    more than the arithmetic.
    """
    return _lj_terms(r2, table[RC2, k], table[C6, k], table[C12, k], table[SHIFT, k],
                     table[RO2, k], table[INV_DEN, k], mode)  # fmt: skip


@njit(cache=True, inline="always", error_model="numpy")
def _lj_terms(r2, rc2, c6, c12, shift, ro2, inv_den, mode):
    """``_lj_pair`` with the type pair's column given as numbers (hoisted out of loops)."""
    inside = 1.0 if r2 < rc2 else 0.0
    inv_r2 = 1.0 / r2
    inv_r6 = inv_r2 * inv_r2 * inv_r2
    a = c12 * inv_r6 * inv_r6
    b = c6 * inv_r6
    u = a - b
    fr = (12.0 * a - 6.0 * b) * inv_r2
    if mode == 1:
        u -= shift
    elif mode == 2:
        gap = rc2 - r2
        switching = r2 > ro2
        switch = gap * gap * (rc2 + 2.0 * r2 - 3.0 * ro2) * inv_den
        dswitch = 6.0 * gap * (ro2 - r2) * inv_den
        switch = switch if switching else 1.0
        dswitch = dswitch if switching else 0.0
        fr = switch * fr - 2.0 * dswitch * u
        u = switch * u
    return u * inside, fr * inside


# The three loops below each run with the cutoff mode a compile-time constant:
# their dispatchers call the inlined loop once per mode. A mode test inside a
# pair loop made it 2.4 times slower.


@njit(cache=True, error_model="numpy")
def _lj_frame_forces(
    positions, types, slots, n_types, table, mode, with_virial,
    frame, frame_types, buffers, energies, virials, forces,
):  # fmt: skip
    """LJ forces over a slot-frame list (``md.neighbors.SlotFrame``), chunk by chunk.

    ``slots`` is (order, images, lengths, shifts, starts, neighbors, codes,
    bounds, tilt), the fields of the SlotFrame. Gathers ``frame[p] =
    positions[order[p]] + images[p] @ h`` (h the cell matrix) and the slot types, then
    chunk c (slots ``bounds[c]`` to ``bounds[c + 1]``) adds its pairs' forces
    into its own ``buffers[c]`` (C, N, 3), its energy into ``energies[c]``
    and, if ``with_virial``, its virial (xx, yy, zz, yz, xz, xy) into
    ``virials[c]``. The chunk buffers are summed in chunk order into
    ``forces`` (N, 3, by atom), so the result is the same on every run for a
    given chunk count. A pair (p, q) is separated by frame[p] - frame[q] -
    shifts[codes[k]]: no minimum image. ``_lj_frame_forces_threaded`` runs
    the chunks on numba's threads; no two chunks write the same memory.
    """
    order, images, lengths, tilt = slots[0], slots[1], slots[2], slots[8]
    n_chunks = slots[7].shape[0] - 1
    for chunk in range(n_chunks):
        _gather_frame(
            chunk, n_chunks, positions, types, order, images, lengths, tilt, frame, frame_types
        )
    for chunk in range(n_chunks):
        _lj_frame_chunk(
            chunk, frame, frame_types, slots, n_types, table, mode, with_virial, buffers,
            energies, virials,
        )  # fmt: skip
    for chunk in range(n_chunks):
        _sum_chunk_forces(chunk, n_chunks, order, buffers, forces)


@njit(cache=True, parallel=True, error_model="numpy")
def _lj_frame_forces_threaded(
    positions, types, slots, n_types, table, mode, with_virial,
    frame, frame_types, buffers, energies, virials, forces,
):  # fmt: skip
    """``_lj_frame_forces`` with one chunk per thread (same arguments, same result)."""
    order, images, lengths, tilt = slots[0], slots[1], slots[2], slots[8]
    n_chunks = slots[7].shape[0] - 1
    for chunk in prange(n_chunks):
        _gather_frame(
            chunk, n_chunks, positions, types, order, images, lengths, tilt, frame, frame_types
        )
    for chunk in prange(n_chunks):
        _lj_frame_chunk(
            chunk, frame, frame_types, slots, n_types, table, mode, with_virial, buffers,
            energies, virials,
        )  # fmt: skip
    for chunk in prange(n_chunks):
        _sum_chunk_forces(chunk, n_chunks, order, buffers, forces)


@njit(cache=True, error_model="numpy")
def _gather_frame(
    chunk, n_chunks, positions, types, order, images, lengths, tilt, frame, frame_types
):
    """Slot positions and types of one chunk's share of the slots (images count cell vectors)."""
    n = positions.shape[0]
    xy, xz, yz = tilt[0], tilt[1], tilt[2]
    sheared = xy != 0.0 or xz != 0.0 or yz != 0.0
    for p in range(chunk * n // n_chunks, (chunk + 1) * n // n_chunks):
        atom = order[p]
        frame[p, 0] = positions[atom, 0] + lengths[0] * images[p, 0]
        frame[p, 1] = positions[atom, 1] + lengths[1] * images[p, 1]
        frame[p, 2] = positions[atom, 2] + lengths[2] * images[p, 2]
        if sheared:
            frame[p, 0] += xy * images[p, 1] + xz * images[p, 2]
            frame[p, 1] += yz * images[p, 2]
        frame_types[p] = types[atom]


@njit(cache=True, error_model="numpy")
def _sum_chunk_forces(chunk, n_chunks, order, buffers, forces):
    """Sum the chunk buffers, in chunk order, into the atoms' forces (one share of the slots)."""
    n = order.shape[0]
    for p in range(chunk * n // n_chunks, (chunk + 1) * n // n_chunks):
        atom = order[p]
        for a in range(3):
            total = buffers[0, p, a]
            for other in range(1, n_chunks):
                total += buffers[other, p, a]
            forces[atom, a] = total


#: LLVM may reorder the sums of the pair loop (energy, force on atom i, virial) into
#: vector lanes and fuse multiply-adds: that is what lets it vectorise the loop. No
#: "nnan"/"ninf": overlapping atoms must still give an infinite energy.
_VECTOR_MATH = {"reassoc", "contract", "nsz", "arcp"}


@njit(cache=True, fastmath=_VECTOR_MATH, error_model="numpy")
def _lj_frame_chunk(
    chunk, frame, frame_types, slots, n_types, table, mode, with_virial, buffers, energies,
    virials,
):  # fmt: skip
    """The pairs of one chunk of ``_lj_frame_forces``, into ``buffers[chunk]``.

    Dispatches to the loop compiled for this cutoff mode, virial or not,
    and one atom type or several (constants inside the loop). The loops are
    inlined here, so this function carries their floating-point flags.
    """
    args = (chunk, frame, frame_types, slots, n_types, table)
    out = (buffers, energies, virials)
    single = n_types == 1
    if mode == 0:
        if with_virial:
            if single:
                _lj_frame_chunk_loop(args, 0, True, True, out)
            else:
                _lj_frame_chunk_loop(args, 0, True, False, out)
        elif single:
            _lj_frame_chunk_loop(args, 0, False, True, out)
        else:
            _lj_frame_chunk_loop(args, 0, False, False, out)
    elif mode == 1:
        if with_virial:
            if single:
                _lj_frame_chunk_loop(args, 1, True, True, out)
            else:
                _lj_frame_chunk_loop(args, 1, True, False, out)
        elif single:
            _lj_frame_chunk_loop(args, 1, False, True, out)
        else:
            _lj_frame_chunk_loop(args, 1, False, False, out)
    elif with_virial:
        if single:
            _lj_frame_chunk_loop(args, 2, True, True, out)
        else:
            _lj_frame_chunk_loop(args, 2, True, False, out)
    elif single:
        _lj_frame_chunk_loop(args, 2, False, True, out)
    else:
        _lj_frame_chunk_loop(args, 2, False, False, out)


@njit(cache=True, error_model="numpy")
def _longest_row(starts, first, last):
    """Most partners of any of the slots first..last-1 (the size of per-row scratch)."""
    most = 0
    for p in range(first, last):
        most = max(most, starts[p + 1] - starts[p])
    return most


@njit(cache=True, error_model="numpy")
def _gather_partners(frame, frame_types, shifts, partners, partner_codes, row, table, mode,
                     single, gx, gy, gz, params):  # fmt: skip
    """Partner positions (with their image shifts) and, with several types, their
    table columns, contiguous for a vectorised pair loop.

    Slices from 0 and unsigned partner slots: indices LLVM knows are not
    negative, so no wrap-around code.
    """
    for k in range(partners.shape[0]):
        q = np.uint32(partners[k])
        code = partner_codes[k]
        gx[k] = frame[q, 0] + shifts[code, 0]
        gy[k] = frame[q, 1] + shifts[code, 1]
        gz[k] = frame[q, 2] + shifts[code, 2]
        if not single:  # contiguous per-partner parameters: the pair loop reads no table
            column = row + frame_types[q]
            params[RC2, k] = table[RC2, column]
            params[C6, k] = table[C6, column]
            params[C12, k] = table[C12, column]
            if mode == 1:
                params[SHIFT, k] = table[SHIFT, column]
            elif mode == 2:
                params[RO2, k] = table[RO2, column]
                params[INV_DEN, k] = table[INV_DEN, column]


@njit(cache=True, inline="always", fastmath=_VECTOR_MATH, error_model="numpy")
def _lj_frame_chunk_loop(args, mode, with_virial, single, out):
    """The loop of ``_lj_frame_chunk`` (inlined there with its flags fixed).

    Per slot, three passes over its partners: gather their positions (with
    the image shift) and, with several types, their pair parameters into
    contiguous scratch, compute
    the pair terms in a branch-free loop the compiler vectorises (masks for
    the cutoff), and scatter the partners' forces into the chunk's buffer.
    The scattered writes, which no CPU vectorises, stay out of the pair loop.
    """
    chunk, frame, frame_types, slots, n_types, table = args
    buffers, energies, virials = out
    shifts, starts, neighbors, codes, bounds = slots[3], slots[4], slots[5], slots[6], slots[7]
    buffer = buffers[chunk]
    for p in range(frame.shape[0]):
        buffer[p, 0] = 0.0
        buffer[p, 1] = 0.0
        buffer[p, 2] = 0.0
    most = _longest_row(starts, bounds[chunk], bounds[chunk + 1])
    gx = np.empty(most)
    gy = np.empty(most)
    gz = np.empty(most)
    params = np.zeros((6, most if not single else 0))  # each partner's table column
    sfx = np.empty(most)
    sfy = np.empty(most)
    sfz = np.empty(most)
    rc2, c6, c12 = table[RC2, 0], table[C6, 0], table[C12, 0]  # one atom type: constants
    shift, ro2, inv_den = table[SHIFT, 0], table[RO2, 0], table[INV_DEN, 0]
    energy = 0.0
    wxx = wyy = wzz = wyz = wxz = wxy = 0.0
    for p in range(bounds[chunk], bounds[chunk + 1]):
        xi = frame[p, 0]
        yi = frame[p, 1]
        zi = frame[p, 2]
        row = frame_types[p] * n_types
        partners = neighbors[starts[p] : starts[p + 1]]
        m = partners.shape[0]
        _gather_partners(frame, frame_types, shifts, partners, codes[starts[p] : starts[p + 1]],
                         row, table, mode, single, gx, gy, gz, params)  # fmt: skip
        for k in range(m):
            dx = xi - gx[k]
            dy = yi - gy[k]
            dz = zi - gz[k]
            r2 = dx * dx + dy * dy + dz * dz
            if single:
                u, fr = _lj_terms(r2, rc2, c6, c12, shift, ro2, inv_den, mode)
            else:
                u, fr = _lj_pair(r2, k, params, mode)
            energy += u
            fx = fr * dx
            fy = fr * dy
            fz = fr * dz
            sfx[k] = fx
            sfy[k] = fy
            sfz[k] = fz
        if with_virial:  # a loop of its own: the pair loop above is the same in every
            for k in range(m):  # variant, so are its forces' bits (on any CPU's vector width)
                dx = xi - gx[k]
                dy = yi - gy[k]
                dz = zi - gz[k]
                wxx += sfx[k] * dx
                wyy += sfy[k] * dy
                wzz += sfz[k] * dz
                wyz += sfz[k] * dy
                wxz += sfz[k] * dx
                wxy += sfy[k] * dx
        # Atom p's force summed apart from the pair loop, as the virial is:
        # this loop is the same in every variant, so are its bits.
        fxi = 0.0
        fyi = 0.0
        fzi = 0.0
        for k in range(m):
            fxi += sfx[k]
            fyi += sfy[k]
            fzi += sfz[k]
        for k in range(m):
            q = np.uint32(partners[k])
            buffer[q, 0] -= sfx[k]
            buffer[q, 1] -= sfy[k]
            buffer[q, 2] -= sfz[k]
        buffer[p, 0] += fxi
        buffer[p, 1] += fyi
        buffer[p, 2] += fzi
    energies[chunk] = energy
    virials[chunk, 0] = wxx
    virials[chunk, 1] = wyy
    virials[chunk, 2] = wzz
    virials[chunk, 3] = wyz
    virials[chunk, 4] = wxz
    virials[chunk, 5] = wxy


@njit(cache=True, error_model="numpy")
def _lj_energy_forces(geometry, n_types, table, mode, forces, virial, energies, virials):
    """Add LJ forces to ``forces`` (zeroed by caller) and return the energy.

    ``geometry`` is (positions, types, lengths, inverse, tilt, starts, neighbors):
    a half list over atom indices in CSR form, minimum image per pair.
    ``table`` as in ``_lj_pair``. Writes ``virial`` as (xx, yy, zz, yz, xz,
    xy) and, when ``energies`` has length N, the per-atom energies and, into
    ``virials`` (N, 6, zeroed), the per-atom virials (half of each pair to
    each atom).
    """
    out = (forces, virial, energies, virials)
    if mode == 0:
        return _lj_energy_forces_loop(geometry, n_types, table, 0, out)
    if mode == 1:
        return _lj_energy_forces_loop(geometry, n_types, table, 1, out)
    return _lj_energy_forces_loop(geometry, n_types, table, 2, out)


@njit(cache=True, inline="always", error_model="numpy")
def _lj_energy_forces_loop(geometry, n_types, table, mode, out):
    """The loop of ``_lj_energy_forces`` for one cutoff mode (inlined there with mode fixed)."""
    positions, types, lengths, inverse, tilt, starts, neighbors = geometry
    forces, virial, energies, virials = out
    n = positions.shape[0]
    per_atom = energies.shape[0] == n
    energy = 0.0
    wxx = wyy = wzz = wyz = wxz = wxy = 0.0
    for i in range(n):
        xi = positions[i, 0]
        yi = positions[i, 1]
        zi = positions[i, 2]
        row = types[i] * n_types
        fxi = 0.0
        fyi = 0.0
        fzi = 0.0
        for p in range(starts[i], starts[i + 1]):
            j = neighbors[p]
            dx, dy, dz = min_image(
                xi - positions[j, 0],
                yi - positions[j, 1],
                zi - positions[j, 2],
                lengths,
                inverse,
                tilt,
            )
            r2 = dx * dx + dy * dy + dz * dz
            u, fr = _lj_pair(r2, row + types[j], table, mode)
            energy += u
            fx = fr * dx
            fy = fr * dy
            fz = fr * dz
            fxi += fx
            fyi += fy
            fzi += fz
            forces[j, 0] -= fx
            forces[j, 1] -= fy
            forces[j, 2] -= fz
            wxx += fx * dx
            wyy += fy * dy
            wzz += fz * dz
            wyz += fz * dy
            wxz += fz * dx
            wxy += fy * dx
            if per_atom:
                energies[i] += 0.5 * u
                energies[j] += 0.5 * u
                _add_half_pair_virial(virials, i, j, fx, fy, fz, dx, dy, dz)
        forces[i, 0] += fxi
        forces[i, 1] += fyi
        forces[i, 2] += fzi
    virial[0] = wxx
    virial[1] = wyy
    virial[2] = wzz
    virial[3] = wyz
    virial[4] = wxz
    virial[5] = wxy
    return energy


@njit(cache=True, inline="always", error_model="numpy")
def _lj_curvature_terms(r2, rc2, c6, c12, ro2, inv_den, mode):
    """Return (inside, t, r, 1/|d|) of one pair at squared distance r2.

    With g(s) the pair energy as a function of s = r^2, the pair block is
    K = 2 g'(s) I + 4 g''(s) d d^T: the transverse eigenvalue t = 2 g'(s) =
    u'(r)/r, the radial one r = 2 g'(s) + 4 g''(s) s = u''(r), along d/|d|.
    u is unshifted (a constant shift has no second derivative). Branch-free
    apart from the smooth mode's switch.
    """
    inside = r2 < rc2
    inv_r2 = 1.0 / r2
    inv_r6 = inv_r2 * inv_r2 * inv_r2
    a = c12 * inv_r6 * inv_r6
    b = c6 * inv_r6
    # u = a - b as a function of s = r^2, and its first two derivatives.
    g = a - b
    g1 = (3.0 * b - 6.0 * a) * inv_r2
    g2 = (42.0 * a - 12.0 * b) * inv_r2 * inv_r2
    if mode == 2:
        gap = rc2 - r2
        switching = r2 > ro2 and inside
        switch = gap * gap * (rc2 + 2.0 * r2 - 3.0 * ro2) * inv_den
        dswitch = 6.0 * gap * (ro2 - r2) * inv_den
        d2switch = 6.0 * (2.0 * r2 - ro2 - rc2) * inv_den
        g2s = d2switch * g + 2.0 * dswitch * g1 + switch * g2
        g1s = dswitch * g + switch * g1
        g2 = g2s if switching else g2
        g1 = g1s if switching else g1
    return inside, 2.0 * g1, 2.0 * g1 + 4.0 * g2 * r2, np.sqrt(inv_r2)


@njit(cache=True, error_model="numpy")
def _lj_pair_curvatures(
    geometry, n_types, table, mode, pair_i, pair_j, transverse, radial, unit
):  # fmt: skip
    """Write the Hessian block of every pair inside its cutoff; return how many.

    Arguments as in ``_lj_energy_forces``; outputs as in ``_lj_pair_curvatures_loop``.
    """
    out = (pair_i, pair_j, transverse, radial, unit)
    if mode == 0:
        return _lj_pair_curvatures_loop(geometry, n_types, table, 0, out)
    if mode == 1:
        return _lj_pair_curvatures_loop(geometry, n_types, table, 1, out)
    return _lj_pair_curvatures_loop(geometry, n_types, table, 2, out)


@njit(cache=True, inline="always", error_model="numpy")
def _lj_pair_curvatures_loop(geometry, n_types, table, mode, out):
    """Write the Hessian block of every pair inside its cutoff, as its eigenvalues and axis.

    With g(s) the pair energy as a function of s = r^2 and d = x_i - x_j
    (minimum image), the pair block is K = 2 g'(s) I + 4 g''(s) d d^T: the
    transverse eigenvalue is 2 g'(s) = u'(r)/r, the radial one
    2 g'(s) + 4 g''(s) s = u''(r), along d/r. Written per pair, in list
    order, into ``pair_i``, ``pair_j``, ``transverse``, ``radial`` (P,) and
    ``unit`` (room for every listed pair; ``out`` holds the five); returns
    P, the number inside. u is unshifted (a constant shift has no second
    derivative).
    """
    positions, types, lengths, inverse, tilt, starts, neighbors = geometry
    pair_i, pair_j, transverse, radial, unit = out
    n_pairs = 0
    for i in range(positions.shape[0]):
        row = types[i] * n_types
        for p in range(starts[i], starts[i + 1]):
            j = neighbors[p]
            dx, dy, dz = separation(positions, i, j, lengths, inverse, tilt)
            r2 = dx * dx + dy * dy + dz * dz
            k = row + types[j]
            # Written branch-free: every listed pair goes to slot n_pairs, which
            # only advances for pairs inside the cutoff (a third lie in the skin).
            inside, t, r, inv_r = _lj_curvature_terms(
                r2, table[RC2, k], table[C6, k], table[C12, k], table[RO2, k],
                table[INV_DEN, k], mode,
            )  # fmt: skip
            pair_i[n_pairs] = i
            pair_j[n_pairs] = j
            transverse[n_pairs] = t
            radial[n_pairs] = r
            unit[n_pairs, 0] = dx * inv_r
            unit[n_pairs, 1] = dy * inv_r
            unit[n_pairs, 2] = dz * inv_r
            n_pairs += inside
    return n_pairs


# ------------------------------------------------------- curvatures in the slot frame
@njit(cache=True, error_model="numpy")
def _lj_frame_curvatures(positions, types, slots, n_types, table, mode, frame, frame_types,
                         out, written):  # fmt: skip
    """Gather the slot frame, then write the pair blocks of every pair inside its cutoff,
    chunk by chunk.

    Chunk c writes its pairs in list order into ``out`` (``pair_i``,
    ``pair_j`` as atom indices, ``transverse``, ``radial``, ``unit``; see
    ``_lj_curvature_terms``) from the index where its listed pairs start,
    ``starts[bounds[c]]``, and sets ``written[c]`` to their number: no two
    chunks write the same memory. ``_lj_frame_curvatures_threaded`` runs the
    chunks on numba's threads.
    """
    order, images, lengths, tilt = slots[0], slots[1], slots[2], slots[8]
    n_chunks = slots[7].shape[0] - 1
    for chunk in range(n_chunks):
        _gather_frame(
            chunk, n_chunks, positions, types, order, images, lengths, tilt, frame, frame_types
        )
    for chunk in range(n_chunks):
        written[chunk] = _lj_frame_curvature_chunk(chunk, frame, frame_types, slots, n_types,
                                                   table, mode, out)  # fmt: skip


@njit(cache=True, parallel=True, error_model="numpy")
def _lj_frame_curvatures_threaded(positions, types, slots, n_types, table, mode, frame,
                                  frame_types, out, written):  # fmt: skip
    """``_lj_frame_curvatures`` with one chunk per thread (same arguments, same result)."""
    order, images, lengths, tilt = slots[0], slots[1], slots[2], slots[8]
    n_chunks = slots[7].shape[0] - 1
    for chunk in prange(n_chunks):
        _gather_frame(
            chunk, n_chunks, positions, types, order, images, lengths, tilt, frame, frame_types
        )
    for chunk in prange(n_chunks):
        written[chunk] = _lj_frame_curvature_chunk(chunk, frame, frame_types, slots, n_types,
                                                   table, mode, out)  # fmt: skip


@njit(cache=True, fastmath=_VECTOR_MATH, error_model="numpy")
def _lj_frame_curvature_chunk(chunk, frame, frame_types, slots, n_types, table, mode, out):
    """One chunk of ``_lj_frame_curvatures``, with the loop compiled per mode and type count;
    returns the number of the chunk's pairs inside."""
    args = (chunk, frame, frame_types, slots, n_types, table)
    single = n_types == 1
    if mode == 0:
        if single:
            return _lj_frame_curvature_loop(args, 0, True, out)
        return _lj_frame_curvature_loop(args, 0, False, out)
    if mode == 1:
        if single:
            return _lj_frame_curvature_loop(args, 1, True, out)
        return _lj_frame_curvature_loop(args, 1, False, out)
    if single:
        return _lj_frame_curvature_loop(args, 2, True, out)
    return _lj_frame_curvature_loop(args, 2, False, out)


@njit(cache=True, inline="always", fastmath=_VECTOR_MATH, error_model="numpy")
def _lj_frame_curvature_loop(args, mode, single, out):
    """The loop of ``_lj_frame_curvature_chunk``: per slot, gather the partners, compute
    every pair's block in a loop the compiler vectorises, then keep those inside; returns
    how many were inside."""
    chunk, frame, frame_types, slots, n_types, table = args
    pair_i, pair_j, transverse, radial, unit = out
    order, shifts, starts, neighbors, codes, bounds = (
        slots[0], slots[3], slots[4], slots[5], slots[6], slots[7],
    )  # fmt: skip
    most = _longest_row(starts, bounds[chunk], bounds[chunk + 1])
    gx = np.empty(most)
    gy = np.empty(most)
    gz = np.empty(most)
    params = np.zeros((6, most if not single else 0))
    flags = np.empty(most, dtype=np.uint8)
    st = np.empty(most)
    sr = np.empty(most)
    ux = np.empty(most)
    uy = np.empty(most)
    uz = np.empty(most)
    rc2, c6, c12 = table[RC2, 0], table[C6, 0], table[C12, 0]  # one atom type: constants
    ro2, inv_den = table[RO2, 0], table[INV_DEN, 0]
    start = starts[bounds[chunk]]
    index = start
    unit_flat = unit.reshape(-1)
    one, two, three = np.uint64(1), np.uint64(2), np.uint64(3)
    for p in range(bounds[chunk], bounds[chunk + 1]):
        xi = frame[p, 0]
        yi = frame[p, 1]
        zi = frame[p, 2]
        row = frame_types[p] * n_types
        partners = neighbors[starts[p] : starts[p + 1]]
        m = partners.shape[0]
        _gather_partners(frame, frame_types, shifts, partners, codes[starts[p] : starts[p + 1]],
                         row, table, mode, single, gx, gy, gz, params)  # fmt: skip
        for k in range(m):
            dx = xi - gx[k]
            dy = yi - gy[k]
            dz = zi - gz[k]
            r2 = dx * dx + dy * dy + dz * dz
            if single:
                inside, t, r, inv_r = _lj_curvature_terms(r2, rc2, c6, c12, ro2, inv_den, mode)
            else:
                inside, t, r, inv_r = _lj_curvature_terms(
                    r2, params[RC2, k], params[C6, k], params[C12, k], params[RO2, k],
                    params[INV_DEN, k], mode,
                )  # fmt: skip
            flags[k] = inside
            st[k] = t
            sr[k] = r
            ux[k] = dx * inv_r
            uy[k] = dy * inv_r
            uz[k] = dz * inv_r
        atom = order[p]
        for k in range(m):
            # Every pair is written at ``index``, which advances only past those inside:
            # it stays below the listed pairs so far, within the chunk's room. The
            # stores are non-temporal: tens of MB that would otherwise be read into the
            # cache line by line before being overwritten (the pass took 3.6 ms, 2.85
            # with these, on the 32000-atom melt at 2 threads). Unsigned indices and
            # the flat unit vectors keep the address arithmetic short.
            at = np.uint64(index)
            stream_store(pair_i, at, atom)
            stream_store(pair_j, at, order[np.uint32(partners[k])])
            stream_store(transverse, at, st[k])
            stream_store(radial, at, sr[k])
            stream_store(unit_flat, three * at, ux[k])
            stream_store(unit_flat, three * at + one, uy[k])
            stream_store(unit_flat, three * at + two, uz[k])
            index += flags[k]
    store_fence()  # the blocks are in memory before anything reads them
    return index - start
