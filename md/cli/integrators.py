"""``md integrators CONFIG.toml``: measure integrators and thermostats on one system.

Order of accuracy, stability limit, energy drift and cost per integrator,
and for thermostats the temperature error and sampling efficiency, with CSV
files and plots: :func:`md.studies.study.prepare_study` and
:meth:`~md.studies.study.Study.run`. With ``--damping``, numerical damping
on a harmonic bond instead: :func:`md.studies.damping.prepare_damping` and
:meth:`~md.studies.damping.DampingStudy.run`. This module parses the options,
prints the tables and maps errors to exit codes (2 bad input or an
unwritable output, 1 the reference runs blew up).
"""

from __future__ import annotations

import math
from pathlib import Path

from md.cli._common import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_OK, fail
from md.config import load_config
from md.errors import ConfigError, SimulationError
from md.studies import prepare_damping, prepare_study
from md.studies.rigid_study import prepare_rigid_study


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


def main(args) -> int:
    """Body of ``md integrators``; returns the exit code."""
    if args.damping:
        return _damping(args)
    try:
        config = load_config(args.config)
        if config.rigid is not None:  # the rotational family of RigidNVE
            study = prepare_rigid_study(
                config,
                integrators=args.integrators,
                dts=args.dt_range,
                span=args.time,
                equilibrate=args.equilibrate,
                out=args.out,
                overwrite=args.overwrite,
            )
        else:
            study = prepare_study(
                config,
                integrators=args.integrators,
                dts=args.dt_range,
                span=args.time,
                equilibrate=args.equilibrate,
                temperature=args.temperature,
                tau=args.tau,
                sample_time=args.sample_time,
                out=args.out,
                overwrite=args.overwrite,
            )
    except ConfigError as error:
        fail(str(error))
        return EXIT_BAD_INPUT
    units, n_atoms = study.config.units, study.state.n_atoms
    t, label = units.config_time, units.config_time_label
    if study.names:
        print(
            f"md integrators: {n_atoms} atoms, span {study.span / t:g} {label}, "
            f"dt {', '.join(f'{dt / t:g}' for dt in study.dts)} {label}"
        )
    if study.thermostat_names:
        setup = study.setup
        print(
            f"md integrators (thermostats): {n_atoms} atoms, T = {setup.temperature:g} "
            f"{units.labels['temperature']}, dt {study.config.integrator.dt / t:g} {label}, "
            f"tau {setup.tau / t:g} {label}, {setup.n_equilibrate} steps to equilibrate, "
            f"{setup.n_sample} sampled"
        )
    try:
        results = study.run(progress=lambda message: print(f"  {message}", flush=True))
    except SimulationError as error:
        fail(
            f"{error}: the {study.reference} reference runs (dt {study.reference_dt / t:.3g} "
            f"and half that, {label}) must stay stable for orders to be measured. Choose smaller "
            "time steps (--dt-range) or a shorter --time; nothing was written"
        )
        return EXIT_FAILED
    except OSError as error:
        fail(f"cannot write the study's files in {study.out}: {error}")
        return EXIT_BAD_INPUT
    if results.reports:
        _print_study_table(results.reports, units)
    if results.thermostat_reports:
        _print_thermostat_table(results.thermostat_reports, units)
    print(f"Wrote {', '.join(str(path) for path in results.files.values())}")
    return EXIT_OK


def _damping(args) -> int:
    """``md integrators CONFIG --damping``: the damping measurement and its table."""
    try:
        study = prepare_damping(
            args.config, args.integrators, args.omega_dt, args.out, args.overwrite
        )
    except ConfigError as error:
        fail(str(error))
        return EXIT_BAD_INPUT
    print(
        f"md integrators --damping: a harmonic bond at dt {study.time_label}, omega dt "
        f"{min(study.omega_dts):g} to {max(study.omega_dts):g} ({len(study.omega_dts)} points)"
    )
    try:
        rows = study.run(progress=lambda message: print(f"  {message}", flush=True))
    except OSError as error:
        fail(f"cannot write the damping files in {study.files['csv'].parent}: {error}")
        return EXIT_BAD_INPUT
    shown = [
        z
        for z in (0.01, 0.1, 1.0, 10.0, 100.0)
        if any(abs(r.omega_dt - z) < 1e-9 * z for r in rows)
    ]
    print(
        f"{'integrator':<18}"
        + "".join(f"{f'|rho| @ {z:g}':>15}" for z in shown)
        + f"{'max |d - d_th| / d_th':>24}"
    )
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
