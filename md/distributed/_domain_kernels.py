"""The kernels of a decomposed run: bricks and fractional coordinates, the owned atoms'
layout, the ghost search's faces and rows, migration's refills, the look-ahead and the
bonded items' nearest copies (numba; arrays and scalars only).

They are shared by :mod:`md.distributed.halo`, :mod:`md.distributed.migration` and
:mod:`md.distributed.forcefield`, so they sit here rather than at the foot of one of
them; :mod:`md.distributed.grid` holds the grid they work in.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from md.box import separation


@njit(cache=True, inline="always", error_model="numpy")
def _cell_fractions(positions, i, inverse, tilt, pbc):
    """Atom i's coordinates along the cell vectors, (sx, sy, sz); 0.5 along open axes.
    ``inverse`` holds 1 / box (:func:`_inverse_lengths`): every kernel that places atoms
    takes its fractions from here, so that they agree on the bricks to the last bit."""
    sz = positions[i, 2] * inverse[2] if pbc[2] else 0.5
    sy = (positions[i, 1] - sz * tilt[2]) * inverse[1] if pbc[1] else 0.5
    x = positions[i, 0] - sy * tilt[0] - sz * tilt[1]
    sx = x * inverse[0] if pbc[0] else 0.5
    return sx, sy, sz


@njit(cache=True, inline="always", error_model="numpy")
def _inverse_lengths(box):
    """1 / box, what :func:`_cell_fractions` multiplies by: a pass over 10^6 atoms dividing
    by the lengths took 3.9 ms on a Zen 4 EPYC (bound by the divider), multiplying 1.7."""
    return np.array([1.0 / box[0], 1.0 / box[1], 1.0 / box[2]])


@njit(cache=True, error_model="numpy")
def fractional_coordinates(positions, box, tilt, pbc, out):
    """Write each position's coordinates along the cell vectors (``s`` with ``r = s @ cell``)
    into ``out`` (N, 3); 0.5 along open axes, which are never cut. ``tilt`` is zero where
    an axis it couples is open (``md.box.periodic_tilt``)."""
    inverse = _inverse_lengths(box)
    for i in range(positions.shape[0]):
        sx, sy, sz = _cell_fractions(positions, i, inverse, tilt, pbc)
        out[i, 0] = sx
        out[i, 1] = sy
        out[i, 2] = sz


@njit(cache=True, inline="always", error_model="numpy")
def _slab(s, p, planes):
    """The slab of ``p`` holding the fraction ``s`` in [0, 1): the even grid's guess,
    then moved to the slab whose planes (a row of :meth:`Grid.cut_table`) enclose it."""
    c = min(max(int(s * p), 0), p - 1)  # s in [0, 1): truncation is the floor
    while c > 0 and s < planes[c]:
        c -= 1
    while c < p - 1 and s >= planes[c + 1]:
        c += 1
    return c


@njit(cache=True, error_model="numpy")
def brick_of(fractions, shape, cuts, out):
    """Write the grid coordinates of the brick holding each wrapped fractional position
    (rows of ``fractions``, taken modulo 1) into ``out`` (N, 3), int64; ``cuts`` is the
    grid's :meth:`Grid.cut_table`."""
    for i in range(fractions.shape[0]):
        for a in range(3):
            s = fractions[i, a] - np.floor(fractions[i, a])
            out[i, a] = _slab(s, shape[a], cuts[a])


@njit(cache=True, error_model="numpy")
def home_layout(positions, box, tilt, pbc, cell, center, bounds, widths, home, out, rows):
    """The owned atoms of a build at the periodic images nearest the brick centred on
    ``center``, in one pass: each atom's fractional coordinates there (``home``, N x 3;
    0.5 along open axes, which are never cut, as :func:`fractional_coordinates`), its
    position there (``out``: positions - n @ cell, ``cell``'s rows a, b, c, a plain copy
    where n = 0) and, for the atoms whose image n is not 0, their indices and images
    (``rows``, scratch of N x 3 int64). ``bounds`` are the brick's (2, 3) lower and upper
    fractional corners, ``widths`` the cell's perpendicular widths.

    Returns (imaged, images, strayed): the atoms with an image of their own
    (increasing), their images (int64 rows) and how far the farthest atom lies
    outside the brick [length]. Where ``rows`` has a fourth column the atoms' indices
    go there (else into scratch of N int64 made here)."""
    strayed = 0.0
    count = 0
    kept = rows.shape[1] > 3
    imaged = np.empty(0 if kept else positions.shape[0], dtype=np.int64)
    inverse = _inverse_lengths(box)
    for i in range(positions.shape[0]):
        sx, sy, sz = _cell_fractions(positions, i, inverse, tilt, pbc)
        kx = np.floor(sx - center[0] + 0.5) if pbc[0] else 0.0
        ky = np.floor(sy - center[1] + 0.5) if pbc[1] else 0.0
        kz = np.floor(sz - center[2] + 0.5) if pbc[2] else 0.0
        hx, hy, hz = sx - kx, sy - ky, sz - kz
        home[i, 0], home[i, 1], home[i, 2] = hx, hy, hz
        if pbc[0]:
            strayed = max(strayed, max(bounds[0, 0] - hx, hx - bounds[1, 0], 0.0) * widths[0])
        if pbc[1]:
            strayed = max(strayed, max(bounds[0, 1] - hy, hy - bounds[1, 1], 0.0) * widths[1])
        if pbc[2]:
            strayed = max(strayed, max(bounds[0, 2] - hz, hz - bounds[1, 2], 0.0) * widths[2])
        if kx != 0.0 or ky != 0.0 or kz != 0.0:
            for a in range(3):
                out[i, a] = positions[i, a] - (kx * cell[0, a] + ky * cell[1, a] + kz * cell[2, a])
            rows[count, 0], rows[count, 1], rows[count, 2] = int(kx), int(ky), int(kz)
            if kept:
                rows[count, 3] = i
            else:
                imaged[count] = i
            count += 1
        else:
            out[i, 0], out[i, 1], out[i, 2] = positions[i, 0], positions[i, 1], positions[i, 2]
    if kept:
        return rows[:count, 3].copy(), rows[:count, :3].copy(), strayed
    return imaged[:count].copy(), rows[:count].copy(), strayed


@njit(cache=True, inline="always", error_model="numpy")
def _doubled(values):
    """A copy of ``values`` with twice the room."""
    grown = np.empty(2 * values.shape[0], dtype=values.dtype)
    grown[: values.shape[0]] = values
    return grown


@njit(cache=True, error_model="numpy")
def leaving_along(positions, box, tilt, pbc, shape, cuts, axis, coordinate):
    """The atoms whose bricks lie one step up and one step down ``axis`` from the brick at
    ``coordinate`` along it (index arrays, increasing), and how many lie further away: the
    split of one migration sweep, in one pass (bricks as :func:`brick_of` of
    :func:`fractional_coordinates` finds them). With two bricks along the axis, "up"
    takes both neighbours."""
    n = positions.shape[0]
    p = shape[axis]
    # (room for an eighth of the atoms, doubled when full: a migration moves few, and
    # scratch of n rows each was most of its memory traffic)
    up = np.empty(n // 8 + 16, dtype=np.int64)
    down = np.empty(n // 8 + 16, dtype=np.int64)
    n_up = 0
    n_down = 0
    lost = 0
    inverse = _inverse_lengths(box)
    own_lower, own_upper = cuts[axis][coordinate], cuts[axis][coordinate + 1]
    for i in range(n):
        # only the fractions the axis needs (z's for all, y's for x and y), as
        # _cell_fractions computes them
        sz = positions[i, 2] * inverse[2] if pbc[2] else 0.5
        f = sz
        if axis < 2:
            sy = (positions[i, 1] - sz * tilt[2]) * inverse[1] if pbc[1] else 0.5
            f = sy
            if axis == 0:
                x = positions[i, 0] - sy * tilt[0] - sz * tilt[1]
                f = x * inverse[0] if pbc[0] else 0.5
        f = f - np.floor(f)
        if own_lower <= f < own_upper:
            continue  # most atoms: still in this slab, as _slab would find
        c = _slab(f, p, cuts[axis])
        if c == coordinate:
            continue
        delta = c - coordinate if c > coordinate else c - coordinate + p
        if delta == 1:
            if n_up == up.shape[0]:
                up = _doubled(up)
            up[n_up] = i
            n_up += 1
        elif delta == p - 1:
            if n_down == down.shape[0]:
                down = _doubled(down)
            down[n_down] = i
            n_down += 1
        else:
            lost += 1
    return up[:n_up].copy(), down[:n_down].copy(), lost


@njit(cache=True, error_model="numpy")
def refill_plan(leaving, n, m):
    """Where a migration sweep puts the rows of a rank's arrays, in place: ``leaving`` (the
    rows that leave, increasing) of ``n`` rows, ``m`` rows arriving. Returns (sources,
    targets, arrivals): row ``sources[k]`` moves to row ``targets[k]``, arriving row j
    goes to ``arrivals[j]``; afterwards the first ``n - len(leaving) + m`` rows hold every
    staying and arriving atom. Arrivals fill the holes the leavers left (the lowest
    first), then go past the end; holes left over are filled by the staying rows past the
    new end, lowest first. Only the rows that move are touched: O(moved), not O(n)."""
    g = leaving.shape[0]
    size = n - g + m
    arrivals = np.empty(m, dtype=np.int64)
    filled = min(m, g)
    for j in range(filled):
        arrivals[j] = leaving[j]
    for j in range(filled, m):
        arrivals[j] = n + j - filled
    holes = 0  # holes below the new end, among leaving[filled:]
    for k in range(filled, g):
        if leaving[k] < size:
            holes += 1
    sources = np.empty(holes, dtype=np.int64)
    targets = np.empty(holes, dtype=np.int64)
    tail = size  # the staying rows at or past the new end, in increasing order
    skip = filled
    while skip < g and leaving[skip] < size:
        skip += 1
    for k in range(holes):
        while skip < g and leaving[skip] == tail:
            skip += 1
            tail += 1
        targets[k] = leaving[filled + k]
        sources[k] = tail
        tail += 1
    return sources, targets, arrivals


@njit(cache=True)
def same_start(a, b):
    """Whether arrays ``a`` and ``b`` begin at the same address (numpy's ``ctypes.data``
    makes an object a call: 1.6 us each, two per array a migration)."""
    return a.ctypes.data == b.ctypes.data


@njit(cache=True, error_model="numpy")
def pack_leaving(rows, positions, velocities, masses, types, ids, carried, out):
    """A migration's message: ``out[k]`` = atom ``rows[k]``'s position (3), velocity (3),
    mass, type, id, then its row of each of ``carried`` (2-D float64 arrays, one row an
    atom), the integers as floats (exact below 2^53): the layout
    :func:`md.distributed.migration.migrate` sends."""
    for k in range(rows.shape[0]):
        i = rows[k]
        for a in range(3):
            out[k, a] = positions[i, a]
            out[k, 3 + a] = velocities[i, a]
        out[k, 6] = masses[i]
        out[k, 7] = types[i]
        out[k, 8] = ids[i]
        column = 9
        for values in carried:
            for a in range(values.shape[1]):
                out[k, column] = values[i, a]
                column += 1


@njit(cache=True, inline="always", error_model="numpy")
def _arrive(rows, r, t, positions, velocities, masses, types, ids, carried):
    """Message row r of :func:`pack_leaving`'s layout into row t of the arrays."""
    for a in range(3):
        positions[t, a] = rows[r, a]
        velocities[t, a] = rows[r, 3 + a]
    masses[t] = rows[r, 6]
    types[t] = np.int32(rows[r, 7])
    ids[t] = np.int64(rows[r, 8])
    column = 9
    for values in carried:
        for a in range(values.shape[1]):
            values[t, a] = rows[r, column]
            column += 1


@njit(cache=True, error_model="numpy")
def unpack_arriving(
    ups, downs, n, lower, upper, positions, velocities, masses, types, ids, carried
):
    """The receiving end of a migration sweep, in place: the atoms ``ups`` and ``downs``
    (increasing each) of the first ``n`` rows leave and the rows of :func:`pack_leaving`'s
    messages ``lower`` then ``upper`` arrive, as :func:`refill_plan` places them, in every
    array (the state's, then each of ``carried``: 2-D, the same rows), which have room
    for them. Returns the rows held after it."""
    if downs.shape[0] == 0:  # (two bricks along the axis: every leaver goes up)
        leaving = ups
    elif ups.shape[0] == 0:
        leaving = downs
    else:
        leaving = np.sort(np.concatenate((ups, downs)))
    m = lower.shape[0] + upper.shape[0]
    sources, targets, arrivals = refill_plan(leaving, n, m)
    for k in range(sources.shape[0]):
        t, f = targets[k], sources[k]
        for a in range(3):
            positions[t, a] = positions[f, a]
            velocities[t, a] = velocities[f, a]
        masses[t] = masses[f]
        types[t] = types[f]
        ids[t] = ids[f]
        for values in carried:
            for a in range(values.shape[1]):
                values[t, a] = values[f, a]
    for j in range(lower.shape[0]):
        _arrive(lower, j, arrivals[j], positions, velocities, masses, types, ids, carried)
    for j in range(upper.shape[0]):
        t = arrivals[lower.shape[0] + j]
        _arrive(upper, j, t, positions, velocities, masses, types, ids, carried)
    return n - leaving.shape[0] + m


@njit(cache=True, error_model="numpy")
def refill_rows(values, sources, targets, incoming, arrivals):
    """Apply :func:`refill_plan` to a 2-D array in place: values[targets[k]] =
    values[sources[k]], then values[arrivals[j]] = incoming[j]."""
    for k in range(sources.shape[0]):
        for a in range(values.shape[1]):
            values[targets[k], a] = values[sources[k], a]
    for j in range(arrivals.shape[0]):
        for a in range(values.shape[1]):
            values[arrivals[j], a] = incoming[j, a]


#: Columns of a swap's row in a build's swap table (the compiled halo's ``table``, see
#: :mod:`md.distributed._mpi_kernels`): its send list's rows in the index (``START`` to
#: ``END``), its ghost rows (from ``OFFSET``, ``COUNT`` of them), the ranks it sends to and
#: receives from, its tag, and its ghosts' first row in the forces sent back (``BACK``).
START, END, OFFSET, COUNT, DEST, SOURCE, TAG, BACK = range(8)
#: Columns of a sweep's row in the sweep table: its axis, whether it sends to this rank
#: itself, and its swaps' rows in the swap table (``FIRST`` to ``LAST``).
AXIS, TO_SELF, FIRST, LAST = range(4)


@njit(cache=True, inline="always", error_model="numpy")
def _swap_entry(table, shifts, j, first, last, dest, source, move):
    """Swap j's send list (index rows ``first`` to ``last``), peers, tag and shift."""
    table[j, START] = first
    table[j, END] = last
    table[j, DEST] = dest
    table[j, SOURCE] = source
    table[j, TAG] = j
    shifts[j] = move


@njit(cache=True, inline="always", error_model="numpy")
def _append_swap(rows, count, n_owned, positions, ghost_fractions, ids, types, table, j, back):
    """Swap j's arrived ``rows`` as local atoms ``count`` onwards, its ghost rows in the
    table; returns the count after them."""
    for k in range(rows.shape[0]):
        i = count + k
        for a in range(3):
            positions[i, a] = rows[k, a]
            ghost_fractions[i - n_owned, a] = rows[k, 3 + a]
        ids[i] = np.int64(rows[k, 6])
        types[i] = np.int32(rows[k, 7])
    table[j, OFFSET] = count
    table[j, COUNT] = rows.shape[0]
    table[j, BACK] = back
    return count + rows.shape[0]


@njit(cache=True, error_model="numpy")
def sweep_send(
    positions,
    owned_fractions,
    ghost_fractions,
    ids,
    types,
    n_owned,
    count,
    axis,
    faces,
    moves,
    peers,
    cell,
    index,
    rows,
    table,
    shifts,
    sweeps,
    s,
):
    """Ghost sweep ``s`` (along ``axis``) of a build, in one pass: its two swaps' send lists
    and the rows they send, and their entries in the swap and sweep tables.

    The local atoms before ``count`` (owned first, then the earlier sweeps' ghosts) whose
    fraction along ``axis`` lies below ``faces[0]`` go down (swap ``2 s``), those at or
    above ``faces[1]`` up (swap ``2 s + 1``), each list in local order (the owned atoms'
    fractions in ``owned_fractions``, the ghosts' in ``ghost_fractions``, row
    ``i - n_owned``). Their indices go into ``index`` from the end of the last sweep's
    (``table[2 s - 1, END]``; 0 for the first), the down list then the up list; their
    rows into ``rows``: row 0 holds the down list's length (column 0; the rest 0), then
    the down rows, then the up rows: position (3) shifted by ``moves[k]`` cell vectors
    along ``axis``, fractional position (3, the same shift along ``axis``), id and type
    (the integers as floats, exact below 2^53). ``peers`` are (the
    rank below, the rank above, whether they are this rank); the down swap sends to the
    rank below and receives from the one above, the up swap the other way, tags ``2 s``
    and ``2 s + 1``. ``OFFSET``, ``COUNT`` and ``BACK`` are :func:`sweep_append`'s.

    Returns (the down list's length, the up list's, whether they fitted): where ``index``
    or ``rows`` is too short for them nothing is written (the caller grows them and calls
    again)."""
    lower, upper = faces
    n_down = 0
    n_up = 0
    for i in range(count):
        f = owned_fractions[i, axis] if i < n_owned else ghost_fractions[i - n_owned, axis]
        if f < lower:
            n_down += 1
        if f >= upper:
            n_up += 1
    j = 2 * s
    start = table[j - 1, END] if s > 0 else 0
    if start + n_down + n_up > index.shape[0] or 1 + n_down + n_up > rows.shape[0]:
        return n_down, n_up, False
    down = start
    up = start + n_down
    for i in range(count):
        f = owned_fractions[i, axis] if i < n_owned else ghost_fractions[i - n_owned, axis]
        if f < lower:
            index[down] = i
            down += 1
        if f >= upper:
            index[up] = i
            up += 1
    for a in range(8):
        rows[0, a] = 0.0
    rows[0, 0] = n_down
    for k in range(n_down + n_up):
        i = index[start + k]
        move = moves[0] if k < n_down else moves[1]
        row = 1 + k
        for a in range(3):
            rows[row, a] = positions[i, a] + move * cell[axis, a]
        if i < n_owned:
            for a in range(3):
                rows[row, 3 + a] = owned_fractions[i, a]
        else:
            for a in range(3):
                rows[row, 3 + a] = ghost_fractions[i - n_owned, a]
        rows[row, 3 + axis] += move
        rows[row, 6] = ids[i]
        rows[row, 7] = types[i]
    down_rank, up_rank, to_self = peers
    _swap_entry(table, shifts, j, start, start + n_down, down_rank, up_rank, moves[0])
    _swap_entry(table, shifts, j + 1, start + n_down, up, up_rank, down_rank, moves[1])
    sweeps[s, AXIS] = axis
    sweeps[s, TO_SELF] = to_self
    sweeps[s, FIRST] = j
    sweeps[s, LAST] = j + 2
    return n_down, n_up, True


@njit(cache=True, error_model="numpy")
def sweep_append(down, up, count, n_owned, positions, ghost_fractions, ids, types, table, s):
    """Sweep ``s``'s arrived rows (:func:`sweep_send`'s rows: ``down``, for its down swap,
    then ``up``) as local atoms ``count`` onwards (ghosts; the arrays hold them), and the
    swaps' ghost rows in the swap table (``OFFSET``, ``COUNT``; ``BACK``: their first row
    among all the swaps' ghosts in order). Returns the local atoms' count after them."""
    j = 2 * s
    back = table[j - 1, BACK] + table[j - 1, COUNT] if s > 0 else 0
    count = _append_swap(
        down, count, n_owned, positions, ghost_fractions, ids, types, table, j, back
    )
    back += down.shape[0]
    count = _append_swap(
        up, count, n_owned, positions, ghost_fractions, ids, types, table, j + 1, back
    )
    return count


@njit(cache=True, error_model="numpy")
def home_positions(positions, listed, images, cell, out):
    """out[i] = positions[i] - n_i @ cell: each atom at the image nearest its brick
    (``cell``: rows a, b, c), where n_i is ``images[k]`` for ``i = listed[k]`` and 0 for
    every atom not listed (most of them: only atoms that crossed a periodic face since
    the positions were last wrapped have an image of their own). One copy and a short
    pass, not a product per atom: the same values (x - 0 is x)."""
    for i in range(positions.shape[0]):
        for a in range(3):
            out[i, a] = positions[i, a]
    shift_rows(positions, listed, images, cell, out)


@njit(cache=True, error_model="numpy")
def shift_rows(positions, listed, images, cell, out):
    """:func:`home_positions` for the listed atoms only (the others already copied)."""
    for k in range(listed.shape[0]):
        i = listed[k]
        n0, n1, n2 = images[k, 0], images[k, 1], images[k, 2]
        for a in range(3):
            out[i, a] = positions[i, a] - (n0 * cell[0, a] + n1 * cell[1, a] + n2 * cell[2, a])


@njit(cache=True, error_model="numpy")
def predicted_positions(positions, velocities, forces, masses, dt, out):
    """out = positions + dt v + dt^2 F / (2 m): where a velocity Verlet step of ``dt`` takes
    each atom; without the dt^2 term when ``forces`` has no rows."""
    half = 0.5 * dt * dt
    with_forces = forces.shape[0] == positions.shape[0]
    for i in range(positions.shape[0]):
        kick = half / masses[i] if with_forces else 0.0
        for a in range(3):
            move = dt * velocities[i, a]
            if with_forces:
                move += kick * forces[i, a]
            out[i, a] = positions[i, a] + move


@njit(cache=True, error_model="numpy")
def pack_rows(values, indices, shift, out):
    """out[k] = values[indices[k]] + shift (one row added to every row)."""
    for k in range(indices.shape[0]):
        i = indices[k]
        for a in range(values.shape[1]):
            out[k, a] = values[i, a] + shift[a]


@njit(cache=True, error_model="numpy")
def add_rows(values, indices, rows):
    """values[indices[k]] += rows[k], in order (``indices`` never repeat within a call)."""
    for k in range(indices.shape[0]):
        i = indices[k]
        for a in range(values.shape[1]):
            values[i, a] += rows[k, a]


@njit(cache=True, error_model="numpy")
def moved_since(positions, reference, mapping, previous, before, copy):
    """Return (largest squared distance of an atom from its build position carried along with
    the cell, ``reference[i] @ mapping``; largest squared move since ``previous``; the
    largest squared distance from the build position an atom may reach in its next move),
    all inf if a position is not finite. With ``copy`` (as many rows as ``positions``,
    else no rows), the positions are copied into it in the same pass (a decomposed run's
    local system takes its owned positions so, with one read of them a step).

    The next move is taken as the last one, s = x - previous, give or take how much the
    last move differed from the one before, (previous - before): |d + s| + 1.5 |s - s'|
    for each atom, d its distance from the build position (with no ``before``, rows 0,
    half its last move instead). A velocity Verlet move changes by dt^2 a from one step
    to the next, so that much of a margin is each atom's own, not the fastest one's.
    """
    since_build = 0.0
    since_previous = 0.0
    coming = 0.0
    finite = True
    known = before.shape[0] == positions.shape[0]
    copying = copy.shape[0] == positions.shape[0]
    for i in range(positions.shape[0]):
        d2 = 0.0
        s2 = 0.0
        c2 = 0.0
        e2 = 0.0
        for a in range(3):
            x = positions[i, a]
            if copying:
                copy[i, a] = x
            mapped = (
                reference[i, 0] * mapping[0, a]
                + reference[i, 1] * mapping[1, a]
                + reference[i, 2] * mapping[2, a]
            )
            d = x - mapped
            s = x - previous[i, a]
            d2 += d * d
            s2 += s * s
            c2 += (d + s) * (d + s)
            if known:
                e = s - (previous[i, a] - before[i, a])
                e2 += e * e
        if not (d2 < np.inf and s2 < np.inf):  # also NaN
            finite = False
        since_build = max(since_build, d2)
        since_previous = max(since_previous, s2)
        margin = 1.5 * np.sqrt(e2) if known else 0.5 * np.sqrt(s2)
        reach = np.sqrt(c2) + margin
        coming = max(coming, reach * reach)
    if not finite:
        return np.inf, np.inf, np.inf
    return since_build, since_previous, coming


@njit(cache=True, error_model="numpy")
def anchored_items(owned_ids, starts, order):
    """The items (bonds, angles) whose anchor atom is owned, and the local index of that
    anchor: ``order[starts[g]:starts[g + 1]]`` are the items of atom id g."""
    total = 0
    for i in range(owned_ids.shape[0]):
        g = owned_ids[i]
        if g + 1 < starts.shape[0]:
            total += starts[g + 1] - starts[g]
    items = np.empty(total, dtype=np.int64)
    anchors = np.empty(total, dtype=np.int64)
    k = 0
    for i in range(owned_ids.shape[0]):
        g = owned_ids[i]
        if g + 1 >= starts.shape[0]:
            continue
        for b in range(starts[g], starts[g + 1]):
            items[k] = order[b]
            anchors[k] = i
            k += 1
    return items, anchors


@njit(cache=True, error_model="numpy")
def nearest_copies(
    anchors, partners, sorted_ids, by_id, positions, lengths, inverse, tilt, found, distances
):
    """For each item k, the local copy of atom id ``partners[k]`` nearest to local atom
    ``anchors[k]`` (-1 and inf if it has none): ``sorted_ids`` are the local atoms' ids in
    increasing order, ``by_id`` the local index of each. Distances are minimum images
    along the local system's periodic axes (``lengths``, ``inverse`` and ``tilt`` as
    :func:`md.box.separation` takes them; zero along open axes)."""
    n = sorted_ids.shape[0]
    for k in range(anchors.shape[0]):
        a = anchors[k]
        g = partners[k]
        j = np.searchsorted(sorted_ids, g)
        best = -1
        best2 = np.inf
        while j < n and sorted_ids[j] == g:
            c = by_id[j]
            dx, dy, dz = separation(positions, c, a, lengths, inverse, tilt)
            d2 = dx * dx + dy * dy + dz * dz
            if d2 < best2:
                best, best2 = c, d2
            j += 1
        found[k] = best
        distances[k] = np.sqrt(best2)


@njit(cache=True, error_model="numpy")
def pack_sweep(positions, index, starts, shifts, axis, cell, offsets, to_self, out):
    """One sweep's ghost positions: for its swap j, the rows ``index[starts[j]:starts[j + 1]]``
    of ``positions`` shifted by ``shifts[j]`` cell vectors along ``axis``, written into
    ``out``'s same rows (messages), or with ``to_self`` into ``positions`` from row
    ``offsets[j]`` on (a single brick along the axis sends to itself). The values of
    :func:`pack_rows` with ``shift = shifts[j] * cell[axis]``."""
    for j in range(starts.shape[0] - 1):
        s0 = shifts[j] * cell[axis, 0]
        s1 = shifts[j] * cell[axis, 1]
        s2 = shifts[j] * cell[axis, 2]
        for k in range(starts[j], starts[j + 1]):
            i = index[k]
            row = offsets[j] + k - starts[j] if to_self else k
            target = positions if to_self else out
            target[row, 0] = positions[i, 0] + s0
            target[row, 1] = positions[i, 1] + s1
            target[row, 2] = positions[i, 2] + s2


@njit(cache=True, error_model="numpy")
def ghost_rows(values, offsets, counts, out):
    """out = the rows ``offsets[j] .. offsets[j] + counts[j]`` of ``values``, j in order (the
    ghosts' forces of a sweep, for their messages back)."""
    row = 0
    for j in range(offsets.shape[0]):
        for k in range(offsets[j], offsets[j] + counts[j]):
            for a in range(values.shape[1]):
                out[row, a] = values[k, a]
            row += 1


@njit(cache=True, error_model="numpy")
def add_sweep(values, index, starts, rows, offsets, from_self):
    """The reverse of a sweep: for its swaps j in reverse order, ``values[index[k]] +=`` the
    row of ``rows`` aligned with k (messages back), or with ``from_self`` the ghost row
    ``offsets[j] + k - starts[j]`` of ``values`` itself; the sums of :func:`add_rows` in
    the order swap after swap."""
    for j in range(starts.shape[0] - 2, -1, -1):
        for k in range(starts[j], starts[j + 1]):
            i = index[k]
            source = values if from_self else rows
            row = offsets[j] + k - starts[j] if from_self else k
            for a in range(values.shape[1]):
                values[i, a] += source[row, a]


@njit(cache=True, error_model="numpy")
def fold_gathered(gathered, n_summed, totals, worst):
    """The one reduction of a force evaluation, from every rank's values (``gathered``, one
    row a rank): ``totals`` = its first ``n_summed`` columns added in rank order (the bits
    of :func:`md.distributed.ranks.in_rank_order`), ``worst`` = the others' largest over
    the ranks (NaN if any is, as numpy's max)."""
    for a in range(n_summed):
        totals[a] = gathered[0, a]
    for r in range(1, gathered.shape[0]):
        for a in range(n_summed):
            totals[a] += gathered[r, a]
    for a in range(n_summed, gathered.shape[1]):
        largest = gathered[0, a]
        for r in range(1, gathered.shape[0]):
            value = gathered[r, a]
            if value != value or value > largest:
                largest = value
        worst[a - n_summed] = largest


__all__ = [
    "add_rows",
    "add_sweep",
    "anchored_items",
    "brick_of",
    "fold_gathered",
    "fractional_coordinates",
    "ghost_rows",
    "home_layout",
    "home_positions",
    "leaving_along",
    "moved_since",
    "pack_leaving",
    "nearest_copies",
    "pack_rows",
    "pack_sweep",
    "predicted_positions",
    "refill_plan",
    "refill_rows",
    "same_start",
    "shift_rows",
    "sweep_append",
    "sweep_send",
    "unpack_arriving",
]
