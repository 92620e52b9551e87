"""``md minimize CONFIG.toml``: relax the config's starting structure with FIRE 2.0.

Builds the system as ``md run`` would, minimises it (``[minimize]`` of the
config, or the options here), prints progress and the final max force, and
writes the relaxed structure as a one-frame H5MD file (with its bonds), which
``[system] structure`` can start a run from.
"""

from __future__ import annotations

from pathlib import Path

from md.cli._common import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_OK, fail
from md.config import MinimizeConfig, load_config
from md.errors import ConfigError, NonFiniteError, TrajectoryError
from md.minimize import minimize
from md.run import build_components, run_topology
from md.simulation import Simulation
from md.trajectory import H5MDWriter


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
    parser.add_argument("--overwrite", action="store_true", help="replace OUTPUT if it exists")
    parser.add_argument("--quiet", "-q", action="store_true", help="no progress lines")


def main(args) -> int:
    """Body of ``md minimize``; returns the exit code."""
    try:
        config = load_config(args.config)
        stage = config.minimize or MinimizeConfig()
        fmax = stage.fmax if args.fmax is None else args.fmax
        max_steps = stage.max_steps if args.max_steps is None else args.max_steps
        max_force = stage.max_force if args.max_force is None else args.max_force
        if not fmax > 0:
            raise ConfigError(f"--fmax must be positive, got {fmax}")
        if isinstance(max_steps, bool) or max_steps < 1:
            raise ConfigError(f"--max-steps must be >= 1, got {max_steps}")
        if max_force is not None and not max_force > 0:
            raise ConfigError(f"--max-force must be positive, got {max_force}")
        output = args.output or config.output.path.with_name(f"{config.output.path.stem}_min.h5")
        if output.exists() and not args.overwrite:
            raise ConfigError(f"{output} already exists; pass --overwrite or choose --output")
        state, potentials, integrator = build_components(config)
        sim = Simulation(state, potentials, integrator, skin=config.run.skin, units=config.units)
    except (ConfigError, ValueError) as error:
        fail(str(error))
        return EXIT_BAD_INPUT
    units = config.units
    force_unit = f"{units.labels['energy']}/{units.labels['length']}"
    print(
        f"md minimize: {state.n_atoms} atoms, FIRE 2.0 to max force <= {fmax:g} {force_unit}, "
        f"at most {max_steps} steps" + (f", forces capped at {max_force:g}" if max_force else "")
    )

    def report(step, energy, largest):
        if not args.quiet:
            print(f"  step {step:>7}  energy {energy:.10g}  max force {largest:.4g}", flush=True)

    try:
        result = minimize(state, sim.forcefield, fmax, max_steps, max_force=max_force,
                          max_step=stage.max_step, callback=report,
                          report_every=stage.report_every)  # fmt: skip
    except NonFiniteError as error:
        fail(f"minimisation failed: {error}")
        return EXIT_FAILED
    print(f"md minimize: {result.describe()}")
    try:
        with H5MDWriter(output, state, units=units, overwrite=args.overwrite,
                        topology=run_topology(sim),
                        parameters={"config": config.text, "minimize": result.describe()},
                        ) as writer:  # fmt: skip
            writer.write(state, thermo=sim.thermo())
    except (FileExistsError, TrajectoryError, OSError) as error:
        fail(str(error))
        return EXIT_BAD_INPUT
    print(f"Wrote the relaxed structure to {output}")
    return EXIT_OK if result.converged else EXIT_FAILED
