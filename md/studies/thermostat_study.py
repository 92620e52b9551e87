"""Measure thermostats on what they are for: ``compare_thermostats``, each at one dt
after an equilibration, on:

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
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from integrators.base import Integrator
from md._files import write_csv_rows
from md.errors import ConvergenceError, NonFiniteError, SimulationError
from md.simulation import Simulation
from md.state import State
from md.studies.plot_style import pyplot

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
        _measure(
            report,
            rows,
            sim,
            wall,
            sim.forcefield.n_evaluations - evaluations_before,
            integrator.dt * int(n_sample),
        )
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
    plt = pyplot()

    labels = labels or {}
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4.2))
    for report in reports:
        if not len(report.times):
            continue
        left.plot(report.times, report.temperatures, lw=0.8, label=report.name)
        x = report.potentials - report.potentials.mean()
        n = len(x)
        lags = min(n - 1, max(10, n // 4))
        acf = [1.0] + [
            float(np.dot(x[:-k], x[k:]) / np.dot(x, x) * n / (n - k)) for k in range(1, lags)
        ]
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
