"""Starting structures from files: anything ``ase.io`` reads, LAMMPS data, GSD and our H5MD.

:func:`read_structure` returns a :class:`md.state.State` in engine units and
the file's bonds and angles as a :class:`md.topology.Topology` (empty where
the format holds none). ``[system] structure`` in configs comes here.

- LAMMPS data files (``.data``, ``.lmp``; ``format = "lammps-data"``) are
  parsed by ASE's reader in double precision (the atom style named in the
  ``Atoms # style`` header, else guessed from the column count): atoms,
  masses, velocities, bonds and bond types, angles and angle types, the box
  from ``xlo xhi`` ... (positions are shifted so the box starts at the
  origin). Type names come from the ``Masses`` comments (``1 39.948 # Ar``)
  when every type has one, else the type numbers; bond and angle type names
  from a leapmd title line. Units are
  LAMMPS ``metal`` for metal runs (velocities in Angstrom/ps) and the
  reduced values for ``lj`` runs. Tilted (triclinic) boxes are read as they are.
- GSD files (``.gsd``; ``format = "gsd"``) through the ``gsd`` package:
  the last frame (or ``frame``), types, masses, velocities, images,
  bonds and angles; the origin-centred GSD box is shifted to start at the origin.
- H5MD trajectories of ours (``.h5``, ``.h5md``): the last frame and the
  stored bonds and angles.
- Anything else goes to ``ase.io.read`` (the last frame of the file).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from md.box import cell_matrix
from md.errors import TrajectoryError
from md.state import State
from md.topology import Topology
from md.trajectory import TrajectoryReader
from md.units import UnitSystem, get_units

LAMMPS_DATA = ("lammps-data", "data", "lmp")
GSD = ("gsd",)
H5MD = ("h5", "h5md")


def structure_kind(path, format: str | None = None) -> str:
    """Return "lammps-data", "gsd", "h5md" or "ase" for a structure file."""
    key = (format or Path(path).suffix.lstrip(".")).lower()
    if key in LAMMPS_DATA:
        return "lammps-data"
    if key in GSD:
        return "gsd"
    if key in H5MD:
        return "h5md"
    return "ase"


def read_structure(
    path, format: str | None = None, units: str | UnitSystem = "metal", mass=None
) -> tuple[State, Topology]:
    """Read a starting structure; return ``(state, topology)`` in engine units.

    Parameters
    ----------
    mass : float or dict, optional
        Masses for a LAMMPS data file without a ``Masses`` section: one for
        every atom, or one per type name (the config's ``[system] mass``,
        which replaces the file's masses anyway). Without it such a file is
        refused.

    Raises
    ------
    ValueError
        Naming the file and what is wrong with it (unreadable, a tilted box,
        atoms without masses, bonds to missing atoms, ...).
    """
    path = Path(path)
    units = get_units(units)
    kind = structure_kind(path, format)
    if kind == "lammps-data":
        state, topology = _read_lammps_data(path, units, mass)
    elif kind in ("gsd", "h5md"):
        state, topology = {"gsd": _read_gsd, "h5md": _read_h5md}[kind](path, units)
    else:
        state, topology = _read_ase(path, format), Topology.empty()
    topology.check(state.n_atoms, where=f"{path}")
    return state, topology


# ---------------------------------------------------------------------- ase.io
def _read_ase(path: Path, format: str | None) -> State:
    import ase.io  # ASE's file readers: loaded only for structure files

    _check_xyz_count(path, format)
    try:
        atoms = ase.io.read(path, format=format)
    except Exception as error:  # ase.io raises many types for unreadable files
        how = f" as format {format!r}" if format else ""
        reason = _reason(error)
        raise ValueError(f"cannot read {path}{how}: ASE's reader failed ({reason})") from None
    if isinstance(atoms, list):
        atoms = atoms[-1]
    try:
        return State.from_ase(atoms)
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None


def _reason(error: BaseException) -> str:
    """An exception of ASE's readers as text that says what it is: a bare KeyError(64)
    reads "64" on its own."""
    text = str(error)
    if isinstance(error, LookupError) or not text:
        return f"{type(error).__name__} {text}".strip()
    return text


def _check_xyz_count(path: Path, format: str | None) -> None:
    """Refuse an (ext)xyz file whose atom-count lines exceed what the file can hold.

    ASE's extxyz reader trusts every frame's count line and, given an absurd one,
    loops for a very long time; every atom needs a line of at least 8 bytes. The
    frames are walked as ASE walks them (a count, a comment, the atoms) up to a
    blank line or the end.
    """
    kind = (format or Path(path).suffix.lstrip(".")).lower()
    if kind not in ("xyz", "extxyz"):
        return
    try:
        size = Path(path).stat().st_size
        with open(path, "rb") as handle:
            while True:
                count = handle.readline(64).strip()
                if not count.isdigit():  # the end, a blank line, or not a count: ASE's to say
                    return
                if int(count) * 8 > size - handle.tell():
                    raise ValueError(
                        f"{path}: the count line at byte {handle.tell() - len(count) - 1} "
                        f"declares {int(count)} atoms, more than a file of {size} bytes can "
                        "hold"
                    )
                for _ in range(int(count) + 1):  # the comment line and the atoms
                    if not handle.readline():
                        return
    except OSError as error:
        raise ValueError(f"cannot read {path} ({error})") from None


# ---------------------------------------------------------------------- LAMMPS data
def _lammps_header(path: Path) -> dict:
    """Box bounds, tilt, Masses comments and a leapmd title from a data file's text."""
    header = {
        "lo": np.zeros(3),
        "hi": np.zeros(3),
        "tilt": None,
        "names": {},
        "bond_names": {},
        "angle_names": {},
        "style": None,
        "columns": 0,
        "masses": False,
        "atoms": 0,
    }
    axis = {"x": 0, "y": 1, "z": 2}
    with open(path, errors="replace") as handle:
        title = handle.readline()
        section = None
        for line in handle:
            text = line.split("#", 1)[0].strip()
            words = text.split()
            if len(words) >= 4 and words[2].endswith("lo") and words[3].endswith("hi"):
                k = axis.get(words[2][0])
                if k is not None:
                    header["lo"][k], header["hi"][k] = float(words[0]), float(words[1])
                continue
            if len(words) == 2 and words[1] == "atoms" and section is None:
                header["atoms"] = int(words[0])
                continue
            if len(words) >= 6 and words[3:6] == ["xy", "xz", "yz"]:
                header["tilt"] = [float(w) for w in words[:3]]
                continue
            if text and text[0].isalpha():
                section = text.split()[0]
                header["masses"] |= section == "Masses"
                if section == "Atoms":
                    hint = line.split("#", 1)[1].split() if "#" in line else []
                    header["style"] = hint[0] if hint else None
                continue
            if section == "Atoms" and words:
                header["columns"] = len(words)
                break
            if section == "Masses" and "#" in line and words:
                header["names"][int(words[0])] = line.split("#", 1)[1].strip()
    match = re.search(r"atom types ([^;)]*)", title)
    if match and "leapmd" in title:
        for item in match.group(1).split():
            number, _, name = item.partition("=")
            header["names"].setdefault(int(number), name)
    for kind in ("bond", "angle"):
        match = re.search(rf"{kind} types ([^;)]*)", title)
        if match and "leapmd" in title:
            for item in match.group(1).split():
                number, _, name = item.partition("=")
                header[f"{kind}_names"][int(number)] = name
    return header


#: LAMMPS atom styles by the column count of an Atoms line (without image flags),
#: for files whose Atoms header names none; 6 columns could also be "charge".
_STYLE_BY_COLUMNS = {5: "atomic", 6: "bond", 7: "full"}


def _read_lammps_data(path: Path, units: UnitSystem, mass=None) -> tuple[State, Topology]:
    import ase.io  # ASE's LAMMPS data reader: loaded only for data files

    try:
        header = _lammps_header(path)
    except (OSError, ValueError) as error:
        raise ValueError(f"cannot read {path} as a LAMMPS data file ({error})") from None
    size = path.stat().st_size
    if header["atoms"] * 8 > size:  # ASE's reader would allocate for them all first
        raise ValueError(
            f"{path}: the header declares {header['atoms']} atoms, more than a file of {size} "
            "bytes can hold"
        )
    tilt = np.zeros(3) if header["tilt"] is None else np.asarray(header["tilt"], float)
    if not header["masses"] and mass is None:
        raise ValueError(
            f"{path}: no Masses section; add one (masses per atom type) or give the masses "
            "([system] mass)"
        )
    box = header["hi"] - header["lo"]
    if not np.all(box > 0):
        raise ValueError(f"{path}: no box (xlo xhi, ylo yhi, zlo zhi lines) or an empty one")
    columns = header["columns"]
    style = header["style"] or _STYLE_BY_COLUMNS.get(columns - 3 if columns > 7 else columns)
    if style is None:
        raise ValueError(
            f"{path}: cannot tell the atom style from {columns} columns; name it in the "
            "Atoms header, e.g. 'Atoms # full'"
        )
    try:
        # Reduced (lj) values are taken as written: ASE's units to its own is the identity.
        atoms = ase.io.read(
            path,
            format="lammps-data",
            atom_style=style,
            units="ASE" if units.name == "lj" else "metal",
        )
    except Exception as error:  # ASE raises many types for unreadable files
        hint = ""
        if isinstance(error, KeyError):  # ASE looks ids and types up in dicts
            hint = (
                ": an id the file refers to is not defined (an atom id in Bonds, Angles or "
                "Velocities missing from Atoms, or an atom type missing from Masses)"
            )
        raise ValueError(
            f"cannot read {path} as a LAMMPS data file with atom_style {style}: ASE's reader "
            f"failed ({_reason(error)}){hint}"
        ) from None
    numbers = np.asarray(atoms.arrays["type"], dtype=np.int64)
    distinct = np.unique(numbers)
    names = header["names"]
    if all(int(t) in names for t in distinct) and len({names[int(t)] for t in distinct}) == len(
        distinct
    ):
        type_names = tuple(names[int(t)] for t in distinct)
    else:
        type_names = tuple(str(t) for t in distinct)
    types = np.searchsorted(distinct, numbers)
    masses = atoms.get_masses()
    if not header["masses"]:  # ASE guessed them: take the ones given
        masses = _given_masses(path, mass, types, type_names)
    with np.errstate(divide="ignore", invalid="ignore"):  # a zero mass: refused by State
        velocities = atoms.get_velocities()  # ASE converted metal (A/ps) to its own units
    try:
        state = State(
            positions=atoms.get_positions() - header["lo"],
            velocities=velocities,
            masses=masses,
            box=box,
            pbc=True,
            types=types,
            type_names=type_names,
            tilt=tilt,  # LAMMPS's restricted triclinic box is the engine's convention
        )
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None
    pairs, bond_numbers = [], []
    for i, listed in enumerate(atoms.arrays.get("bonds", ())):
        if listed == "_":
            continue
        for entry in listed.split(","):
            partner, _, kind = entry.partition("(")
            pairs.append((i, int(partner)))
            bond_numbers.append(int(kind.rstrip(")")))
    topology = Topology.empty()
    if pairs:
        kinds = np.unique(bond_numbers)
        bond_names = [header["bond_names"].get(int(k), f"bond{int(k)}") for k in kinds]
        topology = Topology.from_bonds(pairs, np.searchsorted(kinds, bond_numbers), bond_names)
    triples, angle_numbers = [], []
    for j, listed in enumerate(atoms.arrays.get("angles", ())):  # ASE: "i-k(type)" at vertex j
        if listed == "_":
            continue
        for entry in listed.split(","):
            ends, _, kind = entry.partition("(")
            i, _, k = ends.partition("-")
            triples.append((int(i), j, int(k)))
            angle_numbers.append(int(kind.rstrip(")")))
    if triples:
        kinds = np.unique(angle_numbers)
        names = [header["angle_names"].get(int(k), f"angle{int(k)}") for k in kinds]
        try:
            topology = topology.with_angles(triples, np.searchsorted(kinds, angle_numbers), names)
        except ValueError as error:
            raise ValueError(f"{path}: {error}") from None
    return state, topology


def _given_masses(path: Path, mass, types, type_names) -> np.ndarray:
    """Per-atom masses from ``mass`` (one number, or one per type name) for a file without."""
    if not isinstance(mass, dict):
        return np.full(len(types), float(mass))
    missing = [name for name in type_names if name not in mass]
    if missing:
        raise ValueError(
            f"{path}: no Masses section, and the masses given name no mass for type(s) "
            f"{', '.join(missing)} (the file's types: {', '.join(type_names)})"
        )
    return np.array([float(mass[type_names[t]]) for t in types])


# ---------------------------------------------------------------------- GSD
def _read_gsd(path: Path, units: UnitSystem, frame: int = -1) -> tuple[State, Topology]:
    import gsd.hoomd  # the gsd package: loaded only for GSD files

    try:
        with gsd.hoomd.open(str(path), mode="r") as trajectory:
            if len(trajectory) == 0:
                raise ValueError("it holds no frames")
            snapshot = trajectory[frame]
    except Exception as error:  # gsd raises many types for unreadable files
        raise ValueError(f"cannot read {path} as a GSD file ({error})") from None
    try:
        return _gsd_structure(snapshot, units)
    except ValueError as error:  # State and Topology name what is wrong, not the file
        raise ValueError(f"{path}: {error}") from None


def _gsd_structure(snapshot, units: UnitSystem) -> tuple[State, Topology]:
    box = np.asarray(snapshot.configuration.box, dtype=np.float64)
    lengths = box[:3]
    # HOOMD's tilt factors are dimensionless: xy Ly, xz Lz and yz Lz are the engine's.
    tilt = box[3:] * lengths[[1, 2, 2]]
    cell = cell_matrix(np.where(lengths > 0, lengths, 0.0), tilt)
    particles = snapshot.particles
    n = int(particles.N)
    centre = 0.5 * cell.sum(axis=0)  # HOOMD boxes are centred on the origin
    positions = np.asarray(particles.position, dtype=np.float64).reshape(n, 3) + centre
    if particles.image is not None:
        positions = positions + np.asarray(particles.image).reshape(n, 3) @ cell
    velocities = None
    if particles.velocity is not None:
        factor = units.h5md["velocity"][1] if "velocity" in units.h5md else 1.0
        velocities = np.asarray(particles.velocity, dtype=np.float64).reshape(n, 3) / factor
    types = np.asarray(particles.typeid, dtype=np.int64) if particles.typeid is not None else None
    pbc = [True, True, int(snapshot.configuration.dimensions or 3) == 3]
    state = State(
        positions=positions,
        velocities=velocities,
        masses=np.asarray(particles.mass, dtype=np.float64) if particles.mass is not None else 1,
        box=np.where(lengths > 0, lengths, 1.0),
        pbc=pbc,
        types=types,
        type_names=tuple(particles.types) if particles.types else None,
        tilt=tilt,
    )
    topology = Topology.empty()
    bonds = snapshot.bonds
    if bonds.N:
        topology = Topology.from_bonds(
            np.asarray(bonds.group, dtype=np.int64).reshape(-1, 2),
            np.asarray(bonds.typeid, dtype=np.int64),
            list(bonds.types) if bonds.types else None,
        )
    angles = snapshot.angles
    if angles.N:
        names = list(angles.types) if angles.types else None
        if names is not None:  # one namespace with the bond types (H5MD connectivity)
            names = [f"angle_{n}" if n in topology.bond_type_names else n for n in names]
        topology = topology.with_angles(
            np.asarray(angles.group, dtype=np.int64).reshape(-1, 3),
            np.asarray(angles.typeid, dtype=np.int64),
            names,
        )
    return state, topology


# ---------------------------------------------------------------------- H5MD
def _read_h5md(path: Path, units: UnitSystem) -> tuple[State, Topology]:
    try:
        with TrajectoryReader(path) as reader:
            if reader.units.name != units.name:
                raise ValueError(
                    f"{path} is in {reader.units.name} units, the config in {units.name}"
                )
            state = reader.state(reader.frame(-1))
            topology = reader.topology
    except TrajectoryError as error:
        raise ValueError(str(error)) from None
    except ValueError as error:  # State's checks of the frame name the atom, not the file
        raise ValueError(f"{path}: {error}") from None
    state.step, state.time = 0, 0.0  # a starting structure: the new run counts from zero
    return state, topology


__all__ = ["read_structure", "structure_kind"]
