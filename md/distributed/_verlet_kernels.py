"""The compiled calls of a decomposed velocity Verlet step between list builds
(:meth:`md.distributed.DistributedForceField.verlet_step`): the step's first half and the
halo's forward sweep in one call; the reduction, the reverse sweep and the closing kick in
another.

Each is the passes the step made one call at a time before, in the same order and with the
same arithmetic, so the same bits: the kicks and the drift are those of
``integrators._kernels.kick_drift_by_mass`` and ``kick_by_mass`` (1/m taken per atom, then
v += kick_dt f/m, x += drift_dt v), the displacement pass and the owned rows' copy
:func:`md.distributed._domain_kernels.moved_since` with ``shift_rows`` or
``home_positions``, the messages and the reduction
:func:`md.distributed._mpi_kernels.halo_forward`, ``halo_reverse`` and ``gather_fold``
(which call MPI themselves).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from md.distributed._domain_kernels import home_positions, moved_since, shift_rows
from md.distributed._mpi_kernels import gather_fold, halo_forward, halo_reverse


@njit(cache=True, error_model="numpy")
def step_out(
    held,
    positions,
    velocities,
    forces,
    masses,
    kick_dt,
    drift_dt,
    reference,
    mapping,
    begin,
    before,
    owned,
    copied,
    n_owned,
    imaged,
    images,
    cell,
    local_positions,
    sweeps,
    table,
    shifts,
    index,
    out,
    slots,
    calls,
    list_reference,
):
    """A step's first half on this rank and the ghosts' positions sent, where ``positions``
    are the ``held`` ones (those of the forces, as :func:`md.parallel.same_values` compares
    them: NaN equals nothing; else nothing is done and the code is -1): v += kick_dt f/m and
    x += drift_dt v over the owned atoms; :func:`moved_since` of the new positions (from
    ``reference`` carried by ``mapping``, the last step start ``begin`` and the one
    ``before``; copied into ``owned``, the local system's owned rows, where it has rows);
    the first ``n_owned`` rows of ``local_positions`` at their images (``shift_rows``
    where ``copied``, else ``home_positions``); :func:`halo_forward` of
    ``local_positions``; then, as the local list's check measures it
    (:meth:`md.neighbors.NeighborList.update` over the exact list), the largest squared
    distance of a row of ``local_positions`` from ``list_reference`` (inf where one is not
    finite, or ``list_reference`` has other rows: no list to check). Returns (the MPI
    error code, 0, or -1 where nothing was done; the three squared distances of
    :func:`moved_since`; the local one)."""
    if held.shape[0] != positions.shape[0]:
        return np.int64(-1), 0.0, 0.0, 0.0, 0.0
    for i in range(positions.shape[0]):
        for a in range(3):
            if held[i, a] != positions[i, a]:
                return np.int64(-1), 0.0, 0.0, 0.0, 0.0
    for i in range(positions.shape[0]):
        scale = kick_dt * (1.0 / masses[i])
        for a in range(3):
            v = velocities[i, a] + scale * forces[i, a]
            velocities[i, a] = v
            positions[i, a] += drift_dt * v
    moved2, step2, coming2 = moved_since(positions, reference, mapping, begin, before, owned)
    home = local_positions[:n_owned]
    if copied:
        shift_rows(positions, imaged, images, cell, home)
    else:
        home_positions(positions, imaged, images, cell, home)
    code = halo_forward(local_positions, cell, sweeps, table, shifts, index, out, slots, calls)
    local2 = np.inf
    if code == 0 and list_reference.shape[0] == local_positions.shape[0]:
        local2 = largest_move2(local_positions, list_reference)
    return np.int64(code), moved2, step2, coming2, local2


@njit(cache=True, error_model="numpy")
def largest_move2(positions, reference):
    """The largest squared distance of a row of ``positions`` from ``reference``'s, each
    dx dx + dy dy + dz dz in that order (as the neighbour list's check takes it, so the
    same bits); inf where one is not finite."""
    worst = 0.0
    for i in range(positions.shape[0]):
        dx = positions[i, 0] - reference[i, 0]
        dy = positions[i, 1] - reference[i, 1]
        dz = positions[i, 2] - reference[i, 2]
        d2 = dx * dx + dy * dy + dz * dz
        if not d2 <= worst:  # (also NaN)
            worst = d2 if d2 < np.inf else np.inf
    return worst


@njit(cache=True, error_model="numpy")
def gather_reverse_kick(
    failed,
    energy,
    moved2,
    step2,
    coming2,
    allowed,
    lookahead,
    outgrown,
    stop,
    moved,
    longest,
    values,
    gathered,
    totals,
    worst,
    forces,
    sweeps,
    table,
    index,
    out,
    back,
    slots,
    calls,
    velocities,
    masses,
    kick_dt,
    check,
):
    """The evaluation's reduction (:func:`gather_fold` of ``values``, written here as
    :meth:`md.distributed.DistributedForceField._attempt` writes them for an evaluation
    without virial whose build did not fail on this rank: whether it ``failed``, its
    ``energy``, whether its list was outrun (an atom farther than ``allowed`` from its
    build position, ``moved2`` its largest squared distance, or the layout ``outgrown``),
    the look-ahead ratio (``sqrt(coming2) + lookahead sqrt(step2)`` over ``allowed``, the
    squared distances of :func:`step_out`), its ``stop`` request, whether its positions
    are not finite (``moved2``), what its step's first call found (``moved``) and the
    last build's ``longest`` bond; the sums of the first 11 into
    ``totals``, the largest of the rest into ``worst``), then, where it says that no
    rank's list was outrun (``worst[0]``), no rank's positions are not finite
    (``worst[3]``), no rank's build failed (``worst[5]``), no rank failed (``totals[0]``)
    and the energy is finite, the same on every rank: :func:`halo_reverse` of the local
    ``forces`` (the ghosts' rows summed into their owners') and the closing kick v +=
    kick_dt f/m with the owned rows (the first ``velocities.shape[0]``). With ``check``
    (the local evaluation's finite checks not made yet), first: where ``energy`` or a
    row of ``forces`` is not finite, nothing is done (no message either) and the code
    is -2. Returns (the MPI error code or 0 or -2, whether the reverse sweep and the
    kick were made)."""
    if check and not (np.isfinite(energy) and all_finite(forces)):
        return np.int64(-2), False
    coming = np.sqrt(coming2) + lookahead * np.sqrt(step2)
    outrun = not (np.sqrt(moved2) <= allowed) or outgrown
    if allowed > 0:
        ahead = coming / allowed
    else:  # (inf when nothing may move but something does)
        ahead = np.inf if coming > 0 else 0.0
    values[:] = 0.0
    values[0] = 1.0 if failed else 0.0
    values[1] = energy
    values[11] = 1.0 if outrun else 0.0
    values[12] = ahead
    values[13] = stop
    values[14] = 0.0 if np.isfinite(moved2) else 1.0
    values[15] = moved
    values[17] = longest  # (16: this rank's build did not fail)
    code = gather_fold(values, gathered, 11, totals, worst, calls)
    if code != 0:
        return np.int64(code), False
    if worst[0] != 0.0 or worst[3] != 0.0 or worst[5] != 0.0 or totals[0] != 0.0:
        return np.int64(0), False
    if not np.isfinite(totals[1]):
        return np.int64(0), False
    code = halo_reverse(forces, sweeps, table, index, out, back, slots, calls)
    if code != 0:
        return np.int64(code), False
    closing_kick(velocities, forces, masses, kick_dt)
    return np.int64(0), True


@njit(cache=True, error_model="numpy")
def all_finite(values):
    """Whether every value of the (n, 3) ``values`` is finite."""
    for i in range(values.shape[0]):
        for a in range(3):
            if not np.isfinite(values[i, a]):
                return False
    return True


@njit(cache=True, error_model="numpy")
def closing_kick(velocities, forces, masses, kick_dt):
    """v += kick_dt f/m over the rows of ``velocities`` (``forces`` may have more)."""
    for i in range(velocities.shape[0]):
        scale = kick_dt * (1.0 / masses[i])
        for a in range(3):
            velocities[i, a] += scale * forces[i, a]
