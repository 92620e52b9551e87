"""md sweep: planning and seeds, the TOML writer, and sweeps on a two-worker local Dask cluster.

The cluster tests compare every output of a Dask sweep with the same runs
done serially (``md run`` in this process, one thread), dataset by dataset
and bit for bit; kill a worker while its run is in flight; run a sweep
twice; and let one run blow up.
"""

from __future__ import annotations

import csv
import logging
import math
import os
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import h5py
import numpy as np
import pytest
import tomli_w

import md
from md import parallel
from md.cli import main
from md.sweeps import (
    SweepError,
    SweepTable,
    parse_vary,
    plan_sweep,
    replica_seed,
    run_sweep,
)

BASE_SEED = 5
BASE = f"""\
units = "lj"
seed = {BASE_SEED}

[system]
lattice = "fcc"
cells = 3                  # 108 atoms
density = 0.8442
temperature = 1.0

[[potentials]]
type = "lj"
cutoff = 2.5
cutoff_mode = "shift"

[integrator]
type = "verlet"
dt = 0.005

[run]
steps = 200
thermo_every = 100

[output]
path = "ignored.h5"
every = 10
velocities = true
"""
VARY = {"system.temperature": [1.0, 1.5]}
REPLICAS = 2
EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


# ---------------------------------------------------------------- helpers
def write_base(folder: Path, text: str = BASE, name: str = "base.toml") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    path.write_text(text)
    return path


def run_serially(config_text: str, folder: Path, name: str, *options: str) -> Path:
    """``md run`` of ``config_text`` in this process on one thread, as a sweep's child does."""
    config = folder / f"{name}.toml"
    config.write_text(config_text)
    output = folder / f"{name}.h5"
    before = parallel.get_threads()
    try:
        code = main(
            [
                "run",
                str(config),
                "--output",
                str(output),
                "--threads",
                "1",
                "--no-progress",
                "-q",
                *options,
            ]
        )
    finally:
        parallel.set_threads(before)
    assert code == 0
    return output


def datasets(path: Path) -> dict[str, bytes]:
    """The bytes of every per-frame dataset of an H5MD file (run ids and times excluded)."""
    found = {}

    def visit(name, item):
        if isinstance(item, h5py.Dataset) and (name.endswith("/value") or name.endswith("/step")):
            found[name] = (item.dtype.str, item.shape, item[()].tobytes())

    with h5py.File(path, "r") as f:
        f.visititems(visit)
    return found


def assert_same_run(a: Path, b: Path) -> None:
    first, second = datasets(a), datasets(b)
    assert sorted(first) == sorted(second)
    assert any("velocity" in name for name in first) and any("observables" in n for n in first)
    for name in first:
        assert first[name] == second[name], f"{a} and {b} differ in {name}"


def start_cluster(n_workers: int = 2):
    from distributed import Client, LocalCluster

    cluster = LocalCluster(
        n_workers=n_workers,
        threads_per_worker=1,
        processes=True,
        dashboard_address=":0",
        silence_logs=logging.ERROR,
    )
    return cluster, Client(cluster)


@pytest.fixture(scope="module")
def cluster():
    cluster, client = start_cluster()
    yield client
    client.close()
    cluster.close()


@pytest.fixture(scope="module")
def base_config(tmp_path_factory) -> Path:
    return write_base(tmp_path_factory.mktemp("base"))


@pytest.fixture(scope="module")
def serial(base_config, tmp_path_factory) -> dict[str, Path]:
    """Outputs of the sweep's runs done one after another, by label."""
    folder = tmp_path_factory.mktemp("serial")
    plan = plan_sweep(base_config, VARY, REPLICAS, out=folder / "unused")
    return {run.label: run_serially(run.config_text, folder, run.label) for run in plan.runs}


@pytest.fixture(scope="module")
def first_sweep(base_config, cluster, tmp_path_factory):
    out = tmp_path_factory.mktemp("sweep") / "out"
    table = md.sweep(base_config, vary=VARY, replicas=REPLICAS, out=out, client=cluster)
    return table, out


# ---------------------------------------------------------------- planning
def test_parse_vary_reads_toml_values_lists_ranges_and_plain_strings():
    assert parse_vary("system.temperature=1.0,1.5") == ("system.temperature", [1.0, 1.5])
    assert parse_vary("system.cells=[3, 3, 3],[4,4,4]") == ("system.cells", [[3, 3, 3], [4, 4, 4]])
    assert parse_vary("integrator.dt=0.002:0.006:3") == ("integrator.dt", [0.002, 0.004, 0.006])
    assert parse_vary('system.lattice=fcc,"bcc"') == ("system.lattice", ["fcc", "bcc"])
    key, values = parse_vary("seed=1,2")
    assert values == [1, 2] and all(isinstance(v, int) for v in values)
    for bad, word in (
        ("temperature", "KEY="),
        ("a.b=", "KEY="),
        ("a..b=1", "dotted"),
        ("a=1,1.0", "twice"),
        ("a=1,,2", "empty"),
    ):
        with pytest.raises(SweepError, match=word):
            parse_vary(bad)


def test_plan_is_the_cartesian_product_times_replicas_with_derived_seeds(tmp_path):
    base = write_base(tmp_path)
    vary = ["system.temperature=1.0,1.5", "integrator.dt=0.002,0.004,0.005"]
    plan = plan_sweep(base, vary, replicas=3, out=tmp_path / "out")
    assert len(plan.runs) == 2 * 3 * 3
    assert len({run.label for run in plan.runs}) == len(plan.runs)
    points = [dict(run.point) for run in plan.runs[::3]]
    dts = (0.002, 0.004, 0.005)
    expected = [{"system.temperature": t, "integrator.dt": dt} for t in (1.0, 1.5) for dt in dts]
    assert points == expected
    for run in plan.runs:
        data = tomllib.loads(run.config_text)
        assert data["system"]["temperature"] == dict(run.point)["system.temperature"]
        assert data["integrator"]["dt"] == dict(run.point)["integrator.dt"]
        assert data["seed"] == run.seed == replica_seed(BASE_SEED, run.replica)
        assert data["output"]["path"] == str(tmp_path / "out" / f"{run.label}.h5")
        assert (run.n_frames, run.last_step) == (21, 200)
    # Replica 0 keeps the config's seed; replica r has the same seed at every point,
    # and different replicas have different seeds.
    seeds = {r: {run.seed for run in plan.runs if run.replica == r} for r in range(3)}
    assert seeds[0] == {BASE_SEED}
    assert all(len(s) == 1 for s in seeds.values()) and len(set.union(*seeds.values())) == 3
    # Deterministic: planning again gives the same configs.
    again = plan_sweep(base, vary, replicas=3, out=tmp_path / "out")
    assert [r.config_text for r in again.runs] == [r.config_text for r in plan.runs]
    assert not (tmp_path / "out").exists()  # planning writes nothing


def test_varied_seed_and_thermostat_seed(tmp_path):
    text = BASE.replace(
        'type = "verlet"', 'type = "langevin"\ntemperature = 1.0\nfriction = 1.0\nseed = 11'
    )
    base = write_base(tmp_path, text)
    plan = plan_sweep(base, {"seed": [3, 4]}, replicas=2, out=tmp_path / "out")
    data = [tomllib.loads(run.config_text) for run in plan.runs]
    assert [d["seed"] for d in data] == [3, replica_seed(3, 1), 4, replica_seed(4, 1)]
    assert [d["integrator"]["seed"] for d in data] == [11, replica_seed(11, 1)] * 2


def test_bad_keys_and_values_are_refused_before_anything_is_written(tmp_path, capsys):
    base = write_base(tmp_path)
    out = tmp_path / "out"
    cases = [
        (["system.temprature=1.0"], "temprature"),
        (["integrator.dt=0.005,-0.001"], r"dt=-0.001.*dt: must be positive"),
        (["potentials.cutoff=2.0"], "potentials.0.cutoff"),
        (["potentials.3.cutoff=2.0"], "has 1 entries"),
        (["output.path=x.h5"], "cannot be varied"),
        (["system.lattice=fcc,hcp"], "hcp"),
        (["potentials.0.cutoff=2.0,9.0"], "cutoff=9.0"),
    ]
    for vary, message in cases:
        with pytest.raises(SweepError, match=message):
            plan_sweep(base, vary, out=out)
        argv = ["sweep", str(base), "--out", str(out)] + [f"--vary={v}" for v in vary]
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("md: error:"), err
    assert not out.exists()


def test_toml_writer_round_trips_every_example_config():
    # The sweep writes each run's config with tomli_w: every example must survive it.
    for path in sorted(EXAMPLES.glob("*.toml")):
        data = tomllib.loads(path.read_text())
        assert tomllib.loads(tomli_w.dumps(data)) == data, path


def test_points_average_replicas_with_their_standard_error():
    rows = []
    values = {1.0: [2.0, 2.5, 3.5], 2.0: [7.0]}
    for t, ps in values.items():
        for replica, p in enumerate(ps):
            rows.append(
                {
                    "system.temperature": t,
                    "replica": replica,
                    "status": "done",
                    "pressure": p,
                    "pressure_err": 0.1 * (replica + 1),
                }
            )
    table = SweepTable(keys=["system.temperature"], rows=rows)
    first, second = table.points("P")
    assert first["mean"] == pytest.approx(np.mean(values[1.0]))
    assert first["err"] == pytest.approx(np.std(values[1.0], ddof=1) / math.sqrt(3))
    assert (second["mean"], second["err"], second["n"]) == (7.0, 0.1, 1)  # its own block error
    with pytest.raises(SweepError, match="unknown result column"):
        table.points("pressur")


def test_importing_md_does_not_import_dask():
    code = (
        "import sys, md\n"
        "assert 'distributed' not in sys.modules and 'dask' not in sys.modules\n"
        "sweep = md.sweep\n"
        "assert 'distributed' not in sys.modules and callable(sweep)\n"
        "from md.sweeps import sweep as function\n"
        "assert callable(function) and 'distributed' not in sys.modules\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


# ------------------------------------------------------------- on a cluster
def test_sweep_outputs_equal_serial_runs_bit_for_bit(first_sweep, serial, base_config, tmp_path):
    table, out = first_sweep
    assert [row["status"] for row in table] == ["done"] * 4
    assert sorted(p.name for p in out.glob("*.h5")) == sorted(f"{k}.h5" for k in serial)
    for label, reference in serial.items():
        assert_same_run(out / f"{label}.h5", reference)
    assert not (out / ".partial").exists()
    # Replica 0 is md run of the base config with only the varied key changed.
    text = BASE.replace("temperature = 1.0", "temperature = 1.5")
    plain = run_serially(text, tmp_path, "plain")
    assert_same_run(out / "temperature=1.5_r0.h5", plain)
    # Replicas of a point differ (other seeds).
    velocity = "particles/trajectory/velocity/value"
    first, second = out / "temperature=1.5_r0.h5", out / "temperature=1.5_r1.h5"
    with h5py.File(first) as a, h5py.File(second) as b:
        assert not np.allclose(a[velocity][0], b[velocity][0])


def test_collated_table_holds_each_runs_averages(first_sweep):
    table, out = first_sweep
    with open(out / "sweep.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert [r["label"] for r in rows] == [r["label"] for r in table]
    for row, csv_row in zip(table, rows, strict=True):
        with h5py.File(row["output"]) as f:
            series = {n: f[f"observables/{n}/value"][()] for n in f["observables"]}
            n_atoms = f["particles/trajectory/position/value"].shape[1]
        assert row["temperature"] == pytest.approx(series["temperature"].mean(), rel=1e-12)
        assert row["pressure"] == pytest.approx(series["pressure"].mean(), rel=1e-12)
        assert row["total_energy_per_atom"] == pytest.approx(
            series["total_energy"].mean() / n_atoms, rel=1e-12
        )
        assert row["temperature_err"] > 0
        assert float(csv_row["pressure"]) == row["pressure"]
        assert float(csv_row["system.temperature"]) == row["system.temperature"]
        assert int(csv_row["seed"]) == replica_seed(BASE_SEED, row["replica"])


def test_second_invocation_skips_complete_runs_and_finishes_the_rest(
    first_sweep, serial, base_config, cluster
):
    table, out = first_sweep
    missing = out / "temperature=1.0_r1.h5"
    kept = {p: (p.stat().st_ino, p.stat().st_mtime_ns) for p in out.glob("*.h5") if p != missing}
    missing.unlink()
    again = md.sweep(base_config, vary=VARY, replicas=REPLICAS, out=out, client=cluster)
    status = {row["label"]: row["status"] for row in again}
    assert status == {label: "done" if label == missing.stem else "skipped" for label in serial}
    assert {p: (p.stat().st_ino, p.stat().st_mtime_ns) for p in kept} == kept
    assert_same_run(missing, serial[missing.stem])
    for before, after in zip(table, again, strict=True):
        assert before["pressure"] == after["pressure"]


def test_a_changed_config_does_not_reuse_or_replace_outputs(first_sweep, tmp_path, capsys):
    _, out = first_sweep
    changed = write_base(tmp_path, BASE.replace("steps = 200", "steps = 100"))
    argv = [
        "sweep",
        str(changed),
        "--vary",
        "system.temperature=1.0,1.5",
        "--replicas",
        "2",
        "--out",
        str(out),
    ]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "different config" in err and len(err.strip().splitlines()) == 1


def test_a_failing_run_is_reported_and_the_rest_complete(
    base_config, serial, cluster, tmp_path, capsys
):
    out = tmp_path / "out"
    argv = [
        "sweep",
        str(base_config),
        "--vary",
        "integrator.dt=0.005,0.5",
        "--out",
        str(out),
        "--scheduler",
        cluster.scheduler.address,
        "--no-progress",
        "--plot",
        "T",
    ]
    assert main(argv) == 1
    captured = capsys.readouterr()
    assert "run dt=0.5_r0 failed: md run exit 1: step 1: atom" in captured.err
    assert "1 of 2 runs failed" in captured.err
    # The good run is the temperature = 1.0 replica 0 of the other sweep, bit for bit.
    assert_same_run(out / "dt=0.005_r0.h5", serial["temperature=1.0_r0"])
    assert not (out / "dt=0.5_r0.h5").exists() and not (out / ".partial").exists()
    with open(out / "sweep.csv") as handle:
        rows = {r["label"]: r for r in csv.DictReader(handle)}
    assert rows["dt=0.5_r0"]["status"] == "failed"
    assert "more than the neighbour-list skin" in rows["dt=0.5_r0"]["message"]
    assert rows["dt=0.005_r0"]["status"] == "done" and float(rows["dt=0.005_r0"]["temperature"])
    assert (out / "temperature.png").stat().st_size > 0
    assert "step 1: atom" in (out / "logs" / "dt=0.5_r0.log").read_text()


@pytest.mark.slow  # keeps the default suite within its 10 minutes
def test_an_interrupted_run_resumes_from_its_checkpoint(base_config, serial, cluster, tmp_path):
    out = tmp_path / "out"
    plan = plan_sweep(base_config, VARY, REPLICAS, out=out)
    resumable, damaged = plan.runs[0].label, plan.runs[1].label
    # What a worker killed after step 100 leaves: the run's files in OUT/.partial/<label>/.
    partial = out / ".partial" / resumable
    partial.mkdir(parents=True)
    run_serially(plan.runs[0].config_text, partial, resumable, "--steps", "100")
    assert (partial / f"{resumable}.h5.ckpt").exists()
    # A checkpoint that cannot be read: the run starts afresh.
    (out / ".partial" / damaged).mkdir()
    (out / ".partial" / damaged / f"{damaged}.h5.ckpt").write_bytes(b"not a checkpoint")
    table = md.sweep(base_config, vary=VARY, replicas=REPLICAS, out=out, client=cluster)
    assert [row["status"] for row in table] == ["done"] * 4
    for label, reference in serial.items():
        assert_same_run(out / f"{label}.h5", reference)
    log = (out / "logs" / f"{resumable}.log").read_text()
    assert "--resume" in log and "--overwrite" not in log and "resuming at step 100" in log
    log = (out / "logs" / f"{damaged}.log").read_text()
    assert log.index("--resume") < log.index("--overwrite")
    assert not (out / ".partial").exists()


@pytest.mark.slow  # keeps the default suite within its 10 minutes
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="uses /proc and prctl")
def test_killing_a_worker_mid_run_still_completes_the_sweep(base_config, serial, tmp_path):
    cluster, client = start_cluster()
    killed = {}

    def kill_one_in_flight(progress):
        if killed:
            return
        for info in progress.running.values():
            child = info["child"]
            try:
                os.kill(child, signal.SIGSTOP)  # it cannot finish now; then check it is alive
                for _ in range(200):  # until the stop has taken effect (or it had ended)
                    state = Path(f"/proc/{child}/stat").read_text().rsplit(")", 1)[1].split()[0]
                    if state in "TZX":
                        break
                    time.sleep(0.01)
            except (ProcessLookupError, FileNotFoundError):
                continue
            if state == "T":  # stopped while running: its run is in flight
                os.kill(info["pid"], signal.SIGKILL)
                killed.update(worker=info["pid"], child=child)
                # It dies with its worker, or, if stopped before it could ask for that,
                # sees on waking that its worker is gone and exits.
                os.kill(child, signal.SIGCONT)
                return
            os.kill(child, signal.SIGCONT)

    progress_seen = []
    try:
        plan = plan_sweep(base_config, VARY, REPLICAS, out=tmp_path / "out")
        table = run_sweep(
            plan, client, progress=lambda p: (kill_one_in_flight(p), progress_seen.append(p))
        )
    finally:
        client.close()
        cluster.close()
    assert killed, "no run was seen in flight"
    assert [row["status"] for row in table] == ["done"] * 4
    assert progress_seen[-1].retried >= 1
    for label, reference in serial.items():
        assert_same_run(tmp_path / "out" / f"{label}.h5", reference)
    assert not (tmp_path / "out" / ".partial").exists()
    deadline = time.monotonic() + 30
    while Path(f"/proc/{killed['child']}").exists() and time.monotonic() < deadline:
        time.sleep(0.1)  # the orphaned run was killed with its worker
    assert not Path(f"/proc/{killed['child']}").exists()
