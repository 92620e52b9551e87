"""The device kernels (numba-cuda): neighbour search, pair forces, integrator passes, sums.

Importing this module imports ``numba.cuda`` (the simulator where ``NUMBA_ENABLE_CUDASIM=1``
was set before); ``md.cuda`` loads it only for a run that asks for the device.

Layout: per-atom arrays are (N, 3) or (N,) in the device state's order, but for the
positions, (N, 4) with the atom's type in the fourth column (a 32-byte row: one sector of
memory holds a neighbour's position and type, where (N, 3) rows and a separate type array
touched two or three); the neighbour list is a full list stored column by column,
``neighbors[k, i]`` the k-th partner of atom i, so that the threads of a warp (consecutive
i) read consecutive words. One thread per atom in every per-atom kernel; the force kernel
writes only its own atom's row (no atomics). The physics (the pair term with the frame's
cutoff treatment, the minimum image) is the CPU path's own functions compiled as device
functions (``potentials.device_terms.retarget``).

Each kernel here has a CPU twin that ``tests/test_gpu.py`` compares it with: the search with
the O(N^2) reference, the forces with ``PairPotential.energy_forces``, the passes with
``integrators._kernels`` through the integrators' steps, the sums with numpy's.
"""

from __future__ import annotations

import functools
import math

import numba
import numpy as np
from numba import cuda
from numba.cuda import libdevice

from md.box import min_image
from potentials.device_terms import retarget

#: Threads per block of the per-atom kernels.
BLOCK = 128
#: The most threads per block of the sums and of the passes fused with them (a power of
#: two: :func:`sum_threads` gives fewer to a small system), and the most blocks they take
#: (a grid-stride loop covers the atoms past them).
SUM_THREADS = 128
SUM_BLOCKS = 1024
#: The most threads of the one block that scans the cell counts (a power of two).
SCAN_THREADS = 1024
#: Columns of the per-atom observables: energy, the virial (xx, yy, zz, yz, xz, xy), and
#: the kinetic energy (filled by the sum kernel).
N_OBSERVABLES = 8


#: numpy functions the CUDA target lacks on scalars (its ufunc table has none of these),
#: and what the device functions call instead: math's, which it compiles to libdevice, and
#: libdevice's rint (half to even, as np.rint). The simulator runs the Python as it is,
#: numpy included (its libdevice functions are stubs).
_MATH = ("sqrt", "exp", "expm1", "log", "log1p", "sin", "cos", "tan", "floor", "ceil")
_SUBSTITUTES = (
    {}
    if numba.config.ENABLE_CUDASIM
    else {
        "rint": libdevice.rint,
        "arccos": math.acos,
        "arcsin": math.asin,
        "arctan": math.atan,
        "power": math.pow,
        **{name: getattr(math, name) for name in _MATH},  # math's functions, by name
    }
)


def device_function(function):
    """A numba function (and what it calls) as a CUDA device function."""
    return retarget(
        function, lambda plain: cuda.jit(device=True, inline="always")(plain), _SUBSTITUTES
    )


_min_image = device_function(min_image)


def launch(n: int) -> tuple[int, int]:
    """(blocks, threads per block) for one thread per item of ``n``: BLOCK threads, fewer
    (whole warps) for a system smaller than a block."""
    threads = min(BLOCK, max(32, (n + 31) // 32 * 32))
    return max(1, (n + threads - 1) // threads), threads


# ---------------------------------------------------------------- neighbour search
@cuda.jit(device=True, inline="always")
def _check_moved(positions, reference, limit2, flag, i):
    """Set ``flag[0] = 1`` if atom i moved farther than sqrt(limit2) since the build (the
    same value from every thread that sees it: no atomics needed)."""
    dx = positions[i, 0] - reference[i, 0]
    dy = positions[i, 1] - reference[i, 1]
    dz = positions[i, 2] - reference[i, 2]
    if not dx * dx + dy * dy + dz * dz <= limit2:  # NaN moves count as moved
        flag[0] = 1


@cuda.jit
def _cell_of(positions, lengths, n_cells, rank, cells, counts):
    """Each atom's cell, ``rank[c]`` of its row-major number c over n_cells, in ``cells``
    (``rank`` the identity for the search, the cells' places along a space-filling curve
    for a sort); ``counts`` per cell (atomic increments: this is the counting sort's
    histogram, not the force kernel)."""
    i = cuda.grid(1)
    if i < positions.shape[0]:
        code = 0
        for a in range(3):
            s = positions[i, a] / lengths[a]
            s -= math.floor(s)
            c = int(s * n_cells[a])
            if c >= n_cells[a]:
                c = n_cells[a] - 1
            code = code * n_cells[a] + c
        code = rank[code]
        cells[i] = code
        cuda.atomic.add(counts, code, 1)


def sum_threads(n: int) -> int:
    """Threads per block of the sums over ``n`` atoms: a power of two, 32 to SUM_THREADS."""
    threads = 32
    while threads < min(n, SUM_THREADS):
        threads *= 2
    return threads


def scan_threads(n_cells: int) -> int:
    """Threads of :func:`_cell_starts`'s one block: a power of two, 32 to SCAN_THREADS."""
    threads = 32
    while threads < min(n_cells, SCAN_THREADS):
        threads *= 2
    return threads


@cuda.jit
def _cell_starts(counts, starts, cursors):
    """Exclusive prefix sum of ``counts`` into ``starts`` by one block: each thread sums a
    run of consecutive cells, the block scans those sums (Hillis-Steele, in shared
    memory), each thread writes its run's starts; ``cursors`` and ``counts`` zeroed for
    the scatter and the next histogram."""
    shared = cuda.shared.array(SCAN_THREADS, dtype=numba.int32)
    t = cuda.threadIdx.x
    threads = cuda.blockDim.x
    n = counts.shape[0]
    run = (n + threads - 1) // threads
    first = min(t * run, n)
    last = min(first + run, n)
    own = 0
    for c in range(first, last):
        own += counts[c]
    shared[t] = own
    cuda.syncthreads()
    width = 1
    while width < threads:
        before = shared[t - width] if t >= width else 0
        cuda.syncthreads()
        shared[t] += before
        cuda.syncthreads()
        width *= 2
    total = shared[t] - own  # the cells before this thread's run
    for c in range(first, last):
        starts[c] = total
        total += counts[c]
        cursors[c] = 0
        counts[c] = 0
    if t == threads - 1:
        starts[n] = shared[t]


@cuda.jit
def _scatter(cells, starts, cursors, order):
    """The atoms by cell: ``order[starts[c]:starts[c + 1]]`` are cell c's (in any order)."""
    i = cuda.grid(1)
    if i < cells.shape[0]:
        c = cells[i]
        order[starts[c] + cuda.atomic.add(cursors, c, 1)] = i


@cuda.jit
def _sort_cells(starts, order):
    """Each cell's atoms in index order (insertion sort, one thread per cell): the scatter's
    atomic order varies from run to run, the lists and sums then do not."""
    c = cuda.grid(1)
    if c < starts.shape[0] - 1:
        for a in range(starts[c] + 1, starts[c + 1]):
            atom = order[a]
            b = a - 1
            while b >= starts[c] and order[b] > atom:
                order[b + 1] = order[b]
                b -= 1
            order[b + 1] = atom


@cuda.jit
def _search_cells(
    positions, lengths, inverse, tilt, n_cells, cells, starts, order, radius2, neighbors, counts
):
    """Atom i's partners within sqrt(radius2) from the 27 cells around its own (at least
    three cells along each axis: no cell is visited twice), in cell then index order.
    ``counts[i]`` is the number found, also past the list's room (the host then regrows)."""
    i = cuda.grid(1)
    if i >= positions.shape[0]:
        return
    code = cells[i]
    cz = code % n_cells[2]
    cy = (code // n_cells[2]) % n_cells[1]
    cx = code // (n_cells[2] * n_cells[1])
    m = 0
    for ox in range(-1, 2):
        x = (cx + ox) % n_cells[0]
        for oy in range(-1, 2):
            y = (cy + oy) % n_cells[1]
            for oz in range(-1, 2):
                c = (x * n_cells[1] + y) * n_cells[2] + (cz + oz) % n_cells[2]
                for a in range(starts[c], starts[c + 1]):
                    m = _listed(
                        positions, lengths, inverse, tilt, radius2, neighbors, i, order[a], m
                    )
    counts[i] = m


@cuda.jit(device=True, inline="always")
def _listed(positions, lengths, inverse, tilt, radius2, neighbors, i, j, m):
    """Atom j as atom i's partner number ``m`` if within sqrt(radius2) (its own index
    excluded; written only within the list's room): the count after it."""
    if j == i:
        return m
    dx, dy, dz = _min_image(
        positions[i, 0] - positions[j, 0],
        positions[i, 1] - positions[j, 1],
        positions[i, 2] - positions[j, 2],
        lengths,
        inverse,
        tilt,
    )
    if dx * dx + dy * dy + dz * dz < radius2:
        if m < neighbors.shape[0]:
            neighbors[m, i] = j
        m += 1
    return m


@cuda.jit
def _search_all(positions, lengths, inverse, tilt, radius2, neighbors, counts):
    """Atom i's partners within sqrt(radius2) among all atoms, in index order (small or open
    cells, tilted cells: the O(N^2) search, also the reference of the cell search)."""
    i = cuda.grid(1)
    if i >= positions.shape[0]:
        return
    m = 0
    for j in range(positions.shape[0]):
        m = _listed(positions, lengths, inverse, tilt, radius2, neighbors, i, j, m)
    counts[i] = m


@cuda.jit
def _gather(source, order, out):
    """out[k] = source[order[k]] (a sort's gather of a per-atom vector)."""
    k = cuda.grid(1)
    if k < out.shape[0]:
        out[k] = source[order[k]]


@cuda.jit
def _gather_rows(source, order, out):
    """out[k, :] = source[order[k], :] (a sort's gather of per-atom rows)."""
    k = cuda.grid(1)
    if k < out.shape[0]:
        for a in range(out.shape[1]):
            out[k, a] = source[order[k], a]


@cuda.jit
def _remember(positions, reference, counts, room, flag):
    """Copy the positions the list was built at; ``flag[0] = 1`` if a row overflowed."""
    i = cuda.grid(1)
    if i < positions.shape[0]:
        for a in range(3):
            reference[i, a] = positions[i, a]
        if counts[i] > room:
            flag[0] = 1


# ---------------------------------------------------------------- pair forces
@functools.cache
def pair_kernel(pair, real):
    """The force kernel of one pair potential: ``pair(r2, k, table, mode, data)`` is the
    frame's function (``potentials.device_terms.pair_function``), ``real`` the type r^2 is
    rounded to before it (float32 in mixed precision; the forces and sums stay double).

    One thread per atom over the full list: row i's force, half of each pair's energy and
    virial to atom i; ``accumulate`` adds to what an earlier potential's kernel wrote. The
    atoms' types are read from the positions' fourth column. Compiled once per process
    for each ``(pair, real)`` (the same term at another size or in another run reuses it).
    """
    device_pair = device_function(pair)

    @cuda.jit
    def kernel(
        positions,
        n_types,
        neighbors,
        counts,
        lengths,
        inverse,
        tilt,
        table,
        mode,
        data,
        accumulate,
        forces,
        observables,
    ):
        i = cuda.grid(1)
        if i >= positions.shape[0]:
            return
        xi = positions[i, 0]
        yi = positions[i, 1]
        zi = positions[i, 2]
        row = int(positions[i, 3]) * n_types
        fx = fy = fz = 0.0
        u_sum = wxx = wyy = wzz = wyz = wxz = wxy = 0.0
        for k in range(counts[i]):
            j = neighbors[k, i]
            dx, dy, dz = _min_image(
                xi - positions[j, 0],
                yi - positions[j, 1],
                zi - positions[j, 2],
                lengths,
                inverse,
                tilt,
            )
            r2 = real(dx * dx + dy * dy + dz * dz)
            u, fr = device_pair(r2, row + int(positions[j, 3]), table, mode, data)
            ex = fr * dx
            ey = fr * dy
            ez = fr * dz
            fx += ex
            fy += ey
            fz += ez
            u_sum += u
            wxx += ex * dx
            wyy += ey * dy
            wzz += ez * dz
            wyz += ez * dy
            wxz += ez * dx
            wxy += ey * dx
        if accumulate:
            forces[i, 0] += fx
            forces[i, 1] += fy
            forces[i, 2] += fz
            observables[i, 0] += 0.5 * u_sum
            observables[i, 1] += 0.5 * wxx
            observables[i, 2] += 0.5 * wyy
            observables[i, 3] += 0.5 * wzz
            observables[i, 4] += 0.5 * wyz
            observables[i, 5] += 0.5 * wxz
            observables[i, 6] += 0.5 * wxy
        else:
            forces[i, 0] = fx
            forces[i, 1] = fy
            forces[i, 2] = fz
            observables[i, 0] = 0.5 * u_sum
            observables[i, 1] = 0.5 * wxx
            observables[i, 2] = 0.5 * wyy
            observables[i, 3] = 0.5 * wzz
            observables[i, 4] = 0.5 * wyz
            observables[i, 5] = 0.5 * wxz
            observables[i, 6] = 0.5 * wxy

    return kernel


# ---------------------------------------------------------------- bonds and angles
@functools.cache
def bond_kernel(bond, params):
    """The force kernel of one bond potential: ``bond(r2, p) -> (u, u'(r) / r)`` and
    ``params(table, t)`` are the bonded frame's adapters of its term
    (``potentials.device_terms.bonded_function``). One thread per atom over the atom's own
    bonds (``starts``/``entries``: 2 b + the atom's end), adding its force, half of each
    bond's energy and virial to its rows: each bond is evaluated by both its atoms, and
    no thread writes another's row."""
    device_bond = device_function(bond)
    device_params = device_function(params)

    @cuda.jit
    def kernel(
        positions,
        lengths,
        inverse,
        tilt,
        bonds,
        bond_types,
        table,
        starts,
        entries,
        forces,
        observables,
    ):
        i = cuda.grid(1)
        if i >= positions.shape[0]:
            return
        fx = fy = fz = 0.0
        u_sum = wxx = wyy = wzz = wyz = wxz = wxy = 0.0
        for e in range(starts[i], starts[i + 1]):
            b = entries[e] // 2
            a0 = bonds[b, 0]
            a1 = bonds[b, 1]
            dx, dy, dz = _min_image(
                positions[a0, 0] - positions[a1, 0],
                positions[a0, 1] - positions[a1, 1],
                positions[a0, 2] - positions[a1, 2],
                lengths,
                inverse,
                tilt,
            )
            u, g = device_bond(dx * dx + dy * dy + dz * dz, device_params(table, bond_types[b]))
            ex = -g * dx  # the force on the bond's first atom
            ey = -g * dy
            ez = -g * dz
            if entries[e] % 2 == 0:
                fx += ex
                fy += ey
                fz += ez
            else:
                fx -= ex
                fy -= ey
                fz -= ez
            u_sum += u
            wxx += ex * dx
            wyy += ey * dy
            wzz += ez * dz
            wyz += ez * dy
            wxz += ez * dx
            wxy += ey * dx
        _add_row(forces, observables, i, fx, fy, fz, 0.5, u_sum, wxx, wyy, wzz, wyz, wxz, wxy)

    return kernel


@functools.cache
def angle_kernel(angle, params):
    """The force kernel of one angle potential (``angle(c, p) -> (u, du/dc)``, c = cos
    theta), as :func:`bond_kernel`: each atom evaluates its own angles (``entries``: 3 a +
    its place, 1 the vertex) and adds its force and a third of each angle's energy and
    virial (LAMMPS's split, as the CPU's per-atom values)."""
    device_angle = device_function(angle)
    device_params = device_function(params)

    @cuda.jit
    def kernel(
        positions,
        lengths,
        inverse,
        tilt,
        angles,
        angle_types,
        table,
        starts,
        entries,
        forces,
        observables,
    ):
        i = cuda.grid(1)
        if i >= positions.shape[0]:
            return
        fx = fy = fz = 0.0
        u_sum = wxx = wyy = wzz = wyz = wxz = wxy = 0.0
        for e in range(starts[i], starts[i + 1]):
            a = entries[e] // 3
            place = entries[e] % 3
            p0 = angles[a, 0]
            p1 = angles[a, 1]
            p2 = angles[a, 2]
            ax, ay, az = _min_image(
                positions[p0, 0] - positions[p1, 0],
                positions[p0, 1] - positions[p1, 1],
                positions[p0, 2] - positions[p1, 2],
                lengths,
                inverse,
                tilt,
            )
            bx, by, bz = _min_image(
                positions[p2, 0] - positions[p1, 0],
                positions[p2, 1] - positions[p1, 1],
                positions[p2, 2] - positions[p1, 2],
                lengths,
                inverse,
                tilt,
            )
            ra2 = ax * ax + ay * ay + az * az
            rb2 = bx * bx + by * by + bz * bz
            if not (ra2 > 0.0 and rb2 > 0.0):
                continue  # no angle (the CPU loop leaves it out too, and reports it)
            rab = math.sqrt(ra2) * math.sqrt(rb2)
            c = (ax * bx + ay * by + az * bz) / rab
            c = min(max(c, -1.0), 1.0)
            u, d1 = device_angle(c, device_params(table, angle_types[a]))
            a11 = d1 * c / ra2
            a12 = -d1 / rab
            a22 = d1 * c / rb2
            fix = a11 * ax + a12 * bx
            fiy = a11 * ay + a12 * by
            fiz = a11 * az + a12 * bz
            fkx = a22 * bx + a12 * ax
            fky = a22 * by + a12 * ay
            fkz = a22 * bz + a12 * az
            if place == 0:
                fx += fix
                fy += fiy
                fz += fiz
            elif place == 2:
                fx += fkx
                fy += fky
                fz += fkz
            else:
                fx -= fix + fkx
                fy -= fiy + fky
                fz -= fiz + fkz
            u_sum += u
            wxx += ax * fix + bx * fkx
            wyy += ay * fiy + by * fky
            wzz += az * fiz + bz * fkz
            wyz += ay * fiz + by * fkz
            wxz += ax * fiz + bx * fkz
            wxy += ax * fiy + bx * fky
        _add_row(forces, observables, i, fx, fy, fz, 1.0 / 3.0, u_sum, wxx, wyy, wzz, wyz, wxz, wxy)

    return kernel


@cuda.jit(device=True, inline="always")
def _add_row(forces, observables, i, fx, fy, fz, share, u, wxx, wyy, wzz, wyz, wxz, wxy):
    """Add a force to row i and ``share`` of an energy and a virial to its observables."""
    forces[i, 0] += fx
    forces[i, 1] += fy
    forces[i, 2] += fz
    observables[i, 0] += share * u
    observables[i, 1] += share * wxx
    observables[i, 2] += share * wyy
    observables[i, 3] += share * wzz
    observables[i, 4] += share * wyz
    observables[i, 5] += share * wxz
    observables[i, 6] += share * wxy


# ---------------------------------------------------------------- integrator passes
# A step is a few launches (docs/guide/gpu.md counts them per integrator): each pass below
# does what the CPU path does in two or three loops in a row (the kick, the drift, the
# list's displacement check, a thermostat's sum), as one thread per atom, or, where a sum
# over the atoms follows, a grid-stride loop of blocks of up to SUM_THREADS that ends in
# :func:`_finish` (the sum in a fixed order, in the same launch).
@cuda.jit
def _kick_drift_check(
    positions,
    velocities,
    forces,
    inverse_masses,
    alpha,
    kick_dt,
    drift_dt,
    reference,
    limit2,
    flag,
    check,
):
    """v = alpha v + kick_dt f/m, x += drift_dt v, then (``check``) ``flag[0] = 1`` if the
    atom moved farther than sqrt(limit2) since the list's build: Bussi's rescaling
    (alpha; 1 for the other integrators, which leaves v as it is), the CPU's
    ``integrators._kernels.kick_drift`` and the list's look, in one pass."""
    i = cuda.grid(1)
    if i < velocities.shape[0]:
        scale = kick_dt * inverse_masses[i]
        for a in range(3):
            v = alpha * velocities[i, a] + scale * forces[i, a]
            velocities[i, a] = v
            positions[i, a] += drift_dt * v
        if check:
            _check_moved(positions, reference, limit2, flag, i)


@cuda.jit
def _drift_check(positions, velocities, dt, reference, limit2, flag):
    """x += dt v (``integrators._kernels._drift``'s twin), then the list's look."""
    i = cuda.grid(1)
    if i < positions.shape[0]:
        for a in range(3):
            positions[i, a] += dt * velocities[i, a]
        _check_moved(positions, reference, limit2, flag, i)


@cuda.jit
def _kick(velocities, forces, inverse_masses, kick_dt):
    """v += kick_dt f/m (``integrators._kernels.kick``'s twin)."""
    i = cuda.grid(1)
    if i < velocities.shape[0]:
        scale = kick_dt * inverse_masses[i]
        for a in range(3):
            velocities[i, a] += scale * forces[i, a]


@cuda.jit
def _synchronise(velocities, half_velocities, forces, inverse_masses, half_dt):
    """v = v_half + half_dt f/m (the leapfrog's on-step velocities)."""
    i = cuda.grid(1)
    if i < velocities.shape[0]:
        scale = half_dt * inverse_masses[i]
        for a in range(3):
            velocities[i, a] = half_velocities[i, a] + scale * forces[i, a]


@cuda.jit
def _kick_scale_kinetic(
    velocities, forces, inverse_masses, masses, kick_dt, alpha, partial, counter, out
):
    """v = alpha (v + kick_dt f/m), and the kinetic energy after it into ``out[0]``: the
    end of a Bussi step (the kick with alpha 1; the rescaling with kick_dt 0 and the
    forces' array unread), its sum for the next rescaling in the same launch."""
    t = cuda.threadIdx.x
    shared = cuda.shared.array((SUM_THREADS, 1), dtype=numba.float64)
    last = cuda.shared.array(1, dtype=numba.int32)
    shared[t, 0] = 0.0
    start = cuda.blockIdx.x * cuda.blockDim.x + t
    for i in range(start, velocities.shape[0], cuda.blockDim.x * cuda.gridDim.x):
        scale = kick_dt * inverse_masses[i]
        v2 = 0.0
        for a in range(3):
            v = velocities[i, a]
            if kick_dt != 0.0:
                v += scale * forces[i, a]
            v *= alpha
            velocities[i, a] = v
            v2 += v * v
        shared[t, 0] += 0.5 * masses[i] * v2
    _finish(shared, t, 1, partial, counter, last, out, 0)


def noise_kernel(gaussians):
    """The Langevin noise and the sums before BAOAB's O step, in one launch:
    ``gaussians(k0, k1, step, atom)`` is the CPU path's function of one atom's three
    normal numbers (``integrators.langevin.noise_of_atom``), so atom ``ids[i]`` gets the
    same noise at a step on either device, scaled by ``sigmas[i]``; ``sums[0]`` the kinetic
    energy, ``sums[1:4]`` the noise's momentum, ``sums[4]`` the mass (:func:`_finish`)."""
    return _noise_kernel(gaussians)


@functools.cache
def _noise_kernel(gaussians):
    device_gaussians = device_function(gaussians)

    @cuda.jit
    def kernel(k0, k1, step, ids, sigmas, noise, velocities, masses, partial, counter, sums):
        t = cuda.threadIdx.x
        shared = cuda.shared.array((SUM_THREADS, 5), dtype=numba.float64)
        last = cuda.shared.array(1, dtype=numba.int32)
        for c in range(5):
            shared[t, c] = 0.0
        start = cuda.blockIdx.x * cuda.blockDim.x + t
        for i in range(start, noise.shape[0], cuda.blockDim.x * cuda.gridDim.x):
            g0, g1, g2 = device_gaussians(k0, k1, step, numba.uint64(ids[i]))
            s = sigmas[i]
            noise[i, 0] = g0 * s
            noise[i, 1] = g1 * s
            noise[i, 2] = g2 * s
            m = masses[i]
            v2 = velocities[i, 0] ** 2 + velocities[i, 1] ** 2 + velocities[i, 2] ** 2
            shared[t, 0] += 0.5 * m * v2
            for a in range(3):
                shared[t, 1 + a] += m * noise[i, a]
            shared[t, 4] += m
        _finish(shared, t, 5, partial, counter, last, sums, 0)

    return kernel


@cuda.jit
def _relax_bath(velocities, noise, masses, c, fix_com, partial, counter, sums):
    """v = c v + noise - (the noise's centre-of-mass velocity, ``sums[1:4] / sums[4]``,
    where ``fix_com``): the O step of BAOAB (``integrators.langevin._relax``'s twin); then
    the kinetic energy after it into ``sums[5]`` and the heat bath's energy ``sums[6]``
    less what the kinetic energy gained, in the same launch."""
    t = cuda.threadIdx.x
    shared = cuda.shared.array((SUM_THREADS, 1), dtype=numba.float64)
    last = cuda.shared.array(1, dtype=numba.int32)
    shared[t, 0] = 0.0
    start = cuda.blockIdx.x * cuda.blockDim.x + t
    for i in range(start, velocities.shape[0], cuda.blockDim.x * cuda.gridDim.x):
        v2 = 0.0
        for a in range(3):
            drift = sums[1 + a] / sums[4] if fix_com else 0.0
            v = c * velocities[i, a] + noise[i, a] - drift
            velocities[i, a] = v
            v2 += v * v
        shared[t, 0] += 0.5 * masses[i] * v2
    _finish(shared, t, 1, partial, counter, last, sums, 5)
    if t == 0 and last[0]:
        sums[6] -= sums[5] - sums[0]


# ---------------------------------------------------------------- sums
@cuda.jit
def _sum_observables(observables, velocities, masses, partial, counter, totals):
    """Each observable column summed into ``totals``, the kinetic energy (column 7)
    computed here: each block's threads take a strided share, then a tree,
    and :func:`_finish` adds the blocks' rows in order: the same order on every run, in
    one launch."""
    t = cuda.threadIdx.x
    shared = cuda.shared.array((SUM_THREADS, N_OBSERVABLES), dtype=numba.float64)
    last = cuda.shared.array(1, dtype=numba.int32)
    for c in range(N_OBSERVABLES):
        shared[t, c] = 0.0
    start = cuda.blockIdx.x * cuda.blockDim.x + t
    for i in range(start, observables.shape[0], cuda.blockDim.x * cuda.gridDim.x):
        for c in range(N_OBSERVABLES - 1):
            shared[t, c] += observables[i, c]
        v2 = velocities[i, 0] ** 2 + velocities[i, 1] ** 2 + velocities[i, 2] ** 2
        shared[t, N_OBSERVABLES - 1] += 0.5 * masses[i] * v2
    _finish(shared, t, N_OBSERVABLES, partial, counter, last, totals, 0)


@cuda.jit(device=True, inline="always")
def _tree(shared, t, n_columns):
    """Sum the block's rows of ``shared`` (one a thread: a power of two, at most
    SUM_THREADS) into row 0, pairwise."""
    cuda.syncthreads()
    width = cuda.blockDim.x // 2
    while width > 0:
        if t < width:
            for c in range(n_columns):
                shared[t, c] += shared[t + width, c]
        cuda.syncthreads()
        width //= 2


@cuda.jit(device=True, inline="always")
def _finish(shared, t, n_columns, partial, counter, last, out, offset):
    """The end of a sum over the grid, with no second launch: the block's rows of
    ``shared`` into row 0 (:func:`_tree`) and into ``partial[block]``; the block that
    finishes last (``counter``, an atomic ticket after a memory fence, as CUDA's
    threadFenceReduction sample) adds the blocks' rows in block order into
    ``out[offset:offset + n_columns]``, sets ``last[0]`` and resets the ticket. The order
    of every addition is fixed: the same sums on every run."""
    _tree(shared, t, n_columns)
    if cuda.gridDim.x == 1:  # one block: its row 0 is the sum (as the pass below gives it)
        if t == 0:
            for c in range(n_columns):
                out[offset + c] = shared[0, c]
            last[0] = 1
        cuda.syncthreads()
        return
    if t == 0:
        for c in range(n_columns):
            partial[cuda.blockIdx.x, c] = shared[0, c]
        cuda.threadfence()
        ticket = cuda.atomic.add(counter, 0, 1)
        last[0] = 1 if ticket == cuda.gridDim.x - 1 else 0
    cuda.syncthreads()
    if last[0]:
        for c in range(n_columns):
            shared[t, c] = 0.0
        for b in range(t, cuda.gridDim.x, cuda.blockDim.x):
            for c in range(n_columns):
                shared[t, c] += partial[b, c]
        _tree(shared, t, n_columns)
        if t == 0:
            for c in range(n_columns):
                out[offset + c] = shared[0, c]
            counter[0] = 0


def curve_ranks(n_cells) -> np.ndarray:
    """Each cell's place (row-major cell number -> rank) along a Morton (Z-order) curve
    through an ``n_cells`` grid: the cells sorted by their coordinates' interleaved bits,
    so that cells near along the order are near in space in all three directions (row-major
    order keeps only the last axis's neighbours near). A grid that is not a power of two
    along an axis skips the codes outside it. Atoms sorted by this rank of their cell lie
    near their neighbours in memory (as HOOMD-blue's sort along a Hilbert curve)."""
    nx, ny, nz = (int(c) for c in n_cells)
    x, y, z = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    codes = np.zeros(nx * ny * nz, np.int64)
    bits = max(int(c - 1).bit_length() for c in (nx, ny, nz))
    for b in range(bits):
        for place, axis in enumerate((x, y, z)):
            codes |= ((axis.reshape(-1) >> b) & 1) << (3 * b + 2 - place)
    order = np.argsort(codes, kind="stable")
    ranks = np.empty(order.shape[0], np.int32)
    ranks[order] = np.arange(order.shape[0], dtype=np.int32)
    return ranks


__all__ = [
    "BLOCK",
    "N_OBSERVABLES",
    "SCAN_THREADS",
    "SUM_BLOCKS",
    "SUM_THREADS",
    "angle_kernel",
    "bond_kernel",
    "curve_ranks",
    "device_function",
    "launch",
    "noise_kernel",
    "pair_kernel",
    "scan_threads",
    "sum_threads",
]
