"""The H5MD readers: a whole file into engine units (:func:`read_trajectory`), frames a chunk
at a time (:class:`TrajectoryReader`), the connectivity (:func:`read_topology`), the
steps stored (:func:`read_frame_steps`), a check of every frame (:func:`verify_frames`),
MDAnalysis (:func:`open_trajectory`) and what ``md info`` prints.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np
from numpy.typing import NDArray

from md._checks import count
from md.box import cell_matrix
from md.errors import TrajectoryError
from md.state import State
from md.topology import Topology
from md.trajectory._layout import (
    _OBSERVABLE_UNITS,
    _complete_frames,
    _is_checksum_error,
    _read_topology,
    attr_text,
    maybe_json,
    split_edges,
    unwrap_frames,
)
from md.trajectory.retries import open_h5md, retry_transient, while_written
from md.units import UnitSystem, get_units


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
            # Rigid bodies' molecule ids (1, 2, ...; 0 free), where the run had bodies.
            self.molecule_ids = f["rigid/molecule"][()] if "rigid/molecule" in f else None
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
            chunk = max(dataset.chunks[0] if dataset.chunks else count, 1)
            # whole chunks at a time, up to about _VERIFY_BYTES a read (one read a frame
            # took ~15 us of h5py each); a read that fails is searched chunk by chunk
            frame_bytes = dataset.dtype.itemsize * int(np.prod(dataset.shape[1:], dtype=np.int64))
            block = chunk * max(1, _VERIFY_BYTES // max(frame_bytes * chunk, 1))
            for start in range(0, count, block):
                end = min(start + block, count)
                try:
                    dataset[start:end]
                except OSError:
                    _first_damaged(path, name, dataset, start, end, chunk)
    return count


#: About how many bytes :func:`verify_frames` reads from a dataset at once.
_VERIFY_BYTES = 8 << 20


def _first_damaged(path: Path, name: str, dataset, start: int, end: int, chunk: int) -> None:
    """Raise naming the first chunk of ``dataset[start:end]`` (a read of which failed)
    that cannot be read."""
    for first in range(start, end, chunk):
        last = min(first + chunk, end)
        try:
            dataset[first:last]
        except OSError as error:
            frames = first if last - first == 1 else f"{first} to {last - 1}"
            raise TrajectoryError(
                f"{path}: frame {frames} is damaged ({name}: {error}); the frames before "
                "it are intact"
            ) from None
    raise TrajectoryError(f"{path}: frames {start} to {end - 1} of {name} cannot be read")


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
