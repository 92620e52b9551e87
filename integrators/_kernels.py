"""Numba kernels shared by the explicit integrators (arrays written in place)."""

from __future__ import annotations

from numba import njit


@njit(cache=True, error_model="numpy")
def _kick_drift(positions, velocities, forces, inverse_masses, kick_dt, drift_dt):
    """v += kick_dt f/m, then x += drift_dt v (the new v), in one pass."""
    for i in range(positions.shape[0]):
        scale = kick_dt * inverse_masses[i]
        for a in range(3):
            v = velocities[i, a] + scale * forces[i, a]
            velocities[i, a] = v
            positions[i, a] += drift_dt * v


@njit(cache=True, error_model="numpy")
def _kick(velocities, forces, inverse_masses, kick_dt):
    """v += kick_dt f/m."""
    for i in range(velocities.shape[0]):
        scale = kick_dt * inverse_masses[i]
        for a in range(3):
            velocities[i, a] += scale * forces[i, a]


@njit(cache=True, error_model="numpy")
def _drift(positions, velocities, dt):
    """x += dt v."""
    for i in range(positions.shape[0]):
        for a in range(3):
            positions[i, a] += dt * velocities[i, a]
