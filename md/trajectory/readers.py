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
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import resource
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np
from numpy.typing import NDArray

from md._checks import count
from md._files import disk_full, write_bytes_atomic
from md._version import __version__
from md.box import cell_matrix, wrap
from md.errors import TrajectoryError
from md.state import State
from md.topology import Topology
from md.units import UnitSystem, get_units

H5MD_VERSION = (1, 1)
OBSERVABLES = (
    "potential_energy", "kinetic_energy", "total_energy", "temperature", "pressure",
    "volume", "density", "pxx", "pyy", "pzz", "pxy", "pxz", "pyz", "conserved_energy",
)  # fmt: skip
_OBSERVABLE_UNITS = {
    "potential_energy": "energy",
    "kinetic_energy": "energy",
    "total_energy": "energy",
    "conserved_energy": "energy",
    "temperature": "temperature",
    "pressure": "pressure",
    "volume": "volume",
    "density": "density",
    **{name: "pressure" for name in ("pxx", "pyy", "pzz", "pxy", "pxz", "pyz")},
}


#: HDF5 raw-chunk cache per dataset while writing [bytes]. A frame chunk is
#: written whole and flushed at once, so it needs no cache; 64 KiB holds the
#: open chunk of each per-frame scalar series. (h5py's default, 1 MiB per
#: dataset, kept ~30 MiB of already-written chunks resident on long runs.)
_CHUNK_CACHE = 1 << 16
#: Room kept free beyond a frame's own bytes for HDF5's growing chunk index [bytes].
_METADATA_MARGIN = 16 << 10


class H5MDWriter:
    """Write frames of a simulation to an H5MD file; an observer and a context manager.

    Parameters
    ----------
    path : str or Path
        Output file. An existing file is only replaced with ``overwrite=True``.
    state : State
        The system, for the atom count, masses, types and periodicity.
    units : {"lj", "metal"} or UnitSystem
        Unit system of the run; decides the unit attributes and conversions.
    velocities, forces : bool
        Also store velocities and forces on every frame.
    parameters : dict, optional
        Run description stored as attributes of ``/parameters`` (strings,
        numbers; dicts and lists are stored as JSON strings).
    overwrite : bool
        Replace an existing file.
    append : bool
        Continue an existing file written by this class (a resumed run): its
        layout decides what is stored, and ``velocities``, ``forces`` and
        ``parameters`` are ignored.
    keep_frames : int, optional
        With ``append``, keep only the first ``keep_frames`` frames and
        discard the rest (frames written after the checkpoint being resumed).
    topology : Topology, optional
        Bonds to store in ``/connectivity`` (see
        :meth:`md.forcefield.ForceField.topology`), so viewers and
        :func:`open_trajectory` see them.
    triclinic : bool, optional
        Store the box as a (3, 3) cell matrix per frame. Default: when
        ``state`` is tilted. A run whose cell may start to tilt (a barostat
        with triclinic coupling) passes True; writing a tilted frame into a
        file of edge lengths raises ValueError.
    conserved : bool
        Also store ``conserved_energy`` (the thermostat's and barostat's
        conserved quantity, from ``sim.thermo()``), so that analyses measure
        the drift of a thermostatted run on it rather than on the total energy.
    in_memory : bool
        Build the whole file in memory and write it to ``path`` only when the
        writer is closed, at once (temporary file, rename): the path then holds
        the complete file or nothing, also on a full disk. For small files
        written in one go, such as a minimised structure; leaving the ``with``
        block by an exception writes nothing.

    Raises
    ------
    FileExistsError
        If ``path`` exists and neither ``overwrite`` nor ``append`` is given.
    OSError
        If the file cannot be written; a full disk says "disk full", and the
        path is then left as it was (a new file is not created).
    ValueError
        If ``path`` exists and is not a regular file (a FIFO, a device node);
        a symbolic link is written through into its target.
    TrajectoryError
        With ``append``, if the file is not one of ours, holds another atom
        count, or fewer than ``keep_frames`` frames.

    Examples
    --------
    >>> # with H5MDWriter("run.h5", sim.state, units="lj") as writer:
    >>> #     sim.attach(writer, interval=100)
    >>> #     sim.run(10_000)
    """

    def __init__(
        self,
        path,
        state: State,
        units: str | UnitSystem = "lj",
        velocities: bool = False,
        forces: bool = False,
        parameters: dict | None = None,
        overwrite: bool = False,
        author: str | None = None,
        append: bool = False,
        keep_frames: int | None = None,
        topology: Topology | None = None,
        triclinic: bool | None = None,
        conserved: bool = False,
        in_memory: bool = False,
    ) -> None:
        self.path = Path(path)
        self.store_conserved = bool(conserved)
        self.triclinic = not state.is_orthorhombic if triclinic is None else bool(triclinic)
        if topology is not None:
            topology.check(state.n_atoms, where="topology")
        self.units = get_units(units)
        self.n_atoms = state.n_atoms
        self.store_velocities = bool(velocities)
        self.store_forces = bool(forces)
        self.n_frames = 0
        self._last_step: int | None = None
        self._file = None
        self._overwrite = bool(overwrite)
        self._in_memory = bool(in_memory) and not append
        if append:
            self._open_existing(state, keep_frames)
            return
        if self.path.exists() and not overwrite:
            raise FileExistsError(
                f"{self.path} already exists; choose another output path or pass --overwrite"
            )
        # The layout is made in memory and written by Python into a temporary file that
        # is renamed into place: HDF5 never meets a full disk while creating it (after a
        # failed write HDF5 can no longer close the file, and the process crashes when
        # it does), and the path never holds a half-made file.
        self._file = _memory_file()
        try:
            self._create_layout(state, parameters or {}, author)
            if topology is not None and (topology.n_bonds or topology.n_angles):
                _write_topology(self._file, topology)
            if self._in_memory:
                return
            self._file.flush()  # the image holds what has been flushed
            image = self._file.id.get_file_image()
        except BaseException:
            self._drop_memory_file()
            raise
        self._drop_memory_file()
        try:
            # Without overwrite the rename is exclusive: a file that appeared meanwhile wins.
            write_bytes_atomic(self.path, image, exclusive=not overwrite)
        except FileExistsError:
            raise FileExistsError(f"{self.path} appeared while the run was starting") from None
        # locking=False: readers (md info, md analyze, MDAnalysis) may open the file
        # while the run writes it; our own claim (md._files) keeps other writers out.
        self._file = h5py.File(self.path, "r+", rdcc_nbytes=_CHUNK_CACHE, locking=False)
        self._bind()

    def _drop_memory_file(self) -> None:
        """Close the in-memory file and forget its datasets (nothing reaches the disk)."""
        self._values, self._step, self._time = {}, None, None
        if self._file is not None:
            self._file.close()
        self._file = None

    @property
    def last_step(self) -> int | None:
        """Step of the last frame written (or kept on append), None before the first."""
        return self._last_step

    def _bind(self) -> None:
        """Find the datasets written to in the open file."""
        f = self._file
        group = f["particles/trajectory"]
        self._step = group["position/step"]
        self._time = group["position/time"]
        self._values = {"position": group["position/value"], "image": group["image/value"]}
        self.store_velocities = "velocity" in group
        self.store_forces = "force" in group
        if self.store_velocities:
            self._values["velocity"] = group["velocity/value"]
        if self.store_forces:
            self._values["force"] = group["force/value"]
        self._values["edges"] = group["box/edges/value"]
        self.triclinic = self._values["edges"].ndim == 3
        for name in OBSERVABLES:
            if name in f["observables"]:  # older files hold fewer observables
                self._values[name] = f["observables"][name]["value"]
        self.units = get_units(attr_text(f["parameters"].attrs["units"]))

    def _open_existing(self, state: State, keep_frames: int | None) -> None:
        """Open a file of ours for appending, dropping frames beyond ``keep_frames``."""
        path = self.path
        open_h5md(path).close()  # TrajectoryError for missing, non-HDF5 or foreign files
        try:
            self._file = h5py.File(path, "r+", rdcc_nbytes=_CHUNK_CACHE, locking=False)
        except OSError as error:
            raise TrajectoryError(f"{path}: cannot open for appending ({error})") from None
        try:
            self._bind()
            n_atoms = self._values["position"].shape[1]
            if n_atoms != state.n_atoms:
                raise TrajectoryError(f"{path}: holds {n_atoms} atoms, the run has {state.n_atoms}")
            n_frames = len(self._step)
            if any(len(v) < n_frames for v in self._values.values()):
                n_frames = min(len(v) for v in self._values.values())  # an interrupted write
            keep = n_frames if keep_frames is None else int(keep_frames)
            if not 0 <= keep <= n_frames:
                raise TrajectoryError(
                    f"{path}: holds {n_frames} complete frames, fewer than the {keep} the "
                    "checkpoint expects"
                )
            self._step.resize((keep,))
            self._time.resize((keep,))
            for dataset in self._values.values():
                dataset.resize(keep, axis=0)
            self.n_frames = keep
            self._last_step = int(self._step[keep - 1]) if keep else None
            self._file.flush()
        except (KeyError, ValueError, TypeError, OSError, RuntimeError) as error:
            failure = (
                error if isinstance(error, TrajectoryError)
                else TrajectoryError(f"{path}: not a trajectory written by leapmd ({error})")
            )  # fmt: skip
        else:
            return
        self._abandon()  # outside the except block: no traceback holds HDF5 objects
        raise failure

    # ------------------------------------------------------------------ layout
    def _create_layout(self, state: State, parameters: dict, author: str | None) -> None:

        f = self._file
        h5md = f.create_group("h5md")
        h5md.attrs["version"] = np.array(H5MD_VERSION, dtype=np.int32)
        h5md.create_group("author").attrs["name"] = author or os.environ.get("USER", "unknown")
        creator = h5md.create_group("creator")
        creator.attrs["name"] = "leapmd"
        creator.attrs["version"] = __version__

        group = f.create_group("particles/trajectory")
        n = self.n_atoms
        position = self._element(group, "position", (n, 3), np.float64, "length")
        self._step = position.create_dataset(
            "step", shape=(0,), maxshape=(None,), dtype=np.int64, chunks=(1024,), fletcher32=True
        )
        self._time = position.create_dataset(
            "time", shape=(0,), maxshape=(None,), dtype=np.float64, chunks=(1024,), fletcher32=True
        )
        self._set_unit(self._time, "time")
        self._values = {"position": position["value"]}
        self._values["image"] = self._element(group, "image", (n, 3), np.int32, None)["value"]
        if self.store_velocities:
            self._values["velocity"] = self._element(
                group, "velocity", (n, 3), np.float64, "velocity"
            )["value"]
        if self.store_forces:
            self._values["force"] = self._element(group, "force", (n, 3), np.float64, "force")[
                "value"
            ]
        box = group.create_group("box")
        box.attrs["dimension"] = 3
        box.attrs["boundary"] = np.array(
            ["periodic" if p else "none" for p in state.pbc], dtype=h5py.string_dtype()
        )
        shape = (3, 3) if self.triclinic else (3,)
        self._values["edges"] = self._element(box, "edges", shape, np.float64, "length")["value"]
        group.create_dataset("species", data=state.types.astype(np.int32))
        mass = group.create_dataset("mass", data=state.masses)
        self._set_unit(mass, "mass")

        observables = f.create_group("observables")
        for name in OBSERVABLES:
            if name == "conserved_energy" and not self.store_conserved:
                continue
            element = self._element(observables, name, (), np.float64, _OBSERVABLE_UNITS[name])
            self._values[name] = element["value"]

        params = f.create_group("parameters")
        params.attrs["units"] = self.units.name
        params.attrs["type_names"] = json.dumps(list(state.type_names))
        params.attrs["leapmd_version"] = __version__
        for key, value in parameters.items():
            params.attrs[key] = value if isinstance(value, str | int | float) else json.dumps(value)
        f.flush()

    def _element(self, parent, name, frame_shape, dtype, quantity):
        element = parent.create_group(name)
        if name != "position":
            element["step"] = self._step
            element["time"] = self._time
        value = element.create_dataset(
            "value",
            shape=(0, *frame_shape),
            maxshape=(None, *frame_shape),
            dtype=dtype,
            chunks=(1, *frame_shape) if frame_shape else (1024,),
            fletcher32=True,  # a checksum per chunk: corrupted frames are detected on reading
        )
        if quantity is not None:
            self._set_unit(value, quantity)
        return element

    def _set_unit(self, dataset, quantity: str) -> None:
        if quantity in self.units.h5md:
            dataset.attrs["unit"] = self.units.h5md[quantity][0]

    def _factor(self, quantity: str) -> float:
        return self.units.h5md[quantity][1] if quantity in self.units.h5md else 1.0

    # ------------------------------------------------------------------ writing
    def __call__(self, sim) -> None:
        """Observer entry point: write the simulation's current frame."""
        forces = sim.forcefield.compute(sim.state).forces if self.store_forces else None
        self.write(sim.state, thermo=sim.thermo(), forces=forces)

    def write(
        self, state: State, thermo: dict | None = None, forces: NDArray | None = None
    ) -> None:
        """Append one frame (positions, images, box, optional velocities/forces, observables)."""
        if self._file is None or not self._file.id.valid:
            raise ValueError(f"{self.path} is closed")
        if state.n_atoms != self.n_atoms:
            raise ValueError(
                f"cannot write {state.n_atoms} atoms to {self.path}, which holds {self.n_atoms}"
            )
        if self._last_step is not None and state.step <= self._last_step:
            raise ValueError(
                f"frame at step {state.step} would not follow the last frame (step "
                f"{self._last_step}) in {self.path}"
            )
        if self.store_forces and forces is None:
            raise ValueError("this writer stores forces: pass forces=")
        if not self.triclinic and not state.is_orthorhombic:
            raise ValueError(
                f"{self.path} stores orthorhombic boxes, but the cell at step {state.step} is "
                f"tilted (xy, xz, yz = {state.tilt.tolist()}); create the writer with "
                "triclinic=True"
            )
        frame = self.n_frames
        if not self._in_memory:
            self._check_space(frame)
        try:
            self._append(state, frame, thermo, forces)
        except (RuntimeError, OSError) as error:  # HDF5 raises either for a failed write
            # Let go of the file while the traceback still holds its datasets: they are
            # closed with it, after its descriptor points elsewhere (see _abandon).
            self._abandon()
            raise _write_failure(error, self.path, frame) from None
        self.n_frames = frame + 1
        self._last_step = state.step

    def _append(self, state: State, frame: int, thermo: dict | None, forces) -> None:
        size = frame + 1
        # Two commits: every other dataset grows and is flushed first, the positions last,
        # so a run killed in between leaves a file whose position count (what MDAnalysis
        # reads) is the count of complete frames (what our readers take).
        self._step.resize((size,))
        self._time.resize((size,))
        for name, dataset in self._values.items():
            if name != "position":
                dataset.resize(size, axis=0)
        self._step[frame] = state.step
        self._time[frame] = state.time * self._factor("time")
        wrapped, images = wrap(state.positions, state.box, state.pbc, state.tilt)
        self._values["image"][frame] = images
        edges = state.cell if self.triclinic else state.box
        self._values["edges"][frame] = edges * self._factor("length")
        if self.store_velocities:
            self._values["velocity"][frame] = state.velocities * self._factor("velocity")
        if self.store_forces:
            self._values["force"][frame] = np.asarray(forces) * self._factor("force")
        for name in OBSERVABLES:
            if name in self._values:
                value = np.nan if thermo is None else thermo.get(name, np.nan)
                self._values[name][frame] = value * self._factor(_OBSERVABLE_UNITS[name])
        self._file.flush()
        self._values["position"].resize(size, axis=0)
        self._values["position"][frame] = wrapped * self._factor("length")
        self._file.flush()

    def _abandon(self) -> None:
        """Let go of a file that HDF5 failed to write (a full disk), without crashing.

        After a failed write HDF5 holds metadata it cannot write back, and
        closing the file, freeing one of its datasets or HDF5's own clean-up
        at exit then crashes the process (segmentation fault). So the file's
        descriptor is first pointed at ``/dev/null``: what HDF5 still writes
        goes nowhere, and the file on disk keeps what the last successful
        flush wrote. Then the datasets are let go and the file is closed.
        """
        f = self._file
        if f is not None and f.id.valid:
            if not self._in_memory:
                with contextlib.suppress(OSError, RuntimeError, TypeError, ValueError):
                    descriptor = f.id.get_vfd_handle()
                    null = os.open(os.devnull, os.O_RDWR)
                    try:
                        os.dup2(null, int(descriptor))
                    finally:
                        os.close(null)
            with contextlib.suppress(RuntimeError, OSError):
                f.close()  # closes every dataset of the file too
        self._file = None
        self._values, self._step, self._time = {}, None, None

    def _check_space(self, frame: int) -> None:
        """Raise OSError(ENOSPC) if the disk or the file-size limit may not hold one more frame.

        A write that HDF5 starts and the disk cannot take leaves a file whose
        recorded end lies past its real end, which HDF5 then refuses to open:
        so the room is checked first, and the run stops with every frame
        written so far readable. (Space taken by another process between this
        check and the write is not covered.)
        """
        datasets = [self._step, self._time, *self._values.values()]
        need = _METADATA_MARGIN
        for dataset in datasets:
            per_frame = dataset.dtype.itemsize * int(np.prod(dataset.shape[1:], dtype=np.int64))
            chunk = dataset.chunks[0] if dataset.chunks else 1
            # A frame that opens a new chunk allocates all of it.
            need += per_frame * chunk if frame % chunk == 0 else per_frame
        size = os.fstat(self._file.id.get_vfd_handle()).st_size
        limit = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
        if limit != resource.RLIM_INFINITY and size + need > limit:
            raise OSError(
                errno.EFBIG,
                f"{self.path} would exceed the file-size limit ({limit} bytes) with frame "
                f"{frame + 1}; the {frame} frames written are intact",
            )
        stats = os.statvfs(os.path.dirname(os.path.abspath(self.path)))
        free = stats.f_bavail * stats.f_frsize
        if free < need:
            raise OSError(
                errno.ENOSPC,
                f"disk full: {free} bytes free for {self.path}, frame {frame + 1} needs about "
                f"{need}; the {frame} frames written are intact",
            )

    def close(self) -> None:
        """Close the file; after a failed write (disk full) the last flushed frames remain.

        An in-memory writer (``in_memory=True``) writes its file now, whole.

        Raises
        ------
        OSError
            An in-memory writer's file could not be written ("disk full"); the
            path is left as it was.
        """
        if self._file is None or not self._file.id.valid:
            return
        if self._in_memory:
            try:
                self._file.flush()
                image = self._file.id.get_file_image()
            finally:
                self._drop_memory_file()
            write_bytes_atomic(self.path, image, exclusive=not self._overwrite)
            return
        try:
            self._file.close()
        except (RuntimeError, OSError):
            # HDF5 could not write its metadata back: what the last flush wrote stays.
            self._abandon()

    def __enter__(self) -> H5MDWriter:
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if self._in_memory and exc_type is not None:
            self._drop_memory_file()  # an in-memory file is written whole or not at all
        else:
            self.close()


def _memory_file() -> h5py.File:
    """A new HDF5 file that lives in memory only (HDF5's core driver, no backing store)."""
    return h5py.File(f"leapmd-{uuid.uuid4().hex}.h5", "w", driver="core", backing_store=False)


def _write_failure(error: BaseException, path: Path, frame: int) -> OSError:
    """A fresh OSError for a frame HDF5 could not write (no traceback of HDF5 objects)."""
    kept = f"the {frame} frames written before are kept"
    if disk_full(error):
        return OSError(errno.ENOSPC, f"disk full: cannot write frame {frame + 1} to {path}; {kept}")
    return OSError(errno.EIO, f"cannot write frame {frame + 1} to {path} ({error}); {kept}")


def _write_topology(f: h5py.File, topology: Topology) -> None:
    connectivity = f.create_group("connectivity")
    connectivity.attrs["bond_types"] = json.dumps(list(topology.bond_type_names))
    if topology.n_angles:
        connectivity.attrs["angle_types"] = json.dumps(list(topology.angle_type_names))
    particles = f["particles/trajectory"].ref
    members = [*topology.by_type().items(), *topology.angles_by_type().items()]
    for name, listed in members:
        dataset = connectivity.create_dataset(name, data=listed.astype(np.int32))
        dataset.attrs["particles_group"] = particles


def _read_topology(f: h5py.File) -> Topology:
    """The bonds and angles of ``/connectivity``, checked against the atom count
    (TrajectoryError naming the file, the type's dataset and the bond or angle)."""
    if "connectivity" not in f:
        return Topology.empty()
    group = f["connectivity"]
    n_atoms = len(f["particles/trajectory/mass"])
    names = []
    for key in ("bond_types", "angle_types"):
        order = maybe_json(group.attrs.get(key, "[]"))
        if isinstance(order, list):
            names += [name for name in order if name in group and name not in names]
    names += sorted(name for name in group if name not in names)
    groups = {2: {}, 3: {}}  # tuple size -> {type name: members}: bonds, angles
    for name in names:
        listed = group[name][()]
        size = listed.shape[1] if listed.ndim == 2 else 0
        if size in groups:  # other tuple lists (dihedrals, ...) are skipped
            _check_members(f, name, listed, n_atoms)
            groups[size][name] = listed.astype(np.int64)
    return Topology.from_groups(groups[2], groups[3])


def _check_members(f: h5py.File, name: str, listed, n_atoms: int) -> None:
    """TrajectoryError naming the file, dataset and entry of a bond or angle that names an
    atom outside the file's atoms, or one atom twice."""
    kind = "bond" if listed.shape[1] == 2 else "angle"
    outside = ((listed < 0) | (listed >= n_atoms)).any(axis=1)
    ordered = np.sort(listed, axis=1)
    repeated = (ordered[:, 1:] == ordered[:, :-1]).any(axis=1)
    bad = np.flatnonzero(outside | repeated)
    if bad.size:
        first = int(bad[0])
        what = (f"names an atom outside 0..{n_atoms - 1}" if outside[first]
                else "names one atom twice")  # fmt: skip
        raise TrajectoryError(
            f"{f.filename}: /connectivity/{name}: {kind} {first} "
            f"{tuple(listed[first].tolist())} {what} ({bad.size} such {kind}(s)); the file's "
            "connectivity is damaged"
        )


def read_topology(path) -> Topology:
    """Return the bonds stored in a trajectory's ``/connectivity`` (empty if none)."""
    path = Path(path)
    with open_h5md(path) as f:
        try:
            return _read_topology(f)
        except TrajectoryError:
            raise
        except (KeyError, ValueError, TypeError, OSError) as error:
            raise TrajectoryError(f"{path}: unreadable connectivity ({error})") from None


# ---------------------------------------------------------------------- reading
@dataclass
class Trajectory:
    """A trajectory read back into engine units (see :func:`read_trajectory`).

    Positions are unwrapped (``position + image @ cell``). ``boxes`` holds
    each frame's edge lengths and ``tilts`` its tilt factors (xy, xz, yz),
    zero for orthorhombic boxes.
    """

    path: Path
    units: UnitSystem
    steps: NDArray[np.int64]
    times: NDArray[np.float64]
    positions: NDArray[np.float64]
    boxes: NDArray[np.float64]
    pbc: NDArray[np.bool_]
    masses: NDArray[np.float64]
    types: NDArray[np.int32]
    type_names: tuple[str, ...]
    velocities: NDArray[np.float64] | None = None
    forces: NDArray[np.float64] | None = None
    observables: dict[str, NDArray[np.float64]] = field(default_factory=dict)
    parameters: dict = field(default_factory=dict)
    topology: Topology = field(default_factory=Topology.empty)
    tilts: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        if self.tilts is None:
            self.tilts = np.zeros_like(self.boxes)

    @property
    def n_frames(self) -> int:
        return len(self.steps)

    def cells(self) -> NDArray[np.float64]:
        """(F, 3, 3) cell matrices, rows a, b, c."""
        return np.array([cell_matrix(b, t) for b, t in zip(self.boxes, self.tilts, strict=True)])

    @property
    def n_atoms(self) -> int:
        return len(self.masses)

    def state(self, frame: int = -1) -> State:
        """Return frame ``frame`` as a State (zero velocities if none were stored)."""
        if not -self.n_frames <= frame < self.n_frames:
            raise IndexError(
                f"{self.path} has {self.n_frames} frames; frame {frame} is out of range"
            )
        return State(
            positions=self.positions[frame],
            velocities=None if self.velocities is None else self.velocities[frame],
            masses=self.masses,
            box=self.boxes[frame],
            pbc=self.pbc,
            types=self.types,
            type_names=self.type_names,
            step=int(self.steps[frame]),
            time=float(self.times[frame]),
            tilt=self.tilts[frame],
        )


def read_trajectory(path) -> Trajectory:
    """Read an H5MD file written by :class:`H5MDWriter` into engine units.

    A file that a run is writing is read as of a moment between two frames.

    Raises
    ------
    TrajectoryError
        If the file is missing, not HDF5, or lacks what the layout requires.
    """
    path = Path(path)
    return while_written(path, lambda: _read_trajectory(path))


def _read_trajectory(path: Path) -> Trajectory:
    with open_h5md(path) as f:
        try:
            # Complete frames only: a run killed inside a write may have grown some
            # per-frame datasets by one frame and not the others.
            n_frames = _complete_frames(f)
        except (KeyError, ValueError, TypeError, OSError, RuntimeError) as error:
            raise TrajectoryError(f"{path}: not a trajectory written by leapmd ({error})") from None
        try:
            return retry_transient(lambda: _read_frames(f, path, n_frames), attempts=5)
        except OSError as error:
            # A run writing the file may have grown its datasets for a frame whose data
            # has not reached the disk yet ("addr overflow"): read the frames before it.
            if n_frames == 0 or _is_checksum_error(error):
                raise _as_trajectory_error(path, error) from None
        try:
            return _read_frames(f, path, n_frames - 1)
        except (KeyError, ValueError, TypeError, OSError, RuntimeError) as error:
            raise _as_trajectory_error(path, error) from None


def _as_trajectory_error(path: Path, error: BaseException) -> TrajectoryError:
    if isinstance(error, TrajectoryError):
        return error
    if _is_checksum_error(error):
        try:
            verify_frames(path)  # raises naming the frame
        except TrajectoryError as named:
            return named
    return TrajectoryError(f"{path}: not a trajectory written by leapmd ({error})")


def _read_frames(f: h5py.File, path: Path, n_frames: int) -> Trajectory:
    """The first ``n_frames`` frames of an open file as a Trajectory."""
    try:
        group = f["particles/trajectory"]
        units = get_units(str(f["parameters"].attrs.get("units", "lj")))
        factors = {q: units.h5md[q][1] for q in units.h5md}

        def scale(quantity: str) -> float:
            return 1.0 / factors.get(quantity, 1.0)

        steps = group["position/step"][:n_frames]
        raw = group["position/value"][:n_frames] * scale("length")
        boxes, tilts = split_edges(group["box/edges/value"][:n_frames] * scale("length"))
        images = group["image/value"][:n_frames] if "image" in group else np.zeros_like(raw)
        positions = unwrap_frames(raw, images, boxes, tilts)
        boundary = [attr_text(b) for b in group["box"].attrs["boundary"]]
        velocities = forces = None
        if "velocity" in group:
            velocities = group["velocity/value"][:n_frames] * scale("velocity")
        if "force" in group:
            forces = group["force/value"][:n_frames] * scale("force")
        observables = {}
        if "observables" in f:
            for name, element in f["observables"].items():
                quantity = _OBSERVABLE_UNITS.get(name, "")
                observables[name] = element["value"][:n_frames] * scale(quantity)
        parameters = {}
        for key, value in f["parameters"].attrs.items():
            parameters[key] = maybe_json(value)
        type_names = tuple(parameters.get("type_names") or ())
        types = group["species"][()].astype(np.int32)
        if not type_names:
            type_names = tuple(f"T{t}" for t in range(int(types.max()) + 1))
        return Trajectory(
            path=path,
            units=units,
            steps=steps,
            times=group["position/time"][:n_frames] * scale("time"),
            positions=positions,
            boxes=boxes,
            pbc=np.array([b == "periodic" for b in boundary]),
            masses=group["mass"][()] * scale("mass"),
            types=types,
            type_names=type_names,
            velocities=velocities,
            forces=forces,
            observables=observables,
            parameters=parameters,
            topology=_read_topology(f),
            tilts=tilts,
        )
    except (KeyError, ValueError, TypeError, RuntimeError) as error:
        raise _as_trajectory_error(path, error) from None


def unwrap_frames(positions, images, boxes, tilts) -> NDArray[np.float64]:
    """Continuous positions (F, N, 3) of stored frames: ``position + image @ cell`` per frame."""
    unwrapped = positions + images * boxes[:, None, :]
    if np.any(tilts != 0.0):  # a tilted cell: images count cell vectors
        unwrapped[..., 0] += images[..., 1] * tilts[:, None, 0] + images[..., 2] * tilts[:, None, 1]
        unwrapped[..., 1] += images[..., 2] * tilts[:, None, 2]
    return unwrapped


def split_edges(
    edges: NDArray[np.float64], frames: bool = True
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(lengths, tilts)`` of H5MD box edges: lengths (3,) or cell matrices (3, 3).

    ``frames``: ``edges`` holds one entry per frame, (F, 3) or (F, 3, 3);
    otherwise it is one frame's. A cell matrix must be lower triangular (a
    along x, b in the xy plane), as this writer stores it.
    """
    edges = np.asarray(edges, dtype=np.float64)
    if edges.ndim != (3 if frames else 2):
        return edges, np.zeros_like(edges)
    upper = edges[..., [0, 0, 1], [1, 2, 2]]
    if np.any(np.abs(upper) > 1e-12 * max(1.0, float(np.abs(edges).max(initial=0.0)))):
        raise ValueError("box edges are not lower triangular (a along x, b in the xy plane)")
    lengths = np.abs(np.diagonal(edges, axis1=-2, axis2=-1)).copy()
    tilts = edges[..., [1, 2, 2], [0, 0, 1]].copy()
    return lengths, tilts


@dataclass
class Frame:
    """One stored frame in engine units (see :class:`TrajectoryReader`).

    ``positions`` are as stored, wrapped into the box; ``images`` count the
    cell vectors to add for the continuous positions (:meth:`unwrapped`);
    ``tilt`` holds the tilt factors (xy, xz, yz), zero for an orthorhombic box.
    """

    index: int
    step: int
    time: float
    positions: NDArray[np.float64]
    images: NDArray[np.int32]
    box: NDArray[np.float64]
    velocities: NDArray[np.float64] | None = None
    forces: NDArray[np.float64] | None = None
    observables: dict[str, float] = field(default_factory=dict)
    tilt: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))

    @property
    def cell(self) -> NDArray[np.float64]:
        return cell_matrix(self.box, self.tilt)

    @property
    def volume(self) -> float:
        return float(np.prod(self.box))

    def unwrapped(self) -> NDArray[np.float64]:
        if not np.any(self.tilt != 0.0):
            return self.positions + self.images * self.box
        return self.positions + self.images @ self.cell


class TrajectoryReader:
    """Frames of an H5MD file of ours, read a chunk at a time (memory flat in frames).

    The time-independent parts (masses, types, periodicity, bonds, units,
    parameters) are read on opening; :meth:`frames` then yields
    :class:`Frame` objects in engine units for a slice of the frames.
    Use as a context manager, or call :meth:`close`.

    Raises
    ------
    TrajectoryError
        If the file is missing, not HDF5, not in our layout, or holds no frames.
    """

    def __init__(self, path) -> None:
        self.path = Path(path)
        self._file = open_h5md(self.path)
        try:
            f = self._file
            group = f["particles/trajectory"]
            self.units = get_units(attr_text(f["parameters"].attrs.get("units", "lj")))
            self.parameters = {k: maybe_json(v) for k, v in f["parameters"].attrs.items()}
            self.masses = group["mass"][()] / self._factor("mass")
            self.types = group["species"][()].astype(np.int32)
            names = self.parameters.get("type_names") or []
            n_types = int(self.types.max()) + 1 if len(self.types) else 1
            self.type_names = tuple(names) or tuple(f"T{t}" for t in range(n_types))
            boundary = [attr_text(b) for b in group["box"].attrs["boundary"]]
            self.pbc = np.array([b == "periodic" for b in boundary])
            self.topology = _read_topology(f)
            self._datasets = {
                "step": group["position/step"],
                "time": group["position/time"],
                "position": group["position/value"],
                "edges": group["box/edges/value"],
            }
            for name in ("image", "velocity", "force"):
                if name in group:
                    self._datasets[name] = group[f"{name}/value"]
            for name, element in f.get("observables", {}).items():
                self._datasets[f"observables/{name}"] = element["value"]
            # Complete frames: those every per-frame dataset holds (a killed write may
            # leave one partial frame).
            self.n_frames = _complete_frames(f)
        except TrajectoryError:  # already names the file and what is wrong
            self._file.close()
            raise
        except (KeyError, ValueError, TypeError, OSError, RuntimeError) as error:
            self._file.close()
            raise TrajectoryError(
                f"{self.path}: not a trajectory written by leapmd ({error})"
            ) from None
        if self.n_frames == 0:
            self._file.close()
            raise TrajectoryError(f"{self.path}: holds no frames yet")

    @property
    def n_atoms(self) -> int:
        return len(self.masses)

    @property
    def has_velocities(self) -> bool:
        return "velocity" in self._datasets

    @property
    def has_forces(self) -> bool:
        return "force" in self._datasets

    def _factor(self, quantity: str) -> float:
        return self.units.h5md[quantity][1] if quantity in self.units.h5md else 1.0

    def select(self, start=None, stop=None, step=None) -> range:
        """Return the frame indices of a slice, as Python slices do (negatives count back).

        Raises
        ------
        IndexError
            If ``start`` or ``stop`` lies outside the file's frames, or the
            slice selects none; the message gives the number of frames.
        ValueError
            If ``step`` is not a positive integer (at most 2^53).
        """
        n = self.n_frames
        if step is not None:
            step = count(step, "step", minimum=1)
        for name, value, limit in (("start", start, n - 1), ("stop", stop, n)):
            if value is not None and not -n <= value <= limit:
                raise IndexError(
                    f"{self.path} holds {n} frames (0 to {n - 1}); {name} {value} is out of range"
                )
        # A step beyond the frames selects the first alone; h5py takes no larger one.
        frames = range(n)[slice(start, stop, None if step is None else min(step, max(n, 1)))]
        if len(frames) == 0:
            raise IndexError(
                f"{self.path} holds {n} frames; start {start}, stop {stop}, step {step} select none"
            )
        return frames

    def times(self, indices: range) -> NDArray[np.float64]:
        """Return the times of the frames ``indices`` [engine time units]."""
        return self._datasets["time"][()][list(indices)] / self._factor("time")

    def frame(self, index: int) -> Frame:
        """Return one frame (negative indices count from the end)."""
        (frame,) = self.frames(self.select(index, index + 1 if index != -1 else None))
        return frame

    def frames(self, indices: range | None = None, chunk: int = 64) -> Iterator[Frame]:
        """Yield the frames ``indices`` (default: all), reading ``chunk`` frames at a time."""
        indices = range(self.n_frames) if indices is None else indices
        scale_length = 1.0 / self._factor("length")
        for first in range(0, len(indices), chunk):
            part = indices[first : first + chunk]
            lo, hi, by = part.start, part.stop, part.step
            if by > 0 and hi > self.n_frames:
                hi = self.n_frames
            read = {}
            try:
                for name, dataset in self._datasets.items():
                    read[name] = dataset[lo:hi:by] if by > 0 else dataset[list(part)]
            except OSError as error:
                if _is_checksum_error(error):
                    verify_frames(self.path)  # raises naming the damaged frame
                raise TrajectoryError(f"{self.path}: cannot read frames ({error})") from None
            for k, index in enumerate(part):
                try:
                    frame = self._frame(read, k, index, scale_length)
                except (TypeError, ValueError) as error:  # datasets of the wrong kind
                    raise TrajectoryError(
                        f"{self.path}: frame {index} is not a frame written by leapmd ({error})"
                    ) from None
                yield frame

    def _frame(self, read: dict, k: int, index: int, scale_length: float) -> Frame:
        """Frame ``index``, the ``k``-th of the datasets' slices ``read``."""
        observables = {
            name.split("/", 1)[1]: float(values[k])
            / self._factor(_OBSERVABLE_UNITS.get(name.split("/", 1)[1], ""))
            for name, values in read.items()
            if name.startswith("observables/")
        }
        positions = read["position"][k] * scale_length
        box, tilt = split_edges(read["edges"][k] * scale_length, frames=False)
        return Frame(
            index=index,
            step=int(read["step"][k]),
            time=float(read["time"][k]) / self._factor("time"),
            positions=positions,
            images=(
                read["image"][k].astype(np.int32)
                if "image" in read
                else np.zeros(positions.shape, dtype=np.int32)
            ),
            box=box,
            tilt=tilt,
            velocities=(
                read["velocity"][k] / self._factor("velocity") if "velocity" in read else None
            ),
            forces=read["force"][k] / self._factor("force") if "force" in read else None,
            observables=observables,
        )

    def state(self, frame: Frame, unwrap: bool = True) -> State:
        """Return a frame as a State (continuous positions unless ``unwrap=False``)."""
        return State(
            positions=frame.unwrapped() if unwrap else frame.positions,
            velocities=frame.velocities,
            masses=self.masses,
            box=frame.box,
            pbc=self.pbc,
            types=self.types,
            type_names=self.type_names,
            step=frame.step,
            time=frame.time,
            tilt=frame.tilt,
        )

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> TrajectoryReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _complete_frames(f: h5py.File) -> int:
    """Frames that every per-frame dataset of the file holds."""
    group = f["particles/trajectory"]
    lengths = [len(group["position/step"]), len(group["position/time"]),
               len(group["position/value"]), len(group["box/edges/value"])]  # fmt: skip
    for name in ("image", "velocity", "force"):
        if name in group:
            lengths.append(len(group[f"{name}/value"]))
    for element in f.get("observables", {}).values():
        lengths.append(len(element["value"]))
    return min(lengths)


def read_frame_steps(path) -> tuple[NDArray[np.int64], dict]:
    """Return the steps of the complete frames of a trajectory and its parameters.

    Reads only the step array and ``/parameters`` (cheap on long files), so a
    resumed run can check that a file belongs to its checkpoint before
    changing anything. A frame counts as complete when every per-frame
    dataset holds it (a run killed in the middle of a write may leave one
    partial frame).

    Raises
    ------
    TrajectoryError
        If the file is missing, not HDF5, or not in our layout.
    """
    path = Path(path)
    with open_h5md(path) as f:
        try:
            group = f["particles/trajectory"]
            steps = group["position/step"][: _complete_frames(f)]
            parameters = {key: maybe_json(value) for key, value in f["parameters"].attrs.items()}
            parameters["n_atoms"] = int(group["position/value"].shape[1])
        except (KeyError, ValueError, TypeError, OSError, IndexError, RuntimeError) as error:
            raise TrajectoryError(f"{path}: not a trajectory written by leapmd ({error})") from None
    return steps, parameters


def _is_checksum_error(error: BaseException) -> bool:
    text = str(error).lower()
    return any(sign in text for sign in ("checksum", "fletcher", "filter returned failure"))


def verify_frames(path, n_frames: int | None = None) -> int:
    """Read every stored frame (the first ``n_frames``) and check its checksums.

    Frame datasets carry HDF5's Fletcher-32 checksum per chunk (one frame per
    chunk), so flipped bytes anywhere in a stored frame are found here.
    Returns the number of frames checked. A frame that a live run is writing
    is not taken for a damaged one (see :func:`while_written`).

    Raises
    ------
    TrajectoryError
        Naming the first damaged frame and dataset.
    """
    path = Path(path)
    return while_written(path, lambda: _verify_frames(path, n_frames))


def _verify_frames(path: Path, n_frames: int | None) -> int:
    with open_h5md(path) as f:
        group = f["particles/trajectory"]
        datasets = {
            name: group[name]["value"]
            for name in ("position", "image", "velocity", "force", "box/edges")
            if name in group
        }
        datasets["step"] = group["position/step"]
        datasets["time"] = group["position/time"]
        for name, element in f.get("observables", {}).items():
            datasets[f"observables/{name}"] = element["value"]
        count = min(len(d) for d in datasets.values())
        count = count if n_frames is None else min(count, n_frames)
        for name, dataset in datasets.items():
            chunk = dataset.chunks[0] if dataset.chunks else count
            for start in range(0, count, max(chunk, 1)):
                try:
                    dataset[start : min(start + chunk, count)]
                except OSError as error:
                    first = start if chunk == 1 else f"{start} to {min(start + chunk, count) - 1}"
                    raise TrajectoryError(
                        f"{path}: frame {first} is damaged ({name}: {error}); the frames before "
                        "it are intact"
                    ) from None
    return count


def open_trajectory(path, **kwargs):
    """Open a trajectory we wrote as an MDAnalysis ``Universe``.

    Masses, types (the type names), bonds (``u.bonds``, typed by bond
    type name) and angles (``u.angles``, typed by angle type name) come
    from the file. Reduced-unit
    files carry no unit attributes, so they are opened with
    ``convert_units=False``; metal files are converted to MDAnalysis's units
    (Angstrom, ps, kJ/(mol Angstrom)) as usual. Extra keyword arguments go to
    MDAnalysis's H5MD reader.
    """
    import MDAnalysis as mda  # heavy: MDAnalysis is imported on first use
    from MDAnalysis.core.topologyattrs import Angles, Bonds  # with MDAnalysis, on first use

    path = Path(path)
    with open_h5md(path) as f:
        try:
            units = str(f["parameters"].attrs.get("units", "lj"))
            masses = f["particles/trajectory/mass"][()]
            types = f["particles/trajectory/species"][()]
            names = maybe_json(f["parameters"].attrs.get("type_names", "[]"))
            n_frames = len(f["particles/trajectory/position/step"])
            topology = _read_topology(f)
        except TrajectoryError:
            raise
        except (KeyError, ValueError, TypeError) as error:
            raise TrajectoryError(f"{path}: not a trajectory written by leapmd ({error})") from None
    if n_frames == 0:  # MDAnalysis's reader cannot open a file without frames
        raise TrajectoryError(
            f"{path}: holds no frames yet (its run was stopped before writing the first)"
        )
    kwargs.setdefault("convert_units", units != "lj")
    universe = mda.Universe.empty(len(masses), trajectory=False)
    retry_transient(lambda: universe.load_new(str(path), format="H5MD", **kwargs))
    names = list(names) or [f"T{t}" for t in range(int(types.max()) + 1)]
    universe.add_TopologyAttr("types", [names[t] for t in types])
    universe.add_TopologyAttr("masses", masses)
    if topology.n_bonds:
        names = topology.bond_type_names
        universe.add_TopologyAttr(
            Bonds(
                [tuple(pair) for pair in topology.bonds.tolist()],
                types=[names[t] for t in topology.bond_types],
            )
        )
    if topology.n_angles:
        names = topology.angle_type_names
        universe.add_TopologyAttr(
            Angles(
                [tuple(triple) for triple in topology.angles.tolist()],
                types=[names[t] for t in topology.angle_types],
            )
        )
    return universe


#: Signs of an HDF5 error caused by a concurrent writer's frame in flight, not by damage.
_TRANSIENT = ("truncated file", "addr overflow", "eoa", "stored_eof")


def retry_transient(action, attempts: int = 20, pause: float = 0.05):
    """Run ``action()``, retrying for up to a second while it fails as a live writer's
    half-written frame makes reads fail (the run flushes each frame whole)."""
    for attempt in range(attempts):
        try:
            return action()
        except (OSError, AttributeError) as error:  # MDAnalysis's reader: AttributeError
            transient = any(sign in str(error).lower() for sign in _TRANSIENT) or (
                isinstance(error, AttributeError) and "_file" in str(error)
            )
            if not transient or attempt == attempts - 1:
                raise
            time.sleep(pause)
    return None


def _file_signature(path: Path) -> tuple[int, int] | None:
    try:
        stat = path.stat()
    except OSError:
        return None
    return stat.st_size, stat.st_mtime_ns


def while_written(path: Path, read, settle: float = 0.1, patience: float = 5.0):
    """Run ``read()`` (which opens ``path`` itself), again while the file is being written.

    A reader that opens the file while a run flushes a frame can see the
    frame's datasets grown before its data, which reads as a truncated file
    ("addr overflow") or a failed checksum. Such an error is believed only
    once the file has stayed unchanged (size and modification time) from
    the start of the read to ``settle`` seconds after it failed; while the
    file keeps changing the read is tried again with a fresh open, for up to
    ``patience`` seconds. A damaged file that nothing writes is reported
    after one extra pause of ``settle`` seconds.
    """
    deadline = time.monotonic() + patience
    while True:
        before = _file_signature(path)
        try:
            return read()
        except TrajectoryError:
            if before is None:  # no file: nothing is writing it
                raise
            time.sleep(settle)
            if _file_signature(path) == before or time.monotonic() > deadline:
                raise


def open_h5md(path: Path) -> h5py.File:
    if not path.exists():
        raise TrajectoryError(f"{path}: no such file")
    try:
        # Read-only; a file a run is writing can be read, since the writer takes no
        # HDF5 file lock. A frame being written can leave the file's recorded end
        # briefly ahead of its real end: such opens are retried.
        f = retry_transient(lambda: h5py.File(path, "r"))
    except OSError as error:
        raise TrajectoryError(f"{path}: not a readable HDF5 file ({error})") from None
    try:
        ours = "h5md" in f and "particles" in f
    except (RuntimeError, OSError, KeyError) as error:  # damaged metadata
        f.close()
        raise TrajectoryError(f"{path}: a damaged HDF5 file ({error})") from None
    if not ours:
        f.close()
        raise TrajectoryError(
            f"{path}: an HDF5 file, but not in the H5MD layout (no h5md/particles)"
        )
    return f


def attr_text(value) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


def maybe_json(value):
    value = attr_text(value) if isinstance(value, bytes | str) else value
    if isinstance(value, str) and value[:1] in "[{":
        try:
            return json.loads(value)
        except json.JSONDecodeError:
            return value
    if isinstance(value, np.generic):
        return value.item()
    return value


def trajectory_summary(traj) -> dict:
    """Plain-data summary of a trajectory (what ``md info`` prints)."""
    to_file_time = traj.units.h5md["time"][1] if "time" in traj.units.h5md else 1.0
    stored = ["position", "image", "box"]
    if traj.velocities is not None:
        stored.append("velocity")
    if traj.forces is not None:
        stored.append("force")
    stored += sorted(traj.observables)
    if traj.topology.n_bonds or traj.topology.n_angles:
        stored.append("connectivity")
    summary = {
        "path": str(traj.path),
        "version": traj.parameters.get("leapmd_version", "?"),
        "n_atoms": traj.n_atoms,
        "n_frames": traj.n_frames,
        "types": list(traj.type_names),
        "units": traj.units.name,
        "first_step": int(traj.steps[0]) if traj.n_frames else None,
        "last_step": int(traj.steps[-1]) if traj.n_frames else None,
        "first_time": float(traj.times[0] * to_file_time) if traj.n_frames else 0.0,
        "last_time": float(traj.times[-1] * to_file_time) if traj.n_frames else 0.0,
        "box": traj.boxes[-1].tolist() if traj.n_frames else None,
        "tilt": traj.tilts[-1].tolist() if traj.n_frames and np.any(traj.tilts[-1]) else None,
        "pbc": traj.pbc.tolist(),
        "stored": stored,
        "bonds": {name: len(pairs) for name, pairs in traj.topology.by_type().items()},
        "angles": {name: len(listed) for name, listed in traj.topology.angles_by_type().items()},
    }
    total = traj.observables.get("total_energy")
    if total is not None and len(total) and np.all(np.isfinite(total)):
        scale = max(abs(total[0]), 1e-300)
        summary["energy"] = {
            "first": float(total[0]),
            "last": float(total[-1]),
            "mean": float(total.mean()),
            "std": float(total.std()),
            "relative_drift": float((total[-1] - total[0]) / scale),
        }
        summary["temperature_mean"] = float(traj.observables["temperature"].mean())
        summary["pressure_mean"] = float(traj.observables["pressure"].mean())
    conserved = traj.observables.get("conserved_energy")
    if conserved is not None and len(conserved) and np.all(np.isfinite(conserved)):
        # relative to the size of the energies, as the total's (the conserved quantity's
        # own origin is arbitrary: it holds the heat bath's energy since the start)
        scale = max(abs(total[0]) if total is not None else 0.0, abs(conserved[0]), 1e-300)
        summary["conserved_energy"] = {
            "first": float(conserved[0]),
            "last": float(conserved[-1]),
            "relative_drift": float((conserved[-1] - conserved[0]) / scale),
        }
    return summary
