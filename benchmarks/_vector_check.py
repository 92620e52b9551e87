"""Did LLVM vectorise the hot loops on this machine? Compile them afresh and read the assembly.

Run as a script (``compare.py`` runs it in a child process): it points numba's
cache at an empty folder, so the kernels are compiled here and their machine
code can be inspected (numba keeps no assembly for kernels loaded from its
cache), runs a small LJ system through the slot-frame force kernel and the
cell search (with ``--pair-styles``, every pair style's pair loop too), and
prints one JSON object: per kernel, the packed
double-precision arithmetic instructions (FMA, multiply, add, subtract,
compare, divide, square root) on 256-bit (ymm) and 512-bit (zmm) registers.
A kernel with none ran scalar.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import sys
import tempfile
from pathlib import Path

#: Packed double arithmetic on a ymm or zmm register (the group: y or z).
PACKED = re.compile(
    r"^\s*v(?:fn?m(?:add|sub)\d{3}pd|mulpd|addpd|subpd|cmp\w*pd|divpd|sqrtpd)\s.*%([yz])mm"
)


def packed_counts(assembly: str) -> dict[str, int]:
    counts = {"ymm": 0, "zmm": 0}
    for line in assembly.splitlines():
        match = PACKED.match(line)
        if match:
            counts[match.group(1) + "mm"] += 1
    return counts


def main() -> None:
    cache = tempfile.mkdtemp(prefix="leapmd_vector_check_")
    os.environ["NUMBA_CACHE_DIR"] = cache  # before numba is imported
    try:
        report(styles="--pair-styles" in sys.argv)
    finally:
        shutil.rmtree(cache, ignore_errors=True)


def report(styles: bool = False) -> None:
    """Print the packed counts; ``styles``: also every pair style's pair loop (minutes)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the checkout, from anywhere
    import numpy as np

    import md
    from md.neighbors import _cell_kernels
    from potentials import POTENTIALS, LennardJones, PairPotential
    from potentials._pair_codegen import kernels_for

    state = md.lattice("fcc", 6, density=0.8442)
    state.positions += np.random.default_rng(0).normal(scale=0.05, size=state.positions.shape)
    lj = LennardJones(cutoff=2.5)
    forcefield = md.ForceField([lj], skin=0.3)
    forcefield.compute(state, virial=False)
    kernels = {
        "LJ pair loop (the frame's _frame_chunk)": kernels_for(lj.term)._frame_chunk,
        "cell search (_cell_kernels._frame_pairs_chunk)": _cell_kernels._frame_pairs_chunk,
    }
    if styles:
        defaults = {"table": None, "buckingham": {"a": 2000.0, "rho": 0.15, "c": 1.0}}
        for name, style in POTENTIALS.items():
            if not issubclass(style, PairPotential) or name in ("lj", "table"):
                continue
            potential = style(**(defaults.get(name) or {}), cutoff=2.5)
            md.ForceField([potential], skin=0.3).compute(state, virial=False)
            kernels[f"{name} pair loop"] = kernels_for(potential.term)._frame_chunk
    out = {}
    for name, kernel in kernels.items():
        counts = {"ymm": 0, "zmm": 0}
        for signature in kernel.signatures:
            for width, n in packed_counts(kernel.inspect_asm(signature)).items():
                counts[width] += n
        out[name] = counts
    print(json.dumps(out))


if __name__ == "__main__":
    main()
