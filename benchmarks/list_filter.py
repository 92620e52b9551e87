"""Cost of a decomposed rank's list (``NeighborList.keep_owned``) against a whole list.

A rank of an MPI run builds its list over its own atoms and the ghost copies
of its neighbours' atoms and keeps each pair on one rank only: the search runs
over the owned atoms' rows alone (owned partners by the half rule, ghosts all
around, the designated-atom rule applied as it writes them:
``md.neighbors._owned_kernels``), so the pairs of two ghosts are never searched.
This times full list builds of an open fcc block (48 x 60 x 60 cells, 691,200
atoms, cutoff 2.5 + skin 0.3, 1 thread) with the first 85 % of the atoms
"owned" and the rest "ghosts", as a rank's list and as the list of every pair,
for ids in lattice order and for randomly permuted ids (the designated-atom
test depends on them). Prints the median build time of each and the rank's
list's time over the whole list's.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine_line  # noqa: E402

import md  # noqa: E402
from md.neighbors import NeighborList  # noqa: E402
from md.parallel import set_threads  # noqa: E402


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", default="48,60,60", help="fcc cells along x,y,z (48,60,60)")
    parser.add_argument("--repeats", type=int, default=5, help="builds timed per case (5)")
    parser.add_argument("--owned", type=float, default=0.85, help="owned share of the atoms")
    args = parser.parse_args(argv)
    print(machine_line())
    set_threads(1)
    cells = tuple(int(c) for c in args.cells.split(","))
    lattice = md.lattice("fcc", cells, density=0.8442)
    state = md.State(positions=lattice.positions, box=lattice.box, pbc=False)
    n = state.n_atoms
    n_owned = int(args.owned * n)
    cases = {
        "lattice ids": np.arange(n, dtype=np.int64),
        "random ids": np.random.default_rng(0).permutation(n).astype(np.int64),
    }
    print(
        f"{n} atoms (open block {cells}), {n_owned} owned, 1 thread, "
        f"median of {args.repeats} builds"
    )
    lists = {}
    for label, ids in cases.items():
        for keep in (False, True):
            neighbors = NeighborList(2.5, 0.3)
            if keep:
                neighbors.keep_owned(ids, n_owned)
            neighbors.build(state)  # compile or load, and size the buffers
            lists[label, keep] = neighbors
    # Interleaved: a core of a shared machine changes speed for seconds at a time.
    runs = {key: [] for key in lists}
    for _ in range(args.repeats):
        for key, neighbors in lists.items():
            start = time.perf_counter()
            neighbors.build(state)
            runs[key].append(time.perf_counter() - start)
    for label in cases:
        plain, kept = (statistics.median(runs[label, keep]) for keep in (False, True))
        share = statistics.median(
            k / p for k, p in zip(runs[label, True], runs[label, False], strict=True)
        )
        print(
            f"{label:12s} whole list {plain:.3f} s ({lists[label, False].n_pairs} pairs), the "
            f"rank's {kept:.3f} s ({lists[label, True].n_pairs} pairs): "
            f"{kept - plain:+.3f} s, {100 * (share - 1):+.0f} % (median of per-repeat ratios)"
        )


if __name__ == "__main__":
    main()
