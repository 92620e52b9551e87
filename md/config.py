"""Run configuration: TOML read into typed records, validated before anything runs.

Each section of a config is read into a frozen record. The fixed sections are
dataclasses whose fields declare their keys (:func:`md.schema.key`):
:class:`SystemConfig`, :class:`RunConfig`, :class:`OutputConfig`,
:class:`MinimizeConfig`. The plug-in sections (``[[potentials]]``,
``[integrator]``, ``[barostat]``) become :class:`PluginEntry` records whose
keys the plug-in named by ``type`` declares in its ``CONFIG_KEYS``
(``potentials.POTENTIALS``, ``integrators.INTEGRATORS``,
``integrators.barostats.BAROSTAT_KEYS``). :func:`sections` lists them all, and
the manual's config reference is generated from it, so a key is declared in
one place: adding a field to a record, or a :class:`md.schema.Key` to a
plug-in's ``CONFIG_KEYS``, is all it takes for the config to accept the key
and the reference to describe it.

Every problem is reported as a :class:`ConfigError` naming the file, the key
and the offending value. Times, rates and pressures are converted from the
config's unit system (``lj`` or ``metal``, where times are in fs and pressures
in bar) into engine units here, by the unit their key declares.

A note on its length (about 1100 lines, over the 800 where a module is split): most
of it is the sections' key declarations, a few lines each as the formatter writes them,
kept beside the reader that walks them.
"""

from __future__ import annotations

import logging
import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from types import MappingProxyType
from typing import Any

from integrators import INTEGRATORS, NoseHooverChain, integrator_class
from integrators.barostats import BAROSTAT_KEYS
from integrators.rattle import BondConstraints
from integrators.rigid import RigidConfig, checked_rigid
from md._checks import MAX_SEED
from md.build import lattice, maxwell_boltzmann
from md.errors import ConfigError, PluginError
from md.polymers import chain_angles, polymer_melt, single_chain
from md.rigid import bodies_on_sites
from md.schema import REQUIRED, Key, Varies, key, key_names, section_keys
from md.structure import read_structure
from md.topology import Topology
from md.units import UNIT_SYSTEMS, UnitSystem
from potentials import POTENTIALS, potential_class

#: Largest lattice accepted (4 x 10^7 fcc atoms), so a typo cannot exhaust memory.
_MAX_CELLS = 10_000_000
logger = logging.getLogger(__name__)


class _Table:
    """A TOML table being consumed key by key; leftovers are unknown keys.

    ``units`` converts numbers by their key's declared unit (None: the
    section holds no converted quantity); ``base`` is the folder that
    relative ``path`` keys are relative to.
    """

    def __init__(
        self,
        data: Any,
        where: str,
        source: str,
        base: Path = Path("."),
        units: UnitSystem | None = None,
    ) -> None:
        if not isinstance(data, dict):
            raise ConfigError(f"{source}: [{where}] must be a table, got {type(data).__name__}")
        self.data = dict(data)
        self.where = where
        self.source = source
        self.base = base
        self.units = units

    def error(self, key: str, message: str) -> ConfigError:
        return ConfigError(f"{self.source}: {self._name(key)}: {message}")

    def _name(self, key: str) -> str:
        return f"[{self.where}] {key}" if self.where else key

    def take(self, name: str, default: Any = REQUIRED) -> Any:
        """The raw value of ``name`` (a section's table), or ``default``."""
        if name not in self.data:
            if default is REQUIRED:
                raise ConfigError(f"{self.source}: missing required key {self._name(name)}")
            return default
        return self.data.pop(name)

    def read(self, key: Key, case: str | None = None, needs: str = "") -> Any:
        """The checked value of ``key`` (in engine units), or its default in ``case``.

        ``needs`` is added to the message for a missing required key.
        """
        if key.name not in self.data:
            default = key.default_in(case)
            if default is REQUIRED:
                raise ConfigError(
                    f"{self.source}: missing required key {self._name(key.name)}{needs}"
                )
            return self.convert(key, default)
        value = self.data.pop(key.name)
        try:
            value = key.check(value)
        except ValueError as error:
            raise self.error(key.name, str(error)) from None
        if key.kind == "path" and not Path(value).is_absolute():
            value = str(self.base / value)  # relative to the config
        elif key.kind == "output path":
            value = Path(value)  # relative to the working directory
        return self.convert(key, value)

    def convert(self, key: Key, value: Any) -> Any:
        """``value`` of a number ``key`` in engine units (times, rates, pressures)."""
        if value is None or key.kind != "number" or key.unit is None:
            return value
        if self.units is None:
            if key.unit in _CONVERTED:
                raise AssertionError(f"[{self.where}] {key.name}: no units to convert it yet")
            return value
        return self.units.from_config(key.unit, value)

    def plugin(
        self, kind: str, keys: tuple[Key, ...], others: set[str], fill_defaults: bool = False
    ) -> dict:
        """The values of a plug-in table of type ``kind`` declaring ``keys``.

        A key the type does not declare is refused, said to belong to another
        type when ``others`` (the keys of every type) holds it. Given keys
        are checked and converted; with ``fill_defaults`` the rest take their
        defaults, else they are left out (the plug-in's own apply).
        """
        names = key_names(keys)
        foreign = [name for name in self.data if name not in names]
        if any(name in others for name in foreign):
            raise ConfigError(
                f"{self.source}: [{self.where}] {', '.join(foreign)}: does not apply to "
                f"type = {kind!r}, which takes {', '.join(names)}"
            )
        if foreign:
            raise ConfigError(
                f"{self.source}: [{self.where}] ({kind}): unknown key(s): "
                f"{', '.join(sorted(foreign))} (allowed: {', '.join(sorted(names))})"
            )
        case = None if self.units is None else self.units.name
        needs = f" (type = {kind!r} needs it)"
        return {
            k.name: self.read(k, case, needs)
            for k in keys
            if fill_defaults or k.name in self.data or k.default_in(case) is REQUIRED
        }

    def fields(self, record, case: str | None = None) -> dict:
        """The values of the keys a record class declares that apply in ``case``."""
        return {k.name: self.read(k, case) for k in section_keys(record) if k.applies(case)}

    def finish(self, keys: tuple[Key, ...] = (), case: str | None = None) -> None:
        """Refuse what is left: keys of another kind of system, or unknown keys."""
        elsewhere = [k for k in keys if k.name in self.data and not k.applies(case)]
        if elsewhere:
            kinds = sorted({_SYSTEM_KINDS[c] for k in elsewhere for c in k.when})
            raise ConfigError(
                f"{self.source}: [{self.where}] {', '.join(k.name for k in elsewhere)}: does "
                f"not apply to {_SYSTEM_KINDS[case]} (only to {' or '.join(kinds)})"
            )
        if self.data:
            unknown = ", ".join(sorted(self.data))
            raise ConfigError(f"{self.source}: unknown key(s) in {self._where()}: {unknown}")

    def _where(self) -> str:
        return f"[{self.where}]" if self.where else "the top level"


#: Quantities a config gives in its own units (times in fs, pressures in bar for metal).
_CONVERTED = ("time", "1/time", "pressure", "1/pressure")

# ------------------------------------------------------------------ fixed sections
#: The kinds of [system], named as keys' ``when`` and ``Varies`` defaults name them.
_SYSTEM_KINDS = {
    "lattice": "a lattice",
    "melt": 'polymer = "melt"',
    "chain": 'polymer = "chain"',
    "structure": "a structure file",
}
SYSTEM_KINDS = MappingProxyType(_SYSTEM_KINDS)
_POLYMER = ("melt", "chain")


@dataclass(frozen=True)
class SystemConfig:
    """``[system]``: what to simulate, a lattice, a polymer or a structure file, and its start.

    Exactly one of ``lattice``, ``polymer`` and ``structure`` says the kind of
    system (:data:`SYSTEM_KINDS`); each key applies to the kinds its
    declaration names (``when``). Fields of keys that do not apply hold a
    fixed value (``unset``), as they always have: checkpoints compare them.
    """

    lattice: str | None = key(
        None,
        "string",
        choices=("sc", "bcc", "fcc"),
        when=("lattice",),
        doc="A cubic lattice filling the box; needs `cells` and one of `density` and "
        "`lattice_constant`.",
    )
    polymer: str | None = key(
        None,
        "string",
        choices=("melt", "chain"),
        when=_POLYMER,
        doc="Bead-spring chains: `melt` (chains at a density, periodic) or `chain` (one chain, "
        "open); see the polymers guide.",
    )
    chains: int = key(
        REQUIRED, "integer", unset=1, minimum=1, when=("melt",), doc="The number of chains."
    )
    chain_length: int = key(
        REQUIRED, "integer", unset=2, minimum=2, when=_POLYMER, doc="Beads per chain."
    )
    bond_length: float = key(
        0.97,
        "number",
        unit="length",
        positive=True,
        when=_POLYMER,
        doc="The bead spacing the builder places (0.97: Kremer-Grest's mean bond).",
    )
    straight: bool = key(
        False,
        "boolean",
        when=("chain",),
        doc="Build the chain straight instead of as a random walk.",
    )
    cells: tuple[int, int, int] = key(
        REQUIRED,
        "integer or list of three",
        unset=(1, 1, 1),
        when=("lattice",),
        doc="Unit cells along x, y and z (one number: all three).",
    )
    density: float | None = key(
        Varies(lattice=None, melt=REQUIRED),
        "number",
        unset=None,
        unit="number density",
        positive=True,
        when=("lattice", "melt"),
        doc="Atoms (beads) per volume. A lattice needs this or `lattice_constant`.",
    )
    lattice_constant: float | None = key(
        None,
        "number",
        unit="length",
        positive=True,
        when=("lattice",),
        doc="The cubic cell's edge; instead of `density`.",
    )
    shear: tuple[float, float, float] | None = key(
        None,
        "number or list of three",
        when=("lattice",),
        doc="Tilt factors (xy, xz, yz) of a lattice in a sheared cell (HOOMD-blue's).",
    )
    structure: Path | None = key(
        None,
        "path",
        when=("structure",),
        doc="A structure file (anything ase.io reads, LAMMPS data, GSD, H5MD), relative to "
        "the config; its bonds and angles come along.",
    )
    format: str | None = key(
        None,
        "string",
        when=("structure",),
        doc="The ase.io format of the structure file.",
        default_doc="guessed from the name",
    )
    mass: float | dict[str, float] | None = key(
        None,
        "number or table",
        unit="mass",
        doc="Atom mass, > 0; for a structure file also per type name (`{Ar = 39.95}`).",
        default_doc="1; a structure file's own, else ASE's table",
    )
    type_name: str = key(
        Varies(lattice="A", melt="M", chain="M"),
        "string",
        unset="A",
        when=("lattice", *_POLYMER),
        doc="The atoms' type name.",
    )
    pbc: tuple[bool, bool, bool] | None = key(
        None,
        "boolean or list of three",
        doc="Periodic along x, y and z (one value: all three).",
        default_doc='true; false for `polymer = "chain"`; a structure file\'s own',
    )
    temperature: float | None = key(
        None,
        "number",
        unit="temperature",
        minimum=0.0,
        doc="Draw Maxwell-Boltzmann velocities at exactly this temperature (zero total momentum).",
        default_doc="zero velocities, or a structure file's own",
    )


@dataclass(frozen=True)
class RunConfig:
    """``[run]``: how long, and how the engine runs it (all optional)."""

    steps: int = key(
        1000,
        "integer",
        unit="steps",
        minimum=0,
        doc="Time steps to run (`md run --steps` overrides it).",
    )
    skin: float = key(
        0.3,
        "number",
        unit="length",
        minimum=0.0,
        doc="Neighbour-list skin: the list is rebuilt when an atom moved more than half of it.",
    )
    outer_skin: float | None = key(
        None,
        "number",
        unit="length",
        minimum=0.0,
        doc="The cluster list's outer skin (mixed precision on one process): the search "
        "lists the pairs within cutoff + `outer_skin`, and the list the kernels read is "
        "that one pruned to cutoff + `skin`, again whenever an atom moved more than half "
        "the skin, until one moved more than half of `outer_skin - skin` since the "
        "search (as GROMACS's dynamic pruning). At most `skin`: no outer list, a search "
        "whenever the skin says. Not physics: the kernels sum the same pairs.",
        default_doc="5 x `skin`",
    )
    neighbor_every: int = key(
        1,
        "integer",
        unit="steps",
        minimum=1,
        doc="Look at the neighbour list only every this many steps (LAMMPS's `neigh_modify "
        "every`, GROMACS's `nstlist`); between looks it is kept whatever the atoms do. "
        "Above 1 a pair can come within the cutoff unseen until the next look, and the "
        "energy drifts: the default, 1, misses none. One process only.",
    )
    neighbor_check: bool = key(
        True,
        "boolean",
        doc="At a look, rebuild only if an atom moved more than half the skin since the last "
        "build (LAMMPS's `check yes`); false: rebuild at every look (`check no`, as "
        "GROMACS does every `nstlist` steps), which misses pairs too. One process "
        "only.",
    )
    thermo_every: int = key(
        100, "integer", unit="steps", minimum=1, doc="Steps between lines of the thermo table."
    )
    threads: int | None = key(
        None,
        "integer",
        minimum=1,
        doc="Kernel threads (`md run --threads` overrides it); not physics.",
        default_doc="every core",
    )
    decomposition: tuple[int, int, int] | None = key(
        None,
        "integer or list of three",
        doc="Bricks along a, b and c when the run is shared by MPI ranks (`mpiexec -n P md "
        "run`; their product is P, see the MPI guide); not physics.",
        default_doc="chosen from P and the cell",
    )
    balance_every: int = key(
        0,
        "integer",
        unit="steps",
        minimum=0,
        doc="Under MPI, dynamic load balancing: steps between checks of the ranks' busy "
        "time (wall time less time spent communicating); where the busiest rank's "
        "exceeds the mean by more than `balance_threshold`, the planes between bricks "
        "move towards an even share at the next migration (as LAMMPS's `fix balance "
        "... shift`). 0: never. A balanced run's trajectory depends on the ranks' "
        "timings, so it is not repeatable bit for bit; not physics.",
        default_doc="0 (never)",
    )
    balance_threshold: float = key(
        1.05,
        "number",
        minimum=1.0,
        doc="The imbalance (busiest rank's busy time over the mean) at which "
        "`balance_every`'s checks move the planes.",
    )
    precision: str = key(
        "double",
        "string",
        choices=("double", "mixed"),
        doc="`mixed`: the pair potentials' pair terms in float32 (r^2 rounded from double; "
        "forces within about 3e-7 of the largest), every sum, the positions and the "
        "integrator in double; bonds and angles stay double. A checkpoint keeps it: "
        "a resume must ask for the same.",
    )
    device: str = key(
        "cpu",
        "string",
        choices=("cpu", "cuda"),
        doc="`cuda`: the time step on an NVIDIA GPU (numba-cuda, `pip install "
        "'leapmd[cuda]'`; `md run --device` overrides it): the pair, bond and angle "
        "potentials of the frames, velocity Verlet, leapfrog, Langevin and Bussi; anything "
        "else is refused "
        "before the run "
        "writes anything. With `NUMBA_ENABLE_CUDASIM=1` it runs on numba's CUDA simulator. "
        "Not physics: a checkpoint of either device resumes on the other.",
    )


@dataclass(frozen=True)
class OutputConfig:
    """``[output]``: the trajectory and checkpoints (all optional)."""

    path: Path = key(
        Path("trajectory.h5"),
        "output path",
        doc="The H5MD trajectory, relative to the working directory; never overwritten "
        "without `--overwrite` (`md run --output` overrides it).",
    )
    every: int = key(
        100,
        "integer",
        unit="steps",
        minimum=1,
        doc="Steps between frames (positions, box, observables).",
    )
    velocities: bool = key(False, "boolean", doc="Store velocities in every frame.")
    forces: bool = key(False, "boolean", doc="Store forces in every frame.")
    checkpoint_every: int = key(
        1000,
        "integer",
        unit="steps",
        minimum=0,
        doc="Steps between checkpoints (0: only at the end and on signals).",
    )


@dataclass(frozen=True)
class MinimizeConfig:
    """``[minimize]``: FIRE 2.0 before the dynamics (see :mod:`md.minimize`).

    ``fmax`` and ``max_force`` [energy/length] and ``max_step`` [length] are
    in engine units, which are the config's in both unit systems.
    """

    fmax: float = key(
        1e-2,
        "number",
        unit="force",
        positive=True,
        doc="Converged when the largest force is below this.",
    )
    max_steps: int = key(10_000, "integer", minimum=1, doc="Most FIRE steps.")
    max_force: float | None = key(
        None,
        "number",
        unit="force",
        positive=True,
        doc="Cap on the forces of a push-off before FIRE (overlapping starts).",
        default_doc="no cap",
    )
    max_step: float = key(
        0.1, "number", unit="length", positive=True, doc="Largest move of an atom in one step."
    )
    report_every: int = key(
        100, "integer", unit="steps", minimum=1, doc="Steps between progress reports."
    )


#: The top level's own keys (the rest are the sections).
TOP_KEYS = (
    Key(
        "units",
        "string",
        None,
        choices=tuple(UNIT_SYSTEMS),
        doc='`"lj"`: reduced (epsilon = sigma = m = kB = 1, time in tau); `"metal"`: eV, '
        "Angstrom, amu, K, with times in fs and pressures in bar.",
        default_doc='`"metal"` with a structure file, else `"lj"`',
    ),
    Key(
        "seed",
        "integer",
        None,
        minimum=0,
        maximum=MAX_SEED,
        doc="Seeds the initial velocities and, for a thermostat or barostat without its own "
        "`seed`, their random streams.",
        default_doc="fresh entropy",
    ),
)


# ------------------------------------------------------------------ plug-in sections
@dataclass(frozen=True)
class PluginEntry:
    """A plug-in section read: the ``type`` it names and the values it is built with.

    ``values`` (read-only) holds the keys given, checked and in engine units,
    and what the config adds: ``kB`` for a thermostat, a seed derived from
    the top-level one for a stochastic thermostat or a barostat, and for a
    barostat the default of every key not given.
    """

    type: str
    values: Mapping[str, Any]

    def __post_init__(self) -> None:
        object.__setattr__(self, "values", MappingProxyType(dict(self.values)))

    def __reduce__(self):
        return (type(self), (self.type, dict(self.values)))

    def __contains__(self, name: str) -> bool:
        return name in self.values

    def get(self, name: str, default: Any = None) -> Any:
        """The value of ``name`` if the table gave it (or the config added it), else ``default``."""
        return self.values.get(name, default)

    @property
    def dt(self) -> float:
        """The time step [time] (of an ``[integrator]``)."""
        return self.values["dt"]


@dataclass(frozen=True)
class Section:
    """One section of a config, as :func:`sections` lists it for the reference.

    A fixed section has ``keys``; a plug-in section has ``types``, the keys
    of each type its ``type`` may name, and ``summaries``, one line about
    each type (from the plug-in's docstring).
    """

    name: str
    title: str
    doc: str
    keys: tuple[Key, ...] = ()
    types: Mapping[str, tuple[Key, ...]] | None = None
    summaries: Mapping[str, str] | None = None


def _summary(obj) -> str:
    doc = (getattr(obj, "__doc__", None) or "").strip()
    return doc.split("\n\n")[0].replace("\n", " ") if doc else ""


def sections() -> tuple[Section, ...]:
    """Every section a config may hold, with its keys, in the reference's order."""
    return (
        Section("", "Top level", "Scalars before the first table.", TOP_KEYS),
        Section(
            "system",
            "[system]",
            "What to simulate. Exactly one of `lattice`, `polymer` and `structure`; each "
            "other key applies to the kinds of system its row names.",
            section_keys(SystemConfig),
        ),
        Section(
            "potentials",
            "[[potentials]]",
            "One table per potential, summed; `type` names it: a style below, or a "
            "plug-in (an entry-point name or `module:attribute`; see the Plug-ins page).",
            types={n: c.CONFIG_KEYS for n, c in POTENTIALS.items()},
            summaries={n: _summary(c) for n, c in POTENTIALS.items()},
        ),
        Section(
            "integrator",
            "[integrator]",
            "How the system moves; `type` names the integrator or thermostat (or a "
            "plug-in, as for `[[potentials]]`).",
            types={n: c.CONFIG_KEYS for n, c in INTEGRATORS.items()},
            summaries={n: _summary(c) for n, c in INTEGRATORS.items()},
        ),
        Section(
            "integrator.constraints",
            "[integrator.constraints]",
            "Rigid bonds, for the integrators whose keys list `constraints`.",
            BondConstraints.CONFIG_KEYS,
        ),
        Section(
            "rigid",
            "[rigid]",
            "Rigid bodies moved as wholes (optional); `[integrator]` must be velocity "
            "Verlet, Langevin, Bussi or Nose-Hoover chains.",
            section_keys(RigidConfig),
        ),
        Section(
            "barostat",
            "[barostat]",
            "Constant pressure, with a thermostat as `[integrator]`; `type` names it.",
            types=dict(BAROSTAT_KEYS),
            summaries=dict(_BAROSTAT_SUMMARIES),
        ),
        Section(
            "minimize",
            "[minimize]",
            "FIRE 2.0 before the dynamics, on a fresh run (optional).",
            section_keys(MinimizeConfig),
        ),
        Section(
            "run",
            "[run]",
            "How long, and how the engine runs it (optional).",
            section_keys(RunConfig),
        ),
        Section(
            "output",
            "[output]",
            "The trajectory and checkpoints (optional).",
            section_keys(OutputConfig),
        ),
    )


_BAROSTAT_SUMMARIES = {
    "c_rescale": "Stochastic cell rescaling (Bernetti and Bussi): samples the "
    "isothermal-isobaric ensemble with any canonical thermostat.",
    "mtk": "Martyna-Tobias-Klein: cell and particles integrated together, with "
    '`[integrator] type = "nose_hoover_chain"`.',
    "berendsen": "Berendsen's weak coupling: relaxes the volume, for equilibration only "
    "(it does not sample the isothermal-isobaric ensemble).",
}


@dataclass(frozen=True)
class Config:
    """A validated run configuration: typed records in engine units, objects not yet built."""

    source: str
    text: str
    units: UnitSystem
    seed: int | None
    system: SystemConfig
    potentials: tuple[PluginEntry, ...]
    integrator: PluginEntry
    run: RunConfig
    output: OutputConfig
    minimize: MinimizeConfig | None = None
    barostat: PluginEntry | None = None
    rigid: RigidConfig | None = None


def load_config(path) -> Config:
    """Read and validate a TOML config file.

    Raises
    ------
    ConfigError
        For a missing or unreadable file, invalid TOML, unknown keys, missing
        or wrongly typed values; the message names the file and key.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found") from None
    except (OSError, UnicodeDecodeError) as error:
        raise ConfigError(f"{path}: cannot read config file ({error})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"{path}: invalid TOML ({error})") from None
    return parse_config(data, source=str(path), text=text, base=path.parent)


def parse_config(data: dict, source: str = "<config>", text: str = "", base=".") -> Config:
    """Validate a config already parsed into a dict (see :func:`load_config`)."""
    base = Path(base)
    top = _Table(data, "", source, base)
    units_key, seed_key = TOP_KEYS
    units_name = top.read(units_key)
    seed = top.read(seed_key)
    system = _parse_system(_Table(top.take("system"), "system", source, base))
    # Structure files come from ASE's world (eV, Angstrom, amu): metal units unless told.
    units = UNIT_SYSTEMS[units_name or ("metal" if system.structure is not None else "lj")]

    raw_potentials = top.take("potentials")
    if not isinstance(raw_potentials, list) or not raw_potentials:
        raise ConfigError(
            f"{source}: potentials must be a non-empty array of tables ([[potentials]])"
        )
    every_key = {k.name for c in POTENTIALS.values() for k in c.CONFIG_KEYS}
    potentials = []
    for index, entry in enumerate(raw_potentials):
        table = _Table(entry, f"potentials.{index}", source, base, units)
        kind, cls = _read_type(table, potential_class)
        values = table.plugin(kind, cls.CONFIG_KEYS, every_key)
        for entry in _pair_files(values):  # a table style's file for one type pair
            if not Path(entry["file"]).is_absolute():
                entry["file"] = str(base / entry["file"])  # relative to the config
        potentials.append(PluginEntry(kind, values))

    integrator = _parse_integrator(
        _Table(top.take("integrator"), "integrator", source, base, units), seed
    )
    table = _Table(top.take("run", {}), "run", source, base, units)
    run = RunConfig(**table.fields(RunConfig))
    if run.decomposition is not None and min(run.decomposition) < 1:
        raise table.error(
            "decomposition", f"must be positive integers, got {list(run.decomposition)}"
        )
    table.finish()
    table = _Table(top.take("output", {}), "output", source, base, units)
    output = OutputConfig(**table.fields(OutputConfig))
    table.finish()
    barostat = None
    if "barostat" in top.data:
        table = _Table(top.take("barostat"), "barostat", source, base, units)
        barostat = _parse_barostat(table, seed, integrator)
    rigid = None
    if "rigid" in top.data:
        table = _Table(top.take("rigid"), "rigid", source, base, units)
        rigid = _parse_rigid(table, integrator, barostat)
        if "minimize" in top.data:
            raise table.error("bodies", "a [minimize] stage does not keep rigid bodies (yet)")
    minimize = None
    if "minimize" in top.data:
        table = _Table(top.take("minimize"), "minimize", source, base, units)
        minimize = _parse_minimize(table, integrator)
    top.finish()
    return Config(
        source=source,
        text=text,
        units=units,
        seed=seed,
        system=system,
        potentials=tuple(potentials),
        integrator=integrator,
        run=run,
        output=output,
        minimize=minimize,
        barostat=barostat,
        rigid=rigid,
    )


def _type_key(registry: Mapping) -> Key:
    return Key("type", "string", REQUIRED, choices=tuple(registry))


def _read_type(table: _Table, resolve) -> tuple[str, type]:
    """A plug-in section's ``type`` and the class it names (``resolve``: a registry's
    ``potential_class`` or ``integrator_class``; a plug-in's import happens here)."""
    kind = table.read(Key("type", "string", REQUIRED))
    try:
        return kind, resolve(kind)
    except PluginError as error:
        raise table.error("type", str(error)) from None


def _parse_system(table: _Table) -> SystemConfig:
    keys = {k.name: k for k in section_keys(SystemConfig)}
    lattice = table.read(keys["lattice"])
    structure = table.read(keys["structure"])
    polymer = table.read(keys["polymer"])
    if sum(x is not None for x in (lattice, structure, polymer)) != 1:
        raise ConfigError(
            f"{table.source}: [system] needs exactly one of 'lattice', 'structure' and 'polymer'"
        )
    case = "lattice" if lattice is not None else polymer if polymer is not None else "structure"
    values = {"lattice": lattice, "polymer": polymer}
    if structure is not None:
        values["structure"] = Path(structure)
        if not values["structure"].is_file():
            raise table.error("structure", f"file not found: {values['structure']}")
    if case == "structure" and isinstance(table.data.get("mass"), dict):
        values["mass"] = {}  # per type name (chemical symbol); the rest from ASE's table
        for name, value in table.take("mass").items():
            if isinstance(value, bool) or not isinstance(value, int | float) or not value > 0:
                raise table.error("mass", f"{name}: expected a positive number, got {value!r}")
            values["mass"][name] = float(value)
    else:
        values["mass"] = table.read(replace(keys["mass"], kind="number", positive=True))
    for name, k in keys.items():
        if name not in values and k.applies(case):
            values[name] = table.read(k, case)
    cells = values.get("cells")
    if cells is not None:
        if any(c < 1 for c in cells):
            raise table.error("cells", f"must be positive integers, got {list(cells)}")
        if math.prod(cells) > _MAX_CELLS:
            raise table.error("cells", f"{list(cells)} is more than {_MAX_CELLS:,} unit cells")
    if case == "lattice" and (values["density"] is None) == (values["lattice_constant"] is None):
        raise ConfigError(
            f"{table.source}: [system] a lattice needs exactly one of 'density' and "
            "'lattice_constant'"
        )
    table.finish(tuple(keys.values()), case)
    return SystemConfig(**values)


def _parse_integrator(table: _Table, seed: int | None) -> PluginEntry:
    """``[integrator]``: its type's keys; ``kB`` and a derived seed for a thermostat.

    ``temperature`` stays in config units and ``kB`` of the unit system goes
    with it; a stochastic thermostat without its own ``seed`` gets a random
    stream derived from the top-level seed (independent of the velocity draw).
    ``[integrator.constraints]`` is checked here and built later.
    """
    kind, cls = _read_type(table, integrator_class)
    if "constraints" in table.data and not cls.supports_constraints:
        raise ConfigError(f"{table.source}: [integrator] ({kind}) {_refuse_constraints()}")
    every_key = {k.name for c in INTEGRATORS.values() for k in c.CONFIG_KEYS}
    values = table.plugin(kind, cls.CONFIG_KEYS, every_key)
    if "constraints" in values:  # only the keys given, as for the integrator's own
        constraints = _Table(
            values["constraints"], "integrator.constraints", table.source, table.base, table.units
        )
        values["constraints"] = {
            k.name: constraints.read(k)
            for k in BondConstraints.CONFIG_KEYS
            if k.name in constraints.data
        }
        constraints.finish()
    if cls.thermostat:
        values["kB"] = table.units.kB
        if cls.stochastic and "seed" not in values and seed is not None:
            values["seed"] = [seed, 1]
    return PluginEntry(kind, values)


def _refuse_constraints() -> str:
    takers = [n for n, c in INTEGRATORS.items() if c.supports_constraints]
    return f"does not apply constraints; use one of {', '.join(takers)}"


def _parse_barostat(table: _Table, seed: int | None, integrator: PluginEntry) -> PluginEntry:
    """``[barostat]``: its type's keys, every one with its default if not given.

    Pressure is in epsilon/sigma^3 (lj) or bar (metal), tau in config time
    units, compressibility in sigma^3/epsilon or 1/bar; converted to engine units.
    """
    kind = table.read(_type_key(BAROSTAT_KEYS))
    integrator_cls = integrator_class(integrator.type)  # resolved: read before [barostat]
    if not integrator_cls.thermostat:
        raise table.error(
            "type",
            "a barostat needs a thermostat ([integrator] type langevin, bussi, "
            "nose_hoover_chain or berendsen); the integrator given runs at constant energy",
        )
    own = key_names(BAROSTAT_KEYS[kind])
    if kind == "mtk":
        if integrator_cls is not NoseHooverChain:
            raise table.error(
                "type",
                "the mtk barostat runs with its own Nose-Hoover chains: set [integrator] "
                "type = 'nose_hoover_chain' (or use type = 'c_rescale' with any thermostat)",
            )
        if "constraints" in integrator:
            raise table.error(
                "type",
                "the mtk barostat does not keep [integrator.constraints]; use type = 'c_rescale'",
            )
        for name in key_names(BAROSTAT_KEYS["c_rescale"]):
            if name in table.data and name not in own:
                raise table.error(
                    name,
                    "does not apply to the mtk barostat (it moves the "
                    "cell every step, deterministically)",
                )
    every_key = {k.name for keys in BAROSTAT_KEYS.values() for k in keys}
    values = table.plugin(kind, BAROSTAT_KEYS[kind], every_key, fill_defaults=True)
    if "seed" in own and values["seed"] is None and seed is not None:
        values["seed"] = [seed, 2]
    if kind == "berendsen":
        logger.warning(
            "[barostat] type = 'berendsen' relaxes the volume but does not sample the "
            "isothermal-isobaric ensemble: use it to equilibrate, then c_rescale"
        )
    return PluginEntry(kind, values)


def _parse_rigid(table: _Table, integrator: PluginEntry, barostat) -> RigidConfig:
    """``[rigid]``: its keys, refused with what it cannot be combined with (yet)."""
    result = RigidConfig(**table.fields(RigidConfig))
    table.finish()
    try:
        return checked_rigid(result, integrator.type, integrator.values, barostat)
    except ValueError as error:  # (key, message)
        raise table.error(*error.args) from None


def _parse_minimize(table: _Table, integrator: PluginEntry) -> MinimizeConfig:
    """``[minimize]``: FIRE's targets, in the config's units (force and length units are
    the engine's in both unit systems: eV/Angstrom, epsilon/sigma)."""
    if "constraints" in integrator:
        raise table.error("fmax", "a [minimize] stage cannot keep [integrator.constraints]")
    result = MinimizeConfig(**table.fields(MinimizeConfig))
    table.finish()
    return result


def input_files(config: Config) -> list[Path]:
    """The files a config reads: a structure file, and what its ``path`` keys name."""
    files = [] if config.system.structure is None else [Path(config.system.structure)]
    tables = [(p.values, potential_class(p.type).CONFIG_KEYS) for p in config.potentials]
    tables.append((config.integrator.get("constraints") or {}, BondConstraints.CONFIG_KEYS))
    for values, keys in tables:
        files += [
            Path(values[k.name])
            for k in keys
            if k.kind == "path" and isinstance(values.get(k.name), str)
        ]
        files += [Path(entry["file"]) for entry in _pair_files(values)]
    return files


def _pair_files(values: Mapping) -> list[dict]:
    """The ``[[potentials.pairs]]`` tables of a potential's values that name a ``file``
    (a table style's file for one type pair; a path, as the style's own ``file``)."""
    pairs = values.get("pairs")
    if not isinstance(pairs, list):  # none, or not tables: refused with the style's keys
        return []
    return [
        entry for entry in pairs if isinstance(entry, dict) and isinstance(entry.get("file"), str)
    ]


#: Where bonds = "system" finds its bonds.
_SYSTEM_BONDS = "bonds from [system]: a polymer builder, or a structure file that holds bonds"
#: Where angles = "system" finds its angles.
_SYSTEM_ANGLES = (
    "angles from [system]: a polymer builder (consecutive triples along each chain), or a "
    "structure file that holds angles (LAMMPS data Angles, GSD angles, an H5MD file of ours)"
)


def potential_from_config(
    entry: PluginEntry, type_names, source: str, index: int, system_bonds=None
):
    """Build a potential from its config table (type names resolved to indices).

    ``bonds = "system"`` takes the bonds of ``[system]`` (a polymer builder's
    or a structure file's; ``system_bonds``, a Topology or an array), and
    their bond types when the file has several and the table gives none;
    ``angles = "system"`` likewise takes its angles (``system_bonds`` a Topology).
    """
    params = dict(entry.values)
    kind = entry.type
    where = f"{source}: [potentials.{index}] ({kind})"
    topology = system_bonds
    if params.get("bonds") == "system":
        if system_bonds is None or not len(system_bonds):
            raise ConfigError(f'{where}: bonds = "system" needs {_SYSTEM_BONDS}')
        if isinstance(system_bonds, Topology):
            if len(system_bonds.bond_type_names) > 1 and "bond_types" not in params:
                params["bond_types"] = system_bonds.bond_types
            system_bonds = system_bonds.bonds
        params["bonds"] = system_bonds
    if params.get("angles") == "system":
        if not isinstance(topology, Topology) or not topology.n_angles:
            raise ConfigError(f'{where}: angles = "system" needs {_SYSTEM_ANGLES}')
        if len(topology.angle_type_names) > 1 and "angle_types" not in params:
            params["angle_types"] = topology.angle_types
        params["angles"] = topology.angles
    try:
        cls = potential_class(kind)
    except PluginError as error:
        raise ConfigError(f"{source}: [potentials.{index}] type: {error}") from None
    try:
        return cls.from_config(params, tuple(type_names))
    except (ValueError, TypeError) as error:
        raise ConfigError(f"{where}: {error}") from None
    except Exception as error:  # noqa: BLE001 (a plug-in's constructor may raise anything)
        if kind in POTENTIALS:
            raise
        raise ConfigError(f"{where}: building it raised {type(error).__name__}: {error}") from None


def integrator_from_config(entry: PluginEntry, source: str, system_bonds=None):
    """Build the integrator from its config entry (dt already in engine units).

    ``[integrator.constraints]`` becomes :class:`integrators.rattle.BondConstraints`;
    its ``bonds = "system"`` takes ``system_bonds`` (a Topology or an array).
    """
    if isinstance(system_bonds, Topology):
        system_bonds = system_bonds.bonds
    params = dict(entry.values)
    kind = entry.type
    try:
        cls = integrator_class(kind)
    except PluginError as error:
        raise ConfigError(f"{source}: [integrator] type: {error}") from None
    if "constraints" in params:
        if not cls.supports_constraints:
            raise ConfigError(f"{source}: [integrator] ({kind}) {_refuse_constraints()}")
        try:
            constraints = BondConstraints.from_config(params["constraints"], system_bonds)
            params["constraints"] = constraints
        except (ValueError, TypeError) as error:
            raise ConfigError(f"{source}: [integrator.constraints]: {error}") from None
    try:
        return cls(**params)
    except (TypeError, ValueError) as error:
        raise ConfigError(f"{source}: [integrator] ({kind}): {error}") from None
    except Exception as error:  # noqa: BLE001 (a plug-in's constructor may raise anything)
        if kind in INTEGRATORS:
            raise
        raise ConfigError(
            f"{source}: [integrator] ({kind}): building it raised {type(error).__name__}: {error}"
        ) from None


def build_system(config: Config):
    """Return ``(state, topology)``: the initial State and its bonds and angles (or None).

    The bonds are a polymer builder's, or those a structure file holds (LAMMPS
    data, GSD, H5MD), as a :class:`md.topology.Topology`; ``bonds = "system"``
    in a potential or in ``[integrator.constraints]`` takes them. The angles
    are a polymer builder's consecutive triples along each chain, or a
    structure file's; ``angles = "system"`` in an angle potential takes them.
    """
    system = config.system
    where = f"{config.source}: [system]"
    topology = None
    try:
        if system.polymer == "melt":
            state, bonds = polymer_melt(
                system.chains,
                system.chain_length,
                density=system.density,
                bond_length=system.bond_length,
                seed=config.seed,
            )
        elif system.polymer == "chain":
            state, bonds = single_chain(
                system.chain_length,
                bond_length=system.bond_length,
                straight=system.straight,
                seed=config.seed,
                pbc=system.pbc if system.pbc is not None else False,
            )
        if system.polymer is not None:
            chains = system.chains if system.polymer == "melt" else 1
            topology = Topology.from_bonds(bonds)
            if system.chain_length > 2:
                topology = topology.with_angles(chain_angles(chains, system.chain_length))
            state.type_names = (system.type_name,)
            if system.mass is not None:
                state.masses[:] = system.mass
            if system.pbc is not None:
                state.pbc[:] = system.pbc
            state.validate()
        elif system.lattice is not None:
            state = lattice(
                system.lattice,
                system.cells,
                density=system.density,
                lattice_constant=system.lattice_constant,
                mass=system.mass if system.mass is not None else 1.0,
                pbc=system.pbc if system.pbc is not None else True,
                type_name=system.type_name,
                shear=system.shear,
            )
        else:
            try:
                state, topology = read_structure(
                    system.structure, system.format, config.units, mass=system.mass
                )
            except ValueError as error:
                raise ConfigError(f"{where} structure: {error}") from None
            if not (topology.n_bonds or topology.n_angles):
                topology = None
            if isinstance(system.mass, dict):
                unknown = sorted(set(system.mass) - set(state.type_names))
                if unknown:
                    raise ValueError(
                        f"mass given for {', '.join(unknown)}, but the structure's types are "
                        f"{', '.join(state.type_names)}"
                    )
                for index, name in enumerate(state.type_names):
                    if name in system.mass:
                        state.masses[state.types == index] = system.mass[name]
            elif system.mass is not None:
                state.masses[:] = system.mass
            if system.pbc is not None:
                state.pbc[:] = system.pbc
            state.validate()
        rigid = config.rigid
        if rigid is not None and rigid.template is not None:  # a body on every site
            if topology is not None:
                raise ValueError(
                    "[rigid] template: the system has bonds; a template replaces its atoms "
                    "by bodies, so start from a lattice or a structure without bonds"
                )
            seed = None if config.seed is None else [config.seed, 3]  # its own stream
            try:
                state = bodies_on_sites(state, rigid, seed)
            except ValueError as error:
                raise ConfigError(f"{config.source}: [rigid] {error}") from None
        if system.temperature is not None:
            maxwell_boltzmann(state, system.temperature, seed=config.seed, kB=config.units.kB)
    except ConfigError:
        raise  # already names the file and key
    except ValueError as error:
        raise ConfigError(f"{where}: {error}") from None
    if state.n_atoms == 0:
        raise ConfigError(f"{where}: the system has no atoms")
    return state, topology


__all__ = [
    "SYSTEM_KINDS",
    "TOP_KEYS",
    "Config",
    "ConfigError",
    "MinimizeConfig",
    "OutputConfig",
    "PluginEntry",
    "RigidConfig",
    "RunConfig",
    "Section",
    "SystemConfig",
    "build_system",
    "input_files",
    "integrator_from_config",
    "load_config",
    "parse_config",
    "potential_from_config",
    "sections",
]
