"""Explicit Runge-Kutta integrators: classical RK4 and adaptive Runge-Kutta-Fehlberg 4(5).

Both treat Newton's equations as the first-order system y = (x, v),
y' = (v, f(x)/m). A stage's forces are evaluated by writing the stage
positions into ``state.positions`` (in place) and calling
``forcefield.compute``; the step then writes the final positions and
velocities. Neither method is symplectic: the energy drifts, slowly for small
``dt``. They serve as accurate references (convergence studies, short
trajectories) rather than for long NVE runs.

If a force evaluation (or, for RKF45, the step-size control) raises, the
state is restored to where the step started before the exception propagates.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from numba import njit

from integrators.base import DT, ConvergenceError, IntegratorBase, check_dt
from md._checks import positive
from md.errors import NonFiniteError
from md.parallel import global_max
from md.schema import Key


class _Tableau:
    """Butcher tableau of an explicit method (autonomous system: no ``c`` needed)."""

    def __init__(self, a: list[list[float]], b: list[float], b_low: list[float] | None = None):
        self.n_stages = len(b)
        # rows[i] holds a[i][0..i-1]; rows[0] is empty (the first stage is the start).
        self.rows = [np.zeros(0)] + [np.array(row, dtype=np.float64) for row in a]
        self.b = np.array(b, dtype=np.float64)
        self.error = None if b_low is None else self.b - np.array(b_low, dtype=np.float64)


_RK4 = _Tableau(
    a=[[0.5], [0.0, 0.5], [0.0, 0.0, 1.0]],
    b=[1 / 6, 1 / 3, 1 / 3, 1 / 6],
)

# Fehlberg's 4(5) pair; ``b`` is the fifth-order solution (propagated: local
# extrapolation), ``b_low`` the embedded fourth-order one.
_RKF45 = _Tableau(
    a=[
        [1 / 4],
        [3 / 32, 9 / 32],
        [1932 / 2197, -7200 / 2197, 7296 / 2197],
        [439 / 216, -8.0, 3680 / 513, -845 / 4104],
        [-8 / 27, 2.0, -3544 / 2565, 1859 / 4104, -11 / 40],
    ],
    b=[16 / 135, 0.0, 6656 / 12825, 28561 / 56430, -9 / 50, 2 / 55],
    b_low=[25 / 216, 0.0, 1408 / 2565, 2197 / 4104, -1 / 5, 0.0],
)


class _Workspace:
    """Start-of-step copies and stage derivatives, reallocated when N changes."""

    def __init__(self, n_stages: int) -> None:
        self.n_stages = n_stages
        self.n_atoms = -1

    def fit(self, n_atoms: int) -> None:
        if n_atoms != self.n_atoms:
            self.n_atoms = n_atoms
            self.x0 = np.empty((n_atoms, 3))
            self.v0 = np.empty((n_atoms, 3))
            self.kx = np.empty((self.n_stages, n_atoms, 3))  # stage velocities dx/dt
            self.kv = np.empty((self.n_stages, n_atoms, 3))  # stage accelerations dv/dt

    def start(self, state, forcefield, inverse_masses) -> None:
        """Copy the state as the substep start and evaluate the first stage there."""
        np.copyto(self.x0, state.positions)
        np.copyto(self.v0, state.velocities)
        np.copyto(self.kx[0], self.v0)
        _accelerations(self.kv[0], forcefield.compute(state, virial=False).forces, inverse_masses)

    def advance(self, state, forcefield, tableau: _Tableau, h: float, inverse_masses) -> None:
        """Evaluate stages 2..s from the start and write the solution into the state."""
        x0, v0, kx, kv = self.x0, self.v0, self.kx, self.kv
        for i in range(1, tableau.n_stages):
            row = tableau.rows[i]
            _combine(state.positions, x0, kx[:i], row, h)
            _combine(kx[i], v0, kv[:i], row, h)
            _accelerations(kv[i], forcefield.compute(state, virial=False).forces, inverse_masses)
        _combine(state.positions, x0, kx, tableau.b, h)
        _combine(state.velocities, v0, kv, tableau.b, h)

    def restore(self, state) -> None:
        np.copyto(state.positions, self.x0)
        np.copyto(state.velocities, self.v0)


class RK4(IntegratorBase):
    """Classical fourth-order Runge-Kutta on (x, v).

    Four force evaluations per step, none served from the cache (the last
    stage is at x0 + dt k3, not at the new positions). Fourth order, but
    neither symplectic nor time-reversible.

    Parameters
    ----------
    dt : float
        Time step [time].

    Attributes
    ----------
    statistics : dict
        Cumulative counters: ``steps``.

    Examples
    --------
    >>> RK4(dt=0.01).describe()
    {'type': 'rk4', 'dt': 0.01}
    """

    order = 4
    distributed = True

    def __init__(self, dt: float) -> None:
        self.dt = check_dt(dt)
        self.statistics = {"steps": 0}
        self._work = _Workspace(_RK4.n_stages)

    def step(self, state, forcefield) -> None:
        work = self._work
        work.fit(state.n_atoms)
        inverse_masses = 1.0 / state.masses
        work.start(state, forcefield, inverse_masses)
        try:
            work.advance(state, forcefield, _RK4, self.dt, inverse_masses)
        except BaseException:
            work.restore(state)
            raise
        self.end_step(state)
        self.statistics["steps"] += 1

    def reset(self) -> None:
        """Nothing to forget: RK4 is a one-step method."""

    def describe(self) -> dict:
        return {"type": "rk4", "dt": self.dt}


class RKF45(IntegratorBase):
    """Runge-Kutta-Fehlberg 4(5) with adaptive internal substeps.

    :meth:`step` advances the state by exactly ``dt`` (so frames and
    observers land on the requested times) in as many internal substeps as
    the error control needs. Each substep evaluates six forces; the fifth-order
    solution is propagated and the difference to the embedded fourth-order
    one is the local error estimate::

        err = max |h sum_j (b5_j - b4_j) k_j|

    over every position [length] and velocity [length/time] component (an
    absolute max norm, so it is independent of where the origin lies). A
    substep is accepted when err <= ``tol``; the next substep size is
    h 0.9 (tol / err)^(1/5) with the factor rounded down to a power of
    2^(1/4) and limited to [0.2 h, 5 h]. The rounding keeps the last bits of
    err out of the substep sizes: a factor smooth in err would pass them on
    to every later substep, where they grow (each size sets where the next
    error is measured), and two runs whose forces differ only in round-off
    (another order of the sums: another number of MPI ranks) would part by
    about ``tol`` within a few steps; rounded, they take the same substeps
    and agree to round-off, as fixed-step methods do. A substep never
    overshoots the output time: the last one is cut to what remains (or the
    remainder is split in two rather than leave a sliver). The proposed size
    after the last accepted substep is kept for the next call (``reset``
    forgets it, and the next step starts trying ``dt``). A force evaluation
    that raises ``NonFiniteError`` inside a substep counts as a rejection.

    Parameters
    ----------
    dt : float
        Output time step [time].
    tol : float
        Absolute local error tolerance per substep (see above).
    dt_min : float, optional
        Smallest substep [time] the control may ask for; default ``1e-12 dt``.
    max_substeps : int
        Most substeps (accepted plus rejected) within one output step.

    Attributes
    ----------
    statistics : dict
        Cumulative counters: ``steps`` (output steps), ``accepted`` and
        ``rejected`` substeps, and ``substeps`` (their sum, the attempts; six
        force evaluations each, less one per rejection).

    Raises
    ------
    ConvergenceError
        From :meth:`step`, when the substep would fall below ``dt_min`` or
        ``max_substeps`` is exceeded; ``residual`` is the last error estimate.
        The state is left as it was before the step.

    Examples
    --------
    >>> RKF45(dt=0.01, tol=1e-6).describe()
    {'type': 'rkf45', 'dt': 0.01, 'tol': 1e-06, 'dt_min': None, 'max_substeps': 100000}

    References
    ----------
    E. Fehlberg, NASA Technical Report R-315 (1969); E. Hairer, S. P. Norsett,
    G. Wanner, *Solving Ordinary Differential Equations I*, 2nd ed.
    (Springer, 1993), sec. II.4.
    """

    SAFETY = 0.9
    GROWTH_MAX = 5.0
    SHRINK_MIN = 0.2

    #: The step size is chosen by the error control, so ``dt`` only sets the
    #: output times; an order of accuracy in ``dt`` is not meaningful.
    adaptive = True
    distributed = True
    CONFIG_KEYS = (
        replace(DT, doc="The output time step (the substeps are the error control's)."),
        Key(
            "tol",
            "number",
            1e-8,
            doc="Absolute local error tolerance per substep (max norm over positions and "
            "velocities).",
        ),
        Key(
            "dt_min",
            "number",
            None,
            unit="time",
            positive=True,
            doc="The smallest substep the control may ask for.",
            default_doc="1e-12 `dt`",
        ),
        Key(
            "max_substeps",
            "integer",
            100000,
            doc="Most substeps (accepted and rejected) within one output step.",
        ),
    )

    def __init__(
        self,
        dt: float,
        tol: float = 1e-8,
        dt_min: float | None = None,
        max_substeps: int = 100000,
    ) -> None:
        self.dt = check_dt(dt)
        self.tol = positive(tol, "tol")
        self.dt_min = None if dt_min is None else positive(dt_min, "dt_min")
        if (
            isinstance(max_substeps, bool)
            or not isinstance(max_substeps, int | np.integer)
            or max_substeps < 1
        ):
            raise ValueError(f"max_substeps must be a positive integer, got {max_substeps!r}")
        self.max_substeps = int(max_substeps)
        self.statistics = {"steps": 0, "accepted": 0, "rejected": 0, "substeps": 0}
        self._h: float | None = None  # proposed next substep size
        self._work = _Workspace(_RKF45.n_stages)
        self._start_positions = np.empty((0, 3))
        self._start_velocities = np.empty((0, 3))

    def step(self, state, forcefield) -> None:
        dt = self.dt
        dt_min = self.dt_min if self.dt_min is not None else 1e-12 * dt
        work = self._work
        work.fit(state.n_atoms)
        if self._start_positions.shape != state.positions.shape:
            self._start_positions = np.empty_like(state.positions)
            self._start_velocities = np.empty_like(state.velocities)
        np.copyto(self._start_positions, state.positions)
        np.copyto(self._start_velocities, state.velocities)
        inverse_masses = 1.0 / state.masses
        stats = self.statistics
        h = dt if self._h is None else min(self._h, dt)
        remaining = dt
        attempts = 0
        error = 0.0
        try:
            work.start(state, forcefield, inverse_masses)
            while True:
                if attempts >= self.max_substeps:
                    raise ConvergenceError(
                        state.step + 1,
                        error,
                        f"step {state.step + 1}: RKF45 needed more than {self.max_substeps} "
                        f"substeps (last error estimate {error:.3g}, tol {self.tol:.3g})",
                    )
                attempts += 1
                stats["substeps"] += 1
                if h >= remaining:
                    take, last = remaining, True
                elif 2.0 * h > remaining:  # split the rest evenly rather than leave a sliver
                    take, last = 0.5 * remaining, False
                else:
                    take, last = h, False
                try:
                    work.advance(state, forcefield, _RKF45, take, inverse_masses)
                    error = global_max(_error_norm(work.kx, work.kv, _RKF45.error, take))
                except NonFiniteError:
                    error = math.inf
                if error <= self.tol:
                    stats["accepted"] += 1
                    factor = self._factor(error)
                    proposed = take * factor
                    if take < h and factor >= 1.0:  # a cut substep says nothing against h
                        proposed = max(proposed, h)
                    h = proposed
                    if last:
                        break
                    remaining -= take
                    work.start(state, forcefield, inverse_masses)
                else:
                    stats["rejected"] += 1
                    work.restore(state)
                    h = take * self._factor(error)
                    if h < dt_min:
                        raise ConvergenceError(
                            state.step + 1,
                            error,
                            f"step {state.step + 1}: RKF45 substep {h:.3g} fell below dt_min "
                            f"{dt_min:.3g} (error estimate {error:.3g}, tol {self.tol:.3g})",
                        )
        except BaseException:
            np.copyto(state.positions, self._start_positions)
            np.copyto(state.velocities, self._start_velocities)
            raise
        self._h = h
        self.end_step(state)
        stats["steps"] += 1

    def reset(self) -> None:
        """Forget the adapted substep size; the next step starts by trying ``dt``."""
        self._h = None

    def get_state(self) -> dict:
        """Return the private state for a checkpoint: the proposed next substep size [time]."""
        return {"h": self._h, "statistics": dict(self.statistics)}

    def set_state(self, saved: dict) -> None:
        """Restore :meth:`get_state`'s result, so the run continues with the same substeps."""
        h = saved["h"]
        if h is not None:
            h = float(h)
            if not (math.isfinite(h) and h > 0):
                raise ValueError(f"saved substep size must be positive and finite, got {h!r}")
        self._h = h
        self.statistics.update({k: int(v) for k, v in saved.get("statistics", {}).items()})

    def describe(self) -> dict:
        return {
            "type": "rkf45",
            "dt": self.dt,
            "tol": self.tol,
            "dt_min": self.dt_min,
            "max_substeps": self.max_substeps,
        }

    def _factor(self, error: float) -> float:
        """Step-size factor 0.9 (tol/err)^(1/5) rounded down to a power of 2^(1/4),
        limited to [0.2, 5] (the rounding: see the class docstring)."""
        if error == 0.0:
            return self.GROWTH_MAX
        if not math.isfinite(error):
            return self.SHRINK_MIN
        factor = self.SAFETY * (self.tol / error) ** 0.2
        if factor > 0.0:  # not an underflow of (tol / err)
            factor = 2.0 ** (math.floor(4.0 * math.log2(factor)) / 4.0)
        return min(self.GROWTH_MAX, max(self.SHRINK_MIN, factor))


@njit(cache=True, error_model="numpy")
def _combine(out, base, stages, coefficients, h):
    """out = base + h sum_j coefficients[j] stages[j] (j < len(coefficients)), in place."""
    n_stages = coefficients.shape[0]
    for i in range(base.shape[0]):
        for a in range(3):
            total = 0.0
            for j in range(n_stages):
                total += coefficients[j] * stages[j, i, a]
            out[i, a] = base[i, a] + h * total


@njit(cache=True, error_model="numpy")
def _accelerations(out, forces, inverse_masses):
    """out = f / m, in place."""
    for i in range(out.shape[0]):
        for a in range(3):
            out[i, a] = forces[i, a] * inverse_masses[i]


@njit(cache=True, error_model="numpy")
def _error_norm(kx, kv, coefficients, h):
    """max |h sum_j coefficients[j] k_j| over positions and velocities; inf if not finite."""
    worst = 0.0
    n_stages = coefficients.shape[0]
    for i in range(kx.shape[1]):
        for a in range(3):
            ex = 0.0
            ev = 0.0
            for j in range(n_stages):
                ex += coefficients[j] * kx[j, i, a]
                ev += coefficients[j] * kv[j, i, a]
            ex = abs(h * ex)
            ev = abs(h * ev)
            if not (ex < np.inf and ev < np.inf):  # also NaN
                return np.inf
            if ex > worst:
                worst = ex
            if ev > worst:
                worst = ev
    return worst


__all__ = ["RK4", "RKF45"]
