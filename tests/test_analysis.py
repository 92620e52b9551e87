"""Trajectory analysis (md.analysis) against analytic results and direct numpy references.

Synthetic trajectories are written through H5MDWriter, so every test reads the
real file format (wrapped positions plus images, file units).
"""

from __future__ import annotations

import math

import h5py
import numpy as np
import pytest

import md
from md import analysis
from md.analysis import AnalysisError, block_average, velocity_autocorrelation
from md.thermo import temperature
from md.trajectory import H5MDWriter
from md.units import METAL, ps


def write_trajectory(
    path,
    positions,
    box,
    times,
    velocities=None,
    types=None,
    units="lj",
    thermo=None,
    pbc=True,
    masses=1.0,
):
    """Write frames (positions (F, N, 3) unwrapped, engine units) through H5MDWriter."""
    positions = np.asarray(positions, dtype=float)
    n_frames, n_atoms = positions.shape[:2]
    state = md.State(
        positions=positions[0],
        masses=masses,
        box=np.broadcast_to(np.asarray(box, float), (3,)).copy(),
        pbc=pbc,
        types=None if types is None else list(types),
    )
    with H5MDWriter(path, state, units=units, velocities=velocities is not None) as writer:
        for frame in range(n_frames):
            state.positions[:] = positions[frame]
            if velocities is not None:
                state.velocities[:] = velocities[frame]
            state.step = frame
            state.time = float(times[frame])
            writer.write(state, thermo=None if thermo is None else thermo[frame])
    return path


def minimum_image_distances(a, b, box, same):
    d = a[:, None, :] - b[None, :, :]
    d -= box * np.round(d / box)
    r = np.sqrt(np.einsum("ijk,ijk->ij", d, d))
    if same:
        r = r[~np.eye(len(a), dtype=bool)]
    return r.ravel()


# --------------------------------------------------------------------- block averages
def test_block_average_of_uneven_series_drops_earliest_samples_from_blocks():
    values = np.array([100.0, 1, 1, 2, 2, 3, 3])
    result = block_average(values, n_blocks=3)
    assert result.mean == pytest.approx(values.mean(), rel=1e-15)
    assert result.std == pytest.approx(np.std(values, ddof=1), rel=1e-15)
    # block means 1, 2, 3: standard deviation 1
    assert result.sem == pytest.approx(1.0 / math.sqrt(3.0), rel=1e-14)
    assert result.n_blocks == 3


def test_block_average_error_of_correlated_series_matches_theory(rng):
    # AR(1): x_n = phi x_{n-1} + noise has variance 1/(1 - phi^2) and the standard
    # error of the mean sqrt(var / n * (1 + phi) / (1 - phi)), 4.4x the naive one.
    phi, n = 0.9, 200_000
    noise = rng.standard_normal(n)
    x = np.empty(n)
    x[0] = noise[0] / math.sqrt(1 - phi**2)
    for i in range(1, n):
        x[i] = phi * x[i - 1] + noise[i]
    variance = 1.0 / (1 - phi**2)
    expected = math.sqrt(variance / n * (1 + phi) / (1 - phi))
    naive = math.sqrt(variance / n)
    result = block_average(x, n_blocks=20)
    # 20 blocks estimate the error to about +-16 % (one sigma)
    assert 0.6 * expected < result.sem < 1.5 * expected
    assert result.sem > 2.5 * naive


# --------------------------------------------------------------------------- thermo
def test_thermo_averages_and_drift_equal_numpy_on_stored_arrays(tmp_path, rng):
    n_atoms, n_frames = 20, 60
    dt = 10 * METAL.config_time  # 10 fs in engine units
    times = np.arange(n_frames) * dt
    slope = 2e-3  # eV per engine time unit
    total = -50.0 + slope * times + rng.normal(scale=0.01, size=n_frames)
    thermo = [
        {
            "potential_energy": total[i] - 3.0 - 0.1 * rng.random(),
            "kinetic_energy": 3.0 + 0.1 * rng.random(),
            "total_energy": total[i],
            "temperature": 300 + rng.normal(scale=5),
            "pressure": 1e-3 * rng.random(),
        }
        for i in range(n_frames)
    ]
    positions = rng.uniform(0, 8.0, size=(n_frames, n_atoms, 3))
    path = write_trajectory(tmp_path / "t.h5", positions, 8.0, times, units="metal", thermo=thermo)
    result = analysis.thermo(path, start=4, stop=57, step=2, n_blocks=5)
    with h5py.File(path) as f:
        stored = {name: f[f"observables/{name}/value"][4:57:2] for name in thermo[0]}
        stored_times = f["particles/trajectory/position/time"][4:57:2]
    assert set(result.series) == set(stored)
    for name, values in stored.items():
        np.testing.assert_array_equal(result.series[name], values)
        average = result.averages[name]
        assert average.mean == pytest.approx(np.mean(values), rel=1e-14)
        assert average.std == pytest.approx(np.std(values, ddof=1), rel=1e-12)
        assert average.n_blocks == 5
    np.testing.assert_allclose(result.times, stored_times, rtol=1e-15)
    # Times are in the file's unit (ps), so the drift is per atom per ps.
    assert result.times[1] - result.times[0] == pytest.approx(2 * 10e-3, rel=1e-9)
    fit_slope, fit_intercept = np.polyfit(stored_times, stored["total_energy"] / n_atoms, 1)
    assert result.energy_drift == pytest.approx(fit_slope, rel=1e-9)
    expected_drift = slope * ps / n_atoms  # eV per engine time -> eV per ps, per atom
    assert abs(result.energy_drift - expected_drift) < 4 * result.energy_drift_err
    residual = stored["total_energy"] / n_atoms - (fit_slope * stored_times + fit_intercept)
    assert result.energy_fluctuation == pytest.approx(np.std(residual), rel=1e-9)


def test_thermo_needs_observables(tmp_path, rng):
    path = write_trajectory(tmp_path / "t.h5", rng.uniform(0, 5, (3, 4, 3)), 5.0, [0, 1, 2])
    with pytest.raises(AnalysisError, match="no thermodynamic observables"):
        analysis.thermo(path)


# ------------------------------------------------------------------------------ g(r)
def test_ideal_gas_rdf_is_one_within_noise(tmp_path, rng):
    n_atoms, box, n_frames = 600, 10.0, 4
    positions = rng.uniform(0, box, size=(n_frames, n_atoms, 3))
    types = np.arange(n_atoms) % 2
    path = write_trajectory(tmp_path / "gas.h5", positions, box, np.arange(n_frames), types=types)
    result = analysis.rdf(path, bins=25, r_range=(1.0, 5.0))
    assert set(result.g) == {"all", "A-A", "A-B", "B-B"}
    shell_volumes = 4 / 3 * np.pi * np.diff(result.edges**3)
    for pair, g in result.g.items():
        n_a = n_atoms if pair == "all" else n_atoms // 2
        n_b = n_a
        # ordered pairs per bin; same-group pairs come twice, so half are independent
        expected = n_frames * n_a * n_b * shell_volumes / box**3
        independent = expected / 2 if pair != "A-B" else expected
        sigma = 1.0 / np.sqrt(independent)
        assert np.all(np.abs(g - 1.0) < 5 * sigma), pair
        mean_sigma = 1.0 / math.sqrt(independent.sum())
        assert abs(np.average(g, weights=independent) - 1.0) < 4 * mean_sigma, pair


def test_fcc_rdf_peaks_at_shells_with_coordination_12_6_24(tmp_path):
    state = md.lattice("fcc", 4, density=1.0)
    a = state.box[0] / 4
    path = write_trajectory(tmp_path / "fcc.h5", state.positions[None], state.box, [0.0])
    result = analysis.rdf(path, bins=600, r_range=(0.0, 1.5 * a))
    g, r = result.g["A-A"], result.r
    width = result.edges[1] - result.edges[0]
    shells = a * np.sqrt([0.5, 1.0, 1.5, 2.0])
    counts = [12, 6, 24, 12]
    occupied = r[g > 0]
    # every non-empty bin lies on a shell, and every shell has one
    assert np.all(np.min(np.abs(occupied[:, None] - shells[None, :]), axis=1) <= width)
    assert all(np.min(np.abs(occupied - s)) <= width for s in shells)
    cumulative = 0
    for inner, outer, count in zip([0.0, *shells[:-1]], shells, counts, strict=True):
        between = 0.5 * (inner + outer)
        assert result.coordination_at("A-A", between) == pytest.approx(cumulative, abs=1e-12)
        cumulative += count
    assert result.coordination_at("A-A", 1.5 * a) == pytest.approx(54, abs=1e-12)
    shell = result.shells["A-A"]
    assert shell.r_peak == pytest.approx(shells[0], abs=width)
    assert shells[0] < shell.r_min < shells[1]
    assert shell.coordination == pytest.approx(12, abs=1e-12)


def test_rdf_equals_direct_histogram_on_same_frames(tmp_path, rng):
    n_atoms, box, n_frames = 80, np.array([6.0, 6.5, 7.0]), 7
    positions = rng.uniform(-6.0, 12.0, size=(n_frames, n_atoms, 3))  # outside the box too
    types = rng.integers(0, 2, size=n_atoms)
    types[:2] = [0, 1]
    path = write_trajectory(tmp_path / "r.h5", positions, box, np.arange(n_frames), types=types)
    bins, r_range = 40, (0.2, 2.9)
    result = analysis.rdf(path, bins=bins, r_range=r_range, start=1, stop=7, step=2)
    assert result.n_frames == 3
    with h5py.File(path) as f:
        # MDAnalysis works in float32; the reference uses the same rounded values
        stored = f["particles/trajectory/position/value"][1:7:2].astype(np.float32)
    edges = np.linspace(*r_range, bins + 1)
    shell_volumes = 4 / 3 * np.pi * np.diff(edges**3)
    box32 = box.astype(np.float32).astype(float)
    groups = {"all": np.arange(n_atoms), "A": np.flatnonzero(types == 0)}
    groups["B"] = np.flatnonzero(types == 1)
    for pair, (first, second) in {
        "all": ("all", "all"),
        "A-A": ("A", "A"),
        "A-B": ("A", "B"),
        "B-B": ("B", "B"),
    }.items():
        counts = np.zeros(bins)
        for frame in stored.astype(float):
            r = minimum_image_distances(
                frame[groups[first]], frame[groups[second]], box32, same=first == second
            )
            counts += np.histogram(r, bins=edges)[0]
        n_a, n_b = len(groups[first]), len(groups[second])
        n_pairs = n_a * (n_b - 1) if first == second else n_a * n_b
        reference = counts / (3 * shell_volumes * n_pairs / np.prod(box32))
        np.testing.assert_allclose(result.g[pair], reference, rtol=1e-6, atol=0, err_msg=pair)
        np.testing.assert_allclose(
            result.coordination[pair][1:], np.cumsum(counts) / (3 * n_a), rtol=1e-12
        )


def test_rdf_rejects_range_beyond_half_box_and_open_boxes(tmp_path, rng):
    positions = rng.uniform(0, 6.0, size=(2, 10, 3))
    path = write_trajectory(tmp_path / "p.h5", positions, 6.0, [0, 1])
    with pytest.raises(AnalysisError, match="half the smallest cell width"):
        analysis.rdf(path, r_range=(0.0, 3.5))
    open_path = write_trajectory(tmp_path / "o.h5", positions, 6.0, [0, 1], pbc=False)
    with pytest.raises(AnalysisError, match="periodic"):
        analysis.rdf(open_path)


# ------------------------------------------------------------------------------- MSD
@pytest.mark.parametrize("units", ["lj", "metal"])
def test_ballistic_msd_is_v2_t2_through_unwrapped_images(tmp_path, rng, units):
    n_atoms, n_frames, box = 30, 40, 5.0
    unit_time = 1.0 if units == "lj" else METAL.config_time * 1000  # 1 tau, or 1 ps
    dt = 0.25 * unit_time
    velocities = rng.normal(scale=2.0 / unit_time, size=(n_atoms, 3))
    times = np.arange(n_frames) * dt
    start_positions = rng.uniform(0, box, size=(n_atoms, 3))
    positions = start_positions + times[:, None, None] * velocities
    path = write_trajectory(tmp_path / "b.h5", positions, box, times, units=units)
    with h5py.File(path) as f:
        assert np.abs(f["particles/trajectory/image/value"][-1]).max() >= 2  # crossed the box
    result = analysis.msd(path, start=3, step=2)
    lags = np.arange(len(result.lag_times)) * 2 * 0.25  # file time units (tau or ps)
    np.testing.assert_allclose(result.lag_times, lags, rtol=1e-12)
    speed2 = np.mean(np.sum((velocities * unit_time) ** 2, axis=1))  # [length^2 / file time^2]
    np.testing.assert_allclose(result.msd, speed2 * lags**2, rtol=2e-6, atol=1e-12)


def test_msd_needs_five_evenly_spaced_frames_and_a_fitting_window(tmp_path, rng):
    positions = rng.uniform(0, 5, (8, 4, 3))
    path = write_trajectory(tmp_path / "m.h5", positions, 5.0, [0, 1, 2, 3, 4, 5, 7, 9])
    with pytest.raises(AnalysisError, match="at least 5 frames"):
        analysis.msd(path, stop=4)
    with pytest.raises(AnalysisError, match="not evenly spaced"):
        analysis.msd(path)
    with pytest.raises(AnalysisError, match="holds 1 lag time"):
        analysis.msd(path, stop=6, window=(1.5, 2.5))
    with pytest.raises(AnalysisError, match="beyond the longest lag"):
        analysis.msd(path, stop=6, window=(1.0, 5.5))
    with pytest.raises(AnalysisError, match="step must be a positive integer"):
        analysis.msd(path, step=0)
    assert analysis.msd(path, stop=6, window=(1.0, 5.0)).diffusion.n_blocks == 1


# ------------------------------------------------------------------------------ VACF
def test_vacf_by_fft_equals_direct_average_over_time_origins(rng):
    velocities = rng.normal(size=(37, 5, 3))
    result = velocity_autocorrelation(velocities, chunk=2)  # several chunks
    n_frames = len(velocities)
    for lag in range(n_frames):
        direct = np.einsum("tij,tij->i", velocities[: n_frames - lag], velocities[lag:])
        np.testing.assert_allclose(result[lag], direct / (n_frames - lag), rtol=1e-10, atol=1e-13)


def ornstein_uhlenbeck(rng, n_atoms, n_frames, dt, gamma, kT):
    """Velocities of an OU process sampled every dt, positions by the trapezoidal rule."""
    phi = math.exp(-gamma * dt)
    kicks = rng.normal(scale=math.sqrt(kT * (1 - phi**2)), size=(n_frames, n_atoms, 3))
    velocities = np.empty((n_frames, n_atoms, 3))
    velocities[0] = rng.normal(scale=math.sqrt(kT), size=(n_atoms, 3))
    for i in range(1, n_frames):
        velocities[i] = phi * velocities[i - 1] + kicks[i]
    steps = 0.5 * dt * (velocities[1:] + velocities[:-1])
    positions = np.concatenate([np.zeros((1, n_atoms, 3)), np.cumsum(steps, axis=0)])
    # Both estimators measure the discrete process's D = dt kT (1 + phi) / (2 (1 - phi)),
    # which is kT / gamma up to (gamma dt)^2 / 12.
    exact = dt * kT * (1 + phi) / (2 * (1 - phi))
    return positions, velocities, exact


@pytest.mark.slow  # 9-18 s; keeps the cold default suite within 10 minutes on 2 cores
def test_msd_and_vacf_recover_the_diffusion_of_an_ornstein_uhlenbeck_process(tmp_path, rng):
    dt, gamma, kT = 0.05, 1.0, 1.5
    positions, velocities, exact = ornstein_uhlenbeck(rng, 64, 1500, dt, gamma, kT)
    assert exact == pytest.approx(kT / gamma, rel=1e-3)
    times = np.arange(len(positions)) * dt
    box = 6.0
    path = write_trajectory(tmp_path / "ou.h5", positions + 3.0, box, times, velocities=velocities)
    window = (5.0, 7.0)  # many correlation times 1/gamma; 5 blocks of 15 time units
    d_msd = analysis.msd(path, window=window).diffusion
    v = analysis.vacf(path, window=window)
    d_vacf = v.diffusion
    assert v.vacf[0] == pytest.approx(3 * kT, rel=0.05)
    for d in (d_msd, d_vacf):
        assert d.window == window
        assert d.n_blocks == 5
        assert 0 < d.error < 0.2 * exact
        assert abs(d.value - exact) < 4 * d.error
    assert abs(d_msd.value - d_vacf.value) < 4 * math.hypot(d_msd.error, d_vacf.error)
    assert v.warnings == []
    assert v.simpson_diffusion == pytest.approx(d_vacf.value, rel=0.01)


def test_vacf_warns_when_frames_are_too_sparse(tmp_path, rng):
    dt, gamma = 1.5, 1.0  # frames far apart compared with the decay time 1/gamma
    positions, velocities, _ = ornstein_uhlenbeck(rng, 16, 200, dt, gamma, 1.0)
    times = np.arange(len(positions)) * dt
    path = write_trajectory(tmp_path / "c.h5", positions, 50.0, times, velocities=velocities)
    result = analysis.vacf(path)
    assert result.warnings and "too sparse" in result.warnings[0]


def test_vacf_needs_velocities(tmp_path, rng):
    path = write_trajectory(tmp_path / "n.h5", rng.uniform(0, 5, (5, 4, 3)), 5.0, range(5))
    with pytest.raises(AnalysisError, match="no velocities"):
        analysis.vacf(path)


def test_selection_restricts_atoms(tmp_path, rng):
    n_frames, dt = 20, 0.1
    velocities = np.zeros((2, 3))
    velocities[1, 0] = 1.0  # only the B atom moves
    times = np.arange(n_frames) * dt
    positions = times[:, None, None] * velocities[None]
    v = np.broadcast_to(velocities, (n_frames, 2, 3))
    path = write_trajectory(tmp_path / "s.h5", positions, 5.0, times, velocities=v, types=[0, 1])
    np.testing.assert_allclose(analysis.msd(path, select="type B").msd, times**2, rtol=1e-6)
    np.testing.assert_allclose(analysis.msd(path, select="type A").msd, 0.0, atol=0)
    np.testing.assert_allclose(analysis.vacf(path, select="type B").vacf, 1.0, rtol=1e-12)
    with pytest.raises(AnalysisError, match="matches no atoms"):
        analysis.msd(path, select="type C")


# ------------------------------------------------------------------- LJ liquid (slow)
@pytest.mark.slow
def test_lj_liquid_diffusion_from_msd_and_vacf_agree(tmp_path):
    """T = 1.0, rho = 0.8, 500 atoms, 40 tau of NVE: Einstein and Green-Kubo D agree."""
    from integrators import VelocityVerlet
    from potentials import LennardJones

    state = md.lattice("fcc", 5, density=0.8)
    md.maxwell_boltzmann(state, 2.0, seed=3)
    potential = LennardJones(cutoff=2.5)
    sim = md.Simulation(state, [potential], VelocityVerlet(dt=0.005))
    for _ in range(30):
        sim.run(50)
        state.velocities *= np.sqrt(1.0 / temperature(state.velocities, state.masses))
    state.step, state.time = 0, 0.0
    production = md.Simulation(state, [potential], VelocityVerlet(dt=0.005))
    path = tmp_path / "liquid.h5"
    with H5MDWriter(path, state, velocities=True) as writer:
        production.attach(writer, interval=5)
        production.run(8000)
    d_msd = analysis.msd(path).diffusion  # 5 blocks of 8 tau, window 0.8 to 4 tau
    v = analysis.vacf(path)
    assert v.warnings == []
    assert d_msd.n_blocks == v.diffusion.n_blocks == 5
    assert d_msd.value > 10 * d_msd.error > 0  # a liquid, and a measurement
    difference = abs(d_msd.value - v.diffusion.value)
    assert difference < 3 * math.hypot(d_msd.error, v.diffusion.error)
    t = analysis.thermo(path)
    assert t.averages["temperature"].mean == pytest.approx(1.0, abs=0.05)
