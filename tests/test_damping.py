"""Numerical damping measured on a harmonic bond against each method's amplification factor."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest

from integrators import INTEGRATORS
from md.forcefield import ForceField
from md.studies.damping import (
    DAMPING_COLUMNS,
    OMEGA_DT,
    bond_oscillator,
    measure_damping,
    plot_damping,
    write_damping_csv,
)

IMPLICIT = ("implicit_euler", "implicit_midpoint", "trapezoidal", "bdf2", "gauss_legendre4", "xpbd")


def factory(name, tol=1e-11):
    cls = INTEGRATORS[name]
    return (lambda dt: cls(dt)) if name == "verlet" else (lambda dt: cls(dt, tol=tol))


# ------------------------------------------------------------------------ theory


@pytest.mark.parametrize("z", [0.01, 0.3, 1.0, 5.0, 100.0])
def test_amplification_factors_are_the_known_closed_forms(z):
    """Each method's principal root against its closed form, and its roots solve the
    method's recurrence (checked on the explicit one-step maps of the oscillator)."""
    modulus = {name: abs(INTEGRATORS[name].amplification(z)[0]) for name in (*IMPLICIT, "verlet")}
    assert modulus["implicit_euler"] == pytest.approx(1.0 / math.sqrt(1.0 + z * z), rel=1e-12)
    assert modulus["xpbd"] == modulus["implicit_euler"]
    for name in ("implicit_midpoint", "trapezoidal", "gauss_legendre4"):
        assert modulus[name] == pytest.approx(1.0, abs=1e-12), name
    assert modulus["verlet"] == pytest.approx(1.0, abs=1e-12) if z <= 2 else modulus["verlet"] > 1
    # The one-step maps (x, v) -> (x1, v1) of the oscillator x'' = -omega^2 x, dt = 1:
    w2 = z * z
    maps = {
        "implicit_euler": np.linalg.inv([[1.0, -1.0], [w2, 1.0]]),
        "implicit_midpoint": np.linalg.solve(
            [[1.0, -0.5], [0.5 * w2, 1.0]], [[1.0, 0.5], [-0.5 * w2, 1.0]]
        ),
        "verlet": np.array([[1.0 - 0.5 * w2, 1.0], [-w2 * (1.0 - 0.25 * w2), 1.0 - 0.5 * w2]]),
    }
    for name, step_map in maps.items():
        eigenvalues = np.linalg.eigvals(step_map)
        roots = INTEGRATORS[name].amplification(z)

        def ordered(values):
            return sorted(values, key=lambda c: (round(c.imag, 9), c.real))

        assert ordered(eigenvalues) == pytest.approx(ordered(roots), rel=1e-12, abs=1e-12)
    # BDF2's principal root: 1 - z^4/4 + O(z^6) for small z, and it is the larger pair.
    roots = INTEGRATORS["bdf2"].amplification(z)
    assert len(roots) == 4 and abs(roots[0]) >= abs(roots[2])
    if z <= 0.01:
        assert abs(roots[0]) == pytest.approx(1.0 - z**4 / 4.0, abs=z**6)  # next: +0.62 z^6
    # Gauss-Legendre's phase error is O(z^5) per step: the (2, 2) Pade approximant.
    if z <= 0.3:
        phase = np.angle(INTEGRATORS["gauss_legendre4"].amplification(z)[0])
        assert abs(phase - z) < z**5 / 100


# ------------------------------------------------------------------- measurement


@pytest.fixture(scope="module")
def rows():
    return measure_damping({name: factory(name) for name in ("verlet", *IMPLICIT)})


def test_measured_damping_is_within_5_percent_of_theory_across_the_ladder(rows):
    """The amplitude ratio per step measured on the bond, every method and omega dt
    from 0.01 to 100: the damping per step 1 - |rho| within 5% of theory (or 1e-9
    absolute, where theory says none), and the phase per step within 1e-6."""
    by_method = {}
    for row in rows:
        by_method.setdefault(row.integrator, []).append(row)
        if row.integrator == "verlet" and row.omega_dt > 2.0:
            assert math.isnan(row.measured) and "unstable" in row.note
            continue
        assert row.note == "", (row.integrator, row.omega_dt, row.note)
        assert abs(row.damping_measured - row.damping_theory) <= (
            0.05 * abs(row.damping_theory) + 1e-9
        ), (row.integrator, row.omega_dt, row.measured, row.theory)
        assert row.phase_measured == pytest.approx(row.phase_theory, abs=1e-6)
    assert {name: len(r) for name, r in by_method.items()} == {
        name: len(OMEGA_DT) for name in ("verlet", *IMPLICIT)
    }
    # What the figure shows: at omega dt = 100, implicit Euler keeps 1% of the amplitude
    # per step, BDF2 8%, the non-damping methods all of it.
    at_100 = {r.integrator: r.measured for r in rows if r.omega_dt == 100.0}
    assert at_100["implicit_euler"] == pytest.approx(0.0099995, rel=1e-4)
    assert at_100["bdf2"] == pytest.approx(0.0781, rel=1e-3)
    for name in ("implicit_midpoint", "trapezoidal", "gauss_legendre4"):
        assert at_100[name] == pytest.approx(1.0, abs=1e-9)


def test_measurement_sees_a_method_that_is_not_the_theory(rows):
    """Control: a measurement that could only return the theory would be worthless. The
    trapezoidal rule measured against implicit Euler's theory fails the 5% test."""
    trapezoidal = {r.omega_dt: r.measured for r in rows if r.integrator == "trapezoidal"}
    euler = {r.omega_dt: r.theory for r in rows if r.integrator == "implicit_euler"}
    assert abs(trapezoidal[1.0] - euler[1.0]) > 0.05 * (1.0 - euler[1.0])


def test_bond_oscillator_has_the_requested_frequency():
    state, potentials = bond_oscillator(7.0, mass=2.0)
    forcefield = ForceField(potentials)
    hessian = forcefield.hessian_operator(state).tocsr().toarray()
    masses = np.repeat(state.masses, 3)
    frequencies = np.sqrt(np.abs(np.linalg.eigvalsh(hessian / np.sqrt(np.outer(masses, masses)))))
    assert frequencies.max() == pytest.approx(7.0, rel=1e-12)


def test_loose_solver_tolerance_shows_in_the_measurement():
    """The measurement measures what runs: implicit Euler solved to tol 1e-3 misses the
    theory's damping at omega dt = 0.01 by ~1e-6 (2%; the solve stops early), a
    thousand times more than at tol 1e-11."""
    z = (0.01,)
    tight = measure_damping({"implicit_euler": factory("implicit_euler", 1e-11)}, z)[0]
    loose = measure_damping({"implicit_euler": factory("implicit_euler", 1e-3)}, z)[0]
    tight_error = abs(tight.damping_measured - tight.damping_theory)
    assert tight_error < 1e-9
    assert abs(loose.damping_measured - loose.damping_theory) > max(1e-7, 100 * tight_error)


def test_csv_and_figure(tmp_path, rows):
    write_damping_csv(rows, tmp_path / "damping.csv")
    with open(tmp_path / "damping.csv", newline="") as handle:
        table = list(csv.DictReader(handle))
    assert tuple(table[0]) == DAMPING_COLUMNS
    assert len(table) == len(rows)
    first = table[0]
    assert float(first["theory"]) == pytest.approx(rows[0].theory)
    with pytest.raises(FileExistsError):  # never replaces a file
        write_damping_csv(rows, tmp_path / "damping.csv")
    plot_damping(rows, {n: INTEGRATORS[n] for n in ("verlet", *IMPLICIT)}, tmp_path / "d.png")
    assert (tmp_path / "d.png").stat().st_size > 10_000


# ---------------------------------------------------------------------------- CLI


@pytest.fixture
def config(tmp_path):
    from conftest import lj_config_text

    path = tmp_path / "lj.toml"
    path.write_text(lj_config_text(run=None, output=None))
    return path


def test_cli_damping_writes_csv_figure_and_table(tmp_path, config, capsys):
    from md.cli import main

    out = tmp_path / "out"
    argv = [
        "integrators",
        str(config),
        "--damping",
        "--integrators",
        "implicit_euler,bdf2",
        "--omega-dt",
        "0.1,10",
        "--out",
        str(out),
    ]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "implicit_euler" in printed and "damping.csv" in printed
    with open(out / "damping.csv", newline="") as handle:
        table = list(csv.DictReader(handle))
    assert [(r["integrator"], float(r["omega_dt"])) for r in table] == [
        ("implicit_euler", 0.1),
        ("implicit_euler", 10.0),
        ("bdf2", 0.1),
        ("bdf2", 10.0),
    ]
    assert float(table[1]["measured"]) == pytest.approx(1 / math.sqrt(101), rel=1e-9)
    assert (out / "damping.png").stat().st_size > 10_000
    # Existing files: refused without --overwrite, untouched.
    before = (out / "damping.csv").read_bytes()
    assert main(argv) == 2
    assert "exist" in capsys.readouterr().err
    assert (out / "damping.csv").read_bytes() == before
    assert main([*argv, "--overwrite"]) == 0


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--integrators", "nope"], "unknown nope"),
        (["--integrators", "langevin"], "deterministic fixed-step"),
        (["--omega-dt", "0:1:3"], "positive"),
        (["--omega-dt", "a,b"], "MIN:MAX:N"),
    ],
)
def test_cli_damping_bad_input_exits_2_and_writes_nothing(tmp_path, config, capsys, extra, message):
    from md.cli import main

    out = tmp_path / "out"
    assert main(["integrators", str(config), "--damping", "--out", str(out), *extra]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()
