"""The exceptions the engine raises, in one place (layer 0: imports nothing of ours).

Every error here subclasses a built-in (``ValueError`` for bad input,
``RuntimeError`` for a run that broke down), so callers that do not know
this module can still catch them; the messages name the file, key, value or
step involved.
"""

from __future__ import annotations


class NonFiniteError(FloatingPointError):
    """A coordinate or energy became NaN or infinite."""


class PairCollapseError(NonFiniteError):
    """Two atoms came closer than a pair potential allows: inside the barrier of an
    energy that falls to minus infinity (Buckingham), or below a table's first
    distance. Named with the pair, its types, distance, the limit and the step.

    A subclass of :class:`NonFiniteError`, so the simulation loop reports it as a
    :class:`SimulationError` at the failing step.
    """

    def __init__(self, style: str, i: int, j: int, type_names, distance: float,
                 limit: float, step: int, reason: str) -> None:  # fmt: skip
        self.i, self.j, self.distance, self.limit, self.step = i, j, distance, limit, step
        pair = "-".join(str(name) for name in type_names)
        super().__init__(
            f"{style}: atoms {i} and {j} (types {pair}) are {distance:.6g} apart at step "
            f"{step}, closer than r = {limit:.6g}: {reason}"
        )


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


__all__ = [
    "AnalysisError",
    "CheckpointError",
    "ConfigError",
    "ConvergenceError",
    "NonFiniteError",
    "PairCollapseError",
    "SimulationError",
    "TrajectoryError",
]
