"""When a player's next frame is due, from the rhythm of the ones before.

A headset streams at its display rate (90 Hz for a Vive), so a player's frames reach the
server one period apart, give or take the network's jitter. A room keeps a burst open for
the frames due within it (``server.room``): players whose headsets tick together are
solved in one batch however their frames happen to be spaced, and a player whose frames
come at another phase is not waited for. No I/O: arrival times go in, a yes or no comes
out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

MIN_PERIOD_S = 0.002  # 500 Hz: faster than any headset
MAX_PERIOD_S = 0.1  # 10 Hz: slower, the player paused; there is no rhythm to follow
SMOOTHING = 0.1  # weight of each new interval in the running period
# an interval this far off the running period is a skipped or doubled frame, not a change
# of rate: it leaves the period alone, unless this many come in a row (the rate changed)
OUTLIER = 0.5
OUTLIERS_TO_RESET = 3


@dataclass
class Cadence:
    """A player's last arrival time and its frame period (0 until two frames came)."""

    last: float = -math.inf
    period: float = 0.0
    outliers: int = 0  # intervals in a row far off the period

    def arrived(self, t: float) -> None:
        interval = t - self.last
        self.last = t
        if not MIN_PERIOD_S <= interval <= MAX_PERIOD_S:
            return
        if abs(interval - self.period) <= OUTLIER * self.period:
            self.period += SMOOTHING * (interval - self.period)
            self.outliers = 0
        else:  # a skipped or doubled frame, or (if it lasts, or at first) a new rate
            self.outliers += 1
            if self.period == 0.0 or self.outliers >= OUTLIERS_TO_RESET:
                self.period = interval
                self.outliers = 0

    def due(self) -> float | None:
        """When the next frame is due; None while the period is unknown."""
        return self.last + self.period if self.period > 0.0 else None

    def due_within(self, start: float, end: float) -> bool:
        """Is the next frame due in [start, end]? False while the period is unknown."""
        due = self.due()
        return due is not None and start <= due <= end
