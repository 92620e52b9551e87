"""Triclinic cells in runs and files: H5MD (3, 3) edges, MDAnalysis, resume, convert, analyze."""

import numpy as np
import pytest
from MDAnalysis.lib.mdamath import triclinic_box

import md
from md import analysis
from md.box import cell_matrix
from md.checkpoint import checkpoint_path, read_checkpoint
from md.cli import main
from md.structure import read_structure
from md.trajectory import H5MDWriter, read_trajectory
from tests.conftest import lj_config_text

SHEAR = (0.2, 0.1, -0.15)


@pytest.fixture(autouse=True)
def in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)


def sheared_config(steps=60):
    text = lj_config_text(
        cells=5,
        integrator='type = "langevin"\ndt = 0.005\ntemperature = 1.0\nfriction = 1.0',
        run=f"steps = {steps}\nthermo_every = 10",
        output='path = "out.h5"\nevery = 10\nvelocities = true\ncheckpoint_every = 20',
    )
    return text.replace('lattice = "fcc"\n', f'lattice = "fcc"\nshear = {list(SHEAR)}\n')


def run(*args) -> int:
    return main(["run", *map(str, args), "--no-progress", "-q"])


def test_sheared_run_writes_a_cell_matrix_that_mdanalysis_reads(tmp_path, capsys):
    import h5py
    from MDAnalysis.coordinates.H5MD import H5MDReader

    (tmp_path / "run.toml").write_text(sheared_config())
    assert run("run.toml") == 0
    with h5py.File("out.h5") as f:
        edges = f["particles/trajectory/box/edges/value"][()]
    assert edges.shape == (7, 3, 3)
    box = np.diag(edges[0])
    np.testing.assert_allclose(
        edges[0], cell_matrix(box, np.array(SHEAR) * box[[1, 2, 2]]), rtol=1e-14
    )
    expected = triclinic_box(*edges[-1])
    # MDAnalysis's own H5MD reader, without our wrapper.
    plain = H5MDReader("out.h5", convert_units=False)
    np.testing.assert_allclose(plain[-1].dimensions, expected, rtol=1e-6)
    plain.close()
    ours = md.open_trajectory("out.h5")
    ours.trajectory[-1]
    np.testing.assert_allclose(ours.dimensions, expected, rtol=1e-6)
    # Unwrapped positions of the last frame are the run's final (continuous) positions.
    final = read_checkpoint(checkpoint_path("out.h5")).state
    traj = read_trajectory("out.h5")
    np.testing.assert_allclose(traj.tilts[-1], final.tilt)
    np.testing.assert_allclose(traj.positions[-1], final.positions, atol=1e-10)
    assert main(["info", "out.h5"]) == 0
    assert "tilt         xy 1.6" in capsys.readouterr().out


def test_sheared_run_resumes_bit_for_bit(tmp_path):
    (tmp_path / "run.toml").write_text(sheared_config())
    assert run("run.toml", "-o", "full.h5") == 0
    assert run("run.toml", "-o", "cut.h5", "--steps", "20") == 0
    assert run("run.toml", "-o", "cut.h5", "--resume") == 0
    a, b = read_trajectory("full.h5"), read_trajectory("cut.h5")
    assert np.array_equal(a.positions, b.positions)
    assert np.array_equal(a.velocities, b.velocities)
    assert np.array_equal(a.tilts, b.tilts)


def test_conversions_keep_the_cell(tmp_path):
    import MDAnalysis as mda

    (tmp_path / "run.toml").write_text(sheared_config(steps=20))
    assert run("run.toml") == 0
    traj = read_trajectory("out.h5")
    cell = traj.cells()[-1]
    assert main(["convert", "out.h5", "out.gsd"]) == 0
    state, _ = read_structure(tmp_path / "out.gsd")  # last frame, HOOMD's centred box undone
    np.testing.assert_allclose(state.cell, cell, rtol=1e-6)
    np.testing.assert_allclose(state.positions, traj.positions[-1], atol=1e-4)
    import ase.io

    assert main(["convert", "out.h5", "out.extxyz"]) == 0
    np.testing.assert_allclose(ase.io.read("out.extxyz", index=-1).cell.array, cell, rtol=1e-6)
    assert main(["convert", "out.h5", "out.xtc"]) == 0
    assert main(["convert", "out.h5", "out.lammpstrj"]) == 0
    for universe in (
        mda.Universe("out.gsd", "out.xtc", convert_units=False),  # reduced values, as written
        mda.Universe("out.lammpstrj", format="LAMMPSDUMP", topology_format="LAMMPSDUMP"),
    ):
        universe.trajectory[-1]
        np.testing.assert_allclose(universe.dimensions, triclinic_box(*cell), rtol=1e-5)


def _write(path, states):
    with H5MDWriter(path, states[0], units="lj", triclinic=True) as writer:
        for state in states:
            writer.write(state)
    return path


def test_rdf_of_an_ideal_gas_is_one_when_the_volume_changes(tmp_path):
    """Frames of volume V and 2.4 V: each normalised with its own volume, g(r) = 1."""
    rng = np.random.default_rng(4)
    n, states = 600, []
    for k, (edge, tilt) in enumerate([(8.0, (2.0, -1.0, 1.5)), (10.7, (0.0, 3.0, -2.0))] * 6):
        box = np.full(3, edge)
        positions = rng.random((n, 3)) @ cell_matrix(box, tilt)
        states.append(md.State(positions=positions, box=box, tilt=tilt, step=k))
    path = _write(tmp_path / "gas.h5", states)
    result = analysis.rdf(path, bins=20)
    g = result.g["A-A"]
    assert np.all(np.abs(g[4:] - 1.0) < 0.1), g
    assert abs(np.mean(g[4:]) - 1.0) < 0.02


def test_msd_unwraps_through_the_cell_matrix(tmp_path):
    """Atoms moving in straight lines across a tilted cell: MSD = v^2 t^2 exactly."""
    rng = np.random.default_rng(2)
    box, tilt = np.array([6.0, 6.5, 7.0]), np.array([2.5, -2.0, 3.0])
    start = rng.random((40, 3)) @ cell_matrix(box, tilt)
    velocities = rng.normal(0, 3.0, (40, 3))
    states = [
        md.State(positions=start + velocities * t, box=box, tilt=tilt, step=k, time=t)
        for k, t in enumerate(np.arange(40) * 0.5)
    ]
    path = _write(tmp_path / "ballistic.h5", states)
    result = analysis.msd(path, n_blocks=1)
    lag = np.arange(len(result.msd)) * 0.5
    np.testing.assert_allclose(
        result.msd, np.mean(np.sum(velocities**2, axis=1)) * lag**2, rtol=1e-5, atol=1e-6
    )


def test_writing_a_tilted_frame_into_an_orthorhombic_file_is_refused(tmp_path):
    state = md.lattice("fcc", 5, density=0.8)
    with H5MDWriter(tmp_path / "o.h5", state, units="lj") as writer:
        writer.write(state)
        sheared = state.copy()
        sheared.tilt[:] = [1.0, 0.0, 0.0]
        sheared.step = 1
        with pytest.raises(ValueError, match="triclinic=True"):
            writer.write(sheared)
