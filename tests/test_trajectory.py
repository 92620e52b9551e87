"""H5MD output: layout, round trip, MDAnalysis compatibility, units at the edge."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

import md
from conftest import POLYMER
from integrators import VelocityVerlet
from md import units
from md.trajectory import H5MDWriter, TrajectoryError, open_trajectory, read_trajectory
from potentials import LennardJones


class Recorder:
    """Observer keeping copies of what the simulation held at each call."""

    def __init__(self) -> None:
        self.frames = []

    def __call__(self, sim) -> None:
        state = sim.state
        self.frames.append(
            {
                "positions": state.positions.copy(),
                "velocities": state.velocities.copy(),
                "forces": sim.forcefield.compute(state).forces.copy(),
                "box": state.box.copy(),
                "step": state.step,
                "time": state.time,
                "thermo": sim.thermo(),
            }
        )


def _run_with_writer(path, state, n_steps=60, every=10, units_name="lj", dt=0.005, **kwargs):
    sim = md.Simulation(
        state,
        [LennardJones(**kwargs.pop("lj", {"cutoff": 2.5}))],
        VelocityVerlet(dt=dt),
        units=units_name,
    )
    recorder = Recorder()
    with H5MDWriter(
        path,
        state,
        units=units_name,
        velocities=True,
        forces=True,
        parameters={"seed": 7, "integrator": {"type": "verlet"}},
    ) as writer:
        sim.attach(writer, every)
        sim.attach(recorder, every)
        sim.run(n_steps)
    return sim, recorder


@pytest.fixture
def hot_liquid(fcc_lattice):
    # Hot enough that atoms cross the periodic boundaries within the run.
    return fcc_lattice(cells=3, density=0.8442, perturbation=0.05, temperature=4.0)


def test_layout_follows_h5md(tmp_path, hot_liquid):
    path = tmp_path / "t.h5"
    _run_with_writer(path, hot_liquid)
    with h5py.File(path, "r") as f:
        assert list(f["h5md"].attrs["version"]) == [1, 1]
        assert f["h5md/creator"].attrs["name"] == "leapmd"
        group = f["particles/trajectory"]
        assert (
            list(group["box"].attrs["boundary"]) == [b"periodic"] * 3
            or list(group["box"].attrs["boundary"]) == ["periodic"] * 3
        )
        assert group["box"].attrs["dimension"] == 3
        n = hot_liquid.n_atoms
        for name in ("position", "velocity", "force", "image"):
            value = group[name]["value"]
            assert value.shape == (7, n, 3)
            assert value.chunks == (1, n, 3)
            assert value.maxshape == (None, n, 3)
            # step and time are one dataset hard-linked into every element
            assert group[name]["step"].id == group["position/step"].id
            assert group[name]["time"].id == group["position/time"].id
        assert list(group["position/step"][()]) == [0, 10, 20, 30, 40, 50, 60]
        for name in (
            "potential_energy",
            "kinetic_energy",
            "total_energy",
            "temperature",
            "pressure",
        ):
            assert f["observables"][name]["value"].shape == (7,)
            assert f["observables"][name]["step"].id == group["position/step"].id
        # reduced units carry no unit attributes
        assert "unit" not in group["position/value"].attrs
        assert "unit" not in group["position/time"].attrs


def test_round_trip_equals_what_the_run_held(tmp_path, hot_liquid):
    path = tmp_path / "t.h5"
    _, recorder = _run_with_writer(path, hot_liquid)
    traj = read_trajectory(path)
    assert traj.n_frames == len(recorder.frames) == 7
    crossed = False
    for k, frame in enumerate(recorder.frames):
        np.testing.assert_allclose(traj.positions[k], frame["positions"], rtol=0, atol=1e-12)
        np.testing.assert_array_equal(traj.velocities[k], frame["velocities"])
        np.testing.assert_array_equal(traj.forces[k], frame["forces"])
        np.testing.assert_array_equal(traj.boxes[k], frame["box"])
        assert traj.steps[k] == frame["step"] and traj.times[k] == frame["time"]
        for name, value in frame["thermo"].items():
            if name in traj.observables:
                assert traj.observables[name][k] == value
        crossed |= bool(np.any((frame["positions"] < 0) | (frame["positions"] > frame["box"])))
    assert crossed, "the test system should have atoms outside the box to test unwrapping"
    state = traj.state(-1)
    assert state.step == 60 and state.n_atoms == hot_liquid.n_atoms
    assert traj.parameters["seed"] == 7 and traj.parameters["integrator"] == {"type": "verlet"}


def test_mdanalysis_reads_reduced_units(tmp_path, hot_liquid):
    path = tmp_path / "t.h5"
    _, recorder = _run_with_writer(path, hot_liquid)
    u = open_trajectory(path)
    assert u.atoms.n_atoms == hot_liquid.n_atoms
    assert u.trajectory.n_frames == 7
    assert list(np.unique(u.atoms.types)) == ["A"]
    np.testing.assert_array_equal(u.atoms.masses, hot_liquid.masses)
    for ts, frame in zip(u.trajectory, recorder.frames, strict=True):
        box = frame["box"]
        wrapped = frame["positions"] - np.floor(frame["positions"] / box) * box
        # MDAnalysis stores float32 coordinates
        np.testing.assert_allclose(ts.positions, wrapped, atol=2e-5 * box.max())
        np.testing.assert_allclose(ts.dimensions[:3], box, rtol=1e-6)
        np.testing.assert_allclose(ts.dimensions[3:], 90.0)
        assert ts.time == pytest.approx(frame["time"])
        assert ts.data["step"] == frame["step"]
        for name in (
            "potential_energy",
            "kinetic_energy",
            "total_energy",
            "temperature",
            "pressure",
        ):
            assert ts.data[name] == pytest.approx(frame["thermo"][name], rel=1e-12)
        np.testing.assert_allclose(ts.velocities, frame["velocities"], rtol=1e-5, atol=1e-5)


def test_metal_units_are_converted_at_the_edge(tmp_path):
    # Argon-like fcc crystal in ASE's units; dt 5 fs.
    state = md.lattice("fcc", 3, lattice_constant=5.26, mass=39.948, type_name="Ar")
    md.maxwell_boltzmann(state, 60.0, seed=3, kB=units.kB)
    path = tmp_path / "ar.h5"
    lj = {"epsilon": 0.0104, "sigma": 3.40, "cutoff": 7.5}
    _, recorder = _run_with_writer(
        path, state, n_steps=20, every=10, units_name="metal", dt=5 * units.fs, lj=lj
    )
    with h5py.File(path, "r") as f:
        group = f["particles/trajectory"]
        assert group["position/value"].attrs["unit"] == "Angstrom"
        assert group["position/time"].attrs["unit"] == "ps"
        assert group["velocity/value"].attrs["unit"] == "Angstrom ps-1"
        assert group["force/value"].attrs["unit"] == "kJ mol-1 Angstrom-1"
    u = open_trajectory(path)  # converts to MDAnalysis units: Angstrom, ps, kJ/(mol A)
    assert list(np.unique(u.atoms.types)) == ["Ar"]
    frame = recorder.frames[-1]
    ts = u.trajectory[-1]
    assert ts.time == pytest.approx(frame["time"] / units.ps)  # engine time -> ps
    assert ts.time == pytest.approx(20 * 5e-3)  # 20 steps of 5 fs
    # ASE: 1 eV/A = 96.485 kJ/(mol A); velocities A/ps
    np.testing.assert_allclose(ts.forces, frame["forces"] * 96.485332, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(ts.velocities, frame["velocities"] * units.ps, rtol=1e-5, atol=1e-4)
    # our reader returns engine units again
    traj = read_trajectory(path)
    np.testing.assert_allclose(traj.times[-1], frame["time"], rtol=1e-14)
    np.testing.assert_allclose(traj.forces[-1], frame["forces"], rtol=1e-12)
    np.testing.assert_allclose(traj.velocities[-1], frame["velocities"], rtol=1e-12)


def test_open_axes_are_marked_none(tmp_path, random_gas):
    state = random_gas(40, box=[8.0, 8.0, 8.0], pbc=[True, True, False])
    path = tmp_path / "slab.h5"
    with H5MDWriter(path, state) as writer:
        writer.write(state)
    with h5py.File(path, "r") as f:
        boundary = [
            b.decode() if isinstance(b, bytes) else b
            for b in f["particles/trajectory/box"].attrs["boundary"]
        ]
    assert boundary == ["periodic", "periodic", "none"]
    traj = read_trajectory(path)
    assert traj.pbc.tolist() == [True, True, False]
    np.testing.assert_allclose(traj.positions[0], state.positions, atol=1e-12)


def test_existing_file_is_not_overwritten(tmp_path, dimer):
    path = tmp_path / "keep.h5"
    path.write_bytes(b"precious")
    with pytest.raises(FileExistsError, match="keep.h5"):
        H5MDWriter(path, dimer())
    assert path.read_bytes() == b"precious"
    with H5MDWriter(path, dimer(), overwrite=True) as writer:
        writer.write(dimer())
    assert read_trajectory(path).n_frames == 1


def test_frames_must_advance(tmp_path, dimer):
    state = dimer()
    with H5MDWriter(tmp_path / "t.h5", state) as writer:
        writer.write(state)
        with pytest.raises(ValueError, match="step 0"):
            writer.write(state)
    assert read_trajectory(tmp_path / "t.h5").n_frames == 1


def test_killed_writer_leaves_a_readable_file(tmp_path):
    # A child process writes three frames and dies without closing the file
    # (os._exit skips every cleanup); the frames must all be readable.
    import subprocess
    import sys
    import textwrap

    path = tmp_path / "killed.h5"
    script = textwrap.dedent(
        f"""
        import os, numpy as np, md
        from md.trajectory import H5MDWriter
        state = md.lattice("sc", 2, density=0.5)
        writer = H5MDWriter({str(path)!r}, state)
        for step in range(3):
            state.step = step
            state.positions += 0.01
            writer.write(state)
        os._exit(9)
        """
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert result.returncode == 9, result.stderr
    traj = read_trajectory(path)
    assert traj.n_frames == 3
    assert list(traj.steps) == [0, 1, 2]
    assert open_trajectory(path).trajectory.n_frames == 3


@pytest.mark.parametrize("content", [b"", b"not an hdf5 file at all", None])
def test_bad_files_are_refused(tmp_path, content):
    path = tmp_path / "bad.h5"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(TrajectoryError, match="bad.h5"):
        read_trajectory(path)


def test_foreign_hdf5_file_is_refused(tmp_path):
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as f:
        f["data"] = np.arange(3)
    with pytest.raises(TrajectoryError, match="H5MD"):
        read_trajectory(path)
    with pytest.raises(TrajectoryError):
        open_trajectory(path)


def test_outputs_get_the_usual_permissions(tmp_path):
    """Files renamed into place from a private temporary get 0666 less the umask, not 0600."""
    import os
    import stat

    from md.checkpoint import write_checkpoint
    from md.forcefield import ForceField

    umask = os.umask(0o022)
    try:
        state = md.lattice("fcc", 2, density=0.8)
        with H5MDWriter(tmp_path / "t.h5", state, units="lj") as writer:
            writer.write(state)
        forcefield = ForceField([LennardJones(cutoff=1.5)])
        forcefield.compute(state)
        write_checkpoint(
            tmp_path / "t.ckpt",
            state,
            VelocityVerlet(0.005),
            forcefield,
            n_frames=1,
            last_frame_step=0,
        )
    finally:
        os.umask(umask)
    for name in ("t.h5", "t.ckpt"):
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == 0o644


def test_a_file_without_frames_is_reported_not_crashed_on(tmp_path):
    state = md.lattice("fcc", 2, density=0.8)
    path = tmp_path / "empty.h5"
    with H5MDWriter(path, state, units="lj"):
        pass  # a run killed between creating the file and its first frame
    assert read_trajectory(path).n_frames == 0
    with pytest.raises(TrajectoryError, match="no frames yet"):
        open_trajectory(path)


# --------------------------------------------------- damaged connectivity (issue 33 item 16)
@pytest.fixture(scope="module")
def polymer_file(tmp_path_factory):
    folder = tmp_path_factory.mktemp("bonds")
    (folder / "polymer.toml").write_text(POLYMER)
    md.run_config(folder / "polymer.toml", output=folder / "polymer.h5")
    return folder / "polymer.h5"


@pytest.mark.parametrize(
    ("pair", "what"),
    [
        ((3, 999), "names an atom outside 0..31"),
        ((5, 5), "names one atom twice"),
        ((4, 40, 6), "names an atom outside 0..31"),
        ((7, 8, 7), "names one atom twice"),
    ],
)
def test_a_damaged_bond_is_named_on_opening_by_every_reader(
    polymer_file, tmp_path, monkeypatch, capsys, pair, what
):
    """md info, md analyze and conversion to GSD accepted an out-of-range bond (the GSD got
    it), LAMMPS data, render and the API failed with a raw IndexError. Angles alike."""
    import shutil

    from md.cli import main
    from md.trajectory import TrajectoryReader, read_topology

    monkeypatch.chdir(tmp_path)
    shutil.copy(polymer_file, "bad.h5")
    with h5py.File("bad.h5", "r+") as f:
        if len(pair) == 2:
            f["connectivity/fene"][3] = pair
        else:  # an angle list (a triple per angle, the vertex in the middle)
            f["connectivity"].create_dataset("bend", data=[[0, 1, 2], [1, 2, 3], [2, 3, 4], pair])
    name, kind = ("fene", "bond") if len(pair) == 2 else ("bend", "angle")
    message = f"bad.h5: /connectivity/{name}: {kind} 3 {pair} {what}"
    for command in (
        ["info", "bad.h5"],
        ["analyze", "bad.h5", "--no-progress"],
        ["convert", "bad.h5", "bad.gsd"],
        ["convert", "bad.h5", "bad.data"],
        ["render", "bad.h5", "-o", "bad.png"],
    ):
        assert main(command) == 2, command
        assert message in capsys.readouterr().err, command
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.h5"]  # nothing written
    for reader in (read_trajectory, open_trajectory, TrajectoryReader, read_topology):
        with pytest.raises(TrajectoryError, match=message.replace("(", r"\(").replace(")", r"\)")):
            reader("bad.h5")


# ------------------------------------------- a file that a live run is writing
def test_a_read_that_fails_while_the_file_changes_is_tried_again(tmp_path):
    from md.trajectory import while_written

    path = tmp_path / "growing.h5"
    path.write_bytes(b"frame 1")
    calls = []

    def read():
        calls.append(len(calls))
        if len(calls) < 3:
            path.write_bytes(b"frame 1" * (len(calls) + 1))  # the writer adds a frame meanwhile
            raise TrajectoryError("frame 1 is damaged (addr overflow)")
        return "frames read"

    assert while_written(path, read, settle=0.01) == "frames read"
    assert len(calls) == 3


def test_a_damaged_file_that_nothing_writes_is_reported_after_one_read(tmp_path):
    from md.trajectory import while_written

    path = tmp_path / "damaged.h5"
    path.write_bytes(b"frame 1")
    calls = []

    def read():
        calls.append(1)
        raise TrajectoryError("frame 0 is damaged")

    with pytest.raises(TrajectoryError, match="frame 0 is damaged"):
        while_written(path, read, settle=0.01)
    assert len(calls) == 1
