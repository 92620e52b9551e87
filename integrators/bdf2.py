"""BDF2: the second-order backward differentiation formula, as an incremental potential."""

from __future__ import annotations

import numpy as np

from integrators.base import amplification_roots
from integrators.implicit_euler import ImplicitBase

#: Alexander's two-stage, stiffly accurate, L-stable SDIRK method: A = [[g, 0], [1 - g, g]].
SDIRK_GAMMA = 1.0 - 1.0 / np.sqrt(2.0)
#: Keys of BDF2's own history in :meth:`BDF2.get_state` (besides the predictor's).
_HISTORY_KEYS = ("last_displacement", "previous_velocities")


class BDF2(ImplicitBase):
    r"""Second-order backward differentiation (BDF2): A-stable and L-stable, damping.

    Applied to :math:`\dot x = v`, :math:`\dot v = M^{-1} F(x)`:

    .. math::

        x_{n+1} - \tfrac43 x_n + \tfrac13 x_{n-1} = \tfrac23 \Delta t\, v_{n+1}, \qquad
        v_{n+1} - \tfrac43 v_n + \tfrac13 v_{n-1} = \tfrac23 \Delta t\, M^{-1} F(x_{n+1}).

    With :math:`h = \tfrac23 \Delta t`, :math:`\hat x = (4 x_n - x_{n-1})/3` and
    :math:`\hat v = (4 v_n - v_{n-1})/3`, eliminating :math:`v_{n+1}` leaves
    :math:`M (x_{n+1} - \hat x - h \hat v) = h^2 F(x_{n+1})`: a backward Euler
    step of ``h`` from :math:`\hat x` with velocity :math:`\hat v`, i.e. the
    minimum of the incremental potential
    :math:`\tfrac12 |x - \hat x - h \hat v|_M^2 + h^2 U(x)`, found by the same
    Newton solver as :class:`integrators.implicit_euler.ImplicitEuler`
    (Hessian :math:`M + h^2 H`, line search, clamped negative curvature,
    ``statistics``). Then :math:`v_{n+1} = (x_{n+1} - \hat x) / h`. The
    minimisation form is the better one here: it keeps Newton globally
    convergent (descent on a potential) where stiff bonds make the plain
    residual form stall, exactly as for implicit Euler. The unknown is the
    displacement from :math:`x_n`, and the method keeps the last
    displacement :math:`x_n - x_{n-1}` rather than :math:`x_{n-1}`, so no
    large unwrapped coordinates are subtracted.

    BDF2 damps: on a harmonic oscillator the principal root of
    :math:`(\tfrac32 - i\omega\Delta t)\rho^2 - 2\rho + \tfrac12 = 0` has
    :math:`|\rho| = 1 - (\omega\Delta t)^4/4 + O((\omega\Delta t)^6)` (implicit
    Euler: :math:`1 - (\omega\Delta t)^2/2`), so it damps slow modes far less
    than implicit Euler, and fast modes (:math:`\omega\Delta t \gg 1`) by about
    :math:`1/\sqrt{2\omega\Delta t}` per step.

    The start. A two-step method needs one step of history; the first step
    (and the first after :meth:`reset`) is one step of Alexander's two-stage
    SDIRK method (gamma = 1 - 1/sqrt(2), stiffly accurate), whose stages are
    each a backward Euler step of gamma dt from a shifted start, solved by
    the same solver. It is second order, so it adds an O(dt^3) term to the
    global error against BDF2's own O(dt^2), where an implicit Euler start
    (local error O(dt^2)) adds a second-order error of its own, larger than
    BDF2's at every dt measured; and it is L-stable like BDF2 itself, so it
    damps stiff bond vibrations at once, where a trapezoidal start (also
    second order) leaves them ringing undamped (``|rho|`` -> 1 as omega dt grows)
    and the first BDF2 step extrapolates from a ringing pair of points: on
    the stiff chain of ``examples/implicit-stiff.toml`` at 100 times
    velocity Verlet's step, that step's Newton solve then does not converge
    (``tests/test_implicit_family.py`` measures both).

    Parameters
    ----------
    dt, tol, max_iter, linear_solver
        As for :class:`integrators.implicit_euler.ImplicitEuler` (the
        residual is that of the equation above, with ``h = 2 dt / 3``).

    Attributes
    ----------
    statistics : dict of int
        As for :class:`integrators.implicit_euler.ImplicitEuler`.

    Examples
    --------
    >>> BDF2(dt=0.01).describe()["type"]
    'bdf2'

    References
    ----------
    E. Hairer, G. Wanner, Solving Ordinary Differential Equations II, 2nd ed.
    (Springer, 1996), section V.1. C. Kane, J. E. Marsden, M. Ortiz, M. West,
    Int. J. Numer. Meth. Engng 49, 1295 (2000) (incremental potentials).
    """

    order = 2

    _type = "bdf2"
    _label = "BDF2"

    def __init__(
        self, dt: float, tol: float = 1e-8, max_iter: int = 50, linear_solver: str = "auto"
    ) -> None:
        super().__init__(dt, tol, max_iter, linear_solver)
        #: (x_n - x_{n-1}, v_{n-1}), each (N, 3), or None before the first step.
        self._previous: tuple[np.ndarray, np.ndarray] | None = None

    @staticmethod
    def amplification(omega_dt: float):
        """The roots of (3/2 -+ i omega dt) rho^2 - 2 rho + 1/2 (both signs): the
        principal pair, then the parasitic pair (``|rho|`` -> 1/3 as omega dt -> 0)."""
        z = float(omega_dt)
        return amplification_roots([1.5 - 1j * z, -2.0, 0.5], [1.5 + 1j * z, -2.0, 0.5])

    def step(self, state, forcefield) -> None:
        """Advance ``state`` by ``dt`` in place (the first step is one SDIRK2 step)."""
        previous_velocities = state.velocities.copy()
        history = self._previous
        if history is None or history[0].shape != state.positions.shape:
            displacement = sdirk2_displacement(
                self._solver, state, forcefield, self.dt, self._label + " (SDIRK2 start)"
            )
        else:
            last_displacement, older_velocities = history
            h = 2.0 * self.dt / 3.0
            back = last_displacement / 3.0  # x_hat - x_n
            v_hat = (4.0 * state.velocities - older_velocities) / 3.0
            # M (dx - s) = h^2 F(x_n + dx) with s = back + h v_hat: the solver's form
            # with the velocity s / h.
            displacement = self._solver.solve(
                state, forcefield, h, self._label, reach=1.0, velocities=back / h + v_hat
            )
            state.velocities[:] = (displacement - back) / h
        self._previous = (displacement.copy(), previous_velocities)
        self.end_step(state)

    def reset(self) -> None:
        """Forget the last step and the predictor's history: the next step is a
        SDIRK2 start again. The cumulative ``statistics`` are kept."""
        super().reset()
        self._previous = None

    def get_state(self) -> dict:
        """Return the private state for a checkpoint: the predictor's (see
        :meth:`integrators.implicit_euler.ImplicitEuler.get_state`) and BDF2's
        own, ``last_displacement`` x_n - x_{n-1} and ``previous_velocities``
        v_{n-1} (each (N, 3), None before the first step)."""
        saved = super().get_state()
        last, older = self._previous if self._previous is not None else (None, None)
        saved["last_displacement"] = None if last is None else last.copy()
        saved["previous_velocities"] = None if older is None else older.copy()
        return saved

    def set_state(self, saved: dict) -> None:
        """Restore :meth:`get_state`'s result.

        Raises
        ------
        ValueError
            If ``saved`` is not a BDF2 state (another integrator's checkpoint,
            which holds no ``last_displacement``), or its arrays do not fit.
        """
        missing = [key for key in _HISTORY_KEYS if key not in saved]
        if missing:
            raise ValueError(
                f"not a BDF2 state: it has no {' or '.join(missing)} (a checkpoint written by "
                f"another integrator, with keys {', '.join(sorted(saved)) or 'none'}); BDF2 "
                "cannot continue it exactly"
            )
        last, older = (saved[key] for key in _HISTORY_KEYS)
        if (last is None) != (older is None):
            raise ValueError("last_displacement and previous_velocities must both be given")
        if last is not None:
            last = np.array(last, dtype=np.float64)
            older = np.array(older, dtype=np.float64)
            if last.ndim != 2 or last.shape[1] != 3 or older.shape != last.shape:
                raise ValueError(
                    f"last_displacement and previous_velocities must both have shape (N, 3), "
                    f"got {last.shape} and {older.shape}"
                )
            if not (np.all(np.isfinite(last)) and np.all(np.isfinite(older))):
                raise ValueError("last_displacement and previous_velocities must be finite")
        super().set_state(saved)
        self._previous = None if last is None else (last, older)


def sdirk2_displacement(solver, state, forcefield, dt: float, name: str):
    """One step of Alexander's L-stable SDIRK2; leave ``state`` at its end, return dx.

    Each stage is a backward Euler step of h = gamma dt: stage 1 from (x0, v0),
    M (X1 - x0 - h v0) = h^2 F(X1), V1 = (X1 - x0) / h; stage 2 from
    x^ = x0 + (1 - gamma) dt V1 with velocity v^ = v0 + (1 - gamma) dt A1
    (A1 = M^-1 F(X1)), M (X2 - x^ - h v^) = h^2 F(X2). The step ends at the
    last stage (stiffly accurate): x1 = X2, v1 = (X2 - x^) / h. Both solves go
    through ``solver`` (an :class:`integrators._newton.IncrementalSolver`);
    its predictor history gets the step's start accelerations once, and its
    ``statistics["steps"]`` counts the step once (its other counters count both
    solves).
    Leaves step and time alone.
    """
    h = SDIRK_GAMMA * dt
    rest = (1.0 - SDIRK_GAMMA) * dt
    x0 = state.positions.copy()
    v0 = state.velocities
    history = solver.history
    first = solver.solve(state, forcefield, h, name, reach=SDIRK_GAMMA)
    after_first = solver.history  # the step's start accelerations appended once
    stage_velocities = first / h
    stage_accelerations = forcefield.compute(state, virial=False).forces / state.masses[:, None]
    state.positions[:] = x0
    back = rest * stage_velocities  # x^ - x0
    v_hat = v0 + rest * stage_accelerations
    try:
        displacement = solver.solve(
            state, forcefield, h, name, reach=1.0, velocities=back / h + v_hat
        )
    except BaseException:
        solver.history = history  # the step was not taken
        raise
    solver.history = after_first
    solver.statistics["steps"] -= 1  # two solves, one step
    state.velocities[:] = (displacement - back) / h
    return displacement


__all__ = ["BDF2", "sdirk2_displacement"]
