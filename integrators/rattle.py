"""Rigid bonds: SHAKE for positions, RATTLE for velocities, and velocity Verlet with both.

:class:`BondConstraints` holds the constrained pairs and their lengths and
applies the two corrections; any integrator built on kicks and drifts can
call them (:class:`Rattle` here, and the thermostats in this package).
The corrections are iterative (one bond at a time, Gauss-Seidel) and stop
when every bond satisfies the tolerance; an iteration limit turns a failure
into :class:`ConstraintError` naming the step and the worst bond.

Constraint forces enter the thermodynamics in two places:

* each constraint removes one degree of freedom from the kinetic
  temperature (:meth:`Rattle.degrees_of_freedom`);
* the pressure needs the constraint forces' virial. It is computed from the
  state alone by :meth:`BondConstraints.constraint_forces`, which solves for
  the Lagrange multipliers that keep every bond length's second time
  derivative zero, so it is the exact instantaneous constraint force of the
  continuous dynamics at that phase point, whatever integrator produced it.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
from numba import njit
from numpy.typing import ArrayLike, NDArray

from integrators._kernels import kick, kick_drift
from integrators.base import DT, IntegratorBase, check_dt
from md._checks import bond_array, read_bonds_file
from md.box import minimum_image, periodic_lengths, periodic_tilt, separation
from md.errors import ConstraintError
from md.schema import REQUIRED, Key, check_names
from md.thermo import degrees_of_freedom as unconstrained_dof


class BondConstraints:
    """Fixed distances between atom pairs, applied by SHAKE and RATTLE.

    Parameters
    ----------
    bonds : array_like of int, shape (B, 2)
        Constrained atom pairs ``(i, j)``, ``i != j``, each pair at most once.
        Distances use the minimum image along periodic axes, as bonds do.
    lengths : float or array_like of float, shape (B,), optional
        Bond lengths [length]. By default each bond keeps the length it has
        when an integrator first sees the state.
    tol : float
        Relative tolerance: SHAKE stops when every ``|r - d| / d <= tol``, RATTLE
        when every ``|r . v_ij| dt / d^2 <= tol`` (the bond-length change over one
        step, relative to its length).
    max_iter : int
        Iterations (sweeps over all bonds) before :class:`ConstraintError`.

    Examples
    --------
    >>> constraints = BondConstraints([[0, 1], [1, 2]], lengths=1.0, tol=1e-10)
    >>> constraints.n_constraints
    2
    """

    #: The keys of an ``[integrator.constraints]`` table (see :meth:`from_config`).
    CONFIG_KEYS = (
        Key(
            "bonds",
            'list or "system"',
            None,
            doc='The constrained atom pairs, a list of `[i, j]`, or `"system"`: the bonds '
            "`[system]` made (a polymer) or read (a structure file). Give this or "
            "`bonds_file`.",
        ),
        Key(
            "bonds_file",
            "path",
            None,
            doc="A text file of two integer columns (atom indices; `#` comments), relative to "
            "the config. Give this or `bonds`.",
        ),
        Key(
            "lengths",
            "number or list",
            None,
            unit="length",
            doc="The bond lengths, one for all or one per bond.",
            default_doc="each bond's starting length",
        ),
        Key(
            "tol",
            "number",
            1e-8,
            doc="Relative tolerance of SHAKE (bond lengths) and RATTLE (bond-length rates), "
            "in (0, 1).",
        ),
        Key(
            "max_iter",
            "integer",
            1000,
            doc="Sweeps over all bonds before the step fails with a constraint error.",
        ),
    )

    def __init__(
        self,
        bonds: ArrayLike,
        lengths: float | ArrayLike | None = None,
        tol: float = 1e-8,
        max_iter: int = 1000,
    ) -> None:
        self.bonds = bond_array(bonds)
        self.bonds.flags.writeable = False
        keys = np.sort(self.bonds, axis=1)
        unique, counts = np.unique(keys, axis=0, return_counts=True)
        if np.any(counts > 1):
            pair = unique[np.flatnonzero(counts > 1)[0]].tolist()
            raise ValueError(f"atoms {pair[0]} and {pair[1]} are constrained more than once")
        if isinstance(tol, bool) or not (isinstance(tol, int | float) and 0 < tol < 1):
            raise ValueError(f"tol must be a number in (0, 1), got {tol!r}")
        if isinstance(max_iter, bool) or not isinstance(max_iter, int | np.integer) or max_iter < 1:
            raise ValueError(f"max_iter must be a positive integer, got {max_iter!r}")
        self.tol = float(tol)
        self.max_iter = int(max_iter)
        self.lengths: NDArray[np.float64] | None = None
        if lengths is not None:
            values = np.asarray(lengths, dtype=np.float64)
            if values.ndim > 1 or (values.ndim == 1 and len(values) != self.n_constraints):
                raise ValueError(
                    f"lengths must be one number or one per constraint "
                    f"({self.n_constraints}), got {lengths!r}"
                )
            values = np.broadcast_to(values, (self.n_constraints,))
            if not np.all(np.isfinite(values) & (values > 0)):
                raise ValueError(f"lengths must be finite and > 0, got {lengths!r}")
            self.lengths = values.copy()
        self._given_lengths = None if self.lengths is None else self.lengths.copy()
        self.statistics = {"shake_iterations": 0, "rattle_iterations": 0}
        self._bound = False

    @property
    def n_constraints(self) -> int:
        return len(self.bonds)

    @classmethod
    def from_config(cls, params: Mapping, system_bonds=None) -> BondConstraints:
        """Build from a config table ``[integrator.constraints]``.

        Keys: ``bonds`` (a list of ``[i, j]``, or ``"system"`` for the bonds
        a ``[system]`` polymer builder made) or ``bonds_file`` (two integer
        columns, the path used as given), optional ``lengths`` (a number or
        one per bond; default: the starting lengths), ``tol``, ``max_iter``.
        """
        params = dict(params)
        check_names(params, cls.CONFIG_KEYS)
        if ("bonds" in params) == ("bonds_file" in params):
            raise ValueError(
                "give exactly one of 'bonds' (a list of [i, j], or \"system\") and 'bonds_file'"
            )
        if "bonds_file" in params:
            bonds = read_bonds_file(params.pop("bonds_file"))
        else:
            bonds = params.pop("bonds")
            if bonds == "system":
                if system_bonds is None:
                    raise ValueError(
                        'bonds = "system" needs bonds from [system]: a polymer builder, or a '
                        "structure file that holds bonds"
                    )
                bonds = system_bonds
            elif isinstance(bonds, str) or not isinstance(bonds, list | np.ndarray):
                raise ValueError(f'bonds: expected a list of [i, j] or "system", got {bonds!r}')
        lengths = params.get("lengths")
        values = lengths if isinstance(lengths, list) else [lengths]
        if any(isinstance(v, bool) or not isinstance(v, int | float | None) for v in values):
            raise ValueError(f"lengths: expected a number or a list of numbers, got {lengths!r}")
        return cls(bonds, **params)

    def describe(self) -> dict:
        """Parameters as given (``lengths`` None: the starting lengths), as plain data."""
        lengths = None
        if self._given_lengths is not None:
            lengths = sorted({float(d) for d in self._given_lengths})
            if len(lengths) > 8:
                lengths = [lengths[0], lengths[-1]]  # the range is enough for metadata
        return {
            "n_constraints": self.n_constraints,
            "lengths": lengths,
            "tol": self.tol,
            "max_iter": self.max_iter,
        }

    # ---------------------------------------------------------------- binding
    def bind(self, state, dt: float = 1.0, step: int = 0) -> None:
        """Check the bonds against ``state`` and put it on the constraint surface.

        On first use: lengths not given are taken from the state; if the
        positions violate the lengths by more than ``tol`` they are moved
        onto them (SHAKE along the current bond vectors), and the velocities
        are projected onto the constraint surface (RATTLE, tolerance judged
        with the time step ``dt``). Later calls are no-ops unless the number
        of atoms changed; ``step`` names the step in errors.
        """
        if self._bound and self._n_atoms == state.n_atoms:
            return
        if self.n_constraints and int(self.bonds.max()) >= state.n_atoms:
            bad = int(np.flatnonzero(self.bonds.max(axis=1) >= state.n_atoms)[0])
            raise ValueError(
                f"constraint {bad} {tuple(self.bonds[bad].tolist())} names an atom beyond "
                f"the {state.n_atoms} atoms of the state"
            )
        if self.n_constraints:
            vectors = self.bond_vectors(state)
            current = np.sqrt(np.einsum("ij,ij->i", vectors, vectors))
            if np.any(current == 0):
                raise ValueError("a constrained pair sits on top of each other (zero length)")
            if self.lengths is None:
                self.lengths = current
        self._d2 = self.lengths**2 if self.n_constraints else np.zeros(0)
        self._n_atoms = state.n_atoms
        # Positions before a drift, SHAKE's reference; a buffer integrators fill and pass in.
        self.reference_buffer = np.empty_like(state.positions)
        inverse_masses = 1.0 / state.masses
        self.shake(state, state.positions.copy(), 1.0, inverse_masses, step, move_velocities=False)
        self.rattle(state, dt, inverse_masses, step)
        self._bound = True

    def get_state(self) -> dict:
        """The lengths in use (taken from the first state when not given), for checkpoints."""
        return {"lengths": None if self.lengths is None else self.lengths.tolist()}

    def set_state(self, saved: dict) -> None:
        """Restore the lengths from :meth:`get_state`, so a resumed run continues exactly."""
        if saved.get("lengths") is None:
            return
        lengths = np.array(saved["lengths"], dtype=np.float64)
        if lengths.shape != (self.n_constraints,):
            raise ValueError(
                f"saved constraint lengths have shape {lengths.shape}, expected "
                f"({self.n_constraints},)"
            )
        self.lengths = lengths
        if self._bound:
            self._d2 = lengths**2

    def bond_vectors(self, state) -> NDArray[np.float64]:
        """Return r_i - r_j for every constrained pair (minimum image) [length]."""
        i, j = self.bonds[:, 0], self.bonds[:, 1]
        return minimum_image(
            state.positions[i] - state.positions[j], state.box, state.pbc, state.tilt
        )

    def errors(self, state) -> NDArray[np.float64]:
        """Return ``|r - d| / d`` for every constrained pair (dimensionless)."""
        if self.lengths is None:
            raise ValueError("the constraints have no lengths yet (bind them to a state first)")
        vectors = self.bond_vectors(state)
        return np.abs(np.sqrt(np.einsum("ij,ij->i", vectors, vectors)) - self.lengths) / (
            self.lengths
        )

    # ------------------------------------------------------------ corrections
    def shake(
        self,
        state,
        reference: NDArray[np.float64],
        dt: float,
        inverse_masses: NDArray[np.float64],
        step: int,
        move_velocities: bool = True,
    ) -> None:
        """Move positions back onto the bond lengths (SHAKE), in place.

        Each correction is along the bond vector of ``reference`` (the
        positions before the drift, which satisfied the constraints) and is
        mass weighted, so it conserves momentum. With ``move_velocities``
        the velocities get the same displacement divided by ``dt`` (the
        drift's duration), as if the constraint force had acted during it.

        Raises
        ------
        ConstraintError
            If some bond is still off by more than ``tol`` after ``max_iter`` sweeps.
        """
        if not self.n_constraints:
            return
        lengths, inverse = periodic_lengths(state.box, state.pbc)
        tilt = periodic_tilt(state.tilt, state.pbc)
        iterations, residual, worst = _shake(
            state.positions,
            state.velocities,
            reference,
            self.bonds,
            self._d2,
            inverse_masses,
            lengths,
            inverse,
            tilt,
            1.0 / dt if move_velocities else 0.0,
            self.tol,
            self.max_iter,
        )
        self.statistics["shake_iterations"] += iterations
        if iterations > self.max_iter or not np.isfinite(residual):
            self._fail(step, "positions", residual, worst)

    def rattle(self, state, dt: float, inverse_masses: NDArray[np.float64], step: int) -> None:
        """Remove every bond's relative velocity along the bond (RATTLE), in place.

        The result is the mass-weighted projection of the velocities onto
        the constraint surface's tangent space: it conserves momentum and
        only removes kinetic energy.

        Raises
        ------
        ConstraintError
            If some bond still stretches faster than ``tol`` d / dt after ``max_iter`` sweeps.
        """
        if not self.n_constraints:
            return
        lengths, inverse = periodic_lengths(state.box, state.pbc)
        tilt = periodic_tilt(state.tilt, state.pbc)
        iterations, residual, worst = _rattle(
            state.positions,
            state.velocities,
            self.bonds,
            self._d2,
            inverse_masses,
            lengths,
            inverse,
            tilt,
            dt,
            self.tol,
            self.max_iter,
        )
        self.statistics["rattle_iterations"] += iterations
        if iterations > self.max_iter or not np.isfinite(residual):
            self._fail(step, "velocities", residual, worst)

    def _fail(self, step, stage, residual, worst):
        i, j = (int(a) for a in self.bonds[worst]) if worst >= 0 else (-1, -1)
        raise ConstraintError(step, stage, residual, int(worst), i, j, self.tol, self.max_iter)

    # ---------------------------------------------------------- thermodynamics
    def constraint_forces(
        self, state, forces: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Return the constraint forces and their virial in ``state``.

        Solves (J M^-1 J^T) lambda = -(J M^-1 F + w) for the multipliers,
        where row k of J holds +r_k on atom i and -r_k on atom j
        (r_k = r_i - r_j) and ``w_k = |v_i - v_j|^2``: the forces J^T lambda that
        keep every ``d^2 |r_k|^2 / dt^2`` zero given the potential forces F and the
        current velocities (assumed tangent, as after RATTLE).

        Returns
        -------
        constraint_forces : ndarray of float64, shape (N, 3)
            Force on every atom [energy/length].
        virial : ndarray of float64, shape (3, 3)
            sum_k lambda_k r_k (x) r_k, the constraint part of the pair
            virial in the convention of :class:`potentials.base.ForceResult` [energy].
        """
        n = state.n_atoms
        if not self.n_constraints:
            return np.zeros((n, 3)), np.zeros((3, 3))
        i, j = self.bonds[:, 0], self.bonds[:, 1]
        vectors = self.bond_vectors(state)
        relative = state.velocities[i] - state.velocities[j]
        inverse_masses = 1.0 / state.masses
        n_bonds = self.n_constraints
        rows = np.repeat(np.arange(n_bonds), 6)
        columns = np.concatenate(
            [3 * i[:, None] + np.arange(3), 3 * j[:, None] + np.arange(3)], axis=1
        ).ravel()
        values = np.concatenate([vectors, -vectors], axis=1).ravel()
        jacobian = scipy.sparse.csr_matrix((values, (rows, columns)), shape=(n_bonds, 3 * n))
        inverse_mass_diagonal = scipy.sparse.diags(np.repeat(inverse_masses, 3))
        weighted = jacobian @ inverse_mass_diagonal
        matrix = (weighted @ jacobian.T).tocsc()
        rhs = -(weighted @ forces.ravel() + np.einsum("ij,ij->i", relative, relative))
        multipliers = np.atleast_1d(scipy.sparse.linalg.spsolve(matrix, rhs))
        result = (jacobian.T @ multipliers).reshape(n, 3)
        virial = np.einsum("k,ka,kb->ab", multipliers, vectors, vectors)
        return result, virial


def as_constraints(constraints) -> BondConstraints | None:
    """Return ``constraints`` as BondConstraints (None, an instance, or a bond list)."""
    if constraints is None or isinstance(constraints, BondConstraints):
        return constraints
    return BondConstraints(constraints)


def constrained_verlet_step(state, forcefield, dt: float, constraints) -> None:
    """One velocity Verlet step with SHAKE after the drift and RATTLE after the last kick.

    Leaves ``state.step`` and ``state.time`` to the caller. ``constraints``
    may be None (plain velocity Verlet).
    """
    forces = forcefield.compute(state, virial=False).forces
    inverse_masses = 1.0 / state.masses
    half = 0.5 * dt
    if constraints is None:
        kick_drift(state.positions, state.velocities, forces, inverse_masses, half, dt)
        forces = forcefield.compute(state, virial=False).forces
        kick(state.velocities, forces, inverse_masses, half)
        return
    step = state.step + 1
    reference = constraints.reference_buffer
    reference[:] = state.positions
    kick_drift(state.positions, state.velocities, forces, inverse_masses, half, dt)
    constraints.shake(state, reference, dt, inverse_masses, step)
    forces = forcefield.compute(state, virial=False).forces
    kick(state.velocities, forces, inverse_masses, half)
    constraints.rattle(state, dt, inverse_masses, step)


def constrained_thermo_terms(constraints, n_dof: int, state, result) -> dict:
    """``n_dof`` and the constraint virial, as :meth:`md.Simulation.thermo` takes them."""
    terms = {"n_dof": n_dof}
    if constraints is not None and constraints.n_constraints:
        terms["virial"] = constraints.constraint_forces(state, result.forces)[1]
    return terms


#: Rigid bonds, a key of the integrators that take them: the ``[integrator.constraints]``
#: table, whose keys are :attr:`BondConstraints.CONFIG_KEYS`.
CONSTRAINTS = Key(
    "constraints", "table", None, doc="Rigid bonds: the `[integrator.constraints]` table (below)."
)


class Rattle(IntegratorBase):
    """Velocity Verlet with rigid bonds: SHAKE after the drift, RATTLE after the last kick.

    Symplectic and time reversible on the constraint surface, second order
    like velocity Verlet, one force evaluation per step. On the first step
    the state is put on the constraint surface (see
    :meth:`BondConstraints.bind`).

    Parameters
    ----------
    dt : float
        Time step [time].
    constraints : BondConstraints or array_like of int, shape (B, 2)
        The rigid bonds (a bond list keeps its starting lengths, tol 1e-8).

    Attributes
    ----------
    statistics : dict
        Cumulative ``steps``, ``shake_iterations`` and ``rattle_iterations``.

    Examples
    --------
    >>> Rattle(dt=0.002, constraints=[[0, 1]]).constraints.n_constraints
    1

    References
    ----------
    J.-P. Ryckaert, G. Ciccotti, H. J. C. Berendsen, J. Comput. Phys. 23, 327
    (1977) (SHAKE); H. C. Andersen, J. Comput. Phys. 52, 24 (1983) (RATTLE).
    """

    CONFIG_KEYS = (
        DT,
        Key(
            "constraints",
            "table",
            REQUIRED,
            doc="The rigid bonds: the `[integrator.constraints]` table (below).",
        ),
    )

    order = 2

    supports_constraints = True
    #: It cannot run without constraints (``md integrators`` leaves it out).
    requires_constraints = True

    def __init__(self, dt: float, constraints) -> None:
        self.dt = check_dt(dt)
        self.constraints = as_constraints(constraints)
        if self.constraints is None:
            raise ValueError("Rattle needs constraints (use VelocityVerlet without them)")
        self._steps = 0

    @property
    def statistics(self) -> dict:
        return {"steps": self._steps, **self.constraints.statistics}

    def step(self, state, forcefield) -> None:
        self.constraints.bind(state, self.dt, state.step + 1)
        constrained_verlet_step(state, forcefield, self.dt, self.constraints)
        self._steps += 1
        self.end_step(state)

    def reset(self) -> None:
        """Nothing to forget: RATTLE is a one-step method."""

    def get_state(self) -> dict:
        """The constraint lengths in use and the step count, for checkpoints."""
        return {"steps": self._steps, "constraints": self.constraints.get_state()}

    def set_state(self, saved: dict) -> None:
        self._steps = int(saved.get("steps", 0))
        self.constraints.set_state(saved["constraints"])

    def degrees_of_freedom(self, n_atoms: int) -> int:
        """3N - 3 - (number of constraints): momentum is conserved and not counted."""
        return unconstrained_dof(n_atoms) - self.constraints.n_constraints

    def thermo_terms(self, state, result) -> dict:
        """Degrees of freedom and constraint virial for :meth:`md.Simulation.thermo`."""
        n_dof = self.degrees_of_freedom(state.n_atoms)
        return constrained_thermo_terms(self.constraints, n_dof, state, result)

    def describe(self) -> dict:
        return {"type": "rattle", "dt": self.dt, "constraints": self.constraints.describe()}


# ------------------------------------------------------------------- kernels


@njit(cache=True, error_model="numpy")
def _shake(
    positions,
    velocities,
    reference,
    bonds,
    d2,
    inverse_masses,
    lengths,
    inverse,
    tilt,
    inverse_dt,
    tol,
    max_iter,
):
    """SHAKE sweeps until every |r^2 - d^2| / (2 d^2) <= tol; positions (and
    velocities, scaled by inverse_dt, 0 for none) written in place.

    Returns (sweeps, largest residual of the last sweep, its bond);
    sweeps = max_iter + 1 when not converged, residual inf when a bond
    turned by 90 degrees or more from its reference direction.
    """
    n_bonds = bonds.shape[0]
    worst = 0.0
    worst_bond = -1
    for sweep in range(max_iter + 1):
        worst = 0.0
        worst_bond = -1
        for k in range(n_bonds):
            i = bonds[k, 0]
            j = bonds[k, 1]
            sx, sy, sz = separation(positions, i, j, lengths, inverse, tilt)
            diff = d2[k] - (sx * sx + sy * sy + sz * sz)
            error = abs(diff) / (2.0 * d2[k])
            if error > worst:
                worst = error
                worst_bond = k
            if error <= tol or sweep == max_iter:
                continue
            rx, ry, rz = separation(reference, i, j, lengths, inverse, tilt)
            rs = rx * sx + ry * sy + rz * sz
            if not rs > 1e-6 * d2[k]:
                return max_iter + 1, np.inf, k
            g = diff / (2.0 * rs * (inverse_masses[i] + inverse_masses[j]))
            gi = g * inverse_masses[i]
            gj = g * inverse_masses[j]
            positions[i, 0] += gi * rx
            positions[i, 1] += gi * ry
            positions[i, 2] += gi * rz
            positions[j, 0] -= gj * rx
            positions[j, 1] -= gj * ry
            positions[j, 2] -= gj * rz
            velocities[i, 0] += gi * rx * inverse_dt
            velocities[i, 1] += gi * ry * inverse_dt
            velocities[i, 2] += gi * rz * inverse_dt
            velocities[j, 0] -= gj * rx * inverse_dt
            velocities[j, 1] -= gj * ry * inverse_dt
            velocities[j, 2] -= gj * rz * inverse_dt
        if worst <= tol:
            return sweep, worst, worst_bond
    return max_iter + 1, worst, worst_bond


@njit(cache=True, error_model="numpy")
def _rattle(
    positions, velocities, bonds, d2, inverse_masses, lengths, inverse, tilt, dt, tol, max_iter
):
    """RATTLE sweeps until every |r . v_ij| dt / d^2 <= tol; velocities written in place.

    Returns (sweeps, largest residual of the last sweep, its bond);
    sweeps = max_iter + 1 when not converged.
    """
    n_bonds = bonds.shape[0]
    # Positions do not move here: bond vectors and their weights once, before the sweeps.
    vectors = np.empty((n_bonds, 3))
    weights = np.empty(n_bonds)
    for k in range(n_bonds):
        i = bonds[k, 0]
        j = bonds[k, 1]
        vectors[k, 0], vectors[k, 1], vectors[k, 2] = separation(
            positions, i, j, lengths, inverse, tilt
        )
        r2 = vectors[k, 0] ** 2 + vectors[k, 1] ** 2 + vectors[k, 2] ** 2
        weights[k] = 1.0 / (r2 * (inverse_masses[i] + inverse_masses[j]))
    worst = 0.0
    worst_bond = -1
    for sweep in range(max_iter + 1):
        worst = 0.0
        worst_bond = -1
        for k in range(n_bonds):
            i = bonds[k, 0]
            j = bonds[k, 1]
            rx = vectors[k, 0]
            ry = vectors[k, 1]
            rz = vectors[k, 2]
            rv = (
                rx * (velocities[i, 0] - velocities[j, 0])
                + ry * (velocities[i, 1] - velocities[j, 1])
                + rz * (velocities[i, 2] - velocities[j, 2])
            )
            error = abs(rv) * dt / d2[k]
            if error > worst:
                worst = error
                worst_bond = k
            if error <= tol or sweep == max_iter:
                continue
            g = rv * weights[k]
            gi = g * inverse_masses[i]
            gj = g * inverse_masses[j]
            velocities[i, 0] -= gi * rx
            velocities[i, 1] -= gi * ry
            velocities[i, 2] -= gi * rz
            velocities[j, 0] += gj * rx
            velocities[j, 1] += gj * ry
            velocities[j, 2] += gj * rz
        if worst <= tol:
            return sweep, worst, worst_bond
    return max_iter + 1, worst, worst_bond


__all__ = ["CONSTRAINTS", "BondConstraints", "ConstraintError", "Rattle"]
