"""Bonded pair potentials over a fixed bond list: harmonic springs and FENE bonds.

Bonds are pairs of atom indices ``(i, j)`` that interact whatever their
distance, so these potentials need no neighbour list (``cutoff = None``).
Bond vectors use the minimum image along periodic axes (:mod:`md.box`), so a
bond may cross the box boundary; it must stay shorter than half the box edge.

Each is a bond term (:class:`potentials.BondTerm`: u and its derivative as a plain
function of the squared bond length) and a small class naming its parameters; the
bonded frame (:class:`potentials.BondPotential`) does the rest. Both offer the
optional Hessian capability (:class:`potentials.base.SupportsHessian`) as a sparse
(3N, 3N) matrix, and their law bond by bond (:class:`potentials.base.BondLaw`) for
the solvers that move bonds one at a time.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike

from md._checks import bond_array, read_bonds_file
from md.errors import BondStretchError
from md.schema import REQUIRED, Key
from potentials._bonded import bonded_keys, config_values
from potentials._bonded_frame import BondPotential, BondTerm
from potentials.base import BondLaw


# ------------------------------------------------------------------- terms
def harmonic_energy(r2, k, r0):
    """u = k/2 (r - r0)^2 and u'(r) / r (k for r0 = 0, also at r = 0)."""
    r = np.sqrt(r2)
    stretch = r - r0
    return 0.5 * k * stretch * stretch, (k * (1.0 - r0 / r) if r0 > 0.0 else k)


def harmonic_curvature(r2, k, r0):
    r = np.sqrt(r2)
    stretch = r - r0
    return 0.5 * k * stretch * stretch, (k * (1.0 - r0 / r) if r0 > 0.0 else k), k


def fene_energy(r2, k, r_max):
    """u = -k/2 r_max^2 ln(1 - r^2 / r_max^2) and u'(r) / r; not finite from r = r_max on."""
    r_max2 = r_max * r_max
    x = r2 / r_max2
    return -0.5 * k * r_max2 * np.log1p(-x), k / (1.0 - x)


def fene_curvature(r2, k, r_max):
    r_max2 = r_max * r_max
    x = r2 / r_max2
    s = 1.0 - x
    g = k / s
    return -0.5 * k * r_max2 * np.log1p(-x), g, g + 2.0 * k * x / (s * s)


HARMONIC = BondTerm(harmonic_energy, harmonic_curvature, name="harmonic", variable="r2")
FENE = BondTerm(fene_energy, fene_curvature, name="fene", variable="r2")


class _LawBonds(BondPotential):
    """A built-in bond style: parameters >= 0, config keys, and its law bond by bond."""

    NONNEGATIVE = True
    #: The law's form (:class:`BondLaw`); its two parameters are k and the length.
    _law: str

    def _setup(self, term: BondTerm, bonds, bond_types, **values) -> None:
        self._setup_term(term, bond_array(bonds), bond_types, values)

    def bond_law(self) -> BondLaw:
        """Return the law of every bond (per-type parameters spread per bond)."""
        k, length = (table[self.bond_types] for table in self._tables)
        return BondLaw(self._law, self.bonds.astype(np.int64), k, length)


class HarmonicBonds(_LawBonds):
    r"""Harmonic springs :math:`U = \sum_b \tfrac{k_b}{2} (r_b - r_{0,b})^2` over listed bonds.

    Parameters
    ----------
    bonds : array_like of int, shape (B, 2)
        Atom index pairs ``(i, j)``, ``i != j``; a pair listed twice counts twice.
    k : float or sequence of float
        Spring constant(s) [energy/length^2], >= 0: one for every bond, or one
        per bond type (then ``bond_types`` is required).
    r0 : float or sequence of float
        Rest length(s) [length], >= 0; a scalar or one per bond type.
    bond_types : array_like of int, shape (B,), optional
        Type index of each bond into per-type ``k`` and ``r0``.

    Examples
    --------
    >>> import numpy as np
    >>> from md.state import State
    >>> springs = HarmonicBonds([[0, 1]], k=2.0, r0=1.0)
    >>> state = State(positions=[[0, 0, 0], [1.5, 0, 0]], box=10.0, pbc=False)
    >>> float(springs.energy_forces(state, None).energy)  # 2 / 2 * 0.5**2
    0.25
    """

    _law = "harmonic"
    bond_style = "spring"
    #: The keys of its config table (see :meth:`from_config`).
    CONFIG_KEYS = bonded_keys(
        "bond",
        "[i, j]",
        Key(
            "k",
            "number or list",
            REQUIRED,
            unit="energy/length^2",
            doc="The spring constant, >= 0: one for all bonds, or one per bond type.",
        ),
        Key(
            "r0",
            "number or list",
            REQUIRED,
            unit="length",
            doc="The rest length, >= 0: one, or one per bond type.",
        ),
    )

    def __init__(
        self,
        bonds: ArrayLike,
        k: float | Sequence[float],
        r0: float | Sequence[float],
        bond_types: ArrayLike | None = None,
    ) -> None:
        self._setup(HARMONIC, bonds, bond_types, k=k, r0=r0)
        self.k, self.r0 = self._tables

    @classmethod
    def from_config(cls, params: Mapping, type_names: Sequence[str] = ()) -> HarmonicBonds:
        """Build from a config table.

        Keys: ``bonds`` (a list of ``[i, j]`` atom index pairs) or
        ``bonds_file`` (a text file of two integer columns, ``#`` comments;
        the path is used as given), ``k``, ``r0`` (numbers, or lists indexed
        by bond type) and optional ``bond_types`` (one integer per bond).
        ``type_names`` is unused: bonds name atoms, not types.
        """
        return cls(**_config_values(params, cls.CONFIG_KEYS))


class FENEBonds(_LawBonds):
    r"""FENE bonds :math:`U = -\tfrac{k}{2} r_{max}^2 \ln(1 - (r / r_{max})^2)` (Kremer-Grest).

    The bonds of the Kremer-Grest bead-spring polymer model pair this with
    the purely repulsive WCA potential between all beads, which is
    ``LennardJones(epsilon=1, sigma=1, cutoff=2**(1/6), cutoff_mode="shift")``;
    with the defaults k = 30 and r_max = 1.5 the bond energy (FENE + WCA) is
    lowest at r = 0.961, and bonds in a melt at T = 1 average about 0.97.

    A bond reaching ``r_max`` has infinite energy: :meth:`energy_forces`
    and :meth:`hessian` then raise :class:`BondStretchError`.

    Parameters
    ----------
    bonds : array_like of int, shape (B, 2)
        Atom index pairs ``(i, j)``, ``i != j``.
    k : float or sequence of float
        Spring constant(s) [energy/length^2], >= 0; one per bond type if a sequence.
    r_max : float or sequence of float
        Maximum bond extension(s) [length], > 0; one per bond type if a sequence.
    bond_types : array_like of int, shape (B,), optional
        Type index of each bond into per-type ``k`` and ``r_max``.

    Examples
    --------
    >>> from md.state import State
    >>> fene = FENEBonds([[0, 1]])
    >>> state = State(positions=[[0, 0, 0], [1.6, 0, 0]], box=10.0, pbc=False)
    >>> try:
    ...     fene.energy_forces(state, None)
    ... except BondStretchError as error:
    ...     print(error.bond, error.i, error.j, error.length)
    0 0 1 1.6

    References
    ----------
    K. Kremer and G. S. Grest, J. Chem. Phys. 92, 5057 (1990).
    """

    _law = "fene"
    bond_style = "fene"
    #: The keys of its config table (see :meth:`from_config`).
    CONFIG_KEYS = bonded_keys(
        "bond",
        "[i, j]",
        Key(
            "k",
            "number or list",
            30.0,
            unit="energy/length^2",
            doc="The spring constant, >= 0: one for all bonds, or one per bond type.",
        ),
        Key(
            "r_max",
            "number or list",
            1.5,
            unit="length",
            doc="The maximum extension, > 0: one, or one per bond type.",
        ),
    )

    def __init__(
        self,
        bonds: ArrayLike,
        k: float | Sequence[float] = 30.0,
        r_max: float | Sequence[float] = 1.5,
        bond_types: ArrayLike | None = None,
    ) -> None:
        self._setup(FENE, bonds, bond_types, k=k, r_max=r_max)
        if not np.all(self._tables[1] > 0):
            raise ValueError(f"r_max must be > 0, got {r_max!r}")
        self.k, self.r_max = self._tables

    @classmethod
    def from_config(cls, params: Mapping, type_names: Sequence[str] = ()) -> FENEBonds:
        """Build from a config table.

        Keys: ``bonds`` or ``bonds_file`` (as for
        :meth:`HarmonicBonds.from_config`), ``k`` (default 30), ``r_max``
        (default 1.5), optional ``bond_types``.
        """
        return cls(**_config_values(params, cls.CONFIG_KEYS))

    def _raise_bad(self, state, bad: int):
        i, j = (int(a) for a in self.bonds[bad])
        r_max = float(self.r_max[self.bond_types[bad]])
        raise BondStretchError(bad, i, j, self._length(state, bad), r_max)


# ------------------------------------------------------------------- helpers


def _config_values(params: Mapping, keys: tuple[Key, ...]) -> dict:
    """Check a bond potential's config table; return constructor arguments."""
    return config_values(params, keys, "bond", read_bonds_file, "[i, j]")
