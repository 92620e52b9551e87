"""Kernels run as Python under ``NUMBA_DISABLE_JIT=1`` (a debugger, coverage, tracebacks).

numba cannot call an LLVM-IR intrinsic from Python, so each has a Python twin
(``md._simd.python_twin``) that stands in for it in that mode. Here every
intrinsic is compared with its twin on the same inputs (compiled), and the
serial engine, LJ and velocity Verlet over an O(N^2) list and over a cell list
(both the AVX2 permute path and the bit-mask scan), is run with numba off in a
subprocess and compared with the compiled run; so are the pair frame's other
paths (Morse's vectorising exp, a spline table, a user's term; per-atom values
and Hessian blocks; LJ runs on the frame too).
"""

from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from numba import njit

from md._simd import (
    PERMUTATIONS,
    PERMUTE,
    bit_count,
    bits_float,
    float_bits,
    gather_rows4,
    gather_shifted_rows4,
    move_within,
    scatter_sub_rows4,
    store_fence,
    stream_store,
    trailing_zeros,
)
from md.neighbors import _candidates as candidate_kernels
from md.neighbors._candidates import _near_bits
from md.neighbors._cell_kernels import GATHER_BLOCK, _copy_block
from md.neighbors._cluster_grid import cluster_grid, column_counts
from md.neighbors._cluster_prune import _near_pair, cluster_positions, keep_window
from md.neighbors._cluster_search import search_pairs

ROOT = Path(__file__).resolve().parents[1]


def _modules_with_intrinsics() -> list[str]:
    """Every project module whose source builds an intrinsic (``intrinsic(`` or ``@intrinsic``)."""
    found = []
    for package in ("md", "potentials", "integrators"):
        for path in sorted((ROOT / package).rglob("*.py")):
            text = path.read_text()
            if "@intrinsic" in text or "intrinsic(" in text:
                found.append(".".join(path.relative_to(ROOT).with_suffix("").parts))
    return found


def test_every_intrinsic_has_a_python_twin():
    intrinsic_type = type(trailing_zeros)
    modules = _modules_with_intrinsics()
    assert {"md._simd", "md.neighbors._cell_kernels", "md.neighbors._candidates"} <= set(modules)
    found = []
    for name in modules:
        for attribute, value in vars(importlib.import_module(name)).items():
            if isinstance(value, intrinsic_type):
                found.append(attribute)
                assert callable(getattr(value, "python_twin", None)), f"{name}.{attribute}"
    assert {
        "trailing_zeros",
        "float_bits",
        "_near_bits",
        "_copy_block",
        "_near_pair",
        "_mark_near",
        "_compress_kept",
        "keep_window",
    } <= set(found)


@njit
def _near_pairs(xi, xj, starts, partners, offsets, reach2, near):
    for ci in range(starts.shape[0] - 1):
        for k in range(starts[ci] + 1, starts[ci + 1]):  # not the cluster with itself
            near[k] = _near_pair(
                xi, xj, ci, partners[k], offsets[k, 0], offsets[k, 1], offsets[k, 2], reach2
            )


def _cluster_list(fcc_lattice):
    """A rattled lattice's clusters and their list of radius 2.8: (state, atom, xi, xj,
    (lower, upper) bounding boxes, starts, partners, offsets)."""
    state = fcc_lattice(cells=6, perturbation=0.1)
    ncx, ncy = column_counts(state.box, state.n_atoms, 2.8)
    first, atom, origin, lower, upper = cluster_grid(state.positions, state.box, ncx, ncy)
    xi = np.empty(3 * len(atom), np.float32)
    xj = np.empty(3 * len(atom), np.float32)
    cluster_positions(state.positions, atom, origin, xi, xj)
    starts, partners, offsets = search_pairs(
        state.box, ncx, ncy, first, lower, upper, 2.8, 1, 256, xi, xj, np.float32(2.8**2)
    )
    return state, atom, xi, xj, (lower, upper), starts, partners, offsets


def test_the_cluster_pair_check_equals_its_twin_and_the_atom_distances(fcc_lattice):
    """The atom-distance check of the cluster search and prune, compiled and as numpy, on
    every pair of a list (a reach between the lattice's shells, so both verdicts occur),
    and against the atoms' own distances (double, minimum image) away from the reach."""
    state, atom, xi, xj, _, starts, partners, offsets = _cluster_list(fcc_lattice)
    reach = 2.0
    compiled = np.zeros(len(partners), np.uint8)
    _near_pairs(xi, xj, starts, partners, offsets, np.float32(reach**2), compiled)
    rows = set(starts[:-1].tolist())
    checked = 0
    for ci in range(len(starts) - 1):
        for k in range(starts[ci] + 1, starts[ci + 1]):
            twin = _near_pair.python_twin(
                xi, xj, ci, partners[k], *offsets[k], np.float32(reach**2)
            )
            assert twin == bool(compiled[k]), k
            mine = atom[4 * ci : 4 * ci + 4]
            theirs = atom[4 * partners[k] : 4 * partners[k] + 4]
            mine, theirs = mine[mine >= 0], theirs[theirs >= 0]
            d = state.positions[mine][:, None] - state.positions[theirs][None]
            d -= state.box * np.round(d / state.box)
            r = np.sqrt((d * d).sum(axis=-1)).min() if len(mine) and len(theirs) else np.inf
            if abs(r - reach) > 1e-4:  # float32 decides the pairs at the reach itself
                assert bool(compiled[k]) == (r < reach), (k, r)
                checked += 1
    assert checked > 0.9 * (len(partners) - len(rows))
    assert 0 < compiled.sum() < len(partners) - len(rows)


@njit
def _windows(xi, xj, rows, spans, shifts, centres, reach2, partners, offsets, ends):
    k = 0
    for w in range(rows.shape[0]):
        k = keep_window(
            xi,
            xj,
            rows[w],
            spans[w, 0],
            spans[w, 1],
            shifts[w, 0],
            shifts[w, 1],
            shifts[w, 2],
            centres[0],
            centres[1],
            centres[2],
            reach2,
            partners,
            offsets,
            k,
        )
        ends[w] = k


def test_the_search_window_equals_its_twin_and_the_pair_check(fcc_lattice, rng):
    """The search's window of candidates (:func:`md.neighbors._cluster_prune.keep_window`, the
    loop in IR): each candidate's float32 offset (centre difference less the shift, in
    double, then rounded), and the candidates kept as ``_near_pair`` decides them, in
    order, as its Python twin writes them; an empty window writes nothing."""
    state, atom, xi, xj, (lower, upper), *_ = _cluster_list(fcc_lattice)
    centres = np.ascontiguousarray((0.5 * (lower + upper)).T)
    n = len(lower)
    rows = rng.integers(0, n, 40)
    spans = np.stack([np.maximum(rows - 8, 0), np.minimum(rows + 8, n)], axis=1)  # its column
    spans[5, 1] = spans[5, 0]  # an empty window
    images = np.zeros((40, 3))
    images[::4] = rng.choice([-1.0, 1.0], (10, 3))  # far images: none kept
    shifts = centres.T[rows] - images * state.box
    reach2 = np.float32(2.0**2)
    room = int((spans[:, 1] - spans[:, 0]).sum()) + 1
    partners, offsets = np.zeros(room, np.int32), np.zeros((room, 3), np.float32)
    ends = np.zeros(40, np.int64)
    _windows(xi, xj, rows, spans, shifts, centres, reach2, partners, offsets, ends)
    twin_partners, twin_offsets = np.zeros_like(partners), np.zeros_like(offsets)
    k, kept = 0, []
    for w in range(40):
        for j in range(spans[w, 0], spans[w, 1]):
            o = (shifts[w] - centres[:, j]).astype(np.float32)
            if _near_pair.python_twin(xi, xj, rows[w], j, *o, reach2):
                kept.append((j, o))
        k = keep_window.python_twin(
            xi,
            xj,
            rows[w],
            spans[w, 0],
            spans[w, 1],
            *shifts[w],
            *centres,
            reach2,
            twin_partners,
            twin_offsets,
            k,
        )
        assert ends[w] == k == len(kept), w
    assert 0 < len(kept) < room - 1
    assert np.array_equal(partners[: len(kept)], [j for j, _ in kept])
    assert np.array_equal(offsets[: len(kept)], np.array([o for _, o in kept]))
    assert np.array_equal(twin_partners[:k], partners[:k])
    assert np.array_equal(twin_offsets[:k], offsets[:k])


@njit
def _scalars(word, x, bits):
    return trailing_zeros(word), bit_count(word), float_bits(x), bits_float(bits)


def test_scalar_twins_equal_their_intrinsics(rng):
    words = [np.uint64(1), np.uint64(1 << 63), np.uint64(2**64 - 1)]
    words += [np.uint64(w) | np.uint64(1 << 40) for w in rng.integers(0, 2**63, 50)]
    floats = [0.0, -0.0, 1.0, np.inf, -np.inf, np.nan, 5e-324, 1.7e308, *rng.normal(size=50)]
    for word, x in zip(words * 2, floats, strict=False):
        bits = np.int64(rng.integers(-(2**63), 2**63 - 1))
        compiled = _scalars(word, x, bits)
        twins = (
            trailing_zeros.python_twin(word),
            bit_count.python_twin(word),
            float_bits.python_twin(x),
            bits_float.python_twin(bits),
        )
        assert compiled[:3] == twins[:3], (word, x)
        assert np.array_equal(compiled[3], twins[3], equal_nan=True)
        assert all(isinstance(t, np.int64) for t in twins[:3]) and isinstance(twins[3], np.float64)


@njit
def _stores(array, values):
    for k in range(values.shape[0]):
        stream_store(array, np.uint64(k), values[k])
    store_fence()


@njit
def _move(array, to, start, count):
    move_within(array, to, start, count)


def test_store_and_move_twins_equal_their_intrinsics(rng):
    values = rng.normal(size=20)
    compiled, twin = np.zeros(20), np.zeros(20)
    _stores(compiled, values)
    for k in range(20):
        stream_store.python_twin(twin, np.uint64(k), values[k])
    store_fence.python_twin()
    assert np.array_equal(compiled, twin) and np.array_equal(compiled, values)
    for to, start, count in [(0, 5, 10), (5, 0, 10), (3, 3, 4), (0, 0, 0), (10, 2, 9)]:
        base = rng.integers(0, 1000, 30).astype(np.int32)
        compiled, twin = base.copy(), base.copy()
        _move(compiled, to, start, count)
        move_within.python_twin(twin, to, start, count)
        expected = base.copy()
        expected[to : to + count] = base[start : start + count].copy()
        assert np.array_equal(compiled, twin) and np.array_equal(compiled, expected)


@njit
def _rows4(rows, partners, columns, forces):
    for k in range(0, partners.shape[0], 4):
        gather_rows4(rows, partners, k, columns[0], columns[1], columns[2])
        scatter_sub_rows4(rows, partners, k, forces[0], forces[1], forces[2])


@njit
def _shifted_rows4(rows, partners, shifts, codes, columns):
    for k in range(0, partners.shape[0], 4):
        gather_shifted_rows4(rows, partners, shifts, codes, k, columns[0], columns[1], columns[2])


def _rows4_twin(rows, partners, columns, forces):
    for k in range(0, partners.shape[0], 4):
        gather_rows4.python_twin(rows, partners, k, columns[0], columns[1], columns[2])
        scatter_sub_rows4.python_twin(rows, partners, k, forces[0], forces[1], forces[2])


@pytest.mark.parametrize(
    ("dtype", "real"), [(np.int32, np.float64), (np.uint32, np.float64), (np.int32, np.float32)]
)
def test_row_gather_and_scatter_twins_equal_their_intrinsics(rng, dtype, real):
    """Four partners' rows gathered into columns (with image shifts added, and without)
    and forces subtracted from them: the intrinsics (16-byte loads, transposes in
    registers) give the twin's bits, which are plain indexing's, at any partner (first
    and last rows included)."""
    rows = rng.normal(size=(41, 3)).astype(real)
    partners = np.concatenate([[0, 40, 17, 3], rng.permutation(41)[:12]]).astype(dtype)
    forces = rng.normal(size=(3, 16)).astype(real)
    compiled, twin = (rows.copy(), np.zeros((3, 16), real)), (rows.copy(), np.zeros((3, 16), real))
    _rows4(compiled[0], partners, compiled[1], forces)
    _rows4_twin(twin[0], partners, twin[1], forces)
    assert np.array_equal(compiled[1], twin[1]) and np.array_equal(compiled[0], twin[0])
    expected = rows.copy()
    for k in range(0, 16, 4):  # each group gathered before its forces are taken off
        group = partners[k : k + 4]
        np.testing.assert_array_equal(compiled[1][:, k : k + 4], expected[group].T)
        expected[group] -= forces[:, k : k + 4].T
    np.testing.assert_array_equal(compiled[0], expected)
    shifts = rng.normal(size=(27, 3)).astype(real)
    codes = rng.integers(0, 27, 16).astype(np.uint8)
    compiled, twin = np.zeros((3, 16), real), np.zeros((3, 16), real)
    _shifted_rows4(rows, partners, shifts, codes, compiled)
    for k in range(0, 16, 4):
        gather_shifted_rows4.python_twin(rows, partners, shifts, codes, k, *twin)
    assert np.array_equal(compiled, twin)
    np.testing.assert_array_equal(compiled, (rows[partners] + shifts[codes]).T)


def _candidates(rng, n=200):
    """A centre and candidates around it, some beyond r2_max = 1, with uint32 tags."""
    xs, ys, zs = (rng.uniform(-1.2, 1.2, n) for _ in range(3))
    packed = rng.integers(0, 2**32, n, dtype=np.uint64).astype(np.uint32)
    return xs, ys, zs, packed


@njit
def _copy(xs, ys, zs, slots, first, sx, sy, sz, tag, cx, cy, cz, c_packed, m):
    _copy_block(xs, ys, zs, slots, first, sx, sy, sz, tag, cx, cy, cz, c_packed, m)


@njit
def _bits(xi, yi, zi, r2, tx, ty, tz, packed, start):
    return _near_bits(xi, yi, zi, r2, tx, ty, tz, packed, start)


def test_vector_twins_of_the_cell_search_equal_their_intrinsics(rng):
    xs, ys, zs, packed = _candidates(rng)
    for first, m in [(0, 0), (13, 40), (150, 3)]:
        compiled = [np.zeros(200) for _ in range(3)] + [np.zeros(200, dtype=np.uint32)]
        twin = [a.copy() for a in compiled]
        tag = np.uint32(5) << np.uint32(27)
        _copy(xs, ys, zs, packed, first, 0.5, -1.0, 2.0, tag, *compiled, m)
        _copy_block.python_twin(xs, ys, zs, packed, first, 0.5, -1.0, 2.0, tag, *twin, m)
        assert all(np.array_equal(a, b) for a, b in zip(compiled, twin, strict=True))
        assert np.array_equal(compiled[0][m : m + GATHER_BLOCK], xs[first : first + 8] + 0.5)
    for start in (0, 7, 100, 136):
        centre = rng.uniform(-0.3, 0.3, 3)
        compiled = _bits(*centre, 1.0, xs, ys, zs, packed, start)
        assert compiled == _near_bits.python_twin(*centre, 1.0, xs, ys, zs, packed, start)
        assert 0 < bit_count.python_twin(compiled) < 64  # both kinds of lane were tested


@njit
def _pack_whole(xi, yi, zi, r2, tx, ty, tz, packed, start, valid, table, out, at):
    return candidate_kernels._near_pack_permute_whole(
        xi, yi, zi, r2, tx, ty, tz, packed, start, valid, table, out, at
    )


@njit
def _pack_block(xi, yi, zi, r2, tx, ty, tz, packed, start, valid, table, out, at):
    return candidate_kernels._near_pack_permute_block(
        xi, yi, zi, r2, tx, ty, tz, packed, start, valid, table, out, at
    )


@pytest.mark.skipif(not PERMUTE, reason="the AVX2 permute intrinsics exist only with AVX2")
@pytest.mark.parametrize("call", [_pack_whole, _pack_block], ids=["whole", "block"])
def test_permute_twins_equal_their_intrinsics(rng, call):
    packer = candidate_kernels._near_pack_permute_whole
    if call is _pack_block:
        packer = candidate_kernels._near_pack_permute_block
    xs, ys, zs, packed = _candidates(rng)
    for start, valid, at in [(0, 64, 0), (5, 64, 17), (64, 3, 2), (100, 8, 0), (120, 1, 9)]:
        centre = rng.uniform(-0.3, 0.3, 3)
        args = (*centre, 1.0, xs, ys, zs, packed, start, valid, PERMUTATIONS)
        compiled, twin = np.zeros(200, np.uint32), np.zeros(200, np.uint32)
        end = call(*args, compiled, at)
        assert end == packer.python_twin(*args, twin, at)
        assert np.array_equal(compiled, twin)


# The serial engine with numba off, against the compiled run.

_RUN = """
import json, sys
import numpy as np
import md
from md._simd import PERMUTE
from integrators import VelocityVerlet
from potentials import LennardJones
results = {}
# (fcc cells, LJ cutoff): an O(N^2) list (box < 5 half-radius cells), a cell list
for cells, cutoff in [(3, 2.5), (4, 1.5)]:
    state = md.lattice("fcc", cells, density=0.8442)
    md.maxwell_boltzmann(state, temperature=1.5, seed=3)
    sim = md.Simulation(state, [LennardJones(cutoff=cutoff)], VelocityVerlet(dt=0.005),
                        skin=0.05, threads=1, max_displacement=0.5)
    sim.run(6)
    nl = sim.forcefield.neighbor_list
    pairs = [(i, int(j)) for i in range(len(state.positions))
             for j in nl.neighbors[nl.starts[i]:nl.starts[i + 1]]]
    results[str(cells)] = {
        "cells": nl.used_cells, "builds": nl.n_builds, "pairs": sorted(pairs),
        "positions": state.positions.tolist(), "velocities": state.velocities.tolist(),
        "forces": sim.forcefield.compute(state).forces.tolist(),
        "thermo": {k: float(v) for k, v in sim.thermo().items()},
        "permute": PERMUTE,
        # no dispatcher
        "as_python": not hasattr(md.neighbors._build_kernels._cell_list, "py_func"),
    }
print(json.dumps(results))
"""


def _engine(script: str = _RUN, **env) -> dict:
    environment = {**os.environ, **env}
    paths = [str(ROOT), os.environ.get("PYTHONPATH")]
    environment["PYTHONPATH"] = os.pathsep.join(filter(None, paths))
    done = subprocess.run(
        [sys.executable, "-c", script],
        env=environment,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def compiled_run():
    return _engine(NUMBA_DISABLE_JIT="0")


@pytest.mark.parametrize(
    "features",
    [None, pytest.param("-avx2", marks=pytest.mark.slow)],  # the host's path by default
    ids=["host CPU (AVX2: permute path)", "no AVX2 (scan path)"],
)
def test_serial_engine_under_disable_jit_matches_the_compiled_run(compiled_run, features):
    env = {"NUMBA_DISABLE_JIT": "1"}
    if features is not None:
        env["NUMBA_CPU_FEATURES"] = features  # read by md._simd only: nothing is compiled
    python = _engine(**env)
    assert python["4"]["as_python"] and not compiled_run["4"]["as_python"]
    assert python["4"]["permute"] == (PERMUTE and features is None)
    for cells, uses_cells in [("3", False), ("4", True)]:
        ours, reference = python[cells], compiled_run[cells]
        assert ours["cells"] is reference["cells"] is uses_cells
        assert ours["builds"] == reference["builds"] > 1  # a rebuild within the run
        assert ours["pairs"] == reference["pairs"]  # the same list, exactly
        for key in ("positions", "velocities", "forces"):
            np.testing.assert_allclose(ours[key], reference[key], rtol=1e-11, atol=1e-11)
        for key, value in reference["thermo"].items():
            assert ours["thermo"][key] == pytest.approx(value, rel=1e-11, abs=1e-11), key


# The pair frame's other paths with numba off: a term calling pair_math.exp (Morse), a
# tabulated term with jittable helpers and a data array, and a user's term, each through
# the slot-frame kernel, the atom-order kernel (per-atom values) and the Hessian blocks.

_FRAME_RUN = """
import json
import numpy as np
import md
from potentials import Morse, PairPotential, Table, pair_term

@pair_term
def soft_wall(r2, k, width):
    gap = width - r2**0.5
    return 0.5 * k * gap * gap, k * gap / r2**0.5

r = np.linspace(0.5, 2.0, 200)
e = np.exp(-3.0 * r)
rows = "".join(f"{k + 1} {r[k]:.17g} {e[k]:.17g} {3.0 * e[k]:.17g}\\n" for k in range(200))
with open("pair.table", "w") as handle:
    handle.write("E\\nN 200 R 0.5 2.0\\n\\n" + rows)
state = md.lattice("fcc", 4, density=0.8, shear=(0.2, 0.0, 0.1))
state.positions += np.random.default_rng(1).normal(0.0, 0.04, state.positions.shape)
results = {}
for name, potential in [("morse", Morse(d0=1.0, alpha=2.0, r0=1.1, cutoff=1.5)),
                        ("table", Table("pair.table", "E", "spline", cutoff=1.5)),
                        ("user", PairPotential(soft_wall, k=5.0, width=1.3, cutoff=1.3))]:
    forcefield = md.ForceField([potential], skin=0.1)
    fast = forcefield.compute(state, virial=True)
    nl = forcefield.neighbor_list
    per_atom = potential.energy_forces(state, nl, per_atom=True)
    blocks = potential.hessian_operator(state, nl).tocsr() if name != "user" else None
    results[name] = {
        "frame": nl.frame is not None, "energy": fast.energy, "forces": fast.forces.tolist(),
        "virial": fast.virial.tolist(), "energies": per_atom.energies.tolist(),
        "hessian": None if blocks is None else blocks.toarray().tolist(),
    }
print(json.dumps(results))
"""


@pytest.mark.slow  # the frame's loops in plain Python: 25 s on a cold cache
def test_pair_frame_under_disable_jit_matches_the_compiled_run(tmp_path):
    compiled = _engine(
        _FRAME_RUN.replace("pair.table", str(tmp_path / "a.table")), NUMBA_DISABLE_JIT="0"
    )
    python = _engine(
        _FRAME_RUN.replace("pair.table", str(tmp_path / "b.table")), NUMBA_DISABLE_JIT="1"
    )
    for name, reference in compiled.items():
        ours = python[name]
        assert ours["frame"] and reference["frame"], name  # the slot-frame path ran
        assert ours["energy"] == pytest.approx(reference["energy"], rel=1e-11), name
        for key in ("forces", "virial", "energies", "hessian"):
            if reference[key] is not None:
                scale = np.abs(reference[key]).max()
                np.testing.assert_allclose(
                    ours[key], reference[key], rtol=0, atol=1e-11 * scale, err_msg=f"{name} {key}"
                )
