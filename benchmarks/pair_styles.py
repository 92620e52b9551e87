"""Pair time per listed pair of every pair style, next to Lennard-Jones's, on one list.

The LJ melt's configuration (fcc at reduced density 0.8442, randomly
displaced; 20^3 cells = 32000 atoms by default), one neighbour list (cutoff
2.5, skin 0.3) shared by every style, each style at cutoff 2.5 with
parameters giving forces of LJ's magnitude, and a user-written pair term
(a Gaussian core, ``potentials.pair_term``). Each row: the median time of
``energy_forces(virial=False)`` over the interleaved repeats (the styles take
turns, so a loaded machine slows them alike), its min-max, nanoseconds per
listed pair, and the ratio to LJ: the median over the repeats of the style's
time over LJ's in the same repeat; and the same ratio over the quarter of the
repeats in which LJ ran fastest (a core of a shared machine runs at two
speeds for seconds at a time, and the ratios differ between them).
Compilation is excluded (a warm-up call).

``--reference TREE`` adds a row for the Lennard-Jones of another source tree
(its ``potentials/lennard_jones.py``, loaded as a module of its own beside
this tree's packages, which it imports), timed in the same interleaved turns:
its ratio is this tree's LJ against that one, e.g. the pair frame's LJ against
main's LJ (``git archive main | tar -x -C /tmp/main``). A reference whose LJ
needs names this tree lacks fails with its ImportError.

    python benchmarks/pair_styles.py                 # 32000 atoms, 1 thread, 15 repeats
    python benchmarks/pair_styles.py --cells 12 --repeats 31
    python benchmarks/pair_styles.py --only lj --reference /tmp/main --threads 2 --repeats 41
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the checkout, from anywhere

from _machine import machine_line  # noqa: E402

import md  # noqa: E402
from md._kernel_cache import kernel_cache  # noqa: E402
from md.parallel import set_threads  # noqa: E402
from potentials import (  # noqa: E402
    Buckingham,
    LennardJones,
    Mie,
    Morse,
    PairPotential,
    Soft,
    Table,
    Yukawa,
    pair_term,
)
from potentials.pair_math import exp  # noqa: E402


@pair_term
def gaussian_core(r2, epsilon, sigma):
    """A user's term: u = eps exp(-r^2 / sigma^2) (the guide's vectorising exp)."""
    u = epsilon * exp(-r2 / (sigma * sigma))
    return u, 2.0 * u / (sigma * sigma)


def table_file(folder: Path) -> Path:
    """LJ tabulated on 2000 points from 0.5 to 2.5 (RSQ spacing)."""
    n = 2000
    r = np.sqrt(0.25 + (2.5**2 - 0.25) * np.arange(n) / (n - 1))
    e = 4.0 * (r**-12 - r**-6)
    f = 24.0 * (2.0 * r**-13 - r**-7)
    path = folder / "lj.table"
    path.write_text(
        "LJ\nN 2000 RSQ 0.5 2.5\n\n"
        + "".join(f"{k + 1} {r[k]:.17g} {e[k]:.17g} {f[k]:.17g}\n" for k in range(n))
    )
    return path


def styles(folder: Path) -> dict:
    cutoff = 2.5
    path = table_file(folder)
    return {
        "lj": LennardJones(cutoff=cutoff),
        "morse": Morse(d0=1.0, alpha=3.0, r0=1.1, cutoff=cutoff),
        "mie": Mie(n=13.0, m=6.5, cutoff=cutoff),
        "buckingham": Buckingham(a=2000.0, rho=0.15, c=1.0, cutoff=cutoff),
        "yukawa": Yukawa(a=1.0, kappa=1.5, cutoff=cutoff),
        "soft": Soft(a=1.0, cutoff=cutoff),
        "table linear": Table(path, "LJ", "linear"),
        "table spline": Table(path, "LJ", "spline"),
        "user (Gaussian core)": PairPotential(gaussian_core, epsilon=1.0, sigma=1.0, cutoff=cutoff),
    }


def reference_lj(tree: Path) -> LennardJones:
    """Lennard-Jones (default parameters, cutoff 2.5) from another tree's lennard_jones.py."""
    spec = importlib.util.spec_from_file_location(
        "reference_lennard_jones", Path(tree) / "potentials" / "lennard_jones.py"
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # numba's parallel lowering looks kernels' modules up
    with kernel_cache():
        spec.loader.exec_module(module)
    return module.LennardJones(cutoff=2.5)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=20, help="fcc cells per edge (20)")
    parser.add_argument("--repeats", type=int, default=15, help="interleaved repeats (15)")
    parser.add_argument("--threads", type=int, default=1, help="threads (1)")
    parser.add_argument("--only", default=None, help="comma-separated styles (default all)")
    parser.add_argument(
        "--reference",
        type=Path,
        default=None,
        help="another source tree whose LJ gets a row (e.g. main's)",
    )
    args = parser.parse_args(argv)
    print(machine_line())
    set_threads(args.threads)
    state = md.lattice("fcc", args.cells, density=0.8442)
    state.positions += np.random.default_rng(1).normal(0.0, 0.05, state.positions.shape)
    with tempfile.TemporaryDirectory() as folder:
        potentials = styles(Path(folder))
        if args.only:
            chosen = args.only.split(",")
            potentials = {k: v for k, v in potentials.items() if k in chosen or k == "lj"}
        if args.reference is not None:
            potentials["lj (--reference)"] = reference_lj(args.reference)
        neighbors = md.NeighborList(2.5, 0.3)
        neighbors.update(state)
        pairs = int(neighbors.frame.starts[-1])
        for potential in potentials.values():
            potential.energy_forces(state, neighbors, virial=False)  # compile or load
        times = {name: [] for name in potentials}
        for _ in range(args.repeats):
            for name, potential in potentials.items():
                start = time.perf_counter()
                potential.energy_forces(state, neighbors, virial=False)
                times[name].append(time.perf_counter() - start)
    lj = times["lj"]
    # The repeats in which LJ ran fastest: on a shared machine a core runs at two speeds
    # for seconds at a time (here 6.6 and 9.6 ms for the same LJ call), and the ratios
    # differ between the two (Morse/LJ 1.58 fast, 1.50 slow), so both are printed.
    fastest = sorted(range(len(lj)), key=lj.__getitem__)[: max(1, len(lj) // 4)]
    print(
        f"{state.n_atoms} atoms, {pairs} listed pairs (cutoff 2.5 + skin 0.3), "
        f"{args.repeats} interleaved repeats, {args.threads} thread(s)"
    )
    print(f"{'style':<22}{'ms':>9}{'min-max':>18}{'ns/pair':>10}{'/ LJ':>8}{'/ LJ fast':>11}")
    for name, values in times.items():
        median = statistics.median(values)
        ratio = statistics.median(t / reference for t, reference in zip(values, lj, strict=True))
        fast = statistics.median(values[k] / lj[k] for k in fastest)
        print(
            f"{name:<22}{1e3 * median:>9.2f}{1e3 * min(values):>9.2f}-{1e3 * max(values):<8.2f}"
            f"{1e9 * median / pairs:>10.2f}{ratio:>8.2f}{fast:>11.2f}"
        )
    print(
        "/ LJ: median of per-repeat ratios; / LJ fast: the same over the quarter of the "
        "repeats in which LJ ran fastest"
    )


if __name__ == "__main__":
    main()
