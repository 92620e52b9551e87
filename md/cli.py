"""Command-line interface: ``md run CONFIG.toml`` and ``md info TRAJ.h5``.

The CLI builds objects and prints; the physics lives in the library. Exit
codes: 0 success, 1 the dynamics blew up (NaN or infinite energy), 2 bad
input (config, structure file, existing output, unreadable trajectory),
130 interrupted.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130


class _ArgumentParser(argparse.ArgumentParser):
    def error(self, message: str):  # argparse's own exit code is 2 as well
        self.print_usage(sys.stderr)
        self.exit(EXIT_BAD_INPUT, f"md: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _ArgumentParser(prog="md", description="leapmd molecular dynamics engine")
    parser.add_argument("--version", action="version", version=_version())
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_ArgumentParser)

    run = sub.add_parser("run", help="run a simulation described by a TOML config")
    run.add_argument("config", type=Path, help="TOML config file")
    run.add_argument("--steps", type=int, help="number of steps (overrides [run] steps)")
    run.add_argument("--output", "-o", type=Path, help="trajectory path (overrides [output] path)")
    run.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    run.add_argument("--no-progress", action="store_true", help="no progress bar")
    run.add_argument("--quiet", "-q", action="store_true", help="no thermo table")

    study = sub.add_parser(
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
        "(default: the config dt times 1/8, 1/4, 1/2, 1)",
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
    study.add_argument("--out", type=Path, help="output folder (default integrators-<config>)")
    study.add_argument("--overwrite", action="store_true", help="replace existing output files")

    info = sub.add_parser("info", help="describe an H5MD trajectory")
    info.add_argument("trajectory", type=Path, help="H5MD file written by md run")
    info.add_argument("--json", action="store_true", help="print the summary as JSON")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``md`` command; returns the exit code."""
    args = build_parser().parse_args(argv)
    try:
        if args.command == "run":
            return _run(args)
        if args.command == "integrators":
            return _integrators(args)
        return _info(args)
    except KeyboardInterrupt:
        print("md: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


# ---------------------------------------------------------------------- md run
def _run(args) -> int:
    from md.config import (
        ConfigError,
        build_system,
        integrator_from_config,
        load_config,
        potential_from_config,
    )
    from md.neighbors import NonFiniteError
    from md.observers import Progress
    from md.simulation import Simulation, SimulationError
    from md.trajectory import H5MDWriter

    # Everything is validated and built before the output file is touched.
    try:
        config = load_config(args.config)
        if args.steps is not None:
            if args.steps < 0:
                raise ConfigError(f"--steps must be >= 0, got {args.steps}")
            config.run.steps = args.steps
        output = args.output if args.output is not None else config.output.path
        if output.exists() and not args.overwrite:
            raise ConfigError(
                f"output file {output} already exists; pass --overwrite to replace it "
                "or --output to choose another path"
            )
        if output.exists() and output.is_dir():
            raise ConfigError(f"output path {output} is a directory")
        if not output.parent.exists():
            raise ConfigError(f"output directory {output.parent} does not exist")
        state, bonds = build_system(config)
        potentials = [
            potential_from_config(entry, state.type_names, config.source, index, bonds)
            for index, entry in enumerate(config.potentials)
        ]
        integrator = integrator_from_config(config.integrator, config.source)
        try:
            sim = Simulation(
                state, potentials, integrator, skin=config.run.skin, units=config.units
            )
        except ValueError as error:
            raise ConfigError(f"{config.source}: {error}") from None
        try:
            sim.forcefield.compute(state)
        except NonFiniteError as error:
            raise ConfigError(
                f"{config.source}: the initial configuration cannot be evaluated: {error} "
                "(overlapping atoms, or a stretched bond?)"
            ) from None
    except ConfigError as error:
        _fail(str(error))
        return EXIT_BAD_INPUT

    units = config.units
    parameters = {
        "config": config.text,
        "config_file": str(args.config),
        "potentials": [p.describe() for p in potentials],
        "integrator": integrator.describe(),
        "dt_config": integrator.dt / units.config_time,
        "dt_config_unit": units.config_time_label,
        "skin": config.run.skin,
        "seed": -1 if config.seed is None else config.seed,
        "n_steps": config.run.steps,
    }
    n_steps = config.run.steps
    print(
        f"md run: {state.n_atoms} atoms, {n_steps} steps, dt = "
        f"{integrator.dt / units.config_time:g} {units.config_time_label}, units {units.name}, "
        f"output {output} every {config.output.every} steps"
    )
    try:
        writer = H5MDWriter(
            output,
            state,
            units=units,
            velocities=config.output.velocities,
            forces=config.output.forces,
            parameters=parameters,
            overwrite=args.overwrite,
        )
    except (OSError, ValueError) as error:
        _fail(f"cannot create {output}: {error}")
        return EXIT_BAD_INPUT

    bar = _progress_bar(n_steps, disable=args.no_progress)
    table = _ThermoTable(units, bar, quiet=args.quiet)
    sim.attach(writer, interval=config.output.every)
    sim.attach(table, interval=config.run.thermo_every)
    sim.attach(Progress(bar), interval=max(1, n_steps // 500))
    first = sim.thermo()
    timings_before = sim.timing_summary()
    start = time.perf_counter()
    status = EXIT_OK
    try:
        with writer:
            sim.run(n_steps)
    except SimulationError as error:
        bar.close()
        _fail(f"{error}. Frames written so far are kept in {output} ({writer.n_frames} frames).")
        status = EXIT_FAILED
    except KeyboardInterrupt:
        bar.close()
        _fail(f"interrupted at step {state.step}; {writer.n_frames} frames kept in {output}")
        return EXIT_INTERRUPTED
    finally:
        bar.close()
    wall = time.perf_counter() - start
    if status == EXIT_OK:
        _print_summary(sim, first, timings_before, n_steps, wall, output, writer.n_frames)
    return status


class _ThermoTable:
    """Observer printing one thermo row every interval (above the progress bar)."""

    columns = (
        "step",
        "time",
        "temperature",
        "potential_energy",
        "kinetic_energy",
        "total_energy",
        "pressure",
    )
    headers = ("Step", "Time", "Temp", "PotEng", "KinEng", "TotEng", "Press")

    def __init__(self, units, bar, quiet: bool) -> None:
        self.units = units
        self.bar = bar
        self.quiet = quiet
        self.rows: list[dict] = []
        self._printed_header = False

    def __call__(self, sim) -> None:
        row = sim.thermo()
        self.rows.append(row)
        if self.quiet:
            return
        if not self._printed_header:
            self._write("".join(f"{h:>14}" for h in self.headers))
            self._printed_header = True
        time_value = row["time"] / self.units.config_time
        cells = [f"{row['step']:>14d}", f"{time_value:>14.6g}"]
        cells += [f"{row[c]:>14.6g}" for c in self.columns[2:]]
        self._write("".join(cells))

    def _write(self, line: str) -> None:
        from tqdm import tqdm

        tqdm.write(line)


def _progress_bar(total: int, disable: bool):
    from tqdm import tqdm

    return tqdm(
        total=total,
        unit="step",
        disable=disable or total == 0,
        dynamic_ncols=True,
        desc="md run",
        leave=False,
    )


def _print_summary(sim, first, timings_before, n_steps, wall, output, n_frames) -> None:
    last = sim.thermo()
    state = sim.state
    timings = {k: v - timings_before[k] for k, v in sim.timing_summary().items()}
    other = max(wall - sum(timings.values()), 0.0)
    atom_steps = state.n_atoms * n_steps / wall if wall > 0 and n_steps else float("nan")
    energy_scale = max(abs(first["total_energy"]), abs(first["kinetic_energy"]), 1e-300)
    drift = (last["total_energy"] - first["total_energy"]) / energy_scale
    print(
        f"\nLoop time {wall:.3f} s for {n_steps} steps of {state.n_atoms} atoms: "
        f"{atom_steps:,.0f} atom-steps/s"
    )
    print(f"{'Section':<10}{'time (s)':>12}{'%total':>9}")
    for name, seconds in [*timings.items(), ("other", other)]:
        share = 100 * seconds / wall if wall > 0 else 0.0
        print(f"{name:<10}{seconds:>12.4f}{share:>9.1f}")
    nl = sim.forcefield.neighbor_list
    if nl is not None:
        print(f"Neighbour list builds: {nl.n_builds} (rebuilt when an atom moved > skin/2)")
    statistics = getattr(sim.integrator, "statistics", None)
    if statistics and statistics.get("steps"):
        per_step = ", ".join(
            f"{name.replace('_', ' ')} {value / statistics['steps']:.3g}"
            for name, value in statistics.items()
            if name != "steps"
        )
        if per_step:
            print(f"Integrator, per step: {per_step}")
    print(f"Relative total-energy drift (E_end - E_start)/|E_start|: {drift:.3e}")
    print(f"Wrote {n_frames} frames to {output}")


# -------------------------------------------------------------- md integrators
def _parse_dts(text: str | None, dt: float) -> list[float]:
    from md.config import ConfigError

    if text is None:
        return [dt / 8, dt / 4, dt / 2, dt]
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


def _integrators(args) -> int:
    from integrators import INTEGRATORS
    from md.config import (
        ConfigError,
        build_system,
        load_config,
        potential_from_config,
    )
    from md.integrator_study import (
        compare_integrators,
        plot_energy_vs_time,
        plot_error_vs_dt,
        write_csv,
    )

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
        state, bonds = build_system(config)

        def make_potentials():
            return [
                potential_from_config(entry, state.type_names, config.source, index, bonds)
                for index, entry in enumerate(config.potentials)
            ]

        if args.equilibrate:
            from integrators import VelocityVerlet
            from md.simulation import Simulation, SimulationError

            try:
                Simulation(
                    state, make_potentials(), VelocityVerlet(config.integrator["dt"]),
                    skin=config.run.skin, units=units,
                ).run(args.equilibrate)  # fmt: skip
            except (SimulationError, ValueError) as error:
                raise ConfigError(f"{config.source}: equilibration failed: {error}") from None
            state.step, state.time = 0, 0.0
        out = args.out or Path(f"integrators-{args.config.stem}")
        files = {
            "csv": out / "integrators.csv",
            "error": out / "error_vs_dt.png",
            "energy": out / "energy_vs_time.png",
        }
        existing = [str(p) for p in files.values() if p.exists()]
        if existing and not args.overwrite:
            raise ConfigError(
                f"output file(s) exist: {', '.join(existing)}; pass --overwrite or --out"
            )
    except ConfigError as error:
        _fail(str(error))
        return EXIT_BAD_INPUT

    def factory(name):
        cls = INTEGRATORS[name]

        def build(dt):
            return cls(dt=dt)

        build.adaptive = getattr(cls, "adaptive", False)
        return build

    label = units.config_time_label
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
        reference=factory("rk4") if "rk4" in INTEGRATORS else None,
        measure_dt=dts[-1] if args.dt_range is None else None,
        progress=lambda message: print(f"  {message}", flush=True),
    )
    out.mkdir(parents=True, exist_ok=True)
    for path in files.values():
        if path.exists():
            path.unlink()
    write_csv(reports, files["csv"])
    plot_error_vs_dt(reports, files["error"], f"[{label}]")
    plot_energy_vs_time(reports, files["energy"], {"time": f"[{units.labels['time']}]"})
    _print_study_table(reports, units)
    print(f"Wrote {files['csv']}, {files['error']}, {files['energy']}")
    return EXIT_OK


def _integrator_names(text, registry) -> list[str]:
    from md.config import ConfigError

    if text is None:
        names, seen = [], set()
        for name, cls in registry.items():
            if cls not in seen:
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
    return names


def _print_study_table(reports, units) -> None:
    t = units.config_time
    header = (
        f"{'integrator':<18}{'order':>7}{'dt_max_stable':>15}{'drift/atom/t':>14}"
        f"{'fluct/atom':>12}{'evals/t':>10}{'wall s/t':>10}{'at dt':>9}"
    )
    print(header)
    for r in reports:
        print(
            f"{r.name:<18}{r.order:>7.2f}{r.dt_max_stable / t:>15.4g}{r.energy_drift * t:>14.3e}"
            f"{r.energy_fluctuation:>12.3e}{r.evals_per_time * t:>10.4g}"
            f"{r.wall_per_time * t:>10.4g}{r.reference_dt / t:>9.4g}"
        )
    print(
        f"(times in config units, {units.config_time_label}; energies in {units.labels['energy']})"
    )


# ---------------------------------------------------------------------- md info
def _info(args) -> int:
    from md.trajectory import TrajectoryError, read_trajectory

    try:
        traj = read_trajectory(args.trajectory)
    except TrajectoryError as error:
        _fail(str(error))
        return EXIT_BAD_INPUT
    summary = trajectory_summary(traj)
    if args.json:
        print(json.dumps(summary, indent=2, default=str))
        return EXIT_OK
    units = traj.units
    print(f"{traj.path}: H5MD trajectory written by leapmd {summary['version']}")
    print(f"  atoms        {summary['n_atoms']} ({', '.join(summary['types'])})")
    print(
        f"  frames       {summary['n_frames']} (steps {summary['first_step']} to "
        f"{summary['last_step']})"
    )
    label = units.labels["time"]
    print(f"  time         {summary['first_time']:g} to {summary['last_time']:g} {label}")
    print(f"  units        {units.name}")
    print(f"  box          {summary['box']}  pbc {summary['pbc']}")
    print(f"  stored       {', '.join(summary['stored'])}")
    for key in ("integrator", "potentials", "seed", "skin"):
        if key in traj.parameters:
            print(f"  {key:<12} {json.dumps(traj.parameters[key])}")
    energy = summary.get("energy")
    if energy:
        e_label = units.labels["energy"]
        print(
            f"  total energy {energy['first']:.8g} -> {energy['last']:.8g} {e_label} "
            f"(mean {energy['mean']:.8g}, std {energy['std']:.3g}, "
            f"relative drift {energy['relative_drift']:.3e})"
        )
        print(
            f"  temperature  mean {summary['temperature_mean']:.6g} {units.labels['temperature']}"
            f", pressure mean {summary['pressure_mean']:.6g} {units.labels['pressure']}"
        )
    return EXIT_OK


def trajectory_summary(traj) -> dict:
    """Plain-data summary of a trajectory (what ``md info`` prints)."""
    to_file_time = traj.units.h5md["time"][1] if "time" in traj.units.h5md else 1.0
    stored = ["position", "image", "box"]
    if traj.velocities is not None:
        stored.append("velocity")
    if traj.forces is not None:
        stored.append("force")
    stored += sorted(traj.observables)
    summary = {
        "path": str(traj.path),
        "version": traj.parameters.get("leapmd_version", "?"),
        "n_atoms": traj.n_atoms,
        "n_frames": traj.n_frames,
        "types": list(traj.type_names),
        "units": traj.units.name,
        "first_step": int(traj.steps[0]) if traj.n_frames else None,
        "last_step": int(traj.steps[-1]) if traj.n_frames else None,
        "first_time": float(traj.times[0] * to_file_time) if traj.n_frames else 0.0,
        "last_time": float(traj.times[-1] * to_file_time) if traj.n_frames else 0.0,
        "box": traj.boxes[-1].tolist() if traj.n_frames else None,
        "pbc": traj.pbc.tolist(),
        "stored": stored,
    }
    total = traj.observables.get("total_energy")
    if total is not None and len(total) and np.all(np.isfinite(total)):
        scale = max(abs(total[0]), 1e-300)
        summary["energy"] = {
            "first": float(total[0]),
            "last": float(total[-1]),
            "mean": float(total.mean()),
            "std": float(total.std()),
            "relative_drift": float((total[-1] - total[0]) / scale),
        }
        summary["temperature_mean"] = float(traj.observables["temperature"].mean())
        summary["pressure_mean"] = float(traj.observables["pressure"].mean())
    return summary


def _fail(message: str) -> None:
    print(f"md: error: {message}", file=sys.stderr)


def _version() -> str:
    from md import __version__

    return f"leapmd {__version__}"


if __name__ == "__main__":
    sys.exit(main())
