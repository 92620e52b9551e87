"""Pressure control: a barostat applied to a thermostatted integrator every few steps.

:class:`PressureCoupled` wraps a thermostat (Langevin, Bussi, Nose-Hoover
chains, ...) and, every ``every`` steps, lets its barostat rescale the box and
the positions (and, for stochastic cell rescaling, the velocities) towards
the target pressure. Coupling is ``isotropic`` (one scale factor),
``anisotropic`` (each edge on its own diagonal pressure component) or
``triclinic`` (also the tilt factors, on the off-diagonal components, towards
zero shear stress). The Martyna-Tobias-Klein barostat (``mtk``) is a
deterministic integrator of its own, :class:`integrators.mtk.MartynaTobiasKlein`;
:func:`pressure_control` picks the right one for a :class:`Barostat`.

``c_rescale``
    Stochastic cell rescaling (Bernetti and Bussi, J. Chem. Phys. 153,
    114107, 2020). With eps = ln V and the instantaneous pressure P,

        d eps = -(beta / tau) (P0 - P - kT / V) dt + sqrt(2 kT beta dt / (V tau)) xi,

    positions and box are scaled by mu = exp(d eps / 3) and velocities by
    1 / mu. Anisotropic coupling applies the same equation to each edge
    (eps_a = ln L_a) with P_aa and the compressibility divided by three, so
    the volume relaxes at the isotropic rate (the diagonal of the anisotropic
    scheme of Del Tatto, Raiteri, Bernetti and Bussi, Appl. Sci. 12, 1139,
    2022); triclinic coupling adds, for each tilt, d eps_ab = (beta / 3 tau)
    P_ab dt plus noise of the same size, and applies the lower-triangular
    deformation r -> r mu (velocities v -> v mu^-T) that keeps the cell in
    the engine's frame. A cell that tilts beyond half an edge is flipped to
    the equivalent shorter tilts (``md.box.reduced_tilt``). Isotropic
    coupling samples the isothermal-isobaric ensemble (for an ideal gas
    <V> = (N + 1) kT / P0) with any canonical thermostat; ``beta`` (the
    compressibility given) and ``tau`` only set how fast the volume relaxes.
``berendsen``
    Berendsen's weak coupling, mu = (1 - beta dt (P0 - P) / tau)^(1/3):
    for equilibration only; it relaxes the volume but suppresses its
    fluctuations, so it does not sample the isothermal-isobaric ensemble
    (the config warns).

Each move's change of kinetic plus potential energy, plus P0 times the
change of volume, is subtracted into the barostat's reservoir, so
``conserved_energy`` (total + P0 V + both reservoirs) checks the time step as
in NVT.
"""

from __future__ import annotations

import copy
import math
from dataclasses import replace

import numpy as np

from integrators.base import (
    Integrator,
    IntegratorBase,
    Restartable,
    ScalesCell,
    Statistics,
    constraints_of,
)
from integrators.mtk import MartynaTobiasKlein
from md._checks import MAX_SEED, count, positive
from md.box import TILT_AXES, reduced_tilt
from md.errors import SimulationError
from md.parallel import global_sum
from md.schema import REQUIRED, Key, Varies
from md.thermo import kinetic_energy, kinetic_tensor, pressure

#: Barostat types and whether they sample the isothermal-isobaric ensemble.
BAROSTATS = {"c_rescale": True, "mtk": True, "berendsen": False}
COUPLINGS = ("isotropic", "anisotropic", "triclinic")

_PRESSURE = Key("pressure", "number", REQUIRED, unit="pressure", doc="The target pressure P0.")
_COUPLE = Key(
    "couple",
    "string",
    "isotropic",
    choices=COUPLINGS,
    doc="One scale factor (`isotropic`), one per edge on its diagonal pressure "
    "(`anisotropic`), or also the tilts towards zero shear stress (`triclinic`).",
)
#: The keys of a ``[barostat]`` table, per type (the config reads them in this order).
BAROSTAT_KEYS = {
    "c_rescale": (
        _PRESSURE,
        Key(
            "tau",
            "number",
            REQUIRED,
            unit="time",
            positive=True,
            doc="The coupling time: how fast the volume relaxes.",
        ),
        _COUPLE,
        Key(
            "compressibility",
            "number",
            Varies(lj=0.1, metal=4.5e-5),
            unit="1/pressure",
            positive=True,
            doc="The isothermal compressibility beta of the coupling; with `tau` it sets only "
            "how fast the volume relaxes (an LJ liquid's order of magnitude in lj units, "
            "GROMACS's default in metal units).",
        ),
        Key(
            "every",
            "integer",
            10,
            unit="steps",
            minimum=1,
            doc="Steps between barostat moves (each move spans `every` steps).",
        ),
        Key(
            "seed",
            "integer",
            None,
            minimum=0,
            maximum=MAX_SEED,
            doc="The random stream of the cell moves.",
            default_doc="derived from the top-level `seed`",
        ),
    ),
    "mtk": (
        _PRESSURE,
        Key(
            "tau",
            "number",
            REQUIRED,
            unit="time",
            positive=True,
            doc="The period of the barostat's oscillation.",
        ),
        _COUPLE,
    ),
}
BAROSTAT_KEYS["berendsen"] = (
    *BAROSTAT_KEYS["c_rescale"][:-1],
    replace(
        BAROSTAT_KEYS["c_rescale"][-1],
        doc="Accepted and kept; Berendsen's moves draw no random numbers.",
    ),
)


class Barostat:
    """Target pressure, coupling time and compressibility of a barostat.

    Parameters
    ----------
    kind : {"c_rescale", "mtk", "berendsen"}
    pressure : float
        Target pressure P0 [energy/length^3] (any finite value).
    tau : float
        Coupling time [time], > 0 (for ``mtk``, the period of the barostat).
    compressibility : float, optional
        Isothermal compressibility beta used in the coupling [length^3/energy],
        > 0; needed by ``c_rescale`` and ``berendsen``, not used by ``mtk``.
    couple : {"isotropic", "anisotropic", "triclinic"}
    every : int
        Steps between barostat moves (the moves use dt * every); ``mtk`` moves
        the cell every step.
    seed : int, list of int or None
        Random stream of ``c_rescale``.
    """

    def __init__(
        self,
        kind: str,
        pressure: float,
        tau: float,
        compressibility: float | None = None,
        couple: str = "isotropic",
        every: int = 10,
        seed=None,
    ) -> None:
        if kind not in BAROSTATS:
            raise ValueError(f"unknown barostat {kind!r}; known: {', '.join(BAROSTATS)}")
        if couple not in COUPLINGS:
            raise ValueError(f"unknown couple = {couple!r}; known: {', '.join(COUPLINGS)}")
        self.kind = kind
        if isinstance(pressure, bool) or not math.isfinite(float(pressure)):
            raise ValueError(f"pressure must be a finite number, got {pressure!r}")
        self.pressure = float(pressure)
        self.tau = positive(tau, "tau")
        if compressibility is None and kind != "mtk":
            raise ValueError(f"the {kind} barostat needs a compressibility (> 0)")
        self.compressibility = (
            None if compressibility is None else positive(compressibility, "compressibility")
        )
        self.couple = couple
        self.every = count(every, "every", minimum=1)
        self.seed = seed
        self.rng = np.random.default_rng(seed)
        self.reservoir = 0.0
        self.moves = 0

    @property
    def samples_npt(self) -> bool:
        return BAROSTATS[self.kind]

    def scale_factor(self, p_now: float, volume: float, kT: float, dt: float) -> float:
        """The isotropic scale factor mu of one move lasting ``dt``.

        For ``berendsen`` the real cube root: zero or negative when the move
        overshoots (``beta dt (P0 - P) / tau > 1``), which the caller reports.
        """
        rate = self.compressibility / self.tau
        if self.kind == "berendsen":  # the real cube root: negative when the move overshoots
            return float(np.cbrt(1.0 - rate * dt * (self.pressure - p_now)))
        drift = -rate * (self.pressure - p_now - kT / volume) * dt
        noise = math.sqrt(2.0 * kT * rate * dt / volume) * self.rng.standard_normal()
        return math.exp((drift + noise) / 3.0)

    def deformation(self, tensor, volume: float, kT: float, dt: float, pbc) -> np.ndarray:
        """The lower-triangular (3, 3) deformation mu of one anisotropic or triclinic move.

        ``tensor`` is the instantaneous pressure tensor (kinetic + virial) / V;
        positions move as r -> r mu. Open axes keep their length.
        """
        rate = self.compressibility / (3.0 * self.tau)
        mu = np.eye(3)
        for a in range(3):
            if not pbc[a]:
                continue
            if self.kind == "berendsen":
                mu[a, a] = 1.0 - rate * dt * (self.pressure - tensor[a, a])
                continue
            drift = -rate * (self.pressure - tensor[a, a] - kT / volume) * dt
            noise = math.sqrt(2.0 * kT * rate * dt / volume) * self.rng.standard_normal()
            mu[a, a] = math.exp(drift + noise)
        if self.couple == "triclinic":
            for b, a in TILT_AXES:  # tilt xy sits at row y, column x of the cell
                if not (pbc[a] and pbc[b]):
                    continue
                shear = rate * dt * tensor[a, b]
                if self.kind != "berendsen":
                    shear += math.sqrt(2.0 * kT * rate * dt / volume) * self.rng.standard_normal()
                mu[a, b] = shear
        return mu

    def check(self, pbc) -> None:
        """Raise ValueError if this barostat cannot act on a system with periodicity ``pbc``.

        A pressure needs a volume, which only periodic axes give: ``mtk`` needs
        all three periodic; the others at least one, and isotropic coupling
        (which scales every edge alike) all three, since it would also scale
        the nominal length of an open axis.
        """
        flags = [bool(p) for p in pbc]
        if all(flags):
            return
        open_axes = ", ".join("xyz"[k] for k in range(3) if not flags[k])
        if self.kind == "mtk":
            raise ValueError(
                f"the mtk barostat needs a box periodic along x, y and z; the system is open "
                f"along {open_axes} (pbc {flags})"
            )
        if not any(flags):
            raise ValueError(
                f"the {self.kind} barostat needs periodic axes (a volume to scale); the system "
                f"is periodic along none (pbc {flags}): drop [barostat] or make the box periodic"
            )
        if self.couple == "isotropic":
            raise ValueError(
                f"isotropic coupling scales all three edges, but the system is open along "
                f"{open_axes} (pbc {flags}); use couple = 'anisotropic' (or 'triclinic'), which "
                "scales only the periodic edges"
            )

    def overshoot(self, what: str) -> str:
        """The message for a move that overshot: what went wrong, and what to change."""
        return (
            f"the {self.kind} barostat's {what}: its move overshoots (the pressure is too far "
            "from the target for the coupling); use a larger [barostat] tau, or a target "
            "pressure nearer the current one"
        )

    def describe(self) -> dict:
        if self.kind == "mtk":
            return {
                "type": self.kind,
                "pressure": self.pressure,
                "tau": self.tau,
                "couple": self.couple,
            }
        return {
            "type": self.kind,
            "pressure": self.pressure,
            "tau": self.tau,
            "compressibility": self.compressibility,
            "couple": self.couple,
            "every": self.every,
            "seed": self.seed,
        }


def pressure_control(integrator, barostat: Barostat):
    """``integrator`` under ``barostat``: MTK's own integrator for ``mtk``, else PressureCoupled.

    Raises
    ------
    ValueError
        If the pair cannot work together (an NVE integrator; ``mtk`` without
        Nose-Hoover chains), with a message that names what to use instead.
    """
    if barostat.kind == "mtk":
        if not (isinstance(integrator, Integrator) and integrator.thermostat):
            raise ValueError(
                "a barostat needs a thermostat: the mtk barostat runs with [integrator] "
                "type = 'nose_hoover_chain', not an NVE integrator"
            )
        return MartynaTobiasKlein(integrator, barostat)
    return PressureCoupled(integrator, barostat)


class PressureCoupled(IntegratorBase):
    """A thermostatted integrator with a :class:`Barostat`; see the module docstring.

    Raises
    ------
    ValueError
        If the integrator is not a thermostat (pressure control needs a temperature).
    """

    stochastic = True
    splits_forces = False
    distributed = True

    def __init__(self, integrator, barostat: Barostat) -> None:
        if barostat.kind == "mtk":
            raise ValueError("the mtk barostat is its own integrator: use pressure_control()")
        if not (isinstance(integrator, Integrator) and integrator.thermostat):
            raise ValueError(
                "a barostat needs a thermostat ([integrator] type langevin, bussi, "
                "nose_hoover_chain or berendsen), not an NVE integrator"
            )
        self.inner = integrator
        self.barostat = barostat
        self.dt = integrator.dt
        self.thermostat = True
        self.canonical = integrator.canonical and barostat.samples_npt
        self.supports_constraints = integrator.supports_constraints
        self._steps = 0

    @property
    def constraints(self):
        return constraints_of(self.inner)

    @property
    def kT(self) -> float:
        return self.inner.kT

    def step(self, state, forcefield) -> None:
        self.inner.step(state, forcefield)
        self._steps += 1
        if self._steps % self.barostat.every == 0:
            self._move(state, forcefield)

    def _move(self, state, forcefield) -> None:
        barostat = self.barostat
        barostat.check(state.pbc)
        result = forcefield.compute(state, virial=True)
        terms = self.inner.thermo_terms(state, result)
        virial = result.virial + terms["virial"] if "virial" in terms else result.virial
        volume = state.volume
        kinetic = global_sum(kinetic_energy(state.velocities, state.masses))
        before = kinetic + result.energy
        interval = self.dt * barostat.every
        if barostat.couple == "isotropic":
            p_now = pressure(kinetic, virial, volume)
            mu = barostat.scale_factor(p_now, volume, self.kT, interval)
            if not (math.isfinite(mu) and mu > 0):
                raise SimulationError(state.step, barostat.overshoot(f"scale factor is {mu:.4g}"))
            if isinstance(self.inner, ScalesCell):  # rigid bodies: centres move, not shapes
                self.inner.scale_cell(state, mu, barostat.kind == "c_rescale")
            else:
                state.positions *= mu
                state.box = state.box * mu
                state.tilt = state.tilt * mu
                if barostat.kind == "c_rescale":
                    state.velocities /= mu
        else:
            kinetic_part = global_sum(kinetic_tensor(state.velocities, state.masses))
            tensor = (kinetic_part + virial) / volume
            mu = barostat.deformation(tensor, volume, self.kT, interval, state.pbc)
            if not (np.all(np.isfinite(mu)) and np.all(np.diag(mu) > 0)):
                scales = ", ".join(f"{x:.4g}" for x in np.diag(mu))
                raise SimulationError(
                    state.step, barostat.overshoot(f"scale factors of the edges are {scales}")
                )
            if isinstance(self.inner, ScalesCell):  # rigid bodies: centres move, not shapes
                self.inner.scale_cell(state, mu, barostat.kind == "c_rescale")
            else:
                cell = state.cell @ mu
                state.positions[:] = state.positions @ mu
                state.box = np.diag(cell).copy()
                state.tilt = reduced_tilt(state.box, cell[[1, 2, 2], [0, 0, 1]], state.pbc)
                if barostat.kind == "c_rescale":
                    state.velocities[:] = state.velocities @ np.linalg.inv(mu).T
        try:
            energy = forcefield.compute(state, virial=False).energy
        except ValueError as error:  # the box shrank below what the cutoff allows
            raise SimulationError(
                state.step, barostat.overshoot(f"move left a box the cutoff does not fit ({error})")
            ) from None
        after = global_sum(kinetic_energy(state.velocities, state.masses)) + energy
        barostat.reservoir -= (after - before) + barostat.pressure * (state.volume - volume)
        barostat.moves += 1

    def thermo_terms(self, state, result) -> dict:
        terms = dict(self.inner.thermo_terms(state, result))
        # conserved = K + U + P0 V + heat bath + barostat reservoir
        terms["reservoir_energy"] = (
            terms.get("reservoir_energy", 0.0)
            + self.barostat.reservoir
            + self.barostat.pressure * state.volume
        )
        return terms

    @property
    def statistics(self) -> dict:
        stats = dict(self.inner.statistics) if isinstance(self.inner, Statistics) else {}
        stats["barostat_moves"] = self.barostat.moves
        return stats

    def reset(self) -> None:
        self.inner.reset()

    def get_state(self) -> dict:
        inner = self.inner.get_state() if isinstance(self.inner, Restartable) else None
        barostat = self.barostat
        return {
            "inner": inner,
            "steps": self._steps,
            "barostat": {
                "reservoir": barostat.reservoir,
                "moves": barostat.moves,
                "rng": copy.deepcopy(barostat.rng.bit_generator.state),
            },
        }

    def set_state(self, saved: dict) -> None:
        if saved.get("inner") is not None:
            self.inner.set_state(saved["inner"])
        self._steps = int(saved["steps"])
        mine = saved["barostat"]
        self.barostat.reservoir = float(mine["reservoir"])
        self.barostat.moves = int(mine["moves"])
        self.barostat.rng.bit_generator.state = copy.deepcopy(mine["rng"])

    def describe(self) -> dict:
        return {**self.inner.describe(), "barostat": self.barostat.describe()}


__all__ = ["BAROSTATS", "COUPLINGS", "Barostat", "PressureCoupled", "pressure_control"]
