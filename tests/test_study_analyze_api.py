"""``md integrators`` and ``md analyze`` from Python: prepare (validate, write nothing), then run.

The library functions (:func:`md.studies.prepare_study`,
:func:`md.analysis.prepare_analysis` / :func:`md.analysis.analyze`) do what the
commands do, file for file; the commands only parse, print and map errors to
exit codes. Also the commands' refusals of issue 33 (items 14 and 15): RESPA
without bonds, a reference run that blows up, an output folder on a read-only
filesystem, and spans too long to finish, each a message and an exit code,
never a traceback or a run that never ends.
"""

from __future__ import annotations

import contextlib
import csv
import json
import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_respa import FENE, RUN

import md.analysis.output
import md.studies.study
from conftest import lj_config_text
from md.analysis import AnalysisResults, MSDResult, ThermoResult, analyze, prepare_analysis
from md.assemble import build_components
from md.cli import main
from md.config import load_config
from md.errors import AnalysisError, ConfigError
from md.studies import CSV_COLUMNS, prepare_study

ROOT = Path(__file__).resolve().parents[1]
STUDY = lj_config_text(
    seed=3, temperature=1.2, potential='cutoff_mode = "smooth"\nr_on = 2.0', run=None, output=None
)
BONDED = RUN.format(kind="verlet", extra="", fene=FENE)  # a polymer melt with FENE bonds


@pytest.fixture
def study_config(tmp_path):
    path = tmp_path / "study.toml"
    path.write_text(STUDY)
    return path


@pytest.fixture
def read_only_folder(tmp_path):
    """A folder on a read-only filesystem (a tmpfs mounted ro), or one without write permission.

    Root ignores permissions, so as root the folder is a read-only tmpfs; the
    test is skipped where that cannot be mounted.
    """
    folder = tmp_path / "read-only"
    folder.mkdir()
    if os.geteuid() != 0:
        folder.chmod(0o555)
        yield folder
        folder.chmod(0o755)
        return
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "ro,size=64k", "tmpfs", str(folder)], capture_output=True
    )
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a read-only tmpfs: {mounted.stderr.decode().strip()}")
    try:
        yield folder
    finally:
        subprocess.run(["umount", "-l", str(folder)], check=False)


@contextlib.contextmanager
def deadline(seconds: int):
    """Fail (TimeoutError) instead of hanging when the block runs longer than ``seconds``."""

    def expire(signum, frame):
        raise TimeoutError(f"still running after {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def read_rows(path):
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


# ------------------------------------------------------------------ integrator study
@pytest.mark.slow  # 9-18 s; keeps the cold default suite within 10 minutes on 2 cores
def test_prepare_study_writes_nothing_and_run_gives_what_the_cli_gives(study_config, tmp_path):
    out = tmp_path / "python"
    study = prepare_study(
        study_config, integrators="verlet", dts="0.001:0.004:3", span=0.2, out=out
    )
    assert not out.exists()  # prepared, equilibrated, nothing written
    assert study.names == ["verlet"] and study.thermostat_names == []
    assert study.dts == pytest.approx([0.001, 0.002, 0.004]) and study.span == 0.2
    assert study.state.step == 0 and study.state.time == 0.0
    results = study.run()
    (report,) = results.reports
    assert report.name == "verlet" and abs(report.order - 2.0) < 0.2
    assert sorted(results.files) == ["csv", "energy", "error", "work", "work_csv"]
    assert all(path.parent == out and path.exists() for path in results.files.values())

    cli = tmp_path / "cli"
    assert (
        main(
            [
                "integrators",
                str(study_config),
                "--integrators",
                "verlet",
                "--time",
                "0.2",
                "--dt-range",
                "0.001:0.004:3",
                "--out",
                str(cli),
            ]
        )
        == 0
    )
    python_rows, cli_rows = read_rows(out / "integrators.csv"), read_rows(cli / "integrators.csv")
    measured = [c for c in CSV_COLUMNS if c not in ("wall_per_time",)]
    assert [{c: r[c] for c in measured} for r in python_rows] == [
        {c: r[c] for c in measured} for r in cli_rows
    ]  # the same study, bit for bit (wall-clock times aside)


def test_prepare_study_takes_a_parsed_config_and_sequences(study_config, tmp_path):
    config = load_config(study_config)
    study = prepare_study(
        config,
        integrators=["verlet", "leapfrog"],
        dts=[0.002, 0.004],
        equilibrate=0,
        out=tmp_path / "o",
    )
    assert study.names == ["verlet", "leapfrog"] and study.dts == [0.002, 0.004]
    assert study.measure_dt is None  # an explicit ladder: drift measured mid-ladder
    # no equilibration: the start is the config's system exactly
    built, _, _ = build_components(config)
    np.testing.assert_array_equal(study.state.positions, built.positions)
    with pytest.raises(ConfigError, match="--integrators: unknown warp"):
        prepare_study(config, integrators="warp", out=tmp_path / "o")


def test_thermostats_are_built_as_md_run_builds_them(study_config, tmp_path):
    study = prepare_study(
        study_config,
        integrators="langevin,bussi",
        tau=0.1,
        sample_time=1.0,
        equilibrate=0,
        out=tmp_path / "o",
    )
    assert study.names == [] and study.thermostat_names == ["langevin", "bussi"]
    assert study.setup.temperature == 1.2 and study.setup.tau == pytest.approx(0.1)
    assert (study.setup.n_equilibrate, study.setup.n_sample) == (200, 200)
    for name, coupling in (("langevin", "friction = 10.0"), ("bussi", "tau = 0.1")):
        config = tmp_path / f"{name}.toml"
        config.write_text(
            STUDY.replace('type = "verlet"', f'type = "{name}"\ntemperature = 1.2\n{coupling}')
        )
        _, _, integrator = build_components(load_config(config))
        assert study.thermostat(name).describe() == integrator.describe(), name
    assert study.thermostat("langevin") is not study.thermostat("langevin")  # fresh each time


def test_a_study_that_fails_to_write_leaves_none_of_its_files(study_config, tmp_path, monkeypatch):
    out = tmp_path / "o"
    study = prepare_study(
        study_config, integrators="verlet", dts="0.002,0.004", span=0.05, equilibrate=0, out=out
    )

    def disk_full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(md.studies.study, "plot_work_precision", disk_full)
    with pytest.raises(OSError, match="No space left"):
        study.run()
    assert list(out.iterdir()) == []  # the CSVs and plots written before are gone


def test_respa_without_bonds_is_refused_with_a_message(study_config, tmp_path, capsys):
    out = tmp_path / "o"
    assert (
        main(["integrators", str(study_config), "--integrators", "respa", "--out", str(out)]) == 2
    )
    err = capsys.readouterr().err
    assert "--integrators respa" in err and "no fast potential" in err and "bonds" in err
    assert "Traceback" not in err and not out.exists()
    bonded = tmp_path / "bonded.toml"
    bonded.write_text(BONDED)
    study = prepare_study(bonded, integrators="respa", equilibrate=0, out=out)
    assert study.names == ["respa"]


def test_a_failed_reference_run_is_reported_not_raised(study_config, tmp_path, capsys):
    out = tmp_path / "o"
    # dt 1 and 2 tau: the reference runs at 0.125 and 0.0625 tau blow the liquid up
    assert (
        main(
            [
                "integrators",
                str(study_config),
                "--integrators",
                "verlet",
                "--time",
                "5",
                "--dt-range",
                "1,2",
                "--out",
                str(out),
            ]
        )
        == 1
    )
    err = capsys.readouterr().err
    assert "the reference run at dt = 0.125 failed" in err and "--dt-range" in err
    assert "Traceback" not in err and not out.exists()


def test_an_endless_study_span_is_refused_in_a_real_process(study_config, tmp_path):
    out = tmp_path / "o"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "md.cli",
            "integrators",
            str(study_config),
            "--time",
            "1e300",
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert done.returncode == 2, done.stderr
    assert "1e+300" in done.stderr and "reasonable time" in done.stderr
    assert "Traceback" not in done.stderr and not out.exists()


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (["--time", "inf"], "--time must be"),
        (["--dt-range", "1e-300,1e-299"], "reasonable time"),
        (["--dt-range", "0.001:0.002:100000000"], "--dt-range needs 2 to 1000 time steps"),
        (["--integrators", "bussi", "--sample-time", "1e300"], "--sample-time"),
        (["--integrators", "bussi", "--tau", "1e300"], "--tau"),
        (["--equilibrate", "1000000000000"], "--equilibrate"),
    ],
)
def test_spans_that_cannot_finish_are_refused(study_config, tmp_path, capsys, options, message):
    out = tmp_path / "o"
    with deadline(300):
        assert main(["integrators", str(study_config), "--out", str(out), *options]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and not out.exists()


def test_a_default_study_fits_the_step_budget(study_config, tmp_path):
    study = prepare_study(study_config, out=tmp_path / "o")
    assert len(study.names) >= 13 and study.thermostat_names  # the config gives a temperature
    with pytest.raises(ConfigError, match="reasonable time"):
        prepare_study(study_config, out=tmp_path / "o", max_steps=10_000)


def test_integrators_out_on_a_read_only_filesystem_exits_2(study_config, read_only_folder, capsys):
    out = read_only_folder / "study"
    assert (
        main(["integrators", str(study_config), "--integrators", "verlet", "--out", str(out)]) == 2
    )
    err = capsys.readouterr().err
    assert str(read_only_folder) in err and "Traceback" not in err
    assert ("read-only" in err) == (os.geteuid() == 0)


# ------------------------------------------------------------------ analysis
@pytest.fixture(scope="module")
def trajectory(tmp_path_factory):
    """108-atom LJ liquid, 21 frames 0.025 tau apart, with velocities."""
    folder = tmp_path_factory.mktemp("run")
    config = folder / "liquid.toml"
    config.write_text(
        lj_config_text(
            seed=11,
            run="steps = 100\nthermo_every = 1000",
            output='path = "liquid.h5"\nevery = 5\nvelocities = true',
        )
    )
    output = folder / "liquid.h5"
    assert main(["run", str(config), "-o", str(output), "--no-progress", "--quiet"]) == 0
    return output


def test_analyze_from_python_writes_what_the_cli_writes(trajectory, tmp_path, capsys):
    done = analyze(trajectory, ["thermo", "msd"], n_blocks=2, out=tmp_path / "python")
    assert isinstance(done, AnalysisResults)
    assert list(done.results) == ["thermo", "msd"] and done.skipped == []
    assert isinstance(done.results["thermo"], ThermoResult)
    assert isinstance(done.results["msd"], MSDResult)
    assert done.files == ["thermo.csv", "thermo.png", "msd.csv", "msd.png", "summary.json"]
    assert sorted(p.name for p in done.out.iterdir()) == sorted(done.files)
    summary = json.loads((done.out / "summary.json").read_text())
    assert summary["msd"]["D"] == done.results["msd"].diffusion.value > 0
    assert summary["frames"]["n_selected"] == 21

    cli = tmp_path / "cli"
    assert (
        main(
            [
                "analyze",
                str(trajectory),
                "--thermo",
                "--msd",
                "--blocks",
                "2",
                "--out",
                str(cli),
                "--no-progress",
            ]
        )
        == 0
    )
    assert "D (MSD" in capsys.readouterr().out
    for name in ("thermo.csv", "msd.csv", "summary.json"):
        assert (cli / name).read_bytes() == (done.out / name).read_bytes(), name


def test_prepare_analysis_checks_everything_and_writes_nothing(trajectory, tmp_path):
    out = tmp_path / "o"
    prepared = prepare_analysis(trajectory, out=out, snapshot=True)
    assert prepared.selected == ["thermo", "rdf", "msd", "vacf"] and prepared.skipped == []
    assert prepared.files[-2:] == ["summary.json", "snapshot.png"] and not out.exists()
    partial = prepare_analysis(trajectory, stop=3, out=out)  # 3 frames: no MSD, no VACF
    assert partial.selected == ["thermo", "rdf"]
    assert [note.split(":")[0] for note in partial.skipped] == ["msd skipped", "vacf skipped"]
    with pytest.raises(AnalysisError, match="cannot compute msd: msd needs at least 5 frames"):
        prepare_analysis(trajectory, stop=3, required=["msd"], out=out)
    with pytest.raises(AnalysisError, match="unknown analysis 'gofr'"):
        prepare_analysis(trajectory, ["gofr"], out=out)
    with pytest.raises(AnalysisError, match="--fit needs 0 <= START < END"):
        prepare_analysis(trajectory, ["msd"], window=(0.5, math.inf), out=out)
    assert not out.exists()


def test_analysis_that_fails_to_write_leaves_none_of_its_files(
    trajectory, tmp_path, monkeypatch, capsys
):
    def disk_full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setitem(md.analysis.output.WRITERS, "msd", disk_full)
    out = tmp_path / "o"
    assert (
        main(["analyze", str(trajectory), "--thermo", "--msd", "--out", str(out), "--no-progress"])
        == 2
    )
    err = capsys.readouterr().err
    assert "cannot write the analysis files" in err and "No space left" in err
    assert "Traceback" not in err and list(out.iterdir()) == []  # thermo's files removed


def test_analyze_out_on_a_read_only_filesystem_exits_2(trajectory, read_only_folder, capsys):
    out = read_only_folder / "analysis"
    assert main(["analyze", str(trajectory), "--thermo", "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert str(read_only_folder) in err and "Traceback" not in err
    assert ("read-only" in err) == (os.geteuid() == 0)
    assert not out.exists()
