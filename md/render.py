"""Pictures of a trajectory frame without writing code: matplotlib, or POV-Ray where installed.

:func:`render` draws one frame of an H5MD trajectory: atoms as spheres
coloured by type, bonds as lines, the box edges (along open axes the stored
edge widened to the atoms' extent, or their bounding box where the edge is
zero: :func:`md.box.enclosing_cell`). Positions are drawn wrapped into the
box; a bond that crosses a periodic boundary is drawn from each of its
atoms towards the other's nearest image, so it pokes out
of the box on both sides instead of spanning it. ``engine="povray"`` writes
the same scene through ASE's POV-Ray writer and renders it with the
``povray`` program (bonds and box included), for publication pictures.
"""

from __future__ import annotations

import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from md._files import atomic_path, exclusive_claim, output_target, remove_stale_temporaries
from md.box import cell_matrix, enclosing_cell, minimum_image
from md.trajectory import Frame, TrajectoryReader

#: Engines :func:`render` offers.
ENGINES = ("matplotlib", "povray")
#: Largest picture edge in pixels.
MAX_PIXELS = 8000


def render(
    trajectory,
    output,
    frame: int = -1,
    engine: str = "matplotlib",
    size: int = 800,
    overwrite: bool = False,
    elevation: float = 20.0,
    azimuth: float = -60.0,
) -> Path:
    """Draw frame ``frame`` of a trajectory into the PNG file ``output``.

    Parameters
    ----------
    trajectory : path
        H5MD file written by leapmd.
    output : path
        PNG file to write (replaced only with ``overwrite=True``).
    frame : int
        Frame index; negative counts from the end (-1: the last frame).
    engine : {"matplotlib", "povray"}
        The renderer; POV-Ray needs the ``povray`` program.
    size : int
        Picture edge [pixels].
    elevation, azimuth : float
        View direction [degrees] (matplotlib's 3-D view angles).

    Returns
    -------
    Path
        The file written.

    Raises
    ------
    ValueError
        Unknown engine, a size out of range, POV-Ray not installed, or an
        output that is not a .png file.
    IndexError
        A frame outside the file's frames.
    FileExistsError
        ``output`` exists and ``overwrite`` is not given, or another run is
        writing it (its claim, see :func:`md._files.exclusive_claim`).
    TrajectoryError
        The input is not an H5MD trajectory of ours.

    Notes
    -----
    A symbolic link is written through into its target; a special file
    (FIFO, device node) is refused with ValueError, never replaced.
    """
    output = Path(output)
    if engine not in ENGINES:
        raise ValueError(f"unknown engine {engine!r}; choose one of {', '.join(ENGINES)}")
    if isinstance(size, bool) or not isinstance(size, int) or not 16 <= size <= MAX_PIXELS:
        raise ValueError(f"size must be an integer number of pixels in 16..{MAX_PIXELS}")
    if output.suffix.lower() != ".png":
        raise ValueError(f"{output}: pictures are written as PNG; name the output *.png")
    output = output_target(output)  # a symlink's target; a special file is refused
    if output.exists() and not overwrite:
        raise FileExistsError(f"{output} already exists; choose another name or pass --overwrite")
    if engine == "povray" and shutil.which("povray") is None:
        raise ValueError(
            "POV-Ray is not installed (no povray program on PATH); install it (apt install "
            "povray) or use the default matplotlib engine"
        )
    with TrajectoryReader(trajectory) as reader:
        if isinstance(frame, bool) or not isinstance(frame, int):
            raise ValueError(f"frame must be an integer, got {frame!r}")
        n = reader.n_frames
        if not -n <= frame < n:
            raise IndexError(
                f"{reader.path} holds {n} frames (0 to {n - 1}); frame {frame} is out of range"
            )
        snapshot = reader.frame(frame)
        with exclusive_claim(output):
            remove_stale_temporaries(output)  # an interrupted render's, under the claim
            with atomic_path(output, exclusive=not overwrite) as temporary:
                if engine == "matplotlib":
                    _draw_matplotlib(reader, snapshot, temporary, size, elevation, azimuth)
                else:
                    _draw_povray(reader, snapshot, temporary, size, elevation, azimuth)
    return output


def bond_segments(reader: TrajectoryReader, snapshot: Frame) -> np.ndarray:
    """Return (2 B, 2, 3) half-bond segments: each atom to the midpoint towards its partner.

    The partner is taken at its nearest image, so bonds across a periodic
    boundary are drawn as two halves, each starting at its own atom.
    """
    bonds = reader.topology.bonds
    if len(bonds) == 0:
        return np.zeros((0, 2, 3))
    r = snapshot.positions
    d = minimum_image(r[bonds[:, 1]] - r[bonds[:, 0]], snapshot.box, reader.pbc, snapshot.tilt)
    first = np.stack([r[bonds[:, 0]], r[bonds[:, 0]] + 0.5 * d], axis=1)
    second = np.stack([r[bonds[:, 1]], r[bonds[:, 1]] - 0.5 * d], axis=1)
    return np.concatenate([first, second])


def box_edges(box, tilt=None, origin=None) -> np.ndarray:
    """Return the 12 edges of the cell (edge lengths ``box``, tilt factors ``tilt``, corner
    ``origin``, default 0) as (12, 2, 3) segments; a tilted cell is drawn as its
    parallelepiped."""
    fractional = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], float)
    corners = fractional @ cell_matrix(np.asarray(box, dtype=float), tilt)
    if origin is not None:
        corners += np.asarray(origin, dtype=float)
    edges = [
        (a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1
    ]  # corners that differ in one coordinate
    return np.array([[corners[a], corners[b]] for a, b in edges])


def _atom_radius(reader: TrajectoryReader, box) -> float:
    volume = float(np.prod(box))
    return 0.5 * (volume / max(reader.n_atoms, 1)) ** (1.0 / 3.0)


def _draw_matplotlib(reader, snapshot, path: Path, size: int, elevation, azimuth) -> None:
    from matplotlib.figure import Figure  # heavy: matplotlib only when drawing
    from mpl_toolkits.mplot3d.art3d import Line3DCollection  # with matplotlib

    dpi = 100
    fig = Figure(figsize=(size / dpi, size / dpi), dpi=dpi)
    ax = fig.add_subplot(projection="3d")
    origin, box, tilt = enclosing_cell(snapshot.positions, snapshot.box, reader.pbc, snapshot.tilt)
    colours = [f"C{t % 10}" for t in range(len(reader.type_names))]
    # Marker area [points^2]: atoms about half their spacing across, at the view's scale
    # (the box spans roughly half the picture).
    points_per_length = 0.5 * size / float(np.max(box)) * 72 / dpi
    area = (0.5 * 2 * _atom_radius(reader, box) * points_per_length) ** 2
    for t, name in enumerate(reader.type_names):
        mine = reader.types == t
        if np.any(mine):
            r = snapshot.positions[mine]
            ax.scatter(
                r[:, 0],
                r[:, 1],
                r[:, 2],
                s=area,
                c=colours[t],
                label=name,
                depthshade=True,
                edgecolors="none",
            )
    segments = bond_segments(reader, snapshot)
    if len(segments):
        ax.add_collection3d(Line3DCollection(segments, colors="0.3", linewidths=0.8))
    edges = box_edges(box, tilt, origin)
    ax.add_collection3d(Line3DCollection(edges, colors="k", linewidths=0.8))
    low, high = edges.min(axis=(0, 1)), edges.max(axis=(0, 1))
    ax.set_xlim(low[0], high[0])
    ax.set_ylim(low[1], high[1])
    ax.set_zlim(low[2], high[2])
    ax.set_box_aspect(high - low)
    ax.view_init(elev=elevation, azim=azimuth)
    ax.set_axis_off()
    ax.legend(loc="upper left", fontsize="small", markerscale=float(np.sqrt(40 / max(area, 1e-6))))
    ax.set_title(
        f"{reader.path.name}: frame {snapshot.index}, step {snapshot.step}"
        + (f", {reader.topology.n_bonds} bonds" if reader.topology.n_bonds else ""),
        fontsize="small",
    )
    fig.savefig(path, format="png", dpi=dpi)


def _draw_povray(reader, snapshot, path: Path, size: int, elevation, azimuth) -> None:
    from ase.io import write  # ASE's POV-Ray writer: loaded on first use
    from matplotlib.colors import to_rgb  # the type colours of the matplotlib engine

    atoms = reader.state(snapshot, unwrap=False).to_ase()
    origin, box, tilt = enclosing_cell(snapshot.positions, snapshot.box, reader.pbc, snapshot.tilt)
    atoms.set_cell(cell_matrix(box, tilt))  # drawn from the origin: move the atoms with it
    atoms.positions -= origin
    radius = _atom_radius(reader, box)
    bonds = reader.topology.bonds
    r = snapshot.positions
    # Each bond to its partner's nearest image: ASE takes the partner's cell offset,
    # in cell vectors (the nearest image's shift solved through the cell matrix).
    d = r[bonds[:, 1]] - r[bonds[:, 0]]
    nearest = minimum_image(d, snapshot.box, reader.pbc, snapshot.tilt)
    cell = cell_matrix(np.where(reader.pbc, snapshot.box, 1.0), snapshot.tilt)  # open: any
    offsets = np.rint(np.linalg.solve(cell.T, (nearest - d).T).T) * reader.pbc
    bondatoms = [
        (int(i), int(j), tuple(int(k) for k in offset))
        for (i, j), offset in zip(bonds, offsets, strict=True)
    ]
    with tempfile.TemporaryDirectory() as folder:
        scene = Path(folder) / "scene.pov"
        settings = {
            "canvas_width": size,
            "bondatoms": bondatoms,
            "transparent": False,
            "bondlinewidth": 0.15 * radius,
            "celllinewidth": 0.05 * radius,
        }
        palette = [to_rgb(f"C{t % 10}") for t in range(len(reader.type_names))]
        write(
            scene,
            atoms,
            format="pov",
            radii=[0.6 * radius] * len(atoms),
            rotation=f"{-elevation}x,{azimuth}y",
            show_unit_cell=2,
            colors=[palette[t] for t in reader.types],
            povray_settings=settings,
        )
        # The .ini names the scene relative to its folder: render there.
        done = subprocess.run(
            ["povray", scene.with_suffix(".ini").name], cwd=folder, capture_output=True, text=True
        )
        if done.returncode != 0:
            tail = done.stderr.strip().splitlines()[-3:]
            raise ValueError(f"POV-Ray failed (exit {done.returncode}): {' / '.join(tail)}")
        shutil.copyfile(scene.with_suffix(".png"), path)


__all__ = ["ENGINES", "bond_segments", "box_edges", "render"]
