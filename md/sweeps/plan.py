"""Planning a sweep: expand a base config over varied keys and replicas, validate every run."""

from __future__ import annotations

import copy
import itertools
import logging
import math
import re
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w

from md.assemble import build_components
from md.config import Config, parse_config
from md.errors import ConfigError, SweepError, TrajectoryError
from md.forcefield import ForceField
from md.trajectory import read_frame_steps

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
    "density": "density",
    "volume": "volume",
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
    "rho": "density",
    "V": "volume",
    "PE": "potential_energy_per_atom",
    "KE": "kinetic_energy_per_atom",
    "E": "total_energy_per_atom",
    "drift": "energy_drift_per_atom",
    "D": "diffusion",
}


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


#: Most runs a sweep plans unless asked for more (``md sweep --max-runs``).
MAX_RUNS = 10_000


def count_runs(vary, replicas: int = 1) -> int:
    """Runs a sweep over ``vary`` (as for :func:`plan_sweep`) with ``replicas`` has."""
    return math.prod(len(values) for _, values in _vary_pairs(vary)) * replicas


def parse_vary(text: str, max_values: int = MAX_RUNS) -> tuple[str, list]:
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
        spaced = _linspace(part, max_values)
        values.extend(spaced if spaced is not None else [_literal(part)])
    seen: dict = {}  # equal values (1 and 1.0 too) share a key: linear, not quadratic
    repeated = set()
    for value in values:
        comparable = _comparable(value)
        if comparable in seen:
            repeated.add(format_value(value))
        seen[comparable] = value
    repeated = sorted(repeated)
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
    max_runs: int = MAX_RUNS,
) -> SweepPlan:
    """Expand a base config into every run of a sweep and validate each one.

    A sweep of more than ``max_runs`` runs is refused before anything is
    built. Runs that differ only in seeds are validated once.

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
    n_runs = math.prod(len(values) for _, values in pairs) * replicas
    if n_runs > max_runs:
        raise SweepError(
            f"the sweep has {n_runs} runs, more than the cap of {max_runs}; pass --max-runs "
            f"{n_runs} (max_runs=) to allow it"
        )
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
    short = short_names(keys)
    runs, labels = [], {}
    validated: dict[str, Config] = {}  # by config text without seeds and output path
    for point in itertools.product(*(values for _, values in pairs)):
        point = tuple(zip(keys, point, strict=True))
        data = copy.deepcopy(base)
        where = f"{config}" + (
            " with " + ", ".join(f"{k}={format_value(v)}" for k, v in point) if point else ""
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
                + "".join(f", {k} = {format_value(v)}" for k, v in point)
                + f", replica {replica}, seed {run_seed}\n"
            )
            run_text = header + tomli_w.dumps(data)
            if parsed is None:  # replicas differ only in seeds: validate each point once
                shape = _without_seeds(data)
                parsed = validated.get(shape)
                if parsed is None:
                    try:
                        parsed = _validate(run_text, where)
                    except ConfigError as error:
                        raise SweepError(str(error)) from None
                    validated[shape] = parsed
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


def _without_seeds(data: dict) -> str:
    """The config as text with its seeds and output path left out (what validity depends on)."""
    shape = copy.deepcopy(data)
    shape.pop("seed", None)
    if isinstance(shape.get("integrator"), dict):
        shape["integrator"].pop("seed", None)
    if isinstance(shape.get("output"), dict):
        shape["output"].pop("path", None)
    return tomli_w.dumps(shape)


def _validate(text: str, where: str):
    """Check a run's config as ``md run`` does before it writes anything; return it."""
    config = parse_config(tomllib.loads(text), source=where, text=text, base=".")
    state, potentials, _ = build_components(config)
    try:
        ForceField(potentials, skin=config.run.skin).check(state)
    except ValueError as error:
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


def short_names(keys: list[str]) -> dict[str, str]:
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


def _comparable(value):
    """A hashable stand-in for a TOML value, equal where the values are equal."""
    if isinstance(value, list | tuple):
        return ("list", tuple(_comparable(v) for v in value))
    if isinstance(value, dict):
        return ("table", tuple(sorted((k, _comparable(v)) for k, v in value.items())))
    return value


def _linspace(text: str, max_values: int = MAX_RUNS) -> list[float] | None:
    parts = text.split(":")
    if len(parts) != 3:
        return None
    try:
        low, high, count = float(parts[0]), float(parts[1]), int(parts[2])
    except ValueError:
        return None
    if count < 2 or not (math.isfinite(low) and math.isfinite(high)):
        raise SweepError(f"--vary range {text!r}: needs finite ends and at least 2 values")
    if count > max_values:
        raise SweepError(
            f"--vary range {text!r} asks for {count} values, more than the {max_values} runs a "
            "sweep may have; pass --max-runs to allow more"
        )
    return [float(f"{v:.12g}") for v in np.linspace(low, high, count)]


def format_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, list):
        return "[" + ", ".join(format_value(v) for v in value) + "]"
    return str(value)


def _label_text(value) -> str:
    if isinstance(value, list):
        return "x".join(_label_text(v) for v in value)
    return re.sub(r"[^A-Za-z0-9.+-]", "-", format_value(value))


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
