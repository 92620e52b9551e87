"""What the kernel cache's dependency stamp costs at ``import md, potentials, integrators``.

    python3 benchmarks/kernel_cache_stamp.py [--repeats 5]

Each repeat is a fresh process (the stamp is memoised per process) that imports the
three packages with ``md._kernel_cache.dependency_stamp`` timed (``perf_counter``
around each call, the wrapper's own overhead included): the stamp's total against the
whole import's wall time. The import itself swings by tens of ms on a busy machine, so
this in-process share is the figure to read, not the difference of two imports. No
peer has this cost (LAMMPS and GROMACS compile ahead of time), so no ratio to one.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine_line  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]

CHILD = """
import importlib.util, json, sys, time
spec = importlib.util.spec_from_file_location("md._kernel_cache", sys.argv[1])
kc = importlib.util.module_from_spec(spec)
sys.modules["md._kernel_cache"] = kc
spec.loader.exec_module(kc)
spent = [0.0, 0]
stamp = kc.dependency_stamp
def timed(*args):
    start = time.perf_counter()
    try:
        return stamp(*args)
    finally:
        spent[0] += time.perf_counter() - start
        spent[1] += 1
kc.dependency_stamp = timed
start = time.perf_counter()
import md, potentials, integrators
total = time.perf_counter() - start
print(json.dumps({"import_ms": total * 1e3, "stamp_ms": spent[0] * 1e3, "calls": spent[1],
                  "files": kc._imports_of.cache_info().currsize}))
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    print(machine_line())
    rows = []
    for _ in range(args.repeats):
        done = subprocess.run(
            [sys.executable, "-c", CHILD, str(ROOT / "md" / "_kernel_cache.py")],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
        )
        rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
    for row in rows:
        print(
            f"import {row['import_ms']:7.1f} ms   stamp {row['stamp_ms']:5.2f} ms "
            f"({row['calls']} kernels, {row['files']} files scanned)"
        )
    stamp = statistics.median(r["stamp_ms"] for r in rows)
    share = statistics.median(r["stamp_ms"] / r["import_ms"] for r in rows)
    print(f"median: stamp {stamp:.2f} ms, {100 * share:.1f} % of the import")


if __name__ == "__main__":
    main()
