"""Interaction potentials: each one class fitting :class:`potentials.base.Potential`.

``POTENTIALS`` maps the names used in configs to the classes. Pair potentials
share one pair-kernel frame (:class:`PairPotential`); a user's own pair term
(:func:`pair_term`) gets the same lists, threads, virials and Hessians, and
:func:`check_term` compares its derivatives with finite differences (a bonded
term's too). Bonds and angles share the bonded frame likewise: a user's bond term
(:func:`bond_term`, with :class:`BondPotential`) or angle term (:func:`angle_term`,
:class:`AnglePotential`) gets the loops, per-type parameters, virials and Hessians
of the built-in styles.

:func:`potential_class` resolves a config's ``type``: a name in ``POTENTIALS``, a
plug-in registered under the entry-point group ``leapmd.potentials``, or a
``module:attribute`` path (:mod:`md.plugins`). A plug-in style is written as the
built-in ones are, from the public names here: a :class:`PairPotential`,
:class:`BondPotential` or :class:`AnglePotential` subclass whose constructor passes
its term and values to the frame; without ``CONFIG_KEYS`` its keys follow from its
constructor (see those classes' ``__init_subclass__``), with them they are made by
:func:`pair_config_keys`, :func:`bond_config_keys` or :func:`angle_config_keys`.
"""

from md import plugins
from md._kernel_cache import kernel_cache
from md.schema import Key, key_names

# Kernel modules are imported here so numba caches them per user (md._kernel_cache).
with kernel_cache():
    from potentials._bonded_frame import (
        AnglePotential,
        AngleTerm,
        BondPotential,
        BondTerm,
        angle_config_keys,
        angle_term,
        bond_config_keys,
        bond_term,
    )
    from potentials._pair_frame import PairPotential, pair_config_keys
    from potentials.angles import AngleCollapseError, CosineAngles, HarmonicAngles
    from potentials.base import ForceResult, Potential, SupportsHessian
    from potentials.lennard_jones import LennardJones
    from potentials.pair_styles import Buckingham, Mie, Morse, Soft, Yukawa
    from potentials.pair_terms import PairTerm, pair_term
    from potentials.springs import BondStretchError, FENEBonds, HarmonicBonds
    from potentials.table import Table
    from potentials.term_check import TermCheck, check_term

POTENTIALS = {
    "lj": LennardJones,
    "morse": Morse,
    "mie": Mie,
    "buckingham": Buckingham,
    "yukawa": Yukawa,
    "soft": Soft,
    "table": Table,
    "spring": HarmonicBonds,
    "fene": FENEBonds,
    "angle_harmonic": HarmonicAngles,
    "angle_cosine": CosineAngles,
}

#: What a potential plug-in that is no frame's subclass must have (the Potential protocol
#: and what the config builds it with).
_MEMBERS = ("CONFIG_KEYS", "from_config", "energy_forces", "describe", "check")
_KIND = (
    "a potential class: a PairPotential, BondPotential or AnglePotential subclass (see "
    "docs/guide/plugins.md), or a class with CONFIG_KEYS, from_config, energy_forces, "
    "describe and check"
)


def potential_class(name: str) -> type:
    """The potential class a config's ``type = name`` names: a built-in style
    (``POTENTIALS``, which win over plug-ins of the same name), a plug-in under the
    entry-point group ``leapmd.potentials``, or ``module:attribute``.

    Raises :class:`md.errors.PluginError` naming the plug-in when it is missing, its import
    raises, it is not a potential class, or its constructor does not take its config keys.
    """
    return plugins.load(name, "potentials", POTENTIALS, _potential_problem)


def _potential_problem(found) -> str | None:
    """What keeps ``found`` from serving as a config's potential (None: nothing)."""
    if not isinstance(found, type):
        return f"is {type(found).__name__} {found!r}, not {_KIND}"
    frame = next(
        (c for c in (PairPotential, BondPotential, AnglePotential) if issubclass(found, c)), None
    )
    missing = [m for m in _MEMBERS if not hasattr(found, m)]  # a foreign class's protocol
    if frame is None and missing:
        return f"{found.__name__} is not {_KIND} (it lacks {', '.join(missing)})"
    keys = found.CONFIG_KEYS
    if not isinstance(keys, tuple) or not all(isinstance(k, Key) for k in keys):
        return f"CONFIG_KEYS must be a tuple of md.schema.Key, got {keys!r}"
    if frame is None:
        return None  # its own from_config reads its keys
    # a from_config of its own (not the frame's) reads its keys itself
    if getattr(found.from_config, "__func__", None) is not frame.from_config.__func__:
        return None
    names = key_names(keys)
    if frame is not PairPotential:  # the frame reads <item>s_file into <item>s
        names = tuple(n for n in names if n != f"{frame.ITEM}s_file")
    return plugins.signature_problem(found, names)


__all__ = [
    "POTENTIALS",
    "AngleCollapseError",
    "AnglePotential",
    "AngleTerm",
    "BondPotential",
    "BondTerm",
    "BondStretchError",
    "Buckingham",
    "CosineAngles",
    "FENEBonds",
    "ForceResult",
    "HarmonicAngles",
    "HarmonicBonds",
    "LennardJones",
    "Mie",
    "Morse",
    "PairPotential",
    "PairTerm",
    "Potential",
    "Soft",
    "SupportsHessian",
    "Table",
    "TermCheck",
    "Yukawa",
    "angle_config_keys",
    "angle_term",
    "bond_config_keys",
    "bond_term",
    "check_term",
    "pair_config_keys",
    "pair_term",
    "potential_class",
]
