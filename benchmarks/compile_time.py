"""Cold compile time of the kernels a run needs: CPU seconds per compiled function.

Each case runs in a child process with an empty numba cache (a fresh temporary
``NUMBA_CACHE_DIR``), and numba's compile events give each function's exclusive CPU time
(its callees' compiles subtracted) and how many times it was compiled. Cases: ``cell``
(one cell-list build), ``lj`` (one Lennard-Jones force call, double), ``hessian`` (LJ's
Hessian operator: the curvature pass), ``step`` (three Simulation steps, double then
mixed), on an fcc crystal of ``--cells`` cells (12: 6912 atoms, several chunks on two
threads, the threaded kernels).

``--tree DIR`` runs every case from that source tree too (an export of another commit:
``git archive main | tar -x -C /tmp/main``), alternating with this one, so both see the
same load; the table gives both totals. No peer program applies (LAMMPS and GROMACS are
compiled ahead of time). The test suite's cold time is about half numba compiling, so
this is its budget (benchmarks/README.md, "Cold compile time").

    python benchmarks/compile_time.py --cases cell lj --tree /tmp/main --top 8
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine_line  # noqa: E402

HERE = Path(__file__).resolve().parents[1]

#: The child: runs one case, prints {function: [exclusive CPU seconds, compiles]} as JSON.
CHILD = r"""
import collections, json, sys, time
from numba.core import event
seconds = collections.defaultdict(float); counts = collections.Counter(); stack = []
class Listener(event.Listener):
    def on_start(self, e):
        f = getattr(e.data.get("dispatcher"), "py_func", None)
        name = f"{getattr(f, '__module__', '')}.{getattr(f, '__qualname__', '?')}"
        stack.append([time.process_time(), name, 0.0])
    def on_end(self, e):
        start, name, inner = stack.pop()
        spent = time.process_time() - start
        seconds[name] += spent - inner; counts[name] += 1
        if stack:
            stack[-1][2] += spent
event.register("numba:compile", Listener())
import md
from integrators import VelocityVerlet
from potentials import LennardJones
case, cells = sys.argv[1], int(sys.argv[2])
state = md.build.maxwell_boltzmann(md.lattice("fcc", cells, density=0.8442), 1.5, seed=7)
if case == "cell":
    md.NeighborList(2.5, 0.3).update(state)
elif case == "lj":
    md.ForceField([LennardJones(cutoff=2.5)]).compute(state)
elif case == "hessian":
    neighbors = md.NeighborList(2.5, 0.3); neighbors.update(state)
    LennardJones(cutoff=2.5).hessian_operator(state, neighbors)
elif case == "step":
    for precision in ("double", "mixed"):
        sim = md.Simulation(state.copy(), [LennardJones(cutoff=2.5)], VelocityVerlet(dt=0.005),
                            precision=precision)
        sim.run(3)
print(json.dumps({k: [v, counts[k]] for k, v in seconds.items()}))
"""


def run_case(tree: Path, case: str, cells: int) -> dict[str, list]:
    """{function: [exclusive CPU seconds, compiles]} of one case run cold from ``tree``."""
    with tempfile.TemporaryDirectory(prefix="md-cold-") as cache:
        environment = dict(os.environ, PYTHONPATH=str(tree), NUMBA_CACHE_DIR=cache)
        done = subprocess.run(
            [sys.executable, "-c", CHILD, case, str(cells)],
            env=environment,
            capture_output=True,
            text=True,
            check=True,
            cwd=tree,
        )
    return json.loads(done.stdout.strip().splitlines()[-1])


def _short(name: str) -> str:
    """A term module's name without its hash: ``potentials._pair_kernels_lj.X``."""
    head, _, tail = name.rpartition(".")
    parts = head.split("_")
    if len(parts) > 1 and len(parts[-1]) == 20:
        head = "_".join(parts[:-1])
    elif len(parts) > 2 and parts[-1] == "mixed" and len(parts[-2]) == 20:
        head = "_".join(parts[:-2] + ["mixed"])
    return f"{head}.{tail}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", default=["cell", "lj", "hessian", "step"])
    parser.add_argument("--cells", type=int, default=12)
    parser.add_argument("--tree", type=Path, help="another source tree, run alternately")
    parser.add_argument("--top", type=int, default=10, help="functions listed per case")
    args = parser.parse_args()
    print(machine_line())
    print(f"load average at start {os.getloadavg()[0]:.2f} (CPU seconds, not wall)")
    trees = [("this", HERE)] + ([("--tree", args.tree.resolve())] if args.tree else [])
    for case in args.cases:
        results = {label: run_case(tree, case, args.cells) for label, tree in trees}
        totals = ", ".join(
            f"{label} {sum(v[0] for v in r.values()):.1f} s" for label, r in results.items()
        )
        print(f"\n{case} (fcc {args.cells}^3): compile CPU {totals}")
        merged: dict[str, dict[str, list]] = {}
        for label, result in results.items():
            for name, value in result.items():
                merged.setdefault(_short(name), {})[label] = value
        rows = sorted(merged.items(), key=lambda item: -item[1].get("this", [0.0])[0])
        for name, by_tree in rows[: args.top]:
            cells = "  ".join(
                f"{label} {by_tree[label][0]:5.2f} s x{by_tree[label][1]}"
                if label in by_tree
                else f"{label}    -     "
                for label, _ in trees
            )
            print(f"  {cells}  {name}")


if __name__ == "__main__":
    main()
