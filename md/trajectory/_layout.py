"""What the H5MD writer and readers share: the observables and their units, attribute
text, the connectivity's reading, the box edges' split, unwrapping, complete frames.
Re-exported by :mod:`md.trajectory` where public; private to the package otherwise.
"""

from __future__ import annotations

import json

import h5py
import numpy as np
from numpy.typing import NDArray

from md.errors import TrajectoryError
from md.topology import Topology

H5MD_VERSION = (1, 1)


OBSERVABLES = (
    "potential_energy",
    "kinetic_energy",
    "total_energy",
    "temperature",
    "pressure",
    "volume",
    "density",
    "pxx",
    "pyy",
    "pzz",
    "pxy",
    "pxz",
    "pyz",
    "conserved_energy",
)


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
        what = (
            f"names an atom outside 0..{n_atoms - 1}" if outside[first] else "names one atom twice"
        )
        raise TrajectoryError(
            f"{f.filename}: /connectivity/{name}: {kind} {first} "
            f"{tuple(listed[first].tolist())} {what} ({bad.size} such {kind}(s)); the file's "
            "connectivity is damaged"
        )


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


def _complete_frames(f: h5py.File) -> int:
    """Frames that every per-frame dataset of the file holds."""
    group = f["particles/trajectory"]
    lengths = [
        len(group["position/step"]),
        len(group["position/time"]),
        len(group["position/value"]),
        len(group["box/edges/value"]),
    ]
    for name in ("image", "velocity", "force"):
        if name in group:
            lengths.append(len(group[f"{name}/value"]))
    for element in f.get("observables", {}).values():
        lengths.append(len(element["value"]))
    return min(lengths)


def _is_checksum_error(error: BaseException) -> bool:
    text = str(error).lower()
    return any(sign in text for sign in ("checksum", "fletcher", "filter returned failure"))


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
