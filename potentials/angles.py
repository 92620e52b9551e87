r"""Angle potentials over a fixed list of atom triples: harmonic and cosine bending.

An angle is a triple ``(i, j, k)`` of atom indices with ``j`` the vertex
(LAMMPS's order: atom2 is the apex); theta is the angle between the arms
x_i - x_j and x_k - x_j, 180 degrees for three atoms in a straight line.
Both forms are LAMMPS's, with its parameter conventions:

- :class:`HarmonicAngles`, config type ``angle_harmonic``:
  U = K (theta - theta0)^2, theta0 in degrees (``angle_style harmonic``);
- :class:`CosineAngles`, config type ``angle_cosine``:
  U = K [1 + cos theta] (``angle_style cosine``).

Neither has a factor 1/2: ``k`` is LAMMPS's K. Both are lowest for a
straight triple when theta0 = 180, which makes bead-spring chains
semiflexible (the cosine form is the usual choice for Kremer-Grest chains:
its persistence length is about K / kT bonds for large K).

Like the bonds of :mod:`potentials.springs`, angles need no neighbour list
(``cutoff = None``), use the minimum image along periodic axes (each arm
must stay shorter than half the box), and offer a sparse (3N, 3N) Hessian,
so the implicit integrators can use Newton's method with them.

Straight and folded triples
    d theta / dx is singular where theta is 0 or 180 degrees (sin theta = 0).
    As LAMMPS does, cos theta is clamped to [-1, 1] and, for the harmonic form,
    sin theta to at least 0.001 in the force's 1/sin theta: forces stay finite
    there (and are zero for an exactly straight or folded triple, whose
    gradient of cos theta vanishes), and equal the true gradient wherever
    sin theta > 0.001 (theta more than 0.057 degrees from 0 and 180). The
    cosine form has no 1/sin theta and is exact everywhere. An arm of zero
    length (two atoms of an angle at one place) leaves theta undefined:
    :class:`md.errors.AngleCollapseError`.

Energy, forces and virial are LAMMPS's: each angle's energy and virial go a
third to each of its atoms in per-atom results, its virial is
x_ij (x) F_i + x_kj (x) F_k.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from md._checks import angle_array, read_index_file
from md.errors import AngleCollapseError
from md.schema import REQUIRED, Key
from potentials._bonded import bonded_keys, config_values
from potentials._bonded_frame import SMALL, AnglePotential, AngleTerm, angle_values

__all__ = ["SMALL", "AngleCollapseError", "CosineAngles", "HarmonicAngles", "angle_values"]


# ------------------------------------------------------------------- terms
def harmonic_energy(theta, k, theta0):
    """u = k (theta - theta0)^2 and du/dtheta (theta0 in radians)."""
    dtheta = theta - theta0
    return k * dtheta * dtheta, 2.0 * k * dtheta


def harmonic_curvature(theta, k, theta0):
    dtheta = theta - theta0
    return k * dtheta * dtheta, 2.0 * k * dtheta, 2.0 * k


def cosine_energy(c, k):
    """u = k (1 + cos theta) and du/dcos theta."""
    return k * (1.0 + c), k


def cosine_curvature(c, k):
    return k * (1.0 + c), k, 0.0


HARMONIC = AngleTerm(harmonic_energy, harmonic_curvature, name="angle_harmonic")
COSINE = AngleTerm(cosine_energy, cosine_curvature, name="angle_cosine", variable="cos")


class _AngleStyle(AnglePotential):
    """A built-in angle style: parameters >= 0 and config keys."""

    NONNEGATIVE = True

    def _setup(self, term: AngleTerm, angles, angle_types, **values) -> None:
        self._setup_term(term, angle_array(angles), angle_types, values)


class HarmonicAngles(_AngleStyle):
    r"""Harmonic bending :math:`U = \sum_a K_a (\theta_a - \theta_{0,a})^2` (LAMMPS ``harmonic``).

    No factor 1/2, as in LAMMPS: the curvature at theta0 is 2K.

    Parameters
    ----------
    angles : array_like of int, shape (A, 3)
        Atom index triples ``(i, j, k)``, ``j`` the vertex, three distinct atoms.
    k : float or sequence of float
        K [energy/radian^2], >= 0: one for every angle, or one per angle type
        (then ``angle_types`` is required).
    theta0 : float or sequence of float
        Rest angle(s) [degrees], 0 to 180; a scalar or one per angle type.
    angle_types : array_like of int, shape (A,), optional
        Type index of each angle into per-type ``k`` and ``theta0``.

    Examples
    --------
    >>> from md.state import State
    >>> bend = HarmonicAngles([[0, 1, 2]], k=2.0, theta0=180.0)
    >>> state = State(positions=[[1, 0, 0], [0, 0, 0], [0, 1, 0]], box=10.0, pbc=False)
    >>> round(float(bend.energy_forces(state).energy), 12)  # 2 (pi/2)^2
    4.934802200545
    """

    angle_style = "angle_harmonic"
    #: The keys of its config table (see :meth:`from_config`).
    CONFIG_KEYS = bonded_keys(
        "angle",
        "[i, j, k]",
        Key(
            "k",
            "number or list",
            REQUIRED,
            unit="energy/radian^2",
            doc="K of K (theta - theta0)^2 (no factor 1/2, as in LAMMPS), >= 0: one for all "
            "angles, or one per angle type.",
        ),
        Key(
            "theta0",
            "number or list",
            REQUIRED,
            unit="degrees",
            doc="The rest angle, 0 to 180: one, or one per angle type.",
        ),
    )

    def __init__(
        self,
        angles: ArrayLike,
        k: float | Sequence[float],
        theta0: float | Sequence[float],
        angle_types: ArrayLike | None = None,
    ) -> None:
        self._setup(HARMONIC, angles, angle_types, k=k, theta0=theta0)
        self.k, self.theta0 = self._tables
        if np.any(self.theta0 > 180.0):
            raise ValueError(f"theta0 must be between 0 and 180 degrees, got {theta0!r}")
        self._table[1] = np.radians(self.theta0)  # the term's theta0 is in radians

    @classmethod
    def from_config(cls, params: Mapping, type_names: Sequence[str] = ()) -> HarmonicAngles:
        """Build from a config table.

        Keys: ``angles`` (a list of ``[i, j, k]`` atom index triples, ``j``
        the vertex) or ``angles_file`` (a text file of three integer columns,
        ``#`` comments; the path is used as given), ``k`` and ``theta0``
        (degrees; numbers, or lists indexed by angle type) and optional
        ``angle_types`` (one integer per angle). ``type_names`` is unused.
        """
        return cls(**_config_values(params, cls.CONFIG_KEYS))


class CosineAngles(_AngleStyle):
    r"""Cosine bending :math:`U = \sum_a K_a [1 + \cos\theta_a]` (LAMMPS ``cosine``).

    Lowest (zero) for a straight triple. For an isolated angle at temperature
    T, <cos theta> = 1 / (K / kT) - coth(K / kT): the semiflexible
    Kremer-Grest chain's bending term, persistence length about K / kT bonds.

    Parameters
    ----------
    angles : array_like of int, shape (A, 3)
        Atom index triples ``(i, j, k)``, ``j`` the vertex, three distinct atoms.
    k : float or sequence of float
        K [energy], >= 0; one per angle type if a sequence.
    angle_types : array_like of int, shape (A,), optional
        Type index of each angle into per-type ``k``.

    Examples
    --------
    >>> from md.state import State
    >>> bend = CosineAngles([[0, 1, 2]], k=1.5)
    >>> state = State(positions=[[1, 0, 0], [0, 0, 0], [0, 1, 0]], box=10.0, pbc=False)
    >>> float(bend.energy_forces(state).energy)  # 1.5 (1 + cos 90)
    1.5
    """

    angle_style = "angle_cosine"
    #: The keys of its config table (see :meth:`from_config`).
    CONFIG_KEYS = bonded_keys(
        "angle",
        "[i, j, k]",
        Key(
            "k",
            "number or list",
            REQUIRED,
            unit="energy",
            doc="K of K (1 + cos theta), >= 0: one for all angles, or one per angle type.",
        ),
    )

    def __init__(
        self,
        angles: ArrayLike,
        k: float | Sequence[float],
        angle_types: ArrayLike | None = None,
    ) -> None:
        self._setup(COSINE, angles, angle_types, k=k)
        (self.k,) = self._tables

    @classmethod
    def from_config(cls, params: Mapping, type_names: Sequence[str] = ()) -> CosineAngles:
        """Build from a config table.

        Keys: ``angles`` or ``angles_file`` (as for
        :meth:`HarmonicAngles.from_config`), ``k`` (a number, or a list
        indexed by angle type), optional ``angle_types``.
        """
        return cls(**_config_values(params, cls.CONFIG_KEYS))


# ------------------------------------------------------------------- helpers


def _read_angles_file(path) -> NDArray[np.int64]:
    return read_index_file(path, 3, "angles_file")


def _config_values(params: Mapping, keys: tuple[Key, ...]) -> dict:
    """Check an angle potential's config table; return constructor arguments."""
    return config_values(params, keys, "angle", _read_angles_file, "[i, j, k]")
