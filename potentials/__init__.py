"""Interaction potentials: each one class fitting :class:`potentials.base.Potential`.

``POTENTIALS`` maps the names used in configs to the classes. Pair potentials
share one pair-kernel frame (:class:`PairPotential`); a user's own pair term
(:func:`pair_term`) gets the same lists, threads, virials and Hessians, and
:func:`check_term` compares its derivatives with finite differences (a bonded
term's too). Bonds and angles share the bonded frame likewise: a user's bond term
(:func:`bond_term`, with :class:`BondPotential`) or angle term (:func:`angle_term`,
:class:`AnglePotential`) gets the loops, per-type parameters, virials and Hessians
of the built-in styles.
"""

from md._kernel_cache import kernel_cache

# Kernel modules are imported here so numba caches them per user (md._kernel_cache).
with kernel_cache():
    from potentials._bonded_frame import (
        AnglePotential,
        AngleTerm,
        BondPotential,
        BondTerm,
        angle_term,
        bond_term,
    )
    from potentials._pair_frame import PairPotential
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
    "angle_term",
    "bond_term",
    "check_term",
    "pair_term",
]
