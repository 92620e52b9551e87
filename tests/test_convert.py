"""Bonds in H5MD, md convert, starting structures from LAMMPS data and GSD, md render, md.show.

Round trips: our H5MD file -> each format -> read back with the library that
reads that format (MDAnalysis, ase.io, gsd) gives the same positions (to the
format's precision), box, types, and bonds where the format holds them.
"""

from __future__ import annotations

import itertools
import shutil
import sys
import tracemalloc
import types as pytypes

import ase.io
import gsd.hoomd
import h5py
import MDAnalysis as mda
import numpy as np
import pytest

import md
from conftest import POLYMER
from integrators import VelocityVerlet
from md.cli import main
from md.convert import FORMATS, convert, molecules, output_format
from md.polymers import polymer_melt
from md.render import bond_segments, box_edges, render
from md.structure import read_structure
from md.topology import Topology, combine
from md.trajectory import H5MDWriter, TrajectoryReader, read_trajectory
from potentials import HarmonicBonds, LennardJones

#: Position tolerance of each format, relative to the box edge: XTC keeps 1e-3 nm
#: (about 1e-4 of these boxes); MDAnalysis reads everything in single precision (DCD,
#: TRR, NetCDF, LAMMPS dump and data), as GSD stores it; the ASE text formats keep
#: about 10 significant digits and ASE trajectories double precision.
TOLERANCE = {
    "xtc": 5e-4,
    "trr": 1e-6,
    "dcd": 1e-6,
    "nc": 1e-6,
    "gsd": 1e-6,
    "lammpstrj": 1e-6,
    "data": 1e-6,
    "xyz": 1e-9,
    "extxyz": 1e-8,
    "traj": 1e-14,
}

FENE = '[[potentials]]\ntype = "fene"\nbonds = "system"\nk = 30.0\nr_max = 1.5\n'
QUIET = ("-q", "--no-progress")


@pytest.fixture(autouse=True)
def in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)


@pytest.fixture(scope="module")
def polymer(tmp_path_factory):
    """A reduced-unit polymer melt: 32 beads, FENE bonds, velocities and forces, 7 frames."""
    folder = tmp_path_factory.mktemp("polymer")
    config = folder / "polymer.toml"
    config.write_text(POLYMER)
    md.run_config(config, output=folder / "polymer.h5")
    return folder / "polymer.h5"


@pytest.fixture(scope="module")
def mixture(tmp_path_factory):
    """A metal-unit two-type crystal with springs of two bond types, written from Python."""
    folder = tmp_path_factory.mktemp("mixture")
    state = md.lattice("fcc", 3, lattice_constant=5.26, mass=39.948, type_name="Ar")
    state.types[1::2] = 1
    state.type_names = ("Ar", "Kr")
    state.masses[1::2] = 83.8
    md.maxwell_boltzmann(state, 300.0, seed=4, kB=md.get_units("metal").kB)
    bonds = np.array([[0, 1], [0, 2], [4, 5], [4, 6], [8, 9]])  # nearest neighbours
    springs = HarmonicBonds(bonds, k=[0.5, 1.0], r0=[3.7, 3.8], bond_types=[0, 1, 0, 1, 1])
    lj = LennardJones(epsilon=0.0104, sigma=3.4, cutoff=7.0)
    sim = md.Simulation(
        state, [lj, springs], VelocityVerlet(dt=0.5 * md.units.fs), skin=0.5, units="metal"
    )
    path = folder / "mixture.h5"
    with H5MDWriter(
        path, state, units="metal", velocities=True, forces=True, topology=sim.forcefield.topology()
    ) as writer:
        sim.attach(writer, interval=10)
        sim.run(40)
    return path


# ---------------------------------------------------------------------- topology
def test_topology_combines_styles_into_named_bond_types():
    topology = combine(
        [("spring", [[0, 1], [1, 2]], [0, 1]), ("fene", [[3, 4]], None), ("constraint", [], None)]
    )
    assert topology.bond_type_names == ("spring.0", "spring.1", "fene", "constraint")
    assert topology.bond_types.tolist() == [0, 1, 2]
    groups = topology.by_type()
    assert groups["constraint"].shape == (0, 2)
    again = Topology.from_groups(groups)
    assert again.bond_type_names == topology.bond_type_names
    assert np.array_equal(again.bonds, topology.bonds)
    with pytest.raises(ValueError, match="names an atom beyond the 4"):
        topology.check(4)
    with pytest.raises(ValueError, match="only 1 bond type names"):
        Topology.from_bonds([[0, 1], [1, 2]], [0, 1], ["a"])
    with pytest.raises(ValueError, match="joins atom 2 to itself"):
        Topology.from_bonds([[2, 2]])


def test_molecules_are_the_bonded_clusters():
    topology = Topology.from_bonds([[0, 1], [1, 2], [4, 3]])
    assert molecules(topology, 6).tolist() == [1, 1, 1, 2, 2, 3]


def test_polymer_bonds_are_stored_in_h5md_connectivity(polymer):
    _, bonds = polymer_melt(4, 8, density=0.8, bond_length=0.97, seed=3)
    with h5py.File(polymer, "r") as f:
        dataset = f["connectivity/fene"]
        assert dataset.shape == (28, 2) and dataset.dtype == np.int32
        assert f[dataset.attrs["particles_group"]].name == "/particles/trajectory"
        assert np.array_equal(dataset[()], bonds)
    universe = md.open_trajectory(polymer)
    assert np.array_equal(universe.bonds.to_indices(), np.sort(bonds, axis=1))
    assert universe.bonds.types() == ["fene"]
    assert read_trajectory(polymer).topology.n_bonds == 28


def test_two_bond_types_and_constraints_reach_the_file(mixture, tmp_path):
    universe = md.open_trajectory(mixture)
    assert sorted(universe.bonds.types()) == ["spring.0", "spring.1"]
    assert [b.type for b in universe.bonds].count("spring.1") == 3
    rigid = (
        POLYMER.replace(FENE, "")
        .replace('type = "verlet"', 'type = "rattle"')
        .replace("dt = 0.002", 'dt = 0.002\n[integrator.constraints]\nbonds = "system"')
    )
    (tmp_path / "rigid.toml").write_text(rigid)
    assert (
        main(["run", "rigid.toml", "-o", "rigid.h5", "--steps", "10", "-q", "--no-progress"]) == 0
    )
    universe = md.open_trajectory("rigid.h5")
    assert universe.bonds.types() == ["constraint"] and len(universe.bonds) == 28
    universe.trajectory.close()
    # a resumed run appends frames and keeps the connectivity
    assert main(["run", "rigid.toml", "-o", "rigid.h5", "--steps", "20", "--resume", *QUIET]) == 0
    universe = md.open_trajectory("rigid.h5")
    assert len(universe.trajectory) == 3 and len(universe.bonds) == 28
    universe.trajectory.close()


def test_md_info_counts_bonds(polymer, capsys):
    assert main(["info", str(polymer)]) == 0
    assert "bonds        28 fene" in capsys.readouterr().out


# ---------------------------------------------------------------------- reading frames
def test_reader_yields_the_frames_read_trajectory_reads(mixture):
    whole = read_trajectory(mixture)
    with TrajectoryReader(mixture) as reader:
        frames = list(reader.frames(reader.select(1, None, 2), chunk=1))
        assert [f.index for f in frames] == [1, 3]
        for frame in frames:
            assert np.allclose(frame.unwrapped(), whole.positions[frame.index], atol=1e-12)
            assert np.allclose(frame.velocities, whole.velocities[frame.index], rtol=1e-14)
            assert np.allclose(frame.forces, whole.forces[frame.index], rtol=1e-14)
            assert frame.observables["potential_energy"] == pytest.approx(
                whole.observables["potential_energy"][frame.index], rel=1e-14
            )
        with pytest.raises(IndexError, match="holds 5 frames .0 to 4.; start 7 is out of range"):
            reader.select(7)
        with pytest.raises(IndexError, match="select none"):
            reader.select(3, 1)


# ---------------------------------------------------------------------- round trips
def _wrapped(traj):
    return [np.mod(p, b) for p, b in zip(traj.positions, traj.boxes, strict=True)]


def _pairs(bonds) -> list[tuple[int, int]]:
    """Bonds as a sorted list of (low, high) index pairs: order and direction do not count."""
    return sorted((int(min(i, j)), int(max(i, j))) for i, j in np.asarray(bonds))


def _read_back(path, kind, traj):
    """Positions per frame, box of the last frame and type names, read by the format's library."""
    lj = traj.units.name == "lj"
    if kind in ("xtc", "trr", "dcd", "nc"):
        universe = mda.Universe.empty(traj.n_atoms)
        # Reduced values were written unchanged; metal ones converted to the format's units.
        universe.load_new(str(path), convert_units=not lj)
        positions = [ts.positions.astype(float).copy() for ts in universe.trajectory]
        return positions, universe.trajectory[-1].dimensions[:3], None, None
    if kind in ("xyz", "extxyz", "traj"):
        frames = ase.io.read(path, index=":")
        names = frames[0].info.get("type_names") or frames[0].get_chemical_symbols()
        return [a.positions for a in frames], np.diag(frames[-1].cell[:]), names, None
    if kind == "lammpstrj":
        universe = mda.Universe(str(path), format="LAMMPSDUMP")
        positions = [ts.positions.astype(float).copy() for ts in universe.trajectory]
        return positions, universe.trajectory[-1].dimensions[:3], None, None
    if kind == "data":
        universe = mda.Universe(str(path), format="DATA")
        bonds = universe.bonds.to_indices() if hasattr(universe, "bonds") else np.zeros((0, 2))
        return [universe.atoms.positions.astype(float)], universe.dimensions[:3], None, bonds
    with gsd.hoomd.open(str(path)) as frames:
        box = frames[-1].configuration.box[:3]
        positions = [f.particles.position + 0.5 * f.configuration.box[:3] for f in frames]
        last = frames[-1]
        bonds = last.bonds.group if last.bonds.N else np.zeros((0, 2))
        return positions, box, list(last.particles.types), bonds


@pytest.mark.parametrize("kind", sorted(set(FORMATS.values())))
@pytest.mark.parametrize("which", ["polymer", "mixture"])
def test_round_trip_through_each_format(kind, which, request, tmp_path):
    source = request.getfixturevalue(which)
    traj = read_trajectory(source)
    out = tmp_path / f"out.{kind}"
    assert main(["convert", str(source), str(out), "--no-progress"]) == 0
    positions, box, names, bonds = _read_back(out, kind, traj)
    expected = _wrapped(traj)
    if kind == "data":
        expected = expected[-1:]
    assert len(positions) == len(expected)
    for got, want in zip(positions, expected, strict=True):
        # Wrapped positions may land on either face of the box.
        diff = np.asarray(got, dtype=float) - want
        diff -= traj.boxes[-1] * np.round(diff / traj.boxes[-1])
        assert np.abs(diff).max() <= TOLERANCE[kind] * traj.boxes[-1].max()
    if kind != "xyz":  # plain XYZ has no box
        assert np.allclose(box, traj.boxes[-1], rtol=1e-6)
    if names is not None and kind != "xyz":
        assert set(names) <= set(traj.type_names) | {"X"}
    if kind in ("data", "gsd"):
        assert _pairs(bonds) == _pairs(traj.topology.bonds)


def test_extxyz_and_traj_carry_energy_forces_velocities_and_units(mixture, tmp_path):
    traj = read_trajectory(mixture)
    for kind in ("extxyz", "traj"):
        assert convert(mixture, tmp_path / f"m.{kind}") == traj.n_frames
        last = ase.io.read(tmp_path / f"m.{kind}", index=-1)
        assert np.allclose(last.get_forces(), traj.forces[-1], rtol=1e-7, atol=1e-8)
        # metal engine units are ASE's: velocities and energies unchanged
        assert np.allclose(last.get_velocities(), traj.velocities[-1], rtol=1e-6, atol=1e-9)
        assert last.get_potential_energy() == pytest.approx(
            traj.observables["potential_energy"][-1], rel=1e-10
        )
        assert last.get_chemical_symbols()[:2] == ["Ar", "Kr"]
    header = (tmp_path / "m.extxyz").read_text().splitlines()[1]
    assert "units=metal" in header and "step=0" in header


def test_trr_and_lammps_dump_convert_velocities_to_their_units(mixture, tmp_path):
    traj = read_trajectory(mixture)
    ps = md.units.ps
    convert(mixture, tmp_path / "m.trr")
    universe = mda.Universe.empty(traj.n_atoms)
    universe.load_new(str(tmp_path / "m.trr"))  # MDAnalysis converts nm/ps back to A/ps
    last = universe.trajectory[-1]
    assert np.allclose(last.velocities, traj.velocities[-1] * ps, rtol=1e-5, atol=1e-4)
    assert last.time == pytest.approx(traj.times[-1] / ps, rel=1e-6)
    convert(mixture, tmp_path / "m.lammpstrj")
    text = (tmp_path / "m.lammpstrj").read_text().splitlines()
    assert text[8] == "ITEM: ATOMS id type mol x y z ix iy iz vx vy vz fx fy fz"
    first = np.array(text[9].split(), dtype=float)
    assert first[9:12] == pytest.approx(traj.velocities[0][0] * ps, rel=1e-8)  # A/ps (metal)
    assert first[12:15] == pytest.approx(traj.forces[0][0], rel=1e-8)  # eV/A


def test_unwrap_writes_continuous_positions_and_no_images(polymer, tmp_path):
    traj = read_trajectory(polymer)
    assert np.any(np.abs(traj.positions[-1] - _wrapped(traj)[-1]) > 0.1), "nothing crossed"
    convert(polymer, tmp_path / "u.gsd", unwrap=True)
    with gsd.hoomd.open(str(tmp_path / "u.gsd")) as frames:
        last = frames[-1]
        assert not np.any(last.particles.image)
        got = last.particles.position + 0.5 * last.configuration.box[:3]
    assert np.allclose(got, traj.positions[-1], atol=1e-5)
    convert(polymer, tmp_path / "w.gsd")
    with gsd.hoomd.open(str(tmp_path / "w.gsd")) as frames:
        last = frames[-1]
        unwrapped = (
            last.particles.position
            + 0.5 * last.configuration.box[:3]
            + last.particles.image * last.configuration.box[:3]
        )
    assert np.allclose(unwrapped, traj.positions[-1], atol=1e-5)


def test_lammps_data_title_states_units_and_names_types(mixture, tmp_path):
    convert(mixture, tmp_path / "m.data")
    text = (tmp_path / "m.data").read_text()
    assert text.splitlines()[0].startswith("LAMMPS data file written by leapmd")
    assert "units metal" in text.splitlines()[0]
    assert "bond types 1=spring.0 2=spring.1" in text.splitlines()[0]
    assert "# Ar" in text and "# Kr" in text


# ---------------------------------------------------------------------- starting structures
@pytest.mark.parametrize("kind", ["data", "gsd", "h5"])
def test_converted_files_start_a_run_with_their_bonds(polymer, kind, tmp_path):
    source = tmp_path / f"start.{kind}"
    if kind == "h5":
        source = polymer
    else:
        convert(polymer, source, start=-1)
    traj = read_trajectory(polymer)
    state, topology = read_structure(source, units="lj")
    tolerance = 1e-5 if kind == "gsd" else 1e-9
    assert np.allclose(state.positions, traj.positions[-1], atol=tolerance) or np.allclose(
        np.mod(state.positions, state.box), _wrapped(traj)[-1], atol=tolerance
    )
    assert np.allclose(state.velocities, traj.velocities[-1], atol=tolerance)
    assert np.allclose(state.box, traj.boxes[-1])
    assert topology.n_bonds == 28
    assert _pairs(topology.bonds) == _pairs(traj.topology.bonds)
    assert topology.bond_type_names == ("fene",)
    config = POLYMER.replace(
        'polymer = "melt"\nchains = 4\nchain_length = 8\ndensity = 0.8\nbond_length = 0.97\n'
        "temperature = 1.0",
        f'structure = "{source}"',
    )
    (tmp_path / "again.toml").write_text(config)
    assert (
        main(["run", "again.toml", "-o", "again.h5", "--steps", "20", "-q", "--no-progress"]) == 0
    )
    again = md.open_trajectory("again.h5")
    assert len(again.bonds) == 28


def test_lammps_data_with_two_types_reads_names_masses_and_bond_types(mixture, tmp_path):
    convert(mixture, tmp_path / "m.data")
    state, topology = read_structure(tmp_path / "m.data", units="metal")
    traj = read_trajectory(mixture)
    assert state.type_names == ("Ar", "Kr")
    assert np.array_equal(state.types, traj.types)
    assert np.allclose(state.masses, traj.masses)
    assert np.allclose(state.velocities, traj.velocities[-1], rtol=1e-9, atol=1e-12)
    assert topology.bond_type_names == ("spring.0", "spring.1")
    assert topology.bond_types.tolist() == [0, 1, 0, 1, 1]


def test_plain_lammps_data_from_ase_reads_and_shifts_the_origin(tmp_path):
    text = """LAMMPS data file from elsewhere

3 atoms
1 bonds
2 atom types
1 bond types

-5.0 5.0 xlo xhi
-5.0 5.0 ylo yhi
0.0 10.0 zlo zhi

Masses

1 12.011
2 15.999

Atoms # bond

1 1 1 0.0 0.0 1.0
2 1 2 1.2 0.0 1.0
3 2 1 -4.0 -4.0 9.0

Bonds

1 1 1 2
"""
    (tmp_path / "plain.data").write_text(text)
    state, topology = read_structure(tmp_path / "plain.data")
    assert state.type_names == ("1", "2")
    assert np.allclose(state.box, [10, 10, 10])
    assert np.allclose(state.positions[0], [5.0, 5.0, 1.0])
    assert topology.bonds.tolist() == [[0, 1]]
    tilted = text.replace("0.0 10.0 zlo zhi\n", "0.0 10.0 zlo zhi\n1.0 0.0 0.0 xy xz yz\n")
    (tmp_path / "tilted.data").write_text(tilted)
    sheared, _ = read_structure(tmp_path / "tilted.data")  # LAMMPS's triclinic box as it is
    np.testing.assert_array_equal(sheared.tilt, [1.0, 0.0, 0.0])
    np.testing.assert_allclose(sheared.positions, state.positions)
    (tmp_path / "nomass.data").write_text(text.replace("Masses\n\n1 12.011\n2 15.999\n\n", ""))
    with pytest.raises(ValueError, match="no Masses section"):
        read_structure(tmp_path / "nomass.data")


# ---------------------------------------------------------------------- bad input
def test_bad_conversions_exit_2_and_leave_nothing(polymer, tmp_path, capsys):
    def files():
        return sorted(p.name for p in tmp_path.iterdir())

    before = files()
    assert main(["convert", str(polymer), "out.pdbx"]) == 2
    assert "suffix .pdbx names no format" in capsys.readouterr().err
    assert main(["convert", str(polymer), "out.xyz", "--start", "20"]) == 2
    assert "holds 7 frames (0 to 6); start 20 is out of range" in capsys.readouterr().err
    assert main(["convert", str(polymer), "out.xyz", "--step", "0"]) == 2
    (tmp_path / "notes.h5").write_text("not HDF5")
    before = files()
    assert main(["convert", "notes.h5", "out.xyz"]) == 2
    assert "not a readable HDF5 file" in capsys.readouterr().err
    with h5py.File(tmp_path / "other.h5", "w") as f:
        f["x"] = 1
    before = files()
    assert main(["convert", "other.h5", "out.xyz"]) == 2
    assert "not in the H5MD layout" in capsys.readouterr().err
    assert files() == before
    (tmp_path / "keep.xyz").write_text("precious")
    assert main(["convert", str(polymer), "keep.xyz"]) == 2
    assert "already exists" in capsys.readouterr().err
    assert (tmp_path / "keep.xyz").read_text() == "precious"
    assert main(["convert", str(polymer), "keep.xyz", "--overwrite", "--no-progress"]) == 0
    assert (tmp_path / "keep.xyz").read_text().startswith("32\n")


def test_a_conversion_that_fails_midway_leaves_no_partial_file(polymer, tmp_path, monkeypatch):
    calls = []

    def progress(count):
        calls.append(count)
        if count == 3:
            raise OSError("disk full (simulated)")

    with pytest.raises(OSError, match="simulated"):
        convert(polymer, tmp_path / "half.xyz", progress=progress)
    assert calls == [1, 2, 3]
    assert not any(p.name.startswith(".half") or p.name == "half.xyz" for p in tmp_path.iterdir())


def test_conversion_reads_in_chunks_so_memory_is_flat_in_frames(tmp_path):
    state = md.lattice("fcc", 4, density=0.8)  # 256 atoms: 12 kB of positions and velocities

    def write(path, n_frames):
        with H5MDWriter(path, state, units="lj", velocities=True) as writer:
            for step in range(n_frames):
                state.step = step
                writer.write(state)

    def peak(path):
        tracemalloc.start()
        convert(path, tmp_path / f"{path.stem}.gsd", chunk=4, overwrite=True)
        size = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        return size

    write(tmp_path / "short.h5", 8)
    write(tmp_path / "long.h5", 400)  # 5 MB in all: far more than a chunk
    peak(tmp_path / "short.h5")  # first use: imports and caches out of the measurement
    short, long = peak(tmp_path / "short.h5"), peak(tmp_path / "long.h5")
    assert long < 1.5 * short + 1e6, (short, long)


def test_output_format_names_the_known_suffixes():
    assert output_format("a.XTC") == "xtc"
    assert output_format("a.out", "extxyz") == "extxyz"
    with pytest.raises(ValueError, match="unknown format 'pdbq'"):
        output_format("a.xyz", "pdbq")


# ---------------------------------------------------------------------- pictures
def test_render_draws_a_png_of_the_requested_size(polymer, tmp_path, capsys):
    import matplotlib.image

    assert main(["render", str(polymer), "-o", "shot.png", "--size", "300"]) == 0
    image = matplotlib.image.imread(tmp_path / "shot.png")
    assert image.shape[:2] == (300, 300)
    assert image[..., :3].std() > 0.05  # something was drawn
    assert main(["render", str(polymer), "-o", "shot.png"]) == 2
    assert "already exists" in capsys.readouterr().err
    assert main(["render", str(polymer), "--frame", "7", "-o", "other.png"]) == 2
    assert "frame 7 is out of range" in capsys.readouterr().err
    assert main(["render", str(polymer), "-o", "shot.jpg"]) == 2
    assert not (tmp_path / "other.png").exists() and not (tmp_path / "shot.jpg").exists()


def test_render_with_povray_or_a_message_saying_it_is_missing(polymer, tmp_path, monkeypatch):
    import matplotlib.image

    if shutil.which("povray") is None:
        with pytest.raises(ValueError, match="POV-Ray is not installed"):
            render(polymer, tmp_path / "p.png", engine="povray")
        return
    render(polymer, tmp_path / "p.png", engine="povray", size=200)
    image = matplotlib.image.imread(tmp_path / "p.png")
    assert image.shape[1] == 200 and image[..., :3].std() > 0.05
    monkeypatch.setenv("PATH", "")  # as on a machine without it
    with pytest.raises(ValueError, match="POV-Ray is not installed"):
        render(polymer, tmp_path / "q.png", engine="povray")
    assert not (tmp_path / "q.png").exists()


def test_half_bonds_start_at_their_atoms_and_meet_at_the_nearest_image(polymer):
    with TrajectoryReader(polymer) as reader:
        frame = reader.frame(-1)
        segments = bond_segments(reader, frame)
        bonds = reader.topology.bonds
    n = len(bonds)
    assert segments.shape == (2 * n, 2, 3)
    assert np.allclose(segments[:n, 0], frame.positions[bonds[:, 0]])
    assert np.allclose(segments[n:, 0], frame.positions[bonds[:, 1]])
    halves = np.linalg.norm(segments[:, 1] - segments[:, 0], axis=1)
    assert halves.max() < 0.5 * 1.5  # half the FENE r_max: never across the box
    edges = box_edges(np.array([1.0, 2.0, 3.0]))
    lengths = sorted(np.round(np.linalg.norm(edges[:, 1] - edges[:, 0], axis=1), 12))
    assert lengths == [1.0] * 4 + [2.0] * 4 + [3.0] * 4
    # a tilted cell: its 12 edges are 4 copies of each cell vector
    cell = md.box.cell_matrix([1.0, 2.0, 3.0], [0.4, -0.3, 0.5])
    vectors = box_edges([1.0, 2.0, 3.0], [0.4, -0.3, 0.5])
    vectors = vectors[:, 1] - vectors[:, 0]
    for row in cell:
        assert np.sum(np.all(np.isclose(vectors, row), axis=1)) == 4


def test_analyze_all_adds_a_snapshot(polymer, tmp_path):
    assert main(["analyze", str(polymer), "--all", "--out", "ana", "--no-progress"]) == 0
    assert (tmp_path / "ana" / "snapshot.png").stat().st_size > 1000


# ---------------------------------------------------------------------- notebooks
def test_show_says_what_to_install_without_nglview(polymer, monkeypatch):
    monkeypatch.setitem(sys.modules, "nglview", None)  # import fails
    with pytest.raises(ImportError, match="pip install 'leapmd\\[notebook\\]'"):
        md.show(polymer)


def test_show_hands_nglview_a_universe_with_every_bond(polymer, monkeypatch):
    class Adaptor:
        def __init__(self, universe):
            self.atomgroup = universe.atoms

    fake = pytypes.SimpleNamespace(MDAnalysisTrajectory=Adaptor, NGLWidget=lambda t, **k: (t, k))
    monkeypatch.setitem(sys.modules, "nglview", fake)
    adaptor, options = md.show(polymer, gui=False)
    assert options == {"gui": False}
    pdb = adaptor.get_structure_string()
    partners = sum(len(line.split()) - 2 for line in pdb.splitlines() if line.startswith("CONECT"))
    assert partners == 2 * 28  # every bond, listed from both ends


def test_show_with_real_nglview(polymer):
    nglview = pytest.importorskip("nglview")
    view = md.show(polymer)
    assert isinstance(view, nglview.NGLWidget)


# ---------------------------------------------------------------------- OVITO (optional, slow)
@pytest.mark.slow
def test_ovito_opens_our_extxyz_dump_data_and_gsd_files(polymer, tmp_path):
    io = pytest.importorskip("ovito.io", reason="pip install ovito (leapmd[viewers])")
    traj = read_trajectory(polymer)
    for kind in ("extxyz", "lammpstrj", "data", "gsd"):
        path = tmp_path / f"o.{kind}"
        convert(polymer, path)
        pipeline = io.import_file(str(path))
        data = pipeline.compute(pipeline.source.num_frames - 1)
        assert data.particles.count == traj.n_atoms
        assert np.allclose(np.diag(np.asarray(data.cell[:, :3])), traj.boxes[-1], rtol=1e-6)
        if kind in ("data", "gsd"):  # the polymer's bonds and the type names survive
            assert data.particles.bonds.count == traj.topology.n_bonds
            names = [t.name for t in data.particles.particle_types.types]
            assert names == list(traj.type_names)
        if kind in ("lammpstrj", "gsd", "extxyz"):
            assert pipeline.source.num_frames == traj.n_frames


def test_readers_keep_only_frames_every_dataset_holds(polymer, tmp_path):
    """A run killed inside a write may grow some datasets by a frame and not others."""
    import shutil as copier

    path = tmp_path / "partial.h5"
    copier.copy(polymer, path)
    with h5py.File(path, "r+") as f:
        for name in ("position/step", "position/time", "position/value"):
            dataset = f[f"particles/trajectory/{name}"]
            dataset.resize(len(dataset) + 1, axis=0)
    whole = read_trajectory(polymer)
    partial = read_trajectory(path)
    assert partial.n_frames == whole.n_frames == 7
    assert np.array_equal(partial.positions, whole.positions)
    with TrajectoryReader(path) as reader:
        assert reader.n_frames == 7
    assert md.trajectory.read_frame_steps(path)[0].tolist() == whole.steps.tolist()


def test_lammps_data_from_a_reduced_run_states_its_values_exactly(tmp_path):
    """Masses, positions and velocities as stored (issue 33 item 18: a round trip of the
    units through ASE's metal wrote a mass of 1 as 0.99999999974)."""
    config = tmp_path / "run.toml"
    config.write_text(
        POLYMER.replace("temperature = 1.0", "temperature = 1.0\nmass = 1.7").replace(
            "polymer.h5", "heavy.h5"
        )
    )
    md.run_config(config, output=tmp_path / "heavy.h5")
    assert main(["convert", "heavy.h5", "heavy.data", "--stop", "1"]) == 0  # frame 0: wrapped
    lines = (tmp_path / "heavy.data").read_text().splitlines()

    def section(name):
        start = lines.index(name) + 2
        rows = itertools.takewhile(str.strip, lines[start:])
        return np.array([[float(w) for w in row.split("#")[0].split()] for row in rows])

    with TrajectoryReader(tmp_path / "heavy.h5") as reader:
        frame = reader.frame(0)
    assert section("Masses").tolist() == [[1.0, 1.7]]
    atoms = section("Atoms # full")
    velocities = section("Velocities")
    np.testing.assert_array_equal(atoms[:, 0], np.arange(1, 33))
    np.testing.assert_array_equal(atoms[:, 4:7], frame.positions)
    np.testing.assert_array_equal(velocities[:, 1:], frame.velocities)
