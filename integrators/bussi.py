"""Stochastic velocity rescaling (Bussi, Donadio and Parrinello) around velocity Verlet."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from integrators._thermostat import FIX_COM, SEED, TAU, TEMPERATURE, Thermostat, make_rng
from integrators.base import DT
from integrators.rattle import CONSTRAINTS, constrained_verlet_step
from md._checks import positive
from md.parallel import global_sum
from md.thermo import kinetic_energy


class Bussi(Thermostat):
    """Canonical sampling by stochastic velocity rescaling (the "CSVR" thermostat).

    Half a thermostat step, a velocity Verlet step, half a thermostat step.
    The thermostat moves the kinetic energy K by the exact solution over
    dt/2 of the stochastic differential equation

        dK = (K0 - K) dt / tau + 2 sqrt(K K0 / n_dof) dW / sqrt(tau),
        K0 = n_dof kB T / 2,

    and rescales all velocities by the common factor sqrt(K_new / K), so it
    leaves the direction of the velocity vector (and the zero total
    momentum and the rigid bonds) alone. The stationary distribution is
    canonical, and the dynamics approaches plain velocity Verlet as tau
    grows. The energy the rescalings add is booked in ``reservoir_energy``;
    kinetic + potential + reservoir energy (the "effective energy") is
    conserved up to the integration error, a check on dt.

    Parameters
    ----------
    dt : float
        Time step [time].
    temperature : float
        Target temperature [temperature], >= 0.
    tau : float
        Relaxation time of the kinetic energy [time], > 0; ~100 dt is usual.
    kB : float
        Boltzmann constant [energy/temperature].
    seed : int, list of int, numpy Generator or None
        Seed of the random stream; :meth:`get_state` includes its state.
    constraints : BondConstraints or array_like of int, shape (B, 2), optional
        Rigid bonds, kept by SHAKE and RATTLE in the velocity Verlet step.
    fix_com : bool
        Count 3 fewer degrees of freedom for the conserved total momentum
        (the default; False for systems in an external field).

    Examples
    --------
    >>> Bussi(dt=0.005, temperature=1.0, tau=0.5, seed=1).describe()["tau"]
    0.5

    References
    ----------
    G. Bussi, D. Donadio, M. Parrinello, J. Chem. Phys. 126, 014101 (2007).
    """

    stochastic = True
    CONFIG_KEYS = (
        DT,
        TEMPERATURE,
        replace(TAU, doc="The relaxation time of the kinetic energy; about 100 `dt` is usual."),
        SEED,
        CONSTRAINTS,
        FIX_COM,
    )

    def __init__(
        self,
        dt: float,
        temperature: float,
        tau: float,
        kB: float = 1.0,
        seed=None,
        constraints=None,
        fix_com: bool = True,
    ) -> None:
        super().__init__(dt, temperature, kB, constraints, fix_com)
        self.tau = positive(tau, "tau")
        self.seed = seed if not isinstance(seed, np.random.Generator) else None
        self.rng = make_rng(seed)

    def step(self, state, forcefield) -> None:
        self._prepare(state)
        n_dof = self.degrees_of_freedom(global_sum(state.n_atoms))
        c = math.exp(-0.5 * self.dt / self.tau)
        self._rescale(state, n_dof, c)
        constrained_verlet_step(state, forcefield, self.dt, self.constraints)
        self._rescale(state, n_dof, c)
        self._advance(state)

    def _rescale(self, state, n_dof: int, c: float) -> None:
        kinetic = global_sum(kinetic_energy(state.velocities, state.masses))
        alpha = self.rescale_factor(kinetic, n_dof, c)
        if alpha != 1.0:
            state.velocities *= alpha

    def rescale_factor(self, kinetic: float, n_dof: int, c: float) -> float:
        """The factor of one half-step's velocity rescaling at kinetic energy ``kinetic``,
        drawn from the integrator's stream, the bath's energy updated (1.0, and nothing
        drawn, for a system at rest). The GPU path (``md.cuda``) sums the kinetic energy on
        the device and calls this, so its run follows the CPU's stream."""
        if kinetic <= 0.0 or n_dof <= 0:
            return 1.0  # nothing to rescale: a system at rest stays at rest
        target = 0.5 * n_dof * self.kT
        # Exact update of K over the interval: K_new = (sqrt(c K) + s r)^2 + s^2 chi2(n - 1),
        # s^2 = (1 - c) K0 / n_dof; alpha keeps the sign of sqrt(c K) + s r.
        s = math.sqrt((1.0 - c) * target / n_dof)
        r = self.rng.standard_normal()
        rest = 2.0 * self.rng.standard_gamma(0.5 * (n_dof - 1)) if n_dof > 1 else 0.0
        root = math.sqrt(c * kinetic) + s * r
        new_kinetic = root * root + s * s * rest
        alpha = math.copysign(math.sqrt(new_kinetic / kinetic), root)
        self.reservoir -= new_kinetic - kinetic
        return alpha

    def describe(self) -> dict:
        return self._describe("bussi", tau=self.tau, seed=self.seed)


__all__ = ["Bussi"]
