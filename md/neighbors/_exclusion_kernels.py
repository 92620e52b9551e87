"""The pairs within one group left out of a built list (``NeighborList.exclude_groups``).

One pass over the list a search has just built, whichever search it was (the cell
search on any number of threads, the small-box search, the O(N^2) one over atom
indices): the pairs of two atoms in one group (a rigid body) are dropped and the
rest move up, in place, in their order. As LAMMPS's ``neigh_modify exclude
molecule/intra``, the pairs are never listed, so no pair kernel sees them.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _drop_grouped_pairs(order, starts, neighbors, codes, groups):
    """Drop, in place, the listed pairs whose two atoms are in one group; return the new
    pair count.

    ``groups`` (N,) int64: each atom's group, or -1 (in none: every pair of it is kept).
    ``order`` (N,): the atom in each slot (empty for a list over atom indices);
    ``starts`` (N + 1,) CSR offsets, rewritten; ``neighbors`` (P,) partner slots and
    ``codes`` (P,) image codes (or empty), compacted. A row of an atom in no group
    moves as one block.
    """
    n = starts.shape[0] - 1
    slot_groups = np.empty(n, dtype=np.int64)
    for p in range(n):
        slot_groups[p] = groups[order[p] if order.shape[0] > 0 else p]
    with_codes = codes.shape[0] > 0
    kept = 0
    begin = starts[0]
    for p in range(n):
        end = starts[p + 1]
        group = slot_groups[p]
        if group < 0:
            if kept != begin:
                for k in range(begin, end):
                    neighbors[kept + k - begin] = neighbors[k]
                if with_codes:
                    for k in range(begin, end):
                        codes[kept + k - begin] = codes[k]
            kept += end - begin
        else:
            for k in range(begin, end):
                q = neighbors[k]
                if slot_groups[q] != group:
                    neighbors[kept] = q
                    if with_codes:
                        codes[kept] = codes[k]
                    kept += 1
        starts[p + 1] = kept
        begin = end
    starts[0] = 0
    return kept
