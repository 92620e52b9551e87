"""Minimise a config's structure from Python: what ``md minimize`` does, without the terminal.

:func:`prepare_minimize` validates and builds (writing nothing);
:meth:`PreparedMinimize.execute` claims the output, runs FIRE and writes the structure
as a one-frame H5MD file, whole at the end; :func:`minimize_config` does both. The
statuses are :mod:`md.guards`'.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

from md._checks import count, positive
from md._files import exclusive_claim, remove_stale_temporaries
from md.assemble import build_components, run_topology, set_run_threads
from md.config import Config, MinimizeConfig, load_config
from md.errors import ConfigError, NonFiniteError, OutputBusyError
from md.guards import (
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
from md.simulation import Simulation
from md.trajectory import H5MDWriter

#: Suffixes of the H5MD files ``md minimize`` writes.
H5MD_SUFFIXES = (".h5", ".hdf5", ".h5md", ".hdf")


@dataclass
class MinimizeSummary:
    """What :meth:`PreparedMinimize.execute` did.

    ``status`` is ``"completed"`` (the structure was written; ``result.converged``
    says whether FIRE reached ``fmax``), ``"failed"`` (forces became
    non-finite), ``"output_error"`` (the file could not be written, e.g. disk
    full: nothing was left) or ``"stopped"`` (a signal, named in ``signal``:
    nothing was written). ``message`` holds the error.
    """

    status: str
    output: Path
    result: MinimizeResult | None = None
    message: str = ""
    signal: str | None = None


@dataclass
class PreparedMinimize:
    """A validated minimisation that has written nothing yet (see :func:`prepare_minimize`).

    ``stage`` holds the FIRE settings in use (the config's ``[minimize]``
    with the arguments' overrides); ``output`` is the file to write (a
    symlink's target).
    """

    config: Config
    sim: Simulation
    output: Path
    overwrite: bool
    stage: MinimizeConfig

    def execute(
        self,
        callback: Callable[[int, float, float], None] | None = None,
        handle_signals: bool = True,
    ) -> MinimizeSummary:
        """Claim the output, minimise, and write the structure as a one-frame H5MD file.

        The file is built in memory and written whole at the end, so a full
        disk, an error or a signal leaves no file behind. SIGINT/SIGTERM stop
        the minimisation at its next step (a second one at once).

        Raises
        ------
        ConfigError
            If the output appeared meanwhile.
        OutputBusyError
            If another run claimed the output meanwhile.
        """
        with contextlib.ExitStack() as claimed:
            try:
                claimed.enter_context(exclusive_claim(self.output))
            except OutputBusyError:
                raise
            except OSError as error:  # no room even for the claim's lock file
                return MinimizeSummary(OUTPUT_ERROR, self.output, message=str(error))
            remove_stale_temporaries(self.output)
            if self.output.exists() and not self.overwrite:
                raise ConfigError(f"output file {self.output} appeared while minimising started")
            return self._execute(callback, handle_signals)

    def _execute(self, callback, handle_signals: bool) -> MinimizeSummary:
        sim, stage, state = self.sim, self.stage, self.sim.state
        stop = StopRequest()
        previous = catch_stop_signals(stop.request, stop.pending) if handle_signals else {}
        try:
            result = minimize(
                state,
                sim.forcefield,
                stage.fmax,
                stage.max_steps,
                max_force=stage.max_force,
                max_step=stage.max_step,
                callback=callback,
                report_every=stage.report_every,
                stop=stop,
            )
        except NonFiniteError as error:
            return MinimizeSummary(FAILED, self.output, message=str(error))
        finally:
            restore_signals(previous)
        if result.stopped:
            return MinimizeSummary(STOPPED, self.output, result, signal=stop.signal)
        try:
            with H5MDWriter(
                self.output,
                state,
                units=self.config.units,
                overwrite=self.overwrite,
                topology=run_topology(sim),
                in_memory=True,
                parameters={"config": self.config.text, "minimize": result.describe()},
            ) as writer:
                writer.write(state, thermo=sim.thermo())
        except OSError as error:
            return MinimizeSummary(OUTPUT_ERROR, self.output, result, message=str(error))
        return MinimizeSummary(COMPLETED, self.output, result)


def prepare_minimize(
    path_or_config: str | os.PathLike | Config,
    output: str | os.PathLike | None = None,
    overwrite: bool = False,
    fmax: float | None = None,
    max_steps: int | None = None,
    max_force: float | None = None,
    threads: int | None = None,
) -> PreparedMinimize:
    """Validate and build what ``md minimize`` does; write nothing.

    Parameters
    ----------
    path_or_config : path or Config
        The config describing the system; its ``[minimize]`` table gives
        the defaults.
    output : path, optional
        H5MD file to write (``.h5``, ``.hdf5``, ``.h5md``); default
        ``<[output] path stem>_min.h5``.
    overwrite : bool
        Replace an existing output (never a file another run is writing,
        one of the config's inputs, or anything but a regular file).
    fmax, max_steps, max_force : optional
        Override ``[minimize]`` fmax [energy/length], max_steps and the
        push-off's force cap.
    threads : int, optional
        Kernel threads, overriding ``[run] threads``.

    Raises
    ------
    ConfigError
        For anything wrong; the message names the option, key or file.
    """
    config = path_or_config if isinstance(path_or_config, Config) else load_config(path_or_config)
    config_file = str(path_or_config) if not isinstance(path_or_config, Config) else config.source
    if config.rigid is not None:  # FIRE moves atoms one by one
        raise ConfigError(
            f"{config.source}: [rigid]: md minimize does not keep rigid bodies (yet); drop the "
            "[rigid] table to minimise the atoms, or start from a relaxed structure"
        )
    overrides = {}
    try:
        if fmax is not None:
            overrides["fmax"] = positive(fmax, "--fmax")
        if max_steps is not None:
            overrides["max_steps"] = count(max_steps, "--max-steps", minimum=1)
        if max_force is not None:
            overrides["max_force"] = positive(max_force, "--max-force")
    except ValueError as error:
        raise ConfigError(str(error)) from None
    stage = replace(config.minimize or MinimizeConfig(), **overrides)
    if output is None:
        output = config.output.path.with_name(f"{config.output.path.stem}_min.h5")
    output = writable_output(Path(output))
    refuse_inputs_as_outputs(config, config_file, path_or_config, (output,))
    if output.suffix.lower() not in H5MD_SUFFIXES:
        raise ConfigError(
            f"{output}: md minimize writes H5MD, so name the output *.h5; to get another "
            f"format, convert it afterwards: md convert {output.with_suffix('.h5')} {output}"
        )
    refuse_claimed(output)
    if output.exists() and not overwrite:
        raise ConfigError(f"{output} already exists; pass --overwrite or choose --output")
    state, potentials, integrator = build_components(config)
    set_run_threads(config, threads)
    try:
        sim = Simulation(
            state,
            potentials,
            integrator,
            skin=config.run.skin,
            units=config.units,
            precision=config.run.precision,
            outer_skin=config.run.outer_skin,
        )
    except ValueError as error:
        raise ConfigError(f"{config.source}: {error}") from None
    return PreparedMinimize(config, sim, output, overwrite, stage)


def minimize_config(
    path_or_config: str | os.PathLike | Config, **options
) -> tuple[Simulation, MinimizeSummary]:
    """Minimise the structure a config builds and write it, as ``md minimize`` does.

    ``options`` are those of :func:`prepare_minimize`. Returns the Simulation
    (at the relaxed state) and a :class:`MinimizeSummary`.
    """
    prepared = prepare_minimize(path_or_config, **options)
    return prepared.sim, prepared.execute()


__all__ = [
    "H5MD_SUFFIXES",
    "MinimizeSummary",
    "PreparedMinimize",
    "minimize_config",
    "prepare_minimize",
]
