"""``md render TRAJ.h5``: draw one frame (atoms by type, bonds, box) into a PNG file."""

from __future__ import annotations

from pathlib import Path

from md.cli._common import EXIT_BAD_INPUT, EXIT_OK, fail, writing_whole_file
from md.errors import TrajectoryError
from md.render import ENGINES, render


def add_parser(subparsers) -> None:
    """Add ``md render`` and its options."""
    parser = subparsers.add_parser(
        "render",
        help="draw a frame of a trajectory into a PNG picture",
        description=(
            "Draw one frame of an H5MD trajectory: atoms coloured by type, bonds as lines, "
            "the box edges. matplotlib by default; --engine povray uses ASE's POV-Ray writer "
            "and the povray program."
        ),
    )
    parser.add_argument("trajectory", type=Path, help="H5MD file written by md run")
    parser.add_argument(
        "--frame", type=int, default=-1, help="frame to draw (negative: from the end; default -1)"
    )
    parser.add_argument(
        "-o", "--output", type=Path, default=Path("snapshot.png"), help="PNG file (snapshot.png)"
    )
    parser.add_argument("--engine", choices=ENGINES, default="matplotlib", help="renderer")
    parser.add_argument("--size", type=int, default=800, help="picture edge in pixels (800)")
    parser.add_argument("--overwrite", action="store_true", help="replace OUTPUT if it exists")


def main(args) -> int:
    """Body of ``md render``; returns the exit code (130/143 after SIGINT/SIGTERM)."""
    return writing_whole_file("render", args.output, lambda: _render(args))


def _render(args) -> int:
    try:
        path = render(
            args.trajectory,
            args.output,
            frame=args.frame,
            engine=args.engine,
            size=args.size,
            overwrite=args.overwrite,
        )
    except (TrajectoryError, ValueError, IndexError, FileExistsError, OSError) as error:
        fail(str(error))
        return EXIT_BAD_INPUT
    print(f"Wrote frame {args.frame} of {args.trajectory} to {path}")
    return EXIT_OK
