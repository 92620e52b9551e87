"""Energy minimisation with FIRE 2.0, and a capped-force push-off for overlapping starts.

FIRE (Bitzek, Koskinen, Gaehler, Moseler and Gumbsch, Phys. Rev. Lett. 97,
170201, 2006) runs damped dynamics that turn the velocity towards the force
and speed up while the power P = F . v stays positive; FIRE 2.0 (Guenole,
Noehring, Vaid, Houlle, Xie, Prakash and Bitzek, Comput. Mater. Sci. 175,
109584, 2020) adds the semi-implicit Euler step, a half step back when P turns
negative, an initial delay before the time step may shrink, and a lower
bound on the time step. All atoms have unit mass here (as in ASE's FIRE), so
the path depends on the forces alone.

A push-off is the same minimiser with every atom's force capped at
``max_force`` before it enters the dynamics: atoms started on top of each
other (a random-walk polymer, a packed structure) separate at a bounded
pace instead of being shot apart by the 1/r^13 wall, and the run then starts
from a relaxed structure without the heat the overlaps would have released.
The convergence test always uses the true forces.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from md._checks import count, positive
from md.forcefield import ForceField
from md.parallel import global_max, global_sum
from md.state import State


@dataclass
class MinimizeResult:
    """How a minimisation ended.

    ``fmax`` is the largest per-atom force norm at the end [energy/length];
    ``history`` holds (step, energy, fmax) every ``report_every`` steps;
    ``stopped`` says that the caller's ``stop`` asked to end before convergence.
    """

    converged: bool
    steps: int
    energy: float
    fmax: float
    target: float
    history: list[tuple[int, float, float]] = field(default_factory=list)
    stopped: bool = False

    def describe(self) -> str:
        verdict = "converged" if self.converged else "NOT converged"
        if self.stopped:
            verdict = "stopped"
        relation = "<=" if self.converged else ">"
        return (
            f"{verdict} after {self.steps} steps: max force {self.fmax:.4g} {relation} "
            f"fmax {self.target:.4g}, energy {self.energy:.10g}"
        )


class FIRE:
    """The FIRE 2.0 minimiser (parameters as in Guenole et al. 2020, Table 1).

    Parameters
    ----------
    dt : float
        Initial time step [time, unit masses]; ``dt_max`` = 10 dt and
        ``dt_min`` = 0.02 dt by default.
    max_step : float
        Largest displacement of any atom in one step [length].
    max_force : float, optional
        Cap on each atom's force norm in the dynamics (a push-off); None: no cap.
    n_delay, f_inc, f_dec, alpha_start, f_alpha
        FIRE's constants (20, 1.1, 0.5, 0.25, 0.99).
    """

    def __init__(
        self,
        dt: float = 0.005,
        max_step: float = 0.1,
        max_force: float | None = None,
        dt_max: float | None = None,
        dt_min: float | None = None,
        n_delay: int = 20,
        f_inc: float = 1.1,
        f_dec: float = 0.5,
        alpha_start: float = 0.25,
        f_alpha: float = 0.99,
    ) -> None:
        self.dt0 = positive(dt, "dt")
        self.max_step = positive(max_step, "max_step")
        self.max_force = None if max_force is None else positive(max_force, "max_force")
        self.dt_max = positive(dt_max, "dt_max") if dt_max is not None else 10.0 * self.dt0
        self.dt_min = positive(dt_min, "dt_min") if dt_min is not None else 0.02 * self.dt0
        self.n_delay = count(n_delay, "n_delay")
        self.f_inc, self.f_dec = positive(f_inc, "f_inc"), positive(f_dec, "f_dec")
        self.alpha_start = positive(alpha_start, "alpha_start")
        self.f_alpha = positive(f_alpha, "f_alpha")

    def run(
        self,
        state: State,
        forcefield: ForceField,
        fmax: float,
        max_steps: int,
        callback: Callable[[int, float, float], None] | None = None,
        report_every: int = 100,
        between_steps: Callable[[np.ndarray], np.ndarray] | None = None,
        stop: Callable[[], bool] | None = None,
    ) -> MinimizeResult:
        """Move ``state.positions`` towards a local minimum until every ``|F_i| <= fmax``.

        Velocities, step and time of the state are left as they were. ``callback(step,
        energy, fmax)`` is called every ``report_every`` steps and at the end.
        ``between_steps(velocities)``, called before each step, may replace the
        state's arrays and returns the minimiser's velocities for the atoms it then
        holds (a decomposed run migrates atoms between ranks there,
        :meth:`md.distributed.DistributedSimulation.minimize`); its sums and maxima
        over atoms go through :func:`md.parallel.global_sum` and ``global_max``.
        ``stop()`` is asked before each step; when it returns True the
        minimisation ends there (``result.stopped``), at a consistent state.

        Raises
        ------
        ValueError
            If ``fmax`` is not > 0 or ``max_steps`` not a positive integer, or the
            force field's neighbour list is not exact (``every`` > 1 or no check).
        NonFiniteError
            If forces or energy become non-finite.
        """
        fmax = positive(fmax, "fmax")
        max_steps = count(max_steps, "max_steps", minimum=1)
        neighbors = forcefield.neighbor_list
        if neighbors is not None and not neighbors.exact:
            raise ValueError(
                f"minimisation needs a neighbour list looked at on every evaluation, not "
                f"every {neighbors.every} step(s) with check={neighbors.check}: the state's "
                "step does not advance while minimising, so the list would never be rebuilt"
            )
        report_every = count(report_every, "report_every", minimum=1)
        velocity = np.zeros_like(state.positions)
        dt, alpha = self.dt0, self.alpha_start
        positive_steps = 0
        result = MinimizeResult(False, 0, math.nan, math.nan, fmax)
        for step in range(max_steps + 1):
            if between_steps is not None:
                velocity = between_steps(velocity)
            positions = state.positions
            evaluated = forcefield.compute(state, virial=False)
            forces = evaluated.forces
            largest = global_max(_largest_norm(forces))
            result.steps, result.energy, result.fmax = step, float(evaluated.energy), largest
            if step % report_every == 0:
                result.history.append((step, result.energy, largest))
                if callback is not None:
                    callback(step, result.energy, largest)
            if largest <= fmax:
                result.converged = True
                break
            if step == max_steps:
                break
            if stop is not None and stop():
                result.stopped = True
                break
            forces = self._capped(forces)
            power = global_sum(float(np.sum(forces * velocity)))
            if power > 0.0:
                positive_steps += 1
                if positive_steps > self.n_delay:
                    dt = min(dt * self.f_inc, self.dt_max)
                    alpha *= self.f_alpha
            else:
                positive_steps = 0
                if step >= self.n_delay:  # FIRE 2.0's initial delay
                    dt = max(dt * self.f_dec, self.dt_min)
                    alpha = self.alpha_start
                positions -= 0.5 * dt * velocity  # back half a step, then stop
                velocity[:] = 0.0
            velocity += dt * forces  # semi-implicit Euler, unit masses
            norm_v = math.sqrt(global_sum(float(np.sum(velocity * velocity))))
            norm_f = math.sqrt(global_sum(float(np.sum(forces * forces))))
            if norm_f > 0.0:
                velocity *= 1.0 - alpha
                velocity += alpha * norm_v / norm_f * forces
            displacement = dt * velocity
            longest = global_max(_largest_norm(displacement))
            if longest > self.max_step:
                displacement *= self.max_step / longest
            positions += displacement
        if callback is not None and result.history and result.history[-1][0] != result.steps:
            callback(result.steps, result.energy, result.fmax)
        return result

    def _capped(self, forces: np.ndarray) -> np.ndarray:
        if self.max_force is None:
            return forces
        norms = np.sqrt(np.sum(forces * forces, axis=1))
        scale = np.minimum(1.0, self.max_force / np.maximum(norms, 1e-300))
        return forces * scale[:, None]


def _largest_norm(vectors: np.ndarray) -> float:
    return float(np.sqrt(np.max(np.sum(vectors * vectors, axis=1)))) if len(vectors) else 0.0


def minimize(
    state: State,
    forcefield: ForceField,
    fmax: float,
    max_steps: int = 10_000,
    max_force: float | None = None,
    dt: float = 0.005,
    max_step: float = 0.1,
    callback: Callable[[int, float, float], None] | None = None,
    report_every: int = 100,
    between_steps: Callable[[np.ndarray], np.ndarray] | None = None,
    stop: Callable[[], bool] | None = None,
) -> MinimizeResult:
    """Relax ``state`` with FIRE 2.0 (a push-off when ``max_force`` is given); see :class:`FIRE`.

    Examples
    --------
    >>> import md
    >>> from potentials import LennardJones
    >>> state = md.State(positions=[[0, 0, 0], [1.0, 0, 0]], box=10.0, pbc=False)
    >>> result = minimize(state, md.ForceField([LennardJones(cutoff=3.0)]), fmax=1e-6)
    >>> round(float(state.positions[1, 0] - state.positions[0, 0]), 5)  # 2^(1/6)
    1.12246
    """
    fire = FIRE(dt=dt, max_step=max_step, max_force=max_force)
    return fire.run(state, forcefield, fmax, max_steps, callback, report_every, between_steps, stop)


__all__ = ["FIRE", "MinimizeResult", "minimize"]
