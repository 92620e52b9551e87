"""Rigid bodies: velocity Verlet for centres and free atoms, a rotational method for
orientations, and heat baths and a barostat hook for them.

The integrators here take a :class:`md.rigid.RigidBodies` and are built by
:mod:`md.rigid_setup` from a config's ``[rigid]`` table (:class:`RigidConfig`, checked
by :func:`checked_rigid`), not from the ``INTEGRATORS`` registry: :class:`RigidNVE`
(``[integrator]`` velocity Verlet), :class:`RigidLangevin`, :class:`RigidBussi` and
:class:`RigidNoseHoover` (Langevin, Bussi and Nose-Hoover chains on every momentum);
``RigidNVE.scale_cell`` is how an isotropic barostat moves bodies
(:class:`integrators.base.ScalesCell`).

:class:`RigidNVE` kicks each body's momentum and angular momentum (space frame) by
half a step of force and torque, drifts the centres and free atoms, turns the
orientations by the free rotor over ``dt`` with one of :data:`ROTATIONS`, places
the constituents (:meth:`md.rigid.RigidBodies.place`), evaluates the forces and
kicks again. The rotational methods, each a free-rotor map
``(quaternions, angular_momenta, inverse_moments, dt) -> quaternions`` that
keeps the space-frame angular momentum:

``no_squish``
    Miller et al.'s symmetric splitting of the free rotor into rotations about the
    principal axes, 3(dt/2) 2(dt/2) 1(dt) 2(dt/2) 3(dt/2), on quaternions (LAMMPS's
    ``fix rigid/nve``); symplectic, second order.
``dlm``
    Dullweber, Leimkuhler and McLachlan's splitting 1(dt/2) 2(dt/2) 3(dt) 2(dt/2)
    1(dt/2) on the rotation matrix, turned back into a quaternion; second order.
``richardson``
    Richardson extrapolation of two half-step and one full-step forward-Euler
    quaternion updates, each renormalised (the scheme of LAMMPS's ``fix rigid``);
    second order, not symplectic.
``rk4``
    Classical Runge-Kutta on dq/dt = 1/2 (0, omega) q with the quaternion
    renormalised at the end; fourth order on the free rotor, second in a force
    field (the kick-drift-kick splitting around it is second order).

References
----------
T. F. Miller III et al., J. Chem. Phys. 116, 8649 (2002).
A. Dullweber, B. Leimkuhler, R. McLachlan, J. Chem. Phys. 107, 5840 (1997).
H. Kamberaj, R. J. Low, M. P. Neal, J. Chem. Phys. 122, 224114 (2005).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from integrators._rigid_kernels import _axis_turns, _richardson, _rk4
from integrators.base import IntegratorBase, Wraps, check_dt
from integrators.nose_hoover import YOSHIDA_WEIGHTS, chain_half_step
from md.box import reduced_tilt
from md.rigid import RigidBodies
from md.schema import Key, key

#: NO_SQUISH's turns, (axis, fraction of dt): 3(dt/2) 2(dt/2) 1(dt) 2(dt/2) 3(dt/2).
_NO_SQUISH = (np.array([2, 1, 0, 1, 2]), np.array([0.5, 0.5, 1.0, 0.5, 0.5]))
#: DLM's: 1(dt/2) 2(dt/2) 3(dt) 2(dt/2) 1(dt/2).
_DLM = (np.array([0, 1, 2, 1, 0]), np.array([0.5, 0.5, 1.0, 0.5, 0.5]))


def no_squish(q, angular_momenta, inverse_moments, dt):
    """NO_SQUISH free-rotor step: 3(dt/2) 2(dt/2) 1(dt) 2(dt/2) 3(dt/2) on quaternions."""
    out = np.empty((len(q), 4))
    _axis_turns(q, angular_momenta, inverse_moments, float(dt), *_NO_SQUISH, False, out)
    return out


def dlm(q, angular_momenta, inverse_moments, dt):
    """DLM free-rotor step: 1(dt/2) 2(dt/2) 3(dt) 2(dt/2) 1(dt/2) on rotation matrices."""
    out = np.empty((len(q), 4))
    _axis_turns(q, angular_momenta, inverse_moments, float(dt), *_DLM, True, out)
    return out


def richardson(q, angular_momenta, inverse_moments, dt):
    """Richardson-iterated quaternion step: 2 q(two half Euler steps) - q(one full step)."""
    out = np.empty((len(q), 4))
    _richardson(q, angular_momenta, inverse_moments, float(dt), out)
    return out


def rk4(q, angular_momenta, inverse_moments, dt):
    """RK4 on dq/dt = 1/2 (0, omega(q)) q at fixed space-frame L, renormalised at the end."""
    out = np.empty((len(q), 4))
    _rk4(q, angular_momenta, inverse_moments, float(dt), out)
    return out


#: The rotational methods by config name, and their order on the free rotor.
ROTATIONS = {"no_squish": no_squish, "dlm": dlm, "richardson": richardson, "rk4": rk4}
ROTATION_ORDERS = {"no_squish": 2, "dlm": 2, "richardson": 2, "rk4": 4}

ROTATION = Key(
    "rotation",
    "string",
    "no_squish",
    choices=tuple(ROTATIONS),
    doc="The rotational integrator: NO_SQUISH (LAMMPS fix rigid/nve), the DLM splitting, "
    "Richardson-iterated quaternions (LAMMPS fix rigid) or RK4 on quaternions.",
)


@dataclass(frozen=True)
class RigidConfig:
    """``[rigid]``: rigid bodies, the keys :mod:`md.config` reads (see :mod:`md.rigid`)."""

    bodies: str = key(
        "molecules",
        "string",
        choices=("molecules", "template"),
        doc="Which atoms make a body: `'molecules'`, one body per molecule id of a LAMMPS "
        "data file's molecule column (as `fix rigid ... molecule`), else per bonded cluster "
        "of the topology; atoms of molecule id 0 stay free. `'template'`: a copy of `template` "
        "on every atom of the system (a lattice's sites, as HOOMD-blue's body types).",
    )
    template: tuple | None = key(
        None,
        "list of positions",
        doc="With `bodies = 'template'`: the constituents' positions [[x, y, z], ...] "
        "(two or more, any origin: centred on each site by their centre of mass).",
        default_doc="none",
    )
    template_masses: float | tuple | None = key(
        None,
        "number or list",
        doc="The constituents' masses: one for all, or one per template position.",
        default_doc="the site's mass",
    )
    orientation: str = key(
        "random",
        "string",
        choices=("random", "aligned"),
        doc="With a template: each copy turned at random (from the top-level seed), or all "
        "aligned with the template's axes.",
    )
    rotation: str = key(
        "no_squish",
        "string",
        choices=tuple(ROTATIONS),
        doc="The rotational integrator, while `[integrator]` (velocity Verlet, or Langevin "
        "Bussi or Nose-Hoover chains on every momentum) moves the "
        "centres and free atoms: NO_SQUISH, the DLM splitting, Richardson-iterated "
        "quaternions or RK4 on quaternions.",
    )
    exclude: bool = key(
        True,
        "boolean",
        doc="Leave the pairs inside one body out of the neighbour list, as LAMMPS's "
        "`neigh_modify exclude molecule/intra` does (they move no body; the potential "
        "energy then holds the pairs between bodies and free atoms alone). false keeps "
        "them and their constant energy, as LAMMPS does without `neigh_modify exclude`.",
    )


#: The ``[integrator]`` types that move bodies (each has its class here).
RIGID_TAKERS = ("verlet", "velocity_verlet", "langevin", "bussi", "nose_hoover_chain", "nhc")


def checked_rigid(
    record: RigidConfig, integrator_type: str, integrator_values, barostat=None
) -> RigidConfig:
    """``record`` with its template as a tuple of (x, y, z); ValueError ``(key, message)``
    for a template that does not fit ``bodies`` or its masses, and for what bodies cannot
    be combined with (yet): another integrator, rigid bonds, ``fix_com = false``, a
    barostat (``barostat``: its config entry, with ``type`` and ``values``) other than
    c_rescale or Berendsen (MTK)."""
    if (record.bodies == "template") != (record.template is not None):
        raise ValueError(
            "template",
            "give a template exactly when bodies = 'template' (the constituents' positions)",
        )
    if record.template is not None:
        try:
            positions = [[float(x) for x in row] for row in record.template]
            masses = record.template_masses
            masses = None if masses is None else np.asarray(masses, dtype=float)
        except (TypeError, ValueError):
            raise ValueError(
                "template", f"must be a list of [x, y, z] numbers, got {record.template!r}"
            ) from None
        if len(positions) < 2 or any(len(row) != 3 for row in positions):
            raise ValueError(
                "template", f"needs two or more [x, y, z] positions, got {record.template!r}"
            )
        if masses is not None and masses.ndim == 1 and len(masses) != len(positions):
            raise ValueError(
                "template_masses", f"{len(masses)} masses for {len(positions)} template positions"
            )
        record = replace(record, template=tuple(map(tuple, positions)))
    elif record.template_masses is not None:
        raise ValueError("template_masses", "applies only with bodies = 'template'")
    if integrator_type not in RIGID_TAKERS:
        raise ValueError(
            "rotation",
            "rigid bodies move by velocity Verlet, Langevin, Bussi or Nose-Hoover chains for "
            "now: set [integrator] type = 'velocity_verlet', 'langevin', 'bussi' or "
            f"'nose_hoover_chain' (got {integrator_type!r})",
        )
    if integrator_values.get("fix_com") is False:
        raise ValueError("bodies", "[integrator] fix_com = false does not apply to bodies")
    if "constraints" in integrator_values:
        raise ValueError("bodies", "rigid bodies and [integrator.constraints] do not mix (yet)")
    if barostat is not None and barostat.type not in ("c_rescale", "berendsen"):
        raise ValueError(
            "rotation",
            "rigid bodies take a c_rescale or berendsen [barostat] (it moves their centres); "
            f"not {barostat.type} (yet)",
        )
    return record


class RigidNVE(IntegratorBase):
    """Velocity Verlet for body centres and free atoms, ``rotation`` for orientations.

    Parameters
    ----------
    dt : float
        Time step [time].
    bodies : md.rigid.RigidBodies
        The bodies; their arrays are the integrator's state and move in place.
    rotation : str
        A name in :data:`ROTATIONS`.
    exclude : bool
        Leave the pairs inside each body out of the neighbour list (``pair_groups``:
        each atom's body, -1 for a free atom, which :class:`md.simulation.Simulation`
        hands to its force field; LAMMPS's ``neigh_modify exclude molecule/intra``).
        Forces within a rigid body move nothing; left out, they are not computed, and
        the potential energy holds only the pairs between bodies and free atoms.

    Examples
    --------
    >>> from md.state import State
    >>> state = State(positions=[[0, 0, 0], [1, 0, 0], [0, 2, 0]], velocities=np.zeros((3, 3)),
    ...               masses=[1, 1, 1], box=[10, 10, 10], pbc=[True] * 3)
    >>> RigidNVE(0.01, RigidBodies.from_molecules(state, [1, 1, 1])).describe()["rotation"]
    'no_squish'
    """

    order = 2
    #: Whether the total momentum is conserved (then 3 fewer degrees of freedom).
    conserves_momentum = True

    def __init__(
        self, dt: float, bodies: RigidBodies, rotation: str = "no_squish", exclude: bool = True
    ) -> None:
        self.dt = check_dt(dt)
        if rotation not in ROTATIONS:
            raise ValueError(f"rotation must be one of {', '.join(ROTATIONS)}, got {rotation!r}")
        self.rotation = rotation
        self.bodies = bodies
        self.exclude = bool(exclude)
        self._turn = ROTATIONS[rotation]

    @property
    def pair_groups(self) -> NDArray[np.int64] | None:
        """Each atom's body (-1: free) when the pairs inside bodies are left out, else None
        (the :class:`integrators.base.GroupsPairs` hook)."""
        return self.bodies.body_of if self.exclude else None

    def _kick(self, state, forces, half: float) -> None:
        bodies = self.bodies
        free = bodies.free
        state.velocities[free] += half * forces[free] / state.masses[free, None]
        force, torque = bodies.force_torque(forces)
        bodies.momenta += half * force
        bodies.angular_momenta += half * torque

    def step(self, state, forcefield) -> None:
        bodies = self.bodies
        half = 0.5 * self.dt
        self._kick(state, forcefield.compute(state, virial=False).forces, half)
        free = bodies.free
        state.positions[free] += self.dt * state.velocities[free]
        bodies.centres += self.dt * bodies.momenta / bodies.masses[:, None]
        bodies.quaternions[:] = self._turn(
            bodies.quaternions, bodies.angular_momenta, bodies.inverse_moments, self.dt
        )
        bodies.place(state)
        self._kick(state, forcefield.compute(state, virial=False).forces, half)
        bodies.place(state)
        self.end_step(state)

    def scale_cell(self, state, mu, velocities: bool) -> None:
        """A barostat's move: the cell, free atoms and body centres by ``mu`` (a scale
        factor, or a (3, 3) deformation r -> r mu), the bodies keeping their shapes and
        orientations; with ``velocities`` the free atoms' velocities and the centres'
        momenta by its inverse (see :class:`integrators.base.ScalesCell`)."""
        bodies = self.bodies
        free = bodies.free
        if np.ndim(mu) == 0:
            state.box = state.box * mu
            state.tilt = state.tilt * mu
            state.positions[free] *= mu
            bodies.centres *= mu
            if velocities:
                state.velocities[free] /= mu
                bodies.momenta /= mu
        else:
            mu = np.asarray(mu, dtype=np.float64)
            cell = state.cell @ mu
            state.box = np.diag(cell).copy()
            state.tilt = reduced_tilt(state.box, cell[[1, 2, 2], [0, 0, 1]], state.pbc)
            state.positions[free] = state.positions[free] @ mu
            bodies.centres[:] = bodies.centres @ mu
            if velocities:
                inverse = np.linalg.inv(mu).T
                state.velocities[free] = state.velocities[free] @ inverse
                bodies.momenta[:] = bodies.momenta @ inverse
        bodies.place(state)

    def thermo_terms(self, state, result) -> dict:
        """Degrees of freedom of bodies and free atoms, the rigid-body virial (see
        :meth:`md.rigid.RigidBodies.virial_correction`), and the translational and
        rotational temperatures (in kB = 1 units of energy per degree of freedom, scaled
        by the Simulation)."""
        bodies = self.bodies
        terms = {"n_dof": bodies.n_dof(self.conserves_momentum)}
        if result.virial is not None:
            terms["virial"] = bodies.virial_correction(state, result.forces)
        translational, rotational = bodies.kinetic_energies(state)
        n_rot = 3 * bodies.n_bodies - int(np.sum(bodies.linear))
        n_trans = terms["n_dof"] - n_rot
        terms["kinetic_split"] = {
            "translational": (translational, n_trans),
            "rotational": (rotational, n_rot),
        }
        return terms

    def get_state(self) -> dict:
        return self.bodies.get_state()

    def set_state(self, saved: dict) -> None:
        self.bodies.set_state(saved)

    def describe(self) -> dict:
        return {"type": "rigid_nve", "dt": self.dt, "rotation": self.rotation}


class _RigidBath(RigidNVE):
    """What the heat baths on bodies share: the BAOAB step (half kick, half drift of the
    centres, free atoms and ``rotation`` over dt/2, the bath's O step, half drift, half
    kick), the random stream of step n drawn from ``(seed, n)`` alone (so a resumed run
    draws the same), and its saved entropy."""

    stochastic = True
    thermostat = True

    def __init__(
        self, dt: float, bodies: RigidBodies, rotation: str, kT: float, seed, exclude: bool = True
    ) -> None:
        super().__init__(dt, bodies, rotation, exclude)
        self.kT = float(kT)
        self.reservoir = 0.0  # the heat the bath took out [energy]
        if not self.kT >= 0:
            raise ValueError(f"kT must be >= 0, got {kT!r}")
        # The seed's entropy as 32-bit words (fresh entropy without a seed), kept for resumes.
        words = []
        for value in np.atleast_1d(np.random.SeedSequence(seed).entropy).tolist():
            value = int(value)
            words += [
                (value >> (32 * k)) & 0xFFFFFFFF
                for k in range(max(1, -(-value.bit_length() // 32)))
            ]
        self.entropy = np.array(words, dtype=np.int64)

    def _random(self, state) -> np.random.Generator:
        return np.random.default_rng([*self.entropy.tolist(), state.step + 1])

    def _drift(self, state, span: float) -> None:
        bodies = self.bodies
        free = bodies.free
        state.positions[free] += span * state.velocities[free]
        bodies.centres += span * bodies.momenta / bodies.masses[:, None]
        bodies.quaternions[:] = self._turn(
            bodies.quaternions, bodies.angular_momenta, bodies.inverse_moments, span
        )

    def _thermalise(self, state) -> None:
        raise NotImplementedError

    def step(self, state, forcefield) -> None:
        half = 0.5 * self.dt
        self._kick(state, forcefield.compute(state, virial=False).forces, half)
        self._drift(state, half)
        before = sum(self.bodies.kinetic_energies(state))
        self._thermalise(state)
        self.reservoir -= sum(self.bodies.kinetic_energies(state)) - before
        self._drift(state, half)
        self.bodies.place(state)
        self._kick(state, forcefield.compute(state, virial=False).forces, half)
        self.bodies.place(state)
        self.end_step(state)

    def thermo_terms(self, state, result) -> dict:
        """:class:`RigidNVE`'s, and the heat the bath took out as ``reservoir_energy``."""
        terms = super().thermo_terms(state, result)
        terms["reservoir_energy"] = self.reservoir
        return terms

    def get_state(self) -> dict:
        saved = super().get_state()
        saved["entropy"] = self.entropy.copy()
        saved["reservoir"] = np.array([self.reservoir])
        return saved

    def set_state(self, saved: dict) -> None:
        super().set_state(saved)
        self.entropy = np.asarray(saved["entropy"], dtype=np.int64).copy()
        self.reservoir = float(np.asarray(saved["reservoir"]).reshape(-1)[0])


class RigidLangevin(_RigidBath):
    """Langevin dynamics of bodies and free atoms, BAOAB: half kick, half drift (centres,
    free atoms and ``rotation`` over dt/2), Ornstein-Uhlenbeck on every momentum, half
    drift, half kick.

    The O step draws the free atoms' and the centres' momenta toward the Maxwell
    distribution at ``kT`` with rate ``friction`` [1/time], and each body's angular
    momentum in its principal frame with rate ``rotational_friction`` (default
    ``friction``), component k with variance I_k kT (none along a linear body's axis):
    exact for its part, so both temperatures relax to the target. The noise of step n
    comes from ``(seed, n)`` alone, so a resumed run draws the same.

    References
    ----------
    B. Leimkuhler, C. Matthews, Appl. Math. Res. Express 2013, 34 (BAOAB).
    R. L. Davidchack, T. E. Ouldridge, M. V. Tretyakov, J. Chem. Phys. 142, 144114 (2015)
    (Langevin thermostats for rigid bodies).
    """

    conserves_momentum = False

    def __init__(
        self,
        dt: float,
        bodies: RigidBodies,
        rotation: str = "no_squish",
        kT: float = 1.0,
        friction: float = 1.0,
        rotational_friction: float | None = None,
        seed=None,
        exclude: bool = True,
    ) -> None:
        super().__init__(dt, bodies, rotation, kT, seed, exclude)
        self.friction = float(friction)
        self.rotational_friction = (
            self.friction if rotational_friction is None else float(rotational_friction)
        )
        if not (self.friction >= 0 and self.rotational_friction >= 0):
            raise ValueError("the frictions must be >= 0")

    def _thermalise(self, state) -> None:
        bodies = self.bodies
        rng = self._random(state)
        c = np.exp(-self.friction * self.dt)
        free = bodies.free
        sigma = np.sqrt((1 - c * c) * self.kT / state.masses[free])[:, None]
        state.velocities[free] = c * state.velocities[free] + sigma * rng.standard_normal(
            (len(free), 3)
        )
        sigma = np.sqrt((1 - c * c) * self.kT * bodies.masses)[:, None]
        bodies.momenta[:] = c * bodies.momenta + sigma * rng.standard_normal((bodies.n_bodies, 3))
        c = np.exp(-self.rotational_friction * self.dt)
        a = bodies.matrices()
        body = np.einsum("bji,bj->bi", a, bodies.angular_momenta)
        sigma = np.sqrt((1 - c * c) * self.kT * bodies.moments)  # 0 along a linear axis
        body = np.where(bodies.moments > 0, c * body, 0.0)
        body += sigma * rng.standard_normal((bodies.n_bodies, 3))
        bodies.angular_momenta[:] = np.einsum("bij,bj->bi", a, body)

    def describe(self) -> dict:
        return {
            "type": "rigid_langevin",
            "dt": self.dt,
            "rotation": self.rotation,
            "kT": self.kT,
            "friction": self.friction,
            "rotational_friction": self.rotational_friction,
        }


class RigidBussi(_RigidBath):
    """Bussi-Donadio-Parrinello stochastic velocity rescaling of bodies and free atoms:
    the BAOAB step with an O that scales every momentum (free atoms', centres', angular)
    by one factor, drawn so that the kinetic energy follows the canonical distribution
    with relaxation time ``tau`` [time] (the rotational kinetic energy is quadratic in the
    angular momentum at fixed orientation, so it scales with the rest). A zero total
    momentum stays zero, so 3 degrees of freedom are removed.

    References
    ----------
    G. Bussi, D. Donadio, M. Parrinello, J. Chem. Phys. 126, 014101 (2007).
    """

    conserves_momentum = True

    def __init__(
        self,
        dt: float,
        bodies: RigidBodies,
        rotation: str = "no_squish",
        kT: float = 1.0,
        tau: float = 1.0,
        seed=None,
        exclude: bool = True,
    ) -> None:
        super().__init__(dt, bodies, rotation, kT, seed, exclude)
        self.tau = float(tau)
        if not self.tau > 0:
            raise ValueError(f"tau must be > 0, got {tau!r}")

    def _thermalise(self, state) -> None:
        bodies = self.bodies
        kinetic = sum(bodies.kinetic_energies(state))
        n_dof = bodies.n_dof(self.conserves_momentum)
        if kinetic <= 0 or n_dof < 1:
            return  # nothing moves: no factor scales it up
        rng = self._random(state)
        c = np.exp(-self.dt / self.tau)
        target = 0.5 * n_dof * self.kT
        r1 = rng.standard_normal()
        rest = 2.0 * rng.standard_gamma(0.5 * (n_dof - 1)) if n_dof > 1 else 0.0
        ratio = target / (n_dof * kinetic)
        alpha2 = c + (1 - c) * ratio * (r1 * r1 + rest) + 2 * r1 * np.sqrt(c * (1 - c) * ratio)
        sign = np.sign(r1 + np.sqrt(c / ((1 - c) * ratio))) if c < 1 else 1.0
        alpha = sign * np.sqrt(max(alpha2, 0.0))
        state.velocities[bodies.free] *= alpha
        bodies.momenta *= alpha
        bodies.angular_momenta *= alpha

    def describe(self) -> dict:
        return {
            "type": "rigid_bussi",
            "dt": self.dt,
            "rotation": self.rotation,
            "kT": self.kT,
            "tau": self.tau,
        }


class RigidNoseHoover(RigidNVE):
    """Nose-Hoover chains on bodies and free atoms: the chain's half step (Martyna,
    Tuckerman, Tobias and Klein's, with the Suzuki-Yoshida composition of
    :func:`integrators.nose_hoover.chain_half_step`) scales every momentum (free atoms',
    centres', angular) by one factor before and after the NVE step, driven by the total
    kinetic energy over the bodies' degrees of freedom. ``thermo_terms`` adds the chain's
    energy, so ``conserved_energy`` measures the integration error. The masses are
    Q_1 = n_dof kT tau^2 and Q_j = kT tau^2.

    References
    ----------
    G. J. Martyna, M. E. Tuckerman, D. J. Tobias, M. L. Klein, Mol. Phys. 87, 1117 (1996);
    H. Kamberaj, R. J. Low, M. P. Neal, J. Chem. Phys. 122, 224114 (2005) (LAMMPS's
    fix rigid/nvt).
    """

    thermostat = True  # a heat bath with an energy: the trajectory keeps conserved_energy

    def __init__(
        self,
        dt: float,
        bodies: RigidBodies,
        rotation: str = "no_squish",
        kT: float = 1.0,
        tau: float = 1.0,
        chain_length: int = 3,
        n_substeps: int = 1,
        exclude: bool = True,
    ) -> None:
        super().__init__(dt, bodies, rotation, exclude)
        self.kT, self.tau = float(kT), float(tau)
        if not (self.kT > 0 and self.tau > 0):
            raise ValueError("kT and tau must be > 0")
        self.chain_length, self.n_substeps = int(chain_length), int(n_substeps)
        self.xi = np.zeros(self.chain_length)
        self.v_xi = np.zeros(self.chain_length)

    def _masses(self, n_dof: int) -> np.ndarray:
        q = np.full(self.chain_length, self.kT * self.tau**2)
        q[0] *= n_dof
        return q

    def _chain(self, state, duration: float) -> None:
        bodies = self.bodies
        n_dof = bodies.n_dof(self.conserves_momentum)
        kinetic = sum(bodies.kinetic_energies(state))
        scale = chain_half_step(
            self.xi,
            self.v_xi,
            self._masses(n_dof),
            kinetic,
            float(n_dof),
            self.kT,
            duration,
            YOSHIDA_WEIGHTS,
            self.n_substeps,
        )
        state.velocities[bodies.free] *= scale
        bodies.momenta *= scale
        bodies.angular_momenta *= scale

    def step(self, state, forcefield) -> None:
        self._chain(state, 0.5 * self.dt)
        super().step(state, forcefield)
        self._chain(state, 0.5 * self.dt)
        self.bodies.place(state)

    def thermo_terms(self, state, result) -> dict:
        terms = super().thermo_terms(state, result)
        n_dof = terms["n_dof"]
        q = self._masses(n_dof)
        terms["reservoir_energy"] = float(
            0.5 * np.dot(q, self.v_xi**2)
            + n_dof * self.kT * self.xi[0]
            + self.kT * self.xi[1:].sum()
        )
        return terms

    def get_state(self) -> dict:
        saved = super().get_state()
        saved["xi"], saved["v_xi"] = self.xi.copy(), self.v_xi.copy()
        return saved

    def set_state(self, saved: dict) -> None:
        super().set_state(saved)
        self.xi[:] = np.asarray(saved["xi"], dtype=np.float64)
        self.v_xi[:] = np.asarray(saved["v_xi"], dtype=np.float64)

    def describe(self) -> dict:
        return {
            "type": "rigid_nose_hoover_chain",
            "dt": self.dt,
            "rotation": self.rotation,
            "kT": self.kT,
            "tau": self.tau,
            "chain_length": self.chain_length,
            "n_substeps": self.n_substeps,
        }


def bodies_of(integrator) -> RigidBodies | None:
    """The rigid bodies an integrator moves (also under a barostat's ``inner``), or None."""
    while not isinstance(integrator, RigidNVE):
        if not isinstance(integrator, Wraps):
            return None
        integrator = integrator.inner
    return integrator.bodies


__all__ = [
    "RIGID_TAKERS",
    "ROTATION",
    "ROTATIONS",
    "ROTATION_ORDERS",
    "RigidBussi",
    "RigidConfig",
    "RigidLangevin",
    "RigidNVE",
    "RigidNoseHoover",
    "bodies_of",
    "checked_rigid",
]
