"""Implicit (backward) Euler and implicit midpoint, solved by Newton's method.

Both solve one nonlinear system per step with the shared
:class:`integrators._newton.IncrementalSolver`, which minimises the
incremental potential of a backward Euler step over a time ``h``:

    Phi(x) = 1/2 (x - x0 - h v0)^T M (x - x0 - h v0) + h^2 U(x).

Implicit Euler takes ``h = dt``; implicit midpoint is a backward Euler half
step to the midpoint followed by a forward Euler half step, so it takes
``h = dt / 2`` and extrapolates.
"""

from __future__ import annotations

import numpy as np

from integrators._newton import (
    LINEAR_SOLVERS,
    PREDICTOR_HISTORY,
    IncrementalSolver,
    check_solver_options,
    new_statistics,
)
from integrators.base import DT, IntegratorBase, amplification_roots, check_dt
from md.schema import Key


class ImplicitBase(IntegratorBase):
    """Options, statistics, the Newton solver and its checkpointed predictor history,
    shared by the implicit methods built on :class:`integrators._newton.IncrementalSolver`
    (implicit Euler, implicit midpoint, the trapezoidal rule, BDF2) and by
    Gauss-Legendre (whose stage solver keeps the same ``history``)."""

    _type = ""
    _label = ""
    CONFIG_KEYS = (
        DT,
        Key(
            "tol",
            "number",
            1e-8,
            doc="Newton's convergence threshold on the relative residual (an acceleration "
            "error relative to the largest of the step's accelerations and velocities / "
            "`dt`), at least 4 x the double epsilon (8.9e-16) and below 1.",
        ),
        Key("max_iter", "integer", 50, doc="Most Newton iterations per step."),
        Key(
            "linear_solver",
            "string",
            "auto",
            choices=LINEAR_SOLVERS,
            doc='Sparse LU (`"direct"`) or conjugate gradients (`"cg"`); `"auto"` factorises '
            "small bonded systems (below 3000 unknowns) and uses CG for the rest.",
        ),
    )

    def __init__(
        self, dt: float, tol: float = 1e-8, max_iter: int = 50, linear_solver: str = "auto"
    ) -> None:
        self.dt = check_dt(dt)
        self.tol, self.max_iter, self.linear_solver = check_solver_options(
            tol, max_iter, linear_solver
        )
        self.statistics = new_statistics()
        self._solver = IncrementalSolver(
            self.tol, self.max_iter, self.linear_solver, self.statistics
        )

    def reset(self) -> None:
        """Forget the accelerations of past steps that the predictor extrapolates.

        The next step starts from the explicit prediction. The cumulative
        ``statistics`` are kept.
        """
        self._solver.history = []

    def get_state(self) -> dict:
        """Return the private state for a checkpoint.

        The start accelerations M^-1 F of the last steps, which the predictor
        extrapolates (``(K, 3N)``, oldest first, K <= 2; None before the first
        step or after :meth:`reset`), and the statistics.
        """
        history = self._solver.history
        return {
            "start_accelerations": np.array(history) if history else None,
            "statistics": dict(self.statistics),
        }

    def set_state(self, saved: dict) -> None:
        """Restore :meth:`get_state`'s result.

        The next step then predicts as the saved run would have, so a resumed
        run repeats its iterations exactly.
        """
        history = saved.get("start_accelerations")
        if history is None:
            self._solver.history = []
        else:
            history = np.array(history, dtype=np.float64)
            if history.ndim != 2 or not 1 <= history.shape[0] <= PREDICTOR_HISTORY:
                raise ValueError(
                    f"start_accelerations must have shape (K, 3N) with 1 <= K <= "
                    f"{PREDICTOR_HISTORY}, got {history.shape}"
                )
            if not np.all(np.isfinite(history)):
                raise ValueError("start_accelerations must be finite")
            self._solver.history = [np.ascontiguousarray(row) for row in history]
        self.statistics.update({k: int(v) for k, v in saved.get("statistics", {}).items()})

    def describe(self) -> dict:
        return {"type": self._type, "dt": self.dt, "tol": self.tol, "max_iter": self.max_iter}


def cayley_roots(omega_dt: float):
    """Roots of (1 + z^2/4) rho^2 - 2 (1 - z^2/4) rho + (1 + z^2/4), z = omega dt: the
    amplification of implicit midpoint and the trapezoidal rule on linear forces."""
    q = 0.25 * float(omega_dt) ** 2
    return amplification_roots([1.0 + q, -2.0 * (1.0 - q), 1.0 + q])


class ImplicitEuler(ImplicitBase):
    r"""Implicit (backward) Euler: first order, unconditionally stable, dissipative.

    .. math::

        x_1 = x_0 + \Delta t\, v_1, \qquad v_1 = v_0 + \Delta t\, M^{-1} F(x_1)

    ``x_1`` minimises the incremental potential
    :math:`\Phi(x) = \tfrac12 (x - x_0 - \Delta t v_0)^T M (x - x_0 - \Delta t v_0)
    + \Delta t^2 U(x)`, found by Newton's method with the Hessian
    :math:`M + \Delta t^2 H(x)` (the force field's ``hessian``), a
    backtracking line search on :math:`\Phi`, and shifted or gradient steps
    where :math:`H` makes the Newton direction useless. Then
    :math:`v_1 = (x_1 - x_0) / \Delta t`. On a harmonic oscillator the energy
    shrinks by exactly :math:`1 / (1 + \omega^2 \Delta t^2)` per step; stiff
    modes are damped instead of blowing up, so ``dt`` can far exceed velocity
    Verlet's stability limit (at the price of accuracy and energy).

    Parameters
    ----------
    dt : float
        Time step [time].
    tol : float
        Convergence threshold of the relative residual: the largest error of
        :math:`(x - x_0 - \Delta t v_0)/\Delta t^2 = M^{-1}F(x)`, an
        acceleration, divided by :math:`\max(\max|M^{-1}F(x_0)|, \max|v_0|/\Delta t)`
        (see :class:`integrators._newton.IncrementalSolver`).
    max_iter : int
        Most Newton iterations per step.
    linear_solver : {"auto", "direct", "cg"}
        Sparse LU (``"direct"``) or Jacobi-preconditioned conjugate gradients
        truncated at negative curvature (``"cg"``); ``"auto"`` factorises
        systems below 3000 unknowns (3N) with at most ~10 partners per atom
        (bonded chains) and uses CG for the rest (dense pair networks such as
        liquids, where LU fill-in makes factorising slow).

    Attributes
    ----------
    statistics : dict of int
        Cumulative ``steps``, ``newton_iterations``, ``linear_iterations``
        (one per factorisation, or CG iterations), ``line_search_backtracks``,
        ``fallbacks`` (shifted or gradient directions, negative curvature),
        ``projections`` (iterations that clamped negative pair curvatures) and
        ``hessian_evaluations`` (fewer than the iterations where CG reused the
        last one: chord steps, see ``integrators._newton.IncrementalSolver``).

    Raises
    ------
    integrators.base.ConvergenceError
        From :meth:`step`, naming the step, when Newton does not reach
        ``tol`` within ``max_iter`` iterations; the state is then left as it
        was at the start of the step.

    Examples
    --------
    >>> integrator = ImplicitEuler(dt=0.01, tol=1e-10)
    >>> integrator.describe()["type"]
    'implicit_euler'

    References
    ----------
    E. Hairer, G. Wanner, Solving Ordinary Differential Equations II, 2nd ed.
    (Springer, 1996). C. Kane, J. E. Marsden, M. Ortiz, M. West, Int. J. Numer.
    Meth. Engng 49, 1295 (2000) (the incremental potential).
    """

    order = 1

    _type = "implicit_euler"
    _label = "implicit Euler"

    @staticmethod
    def amplification(omega_dt: float):
        """rho = 1 / (1 -+ i omega dt), the roots of (1 + (omega dt)^2) rho^2 - 2 rho + 1:
        the amplitude shrinks by 1 / sqrt(1 + (omega dt)^2) per step."""
        z2 = float(omega_dt) ** 2
        return amplification_roots([1.0 + z2, -2.0, 1.0])

    def step(self, state, forcefield) -> None:
        """Advance ``state`` by ``dt`` in place."""
        displacement = self._solver.solve(state, forcefield, self.dt, self._label)
        # The solver left the positions at x0 + dx.
        state.velocities[:] = displacement / self.dt
        self.end_step(state)


class ImplicitMidpoint(ImplicitBase):
    r"""Implicit midpoint rule: second order, symplectic, time-reversible.

    .. math::

        x_1 = x_0 + \Delta t \frac{v_0 + v_1}{2}, \qquad
        v_1 = v_0 + \Delta t\, M^{-1} F\!\left(\frac{x_0 + x_1}{2}\right)

    Written for the midpoint :math:`y = (x_0 + x_1)/2` this is a backward
    Euler step of :math:`h = \Delta t/2`: :math:`M (y - x_0 - h v_0) = h^2 F(y)`,
    the stationarity condition of the same incremental potential as
    :class:`ImplicitEuler` with :math:`\Delta t \to h`. The shared Newton
    solver finds :math:`y` (Jacobian :math:`M + h^2 H(y)`), then
    :math:`x_1 = 2 y - x_0` and :math:`v_1 = 2 (y - x_0)/h - v_0`. It conserves
    quadratic invariants exactly, so a harmonic oscillator keeps its energy to
    solver tolerance; it is stable for any ``dt`` on linear problems but, unlike
    implicit Euler, does not damp stiff modes.

    Parameters
    ----------
    dt, tol, max_iter, linear_solver
        As for :class:`ImplicitEuler` (the residual is that of the midpoint
        equation, with ``h = dt / 2`` in place of ``dt``).

    Attributes
    ----------
    statistics : dict of int
        As for :class:`ImplicitEuler`.

    Examples
    --------
    >>> ImplicitMidpoint(dt=0.05).describe()["type"]
    'implicit_midpoint'

    References
    ----------
    E. Hairer, C. Lubich, G. Wanner, Geometric Numerical Integration, 2nd ed.
    (Springer, 2006), section VI.3.
    """

    order = 2

    _type = "implicit_midpoint"
    _label = "implicit midpoint"

    @staticmethod
    def amplification(omega_dt: float):
        """rho = (1 +- i omega dt / 2) / (1 -+ i omega dt / 2) (the Cayley transform):
        ``|rho| = 1`` for every omega dt, phase 2 atan(omega dt / 2) per step."""
        return cayley_roots(omega_dt)

    def step(self, state, forcefield) -> None:
        """Advance ``state`` by ``dt`` in place."""
        half = 0.5 * self.dt
        x0 = state.positions.copy()
        displacement = self._solver.solve(state, forcefield, half, self._label, reach=0.5)
        state.positions[:] = x0 + 2.0 * displacement
        state.velocities[:] = 2.0 * displacement / half - state.velocities
        self.end_step(state)


__all__ = ["ImplicitEuler", "ImplicitMidpoint"]
