"""Dynamic load balancing of a decomposed run (:class:`LoadBalance`).

At a migration every ``every`` steps or more, the ranks share their busy seconds since
the last check (wall time less the time they spent communicating, waits included);
where the busiest rank's exceed the mean by more than the factor ``threshold``, the
planes between bricks move towards an even share (:meth:`md.distributed.grid.Grid.
balanced`, per cut axis), and the migration that follows takes the atoms to their new
bricks. :class:`md.distributed.DistributedForceField` asks at each migration.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from md.box import periodic_tilt, perpendicular_widths
from md.state import State

logger = logging.getLogger(__name__)


class LoadBalance:
    """When and where a decomposed run's planes between bricks move (see the module).

    Parameters
    ----------
    every : int
        Steps between checks at the least (0: never).
    threshold : float
        The busiest rank's busy time over the mean (>= 1) above which a check moves
        the planes.

    Attributes
    ----------
    imbalance : float
        The busiest rank's busy seconds over the mean at the last check.
    balances : int
        How many checks moved the planes.
    """

    def __init__(self, every: int = 0, threshold: float = 1.05) -> None:
        if every < 0 or not threshold >= 1.0:
            raise ValueError(
                f"balance_every must be >= 0 and balance_threshold >= 1, got "
                f"{every} and {threshold}"
            )
        self.every = int(every)
        self.threshold = float(threshold)
        self.imbalance = 1.0
        self.balances = 0
        self._mark: tuple[float, float, int] | None = None  # (wall, comm, step) then

    def check(self, state: State, domain, ranks, room: float) -> None:
        """Move the planes of ``domain``'s grid towards an even share of the ranks' busy
        time, if ``every`` steps have passed since the last check and the imbalance
        exceeds ``threshold``; a brick keeps ``room`` [length] (the ghost shell and how
        far atoms stray before a build). Collective (over ``ranks``, its sum on their
        clock); the migration that follows takes the atoms to their new bricks."""
        now, communicated = time.perf_counter(), ranks.clock.seconds
        mark = self._mark
        if mark is not None and state.step - mark[2] < self.every:
            return
        self._mark = (now, communicated, state.step)
        if mark is None:  # the first migration starts the clock
            return
        mine = np.zeros(ranks.n_ranks)
        mine[ranks.rank] = max((now - mark[0]) - (communicated - mark[1]), 0.0)
        with ranks.clock:
            busy = ranks.sum(mine)  # one non-zero term per entry: the same on every rank
        mean = float(busy.mean())
        self.imbalance = float(busy.max()) / mean if mean > 0.0 else 1.0
        if self.imbalance <= self.threshold:
            return
        widths = perpendicular_widths(state.box, periodic_tilt(state.tilt, state.pbc))
        grid = domain.grid.balanced(busy, widths, room)
        domain.set_grid(grid)
        self.balances += 1
        cuts, shares = [np.round(c, 4).tolist() for c in grid.cuts], np.round(busy, 4).tolist()
        message = "step %d: ranks' busy time %s s (max/mean %.3f); cuts now %s"
        logger.info(message, state.step, shares, self.imbalance, cuts)
