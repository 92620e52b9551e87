"""The H5MD writer: :class:`H5MDWriter`, an observer and a context manager that writes the
layout described in :mod:`md.trajectory`, flushed after every frame.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import resource
import uuid
from pathlib import Path

import h5py
import numpy as np
from numpy.typing import NDArray

from md._files import disk_full, write_bytes_atomic
from md._version import __version__
from md.box import wrap
from md.errors import TrajectoryError
from md.state import State
from md.topology import Topology
from md.trajectory._layout import _OBSERVABLE_UNITS, H5MD_VERSION, OBSERVABLES, attr_text
from md.trajectory.retries import open_h5md
from md.units import UnitSystem, get_units

#: HDF5 raw-chunk cache per dataset while writing [bytes]. Every chunk holds one
#: frame and is written whole and flushed at once, so it needs no cache. (h5py's
#: default, 1 MiB per dataset, kept ~30 MiB of already-written chunks resident on
#: long runs.)
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
    bodies : md.rigid.RigidBodies, optional
        Rigid bodies whose ``centres`` (unwrapped [length]) and ``quaternions``
        (w, x, y, z) are stored with every frame, under ``rigid/centre`` and
        ``rigid/orientation`` (step and time linked as for the particles), and
        each atom's body (1, 2, ...; 0 for a free atom) in ``rigid/molecule``; an
        appending writer keeps writing them where the file has them.

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
        bodies=None,
    ) -> None:
        self.path = Path(path)
        self._bodies = bodies
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
        if "rigid" in f:
            self._values["body_centre"] = f["rigid/centre/value"]
            self._values["body_orientation"] = f["rigid/orientation/value"]
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
                error
                if isinstance(error, TrajectoryError)
                else TrajectoryError(f"{path}: not a trajectory written by leapmd ({error})")
            )
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
            "step", shape=(0,), maxshape=(None,), dtype=np.int64, chunks=(1,), fletcher32=True
        )
        self._time = position.create_dataset(
            "time", shape=(0,), maxshape=(None,), dtype=np.float64, chunks=(1,), fletcher32=True
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

        if self._bodies is not None:  # rigid bodies: centres and quaternions per frame
            rigid = f.create_group("rigid")
            n_bodies = len(self._bodies.centres)
            element = self._element(rigid, "centre", (n_bodies, 3), np.float64, "length")
            self._values["body_centre"] = element["value"]
            element = self._element(rigid, "orientation", (n_bodies, 4), np.float64, None)
            self._values["body_orientation"] = element["value"]
            # The molecule id of every atom (its body's number from 1; 0: a free atom).
            rigid.create_dataset("molecule", data=self._bodies.body_of + 1)

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
            # One frame a chunk, scalar series too: a chunk is written once, so a run
            # killed inside a write (the kernel may stop a write of several pages
            # part way for SIGKILL) can damage only the frame it was writing; a
            # chunk of 1024 frames rewritten at every frame lost all of them at once.
            chunks=(1, *frame_shape),
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
        if self._bodies is not None and "body_centre" in self._values:
            centres = self._bodies.centres  # unwrapped, as the integrator moves them
            self._values["body_centre"][frame] = centres * self._factor("length")
            self._values["body_orientation"][frame] = self._bodies.quaternions
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
