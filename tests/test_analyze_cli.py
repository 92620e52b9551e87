"""md analyze: every promised file with real content, consistent numbers, clean refusals."""

from __future__ import annotations

import csv
import json

import h5py
import numpy as np
import pytest

import md
from conftest import lj_config_text
from md.cli import main
from md.trajectory import H5MDWriter

CONFIG = lj_config_text(
    seed=7,
    cells=4,
    density=0.8,
    run="steps = {steps}\nthermo_every = 1000",
    output='path = "{name}.h5"\nevery = 5\nvelocities = {velocities}',
)

EVERY_FILE = {
    "thermo.csv",
    "thermo.png",
    "rdf.csv",
    "rdf.png",
    "msd.csv",
    "msd.png",
    "vacf.csv",
    "vacf.png",
    "summary.json",
}


def _simulate(folder, name, steps, velocities):
    config = folder / f"{name}.toml"
    config.write_text(CONFIG.format(steps=steps, name=name, velocities=velocities))
    output = folder / f"{name}.h5"
    assert main(["run", str(config), "-o", str(output), "--no-progress", "--quiet"]) == 0
    return output


@pytest.fixture(scope="module")
def trajectory(tmp_path_factory):
    """256-atom LJ liquid, 61 frames 0.025 tau apart, with velocities."""
    return _simulate(tmp_path_factory.mktemp("run"), "liquid", 300, "true")


@pytest.fixture(scope="module")
def no_velocities(tmp_path_factory):
    """The same system, 5 frames, positions only."""
    return _simulate(tmp_path_factory.mktemp("run"), "positions", 20, "false")


def read_csv(path):
    with open(path, newline="") as handle:
        rows = list(csv.reader(handle))
    header, values = rows[0], np.array(rows[1:], dtype=float)
    return {name: values[:, i] for i, name in enumerate(header)}


def column(table, prefix):
    (name,) = [n for n in table if n == prefix or n.startswith(prefix + " [")]
    return table[name]


def assert_real_image(path):
    import matplotlib.image

    pixels = matplotlib.image.imread(path)
    assert pixels.ndim == 3 and pixels.shape[0] > 200 and pixels.shape[1] > 300
    gray = pixels[..., :3].mean(axis=2)
    drawn = gray < 0.9  # anything not (near) white: axes, text, curves
    assert 0.02 < drawn.mean() < 0.6
    assert gray.std() > 0.1
    # several distinct colours: the curves are drawn, not only black axes
    colours = np.unique((pixels[..., :3] * 255).astype(np.uint8).reshape(-1, 3), axis=0)
    assert len(colours) > 20


def test_analyze_writes_every_promised_file_with_consistent_content(trajectory, tmp_path, capsys):
    out = tmp_path / "analysis"
    assert main(["analyze", str(trajectory), "--out", str(out), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert {p.name for p in out.iterdir()} == EVERY_FILE
    for png in out.glob("*.png"):
        assert_real_image(png)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["units"] == "lj" and summary["unit_labels"]["diffusion"] == "sigma^2/tau"
    assert summary["frames"]["n_selected"] == 61 and summary["skipped"] == []

    # thermo: the CSV holds the stored observables; the summary their numpy mean
    thermo = read_csv(out / "thermo.csv")
    with h5py.File(trajectory) as f:
        stored_temperature = f["observables/temperature/value"][()]
        stored_steps = f["particles/trajectory/position/step"][()]
    np.testing.assert_array_equal(thermo["step"], stored_steps)
    np.testing.assert_allclose(column(thermo, "temperature"), stored_temperature, rtol=1e-15)
    mean = summary["thermo"]["temperature"]["mean"]
    assert mean == pytest.approx(np.mean(stored_temperature), rel=1e-14)
    assert summary["thermo"]["temperature"]["sem"] > 0

    # rdf: the summary's first peak is the CSV maximum; 1.5 tau after the start from
    # an fcc lattice the first shell is still near a / sqrt(2) with about 12 neighbours
    rdf = read_csv(out / "rdf.csv")
    r, g = column(rdf, "r"), rdf["g_A-A"]
    assert len(r) == 200
    shell = summary["rdf"]["A-A"]
    assert shell["first_peak_r"] == pytest.approx(r[np.argmax(g)], rel=1e-12)
    assert shell["first_peak_r"] == pytest.approx((4 / 0.8) ** (1 / 3) / np.sqrt(2), abs=0.1)
    assert shell["coordination"] == pytest.approx(12, abs=1.0)
    upper_edges = r + 0.5 * (r[1] - r[0])  # n(r) is counted up to each bin's upper edge
    n_at_min = np.interp(shell["first_min_r"], upper_edges, rdf["n_A-A"])
    assert shell["coordination"] == pytest.approx(n_at_min, rel=1e-9)

    # msd: refitting the CSV over the reported window gives the reported D
    msd = read_csv(out / "msd.csv")
    lags, values = column(msd, "lag_time"), column(msd, "msd")
    t0, t1 = summary["msd"]["window"]
    inside = (lags >= t0 * (1 - 1e-9)) & (lags <= t1 * (1 + 1e-9))
    assert summary["msd"]["D"] == pytest.approx(np.polyfit(lags[inside], values[inside], 1)[0] / 6)

    # vacf: D is the mean of the running integral over the window
    vacf = read_csv(out / "vacf.csv")
    running = column(vacf, "running_D")
    assert summary["vacf"]["D"] == pytest.approx(running[inside].mean(), rel=1e-12)
    assert vacf["vacf_normalized"][0] == pytest.approx(1.0, rel=1e-12)
    for name in ("<temperature>", "first peak", "D (MSD", "D (VACF", "coordination A-A"):
        assert name in printed


def test_frame_range_selects_the_same_frames_everywhere(trajectory, tmp_path):
    out = tmp_path / "a"
    options = ["--start", "10", "--step", "2", "--thermo", "--msd", "--no-progress"]
    assert main(["analyze", str(trajectory), "--out", str(out), *options]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"]["n_selected"] == len(range(10, 61, 2))
    with h5py.File(trajectory) as f:
        steps = f["particles/trajectory/position/step"][10::2]
        frame_dt = np.diff(f["particles/trajectory/position/time"][:2])[0]
    np.testing.assert_array_equal(read_csv(out / "thermo.csv")["step"], steps)
    lags = column(read_csv(out / "msd.csv"), "lag_time")
    np.testing.assert_allclose(np.diff(lags), 2 * frame_dt, rtol=1e-9)
    written = {p.name for p in out.iterdir()}
    assert written == {"thermo.csv", "thermo.png", "msd.csv", "msd.png", "summary.json"}


def test_existing_output_is_never_replaced_without_overwrite(trajectory, tmp_path, capsys):
    out = tmp_path / "a"
    command = ["analyze", str(trajectory), "--out", str(out), "--thermo", "--no-progress"]
    assert main(command) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    capsys.readouterr()
    assert main([*command, "--stop", "30"]) == 2
    err = capsys.readouterr().err
    assert "exist" in err and "--overwrite" in err and "Traceback" not in err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert main([*command, "--stop", "30", "--overwrite"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"]["n_selected"] == 30


def test_missing_velocities_stop_an_explicit_vacf_and_are_skipped_by_all(
    no_velocities, tmp_path, capsys
):
    out = tmp_path / "a"
    assert main(["analyze", str(no_velocities), "--vacf", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "no velocities" in err and "velocities = true" in err and "Traceback" not in err
    assert not out.exists()
    assert main(["analyze", str(no_velocities), "--all", "--out", str(out), "--no-progress"]) == 0
    assert "vacf skipped: the file stores no velocities" in capsys.readouterr().out
    assert not (out / "vacf.png").exists() and (out / "msd.png").exists()
    summary = json.loads((out / "summary.json").read_text())
    assert "vacf" not in summary and summary["skipped"]


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (["--msd", "--stop", "3"], "needs at least 5 frames"),
        (["--rdf", "--rdf-range", "100"], "half the smallest cell width"),
        (["--rdf", "--rdf-range", "a:b"], "--rdf-range must be MAX or MIN:MAX"),
        (["--rdf", "--rdf-bins", "0"], "--rdf-bins must be >= 1"),
        (["--msd", "--fit", "0.5:0.1"], "--fit needs 0 <= START < END"),
        (["--msd", "--fit", "0.1:30"], "beyond the longest lag"),
        (["--thermo", "--start", "1000"], "selects no frames"),
        (["--thermo", "--step", "0"], "step must be a positive integer"),
        (["--msd", "--select", "type Z"], "matches no atoms"),
        (["--thermo", "--blocks", "0"], "--blocks must be >= 1"),
    ],
)
def test_bad_options_exit_2_with_a_message_and_write_nothing(
    trajectory, tmp_path, capsys, options, message
):
    out = tmp_path / "a"
    assert main(["analyze", str(trajectory), "--out", str(out), "--no-progress", *options]) == 2
    err = capsys.readouterr().err
    assert message in err and err.startswith("md: error:") and "Traceback" not in err
    assert not out.exists()


def test_unreadable_files_exit_2(tmp_path, capsys):
    text = tmp_path / "notes.h5"
    text.write_text("not hdf5")
    plain = tmp_path / "plain.h5"
    with h5py.File(plain, "w") as f:
        f["x"] = np.arange(3)
    for path, message in [
        (tmp_path / "missing.h5", "no such file"),
        (text, "not a readable HDF5 file"),
        (plain, "not in the H5MD layout"),
    ]:
        assert main(["analyze", str(path), "--out", str(tmp_path / "o")]) == 2
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_progress_bar_for_long_analyses(trajectory, tmp_path, capsys):
    assert main(["analyze", str(trajectory), "--rdf", "--out", str(tmp_path / "a")]) == 0
    assert "100%" in capsys.readouterr().err


def test_metal_units_are_labelled_in_files(tmp_path, rng):
    state = md.lattice("fcc", 3, lattice_constant=5.26, type_name="Ar", mass=39.948)
    md.maxwell_boltzmann(state, 100.0, seed=rng, kB=md.units.kB)
    path = tmp_path / "argon.h5"
    with H5MDWriter(path, state, units="metal", velocities=True) as writer:
        for frame in range(12):
            thermo = dict.fromkeys(
                ("potential_energy", "kinetic_energy", "total_energy", "temperature", "pressure"),
                float(frame),
            )
            writer.write(state, thermo=thermo)
            state.positions += state.velocities * 10 * md.units.fs
            state.step, state.time = state.step + 1, state.time + 10 * md.units.fs
    out = tmp_path / "a"
    assert main(["analyze", str(path), "--out", str(out), "--no-progress"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["unit_labels"]["diffusion"] == "A^2/ps"
    assert "time [ps]" in read_csv(out / "thermo.csv")
    assert "r [A]" in read_csv(out / "rdf.csv")
    lags = column(read_csv(out / "msd.csv"), "lag_time")
    assert lags[1] == pytest.approx(0.01, rel=1e-9)  # 10 fs in ps
    vacf0 = summary["vacf"]["vacf_0"]  # <v.v> in (A/ps)^2 = 3 kB T / m converted
    with h5py.File(path) as f:
        stored = f["particles/trajectory/velocity/value"][()]
    assert vacf0 == pytest.approx(np.mean(np.sum(stored**2, axis=2)), rel=1e-12)


@pytest.mark.slow
def test_example_script_runs_and_analyses_an_lj_liquid(tmp_path, monkeypatch):
    import runpy
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "examples" / "lj_liquid_analysis.py"
    monkeypatch.chdir(tmp_path)
    example = runpy.run_path(str(script))  # not as __main__: nothing runs yet
    assert example["main"](["--steps", "2000"]) == 0
    summary = json.loads((tmp_path / "lj_liquid_analysis" / "summary.json").read_text())
    assert {"thermo", "rdf", "msd", "vacf"} <= set(summary)
    assert summary["thermo"]["temperature"]["mean"] == pytest.approx(1.0, abs=0.05)
    assert summary["vacf"]["warnings"] == []
