"""The integrator study: measured order, stability scan, energy figures, CLI outputs."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest

import md
from conftest import lj_config_text
from integrators import INTEGRATORS, VelocityVerlet
from md.cli import main
from md.studies import CSV_COLUMNS, WORK_PRECISION_COLUMNS, compare_integrators
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


@pytest.mark.slow  # keeps the default suite within its 10 minutes
def test_cli_writes_table_csv_and_plots(tmp_path, capsys):
    config = tmp_path / "study.toml"
    config.write_text(CONFIG)
    out = tmp_path / "study"
    args = [
        "integrators",
        str(config),
        "--integrators",
        "verlet",
        "--time",
        "0.2",
        "--dt-range",
        "0.001:0.004:3",
        "--out",
        str(out),
    ]
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "order" in text and "verlet" in text
    with open(out / "integrators.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert set(CSV_COLUMNS) <= set(rows[0])
    assert rows[0]["integrator"] == "verlet"
    assert abs(float(rows[0]["order"]) - 2.0) < 0.2
    for name in ("error_vs_dt.png", "energy_vs_time.png", "work_precision.png"):
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


# ------------------------------------------------------------------ honest orders
def _cluster():
    """32 atoms in an open box, every pair inside the cutoff: analytic forces along the path."""
    state = md.lattice("fcc", 2, density=0.9, pbc=False)
    return md.maxwell_boltzmann(state, 0.4, seed=5)


def _factory(cls):
    def build(dt, tol=None):
        return cls(dt=dt) if tol is None else cls(dt=dt, tol=tol)

    build.order, build.adaptive = cls.order, cls.adaptive
    return build


@pytest.fixture(scope="module")
def every_order():
    """The study over every registered NVE integrator (each class once) on the cluster."""
    classes = {}
    for name, cls in INTEGRATORS.items():
        plain = not (cls.thermostat or cls.requires_constraints or cls.splits_forces)
        if plain and cls not in classes.values():
            classes[name] = cls
    return compare_integrators(
        make_state=_cluster,
        potentials_factory=lambda: [LennardJones(cutoff=8.0)],
        integrators=classes,  # implicit ones solve to compare_integrators' solver_tol
        dts=[0.005 / 2**k for k in range(5)],
        span=0.5,
        reference=_factory(INTEGRATORS["yoshida6"]),
        reference_dt=0.005 / 2**5,  # half the finest step: yoshida6's error there is at round-off
        tolerances=(1e-6, 1e-7, 1e-8, 1e-9),
        max_doublings=0,
    )


def test_every_integrator_shows_its_order_within_0_15(every_order):
    assert len(every_order) >= 13
    for report in every_order:
        if report.order_vs == "tol":  # RKF45: the global error follows the tolerance
            assert report.order == pytest.approx(1.0, abs=0.15), report.name
            assert report.fit_points >= 3
            continue
        assert report.order == pytest.approx(report.expected_order, abs=0.15), (
            report.name,
            report.order,
            [(r.dt, r.error) for r in report.runs],
        )
        assert report.fit_points >= 3, report.name


def test_fits_drop_points_at_the_reference_floor(every_order):
    yoshida6 = next(r for r in every_order if r.name == "yoshida6")
    below = [r for r in yoshida6.runs if r.stable and r.error <= yoshida6.floor]
    assert below, "the finest Yoshida 6 runs reach the reference's floor"
    assert not any(r.in_fit for r in below)
    assert 1e-14 < yoshida6.floor < 1e-9


def test_the_window_stops_where_the_asymptotic_range_ends():
    """A synthetic ladder: second order, then saturating towards the stability limit."""
    from md.studies.integrator_study import RunRecord, _fit_order

    dts = [0.001, 0.002, 0.004, 0.008, 0.016]
    errors = [1e-6, 4e-6, 1.6e-5, 3e-5, 4e-5]
    runs = [RunRecord(dt=d, stable=True, error=e) for d, e in zip(dts, errors, strict=True)]
    slope, (low, high), n, note = _fit_order(dts, runs, floor=1e-9, slope_tolerance=0.15)
    assert slope == pytest.approx(2.0, abs=1e-9) and (low, high, n) == (0.001, 0.004, 3)
    assert [r.in_fit for r in runs] == [True, True, True, False, False]
    assert note == (
        "2 coarser point(s) (dt >= 0.008) beyond the asymptotic range (local slope 0.907): left out"
    )


def test_an_order_needs_three_points_in_the_asymptotic_range():
    """Two points give a slope whatever the errors do: no order from them, and the note
    says why (the AVX-512 run that fitted implicit midpoint at 3.54 from 2 points)."""
    from md.studies import fit_order

    dts = [0.00015625 * 2**k for k in range(6)]
    # Implicit midpoint as one machine measured it: the finest point under the trend.
    errors = [1.25e-07, 1.46e-06, 5.85e-06, 2.34e-05, 9.35e-05, 3.73e-04]
    slope, used, note = fit_order(dts, errors, floor=4.26e-13)
    assert slope == pytest.approx(2.0, abs=0.01) and used == [1, 2, 3, 4, 5]
    assert note.startswith("the finest 1 point(s) (dt <= 0.000156) depart from the trend")
    # Only two points above the reference's floor: no order.
    slope, used, note = fit_order(dts[:4], [1e-14, 2e-14, 4e-12, 6e-11], floor=1e-13)
    assert math.isnan(slope) and used == []
    assert note.startswith("no order: only 2 point(s) above the reference's error floor")
    assert "2 point(s) at dt <= 0.000313 below the reference's error floor 1.00e-13" in note
    # A round-off floor: the error stops falling at the fine end, and the rest disagree.
    errors = [3e-12, 2.9e-12, 3.2e-12, 4e-11, 2e-9, 9e-9]
    slope, used, note = fit_order(dts, errors, floor=1e-14)
    assert math.isnan(slope)
    assert note.startswith(
        "no order: round-off or solver-tolerance floor reached at dt = 0.000625; no 3 "
        "successive points agree"
    ), note
    # Saturation alone (slope ~0.2) is no convergence range, however long.
    slope, used, note = fit_order(dts, [0.10, 0.115, 0.13, 0.15, 0.17, 0.19], floor=0.0)
    assert math.isnan(slope) and note.startswith("no order: the error does not fall")


def test_work_precision_rows_for_every_run(every_order, tmp_path):
    from md.studies import plot_work_precision, write_work_precision_csv

    write_work_precision_csv(every_order, tmp_path / "wp.csv")
    with open(tmp_path / "wp.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert tuple(rows[0]) == WORK_PRECISION_COLUMNS
    assert len(rows) == sum(len(r.runs) for r in every_order)
    verlet = [row for row in rows if row["integrator"] == "verlet"]
    energy = [float(row["max_energy_error"]) for row in verlet]
    evals = [int(float(row["force_evaluations"])) for row in verlet]
    # finer steps: more force evaluations, smaller energy error (second order: ~4x per halving)
    assert evals == sorted(evals, reverse=True) and energy == sorted(energy)
    assert energy[-1] / energy[-2] == pytest.approx(4.0, rel=0.3)
    yoshida6 = next(r for r in every_order if r.name == "yoshida6")
    per_step = INTEGRATORS["yoshida6"](0.01).force_evaluations
    run = yoshida6.runs[-1]
    assert run.evaluations == pytest.approx(per_step * round(0.5 / run.dt), abs=1)
    plot_work_precision(every_order, tmp_path / "wp.png")
    assert (tmp_path / "wp.png").read_bytes().startswith(b"\x89PNG")
