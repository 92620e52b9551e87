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
    """

    name: str
    kB: float
    config_time: float
    config_time_label: str
    labels: dict[str, str] = field(default_factory=dict)
    h5md: dict[str, tuple[str, float]] = field(default_factory=dict)


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
    },  # fmt: skip
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
