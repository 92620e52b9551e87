"""The Potential protocol and the ForceResult it returns."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from md.neighbors import NeighborList
    from md.state import State
    from potentials.pair_hessian import PairHessian


#: The precisions a potential may offer (its ``PRECISIONS``; the ForceField passes
#: ``precision=`` only to those that list the one asked for): ``"double"`` everywhere,
#: ``"mixed"`` (float32 pair arithmetic, double sums) in the pair-kernel frame.
PRECISIONS = ("double", "mixed")


def check_precision_name(precision) -> str:
    """Return ``precision`` if it is one of :data:`PRECISIONS`, else raise ValueError."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
    return precision


@dataclass
class ForceResult:
    """Energy, forces and virial of a configuration.

    Attributes
    ----------
    energy : float
        Potential energy [energy].
    forces : ndarray of float64, shape (N, 3)
        Forces [energy/length].
    virial : ndarray of float64, shape (3, 3), or None
        Pair virial W_ab = sum over interactions of r_ij,a F_ij,b [energy];
        its trace over 3 V is the configurational pressure. None when the
        caller said it needs no virial (``virial=False``), as integrators do
        between thermo outputs (LAMMPS's vflag).
    energies : ndarray of float64, shape (N,), optional
        Per-atom energies (each pair split half and half), when asked for.
    virials : ndarray of float64, shape (N, 6), optional
        Per-atom virials (each pair's r_ij (x) F_ij split half and half) as
        (xx, yy, zz, yz, xz, xy) [energy], when asked for and provided.
    """

    energy: float
    forces: NDArray[np.float64]
    virial: NDArray[np.float64] | None
    energies: NDArray[np.float64] | None = None
    virials: NDArray[np.float64] | None = None


@runtime_checkable
class ForceSource(Protocol):
    """What integrators, the simulation and checkpoints ask of a force field.

    :class:`md.forcefield.ForceField` (one process) and
    :class:`md.distributed.DistributedForceField` (one rank of a decomposed run) both
    meet it, so an integrator takes either without looking for methods
    (``tests/test_distributed_package.py`` checks both). ``compute`` caches its result
    while positions and cell are unchanged; ``virial_wanted`` asks the next calls for the
    virial (an observer will read it); ``timings`` holds seconds by section.
    """

    potentials: list
    precision: str
    virial_wanted: bool
    timings: dict

    def compute(self, state: State, per_atom: bool = False, virial: bool = True) -> ForceResult:
        """Energy, forces (and virial) of ``state``."""
        ...

    def compute_subset(self, state: State, which, virial: bool = False) -> ForceResult:
        """The same for the potentials numbered in ``which`` (RESPA's splits)."""
        ...

    def hessian_operator(self, state: State):
        """The Hessian as a linear operator (the implicit integrators' Newton steps)."""
        ...

    def invalidate(self) -> None:
        """Forget the cached result (the positions changed behind its back)."""
        ...


@runtime_checkable
class Potential(Protocol):
    """What the ForceField needs of a potential.

    ``cutoff`` is the interaction range, or None for potentials that need no
    neighbour list (bonded terms). ``energy_forces`` returns a new
    ForceResult and leaves the state untouched; ``neighbors`` is a list built
    with a radius of at least ``cutoff`` (None: loop over all pairs).
    ``per_atom`` asks for per-atom energies (and, where provided, per-atom
    virials); ``virial=False`` lets the potential skip the virial (the
    result's ``virial`` is then None), which integrators ask for between
    thermo outputs. The ForceField always passes both keywords.

    A pair potential reads the list through ``neighbors.frame`` (a
    :class:`md.neighbors.SlotFrame`: slot order, images, per-chunk bounds; no
    minimum image needed) or, when that is None or per-atom results are
    wanted, ``neighbors.starts``/``neighbors.neighbors`` over atom indices
    (minimum image per pair).

    Optional hooks, found by the ForceField and the implicit integrators:
    ``hessian(state, neighbors)`` (:class:`SupportsHessian`: a sparse
    (3N, 3N) matrix, for Newton's method) and ``hessian_operator(state,
    neighbors)`` (:class:`SupportsHessianOperator`: pair blocks applied
    without assembly, and clamped where a pair's curvature is negative).
    ``from_config(params, type_names)`` (a classmethod) builds the potential
    from a config table, whose keys the class declares in ``CONFIG_KEYS`` (a
    tuple of :class:`md.schema.Key`: the config refuses others and the config
    reference lists them); the registry ``potentials.POTENTIALS`` maps config
    names to classes.
    """

    cutoff: float | None

    def energy_forces(
        self,
        state: State,
        neighbors: NeighborList | None,
        per_atom: bool = False,
        virial: bool = True,
    ) -> ForceResult: ...

    def check(self, state: State) -> None:
        """Raise ValueError if the potential cannot act on this state (types, sizes)."""
        ...

    def describe(self) -> dict:
        """Return the parameters as plain values, for trajectory metadata."""
        ...


@runtime_checkable
class SupportsPrecision(Protocol):
    """Optional capability: the precisions ``energy_forces`` offers (a subset of
    :data:`PRECISIONS`); the ForceField passes ``precision=`` to a potential that lists
    the one asked for, and to no other (those run double). A class attribute: the
    ForceField asks whether a class has it once, of its first instance."""

    PRECISIONS: tuple[str, ...]


@runtime_checkable
class SupportsVerletStep(Protocol):
    """Optional capability of a potential: a velocity Verlet step with its forces in one
    compiled call while the list holds (:meth:`potentials.PairPotential.verlet_step`
    says the contract); the ForceField asks whether a class has it once."""

    def verlet_step(self, state, neighbors, kicks, kick_dt, drift_dt, reference, allowed2): ...


@runtime_checkable
class SupportsKeptCall(Protocol):
    """Optional capability of a potential: the compiled call its ``energy_forces`` makes
    for a state over a list, handed to a caller that makes it itself between list
    builds (:meth:`potentials.PairPotential.kept_call` says the contract); the
    ForceField asks whether a class has it once."""

    def kept_call(self, state, neighbors) -> tuple | None: ...


@runtime_checkable
class SupportsMixedVerletStep(Protocol):
    """Optional capability of a potential: velocity Verlet's mixed-precision step over a
    cluster-pair list in compiled calls around its kernel
    (:meth:`potentials.PairPotential.mixed_verlet_step` says the contract); the ForceField
    asks whether a class has it once."""

    def mixed_verlet_step(
        self, state, neighbors, kicks, kick_dt, drift_dt, held, allowed2, key
    ): ...


@runtime_checkable
class FusesVerletStep(Protocol):
    """Optional capability of a force source: velocity Verlet's whole step in one call
    where it can be (:meth:`md.ForceField.verlet_step`: 2 done, 1 kicked and drifted,
    0 nothing done; ``threaded``: the caller's own passes would run on the threads);
    velocity Verlet asks whether a class has it once."""

    def verlet_step(
        self, state: State, kick_dt: float, drift_dt: float, threaded: bool = False
    ) -> int: ...


@runtime_checkable
class SupportsHessian(Protocol):
    """Optional capability: the (3N, 3N) second derivative of the energy."""

    def hessian(self, state: State, neighbors: NeighborList | None) -> NDArray[np.float64]: ...


@runtime_checkable
class Bonded(Protocol):
    """Optional capability: a fixed bond list, stored in trajectories as topology.

    ``bonds`` is a (B, 2) integer array of atom pairs, ``bond_types`` a (B,)
    type index per bond, and ``bond_style`` names the form ("spring", "fene").
    """

    bonds: NDArray[np.int64]
    bond_types: NDArray[np.int64]
    bond_style: str


@runtime_checkable
class BondedAngles(Protocol):
    """Optional capability: a fixed angle list, stored in trajectories as topology.

    ``angles`` is an (A, 3) integer array of atom triples ``(i, j, k)``, ``j``
    the vertex, ``angle_types`` an (A,) type index per angle, and
    ``angle_style`` names the form ("angle_harmonic", "angle_cosine").
    """

    angles: NDArray[np.int64]
    angle_types: NDArray[np.int64]
    angle_style: str


@runtime_checkable
class TypedParameters(Protocol):
    """Optional capability: parameters that can depend on the particle type.

    ``per_type_parameters`` is True when they do (one value per type, or
    explicit pair values), so whoever maps particles onto type indices must
    follow the parameters' type order: the ASE calculator then asks for
    ``type_names``. A potential without the attribute acts alike on every type.
    """

    @property
    def per_type_parameters(self) -> bool: ...


@runtime_checkable
class SupportsHessianOperator(Protocol):
    """Optional capability: the Hessian as pair blocks (a ``PairHessian``)."""

    def hessian_operator(self, state: State, neighbors: NeighborList | None) -> PairHessian: ...


@dataclass(frozen=True)
class BondLaw:
    """A bonded potential's radial law, bond by bond, as plain arrays.

    For solvers that move bonds one at a time (XPBD) and must evaluate the
    law at trial lengths themselves.

    Attributes
    ----------
    form : {"harmonic", "fene"}
        ``"harmonic"``: U = k/2 (r - length)^2 (``length`` is the rest length);
        ``"fene"``: U = -k/2 length^2 ln(1 - r^2 / length^2) (``length`` is r_max).
    bonds : ndarray of int64, shape (B, 2)
        Atom pairs.
    k : ndarray of float64, shape (B,)
        Spring constant of each bond [energy/length^2].
    length : ndarray of float64, shape (B,)
        Rest length (harmonic) or maximum extension (FENE) of each bond [length].
    """

    form: str
    bonds: NDArray[np.int64]
    k: NDArray[np.float64]
    length: NDArray[np.float64]


@runtime_checkable
class SupportsBondLaw(Protocol):
    """Optional capability: the radial law of each bond (:class:`BondLaw`)."""

    def bond_law(self) -> BondLaw: ...
