"""The optional hooks of integrators, observers and potentials, declared as Protocols.

Each hook is a ``runtime_checkable`` Protocol (``integrators.base``,
``potentials.base``, ``md.simulation``); the engine asks ``isinstance``
before it uses one. These tests check which registry classes offer which
hook, that an object without a hook is treated as before (no thermo terms,
no private state, no rigid bonds, a virial for its steps), that a duck-typed
object offering a hook is honoured without deriving from the base class, and
that every integrator closes its step through ``IntegratorBase.end_step``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

import md
from integrators import INTEGRATORS, RESPA, BondConstraints, Langevin, VelocityVerlet
from integrators.barostats import Barostat, PressureCoupled
from integrators.base import (
    Constrained,
    ForceSplit,
    Integrator,
    IntegratorBase,
    Restartable,
    Statistics,
    ThermoTerms,
    constraints_of,
)
from md.assemble import run_topology
from md.calculator import MDCalculator
from md.checkpoint import read_checkpoint, restore, write_checkpoint
from md.errors import CheckpointError
from md.observers import Progress
from md.run import RunSummary
from md.simulation import VirialUse
from potentials import HarmonicBonds, LennardJones
from potentials.base import ForceResult, TypedParameters


class _PlainVerlet:
    """Velocity Verlet with nothing but the required members: no hook at all."""

    thermostat = stochastic = adaptive = splits_forces = False
    supports_constraints = requires_constraints = False
    canonical = True
    order = 2

    def __init__(self, dt: float) -> None:
        self.dt = dt

    def step(self, state, forcefield) -> None:
        VelocityVerlet(self.dt).step(state, forcefield)

    def reset(self) -> None:
        pass

    def describe(self) -> dict:
        return {"type": "plain_verlet", "dt": self.dt}


class _BathVerlet(_PlainVerlet):
    """Duck-typed (no IntegratorBase): a fixed heat-bath energy and a private counter."""

    def __init__(self, dt: float) -> None:
        super().__init__(dt)
        self.counter = 0

    def step(self, state, forcefield) -> None:
        super().step(state, forcefield)
        self.counter += 1

    def thermo_terms(self, state, result) -> dict:
        return {"reservoir_energy": 0.25}

    def get_state(self) -> dict:
        return {"counter": self.counter}

    def set_state(self, saved: dict) -> None:
        self.counter = int(saved["counter"])


def _sim(state, integrator):
    return md.Simulation(state.copy(), [LennardJones(cutoff=2.5)], integrator)


def test_registry_integrators_offer_the_hooks_they_implement():
    for name, cls in INTEGRATORS.items():
        assert issubclass(cls, IntegratorBase), name
        # every registry integrator has constraints (None by default) and closes steps alike
        assert cls.end_step is IntegratorBase.end_step, name
    verlet, langevin, respa = VelocityVerlet(0.005), Langevin(0.005, 1.0, 1.0, seed=1), RESPA(0.005)
    assert isinstance(verlet, Integrator) and isinstance(verlet, Constrained)
    assert verlet.constraints is None and constraints_of(verlet) is None
    assert not isinstance(verlet, ThermoTerms | Restartable | ForceSplit)
    assert isinstance(langevin, ThermoTerms) and isinstance(langevin, Restartable)
    assert isinstance(langevin, Statistics) and langevin.statistics["steps"] == 0
    assert isinstance(respa, ForceSplit) and not isinstance(verlet, ForceSplit)


def test_an_integrator_without_hooks_is_treated_as_before(fcc_lattice, tmp_path):
    plain = _PlainVerlet(0.005)
    assert isinstance(plain, Integrator)
    assert not isinstance(plain, Constrained | ThermoTerms | Restartable | Statistics | ForceSplit)
    start = fcc_lattice(cells=3, perturbation=0.02, temperature=0.5)
    sim = _sim(start, plain)
    reference = _sim(start, VelocityVerlet(0.005))
    sim.run(5)
    reference.run(5)
    np.testing.assert_array_equal(sim.state.positions, reference.state.positions)
    row = sim.thermo()
    assert "conserved_energy" not in row  # no thermo_terms: no bath energy
    assert row["temperature"] == reference.thermo()["temperature"]  # 3N degrees of freedom
    assert constraints_of(plain) is None
    assert len(run_topology(sim).bonds) == 0
    # No private state: the checkpoint holds none and restores into the plain integrator.
    path = write_checkpoint(tmp_path / "plain.ckpt", sim.state, plain, sim.forcefield)
    saved = read_checkpoint(path)
    assert saved.integrator_state is None
    restore(saved, _PlainVerlet(0.005), sim.forcefield)


def test_a_duck_typed_integrator_offering_hooks_is_honoured(fcc_lattice, tmp_path):
    bath = _BathVerlet(0.005)
    assert isinstance(bath, ThermoTerms) and isinstance(bath, Restartable)
    assert not isinstance(bath, IntegratorBase)
    sim = _sim(fcc_lattice(cells=3, perturbation=0.02, temperature=0.5), bath)
    sim.run(3)
    row = sim.thermo()
    assert row["conserved_energy"] == row["total_energy"] + 0.25
    path = write_checkpoint(tmp_path / "bath.ckpt", sim.state, bath, sim.forcefield)
    again = _BathVerlet(0.005)
    restore(read_checkpoint(path), again, sim.forcefield)
    assert again.counter == 3
    # A checkpoint with private state cannot go into an integrator without set_state.
    with pytest.raises(CheckpointError, match="cannot take it"):
        restore(read_checkpoint(path), _PlainVerlet(0.005), sim.forcefield)


def test_pressure_coupling_passes_on_only_the_hooks_its_thermostat_has():
    bonds = BondConstraints([[0, 1]], lengths=[1.0])
    constrained = Langevin(0.005, 1.0, 1.0, seed=1, constraints=bonds)
    coupled = PressureCoupled(
        constrained, Barostat("c_rescale", pressure=1.0, tau=1.0, compressibility=1.0)
    )
    assert constraints_of(coupled) is bonds
    assert coupled.statistics == {
        "steps": 0,
        "shake_iterations": 0,
        "rattle_iterations": 0,
        "barostat_moves": 0,
    }

    class PlainThermostat(_BathVerlet):
        thermostat = True
        kT = 1.0

    bare = PressureCoupled(
        PlainThermostat(0.005), Barostat("c_rescale", pressure=1.0, tau=1.0, compressibility=1.0)
    )
    assert constraints_of(bare) is None
    assert bare.statistics == {"barostat_moves": 0}
    assert bare.get_state()["inner"] == {"counter": 0}
    with pytest.raises(ValueError, match="needs a thermostat"):
        PressureCoupled(
            _PlainVerlet(0.005), Barostat("c_rescale", pressure=1.0, tau=1.0, compressibility=1.0)
        )


class _VirialSpy(LennardJones):
    """LJ that records whether each evaluation was asked for the virial."""

    def __init__(self) -> None:
        super().__init__(cutoff=2.5)
        self.asked: list[bool] = []

    def energy_forces(self, state, neighbors, per_atom=False, virial=True) -> ForceResult:
        self.asked.append(virial)
        return super().energy_forces(state, neighbors, per_atom=per_atom, virial=virial)


def test_observers_without_uses_virial_get_the_virial(fcc_lattice):
    start = fcc_lattice(cells=3, temperature=0.5)
    asked = {}
    for declares in (None, True, False):
        spy = _VirialSpy()
        sim = md.Simulation(start.copy(), [spy], VelocityVerlet(0.005))

        def observer(sim) -> None:
            pass

        if declares is not None:
            observer.uses_virial = declares
        assert isinstance(observer, VirialUse) == (declares is not None)
        sim.attach(observer, interval=2)
        sim.run(6)
        asked[declares] = sum(spy.asked)
    # Steps 2, 4 and 6 end with an observer: their forces carry the virial unless it says no.
    assert asked[None] == asked[True] == asked[False] + 3
    assert isinstance(Progress(None), VirialUse) and not Progress(None).uses_virial


def test_end_step_advances_step_and_time_as_repeated_addition(fcc_lattice):
    for name in ("verlet", "leapfrog", "pefrl", "rk4", "implicit_midpoint", "respa"):
        dt = 0.0031
        state = fcc_lattice(cells=3, perturbation=0.01, temperature=0.3)
        potentials = [LennardJones(cutoff=2.5)]
        if name == "respa":
            potentials.append(HarmonicBonds([[0, 1]], k=1.0, r0=1.0))
        sim = md.Simulation(state, potentials, INTEGRATORS[name](dt))
        sim.run(7)
        expected = 0.0
        for _ in range(7):
            expected += dt
        assert state.step == 7 and state.time == expected, name


def test_the_calculator_asks_potentials_for_typed_parameters_through_the_protocol():
    assert isinstance(LennardJones(sigma=[1.0, 1.2], epsilon=[1.0, 1.0]), TypedParameters)
    assert LennardJones(sigma=[1.0, 1.2], epsilon=[1.0, 1.0]).per_type_parameters
    assert LennardJones(pairs={(0, 1): {"sigma": 1.1}}).per_type_parameters
    assert not LennardJones().per_type_parameters
    MDCalculator([LennardJones()])  # one parameter set: chemical numbers need no names
    with pytest.raises(ValueError, match="LennardJones has per-type parameters"):
        MDCalculator([LennardJones(sigma=[1.0, 1.2], epsilon=[1.0, 1.0])])

    class Typed(LennardJones):
        """Scalar LJ that declares per-type parameters: the declaration is what counts."""

        per_type_parameters = True

    with pytest.raises(ValueError, match="Typed has per-type parameters"):
        MDCalculator([Typed()])
    assert MDCalculator([Typed()], type_names=["Ar"]).type_names == ("Ar",)


def test_run_summary_reports_the_integrators_counters_and_the_drift(tmp_path, lj_config):
    config = tmp_path / "run.toml"
    config.write_text(lj_config(integrator='type = "leapfrog"\ndt = 0.005', run="steps = 20"))
    sim, summary = md.run_config(config, output=tmp_path / "run.h5")
    assert summary.status == "completed"
    assert summary.statistics == {"steps": 20, "restarts": 1} == sim.integrator.statistics
    assert summary.per_step() == {"restarts": 1 / 20}
    first, last = summary.first, summary.last
    scale = max(abs(first["total_energy"]), first["kinetic_energy"])
    assert summary.relative_change() == (last["total_energy"] - first["total_energy"]) / scale
    assert math.isnan(summary.relative_change("conserved_energy"))  # no thermostat


def test_run_summary_without_counters_or_a_last_row():
    summary = RunSummary("failed", Path("x.h5"), Path("x.h5.ckpt"), 10, first={"total_energy": 1.0})
    assert summary.statistics == {} and summary.per_step() == {}
    assert math.isnan(summary.relative_change())
