"""``md integrators CONFIG.toml``: measure integrators and thermostats on one system.

Order of accuracy, stability limit, energy drift and cost per integrator
(:func:`md.integrator_study.compare_integrators`), and for thermostats the
temperature error and sampling efficiency
(:func:`md.integrator_study.compare_thermostats`), with CSV files and plots.
"""

from __future__ import annotations

import inspect
import math
from pathlib import Path

import numpy as np

from integrators import INTEGRATORS, VelocityVerlet
from integrators.rattle import BondConstraints
from md.cli._common import EXIT_BAD_INPUT, EXIT_OK, fail
from md.config import build_system, load_config, potential_from_config
from md.damping import prepare_damping
from md.errors import ConfigError
from md.integrator_study import (
    compare_integrators,
    compare_thermostats,
    plot_energy_vs_time,
    plot_error_vs_dt,
    plot_thermostats,
    plot_work_precision,
    write_csv,
    write_thermostat_csv,
    write_work_precision_csv,
)
from md.simulation import Simulation, SimulationError


def add_parser(subparsers) -> None:
    """Add ``md integrators`` and its options."""
    study = subparsers.add_parser(
        "integrators",
        help="measure integrators on a system: order, stability, energy drift, cost",
    )
    study.add_argument("config", type=Path, help="TOML config describing the system")
    study.add_argument(
        "--integrators", help="comma-separated names (default: every registered integrator)"
    )
    study.add_argument(
        "--dt-range",
        help="time steps in config time units: MIN:MAX:N (log-spaced) or a comma list "
        "(default: the config dt times 1/32, 1/16, 1/8, 1/4, 1/2, 1)",
    )
    study.add_argument(
        "--time", type=float, help="simulated span of every run, config time units (default 100 dt)"
    )
    study.add_argument(
        "--equilibrate",
        type=int,
        default=200,
        help="velocity Verlet steps at the config dt before the study, so it starts from a "
        "generic state rather than a force-free lattice (default 200)",
    )
    study.add_argument(
        "--temperature",
        type=float,
        help="thermostats' target, config temperature units (default: the config's thermostat "
        "temperature or [system] temperature)",
    )
    study.add_argument(
        "--tau",
        type=float,
        help="thermostats' coupling time (Langevin: 1/friction), config time units "
        "(default: the config's, else 100 dt)",
    )
    study.add_argument(
        "--sample-time",
        type=float,
        help="time each thermostat is sampled after equilibrating for 10 tau, config time "
        "units (default 4000 dt)",
    )
    study.add_argument(
        "--damping",
        action="store_true",
        help="measure numerical damping instead: amplitude ratio and phase per step on a "
        "harmonic bond over omega*dt from 0.01 to 100, against each method's theory "
        "(damping.csv, damping.png); default integrators: verlet and the implicit family",
    )
    study.add_argument(
        "--omega-dt", help="with --damping: the omega*dt ladder, MIN:MAX:N or a comma list"
    )
    study.add_argument("--out", type=Path, help="output folder (default integrators-<config>)")
    study.add_argument("--overwrite", action="store_true", help="replace existing output files")


def _parse_dts(text: str | None, dt: float) -> list[float]:

    if text is None:
        return [dt / 32, dt / 16, dt / 8, dt / 4, dt / 2, dt]
    try:
        if ":" in text:
            low, high, count = text.split(":")
            values = np.geomspace(float(low), float(high), int(count)).tolist()
        else:
            values = [float(v) for v in text.split(",")]
    except ValueError:
        raise ConfigError(
            f"--dt-range must be MIN:MAX:N or a comma list of numbers, got {text!r}"
        ) from None
    if len(values) < 2 or not all(np.isfinite(v) and v > 0 for v in values):
        raise ConfigError(f"--dt-range needs at least two positive time steps, got {text!r}")
    return values


def main(args) -> int:
    """Body of ``md integrators``; returns the exit code."""

    if args.damping:
        return _damping(args)
    try:
        config = load_config(args.config)
        units = config.units
        config_dt = config.integrator["dt"] / units.config_time
        dts = [dt * units.config_time for dt in _parse_dts(args.dt_range, config_dt)]
        span = (args.time if args.time is not None else 100 * config_dt) * units.config_time
        if not span > 0:
            raise ConfigError(f"--time must be positive, got {args.time}")
        names = _integrator_names(args.integrators, INTEGRATORS)
        if args.equilibrate < 0:
            raise ConfigError(f"--equilibrate must be >= 0, got {args.equilibrate}")
        # Thermostats are measured apart: sampling at a temperature, not order in dt.
        thermostat_names = [n for n in names if INTEGRATORS[n].thermostat]
        names = [n for n in names if n not in thermostat_names]
        thermostats = _thermostat_setup(args, config, thermostat_names, INTEGRATORS)
        if thermostats is None and args.integrators is None:
            thermostat_names = []  # no target temperature known: the NVE family only
        state, bonds = build_system(config)

        def make_potentials():
            return [
                potential_from_config(entry, state.type_names, config.source, index, bonds)
                for index, entry in enumerate(config.potentials)
            ]

        if args.equilibrate:
            try:
                Simulation(
                    state, make_potentials(), VelocityVerlet(config.integrator["dt"]),
                    skin=config.run.skin, units=units,
                ).run(args.equilibrate)  # fmt: skip
            except (SimulationError, ValueError) as error:
                raise ConfigError(f"{config.source}: equilibration failed: {error}") from None
            state.step, state.time = 0, 0.0
        out = args.out or Path(f"integrators-{args.config.stem}")
        files = {}
        if names:
            files["csv"] = out / "integrators.csv"
            files["error"] = out / "error_vs_dt.png"
            files["energy"] = out / "energy_vs_time.png"
            files["work_csv"] = out / "work_precision.csv"
            files["work"] = out / "work_precision.png"
        if thermostat_names:
            files["thermostats"] = out / "thermostats.csv"
            files["thermostats_plot"] = out / "thermostats.png"
        existing = [str(p) for p in files.values() if p.exists()]
        if existing and not args.overwrite:
            raise ConfigError(
                f"output file(s) exist: {', '.join(existing)}; pass --overwrite or --out"
            )
        if thermostat_names:
            # Built now, so bad parameters (tau, constraints) stop here, before any output.
            built = {n: thermostats["factory"](n, bonds)() for n in thermostat_names}
            factories = {n: (lambda n=n: built[n]) for n in thermostat_names}
    except ConfigError as error:
        fail(str(error))
        return EXIT_BAD_INPUT

    def factory(name):
        # The class itself: compare_integrators calls it with dt (and tol: the adaptive
        # ones' ladder, the implicit ones' solver tolerance).
        return INTEGRATORS[name]

    label = units.config_time_label
    progress = lambda message: print(f"  {message}", flush=True)  # noqa: E731
    out.mkdir(parents=True, exist_ok=True)
    for path in files.values():
        if path.exists():
            path.unlink()
    if names:
        print(
            f"md integrators: {state.n_atoms} atoms, span {span / units.config_time:g} {label}, "
            f"dt {', '.join(f'{dt / units.config_time:g}' for dt in dts)} {label}"
        )
        reports = compare_integrators(
            make_state=state.copy,
            potentials_factory=make_potentials,
            integrators={name: factory(name) for name in names},
            dts=dts,
            span=span,
            skin=config.run.skin,
            units=units,
            reference=factory("yoshida6" if "yoshida6" in INTEGRATORS else "rk4"),
            measure_dt=dts[-1] if args.dt_range is None else None,
            progress=progress,
        )
        write_csv(reports, files["csv"])
        write_work_precision_csv(reports, files["work_csv"])
        plot_error_vs_dt(reports, files["error"], f"[{label}]")
        plot_energy_vs_time(reports, files["energy"], {"time": f"[{units.labels['time']}]"})
        plot_work_precision(
            reports, files["work"],
            {"energy": f"[{units.labels['energy']}]", "length": f"[{units.labels['length']}]"},
        )  # fmt: skip
        _print_study_table(reports, units)
        written = ("csv", "work_csv", "error", "energy", "work")
        print(f"Wrote {', '.join(str(files[k]) for k in written)}")
    if thermostat_names:
        t = units.config_time
        n_equilibrate, n_sample = thermostats["n_equilibrate"], thermostats["n_sample"]
        print(
            f"md integrators (thermostats): {state.n_atoms} atoms, T = "
            f"{thermostats['temperature']:g} {units.labels['temperature']}, dt "
            f"{config_dt:g} {label}, tau {thermostats['tau'] / t:g} {label}, "
            f"{n_equilibrate} steps to equilibrate, {n_sample} sampled"
        )
        thermo_reports = compare_thermostats(
            make_state=state.copy,
            potentials_factory=make_potentials,
            thermostats=factories,
            target_temperature=thermostats["temperature"],
            n_equilibrate=n_equilibrate,
            n_sample=n_sample,
            skin=config.run.skin,
            units=units,
            progress=progress,
        )
        write_thermostat_csv(thermo_reports, files["thermostats"])
        plot_thermostats(
            thermo_reports,
            files["thermostats_plot"],
            {"time": f"[{units.labels['time']}]",
             "temperature": f"[{units.labels['temperature']}]"},
        )  # fmt: skip
        _print_thermostat_table(thermo_reports, units)
        print(f"Wrote {files['thermostats']}, {files['thermostats_plot']}")
    return EXIT_OK


def _damping(args) -> int:
    """``md integrators CONFIG --damping``: the damping measurement and its table."""
    try:
        study = prepare_damping(args.config, args.integrators, args.omega_dt, args.out,
                                args.overwrite)  # fmt: skip
    except ConfigError as error:
        fail(str(error))
        return EXIT_BAD_INPUT
    print(
        f"md integrators --damping: a harmonic bond at dt {study.time_label}, omega dt "
        f"{min(study.omega_dts):g} to {max(study.omega_dts):g} ({len(study.omega_dts)} points)"
    )
    rows = study.run(progress=lambda message: print(f"  {message}", flush=True))
    shown = [z for z in (0.01, 0.1, 1.0, 10.0, 100.0)
             if any(abs(r.omega_dt - z) < 1e-9 * z for r in rows)]  # fmt: skip
    print(f"{'integrator':<18}" + "".join(f"{f'|rho| @ {z:g}':>15}" for z in shown)
          + f"{'max |d - d_th| / d_th':>24}")  # fmt: skip
    for name in study.names:
        mine = [r for r in rows if r.integrator == name]
        cells = []
        for z in shown:
            row = next(r for r in mine if abs(r.omega_dt - z) < 1e-9 * z)
            cells.append(f"{row.measured:>15.6g}" if math.isfinite(row.measured) else f"{'-':>15}")
        deviations = [
            abs(r.damping_measured - r.damping_theory) / r.damping_theory
            for r in mine
            if math.isfinite(r.measured) and r.damping_theory > 1e-9
        ]
        worst = f"{max(deviations):.2e}" if deviations else "(no damping)"
        print(f"{name:<18}" + "".join(cells) + f"{worst:>24}")
        for row in mine:
            if row.note and not row.note.startswith("unstable"):
                print(f"  {name} at omega dt {row.omega_dt:.3g}: {row.note}")
    print(
        "(|rho|: amplitude kept per step, measured; d = 1 - |rho|, the damping per step, "
        "against theory where the method damps; '-': beyond the stability limit)"
    )
    print(f"Wrote {study.files['csv']}, {study.files['plot']}")
    return EXIT_OK


def _thermostat_setup(args, config, names, registry) -> dict | None:
    """Target temperature, coupling time, run lengths and a factory for the thermostat study.

    The temperature is --temperature, else the config's thermostat target,
    else [system] temperature; tau is --tau, else the config's tau (or
    1/friction), else 100 dt. Returns None when no temperature is known and
    no thermostat was named; raises ConfigError if one was named.
    """

    units = config.units
    t = units.config_time
    entry = config.integrator
    dt = entry["dt"]
    temperature = args.temperature
    if temperature is None:
        temperature = entry.get("temperature", config.system.temperature)
    if temperature is None:
        if names and args.integrators is not None:
            raise ConfigError(
                f"thermostats ({', '.join(names)}) need a target temperature: pass "
                "--temperature, or give [integrator] temperature or [system] temperature"
            )
        return None
    if not (math.isfinite(temperature) and temperature > 0):
        raise ConfigError(f"--temperature must be positive, got {temperature}")
    if args.tau is not None:
        if not (math.isfinite(args.tau) and args.tau > 0):
            raise ConfigError(f"--tau must be positive, got {args.tau}")
        tau = args.tau * t
    elif "tau" in entry:
        tau = entry["tau"]
    elif entry.get("friction"):
        tau = 1.0 / entry["friction"]
    else:
        tau = 100 * dt
    sample_time = args.sample_time * t if args.sample_time is not None else 4000 * dt
    if not sample_time > 0:
        raise ConfigError(f"--sample-time must be positive, got {args.sample_time}")
    seed = 0 if config.seed is None else config.seed

    def factory(name, bonds):
        cls = registry[name]
        accepted = inspect.signature(cls).parameters

        def build():
            params = {"dt": dt, "temperature": temperature, "kB": units.kB}
            params["friction" if "friction" in accepted else "tau"] = (
                1.0 / tau if "friction" in accepted else tau
            )
            if cls.stochastic:
                params["seed"] = [seed, 1]
            if "constraints" in entry:
                try:
                    params["constraints"] = BondConstraints.from_config(entry["constraints"], bonds)
                except ValueError as error:
                    raise ConfigError(
                        f"{config.source}: [integrator.constraints]: {error}"
                    ) from None
            try:
                return cls(**params)
            except (TypeError, ValueError) as error:
                raise ConfigError(f"{name}: {error}") from None

        return build

    return {
        "temperature": float(temperature),
        "tau": tau,
        "n_equilibrate": max(1, round(10 * tau / dt)),
        "n_sample": max(10, round(sample_time / dt)),
        "factory": factory,
    }


def _print_thermostat_table(reports, units) -> None:
    t = units.config_time
    header = (
        f"{'thermostat':<18}{'T_mean':>10}{'T-T0':>11}{'+-':>9}{'PE/atom':>11}"
        f"{'tau_PE':>9}{'samples/t':>11}{'drift/atom/t':>14}{'evals/t':>9}{'wall s/t':>10}"
    )
    print(header)
    for r in reports:
        if r.message:
            print(f"{r.name:<18} failed: {r.message}")
            continue
        print(
            f"{r.name:<18}{r.mean_temperature:>10.5g}{r.temperature_error:>11.3e}"
            f"{r.temperature_stderr:>9.2e}{r.mean_potential_energy:>11.5g}"
            f"{r.potential_autocorrelation_time / t:>9.4g}{r.sampling_efficiency * t:>11.4g}"
            f"{r.conserved_drift * t:>14.3e}{r.evals_per_time * t:>9.4g}"
            f"{r.wall_per_time * t:>10.4g}{'' if r.canonical else '  (not canonical)'}"
        )
    print(
        f"(T in {units.labels['temperature']}, times in config units, "
        f"{units.config_time_label}; samples/t = independent potential-energy samples per unit "
        "time, 1/(2 tau_PE); drift of kinetic + potential + heat-bath energy)"
    )


def _integrator_names(text, registry) -> list[str]:

    # Rattle follows rigid bonds that the reference run and the others cannot: not compared.
    if text is None:
        names, seen = [], set()
        for name, cls in registry.items():
            if cls not in seen and not cls.requires_constraints and not cls.splits_forces:
                names.append(name)
                seen.add(cls)
        return names
    names = [n.strip() for n in text.split(",") if n.strip()]
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


def _print_study_table(reports, units) -> None:
    t = units.config_time
    header = (
        f"{'integrator':<18}{'order':>7}{'expect':>7}{'fit pts':>8}{'dt_max_stable':>15}"
        f"{'drift/atom/t':>14}{'fluct/atom':>12}{'max dE/atom':>12}{'evals/t':>10}"
        f"{'wall s/t':>10}{'at dt':>9}"
    )
    print(header)
    for r in reports:
        run = r.measured_run()
        order = f"{r.order:.2f}" if math.isfinite(r.order) else "-"
        order += "/tol" if r.order_vs == "tol" and math.isfinite(r.order) else ""
        expected = "-" if math.isnan(r.expected_order) else f"{r.expected_order:g}"
        print(
            f"{r.name:<18}{order:>7}{expected:>7}{r.fit_points:>8}{r.dt_max_stable / t:>15.4g}"
            f"{r.energy_drift * t:>14.3e}{r.energy_fluctuation:>12.3e}"
            f"{(run.max_energy_error if run else math.nan):>12.3e}"
            f"{r.evals_per_time * t:>10.4g}{r.wall_per_time * t:>10.4g}{r.reference_dt / t:>9.4g}"
        )
    for r in reports:
        if r.fit_note:
            print(f"  {r.name}: {r.fit_note}")
    floor = next((r.floor for r in reports), math.nan)
    print(
        f"(times in config units, {units.config_time_label}; energies in {units.labels['energy']}; "
        f"orders fitted in the asymptotic range above the reference's error floor {floor:.2e}; "
        "'/tol': the slope against the tolerance; '-': no order, see the note)"
    )
