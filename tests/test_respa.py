"""Reversible RESPA: velocity Verlet at inner_steps = 1, order, reversibility, resonance, input."""

from __future__ import annotations

import numpy as np
import pytest

import md
from integrators import RESPA, VelocityVerlet, Yoshida6
from md.cli import main
from md.polymers import polymer_melt, single_chain
from potentials import FENEBonds, HarmonicBonds, LennardJones


def _melt():
    state, bonds = polymer_melt(6, 10, density=0.85, bond_length=0.97, seed=2)
    md.maxwell_boltzmann(state, 1.0, seed=1)
    return state, [LennardJones(cutoff=2 ** (1 / 6)), FENEBonds(bonds, k=30, r_max=1.5)]


def _chain(k=1e4, cutoff=2.5):
    """One chain in vacuum: LJ between all beads (slow), stiff harmonic bonds (fast)."""
    state, bonds = single_chain(20, bond_length=1.0, seed=3, pbc=False)
    md.maxwell_boltzmann(state, 0.5, seed=1)
    return state, [LennardJones(cutoff=cutoff), HarmonicBonds(bonds, k=k, r0=1.0)]


def _energy_error(integrator, make, span):
    state, potentials = make()
    sim = md.Simulation(state, potentials, integrator, skin=0.5)
    energies = []
    sim.attach(lambda s: energies.append(s.thermo()["total_energy"]), 1)
    try:
        sim.run(round(span / integrator.dt))
    except md.SimulationError:
        return np.inf
    energies = np.array(energies)
    return float(np.abs(energies - energies[0]).max()) / state.n_atoms


def test_inner_steps_1_is_velocity_verlet_bit_for_bit():
    (a, pa), (b, pb) = _melt(), _melt()
    md.Simulation(a, pa, RESPA(0.003, inner_steps=1), skin=0.3).run(300)
    md.Simulation(b, pb, VelocityVerlet(0.003), skin=0.3).run(300)
    assert np.array_equal(a.positions, b.positions)
    assert np.array_equal(a.velocities, b.velocities)


def test_second_order_in_the_outer_step():
    """Fixed inner_steps: halving dt quarters the error (a reference by Yoshida 6).

    The LJ cutoff is longer than the chain, so no pair crosses it (analytic forces).
    """

    def final(integrator):
        state, potentials = _chain(k=500.0, cutoff=40.0)
        md.Simulation(state, potentials, integrator, skin=0.5).run(round(0.4 / integrator.dt))
        return state.positions

    reference = final(Yoshida6(0.4 / 4096))
    dts = 0.4 / np.array([80, 160, 320])  # local slopes 2.02, 2.005 here (2.38 at 0.4/20)
    errors = [
        np.sqrt(np.mean(np.sum((final(RESPA(dt, 4)) - reference) ** 2, axis=1))) for dt in dts
    ]
    assert np.polyfit(np.log(dts), np.log(errors), 1)[0] == pytest.approx(2.0, abs=0.15)


def test_time_reversible():
    state, potentials = _chain()
    start = state.positions.copy(), state.velocities.copy()
    sim = md.Simulation(state, potentials, RESPA(0.005, inner_steps=10), skin=0.5)
    sim.run(200)
    state.velocities *= -1.0
    sim.run(200)
    state.velocities *= -1.0
    assert np.abs(state.positions - start[0]).max() < 1e-10
    assert np.abs(state.velocities - start[1]).max() < 1e-8


def test_fast_forces_at_the_inner_step_keep_stiff_bonds_stable():
    """Stiff bonds (period 0.044): VV at dt = 0.014 blows up; RESPA at 0.014, 20 substeps, holds."""
    assert _energy_error(VelocityVerlet(0.014), _chain, 2.0) > 1e3
    assert _energy_error(RESPA(0.014, inner_steps=20), _chain, 2.0) < 0.1
    # at dt = 0.01 both hold, RESPA with a 20x smaller energy error
    assert _energy_error(RESPA(0.01, 20), _chain, 2.0) < 0.1 * _energy_error(
        VelocityVerlet(0.01), _chain, 2.0
    )
    # and costs one slow force per outer step
    state, potentials = _chain()
    sim = md.Simulation(state, potentials, RESPA(0.01, inner_steps=20), skin=0.5)
    before = sim.forcefield.n_subset_evaluations
    sim.run(10)
    # per step one slow and 20 fast (the last step's end serves the next's start), plus
    # the first step's start
    assert sim.forcefield.n_subset_evaluations - before == 10 * (1 + 20) + 2


def test_resonance_near_half_the_bond_period():
    """However fine the inner step, an outer step near half the bond period blows up."""
    period = 2 * np.pi * np.sqrt(0.5 / 1e4)
    below = _energy_error(RESPA(0.3 * period, inner_steps=round(0.3 * period / 5e-4)), _chain, 5.0)
    at = _energy_error(RESPA(0.5 * period, inner_steps=round(0.5 * period / 5e-4)), _chain, 5.0)
    assert below < 0.1
    assert at > 100 * below


def test_fast_potentials_by_index_and_refusals():
    state, potentials = _melt()
    forcefield = md.ForceField(potentials)
    assert RESPA(0.005, 2).split(forcefield) == ((1,), (0,))
    assert RESPA(0.005, 2, fast=[0]).split(forcefield) == ((0,), (1,))
    with pytest.raises(ValueError, match="every potential is fast"):
        RESPA(0.005, 2, fast=[0, 1]).split(forcefield)
    with pytest.raises(ValueError, match="only 2"):
        RESPA(0.005, 2, fast=[5]).split(forcefield)
    with pytest.raises(ValueError, match="no fast potential"):
        RESPA(0.005, 2).split(md.ForceField([LennardJones()]))
    with pytest.raises(ValueError, match="inner_steps must be an integer >= 1"):
        RESPA(0.005, 0)
    with pytest.raises(ValueError, match='fast must be "bonded"'):
        RESPA(0.005, 2, fast="slow")


RUN = """
units = "lj"
seed = 7
[system]
polymer = "melt"
chains = 4
chain_length = 10
density = 0.85
bond_length = 0.97
temperature = 1.0
[[potentials]]
type = "lj"
cutoff = 1.122462048309373
{fene}
[integrator]
type = "{kind}"
dt = 0.004
{extra}
[run]
steps = 20
[output]
path = "out.h5"
every = 10
"""
FENE = '[[potentials]]\ntype = "fene"\nbonds = "system"\nk = 30.0\nr_max = 1.5'


@pytest.mark.parametrize(
    ("kind", "extra", "fene", "message"),
    [
        ("respa", "inner_steps = 0", FENE, "inner_steps must be an integer >= 1"),
        ("respa", "inner_steps = 2", "", "no fast potential"),
        ("respa", 'inner_steps = 2\nfast = "everything"', FENE, 'fast must be "bonded"'),
        ("warp", "", FENE, "[integrator] type: must be one of"),
    ],
)
def test_bad_integrator_input_exits_2_and_writes_nothing(
    tmp_path, monkeypatch, capsys, kind, extra, fene, message
):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "run.toml").write_text(RUN.format(kind=kind, extra=extra, fene=fene))
    assert main(["run", "run.toml", "--no-progress", "-q"]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out.h5").exists()


def test_respa_runs_from_a_config(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "run.toml").write_text(RUN.format(kind="respa", extra="inner_steps = 4", fene=FENE))
    assert main(["run", "run.toml", "--no-progress", "-q"]) == 0
