"""Measure integrators instead of describing them: order, stability, energy, cost.

``compare_integrators`` runs one system under each integrator across a
ladder of time steps, all to the same final time, and measures:

order
    Slope of log(global position error at the final time) against log(dt),
    fitted by least squares over the asymptotic range only: stable runs on
    the dt ladder, above the reference's error floor, from the finest dt
    upward while each successive slope stays within ``slope_tolerance`` of
    the finest pair's (past that, the error leaves the asymptotic regime on
    its way to the stability limit). The error is the RMS distance
    (positions are continuous) to a reference run with a high-order method
    (Yoshida 6 by default) at a step eight times finer than the smallest dt
    studied; the reference is run again at half that step, and Richardson's
    estimate of its own error, |x(h) - x(h/2)| / (2^p - 1), sets the floor
    (ten times it): points below the floor measure the reference, not the
    integrator. Adaptive integrators run with output steps of span / 10 (so
    their controller picks the substeps) over a tolerance ladder, and the
    slope is taken against the tolerance instead (``order_vs``: "tol"). An
    order p needs forces whose p-th time derivative exists along the
    trajectory: a pair crossing a
    cutoff where the force (``shift``) or its derivative (``smooth``) jumps
    adds error terms of order 1 or 2 that hide higher orders. Keep the span
    short on chaotic systems, or the error measures Lyapunov divergence
    rather than truncation.
max_energy_error, position_error (work-precision)
    Per run: max over the run of |E(t) - E(0)| per atom (sampled at
    ``samples`` points) and the final position error, against wall time and
    force evaluations; :func:`plot_work_precision` draws them.
energy_drift
    Slope of a least-squares line through the total energy against time,
    per atom [energy / (atom time)], at the integrator's reference dt.
energy_fluctuation
    Standard deviation of the total energy about that line, per atom.
dt_max_stable
    The largest dt on the ladder (extended upward by doublings until the
    first failure) at which the run finishes with finite energy and
    max |E(t) - E(0)| below ``stability_tolerance`` times the initial kinetic
    energy (or |E(0)| when that is larger).
evals_per_time, wall_per_time
    Force evaluations and wall-clock seconds per unit simulated time at the
    reference dt.

Thermostats are measured by ``compare_thermostats`` instead, each at one
dt after an equilibration, on what they are for:

temperature_error
    Mean kinetic temperature minus the target, with its standard error
    (from the statistical inefficiency of the temperature series).
potential_autocorrelation_time
    Integrated autocorrelation time tau of the potential energy [time];
    ``sampling_efficiency`` = 1 / (2 tau) is the number of statistically
    independent potential-energy samples per unit time, the figure of merit
    of a thermostat's sampling (strong coupling disturbs the dynamics and can
    slow configurational sampling down, weak coupling equilibrates slowly).
conserved_drift
    Slope of the conserved quantity (total plus heat-bath energy) per atom
    [energy / (atom time)]: an integration-error check.

:func:`prepare_study` builds what ``md integrators`` measures from a config
(validating every option and writing nothing) and :meth:`Study.run` measures
it and writes the CSV files and plots; the command prints the tables. This
module is library code (no printing).
"""

from __future__ import annotations

import functools
import inspect
import logging
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from integrators import INTEGRATORS, VelocityVerlet
from integrators.base import DeclaresAdaptive, DeclaresOrder, ForceSplit, Integrator
from md._checks import count, positive
from md._files import removed_on_error, unwritable_folder, write_csv_rows
from md.assemble import build_potentials
from md.config import (
    Config,
    PluginEntry,
    build_system,
    integrator_from_config,
    load_config,
)
from md.errors import ConfigError, ConvergenceError, NonFiniteError, SimulationError
from md.forcefield import ForceField
from md.plot_style import grouped, legend_outside, reference_slopes, styles
from md.simulation import Simulation
from md.state import State
from md.thermo import kinetic_energy
from md.topology import Topology

logger = logging.getLogger(__name__)

CSV_COLUMNS = (
    "integrator",
    "dt_max_stable",
    "order",
    "expected_order",
    "order_vs",
    "fit_low",
    "fit_high",
    "fit_points",
    "fit_note",
    "energy_drift",
    "energy_fluctuation",
    "evals_per_time",
    "wall_per_time",
    "max_energy_error",
    "position_error",
)
#: Columns of ``work_precision.csv``: one row per run (integrator and dt or tolerance).
WORK_PRECISION_COLUMNS = (
    "integrator",
    "dt",
    "tol",
    "stable",
    "position_error",
    "max_energy_error",
    "force_evaluations",
    "wall",
    "in_order_fit",
)


@dataclass
class RunRecord:
    """One run of one integrator at one dt."""

    dt: float
    stable: bool
    error: float = math.nan
    times: np.ndarray = field(default_factory=lambda: np.zeros(0))
    energies: np.ndarray = field(default_factory=lambda: np.zeros(0))
    evaluations: int = 0
    wall: float = 0.0
    n_atoms: int = 1
    final_positions: np.ndarray | None = None
    message: str = ""
    tol: float = math.nan
    in_fit: bool = False
    #: The step at which an unstable run failed (its last step when the energy strayed).
    failed_step: int | None = None

    @property
    def max_energy_error(self) -> float:
        """max |E(t) - E(0)| per atom over the sampled energies (NaN if unstable)."""
        if not self.stable or not len(self.energies):
            return math.nan
        return float(np.max(np.abs(self.energies - self.energies[0]))) / self.n_atoms


@dataclass
class IntegratorReport:
    """Measured behaviour of one integrator (see the module docstring)."""

    name: str
    runs: list[RunRecord]
    order: float
    dt_max_stable: float
    energy_drift: float
    energy_fluctuation: float
    evals_per_time: float
    wall_per_time: float
    reference_dt: float
    statistics: dict = field(default_factory=dict)
    expected_order: float = math.nan
    order_vs: str = "dt"
    fit_range: tuple[float, float] = (math.nan, math.nan)
    fit_points: int = 0
    fit_note: str = ""
    floor: float = math.nan

    def measured_run(self) -> RunRecord | None:
        """The run at the measuring dt (``reference_dt``), if it was stable."""
        return next((r for r in self.runs if r.stable and r.dt == self.reference_dt), None)

    def row(self) -> dict:
        run = self.measured_run()
        return {
            "integrator": self.name,
            "dt_max_stable": self.dt_max_stable,
            "order": self.order,
            "expected_order": self.expected_order,
            "order_vs": self.order_vs,
            "fit_low": self.fit_range[0],
            "fit_high": self.fit_range[1],
            "fit_points": self.fit_points,
            "fit_note": self.fit_note,
            "max_energy_error": run.max_energy_error if run else math.nan,
            "position_error": run.error if run else math.nan,
            "energy_drift": self.energy_drift,
            "energy_fluctuation": self.energy_fluctuation,
            "evals_per_time": self.evals_per_time,
            "wall_per_time": self.wall_per_time,
        }


#: Tolerance of the implicit integrators' solves in the study (see compare_integrators).
SOLVER_TOL = 1e-12
#: Default tolerance ladder of adaptive integrators.
TOLERANCES = (1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10)


def compare_integrators(
    make_state: Callable[[], State],
    potentials_factory: Callable[[], Sequence],
    integrators: dict[str, Callable[[float], object]],
    dts: Sequence[float],
    span: float,
    skin: float = 0.3,
    units: str = "lj",
    reference: Callable[[float], object] | None = None,
    reference_dt: float | None = None,
    reference_order: int | None = None,
    samples: int = 200,
    stability_tolerance: float = 0.5,
    max_doublings: int = 6,
    measure_dt: float | None = None,
    tolerances: Sequence[float] = TOLERANCES,
    slope_tolerance: float = 0.15,
    progress: Callable[[str], None] | None = None,
    solver_tol: float | None = SOLVER_TOL,
) -> list[IntegratorReport]:
    """Run every integrator over the dt ladder and measure it.

    Parameters
    ----------
    make_state : callable
        Returns a fresh copy of the initial State for every run.
    potentials_factory : callable
        Returns fresh potentials for every run.
    integrators : dict
        Name -> factory ``f(dt)`` building the integrator; a factory may
        carry ``order`` (the expected order) and ``adaptive`` (then it is
        called as ``f(dt, tol=...)`` over ``tolerances``).
    dts : sequence of float
        Time steps to study [time], at least two.
    span : float
        Simulated time of every run [time]; each dt is adjusted down so a
        whole number of steps lands on ``span``.
    reference : callable, optional
        Factory of the reference integrator (default: the one named
        "yoshida6", else "rk4", else the first given).
    reference_dt : float, optional
        Its step (default: min(dts) / 8).
    reference_order : int, optional
        Its order, for Richardson's error estimate (default: the factory's
        ``order``, else 4).
    samples : int
        Energy samples per run (for drift, fluctuation and the energy error).
    measure_dt : float, optional
        The dt at which drift, fluctuation and cost are compared (default:
        the middle of the ladder); an integrator unstable there is measured
        at its largest stable dt below it.
    slope_tolerance : float
        How far a local slope may stray from the fitted one and still count as
        asymptotic (see :func:`fit_order`).
    solver_tol : float or None
        The tolerance implicit integrators solve their steps to: a factory that
        is an integrator class taking ``tol`` (and is not adaptive) is called
        as ``f(dt, tol=solver_tol)``. A solve stopped at the default 1e-8 leaves
        an error of its own that the finer steps' errors fall to, and the fit
        measures that floor instead of the method (None: the classes' default).
    """
    dts = sorted(float(dt) for dt in dts)
    if len(dts) < 2 or dts[0] <= 0:
        raise ValueError(f"need at least two positive time steps, got {dts}")
    if not span > 0:
        raise ValueError(f"span must be positive, got {span}")
    if reference is None:
        named = [integrators.get("yoshida6"), integrators.get("rk4")]
        reference = next((f for f in named if f is not None), next(iter(integrators.values())))
    reference_dt = reference_dt or dts[0] / 8
    reference_order = reference_order or _declared_order(reference) or 4
    say = progress or (lambda message: None)
    say(f"reference runs: dt = {reference_dt:g} and {reference_dt / 2:g}")
    args = (make_state, potentials_factory)
    coarse = _run(*args, reference, reference_dt, span, skin, units, samples)
    fine = _run(*args, reference, reference_dt / 2, span, skin, units, samples)
    for run in (coarse, fine):
        if not run.stable:
            raise SimulationError(
                run.failed_step, f"the reference run at dt = {run.dt:.3g} failed ({run.message})"
            )
    reference_positions = fine.final_positions
    # Richardson: x(h) - x(h/2) ~ (2^p - 1) C (h/2)^p, the error of the finer run.
    difference = coarse.final_positions - fine.final_positions
    reference_error = float(np.sqrt(np.mean(np.sum(difference**2, axis=1))))
    reference_error /= 2.0**reference_order - 1.0
    scale = float(np.sqrt(np.mean(np.sum(fine.final_positions**2, axis=1))))
    floor = max(10.0 * reference_error, 1e-13 * scale)
    say(f"reference error (Richardson) {reference_error:.2e}; fits use errors above {floor:.2e}")

    reports = []
    for name, factory in integrators.items():
        adaptive = isinstance(factory, DeclaresAdaptive) and bool(factory.adaptive)
        if solver_tol is not None and not adaptive and _takes_tol(factory):
            order = _declared_order(factory)
            factory = functools.partial(factory, tol=solver_tol)
            factory.order = order
        runs = []
        if adaptive:
            dt = span / 10  # output steps long enough that the controller picks the substeps
            for tol in tolerances:
                say(f"{name}: dt = {dt:g}, tol = {tol:g}")
                at_tol = functools.partial(factory, tol=tol)
                record = _run(*args, at_tol, dt, span, skin, units, samples, reference_positions,
                              stability_tolerance)  # fmt: skip
                record.tol = tol
                runs.append(record)
        else:
            for dt in dts:
                say(f"{name}: dt = {dt:g}")
                runs.append(
                    _run(*args, factory, dt, span, skin, units, samples, reference_positions,
                         stability_tolerance)
                )  # fmt: skip
            dt = dts[-1]
            doublings = 0
            while runs[-1].stable and doublings < max_doublings:
                dt *= 2.0
                doublings += 1
                if dt > span:
                    break
                say(f"{name}: stability scan dt = {dt:g}")
                runs.append(
                    _run(*args, factory, dt, span, skin, units, samples, reference_positions,
                         stability_tolerance)
                )  # fmt: skip
        measured_at = span / 10 if adaptive else (measure_dt or dts[len(dts) // 2])
        report = _report(name, runs, dts, span, measured_at)
        report.floor = floor
        expected = _declared_order(factory)
        report.expected_order = math.nan if expected is None else float(expected)
        if adaptive:
            report.order_vs = "tol"
            ladder = [r for r in runs if r.stable]
            report.order, report.fit_range, report.fit_points, report.fit_note = _fit_order(
                [r.tol for r in ladder], ladder, floor, slope_tolerance
            )
        else:
            # The stability scan's runs too: for a high-order method they may be the
            # only errors above the reference's floor; the fit leaves out any that have
            # left the asymptotic range.
            ladder = [r for r in runs if r.stable]
            report.order, report.fit_range, report.fit_points, report.fit_note = _fit_order(
                [r.dt for r in ladder], ladder, floor, slope_tolerance
            )
        reports.append(report)
    return reports


def _declared_order(factory) -> int | None:
    """The order in dt a factory's integrators are built for, where it declares one (an
    integrator class, or a partial given one above); None for a plain function."""
    return factory.order if isinstance(factory, DeclaresOrder) else None


def _takes_tol(factory) -> bool:
    """Whether ``factory`` is an integrator class with a ``tol`` parameter."""
    return isinstance(factory, type) and "tol" in inspect.signature(factory).parameters


#: Fewest points an order is fitted from: two points give a slope whatever the errors do.
MIN_FIT_POINTS = 3
#: A range whose slope is below this is not a convergence range (the error does not fall
#: with the step: a floor, or saturation near the stability limit), whatever its length.
MIN_FIT_SLOPE = 0.5


def fit_order(steps, errors, floor: float = 0.0, slope_tolerance: float = 0.15):
    """Fit the order of convergence over the asymptotic range, or say why there is none.

    The points are (step, error) pairs; those at or below ``floor`` (the
    reference's error) are left out. The asymptotic range is the longest run
    of at least :data:`MIN_FIT_POINTS` successive points (the finest of equal
    length) whose every local slope, between neighbours, lies within
    ``slope_tolerance`` of the least-squares slope through them, and whose
    slope is at least :data:`MIN_FIT_SLOPE`. Points finer than it depart from
    the trend (round-off, the solver's tolerance, the reference), coarser ones
    leave the asymptotic regime on the way to the stability limit.

    Returns
    -------
    slope : float
        The order, NaN when no range qualifies.
    used : list of int
        Indices (into the given points) of the points fitted, empty if none.
    note : str
        Why there is no order, or which points were left out and why; "" when
        every point was used.

    Examples
    --------
    >>> steps = [0.01, 0.02, 0.04, 0.08]
    >>> slope, used, note = fit_order(steps, [1e-12, 4e-8, 1.6e-7, 6.4e-7], floor=1e-13)
    >>> round(slope, 3), used
    (2.0, [1, 2, 3])
    >>> note
    'the finest 1 point(s) (dt <= 0.01) depart from the trend (local slope 15.3): left out'
    """
    order = sorted(range(len(steps)), key=lambda k: steps[k])
    finite = [k for k in order if math.isfinite(errors[k]) and errors[k] > 0.0]
    above = [k for k in finite if errors[k] > floor]
    below = [steps[k] for k in finite if errors[k] <= floor]
    notes = []
    if below:
        notes.append(
            f"{len(below)} point(s) at dt <= {max(below):.3g} below the reference's error "
            f"floor {floor:.2e}"
        )
    if len(above) < MIN_FIT_POINTS:
        notes.insert(0, f"no order: only {len(above)} point(s) above the reference's error "
                        f"floor (an order needs {MIN_FIT_POINTS})")  # fmt: skip
        return math.nan, [], "; ".join(notes)
    x = np.log([steps[k] for k in above])
    y = np.log([errors[k] for k in above])
    local = np.diff(y) / np.diff(x)
    best = None
    for i in range(len(above)):
        for j in range(i + MIN_FIT_POINTS - 1, len(above)):
            slope = float(np.polyfit(x[i : j + 1], y[i : j + 1], 1)[0])
            if slope < MIN_FIT_SLOPE or np.any(np.abs(local[i:j] - slope) > slope_tolerance):
                continue
            if best is None or (j - i, -i) > (best[1] - best[0], -best[0]):
                best = (i, j, slope)
    slopes = ", ".join(f"{v:.2f}" for v in local)
    if best is None:
        # Where the error stops falling as dt shrinks: a floor.
        flat = 0
        while flat < len(local) and local[flat] < MIN_FIT_SLOPE:
            flat += 1
        if flat == len(local):
            reason = "the error does not fall as dt shrinks; "
        elif flat:
            where = steps[above[flat]]
            reason = f"round-off or solver-tolerance floor reached at dt = {where:.3g}; "
        else:
            reason = ""
        notes.insert(0, f"no order: {reason}no {MIN_FIT_POINTS} successive points agree on a "
                        f"slope within {slope_tolerance:g} (local slopes {slopes})")  # fmt: skip
        return math.nan, [], "; ".join(notes)
    i, j, slope = best
    if i:
        kind = "an error floor (round-off or solver tolerance)" if local[i - 1] < slope else (
            "depart from the trend")  # fmt: skip
        what = f"reach {kind}" if kind.startswith("an") else kind
        notes.insert(0, f"the finest {i} point(s) (dt <= {steps[above[i - 1]]:.3g}) {what} "
                        f"(local slope {local[i - 1]:.3g}): left out")  # fmt: skip
    if j < len(above) - 1:
        notes.append(
            f"{len(above) - 1 - j} coarser point(s) (dt >= {steps[above[j + 1]]:.3g}) beyond "
            f"the asymptotic range (local slope {local[j]:.3g}): left out"
        )
    return slope, above[i : j + 1], "; ".join(notes)


def _fit_order(steps, runs, floor, slope_tolerance):
    """:func:`fit_order` over runs; mark the runs used. Returns (slope, (low, high),
    n_points, note)."""
    for run in runs:
        run.in_fit = False
    slope, used, note = fit_order(steps, [r.error for r in runs], floor, slope_tolerance)
    for k in used:
        runs[k].in_fit = True
    if not used:
        return slope, (math.nan, math.nan), 0, note
    return slope, (steps[used[0]], steps[used[-1]]), len(used), note


def _run(make_state, potentials_factory, factory, dt, span, skin, units, samples,
         reference_positions=None, stability_tolerance=0.5) -> RunRecord:  # fmt: skip
    n_steps = max(1, round(span / dt))
    dt = span / n_steps
    state = make_state()
    record = RunRecord(dt=dt, stable=False, n_atoms=state.n_atoms)
    times, energies = [], []
    # Energies are sampled through a separate ForceField, so the integrator's
    # own force evaluations are counted alone and its cache is left untouched.
    sampler = ForceField(potentials_factory(), skin=skin)

    sampling_wall = [0.0]

    def sample(sim) -> None:
        start = time.perf_counter()
        state = sim.state
        times.append(state.time)
        potential = sampler.compute(state).energy
        energies.append(potential + kinetic_energy(state.velocities, state.masses))
        sampling_wall[0] += time.perf_counter() - start

    try:
        sim = Simulation(state, potentials_factory(), factory(dt), skin=skin, units=units)
        thermo = sim.thermo()
        scale = max(abs(thermo["total_energy"]), thermo["kinetic_energy"], 1e-300)
        sim.attach(sample, interval=max(1, n_steps // samples))
        evaluations_before = sim.forcefield.n_evaluations
        start = time.perf_counter()
        sim.run(n_steps)
        record.wall = time.perf_counter() - start - sampling_wall[0]
        record.evaluations = sim.forcefield.n_evaluations - evaluations_before
        if times[-1] != state.time:
            sample(sim)
    except (SimulationError, ConvergenceError, NonFiniteError, ArithmeticError) as error:
        record.message = str(error)
        stepped = isinstance(error, SimulationError | ConvergenceError)
        record.failed_step = error.step if stepped else state.step + 1
        return record
    record.times = np.array(times)
    record.energies = np.array(energies)
    excursion = float(np.max(np.abs(record.energies - record.energies[0])))
    record.stable = bool(
        np.all(np.isfinite(record.energies)) and excursion < stability_tolerance * scale
    )
    if not record.stable:
        record.message = (
            f"energy excursion {excursion:.3g} exceeds {stability_tolerance:g} x {scale:.3g}"
        )
        record.failed_step = state.step
        return record
    record.final_positions = state.positions.copy()
    if reference_positions is not None:
        diff = state.positions - reference_positions
        record.error = float(np.sqrt(np.mean(np.sum(diff * diff, axis=1))))
    return record


def _report(name, runs, dts, span, measure_dt) -> IntegratorReport:
    stable = [r for r in runs if r.stable]
    dt_max_stable = max((r.dt for r in stable), default=math.nan)
    order = math.nan  # fitted by compare_integrators
    # Energy behaviour and cost at measure_dt, or the largest stable dt below it.
    base = max((r for r in stable if r.dt <= measure_dt * 1.0000001), key=lambda r: r.dt,
               default=None)  # fmt: skip
    drift = fluctuation = evals = wall = math.nan
    reference_dt = math.nan
    if base is not None:
        n_atoms = base.n_atoms
        slope, intercept = np.polyfit(base.times, base.energies, 1)
        residual = base.energies - (slope * base.times + intercept)
        drift = float(slope) / n_atoms
        fluctuation = float(np.std(residual)) / n_atoms
        evals = base.evaluations / span
        wall = base.wall / span
        reference_dt = base.dt
    return IntegratorReport(
        name=name,
        runs=runs,
        order=order,
        dt_max_stable=dt_max_stable,
        energy_drift=drift,
        energy_fluctuation=fluctuation,
        evals_per_time=evals,
        wall_per_time=wall,
        reference_dt=reference_dt,
    )


def write_csv(reports: Sequence[IntegratorReport], path) -> None:
    """Write one row per integrator with :data:`CSV_COLUMNS` (and the measuring dt)."""
    rows = ({**report.row(), "measured_at_dt": report.reference_dt} for report in reports)
    write_csv_rows(path, [*CSV_COLUMNS, "measured_at_dt"], rows)


def write_work_precision_csv(reports: Sequence[IntegratorReport], path) -> None:
    """Write one row per run with :data:`WORK_PRECISION_COLUMNS` (the work-precision data)."""
    rows = (
        {
            "integrator": report.name, "dt": run.dt, "tol": run.tol,
            "stable": run.stable, "position_error": run.error,
            "max_energy_error": run.max_energy_error,
            "force_evaluations": run.evaluations if run.stable else math.nan,
            "wall": run.wall if run.stable else math.nan, "in_order_fit": run.in_fit,
        }
        for report in reports
        for run in report.runs
    )  # fmt: skip
    write_csv_rows(path, WORK_PRECISION_COLUMNS, rows)


def _pyplot():
    import matplotlib  # heavy: matplotlib only when plotting

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # heavy: matplotlib only when plotting

    return plt


def plot_error_vs_dt(reports: Sequence[IntegratorReport], path, time_label: str = "") -> None:
    """Log-log global position error against dt, one colour and marker per integrator.

    Integrators are grouped by family (line style and hue; the legend lists
    them family by family, outside the axes). Filled markers are the points the
    order fit used, hollow ones the rest; dashed grey lines are reference slopes
    for the orders expected; a dotted line is the reference's error floor.
    """
    plt = _pyplot()
    shown = [r for r in reports if r.order_vs == "dt"]
    names = grouped([r.name for r in shown])
    by_name = {r.name: r for r in shown}
    style = styles(names)
    fig, ax = plt.subplots(figsize=(8.6, 5.6))
    xs, ys = [], []
    for name in names:
        report, s = by_name[name], style[name]
        points = sorted((r.dt, r.error, r.in_fit) for r in report.runs if r.stable and r.error > 0)
        if not points:
            continue
        dts, errors, used = zip(*points, strict=True)
        xs += dts
        ys += errors
        order = f"{report.order:.2f}" if math.isfinite(report.order) else "none"
        ax.loglog(dts, errors, ls=s["linestyle"], color=s["color"], lw=0.9,
                  label=f"{name} (order {order}, {report.fit_points} pts)")  # fmt: skip
        for fitted in (True, False):
            chosen = [(d, e) for d, e, u in points if u == fitted]
            if chosen:
                ax.loglog(*zip(*chosen, strict=True), ls="none", marker=s["marker"],
                          color=s["color"], mfc=s["color"] if fitted else "white", ms=5,
                          mew=1.0)  # fmt: skip
    expected = [r.expected_order for r in shown if math.isfinite(r.expected_order)]
    reference_slopes(ax, xs, ys, expected or [1, 2, 4])
    floors = [r.floor for r in reports if math.isfinite(r.floor)]
    if floors:
        ax.axhline(floors[0], color="k", ls=":", lw=0.8, label="reference error floor (x10)")
    ax.set_xlabel(f"time step dt {time_label}".strip())
    ax.set_ylabel("RMS position error at the final time")
    ax.set_title("Global error against a Richardson-checked reference\n"
                 "(filled: fitted for the order; hollow: left out; grey: reference slopes)",
                 fontsize="medium")  # fmt: skip
    legend_outside(fig, ax)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)


def plot_work_precision(reports: Sequence[IntegratorReport], path, labels=None) -> None:
    """Work-precision diagrams: energy and position error against wall time and force calls.

    One curve per integrator over its stable runs (its dt ladder up to the
    stability limit, or its tolerance ladder), as SciMLBenchmarks draws them;
    one colour and marker per integrator, families grouped, the legend beside
    the panels; on the force-evaluation panels, reference slopes -1, -2, -4
    (error ~ work^-p for an order-p method, work ~ 1/dt).
    """
    labels = labels or {}
    plt = _pyplot()
    fig, axes = plt.subplots(2, 2, figsize=(12.5, 8.5))
    measures = (("max_energy_error", "max |E(t) - E(0)| per atom"),
                ("error", "RMS position error at the final time"))  # fmt: skip
    works = (("wall", "wall time [s]"), ("evaluations", "force evaluations"))
    names = grouped([r.name for r in reports])
    by_name = {r.name: r for r in reports}
    style = styles(names)
    drawn = {(row, column): ([], []) for row in range(2) for column in range(2)}
    for name in names:
        s = style[name]
        runs = sorted((r for r in by_name[name].runs if r.stable), key=lambda r: (r.dt, -r.tol))
        for row, (measure, _) in enumerate(measures):
            for column, (work, _) in enumerate(works):
                # (two of the run record's fields, by name: the axes of this panel)
                pairs = [(getattr(r, work), getattr(r, measure)) for r in runs]
                pairs = [(a, b) for a, b in pairs if a > 0 and b > 0]
                if not pairs:
                    continue
                x, y = zip(*pairs, strict=True)
                drawn[row, column][0].extend(x)
                drawn[row, column][1].extend(y)
                axes[row, column].loglog(x, y, ls=s["linestyle"], marker=s["marker"], ms=4,
                                         color=s["color"], lw=0.9, label=name)  # fmt: skip
    for row, (_, measure_label) in enumerate(measures):
        for column, (_, work_label) in enumerate(works):
            ax = axes[row, column]
            if column == 1:
                reference_slopes(ax, *drawn[row, column], [1, 2, 4], sign=-1)
            ax.set_xlabel(work_label)
            ax.set_ylabel(f"{measure_label} {labels.get(('energy', 'length')[row], '')}".strip())
            ax.grid(True, which="both", alpha=0.3)
    legend_outside(fig, axes[0, 1], title="integrator (by family)")
    fig.suptitle("Work-precision: error against cost, one curve per integrator over its dt ladder")
    fig.tight_layout()
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)


def plot_energy_vs_time(reports: Sequence[IntegratorReport], path, labels=None) -> None:
    """Total energy per atom against time for each integrator at its measuring dt."""
    plt = _pyplot()

    labels = labels or {}
    fig, ax = plt.subplots(figsize=(6.4, 4.8))
    for report in reports:
        run = next((r for r in report.runs if r.dt == report.reference_dt), None)
        if run is None or not len(run.times):
            continue
        energy = (run.energies - run.energies[0]) / run.n_atoms
        ax.plot(run.times, energy, label=f"{report.name} (dt {run.dt:.3g})")
    ax.set_xlabel(f"time {labels.get('time', '')}".strip())
    ax.set_ylabel(f"E(t) - E(0) per atom {labels.get('energy', '')}".strip())
    ax.set_title("Total energy")
    ax.legend(fontsize="small")
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# ------------------------------------------------------------------ thermostats

THERMOSTAT_CSV_COLUMNS = (
    "thermostat",
    "dt",
    "target_temperature",
    "mean_temperature",
    "temperature_error",
    "temperature_stderr",
    "mean_potential_energy",
    "potential_energy_stderr",
    "potential_autocorrelation_time",
    "sampling_efficiency",
    "conserved_drift",
    "evals_per_time",
    "wall_per_time",
    "canonical",
)


@dataclass
class ThermostatReport:
    """Measured sampling of one thermostat (see the module docstring).

    Energies are per atom; ``mean_potential_energy`` [energy],
    ``potential_autocorrelation_time`` [time], ``sampling_efficiency``
    [1/time], ``conserved_drift`` [energy / (atom time)] (NaN if the
    integrator reports no conserved quantity). ``canonical`` is False for a
    thermostat that does not sample the canonical ensemble (Berendsen), whose
    small temperature error and short correlation times are artefacts of
    suppressed fluctuations. A run that failed has NaN figures and its ``message``.
    """

    name: str
    dt: float
    target_temperature: float
    mean_temperature: float = math.nan
    temperature_error: float = math.nan
    temperature_stderr: float = math.nan
    mean_potential_energy: float = math.nan
    potential_energy_stderr: float = math.nan
    potential_autocorrelation_time: float = math.nan
    sampling_efficiency: float = math.nan
    conserved_drift: float = math.nan
    evals_per_time: float = math.nan
    wall_per_time: float = math.nan
    canonical: bool = True
    times: np.ndarray = field(default_factory=lambda: np.zeros(0))
    temperatures: np.ndarray = field(default_factory=lambda: np.zeros(0))
    potentials: np.ndarray = field(default_factory=lambda: np.zeros(0))
    message: str = ""

    def row(self) -> dict:
        return {
            "thermostat": self.name,
            **{k: getattr(self, k) for k in THERMOSTAT_CSV_COLUMNS[1:]},  # its own fields
        }


def statistical_inefficiency(values, window_factor: float = 5.0) -> float:
    """Return g = 1 + 2 sum_{t>=1} rho(t) of a time series, in samples (>= 1).

    rho is the normalised autocorrelation function (by FFT); the sum runs
    up to the first window M with M >= ``window_factor`` * g(M) / 2, Sokal's
    automatic window, which keeps the noise of the tail out. The standard
    error of the mean of n samples is sqrt(var * g / n), and the integrated
    autocorrelation time is g / 2 sample intervals. NaN for fewer than 4
    samples; 1 for a constant series.
    """
    x = np.asarray(values, dtype=np.float64)
    n = len(x)
    if n < 4:
        return math.nan
    x = x - x.mean()
    variance = float(np.dot(x, x)) / n
    if variance == 0.0:
        return 1.0
    size = 1 << (2 * n - 1).bit_length()
    spectrum = np.fft.rfft(x, size)
    acf = np.fft.irfft(spectrum * np.conj(spectrum), size)[:n] / (variance * np.arange(n, 0, -1))
    g = 1.0
    for lag in range(1, n):
        g += 2.0 * acf[lag]
        if lag >= window_factor * g / 2.0:
            break
    return max(g, 1.0)


def compare_thermostats(
    make_state: Callable[[], State],
    potentials_factory: Callable[[], Sequence],
    thermostats: dict[str, Callable[[], object]],
    target_temperature: float,
    n_equilibrate: int,
    n_sample: int,
    skin: float = 0.3,
    units: str = "lj",
    sample_every: int = 1,
    progress: Callable[[str], None] | None = None,
) -> list[ThermostatReport]:
    """Run every thermostat from the same state and measure its sampling.

    Parameters
    ----------
    make_state, potentials_factory : callable
        Fresh copies of the initial State and potentials for every run.
    thermostats : dict
        Name -> factory ``f()`` building the thermostat (with its dt).
    target_temperature : float
        The thermostats' target [temperature in the units' kB].
    n_equilibrate, n_sample : int
        Steps run before sampling, and sampled.
    sample_every : int
        Steps between samples of temperature, potential and conserved energy.
    """
    say = progress or (lambda message: None)
    reports = []
    for name, factory in thermostats.items():
        say(f"{name}: {n_equilibrate} + {n_sample} steps")
        integrator = factory()
        report = ThermostatReport(
            name=name, dt=integrator.dt, target_temperature=target_temperature
        )
        report.canonical = integrator.canonical if isinstance(integrator, Integrator) else True
        rows = []
        sampling_wall = [0.0]

        def sample(sim, rows=rows, sampling_wall=sampling_wall) -> None:
            start = time.perf_counter()
            rows.append(sim.thermo())
            sampling_wall[0] += time.perf_counter() - start

        try:
            sim = Simulation(make_state(), potentials_factory(), integrator, skin=skin, units=units)
            sim.run(int(n_equilibrate))
            sim.attach(sample, interval=max(1, int(sample_every)))
            evaluations_before = sim.forcefield.n_evaluations
            start = time.perf_counter()
            sim.run(int(n_sample))
            wall = time.perf_counter() - start - sampling_wall[0]
        except (SimulationError, ConvergenceError, NonFiniteError, ArithmeticError) as error:
            report.message = str(error)
            reports.append(report)
            continue
        _measure(report, rows, sim, wall, sim.forcefield.n_evaluations - evaluations_before,
                 integrator.dt * int(n_sample))  # fmt: skip
        reports.append(report)
    return reports


def _measure(report, rows, sim, wall, evaluations, span) -> None:
    n_atoms = sim.state.n_atoms
    report.times = np.array([row["time"] for row in rows])
    report.temperatures = np.array([row["temperature"] for row in rows])
    report.potentials = np.array([row["potential_energy"] for row in rows]) / n_atoms
    n = len(rows)
    interval = (report.times[-1] - report.times[0]) / (n - 1) if n > 1 else math.nan
    g_temperature = statistical_inefficiency(report.temperatures)
    g_potential = statistical_inefficiency(report.potentials)
    report.mean_temperature = float(report.temperatures.mean())
    report.temperature_error = report.mean_temperature - report.target_temperature
    report.temperature_stderr = math.sqrt(report.temperatures.var() * g_temperature / n)
    report.mean_potential_energy = float(report.potentials.mean())
    report.potential_energy_stderr = math.sqrt(report.potentials.var() * g_potential / n)
    report.potential_autocorrelation_time = 0.5 * g_potential * interval
    report.sampling_efficiency = 1.0 / (2.0 * report.potential_autocorrelation_time)
    if "conserved_energy" in rows[0] and n > 1:
        conserved = np.array([row["conserved_energy"] for row in rows])
        report.conserved_drift = float(np.polyfit(report.times, conserved, 1)[0]) / n_atoms
    report.evals_per_time = evaluations / span
    report.wall_per_time = wall / span


def write_thermostat_csv(reports: Sequence[ThermostatReport], path) -> None:
    """Write one row per thermostat with :data:`THERMOSTAT_CSV_COLUMNS`."""
    write_csv_rows(path, THERMOSTAT_CSV_COLUMNS, (report.row() for report in reports))


def plot_thermostats(reports: Sequence[ThermostatReport], path, labels=None) -> None:
    """Kinetic temperature against time, and the potential energy's autocorrelation."""
    plt = _pyplot()

    labels = labels or {}
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4.2))
    for report in reports:
        if not len(report.times):
            continue
        left.plot(report.times, report.temperatures, lw=0.8, label=report.name)
        x = report.potentials - report.potentials.mean()
        n = len(x)
        lags = min(n - 1, max(10, n // 4))
        acf = [1.0] + [float(np.dot(x[:-k], x[k:]) / np.dot(x, x) * n / (n - k))
                       for k in range(1, lags)]  # fmt: skip
        interval = (report.times[-1] - report.times[0]) / (n - 1)
        label = f"{report.name} (tau {report.potential_autocorrelation_time:.3g})"
        right.plot(np.arange(lags) * interval, acf, label=label)
    if reports:
        left.axhline(reports[0].target_temperature, color="k", lw=0.8, ls="--")
    left.set_xlabel(f"time {labels.get('time', '')}".strip())
    left.set_ylabel(f"kinetic temperature {labels.get('temperature', '')}".strip())
    right.set_xlabel(f"lag {labels.get('time', '')}".strip())
    right.set_ylabel("potential-energy autocorrelation")
    right.axhline(0.0, color="k", lw=0.5)
    for ax in (left, right):
        ax.legend(fontsize="small")
        ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# ------------------------------------------------------------------ the study of a config
#: Most steps, summed over every run (equilibration and references included), of a study.
MAX_STUDY_STEPS = 10**9
#: Most time steps on a dt ladder.
MAX_DTS = 1000
#: Reference integrators of the NVE comparison, in order of preference.
REFERENCES = ("yoshida6", "rk4")
#: Output files of the two comparisons, by kind.
INTEGRATOR_FILES = {
    "csv": "integrators.csv",
    "work_csv": "work_precision.csv",
    "error": "error_vs_dt.png",
    "energy": "energy_vs_time.png",
    "work": "work_precision.png",
}
THERMOSTAT_FILES = {"thermostats": "thermostats.csv", "thermostats_plot": "thermostats.png"}


@dataclass
class ThermostatSetup:
    """How the thermostats are compared (see :func:`prepare_study`).

    Attributes
    ----------
    temperature : float
        Target [the config's temperature unit; the units' kB goes with it].
    tau : float
        Coupling time [time] (Langevin: friction 1 / tau).
    n_equilibrate, n_sample : int
        Steps run before sampling (10 tau), and sampled.
    """

    temperature: float
    tau: float
    n_equilibrate: int
    n_sample: int


@dataclass
class StudyResults:
    """What :meth:`Study.run` measured and wrote.

    ``files`` maps each kind (``csv``, ``work_csv``, ``error``, ``energy``,
    ``work``, ``thermostats``, ``thermostats_plot``) to the path written.
    """

    reports: list[IntegratorReport]
    thermostat_reports: list[ThermostatReport]
    files: dict[str, Path]


@dataclass
class Study:
    """A validated integrator study that has written nothing yet (see :func:`prepare_study`).

    Attributes
    ----------
    config : Config
        The parsed config.
    state : State
        The starting state every run copies (equilibrated, at step 0).
    bonds : Topology or None
        The system's bonds, for ``bonds = "system"`` in potentials and constraints.
    names : list of str
        The NVE integrators compared (order in dt).
    thermostat_names : list of str
        The thermostats compared (sampling at ``setup.temperature``).
    dts : list of float
        The dt ladder [time]; ``span`` [time] is every run's length.
    measure_dt : float or None
        Where drift and cost are compared (None: the middle of the ladder).
    setup : ThermostatSetup or None
        The thermostats' target, coupling and run lengths.
    out : Path
        Output folder; ``files`` maps each kind to the path it will get.
    """

    config: Config
    state: State
    bonds: Topology | None
    names: list[str]
    thermostat_names: list[str]
    dts: list[float]
    span: float
    measure_dt: float | None
    setup: ThermostatSetup | None
    out: Path
    files: dict[str, Path]
    overwrite: bool = False

    @property
    def reference(self) -> str:
        """Name of the reference integrator."""
        return next(name for name in REFERENCES if name in INTEGRATORS)

    @property
    def reference_dt(self) -> float:
        """The coarser reference run's step [time] (it is run again at half of it)."""
        return min(self.dts) / 8

    def potentials(self) -> list:
        """Fresh potentials, as ``md run`` builds them from the config."""
        return build_potentials(self.config, self.state.type_names, self.bonds)

    def thermostat(self, name: str):
        """A fresh thermostat ``name`` with the study's target and coupling."""
        return _build_thermostat(self.config, name, self.setup, self.bonds)

    def run(self, progress: Callable[[str], None] | None = None) -> StudyResults:
        """Measure the integrators, then the thermostats; write the files; return the results.

        ``progress(message)`` hears of each run as it starts.

        Raises
        ------
        SimulationError
            If a reference run of the NVE comparison fails (time steps or span
            too long for the system); nothing is written then.
        OSError
            If the files cannot be written (the files of this call are removed).
        """
        units, skin = self.config.units, self.config.run.skin
        reports: list[IntegratorReport] = []
        if self.names:
            reports = compare_integrators(
                make_state=self.state.copy, potentials_factory=self.potentials,
                integrators={name: INTEGRATORS[name] for name in self.names}, dts=self.dts,
                span=self.span, skin=skin, units=units, reference=INTEGRATORS[self.reference],
                measure_dt=self.measure_dt, progress=progress,
            )  # fmt: skip
        thermostat_reports: list[ThermostatReport] = []
        if self.thermostat_names:
            setup = self.setup
            thermostat_reports = compare_thermostats(
                make_state=self.state.copy, potentials_factory=self.potentials,
                thermostats={n: functools.partial(self.thermostat, n)
                             for n in self.thermostat_names},
                target_temperature=setup.temperature, n_equilibrate=setup.n_equilibrate,
                n_sample=setup.n_sample, skin=skin, units=units, progress=progress,
            )  # fmt: skip
        self.write(reports, thermostat_reports)
        return StudyResults(reports, thermostat_reports, dict(self.files))

    def write(self, reports, thermostat_reports) -> None:
        """Write the CSV files and plots of both comparisons into ``out``.

        Files that exist are replaced only with ``overwrite``; if writing
        fails, the files this call wrote are removed before the error is raised.
        """
        units, files = self.config.units, self.files
        labels = {name: f"[{units.labels[name]}]" for name in ("time", "energy", "length",
                                                                "temperature")}  # fmt: skip
        writers = []
        if reports:
            writers += [
                (files["csv"], lambda path: write_csv(reports, path)),
                (files["work_csv"], lambda path: write_work_precision_csv(reports, path)),
                (files["error"], lambda path: plot_error_vs_dt(
                    reports, path, f"[{units.config_time_label}]")),
                (files["energy"], lambda path: plot_energy_vs_time(reports, path, labels)),
                (files["work"], lambda path: plot_work_precision(reports, path, labels)),
            ]  # fmt: skip
        if thermostat_reports:
            writers += [
                (files["thermostats"], lambda path: write_thermostat_csv(thermostat_reports, path)),
                (files["thermostats_plot"],
                 lambda path: plot_thermostats(thermostat_reports, path, labels)),
            ]  # fmt: skip
        with removed_on_error() as written:
            self.out.mkdir(parents=True, exist_ok=True)
            for path, write in writers:
                if self.overwrite:
                    path.unlink(missing_ok=True)
                written.append(path)
                write(path)


def prepare_study(
    config: str | os.PathLike | Config,
    integrators: str | Sequence[str] | None = None,
    dts: str | Sequence[float] | None = None,
    span: float | None = None,
    equilibrate: int = 200,
    temperature: float | None = None,
    tau: float | None = None,
    sample_time: float | None = None,
    out: str | os.PathLike | None = None,
    overwrite: bool = False,
    max_steps: int = MAX_STUDY_STEPS,
) -> Study:
    """Validate and build the study ``md integrators`` makes of a config; write nothing.

    The system, potentials and units come from the config; the starting state
    is the config's system after ``equilibrate`` velocity Verlet steps at the
    config's dt (so the study starts from a generic state, not a force-free
    lattice). Times are in the config's time unit, as on the command line.

    Parameters
    ----------
    config : path or Config
        The TOML config (or one parsed by :func:`md.config.load_config`).
    integrators : str or sequence of str, optional
        Registry names (a comma list as text). Default: every registered
        integrator once, less those that need rigid bonds or split forces,
        and the thermostats only if a target temperature is known.
        Thermostats are measured apart (:func:`compare_thermostats`).
    dts : str or sequence of float, optional
        The dt ladder: ``"MIN:MAX:N"`` (log-spaced), a comma list, or numbers
        (default: the config dt times 1/32, 1/16, 1/8, 1/4, 1/2, 1).
    span : float, optional
        Simulated time of every NVE run (``--time``; default 100 config dt).
    equilibrate : int
        Velocity Verlet steps before the study.
    temperature, tau, sample_time : float, optional
        The thermostats' target (default: the config's thermostat temperature,
        else ``[system] temperature``), coupling time (default: the config's
        tau or 1/friction, else 100 dt) and sampled time after 10 tau of
        equilibration (default 4000 dt).
    out : path, optional
        Output folder (default ``integrators-<config stem>``).
    overwrite : bool
        Replace existing output files.
    max_steps : int
        Refuse a study whose runs add up to more steps than this.

    Raises
    ------
    ConfigError
        For anything wrong, naming the option or config key and value: an
        unknown integrator, a bad ladder or span, a study too long to finish,
        an integrator that cannot run on the system (RESPA without bonds),
        output files that exist, an unwritable output folder, or an
        equilibration that blew up.

    Examples
    --------
    >>> from md.integrator_study import prepare_study
    >>> study = prepare_study("examples/lj_small.toml", integrators="verlet",
    ...                       out=tmp / "study")  # doctest: +SKIP
    >>> results = study.run()  # doctest: +SKIP
    >>> results.reports[0].order  # doctest: +SKIP
    2.0...
    """
    if not isinstance(config, Config):
        source = Path(config)
        config = load_config(config)
    else:
        source = Path(config.source)
    units = config.units
    t = units.config_time
    config_dt = config.integrator.dt / t
    ladder = [dt * t for dt in _parse_dts(dts, config_dt)]
    run_span = (100 * config_dt if span is None else _positive_option(span, "--time")) * t
    names = _integrator_names(integrators, INTEGRATORS)
    equilibrate = _count_option(equilibrate, "--equilibrate")
    # Thermostats are measured apart: sampling at a temperature, not order in dt.
    thermostat_names = [n for n in names if INTEGRATORS[n].thermostat]
    names = [n for n in names if n not in thermostat_names]
    setup = _thermostat_setup(config, thermostat_names, integrators is not None, temperature,
                              tau, sample_time)  # fmt: skip
    if setup is None:
        thermostat_names = []  # no target temperature known: the NVE family only
    out = Path(out) if out is not None else Path(f"integrators-{source.stem}")
    files = {}
    if names:
        files.update({kind: out / name for kind, name in INTEGRATOR_FILES.items()})
    if thermostat_names:
        files.update({kind: out / name for kind, name in THERMOSTAT_FILES.items()})
    problem = unwritable_folder(out)
    if problem is not None:
        raise ConfigError(f"output folder {out}: {problem}; choose another --out")
    existing = [str(p) for p in files.values() if p.exists()]
    if existing and not overwrite:
        raise ConfigError(f"output file(s) exist: {', '.join(existing)}; pass --overwrite or --out")
    measure_dt = ladder[-1] if dts is None else None
    _check_length(names, thermostat_names, ladder, run_span, setup, equilibrate, max_steps, units)

    state, bonds = build_system(config)
    study = Study(config, state, bonds, names, thermostat_names, ladder, run_span, measure_dt,
                  setup, out, files, overwrite)  # fmt: skip
    forcefield = ForceField(study.potentials(), skin=config.run.skin)
    for name in names:  # RESPA: both kinds of potential must be there
        if issubclass(INTEGRATORS[name], ForceSplit):
            try:
                INTEGRATORS[name](ladder[0]).split(forcefield)
            except ValueError as error:
                raise ConfigError(
                    f"--integrators {name}: {error}; the study splits bonded (fast) from pair "
                    f"(slow) potentials, so it measures {name} only on a system with bonds"
                ) from None
    for name in thermostat_names:  # built now, so bad parameters stop here
        study.thermostat(name)
    if equilibrate:
        try:
            Simulation(state, study.potentials(), VelocityVerlet(config.integrator.dt),
                       skin=config.run.skin, units=units).run(equilibrate)  # fmt: skip
        except (SimulationError, ValueError) as error:
            raise ConfigError(f"{config.source}: equilibration failed: {error}") from None
        state.step, state.time = 0, 0.0
    return study


def _positive_option(value, option: str) -> float:
    try:
        return positive(value, option)
    except (TypeError, ValueError) as error:
        raise ConfigError(str(error)) from None


def _count_option(value, option: str) -> int:
    try:
        return count(value, option, minimum=0)
    except (TypeError, ValueError) as error:
        raise ConfigError(str(error)) from None


def _parse_dts(text, dt: float) -> list[float]:
    """The dt ladder [config time] from MIN:MAX:N, a comma list, or numbers."""
    if text is None:
        return [dt / 32, dt / 16, dt / 8, dt / 4, dt / 2, dt]
    try:
        if not isinstance(text, str):
            values = [float(v) for v in text]
        elif ":" in text:
            low, high, n = text.split(":")
            low, high, n = float(low), float(high), int(n)
        else:
            values = [float(v) for v in text.split(",")]
    except (TypeError, ValueError):
        raise ConfigError(
            f"--dt-range must be MIN:MAX:N or a comma list of numbers, got {text!r}"
        ) from None
    if isinstance(text, str) and ":" in text:
        if not 2 <= n <= MAX_DTS:
            raise ConfigError(f"--dt-range needs 2 to {MAX_DTS} time steps, got {text!r}")
        positive_ends = all(math.isfinite(v) and v > 0 for v in (low, high))
        values = np.geomspace(low, high, n).tolist() if positive_ends else []
    if len(values) < 2 or not all(np.isfinite(v) and v > 0 for v in values):
        raise ConfigError(f"--dt-range needs at least two positive time steps, got {text!r}")
    if len(values) > MAX_DTS:
        raise ConfigError(f"--dt-range needs 2 to {MAX_DTS} time steps, got {len(values)}")
    return values


def _integrator_names(text, registry) -> list[str]:
    """The names to study: ``text`` (a comma list or names) checked, or the default set."""
    # Rattle follows rigid bonds that the reference run and the others cannot: not compared.
    if text is None:
        names, seen = [], set()
        for name, cls in registry.items():
            if cls not in seen and not cls.requires_constraints and not cls.splits_forces:
                names.append(name)
                seen.add(cls)
        return names
    given = text.split(",") if isinstance(text, str) else list(text)
    names = [n.strip() for n in given if n.strip()]
    unknown = [n for n in names if n not in registry]
    if unknown or not names:
        raise ConfigError(
            f"--integrators: unknown {', '.join(unknown) or '(none given)'}; "
            f"known: {', '.join(registry)}"
        )
    constrained = [n for n in names if registry[n].requires_constraints]
    if constrained:
        raise ConfigError(
            f"--integrators: {', '.join(constrained)} needs rigid bonds, which the NVE "
            "comparison cannot follow; md integrators does not measure it"
        )
    return names


def _thermostat_setup(config, names, named: bool, temperature, tau, sample_time):
    """Target temperature, coupling time and run lengths of the thermostat comparison.

    The temperature is ``temperature``, else the config's thermostat target,
    else [system] temperature; tau is ``tau``, else the config's tau (or
    1/friction), else 100 dt. Returns None when no temperature is known and
    no thermostat was named (``named``); raises ConfigError if one was.
    """
    t = config.units.config_time
    entry = config.integrator
    dt = entry.dt
    if temperature is None:
        temperature = entry.get("temperature", config.system.temperature)
    if temperature is None:
        if names and named:
            raise ConfigError(
                f"thermostats ({', '.join(names)}) need a target temperature: pass "
                "--temperature, or give [integrator] temperature or [system] temperature"
            )
        return None
    temperature = _positive_option(temperature, "--temperature")
    if tau is not None:
        tau = _positive_option(tau, "--tau") * t
    elif "tau" in entry:
        tau = entry.get("tau")
    elif entry.get("friction"):
        tau = 1.0 / entry.get("friction")
    else:
        tau = 100 * dt
    if sample_time is not None:
        sample_time = _positive_option(sample_time, "--sample-time") * t
    else:
        sample_time = 4000 * dt
    # Capped before rounding (an infinite quotient has no int); the step budget refuses them.
    n_equilibrate, n_sample = min(10 * tau / dt, 1e300), min(sample_time / dt, 1e300)
    return ThermostatSetup(
        temperature=float(temperature),
        tau=tau,
        n_equilibrate=max(1, round(n_equilibrate)),
        n_sample=max(10, round(n_sample)),
    )


def _build_thermostat(config, name: str, setup: ThermostatSetup, bonds):
    """Thermostat ``name`` at the study's target and coupling, built as ``md run`` builds one."""
    cls = INTEGRATORS[name]
    values = {"dt": config.integrator.dt, "temperature": setup.temperature,
              "kB": config.units.kB, **cls.coupling(setup.tau)}  # fmt: skip
    if cls.stochastic:
        values["seed"] = [0 if config.seed is None else config.seed, 1]
    if "constraints" in config.integrator:
        values["constraints"] = config.integrator.get("constraints")
    return integrator_from_config(PluginEntry(name, values), config.source, bonds)


def _check_length(study_names, thermostat_names, dts, span, setup, equilibrate, max_steps,
                  units) -> None:  # fmt: skip
    """Raise ConfigError if the study's runs add up to more than ``max_steps`` steps."""

    def steps(dt: float) -> float:
        return max(1.0, span / dt)

    reference = min(dts) / 8
    total = float(equilibrate)
    if study_names:
        total += steps(reference) + steps(reference / 2)
        for name in study_names:
            if INTEGRATORS[name].adaptive:  # output steps of span / 10, per tolerance
                total += 10.0 * len(TOLERANCES)
            else:  # the ladder, then the stability scan's doublings
                total += sum(steps(dt) for dt in dts)
                total += sum(steps(max(dts) * 2**k) for k in range(1, 7))
    if thermostat_names:
        total += len(thermostat_names) * (setup.n_equilibrate + setup.n_sample)
    if total <= max_steps:
        return
    t, label = units.config_time, units.config_time_label
    reasons = []
    if study_names and steps(reference / 2) > max_steps / 10:
        reasons.append(
            f"a span (--time) of {span / t:g} {label} takes {steps(reference / 2):.3g} steps in "
            f"the finer reference run alone (dt {reference / 2 / t:.3g} {label}, the smallest "
            "dt / 16): choose a shorter --time or larger time steps (--dt-range)"
        )
    if thermostat_names and setup.n_equilibrate + setup.n_sample > max_steps / 10:
        reasons.append(
            f"each thermostat runs {setup.n_equilibrate:.3g} steps to equilibrate (10 tau, "
            f"tau {setup.tau / t:g} {label}) and {setup.n_sample:.3g} sampled: choose a "
            "shorter --tau or --sample-time"
        )
    if equilibrate > max_steps / 10:
        reasons.append(f"--equilibrate {equilibrate} is that many steps: choose fewer")
    raise ConfigError(
        f"the study would take {total:.3g} steps in all, more than the {max_steps:.3g} that "
        f"can finish in reasonable time; {'; '.join(reasons) or 'measure fewer integrators'}"
    )
