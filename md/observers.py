"""Observers: callables attached to a Simulation that read its state."""

from __future__ import annotations

from collections.abc import Callable


class ThermoLog:
    """Record ``sim.thermo()`` rows; optionally hand each to a callback.

    Examples
    --------
    >>> log = ThermoLog()
    >>> # sim.attach(log, interval=100); sim.run(1000); log.rows[-1]["temperature"]
    """

    def __init__(self, callback: Callable[[dict], None] | None = None) -> None:
        self.rows: list[dict[str, float]] = []
        self.callback = callback

    def __call__(self, sim) -> None:
        row = sim.thermo()
        self.rows.append(row)
        if self.callback is not None:
            self.callback(row)


class Progress:
    """Advance a progress bar (anything with ``update(n)``) as steps complete."""

    #: Reads no pressure, so its steps need no virial (see ``Simulation.attach``).
    uses_virial = False
    #: Reads only the step: a run decomposed over MPI ranks need not gather its atoms.
    whole_system = False

    def __init__(self, bar) -> None:
        self.bar = bar
        self._last: int | None = None

    def __call__(self, sim) -> None:
        step = sim.state.step
        if self._last is not None and step > self._last:
            self.bar.update(step - self._last)
        self._last = step
