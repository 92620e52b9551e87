"""Convert our H5MD trajectories to the formats viewers and other codes read.

One :class:`md.trajectory.TrajectoryReader` feeds one writer per format,
a chunk of frames at a time, so memory stays flat in the number of frames.
The writers are the well-kept libraries':

======================  =================  =====================================
suffix                  library            units written (metal runs)
======================  =================  =====================================
``.xtc``, ``.trr``      MDAnalysis         nm, ps, kJ/(mol nm) (GROMACS)
``.dcd``                MDAnalysis         Angstrom, AKMA time (CHARMM/NAMD)
``.nc``, ``.ncdf``      MDAnalysis         Angstrom, ps, kcal/(mol Angstrom) (AMBER)
``.xyz``, ``.extxyz``   ase.io             ASE: Angstrom, eV, eV/Angstrom
``.traj``               ase.io             ASE
``.data``               ase.io (LAMMPS)    LAMMPS ``metal``, one frame, with bonds
                                           and angles
``.gsd``                gsd                Angstrom, ps, amu (GSD has no units)
``.lammpstrj``          our own (text)     LAMMPS ``metal`` (no library writes dumps)
======================  =================  =====================================

Reduced-unit (``lj``) runs are written unchanged, in sigma, tau and
epsilon, wherever the format would otherwise convert. Formats that need a
box with a volume (LAMMPS data and dumps, GSD) get, along open axes, the
stored edge widened to the atoms' extent, or the atoms' bounding box where
the edge is zero (a cluster or a slab read without a cell there:
:func:`md.box.enclosing_cell`). Where a format has a
header or metadata (extxyz's comment line, the LAMMPS data title, DCD and
NetCDF remarks) the units are stated there.

The output is written to a temporary file beside it and moved into place
only when complete, so a failed conversion leaves no partial file, and an
existing file is replaced only with ``overwrite=True``.
"""

from __future__ import annotations

import errno
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from md._files import (
    atomic_path,
    disk_full,
    exclusive_claim,
    output_target,
    remove_stale_temporaries,
)
from md._version import __version__
from md.box import cell_matrix, enclosing_cell
from md.topology import Topology
from md.trajectory import Frame, TrajectoryReader

#: Output formats by suffix (lower case, without the dot).
FORMATS = {
    "xyz": "xyz",
    "extxyz": "extxyz",
    "lammpstrj": "lammpstrj",
    "dump": "lammpstrj",
    "data": "data",
    "lmp": "data",
    "dcd": "dcd",
    "xtc": "xtc",
    "trr": "trr",
    "gsd": "gsd",
    "nc": "nc",
    "ncdf": "nc",
    "traj": "traj",
}
#: Formats that hold one frame (the last one selected is written).
SINGLE_FRAME = ("data",)


def output_format(path, format: str | None = None) -> str:
    """Return the format name for an output path (or the explicit ``format``).

    Raises
    ------
    ValueError
        For an unknown suffix or format, listing the known ones.
    """
    known = ", ".join(sorted(FORMATS))
    if format is not None:
        key = format.lower().lstrip(".")
        if key not in FORMATS:
            raise ValueError(f"unknown format {format!r}; known formats: {known}")
        return FORMATS[key]
    suffix = Path(path).suffix.lower().lstrip(".")
    if suffix not in FORMATS:
        what = f"suffix .{suffix}" if suffix else "no suffix"
        raise ValueError(f"{path}: {what} names no format I write; use one of {known} (--format)")
    return FORMATS[suffix]


def convert(
    trajectory,
    output,
    format: str | None = None,
    start: int | None = None,
    stop: int | None = None,
    step: int | None = None,
    unwrap: bool = False,
    overwrite: bool = False,
    chunk: int = 64,
    progress: Callable[[int], None] | None = None,
) -> int:
    """Write frames ``[start:stop:step]`` of an H5MD trajectory to ``output``.

    Parameters
    ----------
    trajectory : path
        H5MD file written by leapmd.
    output : path
        File to write; the format comes from its suffix or from ``format``.
    unwrap : bool
        Write continuous positions (``position + image * box``) instead of
        positions wrapped into the box (with image flags where the format
        stores them).
    overwrite : bool
        Replace an existing ``output``.
    chunk : int
        Frames read from the file at a time.
    progress : callable, optional
        Called with the number of frames written after each frame.

    Returns
    -------
    int
        The number of frames written.

    Raises
    ------
    ValueError
        Unknown format, or a format that cannot hold this trajectory.
    IndexError
        A frame selection outside the file's frames, or one that selects none.
    FileExistsError
        ``output`` exists and ``overwrite`` is not given, or another run is
        writing it (:class:`md._files.OutputBusyError`).
    OSError
        The output could not be written ("disk full" when there is no room);
        nothing is left behind.
    TrajectoryError
        The input is not an H5MD trajectory of ours (or is damaged).

    Notes
    -----
    ``output`` is written through a symbolic link into its target; a special
    file (FIFO, device node) is refused with ValueError, never replaced. The
    output is claimed as ``md run`` claims its own, so a running simulation's
    trajectory is never replaced, and temporaries an interrupted conversion
    left beside it are removed.
    """
    trajectory = Path(trajectory)
    kind = output_format(output, format)
    output = output_target(output)  # a symlink's target; a special file is refused
    if output.exists() and not overwrite:
        raise FileExistsError(f"{output} already exists; choose another name or pass --overwrite")
    if output.exists() and output.resolve() == trajectory.resolve():
        raise ValueError(f"{output} is the input trajectory; choose another output")
    if not output.parent.is_dir():
        raise FileNotFoundError(f"{output}: directory {output.parent} does not exist")
    with TrajectoryReader(trajectory) as reader, exclusive_claim(output):
        frames = reader.select(start, stop, step)
        if kind in SINGLE_FRAME:
            frames = frames[-1:]
        writer_class = WRITERS[kind]
        remove_stale_temporaries(output)  # an interrupted conversion's, under the claim
        with atomic_path(output, exclusive=not overwrite) as temporary:
            writer = writer_class(temporary, reader, frames, unwrap=unwrap, kind=kind)
            count = 0
            try:
                try:
                    for frame in reader.frames(frames, chunk=chunk):
                        writer.write(frame)
                        count += 1
                        if progress is not None:
                            progress(count)
                finally:
                    writer.close()
                writer.verify(temporary, count)
            except (OSError, RuntimeError) as error:  # the writers' libraries raise either
                raise _write_failure(error, temporary, output, reader.n_atoms) from None
    return count


# ---------------------------------------------------------------------- helpers
def _write_failure(error: BaseException, temporary: Path, output: Path, n_atoms: int) -> OSError:
    """The OSError for a failed conversion: "disk full" when the disk has no room for a frame.

    The writers' C libraries (XTC, TRR, DCD) do not say why a write failed, so
    the free space left beside the temporary file decides.
    """
    detail = error.strerror if isinstance(error, OSError) and error.strerror else str(error)
    stats = os.statvfs(temporary.parent)
    # room for less than one frame of float32 x, y, z
    if disk_full(error) or stats.f_bavail * stats.f_frsize < 12 * n_atoms + 4096:
        return OSError(errno.ENOSPC, f"disk full: cannot write {output} ({detail})")
    return OSError(errno.EIO, f"cannot write {output}: {detail}")


def _positions(frame: Frame, unwrap: bool):
    return frame.unwrapped() if unwrap else frame.positions


def cell_dimensions(box, tilt) -> NDArray[np.float64]:
    """MDAnalysis's ``dimensions`` (a, b, c, alpha, beta, gamma) of a cell [length, degrees]."""
    from MDAnalysis.lib.mdamath import triclinic_box  # MDAnalysis: loaded with the converters

    if not np.any(np.asarray(tilt) != 0.0):
        return np.array([*box, 90.0, 90.0, 90.0])
    return np.asarray(triclinic_box(*cell_matrix(box, tilt)), dtype=np.float64)


def _images(frame: Frame, unwrap: bool):
    return np.zeros_like(frame.images) if unwrap else frame.images


def _units_note(reader: TrajectoryReader, convention: str) -> str:
    if reader.units.name == "lj":
        return f"leapmd {__version__}: reduced LJ units (sigma, tau, epsilon), written unchanged"
    return f"leapmd {__version__}: {convention}"


def _molecule_ids(reader: TrajectoryReader) -> np.ndarray:
    """The rigid bodies of a run that had them (what ``fix rigid ... molecule`` takes; 0 for
    free atoms), else the bonded clusters."""
    if reader.molecule_ids is not None:
        return np.asarray(reader.molecule_ids, dtype=np.int64)
    return molecules(reader.topology, reader.n_atoms)


def molecules(topology: Topology, n_atoms: int) -> np.ndarray:
    """Return a molecule number (1, 2, ...) per atom: the connected components of the bonds."""
    parent = np.arange(n_atoms)

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, j in topology.bonds.tolist():
        a, b = root(i), root(j)
        if a != b:
            parent[max(a, b)] = min(a, b)
    roots = np.array([root(i) for i in range(n_atoms)])
    _, numbers = np.unique(roots, return_inverse=True)
    return numbers + 1


# ---------------------------------------------------------------------- writers
#: MDAnalysis's names of the quantities whose units its writers convert.
_QUANTITY = {"length": "length", "time": "time", "velocity": "speed", "force": "force"}


class _Writer:
    """A format's writer: ``__init__(path, reader, frames, unwrap, kind)``, ``write(frame)``,
    ``close()`` and ``verify(path, count)``."""

    def close(self) -> None:
        """Finish the file (flush, close)."""

    def verify(self, path: Path, count: int) -> None:
        """Raise OSError unless the closed file holds ``count`` frames.

        Only writers whose library does not report failed writes check: the
        others raise from ``write`` or ``close`` already.
        """


class _MDAnalysisWriter(_Writer):
    """XTC, TRR, DCD and AMBER NetCDF through MDAnalysis's writers.

    Frames go in as MDAnalysis's base units (Angstrom, ps, kJ/(mol
    Angstrom)), which are the H5MD file's own for metal runs; the writer
    converts to its format's convention. Reduced units pass unchanged.
    """

    _FORMATS = {"xtc": "XTC", "trr": "TRR", "dcd": "DCD", "nc": "NCDF"}

    def __init__(
        self, path: Path, reader: TrajectoryReader, frames: range, unwrap: bool, kind: str
    ) -> None:
        import MDAnalysis as mda  # heavy: MDAnalysis is imported on first use

        self.reader, self.unwrap = reader, unwrap
        self.kind = self._FORMATS[kind]
        self.velocities = reader.has_velocities and self.kind in ("TRR", "NCDF")
        self.forces = reader.has_forces and self.kind in ("TRR", "NCDF")
        self.universe = mda.Universe.empty(
            reader.n_atoms, trajectory=True, velocities=self.velocities, forces=self.forces
        )
        self.universe.add_TopologyAttr("types", [reader.type_names[t] for t in reader.types])
        self.universe.add_TopologyAttr("masses", reader.masses)
        options = {}
        if self.kind in ("DCD", "NCDF"):
            options["remarks"] = _units_note(reader, "written from Angstrom and ps")
        if self.kind == "DCD":  # DCD keeps no time per frame, only a start and an interval
            times = reader.times(frames) * (
                reader.units.h5md["time"][1] if "time" in reader.units.h5md else 1.0
            )
            options["dt"] = float(times[1] - times[0]) if len(times) > 1 else 1.0
        self.writer = mda.Writer(str(path), n_atoms=reader.n_atoms, format=self.kind, **options)
        # Frames go in as MDAnalysis's base units; the writer converts them to its own.
        # For metal runs those are the H5MD file's units; reduced (lj) values are
        # pre-scaled by the inverse of the writer's conversion, so they land unchanged.
        scale = reader.units.h5md
        base = {
            "length": "Angstrom",
            "time": "ps",
            "velocity": "Angstrom/ps",
            "force": "kJ/(mol*Angstrom)",
        }
        self.factor = {}
        for quantity, unit in base.items():
            if reader.units.name != "lj":
                self.factor[quantity] = scale[quantity][1] if quantity in scale else 1.0
            elif quantity in self.writer.units and self.writer.units[quantity]:
                native = self.writer.units[quantity]
                self.factor[quantity] = 1.0 / mda.units.get_conversion_factor(
                    _QUANTITY[quantity], unit, native
                )
            else:
                self.factor[quantity] = 1.0

    def write(self, frame: Frame) -> None:
        factor = self.factor
        ts = self.universe.trajectory.ts
        ts.positions = _positions(frame, self.unwrap) * factor["length"]
        dimensions = cell_dimensions(frame.box, frame.tilt)
        dimensions[:3] *= factor["length"]
        ts.dimensions = dimensions
        ts.time = frame.time * factor["time"]
        ts.data["step"] = frame.step
        if self.velocities:
            ts.velocities = frame.velocities * factor["velocity"]
        if self.forces:
            ts.forces = frame.forces * factor["force"]
        self.writer.write(self.universe.atoms)

    def close(self) -> None:
        self.writer.close()

    def verify(self, path: Path, count: int) -> None:
        """Raise OSError unless ``path`` holds ``count`` frames.

        The XTC, TRR and DCD writers are C code that does not check its
        writes: on a full disk they end without error, leaving a short file.
        """
        from MDAnalysis.lib.formats.libdcd import DCDFile  # MDAnalysis: with the writer
        from MDAnalysis.lib.formats.libmdaxdr import TRRFile, XTCFile  # as is DCDFile

        opener = {"DCD": DCDFile, "XTC": XTCFile, "TRR": TRRFile}.get(self.kind)
        if opener is None:  # NetCDF: written by scipy, which raises on a failed write
            return
        try:
            with opener(str(path)) as written:
                found = written.n_frames if self.kind == "DCD" else len(written.offsets)
        except (OSError, RuntimeError, ValueError, EOFError) as error:
            unreadable = f"the {self.kind} file written cannot be read ({error})"
            raise OSError(errno.EIO, unreadable) from None
        if found != count:
            raise OSError(errno.EIO, f"{found} of the {count} frames reached the {self.kind} file")


class _ASEWriter(_Writer):
    """Plain XYZ, extended XYZ and ASE trajectories through ``ase.io``.

    Extended XYZ and ASE trajectories carry the potential energy, forces and
    velocities of each frame (a single-point calculator and momenta), and
    ``step``, ``time`` and ``units`` in the frame's info.
    """

    def __init__(
        self, path: Path, reader: TrajectoryReader, frames: range, unwrap: bool, kind: str
    ) -> None:
        self.reader, self.unwrap = reader, unwrap
        self.kind = kind
        if self.kind == "traj":
            from ase.io.trajectory import Trajectory  # ASE's writers: loaded on first use

            self.handle = Trajectory(str(path), "w")
        else:
            self.handle = open(path, "w")  # noqa: SIM115 (closed in close())

    def write(self, frame: Frame) -> None:
        from ase.calculators.singlepoint import SinglePointCalculator  # with ASE's writers
        from ase.io import write  # ASE's writers: loaded on first use

        state = self.reader.state(frame, unwrap=True)
        atoms = state.to_ase()
        atoms.positions[:] = _positions(frame, self.unwrap)
        atoms.info.update(step=frame.step, time=frame.time, units=self.reader.units.name)
        results = {}
        energy = frame.observables.get("potential_energy")
        if energy is not None and np.isfinite(energy):
            results["energy"] = energy
        if frame.forces is not None:
            results["forces"] = frame.forces
        if results and self.kind != "xyz":
            atoms.calc = SinglePointCalculator(atoms, **results)
        if self.kind == "traj":
            self.handle.write(atoms)
        elif self.kind == "extxyz":
            write(self.handle, atoms, format="extxyz")
        else:  # plain XYZ: symbols and positions; step, time and units on the comment line
            comment = f"step={frame.step} time={frame.time:.17g} units={self.reader.units.name}"
            write(self.handle, atoms, format="xyz", comment=comment)

    def close(self) -> None:
        self.handle.close()


class _LammpsDataWriter(_Writer):
    """A LAMMPS data file (``atom_style full``) through ASE's writer, with bonds and angles.

    Atom types are numbered 1, 2, ... in the order of the type names, which
    the ``Masses`` comments give; the title line names the units and the
    bond and angle types; molecules are the bonded clusters. Angles go
    into an ``Angles`` section (``id type i j k``, j the vertex) with the
    ``angles`` and ``angle types`` header lines that ``read_data`` needs;
    like the bonds, they carry no coefficients (no ``Angle Coeffs``: set
    ``angle_style`` and ``angle_coeff`` in the LAMMPS input). Units are LAMMPS
    ``metal`` for metal runs, and the reduced values unchanged for ``lj``
    runs.
    """

    #: ASE keys atom types on chemical symbols: each of our types gets one of these.
    _STAND_INS = ("H", "He", "Li", "Be", "B", "C", "N", "O", "F", "Ne", "Na", "Mg", "Al", "Si")

    def __init__(
        self, path: Path, reader: TrajectoryReader, frames: range, unwrap: bool, kind: str
    ) -> None:
        self.path, self.reader, self.unwrap = path, reader, unwrap
        # ASE's writer converts from its units to the ones named; "ASE" to ASE's own is the
        # identity, so reduced (lj) values are written exactly as they are (a round trip
        # through metal gave masses of 0.99999999974).
        self._ase_units = "ASE" if reader.units.name == "lj" else "metal"
        if len(reader.type_names) > len(self._STAND_INS):
            raise ValueError(
                f"LAMMPS data output takes up to {len(self._STAND_INS)} atom types, the "
                f"trajectory has {len(reader.type_names)}"
            )

    def write(self, frame: Frame) -> None:
        from ase.calculators.lammps import convert as lammps_units  # ASE's LAMMPS units
        from ase.io.lammpsdata import write_lammps_data  # ASE's writer: loaded on first use

        reader, topology = self.reader, self.reader.topology
        state = reader.state(frame, unwrap=True)
        atoms = state.to_ase()
        atoms.positions[:] = _positions(frame, self.unwrap)
        # A box with a volume: open axes span the atoms (their xlo xhi lines are set below).
        origin, lengths, tilt = enclosing_cell(atoms.positions, frame.box, reader.pbc, frame.tilt)
        atoms.set_cell(cell_matrix(lengths, tilt))
        masses = atoms.get_masses()
        atoms.set_chemical_symbols([self._STAND_INS[t] for t in reader.types])
        atoms.set_masses(masses)
        partners = [[] for _ in range(reader.n_atoms)]
        for (i, j), t in zip(topology.bonds.tolist(), topology.bond_types.tolist(), strict=True):
            partners[i].append(f"{j}({t + 1})")
        atoms.arrays["bonds"] = np.array([",".join(p) or "_" for p in partners], dtype=object)
        atoms.arrays["mol-id"] = _molecule_ids(reader)
        stand_ins = list(self._STAND_INS[: len(reader.type_names)])
        with open(self.path, "w") as handle:
            write_lammps_data(
                handle,
                atoms,
                specorder=stand_ins,
                masses=True,
                velocities=False,
                atom_style="full",
                units=self._ase_units,
                bonds=topology.n_bonds > 0,
            )
        lines = self.path.read_text().splitlines(keepends=True)
        # Velocities written here: ASE's writer divides momenta by masses, which is not
        # always the velocity back to the last bit.
        factor = lammps_units(1.0, "velocity", "ASE", self._ase_units)
        lines.append("\nVelocities\n\n")
        lines += [
            f"{i + 1:>6} {x:23.17g} {y:23.17g} {z:23.17g}\n"
            for i, (x, y, z) in enumerate((state.velocities * factor).tolist())
        ]
        units = "lj" if reader.units.name == "lj" else "metal"
        types = " ".join(f"{t + 1}={name}" for t, name in enumerate(reader.type_names))
        bond_types = " ".join(f"{t + 1}={n}" for t, n in enumerate(topology.bond_type_names))
        angle_types = " ".join(f"{t + 1}={n}" for t, n in enumerate(topology.angle_type_names))
        lines[0] = (
            f"LAMMPS data file written by leapmd {__version__} (units {units}; step "
            f"{frame.step}; atom types {types}"
            + (f"; bond types {bond_types}" if bond_types else "")
            + (f"; angle types {angle_types}" if angle_types else "")
            + ")\n"
        )
        for index, line in enumerate(lines[:40]):  # open axes: the bounds of the atoms
            words = line.split()
            if len(words) == 4 and words[2] in ("xlo", "ylo", "zlo"):
                axis = "xyz".index(words[2][0])
                if reader.pbc[axis]:
                    continue
                low, high = origin[axis], origin[axis] + lengths[axis]
                lines[index] = f"{low:.17g} {high:.17g}  {words[2]} {words[3]}\n"
        if topology.n_angles:
            _add_angles(lines, topology)
        in_masses = False
        for index, line in enumerate(lines):  # the Masses comments: our names, not stand-ins
            if line.strip() == "Masses":
                in_masses = True
            elif in_masses and line.strip() and line.strip()[0].isalpha():
                break
            elif in_masses and "#" in line:
                head, symbol = line.split("#", 1)
                name = reader.type_names[stand_ins.index(symbol.strip())]
                lines[index] = f"{head}# {name}\n"
        self.path.write_text("".join(lines))


def _add_angles(lines: list[str], topology: Topology) -> None:
    """Add the angle counts to a data file's header and its ``Angles`` section at the end."""
    header = [
        index
        for index, line in enumerate(lines)
        if line.split()[1:] in (["atom", "types"], ["bond", "types"])
    ]
    counts = [f"{topology.n_angles} angles\n", f"{len(topology.angle_type_names)} angle types\n"]
    lines[header[-1] + 1 : header[-1] + 1] = counts
    if lines[-1].strip():
        lines.append("\n")
    lines += ["\nAngles\n\n"]
    lines += [
        f"{number} {t + 1} {i + 1} {j + 1} {k + 1}\n"
        for number, ((i, j, k), t) in enumerate(
            zip(topology.angles.tolist(), topology.angle_types.tolist(), strict=True), start=1
        )
    ]


class _LammpsDumpWriter(_Writer):
    """A LAMMPS text dump (``.lammpstrj``), written here: MDAnalysis and ASE only read them.

    Columns ``id type mol x y z ix iy iz`` (and ``vx vy vz``, ``fx fy fz``
    when stored); LAMMPS ``metal`` units (Angstrom, ps, eV/Angstrom) for
    metal runs, reduced values for ``lj`` runs. Boundaries are ``pp`` or
    ``ff`` per axis.
    """

    def __init__(
        self, path: Path, reader: TrajectoryReader, frames: range, unwrap: bool, kind: str
    ) -> None:
        self.reader, self.unwrap = reader, unwrap
        self.handle = open(path, "w")  # noqa: SIM115 (closed in close())
        self.molecules = _molecule_ids(reader)
        self.ids = np.arange(1, reader.n_atoms + 1)
        metal = reader.units.name != "lj"
        self.velocity_factor = reader.units.h5md["velocity"][1] if metal else 1.0
        boundary = ["pp" if p else "ff" for p in reader.pbc]
        self.bounds = " ".join(boundary)
        columns = ["id", "type", "mol", "x", "y", "z", "ix", "iy", "iz"]
        if reader.has_velocities:
            columns += ["vx", "vy", "vz"]
        if reader.has_forces:
            columns += ["fx", "fy", "fz"]
        self.columns = " ".join(columns)

    def write(self, frame: Frame) -> None:
        out = self.handle
        out.write(f"ITEM: TIMESTEP\n{frame.step}\n")
        out.write(f"ITEM: NUMBER OF ATOMS\n{self.reader.n_atoms}\n")
        positions = _positions(frame, self.unwrap)
        (ox, oy, oz), (lx, ly, lz), (xy, xz, yz) = enclosing_cell(
            positions, frame.box, self.reader.pbc, frame.tilt
        )
        if xy == 0.0 and xz == 0.0 and yz == 0.0:
            out.write(f"ITEM: BOX BOUNDS {self.bounds}\n")
            for low, length in ((ox, lx), (oy, ly), (oz, lz)):
                out.write(f"{low:.17g} {low + length:.17g}\n")
        else:  # LAMMPS's triclinic dump header: bounds of the tilted box, then each tilt
            low = min(0.0, xy, xz, xy + xz)
            high = max(0.0, xy, xz, xy + xz)
            out.write(f"ITEM: BOX BOUNDS xy xz yz {self.bounds}\n")
            out.write(f"{ox + low:.17g} {ox + lx + high:.17g} {xy:.17g}\n")
            out.write(f"{oy + min(0.0, yz):.17g} {oy + ly + max(0.0, yz):.17g} {xz:.17g}\n")
            out.write(f"{oz:.17g} {oz + lz:.17g} {yz:.17g}\n")
        out.write(f"ITEM: ATOMS {self.columns}\n")
        parts = [
            self.ids[:, None],
            (self.reader.types + 1)[:, None],
            self.molecules[:, None],
            positions,
            _images(frame, self.unwrap),
        ]
        formats = ["%d", "%d", "%d", "%.10g", "%.10g", "%.10g", "%d", "%d", "%d"]
        if self.reader.has_velocities:
            parts.append(frame.velocities * self.velocity_factor)
            formats += ["%.10g"] * 3
        if self.reader.has_forces:
            parts.append(frame.forces)
            formats += ["%.10g"] * 3
        table = np.hstack([np.asarray(p, dtype=np.float64) for p in parts])
        np.savetxt(out, table, fmt=" ".join(formats))

    def close(self) -> None:
        self.handle.close()


class _GSDWriter(_Writer):
    """GSD (HOOMD-blue's format) through the ``gsd`` package: types, masses, bonds, angles,
    box.

    GSD boxes are centred on the origin: positions are shifted by half the
    box. GSD holds single-precision positions and has no units: the values
    are Angstrom, ps and amu for metal runs, reduced for ``lj`` runs.
    """

    def __init__(
        self, path: Path, reader: TrajectoryReader, frames: range, unwrap: bool, kind: str
    ) -> None:
        import gsd.hoomd  # the gsd package: loaded on first use

        self.reader, self.unwrap = reader, unwrap
        self.hoomd = gsd.hoomd
        self.handle = gsd.hoomd.open(str(path), mode="w")
        metal = reader.units.name != "lj"
        self.velocity_factor = reader.units.h5md["velocity"][1] if metal else 1.0

    def write(self, frame: Frame) -> None:
        reader = self.reader
        snapshot = self.hoomd.Frame()
        snapshot.configuration.step = frame.step
        positions = frame.positions if not self.unwrap else frame.unwrapped()
        origin, lengths, tilt = enclosing_cell(positions, frame.box, reader.pbc, frame.tilt)
        lx, ly, lz = lengths
        xy, xz, yz = tilt  # HOOMD's tilt factors are these over Ly, Lz, Lz
        snapshot.configuration.box = [lx, ly, lz, xy / ly, xz / lz, yz / lz]
        snapshot.configuration.dimensions = 3
        snapshot.particles.N = reader.n_atoms
        snapshot.particles.types = list(reader.type_names)
        snapshot.particles.typeid = reader.types.astype(np.uint32)
        snapshot.particles.mass = reader.masses.astype(np.float32)
        # HOOMD boxes are centred on the origin
        centre = origin + 0.5 * cell_matrix(lengths, tilt).sum(axis=0)
        snapshot.particles.position = (positions - centre).astype(np.float32)
        snapshot.particles.image = _images(frame, self.unwrap).astype(np.int32)
        if frame.velocities is not None:
            snapshot.particles.velocity = (frame.velocities * self.velocity_factor).astype(
                np.float32
            )
        topology = reader.topology
        if topology.n_bonds:
            snapshot.bonds.N = topology.n_bonds
            snapshot.bonds.types = list(topology.bond_type_names)
            snapshot.bonds.typeid = topology.bond_types.astype(np.uint32)
            snapshot.bonds.group = topology.bonds.astype(np.uint32)
        if topology.n_angles:
            snapshot.angles.N = topology.n_angles
            snapshot.angles.types = list(topology.angle_type_names)
            snapshot.angles.typeid = topology.angle_types.astype(np.uint32)
            snapshot.angles.group = topology.angles.astype(np.uint32)
        self.handle.append(snapshot)

    def close(self) -> None:
        self.handle.close()


WRITERS = {
    "xtc": _MDAnalysisWriter,
    "trr": _MDAnalysisWriter,
    "dcd": _MDAnalysisWriter,
    "nc": _MDAnalysisWriter,
    "xyz": _ASEWriter,
    "extxyz": _ASEWriter,
    "traj": _ASEWriter,
    "data": _LammpsDataWriter,
    "lammpstrj": _LammpsDumpWriter,
    "gsd": _GSDWriter,
}


__all__ = ["FORMATS", "convert", "molecules", "output_format"]
