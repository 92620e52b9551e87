"""The neighbour list looked at every N steps (LAMMPS's ``neigh_modify every N check
yes/no``, GROMACS's ``nstlist``): when it rebuilds, that it really misses the pairs it
says it may miss (and the exact default does not), that a resume continues it bit for
bit, and the inputs it refuses."""

from __future__ import annotations

import numpy as np
import pytest

import md
from conftest import assert_same_end, lj_config_text, resumed_run
from integrators import VelocityVerlet
from md.checkpoint import read_checkpoint, write_checkpoint
from md.cli import main
from md.minimize import minimize
from md.neighbors import NeighborList
from md.trajectory import read_trajectory
from potentials import LennardJones


def _melt(precision="double", every=1, check=True, cells=6, seed=3, state=None):
    """The LJ melt's simulation with the list rule (``state``: start from it)."""
    if state is None:
        state = md.maxwell_boltzmann(md.lattice("fcc", cells, density=0.8442), 1.5, seed=seed)
    return md.Simulation(
        state,
        [LennardJones(cutoff=2.5)],
        VelocityVerlet(dt=0.005),
        precision=precision,
        neighbor_every=every,
        neighbor_check=check,
    )


def _build_steps(sim, steps):
    """The state.step at each evaluation that rebuilt the list, over ``steps`` steps (the
    first build, at step 0, before them)."""
    sim.forcefield.compute(sim.state)
    nl, found = sim.forcefield.neighbor_list, []
    for _ in range(steps):
        builds = nl.n_builds
        sim.run(1)
        if nl.n_builds > builds:
            found.append(nl.built_step)
    return found


@pytest.mark.parametrize("precision", ["double", "mixed"])
def test_every_n_without_check_rebuilds_every_n_steps_and_never_between(precision):
    """``every=10, check=False``: a build at each evaluation ten steps after the last
    one (state.step 10, 20, ...), none between, however far the atoms went; the cluster
    list then has no outer list to prune (its prunes serve the exact rule)."""
    sim = _melt(precision, every=10, check=False)
    nl = sim.forcefield.neighbor_list
    assert not nl.exact
    assert _build_steps(sim, 45) == [10, 20, 30, 40]
    if precision == "mixed":
        assert nl.clusters is not None and nl.outer_clusters is None and nl.n_prunes == 0
    # the exact default rebuilds (or prunes its outer list) at its own pace, on displacement
    exact = _melt(precision)
    enl = exact.forcefield.neighbor_list
    assert enl.exact
    assert _build_steps(exact, 45) != [10, 20, 30, 40] and enl.n_builds + enl.n_prunes >= 3


def test_every_n_with_check_rebuilds_only_at_looks_where_an_atom_moved_half_the_skin():
    """``every=4`` with the check: a rebuild only at looks (4 or more steps after the
    build) where an atom moved more than skin/2 since it, checked against the positions."""
    sim = _melt(every=4, check=True)
    sim.forcefield.compute(sim.state)  # the first build, at step 0
    nl = sim.forcefield.neighbor_list
    last = 0
    for _ in range(60):
        reference = nl.reference_positions
        step, builds = sim.state.step, nl.n_builds
        sim.run(1)
        if nl.n_builds > builds:
            assert step - last >= 4
            moved = np.sqrt(((sim.state.positions - reference) ** 2).sum(axis=1)).max()
            assert moved > 0.5 * nl.skin
            last = step
    assert last > 0


def test_a_pair_that_comes_within_the_cutoff_between_looks_is_missed_until_the_next():
    """Two atoms that start 3.0 apart (outside cutoff 2.5 + skin 0.3) and close in: the
    exact list finds them within the cutoff at once; the list looked at every 50 steps
    keeps them out (no force) until its next look, then has them."""
    state = md.State(positions=[[5.0, 5.0, 5.0], [8.0, 5.0, 5.0]], box=20.0)
    state.velocities[:] = [[2.0, 0.0, 0.0], [-2.0, 0.0, 0.0]]

    def run(every, check):
        sim = md.Simulation(
            state.copy(),
            [LennardJones(cutoff=2.5)],
            VelocityVerlet(0.005),
            neighbor_every=every,
            neighbor_check=check,
        )
        forces = []
        for _ in range(60):
            sim.run(1)
            gap = sim.state.positions[1, 0] - sim.state.positions[0, 0]
            forces.append((gap, sim.forcefield.compute(sim.state).forces[0, 0]))
        return forces

    exact, lazy = run(1, True), run(50, False)
    inside = [k for k, (gap, _) in enumerate(exact) if gap < 2.5]
    assert inside and inside[0] < 49
    for k in range(inside[0], 49):  # within the cutoff, before the next look
        assert exact[k][1] != 0.0 and lazy[k][1] == 0.0, k
    later = [k for k in range(50, 60) if lazy[k][0] < 2.5]  # after the look at step 50
    assert later and all(lazy[k][1] != 0.0 for k in later), lazy[48:]


@pytest.mark.parametrize(
    ("precision", "at"), [("double", 17), ("mixed", 17), ("double", 21), ("mixed", 21)]
)
def test_a_checkpoint_resumes_an_every_n_list_bit_for_bit(tmp_path, precision, at):
    """The checkpoint keeps the step of the last build, from which ``every`` counts: a
    resume rebuilds on the same steps, so the trajectory is the same bits, also from step
    21, where the next look is the first step's (the resume evaluates the checkpoint's
    positions again at its step, which the run had evaluated within the step before: not
    a look); resumed without it (as from an older checkpoint) the run departs."""
    whole = _melt(precision, every=7, check=False)
    whole.run(40)
    first = _melt(precision, every=7, check=False)
    first.run(at)
    path = write_checkpoint(tmp_path / "ckpt.npz", first.state, first.integrator, first.forcefield)
    saved = read_checkpoint(path)
    assert saved.neighbor_step == first.forcefield.neighbor_list.built_step == 14

    def resumed(checkpoint):
        return resumed_run(
            checkpoint, lambda state: _melt(precision, every=7, check=False, state=state), 40 - at
        )

    assert_same_end(resumed(saved), whole)
    older = read_checkpoint(path)
    older.neighbor_step = None
    assert not np.array_equal(resumed(older).state.positions, whole.state.positions)


def _run(*args) -> int:
    return main(["run", *map(str, args), "--no-progress", "-q"])


def test_md_run_takes_the_keys_and_a_minimize_stage_still_follows_every_move(tmp_path, monkeypatch):
    """``[run] neighbor_every``/``neighbor_check`` reach the run (builds every 10 steps);
    a ``[minimize]`` stage before it looks at the list at every evaluation (its steps are
    not the state's), and the run's fingerprint holds the rule."""
    monkeypatch.chdir(tmp_path)
    config = tmp_path / "run.toml"
    config.write_text(
        lj_config_text(
            cells=6,
            run="steps = 30\nthermo_every = 10\nneighbor_every = 10\nneighbor_check = false",
            output='path = "out.h5"\nevery = 10\ncheckpoint_every = 10',
        )
        + "\n[minimize]\nfmax = 5.0\nmax_steps = 200\n"
    )
    assert _run(config) == 0
    assert read_trajectory("out.h5").positions.shape[0] == 4
    saved = read_checkpoint(tmp_path / "out.h5.ckpt")
    assert saved.fingerprint["run"]["neighbor_every"] == 10
    assert saved.fingerprint["run"]["neighbor_check"] is False
    assert saved.neighbor_step is not None and saved.neighbor_step % 10 == 0


def test_minimising_with_an_every_n_list_is_refused_but_exactly_lets_it():
    sim = _melt(every=5)
    with pytest.raises(ValueError, match="every 5 step.*never be rebuilt"):
        minimize(sim.state, sim.forcefield, fmax=1.0, max_steps=5)
    nl = sim.forcefield.neighbor_list
    with nl.exactly():
        minimize(sim.state, sim.forcefield, fmax=1e3, max_steps=5)
    assert (nl.every, nl.check) == (5, True)


@pytest.mark.parametrize("every", [0, -3, 2.5, True, "10"])
def test_bad_every_is_refused(every):
    with pytest.raises(ValueError, match="'every' must be an integer >= 1"):
        NeighborList(2.5, 0.3, every=every)


def test_bad_check_is_refused_and_bad_keys_name_themselves(tmp_path, monkeypatch, capsys):
    with pytest.raises(ValueError, match="'check' must be True or False"):
        NeighborList(2.5, 0.3, check="no")
    monkeypatch.chdir(tmp_path)
    config = tmp_path / "run.toml"
    for bad, name in (
        ("neighbor_every = 0", "neighbor_every"),
        ('neighbor_check = "no"', "neighbor_check"),
    ):
        config.write_text(lj_config_text(run=f"steps = 10\n{bad}"))
        capsys.readouterr()
        assert _run(config) == 2
        assert name in capsys.readouterr().err
        assert not (tmp_path / "out.h5").exists()
