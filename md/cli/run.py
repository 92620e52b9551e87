"""``md run CONFIG.toml``: run a simulation described by a TOML config.

The run itself is :func:`md.run.prepare` and :meth:`md.run.PreparedRun.execute`;
this module adds the terminal: the thermo table, a progress bar, the summary
and the exit codes (0 done, 1 the dynamics blew up, 2 bad input or an
unwritable output, 130/143 stopped by SIGINT/SIGTERM after a checkpoint).
"""

from __future__ import annotations

import contextlib
import os
import shlex
import sys
from pathlib import Path

from tqdm import tqdm

from md.cli._common import (
    EXIT_BAD_INPUT,
    EXIT_FAILED,
    EXIT_INTERRUPTED,
    EXIT_OK,
    built_unless_stopped,
    exit_for_signal,
    fail,
)
from md.distributed import launch_rank
from md.errors import CheckpointError, ConfigError, OutputBusyError, TrajectoryError
from md.observers import Progress
from md.parallel import get_threads
from md.run import ABORTED, FAILED, OUTPUT_ERROR, STOPPED, prepare


def add_parser(subparsers) -> None:
    """Add ``md run`` and its options."""
    run = subparsers.add_parser("run", help="run a simulation described by a TOML config")
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
    run.add_argument(
        "--device",
        choices=("cpu", "cuda"),
        help="where the time step runs (overrides [run] device; cuda needs numba-cuda and "
        "an NVIDIA GPU, or NUMBA_ENABLE_CUDASIM=1 for numba's simulator)",
    )
    run.add_argument("--no-progress", action="store_true", help="no progress bar")
    run.add_argument("--quiet", "-q", action="store_true", help="no thermo table")


def _print_minimize(step: int, energy: float, fmax: float) -> None:
    print(f"minimize: step {step:>7}  energy {energy:.10g}  max force {fmax:.4g}", flush=True)


def main(args) -> int:
    """Body of ``md run``; returns the exit code.

    Under ``mpiexec -n P`` every rank runs it; rank 0 prints for the run (the
    ranks share every error, so all return the same code) and the others are silent.
    """
    if launch_rank() == 0:
        return _main(args)
    with (
        open(os.devnull, "w") as sink,
        contextlib.redirect_stdout(sink),
        contextlib.redirect_stderr(sink),
    ):
        return _main(args)


def _main(args) -> int:
    # Everything is validated and built before the output file is touched. Building (and
    # compiling) comes before the run's own stop handler: a signal there stops the command
    # with a line, as one during the run does.
    try:
        run, stopped = built_unless_stopped(
            lambda: prepare(
                args.config,
                steps=args.steps,
                output=args.output,
                overwrite=args.overwrite,
                resume=args.resume,
                threads=args.threads,
                device=args.device,
            ),
            "run",
            "the run",
        )
    except (ConfigError, CheckpointError, TrajectoryError) as error:
        fail(str(error))
        return EXIT_BAD_INPUT
    if stopped is not None:
        return stopped
    sim, state, config, units = run.sim, run.sim.state, run.config, run.config.units
    output, saved_path, n_steps = run.output, run.checkpoint_path, run.n_steps
    if run.complete:
        print(f"md run: {output} is already complete at step {state.step}; nothing to do")
        return EXIT_OK
    resuming = (
        f", resuming at step {state.step} of {config.run.steps} from {saved_path}"
        if run.resuming
        else ""
    )
    print(
        f"md run: {run.n_atoms} atoms{_ranks(run)}, {n_steps} steps, dt = "
        f"{sim.integrator.dt / units.config_time:g} {units.config_time_label}, units {units.name}, "
        f"output {output} every {config.output.every} steps{resuming}"
    )
    bar = _progress_bar(n_steps, disable=args.no_progress)
    table = _ThermoTable(units, quiet=args.quiet)
    if config.minimize is not None and not run.resuming:
        stage = config.minimize
        cap = f", forces capped at {stage.max_force:g}" if stage.max_force is not None else ""
        print(
            f"minimize: FIRE 2.0 to max force <= {stage.fmax:g} "
            f"{units.labels['energy']}/{units.labels['length']} in at most {stage.max_steps} "
            f"steps{cap}"
        )
    try:
        summary = run.execute(
            observers=[
                (table, config.run.thermo_every),
                (Progress(bar), max(1, n_steps // 500)),
            ],
            minimize_progress=None if args.quiet else _print_minimize,
        )
    except (TrajectoryError, ConfigError, OutputBusyError) as error:
        fail(str(error))
        return EXIT_BAD_INPUT
    except (OSError, ValueError) as error:
        fail(f"cannot create {output}: {error}")
        return EXIT_BAD_INPUT
    finally:
        bar.close()
    if run.minimized is not None:
        print(f"minimize: {run.minimized.describe()}")
    kept = f"{summary.n_frames} frames kept in {output}"
    if summary.status == FAILED:
        last = summary.last_checkpoint_step
        checkpointed = (
            f"; the last good state (step {last}) is checkpointed in {saved_path}"
            if last is not None
            else ""
        )
        fail(
            f"{summary.message}. Frames written so far are kept in {output} "
            f"({summary.n_frames} frames){checkpointed}"
        )
        return EXIT_FAILED
    if summary.status == ABORTED:
        fail(f"interrupted at step {state.step}; {kept}")
        return EXIT_INTERRUPTED
    if summary.status == OUTPUT_ERROR:
        if not output.exists():
            fail(
                f"cannot write output at step {state.step} ({summary.message}); nothing was "
                f"kept: make room, then run again: {_again(args, run, resume=False)}"
            )
            return EXIT_BAD_INPUT
        checkpointed = (
            f"the last checkpoint (step {summary.last_checkpoint_step}) in {saved_path}; "
            f"make room, then continue with: {_again(args, run, resume=True)}"
            if summary.last_checkpoint_step is not None
            else "no checkpoint was written"
        )
        fail(
            f"cannot write output at step {state.step} ({summary.message}); frames written "
            f"before are kept in {output}, {checkpointed}"
        )
        return EXIT_BAD_INPUT
    if summary.status == STOPPED and summary.message:  # while minimising: nothing written
        print(
            f"md run: {summary.signal} received {summary.message}; nothing was written. "
            f"Start again with: {_again(args, run, resume=False)}",
            file=sys.stderr,
        )
        return exit_for_signal(summary.signal)
    if summary.status == STOPPED:
        print(
            f"md run: {summary.signal} received; stopped after step {state.step}, checkpoint "
            f"written to {saved_path}, {summary.n_frames} frames in {output}. Continue with: "
            f"{_again(args, run, resume=True)}",
            file=sys.stderr,
        )
        return exit_for_signal(summary.signal)
    _print_summary(sim, summary, run.n_atoms)
    return EXIT_OK


class _ThermoTable:
    """Observer printing one thermo row every interval (above the progress bar).

    It keeps no rows: memory stays flat however long the run (the run's
    summary takes its first and last rows from ``sim.thermo()``).
    """

    #: Reads only thermo: a run decomposed over MPI ranks need not gather its atoms.
    whole_system = False

    columns = (
        "step",
        "time",
        "temperature",
        "potential_energy",
        "kinetic_energy",
        "total_energy",
        "pressure",
        "volume",
        "density",
    )
    headers = ("Step", "Time", "Temp", "PotEng", "KinEng", "TotEng", "Press", "Volume", "Density")

    def __init__(self, units, quiet: bool) -> None:
        self.units = units
        self.quiet = quiet
        self._printed_header = False
        self.uses_virial = not quiet  # quiet: prints nothing, so its steps need no virial

    def __call__(self, sim) -> None:
        if self.quiet:
            return
        row = sim.thermo()
        conserved = ("conserved_energy",) if "conserved_energy" in row else ()  # thermostats
        split = ("translational_temperature", "rotational_temperature")  # rigid bodies
        split = split if split[0] in row else ()
        if not self._printed_header:
            headers = self.headers + (("Conserved",) if conserved else ())
            headers += ("TempTrans", "TempRot") if split else ()
            self._write("".join(f"{h:>14}" for h in headers))
            self._printed_header = True
        time_value = row["time"] / self.units.config_time
        cells = [f"{row['step']:>14d}", f"{time_value:>14.6g}"]
        cells += [f"{row[c]:>14.6g}" for c in self.columns[2:] + conserved + split]
        self._write("".join(cells))

    def _write(self, line: str) -> None:
        tqdm.write(line)


def _progress_bar(total: int, disable: bool):
    return tqdm(
        total=total,
        unit="step",
        disable=disable or total == 0,
        dynamic_ncols=True,
        desc="md run",
        leave=False,
    )


def _again(args, run, resume: bool) -> str:
    """The command that continues (``resume``) or starts again this run: the same config,
    ``--output`` and ``--steps``, under ``mpiexec -n P`` when it ran on P ranks."""
    words = ["mpiexec", "-n", str(run.ranks.n_ranks)] if run.ranks is not None else []
    words += ["md", "run", str(args.config)]
    if args.output is not None:
        words += ["--output", str(args.output)]
    if args.steps is not None:
        words += ["--steps", str(args.steps)]
    if resume:
        words.append("--resume")
    elif args.overwrite:  # stopped before anything was written: the old output is still there
        words.append("--overwrite")
    return shlex.join(words)


def _ranks(run) -> str:
    """ ", over P MPI ranks (bricks a x b x c)" for a decomposed run."""
    if run.ranks is None:
        return ""
    shape = " x ".join(str(p) for p in run.parameters["decomposition"])
    return f" over {run.ranks.n_ranks} MPI ranks (bricks {shape})"


def _print_summary(sim, summary, n_atoms: int) -> None:
    first, wall, n_steps = summary.first, summary.wall, summary.n_steps
    output, n_frames = summary.output, summary.n_frames
    timings = summary.timings
    other = max(wall - sum(timings.values()), 0.0)
    atom_steps = n_atoms * n_steps / wall if wall > 0 and n_steps else float("nan")
    # Drifts over the whole run: from step 0's energies, which a resumed run takes from its
    # checkpoint (one written before checkpoints kept them: from where it resumed).
    origin = int(summary.reference["step"])
    since = "" if origin == 0 else f" since step {origin}"
    engine = sim.device_engine
    print(
        f"\nLoop time {wall:.3f} s for {n_steps} steps of {n_atoms} atoms: "
        f"{atom_steps:,.0f} atom-steps/s "
        + (f"on {get_threads()} thread(s)" if engine is None else "on the GPU")
        + (", mixed precision" if sim.forcefield.precision == "mixed" else "")
    )
    sections = [*timings.items(), ("other", other)]
    if engine is not None:  # the host sees the device's steps whole (its kernels run async)
        sections = [("device", timings["integrate"]), ("output", timings["output"])]
        sections.append(("other", other))
    print(f"{'Section':<10}{'time (s)':>12}{'%total':>9}")
    for name, seconds in sections:
        share = 100 * seconds / wall if wall > 0 else 0.0
        print(f"{name:<10}{seconds:>12.4f}{share:>9.1f}")
    nl = sim.forcefield.neighbor_list
    if engine is not None:
        print(
            "(device: the steps on the GPU, forces, list and integrator together; "
            "benchmarks/gpu.py splits a step by kernel)"
        )
        print(
            f"Neighbour list builds on the device: {engine.n_builds} (rebuilt when an atom "
            f"moved > skin/2); sorts of the atoms along the cells' Morton curve: "
            f"{engine.n_sorts}"
        )
    elif nl is not None:
        if nl.exact:
            rule = "rebuilt when an atom moved > skin/2"
        else:
            rule = (
                f"looked at every {nl.every} steps, "
                + ("rebuilt there if an atom moved > skin/2" if nl.check else "rebuilt there")
                + "; not exact: pairs can be missed between looks"
            )
        print(f"Neighbour list builds: {nl.n_builds} ({rule})")
        if not nl.exact:
            print(
                f"Late looks: {summary.late_looks} (looks at which an atom had moved > "
                "skin/2 since the build: pairs within the cutoff may have been missed "
                "before them)"
            )
        if nl.n_prunes:
            print(
                f"Cluster list prunes: {nl.n_prunes} (the outer list pruned again when an "
                "atom moved > skin/2, searched again past (outer_skin - skin)/2)"
            )
    per_step = ", ".join(
        f"{name.replace('_', ' ')} {value:.3g}" for name, value in summary.per_step().items()
    )
    if per_step:
        print(f"Integrator, per step: {per_step}")
    drift = summary.relative_change("total_energy")
    print(f"Relative total-energy drift (E_end - E_start)/|E_start|{since}: {drift:.3e}")
    if "conserved_energy" in first:  # a thermostat: its conserved quantity should not drift
        change = summary.relative_change("conserved_energy")
        print(f"Relative conserved-quantity drift (incl. heat bath){since}: {change:.3e}")
    print(f"Wrote {n_frames} frames to {output}")
