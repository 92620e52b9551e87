"""The trapezoidal rule (Crank-Nicolson), solved by the implicit methods' Newton solver."""

from __future__ import annotations

from integrators.implicit_euler import ImplicitBase, cayley_roots


def trapezoidal_displacement(solver, state, forcefield, dt: float, name: str):
    """Solve one trapezoidal step for its displacement and leave ``state`` at its end.

    With h = dt / 2 and a0 = M^-1 F(x0), the rule's position equation
    x1 = x0 + dt v0 + h^2 (a0 + a1) is ``M (dx - s) = h^2 F(x0 + dx)`` with the
    shift s = 2 h v0 + h^2 a0: the incremental potential of a backward Euler
    step of h whose velocity is s / h, which ``solver`` (an
    :class:`integrators._newton.IncrementalSolver`) minimises. Sets the
    positions to x0 + dx and the velocities to v1 = 2 dx / dt - v0 (the
    velocity equation v1 = v0 + h (a0 + a1) then holds to the solver's
    tolerance); returns dx (N, 3). Leaves step and time alone.
    """
    h = 0.5 * dt
    forces = forcefield.compute(state, virial=False).forces  # cached: the last step's end
    shifted = 2.0 * state.velocities + h * forces / state.masses[:, None]
    displacement = solver.solve(state, forcefield, h, name, reach=1.0, velocities=shifted)
    state.velocities[:] = displacement * (2.0 / dt) - state.velocities
    return displacement


class Trapezoidal(ImplicitBase):
    r"""The trapezoidal rule (Crank-Nicolson): second order, A-stable, no damping.

    .. math::

        x_1 = x_0 + \frac{\Delta t}{2} (v_0 + v_1), \qquad
        v_1 = v_0 + \frac{\Delta t}{2} \left(M^{-1} F(x_0) + M^{-1} F(x_1)\right)

    The forces enter at both ends of the step (implicit midpoint takes them
    at the middle). Eliminating :math:`v_1` leaves
    :math:`M (x_1 - x_0 - \Delta t v_0 - h^2 a_0) = h^2 F(x_1)` with
    :math:`h = \Delta t/2`: the stationarity condition of implicit Euler's
    incremental potential over ``h`` with a shifted start velocity, solved by
    the same Newton machinery (Hessian :math:`M + h^2 H(x_1)`, line search,
    negative-curvature clamping; ``statistics``). On linear forces it is the
    same map as implicit midpoint, the Cayley transform: a harmonic
    oscillator's amplitude is kept exactly for any ``dt`` (A-stable), with
    phase :math:`2\arctan(\omega \Delta t / 2)` per step, so stiff modes are
    neither damped nor blown up but oscillate with a wrong, slow phase. It is
    symmetric (time-reversible) but not symplectic; it is conjugate to the
    symplectic implicit midpoint rule, so on nonlinear forces its energy
    error stays bounded without drift in the same way. The forces at the
    start are the previous step's end forces, taken from the force field's
    cache.

    Parameters
    ----------
    dt, tol, max_iter, linear_solver
        As for :class:`integrators.implicit_euler.ImplicitEuler` (the residual
        is that of the position equation above, with ``h = dt / 2``).

    Attributes
    ----------
    statistics : dict of int
        As for :class:`integrators.implicit_euler.ImplicitEuler`.

    Examples
    --------
    >>> Trapezoidal(dt=0.05).describe()["type"]
    'trapezoidal'

    References
    ----------
    J. Crank, P. Nicolson, Proc. Camb. Phil. Soc. 43, 50 (1947). E. Hairer,
    G. Wanner, Solving Ordinary Differential Equations II, 2nd ed. (Springer,
    1996), section IV.3 (A-stability).
    """

    order = 2

    _type = "trapezoidal"
    _label = "trapezoidal rule"

    @staticmethod
    def amplification(omega_dt: float):
        """The Cayley transform, as implicit midpoint's: ``|rho| = 1`` for every omega dt."""
        return cayley_roots(omega_dt)

    def step(self, state, forcefield) -> None:
        """Advance ``state`` by ``dt`` in place."""
        trapezoidal_displacement(self._solver, state, forcefield, self.dt, self._label)
        self.end_step(state)


__all__ = ["Trapezoidal", "trapezoidal_displacement"]
