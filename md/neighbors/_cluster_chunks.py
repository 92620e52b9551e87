"""Which clusters of a chunked cluster-pair list only their own chunk writes.

The cluster kernels split the i clusters into chunks, one per thread
(``ClusterFrame.bounds``), each with its own force buffer. A row's partners are its
own cluster and later ones, so a cluster's forces come from its own chunk and from
earlier chunks whose rows list it (across the periodic boundary the first chunk's rows
reach the last clusters; each chunk's rows reach the first columns of the next). A
cluster that no earlier chunk lists has its final force after its own row in its own
chunk, which writes it into atom order there (as one chunk writes every cluster's); only
the others, "shared", are summed over the chunks' buffers afterwards
(``potentials._kernels.cluster_atom_forces``). On the 32000-atom melt in two chunks,
0.23 of the clusters are shared: the pass after the kernel then covers those alone,
not every slot.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, parallel=True, error_model="numpy")
def cluster_sharing(starts, partners, bounds):
    """(final, shared) of the list (``starts``, ``partners``) in the chunks ``bounds`` (i
    cluster ranges): ``final`` (uint8 per cluster) 1 where no row of an earlier chunk
    lists the cluster, ``shared`` (int64, ascending) the other clusters. Each chunk marks
    the clusters past its own that its rows list, in its own row of marks, on the
    threads; a pass over the clusters then reads the marks of the chunks before each."""
    n = starts.shape[0] - 1
    chunks = bounds.shape[0] - 1
    marks = np.zeros((chunks, n), np.uint8)
    for c in prange(chunks):
        _mark_reached(partners[starts[bounds[c]] : starts[bounds[c + 1]]], bounds[c + 1], marks[c])
    final = np.ones(n, np.uint8)
    count = 0
    for k in range(1, chunks):
        for cl in range(bounds[k], bounds[k + 1]):
            for c in range(k):
                if marks[c, cl]:
                    final[cl] = 0
            count += 1 - final[cl]
    shared = np.empty(count, np.int64)
    count = 0
    for cl in range(bounds[1] if chunks > 1 else n, n):
        if not final[cl]:
            shared[count] = cl
            count += 1
    return final, shared


@njit(cache=True, error_model="numpy")
def _mark_reached(partners, end, marks):
    """``marks[cj] = 1`` for each partner cj at or past ``end`` (past the chunk's own)."""
    for k in range(partners.shape[0]):
        cj = partners[k]
        if cj >= end:
            marks[cj] = 1
