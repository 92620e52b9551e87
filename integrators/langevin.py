"""Langevin dynamics with the BAOAB splitting (Leimkuhler and Matthews)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from integrators._kernels import _drift, kick
from integrators._noise import atom_gaussians, gaussian_noise, seed_key
from integrators._thermostat import FIX_COM, SEED, TEMPERATURE, Thermostat
from integrators.base import DT
from integrators.rattle import CONSTRAINTS
from md._checks import positive
from md.parallel import global_sum
from md.schema import REQUIRED, Key


class Langevin(Thermostat):
    """Langevin thermostat integrated by BAOAB: kick, drift, friction + noise, drift, kick.

    Each step::

        B: v += dt/2 F/m
        A: x += dt/2 v
        O: v  = c v + sqrt((1 - c^2) kB T / m) xi,   c = exp(-friction dt),  xi ~ N(0, 1)
        A: x += dt/2 v
        B: v += dt/2 F(x)/m

    One force evaluation per step. The configurational distribution is
    sampled with an error of order dt^2 that is much smaller than other
    splittings' (exact for a harmonic system at any stable dt). The
    end-of-step velocities in ``state.velocities`` read a kinetic
    temperature low by about ``dt^2 <|F|^2/m> / (12 N kB T)`` (exactly
    1 - dt^2 k / 4m for a harmonic oscillator; about 0.2 % for the LJ
    liquid at T = 1, dt = 0.005).

    With ``fix_com`` (the default, for systems whose forces sum to zero) the
    noise of every step has zero total momentum, so the centre of mass is
    not thermalised, matching the 3N - 3 degrees of freedom of the
    temperature; its velocity (zero from :func:`md.maxwell_boltzmann`) only
    decays with the friction. Set ``fix_com=False`` for systems in an
    external field. With ``constraints`` every A ends with SHAKE and the
    velocities are projected onto the constraint surface (RATTLE) before and
    after O and at the end of the step: the geodesic form of BAOAB with one
    drift per A.

    The noise is counter-based: atom i's three numbers at step n are
    Philox4x64-10 of the counter (n, i) under a key drawn from ``seed``
    (:mod:`integrators._noise`), so the trajectory depends on the seed alone,
    not on the order of the atoms or on how a decomposed run splits them over
    MPI ranks (``state.ids`` names each atom), and a checkpointed run (which
    keeps the key) continues with the same noise. (Before this stream,
    Langevin drew from numpy's sequential generator: a run resumed from a
    checkpoint written then continues with the new stream.)
    ``reservoir_energy`` is minus the kinetic energy the O steps added
    (the heat taken by the bath).

    Parameters
    ----------
    dt : float
        Time step [time].
    temperature : float
        Target temperature [temperature], >= 0 (0: pure friction).
    friction : float
        Friction coefficient gamma [1/time], >= 0 (0: velocity Verlet). About
        1/(100 dt) disturbs the dynamics little; 1/dt or more is overdamped.
    kB : float
        Boltzmann constant [energy/temperature] (1 in reduced units; ``md.units.kB``
        in metal units).
    seed : int, list of int, numpy Generator or None
        Seed of the noise's key (None: fresh entropy, not reproducible; a
        Generator: the key is drawn from it).
    constraints : BondConstraints or array_like of int, shape (B, 2), optional
        Rigid bonds (see :class:`integrators.rattle.BondConstraints`).
    fix_com : bool
        Keep the total momentum out of the noise (see above).

    Examples
    --------
    >>> Langevin(dt=0.005, temperature=1.0, friction=1.0, seed=1).describe()["friction"]
    1.0

    References
    ----------
    B. Leimkuhler, C. Matthews, Appl. Math. Res. Express 2013, 34 (2013);
    B. Leimkuhler, C. Matthews, Proc. R. Soc. A 472, 20160138 (2016)
    (constrained BAOAB).
    """

    stochastic = True
    CONFIG_KEYS = (
        DT,
        TEMPERATURE,
        Key(
            "friction",
            "number",
            REQUIRED,
            unit="1/time",
            minimum=0.0,
            doc="The friction coefficient gamma: 0 is velocity Verlet, about 1/(100 dt) "
            "disturbs the dynamics little, 1/dt or more is overdamped.",
        ),
        SEED,
        CONSTRAINTS,
        FIX_COM,
    )

    def __init__(
        self,
        dt: float,
        temperature: float,
        friction: float,
        kB: float = 1.0,
        seed=None,
        constraints=None,
        fix_com: bool = True,
    ) -> None:
        super().__init__(dt, temperature, kB, constraints, fix_com)
        self.friction = positive(friction, "friction", allow_zero=True)
        self.seed = seed if not isinstance(seed, np.random.Generator) else None
        self.key = seed_key(seed)
        self._noise: np.ndarray | None = None
        self._ids = np.zeros(0, dtype=np.int64)

    @classmethod
    def coupling(cls, tau: float) -> dict:
        """Langevin couples through its friction: 1 / ``tau``."""
        return {"friction": 1.0 / tau}

    def step(self, state, forcefield) -> None:
        self._prepare(state)
        dt, half = self.dt, 0.5 * self.dt
        constraints = self.constraints
        masses = state.masses
        inverse_masses = 1.0 / masses
        step = state.step + 1
        if self._noise is None or self._noise.shape != state.velocities.shape:
            self._noise = np.empty_like(state.velocities)
        c = math.exp(-self.friction * dt)
        sigmas = np.sqrt((1.0 - c * c) * self.kT * inverse_masses)

        # With constraints, a velocity component off the constraint surface before a drift
        # is exactly what SHAKE's correction removes, so projections (RATTLE) are needed
        # only where the velocities are used otherwise: around O, for its heat, and at the end.
        forces = forcefield.compute(state, virial=False).forces
        kick(state.velocities, forces, inverse_masses, half)  # B
        self._drift(state, half, inverse_masses, step, project=True)  # A
        gaussian_noise(self.key, step, self._atom_ids(state), self._noise)  # O
        before = _kinetic(state.velocities, masses)
        # The noise's momentum and mass, and the atom count, over every rank.
        total = global_sum(np.array([*_scale_noise(self._noise, masses, sigmas), state.n_atoms]))
        drift = total[:3] / total[3] if self.fix_com and total[4] > 1 else np.zeros(3)
        _relax(state.velocities, self._noise, c, drift)
        if constraints is not None:
            constraints.rattle(state, dt, inverse_masses, step)
        self.reservoir -= global_sum(_kinetic(state.velocities, masses) - before)
        self._drift(state, half, inverse_masses, step, project=False)  # A
        forces = forcefield.compute(state, virial=False).forces
        kick(state.velocities, forces, inverse_masses, half)  # B
        if constraints is not None:
            constraints.rattle(state, dt, inverse_masses, step)
        self._advance(state)

    def _atom_ids(self, state) -> np.ndarray:
        """Each atom's id in the whole system: ``state.ids``, or its index."""
        if state.ids is not None:
            return state.ids
        if self._ids.shape[0] != state.n_atoms:
            self._ids = np.arange(state.n_atoms, dtype=np.int64)
        return self._ids

    def get_state(self) -> dict:
        """As :meth:`Thermostat.get_state`, with the noise's key."""
        saved = super().get_state()
        saved["key"] = [int(word) for word in self.key]
        return saved

    def set_state(self, saved: dict) -> None:
        """As :meth:`Thermostat.set_state`; the key too, if the checkpoint has one (older
        ones, of the sequential stream, do not: the seed's key serves)."""
        super().set_state(saved)
        if "key" in saved:
            self.key = np.array(saved["key"], dtype=np.uint64)

    def _drift(self, state, duration, inverse_masses, step, project) -> None:
        constraints = self.constraints
        if constraints is None:
            _drift(state.positions, state.velocities, duration)
            return
        reference = constraints.reference_buffer
        reference[:] = state.positions
        _drift(state.positions, state.velocities, duration)
        constraints.shake(state, reference, duration, inverse_masses, step)
        if project:
            constraints.rattle(state, self.dt, inverse_masses, step)

    def describe(self) -> dict:
        return self._describe("langevin", friction=self.friction, seed=self.seed)


# ------------------------------------------------------------------- kernels


@njit(cache=True, error_model="numpy")
def _kinetic(velocities, masses):
    """Kinetic energy sum 1/2 m v^2."""
    total = 0.0
    for i in range(velocities.shape[0]):
        total += (
            0.5
            * masses[i]
            * (velocities[i, 0] ** 2 + velocities[i, 1] ** 2 + velocities[i, 2] ** 2)
        )
    return total


@njit(cache=True, error_model="numpy")
def _scale_noise(noise, masses, sigmas):
    """noise_i *= sigma_i in place; return the noise's momentum (px, py, pz) and the mass."""
    px = 0.0
    py = 0.0
    pz = 0.0
    total_mass = 0.0
    for i in range(noise.shape[0]):
        s = sigmas[i]
        noise[i, 0] *= s
        noise[i, 1] *= s
        noise[i, 2] *= s
        px += masses[i] * noise[i, 0]
        py += masses[i] * noise[i, 1]
        pz += masses[i] * noise[i, 2]
        total_mass += masses[i]
    return px, py, pz, total_mass


@njit(cache=True, error_model="numpy")
def _relax(velocities, noise, c, drift):
    """v = c v + noise - drift in place (``drift``: the noise's centre-of-mass velocity, or
    zeros): the O step of BAOAB."""
    for i in range(velocities.shape[0]):
        velocities[i, 0] = c * velocities[i, 0] + noise[i, 0] - drift[0]
        velocities[i, 1] = c * velocities[i, 1] + noise[i, 1] - drift[1]
        velocities[i, 2] = c * velocities[i, 2] + noise[i, 2] - drift[2]


#: The noise of one atom at one step (``integrators._noise.atom_gaussians``), public for the
#: GPU path, which compiles the same function for the device.
noise_of_atom = atom_gaussians

__all__ = ["Langevin", "noise_of_atom"]
