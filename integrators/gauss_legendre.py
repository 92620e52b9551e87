"""Two-stage Gauss-Legendre implicit Runge-Kutta (order 4, symplectic), solved by Newton."""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from integrators._newton import (
    DIRECT_SOLVER_LIMIT,
    DIRECT_SOLVER_ROW_NNZ,
    PREDICTOR_HISTORY,
    NewtonOptions,
    extrapolation_weights,
    not_converged,
)
from integrators.base import ConvergenceError, amplification_roots
from integrators.implicit_euler import ImplicitBase
from md.errors import NonFiniteError
from potentials.base import SupportsHessian

_ROOT3 = math.sqrt(3.0)
#: The Butcher tableau: stage times c, weights b, matrix A.
NODES = np.array([0.5 - _ROOT3 / 6.0, 0.5 + _ROOT3 / 6.0])
WEIGHTS = np.array([0.5, 0.5])
MATRIX = np.array([[0.25, 0.25 - _ROOT3 / 6.0], [0.25 + _ROOT3 / 6.0, 0.25]])
#: A^2: the stage positions' coefficients of dt^2 a_j (x'' = a eliminated).
_POSITION_MATRIX = MATRIX @ MATRIX
#: b A: the end position's coefficients of dt^2 a_j.
_POSITION_WEIGHTS = WEIGHTS @ MATRIX
_ARMIJO = 1e-4
_MAX_BACKTRACKS = 30
_FORCING = 0.3
_MAX_FORCING = 0.1
#: GMRES: inner iterations per restart, and restarts, before it gives up (then LU).
_GMRES_RESTART = 40
_GMRES_CYCLES = 5


class StageSolver(NewtonOptions):
    """Newton's method on the two coupled stages of a Gauss-Legendre step.

    The unknowns are the stage displacements D_i = X_i - x0 (i = 1, 2); with
    a_j = M^-1 F(x0 + D_j) the stage equations are

        R_i = D_i - dt c_i v0 - dt^2 sum_j (A^2)_ij a_j = 0,

    their Jacobian (rows times M) ``M delta_ij + dt^2 (A^2)_ij H(X_j)``, from
    the force field's Hessian operator at each stage: assembled and
    factorised by sparse LU for small, sparse systems (as
    :class:`integrators._newton.IncrementalSolver` decides), else applied
    matrix-free in GMRES with a block-diagonal Jacobi preconditioner, to a
    relative residual 0.3 times Newton's (at most 0.1). The system is not
    symmetric, so no potential is minimised; the line search backtracks on the
    merit 1/2 sum_i R_i^T M R_i, for which the Newton direction is always a
    descent direction (its slope is minus twice the merit). The residual, as
    the incremental solver's, is the largest |R| over dt^2 a_scale with
    a_scale = max(max|M^-1 F(x0)|, max|v0| / dt). Force fields without a
    Hessian get the Jacobian's mass part only: a damped fixed-point iteration.

    The start is the stages' explicit prediction from the start accelerations
    of the last steps extrapolated to the stage times (``history``, as the
    incremental solver keeps it, and checkpointed the same way), or, when
    that prediction is far off (stiff forces), the force-free D_i = dt c_i v0.
    """

    def solve(self, state, forcefield, dt: float, name: str):
        """Return the converged stage accelerations a_j, shape (2, 3N).

        The positions are left at the last stage evaluated; on failure they
        are restored and :class:`ConvergenceError` is raised.
        """
        x0 = state.positions.copy()
        try:
            return self._solve(state, forcefield, dt, name, x0)
        finally:
            state.positions[:] = x0

    def _solve(self, state, forcefield, dt, name, x0):
        stats = self.statistics
        step = state.step + 1
        masses = np.repeat(state.masses, 3)
        inverse_masses = 1.0 / masses
        dt2 = dt * dt
        accelerations0 = forcefield.compute(state, virial=False).forces.ravel() * inverse_masses
        velocities0 = state.velocities.ravel().copy()
        scale = max(
            float(np.max(np.abs(accelerations0), initial=0.0)),
            float(np.max(np.abs(velocities0), initial=0.0)) / dt,
        )
        if not (np.isfinite(scale) and scale > 0.0):
            scale = 1.0
        base = np.outer(dt * NODES, velocities0)  # (2, 3N): D_i without forces
        history = [a for a in self.history if a.shape == accelerations0.shape]
        predicted = np.empty_like(base)
        for j, node in enumerate(NODES):
            if history:
                w0, w1, w2 = extrapolation_weights(len(history), node)
                predicted[j] = w0 * accelerations0 + w1 * history[-1] + w2 * history[0]
            else:
                predicted[j] = accelerations0
        use_newton = all(isinstance(p, SupportsHessian) for p in forcefield.potentials)

        def evaluate(displacements):
            """Return (R, a, residual, merit) at the stages x0 + D_j."""
            stage_accelerations = np.empty_like(displacements)
            for j in range(2):
                np.add(x0, displacements[j].reshape(x0.shape), out=state.positions)
                forces = forcefield.compute(state, virial=False).forces.ravel()
                stage_accelerations[j] = forces * inverse_masses
            residual_vector = displacements - base - dt2 * (_POSITION_MATRIX @ stage_accelerations)
            largest = float(np.max(np.abs(residual_vector)))
            merit = 0.5 * float(np.sum(residual_vector * residual_vector * masses))
            return residual_vector, stage_accelerations, largest / (dt2 * scale), merit

        displacements = base + dt2 * (_POSITION_MATRIX @ predicted)
        try:
            values = evaluate(displacements)
        except NonFiniteError:
            values = None
        if values is None or not values[2] < 1.0:
            displacements = base.copy()
            values = evaluate(displacements)
        residual_vector, stage_accelerations, residual, merit = values
        iterations = 0
        while residual > self.tol and iterations < self.max_iter:
            iterations += 1
            stats["newton_iterations"] += 1
            direction = self._direction(
                state,
                forcefield,
                x0,
                displacements,
                residual_vector,
                masses,
                dt2,
                residual,
                use_newton,
            )
            alpha = 1.0
            for _ in range(_MAX_BACKTRACKS):
                trial = displacements + alpha * direction
                try:
                    values = evaluate(trial)
                except NonFiniteError:
                    values = None
                # Armijo on the merit (slope -2 merit), or, at round-off, any step that
                # lowers the residual.
                if values is not None and (
                    values[3] <= (1.0 - 2.0 * _ARMIJO * alpha) * merit
                    or (values[3] <= merit * (1.0 + 1e-12) and values[2] < residual)
                ):
                    break
                alpha *= 0.5
                stats["line_search_backtracks"] += 1
            else:
                raise ConvergenceError(
                    step,
                    residual,
                    f"step {step}: {name} Newton solve stalled after {iterations} iteration(s): "
                    f"no step along the Newton direction lowers the stage residual (residual "
                    f"{residual:.3g}, tol {self.tol:g}); try a smaller dt",
                )
            displacements = trial
            residual_vector, stage_accelerations, residual, merit = values
        if not residual <= self.tol:
            raise not_converged(step, residual, name, self.max_iter, self.tol)
        stats["steps"] += 1
        self.history = (history + [accelerations0])[-PREDICTOR_HISTORY:]
        return stage_accelerations

    def _direction(
        self,
        state,
        forcefield,
        x0,
        displacements,
        residual_vector,
        masses,
        dt2,
        residual,
        use_newton,
    ):
        """Solve (M delta_ij + dt^2 (A^2)_ij H_j) p_j = -M R_i for the Newton step p."""
        stats = self.statistics
        rhs = -(residual_vector * masses).ravel()
        if not use_newton:
            return -residual_vector
        operators = []
        for j in range(2):
            np.add(x0, displacements[j].reshape(x0.shape), out=state.positions)
            operators.append(forcefield.hessian_operator(state))
            stats["hessian_evaluations"] += 1
        size = len(masses)
        solver = self.linear_solver
        if solver == "auto":
            sparse = all(op.nnz <= DIRECT_SOLVER_ROW_NNZ * size for op in operators)
            solver = "direct" if size < DIRECT_SOLVER_LIMIT and sparse else "cg"
        coefficients = dt2 * _POSITION_MATRIX
        if solver == "direct":
            direction = _stage_lu(masses, coefficients, [op.tocsr() for op in operators], rhs)
            stats["linear_iterations"] += 1
        else:
            # The stage system is not symmetric: GMRES, with the inverse of each stage's
            # diagonal block's diagonal as preconditioner.
            diagonals = [
                masses + coefficients[j, j] * op.diagonal() for j, op in enumerate(operators)
            ]
            inverse_diagonal = np.concatenate(
                [1.0 / np.where(d > 0.0, d, masses) for d in diagonals]
            )

            def product(p):
                parts = p.reshape(2, size)
                applied = [op.matvec(parts[j]) for j, op in enumerate(operators)]
                out = np.empty_like(parts)
                for i in range(2):
                    out[i] = (
                        masses * parts[i]
                        + coefficients[i, 0] * applied[0]
                        + coefficients[i, 1] * applied[1]
                    )
                return out.ravel()

            counted = [0]

            def count(_):
                counted[0] += 1

            eta = min(_MAX_FORCING, max(_FORCING * residual, self.tol / max(residual, 1e-300)))
            direction, info = spla.gmres(
                spla.LinearOperator((2 * size, 2 * size), matvec=product),
                rhs,
                rtol=eta,
                atol=0.0,
                M=spla.LinearOperator((2 * size, 2 * size), matvec=lambda r: inverse_diagonal * r),
                callback=count,
                callback_type="pr_norm",
                restart=_GMRES_RESTART,
                maxiter=_GMRES_CYCLES,
            )
            stats["linear_iterations"] += counted[0]
            if info != 0 and 2 * size <= 2 * DIRECT_SOLVER_LIMIT:
                # GMRES stalls where the step is long against the stiffest mode (the
                # system is then far from mass-dominated): factorise instead.
                stats["fallbacks"] += 1
                hessians = [op.tocsr() for op in operators]
                direction = _stage_lu(masses, coefficients, hessians, rhs)
                stats["linear_iterations"] += 1
        if not np.all(np.isfinite(direction)):
            stats["fallbacks"] += 1
            return -residual_vector
        return direction.reshape(2, size)


def _stage_lu(masses, coefficients, hessians, rhs):
    """Solve the assembled stage system (M delta_ij + c_ij H_j) p = rhs by sparse LU
    (NaNs if it is exactly singular)."""
    mass_matrix = sp.diags(masses)
    blocks = [[mass_matrix if i == j else None for j in range(2)] for i in range(2)]
    for i in range(2):
        for j in range(2):
            term = coefficients[i, j] * hessians[j]
            blocks[i][j] = term if blocks[i][j] is None else blocks[i][j] + term
    try:
        return spla.splu(sp.bmat(blocks, format="csc")).solve(rhs)
    except RuntimeError:  # exactly singular
        return np.full_like(rhs, np.nan)


class GaussLegendre4(ImplicitBase):
    r"""The two-stage Gauss-Legendre Runge-Kutta method: order 4, symplectic, A-stable.

    The collocation method at the Gauss points
    :math:`c_{1,2} = \tfrac12 \mp \tfrac{\sqrt3}{6}`: with
    :math:`A = \begin{pmatrix} 1/4 & 1/4 - \sqrt3/6 \\ 1/4 + \sqrt3/6 & 1/4
    \end{pmatrix}`, :math:`b = (\tfrac12, \tfrac12)`, applied to
    :math:`\dot x = v`, :math:`\dot v = a(x) = M^{-1}F(x)`, the stage positions
    satisfy

    .. math::

        X_i = x_0 + c_i \Delta t\, v_0 + \Delta t^2 \sum_j (A^2)_{ij}\, a(X_j),

    and the step ends at
    :math:`x_1 = x_0 + \Delta t\, v_0 + \Delta t^2 \sum_j (bA)_j\, a(X_j)`,
    :math:`v_1 = v_0 + \Delta t \sum_j b_j\, a(X_j)`. The two stages are solved
    together by Newton's method (:class:`StageSolver`: the force field's
    Hessian operator at both stages, LU or GMRES, a line search on the mass
    weighted residual, the implicit family's predictor and ``statistics``;
    two force evaluations and two Hessians per iteration).

    It is the highest-order method of two stages (order 2s = 4), symplectic
    (so the step map preserves the symplectic form, and energy errors stay
    bounded over long runs), symmetric, and it conserves every quadratic
    invariant exactly, so a harmonic oscillator keeps its energy to the
    solver's tolerance at any ``dt``. On that oscillator its amplification is
    the (2, 2) Pade approximant of e^(i omega dt): modulus 1, no damping, phase
    error O((omega dt)^5) per step.

    Parameters
    ----------
    dt, tol, max_iter, linear_solver
        As for :class:`integrators.implicit_euler.ImplicitEuler`; the
        residual is that of the stage equations (above), relative to
        dt^2 max(max|M^-1 F(x0)|, max|v0| / dt), and ``"cg"`` means the
        matrix-free Krylov solver (GMRES: the stage system is not symmetric).

    Attributes
    ----------
    statistics : dict of int
        As for :class:`integrators.implicit_euler.ImplicitEuler`
        (``hessian_evaluations`` counts one per stage and iteration).

    Examples
    --------
    >>> GaussLegendre4(dt=0.05).describe()["type"]
    'gauss_legendre4'

    References
    ----------
    J. C. Butcher, Math. Comp. 18, 50 (1964). E. Hairer, C. Lubich, G. Wanner,
    Geometric Numerical Integration, 2nd ed. (Springer, 2006), sections II.1.3
    and VI.4.
    """

    order = 4

    _type = "gauss_legendre4"
    _label = "Gauss-Legendre 4"

    def __init__(
        self, dt: float, tol: float = 1e-8, max_iter: int = 50, linear_solver: str = "auto"
    ) -> None:
        super().__init__(dt, tol, max_iter, linear_solver)
        self._solver = StageSolver(self.tol, self.max_iter, self.linear_solver, self.statistics)

    @staticmethod
    def amplification(omega_dt: float):
        """rho = (1 - z^2/12 + i z/2) / (1 - z^2/12 - i z/2), z = omega dt, and its
        conjugate: ``|rho| = 1`` for every omega dt."""
        z = float(omega_dt)
        p, q = 1.0 - z * z / 12.0, 0.5 * z
        return amplification_roots([p * p + q * q, -2.0 * (p * p - q * q), p * p + q * q])

    def step(self, state, forcefield) -> None:
        """Advance ``state`` by ``dt`` in place."""
        dt = self.dt
        stage_accelerations = self._solver.solve(state, forcefield, dt, self._label)
        shape = state.positions.shape
        velocities = state.velocities
        kick = (WEIGHTS @ stage_accelerations).reshape(shape)
        drift = (_POSITION_WEIGHTS @ stage_accelerations).reshape(shape)
        state.positions += dt * velocities + (dt * dt) * drift
        velocities += dt * kick
        self.end_step(state)


__all__ = ["GaussLegendre4", "StageSolver"]
