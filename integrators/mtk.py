"""Martyna-Tobias-Klein barostat with Nose-Hoover chains: deterministic NPT.

The cell h (columns a, b, c; upper triangular, i.e. the transpose of
``State.cell``) moves with a barostat velocity matrix Omega = p_g / W, and
the equations of motion are those of Martyna, Tobias and Klein (1994) in the
form of Tuckerman et al. (2006), with N_f the particles' degrees of freedom:

    dr/dt     = v + Omega r
    dv/dt     = F / m - (Omega + tr(Omega) / N_f) v - v_xi v
    dh/dt     = Omega h
    W dOmega/dt = V (P_int - P0) + (2 K / N_f) 1 - v_xi' W Omega

where P_int = (sum m v v^T + virial) / V, v_xi is the particles' chain and
v_xi' a second chain on the barostat. ``couple`` selects the free
components of Omega: one number times the identity (``isotropic``, the
original MTK with eps = ln(V / V0) / 3), the diagonal (``anisotropic``), or
the diagonal and the upper off-diagonal entries (``triclinic``: the cell
keeps the restricted form, as in LAMMPS's ``fix npt tri``, and flips past
half an edge). Off-diagonal components are driven by the shear components of
P_int towards zero shear stress.

A step is the symmetric Trotter factorisation (Tuckerman et al. 2006)

    chains(dt/2) Omega-kick(dt/2) v-kick(dt/2) drift(dt) [forces]
    v-kick(dt/2) Omega-kick(dt/2) chains(dt/2),

whose particle sub-steps are solved exactly for constant Omega with matrix
exponentials (``exp(X)`` and ``phi(X) = (exp(X) - 1) / X``), so the scheme is
time reversible. The extended energy

    H = K + U + P0 V + sum W Omega_ab^2 / 2 + (particle chain) + (barostat chain)

is conserved up to the integration error and is reported as
``conserved_energy``.

Barostat masses: W = (N_f + 3) kT tau^2 for the isotropic mode and a third
of that per component otherwise, so ``tau`` is of the order of the period of
the volume's oscillation (~1000 dt, as LAMMPS advises for ``Pdamp``). The
barostat's chain has masses n kT tau^2 (n: the free components) and kT tau^2.

References
----------
G. J. Martyna, D. J. Tobias, M. L. Klein, J. Chem. Phys. 101, 4177 (1994);
M. E. Tuckerman, J. Alejandre, R. Lopez-Rendon, A. L. Jochim, G. J. Martyna,
J. Phys. A 39, 5629 (2006); W. Shinoda, M. Shiga, M. Mikami, Phys. Rev. B
69, 134103 (2004).
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import expm

from integrators._kernels import _linear_flow
from integrators.base import IntegratorBase
from integrators.nose_hoover import YOSHIDA_WEIGHTS, NoseHooverChain, chain_half_step
from md.box import reduced_tilt
from md.errors import SimulationError
from md.parallel import global_sum
from md.thermo import kinetic_tensor

#: Upper off-diagonal entries (row, column) of Omega, in column convention, freed by
#: triclinic coupling: xy, xz, yz (h[0, 1] is the tilt xy, as State.cell[1, 0]).
_SHEAR = ((0, 1), (0, 2), (1, 2))


def exp_and_phi(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return exp(X) and phi(X) = sum_k X^k / (k + 1)! of a (3, 3) matrix.

    Both come from one exponential of the (6, 6) block matrix [[X, 1], [0, 0]],
    which is well defined when X is singular (phi(0) = 1).

    Examples
    --------
    >>> e, p = exp_and_phi(np.zeros((3, 3)))
    >>> bool(np.allclose(e, np.eye(3)) and np.allclose(p, np.eye(3)))
    True
    """
    diagonal = np.diag(x)
    if not np.any(x - np.diag(diagonal)):  # isotropic and anisotropic coupling: elementwise
        safe = np.where(diagonal == 0.0, 1.0, diagonal)
        phi = np.where(diagonal == 0.0, 1.0, np.expm1(diagonal) / safe)
        return np.diag(np.exp(diagonal)), np.diag(phi)
    block = np.zeros((6, 6))
    block[:3, :3] = x
    block[:3, 3:] = np.eye(3)
    full = expm(block)
    return full[:3, :3], full[:3, 3:]


class MartynaTobiasKlein(IntegratorBase):
    """Nose-Hoover chains at constant pressure: the MTK barostat (see the module docstring).

    Parameters
    ----------
    thermostat : NoseHooverChain
        Its dt, temperature, tau, chain length and substeps serve the particles'
        chain; its chain variables are those of this integrator.
    barostat : integrators.barostats.Barostat
        ``kind = "mtk"``: target pressure, ``tau`` (barostat period [time]) and
        ``couple``.

    Raises
    ------
    ValueError
        If the thermostat is not a Nose-Hoover chain or keeps rigid bonds.
    """

    thermostat = True
    stochastic = False
    canonical = True
    supports_constraints = False
    distributed = True

    def __init__(self, thermostat, barostat) -> None:
        if not isinstance(thermostat, NoseHooverChain):
            name = type(thermostat).__name__
            raise ValueError(
                "the mtk barostat runs with its own Nose-Hoover chains: use [integrator] "
                f"type = 'nose_hoover_chain', not {name} (or type = 'c_rescale' with any "
                "thermostat)"
            )
        if thermostat.constraints is not None:
            raise ValueError("the mtk barostat does not keep rigid bonds; use c_rescale")
        self.chain = thermostat
        self.barostat = barostat
        self.dt = thermostat.dt
        self.omega = np.zeros((3, 3))  # barostat velocity matrix, column convention [1/time]
        self.xi = np.zeros(thermostat.chain_length)  # the barostat's chain
        self.v_xi = np.zeros(thermostat.chain_length)
        self._steps = 0
        self._unit_scale = np.ones(0)

    # -------------------------------------------------------------- parameters
    @property
    def kT(self) -> float:
        return self.chain.kT

    def free_components(self) -> list[tuple[int, int]]:
        """Entries (row, column) of Omega that move; the isotropic mode moves (0, 0) for all."""
        couple = self.barostat.couple
        if couple == "isotropic":
            return [(0, 0)]
        diagonal = [(0, 0), (1, 1), (2, 2)]
        return diagonal + list(_SHEAR) if couple == "triclinic" else diagonal

    def cell_mass(self, n_dof: int) -> float:
        """Barostat mass W [energy time^2] of each free component."""
        mass = (n_dof + 3) * self.kT * self.barostat.tau**2
        return mass if self.barostat.couple == "isotropic" else mass / 3.0

    def _chain_masses(self) -> np.ndarray:
        q = np.full(self.xi.shape[0], self.kT * self.barostat.tau**2)
        q[0] *= len(self.free_components())
        return q

    def cell_kinetic_energy(self, n_dof: int) -> float:
        """sum W Omega_ab^2 / 2 over the free components [energy]."""
        values = np.array([self.omega[a, b] for a, b in self.free_components()])
        return 0.5 * self.cell_mass(n_dof) * float(values @ values)

    # ------------------------------------------------------------------- step
    def step(self, state, forcefield) -> None:
        self.barostat.check(state.pbc)
        n_dof = self.chain.degrees_of_freedom(global_sum(state.n_atoms))
        if n_dof <= 0:
            raise ValueError(f"no degrees of freedom left to thermostat ({state.n_atoms} atoms)")
        half = 0.5 * self.dt
        result = forcefield.compute(state, virial=True)
        self._barostat_chain(n_dof, half)
        self.chain.thermalize(state, n_dof, half)
        self._kick_cell(state, result.virial, n_dof, half)
        self._kick_particles(state, result.forces, n_dof, half)
        self._drift(state, self.dt)
        try:
            result = forcefield.compute(state, virial=True)
        except ValueError as error:  # the box shrank below what the cutoff allows
            raise SimulationError(state.step + 1, f"the mtk barostat's cell: {error}") from None
        self._kick_particles(state, result.forces, n_dof, half)
        self._kick_cell(state, result.virial, n_dof, half)
        self.chain.thermalize(state, n_dof, half)
        self._barostat_chain(n_dof, half)
        self._steps += 1
        self.end_step(state)

    def _barostat_chain(self, n_dof: int, duration: float) -> None:
        free = self.free_components()
        scale = chain_half_step(
            self.xi,
            self.v_xi,
            self._chain_masses(),
            self.cell_kinetic_energy(n_dof),
            float(len(free)),
            self.kT,
            duration,
            YOSHIDA_WEIGHTS,
            self.chain.n_substeps,
        )
        self.omega *= scale

    def _kick_cell(self, state, virial, n_dof: int, duration: float) -> None:
        """Omega += duration * (V (P_int - P0) + 2K / N_f) / W on the free components."""
        velocities = state.velocities
        kinetic = global_sum(kinetic_tensor(velocities, state.masses))  # sum_i m_i v_i v_i^T
        force = kinetic + virial
        force[np.diag_indices(3)] += (
            np.trace(kinetic) / n_dof - self.barostat.pressure * state.volume
        )
        rate = duration / self.cell_mass(n_dof)
        if self.barostat.couple == "isotropic":
            self.omega += rate * np.trace(force) * np.eye(3)
        else:
            for a, b in self.free_components():
                self.omega[a, b] += rate * force[a, b]
        if not np.all(np.isfinite(self.omega)):
            raise SimulationError(state.step + 1, "the mtk barostat's velocity is not finite")

    def _kick_particles(self, state, forces, n_dof: int, duration: float) -> None:
        """v <- exp(-A t) v + t phi(-A t) F / m with A = Omega + tr(Omega) / N_f."""
        a = self.omega + np.trace(self.omega) / n_dof * np.eye(3)
        e, phi = exp_and_phi(-a * duration)
        _linear_flow(state.velocities, forces, 1.0 / state.masses, e, duration * phi)

    def _drift(self, state, duration: float) -> None:
        """r <- exp(Omega t) r + t phi(Omega t) v; the cell h <- exp(Omega t) h."""
        e, phi = exp_and_phi(self.omega * duration)
        _linear_flow(
            state.positions, state.velocities, self._ones(state.n_atoms), e, duration * phi
        )
        cell = state.cell @ e.T  # State.cell holds the cell vectors as rows: h^T
        state.box = np.diag(cell).copy()
        state.tilt = reduced_tilt(state.box, cell[[1, 2, 2], [0, 0, 1]], state.pbc)

    def _ones(self, n: int) -> np.ndarray:
        if self._unit_scale.shape[0] != n:
            self._unit_scale = np.ones(n)
        return self._unit_scale

    # ----------------------------------------------------------- bookkeeping
    def thermo_terms(self, state, result) -> dict:
        terms = dict(self.chain.thermo_terms(state, result))
        n_dof = terms.get("n_dof", self.chain.degrees_of_freedom(global_sum(state.n_atoms)))
        q = self._chain_masses()
        kT = self.kT
        barostat_chain = (
            0.5 * float(q @ self.v_xi**2)
            + len(self.free_components()) * kT * self.xi[0]
            + kT * float(self.xi[1:].sum())
        )
        # conserved = K + U + particle chain + P0 V + cell kinetic energy + barostat chain
        terms["reservoir_energy"] = (
            terms.get("reservoir_energy", 0.0)
            + self.barostat.pressure * state.volume
            + self.cell_kinetic_energy(n_dof)
            + barostat_chain
        )
        return terms

    @property
    def statistics(self) -> dict:
        return {"steps": self._steps}

    def reset(self) -> None:
        """Put both chains and the cell at rest (the extended energy restarts)."""
        self.chain.reset()
        self.omega[:] = 0.0
        self.xi[:] = 0.0
        self.v_xi[:] = 0.0

    def get_state(self) -> dict:
        return {
            "chain": self.chain.get_state(),
            "steps": self._steps,
            "omega": self.omega.tolist(),
            "xi": self.xi.tolist(),
            "v_xi": self.v_xi.tolist(),
        }

    def set_state(self, saved: dict) -> None:
        self.chain.set_state(saved["chain"])
        self._steps = int(saved["steps"])
        for name in ("omega", "xi", "v_xi"):
            current = getattr(self, name)  # its own array of that name
            value = np.array(saved[name], dtype=np.float64)
            if value.shape != current.shape:
                raise ValueError(f"saved {name} has shape {value.shape}, expected {current.shape}")
            current[...] = value

    def describe(self) -> dict:
        return {**self.chain.describe(), "barostat": self.barostat.describe()}


__all__ = ["MartynaTobiasKlein", "exp_and_phi"]
