"""Rigid bodies as data: centres, orientations, momenta and the constituents' places (layer 0).

A :class:`RigidBodies` holds, for each body, its mass, principal moments of
inertia, centre-of-mass position and momentum, orientation quaternion and
angular momentum (space frame), and each constituent's position in the body's
principal frame. Atoms that belong to no body (molecule id 0 or below) are
free particles and move as points. :meth:`RigidBodies.place` writes the
constituents' positions and velocities into a State from the body variables,
:meth:`RigidBodies.force_torque` sums forces on constituents into each body's
force and torque. The integrators that move bodies are in
:mod:`integrators.rigid`.

Conventions: a quaternion ``q = (w, x, y, z)`` rotates the body frame into the
space frame, ``r_space = A(q) d_body``; the principal axes are ordered by
increasing moment and made right-handed, and chosen as LAMMPS's fix rigid chooses
them where moments are equal (:func:`principal_axes`). A linear body has its first moment
zero (below ``1e-7`` of the largest, as LAMMPS takes it), the angular momentum along its axis zero
and five degrees of freedom.

References
----------
T. F. Miller III, M. Eleftheriou, P. Pattnaik, A. Ndirango, D. Newns,
G. J. Martyna, J. Chem. Phys. 116, 8649 (2002) (NO_SQUISH).
LAMMPS ``fix rigid`` (bodystyle ``molecule``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from md.box import minimum_image, perpendicular_widths
from md.state import State

#: A moment below this fraction of the body's largest is zero (a linear body), as in
#: LAMMPS's fix rigid.
LINEAR_TOLERANCE = 1e-7
#: Constituents of one body closer than this fraction of its extent overlap.
OVERLAP_TOLERANCE = 1e-6


def molecules_from_bonds(bonds: ArrayLike, n_atoms: int) -> NDArray[np.int64]:
    """Molecule ids 1, 2, ... per atom: the connected components of ``bonds`` (an atom in
    no bond gets an id of its own)."""
    parent = np.arange(n_atoms)

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, j in np.asarray(bonds, dtype=np.int64).reshape(-1, 2):
        a, b = root(int(i)), int(root(int(j)))
        if a != b:
            parent[max(a, b)] = min(a, b)
    roots = np.array([root(i) for i in range(n_atoms)], dtype=np.int64)
    return np.unique(roots, return_inverse=True)[1].astype(np.int64) + 1


def quaternion_matrices(quaternions: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation matrices A(q), shape (B, 3, 3), of unit quaternions (B, 4) ``(w, x, y, z)``."""
    w, x, y, z = np.moveaxis(np.asarray(quaternions, dtype=np.float64), -1, 0)
    return np.stack(
        [
            np.stack([w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z], -1),
        ],
        -2,
    )


def matrix_quaternions(matrices: NDArray[np.float64]) -> NDArray[np.float64]:
    """Unit quaternions (B, 4), ``w >= 0``, of proper rotation matrices (B, 3, 3)."""
    a = np.asarray(matrices, dtype=np.float64).reshape(-1, 3, 3)
    trace = np.trace(a, axis1=1, axis2=2)
    # Shepperd's choice per matrix: the largest of the four squared components first.
    diagonal = np.stack([trace, a[:, 0, 0], a[:, 1, 1], a[:, 2, 2]], axis=1)
    choice = np.argmax(diagonal, axis=1)
    q = np.zeros((len(a), 4))
    rows = choice == 0
    if np.any(rows):
        m = a[rows]
        w = 0.5 * np.sqrt(1.0 + trace[rows])
        q[rows] = np.stack(
            [
                w,
                (m[:, 2, 1] - m[:, 1, 2]) / (4 * w),
                (m[:, 0, 2] - m[:, 2, 0]) / (4 * w),
                (m[:, 1, 0] - m[:, 0, 1]) / (4 * w),
            ],
            axis=1,
        )
    for k in (1, 2, 3):
        rows = choice == k
        if not np.any(rows):
            continue
        m = a[rows]
        i, j, n = k - 1, k % 3, (k + 1) % 3
        v = 0.5 * np.sqrt(np.maximum(1.0 + 2 * m[:, i, i] - trace[rows], 0.0))
        q[rows, 1 + i] = v
        q[rows, 1 + j] = (m[:, j, i] + m[:, i, j]) / (4 * v)
        q[rows, 1 + n] = (m[:, n, i] + m[:, i, n]) / (4 * v)
        q[rows, 0] = (m[:, n, j] - m[:, j, n]) / (4 * v)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.where(q[:, :1] >= 0, q, -q)


def _mass_centre_inertia(masses, positions):
    """``(mass, centre (3,), inertia tensor (3, 3))`` of point masses (K,) at ``positions``
    (K, 3), summed atom by atom in the order given, as LAMMPS's fix rigid sums them: the
    centre ``sum(x m) / M``, then ``sum m (|d|^2 - d d)`` about it. The principal axes of a
    body with two equal moments depend on the last bits of this tensor (see
    :func:`principal_axes`), so the order of the sums is kept, not left to numpy."""
    total, cx, cy, cz = 0.0, 0.0, 0.0, 0.0
    rows = positions.tolist()
    weights = masses.tolist()
    for m, (x, y, z) in zip(weights, rows, strict=True):
        cx += x * m
        cy += y * m
        cz += z * m
        total += m
    cx, cy, cz = cx / total, cy / total, cz / total
    xx = yy = zz = yz = xz = xy = 0.0
    for m, (x, y, z) in zip(weights, rows, strict=True):
        dx, dy, dz = x - cx, y - cy, z - cz
        xx += m * (dy * dy + dz * dz)
        yy += m * (dx * dx + dz * dz)
        zz += m * (dx * dx + dy * dy)
        yz -= m * dy * dz
        xz -= m * dx * dz
        xy -= m * dx * dy
    tensor = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
    return total, np.array([cx, cy, cz]), tensor


def _jacobi_rotation(a: list, vectors: list, i: int, j: int) -> None:
    """One Jacobi rotation in the (i, j) plane, i < j, of the symmetric 3 x 3 ``a`` (lists,
    in place) that zeroes ``a[i][j]``; the same rotation applied to the rows of
    ``vectors``. The tangent is the root of t^2 + 2 kappa t - 1 = 0 of smaller size,
    kappa = (a_jj - a_ii) / (2 a_ij); t = 1 for equal diagonal entries."""
    aij = a[i][j]
    gap = a[j][j] - a[i][i]
    t = 1.0
    if gap != 0.0:
        t = 0.0
        if aij != 0.0:
            kappa = gap / (2.0 * aij)
            t = 1.0 / (math.sqrt(1.0 + kappa * kappa) + abs(kappa))
            if kappa < 0.0:
                t = -t
    c = 1.0 / math.sqrt(1.0 + t * t)
    s = c * t
    a[i][i] -= t * aij
    a[j][j] += t * aij
    a[i][j] = a[j][i] = 0.0
    w = 3 - i - j  # the third index
    wi, wj = a[w][i], a[w][j]
    a[w][i] = a[i][w] = c * wi - s * wj
    a[w][j] = a[j][w] = s * wi + c * wj
    row_i, row_j = vectors[i], vectors[j]
    for k in range(3):
        vi, vj = row_i[k], row_j[k]
        row_i[k] = c * vi - s * vj
        row_j[k] = s * vi + c * vj


def principal_axes(tensor: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Principal moments (3,) and axes (3, 3, one a column) of an inertia tensor, chosen as
    LAMMPS's fix rigid chooses them.

    Where two moments are equal (a linear body, a symmetric top) any pair of axes in
    their plane is principal, and NO_SQUISH's turns about them do not commute: to follow
    LAMMPS's ``fix rigid/nve`` the axes must be its own. So this is the classical Jacobi
    method as LAMMPS's ``MathEigen::jacobi3`` runs it (A. Jewett's ``jacobi_pd``):
    each rotation zeroes the off-diagonal entry of largest size (the first of
    (0, 1), (0, 2), (1, 2) on a tie), until that entry is zero or below the last bit of
    both its diagonal entries (at most 150 rotations); the moments are then sorted
    increasing by selection sort (equal ones keep that sort's order); a moment below
    :data:`LINEAR_TOLERANCE` of the largest is set to zero; the third axis is turned
    round if the three are left-handed. Written from the algorithm, in double precision
    in the same order of operations, so its result is LAMMPS's to the last bit given the
    same tensor (:func:`_mass_centre_inertia`).
    """
    a = np.array(tensor, dtype=np.float64).tolist()
    vectors = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]  # rows: the axes
    for _ in range(150):
        i, j = 0, 1
        if abs(a[0][2]) > abs(a[0][1]):
            j = 2
        if abs(a[1][2]) > abs(a[i][j]):
            i, j = 1, 2
        if a[i][i] + a[i][j] == a[i][i] and a[j][j] + a[i][j] == a[j][j]:
            break  # below the last bit of both diagonal entries
        if a[i][j] == 0.0:
            break
        _jacobi_rotation(a, vectors, i, j)
    values = [a[0][0], a[1][1], a[2][2]]
    for i in range(2):  # selection sort, increasing
        low = i
        for j in range(i + 1, 3):
            if values[j] < values[low]:
                low = j
        values[i], values[low] = values[low], values[i]
        vectors[i], vectors[low] = vectors[low], vectors[i]
    largest = max(values)
    moments = np.array([0.0 if v < LINEAR_TOLERANCE * largest else v for v in values])
    axes = np.array(vectors).T
    if np.dot(np.cross(axes[:, 0], axes[:, 1]), axes[:, 2]) < 0.0:
        axes[:, 2] = -axes[:, 2]
    return moments, axes


def bodies_on_sites(state: State, rigid, seed=None) -> State:
    """A State with a copy of ``rigid.template`` (K constituent positions, (K, 3)
    [length]) centred on every atom of ``state`` (the sites), turned at random from
    ``seed`` (``rigid.orientation = "random"``) or all aligned with the template's axes
    (``"aligned"``); ``rigid`` is the config's ``[rigid]`` record.

    Each constituent takes its site's type, and ``rigid.template_masses`` (one value or K;
    default: its site's mass); the copies are in site order, K atoms each (molecule ids
    ``repeat(1..n_sites, K)``); velocities are zero. Raises ValueError for fewer than two
    constituents or non-positive masses.
    """
    template = np.asarray(rigid.template, dtype=np.float64)
    masses = rigid.template_masses
    if template.ndim != 2 or template.shape[1] != 3 or len(template) < 2:
        raise ValueError(
            f"template: needs two or more positions [x, y, z], got shape {template.shape}"
        )
    if not np.all(np.isfinite(template)):
        raise ValueError("template: positions must be finite")
    k = len(template)
    if masses is None:
        per_atom = np.repeat(state.masses, k)
    else:
        given = np.broadcast_to(np.asarray(masses, dtype=np.float64), (k,))
        if not np.all(given > 0):
            raise ValueError(f"template_masses must be positive, got {given.tolist()}")
        per_atom = np.tile(given, state.n_atoms)
    weights = per_atom[:k]
    offsets = template - (weights[:, None] * template).sum(0) / weights.sum()
    n = state.n_atoms
    if rigid.orientation == "aligned":
        turns = np.tile(np.eye(3), (n, 1, 1))
    else:
        q = np.random.default_rng(seed).standard_normal((n, 4))
        turns = quaternion_matrices(q / np.linalg.norm(q, axis=1, keepdims=True))
    positions = state.positions[:, None, :] + np.einsum("nij,kj->nki", turns, offsets)
    return State(
        positions=positions.reshape(n * k, 3),
        velocities=np.zeros((n * k, 3)),
        masses=per_atom,
        box=state.box.copy(),
        pbc=state.pbc.copy(),
        types=np.repeat(state.types, k),
        type_names=state.type_names,
        tilt=state.tilt.copy(),
    )


class RigidBodies:
    """Rigid bodies made of a State's atoms, and the free atoms beside them.

    Build with :meth:`from_molecules`. Arrays (B bodies, M constituents in body
    order, ``members[starts[b]:starts[b+1]]`` the atoms of body ``b``):

    ``masses`` (B,) [mass], ``moments`` (B, 3) principal moments [mass length^2],
    ``inverse_moments`` (B, 3) (0 for a linear body's zero moment),
    ``body_positions`` (M, 3) constituents in the principal frame [length],
    ``centres`` (B, 3) [length], ``momenta`` (B, 3) [mass length/time],
    ``quaternions`` (B, 4), ``angular_momenta`` (B, 3) space frame
    [mass length^2/time]; ``body_of`` (N,) the body of each atom or -1,
    ``free`` the indices of the free atoms, ``linear`` (B,) bool.

    Examples
    --------
    >>> state = State(positions=[[0, 0, 0], [1, 0, 0], [0, 1, 0]], velocities=np.zeros((3, 3)),
    ...               masses=[1, 1, 1], box=[10, 10, 10], pbc=[True] * 3)
    >>> bodies = RigidBodies.from_molecules(state, [1, 1, 1])
    >>> bodies.n_bodies, bodies.n_dof()
    (1, 6)
    """

    def __init__(self, members, starts, masses, moments, body_positions, body_of) -> None:
        self.members = np.asarray(members, dtype=np.int64)
        self.starts = np.asarray(starts, dtype=np.int64)
        self.masses = np.asarray(masses, dtype=np.float64)
        self.moments = np.asarray(moments, dtype=np.float64)
        self.body_positions = np.asarray(body_positions, dtype=np.float64)
        self.body_of = np.asarray(body_of, dtype=np.int64)
        self.free = np.flatnonzero(self.body_of < 0)
        self.linear = self.moments[:, 0] == 0.0
        with np.errstate(divide="ignore"):
            self.inverse_moments = np.where(self.moments > 0, 1.0 / self.moments, 0.0)
        self.owner = self.body_of[self.members]  # the body of each constituent, in body order
        n = len(self.masses)
        self.centres = np.zeros((n, 3))
        self.momenta = np.zeros((n, 3))
        self.quaternions = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
        self.angular_momenta = np.zeros((n, 3))

    @property
    def n_bodies(self) -> int:
        return len(self.masses)

    @classmethod
    def from_molecules(cls, state: State, molecule_ids: ArrayLike) -> RigidBodies:
        """One body per molecule id above 0 (atoms with id 0 or below are free), its centre,
        orientation and momenta taken from the state's positions and velocities.

        Raises ValueError for a body of one atom, zero or negative masses, a body wider
        than half the box along a periodic axis, or two constituents of one body on one
        spot. The velocities of constituents keep only their rigid part (:meth:`place`).
        """
        ids = np.asarray(molecule_ids)
        if ids.shape != (state.n_atoms,):
            raise ValueError(
                f"molecule ids: {ids.shape[0] if ids.ndim == 1 else ids.shape} values for "
                f"{state.n_atoms} atoms"
            )
        if not np.all(np.isfinite(ids.astype(float))) or np.any(ids != np.rint(ids)):
            raise ValueError("molecule ids must be integers")
        ids = ids.astype(np.int64)
        labels, inverse, sizes = np.unique(ids, return_inverse=True, return_counts=True)
        in_body = labels > 0
        if not np.any(in_body):
            raise ValueError("no rigid bodies: every molecule id is 0 (free atoms)")
        single = labels[in_body & (sizes == 1)]
        if single.size:
            raise ValueError(
                f"molecule {int(single[0])} has a single atom "
                f"(atom {int(np.flatnonzero(ids == single[0])[0])}); a rigid body needs at least "
                "two (give a free atom molecule id 0)"
            )
        bad = np.flatnonzero(~(state.masses > 0))
        if bad.size:
            raise ValueError(
                f"atom {int(bad[0])} has mass {state.masses[bad[0]]:g}; rigid bodies need "
                "positive masses"
            )
        body_index = np.cumsum(in_body) - 1
        body_of = np.where(in_body[inverse], body_index[inverse], -1)
        order = np.argsort(body_of, kind="stable")
        members = order[body_of[order] >= 0]
        counts = sizes[in_body]
        starts = np.concatenate([[0], np.cumsum(counts)])
        widths = perpendicular_widths(state.box, state.tilt)
        n = len(counts)
        masses = np.zeros(n)
        moments = np.zeros((n, 3))
        body_positions = np.zeros((len(members), 3))
        centres = np.zeros((n, 3))
        quaternions = np.zeros((n, 4))
        for b in range(n):
            atoms = members[starts[b] : starts[b + 1]]
            label = int(labels[in_body][b])
            # Unwrap onto the first constituent by minimum image.
            d = minimum_image(
                state.positions[atoms] - state.positions[atoms[0]],
                state.box,
                state.pbc,
                state.tilt,
            )
            m = state.masses[atoms]
            extent = d.max(axis=0) - d.min(axis=0)
            wide = state.pbc & (extent >= 0.5 * widths)
            if np.any(wide):
                axis = "xyz"[int(np.flatnonzero(wide)[0])]
                raise ValueError(
                    f"molecule {label} spans {extent[np.flatnonzero(wide)[0]]:g} along {axis}, "
                    f"half the box ({0.5 * widths[np.flatnonzero(wide)[0]]:g}) or more; a rigid "
                    "body must be smaller than half the box"
                )
            size = float(np.linalg.norm(extent))
            gaps = np.linalg.norm(d[:, None, :] - d[None, :, :], axis=-1)
            gaps[np.diag_indices(len(atoms))] = np.inf
            if gaps.min() <= OVERLAP_TOLERANCE * size:
                i, j = np.unravel_index(np.argmin(gaps), gaps.shape)
                raise ValueError(
                    f"molecule {label}: atoms {int(atoms[i])} and {int(atoms[j])} overlap "
                    f"(distance {gaps[i, j]:g}); a rigid body's constituents must be apart"
                )
            # The positions themselves where no image is crossed (to the last bit, as
            # LAMMPS's image flags 0 give them), else unwrapped onto the first atom.
            unwrapped = state.positions[atoms[0]] + d
            same = np.all(np.abs(unwrapped - state.positions[atoms]) < 0.25 * widths, axis=1)
            unwrapped[same] = state.positions[atoms][same]
            total, centre, tensor = _mass_centre_inertia(m, unwrapped)
            values, axes = principal_axes(tensor)
            masses[b] = total
            moments[b] = values
            body_positions[starts[b] : starts[b + 1]] = (unwrapped - centre) @ axes  # A^T d
            centres[b] = centre
            quaternions[b] = matrix_quaternions(axes[None])[0]
        bodies = cls(members, starts, masses, moments, body_positions, body_of)
        bodies.centres[:] = centres
        bodies.quaternions[:] = quaternions
        bodies.take_velocities(state)
        return bodies

    # ------------------------------------------------------------------ kinematics
    def matrices(self) -> NDArray[np.float64]:
        """A(q) of every body, (B, 3, 3): space = A @ body."""
        return quaternion_matrices(self.quaternions)

    def offsets(self) -> NDArray[np.float64]:
        """Each constituent's displacement from its centre in the space frame, (M, 3)."""
        return np.einsum("mij,mj->mi", self.matrices()[self.owner], self.body_positions)

    def angular_velocities(self) -> NDArray[np.float64]:
        """omega = A I^-1 A^T L in the space frame, (B, 3)."""
        a = self.matrices()
        body = np.einsum("bji,bj->bi", a, self.angular_momenta) * self.inverse_moments
        return np.einsum("bij,bj->bi", a, body)

    def take_velocities(self, state: State) -> None:
        """Set each body's momentum and angular momentum from its constituents' velocities
        (the rigid part of their motion)."""
        v = state.velocities[self.members]
        m = state.masses[self.members]
        d = self.offsets()
        self.momenta[:] = 0.0
        np.add.at(self.momenta, self.owner, m[:, None] * v)
        self.angular_momenta[:] = 0.0
        np.add.at(self.angular_momenta, self.owner, m[:, None] * np.cross(d, v))
        # A linear body has no angular momentum along its axis.
        a = self.matrices()
        body = np.einsum("bji,bj->bi", a, self.angular_momenta)
        body[self.linear, 0] = 0.0
        self.angular_momenta[:] = np.einsum("bij,bj->bi", a, body)

    def place(self, state: State) -> None:
        """Write the constituents' positions and velocities (centre motion plus omega x d),
        in one compiled pass over the bodies (:func:`_place`)."""
        _place(
            self.members,
            self.starts,
            self.centres,
            self.momenta,
            self.masses,
            self.quaternions,
            self.angular_momenta,
            self.inverse_moments,
            self.body_positions,
            state.positions,
            state.velocities,
        )

    def force_torque(self, forces: NDArray[np.float64]):
        """Sum the forces on constituents into body forces and torques (space frame), (B, 3)
        each, about the current centres (one compiled pass, :func:`_force_torque`)."""
        total = np.empty((self.n_bodies, 3))
        torque = np.empty((self.n_bodies, 3))
        _force_torque(
            self.members, self.starts, self.quaternions, self.body_positions, forces, total, torque
        )
        return total, torque

    # ------------------------------------------------------------------ thermodynamics
    def n_dof(self, remove_momentum: bool = True) -> int:
        """Degrees of freedom: 3 per free atom, 6 per body (5 per linear body), less 3 for
        the total momentum when there is more than one moving object."""
        n = 3 * len(self.free) + 6 * self.n_bodies - int(np.sum(self.linear))
        objects = len(self.free) + self.n_bodies
        return n - 3 if remove_momentum and objects > 1 else n

    def kinetic_energies(self, state: State) -> tuple[float, float]:
        """``(translational, rotational)`` kinetic energy [energy]: free atoms and centres,
        and the bodies' rotation 1/2 L.omega."""
        free = self.free
        translational = 0.5 * float(
            np.sum(state.masses[free, None] * state.velocities[free] ** 2)
        ) + 0.5 * float(np.sum(self.momenta**2 / self.masses[:, None]))
        rotational = 0.5 * float(np.sum(self.angular_momenta * self.angular_velocities()))
        return translational, rotational

    def virial_correction(self, state: State, forces: NDArray[np.float64]) -> NDArray[np.float64]:
        """What turns the atomic kinetic tensor and pair virial into the rigid-body ones,
        (3, 3): minus the constituents' sum d (x) f (forces about the centres, which leaves
        the centres' virial sum R (x) F) and minus the rotational kinetic tensor."""
        d = self.offsets()
        u = np.cross(self.angular_velocities()[self.owner], d)
        m = state.masses[self.members]
        return -np.einsum("mi,mj->ij", d, forces[self.members]) - np.einsum("m,mi,mj->ij", m, u, u)

    # ------------------------------------------------------------------ checkpoints
    #: What a checkpoint keeps: the moving variables, and the constants the start made
    #: (computed again from a resumed state they could differ in the last bit).
    SAVED = ("centres", "momenta", "quaternions", "angular_momenta", "moments", "body_positions")

    def get_state(self) -> dict:
        """The bodies' variables and constants, for a checkpoint."""
        return {name: getattr(self, name).copy() for name in self.SAVED}  # its own fields

    def set_state(self, saved: dict) -> None:
        """Take back :meth:`get_state`'s arrays (ValueError if they do not fit)."""
        for name in self.SAVED:
            value = np.asarray(saved[name], dtype=np.float64)
            target = getattr(self, name)  # its own field of that name
            if value.shape != target.shape:
                raise ValueError(
                    f"saved {name} have shape {value.shape}, the bodies {target.shape}"
                )
            target[:] = value
        with np.errstate(divide="ignore"):
            self.inverse_moments = np.where(self.moments > 0, 1.0 / self.moments, 0.0)
        self.linear = self.moments[:, 0] == 0.0


@njit(cache=True)
def rotation_entries(w, x, y, z):
    """The nine entries of A(q), row by row, of a quaternion ``(w, x, y, z)`` as scalars (a
    rotation for a unit quaternion, else |q|^2 times one), as :func:`quaternion_matrices`
    computes them: for the compiled loops over bodies."""
    return (
        w * w + x * x - y * y - z * z,
        2 * (x * y - w * z),
        2 * (x * z + w * y),
        2 * (x * y + w * z),
        w * w - x * x + y * y - z * z,
        2 * (y * z - w * x),
        2 * (x * z - w * y),
        2 * (y * z + w * x),
        w * w - x * x - y * y + z * z,
    )


@njit(cache=True)
def _place(
    members,
    starts,
    centres,
    momenta,
    masses,
    quaternions,
    angular_momenta,
    inverse_moments,
    body_positions,
    positions,
    velocities,
):
    """Write ``positions`` and ``velocities`` (N, 3) of every constituent from its body:
    x = R + A d, v = P / M + omega x (A d), omega = A I^-1 A^T L. Bodies b own
    ``members[starts[b]:starts[b + 1]]`` (atom indices), whose body-frame positions are
    the same rows of ``body_positions``."""
    for b in range(masses.shape[0]):
        q = quaternions[b]
        a00, a01, a02, a10, a11, a12, a20, a21, a22 = rotation_entries(q[0], q[1], q[2], q[3])
        l0, l1, l2 = angular_momenta[b, 0], angular_momenta[b, 1], angular_momenta[b, 2]
        # omega in the body frame, A^T L / I, then in the space frame
        u0 = (a00 * l0 + a10 * l1 + a20 * l2) * inverse_moments[b, 0]
        u1 = (a01 * l0 + a11 * l1 + a21 * l2) * inverse_moments[b, 1]
        u2 = (a02 * l0 + a12 * l1 + a22 * l2) * inverse_moments[b, 2]
        o0 = a00 * u0 + a01 * u1 + a02 * u2
        o1 = a10 * u0 + a11 * u1 + a12 * u2
        o2 = a20 * u0 + a21 * u1 + a22 * u2
        v0, v1, v2 = momenta[b, 0] / masses[b], momenta[b, 1] / masses[b], momenta[b, 2] / masses[b]
        for m in range(starts[b], starts[b + 1]):
            atom = members[m]
            p0, p1, p2 = body_positions[m, 0], body_positions[m, 1], body_positions[m, 2]
            d0 = a00 * p0 + a01 * p1 + a02 * p2
            d1 = a10 * p0 + a11 * p1 + a12 * p2
            d2 = a20 * p0 + a21 * p1 + a22 * p2
            positions[atom, 0] = centres[b, 0] + d0
            positions[atom, 1] = centres[b, 1] + d1
            positions[atom, 2] = centres[b, 2] + d2
            velocities[atom, 0] = v0 + (o1 * d2 - o2 * d1)
            velocities[atom, 1] = v1 + (o2 * d0 - o0 * d2)
            velocities[atom, 2] = v2 + (o0 * d1 - o1 * d0)


@njit(cache=True)
def _force_torque(members, starts, quaternions, body_positions, forces, total, torque):
    """Write each body's force ``total`` (B, 3) and torque ``torque`` (B, 3) about its
    centre: the sums over its constituents of f and (A d) x f, in member order."""
    for b in range(starts.shape[0] - 1):
        q = quaternions[b]
        a00, a01, a02, a10, a11, a12, a20, a21, a22 = rotation_entries(q[0], q[1], q[2], q[3])
        f0 = f1 = f2 = t0 = t1 = t2 = 0.0
        for m in range(starts[b], starts[b + 1]):
            atom = members[m]
            p0, p1, p2 = body_positions[m, 0], body_positions[m, 1], body_positions[m, 2]
            d0 = a00 * p0 + a01 * p1 + a02 * p2
            d1 = a10 * p0 + a11 * p1 + a12 * p2
            d2 = a20 * p0 + a21 * p1 + a22 * p2
            g0, g1, g2 = forces[atom, 0], forces[atom, 1], forces[atom, 2]
            f0 += g0
            f1 += g1
            f2 += g2
            t0 += d1 * g2 - d2 * g1
            t1 += d2 * g0 - d0 * g2
            t2 += d0 * g1 - d1 * g0
        total[b, 0], total[b, 1], total[b, 2] = f0, f1, f2
        torque[b, 0], torque[b, 1], torque[b, 2] = t0, t1, t2


__all__ = [
    "LINEAR_TOLERANCE",
    "OVERLAP_TOLERANCE",
    "RigidBodies",
    "bodies_on_sites",
    "matrix_quaternions",
    "molecules_from_bonds",
    "principal_axes",
    "quaternion_matrices",
    "rotation_entries",
]
