"""md validate ase: ASE's velocity Verlet (with MDCalculator) against ours, step for step."""

from __future__ import annotations

import ase.units
import numpy as np
import pytest

from md import units
from md.cli import main
from md.validate import compare_trajectories, validate_ase


@pytest.fixture(scope="module")
def report():
    # >= 500 steps of the main comparison; a short ladder of time steps.
    return validate_ase(
        n_atoms=256,
        n_steps=500,
        dt_fs=5.0,
        temperature=100.0,
        seed=7,
        ladder_dts=(2.0, 4.0, 8.0),
        ladder_span_fs=400.0,
        n_equilibrate=200,
    )


def test_time_units_are_ase_units_exactly():
    assert units.fs == ase.units.fs  # bit for bit: dt converts identically on both sides


def test_trajectories_agree_to_amplified_round_off(report):
    main_run = report.main
    assert main_run.n_steps == 500
    # Same operation order reproduces ASE bit for bit, at every step of every run ...
    assert main_run.replay_identical
    assert all(run.replay_identical for run in report.ladder)
    # ... so the rest is rounding (about 1e-16 per step) grown by chaos over 2.5 ps.
    assert main_run.position_differences[0] == 0.0
    assert 0.0 < main_run.max_position_difference < 1e-9  # Angstrom
    assert main_run.relative_momentum_difference < 1e-8
    # The difference grows exponentially, at a Lyapunov-like rate of order 1/ps.
    assert 0.2 < main_run.growth_rate < 20.0


def test_energy_behaviour_matches(report):
    main_run = report.main
    ase_run, ours = main_run.ase, main_run.ours
    assert ours.fluctuation == pytest.approx(ase_run.fluctuation, rel=1e-4)
    span_ps = main_run.n_steps * main_run.dt_fs / 1000.0
    assert abs(ours.drift - ase_run.drift) * span_ps < 1e-4 * ours.fluctuation
    assert ours.fluctuation < 1e-5  # eV/atom: velocity Verlet holds the energy
    assert report.passed


def test_fluctuation_is_second_order_in_dt(report):
    fluctuations = np.array([run.ours.fluctuation for run in report.ladder])
    dts = np.array([run.dt_fs for run in report.ladder])
    order = np.polyfit(np.log(dts), np.log(fluctuations), 1)[0]
    assert order == pytest.approx(2.0, abs=0.25)
    ase_fluctuations = [run.ase.fluctuation for run in report.ladder]
    np.testing.assert_allclose(ase_fluctuations, fluctuations, rtol=1e-3)


def test_temperatures_state_both_conventions(report):
    assert report.temperature == pytest.approx(100.0, rel=1e-12)  # 3N - 3, ours
    n = report.n_atoms
    assert report.temperature_ase == pytest.approx(100.0 * (3 * n - 3) / (3 * n), rel=1e-12)


def test_comparison_leaves_the_state_alone():
    from md.validate import argon_liquid

    state, potential = argon_liquid(n_atoms=108, n_equilibrate=0, seed=1)
    before = state.copy()
    run = compare_trajectories(state, potential, dt_fs=5.0, n_steps=20)
    assert run.replay_identical
    np.testing.assert_array_equal(state.positions, before.positions)
    np.testing.assert_array_equal(state.velocities, before.velocities)


def test_cli_prints_the_report(capsys):
    args = ["validate", "ase", "--atoms", "108", "--steps", "30", "--ladder", "2,4"]
    assert main([*args, "--ladder-time", "40"]) == 0
    out = capsys.readouterr().out
    assert "max |x_ase - x_ours|" in out and "ASE order replayed bitwise  yes" in out
    assert "3N-3" in out and "PASSED" in out
    assert len([line for line in out.splitlines() if line.strip().startswith(("2 ", "4 "))]) == 2


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--atoms", "0"], "n_atoms"),
        (["--steps", "-3"], "n_steps"),
        (["--dt", "0"], "dt_fs"),
        (["--ladder", "1,x"], "--ladder"),
        (["--ladder", "5", "--ladder-time", "2"], "ladder"),
    ],
)
def test_cli_bad_arguments_exit_2(capsys, arguments, message):
    assert main(["validate", "ase", *arguments]) == 2
    err = capsys.readouterr().err
    assert err.startswith("md: error:") and message in err and len(err.splitlines()) == 1


@pytest.mark.parametrize("potential", ["morse", "buckingham"])
def test_cli_validates_other_pair_styles(capsys, potential):
    """ASE's VelocityVerlet with MDCalculator follows ours step for step with the new pair
    styles too (ASE's operation order replayed bitwise, equal energy behaviour)."""
    args = ["validate", "ase", "--atoms", "108", "--steps", "30", "--ladder", "4"]
    assert main([*args, "--ladder-time", "40", "--potential", potential]) == 0
    out = capsys.readouterr().out
    assert f"argon-like atoms ({potential}:" in out
    assert "ASE order replayed bitwise  yes" in out and "PASSED" in out
