"""Extended position-based dynamics (XPBD): stiff bonds as compliant constraints.

Real-time physics steps stiff springs at display rates by treating them as
constraints with a compliance (the inverse stiffness) and moving the atoms of
one constraint at a time (Gauss-Seidel). Here the bonds of the force field's
harmonic and FENE potentials are those constraints, with compliance from
their spring constants, and every other force (pairs) is explicit.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from integrators.base import DT, IntegratorBase, amplification_roots, check_dt
from md._checks import count, positive
from md.box import periodic_lengths, periodic_tilt, separation
from md.errors import NonFiniteError
from md.schema import Key
from potentials.base import SupportsBondLaw

#: Kernel codes of the bond laws.
_FORMS = {"harmonic": 0, "fene": 1}
#: A FENE bond found at or beyond r_max during the sweeps is put back to this
#: fraction of r_max (its law has no value there).
_FENE_RECOVERY = 0.999


class XPBD(IntegratorBase):
    r"""Extended position-based dynamics for bonded springs and FENE bonds.

    One step (Macklin, Mueller and Chentanez 2016, Algorithm 1, one substep):

    1. the explicit prediction :math:`\tilde x = x_n + \Delta t\, v_n + \Delta t^2
       M^{-1} F_\text{other}(x_n)`, with the forces of every potential that is
       not a bond law (pair forces) at the start of the step;
    2. Gauss-Seidel sweeps over the bonds, each bond moving its two atoms
       along the bond by :math:`\pm w_{i,j}\, \Delta\lambda`
       (:math:`w = 1/m`), with :math:`\Delta\lambda = -(C + \tilde\alpha
       \lambda)/(w_i + w_j + \tilde\alpha)` for a harmonic bond
       (:math:`C = r - r_0`, compliance :math:`\alpha = 1/k`,
       :math:`\tilde\alpha = \alpha / \Delta t^2`); a FENE bond uses the same
       update with its law linearised at the current length (:math:`C = U'/U''`,
       :math:`\alpha = 1/U''`), which is Newton's method on the bond's equation
       :math:`\lambda + \Delta t^2 U'(r) = 0`;
    3. :math:`v_{n+1} = (x_{n+1} - x_n)/\Delta t`.

    Converged, the sweeps satisfy every bond's implicit Euler equation
    :math:`\lambda_b + \Delta t^2 U'_b(r_b) = 0`, with the other forces taken
    explicitly (symplectic Euler for them). Each update moves a bond's atoms
    along its direction at that moment, not at the end of the step (XPBD
    leaves out the geometric stiffness, eq. 11 of the paper), so for bonds
    that turn during the step the result differs from implicit Euler's, by
    O(dt^4) in one step (measured; below both methods' O(dt^2) local error),
    and for bonds that keep their direction it is implicit Euler's. So the
    method is first order and, on the bonds, damps as implicit Euler does
    (amplitude ratio :math:`1/\sqrt{1 + (\omega\Delta t)^2}` per step on a bond
    alone). With fewer sweeps than convergence needs, stiff bonds act softer
    still; the steps that end unconverged are counted, not refused: a fixed
    budget of sweeps per step is XPBD's contract, as in real-time physics.

    What it conserves: linear momentum exactly (each bond update is equal and
    opposite, and so are the pair forces), and every bond length within the
    compliance it is given. What it does not: the energy (dissipated, as by
    implicit Euler, at a rate that grows with omega dt), angular momentum
    (only to O(dt) per step; the corrections act along the bonds of the
    moving configuration), the symplectic form, and time reversibility. The
    explicit forces keep their own stability limit (omega dt < 2 for their
    fastest mode), so the method pays off when the bonds are much stiffer
    than everything else and the pair forces stay soft at the step taken:
    two beads that run into a repulsive wall (WCA) within one long step get
    an explicit kick from deep inside it, and the run blows up.

    Parameters
    ----------
    dt : float
        Time step [time].
    iterations : int
        Most Gauss-Seidel sweeps over the bonds per step.
    tol : float
        The sweeps stop early once the largest bond residual
        :math:`|\lambda_b + \Delta t^2 U'_b|\, (w_i + w_j)`, a length, is below
        ``tol`` times :math:`\Delta t^2 \max(\max|a|, \max|v_n| / \Delta t)`,
        with :math:`a` the start accelerations of the bonds and of the other
        forces (the implicit solvers' relative residual).
    compliance : float, optional
        The compliance [length^2/energy] of every harmonic bond, in place of
        1/k: for reproducing a setup given in XPBD's own terms. The dynamics
        then follow springs of stiffness 1/compliance, while the force field
        still reports the potential's energy. Default: 1/k of each bond.

    Attributes
    ----------
    statistics : dict of int
        Cumulative ``steps``, ``sweeps``, ``unconverged_steps`` (steps that
        used every sweep without reaching ``tol``) and ``overstretched`` (FENE
        bonds found at or past r_max during a sweep and put back inside).

    Examples
    --------
    >>> XPBD(dt=0.05, iterations=20).describe()["type"]
    'xpbd'

    References
    ----------
    M. Macklin, M. Mueller, N. Chentanez, XPBD: position-based simulation of
    compliant constrained dynamics, Proc. Motion in Games, 49 (2016).
    M. Macklin, K. Storey, M. Lu, P. Terdiman, N. Chentanez, S. Jeschke,
    M. Mueller, Small steps in physics simulation, Proc. SCA (2019).
    """

    order = 1
    splits_forces = True
    CONFIG_KEYS = (
        DT,
        Key(
            "iterations",
            "integer",
            50,
            minimum=1,
            doc="Most Gauss-Seidel sweeps over the bonds per step; a step that uses them all "
            "without reaching `tol` is counted (`unconverged_steps`), not refused.",
        ),
        Key(
            "tol",
            "number",
            1e-8,
            positive=True,
            doc="The sweeps stop once every bond's residual, relative to the step's largest "
            "acceleration term (as the implicit solvers' `tol`), is below it.",
        ),
        Key(
            "compliance",
            "number",
            None,
            unit="length^2/energy",
            positive=True,
            doc="Every harmonic bond's compliance, in place of 1/`k` (positive and finite).",
            default_doc="1/`k` of each bond",
        ),
    )

    def __init__(
        self, dt: float, iterations: int = 50, tol: float = 1e-8, compliance: float | None = None
    ) -> None:
        self.dt = check_dt(dt)
        self.iterations = count(iterations, "iterations", minimum=1)
        self.tol = positive(tol, "tol")
        if compliance is not None:
            try:
                compliance = positive(compliance, "compliance")
            except ValueError:
                raise ValueError(
                    f"compliance must be a positive, finite number (the inverse stiffness "
                    f"1/k of the harmonic bonds, [length^2/energy]), got {compliance!r}"
                ) from None
        self.compliance = compliance
        self.statistics = {"steps": 0, "sweeps": 0, "unconverged_steps": 0, "overstretched": 0}
        self._laws = None  # (key, forms, bonds, k, lengths) of the last force field

    @staticmethod
    def amplification(omega_dt: float):
        """On a harmonic bond alone, converged: implicit Euler's 1 / (1 -+ i omega dt)."""
        z2 = float(omega_dt) ** 2
        return amplification_roots([1.0 + z2, -2.0, 1.0])

    def split(self, forcefield) -> tuple[tuple[int, ...], tuple[int, ...]]:
        """Return the indices of (the bond potentials, the other potentials).

        Raises
        ------
        ValueError
            If no potential offers a bond law (``bond_law()``: harmonic springs,
            FENE bonds) with at least one bond.
        """
        potentials = forcefield.potentials
        bonded = tuple(
            i
            for i, p in enumerate(potentials)
            if isinstance(p, SupportsBondLaw) and len(p.bond_law().bonds)
        )
        if not bonded:
            kinds = ", ".join(p.describe().get("type", type(p).__name__) for p in potentials)
            raise ValueError(
                "xpbd found no bonds to solve: it moves the bonds of harmonic (spring) and FENE "
                f"potentials as compliant constraints, and the potentials here ({kinds}) have "
                "none; add bonds, or choose another integrator"
            )
        return bonded, tuple(i for i in range(len(potentials)) if i not in bonded)

    def _bond_arrays(self, forcefield, bonded):
        """Per-bond (forms, bonds, k, lengths) of the bond potentials, kept while they stay."""
        key = tuple(id(forcefield.potentials[i]) for i in bonded)
        if self._laws is None or self._laws[0] != key:
            laws = [forcefield.potentials[i].bond_law() for i in bonded]
            forms = np.concatenate([np.full(len(w.bonds), _FORMS[w.form], np.int64) for w in laws])
            stiffness = np.concatenate(
                [
                    np.full(len(w.bonds), 1.0 / self.compliance)
                    if (w.form == "harmonic" and self.compliance is not None)
                    else w.k
                    for w in laws
                ]
            ).astype(np.float64)
            bonds = np.ascontiguousarray(np.concatenate([w.bonds for w in laws]), dtype=np.int64)
            lengths = np.concatenate([w.length for w in laws]).astype(np.float64)
            self._laws = (key, forms, bonds, stiffness, lengths)
        return self._laws[1:]

    def step(self, state, forcefield) -> None:
        """Advance ``state`` by ``dt`` in place."""
        dt = self.dt
        bonded, others = self.split(forcefield)
        forms, bonds, stiffness, lengths = self._bond_arrays(forcefield, bonded)
        inverse_masses = 1.0 / state.masses
        bond_forces = forcefield.compute_subset(state, bonded).forces
        if others:
            forces = forcefield.compute_subset(state, others).forces
        else:
            forces = np.zeros_like(state.positions)
        velocities = state.velocities
        scale = max(
            float(np.max(np.abs(forces * inverse_masses[:, None]), initial=0.0)),
            float(np.max(np.abs(bond_forces * inverse_masses[:, None]), initial=0.0)),
            float(np.max(np.abs(velocities), initial=0.0)) / dt,
        )
        if not (np.isfinite(scale) and scale > 0.0):
            scale = 1.0
        displacement = dt * velocities + (dt * dt) * forces * inverse_masses[:, None]
        start = state.positions.copy()
        state.positions += displacement
        box_lengths, inverse = periodic_lengths(state.box, state.pbc)
        multipliers = np.zeros(len(bonds))
        sweeps, largest, overstretched = _xpbd_sweeps(
            state.positions,
            displacement,
            inverse_masses,
            box_lengths,
            inverse,
            periodic_tilt(state.tilt, state.pbc),
            bonds,
            forms,
            stiffness,
            lengths,
            dt * dt,
            multipliers,
            self.iterations,
            self.tol * dt * dt * scale,
        )
        if not np.all(np.isfinite(state.positions)):
            state.positions[:] = start
            raise NonFiniteError(
                f"step {state.step + 1}: the XPBD sweeps gave non-finite positions"
            )
        velocities[:] = displacement / dt
        stats = self.statistics
        stats["steps"] += 1
        stats["sweeps"] += int(sweeps)
        stats["overstretched"] += int(overstretched)
        if not largest <= self.tol * dt * dt * scale:
            stats["unconverged_steps"] += 1
        self.end_step(state)

    def reset(self) -> None:
        """Nothing to forget: XPBD is a one-step method (``statistics`` are kept)."""

    def get_state(self) -> dict:
        """Return the private state for a checkpoint: the cumulative statistics."""
        return {"statistics": dict(self.statistics)}

    def set_state(self, saved: dict) -> None:
        """Restore :meth:`get_state`'s result."""
        self.statistics.update({k: int(v) for k, v in saved.get("statistics", {}).items()})

    def describe(self) -> dict:
        out = {"type": "xpbd", "dt": self.dt, "iterations": self.iterations, "tol": self.tol}
        if self.compliance is not None:
            out["compliance"] = self.compliance
        return out


@njit(cache=True, error_model="numpy")
def _xpbd_sweeps(
    positions,
    displacement,
    inverse_masses,
    lengths,
    inverse,
    tilt,
    bonds,
    forms,
    stiffness,
    rest,
    dt2,
    multipliers,
    max_sweeps,
    tolerance,
):
    """Gauss-Seidel sweeps over the bonds; return (sweeps, largest residual, overstretched).

    positions, displacement: (N, 3), moved in place by the same amounts;
    bonds (B, 2); forms (B,): 0 harmonic (rest = r0), 1 FENE (rest = r_max);
    stiffness (B,): k; multipliers (B,): the accumulated lambda (zeroed by
    the caller). A bond's residual is |lambda + dt2 U'(r)| (w_i + w_j), a
    length, taken before its update; the sweeps stop when the largest of a
    sweep is at most ``tolerance`` or after ``max_sweeps``. Bonds of zero
    length, zero stiffness or two immovable atoms are skipped.
    """
    sweeps = 0
    largest = np.inf
    overstretched = 0
    while sweeps < max_sweeps:
        sweeps += 1
        largest = 0.0
        for b in range(bonds.shape[0]):
            i = bonds[b, 0]
            j = bonds[b, 1]
            w = inverse_masses[i] + inverse_masses[j]
            k = stiffness[b]
            dx, dy, dz = separation(positions, i, j, lengths, inverse, tilt)
            r = np.sqrt(dx * dx + dy * dy + dz * dz)
            if r == 0.0 or w == 0.0 or k == 0.0:
                continue
            lam = multipliers[b]
            if forms[b] == 0:
                first = k * (r - rest[b])
                second = k
                delta = -(lam + dt2 * first) / (1.0 + dt2 * second * w)
                size = abs(lam + dt2 * first) * w
            else:
                x = r * r / (rest[b] * rest[b])
                if x < 1.0:
                    s = 1.0 - x
                    first = k * r / s
                    second = k * (1.0 + x) / (s * s)
                    delta = -(lam + dt2 * first) / (1.0 + dt2 * second * w)
                    size = abs(lam + dt2 * first) * w
                else:
                    overstretched += 1
                    delta = -(r - _FENE_RECOVERY * rest[b]) / w
                    size = np.inf
            largest = max(largest, size)
            multipliers[b] = lam + delta
            scale = delta / r
            _move(positions, displacement, i, inverse_masses[i] * scale, dx, dy, dz)
            _move(positions, displacement, j, -inverse_masses[j] * scale, dx, dy, dz)
        if largest <= tolerance:
            break
    return sweeps, largest, overstretched


@njit(cache=True, inline="always")
def _move(positions, displacement, atom, factor, dx, dy, dz):
    """Move ``atom`` by factor * (dx, dy, dz) in both arrays."""
    positions[atom, 0] += factor * dx
    positions[atom, 1] += factor * dy
    positions[atom, 2] += factor * dz
    displacement[atom, 0] += factor * dx
    displacement[atom, 1] += factor * dy
    displacement[atom, 2] += factor * dz


__all__ = ["XPBD"]
