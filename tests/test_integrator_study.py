"""The integrator study: measured order, stability scan, energy figures, CLI outputs."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest
from conftest import lj_config_text

import md
from integrators import VelocityVerlet
from md.cli import main
from md.integrator_study import CSV_COLUMNS, compare_integrators
from potentials import LennardJones

CONFIG = lj_config_text(
    seed=3, temperature=1.0, potential='cutoff_mode = "smooth"\nr_on = 2.0', run=None, output=None
)


@pytest.fixture
def liquid():
    state = md.maxwell_boltzmann(md.lattice("fcc", 3, density=0.8442), 1.0, seed=3)
    return state


def _potentials():
    return [LennardJones(cutoff=2.5, cutoff_mode="smooth", r_on=2.0)]


def test_velocity_verlet_measures_second_order(liquid):
    reports = compare_integrators(
        make_state=liquid.copy,
        potentials_factory=_potentials,
        integrators={"verlet": VelocityVerlet},
        dts=[0.001, 0.002, 0.004],
        span=0.2,
        reference_dt=0.000125,
        max_doublings=0,
    )
    (report,) = reports
    assert abs(report.order - 2.0) < 0.15
    errors = [r.error for r in report.runs]
    assert errors == sorted(errors)  # error grows with dt
    assert report.evals_per_time == pytest.approx(1 / 0.002, rel=0.01)  # one per step
    assert report.energy_fluctuation > 0 and math.isfinite(report.energy_drift)


def test_stability_scan_finds_the_blow_up(liquid):
    (report,) = compare_integrators(
        make_state=liquid.copy,
        potentials_factory=_potentials,
        integrators={"verlet": VelocityVerlet},
        dts=[0.005, 0.01],
        span=1.0,
        max_doublings=5,
    )
    unstable = [r for r in report.runs if not r.stable]
    assert unstable, "doubling dt from 0.01 up to 0.32 must eventually blow up"
    assert report.dt_max_stable < min(r.dt for r in unstable)
    assert 0.01 <= report.dt_max_stable <= 0.04  # LJ liquid: VV limit near dt ~ 0.02-0.03


def test_cli_writes_table_csv_and_plots(tmp_path, capsys):
    config = tmp_path / "study.toml"
    config.write_text(CONFIG)
    out = tmp_path / "study"
    args = ["integrators", str(config), "--integrators", "verlet", "--time", "0.2",
            "--dt-range", "0.001:0.004:3", "--out", str(out)]  # fmt: skip
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "order" in text and "verlet" in text
    with open(out / "integrators.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert set(CSV_COLUMNS) <= set(rows[0])
    assert rows[0]["integrator"] == "verlet"
    assert abs(float(rows[0]["order"]) - 2.0) < 0.2
    for name in ("error_vs_dt.png", "energy_vs_time.png"):
        data = (out / name).read_bytes()
        assert data.startswith(b"\x89PNG") and len(data) > 10_000
    # a second run refuses to replace the files
    before = (out / "integrators.csv").read_bytes()
    assert main(args) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert (out / "integrators.csv").read_bytes() == before


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--dt-range", "0.01"], "--dt-range"),
        (["--dt-range", "a:b:c"], "--dt-range"),
        (["--dt-range", "0.01,-0.02"], "--dt-range"),
        (["--integrators", "warp_drive"], "warp_drive"),
        (["--time", "-1"], "--time"),
    ],
)
def test_cli_bad_arguments_exit_2(tmp_path, capsys, extra, message):
    config = tmp_path / "study.toml"
    config.write_text(CONFIG)
    assert main(["integrators", str(config), "--out", str(tmp_path / "o"), *extra]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_energy_plot_values_are_finite(liquid):
    (report,) = compare_integrators(
        make_state=liquid.copy,
        potentials_factory=_potentials,
        integrators={"verlet": VelocityVerlet},
        dts=[0.002, 0.004],
        span=0.1,
        max_doublings=0,
    )
    for run in report.runs:
        assert np.all(np.isfinite(run.energies)) and run.times[-1] == pytest.approx(0.1)
