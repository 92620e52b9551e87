"""Numba kernels shared by the explicit integrators (arrays written in place)."""

from __future__ import annotations

from numba import njit, prange

from md.parallel import chunk_count

#: Fewest atoms per thread worth a chunk of their own in these memory-bound passes
#: (below, waking a thread costs more than the pass). 16000, as the displacement check's:
#: the 32000-atom melt at 2 threads (Emerald Rapids VM) spends 28-32 ms per 100 steps in
#: its integrator with the passes split, 44-46 ms with them whole (the earlier 50000).
_MIN_CHUNK_ATOMS = 16_000

#: Fewest atoms that ``kick_drift`` and ``kick`` split into chunks (below: one pass).
SERIAL_ATOMS = 2 * _MIN_CHUNK_ATOMS


def _chunks(n: int) -> int:
    return chunk_count(n, _MIN_CHUNK_ATOMS)


def kick_drift(positions, velocities, forces, inverse_masses, kick_dt, drift_dt) -> None:
    """v += kick_dt f/m, then x += drift_dt v, on one thread per chunk of atoms (same bits
    on any number: each atom's update is its own)."""
    n = positions.shape[0]
    # (under two chunks' worth there is one chunk on any number of threads: not asked)
    chunks = 1 if n < SERIAL_ATOMS else _chunks(n)
    if chunks == 1:
        _kick_drift(positions, velocities, forces, inverse_masses, kick_dt, drift_dt)
    else:
        _kick_drift_threaded(
            positions, velocities, forces, inverse_masses, kick_dt, drift_dt, chunks
        )


def kick(velocities, forces, inverse_masses, kick_dt) -> None:
    """v += kick_dt f/m, on one thread per chunk of atoms."""
    n = velocities.shape[0]
    chunks = 1 if n < SERIAL_ATOMS else _chunks(n)
    if chunks == 1:
        _kick(velocities, forces, inverse_masses, kick_dt)
    else:
        _kick_threaded(velocities, forces, inverse_masses, kick_dt, chunks)


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
def kick_drift_by_mass(positions, velocities, forces, masses, kick_dt, drift_dt):
    """v += kick_dt f/m, then x += drift_dt v, in one pass on this thread, as
    ``_kick_drift`` but with the masses themselves: 1/m is taken here, atom by atom (the
    same bits as numpy's ``1.0 / masses``: one correctly rounded division each), so a
    small system's step makes no array of inverse masses."""
    for i in range(positions.shape[0]):
        scale = kick_dt * (1.0 / masses[i])
        for a in range(3):
            v = velocities[i, a] + scale * forces[i, a]
            velocities[i, a] = v
            positions[i, a] += drift_dt * v


@njit(cache=True, error_model="numpy")
def kick_by_mass(velocities, forces, masses, kick_dt):
    """v += kick_dt f/m in one pass on this thread, with the masses themselves (see
    ``kick_drift_by_mass``)."""
    for i in range(velocities.shape[0]):
        scale = kick_dt * (1.0 / masses[i])
        for a in range(3):
            velocities[i, a] += scale * forces[i, a]


@njit(cache=True, parallel=True, error_model="numpy")
def _kick_drift_threaded(positions, velocities, forces, inverse_masses, kick_dt, drift_dt, chunks):
    n = positions.shape[0]
    for c in prange(chunks):
        a, b = c * n // chunks, (c + 1) * n // chunks
        _kick_drift(
            positions[a:b], velocities[a:b], forces[a:b], inverse_masses[a:b], kick_dt, drift_dt
        )


@njit(cache=True, parallel=True, error_model="numpy")
def _kick_threaded(velocities, forces, inverse_masses, kick_dt, chunks):
    n = velocities.shape[0]
    for c in prange(chunks):
        a, b = c * n // chunks, (c + 1) * n // chunks
        _kick(velocities[a:b], forces[a:b], inverse_masses[a:b], kick_dt)


@njit(cache=True, error_model="numpy")
def _drift(positions, velocities, dt):
    """x += dt v."""
    for i in range(positions.shape[0]):
        for a in range(3):
            positions[i, a] += dt * velocities[i, a]


@njit(cache=True, error_model="numpy")
def _linear_flow(x, y, y_scale, e, p):
    """x_i <- e x_i + p (y_i y_scale_i) for each row i (column vectors; e, p (3, 3)).

    The exact flow of dx/dt = A x + c over a time t is x <- exp(A t) x +
    t phi(A t) c; the MTK barostat moves positions (c = v) and velocities
    (c = F / m) this way.
    """
    for i in range(x.shape[0]):
        s = y_scale[i]
        x0, x1, x2 = x[i, 0], x[i, 1], x[i, 2]
        y0, y1, y2 = s * y[i, 0], s * y[i, 1], s * y[i, 2]
        for a in range(3):
            x[i, a] = (
                e[a, 0] * x0
                + e[a, 1] * x1
                + e[a, 2] * x2
                + p[a, 0] * y0
                + p[a, 1] * y1
                + p[a, 2] * y2
            )
