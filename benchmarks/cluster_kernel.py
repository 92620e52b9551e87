"""The mixed-precision LJ force call on the cluster list, alone: ns per cluster pair.

The 32000-atom melt (fcc at rho* 0.8442, every atom moved by a Gaussian of 0.05
sigma), LJ cut at 2.5 sigma, the cluster list of ``ForceField(precision="mixed")``
(radius 2.8); ``energy_forces(virial=False, precision="mixed")`` called ``--calls``
times on the same positions after one untimed call (the kernel, the float32 relative
positions and the sum of the chunks into atom order; the list is not rebuilt), on
``--threads`` threads. Prints the minimum and the median per call and per listed
cluster pair.

A change to the kernel is measured by running this script under the two versions
alternately, each in fresh processes with its own ``NUMBA_CACHE_DIR`` and
``XDG_CACHE_HOME`` (the kernels compile once per cache), and comparing the
per-process minima; for another instruction set, set ``NUMBA_CPU_NAME`` and
``NUMBA_CPU_FEATURES`` as in ``benchmarks/README.md``. ``--precision double`` times the
double force call on the slot frame instead (``ForceField(precision="double")``), per
listed atom pair::

    python benchmarks/cluster_kernel.py
    python benchmarks/cluster_kernel.py --precision double
    python benchmarks/cluster_kernel.py --cells 10 --calls 20 --threads 2
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
from md.forcefield import ForceField  # noqa: E402
from md.parallel import get_threads, set_threads  # noqa: E402
from potentials import LennardJones  # noqa: E402


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=20, help="fcc cells per edge (20)")
    parser.add_argument("--calls", type=int, default=40, help="timed calls (40)")
    parser.add_argument("--threads", type=int, default=1, help="threads (1)")
    parser.add_argument("--precision", choices=("mixed", "double"), default="mixed",
                        help="mixed: the cluster kernel (default); double: the slot frame's "
                             "force call, per listed atom pair")  # fmt: skip
    args = parser.parse_args(argv)
    if args.cells < 1 or args.calls < 1 or args.threads < 1:
        parser.error("--cells, --calls and --threads must be at least 1")
    set_threads(args.threads)
    print(machine_line() + f"; {get_threads()} thread(s)")
    state = md.lattice("fcc", args.cells, density=0.8442)
    state.positions += np.random.default_rng(0).normal(scale=0.05, size=state.positions.shape)
    field = ForceField([LennardJones(cutoff=2.5)], precision=args.precision)
    try:
        field.compute(state)  # builds the list, compiles or loads the kernels
    except ValueError as error:
        sys.exit(f"--cells {args.cells}: {error}")
    clusters = field.neighbor_list.clusters
    if clusters is None and args.precision == "mixed":
        sys.exit(f"no cluster list for {state.n_atoms} atoms in this cell: use more --cells")
    potential, neighbors = field.potentials[0], field.neighbor_list
    times = []
    for _ in range(args.calls):
        start = time.perf_counter()
        potential.energy_forces(state, neighbors, virial=False, precision=args.precision)
        times.append(time.perf_counter() - start)
    if clusters is not None:
        pairs, what = len(clusters.partners), "cluster pairs"
    else:
        pairs, what = neighbors.n_pairs, "listed pairs"
    best, middle = min(times), statistics.median(times)
    print(f"{state.n_atoms} atoms, {pairs} {what}, {args.calls} calls: "
          f"min {1e3 * best:.3f} ms ({1e9 * best / pairs:.2f} ns per {what[:-1]}), "
          f"median {1e3 * middle:.3f} ms ({1e9 * middle / pairs:.2f} ns)")


if __name__ == "__main__":
    main()
