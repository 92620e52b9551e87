"""The State of a particle system at one instant."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:  # ASE is only touched at the edges, see from_ase/to_ase.
    import ase


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
    box : ndarray of float64, shape (3,)
        Orthorhombic box edge lengths [length]; positive on periodic axes.
    pbc : ndarray of bool, shape (3,)
        Periodicity per axis.
    types : ndarray of int32, shape (N,)
        Particle type indices 0..n_types-1; zeros if omitted.
    type_names : tuple of str
        A name per type (chemical symbols for ASE structures).
    step, time : int, float
        Step counter and simulated time [time].

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
        self.box = _owned(self.box, "box", (3,), np.float64)
        self.pbc = _owned(self.pbc, "pbc", (3,), bool)
        if self.types is None:
            self.types = np.zeros(n, dtype=np.int32)
        types = np.asarray(self.types)
        if types.shape != (n,):
            raise ValueError(f"types must have shape ({n},), got {types.shape}")
        if types.size and not np.all(types == np.round(types)):
            raise ValueError(f"types must be integers, got {self.types!r}")
        self.types = np.array(types, dtype=np.int32, order="C", copy=True)
        n_types = int(self.types.max()) + 1 if n else 1
        if self.type_names is None:
            self.type_names = tuple(_default_type_name(t) for t in range(n_types))
        self.type_names = tuple(str(name) for name in self.type_names)
        self.step = int(self.step)
        self.time = float(self.time)
        self.validate()

    def validate(self) -> None:
        """Raise ValueError naming the first physically invalid field."""
        if not np.all(np.isfinite(self.positions)):
            bad = int(np.argwhere(~np.isfinite(self.positions))[0, 0])
            raise ValueError(f"positions of atom {bad} are not finite: {self.positions[bad]}")
        if not np.all(np.isfinite(self.velocities)):
            bad = int(np.argwhere(~np.isfinite(self.velocities))[0, 0])
            raise ValueError(f"velocities of atom {bad} are not finite: {self.velocities[bad]}")
        if self.masses.size and not np.all(self.masses > 0):  # also catches NaN
            bad = int(np.argwhere(~(self.masses > 0))[0, 0])
            raise ValueError(f"masses must be positive; atom {bad} has mass {self.masses[bad]}")
        if not np.all(np.isfinite(self.box)) or np.any(self.box[self.pbc] <= 0):
            raise ValueError(
                f"box edges must be finite and positive along periodic axes, got {self.box}"
            )
        if np.any(self.box < 0):
            raise ValueError(f"box edges must not be negative, got {self.box}")
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
        """Box volume [length^3] (the product of the edges)."""
        return float(np.prod(self.box))

    def copy(self) -> State:
        """Return a deep copy."""
        return State(
            positions=self.positions.copy(),
            velocities=self.velocities.copy(),
            masses=self.masses.copy(),
            box=self.box.copy(),
            pbc=self.pbc.copy(),
            types=self.types.copy(),
            type_names=self.type_names,
            step=self.step,
            time=self.time,
        )

    @classmethod
    def from_ase(cls, atoms: ase.Atoms) -> State:
        """Build a State from ASE Atoms (ASE's units are the engine's metal units).

        Types are numbered by increasing atomic number and named by chemical
        symbol. The cell must be orthorhombic (a diagonal matrix).
        """
        cell = np.asarray(atoms.cell[:], dtype=float)
        off_diagonal = cell - np.diag(np.diag(cell))
        if np.any(np.abs(off_diagonal) > 1e-12 * max(1.0, np.abs(cell).max())):
            raise ValueError(
                "only orthorhombic cells are supported: atoms.cell has off-diagonal "
                f"entries {cell.tolist()}"
            )
        numbers = atoms.get_atomic_numbers()
        unique = np.unique(numbers)
        types = np.searchsorted(unique, numbers).astype(np.int32)
        from ase.data import chemical_symbols

        names = tuple(chemical_symbols[z] for z in unique) if len(unique) else ("X",)
        return cls(
            positions=atoms.get_positions(),
            velocities=atoms.get_velocities(),
            masses=atoms.get_masses(),
            box=np.diag(cell).copy(),
            pbc=np.asarray(atoms.pbc, dtype=bool),
            types=types,
            type_names=names,
        )

    def to_ase(self) -> ase.Atoms:
        """Return ASE Atoms with the same positions, velocities, masses and cell.

        Type names that are chemical symbols become the atoms' symbols; other
        names map to dummy atoms ('X') and the type index goes into ``tags``.
        """
        import ase
        from ase.data import chemical_symbols

        symbols = [name if name in chemical_symbols else "X" for name in self.type_names]
        atoms = ase.Atoms(
            symbols=[symbols[t] for t in self.types],
            positions=self.positions,
            cell=np.diag(self.box),
            pbc=self.pbc,
            masses=self.masses,
            tags=self.types,
        )
        atoms.set_velocities(self.velocities)
        return atoms


def _default_type_name(index: int) -> str:
    letters = "ABCDEFGHIJKLMNOPQRSTUVWXYZ"
    return letters[index] if index < len(letters) else f"T{index}"
