"""Run a config from Python: what ``md run`` does, without the terminal.

:func:`prepare` validates and builds everything a config describes (system,
potentials, integrator, threads, a resumed checkpoint) and writes nothing;
:meth:`PreparedRun.execute` then claims the outputs, writes the trajectory
and checkpoints, and runs. :func:`run_config` does both. The CLI (``md
run``) and the sweep workers go through here, so a run started from Python
is the run the command line would make, file for file.

Examples
--------
>>> import md
>>> sim, summary = md.run_config("examples/lj_small.toml", steps=10,
...                              output=tmp / "small.h5")  # doctest: +SKIP
>>> summary.status, summary.n_frames  # doctest: +SKIP
('completed', 1)
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import time
import tomllib
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from integrators.base import Statistics
from integrators.rigid import bodies_of
from md._checks import count
from md._files import exclusive_claim, remove_stale_temporaries
from md.assemble import build_components as build_components  # moved; importable from here
from md.assemble import build_potentials as build_potentials  # moved; importable from here
from md.assemble import build_simulation, run_topology
from md.checkpoint import (
    Checkpoint,
    Checkpointer,
    checkpoint_path,
    fingerprint_changes,
    physics_fingerprint,
    read_checkpoint,
    write_checkpoint,
)
from md.config import (
    Config,
    load_config,
    parse_config,
)
from md.distributed import Elsewhere, agree, mpi_ranks, on_root
from md.errors import (
    CheckpointError,
    ConfigError,
    ConvergenceError,
    SimulationError,
    TrajectoryError,
)
from md.guards import (
    ABORTED,
    COMPLETED,
    FAILED,
    OUTPUT_ERROR,
    STOPPED,
    StopRequest,
    catch_stop_signals,
    refuse_claimed,
    refuse_inputs_as_outputs,
    restore_signals,
    writable_output,
)
from md.minimize import MinimizeResult, minimize
from md.parallel import global_sum
from md.relax import H5MD_SUFFIXES as H5MD_SUFFIXES  # moved; importable from here
from md.relax import MinimizeSummary as MinimizeSummary  # moved; importable from here
from md.relax import PreparedMinimize as PreparedMinimize  # moved; importable from here
from md.relax import minimize_config as minimize_config  # moved; importable from here
from md.relax import prepare_minimize as prepare_minimize  # moved; importable from here
from md.simulation import Simulation
from md.state import State
from md.trajectory import H5MDWriter, read_frame_steps, verify_frames

logger = logging.getLogger(__name__)


@dataclass
class RunSummary:
    """What a run did.

    Attributes
    ----------
    status : str
        ``"completed"``; ``"failed"`` (the dynamics blew up or an implicit
        solve did not converge: ``message`` names the step); ``"output_error"``
        (the trajectory could not be written, e.g. disk full); ``"stopped"``
        (a signal asked it to stop: ``signal`` names it; a checkpoint was
        written, unless ``message`` says the run stopped while minimising,
        before anything was written); ``"aborted"`` (a second signal while
        stopping).
    output, checkpoint : Path
        The trajectory and its checkpoint.
    n_steps : int
        Steps this call was asked to take (the config's total less the
        checkpoint's step when resuming).
    n_frames : int
        Frames in the trajectory at the end.
    wall : float
        Seconds spent in the loop.
    first, last : dict
        ``sim.thermo()`` before and after the loop.
    start : dict
        The energies at the start of the whole run (step 0): ``step``,
        ``total_energy``, ``kinetic_energy`` and, with a thermostat,
        ``conserved_energy``. A resumed run takes them from its checkpoint,
        so drifts can be measured over the whole run; empty when resuming
        from a checkpoint written before checkpoints kept them.
    timings : dict
        Seconds per section (neighbour, force, integrate, observers) in the loop.
    last_checkpoint_step : int or None
        Step of the checkpoint on disk at the end: the last one written, or
        the one resumed from or written at the start if none was written
        since; None if there is none.
    message : str
        The error, for ``failed`` and ``output_error``.
    signal : str or None
        ``"SIGINT"`` or ``"SIGTERM"`` for ``stopped``.
    statistics : dict
        The integrator's cumulative counters at the end (its ``statistics``
        hook, :class:`integrators.base.Statistics`; empty without one).
    late_looks : int
        Looks of a neighbour list that is not exact (``[run] neighbor_every``
        above 1, or ``neighbor_check = false``) at which an atom had moved more
        than half the skin since the list was built, so that pairs within the
        cutoff may have been missed before (see
        :attr:`md.neighbors.NeighborList.n_late_looks`); always 0 for the
        exact list.
    """

    status: str
    output: Path
    checkpoint: Path
    n_steps: int
    n_frames: int = 0
    wall: float = 0.0
    first: dict = field(default_factory=dict)
    last: dict = field(default_factory=dict)
    start: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    last_checkpoint_step: int | None = None
    message: str = ""
    signal: str | None = None
    statistics: dict = field(default_factory=dict)
    late_looks: int = 0

    @property
    def reference(self) -> dict:
        """The row drifts are measured from: ``start`` (step 0, also for a resumed run)
        where it is known, else ``first``."""
        return self.start if "total_energy" in self.start else self.first

    def relative_change(self, key: str = "total_energy") -> float:
        """(last - reference) of a thermo quantity over the reference total energy's scale.

        Over the whole run: from step 0 (:attr:`reference`), which a resumed
        run takes from its checkpoint. The scale is the larger of the
        magnitude of the total energy and the kinetic energy there (so a
        total energy near zero does not blow the ratio up). NaN when the run
        has no ``last`` row (it did not complete) or no ``key``.
        """
        first, last = self.reference, self.last
        if key not in first or key not in last:
            return math.nan
        scale = max(abs(first["total_energy"]), abs(first["kinetic_energy"]), 1e-300)
        return (last[key] - first[key]) / scale

    def per_step(self) -> dict[str, float]:
        """The integrator's counters divided by its steps (``steps`` itself left out)."""
        steps = self.statistics.get("steps")
        if not steps:
            return {}
        return {name: value / steps for name, value in self.statistics.items() if name != "steps"}


#: What a checkpoint keeps of the run's first thermo row, to measure drifts from it.
_START_KEYS = ("step", "total_energy", "kinetic_energy", "conserved_energy")


@dataclass
class PreparedRun:
    """A validated, built run that has written nothing yet (see :func:`prepare`).

    Attributes
    ----------
    config : Config
        The parsed config (with ``steps`` overridden if asked).
    sim : Simulation
        The simulation, at the checkpoint's state when resuming.
    output, checkpoint_path : Path
        Where the trajectory and its checkpoint go.
    n_steps : int
        Steps still to take.
    checkpoint : Checkpoint or None
        The checkpoint being resumed.
    parameters : dict
        What the trajectory's ``/parameters`` group records.
    """

    config: Config
    sim: Simulation
    output: Path
    checkpoint_path: Path
    n_steps: int
    overwrite: bool
    checkpoint: Checkpoint | None
    fingerprint: dict
    run_id: str
    parameters: dict
    config_file: str
    minimized: MinimizeResult | None = None
    #: Atoms in the whole system (a decomposed run's ``sim.state`` holds one rank's).
    n_atoms: int = 0
    #: The ranks of a run decomposed over MPI (None: one process).
    ranks: object = None

    @property
    def resuming(self) -> bool:
        return self.checkpoint is not None

    @property
    def complete(self) -> bool:
        """True when resuming a run that already took all its steps."""
        return self.checkpoint is not None and self.n_steps == 0

    def minimize(
        self,
        callback: Callable[[int, float, float], None] | None = None,
        stop: Callable[[], bool] | None = None,
    ):
        """Run the config's ``[minimize]`` stage on the state; return its MinimizeResult.

        Only a fresh run minimises (a resumed one starts from its checkpoint,
        which holds the minimised state), and only once. FIRE 2.0 moves the
        positions (velocities stay as drawn); ``callback(step, energy, fmax)``
        reports progress; ``stop()`` True ends it early (``result.stopped``).
        Returns None when there is nothing to do.
        """
        stage = self.config.minimize
        if stage is None or self.checkpoint is not None:
            return None
        if self.minimized is None or self.minimized.stopped:
            sim = self.sim
            options = {
                "max_force": stage.max_force,
                "max_step": stage.max_step,
                "callback": callback,
                "report_every": stage.report_every,
            }
            if self.ranks is not None:
                # Not ``stop``: a signal reaches one rank, and every rank must take the
                # same steps; a decomposed run stops after the stage instead.
                self.minimized = sim.minimize(stage.fmax, stage.max_steps, **options)
            else:
                neighbors = sim.forcefield.neighbor_list
                # a list looked at every N steps only would not follow the minimiser,
                # whose steps are not the state's
                with neighbors.exactly() if neighbors is not None else contextlib.nullcontext():
                    self.minimized = minimize(
                        sim.state, sim.forcefield, stage.fmax, stage.max_steps, stop=stop, **options
                    )
            sim.integrator.reset()  # history taken at the old positions is stale
        return self.minimized

    def execute(
        self,
        observers: Sequence[tuple[Callable, int]] = (),
        handle_signals: bool = True,
        minimize_progress: Callable[[int, float, float], None] | None = None,
    ) -> RunSummary:
        """Write the outputs and run; return a :class:`RunSummary`.

        A ``[minimize]`` stage runs first (:meth:`minimize`), under the output's
        claim and before anything is written: the first checkpoint and frame
        hold the minimised state, so ``--resume`` never minimises again, and a
        run killed while minimising has written nothing (a plain re-run
        repeats the deterministic minimisation).

        Parameters
        ----------
        observers : sequence of (callable, int)
            More observers and their intervals (a thermo table, a progress
            bar), attached after the trajectory writer and the checkpointer.
        handle_signals : bool
            Catch SIGINT and SIGTERM (main thread only) so that the run stops
            after the current step with a checkpoint; a second signal stops it
            at once.
        minimize_progress : callable, optional
            ``callback(step, energy, fmax)`` of the minimisation stage.

        Raises
        ------
        TrajectoryError
            If the trajectory cannot be created (nothing was run).
        OSError
            If the first checkpoint or the trajectory cannot be written.
        """
        with self._claim():
            if self.config.minimize is not None and self.checkpoint is None:
                stop = StopRequest()
                previous = catch_stop_signals(stop.request, stop.pending) if handle_signals else {}
                try:
                    self.minimize(minimize_progress, stop=stop)
                finally:
                    restore_signals(previous)
                if stop.signal is not None and self.ranks is not None:
                    # Every rank must leave together: the run stops at its first step.
                    self.sim.request_stop(stop.signal)
                elif stop.signal is not None:
                    return RunSummary(
                        STOPPED,
                        self.output,
                        self.checkpoint_path,
                        self.n_steps,
                        message="while minimising",
                        signal=stop.signal,
                    )
            return self._execute(observers, handle_signals)

    @contextlib.contextmanager
    def _claim(self):
        """:func:`exclusive_claim` on the output, by rank 0 alone in a decomposed run (every
        rank learns whether it got it)."""
        if self.ranks is None:
            with exclusive_claim(self.output):
                yield
            return
        with contextlib.ExitStack() as stack:
            error = None
            if self.ranks.rank == 0:
                try:
                    stack.enter_context(exclusive_claim(self.output))
                except OSError as caught:
                    error = caught
            agree(self.ranks, error)
            yield

    def _execute(self, observers, handle_signals: bool) -> RunSummary:
        sim, state, config, ranks = self.sim, self.sim.state, self.config, self.ranks
        summary = RunSummary(COMPLETED, self.output, self.checkpoint_path, self.n_steps)
        summary.first = sim.thermo()
        if self.checkpoint is None:
            summary.start = {key: summary.first[key] for key in _START_KEYS if key in summary.first}
        else:
            summary.start = dict(self.checkpoint.extra.get("start") or {})
        writer = self._open_outputs(summary.start)  # None on the other ranks of a decomposed run
        saver = Checkpointer(
            self.checkpoint_path,
            writer,
            self.fingerprint,
            self.run_id,
            self.config_file,
            start=summary.start,
        )
        sim.attach(
            writer if writer is not None else Elsewhere(config.output.forces),
            interval=config.output.every,
        )
        # After the writer, so a checkpoint counts the frame of its own step. With
        # checkpoint_every = 0 it only fires at the start of a fresh run (step 0).
        sim.attach(saver, interval=config.output.checkpoint_every or 2**62)
        for observer, interval in observers:
            sim.attach(observer, interval=interval)
        start_step = state.step  # _open_outputs wrote (or resumed) a checkpoint here
        timings_before = sim.timing_summary()
        neighbors = sim.forcefield.neighbor_list
        late_before = neighbors.n_late_looks if neighbors is not None else 0
        previous = (
            catch_stop_signals(sim.request_stop, lambda: sim.stop_requested)
            if handle_signals
            else {}
        )
        start = time.perf_counter()
        try:
            with writer if writer is not None else contextlib.nullcontext():
                sim.run(self.n_steps)
                saved_at = on_root(ranks, lambda: saver.last_step)
                if sim.stop_requested is None or saved_at != state.step:
                    # At the end, and after a signal (a decomposed run gathers it on rank 0).
                    if ranks is None:
                        saver(sim)
                    else:
                        sim.observe(saver)
        except (SimulationError, ConvergenceError) as error:
            summary.status, summary.message = FAILED, str(error)
        except KeyboardInterrupt:  # a second signal while stopping: leave at once
            summary.status = ABORTED
        except (OSError, RuntimeError) as error:  # disk full (h5py raises either), file removed
            summary.status, summary.message = OUTPUT_ERROR, str(error)
        finally:
            restore_signals(previous)
        summary.wall = time.perf_counter() - start
        n_frames = on_root(ranks, lambda: writer.n_frames)
        last_step = on_root(ranks, lambda: saver.last_step)
        if summary.status == OUTPUT_ERROR and self.checkpoint is None and n_frames == 0:
            # Not even the first frame fitted: keep nothing, so a plain re-run can start.
            if ranks is None or ranks.rank == 0:
                self.output.unlink(missing_ok=True)
                self.checkpoint_path.unlink(missing_ok=True)
            last_step = None
        summary.n_frames = n_frames
        summary.last_checkpoint_step = last_step
        if last_step is None and self.checkpoint_path.exists():
            summary.last_checkpoint_step = start_step  # none since: the start's is there
        summary.timings = {k: v - timings_before[k] for k, v in sim.timing_summary().items()}
        if neighbors is not None:
            summary.late_looks = neighbors.n_late_looks - late_before
            if summary.late_looks:  # the first one was a warning: the count goes to the log
                logger.info(
                    "%d looks at the neighbour list (every %d steps%s) found an atom moved "
                    "more than skin/2 since the build: pairs may have been missed",
                    summary.late_looks,
                    neighbors.every,
                    "" if neighbors.check else ", no check",
                )
        if summary.status == COMPLETED and sim.stop_requested is not None:
            summary.status, summary.signal = STOPPED, sim.stop_requested
        if summary.status == COMPLETED:
            summary.last = sim.thermo()
        if isinstance(sim.integrator, Statistics):
            summary.statistics = dict(sim.integrator.statistics)
        return summary

    def _open_outputs(self, start: dict) -> H5MDWriter | None:
        """Under the claim: the first checkpoint, then the trajectory writer.

        A fresh run checks again that its outputs are still free (another run
        may have finished meanwhile). If the trajectory cannot be created (disk
        full), the checkpoint written a moment before is removed again, so a
        plain re-run is not refused because of it. A decomposed run gathers the
        whole system on rank 0, which writes; the other ranks get None.
        """
        if self.ranks is None:
            sim = self.sim
            return self._create_outputs(sim.state, sim.integrator, sim.forcefield, start)
        view = self.sim.global_view(thermo=False, layout=True)  # (a checkpoint's)
        error = writer = None
        if view is not None:
            try:
                writer = self._create_outputs(view.state, view.integrator, view.forcefield, start)
            except (OSError, ValueError, RuntimeError) as caught:  # every rank learns it below
                error = caught
        agree(self.ranks, error)
        return writer

    def _create_outputs(self, state, integrator, forcefield, start: dict) -> H5MDWriter:
        config = self.config
        for path in (self.output, self.checkpoint_path):  # a killed run's half-written files
            remove_stale_temporaries(path)
        if self.checkpoint is None:
            if not self.overwrite:
                for path in (self.output, self.checkpoint_path):
                    if path.exists():
                        raise ConfigError(f"output file {path} appeared while the run started")
            # First a checkpoint of the start, then the trajectory: whenever a run is
            # killed, --resume finds a checkpoint (the file may not exist yet).
            write_checkpoint(
                self.checkpoint_path,
                state,
                integrator,
                forcefield,
                fingerprint=self.fingerprint,
                run_id=self.run_id,
                extra={"config_file": self.config_file, "start": start},
            )
            try:
                return self._new_trajectory(state, overwrite=self.overwrite)
            except BaseException:
                self.checkpoint_path.unlink(missing_ok=True)
                raise
        if self.output.exists():
            return H5MDWriter(
                self.output,
                state,
                units=config.units,
                append=True,
                keep_frames=self.checkpoint.n_frames,
                bodies=bodies_of(self.sim.integrator),  # rigid bodies' frames, if any
            )
        return self._new_trajectory(state, overwrite=True)

    def _new_trajectory(self, state: State, overwrite: bool) -> H5MDWriter:
        output = self.config.output
        return H5MDWriter(
            self.output,
            state,
            units=self.config.units,
            velocities=output.velocities,
            forces=output.forces,
            parameters=self.parameters,
            overwrite=overwrite,
            topology=run_topology(self.sim),
            # A cell that may start to tilt needs (3, 3) edges from the first frame.
            triclinic=not state.is_orthorhombic
            or (
                self.config.barostat is not None
                and self.config.barostat.get("couple") == "triclinic"
            ),
            conserved=self.sim.integrator.thermostat,
            bodies=bodies_of(self.sim.integrator),  # rigid bodies' frames, if any
        )


def prepare(
    path_or_config: str | os.PathLike | Config,
    steps: int | None = None,
    output: str | os.PathLike | None = None,
    overwrite: bool = False,
    resume: bool = False,
    threads: int | None = None,
    device: str | None = None,
) -> PreparedRun:
    """Validate and build the run a config describes; write nothing.

    Parameters are those of :func:`run_config`. Under an MPI launcher with
    several processes (``mpiexec -n P``), every rank validates alike, and the
    run is built decomposed over them (:class:`md.distributed.DistributedSimulation`).

    Raises
    ------
    ConfigError, CheckpointError, TrajectoryError
        For anything wrong with the config, its files, the output path or the
        checkpoint to resume; the message names the file, key or value.
    """
    try:
        ranks = mpi_ranks()
    except RuntimeError as error:  # several processes but no mpi4py
        raise ConfigError(str(error)) from None
    inputs, error = None, None
    try:
        inputs = _inputs(path_or_config, steps, output, overwrite, resume, ranks, device)
    except INPUT_ERRORS as caught:
        if ranks is None:
            raise
        error = caught  # every rank raises the first rank's error below, none waits
    if ranks is not None:
        agree(ranks, error)
    config, config_file, output, saved_path, fingerprint, checkpoint = inputs
    try:
        sim = build_simulation(config, checkpoint, saved_path, threads, ranks)
    except MemoryError:
        raise ConfigError(f"{config_file}: the system is too large to build in memory") from None
    integrator, units = sim.integrator, config.units
    run_id = checkpoint.run_id if checkpoint is not None else uuid.uuid4().hex
    if ranks is not None and checkpoint is None:
        run_id = ranks.broadcast(run_id)
    parameters = {
        "config": config.text,
        "config_file": config_file,
        "potentials": [p.describe() for p in sim.potentials],
        "integrator": integrator.describe(),
        "dt_config": integrator.dt / units.config_time,
        "dt_config_unit": units.config_time_label,
        "skin": config.run.skin,
        "seed": -1 if config.seed is None else config.seed,
        "n_steps": config.run.steps,
        "run_id": run_id,
    }
    if ranks is not None:
        parameters["mpi_ranks"] = ranks.n_ranks
        parameters["decomposition"] = list(sim.grid.shape)
    return PreparedRun(
        config=config,
        sim=sim,
        output=output,
        checkpoint_path=saved_path,
        n_steps=config.run.steps - sim.state.step,
        overwrite=overwrite,
        checkpoint=checkpoint,
        fingerprint=fingerprint,
        run_id=run_id,
        parameters=parameters,
        config_file=config_file,
        n_atoms=_whole_count(sim, ranks),
        ranks=ranks,
    )


def _inputs(path_or_config, steps, output, overwrite: bool, resume: bool, ranks, device=None):
    """Read and check the config, the output paths and a checkpoint to resume (no
    collective calls: a decomposed run's ranks agree on the outcome afterwards)."""
    config = path_or_config if isinstance(path_or_config, Config) else load_config(path_or_config)
    config_file = str(path_or_config) if not isinstance(path_or_config, Config) else config.source
    if steps is not None:
        try:
            config = replace(
                config, run=replace(config.run, steps=count(steps, "--steps", minimum=0))
            )
        except ValueError as error:
            raise ConfigError(str(error)) from None
    if device is not None:
        if device not in ("cpu", "cuda"):
            raise ConfigError(f"--device must be cpu or cuda, got {device!r}")
        config = replace(config, run=replace(config.run, device=device))
    if ranks is not None and config.seed is None:
        config = _seeded(config, ranks)
    where = "--output" if output is not None else f"{config.source}: [output] path"
    try:
        output = writable_output(Path(output) if output is not None else config.output.path)
    except ConfigError as error:  # say where the path came from
        raise ConfigError(f"{where}: {error}") from None
    saved_path = checkpoint_path(output)
    writable_output(saved_path)
    refuse_inputs_as_outputs(config, config_file, path_or_config, (output, saved_path))
    refuse_claimed(output)
    fingerprint = physics_fingerprint(config)
    checkpoint = None
    if resume:
        if overwrite:
            raise ConfigError("--resume continues the existing output; drop --overwrite")
        checkpoint = read_checkpoint(saved_path)
        if not output.exists() and checkpoint.n_frames:
            raise ConfigError(f"--resume: trajectory {output} does not exist")
        changes = fingerprint_changes(checkpoint.fingerprint, fingerprint)
        if changes:
            raise ConfigError(
                f"--resume: {config_file} changed the physics since checkpoint "
                f"{saved_path} was written ({'; '.join(changes)}); only [run] steps, "
                "thermo_every, threads, device, decomposition, balance_every, "
                "balance_threshold and [output] every/checkpoint_every may change"
            )
        if output.exists():
            _check_resumable(output, checkpoint)
        if checkpoint.state.step > config.run.steps:
            raise ConfigError(
                f"--resume: checkpoint {saved_path} is at step {checkpoint.state.step}, "
                f"beyond the {config.run.steps} steps asked for"
            )
    else:
        for path in (output, saved_path):
            if path.exists() and not overwrite:
                raise ConfigError(
                    f"output file {path} already exists; pass --overwrite to replace it, "
                    "--resume to continue it, or --output to choose another path"
                )
    return config, config_file, output, saved_path, fingerprint, checkpoint


def _seeded(config: Config, ranks) -> Config:
    """``config`` with a seed drawn by rank 0 for all ranks: each builds the same system and
    the same random streams (a config without one draws them from fresh entropy)."""
    if not config.text:
        raise ConfigError(f"{config.source}: a run over several MPI ranks needs a seed")
    seed = ranks.broadcast(int(np.random.SeedSequence().generate_state(1)[0]) >> 1)
    data = tomllib.loads(config.text)
    data["seed"] = seed
    seeded = parse_config(
        data, source=config.source, text=config.text, base=Path(config.source).parent
    )
    return replace(seeded, run=replace(seeded.run, steps=config.run.steps))


def _whole_count(sim, ranks) -> int:
    """Atoms in the whole system."""
    return sim.state.n_atoms if ranks is None else int(global_sum(sim.state.n_atoms, ranks))


def run_config(
    path_or_config: str | os.PathLike | Config,
    steps: int | None = None,
    output: str | os.PathLike | None = None,
    overwrite: bool = False,
    resume: bool = False,
    threads: int | None = None,
    device: str | None = None,
) -> tuple[Simulation, RunSummary]:
    """Run a TOML config as ``md run`` does; return the Simulation and a summary.

    Parameters
    ----------
    path_or_config : path or Config
        The config file (or one parsed with :func:`md.config.load_config`).
    steps : int, optional
        Total steps, overriding ``[run] steps``.
    output : path, optional
        Trajectory path, overriding ``[output] path``; the checkpoint goes
        next to it (``OUTPUT.ckpt``).
    overwrite : bool
        Replace an existing output and checkpoint.
    resume : bool
        Continue from the output's checkpoint (bit for bit).
    threads : int, optional
        Kernel threads, overriding ``[run] threads`` (default: every core).
    device : {"cpu", "cuda"}, optional
        Where the time step runs, overriding ``[run] device`` (see :mod:`md.cuda`).

    Returns
    -------
    sim : Simulation
    summary : RunSummary
        ``summary.status`` says whether the run completed; a run that blew
        up reports ``"failed"`` with the step in ``summary.message`` rather
        than raising, as its frames and last checkpoint are kept.

    Raises
    ------
    ConfigError, CheckpointError, TrajectoryError
        Before anything is written, for bad input.
    """
    prepared = prepare(path_or_config, steps, output, overwrite, resume, threads, device)
    if prepared.complete:
        return prepared.sim, RunSummary(
            COMPLETED,
            prepared.output,
            prepared.checkpoint_path,
            0,
            n_frames=prepared.checkpoint.n_frames,
            start=dict(prepared.checkpoint.extra.get("start") or {}),
        )
    return prepared.sim, prepared.execute()


# ------------------------------------------------------------------ helpers
def _check_resumable(output: Path, checkpoint: Checkpoint) -> None:
    """Raise ConfigError unless ``output`` holds the frames ``checkpoint`` counted."""
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
    verify_frames(output, n)  # the frames kept must be intact (checksums)


__all__ = [
    "PreparedRun",
    "RunSummary",
    "prepare",
    "run_config",
]
# Errors a caller of prepare() should expect, for ``except`` clauses.
INPUT_ERRORS = (ConfigError, CheckpointError, TrajectoryError)
