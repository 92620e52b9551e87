"""Parameter sweeps and replica ensembles of ``md run``, executed on Dask.

A sweep is the cartesian product of the values of some config keys, times a
number of replicas that differ only in their random seeds. Every run is an
ordinary ``md run`` of its own config (written to ``OUT/configs/``), and
every run writes its own H5MD file ``OUT/<label>.h5``. The runs are tasks on
a Dask ``distributed`` cluster: by default a ``LocalCluster`` with one
single-threaded worker process per core, otherwise any scheduler the user
names (an address, or their own ``Client``; through ``dask-jobqueue`` that is
SLURM, PBS and the like). ``OUT`` must be on a filesystem that the client and
every worker see (a cluster's home or scratch).

Planning (:func:`plan_sweep`)
    Varied keys are dotted paths into the TOML (``system.temperature``,
    ``integrator.dt``, ``potentials.0.cutoff``, ``seed``). Every parameter
    point is written out, read back and validated as ``md run`` would (config,
    system, potentials, integrator, force-field checks) before anything runs;
    the first bad key or value raises :class:`SweepError` naming it.
    Relative ``structure`` and ``bonds_file`` paths are made absolute.

Seeds
    Replica 0 keeps the config's ``seed`` (0 when it has none), so a
    one-replica sweep repeats exactly what ``md run`` of the same config
    does. Replica ``r > 0`` gets ``replica_seed(seed, r)``, drawn from
    ``numpy.random.SeedSequence([seed, r])``. Seeds depend on the replica
    index and the base seed only, not on the other varied values: replica
    ``r`` of every parameter point starts from the same random stream
    (common random numbers, which makes differences between points less
    noisy); adding a value to a sweep leaves the other runs unchanged. An
    explicit ``[integrator] seed`` (a stochastic thermostat's) is varied
    across replicas the same way. Varying ``seed`` itself sets the base seed
    of each point.

Execution (:func:`run_sweep`)
    Each task runs ``python -m md.sweep PARENT run CONFIG --threads 1
    --no-progress --quiet`` in a child process. A child process isolates
    crashes and process-wide state (the kernels' thread count, numba), lets
    a multi-threaded Dask worker run several runs at once without sharing a
    GIL, and is exactly ``md run``; it costs about a second of start-up per
    run. The child writes into ``OUT/.partial/<label>/``; only when it exits
    cleanly and its file holds every frame is the file renamed to
    ``OUT/<label>.h5``, so that name always means a complete run. A task holds
    an exclusive lock on ``OUT/.partial/<label>.lock`` (shared with its child)
    so that a retry never writes alongside a run still going. The child dies
    with its worker (Linux ``PR_SET_PDEATHSIG``); Dask then reruns the task
    on another worker (up to the scheduler's ``allowed-failures``), which
    resumes from the run's checkpoint (``md run --resume``: bit-for-bit the
    same result) or starts it afresh. A run that fails (exit 1: the dynamics
    blew up; exit 2: bad input found at run time) is reported with ``md
    run``'s message, its partial files are removed, and the other runs go
    on. Running a sweep again skips runs whose output is complete and was
    written from the same config (an output written from another config is
    refused unless ``overwrite``).

Collation
    Each task also summarises its output (:func:`summarize`): block-averaged
    means and standard errors of temperature, pressure and the energies per
    atom, the total-energy drift per atom (:func:`md.analysis.thermo`), and
    on request the Einstein diffusion coefficient (:func:`md.analysis.msd`),
    after discarding a leading fraction of frames. :class:`SweepTable` holds
    one row per run; it writes ``OUT/sweep.csv`` and plots a result against
    a varied key with replica error bars.

Python API::

    import md
    table = md.sweep("lj.toml", vary={"system.temperature": [0.8, 1.2]}, replicas=4,
                     out="sweep-lj", client=my_dask_client)   # or scheduler="tcp://..."
    table.points("pressure")          # mean and replica standard error per point

``md.sweep`` is this module, callable as :func:`sweep`. Importing it does not
import Dask; the functions that need Dask import it.
"""

from __future__ import annotations

import contextlib
import copy
import csv
import itertools
import logging
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import tomllib
import types
import uuid
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

logger = logging.getLogger(__name__)

#: Sub-folders and files of a sweep's output folder.
CONFIG_DIR, LOG_DIR, PARTIAL_DIR, TABLE_FILE = "configs", "logs", ".partial", "sweep.csv"
#: Keys a sweep sets itself and that cannot be varied.
RESERVED_KEYS = {
    "output.path": "the sweep names each run's output OUT/<label>.h5",
    "run.threads": "each run uses one thread (run more workers instead)",
}
#: Result columns of a run, with the quantity naming their unit.
RESULTS = {
    "temperature": "temperature",
    "pressure": "pressure",
    "potential_energy_per_atom": "energy",
    "kinetic_energy_per_atom": "energy",
    "total_energy_per_atom": "energy",
    "energy_drift_per_atom": "drift",
    "diffusion": "diffusion",
}
#: Short names accepted for the result columns (``--plot T``).
ALIASES = {
    "T": "temperature",
    "P": "pressure",
    "PE": "potential_energy_per_atom",
    "KE": "kinetic_energy_per_atom",
    "E": "total_energy_per_atom",
    "drift": "energy_drift_per_atom",
    "D": "diffusion",
}
#: Exit code of the child when its parent (the Dask worker) died before it started.
_ORPHANED = 137


class SweepError(ValueError):
    """Bad sweep input: a varied key or value, a config, an output folder (named)."""


# ------------------------------------------------------------------ planning
@dataclass(frozen=True)
class Run:
    """One run of a sweep: a parameter point and a replica.

    Attributes
    ----------
    index : int
        Position in the sweep (points in the order given, replicas innermost).
    label : str
        File stem of the output, e.g. ``temperature=1.5_r0``.
    point : tuple of (str, value)
        The varied keys and their values at this run.
    replica : int
        Replica index (0 keeps the config's seed).
    seed : int
        Top-level ``seed`` of the run's config.
    config_text : str
        The run's complete TOML config.
    n_frames : int
        Frames a complete output holds.
    last_step : int
        Step of the last frame.
    """

    index: int
    label: str
    point: tuple[tuple[str, Any], ...]
    replica: int
    seed: int
    config_text: str
    n_frames: int
    last_step: int

    def spec(self, out: Path) -> dict:
        """Plain data a Dask task needs to execute this run."""
        return {
            "label": self.label,
            "out": str(out),
            "config_text": self.config_text,
            "n_frames": self.n_frames,
            "last_step": self.last_step,
        }


@dataclass
class SweepPlan:
    """Every run of a sweep, validated, and where its files go."""

    config: Path
    keys: list[str]
    values: dict[str, list]
    replicas: int
    out: Path
    runs: list[Run]

    def output(self, run: Run) -> Path:
        return self.out / f"{run.label}.h5"


def parse_vary(text: str) -> tuple[str, list]:
    """Parse ``KEY=V1,V2,...`` into the dotted key and its values.

    Each value is read as a TOML value (``1.5``, ``2``, ``true``, ``[4, 4, 4]``,
    ``"fcc"``) or, failing that, as a plain string (``fcc``); commas inside
    brackets do not split. ``MIN:MAX:N`` gives N evenly spaced numbers
    (both ends included).

    Raises
    ------
    SweepError
        For a missing ``=``, an empty key or value, or a repeated value.
    """
    key, sep, rest = text.partition("=")
    key = key.strip()
    if not sep or not key or not rest.strip():
        raise SweepError(f"--vary {text!r}: expected KEY=V1,V2,... (e.g. system.temperature=1,2)")
    if any(not part for part in key.split(".")):
        raise SweepError(f"--vary {text!r}: {key!r} is not a dotted config key")
    values = []
    for part in _split_top_level(rest):
        part = part.strip()
        if not part:
            raise SweepError(f"--vary {text!r}: empty value")
        spaced = _linspace(part)
        values.extend(spaced if spaced is not None else [_literal(part)])
    repeated = sorted(
        {_format_value(b) for i, a in enumerate(values) for b in values[i + 1 :] if a == b}
    )
    if repeated:
        raise SweepError(f"--vary {key}: value(s) given twice: {', '.join(repeated)}")
    return key, values


def replica_seed(seed: int, replica: int) -> int:
    """Seed of replica ``replica`` of a run whose config seed is ``seed``.

    Replica 0 keeps ``seed``; others get 63 bits from
    ``numpy.random.SeedSequence([seed, replica])``.
    """
    if replica == 0:
        return int(seed)
    state = np.random.SeedSequence([int(seed), int(replica)]).generate_state(1, np.uint64)[0]
    return int(state >> np.uint64(1))


def plan_sweep(
    config,
    vary: Mapping[str, Sequence] | Sequence[str | tuple[str, Sequence]] = (),
    replicas: int = 1,
    out=None,
) -> SweepPlan:
    """Expand a base config into every run of a sweep and validate each one.

    Parameters
    ----------
    config : str or Path
        The base TOML config (as for ``md run``).
    vary : mapping of key to values, or sequence of ``"KEY=V1,V2"`` strings
        The varied dotted keys, in order (the first is the x axis of plots).
    replicas : int
        Runs per parameter point, with different seeds.
    out : str or Path, optional
        Output folder (default ``sweep-<config stem>``); nothing is written here.

    Raises
    ------
    SweepError
        For an unreadable config, a bad key or value (named with its point),
        or runs whose labels would collide.
    """
    from md.config import ConfigError

    config = Path(config)
    try:
        text = config.read_text()
        base = tomllib.loads(text)
    except FileNotFoundError:
        raise SweepError(f"{config}: config file not found") from None
    except (OSError, UnicodeDecodeError) as error:
        raise SweepError(f"{config}: cannot read config file ({error})") from None
    except tomllib.TOMLDecodeError as error:
        raise SweepError(f"{config}: invalid TOML ({error})") from None
    if isinstance(replicas, bool) or not isinstance(replicas, int) or replicas < 1:
        raise SweepError(f"replicas must be a positive integer, got {replicas!r}")
    pairs = _vary_pairs(vary)
    keys = [key for key, _ in pairs]
    if len(set(keys)) != len(keys):
        raise SweepError(f"a key is varied twice: {', '.join(keys)}")
    for key in keys:
        if key in RESERVED_KEYS:
            raise SweepError(f"--vary {key}: cannot be varied ({RESERVED_KEYS[key]})")
    out = Path(out) if out is not None else Path(f"sweep-{config.stem}")
    out = out.absolute()
    base_dir = config.parent.absolute()
    _absolute_paths(base, base_dir)
    short = _short_names(keys)
    runs, labels = [], {}
    for point in itertools.product(*(values for _, values in pairs)):
        point = tuple(zip(keys, point, strict=True))
        data = copy.deepcopy(base)
        where = f"{config}" + (
            " with " + ", ".join(f"{k}={_format_value(v)}" for k, v in point) if point else ""
        )
        for key, value in point:
            _set_key(data, key, value, where)
        seed = data.get("seed", 0)
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise SweepError(f"{where}: seed: expected an integer >= 0, got {seed!r}")
        integrator = data.get("integrator")
        thermostat_seed = integrator.get("seed") if isinstance(integrator, dict) else None
        parsed = None
        for replica in range(replicas):
            run_seed = replica_seed(seed, replica)
            data["seed"] = run_seed
            if thermostat_seed is not None and replica > 0:
                integrator["seed"] = _vary_seed(thermostat_seed, replica, where)
            label = "_".join([*(f"{short[k]}={_label_text(v)}" for k, v in point), f"r{replica}"])
            if label in labels:
                raise SweepError(
                    f"{where}: runs {labels[label]} and {len(runs)} would share the output "
                    f"name {label}.h5; give values that differ in their file-name form"
                )
            labels[label] = len(runs)
            data.setdefault("output", {})
            if not isinstance(data["output"], dict):
                raise SweepError(f"{where}: [output] must be a table")
            data["output"]["path"] = str(out / f"{label}.h5")
            header = (
                f"# md sweep run {label}: from {config.absolute()}"
                + "".join(f", {k} = {_format_value(v)}" for k, v in point)
                + f", replica {replica}, seed {run_seed}\n"
            )
            run_text = header + dumps_toml(data)
            if parsed is None:  # replicas differ only in seeds: validate each point once
                try:
                    parsed = _validate(run_text, where)
                except ConfigError as error:
                    raise SweepError(str(error)) from None
            steps, every = parsed.run.steps, parsed.output.every
            runs.append(
                Run(
                    index=len(runs),
                    label=label,
                    point=point,
                    replica=replica,
                    seed=run_seed,
                    config_text=run_text,
                    n_frames=steps // every + 1,
                    last_step=(steps // every) * every,
                )
            )
    return SweepPlan(
        config=config,
        keys=keys,
        values={key: list(values) for key, values in pairs},
        replicas=replicas,
        out=out,
        runs=runs,
    )


def check_outputs(plan: SweepPlan, overwrite: bool = False) -> list[Run]:
    """Return the runs whose outputs are already complete (read-only).

    Raises
    ------
    SweepError
        If ``plan.out`` is not a folder, or (without ``overwrite``) an output
        exists that is not a complete run of the same config.
    """
    out = plan.out
    if out.exists() and not out.is_dir():
        raise SweepError(f"output folder {out} exists and is not a folder")
    if not out.exists() and not out.parent.is_dir():
        raise SweepError(f"the parent folder of {out} does not exist")
    complete, conflicts = [], []
    for run in plan.runs:
        verdict = output_verdict(plan.output(run), run.config_text, run.n_frames, run.last_step)
        if verdict == "complete":
            complete.append(run)
        elif verdict is not None:
            conflicts.append(f"{plan.output(run)} ({verdict})")
    if conflicts and not overwrite:
        more = f" and {len(conflicts) - 3} more" if len(conflicts) > 3 else ""
        raise SweepError(
            f"output file(s) of this sweep exist but are not complete runs of its configs: "
            f"{'; '.join(conflicts[:3])}{more}; pass --overwrite (overwrite=True) to redo "
            "them, or choose another output folder"
        )
    return [] if overwrite else complete


def output_verdict(path: Path, config_text: str, n_frames: int, last_step: int) -> str | None:
    """``"complete"``, None when ``path`` does not exist, or why it is not a complete run.

    A complete output holds all ``n_frames`` frames up to ``last_step`` and
    was written from ``config_text`` (compared as TOML data, apart from
    ``[output] path``, so a moved sweep folder still counts).
    """
    from md.trajectory import TrajectoryError, read_frame_steps

    path = Path(path)
    if not path.exists():
        return None
    try:
        steps, parameters = read_frame_steps(path)
    except TrajectoryError as error:
        return f"unreadable: {error}"
    if not _same_config(parameters.get("config"), config_text):
        return "written from a different config"
    if len(steps) != n_frames or int(steps[-1]) != last_step:
        last = int(steps[-1]) if len(steps) else None
        return f"{len(steps)} of {n_frames} frames, last at step {last}, expected {last_step}"
    return "complete"


def _validate(text: str, where: str):
    """Check a run's config as ``md run`` does before it writes anything; return it."""
    from integrators.base import ConvergenceError
    from md.config import (
        ConfigError,
        build_system,
        integrator_from_config,
        parse_config,
        potential_from_config,
    )
    from md.forcefield import ForceField

    config = parse_config(tomllib.loads(text), source=where, text=text, base=".")
    state, bonds = build_system(config)
    potentials = [
        potential_from_config(entry, state.type_names, config.source, index, bonds)
        for index, entry in enumerate(config.potentials)
    ]
    integrator = integrator_from_config(config.integrator, config.source, bonds)
    constraints = getattr(integrator, "constraints", None)
    try:
        if constraints is not None:
            constraints.bind(state, integrator.dt)
        ForceField(potentials, skin=config.run.skin).check(state)
    except (ValueError, ConvergenceError) as error:
        raise ConfigError(f"{where}: {error}") from None
    return config


def _vary_pairs(vary) -> list[tuple[str, list]]:
    if isinstance(vary, str):
        vary = [vary]
    if isinstance(vary, Mapping):
        items = list(vary.items())
    else:
        items = [parse_vary(v) if isinstance(v, str) else tuple(v) for v in vary]
    pairs = []
    for key, values in items:
        if isinstance(values, str | bytes) or not isinstance(values, Sequence | np.ndarray):
            values = [values]
        values = [v.item() if isinstance(v, np.generic) else v for v in values]
        if not values:
            raise SweepError(f"--vary {key}: no values")
        pairs.append((str(key), values))
    return pairs


def _set_key(data: dict, key: str, value, where: str) -> None:
    """Set dotted ``key`` (``potentials.0.cutoff``) in TOML data, creating tables."""
    parts = key.split(".")
    node = data
    for depth, part in enumerate(parts):
        here = ".".join(parts[: depth + 1])
        last = depth == len(parts) - 1
        if isinstance(node, list):
            if not part.isdigit():
                raise SweepError(
                    f"{where}: {'.'.join(parts[:depth])} is an array of {len(node)} tables; "
                    f"name an entry by its index, e.g. {'.'.join(parts[:depth])}.0.{part}"
                )
            index = int(part)
            if index >= len(node):
                raise SweepError(
                    f"{where}: {here}: {'.'.join(parts[:depth])} has {len(node)} entries"
                )
            if last:
                node[index] = value
            else:
                node = node[index]
        elif isinstance(node, dict):
            if last:
                node[part] = value
            else:
                node = node.setdefault(part, {})
        else:
            raise SweepError(f"{where}: {key}: {'.'.join(parts[:depth])} is a value, not a table")


def _absolute_paths(data: dict, base: Path) -> None:
    """Make the config's file paths absolute (run configs live in another folder)."""

    def fix(table, key):
        if isinstance(table, dict) and isinstance(table.get(key), str):
            if not Path(table[key]).is_absolute():
                table[key] = str(base / table[key])

    fix(data.get("system"), "structure")
    for entry in data.get("potentials") or []:
        fix(entry, "bonds_file")
    integrator = data.get("integrator")
    if isinstance(integrator, dict):
        fix(integrator.get("constraints"), "bonds_file")


def _vary_seed(seed, replica: int, where: str):
    if isinstance(seed, int) and not isinstance(seed, bool) and seed >= 0:
        return replica_seed(seed, replica)
    if isinstance(seed, list) and all(isinstance(s, int) and s >= 0 for s in seed):
        return [*seed, replica]
    raise SweepError(f"{where}: [integrator] seed: expected an integer or a list, got {seed!r}")


def _short_names(keys: list[str]) -> dict[str, str]:
    """The last part of each dotted key, or the whole key where two would clash."""
    last = [k.split(".")[-1] for k in keys]
    return {k: (s if last.count(s) == 1 else k) for k, s in zip(keys, last, strict=True)}


def _split_top_level(text: str) -> list[str]:
    parts, depth, current, quote = [], 0, [], None
    for char in text:
        if quote:
            quote = None if char == quote else quote
        elif char in "\"'":
            quote = char
        elif char in "[{":
            depth += 1
        elif char in "]}":
            depth -= 1
        elif char == "," and depth == 0:
            parts.append("".join(current))
            current = []
            continue
        current.append(char)
    parts.append("".join(current))
    return parts


def _literal(text: str):
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        pass
    try:
        return float(text)
    except ValueError:
        return text


def _linspace(text: str) -> list[float] | None:
    parts = text.split(":")
    if len(parts) != 3:
        return None
    try:
        low, high, count = float(parts[0]), float(parts[1]), int(parts[2])
    except ValueError:
        return None
    if count < 2 or not (math.isfinite(low) and math.isfinite(high)):
        raise SweepError(f"--vary range {text!r}: needs finite ends and at least 2 values")
    return [float(f"{v:.12g}") for v in np.linspace(low, high, count)]


def _format_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, list):
        return "[" + ", ".join(_format_value(v) for v in value) + "]"
    return str(value)


def _label_text(value) -> str:
    if isinstance(value, list):
        return "x".join(_label_text(v) for v in value)
    return re.sub(r"[^A-Za-z0-9.+-]", "-", _format_value(value))


def _same_config(stored, text: str) -> bool:
    if not isinstance(stored, str):
        return False
    try:
        a, b = tomllib.loads(stored), tomllib.loads(text)
    except tomllib.TOMLDecodeError:
        return False
    for data in (a, b):
        if isinstance(data.get("output"), dict):
            data["output"].pop("path", None)
    return a == b


# ---------------------------------------------------------------- TOML out
_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")


def dumps_toml(data: Mapping) -> str:
    """Write TOML data (what ``tomllib`` returns, less dates) back as TOML text.

    Tables become ``[a.b]`` sections and arrays of tables ``[[a]]``; tables
    inside other arrays are written inline. ``tomllib.loads(dumps_toml(d)) == d``.
    """
    lines: list[str] = []
    _write_table(lines, [], data, header=None)
    return "\n".join(lines).strip() + "\n"


def _write_table(lines: list[str], path: list[str], table: Mapping, header: str | None) -> None:
    if header is not None:
        lines.append("")
        lines.append(header)
    nested = []
    for key, value in table.items():
        if isinstance(value, Mapping):
            nested.append((key, value, False))
        elif isinstance(value, list) and value and all(isinstance(v, Mapping) for v in value):
            nested.append((key, value, True))
        else:
            lines.append(f"{_toml_key(key)} = {_toml_value(value)}")
    for key, value, is_array in nested:
        name = ".".join(_toml_key(k) for k in [*path, key])
        if is_array:
            for item in value:
                _write_table(lines, [*path, key], item, f"[[{name}]]")
        else:
            _write_table(lines, [*path, key], value, f"[{name}]")


def _toml_key(key) -> str:
    key = str(key)
    return key if _BARE_KEY.fullmatch(key) else _toml_string(key)


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return _toml_string(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, Mapping):
        inner = ", ".join(f"{_toml_key(k)} = {_toml_value(v)}" for k, v in value.items())
        return "{ " + inner + " }" if inner else "{}"
    raise SweepError(f"cannot write {value!r} ({type(value).__name__}) to a TOML config")


def _toml_string(text: str) -> str:
    escapes = {'"': '\\"', "\\": "\\\\", "\n": "\\n", "\t": "\\t", "\r": "\\r"}
    out = []
    for char in text:
        if char in escapes:
            out.append(escapes[char])
        elif ord(char) < 0x20 or ord(char) == 0x7F:
            out.append(f"\\u{ord(char):04x}")
        else:
            out.append(char)
    return '"' + "".join(out) + '"'


# --------------------------------------------------------------- summaries
def summarize(path, discard: float = 0.0, diffusion: bool = False, n_blocks: int = 5) -> dict:
    """Scalar results of one output: means with block errors, drift, optionally D.

    Parameters
    ----------
    path : str or Path
        An H5MD file written by ``md run``.
    discard : float
        Leading fraction of the frames left out (equilibration), 0 <= discard < 1.
    diffusion : bool
        Also fit the Einstein diffusion coefficient to the MSD.
    n_blocks : int
        Blocks of the standard errors (see :func:`md.analysis.block_average`).

    Returns
    -------
    dict
        ``temperature``, ``pressure`` and the energies per atom
        (``potential_energy_per_atom`` etc.), each with ``<name>_err`` (block
        standard error of the mean), ``energy_drift_per_atom`` [energy/time]
        with its error, ``diffusion`` [length^2/time] with its error when asked,
        ``n_atoms``, ``n_frames`` (analysed), ``units``; in the file's units.
    """
    from md import analysis

    info = analysis.trajectory_info(path)
    start = int(math.floor(discard * info.n_frames_total))
    result = analysis.thermo(path, start=start, n_blocks=n_blocks)
    n = result.n_atoms
    row: dict[str, Any] = {"units": result.units, "n_atoms": n, "n_frames": len(result.times)}
    for name in ("temperature", "pressure", "potential_energy", "kinetic_energy", "total_energy"):
        column = name if name in RESULTS else f"{name}_per_atom"
        scale = 1.0 / n if column.endswith("_per_atom") else 1.0
        average = result.averages.get(name)
        row[column] = average.mean * scale if average else math.nan
        row[f"{column}_err"] = average.sem * scale if average else math.nan
    row["energy_drift_per_atom"] = result.energy_drift
    row["energy_drift_per_atom_err"] = result.energy_drift_err
    if diffusion:
        fit = analysis.msd(path, start=start, n_blocks=n_blocks).diffusion
        row["diffusion"], row["diffusion_err"] = fit.value, fit.error
    return row


# --------------------------------------------------------------- the tasks
def _execute_run(spec: dict, options: dict) -> dict:
    """Dask task: run one ``md run`` (unless its output is complete) and summarise it.

    Idempotent: safe to run again after a worker died in the middle of it.
    Returns a dict with ``label``, ``status`` (``done``, ``skipped`` or
    ``failed``), ``message``, ``wall_s``, ``worker`` and the summary.
    """
    try:
        return _execute(spec, options)
    finally:  # in the same event stream as the start, so counts of runs in flight stay right
        _emit(options["topic"], {"event": "end", "label": spec["label"]})


def _execute(spec: dict, options: dict) -> dict:
    import fcntl

    out, label = Path(spec["out"]), spec["label"]
    final = out / f"{label}.h5"
    config = out / CONFIG_DIR / f"{label}.toml"
    started = time.time()
    result = {"label": label, "status": "failed", "message": "", "wall_s": math.nan}
    result["worker"] = _worker_address()
    if not config.is_file():
        result["message"] = (
            f"{config} not found on worker {result['worker']}: the output folder must be on a "
            "filesystem shared by the client and the workers"
        )
        return result
    (out / PARTIAL_DIR).mkdir(exist_ok=True)
    with open(out / PARTIAL_DIR / f"{label}.lock", "a+") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # a run still going elsewhere finishes first
        verdict = output_verdict(final, spec["config_text"], spec["n_frames"], spec["last_step"])
        if verdict == "complete":
            result["status"] = "skipped"
        elif verdict is not None:
            result["message"] = f"{final} exists and is not a complete run of it ({verdict})"
            return result
        else:
            partial = out / PARTIAL_DIR / label
            partial.mkdir(exist_ok=True)
            status, message = _run_child(spec, config, partial, lock, options)
            result["status"], result["message"] = status, message
            result["wall_s"] = time.time() - started
            shutil.rmtree(partial, ignore_errors=True)  # moved into place, or failed
            if status != "done":
                return result
    try:
        result.update(
            summarize(final, options["discard"], options["diffusion"], options["n_blocks"])
        )
    except ValueError as error:  # AnalysisError, TrajectoryError
        result["message"] = f"summary: {error}"
    return result


def _run_child(spec: dict, config: Path, partial: Path, lock, options: dict) -> tuple[str, str]:
    """Run ``md run`` in a child process into ``partial``; move a complete output into place."""
    from md.checkpoint import checkpoint_path

    out, label = Path(spec["out"]), spec["label"]
    output = partial / f"{label}.h5"
    log_path = out / LOG_DIR / f"{label}.log"
    modes = ["--resume", "--overwrite"] if checkpoint_path(output).exists() else ["--overwrite"]
    env = dict(os.environ)
    for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        env.setdefault(name, "1")
    code = None
    for mode in modes:
        command = [
            sys.executable, "-m", "md.sweep", str(os.getpid()), "run", str(config),
            "--output", str(output), "--threads", "1", "--no-progress", "--quiet", mode,
        ]  # fmt: skip
        with open(log_path, "a") as log:
            log.write(f"# {time.strftime('%Y-%m-%d %H:%M:%S')} on {_worker_address()}: md run "
                      f"{config.name} {mode}\n")  # fmt: skip
            log.flush()
            child = subprocess.Popen(
                command, stdout=log, stderr=subprocess.STDOUT, env=env, cwd=out,
                pass_fds=(lock.fileno(),), stdin=subprocess.DEVNULL,
            )  # fmt: skip
            _emit(options["topic"], {
                "event": "start", "label": label, "worker": _worker_address(),
                "pid": os.getpid(), "child": child.pid, "time": time.time(),
                "again": mode != modes[0],  # a refused resume started afresh: no retry
            })  # fmt: skip
            code = child.wait()
        if code == 0:
            verdict = output_verdict(output, spec["config_text"], spec["n_frames"],
                                     spec["last_step"])  # fmt: skip
            if verdict == "complete":
                with open(output, "rb+") as handle:
                    os.fsync(handle.fileno())
                os.replace(output, out / f"{label}.h5")
                return "done", ""
            if mode == "--resume":
                continue  # a checkpoint of other settings: start afresh
            return "failed", f"md run finished but its output is incomplete ({verdict})"
        if not (code == 2 and mode == "--resume"):  # a refused resume starts afresh
            break
    return "failed", _failure_message(code, log_path)


def _failure_message(code: int, log_path: Path) -> str:
    if code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = str(-code)
        why = " (out of memory?)" if -code == signal.SIGKILL else ""
        return f"md run was killed by signal {name}{why}; see {log_path}"
    message = ""
    try:
        for line in log_path.read_text(errors="replace").splitlines():
            if line.startswith("md: error:") or line.startswith("md run: SIG"):
                message = line.removeprefix("md: error:").strip()
                # The partial files it names are removed; the log keeps the whole message.
                message = message.split(". Frames written so far are kept in")[0]
    except OSError:
        pass
    return f"md run exit {code}: {message or 'no message'} (log {log_path})"


def _worker_address() -> str:
    try:
        from distributed import get_worker

        return str(get_worker().address)
    except (ImportError, ValueError):
        return f"pid {os.getpid()}"


def _emit(topic: str, message: dict) -> None:
    try:
        from distributed import get_worker

        get_worker().log_event(topic, message)
    except (ImportError, ValueError):  # not on a Dask worker
        pass


def _child_main(argv: list[str]) -> int:
    """Entry of ``python -m md.sweep PARENT_PID run ...``: ``md run`` that dies with its parent."""
    if len(argv) < 2 or not argv[0].isdigit():
        print("usage: python -m md.sweep PARENT_PID run ... (used by md sweep)", file=sys.stderr)
        return 2
    parent = int(argv[0])
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            pass
    if os.getppid() != parent:
        return _ORPHANED  # the worker died while starting this run
    from md.cli import main

    return main(argv[1:])


# -------------------------------------------------------- progress, client
@dataclass
class SweepProgress:
    """Where a sweep stands; handed to the ``progress`` callback.

    Attributes
    ----------
    total, done, skipped, failed : int
        Runs in the sweep; finished here; complete before; failed.
    running : dict of str to dict
        Runs in flight: label to ``{"worker", "pid", "child", "time"}``.
    retried : int
        Runs started again after their worker died.
    elapsed : float
        Seconds since the sweep was submitted.
    eta : float or None
        Estimated seconds to the end (None until a run has finished).
    finished : list of dict
        Result rows of the runs finished since the previous call.
    """

    total: int
    done: int = 0
    skipped: int = 0
    failed: int = 0
    running: dict = field(default_factory=dict)
    retried: int = 0
    elapsed: float = 0.0
    eta: float | None = None
    finished: list = field(default_factory=list)

    @property
    def n_finished(self) -> int:
        return self.done + self.skipped + self.failed


class _Tracker:
    """Collects start events (Dask's event loop thread) and results (the caller's)."""

    def __init__(self, total: int) -> None:
        self.lock = threading.Lock()
        self.wake = threading.Event()
        self.progress = SweepProgress(total=total)
        self.started: set[str] = set()
        self.start_time = time.monotonic()
        self.first_start: float | None = None

    def on_event(self, event) -> None:
        message = event[1] if isinstance(event, tuple | list) else event
        if not isinstance(message, dict):
            return
        if message.get("event") == "end":
            with self.lock:
                self.progress.running.pop(message.get("label"), None)
            self.wake.set()
            return
        if message.get("event") != "start":
            return
        with self.lock:
            label = message["label"]
            if label in self.started and not message.get("again"):
                self.progress.retried += 1
            self.started.add(label)
            self.progress.running[label] = {
                k: message.get(k) for k in ("worker", "pid", "child", "time")
            }
            if self.first_start is None:
                self.first_start = time.monotonic()
        self.wake.set()

    def finish(self, row: dict) -> None:
        with self.lock:
            self.progress.running.pop(row["label"], None)
            status = row["status"]
            if status == "done":
                self.progress.done += 1
            elif status == "skipped":
                self.progress.skipped += 1
            else:
                self.progress.failed += 1
            self.progress.finished.append(row)

    def forget_workers(self, alive: set[str]) -> None:
        """Drop runs shown as running on workers that have left (they will be rerun)."""
        with self.lock:
            for label, info in list(self.progress.running.items()):
                if info.get("worker") not in alive:
                    del self.progress.running[label]

    def snapshot(self) -> SweepProgress:
        with self.lock:
            p = self.progress
            now = time.monotonic()
            p.elapsed = now - self.start_time
            ran = p.done + p.failed
            remaining = p.total - p.n_finished
            if ran and self.first_start is not None:
                p.eta = (now - self.first_start) / ran * remaining
            elif not remaining:
                p.eta = 0.0
            snapshot = SweepProgress(**{**p.__dict__, "running": dict(p.running)})
            p.finished = []
            return snapshot


@contextlib.contextmanager
def connect(client=None, scheduler: str | None = None, workers: int | None = None) -> Iterator[Any]:
    """A Dask ``Client``: ``client`` itself, one for ``scheduler``, or a new ``LocalCluster``.

    The local cluster has ``workers`` single-threaded worker processes
    (default: one per core this process may use). What this function
    creates it closes on exit; a given ``client`` is left open.

    Raises
    ------
    SweepError
        If Dask is not installed, ``workers`` is not positive or is given
        with a scheduler, or the scheduler cannot be reached.
    """
    if client is not None:
        if scheduler is not None or workers is not None:
            raise SweepError("give a Dask client, or a scheduler address or a worker count")
        yield client
        return
    try:
        from distributed import Client, LocalCluster
    except ImportError as error:
        raise SweepError(
            f"md sweep needs Dask's distributed scheduler: pip install 'dask[distributed]' "
            f"({error})"
        ) from None
    if scheduler is not None:
        if workers is not None:
            raise SweepError(
                "--workers sets the size of the local cluster; with --scheduler the "
                "cluster's own workers run the sweep"
            )
        try:
            remote = Client(scheduler, timeout="20s")
        except (OSError, TimeoutError, ValueError) as error:
            raise SweepError(
                f"cannot connect to the Dask scheduler at {scheduler}: {error}"
            ) from None
        try:
            yield remote
        finally:
            remote.close()
        return
    if workers is None:
        workers = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
        workers = workers or os.cpu_count() or 1
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise SweepError(f"workers must be a positive integer, got {workers!r}")
    cluster = LocalCluster(
        n_workers=workers,
        threads_per_worker=1,
        processes=True,
        dashboard_address=":0",
        silence_logs=logging.ERROR,
    )
    try:
        local = Client(cluster)
        try:
            yield local
        finally:
            local.close()
    finally:
        cluster.close()


def run_sweep(
    plan: SweepPlan,
    client,
    overwrite: bool = False,
    diffusion: bool = False,
    discard: float = 0.0,
    n_blocks: int = 5,
    progress: Callable[[SweepProgress], None] | None = None,
    interval: float = 1.0,
) -> SweepTable:
    """Execute a planned sweep on ``client``, collate it, write ``OUT/sweep.csv``.

    Runs whose outputs are complete are only summarised. ``progress`` is
    called from this thread about every ``interval`` seconds and whenever a
    run starts or finishes. Interrupting (KeyboardInterrupt) cancels the runs
    not yet started.

    Returns
    -------
    SweepTable
        One row per run, in plan order (failed runs included, with messages).
    """
    if not 0.0 <= discard < 1.0:
        raise SweepError(f"discard must be a fraction in [0, 1), got {discard!r}")
    if isinstance(n_blocks, bool) or not isinstance(n_blocks, int) or n_blocks < 1:
        raise SweepError(f"n_blocks must be a positive integer, got {n_blocks!r}")
    _prepare(plan, overwrite)
    topic = f"md-sweep-{uuid.uuid4().hex[:12]}"
    options = {"topic": topic, "discard": discard, "diffusion": diffusion, "n_blocks": n_blocks}
    tracker = _Tracker(len(plan.runs))
    client.subscribe_topic(topic, tracker.on_event)
    futures = {}
    try:
        for run in plan.runs:
            future = client.submit(
                _execute_run, run.spec(plan.out), options, key=f"{topic}-{run.label}", pure=False
            )
            future.add_done_callback(lambda _: tracker.wake.set())
            futures[future] = run
        rows: dict[int, dict] = {}
        pending = set(futures)
        last_check = 0.0
        while pending:
            tracker.wake.clear()
            for future in [f for f in pending if f.done()]:
                pending.discard(future)
                run = futures[future]
                try:
                    row = future.result()
                except Exception as error:  # KilledWorker, a task that raised
                    row = {
                        "label": run.label,
                        "status": "failed",
                        "message": f"{type(error).__name__}: {error}",
                        "wall_s": math.nan,
                    }
                rows[run.index] = row
                tracker.finish(row)
            now = time.monotonic()
            if pending and now - last_check > 2.0:
                last_check = now
                with contextlib.suppress(Exception):  # information only
                    tracker.forget_workers(set(client.scheduler_info()["workers"]))
            if progress is not None:
                progress(tracker.snapshot())
            if pending:
                tracker.wake.wait(interval)
    except BaseException:
        client.cancel(list(futures))
        raise
    finally:
        with contextlib.suppress(Exception):
            client.unsubscribe_topic(topic)
    partial = plan.out / PARTIAL_DIR
    if partial.is_dir() and not any(p.is_dir() for p in partial.iterdir()):
        shutil.rmtree(partial, ignore_errors=True)  # only lock files left
    table = SweepTable.from_results(plan, [rows[run.index] for run in plan.runs])
    table.to_csv(plan.out / TABLE_FILE)
    return table


def _prepare(plan: SweepPlan, overwrite: bool) -> None:
    """Create the output folders, write the run configs, remove what overwrite replaces."""
    check_outputs(plan, overwrite)
    out = plan.out
    for folder in (out, out / CONFIG_DIR, out / LOG_DIR, out / PARTIAL_DIR):
        folder.mkdir(exist_ok=True)
    for run in plan.runs:
        if overwrite:
            plan.output(run).unlink(missing_ok=True)
            shutil.rmtree(out / PARTIAL_DIR / run.label, ignore_errors=True)
        path = out / CONFIG_DIR / f"{run.label}.toml"
        if not path.exists() or path.read_text() != run.config_text:
            _write_atomic(path, run.config_text)


def _write_atomic(path: Path, text: str) -> None:
    from md.trajectory import usual_permissions

    descriptor, temporary = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        usual_permissions(descriptor)
        with os.fdopen(descriptor, "w") as handle:
            handle.write(text)
        os.replace(temporary, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(temporary)
        raise


# ------------------------------------------------------------------- table
@dataclass
class SweepTable:
    """The collated result of a sweep: one row (a dict) per run.

    Row keys: ``index``, ``label``, each varied key (dotted, as given),
    ``replica``, ``seed``, ``status`` (``done``, ``skipped``: complete
    before, ``failed``), ``message``, ``wall_s``, ``n_atoms``, ``n_frames``,
    ``units``, the result columns of :data:`RESULTS` with their ``_err``, and
    ``output``. Results are in the units of the files (NaN for failed runs).

    Examples
    --------
    >>> # table = md.sweep("lj.toml", vary={"system.temperature": [1.0, 1.5]}, replicas=3)
    >>> # table.points("pressure")   # per point: mean, replica error, n
    >>> # table.plot("pressure", "pressure.png")
    """

    keys: list[str]
    rows: list[dict]
    out: Path | None = None

    @classmethod
    def from_results(cls, plan: SweepPlan, results: list[dict]) -> SweepTable:
        rows = []
        for run, result in zip(plan.runs, results, strict=True):
            row = {"index": run.index, "label": run.label, **dict(run.point)}
            row.update(replica=run.replica, seed=run.seed)
            row.update(status=result["status"], message=result.get("message", ""))
            row["wall_s"] = result.get("wall_s", math.nan)
            for name in ("n_atoms", "n_frames", "units"):
                row[name] = result.get(name)
            for name in RESULTS:
                if name == "diffusion" and name not in result:
                    continue
                row[name] = result.get(name, math.nan)
                row[f"{name}_err"] = result.get(f"{name}_err", math.nan)
            row["output"] = str(plan.output(run)) if result["status"] != "failed" else ""
            rows.append(row)
        return cls(keys=list(plan.keys), rows=rows, out=plan.out)

    def __len__(self) -> int:
        return len(self.rows)

    def __iter__(self):
        return iter(self.rows)

    def __getitem__(self, index: int) -> dict:
        return self.rows[index]

    @property
    def columns(self) -> list[str]:
        names: list[str] = []
        for row in self.rows:
            names += [k for k in row if k not in names]
        return names

    @property
    def failed(self) -> list[dict]:
        return [row for row in self.rows if row["status"] == "failed"]

    @property
    def units(self) -> str | None:
        return next((row["units"] for row in self.rows if row.get("units")), None)

    def column(self, name: str) -> np.ndarray:
        """One result column over all runs (NaN where missing)."""
        name = resolve_column(name)
        return np.array([_number(row.get(name)) for row in self.rows])

    def points(self, column: str) -> list[dict]:
        """Mean of ``column`` over the replicas of each parameter point, with its error.

        ``err`` is the standard error over replicas (std / sqrt(n), n >= 2
        finished replicas), or with one replica that run's own block error.
        """
        column = resolve_column(column)
        groups: dict[tuple, list[dict]] = {}
        for row in self.rows:
            groups.setdefault(tuple(_hashable(row[k]) for k in self.keys), []).append(row)
        points = []
        for group in groups.values():
            values = [_number(r.get(column)) for r in group]
            values = [v for v in values if math.isfinite(v)]
            mean = float(np.mean(values)) if values else math.nan
            if len(values) >= 2:
                err = float(np.std(values, ddof=1) / math.sqrt(len(values)))
            elif len(values) == 1:
                own = [r for r in group if math.isfinite(_number(r.get(column)))][0]
                err = _number(own.get(f"{column}_err"))
            else:
                err = math.nan
            points.append({**{k: group[0][k] for k in self.keys}, "mean": mean, "err": err,
                           "n": len(values), "runs": len(group)})  # fmt: skip
        return points

    def to_csv(self, path) -> Path:
        """Write the rows as CSV (atomically); returns the path."""
        import io

        path = Path(path)
        columns = self.columns
        buffer = io.StringIO()
        writer = csv.writer(buffer)
        writer.writerow(columns)
        for row in self.rows:
            writer.writerow([_csv_cell(row.get(c)) for c in columns])
        _write_atomic(path, buffer.getvalue())
        return path

    def to_pandas(self):
        """The rows as a ``pandas.DataFrame`` (needs pandas)."""
        import pandas

        return pandas.DataFrame(self.rows, columns=self.columns)

    def plot(self, column: str, path, key: str | None = None) -> Path:
        """Plot ``column`` against varied ``key`` (default the first) with replica error bars.

        One line per combination of the other varied keys; the points and
        error bars are those of :meth:`points`. Written with matplotlib's Agg
        canvas (no pyplot).
        """
        from matplotlib.figure import Figure

        from md.analysis import unit_labels

        column = resolve_column(column)
        if not self.keys:
            raise SweepError("plotting needs a varied key (the x axis)")
        key = key or self.keys[0]
        if key not in self.keys:
            raise SweepError(f"{key!r} is not a varied key ({', '.join(self.keys)})")
        others = [k for k in self.keys if k != key]
        series: dict[tuple, list] = {}
        for point in self.points(column):
            series.setdefault(tuple(_hashable(point[k]) for k in others), []).append(point)
        x_values = [_hashable(v) for v in dict.fromkeys(_hashable(r[key]) for r in self.rows)]
        numeric = all(isinstance(v, int | float) and not isinstance(v, bool) for v in x_values)
        fig = Figure(figsize=(6.4, 4.4))
        ax = fig.subplots()
        for other, points in series.items():
            xs = [_hashable(p[key]) for p in points]
            xs = xs if numeric else [x_values.index(x) for x in xs]
            label = ", ".join(
                f"{k} = {_format_value(v)}" for k, v in zip(others, other, strict=True)
            )
            ax.errorbar(xs, [p["mean"] for p in points], yerr=[p["err"] for p in points],
                        marker="o", capsize=3, label=label or None)  # fmt: skip
        if not numeric:
            ax.set_xticks(range(len(x_values)), [_format_value(v) for v in x_values])
        labels = unit_labels(self.units or "lj")
        unit = labels.get(RESULTS[column], "")
        ax.set_xlabel(key)
        ax.set_ylabel(f"{column.replace('_', ' ')} [{unit}]")
        replicas = max(p["runs"] for ps in series.values() for p in ps)
        how = "standard error over replicas" if replicas > 1 else "block standard error"
        ax.set_title(f"{column.replace('_', ' ')} vs {key} (error bars: {how})", fontsize="medium")
        if others:
            ax.legend(fontsize="small")
        fig.tight_layout()
        path = Path(path)
        fig.savefig(path, dpi=120)
        return path


def resolve_column(name: str) -> str:
    """A result column from its name or short alias (T, P, PE, KE, E, drift, D)."""
    name = ALIASES.get(name, name)
    if name not in RESULTS:
        known = ", ".join(list(RESULTS) + list(ALIASES))
        raise SweepError(f"unknown result column {name!r} (known: {known})")
    return name


def _number(value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def _hashable(value):
    return tuple(value) if isinstance(value, list) else value


def _csv_cell(value):
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, list):
        return _format_value(value)
    return value


# --------------------------------------------------------------------- API
def sweep(
    config,
    vary: Mapping[str, Sequence] | Sequence[str] = (),
    replicas: int = 1,
    out=None,
    *,
    client=None,
    scheduler: str | None = None,
    workers: int | None = None,
    diffusion: bool = False,
    discard: float = 0.0,
    n_blocks: int = 5,
    overwrite: bool = False,
    progress: Callable[[SweepProgress], None] | None = None,
) -> SweepTable:
    """Run a sweep of ``md run`` over varied config keys and replicas on Dask.

    Parameters
    ----------
    config : str or Path
        Base TOML config.
    vary : mapping of dotted key to values, or sequence of ``"KEY=V1,V2"``
        E.g. ``{"system.temperature": [0.8, 1.2], "integrator.dt": [0.002, 0.005]}``.
    replicas : int
        Runs per parameter point with different seeds (see the module notes).
    out : str or Path, optional
        Output folder (default ``sweep-<config stem>``), shared by client and workers.
    client : distributed.Client, optional
        Run on this client's cluster (left open).
    scheduler : str, optional
        Address of a Dask scheduler to connect to instead.
    workers : int, optional
        Size of the local cluster made when neither is given (default: cores).
    diffusion : bool
        Also summarise the Einstein diffusion coefficient of every run.
    discard : float
        Leading fraction of each run's frames left out of the averages.
    n_blocks : int
        Blocks of the standard errors of the averages.
    overwrite : bool
        Redo runs whose outputs exist (else complete ones are skipped and
        others refused).
    progress : callable, optional
        Called with a :class:`SweepProgress` as the sweep goes.

    Returns
    -------
    SweepTable
        One row per run; also written to ``OUT/sweep.csv``.
    """
    plan = plan_sweep(config, vary, replicas, out)
    check_outputs(plan, overwrite)
    with connect(client, scheduler, workers) as dask_client:
        return run_sweep(
            plan, dask_client, overwrite=overwrite, diffusion=diffusion, discard=discard,
            n_blocks=n_blocks, progress=progress,
        )  # fmt: skip


class _CallableModule(types.ModuleType):
    """``md.sweep`` is this module; calling it calls :func:`sweep`."""

    def __call__(self, *args, **kwargs) -> SweepTable:
        return sweep(*args, **kwargs)


if __name__ == "__main__":
    sys.exit(_child_main(sys.argv[1:]))
else:
    sys.modules[__name__].__class__ = _CallableModule

__all__ = [
    "SweepError",
    "SweepPlan",
    "SweepProgress",
    "SweepTable",
    "check_outputs",
    "connect",
    "dumps_toml",
    "parse_vary",
    "plan_sweep",
    "replica_seed",
    "run_sweep",
    "summarize",
    "sweep",
]
