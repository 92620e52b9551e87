"""Run configuration: TOML read into small dataclasses, validated before anything runs.

Every problem is reported as a :class:`ConfigError` naming the file, the key
and the offending value. Names resolve through ``POTENTIALS`` and
``INTEGRATORS``; physical quantities are converted from the config's unit
system (``lj`` or ``metal``, where times are in fs) into engine units here.
"""

from __future__ import annotations

import inspect
import logging
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from integrators import INTEGRATORS, NoseHooverChain
from integrators.barostats import BAROSTATS, COUPLINGS
from integrators.rattle import BondConstraints
from md._checks import MAX_COUNT, MAX_SEED
from md.build import lattice, maxwell_boltzmann
from md.errors import ConfigError
from md.polymers import chain_angles, polymer_melt, single_chain
from md.structure import read_structure
from md.topology import Topology
from md.units import UNIT_SYSTEMS, UnitSystem, eV_per_A3_in_bar
from potentials import POTENTIALS

_MISSING = object()
#: Largest lattice accepted (4 x 10^7 fcc atoms), so a typo cannot exhaust memory.
_MAX_CELLS = 10_000_000
logger = logging.getLogger(__name__)


class _Table:
    """A TOML table being consumed key by key; leftovers are unknown keys."""

    def __init__(self, data: Any, where: str, source: str) -> None:
        if not isinstance(data, dict):
            raise ConfigError(f"{source}: [{where}] must be a table, got {type(data).__name__}")
        self.data = dict(data)
        self.where = where
        self.source = source

    def error(self, key: str, message: str) -> ConfigError:
        return ConfigError(f"{self.source}: {self._name(key)}: {message}")

    def _name(self, key: str) -> str:
        return f"[{self.where}] {key}" if self.where else key

    def take(self, key: str, default: Any = _MISSING) -> Any:
        if key not in self.data:
            if default is _MISSING:
                raise ConfigError(f"{self.source}: missing required key {self._name(key)}")
            return default
        return self.data.pop(key)

    def number(self, key, default=_MISSING, positive=False, minimum=None) -> float:
        value = self.take(key, default)
        if value is None:
            return None
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.error(key, f"expected a number, got {value!r}")
        if not math.isfinite(value):
            raise self.error(key, f"must be finite, got {value!r}")
        if positive and not value > 0:
            raise self.error(key, f"must be positive, got {value!r}")
        if minimum is not None and value < minimum:
            raise self.error(key, f"must be >= {minimum}, got {value!r}")
        return float(value)

    def integer(self, key, default=_MISSING, minimum=None, maximum=MAX_COUNT) -> int:
        value = self.take(key, default)
        if value is None:
            return None
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.error(key, f"expected an integer, got {value!r}")
        if minimum is not None and value < minimum:
            raise self.error(key, f"must be >= {minimum}, got {value!r}")
        if value > maximum:
            raise self.error(key, f"must be at most {maximum}, got {value!r}")
        return int(value)

    def string(self, key, default=_MISSING, choices=None) -> str:
        value = self.take(key, default)
        if value is None:
            return None
        if not isinstance(value, str):
            raise self.error(key, f"expected a string, got {value!r}")
        if choices is not None and value not in choices:
            raise self.error(key, f"must be one of {', '.join(map(repr, choices))}, got {value!r}")
        return value

    def boolean(self, key, default=_MISSING) -> bool:
        value = self.take(key, default)
        if not isinstance(value, bool):
            raise self.error(key, f"expected true or false, got {value!r}")
        return value

    def triple(self, key, default, kind) -> tuple:
        """A value given once for all axes or as a list of three."""
        value = self.take(key, default)
        values = value if isinstance(value, list) else [value] * 3
        if len(values) != 3 or not all(_is_kind(v, kind) for v in values):
            raise self.error(key, f"expected {kind.__name__} or a list of three, got {value!r}")
        return tuple(values)

    def finish(self) -> None:
        if self.data:
            unknown = ", ".join(sorted(self.data))
            raise ConfigError(f"{self.source}: unknown key(s) in {self._where()}: {unknown}")

    def _where(self) -> str:
        return f"[{self.where}]" if self.where else "the top level"


def _is_kind(value, kind) -> bool:
    if kind is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if kind is float:
        return isinstance(value, int | float) and not isinstance(value, bool)
    return isinstance(value, kind)


@dataclass
class SystemConfig:
    """What to simulate: a lattice or a structure file, and initial velocities."""

    lattice: str | None = None
    polymer: str | None = None
    chains: int = 1
    chain_length: int = 2
    bond_length: float = 0.97
    straight: bool = False
    cells: tuple[int, int, int] = (1, 1, 1)
    density: float | None = None
    lattice_constant: float | None = None
    shear: tuple[float, float, float] | None = None  # HOOMD-style tilt factors of a lattice
    structure: Path | None = None
    format: str | None = None  # ase.io format of a structure file (None: guessed from the name)
    mass: float | dict[str, float] | None = None  # a number, or per type name for structures
    type_name: str = "A"
    pbc: tuple[bool, bool, bool] | None = None
    temperature: float | None = None


@dataclass
class RunConfig:
    steps: int = 1000
    skin: float = 0.3
    thermo_every: int = 100
    threads: int | None = None  # kernel threads (None: every core); not physics


@dataclass
class OutputConfig:
    path: Path = Path("trajectory.h5")
    every: int = 100
    velocities: bool = False
    forces: bool = False
    checkpoint_every: int = 1000  # steps between checkpoints (0: only at the end and on signals)


@dataclass
class MinimizeConfig:
    """``[minimize]``: FIRE 2.0 before the dynamics (see :mod:`md.minimize`).

    ``fmax`` [energy/length] and ``max_force`` (the push-off's force cap,
    None: no cap) in engine units; ``max_step`` [length].
    """

    fmax: float = 1e-2
    max_steps: int = 10_000
    max_force: float | None = None
    max_step: float = 0.1
    report_every: int = 100


@dataclass
class Config:
    """A validated run configuration (engine units, objects not yet built)."""

    source: str
    text: str
    units: UnitSystem
    seed: int | None
    system: SystemConfig
    potentials: list[dict]
    integrator: dict
    run: RunConfig
    output: OutputConfig
    minimize: MinimizeConfig | None = None
    barostat: dict | None = None  # Barostat keyword arguments in engine units


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
    top = _Table(data, "", source)
    units_name = top.string("units", None, choices=tuple(UNIT_SYSTEMS))
    seed = top.integer("seed", None, minimum=0, maximum=MAX_SEED)
    system = _parse_system(_Table(top.take("system"), "system", source), Path(base))
    # Structure files come from ASE's world (eV, Angstrom, amu): metal units unless told.
    units = UNIT_SYSTEMS[units_name or ("metal" if system.structure is not None else "lj")]

    raw_potentials = top.take("potentials")
    base = Path(base)
    if not isinstance(raw_potentials, list) or not raw_potentials:
        raise ConfigError(
            f"{source}: potentials must be a non-empty array of tables ([[potentials]])"
        )
    potentials = []
    for index, entry in enumerate(raw_potentials):
        table = _Table(entry, f"potentials.{index}", source)
        kind = table.string("type", choices=tuple(POTENTIALS))
        for key in ("bonds_file", "angles_file"):
            listed = table.data.get(key)
            if isinstance(listed, str) and not Path(listed).is_absolute():
                table.data[key] = str(base / listed)  # relative to the config
        potentials.append({"type": kind, **table.data})

    table = _Table(top.take("integrator"), "integrator", source)
    kind = table.string("type", choices=tuple(INTEGRATORS))
    dt = table.number("dt", positive=True) * units.config_time
    # Other times an integrator takes (RKF45's smallest substep) are converted too.
    dt_min = table.number("dt_min", None, positive=True)
    extra = _thermostat_params(table, INTEGRATORS[kind], units, seed, base)
    integrator = {"type": kind, "dt": dt, **table.data, **extra}
    if dt_min is not None:
        integrator["dt_min"] = dt_min * units.config_time

    table = _Table(top.take("run", {}), "run", source)
    run = RunConfig(
        steps=table.integer("steps", RunConfig.steps, minimum=0),
        skin=table.number("skin", RunConfig.skin, minimum=0.0),
        thermo_every=table.integer("thermo_every", RunConfig.thermo_every, minimum=1),
        threads=table.integer("threads", None, minimum=1),
    )
    table.finish()

    table = _Table(top.take("output", {}), "output", source)
    output = OutputConfig(
        path=Path(table.string("path", str(OutputConfig.path))),
        every=table.integer("every", OutputConfig.every, minimum=1),
        velocities=table.boolean("velocities", False),
        forces=table.boolean("forces", False),
        checkpoint_every=table.integer(
            "checkpoint_every", OutputConfig.checkpoint_every, minimum=0
        ),
    )
    table.finish()
    barostat = None
    if "barostat" in top.data:
        barostat = _parse_barostat(
            _Table(top.take("barostat"), "barostat", source),
            units,
            seed,
            INTEGRATORS[kind],
            "constraints" in integrator,
        )
    minimize = None
    if "minimize" in top.data:
        minimize = _parse_minimize(_Table(top.take("minimize"), "minimize", source), integrator)
    top.finish()
    return Config(
        source=source,
        text=text,
        units=units,
        seed=seed,
        system=system,
        potentials=potentials,
        integrator=integrator,
        run=run,
        output=output,
        minimize=minimize,
        barostat=barostat,
    )


def _parse_system(table: _Table, base: Path) -> SystemConfig:
    lattice = table.string("lattice", None, choices=("sc", "bcc", "fcc"))
    structure = table.string("structure", None)
    polymer = table.string("polymer", None, choices=("melt", "chain"))
    if sum(x is not None for x in (lattice, structure, polymer)) != 1:
        raise ConfigError(
            f"{table.source}: [system] needs exactly one of 'lattice', 'structure' and 'polymer'"
        )
    system = SystemConfig(lattice=lattice, polymer=polymer)
    if polymer is not None:
        system.chain_length = table.integer("chain_length", minimum=2)
        system.bond_length = table.number("bond_length", 0.97, positive=True)
        if polymer == "melt":
            system.chains = table.integer("chains", minimum=1)
            system.density = table.number("density", positive=True)
        else:
            system.straight = table.boolean("straight", False)
        system.type_name = table.string("type_name", "M")
    elif lattice is not None:
        cells = table.triple("cells", _MISSING, int)
        if any(c < 1 for c in cells):
            raise table.error("cells", f"must be positive integers, got {list(cells)}")
        if math.prod(cells) > _MAX_CELLS:
            raise table.error("cells", f"{list(cells)} is more than {_MAX_CELLS:,} unit cells")
        system.cells = cells
        system.density = table.number("density", None, positive=True)
        system.lattice_constant = table.number("lattice_constant", None, positive=True)
        if (system.density is None) == (system.lattice_constant is None):
            raise ConfigError(
                f"{table.source}: [system] a lattice needs exactly one of 'density' and "
                "'lattice_constant'"
            )
        system.type_name = table.string("type_name", "A")
        if "shear" in table.data:
            system.shear = table.triple("shear", _MISSING, float)
    else:
        system.structure = (
            (base / structure) if not Path(structure).is_absolute() else Path(structure)
        )
        if not system.structure.is_file():
            raise table.error("structure", f"file not found: {system.structure}")
        system.format = table.string("format", None)
    if structure is not None and isinstance(table.data.get("mass"), dict):
        system.mass = {}  # per type name (chemical symbol); the rest from ASE's table
        for name, value in table.take("mass").items():
            if isinstance(value, bool) or not isinstance(value, int | float) or not value > 0:
                raise table.error("mass", f"{name}: expected a positive number, got {value!r}")
            system.mass[name] = float(value)
    else:
        system.mass = table.number("mass", None, positive=True)
    pbc = table.take("pbc", None)
    if pbc is not None:
        table.data["pbc"] = pbc
        system.pbc = table.triple("pbc", _MISSING, bool)
    system.temperature = table.number("temperature", None, minimum=0.0)
    table.finish()
    return system


#: Where bonds = "system" finds its bonds.
_SYSTEM_BONDS = "bonds from [system]: a polymer builder, or a structure file that holds bonds"
#: Where angles = "system" finds its angles.
_SYSTEM_ANGLES = (
    "angles from [system]: a polymer builder (consecutive triples along each chain), or a "
    "structure file that holds angles (LAMMPS data Angles, GSD angles, an H5MD file of ours)"
)


def potential_from_config(entry: dict, type_names, source: str, index: int, system_bonds=None):
    """Build a potential from its config table (type names resolved to indices).

    ``bonds = "system"`` takes the bonds of ``[system]`` (a polymer builder's
    or a structure file's; ``system_bonds``, a Topology or an array), and
    their bond types when the file has several and the table gives none;
    ``angles = "system"`` likewise takes its angles (``system_bonds`` a Topology).
    """
    params = dict(entry)
    kind = params.pop("type")
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
        return POTENTIALS[kind].from_config(params, tuple(type_names))
    except (ValueError, TypeError) as error:
        raise ConfigError(f"{where}: {error}") from None


#: Default compressibility of the barostat's coupling, per unit system [config units]:
#: an LJ liquid's order of magnitude (sigma^3/epsilon), and GROMACS's default (1/bar).
_COMPRESSIBILITY = {"lj": 0.1, "metal": 4.5e-5}


def _parse_barostat(table: _Table, units: UnitSystem, seed, integrator_cls,
                    constrained: bool) -> dict:  # fmt: skip
    """``[barostat]``: type, pressure, tau, couple, compressibility, every, seed.

    Pressure is in epsilon/sigma^3 (lj) or bar (metal), tau in config time
    units, compressibility in sigma^3/epsilon or 1/bar; converted to engine units.
    """
    kind = table.string("type", choices=tuple(BAROSTATS))
    if not integrator_cls.thermostat:
        raise table.error(
            "type",
            "a barostat needs a thermostat ([integrator] type langevin, bussi, "
            "nose_hoover_chain or berendsen); the integrator given runs at constant energy",
        )
    to_engine = 1.0 / eV_per_A3_in_bar if units.name == "metal" else 1.0  # bar -> eV/A^3
    pressure = table.number("pressure") * to_engine
    tau = table.number("tau", positive=True) * units.config_time
    couple = table.string("couple", "isotropic", choices=COUPLINGS)
    if kind == "mtk":
        if integrator_cls is not NoseHooverChain:
            raise table.error(
                "type",
                "the mtk barostat runs with its own Nose-Hoover chains: set [integrator] "
                "type = 'nose_hoover_chain' (or use type = 'c_rescale' with any thermostat)",
            )
        if constrained:
            raise table.error("type", "the mtk barostat does not keep [integrator.constraints]; "
                              "use type = 'c_rescale'")  # fmt: skip
        for key in ("compressibility", "every", "seed"):
            if key in table.data:
                raise table.error(key, "does not apply to the mtk barostat (it moves the "
                                  "cell every step, deterministically)")  # fmt: skip
        table.finish()
        return {"kind": kind, "pressure": pressure, "tau": tau, "couple": couple}
    compressibility = (
        table.number("compressibility", _COMPRESSIBILITY[units.name], positive=True) / to_engine
    )
    every = table.integer("every", 10, minimum=1)
    own_seed = table.integer("seed", None, minimum=0, maximum=MAX_SEED)
    table.finish()
    if kind == "berendsen":
        logger.warning(
            "[barostat] type = 'berendsen' relaxes the volume but does not sample the "
            "isothermal-isobaric ensemble: use it to equilibrate, then c_rescale"
        )
    return {
        "kind": kind, "pressure": pressure, "tau": tau, "compressibility": compressibility,
        "couple": couple, "every": every,
        "seed": own_seed if own_seed is not None else (None if seed is None else [seed, 2]),
    }  # fmt: skip


def _parse_minimize(table: _Table, integrator: dict) -> MinimizeConfig:
    """``[minimize]``: FIRE's targets, in the config's units (force and length units are
    the engine's in both unit systems: eV/Angstrom, epsilon/sigma)."""
    if "constraints" in integrator:
        raise table.error("fmax", "a [minimize] stage cannot keep [integrator.constraints]")
    defaults = MinimizeConfig()
    result = MinimizeConfig(
        fmax=table.number("fmax", defaults.fmax, positive=True),
        max_steps=table.integer("max_steps", defaults.max_steps, minimum=1),
        max_force=table.number("max_force", None, positive=True),
        max_step=table.number("max_step", defaults.max_step, positive=True),
        report_every=table.integer("report_every", defaults.report_every, minimum=1),
    )
    table.finish()
    return result


def _thermostat_params(table: _Table, cls, units: UnitSystem, seed, base: Path) -> dict:
    """Take a thermostat's keys from [integrator], converted to engine units.

    ``temperature`` stays in config units and ``kB`` of the unit system goes
    with it; ``tau`` [config time] and ``friction`` [1/config time] are
    converted; a stochastic thermostat without its own ``seed`` gets a random
    stream derived from the top-level seed (independent of the velocity draw).
    ``[integrator.constraints]`` is checked to be a table (built later).
    """
    extra = {}
    if cls.thermostat:
        extra["temperature"] = table.number("temperature", minimum=0.0)
        extra["kB"] = units.kB
        tau = table.number("tau", None, positive=True)
        if tau is not None:
            extra["tau"] = tau * units.config_time
        friction = table.number("friction", None, minimum=0.0)
        if friction is not None:
            extra["friction"] = friction / units.config_time
        if cls.stochastic and "seed" not in table.data and seed is not None:
            extra["seed"] = [seed, 1]
    constraints = table.take("constraints", None)
    if constraints is not None:
        if not isinstance(constraints, dict):
            raise table.error("constraints", "expected a table [integrator.constraints]")
        constraints = dict(constraints)
        bonds_file = constraints.get("bonds_file")
        if isinstance(bonds_file, str) and not Path(bonds_file).is_absolute():
            constraints["bonds_file"] = str(Path(base) / bonds_file)  # relative to the config
        extra["constraints"] = constraints
    return extra


def integrator_from_config(entry: dict, source: str, system_bonds=None):
    """Build the integrator from its config table (dt already in engine units).

    ``[integrator.constraints]`` becomes :class:`integrators.rattle.BondConstraints`;
    its ``bonds = "system"`` takes ``system_bonds`` (a Topology or an array).
    """
    if isinstance(system_bonds, Topology):
        system_bonds = system_bonds.bonds
    params = dict(entry)
    kind = params.pop("type")
    if "constraints" in params:
        if not INTEGRATORS[kind].supports_constraints:
            takers = [n for n, c in INTEGRATORS.items() if c.supports_constraints]
            raise ConfigError(
                f"{source}: [integrator] ({kind}) does not apply constraints; use one of "
                f"{', '.join(takers)}"
            )
        try:
            constraints = BondConstraints.from_config(params["constraints"], system_bonds)
            params["constraints"] = constraints
        except (ValueError, TypeError) as error:
            raise ConfigError(f"{source}: [integrator.constraints]: {error}") from None
    _check_keys(INTEGRATORS[kind], params, source, "integrator", kind)
    try:
        return INTEGRATORS[kind](**params)
    except TypeError as error:
        raise ConfigError(f"{source}: [integrator] ({kind}): {error}") from None
    except ValueError as error:
        raise ConfigError(f"{source}: [integrator] ({kind}): {error}") from None


def _check_keys(cls, params: dict, source: str, table: str, kind: str) -> None:
    """ConfigError naming a required key of ``cls`` missing from ``params`` (the keys of
    ``[table]`` with ``type = kind``), or a key it does not take, instead of Python's own
    "__init__() missing 1 required positional argument"."""
    try:
        signature = inspect.signature(cls)
    except (TypeError, ValueError):  # no signature to read: the call reports
        return
    parameters = signature.parameters.values()
    named = {p.name: p for p in parameters if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)}
    if not any(p.kind == p.VAR_KEYWORD for p in parameters):
        extra = sorted(set(params) - set(named))
        if extra:  # first: a key of another type (friction for bussi) explains a missing one
            raise ConfigError(
                f"{source}: [{table}] {', '.join(extra)}: does not apply to type = {kind!r}, "
                f"which takes {', '.join(name for name in named if name != 'kB')}"
            )
    missing = [name for name, p in named.items() if p.default is p.empty and name not in params]
    if missing:
        keys = " ".join(f"[{table}] {name}" for name in missing)
        raise ConfigError(f"{source}: missing required key {keys} (type = {kind!r} needs it)")


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
                system.chains, system.chain_length, density=system.density,
                bond_length=system.bond_length, seed=config.seed,
            )  # fmt: skip
        elif system.polymer == "chain":
            state, bonds = single_chain(
                system.chain_length, bond_length=system.bond_length,
                straight=system.straight, seed=config.seed,
                pbc=system.pbc if system.pbc is not None else False,
            )  # fmt: skip
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
    "Config",
    "ConfigError",
    "build_system",
    "integrator_from_config",
    "load_config",
    "parse_config",
    "potential_from_config",
]
