"""Velocity Verlet: the symplectic, time-reversible workhorse of NVE MD."""

from __future__ import annotations

from numba import njit

from integrators.base import check_dt


class VelocityVerlet:
    """Velocity Verlet integrator (kick, drift, force, kick).

    One force evaluation per step: the forces at the end of a step are the
    ForceField's cached result at the start of the next.

    Parameters
    ----------
    dt : float
        Time step [time] (in ASE units for metal systems, e.g. ``2 * ase.units.fs``).

    Examples
    --------
    >>> VelocityVerlet(dt=0.005).dt
    0.005

    References
    ----------
    W. C. Swope, H. C. Andersen, P. H. Berens, K. R. Wilson,
    J. Chem. Phys. 76, 637 (1982).
    """

    def __init__(self, dt: float) -> None:
        self.dt = check_dt(dt)

    def step(self, state, forcefield) -> None:
        forces = forcefield.compute(state).forces
        inverse_masses = 1.0 / state.masses
        _kick_drift(state.positions, state.velocities, forces, inverse_masses, self.dt)
        forces = forcefield.compute(state).forces
        _kick(state.velocities, forces, inverse_masses, 0.5 * self.dt)
        state.step += 1
        state.time += self.dt

    def reset(self) -> None:
        """Nothing to forget: velocity Verlet is a one-step method."""

    def describe(self) -> dict:
        return {"type": "verlet", "dt": self.dt}


@njit(cache=True, error_model="numpy")
def _kick_drift(positions, velocities, forces, inverse_masses, dt):
    """v += dt/2 f/m, then x += dt v, in one pass (arrays written in place)."""
    half = 0.5 * dt
    for i in range(positions.shape[0]):
        scale = half * inverse_masses[i]
        for a in range(3):
            v = velocities[i, a] + scale * forces[i, a]
            velocities[i, a] = v
            positions[i, a] += dt * v


@njit(cache=True, error_model="numpy")
def _kick(velocities, forces, inverse_masses, half_dt):
    """v += half_dt f/m in place."""
    for i in range(velocities.shape[0]):
        scale = half_dt * inverse_masses[i]
        for a in range(3):
            velocities[i, a] += scale * forces[i, a]


__all__ = ["VelocityVerlet"]
