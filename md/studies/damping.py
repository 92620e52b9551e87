"""Numerical damping as a number: amplitude ratio and phase per step on a harmonic bond.

An implicit method damps a vibration whose period is short against its
time step: stiff bonds lose their energy instead of blowing up. How much it
damps a mode of angular frequency omega depends only on omega dt, through
the method's amplification factor rho(omega dt) on the harmonic oscillator:
the amplitude is multiplied by |rho| per step, and the phase advances by
arg(rho) instead of omega dt.

:func:`measure_damping` measures both from trajectories: for every
integrator and every omega dt on a ladder (default 0.01 to 100) it runs a
two-bead harmonic bond of zero rest length (exactly linear forces, so the
bond is the harmonic oscillator, and no rest length whose round-off would
limit how far the amplitude can fall) at the integrator's dt, with the
spring constant set to give that omega dt, and fits the bead separation
x_n (one axis) with the linear recurrence that any linear p-step method's
output obeys, x_{n+1} = sum_k c_k x_{n+1-k} (2 terms for a one-step
method, 4 for a two-step one; Prony's method), by least squares over a few
dozen steps. The roots of 1 - sum_k c_k z^-k are the measured amplification
factors; the one of largest modulus is the principal root: ``measured`` is
its modulus (the amplitude ratio per step) and ``phase_measured`` its
argument. ``theory`` and ``phase_theory`` come from the integrator's
``amplification(omega_dt)`` (:class:`integrators.base.SupportsAmplification`),
derived for each method in its docstring.

This module is library code: it returns rows, writes the CSV and draws the
figure; ``md integrators --damping`` prints the table.
"""

from __future__ import annotations

import inspect
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from integrators import INTEGRATORS
from integrators.base import SupportsAmplification
from md._files import write_csv_rows
from md.config import Config, load_config
from md.errors import ConfigError, ConvergenceError, NonFiniteError
from md.forcefield import ForceField
from md.state import State
from md.studies.plot_style import grouped, legend_outside, styles
from potentials.springs import HarmonicBonds

#: The default ladder of omega dt: 0.01 to 100, four points per decade.
OMEGA_DT = tuple(float(z) for z in np.geomspace(0.01, 100.0, 17))
#: Columns of ``damping.csv``.
DAMPING_COLUMNS = (
    "integrator",
    "omega_dt",
    "measured",
    "theory",
    "damping_measured",
    "damping_theory",
    "phase_measured",
    "phase_theory",
    "phase_error",
    "steps_fitted",
    "note",
)
#: Steps fitted per recurrence term: enough equations that round-off averages out,
#: few enough that a heavily damped signal stays far above the smallest doubles.
_STEPS_PER_TERM = 8
#: Signal values below this fraction of the start are left out of the fit.
_SMALLEST = 1e-250
#: The solver tolerance of implicit integrators in the measurement: tight enough that
#: the damping measured is the method's (a loose solve changes it; tested), loose
#: enough for the round-off floor at omega dt = 100 (a residual of ~2e-12).
SOLVER_TOL = 1e-11
#: Output files of ``md integrators --damping``.
DAMPING_FILES = {"csv": "damping.csv", "plot": "damping.png"}
#: Damping per step below this is drawn as none (round-off of |rho| = 1).
_NO_DAMPING = 1e-11
#: A run stops once its signal has fallen below this fraction of the start (and
#: enough steps are in).
_FALLEN = 1e-8


@dataclass
class DampingRow:
    """One integrator at one omega dt (see the module docstring).

    ``measured`` and ``theory`` are |rho| per step; ``damping_*`` = 1 - |rho|;
    ``phase_*`` = arg(rho) [radians per step]; ``phase_error`` =
    phase_measured / omega_dt - 1 (0 when the phase is exact; it cannot reach
    omega dt > pi, where a step samples less than two points per period).
    ``note`` says why a row has no measurement.
    """

    integrator: str
    omega_dt: float
    measured: float = math.nan
    theory: float = math.nan
    phase_measured: float = math.nan
    phase_theory: float = math.nan
    steps_fitted: int = 0
    note: str = ""

    @property
    def damping_measured(self) -> float:
        return 1.0 - self.measured

    @property
    def damping_theory(self) -> float:
        return 1.0 - self.theory

    @property
    def phase_error(self) -> float:
        return self.phase_measured / self.omega_dt - 1.0

    def row(self) -> dict:
        return {name: getattr(self, name) for name in DAMPING_COLUMNS}  # its own fields


def bond_oscillator(omega: float, mass: float = 1.0, amplitude: float = 0.1):
    """Return ``(state, potentials)``: two beads of ``mass`` on a zero-length harmonic bond.

    The spring constant k = mass omega^2 / 2 gives the separation angular
    frequency ``omega`` (reduced mass mass / 2); the beads start at rest,
    ``amplitude`` apart along x, in an open box.
    """
    k = 0.5 * mass * omega * omega
    half = 0.5 * amplitude
    state = State(
        positions=[[half, 0.0, 0.0], [-half, 0.0, 0.0]], masses=mass, box=[1.0e3] * 3, pbc=False
    )
    return state, [HarmonicBonds([[0, 1]], k=k, r0=0.0)]


def measure_damping(
    integrators: dict[str, Callable[[float], object]],
    omega_dts: Sequence[float] = OMEGA_DT,
    dt: float = 1.0,
    mass: float = 1.0,
    progress: Callable[[str], None] | None = None,
) -> list[DampingRow]:
    """Measure every integrator's amplitude ratio and phase per step over ``omega_dts``.

    Parameters
    ----------
    integrators : dict
        Name -> factory ``f(dt)`` returning the integrator; implicit ones should
        be built with a tight solver tolerance (1e-11), or the measurement
        measures the tolerance. Integrators without ``amplification`` are
        measured with a two-term recurrence and no theory.
    omega_dts : sequence of float
        The ladder of omega dt.
    dt : float
        The time step [time]; omega = omega_dt / dt.
    mass : float
        Bead mass [mass].

    Returns
    -------
    list of DampingRow
        One per integrator and omega dt, in that order. Where the theory says
        the method is unstable (|rho| > 1: velocity Verlet beyond omega dt = 2)
        the row has no measurement and says so; where a run fails (a solver
        that does not converge) the note gives the error.
    """
    say = progress or (lambda message: None)
    rows = []
    for name, factory in integrators.items():
        say(f"{name}: omega dt {min(omega_dts):g} to {max(omega_dts):g}")
        for omega_dt in omega_dts:
            integrator = factory(dt)
            row = DampingRow(name, float(omega_dt))
            n_terms = 2
            if isinstance(integrator, SupportsAmplification):
                roots = np.asarray(integrator.amplification(omega_dt))
                n_terms = len(roots)
                row.theory = float(abs(roots[0]))
                row.phase_theory = float(abs(np.angle(roots[0])))
                if row.theory > 1.0 + 1e-12:
                    row.note = (
                        f"unstable: |rho| = {row.theory:.4g} > 1 at this omega dt "
                        "(beyond the stability limit), not run"
                    )
                    rows.append(row)
                    continue
            try:
                signal = _bond_signal(integrator, omega_dt / dt, mass, n_terms)
            except (ConvergenceError, NonFiniteError, ArithmeticError, ValueError) as error:
                row.note = f"run failed: {error}"
                rows.append(row)
                continue
            principal, used = _principal_root(signal, n_terms)
            row.steps_fitted = used
            if principal is None:
                row.note = f"too few usable steps ({used}) to fit {n_terms} recurrence terms"
            else:
                row.measured = float(abs(principal))
                row.phase_measured = float(abs(np.angle(principal)))
            rows.append(row)
    return rows


def _bond_signal(integrator, omega: float, mass: float, n_terms: int) -> np.ndarray:
    """The bond's x separation at steps 0, 1, ... (the start steps of a multistep method
    left out: from step n_terms / 2 - 1 on, its state is the p-dimensional one)."""
    state, potentials = bond_oscillator(omega, mass)
    forcefield = ForceField(potentials)
    skip = n_terms // 2 - 1
    n_steps = skip + _STEPS_PER_TERM * n_terms + n_terms
    fewest = skip + 2 * n_terms + 3  # n_terms + 2 equations
    values = [state.positions[0, 0] - state.positions[1, 0]]
    for n in range(n_steps):
        integrator.step(state, forcefield)
        values.append(state.positions[0, 0] - state.positions[1, 0])
        # A heavily damped signal is fitted over its first steps only: the implicit
        # solvers' tolerance is relative to the start of each step, so once the
        # amplitude has fallen by many orders the steps carry relative errors that
        # would spoil the fit.
        if n + 2 >= fewest and max(map(abs, values[-n_terms - 1 :])) < _FALLEN * abs(values[0]):
            break
    signal = np.array(values[skip:])
    if not np.all(np.isfinite(signal)):
        raise NonFiniteError("the bond's separation became non-finite")
    return signal


def _principal_root(signal: np.ndarray, n_terms: int):
    """Fit x_{n+1} = sum_k c_k x_{n+1-k} by least squares; return (principal root, steps).

    Equations are scaled by their largest entry, so a decaying signal weighs
    its steps alike; values below _SMALLEST times the first are left out.
    Returns (None, steps) when fewer than n_terms + 2 equations remain.
    """
    # The envelope: the largest |x| over a window of n_terms + 1 steps (a single value
    # may pass through zero).
    envelope = np.array([np.max(np.abs(signal[n : n + n_terms + 1])) for n in range(len(signal))])
    small = np.flatnonzero(envelope < _SMALLEST * envelope[0])
    if len(small):
        signal = signal[: int(small[0]) + n_terms + 1]
    rows = [signal[n - n_terms : n][::-1] for n in range(n_terms, len(signal))]
    if len(rows) < n_terms + 2:
        return None, len(signal)
    matrix = np.array(rows)
    rhs = signal[n_terms:]
    sizes = np.maximum(np.max(np.abs(matrix), axis=1), np.abs(rhs))
    kept = sizes > 0.0  # an equation of zeros says nothing
    matrix, rhs, sizes = matrix[kept], rhs[kept], sizes[kept]
    if len(rhs) < n_terms + 2:
        return None, len(signal)
    weights = 1.0 / sizes
    coefficients = np.linalg.lstsq(matrix * weights[:, None], rhs * weights, rcond=None)[0]
    roots = np.roots(np.concatenate([[1.0], -coefficients]))
    principal = roots[np.argmax(np.abs(roots) + 1e-12 * np.sign(roots.imag))]
    return principal, len(signal)


def write_damping_csv(rows: Sequence[DampingRow], path) -> None:
    """Write one line per row with :data:`DAMPING_COLUMNS` (exclusive create)."""
    write_csv_rows(path, DAMPING_COLUMNS, (row.row() for row in rows))


def theory_curve(integrator, omega_dts) -> tuple[np.ndarray, np.ndarray]:
    """Return (|rho|, arg rho) of an integrator's principal root over ``omega_dts``."""
    roots = [np.asarray(integrator.amplification(z))[0] for z in omega_dts]
    return np.abs(roots), np.abs(np.angle(roots))


def plot_damping(rows: Sequence[DampingRow], theories: dict, path, time_label: str = "") -> None:
    """Draw the measured points on the theory curves, in three panels.

    Left: the amplitude ratio per step |rho| against omega dt; middle: the
    damping per step 1 - |rho| on a log scale (where the small damping of the
    second- and higher-order methods shows); right: the phase per step over
    omega dt. ``theories`` maps integrator names to an object with
    ``amplification`` (the integrator or its class) for the curves.
    """
    import matplotlib  # heavy: matplotlib only when plotting

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # heavy: matplotlib only when plotting

    names = grouped(list(dict.fromkeys(r.integrator for r in rows)))
    style = styles(names)
    fig, (left, middle, right) = plt.subplots(1, 3, figsize=(15.0, 4.6))
    measured_z = [r.omega_dt for r in rows if math.isfinite(r.measured)]
    z_low, z_high = (min(measured_z), max(measured_z)) if measured_z else (0.01, 100.0)
    dense = np.geomspace(z_low, z_high, 400)
    undamped = []
    for k, name in enumerate(names):
        s = style[name]
        mine = [r for r in rows if r.integrator == name and math.isfinite(r.measured)]
        kind = theories.get(name)
        if kind is not None:
            modulus, phase = theory_curve(kind, dense)
            stable = modulus <= 1.0 + 1e-12
            z = dense[stable]
            # Curves that coincide (implicit midpoint and the trapezoidal rule) are told
            # apart by dash offsets.
            line = {
                "color": s["color"],
                "lw": 1.0,
                "ls": (k % 4, (5, 3)) if s["linestyle"] == ":" else s["linestyle"],
            }
            left.plot(z, modulus[stable], **line)
            right.plot(z, phase[stable] / z, **line)
            damps = 1.0 - modulus[stable] > _NO_DAMPING
            if np.any(damps):
                middle.plot(z[damps], 1.0 - modulus[stable][damps], **line)
            else:
                undamped.append(name)
        if not mine:
            continue
        z = np.array([r.omega_dt for r in mine])
        modulus = np.array([r.measured for r in mine])
        phase = np.array([r.phase_measured for r in mine])
        marker = {
            "marker": s["marker"],
            "color": s["color"],
            "ls": "none",
            "ms": 5,
            "mfc": "none",
            "mew": 1.1,
        }
        left.plot(z, modulus, label=name, **marker)
        damping = 1.0 - modulus
        shown = damping > _NO_DAMPING
        middle.plot(z[shown], damping[shown], **marker)
        right.plot(z, phase / z, **marker)
    left.set_ylabel("amplitude ratio per step |rho|")
    left.set_ylim(-0.02, 1.05)
    middle.set_ylabel("numerical damping per step 1 - |rho|")
    middle.set_yscale("log")
    if undamped:
        middle.text(
            0.03,
            0.03,
            "no damping (|rho| = 1; measured within 1e-11):\n" + ", ".join(undamped),
            transform=middle.transAxes,
            fontsize="x-small",
            va="bottom",
        )
    right.set_ylabel("phase per step / (omega dt)  (1: exact)")
    right.set_yscale("log")
    for ax in (left, middle, right):
        ax.set_xscale("log")
        ax.set_xlabel("omega dt")
        ax.grid(True, which="both", alpha=0.3)
    for ax, title in (
        (left, "amplitude kept per step"),
        (middle, "damping per step"),
        (right, "phase"),
    ):
        ax.set_title(title, fontsize="medium")
    fig.suptitle(
        "Numerical damping on a harmonic bond: measured (points) on theory (lines)"
        + (f"; dt {time_label}" if time_label else "")
    )
    legend_outside(fig, right, left.get_legend_handles_labels(), title="integrator (lines: theory)")
    fig.tight_layout()
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)


# ------------------------------------------------------------------ from a config


def default_integrators() -> list[str]:
    """Velocity Verlet and every registered integrator with an amplification factor
    other than the explicit family (the implicit methods and XPBD), one name per class."""
    names, seen = [], set()
    for name, cls in INTEGRATORS.items():
        if cls in seen or not isinstance(cls, type):
            continue
        seen.add(cls)
        if name == "verlet" or (
            isinstance(cls, SupportsAmplification) and "tol" in _parameters(cls)
        ):
            names.append(name)
    return names


def _parameters(cls) -> set[str]:
    return set(inspect.signature(cls).parameters)


@dataclass
class DampingStudy:
    """A validated damping measurement that has written nothing (see :func:`prepare_damping`).

    Attributes
    ----------
    names : list of str
        Integrators measured.
    omega_dts : list of float
        The ladder of omega dt.
    dt : float
        The config's time step [time]; the bond's frequency is omega_dt / dt.
    time_label : str
        The config's time unit, for the figure.
    files : dict of Path
        ``csv`` and ``plot``: where damping.csv and damping.png go.
    overwrite : bool
        Replace existing files.
    """

    names: list[str]
    omega_dts: list[float]
    dt: float
    time_label: str
    files: dict[str, Path] = field(default_factory=dict)
    overwrite: bool = False

    def factory(self, name: str) -> Callable[[float], object]:
        """Build integrator ``name`` at a dt, implicit ones at :data:`SOLVER_TOL`."""
        cls = INTEGRATORS[name]
        if "tol" in _parameters(cls):
            return lambda dt: cls(dt, tol=SOLVER_TOL)
        return lambda dt: cls(dt)

    def run(self, progress: Callable[[str], None] | None = None) -> list[DampingRow]:
        """Measure, write damping.csv and damping.png, and return the rows.

        If writing fails, the files of this call are removed before the error
        is raised.
        """
        rows = measure_damping(
            {name: self.factory(name) for name in self.names},
            self.omega_dts,
            dt=self.dt,
            progress=progress,
        )
        written = []
        try:
            for kind, path in self.files.items():
                path.parent.mkdir(parents=True, exist_ok=True)
                if self.overwrite:
                    path.unlink(missing_ok=True)
                written.append(path)
                if kind == "csv":
                    write_damping_csv(rows, path)
                else:
                    theories = {n: INTEGRATORS[n] for n in self.names}
                    plot_damping(rows, theories, path, self.time_label)
        except BaseException:
            for path in written:
                path.unlink(missing_ok=True)
            raise
        return rows


def prepare_damping(
    config: str | os.PathLike | Config,
    integrators: str | Sequence[str] | None = None,
    omega_dts: str | Sequence[float] | None = None,
    out: str | os.PathLike | None = None,
    overwrite: bool = False,
) -> DampingStudy:
    """Validate what ``md integrators CONFIG --damping`` measures; write nothing.

    The measurement runs on its own two-bead bond, at the config's dt and in
    its units, so the damping of a mode of frequency omega in the config's
    system can be read off at omega dt.

    Parameters
    ----------
    config : path or Config
        The config (its ``[integrator] dt`` and units are used).
    integrators : str or sequence of str, optional
        Names (a comma-separated string or a list); default
        :func:`default_integrators`. Each must be a deterministic fixed-step
        integrator of the registry.
    omega_dts : str or sequence of float, optional
        The ladder: ``"MIN:MAX:N"`` (log-spaced), a comma list, or numbers;
        default :data:`OMEGA_DT` (0.01 to 100, 17 points).
    out : path, optional
        Output folder (default ``integrators-<config stem>``).
    overwrite : bool
        Replace damping.csv and damping.png if they exist.

    Raises
    ------
    ConfigError
        For an unknown or unsuitable integrator, a bad ladder, or output files
        that exist without ``overwrite``.
    """
    if not isinstance(config, Config):
        config = load_config(config)
    names = _damping_names(integrators)
    ladder = _ladder(omega_dts)
    folder = Path(out) if out is not None else Path(f"integrators-{Path(config.source).stem}")
    files = {kind: folder / name for kind, name in DAMPING_FILES.items()}
    existing = [str(p) for p in files.values() if p.exists()]
    if existing and not overwrite:
        raise ConfigError(f"output file(s) exist: {', '.join(existing)}; pass --overwrite or --out")
    units = config.units
    dt = float(config.integrator.dt)
    label = f"{dt / units.config_time:g} {units.config_time_label}"
    return DampingStudy(names, ladder, dt, label, files, overwrite)


def _damping_names(integrators) -> list[str]:
    if integrators is None:
        return default_integrators()
    names = integrators.split(",") if isinstance(integrators, str) else list(integrators)
    names = [n.strip() for n in names if n.strip()]
    unknown = [n for n in names if n not in INTEGRATORS]
    if unknown or not names:
        raise ConfigError(
            f"--integrators: unknown {', '.join(unknown) or '(none given)'}; "
            f"known: {', '.join(INTEGRATORS)}"
        )
    unsuited = [
        n
        for n in names
        if INTEGRATORS[n].thermostat
        or INTEGRATORS[n].stochastic
        or INTEGRATORS[n].adaptive
        or INTEGRATORS[n].requires_constraints
    ]
    if unsuited:
        raise ConfigError(
            f"--damping measures deterministic fixed-step integrators on a bond; not "
            f"{', '.join(unsuited)} (thermostat, adaptive or constrained)"
        )
    return list(dict.fromkeys(names))


def _ladder(omega_dts) -> list[float]:
    if omega_dts is None:
        return list(OMEGA_DT)
    try:
        if isinstance(omega_dts, str):
            if ":" in omega_dts:
                low, high, n = omega_dts.split(":")
                low, high, n = float(low), float(high), int(n)
                ends = [low, high] if n > 0 else []
                ok = ends and all(math.isfinite(v) and v > 0 for v in ends)
                values = np.geomspace(low, high, n).tolist() if ok else ends
            else:
                values = [float(v) for v in omega_dts.split(",")]
        else:
            values = [float(v) for v in omega_dts]
    except ValueError:
        raise ConfigError(
            f"omega dt ladder must be MIN:MAX:N or a comma list of numbers, got {omega_dts!r}"
        ) from None
    if not values or not all(math.isfinite(v) and v > 0 for v in values):
        raise ConfigError(f"omega dt ladder needs positive, finite values, got {omega_dts!r}")
    return values


__all__ = [
    "DAMPING_COLUMNS",
    "DAMPING_FILES",
    "OMEGA_DT",
    "SOLVER_TOL",
    "DampingRow",
    "DampingStudy",
    "bond_oscillator",
    "default_integrators",
    "measure_damping",
    "plot_damping",
    "prepare_damping",
    "theory_curve",
    "write_damping_csv",
]
