"""Soak test of ``md run``: a long run of a small system, stopped by SIGTERM and resumed.

    PYTHONPATH=. python3 benchmarks/soak.py                       # 10^6 steps, 5 cycles
    PYTHONPATH=. python3 benchmarks/soak.py --steps 20000 --cycles 3

Two runs of one config (a small Lennard-Jones liquid, thermo every step,
checkpoints and frames every ``--checkpoint-every`` steps, one thread), each a
real ``md run`` process:

- uninterrupted, from step 0 to ``--steps``;
- interrupted: SIGTERM at ``--cycles`` random steps, each time resumed with the
  command the stopped run prints (``md run CONFIG --resume``), until it completes.

It samples every process's resident memory (RSS) as it runs, and after each
SIGTERM checks that the run exited 143 with a readable trajectory and checkpoint.
At the end it checks that both trajectories open (h5py, our reader, MDAnalysis
through :func:`md.trajectory.open_trajectory`), that the interrupted run's frames,
final positions and velocities and checkpoint equal the uninterrupted run's bit for
bit, that the thermo rows printed for every step agree (the last printed for a
step wins after a resume), and that the uninterrupted run's RSS over its last
fifth of steps exceeds that over its 10-30 % by less than ``--rss-growth-mb``.
It prints a summary; the exit code is 0 when every check passed, 1 otherwise.
"""

from __future__ import annotations

import argparse
import os
import random
import shlex
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import psutil

ROOT = Path(__file__).resolve().parents[1]
MD = [sys.executable, "-m", "md.cli"]

CONFIG = """\
units = "lj"
seed = {seed}

[system]
lattice = "fcc"
cells = {cells}
density = 0.8442
temperature = 1.2

[[potentials]]
type = "lj"
cutoff = {cutoff}
cutoff_mode = "shift"

[integrator]
type = "{integrator}"
dt = 0.004
{extra}
[run]
steps = {steps}
thermo_every = 1

[output]
path = "soak.h5"
every = {every}
velocities = true
checkpoint_every = {every}
"""


def write_config(folder: Path, args) -> Path:
    cells = {32: 2, 108: 3, 256: 4}[args.atoms]
    edge = cells * (4 / 0.8442) ** (1 / 3)
    cutoff = min(2.5, round(0.49 * edge, 3))  # the minimum image needs 2 cutoffs < the box
    extra = "temperature = 1.2\ntau = 0.5\n" if args.integrator == "bussi" else ""
    path = folder / "run.toml"
    path.write_text(
        CONFIG.format(
            seed=args.seed,
            cells=cells,
            cutoff=cutoff,
            steps=args.steps,
            every=args.checkpoint_every,
            integrator=args.integrator,
            extra=extra,
        )
    )
    return path


class Process:
    """One ``md run`` process, its stdout (the thermo rows) in a file, its RSS sampled."""

    def __init__(self, argv, folder: Path, label: str) -> None:
        self.label = label
        self.out_path = folder / f"{label}.out"
        self.err_path = folder / f"{label}.err"
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
        with open(self.out_path, "wb") as out, open(self.err_path, "wb") as err:
            self.popen = subprocess.Popen(argv, cwd=folder, stdout=out, stderr=err, env=env)
        self.started = time.monotonic()
        #: (seconds since start, RSS bytes, last step printed or -1)
        self.samples: list[tuple[float, int, int]] = []
        self._psutil = psutil.Process(self.popen.pid)

    def sample(self) -> None:
        try:
            rss = self._psutil.memory_info().rss
        except psutil.Error:  # it just ended
            return
        step = self.last_step()
        self.samples.append((time.monotonic() - self.started, rss, -1 if step is None else step))

    def last_step(self) -> int | None:
        """The step of the last complete thermo row printed so far."""
        try:
            with open(self.out_path, "rb") as handle:
                handle.seek(max(0, self.out_path.stat().st_size - 400))
                lines = handle.read().split(b"\n")[:-1]  # the last may be half written
        except OSError:
            return None
        for line in reversed(lines):
            words = line.split()
            if words and words[0].isdigit():
                return int(words[0])
        return None

    def wait(self, poll: float, until_step: int | None = None, limit: float = 1e9) -> int | None:
        """Sample RSS until the process ends (return its code) or prints ``until_step``."""
        while time.monotonic() - self.started < limit:
            self.sample()
            code = self.popen.poll()
            if code is not None:
                return code
            if until_step is not None and (self.last_step() or -1) >= until_step:
                return None
            time.sleep(poll)
        self.popen.kill()
        raise TimeoutError(f"{self.label} ran past {limit:g} s")

    def stderr(self) -> str:
        return self.err_path.read_text(errors="replace")

    def peak_mb(self) -> float:
        return max((rss for _, rss, _ in self.samples), default=0) / 2**20


def thermo_rows(paths) -> dict[int, bytes]:
    """Step -> the thermo row printed for it, the later file winning (a resumed run's)."""
    rows: dict[int, bytes] = {}
    for path in paths:
        with open(path, "rb") as handle:
            for line in handle:
                words = line.split(None, 1)
                if words and words[0].isdigit():
                    rows[int(words[0])] = line.rstrip(b"\n")
    return rows


def check_files(folder: Path, expect_complete: int | None = None) -> list[str]:
    """Problems with the trajectory and checkpoint in ``folder`` (empty: none)."""
    import h5py

    from md.checkpoint import checkpoint_path, read_checkpoint
    from md.trajectory import read_trajectory, verify_frames

    problems = []
    output = folder / "soak.h5"
    try:
        with h5py.File(output, "r") as f:
            f.visit(lambda name: None)
        n_frames = verify_frames(output)
        trajectory = read_trajectory(output)
        if len(trajectory.steps) != n_frames or not np.all(np.diff(trajectory.steps) > 0):
            problems.append(f"{output}: frames' steps {trajectory.steps[:5]}... not increasing")
        checkpoint = read_checkpoint(checkpoint_path(output))
        if expect_complete is not None and checkpoint.state.step != expect_complete:
            problems.append(f"checkpoint at step {checkpoint.state.step}, not {expect_complete}")
        leftovers = [p.name for p in folder.glob(".*.tmp")]
        if leftovers:
            problems.append(f"temporary files left in {folder}: {leftovers}")
    except Exception as error:  # any failure to read is the finding
        problems.append(f"{folder}: {type(error).__name__}: {error}")
    return problems


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    a, b = np.ascontiguousarray(a), np.ascontiguousarray(b)
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


def compare(whole: Path, pieces: Path) -> list[str]:
    from md.checkpoint import checkpoint_path, read_checkpoint
    from md.trajectory import open_trajectory, read_trajectory

    problems = []
    a, b = read_trajectory(whole / "soak.h5"), read_trajectory(pieces / "soak.h5")
    if not same_bits(a.steps, b.steps):
        problems.append(f"frame steps differ: {len(a.steps)} frames against {len(b.steps)}")
    else:
        for name in ("positions", "velocities", "boxes"):
            x, y = getattr(a, name, None), getattr(b, name, None)
            if x is None or y is None or not same_bits(np.asarray(x), np.asarray(y)):
                bad = ""
                if x is not None and y is not None and np.shape(x) == np.shape(y):
                    frames = np.flatnonzero(np.any(np.asarray(x) != np.asarray(y), axis=(1, 2)))
                    bad = f" (first differing frame {frames[:1]}, step {a.steps[frames[:1]]})"
                problems.append(f"{name} of the frames differ{bad}")
    ca = read_checkpoint(checkpoint_path(whole / "soak.h5")).state
    cb = read_checkpoint(checkpoint_path(pieces / "soak.h5")).state
    for name in ("positions", "velocities", "box"):
        if not same_bits(getattr(ca, name), getattr(cb, name)):
            problems.append(f"final {name} differ (checkpoints at steps {ca.step}, {cb.step})")
    for folder in (whole, pieces):
        try:
            universe = open_trajectory(folder / "soak.h5")
            universe.trajectory[-1]
            universe.trajectory.close()
            if universe.atoms.n_atoms != ca.n_atoms:
                problems.append(f"MDAnalysis sees {universe.atoms.n_atoms} atoms in {folder}")
        except Exception as error:  # MDAnalysis failing to open it is the finding
            problems.append(f"MDAnalysis cannot open {folder / 'soak.h5'}: {error}")
    return problems


def rss_growth_mb(process: Process, steps: int) -> tuple[float, int]:
    """(RSS late in the run over RSS once it has settled, samples used), in MB: the largest
    sample past 80 % of the steps less the largest between 10 % and 30 % (start-up,
    compiling and the first buffers are over by then)."""
    settled = [rss for _, rss, step in process.samples if 0.1 * steps <= step <= 0.3 * steps]
    late = [rss for _, rss, step in process.samples if step >= 0.8 * steps]
    if not settled or not late:
        return 0.0, 0
    return (max(late) - max(settled)) / 2**20, len(settled) + len(late)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=10**6, help="steps (default 10^6)")
    parser.add_argument("--atoms", type=int, default=108, choices=(32, 108, 256))
    parser.add_argument(
        "--checkpoint-every",
        type=int,
        default=1000,
        help="steps between checkpoints and frames (default 1000)",
    )
    parser.add_argument("--cycles", type=int, default=5, help="SIGTERM/resume cycles (default 5)")
    parser.add_argument(
        "--integrator",
        default="verlet",
        choices=("verlet", "bussi"),
        help="verlet, or bussi (a thermostat with its own random stream)",
    )
    parser.add_argument("--seed", type=int, default=11, help="config seed and SIGTERM steps")
    parser.add_argument(
        "--rss-growth-mb",
        type=float,
        default=16.0,
        help="RSS growth allowed over the uninterrupted run (default 16 MB)",
    )
    parser.add_argument("--poll", type=float, default=0.05, help="seconds between RSS samples")
    parser.add_argument("--workdir", type=Path, help="keep the runs here (default: a temporary)")
    parser.add_argument(
        "--timeout",
        type=float,
        default=4 * 3600.0,
        help="seconds any one process may run (default 4 h)",
    )
    args = parser.parse_args(argv)
    if args.steps < 2 * args.cycles + 2 or args.checkpoint_every < 1:
        parser.error("--steps must leave room for the cycles, --checkpoint-every be >= 1")
    with tempfile.TemporaryDirectory() as name:
        top = args.workdir or Path(name)
        return soak(args, top)


def soak(args, top: Path) -> int:
    whole, pieces = top / "whole", top / "pieces"
    for folder in (whole, pieces):
        folder.mkdir(parents=True, exist_ok=True)
        write_config(folder, args)
    run = [*MD, "run", "run.toml", "--no-progress", "--threads", "1"]
    problems: list[str] = []
    started = time.monotonic()

    print(
        f"soak: {args.atoms} atoms, {args.steps} steps, checkpoints every "
        f"{args.checkpoint_every}, {args.cycles} SIGTERM/resume cycles, in {top}",
        flush=True,
    )
    first = Process(run, whole, "whole")
    code = first.wait(args.poll, limit=args.timeout)
    wall_whole = time.monotonic() - first.started
    if code != 0:
        problems.append(f"the uninterrupted run exited {code}: {first.stderr()[-500:]}")
    problems += check_files(whole, expect_complete=args.steps)

    rng = random.Random(args.seed)
    stops = sorted(rng.sample(range(1, args.steps - 1), args.cycles))
    processes, argv, cycles_done = [], run, 0
    for cycle in range(args.cycles + 1):
        process = Process(argv, pieces, f"pieces{cycle}")
        processes.append(process)
        target = stops[cycle] if cycle < args.cycles else None
        code = process.wait(args.poll, until_step=target, limit=args.timeout)
        if code is None:  # reached its stop step: SIGTERM, then it checkpoints and exits 143
            process.popen.send_signal(signal.SIGTERM)
            code = process.wait(args.poll, limit=args.timeout)
            where = process.last_step()
            if code != 143:
                problems.append(
                    f"cycle {cycle}: SIGTERM near step {where} gave exit {code}: "
                    f"{process.stderr()[-500:]}"
                )
                break
            cycles_done += 1
            problems += [f"cycle {cycle}: {p}" for p in check_files(pieces)]
            told = [
                line.split("Continue with:", 1)[1].strip()
                for line in process.stderr().splitlines()
                if "Continue with:" in line
            ]
            if not told:
                problems.append(f"cycle {cycle}: no resume command in {process.stderr()[-300:]}")
                break
            words = shlex.split(told[-1])
            argv = [*MD, *words[1:], "--no-progress", "--threads", "1"]  # "md" is us
            print(
                f"  cycle {cycle}: SIGTERM at step ~{where}, exit 143, resuming with "
                f"'{told[-1]}'; peak RSS {process.peak_mb():.1f} MB",
                flush=True,
            )
            continue
        if code != 0:
            problems.append(f"cycle {cycle}: exited {code}: {process.stderr()[-500:]}")
        break
    problems += check_files(pieces, expect_complete=args.steps)
    if not problems:
        problems += compare(whole, pieces)
        rows_whole = thermo_rows([first.out_path])
        rows_pieces = thermo_rows([p.out_path for p in processes])
        if len(rows_whole) != args.steps + 1:
            problems.append(
                f"the uninterrupted run printed {len(rows_whole)} thermo rows, not {args.steps + 1}"
            )
        differing = [s for s in rows_whole if rows_pieces.get(s) != rows_whole[s]]
        if differing or len(rows_pieces) != len(rows_whole):
            problems.append(
                f"thermo rows differ at {len(differing)} steps (first "
                f"{differing[:3]}); {len(rows_pieces)} against {len(rows_whole)}"
            )
    growth, used = rss_growth_mb(first, args.steps)
    if growth > args.rss_growth_mb:
        problems.append(
            f"RSS of the uninterrupted run grew {growth:.1f} MB (> {args.rss_growth_mb:g} MB)"
        )
    peaks = [p.peak_mb() for p in processes]
    if peaks and max(peaks) > first.peak_mb() + args.rss_growth_mb:
        problems.append(
            f"a resumed run peaked at {max(peaks):.1f} MB, the whole run at "
            f"{first.peak_mb():.1f} MB"
        )

    print(
        f"soak: uninterrupted run {wall_whole:.1f} s ({args.steps / wall_whole:,.0f} steps/s), "
        f"peak RSS {first.peak_mb():.1f} MB, growth from 10-30 % to 80-100 % of the steps "
        f"{growth:+.1f} MB ({used} of {len(first.samples)} samples)"
    )
    print(
        f"soak: interrupted run {cycles_done} SIGTERM/resume cycles in {len(processes)} "
        f"processes, peak RSS {max(peaks, default=0):.1f} MB; "
        f"total {time.monotonic() - started:.1f} s"
    )
    if problems:
        print("soak: FAILED")
        for problem in problems:
            print(f"  - {problem}")
        return 1
    print(
        "soak: OK: files valid after every stop, the resumed trajectory, final state and "
        "thermo rows equal the uninterrupted run's bit for bit, memory flat"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
