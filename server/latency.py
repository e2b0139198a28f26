"""Latency histograms of the server's stages, per avatar-frame, for ``/metrics``.

Filled a batch at a time with a few numpy calls over the batch's time arrays (no Python
work per frame, and never prometheus_client's own ``Histogram.observe``, which takes a
lock per value): each value is counted into fixed buckets, and a scrape reads the counts
(``server.prometheus``).
"""

from __future__ import annotations

import numpy as np

# upper bounds (seconds, inclusive as Prometheus' "le") from 0.1 ms to 1 s: fine steps
# where the server's figures lie (p99 of ``server`` ~0.5 ms, 16 players), coarse beyond
BUCKET_BOUNDS_S: tuple[float, ...] = (
    0.0001, 0.0002, 0.0003, 0.0004, 0.0005, 0.0006, 0.0008, 0.001, 0.0015, 0.002, 0.003,
    0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0)

# every stage on the server's clock, as the demo names them (README, "The whole session
# on one machine"): capture (the player's t_capture + clock_offset) to its bytes' arrival;
# arrival to solved; arrival to the batch handed to the sockets (or the outboxes)
SERVER_STAGES: tuple[str, ...] = ("capture_to_server", "solve", "server")
# the spectators' stages, from what viewers report (ViewerReport), named as
# ``protocol.batch.stage_latencies`` names them: capture to the batch's arrival at the
# viewer's process, and capture to the frame on its screen
VIEWER_STAGES: tuple[str, ...] = ("capture_to_spectator", "capture_to_presented")
# a headset viewer's (``play --hmd``): from the poses a frame was drawn with to its
# submission to the compositor, on the viewer's own clock
HEADSET_STAGES: tuple[str, ...] = ("pose_to_submit",)


class StageHistograms:
    """Counts per bucket (the last is above every bound: +Inf) and sums, one row per
    stage. With ``pending`` > 0, values wait in a buffer of that many columns and are
    counted together when it fills or the counts are read: a burst's bookkeeping is then
    a copy, not a bucket search (the server's, between one batch and the next)."""

    def __init__(self, stages: tuple[str, ...],
                 bounds: tuple[float, ...] = BUCKET_BOUNDS_S, pending: int = 0) -> None:
        self.stages = stages
        self.bounds = bounds
        self._bounds = np.array(bounds, dtype=np.float64)
        self._counts = np.zeros((len(stages), len(bounds) + 1), dtype=np.int64)
        self._sums = np.zeros(len(stages), dtype=np.float64)
        self._flat = self._counts.reshape(-1)  # a view: add.at works on one axis
        # each stage's first bucket in the flat counts
        self._offsets = (np.arange(len(stages), dtype=np.intp) * (len(bounds) + 1))[:, None]
        self._pending = np.empty((len(stages), pending), dtype=np.float64)
        self._held = 0  # columns of _pending in use

    @property
    def counts(self) -> np.ndarray:
        self.flush()
        return self._counts

    @property
    def sums(self) -> np.ndarray:
        self.flush()
        return self._sums

    def observe(self, values: np.ndarray) -> None:
        """``values``: seconds, shape (stages, n): one column per avatar-frame."""
        n = values.shape[1]
        if n <= self._pending.shape[1]:
            self._reserve(n)[:] = values
        else:
            self._count(values)

    def _reserve(self, n: int) -> np.ndarray:
        """The next ``n`` columns of the buffer, counting what it held first if full."""
        if self._held + n > self._pending.shape[1]:
            self.flush()
        start, self._held = self._held, self._held + n
        return self._pending[:, start:self._held]

    def flush(self) -> None:
        """Count the values held."""
        if self._held:
            held, self._held = self._pending[:, :self._held], 0
            self._count(held)

    def _count(self, values: np.ndarray) -> None:
        index = np.searchsorted(self._bounds, values, side="left")  # first bound >= v
        index += self._offsets
        np.add.at(self._flat, index.reshape(-1), 1)
        self._sums += values.sum(axis=1)

    def cumulative(self, stage: str) -> tuple[list[tuple[str, float]], float]:
        """Prometheus' buckets of one stage, cumulative, ending with +Inf (the count);
        and the sum."""
        row = self.stages.index(stage)
        totals = np.cumsum(self.counts[row]).tolist()
        buckets = [(repr(b), float(c)) for b, c in zip(self.bounds, totals, strict=False)]
        buckets.append(("+Inf", float(totals[-1])))
        return buckets, float(self.sums[row])

    def count(self, stage: str) -> int:
        return int(self.counts[self.stages.index(stage)].sum())


# the server's values held before they are counted: ~1,000 batches of 16 avatars (one
# count every ~6 s at 90 Hz, ~1 ms), or the next scrape of /metrics if sooner
SERVER_PENDING = 16384


class ServerLatency(StageHistograms):
    """The server's stages of each avatar-frame it solves (``SERVER_STAGES``)."""

    def __init__(self) -> None:
        super().__init__(SERVER_STAGES, pending=SERVER_PENDING)

    def batch(self, t_capture: np.ndarray, t_received: np.ndarray, t_solved: float,
              t_sent: float) -> None:
        """One solved batch: each frame's capture and arrival times, the batch's solve
        and send times (all on the server's clock). Held, and counted later: three
        subtractions into the buffer."""
        n = t_received.shape[0]
        held = n <= self._pending.shape[1]  # a batch is at most MAX_AVATARS, far fewer
        values = self._reserve(n) if held else np.empty((3, n), dtype=np.float64)
        np.subtract(t_received, t_capture, out=values[0])
        np.subtract(t_solved, t_received, out=values[1])
        np.subtract(t_sent, t_received, out=values[2])
        if not held:
            self._count(values)


class ViewerLatency(StageHistograms):
    """The spectators' stages of the avatar-frames they report (``VIEWER_STAGES``)."""

    def __init__(self) -> None:
        super().__init__(VIEWER_STAGES)

    def report(self, t_capture: np.ndarray, t_received: np.ndarray,
               t_presented: np.ndarray) -> None:
        """One checked report: its rows' times, all on the server's clock."""
        values = np.empty((2, t_capture.shape[0]), dtype=np.float64)
        np.subtract(t_received, t_capture, out=values[0])
        np.subtract(t_presented, t_capture, out=values[1])
        self.observe(values)


class RelayLatency(StageHistograms):
    """``serve --redis``: from the owner publishing a batch or roster to this process
    receiving it from Redis (``relay``), both on this process's clock. The newest
    MAX_SAMPLES values are kept too, for the demo's percentiles."""

    MAX_SAMPLES = 200_000

    def __init__(self) -> None:
        super().__init__(("relay",))
        self.samples: list[float] = []

    def add(self, seconds: float) -> None:
        self.observe(np.array([[seconds]]))
        if len(self.samples) >= self.MAX_SAMPLES:
            del self.samples[:self.MAX_SAMPLES // 2]
        self.samples.append(seconds)
