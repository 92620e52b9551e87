"""Velocity Verlet: the symplectic, time-reversible workhorse of NVE MD."""

from __future__ import annotations

from integrators._kernels import (
    SERIAL_ATOMS,
    kick,
    kick_by_mass,
    kick_drift,
    kick_drift_by_mass,
)
from integrators.base import IntegratorBase, amplification_roots, check_dt
from potentials.base import FusesVerletStep

#: Per force source class, whether it meets ``FusesVerletStep`` (asked once: a
#: runtime-checkable protocol's ``isinstance`` costs microseconds a call).
_FUSES: dict[type, bool] = {}


class VelocityVerlet(IntegratorBase):
    """Velocity Verlet integrator (kick, drift, force, kick).

    One force evaluation per step: the forces at the end of a step are the
    ForceField's cached result at the start of the next.

    Parameters
    ----------
    dt : float
        Time step [time] (in ASE units for metal systems, e.g. ``2 * ase.units.fs``).

    Examples
    --------
    >>> VelocityVerlet(dt=0.005).dt
    0.005

    References
    ----------
    W. C. Swope, H. C. Andersen, P. H. Berens, K. R. Wilson,
    J. Chem. Phys. 76, 637 (1982).
    """

    order = 2
    distributed = True

    def __init__(self, dt: float) -> None:
        self.dt = check_dt(dt)

    def step(self, state, forcefield) -> None:
        half = 0.5 * self.dt
        masses = state.masses
        if masses.shape[0] < SERIAL_ATOMS:
            # A force field that can make the whole step in one compiled call while the
            # list holds (md.ForceField.verlet_step: 2 done, 1 kicked and drifted, 0
            # nothing done); else one pass each, called directly, 1/m taken inside (the
            # same bits): a small box's step makes no array of inverse masses.
            fuses = _FUSES.get(type(forcefield))
            if fuses is None:
                fuses = _FUSES[type(forcefield)] = isinstance(forcefield, FusesVerletStep)
            done = forcefield.verlet_step(state, half, self.dt) if fuses else 0
            if done == 2:
                self.end_step(state)
                return
            if done == 0:
                forces = forcefield.compute(state, virial=False).forces
                kick_drift_by_mass(state.positions, state.velocities, forces, masses, half, self.dt)
            forces = forcefield.compute(state, virial=False).forces
            kick_by_mass(state.velocities, forces, masses, half)
            self.end_step(state)
            return
        # A force field whose step runs on the threads too (md.ForceField.verlet_step's
        # mixed precision: its passes fused, threaded) makes it; ``threaded`` (passed by
        # position, as every such method takes it) says that this step's passes would be.
        fuses = _FUSES.get(type(forcefield))
        if fuses is None:
            fuses = _FUSES[type(forcefield)] = isinstance(forcefield, FusesVerletStep)
        done = forcefield.verlet_step(state, half, self.dt, True) if fuses else 0
        if done == 2:
            self.end_step(state)
            return
        inverse_masses = 1.0 / masses
        if done == 0:
            forces = forcefield.compute(state, virial=False).forces
            kick_drift(state.positions, state.velocities, forces, inverse_masses, half, self.dt)
        forces = forcefield.compute(state, virial=False).forces
        kick(state.velocities, forces, inverse_masses, half)
        self.end_step(state)

    @staticmethod
    def amplification(omega_dt: float):
        """Roots of rho^2 - (2 - (omega dt)^2) rho + 1 (see
        :class:`integrators.base.SupportsAmplification`): on the unit circle for
        omega dt <= 2, one of them outside beyond (the stability limit)."""
        z2 = float(omega_dt) ** 2
        return amplification_roots([1.0, -(2.0 - z2), 1.0])

    def reset(self) -> None:
        """Nothing to forget: velocity Verlet is a one-step method."""

    def describe(self) -> dict:
        return {"type": "verlet", "dt": self.dt}


__all__ = ["VelocityVerlet"]
