"""Command-line interface: ``md run CONFIG.toml`` and ``md info TRAJ.h5``.

The CLI builds objects and prints; the physics lives in the library. Exit
codes: 0 success, 1 the dynamics blew up (NaN or infinite energy), 2 bad
input (config, structure file, existing output, unreadable trajectory,
unwritable output), 130 interrupted by SIGINT, 143 by SIGTERM (both after a
checkpoint).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
import uuid
from collections.abc import Sequence
from pathlib import Path

import numpy as np

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130
EXIT_TERMINATED = 143  # SIGTERM: 128 + 15


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
    run.add_argument(
        "--resume",
        action="store_true",
        help="continue from the output's checkpoint (OUTPUT.ckpt): same physics, steps may grow",
    )
    run.add_argument(
        "--threads",
        type=int,
        help="threads for the force and neighbour kernels (overrides [run] threads; "
        "default: every core)",
    )
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
    study.add_argument("--out", type=Path, help="output folder (default integrators-<config>)")
    study.add_argument("--overwrite", action="store_true", help="replace existing output files")

    from md.analyze_cli import add_arguments as _analyze_arguments

    _analyze_arguments(sub.add_parser("analyze", help="thermo, g(r), MSD, VACF of a trajectory"))

    from md.sweep_cli import add_arguments as _sweep_arguments

    _sweep_arguments(sub.add_parser("sweep", help="runs over varied keys and replicas, on Dask"))

    info = sub.add_parser("info", help="describe an H5MD trajectory")
    info.add_argument("trajectory", type=Path, help="H5MD file written by md run")
    info.add_argument("--json", action="store_true", help="print the summary as JSON")

    from md.validate import add_parser as add_validate_parser  # md validate ase

    add_validate_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``md`` command; returns the exit code."""
    args = build_parser().parse_args(argv)
    try:
        if args.command == "run":
            return _run(args)
        if args.command == "integrators":
            return _integrators(args)
        if args.command == "validate":
            from md.validate import command as validate_command

            return validate_command(args)
        if args.command == "analyze":
            from md.analyze_cli import run_analyze

            return run_analyze(args)
        if args.command == "sweep":
            from md.sweep_cli import run_sweep_command

            return run_sweep_command(args)
        return _info(args)
    except KeyboardInterrupt:
        print("md: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


# ---------------------------------------------------------------------- md run
def _run(args) -> int:
    from integrators.base import ConvergenceError
    from md.checkpoint import (
        CheckpointError,
        checkpoint_path,
        fingerprint_changes,
        physics_fingerprint,
        read_checkpoint,
        restore,
        write_checkpoint,
    )
    from md.config import (
        ConfigError,
        build_system,
        integrator_from_config,
        load_config,
        potential_from_config,
    )
    from md.neighbors import NonFiniteError
    from md.observers import Progress
    from md.parallel import set_threads
    from md.simulation import Simulation, SimulationError
    from md.trajectory import H5MDWriter, TrajectoryError, read_frame_steps

    # Everything is validated and built before the output file is touched.
    checkpoint = None
    try:
        config = load_config(args.config)
        if args.steps is not None:
            if args.steps < 0:
                raise ConfigError(f"--steps must be >= 0, got {args.steps}")
            config.run.steps = args.steps
        output = args.output if args.output is not None else config.output.path
        if output.name in ("", ".", ".."):
            raise ConfigError(f"output path {str(output)!r} names no file")
        saved_path = checkpoint_path(output)
        if output.exists() and output.is_dir():
            raise ConfigError(f"output path {output} is a directory")
        if not output.parent.is_dir():
            raise ConfigError(f"output directory {output.parent} does not exist")
        if not os.access(output.parent, os.W_OK | os.X_OK):
            raise ConfigError(f"output directory {output.parent} is not writable")
        fingerprint = physics_fingerprint(config)
        if args.resume:
            if args.overwrite:
                raise ConfigError("--resume continues the existing output; drop --overwrite")
            checkpoint = read_checkpoint(saved_path)
            if not output.exists() and checkpoint.n_frames:
                raise ConfigError(f"--resume: trajectory {output} does not exist")
            changes = fingerprint_changes(checkpoint.fingerprint, fingerprint)
            if changes:
                raise ConfigError(
                    f"--resume: {args.config} changed the physics since checkpoint "
                    f"{saved_path} was written ({'; '.join(changes)}); only [run] steps, "
                    "thermo_every and [output] every/checkpoint_every may change"
                )
            if output.exists():
                _check_resumable(output, checkpoint, read_frame_steps)
            if checkpoint.state.step > config.run.steps:
                raise ConfigError(
                    f"--resume: checkpoint {saved_path} is at step {checkpoint.state.step}, "
                    f"beyond the {config.run.steps} steps asked for"
                )
        else:
            for path in (output, saved_path):
                if path.exists() and not args.overwrite:
                    raise ConfigError(
                        f"output file {path} already exists; pass --overwrite to replace it, "
                        "--resume to continue it, or --output to choose another path"
                    )
        state, bonds = build_system(config)
        if checkpoint is not None:
            if checkpoint.state.n_atoms != state.n_atoms:
                raise ConfigError(
                    f"--resume: checkpoint {saved_path} holds {checkpoint.state.n_atoms} atoms, "
                    f"the config builds {state.n_atoms}"
                )
            state = checkpoint.state
        potentials = [
            potential_from_config(entry, state.type_names, config.source, index, bonds)
            for index, entry in enumerate(config.potentials)
        ]
        integrator = integrator_from_config(config.integrator, config.source, bonds)
        constraints = getattr(integrator, "constraints", None)
        if constraints is not None:  # start on the bond lengths, so step 0 is reported there
            try:
                constraints.bind(state, integrator.dt)
            except (ValueError, ConvergenceError) as error:
                raise ConfigError(f"{config.source}: [integrator.constraints]: {error}") from None
        # Blow-up guard: nobody moves farther than the skin in one step (adaptive
        # integrators take long output steps on purpose).
        guard = config.run.skin if config.run.skin > 0 else None
        if getattr(integrator, "adaptive", False):
            guard = None
        threads = args.threads if args.threads is not None else config.run.threads
        try:
            set_threads(threads)
        except ValueError as error:
            where = "--threads" if args.threads is not None else f"{config.source}: [run] threads"
            raise ConfigError(f"{where}: {error}") from None
        try:
            sim = Simulation(
                state,
                potentials,
                integrator,
                skin=config.run.skin,
                units=config.units,
                max_displacement=guard,
            )
        except ValueError as error:
            raise ConfigError(f"{config.source}: {error}") from None
        if checkpoint is not None:
            restore(checkpoint, integrator, sim.forcefield)
            if checkpoint.n_frames:  # else frame 0 was never kept: write it again
                sim.skip_initial_observation()
        try:
            sim.forcefield.compute(state)
        except NonFiniteError as error:
            raise ConfigError(
                f"{config.source}: the initial configuration cannot be evaluated: {error} "
                "(overlapping atoms, or a stretched bond?)"
            ) from None
    except (ConfigError, CheckpointError, TrajectoryError) as error:
        _fail(str(error))
        return EXIT_BAD_INPUT
    except MemoryError:
        _fail(f"{args.config}: the system is too large to build in memory")
        return EXIT_BAD_INPUT

    units = config.units
    run_id = checkpoint.run_id if checkpoint is not None else uuid.uuid4().hex
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
        "run_id": run_id,
    }
    n_steps = config.run.steps - state.step
    if checkpoint is not None and n_steps == 0:
        print(f"md run: {output} is already complete at step {state.step}; nothing to do")
        return EXIT_OK
    resuming = (
        f", resuming at step {state.step} of {config.run.steps} from {saved_path}"
        if checkpoint is not None
        else ""
    )
    print(
        f"md run: {state.n_atoms} atoms, {n_steps} steps, dt = "
        f"{integrator.dt / units.config_time:g} {units.config_time_label}, units {units.name}, "
        f"output {output} every {config.output.every} steps{resuming}"
    )
    try:
        if checkpoint is None:
            # First a checkpoint of the start, then the trajectory: whenever a run is
            # killed, --resume finds a checkpoint (the file may not exist yet).
            write_checkpoint(
                saved_path, state, integrator, sim.forcefield, fingerprint=fingerprint,
                run_id=run_id, extra={"config_file": str(args.config)},
            )  # fmt: skip
        if checkpoint is not None and output.exists():
            writer = H5MDWriter(
                output, state, units=units, append=True, keep_frames=checkpoint.n_frames
            )
        else:
            writer = H5MDWriter(
                output,
                state,
                units=units,
                velocities=config.output.velocities,
                forces=config.output.forces,
                parameters=parameters,
                overwrite=args.overwrite or checkpoint is not None,
            )
    except TrajectoryError as error:
        _fail(str(error))
        return EXIT_BAD_INPUT
    except (OSError, ValueError) as error:
        _fail(f"cannot create {output}: {error}")
        return EXIT_BAD_INPUT

    bar = _progress_bar(n_steps, disable=args.no_progress)
    table = _ThermoTable(units, bar, quiet=args.quiet)
    saver = _Checkpointer(saved_path, sim, writer, fingerprint, run_id, str(args.config))
    sim.attach(writer, interval=config.output.every)
    # After the writer, so a checkpoint counts the frame of its own step. With
    # checkpoint_every = 0 it only fires at the start of a fresh run (step 0).
    sim.attach(saver, interval=config.output.checkpoint_every or 2**62)
    sim.attach(table, interval=config.run.thermo_every)
    sim.attach(Progress(bar), interval=max(1, n_steps // 500))
    first = sim.thermo()
    timings_before = sim.timing_summary()
    start = time.perf_counter()
    status = EXIT_OK
    previous_handlers = _catch_stop_signals(sim)
    try:
        with writer:
            sim.run(n_steps)
            if sim.stop_requested is None or saver.last_step != state.step:
                saver(sim)  # at the end, and after a signal
    except (SimulationError, ConvergenceError) as error:
        bar.close()
        kept = (
            f"; the last good state (step {saver.last_step}) is checkpointed in {saved_path}"
            if saver.last_step is not None
            else ""
        )
        _fail(
            f"{error}. Frames written so far are kept in {output} ({writer.n_frames} frames){kept}"
        )
        status = EXIT_FAILED
    except KeyboardInterrupt:  # a second signal while stopping: leave at once
        bar.close()
        _fail(f"interrupted at step {state.step}; {writer.n_frames} frames kept in {output}")
        return EXIT_INTERRUPTED
    except (OSError, RuntimeError) as error:  # disk full (h5py raises either), file removed
        bar.close()
        _fail(
            f"cannot write output at step {state.step} ({error}); frames written before are "
            f"kept in {output}, the last checkpoint (step {saver.last_step}) in {saved_path}"
        )
        return EXIT_BAD_INPUT
    finally:
        bar.close()
        _restore_signals(previous_handlers)
    if sim.stop_requested is not None:
        name = sim.stop_requested
        print(
            f"md run: {name} received; stopped after step {state.step}, checkpoint written to "
            f"{saved_path}, {writer.n_frames} frames in {output}. Continue with: md run "
            f"{args.config} --resume",
            file=sys.stderr,
        )
        return EXIT_INTERRUPTED if name == "SIGINT" else EXIT_TERMINATED
    wall = time.perf_counter() - start
    if status == EXIT_OK:
        _print_summary(sim, first, timings_before, n_steps, wall, output, writer.n_frames)
    return status


def _check_resumable(output: Path, checkpoint, read_frame_steps) -> None:
    """Raise ConfigError unless ``output`` holds the frames ``checkpoint`` counted."""
    from md.config import ConfigError

    steps, parameters = read_frame_steps(output)
    if parameters.get("run_id") != checkpoint.run_id:
        raise ConfigError(
            f"--resume: {output} was not written by the run that wrote {checkpoint.path} "
            "(different run id)"
        )
    n = checkpoint.n_frames
    if len(steps) < n or (n and int(steps[n - 1]) != checkpoint.last_frame_step):
        raise ConfigError(
            f"--resume: {output} holds {len(steps)} complete frames, but checkpoint "
            f"{checkpoint.path} expects at least {n} ending at step {checkpoint.last_frame_step}"
        )


class _Checkpointer:
    """Observer writing a checkpoint (atomically) with the trajectory's frame count."""

    uses_virial = False  # saves the state; its steps need no virial

    def __init__(self, path: Path, sim, writer, fingerprint, run_id: str, config: str) -> None:
        self.path = path
        self.sim = sim
        self.writer = writer
        self.fingerprint = fingerprint
        self.run_id = run_id
        self.config = config
        self.last_step: int | None = None

    def __call__(self, sim) -> None:
        from md.checkpoint import write_checkpoint

        writer = self.writer
        write_checkpoint(
            self.path,
            sim.state,
            sim.integrator,
            sim.forcefield,
            fingerprint=self.fingerprint,
            n_frames=writer.n_frames,
            last_frame_step=-1 if writer._last_step is None else writer._last_step,
            run_id=self.run_id,
            extra={"config_file": self.config},
        )
        self.last_step = sim.state.step


def _catch_stop_signals(sim) -> dict:
    """SIGINT/SIGTERM ask the run to stop after the current step; a second one stops at once."""
    import signal

    def handler(signum, frame):
        if sim.stop_requested is not None:
            raise KeyboardInterrupt
        sim.request_stop(signal.Signals(signum).name)

    previous = {}
    for signum in (signal.SIGINT, signal.SIGTERM):
        try:
            previous[signum] = signal.signal(signum, handler)
        except ValueError:  # not the main thread: leave signals alone
            break
    return previous


def _restore_signals(previous: dict) -> None:
    import signal

    for signum, handler in previous.items():
        signal.signal(signum, handler)


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
        conserved = ("conserved_energy",) if "conserved_energy" in row else ()  # thermostats
        if not self._printed_header:
            headers = self.headers + (("Conserved",) if conserved else ())
            self._write("".join(f"{h:>14}" for h in headers))
            self._printed_header = True
        time_value = row["time"] / self.units.config_time
        cells = [f"{row['step']:>14d}", f"{time_value:>14.6g}"]
        cells += [f"{row[c]:>14.6g}" for c in self.columns[2:] + conserved]
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
    from md.parallel import get_threads

    last = sim.thermo()
    state = sim.state
    timings = {k: v - timings_before[k] for k, v in sim.timing_summary().items()}
    other = max(wall - sum(timings.values()), 0.0)
    atom_steps = state.n_atoms * n_steps / wall if wall > 0 and n_steps else float("nan")
    energy_scale = max(abs(first["total_energy"]), abs(first["kinetic_energy"]), 1e-300)
    drift = (last["total_energy"] - first["total_energy"]) / energy_scale
    print(
        f"\nLoop time {wall:.3f} s for {n_steps} steps of {state.n_atoms} atoms: "
        f"{atom_steps:,.0f} atom-steps/s on {get_threads()} thread(s)"
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
    if "conserved_energy" in first:  # a thermostat: its conserved quantity should not drift
        change = (last["conserved_energy"] - first["conserved_energy"]) / energy_scale
        print(f"Relative conserved-quantity drift (incl. heat bath): {change:.3e}")
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
        compare_thermostats,
        plot_energy_vs_time,
        plot_error_vs_dt,
        plot_thermostats,
        write_csv,
        write_thermostat_csv,
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
        # Thermostats are measured apart: sampling at a temperature, not order in dt.
        thermostat_names = [n for n in names if getattr(INTEGRATORS[n], "thermostat", False)]
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
        files = {}
        if names:
            files["csv"] = out / "integrators.csv"
            files["error"] = out / "error_vs_dt.png"
            files["energy"] = out / "energy_vs_time.png"
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
        _fail(str(error))
        return EXIT_BAD_INPUT

    def factory(name):
        cls = INTEGRATORS[name]

        def build(dt):
            return cls(dt=dt)

        build.adaptive = getattr(cls, "adaptive", False)
        return build

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
            reference=factory("rk4") if "rk4" in INTEGRATORS else None,
            measure_dt=dts[-1] if args.dt_range is None else None,
            progress=progress,
        )
        write_csv(reports, files["csv"])
        plot_error_vs_dt(reports, files["error"], f"[{label}]")
        plot_energy_vs_time(reports, files["energy"], {"time": f"[{units.labels['time']}]"})
        _print_study_table(reports, units)
        print(f"Wrote {files['csv']}, {files['error']}, {files['energy']}")
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


def _thermostat_setup(args, config, names, registry) -> dict | None:
    """Target temperature, coupling time, run lengths and a factory for the thermostat study.

    The temperature is --temperature, else the config's thermostat target,
    else [system] temperature; tau is --tau, else the config's tau (or
    1/friction), else 100 dt. Returns None when no temperature is known and
    no thermostat was named; raises ConfigError if one was named.
    """
    import inspect

    from md.config import ConfigError

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
            if getattr(cls, "stochastic", False):
                params["seed"] = [seed, 1]
            if "constraints" in entry:
                from integrators.rattle import BondConstraints

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
    from md.config import ConfigError

    # Rattle follows rigid bonds that the reference run and the others cannot: not compared.
    if text is None:
        names, seen = [], set()
        for name, cls in registry.items():
            if cls not in seen and not getattr(cls, "requires_constraints", False):
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
    constrained = [n for n in names if getattr(registry[n], "requires_constraints", False)]
    if constrained:
        raise ConfigError(
            f"--integrators: {', '.join(constrained)} needs rigid bonds, which the NVE "
            "comparison cannot follow; md integrators does not measure it"
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
