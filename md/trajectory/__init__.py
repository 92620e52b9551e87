"""Trajectories in HDF5 following the H5MD 1.1 layout (h5py), readable by MDAnalysis.

Layout written (the intersection of the H5MD specification and what
MDAnalysis's H5MD reader needs)::

    h5md/                      version [1, 1]; author/ and creator/ groups
    particles/trajectory/
        box/                   dimension = 3, boundary = periodic|none per axis
            edges/{step,time,value (F, 3)}  edge lengths, or (F, 3, 3) for a
                               triclinic cell: the cell vectors as rows
                               (H5MD 1.1; MDAnalysis reads both)
        position/{step,time,value (F, N, 3)}   wrapped into the box
        image/{step,time,value (F, N, 3)}      int32 periodic images
        velocity/{step,time,value}             optional
        force/{step,time,value}                optional
        species (N,) int32, mass (N,) float64  time-independent
    connectivity/              bonds and angles, when the run has any (H5MD 1.1's
                               tuple lists):
        <bond type> (B, 2) int32 atom index pairs, one dataset per bond type
                               ("spring", "fene", "constraint", ...), each with
                               attribute particles_group -> /particles/trajectory;
                               attribute bond_types (JSON) gives the type order
        <angle type> (A, 3) int32 atom index triples (i, j, k), j the vertex,
                               one dataset per angle type ("angle_harmonic",
                               "angle_cosine", ...), likewise; attribute
                               angle_types (JSON) gives their order. MDAnalysis's
                               H5MD reader reads no connectivity:
                               :func:`open_trajectory` adds bonds and angles.
    observables/
        potential_energy, kinetic_energy, total_energy, temperature,
        pressure, volume, density, pxx pyy pzz pxy pxz pyz (the pressure
        tensor): {step,time,value (F,)}; files written before volume,
        density and the tensor were added lack them, and appending to
        such a file keeps its set
    parameters/                attributes describing the run (units, config,
                               potentials, integrator, seed, version, ...)

``step`` and ``time`` are stored once, under ``position``, and hard-linked
into every other time-dependent element, so all elements share one frame
axis. Datasets are resizable and chunked one frame at a time, and the file is
flushed after every frame, so a killed run leaves a readable file.
Positions are continuous inside the engine; the file holds them wrapped into
the box together with their images, so ``position + image * edges`` unwraps
exactly (to round-off), or ``position + image @ edges`` for a (3, 3) cell.

Units: metal runs carry H5MD unit strings MDAnalysis understands
(``Angstrom``, ``ps``, ``Angstrom ps-1``, ``kJ mol-1 Angstrom-1``); forces
and times are converted at this edge. Reduced LJ runs carry no unit
attributes, so MDAnalysis must open them with ``convert_units=False``, which
:func:`open_trajectory` does.

Modules: :mod:`~md.trajectory.writer` (:class:`H5MDWriter`),
:mod:`~md.trajectory.readers` (:func:`read_trajectory`, :class:`TrajectoryReader`,
:func:`read_topology`, :func:`read_frame_steps`, :func:`verify_frames`,
:func:`open_trajectory`), :mod:`~md.trajectory.retries` (opening a file a run may be
writing) and ``_layout`` (what the writer and the readers share). The public names are
importable from ``md.trajectory``.
"""

from md.errors import (
    TrajectoryError,  # re-exported: md.trajectory offered it before it was a package
)
from md.trajectory._layout import (
    H5MD_VERSION,
    OBSERVABLES,
    attr_text,
    maybe_json,
    split_edges,
    unwrap_frames,
)
from md.trajectory.readers import (
    Frame,
    Trajectory,
    TrajectoryReader,
    open_trajectory,
    read_frame_steps,
    read_topology,
    read_trajectory,
    trajectory_summary,
    verify_frames,
)
from md.trajectory.retries import open_h5md, retry_transient, while_written
from md.trajectory.writer import H5MDWriter

__all__ = [
    "H5MD_VERSION",
    "OBSERVABLES",
    "Frame",
    "H5MDWriter",
    "Trajectory",
    "TrajectoryError",
    "TrajectoryReader",
    "attr_text",
    "maybe_json",
    "open_h5md",
    "open_trajectory",
    "read_frame_steps",
    "read_topology",
    "read_trajectory",
    "retry_transient",
    "split_edges",
    "trajectory_summary",
    "unwrap_frames",
    "verify_frames",
    "while_written",
]
