"""Thermostats: canonical sampling, conserved quantities, reproducibility, configs, the study.

The canonical thermostats (Langevin BAOAB, Bussi, Nose-Hoover chains) are
checked on what they claim: on a small LJ liquid the mean kinetic
temperature equals the target within its standard error and the kinetic
energy follows the Gamma distribution of n_dof / 2 and kT; on harmonic
tethers the positions have variance kT / k; the conserved quantities of
Bussi and Nose-Hoover chains do not drift; the mean potential energy agrees
with ASE's Langevin on the same system (slow). Berendsen reaches the target
but suppresses the fluctuations, and says so in the log.
"""

from __future__ import annotations

import csv
import logging
import math

import numpy as np
import pytest
from scipy import stats

import md
from conftest import lj_config_text
from integrators import (
    INTEGRATORS,
    Berendsen,
    Bussi,
    Langevin,
    NoseHooverChain,
    VelocityVerlet,
)
from md.checkpoint import read_checkpoint, restore, write_checkpoint
from md.cli import main
from md.config import ConfigError, integrator_from_config, parse_config
from md.observers import ThermoLog
from md.studies import compare_thermostats, statistical_inefficiency
from potentials import ForceResult, LennardJones

T0 = 1.2  # target temperature of the LJ liquid [eps/kB]
DT = 0.005
CANONICAL = {
    "langevin": lambda: Langevin(DT, T0, friction=5.0, seed=11),
    "bussi": lambda: Bussi(DT, T0, tau=0.05, seed=11),
    "nose_hoover_chain": lambda: NoseHooverChain(DT, T0, tau=0.1),
}


def _liquid() -> md.State:
    """108 LJ atoms at the triple-point density, started at the target temperature."""
    return md.maxwell_boltzmann(md.lattice("fcc", 3, density=0.8442), T0, seed=5)


def _lj():
    return [LennardJones(cutoff=2.5, cutoff_mode="smooth", r_on=2.0)]


def _sample(integrator, n_equilibrate=1000, n_sample=15000, state=None):
    """Run on the liquid; return the thermo rows of every sampled step and the simulation."""
    sim = md.Simulation(state if state is not None else _liquid(), _lj(), integrator)
    sim.run(n_equilibrate)
    log = ThermoLog()
    sim.attach(log, interval=1)
    sim.run(n_sample)
    return log.rows, sim


def _column(rows, key) -> np.ndarray:
    return np.array([row[key] for row in rows])


def _mean_and_error(values) -> tuple[float, float]:
    values = np.asarray(values)
    g = statistical_inefficiency(values)
    return float(values.mean()), math.sqrt(values.var() * g / len(values))


# --------------------------------------------------------- canonical sampling
@pytest.fixture(scope="module")
def canonical_runs():
    """One 15000-step run (75 tau) per canonical thermostat, shared by the sampling tests."""
    return {name: _sample(make()) for name, make in CANONICAL.items()}


@pytest.mark.parametrize("name", list(CANONICAL))
def test_mean_temperature_is_the_target(canonical_runs, name):
    """Within 3 standard errors (about 1 %); BAOAB's end-of-step velocities read
    about 0.2 % low at this dt (see Langevin), well inside that."""
    rows, sim = canonical_runs[name]
    mean, error = _mean_and_error(_column(rows, "temperature"))
    assert error < 0.01 * T0  # the run is long enough for the check to mean something
    assert abs(mean - T0) < 3.0 * error, f"{name}: T = {mean:.4f} +- {error:.4f}"


@pytest.mark.parametrize("name", list(CANONICAL))
def test_kinetic_energy_follows_the_gamma_distribution(canonical_runs, name):
    """K of a canonical system with n_dof quadratic terms is Gamma(n_dof / 2, scale kT)."""
    rows, sim = canonical_runs[name]
    kinetic = _column(rows, "kinetic_energy")
    n_dof = sim.integrator.degrees_of_freedom(sim.state.n_atoms)
    assert n_dof == 3 * 108 - 3
    stride = math.ceil(statistical_inefficiency(kinetic))
    independent = kinetic[::stride]
    assert len(independent) > 250
    result = stats.kstest(independent, stats.gamma(n_dof / 2, scale=T0).cdf)
    assert result.pvalue > 0.01, f"{name}: KS p = {result.pvalue:.3g}"
    # The variance carries the ensemble: canonical var(K) = n_dof / 2 (kT)^2.
    assert np.var(independent) == pytest.approx(n_dof / 2 * T0**2, rel=0.2)


def test_berendsen_reaches_the_target_but_is_not_canonical(caplog):
    """Same test as the canonical thermostats: Berendsen fails it (the test has power)."""
    with caplog.at_level(logging.WARNING, logger="integrators.berendsen"):
        berendsen = Berendsen(DT, T0, tau=0.1)
    assert any("does not sample the canonical" in r.getMessage() for r in caplog.records)
    assert "not** sample the canonical" in Berendsen.__doc__
    rows, sim = _sample(berendsen, n_sample=6000)
    kinetic = _column(rows, "kinetic_energy")
    mean, error = _mean_and_error(_column(rows, "temperature"))
    assert abs(mean - T0) < 0.02 * T0
    n_dof = 3 * 108 - 3
    assert np.var(kinetic) < 0.3 * n_dof / 2 * T0**2  # fluctuations suppressed
    stride = math.ceil(statistical_inefficiency(kinetic))
    assert stats.kstest(kinetic[::stride], stats.gamma(n_dof / 2, scale=T0).cdf).pvalue < 1e-6


# ------------------------------------------------------------ conserved energy
@pytest.mark.parametrize("name", ["bussi", "nose_hoover_chain"])
def test_conserved_quantity_does_not_drift(canonical_runs, name):
    """Bound: drift below 2e-4 eps per atom per tau over 75 tau, and the conserved
    quantity's spread within 3x the total-energy spread of plain velocity Verlet
    at the same dt, while the heat bath exchanged far more than that."""
    rows, sim = canonical_runs[name]
    times = _column(rows, "time")
    conserved = _column(rows, "conserved_energy") / 108
    total = _column(rows, "total_energy") / 108
    slope, intercept = np.polyfit(times, conserved, 1)
    assert abs(slope) < 2e-4
    verlet_rows, _ = _sample(VelocityVerlet(DT), n_equilibrate=0, n_sample=4000, state=sim.state)
    verlet_spread = np.std(_column(verlet_rows, "total_energy") / 108)
    assert np.std(conserved - slope * times) < 3.0 * verlet_spread
    assert np.ptp(total) > 50 * np.ptp(conserved)  # the bath did exchange energy


def test_langevin_heat_balance():
    """Langevin's reservoir books the O-step heat: the conserved quantity only
    carries the O(dt^2) splitting error, far below the heat exchanged."""
    rows, sim = _sample(Langevin(DT, T0, friction=2.0, seed=3), n_sample=4000)
    conserved = _column(rows, "conserved_energy")
    reservoir = conserved - _column(rows, "total_energy")
    assert np.ptp(reservoir) > 30 * np.std(conserved)
    slope = np.polyfit(_column(rows, "time"), conserved / 108, 1)[0]
    assert abs(slope) < 1e-3


# ---------------------------------------------------------- harmonic tethers
class Tether:
    """Test-only external potential u = sum k_ia x_ia^2 / 2 (springs to the origin)."""

    cutoff = None

    def __init__(self, k) -> None:
        self.k = np.asarray(k, dtype=float)

    def energy_forces(self, state, neighbors, per_atom=False, virial=True) -> ForceResult:
        x = state.positions
        energies = 0.5 * self.k * x * x
        forces = -self.k * x
        return ForceResult(
            energy=float(energies.sum()),
            forces=forces,
            virial=np.einsum("ia,ib->ab", x, forces),
            energies=energies.sum(axis=1) if per_atom else None,
        )

    def check(self, state) -> None:
        pass

    def describe(self) -> dict:
        return {"type": "tether"}


def _tethered(integrator, k, n_steps, kT, velocities=None):
    state = md.State(positions=np.zeros(k.shape), masses=1.0, box=100.0, pbc=False)
    md.maxwell_boltzmann(state, kT, seed=4)
    forcefield = md.ForceField([Tether(k)])
    for _ in range(500):
        integrator.step(state, forcefield)
    positions = np.empty((n_steps, *k.shape))
    for n in range(n_steps):
        integrator.step(state, forcefield)
        positions[n] = state.positions
        if velocities is not None:
            velocities[n] = state.velocities
    return positions


def test_langevin_harmonic_variance_is_kT_over_k(rng):
    """BAOAB samples a harmonic system's positions exactly at any stable dt, so every
    coordinate has variance kT / k_ia even at omega dt = 0.28; its end-of-step
    velocities have variance (kT / m)(1 - dt^2 k / 4m) (Leimkuhler and Matthews)."""
    k = rng.uniform(0.5, 2.0, size=(8, 3))
    kT, dt, n_steps = 1.5, 0.2, 40000
    velocities = np.empty((n_steps, *k.shape))
    integrator = Langevin(dt, kT, friction=1.0, seed=8, fix_com=False)
    positions = _tethered(integrator, k, n_steps, kT, velocities)
    ratio = positions.var(axis=0) * k / kT
    g = max(statistical_inefficiency(positions[:, i, a]) for i in range(8) for a in range(3))
    error = math.sqrt(2.0 * g / n_steps)  # standard error of one variance ratio
    assert np.all(np.abs(ratio - 1.0) < 4.0 * error), ratio
    assert abs(ratio.mean() - 1.0) < 4.0 * error / math.sqrt(ratio.size)
    g = max(statistical_inefficiency(velocities[:, i, a]) for i in range(8) for a in range(3))
    error = math.sqrt(2.0 * g / n_steps / k.size)  # of the mean over coordinates
    kinetic = velocities.var(axis=0) / kT
    assert abs((kinetic / (1.0 - dt**2 * k / 4.0)).mean() - 1.0) < 3.0 * error
    assert abs(kinetic.mean() - 1.0) > 2.0 * error  # the dt^2 bias is resolved


@pytest.mark.parametrize(
    "make",
    [
        lambda kT: Bussi(0.05, kT, tau=0.5, seed=8, fix_com=False),
        lambda kT: NoseHooverChain(0.05, kT, tau=0.5, fix_com=False),
    ],
    ids=["bussi", "nose_hoover_chain"],
)
def test_global_thermostats_harmonic_variance(rng, make):
    """sum_ia k_ia <x_ia^2> = 3 N kT: the mean of var(x) k / kT over coordinates is 1.

    A global thermostat scales every velocity by one factor, which shares energy
    among a harmonic system's independent normal modes only very slowly, so
    the variance of each coordinate on its own converges slowly (Langevin's
    test above checks each); their mean converges as fast as the total energy.
    """
    k = rng.uniform(0.5, 2.0, size=(8, 3))
    kT = 1.5
    positions = _tethered(make(kT), k, 20000, kT)
    potential = 0.5 * np.einsum("nia,ia->n", positions**2, k)
    mean, error = _mean_and_error(potential / (0.5 * k.size * kT))
    assert error < 0.02
    assert abs(mean - 1.0) < 4.0 * error


# --------------------------------------------------------- ASE reference (slow)
@pytest.mark.slow
def test_mean_potential_energy_agrees_with_ase_langevin():
    """Our Langevin, Bussi and Nose-Hoover chains against ASE's Langevin driven by our
    calculator (energy-shifted cutoff) on the same 108 atoms, eps = sigma = m = 1 read
    as eV, Angstrom, amu: same mean potential energy within the combined standard
    error."""
    from ase import units
    from ase.constraints import FixCom
    from ase.md.langevin import Langevin as AseLangevin

    from md.calculator import MDCalculator

    temperature = 1.0
    start = md.maxwell_boltzmann(md.lattice("fcc", 3, density=0.8442), temperature, seed=9)
    atoms = start.to_ase()
    atoms.set_masses(np.ones(len(atoms)))
    atoms.set_constraint(FixCom())
    atoms.calc = MDCalculator([LennardJones(cutoff=2.5, cutoff_mode="shift")])
    dyn = AseLangevin(
        atoms,
        timestep=DT,
        temperature_K=temperature / units.kB,
        friction=2.0,
        fixcm=False,
        rng=np.random.default_rng(2),
    )
    dyn.run(1000)
    reference = []
    dyn.attach(lambda: reference.append(atoms.get_potential_energy() / len(atoms)), interval=1)
    dyn.run(20000)
    ase_mean, ase_error = _mean_and_error(reference)

    ours = {
        "langevin": Langevin(DT, temperature, friction=2.0, seed=2),
        "bussi": Bussi(DT, temperature, tau=0.1, seed=2),
        "nose_hoover_chain": NoseHooverChain(DT, temperature, tau=0.1),
    }
    for name, integrator in ours.items():
        sim = md.Simulation(
            start.copy(), [LennardJones(cutoff=2.5, cutoff_mode="shift")], integrator
        )
        sim.run(2000)
        log = ThermoLog()
        sim.attach(log, interval=1)
        sim.run(30000)
        mean, error = _mean_and_error(_column(log.rows, "potential_energy") / 108)
        combined = math.hypot(error, ase_error)
        assert combined < 0.01
        assert abs(mean - ase_mean) < 3.5 * combined, (name, mean, error, ase_mean, ase_error)


# ------------------------------------------------------------- reproducibility
@pytest.mark.parametrize(
    "make",
    [
        lambda seed: Langevin(DT, T0, friction=1.0, seed=seed),
        lambda seed: Bussi(DT, T0, tau=0.1, seed=seed),
    ],
    ids=["langevin", "bussi"],
)
def test_same_seed_same_trajectory(make):
    runs = []
    for seed in (4, 4, 5):
        sim = md.Simulation(_liquid(), _lj(), make(seed))
        sim.run(50)
        runs.append(sim.state.positions.copy())
    assert np.array_equal(runs[0], runs[1])
    assert not np.allclose(runs[0], runs[2])


@pytest.mark.parametrize(
    "make",
    [
        lambda: Langevin(DT, T0, friction=1.0, seed=6),
        lambda: Bussi(DT, T0, tau=0.1, seed=6),
        lambda: NoseHooverChain(DT, T0, tau=0.1),
        lambda: Berendsen(DT, T0, tau=0.1),
    ],
    ids=["langevin", "bussi", "nose_hoover_chain", "berendsen"],
)
def test_saved_thermostat_state_continues_the_run_exactly(make, tmp_path):
    """get_state() / set_state() carry the random stream, chain and reservoir, through a
    checkpoint (which also has the neighbour list built where it was: its wraps decide
    the last bits of the pair separations)."""
    first = make()
    sim = md.Simulation(_liquid(), _lj(), first)
    sim.run(40)
    saved = first.get_state()
    write_checkpoint(tmp_path / "at40.ckpt", sim.state, first, sim.forcefield)
    sim.run(40)
    expected = sim.thermo()

    checkpoint = read_checkpoint(tmp_path / "at40.ckpt")
    second = make()  # a fresh object, as after reading a checkpoint
    resumed = md.Simulation(checkpoint.state, _lj(), second)
    restore(checkpoint, second, resumed.forcefield)
    resumed.run(40)
    assert np.array_equal(resumed.state.positions, sim.state.positions)
    assert np.array_equal(resumed.state.velocities, sim.state.velocities)
    assert resumed.thermo()["conserved_energy"] == expected["conserved_energy"]
    import json

    json.dumps(saved)  # plain data, storable in a checkpoint file


def test_langevin_zero_friction_is_velocity_verlet():
    a = md.Simulation(_liquid(), _lj(), Langevin(DT, T0, friction=0.0, seed=1))
    b = md.Simulation(_liquid(), _lj(), VelocityVerlet(DT))
    a.run(100)
    b.run(100)
    np.testing.assert_allclose(a.state.positions, b.state.positions, rtol=0, atol=1e-10)
    assert a.thermo()["conserved_energy"] == pytest.approx(b.thermo()["total_energy"], abs=1e-12)


def test_fix_com_keeps_the_total_momentum_zero():
    sim = md.Simulation(_liquid(), _lj(), Langevin(DT, T0, friction=5.0, seed=1))
    sim.run(200)
    momentum = (sim.state.masses[:, None] * sim.state.velocities).sum(axis=0)
    assert np.abs(momentum).max() < 1e-11
    free = Langevin(DT, T0, friction=5.0, seed=1, fix_com=False)
    sim = md.Simulation(_liquid(), _lj(), free)
    sim.run(200)
    momentum = (sim.state.masses[:, None] * sim.state.velocities).sum(axis=0)
    assert np.abs(momentum).max() > 0.1  # the noise moves the centre of mass
    assert free.degrees_of_freedom(108) == 324


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: Langevin(DT, -1.0, friction=1.0), "temperature"),
        (lambda: Langevin(DT, T0, friction=-1.0), "friction"),
        (lambda: Langevin(DT, T0, friction=1.0, seed="x"), "seed"),
        (lambda: Bussi(DT, T0, tau=0.0), "tau"),
        (lambda: Bussi(0.0, T0, tau=0.1), "dt"),
        (lambda: NoseHooverChain(DT, 0.0, tau=0.1), "temperature"),
        (lambda: NoseHooverChain(DT, T0, tau=0.1, chain_length=0), "chain_length"),
        (lambda: Berendsen(DT, float("nan"), tau=0.1), "temperature"),
        (lambda: Berendsen(DT, T0, tau=0.1, kB=0.0), "kB"),
    ],
)
def test_bad_parameters_are_named(make, message):
    with pytest.raises(ValueError, match=message):
        make()


# ------------------------------------------------------------------ configs
NVT = """\
units = "{units}"
seed = 3

[system]
lattice = "fcc"
cells = 3
density = 0.8442
temperature = {temperature}

[[potentials]]
type = "lj"
cutoff = 2.5

[integrator]
type = "{kind}"
dt = {dt}
temperature = {temperature}
{extra}
"""


def _config(kind="langevin", units="lj", temperature=1.2, dt=0.005, extra="friction = 2.0"):
    text = NVT.format(units=units, temperature=temperature, kind=kind, dt=dt, extra=extra)
    import tomllib

    return parse_config(tomllib.loads(text), source="nvt.toml", text=text)


def test_config_converts_thermostat_units_metal():
    """Metal configs give T in K, tau in fs and friction in 1/fs; the engine gets kB."""
    from md import units

    config = _config(units="metal", temperature=300.0, dt=2.0, extra="friction = 0.01")
    langevin = integrator_from_config(config.integrator, config.source)
    assert isinstance(langevin, Langevin)
    assert langevin.dt == pytest.approx(2.0 * units.fs)
    assert langevin.friction == pytest.approx(0.01 / units.fs)
    assert langevin.kT == pytest.approx(300.0 * units.kB)
    config = _config("nose_hoover_chain", "metal", 300.0, 2.0, "tau = 100.0\nchain_length = 4")
    chain = integrator_from_config(config.integrator, config.source)
    assert chain.tau == pytest.approx(100.0 * units.fs) and chain.chain_length == 4
    assert chain.kT == pytest.approx(300.0 * units.kB)


def test_config_seeds_the_thermostat_from_the_top_level_seed():
    a = integrator_from_config(_config().integrator, "nvt.toml")
    b = integrator_from_config(_config().integrator, "nvt.toml")
    assert np.array_equal(a.key, b.key)  # Langevin's noise is keyed by the seed alone
    assert a.describe()["seed"] == [3, 1]  # a stream apart from the velocity draw's


@pytest.mark.parametrize(
    ("kind", "extra", "message"),
    [
        ("langevin", "", "friction"),
        ("bussi", "friction = 1.0", "friction"),
        ("bussi", "", "tau"),
        ("bussi", "tau = -1.0", "tau"),
        ("verlet", "", "temperature"),
        ("nhc", "tau = 0.5\nchain_length = 0", "chain_length"),
    ],
)
def test_bad_thermostat_configs_name_the_problem(kind, extra, message):
    with pytest.raises(ConfigError, match=message):
        config = _config(kind, extra=extra)
        integrator_from_config(config.integrator, config.source)


def test_run_prints_the_conserved_quantity(tmp_path, capsys):
    path = tmp_path / "nvt.toml"
    text = NVT.format(units="lj", temperature=1.2, kind="bussi", dt=0.005, extra="tau = 0.1")
    path.write_text(text + '\n[run]\nsteps = 40\nthermo_every = 20\n\n[output]\npath = "o.h5"\n')
    assert main(["run", str(path), "--no-progress", "-o", str(tmp_path / "o.h5")]) == 0
    out = capsys.readouterr().out
    assert "Conserved" in out and "conserved-quantity drift" in out


def test_berendsen_run_logs_the_warning(tmp_path, caplog):
    """md run configures no logging, so Python prints the warning on stderr."""
    path = tmp_path / "nvt.toml"
    text = NVT.format(units="lj", temperature=1.2, kind="berendsen", dt=0.005, extra="tau = 0.1")
    path.write_text(text + '\n[run]\nsteps = 5\n\n[output]\npath = "o.h5"\n')
    with caplog.at_level(logging.WARNING):
        assert main(["run", str(path), "--no-progress", "-q", "-o", str(tmp_path / "o.h5")]) == 0
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert any("does not sample the canonical ensemble" in r.getMessage() for r in warnings)


def test_registry_names():
    assert INTEGRATORS["langevin"] is Langevin and INTEGRATORS["bussi"] is Bussi
    assert INTEGRATORS["nose_hoover_chain"] is INTEGRATORS["nhc"] is NoseHooverChain
    assert INTEGRATORS["berendsen"] is Berendsen


# ------------------------------------------------------------------ the study
def test_statistical_inefficiency_of_an_ar1_process(rng):
    """AR(1) x_n = phi x_{n-1} + noise has g = (1 + phi) / (1 - phi)."""
    phi, n = 0.9, 200_000
    noise = rng.standard_normal(n)
    x = np.empty(n)
    x[0] = 0.0
    for i in range(1, n):
        x[i] = phi * x[i - 1] + noise[i]
    assert statistical_inefficiency(x) == pytest.approx((1 + phi) / (1 - phi), rel=0.1)
    assert statistical_inefficiency(rng.standard_normal(10_000)) == pytest.approx(1.0, abs=0.1)


@pytest.mark.parametrize("friction", [0.5, 6.0], ids=["underdamped", "overdamped"])
def test_study_autocorrelation_time_matches_langevin_oscillator_theory(friction):
    """For Langevin oscillators (omega = 1) x(t) is Gaussian with normalised correlation
    C(t) = exp(-gamma t / 2) (cos w t + gamma / (2 w) sin w t), w^2 = omega^2 - gamma^2 / 4,
    so the potential energy (a sum of x^2) has correlation C(t)^2 and integrated
    autocorrelation time int_0^inf C(t)^2 dt: the study must measure that."""
    from scipy.integrate import quad

    gamma, omega = friction, 1.0
    w = complex(omega**2 - gamma**2 / 4) ** 0.5

    def correlation(t):
        return (np.exp(-gamma * t / 2) * (np.cos(w * t) + gamma / (2 * w) * np.sin(w * t))).real

    expected = quad(lambda t: correlation(t) ** 2, 0, 200.0, limit=500)[0]
    k = np.ones((64, 3))

    def make_state():
        state = md.State(positions=np.zeros((64, 3)), masses=1.0, box=100.0, pbc=False)
        return md.maxwell_boltzmann(state, 1.0, seed=2)

    (report,) = compare_thermostats(
        make_state=make_state,
        potentials_factory=lambda: [Tether(k)],
        thermostats={"langevin": lambda: Langevin(0.05, 1.0, friction, seed=3, fix_com=False)},
        target_temperature=1.0,
        n_equilibrate=500,
        n_sample=40000,
        sample_every=2,
    )
    # 2000 time units give the estimate a relative standard error of about 0.1.
    assert report.potential_autocorrelation_time == pytest.approx(expected, rel=0.3)
    assert report.sampling_efficiency == pytest.approx(1 / (2 * expected), rel=0.3)
    assert report.mean_potential_energy == pytest.approx(1.5, rel=0.03)  # 3 kT / 2 per atom
    assert report.evals_per_time == pytest.approx(1 / 0.05, rel=0.01)


STUDY = lj_config_text(
    seed=3, potential='cutoff_mode = "smooth"\nr_on = 2.0', run=None, output=None
)


def test_cli_study_reports_thermostats(tmp_path, capsys):
    config = tmp_path / "study.toml"
    config.write_text(STUDY)
    out = tmp_path / "study"
    names = "langevin,bussi,nhc,berendsen"
    args = [
        "integrators",
        str(config),
        "--integrators",
        names,
        "--tau",
        "0.1",
        "--sample-time",
        "8",
        "--out",
        str(out),
    ]
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "T_mean" in text and "tau_PE" in text
    assert not (out / "integrators.csv").exists()  # only thermostats were named
    with open(out / "thermostats.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert [row["thermostat"] for row in rows] == ["langevin", "bussi", "nhc", "berendsen"]
    assert [row["canonical"] for row in rows] == ["True"] * 3 + ["False"]
    assert "(not canonical)" in text
    for row in rows:
        assert float(row["target_temperature"]) == 1.2
        error, stderr = float(row["temperature_error"]), float(row["temperature_stderr"])
        assert 0 < stderr < 0.05 and abs(error) < 4 * stderr
        assert float(row["potential_autocorrelation_time"]) > 0
        assert abs(float(row["conserved_drift"])) < 1e-3
    assert (out / "thermostats.png").read_bytes().startswith(b"\x89PNG")


def test_cli_study_needs_a_temperature_for_thermostats(tmp_path, capsys):
    config = tmp_path / "study.toml"
    config.write_text(STUDY.replace("temperature = 1.2\n", ""))
    assert (
        main(["integrators", str(config), "--integrators", "bussi", "--out", str(tmp_path / "o")])
        == 2
    )
    assert "target temperature" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
