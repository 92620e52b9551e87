"""Reversible RESPA: multiple time stepping with fast (bonded) and slow (pair) forces.

Tuckerman, Berne and Martyna, J. Chem. Phys. 97, 1990 (1992): the Trotter
splitting of the Liouvillian into slow forces F_s and the rest gives, per
outer step dt with n inner steps h = dt / n,

    v += dt/2 F_s/m;  n x [ v += h/2 F_f/m;  x += h v;  v += h/2 F_f/m ];  v += dt/2 F_s/m

symplectic and time-reversible, second order in dt, with one slow force
evaluation per outer step (the expensive pair forces) and n fast ones (the
cheap bonds). Adjacent kicks at the same positions are merged, so with
``inner_steps = 1`` the step is velocity Verlet, bit for bit.

The resonance limit: the outer kicks act as a periodic impulse on the fast
motion, and when the outer step approaches half the period of the fastest
fast motion (the bond vibration) energy is pumped into it and the run
becomes unstable, however small h is (Biesiadecki and Skeel 1993; Ma, Izaguirre
and Skeel 2003). In practice keep dt below about a third of the bond period.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from integrators._kernels import kick, kick_drift
from integrators.base import DT, IntegratorBase, check_dt
from md._checks import count
from md.schema import Key


class RESPA(IntegratorBase):
    """Reversible RESPA with ``inner_steps`` fast substeps per outer step.

    Parameters
    ----------
    dt : float
        Outer time step [time] (the slow forces' step).
    inner_steps : int
        Fast substeps per outer step, >= 1 (1: velocity Verlet).
    fast : "bonded" or sequence of int
        Which potentials are fast: "bonded" (those without a cutoff: springs,
        FENE bonds) or their indices in the force field's list.

    Examples
    --------
    >>> RESPA(0.01, inner_steps=4).describe()
    {'type': 'respa', 'dt': 0.01, 'inner_steps': 4, 'fast': 'bonded'}
    """

    order = 2
    distributed = True
    splits_forces = True
    CONFIG_KEYS = (
        replace(DT, doc="The outer time step: the slow forces' step."),
        Key(
            "inner_steps",
            "integer",
            2,
            doc="Fast substeps per outer step, >= 1 (1: velocity Verlet).",
        ),
        Key(
            "fast",
            '"bonded" or list of integers',
            "bonded",
            doc='Which potentials are fast: `"bonded"` (those without a cutoff: springs, FENE '
            "bonds, angles) or their indices in `[[potentials]]`.",
        ),
    )

    def __init__(self, dt: float, inner_steps: int = 2, fast: str | Sequence[int] = "bonded"):
        self.dt = check_dt(dt)
        self.inner_steps = count(inner_steps, "inner_steps", minimum=1)
        if isinstance(fast, str) or not isinstance(fast, Sequence | np.ndarray):
            if fast != "bonded":  # also true, 3: not a list, so nothing to iterate over
                raise ValueError(
                    f'fast must be "bonded" or a list of potential indices, got {fast!r}'
                )
            self.fast = fast
        else:
            self.fast = tuple(count(i, "fast potential index") for i in fast)
            if not self.fast:
                raise ValueError("fast lists no potential")

    def split(self, forcefield) -> tuple[tuple[int, ...], tuple[int, ...]]:
        """Return the (fast, slow) potential indices of a force field.

        Raises
        ------
        ValueError
            If no potential is fast, none is slow, or an index names no potential.
        """
        n = len(forcefield.potentials)
        if self.fast == "bonded":
            fast = tuple(i for i, p in enumerate(forcefield.potentials) if p.cutoff is None)
        else:
            bad = [i for i in self.fast if i >= n]
            if bad:
                raise ValueError(f"fast names potential {bad[0]}, but there are only {n}")
            fast = tuple(sorted(set(self.fast)))
        slow = tuple(i for i in range(n) if i not in fast)
        if not fast:
            raise ValueError("RESPA found no fast potential (no bonded potential; give fast = [i])")
        if not slow:
            raise ValueError("RESPA found no slow potential: every potential is fast")
        return fast, slow

    def step(self, state, forcefield) -> None:
        n = self.inner_steps
        dt, h = self.dt, self.dt / n
        inverse_masses = 1.0 / state.masses
        if n == 1:  # merged kicks: velocity Verlet exactly
            forces = forcefield.compute(state, virial=False).forces
            kick_drift(state.positions, state.velocities, forces, inverse_masses, 0.5 * dt, dt)
            forces = forcefield.compute(state, virial=False).forces
            kick(state.velocities, forces, inverse_masses, 0.5 * dt)
        else:
            fast, slow = self.split(forcefield)
            combined = self._outer(state, forcefield, fast, slow)
            kick_drift(state.positions, state.velocities, combined, inverse_masses, 0.5 * dt, h)
            for _ in range(n - 1):
                forces = forcefield.compute_subset(state, fast).forces
                kick_drift(state.positions, state.velocities, forces, inverse_masses, h, h)
            combined = self._outer(state, forcefield, fast, slow)
            kick(state.velocities, combined, inverse_masses, 0.5 * dt)
        self.end_step(state)

    def _outer(self, state, forcefield, fast, slow):
        """F_s + F_f / n: the outer half kick dt/2 and the inner half kick h/2, merged."""
        slow_forces = forcefield.compute_subset(state, slow).forces
        fast_forces = forcefield.compute_subset(state, fast).forces
        return slow_forces + fast_forces / self.inner_steps

    def describe(self) -> dict:
        fast = self.fast if isinstance(self.fast, str) else list(self.fast)
        return {"type": "respa", "dt": self.dt, "inner_steps": self.inner_steps, "fast": fast}


__all__ = ["RESPA"]
