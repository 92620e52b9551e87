"""Interaction potentials: each one class fitting :class:`potentials.base.Potential`.

``POTENTIALS`` maps the names used in configs to the classes.
"""

from md._kernel_cache import kernel_cache

# Kernel modules are imported here so numba caches them per user (md._kernel_cache).
with kernel_cache():
    from potentials.angles import AngleCollapseError, CosineAngles, HarmonicAngles
    from potentials.base import ForceResult, Potential, SupportsHessian
    from potentials.lennard_jones import LennardJones
    from potentials.springs import BondStretchError, FENEBonds, HarmonicBonds

POTENTIALS = {
    "lj": LennardJones,
    "spring": HarmonicBonds,
    "fene": FENEBonds,
    "angle_harmonic": HarmonicAngles,
    "angle_cosine": CosineAngles,
}

__all__ = [
    "POTENTIALS",
    "AngleCollapseError",
    "BondStretchError",
    "CosineAngles",
    "FENEBonds",
    "ForceResult",
    "HarmonicAngles",
    "HarmonicBonds",
    "LennardJones",
    "Potential",
    "SupportsHessian",
]
