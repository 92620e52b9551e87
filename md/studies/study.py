"""The study of a config: what ``md integrators`` measures.

:func:`prepare_study` builds what ``md integrators`` measures from a config
(validating every option and writing nothing) and :meth:`Study.run` measures
it and writes the CSV files and plots; the command prints the tables. This
module is library code (no printing).
"""

from __future__ import annotations

import functools
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from integrators import INTEGRATORS, VelocityVerlet
from integrators.base import ForceSplit
from md._checks import count, positive
from md._files import removed_on_error, unwritable_folder
from md.assemble import build_potentials
from md.config import Config, PluginEntry, build_system, integrator_from_config, load_config
from md.errors import ConfigError, SimulationError
from md.forcefield import ForceField
from md.simulation import Simulation
from md.state import State
from md.studies.integrator_study import (
    TOLERANCES,
    IntegratorReport,
    compare_integrators,
    plot_energy_vs_time,
    plot_error_vs_dt,
    plot_work_precision,
    write_csv,
    write_work_precision_csv,
)
from md.studies.thermostat_study import (
    ThermostatReport,
    compare_thermostats,
    plot_thermostats,
    write_thermostat_csv,
)
from md.topology import Topology

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
                make_state=self.state.copy,
                potentials_factory=self.potentials,
                integrators={name: INTEGRATORS[name] for name in self.names},
                dts=self.dts,
                span=self.span,
                skin=skin,
                units=units,
                reference=INTEGRATORS[self.reference],
                measure_dt=self.measure_dt,
                progress=progress,
            )
        thermostat_reports: list[ThermostatReport] = []
        if self.thermostat_names:
            setup = self.setup
            thermostat_reports = compare_thermostats(
                make_state=self.state.copy,
                potentials_factory=self.potentials,
                thermostats={
                    n: functools.partial(self.thermostat, n) for n in self.thermostat_names
                },
                target_temperature=setup.temperature,
                n_equilibrate=setup.n_equilibrate,
                n_sample=setup.n_sample,
                skin=skin,
                units=units,
                progress=progress,
            )
        self.write(reports, thermostat_reports)
        return StudyResults(reports, thermostat_reports, dict(self.files))

    def write(self, reports, thermostat_reports) -> None:
        """Write the CSV files and plots of both comparisons into ``out``.

        Files that exist are replaced only with ``overwrite``; if writing
        fails, the files this call wrote are removed before the error is raised.
        """
        units, files = self.config.units, self.files
        labels = {
            name: f"[{units.labels[name]}]" for name in ("time", "energy", "length", "temperature")
        }
        writers = []
        if reports:
            writers += [
                (files["csv"], lambda path: write_csv(reports, path)),
                (files["work_csv"], lambda path: write_work_precision_csv(reports, path)),
                (
                    files["error"],
                    lambda path: plot_error_vs_dt(reports, path, f"[{units.config_time_label}]"),
                ),
                (files["energy"], lambda path: plot_energy_vs_time(reports, path, labels)),
                (files["work"], lambda path: plot_work_precision(reports, path, labels)),
            ]
        if thermostat_reports:
            writers += [
                (files["thermostats"], lambda path: write_thermostat_csv(thermostat_reports, path)),
                (
                    files["thermostats_plot"],
                    lambda path: plot_thermostats(thermostat_reports, path, labels),
                ),
            ]
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
    >>> from md.studies import prepare_study
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
    if config.rigid is not None:  # its integrators would move the constituents apart
        raise ConfigError(
            f"{config.source}: [rigid]: this study moves atoms one by one; the rotational "
            "family of rigid bodies is md.studies.rigid_study.prepare_rigid_study's"
        )
    units = config.units
    t = units.config_time
    config_dt = config.integrator.dt / t
    ladder = [dt * t for dt in parse_dts(dts, config_dt)]
    run_span = (100 * config_dt if span is None else positive_option(span, "--time")) * t
    names = _integrator_names(integrators, INTEGRATORS)
    equilibrate = count_option(equilibrate, "--equilibrate")
    # Thermostats are measured apart: sampling at a temperature, not order in dt.
    thermostat_names = [n for n in names if INTEGRATORS[n].thermostat]
    names = [n for n in names if n not in thermostat_names]
    setup = _thermostat_setup(
        config, thermostat_names, integrators is not None, temperature, tau, sample_time
    )
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
    study = Study(
        config,
        state,
        bonds,
        names,
        thermostat_names,
        ladder,
        run_span,
        measure_dt,
        setup,
        out,
        files,
        overwrite,
    )
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
            Simulation(
                state,
                study.potentials(),
                VelocityVerlet(config.integrator.dt),
                skin=config.run.skin,
                units=units,
            ).run(equilibrate)
        except (SimulationError, ValueError) as error:
            raise ConfigError(f"{config.source}: equilibration failed: {error}") from None
        state.step, state.time = 0, 0.0
    return study


def positive_option(value, option: str) -> float:
    try:
        return positive(value, option)
    except (TypeError, ValueError) as error:
        raise ConfigError(str(error)) from None


def count_option(value, option: str) -> int:
    try:
        return count(value, option, minimum=0)
    except (TypeError, ValueError) as error:
        raise ConfigError(str(error)) from None


def parse_dts(text, dt: float) -> list[float]:
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
    temperature = positive_option(temperature, "--temperature")
    if tau is not None:
        tau = positive_option(tau, "--tau") * t
    elif "tau" in entry:
        tau = entry.get("tau")
    elif entry.get("friction"):
        tau = 1.0 / entry.get("friction")
    else:
        tau = 100 * dt
    if sample_time is not None:
        sample_time = positive_option(sample_time, "--sample-time") * t
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
    values = {
        "dt": config.integrator.dt,
        "temperature": setup.temperature,
        "kB": config.units.kB,
        **cls.coupling(setup.tau),
    }
    if cls.stochastic:
        values["seed"] = [0 if config.seed is None else config.seed, 1]
    if "constraints" in config.integrator:
        values["constraints"] = config.integrator.get("constraints")
    return integrator_from_config(PluginEntry(name, values), config.source, bonds)


def _check_length(
    study_names, thermostat_names, dts, span, setup, equilibrate, max_steps, units
) -> None:
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
