"""Mixed-precision runs are as reproducible as double ones.

The same run gives the same trajectory whether this process compiled the kernels or
loaded them from numba's cache (a cold or a warm cache), and a run resumed from a
checkpoint at any step ends where the uninterrupted one does, bit for bit, over both
neighbour-list paths of mixed precision: the cluster list searched at cutoff + skin
(500 atoms) and the outer list pruned between searches (864 atoms), and over the cluster
kernel's threaded form (2048 atoms of two types in two chunks on two threads).

Before the pair frame's variants held their entry point's code (``potentials/
_pair_kernels.py``, the note above the atom-order kernels), a process that compiled
the cluster kernel ran the entry point's own code and a process that loaded it from
the cache ran the variant's linked copy, which rounded differently in float32: a cold
run left a warm one at step ~20 (1e-8 at step 40), and a run resumed in a new process
left the uninterrupted run that had compiled its kernels. Before the cluster kernel's
float32 code took none of LLVM's value-changing freedoms (``potentials._cluster_ir._FLAGS``),
the threaded form, whose ``prange`` body numba compiles as a function of its own and links
into the kernel as a copy optimised again, did the same: forces 1.3e-5 apart from one call
(2048 atoms, two threads), the runs 1.8e-8 apart after 40 steps; with it on the pair
term, forces 4.8e-7 apart where the atoms have two types.
"""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

import md
from potentials import LennardJones

EPS32 = float(np.finfo(np.float32).eps)

#: A child process: each case's uninterrupted run (thermo every 10 steps, so both virial
#: variants run) and its checkpoints every 5 steps; with "resume", each checkpoint
#: restored into a new simulation and run to the end. Writes the ends to an npz.
CHILD = """
import sys
import numpy as np
import md
from integrators import VelocityVerlet
from md.checkpoint import read_checkpoint, restore, write_checkpoint
from md.parallel import set_threads
from potentials import LennardJones

folder, resume = sys.argv[1], sys.argv[2] == "resume"
STEPS, EVERY = 40, 5
CASES = {"clusters": (5, 1, 1), "outer": (6, 1, 1), "threaded": (8, 2, 2)}  # cells, threads, types

def build(state):
    types = int(state.types.max()) + 1
    lj = LennardJones(epsilon=[1.0, 0.8][:types], sigma=[1.0, 0.9][:types], cutoff=2.5,
                      cutoff_mode="smooth", r_on=2.0)
    sim = md.Simulation(state, [lj], VelocityVerlet(dt=0.005), precision="mixed")
    sim.attach(lambda s: s.thermo(), 10)
    return sim

ends = {}
for name, (cells, threads, types) in CASES.items():
    set_threads(threads)
    state = md.build.maxwell_boltzmann(md.lattice("fcc", cells, density=0.8442), 1.5, seed=7)
    state.types[:] = np.arange(state.n_atoms) % types
    state.type_names = ("A", "B")[:types]
    sim = build(state)
    for step in range(0, STEPS, EVERY):
        sim.run(EVERY)
        if step + EVERY < STEPS:
            write_checkpoint(f"{folder}/{name}{step + EVERY}.ckpt", sim.state, sim.integrator,
                             sim.forcefield)
    ends[name] = sim.state.positions.copy()
    ends[name + "_prunes"] = np.array(sim.forcefield.neighbor_list.n_prunes)
    ends[name + "_chunks"] = np.array(len(sim.forcefield.neighbor_list.clusters.bounds) - 1)
    if resume:
        for cut in range(EVERY, STEPS, EVERY):
            saved = read_checkpoint(f"{folder}/{name}{cut}.ckpt")
            again = build(saved.state)
            restore(saved, again.integrator, again.forcefield)
            again.run(STEPS - cut)
            ends[f"{name}_from{cut}"] = again.state.positions.copy()
np.savez(f"{folder}/{'warm' if resume else 'cold'}.npz", **ends)
"""


def _cold_and_warm(tmp_path, child: str):
    """Run ``child`` in a cache folder of its own: the first run compiles every kernel,
    the second ("resume") loads them; returns both runs' ends."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"), XDG_CACHE_HOME=str(tmp_path))
    for mode in ("cold", "resume"):
        done = subprocess.run(
            [sys.executable, "-c", child, str(tmp_path), mode],
            env=env,
            capture_output=True,
            text=True,
            timeout=900,
        )
        assert done.returncode == 0, done.stderr[-3000:]
    return np.load(tmp_path / "cold.npz"), np.load(tmp_path / "warm.npz")


@pytest.mark.skipif(os.environ.get("NUMBA_DISABLE_JIT") == "1", reason="compiles kernels")
def test_mixed_runs_equal_cold_and_warm_and_resume_at_every_checkpoint(tmp_path):
    cold, warm = _cold_and_warm(tmp_path, CHILD)
    assert list((tmp_path / "numba").rglob("*.nbi")), "the first child compiled nothing"
    assert cold["clusters_prunes"] == 0 < cold["outer_prunes"]  # the two list paths
    assert cold["threaded_chunks"] > 1 == cold["clusters_chunks"]  # and the kernel's two forms
    for name in ("clusters", "outer", "threaded"):
        assert np.array_equal(cold[name], warm[name]), f"{name}: a warm cache changes the run"
        for cut in range(5, 40, 5):
            resumed = warm[f"{name}_from{cut}"]
            assert np.array_equal(resumed, cold[name]), (
                f"{name} resumed at step {cut}: {np.abs(resumed - cold[name]).max():.3g} away"
            )


def _relative_energy_error(state) -> float:
    energies = {
        precision: md.ForceField([LennardJones(cutoff=2.5)], precision=precision)
        .compute(state)
        .energy
        for precision in ("double", "mixed")
    }
    return abs(energies["mixed"] - energies["double"]) / abs(energies["double"])


def test_mixed_energy_error_averages_out_on_a_liquid_not_on_a_lattice(fcc_lattice):
    """On a liquid the pair terms' float32 rounding errors are independent and mostly
    cancel in the double sum (~1e-9 relative); on a perfect lattice every pair of one
    shell rounds the same way, so the sum keeps float32's own precision (~1e-7): what
    docs/guide/performance.md says."""
    lattice = _relative_energy_error(fcc_lattice(cells=6))
    disordered = [_relative_energy_error(fcc_lattice(cells=6, perturbation=0.05)) for _ in range(3)]
    assert 0.1 * EPS32 < lattice < 3 * EPS32, lattice
    assert max(disordered) < 0.1 * EPS32, disordered
    assert lattice > 10 * np.median(disordered), (lattice, disordered)
