"""What the thermostats share: parameters, degrees of freedom, bath energy, saved state.

Every thermostat here is an :class:`~integrators.base.Integrator` that also
offers

``degrees_of_freedom(n_atoms)``
    the kinetic degrees of freedom it thermalises: 3N, less 3 with
    ``fix_com`` (the centre-of-mass momentum is conserved and left alone),
    less one per rigid bond;
``reservoir_energy()``
    the energy the heat bath holds relative to the start [energy], so that
    kinetic + potential + reservoir energy is the conserved quantity of the
    scheme (the "effective energy" of Bussi et al., the extended energy of a
    Nose-Hoover chain, the accumulated heat for Langevin and Berendsen): its
    drift measures the integration error;
``thermo_terms(state, result)``
    what :meth:`md.Simulation.thermo` needs from it (degrees of freedom,
    constraint virial, reservoir energy);
``get_state()`` / ``set_state(saved)``
    the private state (random generator, chain variables, reservoir) as
    plain data, for checkpoints.
"""

from __future__ import annotations

import copy
import math

import numpy as np

from integrators.base import IntegratorBase, check_dt
from integrators.rattle import as_constraints, constrained_thermo_terms
from md._checks import positive
from md.parallel import global_sum
from md.schema import REQUIRED, Key

# The keys the thermostats share (each class lists its own in CONFIG_KEYS).
TEMPERATURE = Key(
    "temperature",
    "number",
    REQUIRED,
    unit="temperature",
    minimum=0.0,
    doc="The target temperature.",
)
TAU = Key(
    "tau",
    "number",
    REQUIRED,
    unit="time",
    positive=True,
    doc="The coupling time; about 100 `dt` is usual.",
)
SEED = Key(
    "seed",
    "integer or list of integers",
    None,
    doc="The random stream, for repeatable runs.",
    default_doc="derived from the top-level `seed` (none there: fresh entropy)",
)
FIX_COM = Key(
    "fix_com",
    "boolean",
    True,
    doc="Keep the total momentum (3 fewer degrees of freedom); false for systems in "
    "an external field.",
)


def check_temperature(temperature: float, positive: bool = False) -> float:
    """Return ``temperature`` as a float, or raise ValueError naming the problem."""
    if isinstance(temperature, bool):
        raise ValueError(f"temperature must be a number, got {temperature!r}")
    try:
        value = float(temperature)
    except (TypeError, ValueError):
        raise ValueError(f"temperature must be a number, got {temperature!r}") from None
    if not math.isfinite(value) or value < 0 or (positive and value == 0):
        bound = "> 0" if positive else ">= 0"
        raise ValueError(f"temperature must be finite and {bound}, got {temperature!r}")
    return value


def make_rng(seed) -> np.random.Generator:
    """A numpy Generator from a seed (int, list of ints, None) or a Generator itself."""
    if isinstance(seed, np.random.Generator):
        return seed
    try:
        return np.random.default_rng(seed)
    except (TypeError, ValueError) as error:
        raise ValueError(f"seed must be an integer, a list of integers or None ({error})") from None


class Thermostat(IntegratorBase):
    """Base of the thermostats: parameters, degrees of freedom, bath energy, saved state.

    Subclasses implement ``step`` and ``describe`` and list their private
    attributes in ``_saved`` (arrays and numbers) for :meth:`get_state`.
    """

    #: Marks a class as a thermostat (configs convert its temperature and times).
    thermostat = True
    #: Whether it draws random numbers (configs then give it a seed).
    stochastic = False
    #: Whether it takes ``constraints`` (rigid bonds).
    supports_constraints = True
    #: Whether it samples the canonical ensemble (Berendsen does not).
    canonical = True
    #: The random stream of a stochastic thermostat drawn in sequence (Bussi), whose state
    #: checkpoints keep; None for one keyed by step and atom (Langevin).
    rng: np.random.Generator | None = None
    #: Runs decomposed over MPI ranks (its sums are global; not with constraints).
    distributed = True
    _saved: tuple[str, ...] = ()

    def __init__(self, dt, temperature, kB=1.0, constraints=None, fix_com=True) -> None:
        self.dt = check_dt(dt)
        self.temperature = check_temperature(temperature)
        self.kB = positive(kB, "kB")
        self.constraints = as_constraints(constraints)
        self.fix_com = bool(fix_com)
        self.reservoir = 0.0
        self._steps = 0

    @classmethod
    def coupling(cls, tau: float) -> dict:
        """Keyword arguments that couple the thermostat with time constant ``tau`` [time]."""
        return {"tau": tau}

    @property
    def kT(self) -> float:
        """Target thermal energy kB T [energy]."""
        return self.kB * self.temperature

    @property
    def statistics(self) -> dict:
        stats = {"steps": self._steps}
        if self.constraints is not None:
            stats.update(self.constraints.statistics)
        return stats

    def degrees_of_freedom(self, n_atoms: int) -> int:
        """Kinetic degrees of freedom thermalised: 3N, less 3 with ``fix_com`` when N > 1,
        less one per constraint."""
        n_dof = 3 * n_atoms - (3 if self.fix_com and n_atoms > 1 else 0)
        if self.constraints is not None:
            n_dof -= self.constraints.n_constraints
        return n_dof

    def reservoir_energy(self) -> float:
        """Energy the heat bath holds relative to the start [energy] (see module docstring)."""
        return self.reservoir

    def thermo_terms(self, state, result) -> dict:
        """Degrees of freedom, constraint virial and reservoir energy for ``Simulation.thermo``."""
        n_dof = self.degrees_of_freedom(global_sum(state.n_atoms))
        terms = constrained_thermo_terms(self.constraints, n_dof, state, result)
        terms["reservoir_energy"] = self.reservoir_energy()
        return terms

    def reset(self) -> None:
        """Nothing to forget between steps: the bath energy and random stream are kept."""

    def get_state(self) -> dict:
        """Return the private state as plain data (bath, random stream, chain, bond lengths)."""
        saved = {"reservoir": self.reservoir, "steps": self._steps}
        for name in self._saved:
            value = getattr(self, name)  # its own saved attributes, by name
            saved[name] = value.tolist() if isinstance(value, np.ndarray) else copy.deepcopy(value)
        if self.rng is not None:
            saved["rng"] = copy.deepcopy(self.rng.bit_generator.state)
        if self.constraints is not None:
            saved["constraints"] = self.constraints.get_state()
        return saved

    def set_state(self, saved: dict) -> None:
        """Restore what :meth:`get_state` returned, so a run continues exactly."""
        self.reservoir = float(saved["reservoir"])
        self._steps = int(saved.get("steps", 0))
        for name in self._saved:
            current = getattr(self, name)  # (as get_state)
            value = saved[name]
            if isinstance(current, np.ndarray):
                value = np.array(value, dtype=current.dtype)
                if value.shape != current.shape:
                    raise ValueError(
                        f"saved {name} has shape {value.shape}, expected {current.shape}"
                    )
            setattr(self, name, value)
        if self.rng is not None:
            self.rng.bit_generator.state = copy.deepcopy(saved["rng"])
        if self.constraints is not None and "constraints" in saved:
            self.constraints.set_state(saved["constraints"])

    def _prepare(self, state) -> None:
        """Bind the constraints (first step) before the step proper."""
        if self.constraints is not None:
            self.constraints.bind(state, self.dt, state.step + 1)

    def _advance(self, state) -> None:
        self._steps += 1
        self.end_step(state)

    def _describe(self, kind: str, **params) -> dict:
        described = {
            "type": kind,
            "dt": self.dt,
            "temperature": self.temperature,
            "kB": self.kB,
            **params,
            "fix_com": self.fix_com,
        }
        if self.constraints is not None:
            described["constraints"] = self.constraints.describe()
        return described
