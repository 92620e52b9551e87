"""``md validate ase``: our velocity Verlet against ASE's, from the same start (md.validate)."""

from __future__ import annotations

import sys

from md.cli._common import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_OK, fail
from md.errors import SimulationError
from md.validate import ARGON_STYLES, format_report, validate_ase


def add_parser(subparsers) -> None:
    """Register ``md validate ase`` on the ``md`` command's subparsers."""
    validate = subparsers.add_parser(
        "validate", help="check the engine against an independent reference"
    )
    references = validate.add_subparsers(
        dest="reference", required=True, parser_class=type(validate)
    )
    ase = references.add_parser(
        "ase",
        help="our velocity Verlet against ASE's VelocityVerlet driven by MDCalculator",
        description=(
            "Build an argon-like LJ liquid in metal units (epsilon 0.0104 eV, sigma 3.40 A, "
            "cutoff 8.5 A), thermalise it with a fixed seed, and run ASE's VelocityVerlet with "
            "MDCalculator and our VelocityVerlet from identical positions and momenta. Prints "
            "the largest position and momentum difference, each run's energy drift and "
            "fluctuation per atom and wall time, and the energy behaviour at a ladder of time "
            "steps. Exit code 0 when the runs agree (ASE's operation order replayed bit for "
            "bit, equal energy behaviour), 1 otherwise."
        ),
    )
    ase.add_argument("--atoms", type=int, default=500, help="number of atoms (default 500)")
    ase.add_argument("--steps", type=int, default=1000, help="steps compared (default 1000)")
    ase.add_argument("--dt", type=float, default=5.0, help="time step in fs (default 5)")
    ase.add_argument(
        "--temperature", type=float, default=100.0, help="start temperature in K (default 100)"
    )
    ase.add_argument("--seed", type=int, default=2024, help="random seed (default 2024)")
    ase.add_argument(
        "--cutoff-mode", choices=("shift", "smooth"), default="shift", help="cutoff treatment"
    )
    ase.add_argument(
        "--potential",
        choices=tuple(ARGON_STYLES),
        default="lj",
        help="pair style, with argon-like parameters (default lj)",
    )
    ase.add_argument(
        "--ladder", default="1,2,5,10", help="time steps of the drift table in fs ('' for none)"
    )
    ase.add_argument(
        "--ladder-time", type=float, default=2000.0, help="fs simulated per ladder run"
    )


def main(args) -> int:
    """Body of ``md validate ase``: run, print the report, return the exit code."""
    try:
        ladder = [float(v) for v in args.ladder.split(",") if v.strip()]
    except ValueError:
        fail(f"--ladder must be a comma-separated list of time steps in fs, got {args.ladder!r}")
        return EXIT_BAD_INPUT
    try:
        report = validate_ase(
            n_atoms=args.atoms,
            n_steps=args.steps,
            dt_fs=args.dt,
            temperature=args.temperature,
            seed=args.seed,
            cutoff_mode=args.cutoff_mode,
            potential=args.potential,
            ladder_dts=ladder,
            ladder_span_fs=args.ladder_time,
        )
    except ValueError as error:
        fail(f"validate ase: {error}")
        return EXIT_BAD_INPUT
    except (SimulationError, FloatingPointError) as error:
        fail(f"validate ase: the dynamics blew up ({error}); is --dt too large?")
        return EXIT_FAILED
    print(format_report(report))
    sys.stdout.flush()
    return EXIT_OK if report.passed else EXIT_FAILED
