"""numba helpers shared by the pair and bond kernels (term-free parts of the pair frame)."""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from md._simd import gather_rows4, gather_shifted_rows4, scatter_sub_rows4
from md.parallel import chunk_count

#: Atoms per cluster of the cluster-pair list (md.neighbors._cluster_grid.CLUSTER).
CLUSTER = 4


@njit(cache=True, inline="always")
def _add_half_pair_virial(virials, i, j, fx, fy, fz, dx, dy, dz):
    """Add half of the pair virial d (x) f to atoms i and j of ``virials`` (N, 6).

    d = x_i - x_j and f the force on i; order (xx, yy, zz, yz, xz, xy), the
    order of the total virial.
    """
    w0 = 0.5 * fx * dx
    w1 = 0.5 * fy * dy
    w2 = 0.5 * fz * dz
    w3 = 0.5 * fz * dy
    w4 = 0.5 * fz * dx
    w5 = 0.5 * fy * dx
    virials[i, 0] += w0
    virials[i, 1] += w1
    virials[i, 2] += w2
    virials[i, 3] += w3
    virials[i, 4] += w4
    virials[i, 5] += w5
    virials[j, 0] += w0
    virials[j, 1] += w1
    virials[j, 2] += w2
    virials[j, 3] += w3
    virials[j, 4] += w4
    virials[j, 5] += w5


@njit(cache=True, error_model="numpy")
def _gather_frame(
    chunk, n_chunks, positions, types, order, images, lengths, tilt, frame, frame_types
):
    """Slot positions and types of one chunk's share of the slots (images count cell vectors)."""
    n = positions.shape[0]
    xy, xz, yz = tilt[0], tilt[1], tilt[2]
    sheared = xy != 0.0 or xz != 0.0 or yz != 0.0
    for p in range(chunk * n // n_chunks, (chunk + 1) * n // n_chunks):
        atom = order[p]
        frame[p, 0] = positions[atom, 0] + lengths[0] * images[p, 0]
        frame[p, 1] = positions[atom, 1] + lengths[1] * images[p, 1]
        frame[p, 2] = positions[atom, 2] + lengths[2] * images[p, 2]
        if sheared:
            frame[p, 0] += xy * images[p, 1] + xz * images[p, 2]
            frame[p, 1] += yz * images[p, 2]
        frame_types[p] = types[atom]


@njit(cache=True, error_model="numpy")
def _sum_chunk_forces(chunk, n_chunks, order, buffers, forces):
    """Sum the chunk buffers, in chunk order, into the atoms' forces (one share of the slots)."""
    n = order.shape[0]
    for p in range(chunk * n // n_chunks, (chunk + 1) * n // n_chunks):
        atom = order[p]
        for a in range(3):
            total = buffers[0, p, a]
            for other in range(1, n_chunks):
                total += buffers[other, p, a]
            forces[atom, a] = total


@njit(cache=True, error_model="numpy")
def _longest_row(starts, first, last):
    """Most partners of any of the slots first..last-1 (the size of per-row scratch)."""
    most = 0
    for p in range(first, last):
        most = max(most, starts[p + 1] - starts[p])
    return most


@njit(cache=True, error_model="numpy")
def _gather_partners(frame, shifts, partners, partner_codes, gx, gy, gz):
    """Partner positions with their image shifts, contiguous for a vectorised pair loop.

    Slices from 0 and unsigned partner slots: indices LLVM knows are not
    negative, so no wrap-around code. Shared by every pair term (nothing in it
    depends on the term), so it compiles once. Four partners at a time are loaded
    and transposed in vector registers (``md._simd.gather_shifted_rows4``), the rest
    one by one.
    """
    m = partners.shape[0]
    whole = m - m % 4
    for k in range(0, whole, 4):
        gather_shifted_rows4(frame, partners, shifts, partner_codes, k, gx, gy, gz)
    for k in range(whole, m):
        q = np.uint32(partners[k])
        code = partner_codes[k]
        gx[k] = frame[q, 0] + shifts[code, 0]
        gy[k] = frame[q, 1] + shifts[code, 1]
        gz[k] = frame[q, 2] + shifts[code, 2]


@njit(cache=True, error_model="numpy")
def _gather_unshifted(frame, partners, gx, gy, gz):
    """``_gather_partners`` for a row whose partners all have code 13 (``UNSHIFTED_CODE``
    of ``md.neighbors._cell_kernels``, no image shift):
    their codes and the shift table are not read (LJ's force call -5 % at 32000 atoms).
    Four partners at a time are loaded and transposed in vector registers
    (``md._simd.gather_rows4``), the rest one by one."""
    m = partners.shape[0]
    whole = m - m % 4
    for k in range(0, whole, 4):
        gather_rows4(frame, partners, k, gx, gy, gz)
    for k in range(whole, m):
        q = np.uint32(partners[k])
        gx[k] = frame[q, 0]
        gy[k] = frame[q, 1]
        gz[k] = frame[q, 2]


@njit(cache=True, error_model="numpy")
def _scatter_partners(buffer, partners, sfx, sfy, sfz):
    """``buffer[q] -= (sfx[k], sfy[k], sfz[k])`` for each partner q = ``partners[k]`` of a
    row (distinct slots): four at a time transposed in vector registers
    (``md._simd.scatter_sub_rows4``; the same roundings), the rest one by one."""
    m = partners.shape[0]
    whole = m - m % 4
    for k in range(0, whole, 4):
        scatter_sub_rows4(buffer, partners, k, sfx, sfy, sfz)
    for k in range(whole, m):
        q = np.uint32(partners[k])
        buffer[q, 0] -= sfx[k]
        buffer[q, 1] -= sfy[k]
        buffer[q, 2] -= sfz[k]


@njit(cache=True, error_model="numpy")
def _gather_pair_columns(frame_types, partners, row, table, params):
    """Each partner's type-pair column of ``table`` (every row) into ``params[:, k]``,
    so a pair loop over several atom types reads contiguous parameters, no table."""
    n_rows = table.shape[0]
    for k in range(partners.shape[0]):
        column = row + frame_types[np.uint32(partners[k])]
        for r in range(n_rows):
            params[r, k] = table[r, column]


@njit(cache=True, error_model="numpy")
def _slot_types(types, atom, out):
    """Each slot's atom type (0 for a filler)."""
    for s in range(atom.shape[0]):
        out[s] = types[atom[s]] if atom[s] >= 0 else 0


@njit(cache=True, inline="always", error_model="numpy")
def _slot_base(s):
    """Where slot s's x sits in a cluster-ordered array (12 values per cluster: x0..x3,
    y0..y3, z0..z3); its y and z follow CLUSTER and 2 CLUSTER later."""
    return (s // CLUSTER) * 3 * CLUSTER + s % CLUSTER


#: Fewest slots per thread worth a run of their own in the pass that sums the cluster
#: kernels' chunks into atom order (memory-bound; as the list's displacement check).
_MIN_PASS_SLOTS = 16_000


def cluster_atom_forces(buffers, atom, windows, forces) -> None:
    """:func:`_cluster_atom_forces`, in runs of slots on the threads where there are
    enough of them (the same bits on any number), each run the same work
    (:func:`cluster_sum_runs`)."""
    runs = chunk_count(len(atom), _MIN_PASS_SLOTS)
    if runs == 1:
        _cluster_atom_forces(buffers, atom, windows, forces)
    else:
        first = cluster_sum_runs(windows, len(atom) // CLUSTER, runs)
        _cluster_atom_forces_threaded(buffers, atom, windows, forces, first)


@njit(cache=True, error_model="numpy")
def cluster_sum_runs(windows, n_clusters, runs):
    """Where each of ``runs`` runs of :func:`_cluster_atom_forces_threaded` starts, in
    clusters (runs + 1, the last ``n_clusters``), so that the runs do equal work: a
    cluster costs one unit for its atoms' writes into atom order and one for each
    chunk whose window (``windows``) holds it, read for each value: its own chunk's and
    those of earlier chunks whose rows reach it (the first chunk's window is the whole
    list when its rows reach across the periodic boundary). In two chunks on the
    32000-atom melt runs of equal slot counts took 46 and 71 us (their CPU time on one
    thread: the second chunk's clusters read two buffers); weighted by the reads alone
    62 and 55, so a write costs about a read. The count of windows holding a cluster
    changes only at the windows' ends: the bounds are found segment by segment, with no
    pass over the clusters."""
    chunks = windows.shape[0]
    # the segments between the windows' ends, and each one's cost a cluster (its atoms'
    # writes, and a read for each window holding it)
    edges = np.empty(2 * chunks + 2, np.int64)
    for c in range(chunks):
        edges[2 * c], edges[2 * c + 1] = windows[c, 0], windows[c, 1]
    edges[2 * chunks], edges[2 * chunks + 1] = 0, n_clusters
    edges = np.unique(edges)
    held = np.ones(edges.shape[0] - 1, np.int64)
    total = 0
    for g in range(edges.shape[0] - 1):
        for c in range(chunks):
            if windows[c, 0] <= edges[g] and edges[g] < windows[c, 1]:
                held[g] += 1
        total += held[g] * (edges[g + 1] - edges[g])
    first = np.empty(runs + 1, np.int64)
    first[0], first[runs] = 0, n_clusters
    g, done = 0, 0  # the segment, and the work of the segments before it
    for r in range(1, runs):
        target = r * total // runs
        while g < held.shape[0] and done + held[g] * (edges[g + 1] - edges[g]) <= target:
            done += held[g] * (edges[g + 1] - edges[g])
            g += 1
        if g == held.shape[0]:
            first[r] = n_clusters
        else:
            first[r] = edges[g] + (target - done) // held[g]
        first[r] = max(first[r], first[r - 1])
    return first


@njit(cache=True, error_model="numpy")
def _cluster_atom_forces(buffers, atom, windows, forces):
    """Sum the chunks' cluster-ordered forces, in chunk order, into ``forces`` (N, 3) in
    atom order. ``windows`` (chunks, 3; ``md.neighbors._cluster_search.chunk_windows``): chunk c
    wrote clusters ``windows[c, 0]`` (its first i cluster: a row's partners are its i
    cluster and clusters after it) to ``windows[c, 1]``, 12 values each, into
    ``buffers`` from 12 * ``windows[c, 2]`` on; nothing of a chunk outside its window
    is read."""
    _slot_forces(buffers, atom, windows, forces, 0, atom.shape[0])


@njit(cache=True, parallel=True, error_model="numpy")
def _cluster_atom_forces_threaded(buffers, atom, windows, forces, first):
    """:func:`_cluster_atom_forces` in runs of clusters on the threads, run r from cluster
    ``first[r]`` to ``first[r + 1]`` (:func:`cluster_sum_runs`; the same bits: each
    atom's sum is its own, in chunk order)."""
    for r in prange(first.shape[0] - 1):
        _slot_forces(buffers, atom, windows, forces, CLUSTER * first[r], CLUSTER * first[r + 1])


@njit(cache=True, inline="always", error_model="numpy")
def _slot_forces(buffers, atom, windows, forces, first, end):
    """:func:`_cluster_atom_forces` for slots ``first`` to ``end``: the slots of chunk k's
    i clusters take those of chunks 0 to k whose windows reach them. Returns whether every
    force written is finite (the fused step's check; dead code to the callers that drop it)."""
    chunks = windows.shape[0]
    finite = True
    for k in range(chunks):
        lo = max(first, windows[k, 0] * CLUSTER)
        hi = min(end, (windows[k + 1, 0] if k + 1 < chunks else windows[k, 1]) * CLUSTER)
        for s in range(lo, hi):
            i, base, cluster = atom[s], _slot_base(s), s // CLUSTER
            if i < 0:
                continue
            fx = fy = fz = 0.0
            for c in range(k + 1):
                if cluster < windows[c, 1]:
                    at = 3 * CLUSTER * (windows[c, 2] - windows[c, 0]) + base
                    fx += buffers[at]
                    fy += buffers[at + CLUSTER]
                    fz += buffers[at + 2 * CLUSTER]
            forces[i, 0], forces[i, 1], forces[i, 2] = fx, fy, fz
            finite &= abs(fx) < np.inf and abs(fy) < np.inf and abs(fz) < np.inf
    return finite


#: float32 values per cluster in the cluster kernels' j lanes (``potentials._cluster_ir``).
J_STRIDE = 48

#: Bytes of a cache line, and of an AVX-512 register.
_LINE = 64


def zeros_on_lines(shape, dtype) -> np.ndarray:
    """A C-ordered array of zeros whose data start on a cache line (numpy's own start 16
    bytes past one: every 64-byte vector of the cluster kernels' j lanes would then span
    two lines)."""
    dtype = np.dtype(dtype)
    size = int(np.prod(shape))
    raw = np.zeros(size + _LINE // dtype.itemsize, dtype)
    skip = (-raw.ctypes.data % _LINE) // dtype.itemsize
    return raw[skip : skip + size].reshape(shape)


@njit(cache=True, error_model="numpy")
def cluster_j_remainders(j_sums, j_counts, forces, first):
    """The j forces the cluster kernel's rows left in float32 lanes (``j_sums``, 48 per
    cluster: x, y, z in 16 lanes, lane 4 a + b the pair of i atom a and j atom b; fewer
    than a flush's worth of pairs, ``j_counts``), for clusters ``first`` on: folded over
    the i atoms as the rows fold them, subtracted from ``forces`` (12 per cluster), and
    set to zero with their counts."""
    for cluster in range(first, j_counts.shape[0]):
        if j_counts[cluster] == 0:
            continue
        j_counts[cluster] = 0
        lanes, base = J_STRIDE * cluster, 3 * CLUSTER * cluster
        for d in range(3):
            for b in range(CLUSTER):
                at = lanes + 16 * d + b
                total = (j_sums[at] + j_sums[at + 8]) + (j_sums[at + 4] + j_sums[at + 12])
                forces[base + CLUSTER * d + b] -= np.float64(total)
        j_sums[lanes : lanes + J_STRIDE] = 0.0


@njit(cache=True, inline="always", error_model="numpy")
def _cluster_slot_forces(out, atom, cluster, forces):
    """Cluster ``cluster``'s forces in ``out`` (12 per cluster) into ``forces`` (N, 3), in
    atom order (``atom``: each slot's atom, -1 for a filler)."""
    for s in range(CLUSTER * cluster, CLUSTER * (cluster + 1)):
        i, base = atom[s], _slot_base(s)
        if i >= 0:
            for d in range(3):
                forces[i, d] = out[base + d * CLUSTER]


@njit(cache=True, error_model="numpy")
def _cluster_moments(atom, xi, forces):
    """The sum over atoms of x_rel (x) F (3, 3): the virial's part that the cluster
    kernels leave out (they add each pair's offset (x) force)."""
    moments = np.zeros((3, 3))
    for s in range(atom.shape[0]):
        i, base = atom[s], _slot_base(s)
        if i < 0:
            continue
        for d in range(3):
            x = np.float64(xi[base + d * CLUSTER])
            for e in range(3):
                moments[d, e] += x * forces[i, e]
    return moments
