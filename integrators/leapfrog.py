"""Leapfrog: kick-drift with private half-step velocities, synchronised on output."""

from __future__ import annotations

import numpy as np
from numba import njit

from integrators._kernels import kick_drift
from integrators.base import IntegratorBase, check_dt


class Leapfrog(IntegratorBase):
    """Leapfrog (kick-drift) integrator with half-step velocities kept privately.

    Each step, with a(t) = f(x(t)) / m::

        v(t + dt/2) = v(t - dt/2) + dt a(t)      # kick (first step: v(t) + dt/2 a(t))
        x(t + dt)   = x(t) + dt v(t + dt/2)      # drift
        v(t + dt)   = v(t + dt/2) + dt/2 a(t + dt)

    The last line is the synchronised velocity written into
    ``state.velocities``: the half-step velocity plus half a kick with the force
    at the new positions, which equals the average
    (v(t + dt/2) + v(t + 3dt/2)) / 2 of the neighbouring half-step velocities
    in exact arithmetic. The half-step velocities v(t + dt/2) themselves stay
    private. The scheme is velocity Verlet reorganised: from the same start
    both give the same positions and velocities in exact arithmetic (the
    first step is bitwise identical), and they differ only by round-off
    (one ``dt`` kick here against two ``dt/2`` kicks there).

    One force evaluation per step: the forces at the new positions, needed
    for the synchronised velocities, are the ForceField's cached result at the
    start of the next step.

    The half-step velocities are (re)initialised from ``state.velocities`` on
    the first step, after :meth:`reset`, and whenever the state was changed
    outside the integrator since its last step (another State object,
    positions or velocities replaced or edited in place, ``step``/``time``
    changed, a new ``dt``). Reversing the velocities in place therefore
    restarts the scheme, and the run retraces its path.

    Parameters
    ----------
    dt : float
        Time step [time].

    Attributes
    ----------
    statistics : dict
        Cumulative counters: ``steps`` taken and ``restarts`` (initialisations
        of the half-step velocities).

    Examples
    --------
    >>> Leapfrog(dt=0.005).describe()
    {'type': 'leapfrog', 'dt': 0.005}

    References
    ----------
    R. W. Hockney, J. W. Eastwood, *Computer Simulation Using Particles*
    (McGraw-Hill, 1981); M. P. Allen, D. J. Tildesley, *Computer Simulation
    of Liquids*, 2nd ed. (OUP, 2017), sec. 3.2.
    """

    order = 2
    distributed = True
    per_atom_state = ("half_velocities",)

    def __init__(self, dt: float) -> None:
        self.dt = check_dt(dt)
        self.statistics = {"steps": 0, "restarts": 0}
        self._half: np.ndarray | None = None  # v(t + dt/2) of the last step
        self._state = None
        self._mark: tuple | None = None  # (positions, velocities, step, time, dt) after the step
        self._positions: np.ndarray | None = None  # copies of what the last step left
        self._velocities: np.ndarray | None = None
        self._adopt = False  # set_state: the next step continues whatever state it is given

    def step(self, state, forcefield) -> None:
        dt = self.dt
        forces = forcefield.compute(state, virial=False).forces
        inverse_masses = 1.0 / state.masses
        if self._half is not None and (self._adopted(state) or self._continues(state)):
            kick_drift(state.positions, self._half, forces, inverse_masses, dt, dt)
        else:
            self.statistics["restarts"] += 1
            self._half = state.velocities.copy()
            kick_drift(state.positions, self._half, forces, inverse_masses, 0.5 * dt, dt)
        forces = forcefield.compute(state, virial=False).forces
        _synchronise(state.velocities, self._half, forces, inverse_masses, 0.5 * dt)
        self.end_step(state)
        self.statistics["steps"] += 1
        self._remember(state)

    def reset(self) -> None:
        """Drop the half-step velocities; the next step starts from ``state.velocities``."""
        self._half = None
        self._state = None
        self._mark = None
        self._adopt = False

    def get_state(self) -> dict:
        """Return the private state for a checkpoint: the half-step velocities v(t + dt/2).

        ``{"half_velocities": None}`` before the first step or after :meth:`reset`.
        """
        half = None if self._half is None else self._half.copy()
        return {"half_velocities": half, "statistics": dict(self.statistics)}

    def set_state(self, saved: dict) -> None:
        """Restore :meth:`get_state`'s result; the next step continues from it exactly.

        The next step then trusts that it is given the State saved with these
        half-step velocities (a checkpoint restores both together).
        """
        half = saved["half_velocities"]
        if half is None:
            self.reset()
        else:
            half = np.array(half, dtype=np.float64)
            if half.ndim != 2 or half.shape[1] != 3:
                raise ValueError(f"half_velocities must have shape (N, 3), got {half.shape}")
            self._half = np.ascontiguousarray(half)
            self._state = None
            self._mark = None
            self._adopt = True
        self.statistics.update({k: int(v) for k, v in saved.get("statistics", {}).items()})

    def describe(self) -> dict:
        return {"type": "leapfrog", "dt": self.dt}

    def _remember(self, state) -> None:
        if self._positions is None or self._positions.shape != state.positions.shape:
            self._positions = np.empty_like(state.positions)
            self._velocities = np.empty_like(state.velocities)
        np.copyto(self._positions, state.positions)
        np.copyto(self._velocities, state.velocities)
        self._state = state
        self._mark = (state.positions, state.velocities, state.step, state.time, self.dt)

    def _adopted(self, state) -> bool:
        """Whether set_state asked to continue, for a state of the saved size (used once)."""
        adopt, self._adopt = self._adopt, False
        return adopt and self._half.shape == state.velocities.shape

    def _continues(self, state) -> bool:
        """Whether ``state`` is exactly what the last step left (nothing changed it since)."""
        if state is not self._state or self._mark is None:
            return False
        positions, velocities, step, time, dt = self._mark
        return (
            state.positions is positions
            and state.velocities is velocities
            and state.step == step
            and state.time == time
            and self.dt == dt
            and np.array_equal(state.positions, self._positions)
            and np.array_equal(state.velocities, self._velocities)
        )


@njit(cache=True, error_model="numpy")
def _synchronise(velocities, half_velocities, forces, inverse_masses, half_dt):
    """velocities = v_half + half_dt f/m (written in place)."""
    for i in range(velocities.shape[0]):
        scale = half_dt * inverse_masses[i]
        for a in range(3):
            velocities[i, a] = half_velocities[i, a] + scale * forces[i, a]


__all__ = ["Leapfrog"]
