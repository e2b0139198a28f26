"""Log lines about rejected messages, sampled so that no client can flood or forge the log.

A connection's first few rejections are logged at INFO, each with its (escaped, cut)
message; after that only counts are kept, by error code, and one summary line per
interval (and one when the connection ends) says how many were not logged. A budget
shared by every connection of the server caps the lines themselves: 100k bad messages
over 10k connections still write a bounded log. The counts that matter for alerting are
in ``Metrics.rejected`` whatever is logged.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable

from posecast.protocol.validation import safe_text

LOGGED_CHARS = 160  # of a client-influenced message in one log line


class LineBudget:
    """At most ``lines`` log lines per ``interval`` seconds for the whole server."""

    def __init__(self, lines: int, interval: float) -> None:
        self.lines = lines
        self.interval = interval
        self.left = lines
        self.refill_at = 0.0
        self.suppressed = 0  # lines not written for want of budget, since the last note

    def take(self, t: float) -> bool:
        if t >= self.refill_at:
            self.left = self.lines
            self.refill_at = t + self.interval
        if self.left <= 0:
            self.suppressed += 1
            return False
        self.left -= 1
        return True


class RejectionLog:
    """The log lines about one connection's rejected messages (see the module doc)."""

    def __init__(self, logger: logging.Logger, peer: str, budget: LineBudget,
                 clock: Callable[[], float], first: int, interval: float) -> None:
        self.logger = logger
        self.peer = peer
        self.budget = budget
        self.clock = clock
        self.first = first  # rejections logged one by one
        self.interval = interval  # seconds between summary lines
        self.logged = 0
        self.unlogged: Counter[str] = Counter()  # since the last summary, by code
        self.summary_at = 0.0  # when the next summary line may be written

    def rejected(self, code: str, message: str) -> None:
        t = self.clock()
        if self.logged < self.first and self.budget.take(t):
            self.logged += 1
            self.logger.info("rejected %s from %s: %s", safe_text(code, 64), self.peer,
                             safe_text(message, LOGGED_CHARS))
            if self.logged == self.first:  # the next ones are counted, not shown
                self.summary_at = t + self.interval
            return
        self.unlogged[safe_text(code, 64)] += 1
        if t >= self.summary_at:
            self.summary(t)

    def summary(self, t: float | None = None) -> None:
        """One line with the counts not logged yet (at the interval, and at the end)."""
        t = self.clock() if t is None else t
        if not self.unlogged:
            return
        if not self.budget.take(t):  # counted again in the next summary
            return
        counts = ", ".join(f"{code} x{n}" for code, n in self.unlogged.most_common())
        self.logger.info("rejected %d more messages from %s (not logged one by one): %s",
                         sum(self.unlogged.values()), self.peer, counts)
        self.unlogged.clear()
        self.summary_at = t + self.interval
