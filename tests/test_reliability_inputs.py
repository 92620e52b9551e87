"""Issue 65, items 2, 8 and 9: values beyond double precision, user pair terms, implicit tol.

Each bad input is refused before anything is written, with a message naming the key
(or the term) and the value; the force field refuses NaN forces and virials as it
refuses a NaN energy.
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from _configs import VERLET, fcc_run

import md
from integrators import INTEGRATORS
from md.errors import NonFiniteError
from md.forcefield import ForceField
from potentials import Buckingham, Morse, PairPotential, Soft, Table, Yukawa, pair_term
from potentials.base import ForceResult


def _table_file(folder) -> None:
    r = np.linspace(0.6, 2.3, 50)
    e = np.exp(-6.0 * (r - 1.1)) - 2.0 * np.exp(-3.0 * (r - 1.1))
    f = 6.0 * (np.exp(-6.0 * (r - 1.1)) - np.exp(-3.0 * (r - 1.1)))
    rows = "".join(f"{k + 1} {r[k]:.17g} {e[k]:.17g} {f[k]:.17g}\n" for k in range(len(r)))
    (folder / "pair.table").write_text("T\nN 50 R 0.6 2.3\n\n" + rows)


def _refused(tmp_path, monkeypatch, capsys, potential: str, integrator: str = VERLET) -> str:
    """Run the config through ``md run``: exit 2, nothing written; return stderr."""
    from md.cli import main

    monkeypatch.chdir(tmp_path)
    _table_file(tmp_path)
    config = tmp_path / "run.toml"
    config.write_text(fcc_run(potential, integrator))
    code = main(["run", str(config), "--no-progress", "-q"])
    error = capsys.readouterr().err
    assert code == 2, error
    assert not (tmp_path / "out.h5").exists() and not list(tmp_path.glob("out.h5*")), error
    return error


# ------------------------------------------------- item 2: finite energy, NaN forces
#: Before: the first four evaluated a finite start-up energy, wrote a frame and a
#: checkpoint and stopped at step 1 blaming dt (or, Buckingham's, blamed overlapping
#: atoms); d0 blamed overlapping atoms; the soft cutoff said "math domain error"; the
#: table's points said "the system is too large".
BEYOND = {
    "morse alpha": ('type = "morse"\nalpha = 1e308\ncutoff = 2.5', "alpha = 1e+308"),
    "yukawa kappa": ('type = "yukawa"\nkappa = 1e308\ncutoff = 2.5', "kappa = 1e+308"),
    "soft a": ('type = "soft"\na = 1e308\ncutoff = 1.0', "a = 1e+308"),
    "buckingham a": ('type = "buckingham"\na = 1e308\ncutoff = 2.5', "a = 1e+308"),
    "morse d0": ('type = "morse"\nd0 = 1e308\ncutoff = 2.5', "d0 = 1e+308"),
    "soft cutoff": ('type = "soft"\ncutoff = 1e308', "cutoff = 1e+308"),
    "table points": (
        'type = "table"\nfile = "pair.table"\nkeyword = "T"\npoints = 1000000000000',
        "points: must be at most 1000000, got 1000000000000",
    ),
}


@pytest.mark.parametrize("case", list(BEYOND))
def test_md_run_refuses_values_beyond_double_precision(case, tmp_path, monkeypatch, capsys):
    potential, named = BEYOND[case]
    error = _refused(tmp_path, monkeypatch, capsys, potential)
    assert "potentials.0" in error and named in error, error
    assert "overlapping" not in error and "domain" not in error and "too large" not in error


@pytest.mark.parametrize(
    ("build", "named", "said"),
    [
        (lambda: Morse(alpha=1e308), "alpha = 1e+308", "-u'(r) = nan"),
        (lambda: Yukawa(kappa=1e308), "kappa = 1e+308", "-u'(r) = nan"),
        (lambda: Soft(a=1e308), "a = 1e+308", "-u'(r) = inf"),
        (lambda: Buckingham(a=1e308), "a = 1e+308", "u = 8.2"),
        (lambda: Morse(d0=1e308), "d0 = 1e+308", "-u'(r) = -inf"),
        (lambda: Soft(cutoff=1e308), "cutoff = 1e+308", "overflow"),
    ],
)
def test_constructors_name_the_value_beyond_double_precision(build, named, said):
    with pytest.raises(ValueError, match="beyond what double precision") as caught:
        build()
    assert named in str(caught.value) and said in str(caught.value), caught.value


def test_large_values_that_keep_the_pair_finite_are_accepted():
    """The check refuses what breaks the arithmetic, not large values as such."""
    Morse(d0=1e100, alpha=1.0)
    Yukawa(kappa=1e150)  # zero at every listed distance, and finite
    Soft(a=1e100, cutoff=1.0)


def test_a_huge_table_is_refused_by_the_constructor(tmp_path):
    _table_file(tmp_path)
    with pytest.raises(ValueError, match=r"points must be an integer from 2 to 1000000.*10000000"):
        Table(tmp_path / "pair.table", "T", points=10**7)


class _Broken:
    """A potential with a finite energy and a NaN force or an infinite virial."""

    cutoff = None

    def __init__(self, what: str) -> None:
        self.what = what

    def check(self, state) -> None:
        pass

    def energy_forces(self, state, neighbors, per_atom=False, virial=True):
        forces = np.zeros((state.n_atoms, 3))
        total = np.zeros((3, 3))
        if self.what == "force":
            forces[2, 1] = np.nan
        else:
            total[0, 0] = np.inf
        return ForceResult(energy=-1.5, forces=forces, virial=total)


@pytest.mark.parametrize(
    ("what", "message"),
    [
        ("force", r"the force on atom 2 is \[0.0, nan, 0.0\].*potential energy \(-1.5\) is finite"),
        ("virial", r"the virial is \[\[inf, .*potential energy \(-1.5\) is finite"),
    ],
)
def test_forcefield_refuses_non_finite_forces_and_virial(what, message):
    """Before: compute returned them, and only the energy was checked."""
    state = md.lattice("fcc", 2, density=0.8)
    forcefield = ForceField([_Broken(what)])
    with pytest.raises(NonFiniteError, match=message):
        forcefield.compute(state)
    with pytest.raises(NonFiniteError, match=message):
        forcefield.compute_subset(state, [0], virial=True)


@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")
def test_forcefield_passes_finite_forces_whose_sum_overflows():
    """The check sums squares of forces and virial; a sum that overflows on finite values passes."""

    class Huge(_Broken):
        def energy_forces(self, state, neighbors, per_atom=False, virial=True):
            forces = np.full((state.n_atoms, 3), 1e200)
            return ForceResult(energy=0.0, forces=forces, virial=np.zeros((3, 3)))

    state = md.lattice("fcc", 2, density=0.8)
    assert ForceField([Huge("force")]).compute(state).forces[0, 0] == 1e200


# ------------------------------------------------------------ item 8: user pair terms
@pair_term
def returns_one(r2, epsilon):
    return epsilon / r2


@pair_term
def returns_three(r2, epsilon):
    return epsilon / r2, epsilon / (r2 * r2), 0.0


@pair_term
def returns_nan(r2, epsilon):
    return epsilon / r2, math.nan


@pair_term
def good_term(r2, epsilon):
    return epsilon / r2, 2.0 * epsilon / (r2 * r2)


def _plain_helper(x):  # not compiled: numba cannot call it from a kernel
    return 2.0 * x


@pair_term
def calls_python(r2, epsilon):
    return _plain_helper(epsilon) / r2, 2.0 * epsilon / (r2 * r2)


@pytest.mark.parametrize(
    ("term", "message"),
    [
        (
            returns_one,
            "pair term returns_one: returns_one(r2, epsilon) must return a tuple of two "
            "numbers (u, f_over_r), got 0.25",
        ),
        (
            returns_three,
            "pair term returns_three: returns_three(r2, epsilon) must return a tuple of "
            "two numbers (u, f_over_r), got 3 values (0.25, 0.0625, 0.0)",
        ),
    ],
)
def test_a_term_returning_the_wrong_count_is_named(term, message):
    """Before: a bare unpacking error (too many values / cannot unpack a float)."""
    with pytest.raises(TypeError) as caught:
        PairPotential(term, epsilon=1.0, cutoff=2.0)
    assert str(caught.value) == message


def test_a_term_returning_nan_is_blamed_not_its_parameters():
    """Before: "epsilon 1, cutoff 2 ... are beyond double precision"."""
    with pytest.raises(ValueError) as caught:
        PairPotential(returns_nan, epsilon=1.0, cutoff=2.0)
    text = str(caught.value)
    assert text.startswith("pair term returns_nan: with epsilon = 1, cutoff = 2"), text
    assert "-u'(r) = nan" in text and "must return two finite numbers (u, f_over_r" in text
    assert "beyond double precision" not in text


def test_a_curvature_returning_the_wrong_count_is_named():
    term = pair_term(lambda r2, epsilon: (epsilon / r2, 2.0 * epsilon / (r2 * r2)), name="inv")
    term.with_curvature(lambda r2, epsilon: (epsilon / r2, -epsilon / (r2 * r2)))
    message = "pair term inv: <lambda>(r2, epsilon) must return a tuple of three numbers "
    with pytest.raises(TypeError, match=re.escape(message + "(u, du_ds, d2u_ds2), got 2")):
        PairPotential(term, epsilon=1.0, cutoff=2.0)


@pytest.mark.parametrize("value", ["1.0", True, [1.0, False], np.array(["1"])])
def test_string_and_bool_parameters_are_refused(value):
    """Before: numpy took "1.0" and True as the numbers 1.0."""
    with pytest.raises(ValueError) as caught:
        PairPotential(good_term, epsilon=value, cutoff=2.0)
    text = str(caught.value)
    assert text.startswith("pair term good_term: epsilon must be a number, got "), text
    with pytest.raises(ValueError, match="d0 must be a number"):
        Morse(d0=value)


def test_numbas_typing_error_names_the_term():
    """Before: numba's raw TypingError, naming a kernel of the frame, not the term."""
    potential = PairPotential(calls_python, epsilon=1.0, cutoff=2.0)  # Python evaluates it
    state = md.lattice("fcc", 2, density=0.8)
    with pytest.raises(TypeError) as caught:
        potential.energy_forces(state, None)
    text = str(caught.value)
    assert text.startswith("pair term calls_python: numba cannot compile it"), text
    assert "_plain_helper" in text and "\x1b" not in text, text
    assert "calls_python(r2, epsilon) must be numba-compatible" in text
    assert "returns a tuple of two floats (u, f_over_r)" in text


# ------------------------------------------------------------------ item 9: implicit tol
IMPLICIT = ["implicit_euler", "implicit_midpoint", "trapezoidal", "bdf2", "gauss_legendre4"]


@pytest.mark.parametrize("name", IMPLICIT)
@pytest.mark.parametrize(
    ("tol", "message"),
    [
        (1.0, "tol must be below 1, got 1.0"),
        (5.0, "tol must be below 1, got 5.0"),
        (1e-17, "tol must be at least 8.88e-16, got 1e-17"),
        (5e-324, "tol must be at least 8.88e-16, got 5e-324"),
        (True, "tol must be a number, got True"),
        ("1e-8", "tol must be a number, got '1e-8'"),
    ],
)
def test_implicit_tol_out_of_reach_is_refused_by_the_constructor(name, tol, message):
    """Before: only the sign was checked (and True, "1e-8" were taken as numbers)."""
    with pytest.raises(ValueError, match=re.escape(message)):
        INTEGRATORS[name](dt=0.01, tol=tol)


def test_reachable_tols_are_accepted():
    for tol in (1e-14, 8.9e-16, 0.5):
        assert INTEGRATORS["implicit_euler"](dt=0.01, tol=tol).tol == tol


@pytest.mark.parametrize(
    ("tol", "message"),
    [
        ("1.0", "tol must be below 1, got 1.0"),
        ("1e-20", "tol must be at least 8.88e-16, got 1e-20"),
    ],
)
def test_md_run_refuses_implicit_tol_out_of_reach(tol, message, tmp_path, monkeypatch, capsys):
    integrator = f'type = "implicit_euler"\ndt = 0.002\ntol = {tol}'
    error = _refused(tmp_path, monkeypatch, capsys, 'type = "lj"\ncutoff = 2.5', integrator)
    assert "[integrator]" in error and message in error, error


def test_a_start_that_cannot_be_evaluated_is_not_blamed_on_dt():
    """Overlapping atoms at step 0: the first force call fails before any dynamics, so
    the message says the starting configuration, not "is dt too large?"."""
    from integrators import VelocityVerlet
    from md.errors import SimulationError
    from potentials import LennardJones

    state = md.lattice("fcc", 3, density=0.8442)
    state.positions[1] = state.positions[0]
    sim = md.Simulation(state, [LennardJones(cutoff=2.5)], VelocityVerlet(dt=0.005))
    with pytest.raises(SimulationError, match="starting configuration") as caught:
        sim.run(1)
    assert "dt" not in str(caught.value)
