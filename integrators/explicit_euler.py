"""First-order Euler integrators: explicit (forward) and symplectic (semi-implicit)."""

from __future__ import annotations

from numba import njit

from integrators._kernels import kick_drift
from integrators.base import IntegratorBase, check_dt


class ExplicitEuler(IntegratorBase):
    """Explicit (forward) Euler: x1 = x0 + dt v0, v1 = v0 + dt a(x0).

    First order and not symplectic: on a harmonic oscillator the energy grows
    by the factor 1 + (w dt)^2 every step, so it is a teaching and testing
    baseline, not a production integrator. One force evaluation per step.

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
    >>> ExplicitEuler(dt=0.001).describe()
    {'type': 'explicit_euler', 'dt': 0.001}
    """

    order = 1
    distributed = True

    def __init__(self, dt: float) -> None:
        self.dt = check_dt(dt)
        self.statistics = {"steps": 0}

    def step(self, state, forcefield) -> None:
        forces = forcefield.compute(state, virial=False).forces
        _explicit_euler(state.positions, state.velocities, forces, 1.0 / state.masses, self.dt)
        self.end_step(state)
        self.statistics["steps"] += 1

    def reset(self) -> None:
        """Nothing to forget: explicit Euler is a one-step method."""

    def describe(self) -> dict:
        return {"type": "explicit_euler", "dt": self.dt}


class SymplecticEuler(IntegratorBase):
    """Symplectic (semi-implicit) Euler: v1 = v0 + dt a(x0), x1 = x0 + dt v1.

    First order but symplectic: on an oscillator the energy oscillates within
    bounds and does not drift (it conserves a modified energy exactly). It is
    the leapfrog kick-drift read with unsynchronised velocities. One force
    evaluation per step.

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
    >>> SymplecticEuler(dt=0.001).describe()
    {'type': 'symplectic_euler', 'dt': 0.001}
    """

    order = 1
    distributed = True

    def __init__(self, dt: float) -> None:
        self.dt = check_dt(dt)
        self.statistics = {"steps": 0}

    def step(self, state, forcefield) -> None:
        forces = forcefield.compute(state, virial=False).forces
        kick_drift(state.positions, state.velocities, forces, 1.0 / state.masses, self.dt, self.dt)
        self.end_step(state)
        self.statistics["steps"] += 1

    def reset(self) -> None:
        """Nothing to forget: symplectic Euler is a one-step method."""

    def describe(self) -> dict:
        return {"type": "symplectic_euler", "dt": self.dt}


@njit(cache=True, error_model="numpy")
def _explicit_euler(positions, velocities, forces, inverse_masses, dt):
    """x += dt v (old v), then v += dt f/m, in place."""
    for i in range(positions.shape[0]):
        scale = dt * inverse_masses[i]
        for a in range(3):
            v = velocities[i, a]
            positions[i, a] += dt * v
            velocities[i, a] = v + scale * forces[i, a]


__all__ = ["ExplicitEuler", "SymplecticEuler"]
