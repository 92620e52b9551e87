"""Berendsen weak-coupling thermostat: for equilibration, not for sampling."""

from __future__ import annotations

import logging
import math
from dataclasses import replace

from integrators._thermostat import FIX_COM, TAU, TEMPERATURE, Thermostat
from integrators.base import DT
from integrators.rattle import CONSTRAINTS, constrained_verlet_step
from md._checks import positive
from md.parallel import global_sum
from md.thermo import kinetic_energy

logger = logging.getLogger(__name__)

#: Bounds of the velocity scale factor per step, against a violent first step.
SCALE_LIMITS = (0.8, 1.25)


class Berendsen(Thermostat):
    """Velocity Verlet with velocities rescaled towards the target temperature.

    After each step the velocities are multiplied by

        lambda = sqrt(1 + (dt / tau) (T0 / T - 1)),  clipped to [0.8, 1.25],

    so the kinetic temperature relaxes exponentially with time constant tau.

    .. warning::
       The Berendsen thermostat does **not** sample the canonical ensemble:
       it suppresses the kinetic-energy fluctuations (their variance tends
       to zero as tau -> dt) and can pump energy into slow modes (the
       "flying ice cube"). Use it to bring a system to temperature, then
       switch to :class:`~integrators.langevin.Langevin`,
       :class:`~integrators.bussi.Bussi` or
       :class:`~integrators.nose_hoover.NoseHooverChain` for production.
       Constructing one logs a warning saying so.

    ``reservoir_energy`` books the energy the rescalings removed, so
    kinetic + potential + reservoir energy is conserved up to the
    integration error.

    Parameters
    ----------
    dt : float
        Time step [time].
    temperature : float
        Target temperature [temperature], >= 0.
    tau : float
        Coupling time [time], > 0 (tau = dt rescales to the target at once).
    kB : float
        Boltzmann constant [energy/temperature].
    constraints : BondConstraints or array_like of int, shape (B, 2), optional
        Rigid bonds, kept by SHAKE and RATTLE.
    fix_com : bool
        Count 3 fewer degrees of freedom for the conserved total momentum.

    Examples
    --------
    >>> Berendsen(dt=0.005, temperature=1.0, tau=0.1).describe()["type"]
    'berendsen'

    References
    ----------
    H. J. C. Berendsen, J. P. M. Postma, W. F. van Gunsteren, A. DiNola,
    J. R. Haak, J. Chem. Phys. 81, 3684 (1984).
    """

    canonical = False
    CONFIG_KEYS = (
        DT,
        TEMPERATURE,
        replace(TAU, doc="The coupling time (`tau` = `dt` rescales to the target at once)."),
        CONSTRAINTS,
        FIX_COM,
    )

    def __init__(
        self,
        dt: float,
        temperature: float,
        tau: float,
        kB: float = 1.0,
        constraints=None,
        fix_com: bool = True,
    ) -> None:
        super().__init__(dt, temperature, kB, constraints, fix_com)
        self.tau = positive(tau, "tau")
        logger.warning(
            "Berendsen thermostat: it does not sample the canonical ensemble (kinetic-energy "
            "fluctuations are suppressed); use it for equilibration and switch to langevin, "
            "bussi or nose_hoover_chain for production"
        )

    def step(self, state, forcefield) -> None:
        self._prepare(state)
        constrained_verlet_step(state, forcefield, self.dt, self.constraints)
        n_dof = self.degrees_of_freedom(global_sum(state.n_atoms))
        kinetic = global_sum(kinetic_energy(state.velocities, state.masses))
        if kinetic > 0.0 and n_dof > 0:
            temperature = 2.0 * kinetic / (n_dof * self.kB)
            factor = 1.0 + self.dt / self.tau * (self.temperature / temperature - 1.0)
            scale = min(max(math.sqrt(max(factor, 0.0)), SCALE_LIMITS[0]), SCALE_LIMITS[1])
            state.velocities *= scale
            self.reservoir -= (scale * scale - 1.0) * kinetic
        self._advance(state)

    def describe(self) -> dict:
        return self._describe("berendsen", tau=self.tau)


__all__ = ["Berendsen"]
