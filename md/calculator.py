"""An ASE calculator backed by the engine: :class:`MDCalculator`.

ASE drives (optimisers, its integrators, cell filters); the engine evaluates
energy, forces and stress through a :class:`~md.forcefield.ForceField` that
lives as long as the calculator, so its neighbour list and result cache carry
over from one call to the next. ASE's units (eV, Angstrom, amu) are the
engine's metal units: nothing is converted.

Conventions, as in ASE (``ase.calculators.lj.LennardJones`` in particular):

- ``stress`` is the Voigt 6-vector (xx, yy, zz, yz, xz, xy) of
  ``-W / V`` [eV/Angstrom^3], where ``W`` is the engine's pair virial
  (sum over pairs of r_ij F_ij, positive for repulsion) and ``V`` the cell
  volume: positive when the system pulls inwards (tensile), negative under
  compression, and equal to ``(1/V) dE/d(strain)``.
- ``stresses`` are per-atom Voigt 6-vectors (N, 6), each pair's term split
  half and half between its atoms and divided by the whole cell's volume, so
  they sum to ``stress``.
- ``energies`` split each pair's energy half and half; they sum to ``energy``.
- Stress and per-atom stresses exist only when the cell has a volume (three
  independent vectors), whatever the ``pbc`` flags; otherwise asking for
  them raises ``PropertyNotImplementedError``, as for ASE's own LennardJones.
- Any cell goes in with any ``pbc``, triclinic and rotated ones included:
  the engine works in the restricted frame of :func:`md.box.restricted_cell`
  (a along x, b in the xy plane), built from the periodic cell vectors only
  when some axes are open (the vectors of open axes translate nothing), and
  forces, stress and per-atom stresses are rotated back into the frame of
  ``atoms.cell``. No atoms at all give zero energy and empty forces.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from ase.calculators.calculator import (
    Calculator,
    PropertyNotImplementedError,
    all_changes,
)
from ase.stress import full_3x3_to_voigt_6_stress
from numba import njit
from numpy.typing import NDArray

from md.box import TILT_AXES, cell_matrix, perpendicular_widths, reduced_tilt, restricted_cell
from md.errors import PluginError
from md.forcefield import ForceField
from md.state import State, types_from_ase
from potentials import potential_class
from potentials.base import Potential, TypedParameters

#: Internal atom count from which ``sort_atoms="auto"`` orders atoms spatially.
_SORT_FROM = 8192


class MDCalculator(Calculator):
    """ASE calculator evaluating the engine's potentials.

    Parameters
    ----------
    potentials : sequence of Potential or mapping
        Engine potentials, e.g. ``[LennardJones(epsilon=0.0104, sigma=3.40,
        cutoff=8.5)]``, or config-style tables whose per-type values are
        keyed by chemical symbol, e.g. ``{"type": "lj", "epsilon": {"Ar":
        0.0104, "Kr": 0.0140}, "sigma": {"Ar": 3.40, "Kr": 3.65}, "cutoff":
        9.0}`` (built through ``potentials.potential_class(type).from_config``:
        a built-in style or a plug-in, as in a config; the keys also give
        ``type_names`` when it is not passed).
    type_names : sequence of str, optional
        Name of each type index, in the order of per-type parameters. With
        ``types_from="numbers"`` these are chemical symbols and an atom's
        type is the index of its symbol; without them types are numbered by
        increasing atomic number among the atoms present, which is only
        allowed when no potential has per-type parameters.
    types_from : {"numbers", "tags"}
        Take each atom's type from its atomic number or from its tag
        (``atoms.set_tags``), for example to give one element two types.
    skin : float
        Neighbour-list skin [Angstrom]: the list is rebuilt when an atom has
        moved more than ``skin / 2`` since the last build, or when the
        number of atoms, their types, the cell or ``pbc`` changed. The
        default 0.5 suits argon-like liquids and solids under ASE's
        integrators (benchmarks/ase_calculator.py).
    precision : {"double", "mixed"}
        ``"mixed"`` runs the pair terms of the pair-kernel frame in float32
        (positions, separations' squares taken in double, and every sum kept
        in double), as ``[run] precision = "mixed"`` does: forces agree with
        double ones to float32 round-off (about 1e-7 relative). Bonded terms
        and the per-atom stresses stay double.
    sort_atoms : bool or "auto"
        Hold the atoms internally in spatial order (re-sorted whenever the
        neighbour list is rebuilt), which keeps each atom's neighbours close
        in memory: about a third faster at 32000 atoms, no gain when the
        system fits in cache. ``"auto"``: from 8192 (internal) atoms on.
        Results differ only by summation order (round-off). Never done with
        bonded potentials (no cutoff), whose terms name atoms by index.
    **kwargs
        Passed on to :class:`ase.calculators.calculator.Calculator`.

    Attributes
    ----------
    forcefield : ForceField
        The engine's force field; ``forcefield.n_evaluations`` counts the
        evaluations, ``forcefield.neighbor_list.n_builds`` the list builds.

    Notes
    -----
    One evaluation fills energy, free energy, forces and stress, so asking
    for all of them at the same positions costs one engine call. Per-atom
    energies and stresses cost extra work and are computed when asked for.

    Any cell is accepted, so ASE's cell filters (``FrechetCellFilter``,
    ``UnitCellFilter``) relax all six strain components. A triclinic cell is
    rotated into the engine's frame (see the module notes) and its tilt
    factors reduced to the shortest equivalent ones (the same lattice).
    Along open axes the cell may have zero length or any direction. A cell narrower than the
    minimum image allows (an orthorhombic edge shorter than twice the cutoff,
    or a tilted cell narrower than twice the cutoff plus skin) is handled by
    evaluating an internal supercell, replicated along the narrow axes; energy
    and stress are then per original cell, forces and per-atom values those
    of the first copy (not with bonded potentials, whose terms name atoms by
    index: those need a large cell).

    .. note::
       Hand-written where a library (or the engine) could do it: the
       internal supercell of small cells is tiled with numpy into a reused
       array rather than with ``ase.Atoms.repeat`` (which builds a new Atoms
       object on every call); the positions-only test in :meth:`check_state`
       repeats, cheaper, what ASE's ``compare_atoms`` does; the spatial
       order is a numpy ``lexsort`` of cell indices, although the engine's
       neighbour list bins atoms by cell itself and could hand that order
       out; and the per-atom virial of Lennard-Jones terms is a kernel here
       that repeats the pair expression of ``potentials/lennard_jones.py``
       (``ForceResult`` carries no per-atom virial yet).

    Examples
    --------
    >>> from ase.build import bulk
    >>> from potentials import LennardJones
    >>> atoms = bulk("Ar", "fcc", a=5.26, cubic=True).repeat(4)
    >>> atoms.calc = MDCalculator([LennardJones(epsilon=0.0104, sigma=3.40, cutoff=8.5)])
    >>> round(atoms.get_potential_energy() / len(atoms), 4)
    -0.0776
    """

    implemented_properties = ["energy", "free_energy", "energies", "forces", "stress", "stresses"]
    nolabel = True

    def __init__(
        self,
        potentials: Sequence,
        type_names: Sequence[str] | None = None,
        types_from: str = "numbers",
        skin: float = 0.5,
        sort_atoms: bool | str = "auto",
        precision: str = "double",
        **kwargs,
    ) -> None:
        super().__init__(**kwargs)
        if types_from not in ("numbers", "tags"):
            raise ValueError(f"types_from must be 'numbers' or 'tags', got {types_from!r}")
        if sort_atoms not in (True, False, "auto"):
            raise ValueError(f"sort_atoms must be True, False or 'auto', got {sort_atoms!r}")
        self.types_from = types_from
        self.sort_atoms = sort_atoms
        self.potentials, self.type_names = _build_potentials(potentials, type_names)
        if self.type_names is None and types_from == "numbers":
            per_type = [
                type(p).__name__
                for p in self.potentials
                if isinstance(p, TypedParameters) and p.per_type_parameters
            ]
            if per_type:
                raise ValueError(
                    f"{', '.join(per_type)} has per-type parameters, so MDCalculator needs "
                    "type_names (the chemical symbol of each type, in parameter order), "
                    "or types_from='tags'"
                )
        self.forcefield = ForceField(self.potentials, skin=skin, precision=precision)
        # Bonded terms name atoms by index: no reordering, no internal supercell.
        self._indexed = [type(p).__name__ for p in self.potentials if p.cutoff is None]
        self._state: State | None = None
        self._n_atoms = -1
        self._types: NDArray[np.int32] | None = None
        self._names: tuple[str, ...] = ()
        self._replicas = np.ones(3, dtype=np.int64)
        self._shifts = np.zeros((1, 3))
        self._edges = np.zeros(3)
        self._tilt = np.zeros(3)
        self._volume = 0.0
        self._rotation: NDArray[np.float64] | None = None  # None: the identity
        self._cell = np.zeros((3, 3))
        self._order: NDArray[np.int64] | None = None
        self._sorting = False
        self._asked = None  # the atoms of the last check_state, until the next calculate
        # The atoms (self.atoms, the held copy) whose cell, pbc and types the State was last
        # brought up to, by a _sync that went through; None during and after a failed one
        self._synced = None
        # (held copy, _comparable of it): get_property's side of the comparison, kept
        self._signed: tuple | None = None

    # ----------------------------------------------------------------- ASE API
    def check_state(self, atoms, tol: float = 1e-15) -> list[str]:
        """ASE's comparison, plus ``"tags"`` when types come from tags and they changed.

        When nothing but positions can have changed (the case in MD and
        relaxations), only positions are compared, with ASE's tolerance but
        without the cost of ASE's general comparison, which is a sizeable
        part of a small system's evaluation.
        """
        old = self.atoms
        self._asked = atoms  # see calculate: the copy ASE's get_property makes next
        if old is not None and _identical(old, atoms, but="positions"):
            # ASE's test for positions (allclose with atol=tol, rtol=0), done cheaper.
            held, now = old.arrays["positions"], atoms.arrays["positions"]
            same = _same_bytes(held, now) or bool((np.abs(held - now) <= tol).all())
            changes = [] if same else ["positions"]
        else:
            changes = super().check_state(atoms, tol)
        if self.types_from == "tags" and self.atoms is not None and "tags" not in changes:
            if len(atoms) != len(self.atoms) or not np.array_equal(
                atoms.get_tags(), self.atoms.get_tags()
            ):
                changes.append("tags")
        return changes

    def get_property(self, name, atoms=None, allow_calculation=True):
        """ASE's ``get_property``, with a shorter way for the common call: atoms whose
        positions alone may have changed since the last evaluation (MD, relaxations).

        ASE's ``calculate`` copies ``atoms`` into ``self.atoms`` at each evaluation (an
        ``Atoms.copy``, about 10 us); here, when everything ASE compares but the
        positions is bit for bit the held copy's, the new positions are copied into
        the held copy instead, which so stays a copy of ``atoms`` as ASE's would be
        (the same object from call to call). Anything else (another cell, numbers,
        charges, tags as types, no held copy) takes ASE's way.
        """
        held = self.atoms
        if (
            atoms is None
            or held is None
            or held is atoms
            or self.types_from == "tags"
            or name not in self.implemented_properties
        ):
            return super().get_property(name, atoms, allow_calculation)
        signed = self._signed
        if signed is None or signed[0] is not held:  # the held copy's side, made once
            signed = self._signed = (held, _comparable(held))
        if _comparable(atoms) != signed[1]:  # _identical(held, atoms, but="positions")
            return super().get_property(name, atoms, allow_calculation)
        positions, now = held.arrays["positions"], atoms.arrays["positions"]
        # ASE's test for positions (allclose with atol=1e-15, rtol=0), as check_state's, in
        # one compiled pass that stops at the first coordinate apart (numpy's four passes
        # and two temporaries cost several microseconds on a small cell)
        if _apart(positions.reshape(-1), now.reshape(-1), 1e-15):
            self.results = {}
            np.copyto(positions, now)
            changes = ["positions"]
        else:
            changes = []
        if name not in self.results:
            if not allow_calculation:
                return None
            if self._synced is held:  # the State holds it but for the positions: only those
                self._fill(self._sync_positions(held), [name])
            else:
                self.calculate(None, [name], changes)
        if name not in self.results:
            raise PropertyNotImplementedError(f"{name} not present in this calculation")
        result = self.results[name]
        return result.copy() if isinstance(result, np.ndarray) else result

    def calculate(self, atoms=None, properties=("energy",), system_changes=all_changes) -> None:
        """Evaluate the potentials for ``atoms`` and fill ``self.results``.

        Keeps a copy of ``atoms`` in ``self.atoms``, as ASE's ``Calculator.calculate``
        does (which is not called: it would copy them a second time, 15 us on 256
        atoms, after ``get_property`` has just copied them, and it makes the calculator's
        directory, which this one, writing no files, does not use). The copy
        ``get_property`` made is kept when this call follows its ``check_state`` of the
        same atoms and the copy equals them in everything ASE compares.
        """
        if atoms is not None:
            held = self.atoms
            fresh = (
                held is not None
                and held is not atoms
                and self._asked is atoms
                and self.use_cache
                and _identical(held, atoms)
            )
            if not fresh:
                self.atoms = atoms.copy()
        self._asked = None
        self._fill(self._sync(self.atoms, system_changes), properties)

    def _fill(self, state: State, properties) -> None:
        """Evaluate the force field on the synced ``state`` and fill ``self.results``."""
        per_atom = "energies" in properties or "stresses" in properties
        # The virial costs a quarter of the pair time: only when a stress is asked for.
        with_stress = "stress" in properties or "stresses" in properties
        result = self.forcefield.compute(state, per_atom=per_atom, virial=with_stress)
        copies = len(self._shifts)
        energy = result.energy / copies if copies > 1 else result.energy
        self.results["energy"] = energy
        self.results["free_energy"] = energy
        rotation = self._rotation
        forces = self._originals(result.forces)
        self.results["forces"] = forces if rotation is None else forces @ rotation.T
        volume = self._volume
        if volume > 0 and result.virial is not None:
            stress = -result.virial / (volume * copies)
            if rotation is not None:
                stress = rotation @ stress @ rotation.T
            self.results["stress"] = full_3x3_to_voigt_6_stress(stress)
        if result.energies is not None:
            self.results["energies"] = self._originals(result.energies)
        if "stresses" in properties and volume > 0:
            if result.virials is None:
                names = ", ".join(type(p).__name__ for p in self.potentials)
                raise PropertyNotImplementedError(
                    f"per-atom stresses need per-atom virials, which not every potential of "
                    f"{names} provides"
                )
            stresses = -self._originals(result.virials) / volume
            if rotation is not None:
                stresses = _rotate_voigt(stresses, rotation)
            self.results["stresses"] = stresses

    def todict(self) -> dict:
        """Plain-data description (ASE writes it into trajectories)."""
        return {
            "potentials": [p.describe() for p in self.potentials],
            "type_names": None if self.type_names is None else list(self.type_names),
            "types_from": self.types_from,
            "skin": self.forcefield.neighbor_list.skin if self.forcefield.neighbor_list else None,
        }

    # --------------------------------------------------------------- internals
    def _sync(self, atoms, system_changes) -> State:
        """Bring the internal State (a supercell for small cells) up to ``atoms``."""
        self._synced = None  # until this call is through
        state = self._state
        n = len(atoms)
        if (
            state is not None
            and n == self._n_atoms
            and not {"numbers", "tags"} & set(system_changes)
            and _same_bytes(atoms.cell.array, self._cell)
            and _same_bytes(np.asarray(atoms.pbc, dtype=bool), state.pbc)
        ):  # only positions may have changed (equal values in other bits: the full path)
            return self._sync_positions(atoms)
        state = self._sync_all(atoms, system_changes)
        self._synced = atoms
        return state

    def _sync_positions(self, atoms) -> State:
        """The State's positions from ``atoms``, whose cell, pbc and types it holds."""
        state = self._state
        self._synced = None
        if self._order is None and self._rotation is None:
            if len(self._shifts) == 1:
                np.copyto(state.positions, atoms.positions)
            else:  # the copies written straight into the State, in one compiled pass
                # (numpy's broadcast sum runs its inner loop over three coordinates: 7 us
                # at 864 atoms)
                _tile_into(atoms.positions, self._shifts, state.positions)
            self._synced = atoms
            return state
        positions = self._supercell_positions(atoms)
        if self._order is None:
            state.positions[:] = positions
        else:
            np.take(positions, self._order, axis=0, out=state.positions)
        if self._sorting and self.forcefield.neighbor_list.needs_rebuild(state):
            self._sort(positions)  # the list is rebuilt now anyway
        self._synced = atoms
        return state

    def _sync_all(self, atoms, system_changes) -> State:
        """:meth:`_sync` where more than the positions may have changed."""
        state = self._state
        n = len(atoms)
        self._cell = atoms.cell.array.copy()
        pbc = np.array(atoms.pbc, dtype=bool)
        edges, tilt, rotation = _engine_frame(self._cell, pbc)
        self._rotation = None if np.array_equal(rotation, np.eye(3)) else rotation
        tilt = reduced_tilt(edges, tilt, pbc)
        # ASE's calculators give a stress when the cell has a volume, whatever the pbc.
        self._volume = float(np.prod(edges)) if pbc.all() else _volume(self._cell)
        rebuild = state is None or n != self._n_atoms
        if rebuild or {"numbers", "tags"} & set(system_changes):
            types, names = types_from_ase(
                atoms.numbers, atoms.get_tags(), self.types_from, self.type_names
            )
            if not rebuild and (
                names != self._state.type_names or not np.array_equal(types, self._types)
            ):
                rebuild = True
            self._types, self._names = types, names
        replicas = _replicas(edges, tilt, pbc, self.forcefield)
        if self._indexed and np.any(replicas > 1):
            axis = int(np.argmax(replicas > 1))
            width = perpendicular_widths(edges, tilt)[axis]
            raise ValueError(
                f"the cell width along {'xyz'[axis]} ({width:g}) is "
                f"too short for the cutoff ({self.forcefield.cutoff:g}), and with "
                f"{', '.join(self._indexed)} (terms between atom indices) MDCalculator cannot "
                "replicate the cell: give it a larger cell (atoms.repeat)"
            )
        if not np.array_equal(replicas, self._replicas):
            rebuild = True
        if not (
            np.array_equal(edges, self._edges)
            and np.array_equal(tilt, self._tilt)
            and np.array_equal(replicas, self._replicas)
        ):
            self._shifts = _image_shifts(replicas, cell_matrix(edges, tilt))
        self._replicas, self._edges, self._tilt = replicas, edges, tilt
        positions = self._supercell_positions(atoms)
        if rebuild:
            self._n_atoms = n
            self._order = None
            self._state = state = State(
                positions=positions,
                box=edges * replicas,
                pbc=pbc,
                types=np.tile(self._types, len(self._shifts)),
                type_names=self._names,
                tilt=tilt * replicas[[1, 2, 2]],
            )
            self.forcefield.check(state)
            neighbor_list = self.forcefield.neighbor_list
            self._sorting = (
                neighbor_list is not None
                and n > 0
                and not self._indexed
                and (
                    self.sort_atoms is True
                    or (self.sort_atoms == "auto" and state.n_atoms >= _SORT_FROM)
                )
            )
            if self._sorting:
                self._sort(positions)
            if neighbor_list is not None:
                neighbor_list.build(state)
            return state
        state.box[:] = edges * replicas
        state.tilt[:] = tilt * replicas[[1, 2, 2]]
        state.pbc[:] = pbc
        if self._sorting:
            self._sort(positions)  # the box changed: the list is rebuilt now anyway
        else:
            state.positions[:] = positions
        return state

    def _supercell_positions(self, atoms) -> NDArray[np.float64]:
        """Positions (engine frame) of the atoms and their copies (copies, n) in original order."""
        positions = atoms.positions
        if self._rotation is not None:
            positions = positions @ self._rotation
        if len(self._shifts) == 1:
            return positions
        shifted = positions[None, :, :] + self._shifts[:, None, :]
        return shifted.reshape(-1, 3)

    def _sort(self, positions: NDArray[np.float64]) -> None:
        """Order the internal atoms by spatial cell, for memory locality in the kernels.

        Cells are half a neighbour-list radius wide, in x-major order; the
        internal State holds ``positions[order]`` and results map back
        through :meth:`_originals`. Only the summation order changes.
        """
        state = self._state
        width = 0.5 * self.forcefield.neighbor_list.list_radius
        folded = positions - positions.min(axis=0)
        periodic = state.pbc
        folded[:, periodic] = np.mod(positions[:, periodic], state.box[periodic])
        cells = np.floor(folded / width).astype(np.int64)
        self._order = np.lexsort((cells[:, 2], cells[:, 1], cells[:, 0]))
        np.take(positions, self._order, axis=0, out=state.positions)
        state.types[:] = np.tile(self._types, len(self._shifts))[self._order]

    def _originals(self, values: NDArray) -> NDArray:
        """Per-atom values of the internal State for the original atoms, in their order."""
        n = self._n_atoms
        if self._order is None:
            return values[:n] if len(values) > n else values
        unsorted = np.empty_like(values)
        unsorted[self._order] = values
        return unsorted[:n]


def _engine_frame(cell, pbc) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray]:
    """Return ``(edges, tilt, rotation)`` of an ASE cell in the engine's frame, for any pbc.

    Only periodic cell vectors are translations: a fully periodic cell goes
    through :func:`md.box.restricted_cell`. Otherwise the rotation Q (positions
    ``r @ Q``) takes the first periodic vector along its own axis, the second
    into the plane of its axis and the first's, and so on; the open axes
    complete a right-handed frame and their vectors, which translate nothing,
    are ignored (their edge is kept as their length, without tilt). So a
    tilted or rotated cell is accepted with any pbc, and Q is exactly the
    identity for a cell already in the engine's form.

    Raises
    ------
    ValueError
        If the cell is not finite, a periodic axis has no length, or the
        periodic vectors are linearly dependent.
    """
    what = "atoms.cell (MDCalculator)"
    if pbc.all():
        edges, tilt, rotation = restricted_cell(cell, what)
        if np.any(edges == 0):
            axis = "xyz"[int(np.argmax(edges == 0))]
            raise ValueError(f"atoms are periodic along {axis} but the cell has no length there")
        return edges, tilt, rotation
    h = np.asarray(cell, dtype=np.float64)
    if not np.all(np.isfinite(h)):
        raise ValueError(f"{what} has entries that are not finite: {h.tolist()}")
    tolerance = 1e-12 * max(1.0, float(np.abs(h).max()))
    rotation = np.zeros((3, 3))
    filled: list[int] = []
    for k in np.flatnonzero(pbc):
        if np.linalg.norm(h[k]) <= tolerance:
            axis = "xyz"[k]
            raise ValueError(f"atoms are periodic along {axis} but the cell has no length there")
        rest = h[k] - rotation[:, filled] @ (rotation[:, filled].T @ h[k])
        if np.linalg.norm(rest) <= tolerance:
            raise ValueError(
                f"{what}: the periodic cell vectors are linearly dependent: {h.tolist()}"
            )
        rotation[:, k] = rest / np.linalg.norm(rest)
        filled.append(int(k))
    for k in np.flatnonzero(~pbc):  # the coordinate axis itself where it is free, else another
        for candidate in (k, *range(3)):
            unit = np.eye(3)[candidate]
            rest = unit - rotation[:, filled] @ (rotation[:, filled].T @ unit)
            if np.linalg.norm(rest) > 0.5:
                break
        rotation[:, k] = rest / np.linalg.norm(rest)
        filled.append(int(k))
    if np.linalg.det(rotation) < 0:
        rotation[:, int(np.flatnonzero(~pbc)[-1])] *= -1.0
    lower = h @ rotation
    edges = np.where(pbc, np.diag(lower), np.linalg.norm(h, axis=1))
    tilt = np.array([lower[j, i] if pbc[i] and pbc[j] else 0.0 for i, j in TILT_AXES])
    return edges, np.where(np.abs(tilt) <= tolerance, 0.0, tilt), rotation


def _volume(cell) -> float:
    """The cell's volume where it has one (three independent vectors, as ASE's rank), else 0."""
    cell = np.asarray(cell, dtype=np.float64)
    return abs(float(np.linalg.det(cell))) if np.linalg.matrix_rank(cell) == 3 else 0.0


def _build_potentials(entries: Sequence, type_names: Sequence[str] | None):
    """Return (potentials, type_names): tables built into potentials, names resolved."""
    if isinstance(entries, Mapping) or not isinstance(entries, Sequence) or not entries:
        raise ValueError("potentials must be a non-empty list of potentials or tables")
    names = None if type_names is None else tuple(str(name) for name in type_names)
    tables = [entry for entry in entries if isinstance(entry, Mapping)]
    if tables and names is None:
        found: list[str] = []
        for table in tables:
            for value in table.values():
                if isinstance(value, Mapping):
                    found += [str(key) for key in value if str(key) not in found]
            for pair in table.get("pairs", None) or []:
                found += [str(t) for t in pair.get("types", ()) if str(t) not in found]
        names = tuple(found) or None
    built = []
    for index, entry in enumerate(entries):
        if not isinstance(entry, Mapping):
            if not isinstance(entry, Potential):
                raise TypeError(
                    f"potentials[{index}]: expected a potential object (e.g. "
                    "LennardJones(epsilon=..., sigma=..., cutoff=...)) or a table such as "
                    f"{{'type': 'lj', 'epsilon': ..., 'sigma': ..., 'cutoff': ...}}, got {entry!r}"
                )
            built.append(entry)
            continue
        params = dict(entry)
        kind = params.pop("type", None)
        try:  # a built-in style or a plug-in (md.plugins), as in a config
            cls = potential_class(kind)
        except PluginError as error:
            raise ValueError(f"potentials[{index}]: type {error}") from None
        try:
            built.append(cls.from_config(params, names or ()))
        except (TypeError, ValueError) as error:
            raise ValueError(f"potentials[{index}] ({kind}): {error}") from None
    return built, names


def _identical(old, new, but: str = "") -> bool:
    """True if every property ASE's ``check_state`` compares, except ``but``, is exactly equal
    (bit for bit, dtype and shape too: values equal in other bits, such as -0.0 and 0.0, are
    left to ASE's comparison).

    Written out for ASE's own types (its per-atom arrays, ``cell.array`` and ``pbc`` are
    ndarrays; anything else goes through :func:`_same_bytes`): it runs twice in each
    energy + forces pair of calls, where a generator over ``all_changes`` and the
    conversions cost about a microsecond each time."""
    old_arrays, new_arrays = old.arrays, new.arrays
    if old_arrays.keys() != new_arrays.keys():
        return False
    if old_arrays["positions"].shape != new_arrays["positions"].shape:  # len(atoms)
        return False
    if not (_same_array(old.cell.array, new.cell.array) and _same_array(old.pbc, new.pbc)):
        return False
    for name in _COMPARED:
        if name != but and name in old_arrays:
            if not _same_array(old_arrays[name], new_arrays[name]):
                return False
    return True


def _comparable(atoms) -> tuple:
    """What :func:`_identical` compares but the positions, as one tuple: equal tuples are
    equal in everything ASE's ``check_state`` compares but the positions, bit for bit with
    dtype and shape (so the held copy's side is made once, not at every call)."""
    arrays = atoms.arrays
    cell, pbc = atoms.cell.array, atoms.pbc
    if type(cell) is not np.ndarray or type(pbc) is not np.ndarray:
        cell, pbc = np.asarray(cell), np.asarray(pbc)
    # (dtypes as themselves: a tuple comparison finds numpy's shared ones identical at once)
    held = [
        tuple(arrays),
        arrays["positions"].shape,
        cell.dtype,
        cell.shape,
        cell.tobytes(),
        pbc.dtype,
        pbc.shape,
        pbc.tobytes(),
    ]
    for name in _COMPARED:
        if name != "positions" and name in arrays:
            values = arrays[name]
            held += (name, values.dtype, values.shape, values.tobytes())
    return tuple(held)


#: The per-atom arrays of ASE's ``all_changes`` (cell and pbc are the atoms' attributes).
_COMPARED = tuple(name for name in all_changes if name not in ("cell", "pbc"))


def _same_array(a, b) -> bool:
    """:func:`_same_bytes` without the conversion where both are ndarrays."""
    if type(a) is not np.ndarray or type(b) is not np.ndarray:
        return _same_bytes(a, b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def _same_bytes(a, b) -> bool:
    """Whether two arrays have one dtype, one shape and the same bytes (a few microseconds
    less than ``np.array_equal`` on a small array)."""
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def _replicas(edges, tilt, pbc, forcefield) -> NDArray[np.int64]:
    """Copies of the cell along each axis so that the neighbour list accepts the supercell.

    An orthorhombic supercell needs every periodic edge longer than twice
    the cutoff, a tilted one every perpendicular width longer than twice the
    cutoff plus skin (``NeighborList.check_box``). Replicating n times along
    a cell vector multiplies the width across it by n.
    """
    replicas = np.ones(3, dtype=np.int64)
    cutoff = forcefield.cutoff
    if cutoff is None:
        return replicas
    if np.any(tilt != 0.0) and forcefield.neighbor_list is not None:
        reach = 2.0 * forcefield.neighbor_list.list_radius
        widths = perpendicular_widths(edges, tilt)
    else:
        reach, widths = 2.0 * cutoff, edges
    for axis in range(3):
        if pbc[axis]:
            count = int(reach // widths[axis]) + 1
            while count * widths[axis] <= reach:
                count += 1
            replicas[axis] = count
    return replicas


def _image_shifts(replicas, cell) -> NDArray[np.float64]:
    """Translation of each copy (copies, 3) [length], the original (zero shift) first."""
    grid = np.stack(np.meshgrid(*(np.arange(r) for r in replicas), indexing="ij"), axis=-1)
    return grid.reshape(-1, 3) @ cell


def _rotate_voigt(stresses, rotation) -> NDArray[np.float64]:
    """Rotate (N, 6) Voigt stresses (xx, yy, zz, yz, xz, xy) by Q: Q s Q^T for each."""
    xx, yy, zz, yz, xz, xy = stresses.T
    full = np.stack(
        [np.stack([xx, xy, xz], -1), np.stack([xy, yy, yz], -1), np.stack([xz, yz, zz], -1)],
        axis=-2,
    )
    turned = rotation @ full @ rotation.T
    return np.stack(
        [
            turned[:, 0, 0],
            turned[:, 1, 1],
            turned[:, 2, 2],
            turned[:, 1, 2],
            turned[:, 0, 2],
            turned[:, 0, 1],
        ],
        axis=-1,
    )


__all__ = ["MDCalculator"]


@njit(cache=True)
def _tile_into(positions, shifts, out):
    """``out[c n + i] = positions[i] + shifts[c]`` for each copy c: the supercell's positions
    in copy order (the same additions, one rounding each, as numpy's broadcast sum)."""
    n = positions.shape[0]
    for c in range(shifts.shape[0]):
        for i in range(n):
            for a in range(3):
                out[c * n + i, a] = positions[i, a] + shifts[c, a]


@njit(cache=True)
def _apart(a, b, tol):
    """Whether any ``|a - b| <= tol`` fails (a NaN fails it): ``not np.all(np.abs(a - b) <=
    tol)`` for two arrays of one length. One pass with no early exit, which vectorises:
    the second call of a pair (energy, then forces) finds every coordinate the same and
    reads them all (a loop that stopped at the first apart took 1 us for 500 atoms)."""
    close = True
    for i in range(a.shape[0]):
        close &= abs(a[i] - b[i]) <= tol
    return not close
