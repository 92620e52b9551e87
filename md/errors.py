"""The exceptions the engine raises, in one place (layer 0: imports nothing of ours).

Every error here subclasses a built-in (``ValueError`` for bad input,
``RuntimeError`` for a run that broke down), so callers that do not know
this module can still catch them; the messages name the file, key, value or
step involved.
"""

from __future__ import annotations

import math


class NonFiniteError(FloatingPointError):
    """A coordinate or energy became NaN or infinite."""


class PairCollapseError(NonFiniteError):
    """Two atoms came closer than a pair potential allows: inside the barrier of an
    energy that falls to minus infinity (Buckingham), or below a table's first
    distance. Named with the pair, its types, distance, the limit and the step.

    A subclass of :class:`NonFiniteError`, so the simulation loop reports it as a
    :class:`SimulationError` at the failing step.
    """

    def __init__(
        self,
        style: str,
        i: int,
        j: int,
        type_names,
        distance: float,
        limit: float,
        step: int,
        reason: str,
    ) -> None:
        self.i, self.j, self.distance, self.limit, self.step = i, j, distance, limit, step
        pair = "-".join(str(name) for name in type_names)
        super().__init__(
            f"{style}: atoms {i} and {j} (types {pair}) are {distance:.6g} apart at step "
            f"{step}, closer than r = {limit:.6g}: {reason}"
        )


class DecompositionError(NonFiniteError):
    """A run decomposed over MPI ranks cannot go on (:mod:`md.distributed`).

    An atom moved farther than a brick between two neighbour-list builds, or
    a bond outgrew the ghost shell: signs of a blow-up. A
    :class:`NonFiniteError`, so the simulation loop reports it as a
    :class:`SimulationError` at the failing step.
    """


class ConvergenceError(RuntimeError):
    """An iterative step (implicit solve, SHAKE/RATTLE) failed to converge at ``step``."""

    def __init__(self, step: int, residual: float, message: str = "") -> None:
        self.step = step
        self.residual = residual
        super().__init__(
            message or f"step {step}: implicit solve did not converge (residual {residual:.3g})"
        )


class SimulationError(RuntimeError):
    """The dynamics broke down (NaN or infinite energy or positions) at ``step``."""

    def __init__(self, step: int, message: str) -> None:
        self.step = step
        super().__init__(f"step {step}: {message}")


class BondStretchError(NonFiniteError):
    """A FENE bond reached its maximum extension ``r_max`` (infinite energy).

    A subclass of :class:`NonFiniteError`, so the simulation loop reports it
    as a :class:`SimulationError` at the failing step.

    Attributes
    ----------
    bond : int
        Index of the first overstretched bond in the bond list.
    i, j : int
        Its atoms.
    length : float
        Its length [length].
    r_max : float
        Its maximum extension [length].
    """

    def __init__(self, bond: int, i: int, j: int, length: float, r_max: float) -> None:
        self.bond = bond
        self.i = i
        self.j = j
        self.length = length
        self.r_max = r_max
        super().__init__(
            f"FENE bond {bond} between atoms {i} and {j} is stretched to length "
            f"{length:.6g} >= r_max = {r_max:g}"
        )


#: Stage names of :class:`ConstraintError` messages.
_CONSTRAINT_STAGES = {"positions": "SHAKE (bond lengths)", "velocities": "RATTLE (bond velocities)"}


class ConstraintError(ConvergenceError):
    """SHAKE or RATTLE did not converge within ``max_iter`` iterations.

    Attributes
    ----------
    step : int
        The step being taken when it failed.
    residual : float
        Largest relative error left: ``|r - d| / d`` for positions, the relative
        bond-length change per step ``|r . v_ij| dt / d^2`` for velocities.
    stage : str
        ``"positions"`` (SHAKE) or ``"velocities"`` (RATTLE).
    bond, i, j : int
        Index of the worst bond and its atoms.
    """

    def __init__(self, step, stage, residual, bond, i, j, tol, max_iter) -> None:
        self.stage = stage
        self.bond = bond
        self.i = i
        self.j = j
        if math.isfinite(residual):
            problem = (
                f"did not converge in {max_iter} iterations: bond {bond} (atoms {i}-{j}) has "
                f"relative error {residual:.3g} > tol {tol:g}"
            )
        else:
            problem = (
                f"cannot correct bond {bond} (atoms {i}-{j}): it turned by 90 degrees or "
                "more within the step"
            )
        message = (
            f"step {step}: {_CONSTRAINT_STAGES.get(stage, stage)} {problem} (is dt too large, "
            "or a constrained bond torn apart by the forces?)"
        )
        super().__init__(step, residual, message)


class ConfigError(ValueError):
    """An invalid configuration: the message names the file, key and value."""


class DeviceError(ValueError):
    """A run asks for a device (``[run] device = "cuda"``) that cannot run it: numba-cuda or
    a GPU is missing, or something in the run is not ported to the device (named)."""


class PluginError(ValueError):
    """A plug-in a config names cannot be used: not found, its import raised, or it is not
    a class of the kind its section needs or its constructor does not fit its keys (the
    message names the plug-in and what is wrong; :mod:`md.plugins`)."""


class TrajectoryError(ValueError):
    """A file is not a trajectory this package can read (names the file and what is wrong)."""


class CheckpointError(ValueError):
    """A checkpoint is missing, unreadable, not ours, or does not fit the run."""


class AnalysisError(ValueError):
    """A trajectory lacks what an analysis needs, or its parameters do not fit the data."""


class AngleCollapseError(NonFiniteError):
    """An angle has an arm of zero length (two of its atoms at one place): no angle.

    Raised by the angle potentials (:mod:`potentials.angles`). A
    :class:`NonFiniteError`, so the simulation loop reports it as a
    :class:`SimulationError` at the failing step.

    Attributes
    ----------
    angle : int
        Index of the first such angle in the angle list.
    atoms : tuple of int
        Its atoms ``(i, j, k)``, ``j`` the vertex.
    """

    def __init__(self, angle: int, atoms: tuple[int, int, int]) -> None:
        self.angle = angle
        self.atoms = atoms
        super().__init__(
            f"angle {angle} {atoms} has an arm of zero length (atoms at one place), so its "
            "angle is undefined"
        )


class SweepError(ValueError):
    """Bad sweep input: a varied key or value, a config, an output folder (named)."""


class OutputBusyError(FileExistsError):
    """Another live process holds the claim on an output (the message names it)."""


__all__ = [
    "AnalysisError",
    "AngleCollapseError",
    "BondStretchError",
    "CheckpointError",
    "ConfigError",
    "ConstraintError",
    "ConvergenceError",
    "DecompositionError",
    "DeviceError",
    "NonFiniteError",
    "OutputBusyError",
    "PairCollapseError",
    "PluginError",
    "SimulationError",
    "SweepError",
    "TrajectoryError",
]
