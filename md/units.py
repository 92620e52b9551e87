"""Unit systems at the edges of the engine.

The engine itself is unit-agnostic: it works in any consistent set of units in
which time is ``length * sqrt(mass / energy)``. Two named systems are offered
where numbers enter and leave (configs, the CLI, trajectory files):

``lj``
    Reduced Lennard-Jones units: sigma = epsilon = m = kB = 1. Time is in tau.
``metal``
    ASE's units: eV, Angstrom, amu, and the derived time unit
    Angstrom * sqrt(amu / eV) (about 10.18 fs). Temperatures are in kelvin;
    configs give times (``dt``) in fs, converted here.

The physical constants are CODATA 2014, the set ASE uses by default, so that
``fs``, ``ps`` and ``kB`` equal ``ase.units.fs``, ``ase.units.fs * 1000`` and
``ase.units.kB`` (a test checks this).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

# CODATA 2014 (as in ase.units, default version).
_e = 1.6021766208e-19  # elementary charge [C]
_amu = 1.660539040e-27  # atomic mass unit [kg]
_k = 1.38064852e-23  # Boltzmann constant [J/K]
_Nav = 6.022140857e23  # Avogadro constant [1/mol]

#: One second in the metal time unit Angstrom * sqrt(amu / eV).
second = 1e10 * math.sqrt(_e / _amu)
#: One femtosecond in the metal time unit.
fs = 1e-15 * second
#: One picosecond in the metal time unit.
ps = 1e-12 * second
#: Boltzmann constant [eV/K].
kB = _k / _e
#: eV/Angstrom expressed in kJ mol-1 Angstrom-1.
eV_per_A_in_kJ_per_mol_A = _e * _Nav / 1000.0
#: 1 eV/Angstrom^3 in bar.
eV_per_A3_in_bar = _e * 1e30 / 1e5


@dataclass(frozen=True)
class UnitSystem:
    """A named unit system used at the edges (configs, CLI, files).

    Attributes
    ----------
    name : str
        ``"lj"`` or ``"metal"``.
    kB : float
        Boltzmann constant [energy/temperature].
    config_time : float
        One config time unit (``dt`` in a config) in engine time units.
    config_time_label : str
        Name of the config time unit, for messages and tables.
    labels : dict
        Unit labels of quantities for printed tables.
    h5md : dict
        For trajectory files: quantity -> (H5MD unit string, factor from
        engine units to file units). Empty for reduced units, which carry no
        unit attributes.
    config_units : dict
        For configs: quantity -> (unit as a config gives it, factor, power);
        a config value ``x`` is ``x * factor`` (power 1) or ``x / factor``
        (power -1) in engine units. The quantities are those config keys
        declare (``md.schema.Key.unit``); the config reference shows the labels.
    """

    name: str
    kB: float
    config_time: float
    config_time_label: str
    labels: dict[str, str] = field(default_factory=dict)
    h5md: dict[str, tuple[str, float]] = field(default_factory=dict)
    config_units: dict[str, tuple[str, float, int]] = field(default_factory=dict)

    def from_config(self, quantity: str, value: float) -> float:
        """``value`` of ``quantity``, as a config gives it, in engine units.

        Examples
        --------
        >>> round(METAL.from_config("time", 1.0) / fs, 12)  # 1 fs
        1.0
        """
        _, factor, power = self.config_units[quantity]
        return value * factor if power == 1 else value / factor


def _config_units(
    time: str, time_unit: float, pressure: tuple[str, str], to_engine: float, labels: dict[str, str]
) -> dict[str, tuple[str, float, int]]:
    """Config units of one system: times and pressures (and their inverses) converted,
    the rest as they are. ``pressure`` holds the labels of pressure and its inverse."""
    return {
        "time": (time, time_unit, 1),
        "1/time": (f"1/{time}", time_unit, -1),
        "pressure": (pressure[0], to_engine, 1),
        "1/pressure": (pressure[1], to_engine, -1),
        **{quantity: (label, 1.0, 1) for quantity, label in labels.items()},
    }


#: Quantities that have the same unit in every system.
_PLAIN_UNITS = {"degrees": "degrees", "steps": "steps"}

LJ = UnitSystem(
    name="lj",
    kB=1.0,
    config_time=1.0,
    config_time_label="tau",
    labels={
        "energy": "eps",
        "temperature": "eps/kB",
        "pressure": "eps/sigma^3",
        "time": "tau",
        "length": "sigma",
        "volume": "sigma^3",
        "density": "m/sigma^3",
    },
    config_units=_config_units(
        "τ",
        1.0,
        ("ε/σ³", "σ³/ε"),
        1.0,
        {
            "length": "σ",
            "energy": "ε",
            "temperature": "ε/kB",
            "mass": "m",
            "number density": "1/σ³",
            "force": "ε/σ",
            "energy/length^2": "ε/σ²",
            "length^2/energy": "σ²/ε",
            "energy/radian^2": "ε/rad²",
            "1/length": "1/σ",
            "energy*length": "ε σ",
            "energy*length^6": "ε σ⁶",
            **_PLAIN_UNITS,
        },
    ),
)

METAL = UnitSystem(
    name="metal",
    kB=kB,
    config_time=fs,
    config_time_label="fs",
    labels={
        "energy": "eV",
        "temperature": "K",
        "pressure": "eV/A^3",
        "time": "ps",
        "length": "A",
        "volume": "A^3",
        "density": "amu/A^3",
    },
    h5md={
        "length": ("Angstrom", 1.0),
        "time": ("ps", 1.0 / ps),
        "velocity": ("Angstrom ps-1", ps),
        "force": ("kJ mol-1 Angstrom-1", eV_per_A_in_kJ_per_mol_A),
        "mass": ("amu", 1.0),
        "energy": ("eV", 1.0),
        "temperature": ("K", 1.0),
        "pressure": ("eV Angstrom-3", 1.0),
        "volume": ("Angstrom3", 1.0),
        "density": ("amu Angstrom-3", 1.0),
    },
    config_units=_config_units(
        "fs",
        fs,
        ("bar", "1/bar"),
        1.0 / eV_per_A3_in_bar,
        {
            "length": "Å",
            "energy": "eV",
            "temperature": "K",
            "mass": "amu",
            "number density": "1/Å³",
            "force": "eV/Å",
            "energy/length^2": "eV/Å²",
            "length^2/energy": "Å²/eV",
            "energy/radian^2": "eV/rad²",
            "1/length": "1/Å",
            "energy*length": "eV Å",
            "energy*length^6": "eV Å⁶",
            **_PLAIN_UNITS,
        },
    ),
)

UNIT_SYSTEMS: dict[str, UnitSystem] = {"lj": LJ, "metal": METAL}


def get_units(units: str | UnitSystem) -> UnitSystem:
    """Return the unit system named ``units`` (or ``units`` itself)."""
    if isinstance(units, UnitSystem):
        return units
    try:
        return UNIT_SYSTEMS[units]
    except KeyError:
        known = ", ".join(sorted(UNIT_SYSTEMS))
        raise ValueError(f"unknown unit system {units!r} (known: {known})") from None
