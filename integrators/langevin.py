"""Langevin dynamics with the BAOAB splitting (Leimkuhler and Matthews)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from integrators._kernels import _drift, kick
from integrators._thermostat import FIX_COM, SEED, TEMPERATURE, Thermostat, make_rng
from integrators.base import DT
from integrators.rattle import CONSTRAINTS
from md._checks import positive
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

    The run is reproducible from ``seed``; :meth:`get_state` includes the
    generator's state, so a checkpointed run continues with the same noise.
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
        Seed of the random stream (None: fresh entropy, not reproducible).
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
        Key("friction", "number", REQUIRED, unit="1/time", minimum=0.0,
            doc="The friction coefficient gamma: 0 is velocity Verlet, about 1/(100 dt) "
                "disturbs the dynamics little, 1/dt or more is overdamped."),
        SEED,
        CONSTRAINTS,
        FIX_COM,
    )  # fmt: skip

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
        self.rng = make_rng(seed)
        self._noise: np.ndarray | None = None

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
        fix_com = self.fix_com and state.n_atoms > 1

        # With constraints, a velocity component off the constraint surface before a drift
        # is exactly what SHAKE's correction removes, so projections (RATTLE) are needed
        # only where the velocities are used otherwise: around O, for its heat, and at the end.
        forces = forcefield.compute(state, virial=False).forces
        kick(state.velocities, forces, inverse_masses, half)  # B
        self._drift(state, half, inverse_masses, step, project=True)  # A
        self.rng.standard_normal(out=self._noise)  # O
        before = _kinetic(state.velocities, masses)
        _ornstein_uhlenbeck(state.velocities, self._noise, masses, sigmas, c, fix_com)
        if constraints is not None:
            constraints.rattle(state, dt, inverse_masses, step)
        self.reservoir -= _kinetic(state.velocities, masses) - before
        self._drift(state, half, inverse_masses, step, project=False)  # A
        forces = forcefield.compute(state, virial=False).forces
        kick(state.velocities, forces, inverse_masses, half)  # B
        if constraints is not None:
            constraints.rattle(state, dt, inverse_masses, step)
        self._advance(state)

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
def _ornstein_uhlenbeck(velocities, noise, masses, sigmas, c, fix_com):
    """v = c v + sigma_i xi_i in place; noise (N, 3) holds xi and is overwritten by
    sigma_i xi_i. With fix_com the noise's centre-of-mass velocity is removed first
    (the mass-weighted projection, exact for any masses)."""
    n = velocities.shape[0]
    px = 0.0
    py = 0.0
    pz = 0.0
    total_mass = 0.0
    for i in range(n):
        s = sigmas[i]
        noise[i, 0] *= s
        noise[i, 1] *= s
        noise[i, 2] *= s
        px += masses[i] * noise[i, 0]
        py += masses[i] * noise[i, 1]
        pz += masses[i] * noise[i, 2]
        total_mass += masses[i]
    if fix_com:
        px /= total_mass
        py /= total_mass
        pz /= total_mass
    else:
        px = 0.0
        py = 0.0
        pz = 0.0
    for i in range(n):
        velocities[i, 0] = c * velocities[i, 0] + noise[i, 0] - px
        velocities[i, 1] = c * velocities[i, 1] + noise[i, 1] - py
        velocities[i, 2] = c * velocities[i, 2] + noise[i, 2] - pz


__all__ = ["Langevin"]
