"""Checkpoints: the full dynamical state of a run, written atomically, read back exactly.

A checkpoint is one ``.npz`` file (numpy's zip of arrays, read without
pickle) holding

- the State: positions, velocities, masses, box, pbc, types, type names,
  step and time;
- the integrator's private state, from its ``get_state()`` (half-step
  velocities, adaptive substep size, thermostat variables, the random
  generator's state); integrators that are not
  :class:`integrators.base.Restartable` have none;
- the positions at which the neighbour list was last built, so that a
  resumed run rebuilds the very same list and sums forces in the same order
  (the continuation is then bit-for-bit identical to an uninterrupted run);
- a fingerprint of the physics configuration (everything except the run
  length, the output cadence and the thermo table), compared on resume;
- the number of trajectory frames written up to the checkpoint, the step of
  the last one, and the run id stored in the trajectory, so that a resume
  discards frames written after the checkpoint and refuses a foreign file;
- for a run decomposed over MPI ranks, its grid, each atom's owner at the
  last build and its positions at the last two step starts, so that a resume on
  the same grid rebuilds the same ghosts and lists and migrates atoms at the
  same steps (:meth:`md.distributed.DistributedSimulation.resume`); any other rank
  count, or one process, resumes from the same file.
- in ``extra``, the config file's name and the run's energies at step 0
  (``start``), from which a resumed run reports its drifts.

Writing goes to a temporary file in the same directory, which is flushed,
synced and renamed over the previous checkpoint (``os.replace``), so a crash
during a write leaves the previous checkpoint intact.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from integrators.base import Restartable
from md._files import atomic_path, disk_full
from md.distributed.views import Decomposed
from md.errors import CheckpointError
from md.state import State

FORMAT = "leapmd-checkpoint"
VERSION = 1
#: Suffix appended to the trajectory path to name its checkpoint.
SUFFIX = ".ckpt"
#: A decomposed run's per-atom positions in its layout: the last two step starts, from
#: which the next step's look-ahead measures (None where unknown).
_LAYOUT_POSITIONS = ("step_start", "step_before")
#: The layout's per-atom arrays, kept as arrays of their own (the rest is plain data).
_LAYOUT_ARRAYS = ("owners", "slots", *_LAYOUT_POSITIONS)


def checkpoint_path(trajectory) -> Path:
    """Return the checkpoint path belonging to trajectory path ``trajectory``."""
    trajectory = Path(trajectory)
    return trajectory.with_name(trajectory.name + SUFFIX)


@dataclass
class Checkpoint:
    """A checkpoint read back (see :func:`read_checkpoint`).

    Attributes
    ----------
    state : State
        The system at the checkpoint, in engine units.
    integrator : dict
        ``describe()`` of the integrator that wrote it.
    integrator_state : dict or None
        What its ``get_state()`` returned (None if it has no private state).
    neighbor_reference : ndarray of float64, shape (N, 3), or None
        Positions of the last neighbour-list build [length].
    neighbor_cell : tuple of two ndarrays (3,), or None
        Edge lengths and tilt of the cell at that build [length] (None in
        checkpoints written before lists were kept through cell changes).
    neighbor_pruned : ndarray of float64, shape (N, 3), or None
        Positions of the cluster list's last prune [length] (None where the
        list is not pruned: see ``outer_skin`` in :class:`md.neighbors.NeighborList`).
    neighbor_step : int or None
        The step of that build, from which a list looked at every ``every`` steps
        counts (None in checkpoints written before it was kept).
    fingerprint : dict
        The physics configuration (see :func:`physics_fingerprint`).
    n_frames, last_frame_step : int
        Trajectory frames written up to the checkpoint, and the step of the
        last (-1 if none).
    run_id : str
        Identifier shared with the trajectory file.
    precision : str
        The force field's precision (``"double"`` or ``"mixed"``; ``"double"``
        for checkpoints written before mixed precision existed).
    """

    path: Path
    state: State
    integrator: dict
    integrator_state: dict | None
    neighbor_reference: np.ndarray | None
    fingerprint: dict
    n_frames: int
    last_frame_step: int
    run_id: str
    extra: dict = field(default_factory=dict)
    neighbor_cell: tuple | None = None
    decomposition: dict | None = None
    neighbor_pruned: np.ndarray | None = None
    precision: str = "double"
    neighbor_step: int | None = None


# ---------------------------------------------------------------------- writing
def write_checkpoint(
    path,
    state: State,
    integrator,
    forcefield=None,
    fingerprint: dict | None = None,
    n_frames: int = 0,
    last_frame_step: int = -1,
    run_id: str = "",
    extra: dict | None = None,
) -> Path:
    """Write a checkpoint atomically (temporary file, fsync, rename).

    Parameters
    ----------
    path : str or Path
        Checkpoint file; replaced only once the new one is complete.
    state : State
        The system (copied into the file as is).
    integrator : Integrator
        Its ``describe()`` and, if it has one, ``get_state()`` are stored.
    forcefield : ForceField, optional
        Its neighbour list's build positions are stored, so the resumed run
        rebuilds the same list, and its precision, which :func:`restore` checks.
    fingerprint : dict, optional
        Physics configuration to compare on resume (plain data).
    n_frames, last_frame_step : int
        Trajectory frames written so far, and the step of the last one.
    run_id : str
        Identifier shared with the trajectory.
    extra : dict, optional
        More plain data to keep (e.g. the config file name).

    Raises
    ------
    OSError
        If the file cannot be written (missing directory, no permission,
        disk full); a previous checkpoint is then left as it was.
    """
    path = Path(path)
    arrays: dict[str, np.ndarray] = {
        "positions": state.positions,
        "velocities": state.velocities,
        "masses": state.masses,
        "box": state.box,
        "tilt": state.tilt,
        "pbc": state.pbc,
        "types": state.types,
    }
    nl = None if forcefield is None else forcefield.neighbor_list
    reference = None if nl is None else nl.reference_positions
    if reference is not None and reference.shape == state.positions.shape:
        arrays["neighbor_reference"] = reference
        # the cell of that build: a list kept through a barostat's moves is rebuilt in it
        arrays["neighbor_box"], arrays["neighbor_tilt"] = nl.reference_cell
        pruned = nl.pruned_positions  # the cluster list's last prune: the pairs it holds
        if pruned is not None:
            arrays["neighbor_pruned"] = pruned
        if nl.built_step is not None:  # where `every` counts from
            arrays["neighbor_step"] = np.array(nl.built_step, dtype=np.int64)
    # a decomposed run's grid and owners (its rank-0 view of the force field holds them)
    layout = forcefield.decomposition if isinstance(forcefield, Decomposed) else None
    if layout is not None and layout.get("owners") is not None:
        arrays["domain_owners"] = np.asarray(layout["owners"], dtype=np.int64)
        if layout.get("slots") is not None:  # each atom's row on its rank
            arrays["domain_slots"] = np.asarray(layout["slots"], dtype=np.int64)
        for key in _LAYOUT_POSITIONS:  # the last step starts, where known
            if layout.get(key) is not None:
                arrays[f"domain_{key}"] = np.asarray(layout[key], dtype=np.float64)
        layout = {key: value for key, value in layout.items() if key not in _LAYOUT_ARRAYS}
    saved = integrator.get_state() if isinstance(integrator, Restartable) else None
    meta = {
        "format": FORMAT,
        "version": VERSION,
        "step": int(state.step),
        "time": float(state.time),
        "type_names": list(state.type_names),
        "integrator": _plain(integrator.describe()),
        "integrator_state": None if saved is None else _encode(saved, arrays, "integrator"),
        "fingerprint": _plain(fingerprint or {}),
        "n_frames": int(n_frames),
        "last_frame_step": int(last_frame_step),
        "run_id": str(run_id),
        "extra": _plain(extra or {}),
    }
    if layout is not None:
        meta["decomposition"] = _plain(layout)
    meta["precision"] = "double" if forcefield is None else str(forcefield.precision)
    arrays["meta"] = np.array(json.dumps(meta))
    with atomic_path(path) as temporary, open(temporary, "wb") as handle:
        np.savez(handle, **arrays)
    return path


# ---------------------------------------------------------------------- reading
def read_checkpoint(path) -> Checkpoint:
    """Read a checkpoint written by :func:`write_checkpoint`.

    Raises
    ------
    CheckpointError
        If the file is missing, truncated, corrupted, not a checkpoint, or
        holds an invalid state; the message names the file.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no checkpoint found")
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {name: npz[name] for name in npz.files}
    except Exception as error:  # zipfile, zlib, numpy header and OS errors alike
        # numpy's own text may suggest allow_pickle, which must never be followed here.
        raise CheckpointError(
            f"{path}: the checkpoint is damaged ({type(error).__name__}) and cannot be "
            f"resumed. {_AFTER_DAMAGE}"
        ) from None
    try:
        meta = json.loads(str(arrays.pop("meta")[()]))
        if not isinstance(meta, dict) or meta.get("format") != FORMAT:
            raise ValueError("not a leapmd checkpoint")
        if meta.get("version") != VERSION:
            raise ValueError(f"checkpoint version {meta.get('version')}, expected {VERSION}")
        state = State(
            positions=arrays["positions"],
            velocities=arrays["velocities"],
            masses=arrays["masses"],
            box=arrays["box"],
            tilt=arrays["tilt"] if "tilt" in arrays else None,  # older checkpoints: none
            pbc=arrays["pbc"],
            types=arrays["types"],
            type_names=tuple(meta["type_names"]),
            step=int(meta["step"]),
            time=float(meta["time"]),
        )
        state.validate()
        reference = arrays.get("neighbor_reference")
        if reference is not None and reference.shape != state.positions.shape:
            raise ValueError("neighbour-list positions do not match the atom count")
        pruned = arrays.get("neighbor_pruned") if reference is not None else None
        if pruned is not None and pruned.shape != state.positions.shape:
            raise ValueError("the neighbour list's pruned positions do not match the atom count")
        saved = meta["integrator_state"]
        layout = meta.get("decomposition")
        if layout is not None:
            layout = {
                **layout,
                "owners": arrays.get("domain_owners"),
                "slots": arrays.get("domain_slots"),
            }
            if layout["owners"] is None or layout["owners"].shape != (state.n_atoms,):
                raise ValueError("the decomposition's owners do not match the atom count")
            if layout["slots"] is not None and layout["slots"].shape != (state.n_atoms,):
                raise ValueError("the decomposition's atom rows do not match the atom count")
            for key in _LAYOUT_POSITIONS:  # (None in checkpoints written before they were kept)
                layout[key] = arrays.get(f"domain_{key}")
                if layout[key] is not None and layout[key].shape != state.positions.shape:
                    raise ValueError(f"the decomposition's {key} does not match the atom count")
        return Checkpoint(
            path=path,
            state=state,
            integrator=meta["integrator"],
            integrator_state=None if saved is None else _decode(saved, arrays),
            neighbor_reference=reference,
            fingerprint=meta["fingerprint"],
            n_frames=int(meta["n_frames"]),
            last_frame_step=int(meta["last_frame_step"]),
            run_id=str(meta["run_id"]),
            extra=meta.get("extra", {}),
            neighbor_cell=(
                (arrays["neighbor_box"], arrays["neighbor_tilt"])
                if "neighbor_box" in arrays and reference is not None
                else None
            ),
            decomposition=layout,
            precision=str(meta.get("precision", "double")),
            neighbor_pruned=pruned,
            neighbor_step=(
                int(arrays["neighbor_step"])
                if "neighbor_step" in arrays and reference is not None
                else None
            ),
        )
    except (KeyError, ValueError, TypeError, IndexError, json.JSONDecodeError) as error:
        raise CheckpointError(
            f"{path}: the checkpoint is damaged or not ours ({error}) and cannot be resumed. "
            f"{_AFTER_DAMAGE}"
        ) from None


_AFTER_DAMAGE = (
    "The trajectory's frames are unaffected (md info and md.open_trajectory read them); "
    "to run again, start afresh with --overwrite (or --output elsewhere)"
)


def restore(checkpoint: Checkpoint, integrator, forcefield=None) -> None:
    """Give ``integrator`` its saved private state and rebuild the neighbour list.

    The neighbour list is built at the positions of its last build before the
    checkpoint, so it lists the same pairs in the same order as in the run
    that wrote the checkpoint.

    Raises
    ------
    CheckpointError
        If the integrator differs from the one saved, or rejects the state, or
        ``forcefield`` has another precision than the run that wrote it.
    """
    precision = checkpoint.precision if forcefield is None else forcefield.precision
    if precision != checkpoint.precision:
        raise CheckpointError(
            f"{checkpoint.path}: written by a run in {checkpoint.precision} precision, "
            f'not {precision}; resume with precision = "{checkpoint.precision}"'
        )
    if _plain(integrator.describe()) != checkpoint.integrator:
        raise CheckpointError(
            f"{checkpoint.path}: written by integrator {checkpoint.integrator}, "
            f"not {integrator.describe()}"
        )
    saved = checkpoint.integrator_state
    if saved is not None:
        if not isinstance(integrator, Restartable):
            raise CheckpointError(
                f"{checkpoint.path}: holds private state for {type(integrator).__name__}, "
                "which cannot take it"
            )
        try:
            integrator.set_state(saved)
        except (KeyError, ValueError, TypeError) as error:
            raise CheckpointError(
                f"{checkpoint.path}: the integrator's saved state does not fit ({error})"
            ) from None
    nl = None if forcefield is None else forcefield.neighbor_list
    if nl is not None and checkpoint.neighbor_reference is not None:
        box, tilt = checkpoint.neighbor_cell or (None, None)
        nl.rebuild_at(
            checkpoint.state,
            checkpoint.neighbor_reference,
            box,
            tilt,
            pruned=checkpoint.neighbor_pruned,
            step=checkpoint.neighbor_step,
        )
        # The result cache may hold forces from the built configuration; drop it.
        forcefield.invalidate()


# ------------------------------------------------------------------ fingerprint
def physics_fingerprint(config) -> dict:
    """Plain-data description of everything in ``config`` that shapes the dynamics.

    Includes the units, seed, system (with a SHA-256 of a structure file),
    potentials, integrator, neighbour-list skin (it decides the summation
    order, hence round-off) and which per-atom data the trajectory stores.
    Excluded, so they may change on resume: ``[run] steps`` and
    ``thermo_every``, ``[output] path``, ``every`` and ``checkpoint_every``.

    The layout is what checkpoints hold, so it stays as it is: a plug-in
    section is its type and the values its record holds (``"kind"`` naming
    a barostat's type), the system every field of its record.
    """
    system = {
        key: (str(value) if isinstance(value, Path) else value)
        for key, value in dataclasses.asdict(config.system).items()
    }
    structure = config.system.structure
    barostat = config.barostat
    if structure is not None:
        try:
            system["structure_sha256"] = hashlib.sha256(Path(structure).read_bytes()).hexdigest()
        except OSError:
            system["structure_sha256"] = None
    return _plain(
        {
            "units": config.units.name,
            "seed": config.seed,
            "system": system,
            "potentials": [{"type": p.type, **p.values} for p in config.potentials],
            "integrator": {"type": config.integrator.type, **config.integrator.values},
            # only when set, so checkpoints written before barostats existed still resume
            **({"barostat": {"kind": barostat.type, **barostat.values}} if barostat else {}),
            # precision only when mixed, as the barostat: older checkpoints still resume
            # the list's rule only when not the exact default, as precision
            "run": {
                "skin": config.run.skin,
                **({"precision": config.run.precision} if config.run.precision != "double" else {}),
                **(
                    {
                        "neighbor_every": config.run.neighbor_every,
                        "neighbor_check": config.run.neighbor_check,
                    }
                    if (config.run.neighbor_every, config.run.neighbor_check) != (1, True)
                    else {}
                ),
            },
            "output": {
                "velocities": config.output.velocities,
                "forces": config.output.forces,
            },
        }
    )


def fingerprint_changes(saved: dict, current: dict) -> list[str]:
    """Return one line per difference, e.g. ``"integrator.dt: 0.005 -> 0.004"``."""
    old, new = _flatten(saved), _flatten(current)
    changes = []
    for key in sorted(set(old) | set(new)):
        if key not in new:
            changes.append(f"{key}: {_short(old[key])} -> (removed)")
        elif key not in old:
            changes.append(f"{key}: (not set) -> {_short(new[key])}")
        elif not _same(old[key], new[key]):
            changes.append(f"{key}: {_short(old[key])} -> {_short(new[key])}")
    return changes


def _flatten(value, prefix: str = "") -> dict:
    if isinstance(value, dict):
        flat = {}
        for key, item in value.items():
            flat.update(_flatten(item, f"{prefix}.{key}" if prefix else str(key)))
        return flat
    if isinstance(value, list) and value and any(isinstance(v, dict) for v in value):
        flat = {}
        for index, item in enumerate(value):
            flat.update(_flatten(item, f"{prefix}[{index}]"))
        return flat
    return {prefix: value}


def _same(a, b) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return a == b


def _short(value) -> str:
    text = json.dumps(value)
    return text if len(text) <= 60 else text[:57] + "..."


# ---------------------------------------------------------------- plain data
def _plain(value):
    """JSON round trip: tuples become lists, paths strings, numpy scalars numbers."""
    return json.loads(json.dumps(value, default=_default))


def _default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, set | frozenset):
        return sorted(value)
    raise TypeError(f"cannot store {type(value).__name__} in a checkpoint")


def _encode(value, arrays: dict, prefix: str):
    """Replace arrays by references into ``arrays``; the rest stays JSON (exact floats)."""
    if isinstance(value, np.ndarray):
        key = f"{prefix}:{len(arrays)}"
        arrays[key] = value
        return {"__array__": key}
    if isinstance(value, dict):
        return {str(k): _encode(v, arrays, prefix) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_encode(v, arrays, prefix) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def _decode(value, arrays: dict):
    if isinstance(value, dict):
        if set(value) == {"__array__"}:
            return np.array(arrays[value["__array__"]])
        return {k: _decode(v, arrays) for k, v in value.items()}
    if isinstance(value, list):
        return [_decode(v, arrays) for v in value]
    return value


__all__ = [
    "Checkpoint",
    "CheckpointError",
    "checkpoint_path",
    "fingerprint_changes",
    "physics_fingerprint",
    "read_checkpoint",
    "restore",
    "write_checkpoint",
]


# ------------------------------------------------------------------ observer
class Checkpointer:
    """Observer writing a checkpoint (atomically) with the trajectory's frame count.

    Attach it after the trajectory writer, so that a checkpoint counts the
    frame of its own step.

    Parameters
    ----------
    path : Path
        Checkpoint file (``checkpoint_path(trajectory)``).
    writer : H5MDWriter
        The run's trajectory writer (its ``n_frames`` and ``last_step`` are saved).
    fingerprint : dict
        Physics configuration compared on resume.
    run_id : str
        Identifier shared with the trajectory.
    config : str
        The config file name, kept for messages.
    start : dict, optional
        The run's energies at step 0 (plain numbers), kept so that a resumed
        run reports drifts over the whole run.
    """

    uses_virial = False  # saves the state; its steps need no virial
    #: A decomposed run gathers its layout (build positions, owners, step starts) for it
    #: (:class:`md.distributed.views.LayoutUse`); trajectory frames go without.
    store_layout = True

    def __init__(
        self,
        path: Path,
        writer,
        fingerprint: dict,
        run_id: str,
        config: str,
        start: dict | None = None,
    ) -> None:
        self.path = Path(path)
        self.writer = writer
        self.fingerprint = fingerprint
        self.run_id = run_id
        self.config = config
        self.start = dict(start or {})
        self.last_step: int | None = None

    def __call__(self, sim) -> None:
        """Write the checkpoint of ``sim``'s state.

        Raises
        ------
        OSError
            If it cannot be written; the message says it was the checkpoint, at
            which step ("disk full" when there was no room), and that the
            previous checkpoint is left as it was.
        """
        last = self.writer.last_step
        try:
            write_checkpoint(
                self.path,
                sim.state,
                sim.integrator,
                sim.forcefield,
                fingerprint=self.fingerprint,
                n_frames=self.writer.n_frames,
                last_frame_step=-1 if last is None else last,
                run_id=self.run_id,
                extra={"config_file": self.config, "start": self.start},
            )
        except OSError as error:
            what = "disk full" if disk_full(error) else (error.strerror or str(error))
            previous = (
                "the one written before"
                if self.last_step is None
                else (f"the one of step {self.last_step}")
            )
            raise OSError(
                error.errno,
                f"{what}: cannot write the checkpoint {self.path} at step {sim.state.step}; "
                f"{previous} is left as it was",
            ) from None
        self.last_step = sim.state.step
