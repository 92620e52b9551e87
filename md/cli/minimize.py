"""``md minimize CONFIG.toml``: relax the config's starting structure with FIRE 2.0.

Builds the system as ``md run`` would, minimises it (``[minimize]`` of the
config, or the options here), prints progress and the final max force, and
writes the relaxed structure as a one-frame H5MD file (with its bonds), which
``[system] structure`` can start a run from. The work is
:func:`md.relax.prepare_minimize` and :meth:`md.relax.PreparedMinimize.execute`.
Exit codes: 0 converged, 1 not converged (the structure is still written) or
non-finite forces, 2 bad input or an unwritable output (nothing is left),
130/143 stopped by SIGINT/SIGTERM (nothing is written).
"""

from __future__ import annotations

import sys
from pathlib import Path

from md.cli._common import (
    EXIT_BAD_INPUT,
    EXIT_FAILED,
    EXIT_OK,
    built_unless_stopped,
    exit_for_signal,
    fail,
)
from md.errors import ConfigError, OutputBusyError
from md.guards import FAILED, OUTPUT_ERROR, STOPPED
from md.relax import prepare_minimize


def add_parser(subparsers) -> None:
    """Add ``md minimize`` and its options."""
    parser = subparsers.add_parser(
        "minimize",
        help="relax a config's starting structure with FIRE 2.0 and write it as H5MD",
        description=(
            "Minimise the energy of the system a config builds (FIRE 2.0; a capped-force "
            "push-off with --max-force) and write the relaxed structure as a one-frame H5MD "
            "file. Defaults come from the config's [minimize] table."
        ),
    )
    parser.add_argument("config", type=Path, help="TOML config describing the system")
    parser.add_argument(
        "-o", "--output", type=Path, help="H5MD file to write (default: <output stem>_min.h5)"
    )
    parser.add_argument("--fmax", type=float, help="target max force per atom [energy/length]")
    parser.add_argument("--max-steps", type=int, help="most FIRE steps")
    parser.add_argument("--max-force", type=float, help="cap each atom's force (push-off)")
    parser.add_argument(
        "--threads",
        type=int,
        help="threads for the force and neighbour kernels (overrides [run] threads)",
    )
    parser.add_argument("--overwrite", action="store_true", help="replace OUTPUT if it exists")
    parser.add_argument("--quiet", "-q", action="store_true", help="no progress lines")


def main(args) -> int:
    """Body of ``md minimize``; returns the exit code."""
    # Building (and compiling) comes before FIRE's own stop handler: a signal there
    # stops the command with a line, as one while minimising does.
    try:
        prepared, stopped = built_unless_stopped(
            lambda: prepare_minimize(
                args.config,
                output=args.output,
                overwrite=args.overwrite,
                fmax=args.fmax,
                max_steps=args.max_steps,
                max_force=args.max_force,
                threads=args.threads,
            ),
            "minimize",
            "minimising",
        )
    except ConfigError as error:
        fail(str(error))
        return EXIT_BAD_INPUT
    if stopped is not None:
        return stopped
    stage, units, output = prepared.stage, prepared.config.units, prepared.output
    force_unit = f"{units.labels['energy']}/{units.labels['length']}"
    cap = f", forces capped at {stage.max_force:g}" if stage.max_force is not None else ""
    print(
        f"md minimize: {prepared.sim.state.n_atoms} atoms, FIRE 2.0 to max force <= "
        f"{stage.fmax:g} {force_unit}, at most {stage.max_steps} steps{cap}"
    )

    def report(step, energy, largest):
        if not args.quiet:
            print(f"  step {step:>7}  energy {energy:.10g}  max force {largest:.4g}", flush=True)

    try:
        summary = prepared.execute(callback=report)
    except (ConfigError, OutputBusyError) as error:
        fail(str(error))
        return EXIT_BAD_INPUT
    if summary.status == FAILED:
        fail(f"minimisation failed: {summary.message}")
        return EXIT_FAILED
    result = summary.result
    if summary.status == STOPPED:
        print(
            f"md minimize: {summary.signal} received; stopped at step {result.steps} (max "
            f"force {result.fmax:.4g}); nothing was written to {output}",
            file=sys.stderr,
        )
        return exit_for_signal(summary.signal)
    if result is not None:
        print(f"md minimize: {result.describe()}")
    if summary.status == OUTPUT_ERROR:
        fail(f"cannot write {output} ({summary.message}); nothing was written")
        return EXIT_BAD_INPUT
    print(f"Wrote the relaxed structure to {output}")
    return EXIT_OK if result.converged else EXIT_FAILED
