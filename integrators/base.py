"""The Integrator protocol and the errors integrators raise."""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:
    from md.forcefield import ForceField
    from md.state import State


class Integrator(Protocol):
    """Advance a State by one time step.

    ``step`` updates ``state.positions`` and ``state.velocities`` in place and
    advances ``state.step`` by one and ``state.time`` by ``dt``. Anything
    staggered (half-step velocities, solver history) stays private to the
    integrator; ``reset`` drops it.
    """

    dt: float

    def step(self, state: State, forcefield: ForceField) -> None: ...

    def reset(self) -> None: ...

    def describe(self) -> dict: ...


class ConvergenceError(RuntimeError):
    """An implicit step failed to converge."""

    def __init__(self, step: int, residual: float, message: str = "") -> None:
        self.step = step
        self.residual = residual
        super().__init__(
            message or f"step {step}: implicit solve did not converge (residual {residual:.3g})"
        )


def check_dt(dt: float) -> float:
    """Return ``dt`` as a float, or raise ValueError if it is not positive and finite."""
    try:
        value = float(dt)
    except (TypeError, ValueError):
        raise ValueError(f"dt must be a number, got {dt!r}") from None
    if not (value > 0 and value < float("inf")):
        raise ValueError(f"dt must be positive and finite, got {dt!r}")
    return value
