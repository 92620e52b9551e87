"""``md convert TRAJ.h5 OUT.xyz``: write a trajectory in a format viewers and other codes read."""

from __future__ import annotations

import sys
from pathlib import Path

from tqdm import tqdm

from md.cli._common import EXIT_BAD_INPUT, EXIT_OK, fail, writing_whole_file
from md.convert import FORMATS, SINGLE_FRAME, convert, output_format
from md.errors import TrajectoryError
from md.trajectory import TrajectoryReader


def add_parser(subparsers) -> None:
    """Add ``md convert`` and its options."""
    suffixes = ", ".join(f".{suffix}" for suffix in FORMATS)
    convert_parser = subparsers.add_parser(
        "convert",
        help="write an H5MD trajectory as xyz, extxyz, LAMMPS dump or data, DCD, XTC, TRR, "
        "GSD, NetCDF or an ASE trajectory",
        description=(
            "Write frames of an H5MD trajectory to another format, chosen by the output's "
            f"suffix ({suffixes}) or --format. Bonds go to the formats that hold them "
            "(LAMMPS data, GSD). A LAMMPS data file holds one frame: the last one selected."
        ),
    )
    convert_parser.add_argument("trajectory", type=Path, help="H5MD file written by md run")
    convert_parser.add_argument("output", type=Path, help="file to write")
    convert_parser.add_argument(
        "--format", choices=sorted(FORMATS), help="output format (default: from the suffix)"
    )
    convert_parser.add_argument("--start", type=int, help="first frame (negative: from the end)")
    convert_parser.add_argument("--stop", type=int, help="stop before this frame")
    convert_parser.add_argument("--step", type=int, help="take every STEP-th frame")
    convert_parser.add_argument(
        "--unwrap",
        action="store_true",
        help="write continuous positions instead of positions wrapped into the box",
    )
    convert_parser.add_argument(
        "--overwrite", action="store_true", help="replace OUTPUT if it exists"
    )
    convert_parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def main(args) -> int:
    """Body of ``md convert``; returns the exit code (130/143 after SIGINT/SIGTERM)."""
    return writing_whole_file("convert", args.output, lambda: _convert(args))


def _convert(args) -> int:
    try:
        kind = output_format(args.output, args.format)
        with TrajectoryReader(args.trajectory) as reader:
            frames = reader.select(args.start, args.stop, args.step)
        total = 1 if kind in SINGLE_FRAME else len(frames)
        bar = tqdm(
            total=total,
            unit="frame",
            desc=f"md convert -> {args.output.name}",
            disable=args.no_progress or not sys.stderr.isatty(),
            file=sys.stderr,
        )
        with bar:
            count = convert(
                args.trajectory,
                args.output,
                format=args.format,
                start=args.start,
                stop=args.stop,
                step=args.step,
                unwrap=args.unwrap,
                overwrite=args.overwrite,
                progress=lambda done: bar.update(done - bar.n),
            )
    except (TrajectoryError, ValueError, IndexError, FileExistsError, OSError) as error:
        fail(str(error))
        return EXIT_BAD_INPUT
    note = " (the last selected: LAMMPS data holds one frame)" if kind in SINGLE_FRAME else ""
    print(f"Wrote {count} frame{'s' if count != 1 else ''}{note} to {args.output}")
    return EXIT_OK
