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

Thermostats are measured by :func:`md.studies.thermostat_study.compare_thermostats`;
:func:`md.studies.study.prepare_study` builds what ``md integrators`` measures
from a config. This module is library code (no printing).
"""

from __future__ import annotations

import functools
import inspect
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from integrators.base import DeclaresAdaptive, DeclaresOrder
from md._files import write_csv_rows
from md.errors import ConvergenceError, NonFiniteError, SimulationError
from md.forcefield import ForceField
from md.simulation import Simulation
from md.state import State
from md.studies.plot_style import grouped, legend_outside, pyplot, reference_slopes, styles
from md.thermo import kinetic_energy

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
                record = _run(
                    *args,
                    at_tol,
                    dt,
                    span,
                    skin,
                    units,
                    samples,
                    reference_positions,
                    stability_tolerance,
                )
                record.tol = tol
                runs.append(record)
        else:
            for dt in dts:
                say(f"{name}: dt = {dt:g}")
                runs.append(
                    _run(
                        *args,
                        factory,
                        dt,
                        span,
                        skin,
                        units,
                        samples,
                        reference_positions,
                        stability_tolerance,
                    )
                )
            dt = dts[-1]
            doublings = 0
            while runs[-1].stable and doublings < max_doublings:
                dt *= 2.0
                doublings += 1
                if dt > span:
                    break
                say(f"{name}: stability scan dt = {dt:g}")
                runs.append(
                    _run(
                        *args,
                        factory,
                        dt,
                        span,
                        skin,
                        units,
                        samples,
                        reference_positions,
                        stability_tolerance,
                    )
                )
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
        notes.insert(
            0,
            f"no order: only {len(above)} point(s) above the reference's error "
            f"floor (an order needs {MIN_FIT_POINTS})",
        )
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
        notes.insert(
            0,
            f"no order: {reason}no {MIN_FIT_POINTS} successive points agree on a "
            f"slope within {slope_tolerance:g} (local slopes {slopes})",
        )
        return math.nan, [], "; ".join(notes)
    i, j, slope = best
    if i:
        kind = (
            "an error floor (round-off or solver tolerance)"
            if local[i - 1] < slope
            else ("depart from the trend")
        )
        what = f"reach {kind}" if kind.startswith("an") else kind
        notes.insert(
            0,
            f"the finest {i} point(s) (dt <= {steps[above[i - 1]]:.3g}) {what} "
            f"(local slope {local[i - 1]:.3g}): left out",
        )
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


def _run(
    make_state,
    potentials_factory,
    factory,
    dt,
    span,
    skin,
    units,
    samples,
    reference_positions=None,
    stability_tolerance=0.5,
) -> RunRecord:
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
    base = max(
        (r for r in stable if r.dt <= measure_dt * 1.0000001), key=lambda r: r.dt, default=None
    )
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
            "integrator": report.name,
            "dt": run.dt,
            "tol": run.tol,
            "stable": run.stable,
            "position_error": run.error,
            "max_energy_error": run.max_energy_error,
            "force_evaluations": run.evaluations if run.stable else math.nan,
            "wall": run.wall if run.stable else math.nan,
            "in_order_fit": run.in_fit,
        }
        for report in reports
        for run in report.runs
    )
    write_csv_rows(path, WORK_PRECISION_COLUMNS, rows)


def plot_error_vs_dt(reports: Sequence[IntegratorReport], path, time_label: str = "") -> None:
    """Log-log global position error against dt, one colour and marker per integrator.

    Integrators are grouped by family (line style and hue; the legend lists
    them family by family, outside the axes). Filled markers are the points the
    order fit used, hollow ones the rest; dashed grey lines are reference slopes
    for the orders expected; a dotted line is the reference's error floor.
    """
    plt = pyplot()
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
        ax.loglog(
            dts,
            errors,
            ls=s["linestyle"],
            color=s["color"],
            lw=0.9,
            label=f"{name} (order {order}, {report.fit_points} pts)",
        )
        for fitted in (True, False):
            chosen = [(d, e) for d, e, u in points if u == fitted]
            if chosen:
                ax.loglog(
                    *zip(*chosen, strict=True),
                    ls="none",
                    marker=s["marker"],
                    color=s["color"],
                    mfc=s["color"] if fitted else "white",
                    ms=5,
                    mew=1.0,
                )
    expected = [r.expected_order for r in shown if math.isfinite(r.expected_order)]
    reference_slopes(ax, xs, ys, expected or [1, 2, 4])
    floors = [r.floor for r in reports if math.isfinite(r.floor)]
    if floors:
        ax.axhline(floors[0], color="k", ls=":", lw=0.8, label="reference error floor (x10)")
    ax.set_xlabel(f"time step dt {time_label}".strip())
    ax.set_ylabel("RMS position error at the final time")
    ax.set_title(
        "Global error against a Richardson-checked reference\n"
        "(filled: fitted for the order; hollow: left out; grey: reference slopes)",
        fontsize="medium",
    )
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
    plt = pyplot()
    fig, axes = plt.subplots(2, 2, figsize=(12.5, 8.5))
    measures = (
        ("max_energy_error", "max |E(t) - E(0)| per atom"),
        ("error", "RMS position error at the final time"),
    )
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
                axes[row, column].loglog(
                    x,
                    y,
                    ls=s["linestyle"],
                    marker=s["marker"],
                    ms=4,
                    color=s["color"],
                    lw=0.9,
                    label=name,
                )
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
    plt = pyplot()

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
