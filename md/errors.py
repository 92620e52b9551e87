"""The exceptions the engine raises, in one place (layer 0: imports nothing of ours).

Every error here subclasses a built-in (``ValueError`` for bad input,
``RuntimeError`` for a run that broke down), so callers that do not know
this module can still catch them; the messages name the file, key, value or
step involved.
"""

from __future__ import annotations


class NonFiniteError(FloatingPointError):
    """A coordinate or energy became NaN or infinite."""


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


class ConfigError(ValueError):
    """An invalid configuration: the message names the file, key and value."""


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


__all__ = [
    "AnalysisError",
    "AngleCollapseError",
    "CheckpointError",
    "ConfigError",
    "ConvergenceError",
    "NonFiniteError",
    "SimulationError",
    "TrajectoryError",
]
