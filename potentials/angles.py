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
import scipy.sparse
from numba import njit
from numpy.typing import ArrayLike, NDArray

from md._checks import angle_array, read_index_file
from md.box import minimum_image, periodic_lengths, periodic_tilt, separation
from md.errors import AngleCollapseError
from md.schema import REQUIRED, Key
from potentials._bonded import (
    ListedTuples,
    bonded_keys,
    config_values,
    symmetric,
)
from potentials.base import ForceResult

#: Kernel codes for the angle forms.
_HARMONIC = 0
_COSINE = 1
#: Floor on sin(theta) in the harmonic force's 1/sin(theta) (LAMMPS's SMALL in
#: angle_harmonic.cpp).
SMALL = 0.001


class _AnglePotential(ListedTuples):
    """Shared orchestration of the angle potentials: validation, buffers, kernels.

    Subclasses set ``_form`` (a kernel code) and ``angle_style`` and call
    :meth:`_setup` with the per-angle-type parameter arrays.
    """

    ITEM = "angle"
    _form: int
    #: Name of the angle form: its config type, and the angle type name in files.
    angle_style: str

    def _setup(self, angles, angle_types, params: dict[str, ArrayLike]) -> None:
        self._setup_list(angle_array(angles), angle_types, params)

    @property
    def angles(self) -> NDArray[np.int64]:
        """The (A, 3) atom indices of the angles, vertex in the middle (read-only)."""
        return self._items

    @property
    def angle_types(self) -> NDArray[np.int64]:
        """The (A,) type index of each angle (read-only)."""
        return self._types

    @property
    def n_angles(self) -> int:
        return len(self._items)

    def with_angles(self, angles: ArrayLike, angle_types: ArrayLike) -> _AnglePotential:
        """The same potential over another angle list, whose ``angle_types`` index the same
        per-type parameters: one rank's share of the angles, over its local atoms, in a run
        decomposed over MPI ranks (:mod:`md.distributed`)."""
        return self._with_list(angle_array(angles), angle_types)

    def check(self, state) -> None:
        """Raise ValueError if an angle names an atom the state does not have."""
        self._check_indices(state.n_atoms)

    def energy_forces(
        self, state, neighbors=None, per_atom: bool = False, virial: bool = True
    ) -> ForceResult:
        """Return energy, forces, virial (and per-atom energies and virials) for ``state``.

        ``neighbors`` is ignored (angles are listed explicitly).

        Raises
        ------
        AngleCollapseError
            If an angle has an arm of zero length.
        """
        self._check_indices(state.n_atoms)
        n = state.n_atoms
        lengths, inverse = periodic_lengths(state.box, state.pbc)
        forces = np.zeros((n, 3))
        total = np.zeros(6)
        energies = np.zeros(n if per_atom else 0)
        virials = np.zeros((n if per_atom else 0, 6))
        energy, bad = _angle_energy_forces(
            state.positions, lengths, inverse, periodic_tilt(state.tilt, state.pbc),
            self.angles, self.angle_types, self._form, *self._kernel_tables(),
            forces, total, energies, virials,
        )  # fmt: skip
        if bad >= 0:
            raise AngleCollapseError(bad, tuple(int(a) for a in self.angles[bad]))
        return ForceResult(
            energy=energy,
            forces=forces,
            virial=symmetric(total),
            energies=energies if per_atom else None,
            virials=virials if per_atom else None,
        )

    def hessian(self, state, neighbors=None) -> scipy.sparse.csr_matrix:
        """Return the (3N, 3N) Hessian d^2 U / dx_ia dx_jb as a sparse CSR matrix.

        Row and column ``3 * i + a`` belong to atom ``i``, axis ``a``
        [energy/length^2]. It is the derivative of the forces as computed
        (with LAMMPS's floor on sin theta), one dense 9x9 block per angle.
        The blocks are not positive definite in general (bending has
        negative curvature away from theta0); the implicit integrators'
        Newton solver copes with that by its shifts.
        """
        self._check_indices(state.n_atoms)
        lengths, inverse = periodic_lengths(state.box, state.pbc)
        blocks = np.empty((self.n_angles, 9, 9))
        bad = _angle_hessian_blocks(
            state.positions, lengths, inverse, periodic_tilt(state.tilt, state.pbc),
            self.angles, self.angle_types, self._form, *self._kernel_tables(), blocks,
        )  # fmt: skip
        if bad >= 0:
            raise AngleCollapseError(bad, tuple(int(a) for a in self.angles[bad]))
        index = (3 * self.angles[:, :, None] + np.arange(3)).reshape(-1, 9)
        rows = np.broadcast_to(index[:, :, None], blocks.shape)
        columns = np.broadcast_to(index[:, None, :], blocks.shape)
        size = 3 * state.n_atoms
        return scipy.sparse.coo_matrix(
            (blocks.ravel(), (rows.ravel(), columns.ravel())), shape=(size, size)
        ).tocsr()

    def angle_values(self, state) -> NDArray[np.float64]:
        """Return the (A,) angles theta in ``state`` (minimum image) [degrees]."""
        self._check_indices(state.n_atoms)
        return angle_values(state, self.angles)

    def _kernel_tables(self) -> tuple[np.ndarray, np.ndarray]:
        """(k, theta0 in radians) per angle type; theta0 is unused by the cosine form."""
        raise NotImplementedError

    def _describe(self, **params) -> dict:
        return self._list_description(self.angle_style, **params)


class HarmonicAngles(_AnglePotential):
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

    _form = _HARMONIC
    angle_style = "angle_harmonic"
    #: The keys of its config table (see :meth:`from_config`).
    CONFIG_KEYS = bonded_keys(
        "angle", "[i, j, k]",
        Key("k", "number or list", REQUIRED, unit="energy/radian^2",
            doc="K of K (theta - theta0)^2 (no factor 1/2, as in LAMMPS), >= 0: one for all "
                "angles, or one per angle type."),
        Key("theta0", "number or list", REQUIRED, unit="degrees",
            doc="The rest angle, 0 to 180: one, or one per angle type."),
    )  # fmt: skip

    def __init__(
        self,
        angles: ArrayLike,
        k: float | Sequence[float],
        theta0: float | Sequence[float],
        angle_types: ArrayLike | None = None,
    ) -> None:
        self._setup(angles, angle_types, {"k": k, "theta0": theta0})
        self.k, self.theta0 = self._tables
        if np.any(self.theta0 > 180.0):
            raise ValueError(f"theta0 must be between 0 and 180 degrees, got {theta0!r}")
        self._theta0_radians = np.radians(self.theta0)

    def _kernel_tables(self):
        return self.k, self._theta0_radians

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

    def describe(self) -> dict:
        return self._describe(
            k=_plain(self.k, self.per_type), theta0=_plain(self.theta0, self.per_type)
        )


class CosineAngles(_AnglePotential):
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

    _form = _COSINE
    angle_style = "angle_cosine"
    #: The keys of its config table (see :meth:`from_config`).
    CONFIG_KEYS = bonded_keys(
        "angle", "[i, j, k]",
        Key("k", "number or list", REQUIRED, unit="energy",
            doc="K of K (1 + cos theta), >= 0: one for all angles, or one per angle type."),
    )  # fmt: skip

    def __init__(
        self,
        angles: ArrayLike,
        k: float | Sequence[float],
        angle_types: ArrayLike | None = None,
    ) -> None:
        self._setup(angles, angle_types, {"k": k})
        (self.k,) = self._tables
        self._unused = np.zeros_like(self.k)

    def _kernel_tables(self):
        return self.k, self._unused

    @classmethod
    def from_config(cls, params: Mapping, type_names: Sequence[str] = ()) -> CosineAngles:
        """Build from a config table.

        Keys: ``angles`` or ``angles_file`` (as for
        :meth:`HarmonicAngles.from_config`), ``k`` (a number, or a list
        indexed by angle type), optional ``angle_types``.
        """
        return cls(**_config_values(params, cls.CONFIG_KEYS))

    def describe(self) -> dict:
        return self._describe(k=_plain(self.k, self.per_type))


def angle_values(state, angles: ArrayLike) -> NDArray[np.float64]:
    """Return the angles theta of the triples ``angles`` (``j`` the vertex) [degrees].

    Minimum image along the state's periodic axes; cos theta clamped to
    [-1, 1]. An arm of zero length gives NaN.

    Examples
    --------
    >>> from md.state import State
    >>> state = State(positions=[[1, 0, 0], [0, 0, 0], [-1, 0, 0]], box=10.0, pbc=False)
    >>> angle_values(state, [[0, 1, 2]]).tolist()
    [180.0]
    """
    angles = angle_array(angles)
    positions = state.positions
    a = minimum_image(positions[angles[:, 0]] - positions[angles[:, 1]], state.box, state.pbc,
                      state.tilt)  # fmt: skip
    b = minimum_image(positions[angles[:, 2]] - positions[angles[:, 1]], state.box, state.pbc,
                      state.tilt)  # fmt: skip
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.einsum("ij,ij->i", a, b) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


# ------------------------------------------------------------------- helpers


def _plain(values: np.ndarray, per_type: bool):
    return values.tolist() if per_type else float(values[0])


def _read_angles_file(path) -> NDArray[np.int64]:
    return read_index_file(path, 3, "angles_file")


def _config_values(params: Mapping, keys: tuple[Key, ...]) -> dict:
    """Check an angle potential's config table; return constructor arguments."""
    return config_values(params, keys, "angle", _read_angles_file, "[i, j, k]")


# ------------------------------------------------------------------- kernels


@njit(cache=True, inline="always", error_model="numpy")
def _angle_terms(form, c, k, theta0):
    """Return ``(u, du/dc, d2u/dc2)`` of one angle at cos theta = ``c`` (in [-1, 1]).

    form 0 (harmonic): u = k (theta - theta0)^2, du/dc = -2 k (theta - theta0)
    / s with s = sin theta floored at SMALL (LAMMPS's), and d2u/dc2 the
    derivative of that du/dc as computed; form 1 (cosine): u = k (1 + c).
    """
    if form == 1:
        return k * (1.0 + c), k, 0.0
    exact = np.sqrt(1.0 - c * c)
    s = max(exact, SMALL)
    dtheta = np.arccos(c) - theta0
    d1 = -2.0 * k * dtheta / s
    if exact >= SMALL:
        d2 = (2.0 * k + c * d1) / (s * s)
    elif exact > 0.0:
        d2 = 2.0 * k / (exact * SMALL)  # only dtheta varies: d theta / dc = -1 / sin theta
    else:
        d2 = 0.0  # the gradient of c vanishes here, so d2u/dc2 does not enter
    return k * dtheta * dtheta, d1, d2


@njit(cache=True, error_model="numpy")
def _angle_energy_forces(
    positions, lengths, inverse, tilt, angles, angle_types, form, k, theta0,
    forces, virial, energies, virials,
):  # fmt: skip
    """Add angle forces to ``forces`` (zeroed by caller); return (energy, bad).

    angles: (A, 3) atom indices (i, j, k), j the vertex; angle_types: (A,)
    indices into the per-type tables k and theta0 [radians]. Writes
    ``virial`` (6,) as (xx, yy, zz, yz, xz, xy) of x_ij (x) F_i + x_kj (x) F_k
    summed, and, when ``energies`` has length N, a third of each angle's
    energy and, into ``virials`` (N, 6, zeroed), a third of its virial to
    each of its atoms (LAMMPS's split). ``bad`` is the first angle with an
    arm of zero length, whose terms are left out, or -1.
    """
    n = positions.shape[0]
    per_atom = energies.shape[0] == n
    third = 1.0 / 3.0
    energy = 0.0
    bad = -1
    wxx = wyy = wzz = wyz = wxz = wxy = 0.0
    for a in range(angles.shape[0]):
        i = angles[a, 0]
        j = angles[a, 1]
        m = angles[a, 2]
        t = angle_types[a]
        ax, ay, az = separation(positions, i, j, lengths, inverse, tilt)
        bx, by, bz = separation(positions, m, j, lengths, inverse, tilt)
        ra2 = ax * ax + ay * ay + az * az
        rb2 = bx * bx + by * by + bz * bz
        if not (ra2 > 0.0 and rb2 > 0.0):
            if bad < 0:
                bad = a
            continue
        rab = np.sqrt(ra2) * np.sqrt(rb2)
        c = (ax * bx + ay * by + az * bz) / rab
        c = min(max(c, -1.0), 1.0)
        u, d1, _ = _angle_terms(form, c, k[t], theta0[t])
        energy += u
        # F_i = -du/dc dc/dx_i, dc/dx_i = b / (|a||b|) - c a / |a|^2 (LAMMPS's a11, a12, a22).
        a11 = d1 * c / ra2
        a12 = -d1 / rab
        a22 = d1 * c / rb2
        fix = a11 * ax + a12 * bx
        fiy = a11 * ay + a12 * by
        fiz = a11 * az + a12 * bz
        fkx = a22 * bx + a12 * ax
        fky = a22 * by + a12 * ay
        fkz = a22 * bz + a12 * az
        forces[i, 0] += fix
        forces[i, 1] += fiy
        forces[i, 2] += fiz
        forces[m, 0] += fkx
        forces[m, 1] += fky
        forces[m, 2] += fkz
        forces[j, 0] -= fix + fkx
        forces[j, 1] -= fiy + fky
        forces[j, 2] -= fiz + fkz
        w0 = ax * fix + bx * fkx
        w1 = ay * fiy + by * fky
        w2 = az * fiz + bz * fkz
        w3 = ay * fiz + by * fkz
        w4 = ax * fiz + bx * fkz
        w5 = ax * fiy + bx * fky
        wxx += w0
        wyy += w1
        wzz += w2
        wyz += w3
        wxz += w4
        wxy += w5
        if per_atom:
            for atom in (i, j, m):
                energies[atom] += third * u
                virials[atom, 0] += third * w0
                virials[atom, 1] += third * w1
                virials[atom, 2] += third * w2
                virials[atom, 3] += third * w3
                virials[atom, 4] += third * w4
                virials[atom, 5] += third * w5
    virial[0] = wxx
    virial[1] = wyy
    virial[2] = wzz
    virial[3] = wyz
    virial[4] = wxz
    virial[5] = wxy
    return energy, bad


@njit(cache=True, error_model="numpy")
def _angle_hessian_blocks(
    positions, lengths, inverse, tilt, angles, angle_types, form, k, theta0, blocks
):
    """Write each angle's 9x9 Hessian block into ``blocks`` (A, 9, 9); return the first
    angle with an arm of zero length (its block left zero), or -1.

    Rows and columns run over (x_i, x_j, x_k), three axes each. With
    c = cos theta, g its gradient and G its Hessian, the block is
    u''(c) g g^T + u'(c) G. In the arms a = x_i - x_j, b = x_k - x_j (unit
    vectors e_a, e_b, projectors P_a = I - e_a e_a^T, P_b):
    dc/da = (e_b - c e_a) / |a| =: g_a (g_b likewise), d2c/da2 =
    -(e_a g_a^T + g_a e_a^T) / |a| - c P_a / |a|^2, d2c/da db =
    P_b / (|a||b|) - e_a g_b^T / |a|; then x_i moves a, x_k moves b and x_j
    moves both by minus its displacement.
    """
    g = np.empty(9)
    haa = np.empty((3, 3))
    hbb = np.empty((3, 3))
    hab = np.empty((3, 3))
    bad = -1
    for q in range(angles.shape[0]):
        block = blocks[q]
        block[:, :] = 0.0
        i = angles[q, 0]
        j = angles[q, 1]
        m = angles[q, 2]
        t = angle_types[q]
        ax, ay, az = separation(positions, i, j, lengths, inverse, tilt)
        bx, by, bz = separation(positions, m, j, lengths, inverse, tilt)
        ra = np.sqrt(ax * ax + ay * ay + az * az)
        rb = np.sqrt(bx * bx + by * by + bz * bz)
        if not (ra > 0.0 and rb > 0.0):
            if bad < 0:
                bad = q
            continue
        ea = (ax / ra, ay / ra, az / ra)
        eb = (bx / rb, by / rb, bz / rb)
        c = min(max(ea[0] * eb[0] + ea[1] * eb[1] + ea[2] * eb[2], -1.0), 1.0)
        _, d1, d2 = _angle_terms(form, c, k[t], theta0[t])
        for x in range(3):
            g[x] = (eb[x] - c * ea[x]) / ra
            g[6 + x] = (ea[x] - c * eb[x]) / rb
            g[3 + x] = -g[x] - g[6 + x]
        for x in range(3):
            for y in range(3):
                delta = 1.0 if x == y else 0.0
                haa[x, y] = (-(ea[x] * g[y] + g[x] * ea[y]) / ra
                             - c * (delta - ea[x] * ea[y]) / (ra * ra))  # fmt: skip
                hbb[x, y] = (-(eb[x] * g[6 + y] + g[6 + x] * eb[y]) / rb
                             - c * (delta - eb[x] * eb[y]) / (rb * rb))  # fmt: skip
                hab[x, y] = (delta - eb[x] * eb[y]) / (ra * rb) - ea[x] * g[6 + y] / ra
        for x in range(3):
            for y in range(3):
                # d2c over (x_i, x_j, x_k) from the arm blocks, times u'(c)
                h00 = haa[x, y]
                h02 = hab[x, y]
                h20 = hab[y, x]
                h22 = hbb[x, y]
                block[x, y] = d1 * h00
                block[x, 6 + y] = d1 * h02
                block[6 + x, y] = d1 * h20
                block[6 + x, 6 + y] = d1 * h22
                block[x, 3 + y] = -d1 * (h00 + h02)
                block[3 + x, y] = -d1 * (h00 + h20)
                block[6 + x, 3 + y] = -d1 * (h20 + h22)
                block[3 + x, 6 + y] = -d1 * (h02 + h22)
                block[3 + x, 3 + y] = d1 * (h00 + h02 + h20 + h22)
        if d2 != 0.0:
            for x in range(9):
                for y in range(9):
                    block[x, y] += d2 * g[x] * g[y]
    return bad
