"""Interaction potentials: each one class fitting :class:`potentials.base.Potential`.

``POTENTIALS`` maps the names used in configs to the classes.
"""

from potentials.base import ForceResult, Potential, SupportsHessian
from potentials.lennard_jones import LennardJones

POTENTIALS = {"lj": LennardJones}

__all__ = ["POTENTIALS", "ForceResult", "LennardJones", "Potential", "SupportsHessian"]
