"""The State of a particle system at one instant."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from md.box import TILT_AXES, TILT_NAMES, cell_matrix, is_orthorhombic, restricted_cell

if TYPE_CHECKING:  # ASE is only touched at the edges, see from_ase/to_ase.
    import ase  # ASE: only for conversions to and from Atoms


#: What an adopted State's velocities and masses are views of (read-only: see adopting).
_ZERO_VELOCITY = np.zeros(3)
_ZERO_VELOCITY.flags.writeable = False
_UNIT_MASS = np.ones(())
_UNIT_MASS.flags.writeable = False


def _owned(value, name: str, shape: tuple[int, ...], dtype) -> NDArray:
    """Return a C-contiguous copy of ``value`` broadcast to ``shape`` (the State owns it)."""
    try:
        array = np.asarray(value, dtype=dtype)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be numeric, got {value!r}") from None
    if array.shape != shape:
        try:
            array = np.broadcast_to(array, shape)
        except ValueError:
            expected = "a scalar or shape " + str(shape)
            raise ValueError(f"{name} must be {expected}, got shape {array.shape}") from None
    return np.array(array, dtype=dtype, order="C", copy=True)


@dataclass(eq=False)
class State:
    """Positions, velocities and box of a system at one instant.

    Positions are kept continuous (unwrapped): the engine never folds them back
    into the box, so displacements and diffusion read straight off them.
    Periodic images are resolved where needed (neighbour search, force
    kernels, trajectory output) through :mod:`md.box`.

    Parameters
    ----------
    positions : ndarray of float64, shape (N, 3)
        Particle positions [length].
    velocities : ndarray of float64, shape (N, 3)
        Particle velocities [length/time]; zeros if omitted.
    masses : ndarray of float64, shape (N,)
        Particle masses [mass], all positive; a scalar is broadcast.
    box : ndarray of float64, shape (3,) or (3, 3)
        Box edge lengths (Lx, Ly, Lz) [length], positive on periodic axes; or
        a lower-triangular (3, 3) cell matrix (rows a, b, c, as
        :func:`md.box.cell_matrix` gives), which sets ``box`` and ``tilt``.
        Any other cell is first rotated with :func:`md.box.restricted_cell`
        (``State.from_ase`` does that for ASE's cells).
    pbc : ndarray of bool, shape (3,)
        Periodicity per axis.
    types : ndarray of int32, shape (N,)
        Particle type indices 0..n_types-1; zeros if omitted.
    type_names : tuple of str
        A name per type (chemical symbols for ASE structures).
    step, time : int, float
        Step counter and simulated time [time].
    tilt : ndarray of float64, shape (3,)
        Tilt factors (xy, xz, yz) of a triclinic cell [length], zeros for an
        orthorhombic box; each may be non-zero only when both axes it
        couples are periodic. The cell vectors are a = (Lx, 0, 0),
        b = (xy, Ly, 0) and c = (xz, yz, Lz) (:attr:`cell`).
    ids : ndarray of int64, shape (N,), optional
        Each atom's index in the whole system, when this State holds a part
        of it (one rank's atoms in a run decomposed over MPI ranks,
        :mod:`md.distributed`); None: atom i is atom i. Langevin's noise is
        keyed by it, so a trajectory does not depend on how the system was cut.

    Examples
    --------
    >>> import numpy as np
    >>> s = State(positions=np.zeros((2, 3)), masses=1.0, box=[5.0, 5.0, 5.0])
    >>> s.n_atoms, s.pbc.tolist()
    (2, [True, True, True])
    """

    positions: NDArray[np.float64]
    velocities: NDArray[np.float64] | None = None
    masses: NDArray[np.float64] | float = 1.0
    box: NDArray[np.float64] = field(default_factory=lambda: np.ones(3))
    pbc: NDArray[np.bool_] | bool = True
    types: NDArray[np.int32] | None = None
    type_names: tuple[str, ...] | None = None
    step: int = 0
    time: float = 0.0
    tilt: NDArray[np.float64] | None = None
    ids: NDArray[np.int64] | None = None

    def __post_init__(self) -> None:
        # The State owns copies of its arrays: integrators update them in place,
        # which must never reach back into arrays the caller still holds.
        positions = np.asarray(self.positions, dtype=np.float64)
        if positions.ndim != 2 or positions.shape[1] != 3:
            raise ValueError(f"positions must have shape (N, 3), got {positions.shape}")
        n = positions.shape[0]
        self.positions = np.array(positions, order="C", copy=True)
        if self.velocities is None:
            self.velocities = np.zeros((n, 3))
        velocities = np.asarray(self.velocities, dtype=np.float64)
        if velocities.shape != (n, 3):
            raise ValueError(f"velocities must have shape ({n}, 3), got {velocities.shape}")
        self.velocities = np.array(velocities, order="C", copy=True)
        self.masses = _owned(self.masses, "masses", (n,), np.float64)
        if np.shape(self.box) == (3, 3):
            box, tilt, rotation = restricted_cell(self.box, "box")
            if not np.array_equal(rotation, np.eye(3)):
                raise ValueError(
                    "a (3, 3) box must be lower triangular with a positive diagonal (a along x, "
                    f"b in the xy plane), got {np.asarray(self.box).tolist()}; rotate the "
                    "system with md.box.restricted_cell (State.from_ase does this for ASE cells)"
                )
            if self.tilt is not None and not np.array_equal(self.tilt, tilt):
                raise ValueError("give the tilt either in a (3, 3) box or as tilt, not both")
            self.box, self.tilt = box, tilt
        self.box = _owned(self.box, "box", (3,), np.float64)
        self.pbc = _owned(self.pbc, "pbc", (3,), bool)
        self.tilt = _owned(0.0 if self.tilt is None else self.tilt, "tilt", (3,), np.float64)
        if self.types is None:
            self.types = np.zeros(n, dtype=np.int32)
        types = np.asarray(self.types)
        if types.shape != (n,):
            raise ValueError(f"types must have shape ({n},), got {types.shape}")
        if types.size and not np.all(types == np.round(types)):
            raise ValueError(f"types must be integers, got {self.types!r}")
        self.types = np.array(types, dtype=np.int32, order="C", copy=True)
        if self.ids is not None:
            ids = np.asarray(self.ids)
            if ids.shape != (n,) or (ids.size and not np.issubdtype(ids.dtype, np.integer)):
                raise ValueError(f"ids must be integers of shape ({n},), got {ids.shape}")
            self.ids = np.array(ids, dtype=np.int64, order="C", copy=True)
        n_types = int(self.types.max()) + 1 if n else 1
        if self.type_names is None:
            self.type_names = tuple(_default_type_name(t) for t in range(n_types))
        self.type_names = tuple(str(name) for name in self.type_names)
        self.step = int(self.step)
        self.time = float(self.time)
        self.validate()

    @classmethod
    def adopting(cls, positions, types, box, pbc, type_names) -> State:
        """A State that takes ``positions`` ((N, 3) float64) and ``types`` ((N,) int32),
        both C-contiguous, as they are: no copies and no checks. For systems the engine
        lays out itself from a checked State's values, such as an MPI rank's local system
        (laid out anew at every neighbour-list build, where copying and checking 10^6 atoms
        cost as much as finding the ghosts). Unit masses and zero velocities, read-only
        views of one value (a fresh pair of arrays cost a 10^6-atom rank 35 MB written at
        every build), no tilt."""
        state = cls.__new__(cls)
        n = positions.shape[0]
        state.positions = positions
        # (read-only arrays of stride 0 over one value, made directly: np.broadcast_to's
        # Python took 2 us each, at every build of a rank's local system)
        state.velocities = np.ndarray((n, 3), np.float64, _ZERO_VELOCITY, 0, (0, 8))
        state.masses = np.ndarray((n,), np.float64, _UNIT_MASS, 0, (0,))
        state.box = np.array(box, dtype=np.float64)
        pbc = np.array(pbc, dtype=bool)
        state.pbc = pbc if pbc.shape == (3,) else np.broadcast_to(pbc, (3,)).copy()
        state.types = types
        state.type_names = tuple(str(name) for name in type_names)
        state.step = 0
        state.time = 0.0
        state.tilt = np.zeros(3)
        state.ids = None
        return state

    def validate(self) -> None:
        """Raise ValueError naming the first physically invalid field."""
        if not np.all(np.isfinite(self.positions)):
            bad = int(np.argwhere(~np.isfinite(self.positions))[0, 0])
            raise ValueError(f"positions of atom {bad} are not finite: {self.positions[bad]}")
        # Masses before velocities: velocities from momenta / mass are NaN where a mass is 0.
        if self.masses.size and not np.all(self.masses > 0):  # also catches NaN
            bad = int(np.argwhere(~(self.masses > 0))[0, 0])
            raise ValueError(f"masses must be positive; atom {bad} has mass {self.masses[bad]}")
        if not np.all(np.isfinite(self.velocities)):
            bad = int(np.argwhere(~np.isfinite(self.velocities))[0, 0])
            raise ValueError(f"velocities of atom {bad} are not finite: {self.velocities[bad]}")
        with np.errstate(divide="ignore", over="ignore"):
            usable = np.isfinite(self.masses) & np.isfinite(1.0 / self.masses)
        if self.masses.size and not np.all(usable):  # integrators divide by the mass
            bad = int(np.argwhere(~usable)[0, 0])
            raise ValueError(
                f"mass of atom {bad} ({float(self.masses[bad])!r}) is beyond double precision: the "
                "mass and its inverse must be finite"
            )
        if not np.all(np.isfinite(self.box)) or np.any(self.box[self.pbc] <= 0):
            raise ValueError(
                f"box edges must be finite and positive along periodic axes, got {self.box}"
            )
        if np.any(self.box < 0):
            raise ValueError(f"box edges must not be negative, got {self.box}")
        if not np.all(np.isfinite(self.tilt)):
            raise ValueError(f"tilt factors must be finite, got {self.tilt}")
        for k, (i, j) in enumerate(TILT_AXES):
            if self.tilt[k] != 0.0 and not (self.pbc[i] and self.pbc[j]):
                raise ValueError(
                    f"tilt factor {TILT_NAMES[k]} = {self.tilt[k]:g} couples axes "
                    f"{'xyz'[i]} and {'xyz'[j]}, which must both be periodic"
                )
        if self.types.size and self.types.min() < 0:
            raise ValueError("types must be non-negative integers")
        if self.types.size and int(self.types.max()) >= len(self.type_names):
            raise ValueError(
                f"types go up to {int(self.types.max())} but only "
                f"{len(self.type_names)} type_names were given"
            )

    @property
    def n_atoms(self) -> int:
        return self.positions.shape[0]

    @property
    def n_types(self) -> int:
        return len(self.type_names)

    @property
    def volume(self) -> float:
        """Box volume [length^3] (the product of the edges, tilted or not)."""
        return float(np.prod(self.box))

    @property
    def cell(self) -> NDArray[np.float64]:
        """The (3, 3) cell matrix, rows a, b, c (a new array; set ``box`` and ``tilt``)."""
        return cell_matrix(self.box, self.tilt)

    @property
    def is_orthorhombic(self) -> bool:
        return is_orthorhombic(self.tilt)

    def copy(self) -> State:
        """Return a deep copy."""
        copied = State(
            positions=self.positions.copy(),
            velocities=self.velocities.copy(),
            masses=self.masses.copy(),
            box=self.box.copy(),
            pbc=self.pbc.copy(),
            types=self.types.copy(),
            type_names=self.type_names,
            step=self.step,
            time=self.time,
            tilt=self.tilt.copy(),
            ids=None if self.ids is None else self.ids.copy(),
        )
        momenta = getattr(self, "_ase_momenta", None)  # set only by from_ase (not a field)
        if momenta is not None:
            copied._ase_momenta = momenta.copy()
        return copied

    @classmethod
    def from_ase(
        cls,
        atoms: ase.Atoms,
        types_from: str = "numbers",
        type_names: Sequence[str] | None = None,
    ) -> State:
        """Build a State from ASE Atoms (ASE's units are the engine's metal units).

        Positions, masses, cell and pbc are copied; velocities are
        ``atoms.get_velocities()`` (momenta / masses). Any cell is accepted: a
        cell that is not lower triangular (a along x, b in the xy plane) is
        rotated into that frame with :func:`md.box.restricted_cell`, positions
        and velocities with it (:func:`ase_rotation` gives the rotation). An
        open axis may have zero length.
        :meth:`to_ase` of the returned State gives back ASE's momenta bit for
        bit as long as velocities and masses are unchanged, and ``from_ase``
        of :meth:`to_ase` gives back the velocities bit for bit (a product
        m v followed by a division by m does not always round back to v, so
        each side remembers the other's exact values and uses them only while
        they still match).

        Parameters
        ----------
        atoms : ase.Atoms
            The structure.
        types_from : {"numbers", "tags"}
            Type of each atom from its atomic number or from its tag; see
            :func:`types_from_ase`.
        type_names : sequence of str, optional
            Name of each type index (chemical symbols for ``"numbers"``).
        """
        box, tilt, rotation = restricted_cell(atoms.cell[:], "atoms.cell")
        rotated = not np.array_equal(rotation, np.eye(3))
        types, names = types_from_ase(
            atoms.get_atomic_numbers(),
            atoms.get_tags(),
            types_from,
            type_names,
            atoms.info.get("type_names"),
        )
        masses = atoms.get_masses()
        momenta = atoms.get_momenta()
        with np.errstate(divide="ignore", invalid="ignore"):  # a zero mass: refused below
            velocities = momenta / masses[:, None]  # as ase.Atoms.get_velocities
        remembered = getattr(atoms, "_leapmd_velocities", None)  # ASE Atoms from to_ase only
        if (
            remembered is not None
            and remembered.shape == momenta.shape
            and np.array_equal(remembered * masses[:, None], momenta)
        ):
            velocities = remembered  # written by to_ase and not changed since
        positions = atoms.get_positions()
        if rotated:
            positions, velocities = positions @ rotation, velocities @ rotation
        state = cls(
            positions=positions,
            velocities=velocities,
            masses=masses,
            box=box,
            pbc=np.asarray(atoms.pbc, dtype=bool),
            types=types,
            type_names=names,
            tilt=tilt,
        )
        if not rotated:
            state._ase_momenta = momenta
        return state

    def to_ase(self) -> ase.Atoms:
        """Return ASE Atoms with the same positions, velocities, masses and cell.

        Type names that are chemical symbols become the atoms' symbols; other
        names map to dummy atoms ('X'). The type index always goes into
        ``tags``, and non-chemical names into ``atoms.info["type_names"]``,
        so ``State.from_ase(atoms, types_from="tags")`` recovers the types.
        Momenta are masses times velocities (ASE stores momenta), except that
        momenta this State was built from by :meth:`from_ase` are returned
        unchanged while they still divide back to the current velocities.
        """
        import ase  # ASE: only for conversions to and from Atoms
        from ase.data import chemical_symbols  # ASE: only for conversions to and from Atoms

        symbols = [name if name in chemical_symbols else "X" for name in self.type_names]
        atoms = ase.Atoms(
            symbols=[symbols[t] for t in self.types],
            positions=self.positions,
            cell=self.cell,
            pbc=self.pbc,
            masses=self.masses,
            tags=self.types,
        )
        if any(name not in chemical_symbols for name in self.type_names):
            atoms.info["type_names"] = list(self.type_names)
        masses = self.masses[:, None]
        momenta = self.velocities * masses  # as ase.Atoms.set_velocities
        remembered = getattr(self, "_ase_momenta", None)  # (as in copy)
        if (
            remembered is not None
            and remembered.shape == momenta.shape
            and np.array_equal(remembered / masses, self.velocities)
        ):
            momenta = remembered
        atoms.set_momenta(momenta, apply_constraint=False)
        atoms._leapmd_velocities = self.velocities.copy()
        return atoms


def types_from_ase(
    numbers: NDArray,
    tags: NDArray,
    types_from: str = "numbers",
    type_names: Sequence[str] | None = None,
    stored_names: Sequence[str] | None = None,
) -> tuple[NDArray[np.int32], tuple[str, ...]]:
    """Return ``(types, type_names)`` of atoms from their atomic numbers or tags.

    Parameters
    ----------
    numbers, tags : ndarray of int, shape (N,)
        Atomic numbers and tags (``atoms.numbers``, ``atoms.get_tags()``).
    types_from : {"numbers", "tags"}
        ``"numbers"``: one type per chemical element; with ``type_names``
        (chemical symbols) the type of an atom is the index of its symbol
        there, otherwise types are numbered by increasing atomic number.
        ``"tags"``: the type of an atom is its tag (>= 0).
    type_names : sequence of str, optional
        Name of each type index.
    stored_names : sequence of str, optional
        Names for ``"tags"`` when ``type_names`` is not given (what
        :meth:`State.to_ase` writes to ``atoms.info["type_names"]``); used
        when there is one per tag. Otherwise a tag shared by atoms of a single
        element is named by its symbol, and any other by a letter.

    Raises
    ------
    ValueError
        For an unknown ``types_from``, a symbol missing from ``type_names``, or
        a negative tag or one without a name.
    """
    # ASE: only for conversions to and from Atoms
    from ase.data import atomic_numbers, chemical_symbols

    numbers = np.asarray(numbers)
    if types_from == "numbers":
        if type_names is None:
            unique = np.unique(numbers)
            types = np.searchsorted(unique, numbers).astype(np.int32)
            names = tuple(chemical_symbols[z] for z in unique) if len(unique) else ("X",)
            return types, names
        names = tuple(str(name) for name in type_names)
        index = np.full(len(chemical_symbols), -1, dtype=np.int32)
        for position, name in enumerate(names):
            if name not in atomic_numbers:
                raise ValueError(
                    f"type name {name!r} is not a chemical symbol, so atoms cannot be typed "
                    "by atomic number (use types_from='tags')"
                )
            index[atomic_numbers[name]] = position
        types = index[numbers] if len(numbers) else np.zeros(0, dtype=np.int32)
        if np.any(types < 0):
            bad = int(np.argmax(types < 0))
            raise ValueError(
                f"atom {bad} is {chemical_symbols[numbers[bad]]}, which is not one of the "
                f"types {', '.join(names)}"
            )
        return types.astype(np.int32), names
    if types_from != "tags":
        raise ValueError(f"types_from must be 'numbers' or 'tags', got {types_from!r}")
    tags = np.asarray(tags)
    if tags.size and tags.min() < 0:
        bad = int(tags.argmin())
        raise ValueError(f"tags must be >= 0 to serve as types; atom {bad} has tag {tags[bad]}")
    n_types = int(tags.max()) + 1 if tags.size else 1
    if type_names is not None:
        names = tuple(str(name) for name in type_names)
        if len(names) < n_types:
            raise ValueError(
                f"tags go up to {n_types - 1} but only {len(names)} type_names were given"
            )
    elif stored_names is not None and len(stored_names) >= n_types:
        names = tuple(str(name) for name in stored_names)
    else:
        names = []
        for tag in range(n_types):
            elements = np.unique(numbers[tags == tag])
            if len(elements) == 1 and elements[0] > 0:
                names.append(chemical_symbols[elements[0]])
            else:
                names.append(_default_type_name(tag))
        names = tuple(names)
    return tags.astype(np.int32), names


def _default_type_name(index: int) -> str:
    letters = "ABCDEFGHIJKLMNOPQRSTUVWXYZ"
    return letters[index] if index < len(letters) else f"T{index}"
