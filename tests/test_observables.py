"""Volume, density and the pressure tensor: in sim.thermo(), the thermo table and H5MD files."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

import md
from integrators import VelocityVerlet
from md.analysis import isothermal_compressibility, thermo
from md.cli import main
from md.thermo import PRESSURE_COMPONENTS
from md.trajectory import H5MDWriter, read_trajectory
from potentials import LennardJones


@pytest.fixture
def liquid():
    state = md.maxwell_boltzmann(md.lattice("fcc", 4, density=0.8), 1.2, seed=4)
    sim = md.Simulation(state, [LennardJones(cutoff=2.5)], VelocityVerlet(0.005))
    sim.run(50)
    return sim


def test_pressure_tensor_trace_is_the_pressure_and_density_is_mass_over_volume(liquid):
    row = liquid.thermo()
    state = liquid.state
    assert row["volume"] == pytest.approx(np.prod(state.box))
    assert row["density"] == pytest.approx(state.masses.sum() / np.prod(state.box))
    trace = (row["pxx"] + row["pyy"] + row["pzz"]) / 3
    assert trace == pytest.approx(row["pressure"], rel=1e-12)
    # off-diagonal: the kinetic part from the velocities plus the pair virial's component
    virial = liquid.forcefield.compute(state).virial
    m, v = state.masses, state.velocities
    expected = (np.sum(m * v[:, 0] * v[:, 1]) + virial[0, 1]) / row["volume"]
    assert row["pxy"] == pytest.approx(expected, rel=1e-12)
    # an isotropic liquid: shear components fluctuate about zero, well below the pressure
    assert abs(row["pxy"]) < 0.5 * abs(row["pressure"])


def test_the_file_stores_them_and_appends_to_older_files(liquid, tmp_path):
    path = tmp_path / "t.h5"
    with H5MDWriter(path, liquid.state, units="lj") as writer:
        writer.write(liquid.state, thermo=liquid.thermo())
    traj = read_trajectory(path)
    for name in ("volume", "density", *PRESSURE_COMPONENTS):
        assert traj.observables[name][0] == pytest.approx(liquid.thermo()[name])
    # a file written before these observables existed: appending keeps its layout
    with h5py.File(path, "r+") as f:
        for name in ("volume", "density", *PRESSURE_COMPONENTS):
            del f[f"observables/{name}"]
    liquid.run(1)
    with H5MDWriter(path, liquid.state, units="lj", append=True) as writer:
        writer.write(liquid.state, thermo=liquid.thermo())
    traj = read_trajectory(path)
    assert traj.n_frames == 2 and "volume" not in traj.observables


def test_md_run_table_and_analyze_report_volume_and_density(
    tmp_path, monkeypatch, capsys, lj_config
):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "run.toml").write_text(lj_config())
    assert main(["run", "run.toml", "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "Volume" in out and "Density" in out
    result = thermo("out.h5")
    volume = result.averages["volume"]
    assert volume.std < 1e-10 and volume.mean == pytest.approx(108 / 0.8442)
    assert np.isnan(result.compressibility)  # constant volume: no fluctuation to measure


def test_compressibility_from_volume_fluctuations():
    rng = np.random.default_rng(1)
    kT, mean_v, kappa = 1.5, 1000.0, 0.02
    volumes = rng.normal(mean_v, np.sqrt(kappa * kT * mean_v), size=200_000)
    assert isothermal_compressibility(volumes, temperature=kT) == pytest.approx(kappa, rel=0.01)
    assert np.isnan(isothermal_compressibility([5.0, 5.0, 5.0], temperature=1.0))
