"""Measure integrators instead of describing them: order, stability, energy, cost.

``compare_integrators`` runs one system under each integrator across a
ladder of time steps, all to the same final time, and measures:

order
    Slope of log(global position error at the final time) against log(dt)
    (not reported for adaptive integrators, whose error follows their tolerance),
    fitted by least squares over the stable runs whose error is above the
    round-off floor. The error is the RMS distance (minimum image not needed:
    positions are continuous) to a reference run with RK4 (or velocity
    Verlet when RK4 is not registered) at a step eight times finer than the
    smallest dt studied. Keep the span short on chaotic systems (an LJ
    liquid decorrelates within a few time units), or the error measures
    Lyapunov divergence rather than truncation.
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

This module is library code (no printing); ``md integrators`` prints the
table and writes the CSV and plots.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from md.analysis import kinetic_energy
from md.forcefield import ForceField
from md.neighbors import NonFiniteError
from md.simulation import Simulation, SimulationError
from md.state import State

logger = logging.getLogger(__name__)

CSV_COLUMNS = (
    "integrator",
    "dt_max_stable",
    "order",
    "energy_drift",
    "energy_fluctuation",
    "evals_per_time",
    "wall_per_time",
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

    def row(self) -> dict:
        return {
            "integrator": self.name,
            "dt_max_stable": self.dt_max_stable,
            "order": self.order,
            "energy_drift": self.energy_drift,
            "energy_fluctuation": self.energy_fluctuation,
            "evals_per_time": self.evals_per_time,
            "wall_per_time": self.wall_per_time,
        }


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
    samples: int = 200,
    stability_tolerance: float = 0.5,
    max_doublings: int = 6,
    measure_dt: float | None = None,
    progress: Callable[[str], None] | None = None,
) -> list[IntegratorReport]:
    """Run every integrator over the dt ladder and measure it.

    Parameters
    ----------
    make_state : callable
        Returns a fresh copy of the initial State for every run.
    potentials_factory : callable
        Returns fresh potentials for every run.
    integrators : dict
        Name -> factory ``f(dt)`` building the integrator.
    dts : sequence of float
        Time steps to study [time], at least two.
    span : float
        Simulated time of every run [time]; each dt is adjusted down so a
        whole number of steps lands on ``span``.
    reference : callable, optional
        Factory of the reference integrator (default: the first of
        ``integrators`` named "rk4", else the first given).
    reference_dt : float, optional
        Its step (default: min(dts) / 8).
    samples : int
        Energy samples per run (for drift and fluctuation).
    measure_dt : float, optional
        The dt at which drift, fluctuation and cost are compared (default:
        the middle of the ladder); an integrator unstable there is measured
        at its largest stable dt below it.
    """
    dts = sorted(float(dt) for dt in dts)
    if len(dts) < 2 or dts[0] <= 0:
        raise ValueError(f"need at least two positive time steps, got {dts}")
    if not span > 0:
        raise ValueError(f"span must be positive, got {span}")
    if reference is None:
        reference = integrators.get("rk4") or next(iter(integrators.values()))
    reference_dt = reference_dt or dts[0] / 8
    say = progress or (lambda message: None)
    say(f"reference run: dt = {reference_dt:g}")
    ref = _run(make_state, potentials_factory, reference, reference_dt, span, skin, units, samples)
    if not ref.stable:
        raise SimulationError(0, f"the reference run failed: {ref.message}")
    reference_positions = ref.final_positions

    reports = []
    for name, factory in integrators.items():
        runs = []
        for dt in dts:
            say(f"{name}: dt = {dt:g}")
            runs.append(
                _run(make_state, potentials_factory, factory, dt, span, skin, units, samples,
                     reference_positions, stability_tolerance)
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
                _run(make_state, potentials_factory, factory, dt, span, skin, units, samples,
                     reference_positions, stability_tolerance)
            )  # fmt: skip
        report = _report(name, runs, dts, span, measure_dt or dts[len(dts) // 2])
        if getattr(factory, "adaptive", False):
            report.order = math.nan  # the error follows the tolerance, not dt
        reports.append(report)
    return reports


def _run(make_state, potentials_factory, factory, dt, span, skin, units, samples,
         reference_positions=None, stability_tolerance=0.5) -> RunRecord:  # fmt: skip
    from integrators.base import ConvergenceError

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
        return record
    record.final_positions = state.positions.copy()
    if reference_positions is not None:
        diff = state.positions - reference_positions
        record.error = float(np.sqrt(np.mean(np.sum(diff * diff, axis=1))))
    return record


def _report(name, runs, dts, span, measure_dt) -> IntegratorReport:
    stable = [r for r in runs if r.stable]
    dt_max_stable = max((r.dt for r in stable), default=math.nan)
    fit = [r for r in runs if r.stable and r.dt <= dts[-1] * 1.0000001 and r.error > 1e-11]
    order = math.nan
    if len(fit) >= 2:
        order = float(np.polyfit(np.log([r.dt for r in fit]), np.log([r.error for r in fit]), 1)[0])
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
    import csv

    with open(path, "x", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=[*CSV_COLUMNS, "measured_at_dt"])
        writer.writeheader()
        for report in reports:
            writer.writerow({**report.row(), "measured_at_dt": report.reference_dt})


def plot_error_vs_dt(reports: Sequence[IntegratorReport], path, time_label: str = "") -> None:
    """Log-log plot of the global position error against dt, with fitted slopes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.8))
    for report in reports:
        points = [(r.dt, r.error) for r in report.runs if r.stable and r.error > 0]
        if not points:
            continue
        dts, errors = zip(*sorted(points), strict=True)
        label = f"{report.name} (slope {report.order:.2f})"
        ax.loglog(dts, errors, "o-", label=label)
    ax.set_xlabel(f"time step dt {time_label}".strip())
    ax.set_ylabel("RMS position error at the final time")
    ax.set_title("Global error against a fine-step reference")
    ax.legend(fontsize="small")
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_energy_vs_time(reports: Sequence[IntegratorReport], path, labels=None) -> None:
    """Total energy per atom against time for each integrator at its measuring dt."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
