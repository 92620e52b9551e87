"""Newton solver shared by the implicit integrators.

Both implicit Euler and implicit midpoint reduce to one nonlinear problem per
step: find the displacement ``dx`` that makes the incremental potential

    Phi(dx) = 1/2 (dx - h v0)^T M (dx - h v0) + h^2 U(x0 + dx)

stationary, i.e. ``grad = M (dx - h v0) - h^2 F(x0 + dx) = 0``: backward
Euler over a time ``h`` (``h = dt`` for implicit Euler, ``h = dt / 2`` for
the midpoint of implicit midpoint). :class:`IncrementalSolver` minimises Phi
by Newton's method with the Hessian ``M + h^2 H(x)``, a backtracking line
search, and fallbacks for indefinite Hessians.

The unknown is the displacement from the start of the step, not the
position, so ``dx - h v0`` is formed without cancellation between large
unwrapped coordinates.
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numba import njit, prange

from integrators.base import ConvergenceError
from md.errors import NonFiniteError
from md.parallel import chunk_count
from potentials.base import SupportsHessian

logger = logging.getLogger(__name__)

LINEAR_SOLVERS = ("auto", "direct", "cg")
#: "auto" factorises systems with fewer unknowns (3N) than this ...
DIRECT_SOLVER_LIMIT = 3000
#: ... and at most this many nonzeros per row on average (10 neighbour blocks per
#: atom: bonded chains). Dense 3D pair networks (an LJ liquid has ~55 partners
#: per atom within 2.5 sigma) fill an LU almost completely, where CG on the
#: mass-dominated M + h^2 H needs a handful of iterations: at 3N = 768 sparse
#: LU takes ~30 ms, CG ~1 ms.
DIRECT_SOLVER_ROW_NNZ = 30
#: Armijo constant of the sufficient-decrease test.
_ARMIJO = 1e-4
_MAX_BACKTRACKS = 30
#: Diagonal shifts mu (in units of M) tried when the Newton direction is not a descent one.
_SHIFTS = (1.0, 10.0, 100.0)
_MAX_CG_ITERATIONS = 1000
#: The Hessian of the last iteration is used again (a chord step) while Newton's
#: iterations each cut the residual at least this much with a full step.
_CHORD_REDUCTION = 0.1
#: CG solves each Newton system to a relative residual eta = _FORCING * residual,
#: at most _MAX_FORCING and no smaller than tol / residual. Measured on the
#: 32000-atom LJ melt and a stiff bead-spring melt (benchmarks/implicit.py, 30
#: steps, tol 1e-6 and 1e-8): 0.3 needs fewer force evaluations and products in
#: both than eta = residual (too loose: a third Newton iteration) or 0.1 (more
#: CG iterations than the Newton iterations they save).
_FORCING = 0.3
_MAX_FORCING = 0.1
#: The smallest ``tol``: four units in the last place of 1. The residual is an acceleration
#: error relative to the largest of the step's accelerations, from differences of numbers
#: of that size, so its round-off is a few such units; a tol below them is never reached.
TOL_FLOOR = 4.0 * float(np.finfo(np.float64).eps)
#: Past steps whose start accelerations the predictor extrapolates (quadratic in time).
#: On the 32000-atom LJ melt (dt 0.005, tol 1e-6) it cuts the predictor's residual about
#: threefold and Newton iterations per step from 2.10 to 2.00, CG's from 4.07 to 3.63.
PREDICTOR_HISTORY = 2


def check_solver_options(tol: float, max_iter: int, linear_solver: str) -> tuple[float, int, str]:
    """Validate and return ``(tol, max_iter, linear_solver)``; raise ValueError otherwise."""
    if isinstance(tol, bool | np.bool_ | str | bytes):
        raise ValueError(f"tol must be a number, got {tol!r}")
    try:
        tol = float(tol)
    except (TypeError, ValueError):
        raise ValueError(f"tol must be a number, got {tol!r}") from None
    if not (0.0 < tol < np.inf):
        raise ValueError(f"tol must be positive and finite, got {tol!r}")
    if tol >= 1.0:
        raise ValueError(
            f"tol must be below 1, got {tol!r}: the residual is relative to the step's largest "
            "acceleration, so a tol of 1 or more accepts the first guess unsolved"
        )
    if tol < TOL_FLOOR:
        raise ValueError(
            f"tol must be at least {TOL_FLOOR:.3g}, got {tol!r}: the relative residual is "
            "computed in double precision to a few units in its last place, so a smaller "
            "tol is never reached"
        )
    if isinstance(max_iter, bool) or not isinstance(max_iter, int | np.integer) or max_iter < 1:
        raise ValueError(f"max_iter must be a positive integer, got {max_iter!r}")
    if linear_solver not in LINEAR_SOLVERS:
        raise ValueError(
            f"linear_solver must be one of {', '.join(LINEAR_SOLVERS)}, got {linear_solver!r}"
        )
    return tol, int(max_iter), linear_solver


def not_converged(
    step: int, residual: float, name: str, max_iter: int, tol: float
) -> ConvergenceError:
    """The error of a Newton solve that used its ``max_iter`` iterations."""
    return ConvergenceError(
        step,
        residual,
        f"step {step}: {name} Newton solve did not converge in {max_iter} iteration(s) "
        f"(residual {residual:.3g} > tol {tol:g}); try a smaller dt, a larger max_iter or a "
        "looser tol",
    )


def new_statistics() -> dict[str, int]:
    """Return zeroed cumulative solver counters."""
    return {
        "steps": 0,
        "newton_iterations": 0,
        "linear_iterations": 0,
        "line_search_backtracks": 0,
        "fallbacks": 0,
        "projections": 0,
        "hessian_evaluations": 0,
    }


class NewtonOptions:
    """What every Newton solver of the implicit family holds: its options, the
    ``statistics`` it adds to, and the predictor's ``history``, M^-1 F at the
    start of the last solves (oldest first, at most :data:`PREDICTOR_HISTORY`,
    each (3N,)), which the predictor extrapolates and checkpoints keep."""

    def __init__(self, tol: float, max_iter: int, linear_solver: str, statistics: dict) -> None:
        self.tol = tol
        self.max_iter = max_iter
        self.linear_solver = linear_solver
        self.statistics = statistics
        self.history: list[np.ndarray] = []


class IncrementalSolver(NewtonOptions):
    """Minimise the incremental potential of one implicit step by Newton's method.

    Convergence is measured by the scale-aware residual

        residual = max_i |M^-1 grad|_i / (h^2 a_scale),
        a_scale = max(max|M^-1 F(x0)|, max|v0| / h),

    the largest error of the step equation ``(dx - h v0) / h^2 = F / m`` as an
    acceleration, relative to the largest acceleration term at the start of
    the step (round-off limits the error to about machine precision times
    that scale). ``tol`` is therefore a relative accuracy independent of
    units; a_scale = 1 if both terms vanish.

    Each iteration solves ``(M + h^2 H) p = -grad`` (sparse LU, or Jacobi
    preconditioned CG truncated at negative curvature, applying H matrix-free
    from its pair blocks, to a relative residual of 0.3 times the Newton
    residual, at most 0.1, and no less than tol over it), requires ``p`` to be
    a descent direction of Phi, and backtracks on Phi (Armijo). After an
    iteration whose step had to be shortened, the next one uses H with the
    negative pair curvatures that could outweigh the masses clamped
    (``HessianSum.definite``: M + h^2 H is then positive definite); where no
    descent direction comes out, it is retried with that clamped H, then with
    ``+ mu M`` (``mu`` = 1, 10, 100), then ``-M^-1 grad`` is taken. With CG,
    while each full step cuts the residual at least tenfold, the next
    iteration applies the same Hessian again (a chord step) instead of
    evaluating it; never across steps, so a resumed run repeats the same
    iterations. Near convergence, where Phi's decrease drowns in round-off, a
    step that does not raise Phi beyond round-off and lowers the residual is
    accepted too. Force fields without a Hessian get ``M`` in its place, which
    makes the iteration a damped fixed-point iteration.

    Parameters
    ----------
    tol : float
        Residual at which the solve has converged (relative, see above).
    max_iter : int
        Most Newton iterations per solve.
    linear_solver : {"auto", "direct", "cg"}
        ``"auto"``: ``"direct"`` below :data:`DIRECT_SOLVER_LIMIT` unknowns when
        the matrix is sparse (:data:`DIRECT_SOLVER_ROW_NNZ`), ``"cg"`` otherwise.
    statistics : dict
        Counters (see :func:`new_statistics`) that the solver adds to.
    """

    def __init__(self, tol: float, max_iter: int, linear_solver: str, statistics: dict) -> None:
        super().__init__(tol, max_iter, linear_solver, statistics)
        self._masses = None  # (atom masses, per-coordinate masses, their inverses)

    def solve(
        self, state, forcefield, h: float, name: str, reach: float = 1.0, velocities=None
    ) -> np.ndarray:
        """Return the displacement ``dx`` (N, 3) that makes Phi stationary.

        On return ``state.positions`` holds ``x0 + dx`` and ``forcefield``
        caches its result there. On failure the positions are restored to
        ``x0`` and :class:`ConvergenceError` (or the force field's error)
        is raised; ``name`` labels the method in the message. ``reach`` is
        the time ``x0 + dx`` stands for, in steps from ``x0`` (1 for implicit
        Euler, 1/2 for the midpoint): the predictor extrapolates the
        accelerations of the last steps to it. ``velocities`` (N, 3) replaces
        ``v0`` = ``state.velocities`` in Phi: a method whose step equation is
        ``M (dx - s) = h^2 F(x0 + dx)`` with another known shift ``s`` (the
        trapezoidal rule, BDF2) passes ``s / h``.
        """
        x0 = state.positions.copy()
        velocities = state.velocities if velocities is None else velocities
        try:
            return self._solve(state, forcefield, h, name, x0, reach, velocities)
        except BaseException:
            state.positions[:] = x0
            raise

    # ------------------------------------------------------------------ solve
    def _solve(self, state, forcefield, h, name, x0, reach, velocities):
        stats = self.statistics
        step = state.step + 1
        masses, inverse_masses = self._mass_vectors(state.masses)
        h2 = h * h
        forces0 = forcefield.compute(state, virial=False).forces.ravel()
        # In one pass: target = h v0, M^-1 F(x0), the explicit prediction (below) and
        # the scales.
        target = np.empty_like(forces0)
        accelerations = np.empty_like(forces0)
        predicted = np.empty_like(forces0)
        largest_acceleration, largest_target = _in_chunks(
            _start_terms,
            _start_terms_threaded,
            velocities.ravel(),
            forces0,
            inverse_masses,
            h,
            h2,
            target,
            accelerations,
            predicted,
        )
        history = [a for a in self.history if a.shape == accelerations.shape]
        if history:
            # The acceleration at x0 + dx, extrapolated from this and the last steps'
            # (Lagrange, in steps): the prediction's error falls from O(h^3) to
            # O(h^(3 + len(history))), a Newton iteration in about one step of ten.
            weights = extrapolation_weights(len(history), reach)
            _extrapolate(
                target,
                h2,
                weights,
                accelerations,
                history[-1],
                history[0] if len(history) > 1 else history[-1],
                predicted,
            )
        scale = max(largest_acceleration, largest_target / h2)
        if not (np.isfinite(scale) and scale > 0.0):
            scale = 1.0
        use_newton = all(isinstance(p, SupportsHessian) for p in forcefield.potentials)

        def evaluate(dx):
            """Return (Phi, grad, residual, noise) at x0 + dx, leaving the positions there."""
            np.add(x0, dx.reshape(x0.shape), out=state.positions)
            result = forcefield.compute(state, virial=False)
            grad = np.empty_like(dx)
            kinetic, largest = _in_chunks(
                _incremental_terms,
                _incremental_terms_threaded,
                dx,
                target,
                masses,
                inverse_masses,
                result.forces.ravel(),
                h2,
                grad,
            )
            phi = kinetic + h2 * result.energy
            residual = largest / (h2 * scale)
            # Round-off level of Phi: below it a change in Phi says nothing.
            noise = 1e-12 * (kinetic + h2 * abs(result.energy))
            return phi, grad, residual, noise

        # Start from the explicit prediction x0 + h v0 + h^2 a, a = M^-1 F(x0) or its
        # extrapolation to x0 + dx, when it is good (smooth forces, small h); for stiff
        # systems it overshoots, so fall back to x0 + h v0, from which Phi descends
        # to the solution.
        dx = predicted
        try:
            phi, grad, residual, noise = evaluate(dx)
        except NonFiniteError:
            residual = np.inf
        if not residual < 1.0:
            dx = target.copy()
            phi, grad, residual, noise = evaluate(dx)
        iterations = 0
        globalise = False
        hessian = None
        previous = np.inf
        # The preconditioner of the last linear system, for a chord step's (same
        # matrix); local to this solve, so no operator outlives it here.
        preconditioners = {}
        while residual > self.tol and iterations < self.max_iter:
            iterations += 1
            stats["newton_iterations"] += 1
            # Chord step: while each full step cut the residual tenfold, the Hessian
            # of the last iteration still serves (it changes little within a step,
            # and building it costs about three force evaluations). The residual is
            # always the exact one, so only the iteration count can change.
            if globalise or residual > _CHORD_REDUCTION * previous:
                hessian = None
            previous = residual
            direction, hessian = self._direction(
                state,
                forcefield,
                h2,
                masses,
                grad,
                residual,
                use_newton,
                globalise,
                hessian,
                preconditioners,
            )
            accepted = self._line_search(evaluate, dx, direction, phi, grad, noise)
            # A shortened step means the local model is poor: the next direction
            # comes from the definite Hessian if the exact one may be indefinite.
            globalise = accepted is None or accepted[-1] < 1.0
            if accepted is None and use_newton:
                # The Newton direction led nowhere: one M^-1 gradient step instead.
                hessian = None
                stats["fallbacks"] += 1
                direction = -grad * inverse_masses
                accepted = self._line_search(evaluate, dx, direction, phi, grad, noise)
            if accepted is None:
                raise ConvergenceError(
                    step,
                    residual,
                    f"step {step}: {name} Newton solve stalled after {iterations} "
                    f"iteration(s): no step along the search direction lowers the incremental "
                    f"potential (residual {residual:.3g}, tol {self.tol:g}); try a smaller dt",
                )
            dx, phi, grad, residual, noise, _ = accepted
        if not residual <= self.tol:
            raise not_converged(step, residual, name, self.max_iter, self.tol)
        stats["steps"] += 1
        self.history = (history + [accelerations])[-PREDICTOR_HISTORY:]
        return dx.reshape(x0.shape)

    def _mass_vectors(self, atom_masses):
        """Return (masses, 1 / masses), each repeated per coordinate (3N,), kept while the
        atoms' masses stay the same."""
        held = self._masses
        if held is None or not np.array_equal(held[0], atom_masses):
            masses = np.repeat(atom_masses, 3)
            held = (atom_masses.copy(), masses, 1.0 / masses)
            self._masses = held
        return held[1], held[2]

    def _direction(
        self,
        state,
        forcefield,
        h2,
        masses,
        grad,
        residual,
        use_newton,
        globalise,
        exact,
        preconditioners,
    ):
        """Return a descent direction of Phi and the Hessian operator to use again (or None).

        Newton's direction (exact, clamped or shifted Hessian) or -M^-1 grad.
        ``exact``: the Hessian operator of an earlier iteration to use again, or None
        to evaluate it at the current positions. ``preconditioners`` holds the
        Jacobi preconditioner of the last system M (1 + shift) + h2 H with its key
        (operator, shift, h2), which a chord step finds there; it is emptied before a
        new Hessian is evaluated.
        With ``globalise`` (the last step was shortened) and some pair's negative
        curvature able to outweigh the masses (2 h^2 lambda_min < -m_min: a
        compressed stiff bond or a large step), where the Newton direction
        heads for a saddle, those curvatures are clamped first
        (``HessianSum.definite``), which keeps M + h^2 H positive definite.
        """
        stats = self.statistics
        if not use_newton:
            return -grad / masses, None
        # CG only applies the Hessian (pair blocks, never assembled); LU needs the matrix.
        if exact is None:
            # Let go of the last operator first: a potential may then write the new
            # blocks into its buffers (LennardJones does) instead of fresh memory.
            preconditioners.clear()
            exact = forcefield.hessian_operator(state)
            stats["hessian_evaluations"] += 1
        operator = exact
        size = len(masses)
        solver = self.linear_solver
        if solver == "auto":
            sparse = operator.nnz <= DIRECT_SOLVER_ROW_NNZ * size
            solver = "direct" if size < DIRECT_SOLVER_LIMIT and sparse else "cg"
        # Forcing term of the inexact (CG) solve (Eisenstat and Walker): a fixed
        # fraction of the residual, so that Newton converges superlinearly, but no
        # tighter than the factor this iteration must cut the residual by to reach tol.
        eta = min(_MAX_FORCING, max(_FORCING * residual, self.tol / max(residual, 1e-300)))
        atom_masses = masses[::3]
        projected = globalise and 2.0 * h2 * operator.min_eigenvalue() < -np.min(atom_masses)
        if projected:
            operator = operator.definite(h2, atom_masses)
            stats["projections"] += 1
        assembled = None
        for attempt in range(len(_SHIFTS) + 2):
            if attempt:
                stats["fallbacks"] += 1
            if attempt == 1 and not projected:
                # The exact Hessian gave no descent direction: project it.
                operator, projected = operator.definite(h2, atom_masses), True
                stats["projections"] += 1
            shift = 0.0 if attempt < 2 else _SHIFTS[attempt - 2]
            if solver == "direct" and assembled is not operator:
                assembled = operator
                hessian = operator.tocsr()
            # The system (1 + shift) M + h^2 H; CG only needs its products.
            diagonal = (1.0 + shift) * masses
            if solver == "direct":
                matrix = sp.diags(diagonal) + h2 * hessian
                direction, n_linear, positive = _direct_solve(matrix, -grad)
            else:
                key = (id(operator), shift, h2)
                if preconditioners.get("key") != key:
                    preconditioners.clear()
                    preconditioners["key"] = key
                    preconditioners["operator"] = operator  # keeps id(operator) unique
                    preconditioners["jacobi"] = _jacobi(diagonal, h2, operator.diagonal())
                direction, n_linear, positive = _truncated_cg(
                    lambda x, diagonal=diagonal, op=operator: _in_chunks(
                        _add_scaled, _add_scaled_threaded, diagonal, x, h2, op.matvec(x)
                    ),
                    preconditioners["jacobi"],
                    -grad,
                    eta,
                )
                if not positive and attempt == 0:
                    # CG met negative curvature: its truncated iterate is still a
                    # descent direction (Newton-CG), but the Hessian is indefinite.
                    stats["fallbacks"] += 1
            stats["linear_iterations"] += n_linear
            if _finite_dot(grad, direction) < 0.0:  # NaN if any entry is not finite
                # Only CG uses the operator again: LU would factorise it afresh anyway.
                return direction, (exact if solver == "cg" else None)
        return -grad / masses, None

    def _line_search(self, evaluate, dx, direction, phi, grad, noise):
        """Backtrack along ``direction``; return (dx, Phi, grad, residual, noise, alpha) or None."""
        slope = float(_dot(grad, direction))
        if not slope < 0.0:
            return None
        alpha = 1.0
        for _ in range(_MAX_BACKTRACKS):
            trial = dx + direction if alpha == 1.0 else dx + alpha * direction
            try:
                values = evaluate(trial)
            except NonFiniteError:
                values = None
            if values is not None:
                phi_t, grad_t, _, _ = values
                if phi_t <= phi + _ARMIJO * alpha * slope or (
                    phi_t <= phi + noise and _norm(grad_t) < _norm(grad)
                ):
                    return (trial, *values, alpha)
            alpha *= 0.5
            self.statistics["line_search_backtracks"] += 1
        return None


def _direct_solve(matrix, rhs):
    """Solve by sparse LU; return (solution, 1, True), or NaNs if the matrix is singular."""
    try:
        solution = spla.splu(matrix.tocsc()).solve(rhs)
    except RuntimeError:  # exactly singular
        solution = np.full_like(rhs, np.nan)
    return solution, 1, True


def _truncated_cg(product, preconditioner, rhs, eta):
    """Jacobi-preconditioned CG for ``A x = rhs``, stopped at negative curvature.

    ``product(x)`` returns ``(A x, x . A x)``; ``preconditioner`` is 1 / A's
    diagonal (``_jacobi``).
    Returns ``(x, iterations, positive)``: ``x`` solves to a relative residual
    ``eta``; ``positive`` is False when a search direction of non-positive
    curvature was met, in which case ``x`` is the last iterate (or the
    preconditioned right-hand side at the first iteration), still a descent
    direction (Nocedal and Wright, Numerical Optimization, Algorithm 7.1).
    """
    solution = np.empty_like(rhs)
    residual = np.empty_like(rhs)
    z = np.empty_like(rhs)
    search = np.empty_like(rhs)
    squared, rz = _in_chunks(
        _cg_start, _cg_start_threaded, rhs, preconditioner, solution, residual, z, search
    )
    target = eta * np.sqrt(squared)
    for iteration in range(1, min(_MAX_CG_ITERATIONS, len(rhs)) + 1):
        applied, curvature = product(search)
        if not curvature > 0.0:
            return (z if iteration == 1 else solution), iteration, False
        squared, rz_new = _in_chunks(
            _cg_update,
            _cg_update_threaded,
            rz / curvature,
            search,
            applied,
            preconditioner,
            solution,
            residual,
            z,
        )
        if np.sqrt(squared) <= target:
            return solution, iteration, True
        _cg_direction(z, rz_new / rz, search)
        rz = rz_new
    return solution, min(_MAX_CG_ITERATIONS, len(rhs)), True


#: The sums below may be split over vector lanes and fused multiply-adds: one running
#: sum waits for each addition (about 4 cycles per entry); lanes take a fraction of
#: that. The order is fixed by the compiled code, so runs still repeat bit for bit.
_SUM_MATH = {"reassoc", "contract", "nsz"}


# Sums of products in one thread: numpy's dot and norm go to OpenBLAS, whose threads keep
# spinning after each call and then compete with the threads of the force and Hessian
# kernels (an implicit Euler step on 2 threads took 2.4 times as long).
@njit(cache=True, fastmath=_SUM_MATH, error_model="numpy")
def _dot(a, b) -> float:
    """Return sum(a * b) of two 1-D arrays, in one thread."""
    total = 0.0
    for k in range(a.shape[0]):
        total += a[k] * b[k]
    return total


def _norm(a) -> float:
    """Return the Euclidean norm of a 1-D array (see ``_dot``)."""
    return float(np.sqrt(_dot(a, a)))


# The vector work of one Newton or CG iteration in single passes: numpy would make
# a temporary and a pass over memory per operation (about 1 ms per CG iteration
# on 32000 atoms).
@njit(cache=True, fastmath=_SUM_MATH, error_model="numpy")
def _incremental_terms(dx, target, masses, inverse_masses, forces, h2, grad):
    """Write grad = M (dx - target) - h2 F into ``grad``; return (the kinetic term
    1/2 (dx - target)^T M (dx - target), max |M^-1 grad|), the maximum NaN if any
    entry is NaN."""
    kinetic = 0.0
    largest = 0.0
    finite = True
    for k in range(dx.shape[0]):
        offset = dx[k] - target[k]
        g = masses[k] * offset - h2 * forces[k]
        grad[k] = g
        kinetic += masses[k] * offset * offset
        size = abs(g * inverse_masses[k])
        largest = max(largest, size)
        finite &= size == size
    return 0.5 * kinetic, (largest if finite else np.nan)


@njit(cache=True, fastmath=_SUM_MATH, error_model="numpy")
def _add_scaled(diagonal, x, h2, product):
    """Write ``diagonal * x + h2 * product`` over ``product``; return (it, x . it)."""
    curvature = 0.0
    for k in range(x.shape[0]):
        applied = diagonal[k] * x[k] + h2 * product[k]
        product[k] = applied
        curvature += x[k] * applied
    return product, curvature


@njit(cache=True, error_model="numpy")
def _jacobi(diagonal, h2, hessian_diagonal):
    """Return 1 / d for d = diagonal + h2 hessian_diagonal, with the largest |d| (1 if all
    are 0, NaN if one is NaN) in place of the entries that are not positive."""
    n = diagonal.shape[0]
    out = np.empty(n)
    largest = 0.0
    finite = True
    for k in range(n):
        d = diagonal[k] + h2 * hessian_diagonal[k]
        out[k] = d
        largest = max(largest, abs(d))
        finite &= d == d
    if not finite:
        largest = np.nan
    elif largest == 0.0:
        largest = 1.0
    for k in range(n):
        out[k] = 1.0 / (out[k] if out[k] > 0.0 else largest)
    return out


def extrapolation_weights(n_history: int, reach: float) -> tuple[float, float, float]:
    """Lagrange weights of a(0), a(-1), a(-2) (steps) for a(reach), from the newest
    ``n_history`` + 1 of them (linear or quadratic); unused ones are 0."""
    t = float(reach)
    if n_history == 1:
        return 1.0 + t, -t, 0.0
    return 0.5 * (t + 1.0) * (t + 2.0), -t * (t + 2.0), 0.5 * t * (t + 1.0)


@njit(cache=True, error_model="numpy")
def _extrapolate(target, h2, weights, accelerations, previous, before, predicted):
    """predicted = target + h2 (w0 a + w1 previous + w2 before)."""
    w0, w1, w2 = weights
    for k in range(target.shape[0]):
        a = w0 * accelerations[k] + w1 * previous[k] + w2 * before[k]
        predicted[k] = target[k] + h2 * a


@njit(cache=True, error_model="numpy")
def _start_terms(velocities, forces, inverse_masses, h, h2, target, accelerations, predicted):
    """Write target = h v, accelerations = M^-1 F and the explicit prediction
    h v + h2 M^-1 F; return (max |M^-1 F|, max |target|), NaN where an entry is NaN."""
    largest_acceleration = 0.0
    largest_target = 0.0
    finite = True
    for k in range(velocities.shape[0]):
        t = h * velocities[k]
        a = inverse_masses[k] * forces[k]
        target[k] = t
        accelerations[k] = a
        predicted[k] = t + h2 * a
        largest_acceleration = max(abs(a), largest_acceleration)
        largest_target = max(abs(t), largest_target)
        finite &= (a == a) & (t == t)
    if not finite:
        return np.nan, np.nan
    return largest_acceleration, largest_target


@njit(cache=True, fastmath=_SUM_MATH, error_model="numpy")
def _finite_dot(a, b) -> float:
    """Return sum(a * b), or NaN if any entry of ``b`` is not finite."""
    total = 0.0
    finite = True
    for k in range(a.shape[0]):
        total += a[k] * b[k]
        finite &= abs(b[k]) < np.inf
    return total if finite else np.nan


@njit(cache=True, fastmath=_SUM_MATH, error_model="numpy")
def _cg_start(rhs, preconditioner, solution, residual, z, search):
    """CG's start from x = 0: solution = 0, residual = rhs, z = search = preconditioner
    rhs; return (|rhs|^2, rhs . z)."""
    squared = 0.0
    rz = 0.0
    for k in range(rhs.shape[0]):
        r = rhs[k]
        zk = preconditioner[k] * r
        solution[k] = 0.0
        residual[k] = r
        z[k] = zk
        search[k] = zk
        squared += r * r
        rz += r * zk
    return squared, rz


@njit(cache=True, fastmath=_SUM_MATH, error_model="numpy")
def _cg_update(step, search, applied, preconditioner, solution, residual, z):
    """One CG update in place: solution += step search, residual -= step applied,
    z = preconditioner residual; return (|residual|^2, residual . z)."""
    squared = 0.0
    rz = 0.0
    for k in range(solution.shape[0]):
        solution[k] += step * search[k]
        r = residual[k] - step * applied[k]
        residual[k] = r
        zk = preconditioner[k] * r
        z[k] = zk
        squared += r * r
        rz += r * zk
    return squared, rz


@njit(cache=True, error_model="numpy")
def _cg_direction(z, beta, search):
    """search = z + beta search, in place."""
    for k in range(z.shape[0]):
        search[k] = z[k] + beta * search[k]


# ------------------------------------------------------------------ the passes on threads
#: Fewest vector entries per thread worth a chunk of their own: on the 32000-atom LJ
#: melt (96000 entries) two chunks take an implicit Euler step's passes from 1.7 to
#: 1.2 ms at 2 threads.
_MIN_CHUNK_ENTRIES = 30_000


def _in_chunks(serial, threaded, *args):
    """Run a vector pass: ``serial(*args)``, or for long vectors ``threaded(*args,
    chunks)`` with one chunk per thread. The threaded form sums its chunks' partial
    results in chunk order, so a run repeats bit for bit at a given thread count; with
    one thread it is the serial pass."""
    size = next(len(a) for a in args if isinstance(a, np.ndarray))
    chunks = chunk_count(size, _MIN_CHUNK_ENTRIES)
    return serial(*args) if chunks == 1 else threaded(*args, chunks)


@njit(cache=True, inline="always")
def _bounds(c, chunks, n):
    """Entries first..last-1 of chunk ``c``."""
    return c * n // chunks, (c + 1) * n // chunks


@njit(cache=True, error_model="numpy")
def _largest(values):
    """The largest of the chunks' maxima, NaN if one is NaN."""
    out = values[0]
    for v in values[1:]:
        out = v if (v != v or v > out) else out
    return out if out == out else np.nan


@njit(cache=True, parallel=True, error_model="numpy")
def _start_terms_threaded(
    velocities, forces, inverse_masses, h, h2, target, accelerations, predicted, chunks
):
    """``_start_terms`` in chunks on numba's threads."""
    n = velocities.shape[0]
    parts = np.empty((2, chunks))
    for c in prange(chunks):
        a, b = _bounds(c, chunks, n)
        acceleration, step = _start_terms(
            velocities[a:b],
            forces[a:b],
            inverse_masses[a:b],
            h,
            h2,
            target[a:b],
            accelerations[a:b],
            predicted[a:b],
        )
        parts[0, c] = acceleration
        parts[1, c] = step
    return _largest(parts[0]), _largest(parts[1])


@njit(cache=True, parallel=True, error_model="numpy")
def _incremental_terms_threaded(dx, target, masses, inverse_masses, forces, h2, grad, chunks):
    """``_incremental_terms`` in chunks on numba's threads."""
    n = dx.shape[0]
    parts = np.empty((2, chunks))
    for c in prange(chunks):
        a, b = _bounds(c, chunks, n)
        kinetic, largest = _incremental_terms(
            dx[a:b], target[a:b], masses[a:b], inverse_masses[a:b], forces[a:b], h2, grad[a:b]
        )
        parts[0, c] = kinetic
        parts[1, c] = largest
    return parts[0].sum(), _largest(parts[1])


@njit(cache=True, parallel=True, error_model="numpy")
def _add_scaled_threaded(diagonal, x, h2, product, chunks):
    """``_add_scaled`` in chunks on numba's threads."""
    n = x.shape[0]
    parts = np.empty(chunks)
    for c in prange(chunks):
        a, b = _bounds(c, chunks, n)
        parts[c] = _add_scaled(diagonal[a:b], x[a:b], h2, product[a:b])[1]
    return product, parts.sum()


@njit(cache=True, parallel=True, error_model="numpy")
def _cg_start_threaded(rhs, preconditioner, solution, residual, z, search, chunks):
    """``_cg_start`` in chunks on numba's threads."""
    n = rhs.shape[0]
    parts = np.empty((2, chunks))
    for c in prange(chunks):
        a, b = _bounds(c, chunks, n)
        squared, rz = _cg_start(
            rhs[a:b], preconditioner[a:b], solution[a:b], residual[a:b], z[a:b], search[a:b]
        )
        parts[0, c] = squared
        parts[1, c] = rz
    return parts[0].sum(), parts[1].sum()


@njit(cache=True, parallel=True, error_model="numpy")
def _cg_update_threaded(step, search, applied, preconditioner, solution, residual, z, chunks):
    """``_cg_update`` in chunks on numba's threads."""
    n = search.shape[0]
    parts = np.empty((2, chunks))
    for c in prange(chunks):
        a, b = _bounds(c, chunks, n)
        squared, rz = _cg_update(
            step,
            search[a:b],
            applied[a:b],
            preconditioner[a:b],
            solution[a:b],
            residual[a:b],
            z[a:b],
        )
        parts[0, c] = squared
        parts[1, c] = rz
    return parts[0].sum(), parts[1].sum()
