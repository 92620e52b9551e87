"""Interaction potentials: each one class fitting :class:`potentials.base.Potential`.

``POTENTIALS`` maps the names used in configs to the classes. Pair potentials
share one pair-kernel frame (:class:`PairPotential`); a user's own pair term
(:func:`pair_term`) gets the same lists, threads, virials and Hessians.
"""

from md._kernel_cache import kernel_cache

# Kernel modules are imported here so numba caches them per user (md._kernel_cache).
with kernel_cache():
    from potentials._pair_frame import PairPotential, PairTerm, pair_term
    from potentials.angles import AngleCollapseError, CosineAngles, HarmonicAngles
    from potentials.base import ForceResult, Potential, SupportsHessian
    from potentials.lennard_jones import LennardJones
    from potentials.pair_styles import Buckingham, Mie, Morse, Soft, Yukawa
    from potentials.springs import BondStretchError, FENEBonds, HarmonicBonds
    from potentials.table import Table

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
    "Yukawa",
    "pair_term",
]
