"""Nose-Hoover chains (Martyna, Klein, Tuckerman) around velocity Verlet."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from numba import njit

from integrators._thermostat import FIX_COM, TAU, TEMPERATURE, Thermostat, check_temperature
from integrators.base import DT
from integrators.rattle import CONSTRAINTS, constrained_verlet_step
from md._checks import positive
from md.parallel import global_sum
from md.schema import Key
from md.thermo import kinetic_energy

#: Suzuki-Yoshida weights of the fourth-order composition (three stages).
_W1 = 1.0 / (2.0 - 2.0 ** (1.0 / 3.0))
YOSHIDA_WEIGHTS = np.array([_W1, 1.0 - 2.0 * _W1, _W1])


class NoseHooverChain(Thermostat):
    """Deterministic canonical thermostat: a chain of Nose-Hoover variables, MTK splitting.

    The particles couple to the first of ``chain_length`` thermostat
    variables xi_j with "masses" Q_1 = n_dof kB T tau^2 and
    Q_j = kB T tau^2, each thermostatting the one before it. A step is the
    Trotter factorisation

        exp(iL_chain dt/2) exp(iL_verlet dt) exp(iL_chain dt/2),

    where each chain half step is split by the fourth-order Suzuki-Yoshida
    composition (and ``n_substeps`` equal substeps) and scales all velocities
    by one factor, leaving the total momentum and rigid bonds alone. The
    extended energy

        H = K + U + sum_j Q_j v_xi_j^2 / 2 + n_dof kB T xi_1 + kB T sum_{j>1} xi_j

    is conserved up to the integration error; ``reservoir_energy`` returns
    the chain part. Chains (rather than a single Nose-Hoover variable) make
    the dynamics ergodic enough for small or stiff systems.

    Parameters
    ----------
    dt : float
        Time step [time].
    temperature : float
        Target temperature [temperature], > 0.
    tau : float
        Period of the thermostat's oscillation [time], > 0; ~100 dt is usual.
    chain_length : int
        Number of chained thermostat variables, >= 1 (1: plain Nose-Hoover).
    kB : float
        Boltzmann constant [energy/temperature].
    n_substeps : int
        Substeps of each chain half step (more for a very short tau).
    constraints : BondConstraints or array_like of int, shape (B, 2), optional
        Rigid bonds, kept by SHAKE and RATTLE.
    fix_com : bool
        Count 3 fewer degrees of freedom for the conserved total momentum.

    Examples
    --------
    >>> NoseHooverChain(dt=0.005, temperature=1.0, tau=0.5).describe()["chain_length"]
    3

    References
    ----------
    G. J. Martyna, M. L. Klein, M. Tuckerman, J. Chem. Phys. 97, 2635 (1992);
    G. J. Martyna, M. E. Tuckerman, D. J. Tobias, M. L. Klein, Mol. Phys. 87,
    1117 (1996).
    """

    _saved = ("xi", "v_xi")
    CONFIG_KEYS = (
        DT,
        TEMPERATURE,
        replace(TAU, doc="The period of the thermostat's oscillation; about 100 `dt` is usual."),
        Key(
            "chain_length",
            "integer",
            3,
            doc="Chained thermostat variables, >= 1 (1: plain Nose-Hoover).",
        ),
        Key(
            "n_substeps",
            "integer",
            1,
            doc="Substeps of each chain half step, >= 1 (more for a very short `tau`).",
        ),
        CONSTRAINTS,
        FIX_COM,
    )

    def __init__(
        self,
        dt: float,
        temperature: float,
        tau: float,
        chain_length: int = 3,
        kB: float = 1.0,
        n_substeps: int = 1,
        constraints=None,
        fix_com: bool = True,
    ) -> None:
        super().__init__(
            dt, check_temperature(temperature, positive=True), kB, constraints, fix_com
        )
        self.tau = positive(tau, "tau")
        for name, value in (("chain_length", chain_length), ("n_substeps", n_substeps)):
            if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        self.chain_length = int(chain_length)
        self.n_substeps = int(n_substeps)
        self.xi = np.zeros(self.chain_length)  # chain positions [1]
        self.v_xi = np.zeros(self.chain_length)  # chain velocities [1/time]
        self._n_dof: int | None = None

    def masses(self, n_dof: int) -> np.ndarray:
        """Chain masses Q_j [energy time^2] for ``n_dof`` particle degrees of freedom."""
        q = np.full(self.chain_length, self.kT * self.tau**2)
        q[0] *= n_dof
        return q

    def step(self, state, forcefield) -> None:
        self._prepare(state)
        n_dof = self.degrees_of_freedom(global_sum(state.n_atoms))
        if n_dof <= 0:
            raise ValueError(f"no degrees of freedom left to thermostat ({state.n_atoms} atoms)")
        half = 0.5 * self.dt
        self.thermalize(state, n_dof, half)
        constrained_verlet_step(state, forcefield, self.dt, self.constraints)
        self.thermalize(state, n_dof, half)
        self._advance(state)

    def thermalize(self, state, n_dof: int, duration: float) -> None:
        """Advance the chain over ``duration`` [time] and scale the velocities by it.

        The chain acts on ``n_dof`` degrees of freedom (the particles'; the
        Martyna-Tobias-Klein integrator calls this for its particle chain).
        """
        self._n_dof = n_dof
        kinetic = global_sum(kinetic_energy(state.velocities, state.masses))
        scale = chain_half_step(
            self.xi,
            self.v_xi,
            self.masses(n_dof),
            kinetic,
            float(n_dof),
            self.kT,
            duration,
            YOSHIDA_WEIGHTS,
            self.n_substeps,
        )
        state.velocities *= scale

    def reservoir_energy(self) -> float:
        """Chain energy sum Q v_xi^2 / 2 + n_dof kT xi_1 + kT sum_{j>1} xi_j [energy]."""
        if self._n_dof is None:
            return 0.0
        q = self.masses(self._n_dof)
        kT = self.kT
        return float(
            0.5 * np.dot(q, self.v_xi**2) + self._n_dof * kT * self.xi[0] + kT * self.xi[1:].sum()
        )

    def reset(self) -> None:
        """Put the chain at rest at the origin (its energy restarts from zero)."""
        self.xi[:] = 0.0
        self.v_xi[:] = 0.0

    def get_state(self) -> dict:
        saved = super().get_state()
        saved["n_dof"] = self._n_dof
        return saved

    def set_state(self, saved: dict) -> None:
        super().set_state(saved)
        self._n_dof = saved.get("n_dof")

    def describe(self) -> dict:
        return self._describe(
            "nose_hoover_chain",
            tau=self.tau,
            chain_length=self.chain_length,
            n_substeps=self.n_substeps,
        )


# ------------------------------------------------------------------- kernels


@njit(cache=True, error_model="numpy")
def _chain_force(j, xi_velocities, q, kinetic, n_dof, kT):
    """Force on chain velocity j: (2K - n_dof kT) / Q_1 for j = 0,
    else (Q_{j-1} v_{j-1}^2 - kT) / Q_j."""
    if j == 0:
        return (2.0 * kinetic - n_dof * kT) / q[0]
    return (q[j - 1] * xi_velocities[j - 1] ** 2 - kT) / q[j]


@njit(cache=True, error_model="numpy")
def chain_half_step(xi, xi_velocities, q, kinetic, n_dof, kT, duration, weights, n_substeps):
    """Advance the chain (xi, xi_velocities written in place) over ``duration`` with the
    particles' kinetic energy; return the factor that scales the particle velocities."""
    m = xi.shape[0]
    scale = 1.0
    for _ in range(n_substeps):
        for w in weights:
            d = w * duration / n_substeps
            # chain velocities, from the end of the chain to the particles
            for j in range(m - 1, -1, -1):
                g = _chain_force(j, xi_velocities, q, kinetic, n_dof, kT)
                if j == m - 1:
                    xi_velocities[j] += 0.5 * d * g
                else:
                    e = math.exp(-0.25 * d * xi_velocities[j + 1])
                    xi_velocities[j] = xi_velocities[j] * e * e + 0.5 * d * g * e
            # particle velocities and chain positions
            f = math.exp(-d * xi_velocities[0])
            scale *= f
            kinetic *= f * f
            for j in range(m):
                xi[j] += d * xi_velocities[j]
            # chain velocities, from the particles to the end of the chain
            for j in range(m):
                g = _chain_force(j, xi_velocities, q, kinetic, n_dof, kT)
                if j == m - 1:
                    xi_velocities[j] += 0.5 * d * g
                else:
                    e = math.exp(-0.25 * d * xi_velocities[j + 1])
                    xi_velocities[j] = xi_velocities[j] * e * e + 0.5 * d * g * e
    return scale


__all__ = ["YOSHIDA_WEIGHTS", "NoseHooverChain", "chain_half_step"]
