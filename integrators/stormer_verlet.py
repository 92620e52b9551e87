"""Stormer-Verlet in its position form (drift, kick, drift)."""

from __future__ import annotations

from integrators._kernels import _drift, kick_drift
from integrators.base import IntegratorBase, check_dt


class StormerVerlet(IntegratorBase):
    """Position Verlet: half drift, full kick, half drift.

    ::

        x_half = x0 + dt/2 v0
        v1     = v0 + dt a(x_half)
        x1     = x_half + dt/2 v1

    Second order, symplectic and time-reversible, like velocity Verlet (its
    adjoint splitting). The force is needed at the midpoint positions only,
    so every step costs one force evaluation that the ForceField cache cannot
    serve (an observer's energy at x1 is an extra one). ``state.positions``
    holds ``x_half`` while the force is evaluated; if that evaluation raises,
    the state is left there.

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
    >>> StormerVerlet(dt=0.005).describe()
    {'type': 'stormer_verlet', 'dt': 0.005}

    References
    ----------
    E. Hairer, C. Lubich, G. Wanner, Acta Numerica 12, 399 (2003), eq. (1.17).
    """

    order = 2
    distributed = True

    def __init__(self, dt: float) -> None:
        self.dt = check_dt(dt)
        self.statistics = {"steps": 0}

    def step(self, state, forcefield) -> None:
        dt = self.dt
        _drift(state.positions, state.velocities, 0.5 * dt)
        forces = forcefield.compute(state, virial=False).forces
        kick_drift(state.positions, state.velocities, forces, 1.0 / state.masses, dt, 0.5 * dt)
        self.end_step(state)
        self.statistics["steps"] += 1

    def reset(self) -> None:
        """Nothing to forget: Stormer-Verlet is a one-step method."""

    def describe(self) -> dict:
        return {"type": "stormer_verlet", "dt": self.dt}


__all__ = ["StormerVerlet"]
