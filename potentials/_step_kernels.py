"""numba passes of the mixed-precision velocity Verlet step over a cluster-pair list.

The step made of separate calls (the kick and drift, the list's displacement check, the
force field's copy of the positions for its cache, the cluster kernel's relative
positions; after the kernel the chunks' sum into atom order and the finite check of the
forces) passes over the atoms' arrays six times besides the kernel. These memory-bound
passes do not halve on two cores that share one memory bus, so
:meth:`potentials.PairPotential.mixed_verlet_step` makes them two:

- :func:`kick_drift_slots`: per atom, in atom order, v += dt/2 f/m, x += dt v, the new
  x into the cache's copy and its squared displacement from the list's reference; then,
  while the list holds, per slot of the cluster list the float32 position relative to
  its origin (the kernel's ``xi``/``xj``), gathered by slot: one compiled call, two
  threaded loops (a single loop over the slots, gathering every atom's arrays by slot,
  took 0.47 ms of work a step on the 32000-atom melt against 0.29 for the separate
  passes, this one 0.16);
- :func:`finish_step`: after the kernel, its chunks' sum into atom order with the finite
  check of each force on the way, then (all finite) the last kick: one compiled call.

Each value is computed with the arithmetic of the separate passes (the same bits:
``integrators._kernels``, ``md.neighbors``' displacement check and relative positions,
``potentials._kernels._slot_forces``).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from md._simd import bits_float, float_bits
from md.parallel import chunk_count
from potentials._kernels import CLUSTER, _slot_forces, cluster_sum_runs

#: Fewest slots per thread worth a chunk of their own in these memory-bound passes (as
#: the relative positions' and the sum's: ``md.neighbors``' and ``potentials._kernels``').
_MIN_PASS_SLOTS = 16_000

#: Bit patterns: all but the sign bit, and +inf (every NaN's magnitude bits are above it).
_MAGNITUDE = np.int64(0x7FFFFFFFFFFFFFFF)
_INF_BITS = np.int64(0x7FF0000000000000)


def pass_chunks(n: int) -> int:
    """Chunks of a pass over ``n`` atoms or slots: one per thread, each of at least
    ``_MIN_PASS_SLOTS`` (as the cluster list's relative positions split theirs)."""
    return chunk_count(n, _MIN_PASS_SLOTS)


def kick_drift_slots(
    positions,
    velocities,
    forces,
    masses,
    kick_dt,
    drift_dt,
    held,
    allowed2,
    key,
    atom,
    origin,
    xi,
    xj,
    chunks: int,
) -> float:
    """v += kick_dt f/m and x += drift_dt v for each atom, the new x copied into ``key``
    (N, 3), in ``chunks`` chunks of atoms on the threads; then, if no atom is farther
    than sqrt(``allowed2``) from its place in ``held`` (N, 3), each slot's float32
    position relative to ``origin`` into ``xi`` and ``xj`` (``atom``: each slot's atom,
    -1 for a filler, whose values are left as they are: they do not depend on the
    positions), in ``chunks`` runs of whole clusters. One compiled call. Returns the
    largest squared distance from ``held`` (inf if a coordinate is not finite)."""
    if chunks == 1:
        worst = _kick_drift_slots(
            positions,
            velocities,
            forces,
            masses,
            kick_dt,
            drift_dt,
            held,
            allowed2,
            key,
            atom,
            origin,
            xi,
            xj,
        )
    else:
        worst = _kick_drift_slots_threaded(
            positions,
            velocities,
            forces,
            masses,
            kick_dt,
            drift_dt,
            held,
            allowed2,
            key,
            atom,
            origin,
            xi,
            xj,
            chunks,
        )
    return worst


@njit(cache=True, error_model="numpy")
def _as_float(worst):
    if worst >= _INF_BITS:
        return np.inf
    return bits_float(worst)


@njit(cache=True, error_model="numpy")
def _kick_drift_held(positions, velocities, forces, masses, kick_dt, drift_dt, held, key):
    """The kick, drift and copy of :func:`kick_drift_slots` over these atoms, in atom
    order; the largest squared displacement from ``held`` as its bit pattern, sign
    cleared (as the list's check takes its maximum: the loop vectorises, and inf and
    every NaN lie above the finite values)."""
    worst = np.int64(0)
    for i in range(positions.shape[0]):
        # 1/m and the kick as integrators._kernels.kick_drift_by_mass takes them
        scale = kick_dt * (1.0 / masses[i])
        vx = velocities[i, 0] + scale * forces[i, 0]
        vy = velocities[i, 1] + scale * forces[i, 1]
        vz = velocities[i, 2] + scale * forces[i, 2]
        velocities[i, 0], velocities[i, 1], velocities[i, 2] = vx, vy, vz
        x = positions[i, 0] + drift_dt * vx
        y = positions[i, 1] + drift_dt * vy
        z = positions[i, 2] + drift_dt * vz
        positions[i, 0], positions[i, 1], positions[i, 2] = x, y, z
        key[i, 0], key[i, 1], key[i, 2] = x, y, z
        # the displacement as the list's check takes it
        dx = x - held[i, 0]
        dy = y - held[i, 1]
        dz = z - held[i, 2]
        worst = max(worst, float_bits(dx * dx + dy * dy + dz * dz) & _MAGNITUDE)
    return worst


@njit(cache=True, error_model="numpy")
def _relative_positions(positions, atom, origin, xi, xj):
    """Each real slot's position relative to its origin, in float32, as ``md.neighbors``'
    cluster list writes them (per cluster x0..x3, y0..y3, z0..z3; fillers skipped)."""
    for s in range(atom.shape[0]):
        i = atom[s]
        if i >= 0:
            base = (s // CLUSTER) * 3 * CLUSTER + s % CLUSTER
            for d in range(3):
                value = np.float32(positions[i, d] - origin[s, d])
                xi[base + d * CLUSTER] = value
                xj[base + d * CLUSTER] = value


@njit(cache=True, error_model="numpy")
def _kick_drift_slots(
    positions,
    velocities,
    forces,
    masses,
    kick_dt,
    drift_dt,
    held,
    allowed2,
    key,
    atom,
    origin,
    xi,
    xj,
):
    """:func:`kick_drift_slots` on this thread."""
    worst = _as_float(
        _kick_drift_held(positions, velocities, forces, masses, kick_dt, drift_dt, held, key)
    )
    if worst <= allowed2:
        _relative_positions(positions, atom, origin, xi, xj)
    return worst


@njit(cache=True, parallel=True, error_model="numpy")
def _kick_drift_slots_threaded(
    positions,
    velocities,
    forces,
    masses,
    kick_dt,
    drift_dt,
    held,
    allowed2,
    key,
    atom,
    origin,
    xi,
    xj,
    chunks,
):
    """:func:`kick_drift_slots` on the threads: the atoms' chunks, then (every atom
    drifted) the slots' runs, each of whole clusters, their slots passed as slices
    counted from zero (as ``md.neighbors``' threaded relative positions, for the same
    reason: numba's handling of negative indices otherwise stays in the loop)."""
    n = positions.shape[0]
    largest = np.zeros(chunks, np.int64)
    for c in prange(chunks):
        a, b = c * n // chunks, (c + 1) * n // chunks
        largest[c] = _kick_drift_held(
            positions[a:b],
            velocities[a:b],
            forces[a:b],
            masses[a:b],
            kick_dt,
            drift_dt,
            held[a:b],
            key[a:b],
        )
    worst = _as_float(largest.max())
    if worst <= allowed2:
        m = atom.shape[0] // CLUSTER
        for c in prange(chunks):
            a, b = CLUSTER * (c * m // chunks), CLUSTER * ((c + 1) * m // chunks)
            _relative_positions(
                positions, atom[a:b], origin[a:b], xi[3 * a : 3 * b], xj[3 * a : 3 * b]
            )
    return worst


def cluster_runs(windows, n_slots: int) -> np.ndarray:
    """Where the runs of :func:`finish_step`'s sum start, in clusters (as
    ``potentials._kernels.cluster_atom_forces`` splits its sum: one run per thread, each
    of at least ``_MIN_PASS_SLOTS`` slots, of equal work by ``cluster_sum_runs``)."""
    runs = chunk_count(n_slots, _MIN_PASS_SLOTS)
    if runs == 1:
        return np.array([0, n_slots // CLUSTER], np.int64)
    return cluster_sum_runs(windows, n_slots // CLUSTER, runs)


def finish_step(
    buffers, atom, windows, forces, first, energies, velocities, masses, kick_dt, chunks: int
) -> float:
    """After the cluster kernel: its chunks' cluster-ordered forces summed into
    ``forces`` (N, 3) in atom order where it ran in several (``energies`` holds one
    energy per chunk; ``first``: the sum's runs, :func:`cluster_runs`), as
    ``potentials._kernels.cluster_atom_forces`` sums them, with the finite check of
    each force on the way (one chunk wrote ``forces`` itself: they are checked); the
    energy summed as numpy sums ``energies``; then, if the forces and the energy are
    finite, v += kick_dt f/m (1/m taken atom by atom, as ``integrators._kernels``'
    ``kick_by_mass``) in ``chunks`` chunks of atoms. One compiled call. Returns the
    energy, or NaN where a force or the energy is not finite (then nothing is kicked)."""
    if energies.shape[0] == 1:
        return _finish_one_chunk(forces, energies, velocities, masses, kick_dt)
    if chunks == 1 and first.shape[0] == 2:
        return _finish_summed(
            buffers, atom, windows, forces, first, energies, velocities, masses, kick_dt
        )
    return _finish_summed_threaded(
        buffers, atom, windows, forces, first, energies, velocities, masses, kick_dt, chunks
    )


def finish_forces(forces, energy: float, velocities, masses, kick_dt) -> float:
    """After a force call made apart (the list refreshed since :func:`kick_drift_slots`):
    the finite check of ``forces`` (N, 3, atom order) and of ``energy``, then, all finite,
    v += kick_dt f/m (as :func:`finish_step` kicks). One serial compiled call, the one
    :func:`finish_step` makes after a kernel of one chunk (no other kernel to compile for
    the fifth of the steps that take this path). Returns ``energy``, or NaN where it or
    a force is not finite (nothing kicked)."""
    return _finish_one_chunk(forces, np.full(1, energy), velocities, masses, kick_dt)


@njit(cache=True, inline="always", error_model="numpy")
def _energy(energies):
    """The chunks' energies summed as numpy sums them (left to right from the first)."""
    energy = energies[0]
    for c in range(1, energies.shape[0]):
        energy += energies[c]
    return energy


@njit(cache=True, error_model="numpy")
def _finish_one_chunk(forces, energies, velocities, masses, kick_dt):
    finite = True
    for i in range(forces.shape[0]):
        for a in range(3):
            finite &= abs(forces[i, a]) < np.inf
    energy = _energy(energies)
    if not (finite and abs(energy) < np.inf):
        return np.nan
    _kick_by_mass(velocities, forces, masses, kick_dt)
    return energy


@njit(cache=True, error_model="numpy")
def _finish_summed(buffers, atom, windows, forces, first, energies, velocities, masses, kick_dt):
    finite = _slot_forces(buffers, atom, windows, forces, 0, CLUSTER * first[-1])
    energy = _energy(energies)
    if not (finite and abs(energy) < np.inf):
        return np.nan
    _kick_by_mass(velocities, forces, masses, kick_dt)
    return energy


@njit(cache=True, parallel=True, error_model="numpy")
def _finish_summed_threaded(
    buffers, atom, windows, forces, first, energies, velocities, masses, kick_dt, chunks
):
    runs = first.shape[0] - 1
    finite = np.ones(runs, np.bool_)
    for r in prange(runs):
        finite[r] = _slot_forces(
            buffers, atom, windows, forces, CLUSTER * first[r], CLUSTER * first[r + 1]
        )
    energy = _energy(energies)
    if not (finite.all() and abs(energy) < np.inf):
        return np.nan
    n = velocities.shape[0]
    for c in prange(chunks):
        a, b = c * n // chunks, (c + 1) * n // chunks
        _kick_by_mass(velocities[a:b], forces[a:b], masses[a:b], kick_dt)
    return energy


@njit(cache=True, error_model="numpy")
def _kick_by_mass(velocities, forces, masses, kick_dt):
    """v += kick_dt f/m, 1/m taken atom by atom (as ``integrators._kernels``'
    ``kick_by_mass``: the same bits as a kick with numpy's ``1.0 / masses``)."""
    for i in range(velocities.shape[0]):
        scale = kick_dt * (1.0 / masses[i])
        for a in range(3):
            velocities[i, a] += scale * forces[i, a]
