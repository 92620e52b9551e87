"""Bonded pair potentials over a fixed bond list: harmonic springs and FENE bonds.

Bonds are pairs of atom indices ``(i, j)`` that interact whatever their
distance, so these potentials need no neighbour list (``cutoff = None``).
Bond vectors use the minimum image along periodic axes (:mod:`md.box`), so a
bond may cross the box boundary; it must stay shorter than half the box edge.

Both potentials offer the optional Hessian capability
(:class:`potentials.base.SupportsHessian`) as a sparse (3N, 3N) matrix.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import scipy.sparse
from numba import njit
from numpy.typing import ArrayLike, NDArray

from md._checks import bond_array, read_bonds_file
from md.box import minimum_image, periodic_lengths, periodic_tilt, separation
from md.errors import BondStretchError
from md.schema import REQUIRED, Key
from potentials._bonded import (
    ListedTuples,
    bonded_keys,
    config_values,
    symmetric,
)
from potentials._kernels import _add_half_pair_virial
from potentials.base import BondLaw, ForceResult
from potentials.pair_hessian import PairHessian

#: Kernel codes for the bond forms.
_HARMONIC = 0
_FENE = 1
_FORM_NAMES = {_HARMONIC: "harmonic", _FENE: "fene"}


class _BondedPotential(ListedTuples):
    """Shared orchestration of the bond potentials: validation, buffers, kernels.

    Subclasses set ``_form`` (a kernel code) and ``bond_style`` and call
    :meth:`_setup` with the per-bond-type parameter arrays.
    """

    ITEM = "bond"
    _form: int
    #: Name of the bond form, used in descriptions and as the bond type name in files.
    bond_style: str

    def _setup(self, bonds, bond_types, params: dict[str, ArrayLike]) -> None:
        self._setup_list(bond_array(bonds), bond_types, params)

    @property
    def bonds(self) -> NDArray[np.int64]:
        """The (B, 2) atom indices of the bonds (read-only)."""
        return self._items

    @property
    def bond_types(self) -> NDArray[np.int64]:
        """The (B,) type index of each bond (read-only)."""
        return self._types

    @property
    def n_bonds(self) -> int:
        return len(self._items)

    def with_bonds(self, bonds: ArrayLike, bond_types: ArrayLike) -> _BondedPotential:
        """The same potential over another bond list, whose ``bond_types`` index the same
        per-type parameters: one rank's share of the bonds, over its local atoms, in a run
        decomposed over MPI ranks (:mod:`md.distributed`)."""
        return self._with_list(bond_array(bonds), bond_types)

    # ----------------------------------------------------------------- compute
    def check(self, state) -> None:
        """Raise ValueError if a bond names an atom the state does not have."""
        if self.n_bonds and np.any(self.bonds[:, 0] == self.bonds[:, 1]):
            bad = int(np.flatnonzero(self.bonds[:, 0] == self.bonds[:, 1])[0])
            raise ValueError(f"bond {bad} joins atom {self.bonds[bad, 0]} to itself")
        self._check_indices(state.n_atoms)

    def energy_forces(
        self, state, neighbors=None, per_atom: bool = False, virial: bool = True
    ) -> ForceResult:
        """Return energy, forces, virial (and per-atom energies) for ``state``.

        ``neighbors`` is ignored (bonds are listed explicitly).
        """
        self._check_indices(state.n_atoms)
        n = state.n_atoms
        lengths, inverse = periodic_lengths(state.box, state.pbc)
        forces = np.zeros((n, 3))
        virial = np.zeros(6)
        energies = np.zeros(n if per_atom else 0)
        virials = np.zeros((n if per_atom else 0, 6))
        energy, bad = _bond_energy_forces(
            state.positions,
            lengths,
            inverse,
            periodic_tilt(state.tilt, state.pbc),
            self.bonds,
            self.bond_types,
            self._form,
            *self._tables,
            forces,
            virial,
            energies,
            virials,
        )
        if bad >= 0:
            self._raise_stretched(state, bad)
        return ForceResult(
            energy=energy,
            forces=forces,
            virial=symmetric(virial),
            energies=energies if per_atom else None,
            virials=virials if per_atom else None,
        )

    def hessian(self, state, neighbors=None) -> scipy.sparse.csr_matrix:
        """Return the (3N, 3N) Hessian d^2 U / dx_ia dx_jb as a sparse CSR matrix.

        Row and column ``3 * i + a`` belong to atom ``i``, axis ``a``
        [energy/length^2].
        """
        return self.hessian_operator(state, neighbors).tocsr()

    def hessian_operator(self, state, neighbors=None) -> PairHessian:
        """Return the Hessian as one pair block per bond (:class:`PairHessian`).

        Bond b's block is K = u'' e e^T + (u'/r) (I - e e^T) along its unit
        vector e; a zero-length bond gets K = (u'/r) I.
        """
        self._check_indices(state.n_atoms)
        lengths, inverse = periodic_lengths(state.box, state.pbc)
        transverse = np.empty(self.n_bonds)
        radial = np.empty(self.n_bonds)
        unit = np.empty((self.n_bonds, 3))
        bad = _bond_curvatures(
            state.positions, lengths, inverse, periodic_tilt(state.tilt, state.pbc), self.bonds,
            self.bond_types, self._form,
            *self._tables, transverse, radial, unit,
        )  # fmt: skip
        if bad >= 0:
            self._raise_stretched(state, bad)
        bonds = self.bonds.astype(np.int64)
        return PairHessian(
            state.n_atoms, bonds[:, 0].copy(), bonds[:, 1].copy(), transverse, radial, unit,
            unique=False,
        )  # fmt: skip

    def bond_law(self) -> BondLaw:
        """Return the law of every bond (per-type parameters spread per bond)."""
        k, length = (table[self.bond_types] for table in self._tables)
        return BondLaw(_FORM_NAMES[self._form], self.bonds.astype(np.int64), k, length)

    def bond_lengths(self, state) -> NDArray[np.float64]:
        """Return the (B,) bond lengths in ``state`` (minimum image) [length]."""
        self._check_indices(state.n_atoms)
        d = state.positions[self.bonds[:, 0]] - state.positions[self.bonds[:, 1]]
        return np.linalg.norm(minimum_image(d, state.box, state.pbc, state.tilt), axis=1)

    def _describe(self, **params) -> dict:
        return self._list_description(self.bond_style, **params)

    def _raise_stretched(self, state, bad: int):
        i, j = (int(a) for a in self.bonds[bad])
        d = minimum_image(state.positions[i] - state.positions[j], state.box, state.pbc, state.tilt)
        r_max = float(self._tables[1][self.bond_types[bad]])
        raise BondStretchError(bad, i, j, float(np.linalg.norm(d)), r_max)


class HarmonicBonds(_BondedPotential):
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

    _form = _HARMONIC
    bond_style = "spring"
    #: The keys of its config table (see :meth:`from_config`).
    CONFIG_KEYS = bonded_keys(
        "bond", "[i, j]",
        Key("k", "number or list", REQUIRED, unit="energy/length^2",
            doc="The spring constant, >= 0: one for all bonds, or one per bond type."),
        Key("r0", "number or list", REQUIRED, unit="length",
            doc="The rest length, >= 0: one, or one per bond type."),
    )  # fmt: skip

    def __init__(
        self,
        bonds: ArrayLike,
        k: float | Sequence[float],
        r0: float | Sequence[float],
        bond_types: ArrayLike | None = None,
    ) -> None:
        self._setup(bonds, bond_types, {"k": k, "r0": r0})
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

    def describe(self) -> dict:
        return self._describe(k=_plain(self.k, self.per_type), r0=_plain(self.r0, self.per_type))


class FENEBonds(_BondedPotential):
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

    _form = _FENE
    bond_style = "fene"
    #: The keys of its config table (see :meth:`from_config`).
    CONFIG_KEYS = bonded_keys(
        "bond", "[i, j]",
        Key("k", "number or list", 30.0, unit="energy/length^2",
            doc="The spring constant, >= 0: one for all bonds, or one per bond type."),
        Key("r_max", "number or list", 1.5, unit="length",
            doc="The maximum extension, > 0: one, or one per bond type."),
    )  # fmt: skip

    def __init__(
        self,
        bonds: ArrayLike,
        k: float | Sequence[float] = 30.0,
        r_max: float | Sequence[float] = 1.5,
        bond_types: ArrayLike | None = None,
    ) -> None:
        self._setup(bonds, bond_types, {"k": k, "r_max": r_max})
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

    def describe(self) -> dict:
        return self._describe(
            k=_plain(self.k, self.per_type), r_max=_plain(self.r_max, self.per_type)
        )


# ------------------------------------------------------------------- helpers


def _plain(values: np.ndarray, per_type: bool):
    return values.tolist() if per_type else float(values[0])


def _config_values(params: Mapping, keys: tuple[Key, ...]) -> dict:
    """Check a bond potential's config table; return constructor arguments."""
    return config_values(params, keys, "bond", read_bonds_file, "[i, j]")


# ------------------------------------------------------------------- kernels


@njit(cache=True, inline="always", error_model="numpy")
def _bond_terms(form, r2, k, p):
    """Return ``(u, u'(r) / r, u''(r), ok)`` of one bond of squared length r2.

    form 0 (harmonic, p = r0): u = k/2 (r - r0)^2.
    form 1 (FENE, p = r_max): u = -k/2 r_max^2 ln(1 - r^2 / r_max^2); ok is
    False (and the terms zero) once r >= r_max.
    """
    if form == 0:
        r = np.sqrt(r2)
        stretch = r - p
        u = 0.5 * k * stretch * stretch
        g = k * (1.0 - p / r) if p > 0.0 else k
        return u, g, k, True
    p2 = p * p
    x = r2 / p2
    if not x < 1.0:
        return 0.0, 0.0, 0.0, False
    s = 1.0 - x
    u = -0.5 * k * p2 * np.log1p(-x)
    g = k / s
    return u, g, g + 2.0 * k * x / (s * s), True


@njit(cache=True, error_model="numpy")
def _bond_energy_forces(
    positions,
    lengths,
    inverse,
    tilt,
    bonds,
    bond_types,
    form,
    k,
    p,
    forces,
    virial,
    energies,
    virials,
):
    """Add bond forces to ``forces`` (zeroed by caller); return (energy, bad).

    bonds: (B, 2) atom indices, bond_types: (B,) indices into the per-type
    tables k and p (the second parameter: r0 or r_max). Writes ``virial`` as
    (xx, yy, zz, yz, xz, xy) of sum r_ij (x) F_ij, and, when ``energies`` has
    length N, half of each bond energy and, into ``virials`` (N, 6, zeroed),
    half of its virial to each of its atoms. ``bad`` is the
    first bond beyond its range (FENE), whose terms are left out, or -1.
    """
    n = positions.shape[0]
    per_atom = energies.shape[0] == n
    energy = 0.0
    bad = -1
    wxx = wyy = wzz = wyz = wxz = wxy = 0.0
    for b in range(bonds.shape[0]):
        i = bonds[b, 0]
        j = bonds[b, 1]
        t = bond_types[b]
        dx, dy, dz = separation(positions, i, j, lengths, inverse, tilt)
        u, g, _, ok = _bond_terms(form, dx * dx + dy * dy + dz * dz, k[t], p[t])
        if not ok and bad < 0:
            bad = b
        energy += u
        # Force on i is -u'(r) r_ij / r.
        fx = -g * dx
        fy = -g * dy
        fz = -g * dz
        forces[i, 0] += fx
        forces[i, 1] += fy
        forces[i, 2] += fz
        forces[j, 0] -= fx
        forces[j, 1] -= fy
        forces[j, 2] -= fz
        wxx += fx * dx
        wyy += fy * dy
        wzz += fz * dz
        wyz += fz * dy
        wxz += fz * dx
        wxy += fy * dx
        if per_atom:
            energies[i] += 0.5 * u
            energies[j] += 0.5 * u
            _add_half_pair_virial(virials, i, j, fx, fy, fz, dx, dy, dz)
    virial[0] = wxx
    virial[1] = wyy
    virial[2] = wzz
    virial[3] = wyz
    virial[4] = wxz
    virial[5] = wxy
    return energy, bad


@njit(cache=True, error_model="numpy")
def _bond_curvatures(
    positions, lengths, inverse, tilt, bonds, bond_types, form, k, p, transverse, radial, unit
):
    """Write each bond's Hessian eigenvalues u'/r, u'' and unit vector; return the first bad bond.

    transverse, radial: (B,); unit: (B, 3), along x_i - x_j (minimum image),
    (1, 0, 0) for a zero-length bond, whose radial value is set to u'/r so
    that K = (u'/r) I. Returns -1 when every bond is within its range.
    """
    bad = -1
    for b in range(bonds.shape[0]):
        i = bonds[b, 0]
        j = bonds[b, 1]
        t = bond_types[b]
        dx, dy, dz = separation(positions, i, j, lengths, inverse, tilt)
        r2 = dx * dx + dy * dy + dz * dz
        _, g, h, ok = _bond_terms(form, r2, k[t], p[t])
        if not ok and bad < 0:
            bad = b
        transverse[b] = g
        if r2 > 0.0:
            inv_r = 1.0 / np.sqrt(r2)
            radial[b] = h
            unit[b, 0] = dx * inv_r
            unit[b, 1] = dy * inv_r
            unit[b, 2] = dz * inv_r
        else:
            radial[b] = g
            unit[b, 0] = 1.0
            unit[b, 1] = 0.0
            unit[b, 2] = 0.0
    return bad
