"""``md info TRAJ.h5``: describe an H5MD trajectory written by ``md run``."""

from __future__ import annotations

import json
from pathlib import Path

from md.cli._common import EXIT_BAD_INPUT, EXIT_OK, fail
from md.errors import TrajectoryError
from md.trajectory import read_trajectory, trajectory_summary


def add_parser(subparsers) -> None:
    """Add ``md info`` and its options."""
    info = subparsers.add_parser("info", help="describe an H5MD trajectory")
    info.add_argument("trajectory", type=Path, help="H5MD file written by md run")
    info.add_argument("--json", action="store_true", help="print the summary as JSON")


def main(args) -> int:
    """Body of ``md info``; returns the exit code."""
    try:
        traj = read_trajectory(args.trajectory)
    except TrajectoryError as error:
        fail(str(error))
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
    if summary.get("tilt"):
        xy, xz, yz = summary["tilt"]
        print(f"  tilt         xy {xy:.6g}  xz {xz:.6g}  yz {yz:.6g}  (triclinic)")
    print(f"  stored       {', '.join(summary['stored'])}")
    for key in ("bonds", "angles"):
        if summary.get(key):
            counts = ", ".join(f"{count} {name}" for name, count in summary[key].items())
            print(f"  {key:<12} {counts}")
    for key in ("integrator", "potentials", "seed", "skin"):
        if key in traj.parameters:
            print(f"  {key:<12} {json.dumps(traj.parameters[key])}")
    if "mpi_ranks" in traj.parameters:  # written decomposed: the ranks and their grid
        shape = traj.parameters.get("decomposition")
        bricks = f" (bricks {' x '.join(str(p) for p in shape)})" if shape is not None else ""
        print(f"  mpi ranks    {traj.parameters['mpi_ranks']}{bricks}")
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
    conserved = summary.get("conserved_energy")
    if conserved:
        print(
            f"  conserved    {conserved['first']:.8g} -> {conserved['last']:.8g} "
            f"{units.labels['energy']} (relative drift {conserved['relative_drift']:.3e}; "
            "total energy plus the thermostat's and barostat's)"
        )
    return EXIT_OK
