"""md.run_config: what ``md run`` does, from Python, file for file."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

import md
from conftest import lj_config_text
from md.cli import main
from md.run import FAILED, prepare


@pytest.fixture
def config(tmp_path):
    path = tmp_path / "run.toml"
    path.write_text(lj_config_text(run="steps = 30\nthermo_every = 10"))
    return path


def _frames(path):
    with h5py.File(path, "r") as f:
        group = f["particles/trajectory"]
        return group["position/value"][()], group["velocity/value"][()], group["position/step"][()]


def test_run_config_writes_what_md_run_writes(config, tmp_path):
    sim, summary = md.run_config(config, output=tmp_path / "api.h5")
    assert main(["run", str(config), "-o", str(tmp_path / "cli.h5"), "-q", "--no-progress"]) == 0
    assert summary.status == "completed" and summary.n_frames == 4 and summary.n_steps == 30
    assert sim.state.step == 30
    api, cli = _frames(tmp_path / "api.h5"), _frames(tmp_path / "cli.h5")
    for a, b in zip(api, cli, strict=True):
        np.testing.assert_array_equal(a, b)  # same seed, same kernels: bit for bit
    # The summary's thermo is the simulation's own.
    assert summary.last["total_energy"] == pytest.approx(sim.thermo()["total_energy"])
    assert abs(summary.last["total_energy"] - summary.first["total_energy"]) < 1e-3 * 108


def test_run_config_steps_and_resume_continue_bit_for_bit(config, tmp_path):
    md.run_config(config, steps=30, output=tmp_path / "whole.h5")
    md.run_config(config, steps=20, output=tmp_path / "part.h5")
    sim, summary = md.run_config(config, steps=30, output=tmp_path / "part.h5", resume=True)
    assert summary.status == "completed" and sim.state.step == 30
    whole, part = _frames(tmp_path / "whole.h5"), _frames(tmp_path / "part.h5")
    for a, b in zip(whole, part, strict=True):
        np.testing.assert_array_equal(a, b)


def test_run_config_refuses_bad_input_before_writing(config, tmp_path):
    output = tmp_path / "never.h5"
    with pytest.raises(md.ConfigError, match="steps"):
        md.run_config(config, steps=-1, output=output)
    bad = tmp_path / "bad.toml"
    bad.write_text(lj_config_text(integrator='type = "verlet"\ndt = -1.0'))
    with pytest.raises(md.ConfigError, match="dt"):
        md.run_config(bad, output=output)
    assert not output.exists() and not output.with_name("never.h5.ckpt").exists()
    md.run_config(config, output=tmp_path / "taken.h5")
    with pytest.raises(md.ConfigError, match="already exists"):
        md.run_config(config, output=tmp_path / "taken.h5")


def test_a_blow_up_is_a_failed_summary_with_the_step(tmp_path):
    path = tmp_path / "hot.toml"
    path.write_text(lj_config_text(integrator='type = "verlet"\ndt = 0.5', run="steps = 50"))
    sim, summary = md.run_config(path, output=tmp_path / "hot.h5")
    assert summary.status == FAILED and "step" in summary.message
    assert summary.last_checkpoint_step is not None
    assert (tmp_path / "hot.h5").exists()  # frames written before the blow-up are kept


def test_prepare_writes_nothing_and_reports_the_plan(config, tmp_path):
    run = prepare(config, steps=12, output=tmp_path / "later.h5", threads=1)
    assert run.n_steps == 12 and not run.resuming and not run.complete
    assert not (tmp_path / "later.h5").exists()
    assert run.parameters["n_steps"] == 12 and run.sim.state.n_atoms == 108
    summary = run.execute(handle_signals=False)
    assert summary.status == "completed" and summary.n_frames == 2


def _drift_lines(out: str) -> list[str]:
    return [line for line in out.splitlines() if "drift" in line]


@pytest.mark.parametrize(
    "integrator",
    ['type = "verlet"\ndt = 0.005', 'type = "bussi"\ndt = 0.005\ntemperature = 1.0\ntau = 0.1'],
)
def test_a_resumed_run_reports_the_drift_of_the_whole_run(tmp_path, capsys, integrator):
    """Was the drift of the resumed part only: the checkpoint now keeps step 0's energies."""
    text = lj_config_text(integrator=integrator, run="steps = 40\nthermo_every = 10")
    (tmp_path / "run.toml").write_text(text)
    quiet = ("-q", "--no-progress")
    assert main(["run", str(tmp_path / "run.toml"), "-o", str(tmp_path / "whole.h5"), *quiet]) == 0
    whole = _drift_lines(capsys.readouterr().out)
    part = str(tmp_path / "part.h5")
    assert main(["run", str(tmp_path / "run.toml"), "-o", part, "--steps", "20", *quiet]) == 0
    capsys.readouterr()
    assert main(["run", str(tmp_path / "run.toml"), "-o", part, "--resume", *quiet]) == 0
    resumed = _drift_lines(capsys.readouterr().out)
    assert len(whole) == (2 if "bussi" in integrator else 1)
    assert resumed == whole  # bit-for-bit continuation: the same numbers, from step 0
    _, whole = md.run_config(tmp_path / "run.toml", output=tmp_path / "api.h5")
    md.run_config(tmp_path / "run.toml", output=tmp_path / "api2.h5", steps=20)
    _, again = md.run_config(tmp_path / "run.toml", output=tmp_path / "api2.h5", resume=True)
    assert again.first["step"] == 20 and again.start["step"] == 0
    assert again.start == whole.start == {key: whole.first[key] for key in again.start}


def test_a_checkpoint_without_the_start_energies_reports_from_where_it_resumed(tmp_path, capsys):
    import json

    (tmp_path / "run.toml").write_text(lj_config_text(run="steps = 40\nthermo_every = 10"))
    part, quiet = str(tmp_path / "part.h5"), ("-q", "--no-progress")
    assert main(["run", str(tmp_path / "run.toml"), "-o", part, "--steps", "20", *quiet]) == 0
    checkpoint = tmp_path / "part.h5.ckpt"
    with np.load(checkpoint) as npz:  # as checkpoints were written before they kept them
        arrays = {name: npz[name] for name in npz.files}
    meta = json.loads(str(arrays["meta"][()]))
    del meta["extra"]["start"]
    arrays["meta"] = np.array(json.dumps(meta))
    with open(checkpoint, "wb") as handle:
        np.savez(handle, **arrays)
    capsys.readouterr()
    assert main(["run", str(tmp_path / "run.toml"), "-o", part, "--resume", *quiet]) == 0
    assert "Relative total-energy drift (E_end - E_start)/|E_start| since step 20:" in (
        capsys.readouterr().out
    )
