"""Clock offset between a peer and the server, NTP style, from Ping/Pong exchanges.

One exchange gives t0 (client sends Ping), t1 (server receives), t2 (server sends Pong),
t3 (client receives). With d_up and d_down the two one-way delays:
    t1 = t0 + offset + d_up,   t3 = t2 - offset + d_down
    offset = ((t1 - t0) + (t2 - t3)) / 2 + (d_down - d_up) / 2
    rtt    = (t3 - t0) - (t2 - t1) = d_up + d_down
so the estimate's error is half the delay asymmetry, at most rtt / 2. Samples with the
lowest rtt therefore bound the error most tightly, and ``ClockEstimator`` trusts them.
``offset`` is server clock minus local clock: server_time = local_time + offset.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

from posecast.protocol.messages import Pong


@dataclass(frozen=True)
class ClockSample:
    offset: float  # server - local, seconds
    rtt: float  # round trip minus the server's own hold time, seconds
    t_local: float  # t3: when the sample was taken, local clock


def clock_sample(t0: float, t1: float, t2: float, t3: float) -> ClockSample:
    """Offset and round-trip time of one Ping/Pong exchange (t0, t3 local; t1, t2 server)."""
    if not all(math.isfinite(t) for t in (t0, t1, t2, t3)):
        raise ValueError(f"clock sample times must be finite: {(t0, t1, t2, t3)}")
    return ClockSample(offset=((t1 - t0) + (t2 - t3)) / 2.0, rtt=(t3 - t0) - (t2 - t1),
                       t_local=t3)


class ClockEstimator:
    """The offset to the server from recent samples, trusting the lowest-RTT ones.

    Keeps the last ``window`` samples no older than ``max_age`` seconds, and reports the
    median offset of the ``use_best`` samples with the smallest RTT (the median, so one
    sample with a lopsided route cannot pull it), kept within what every sample allows.
    Refresh it by pinging every second or so: old samples age out, so the estimate
    follows drift (two crystals differ by up to ~50 ppm, 0.5 ms over the default 10 s)
    and a changed route.
    """

    def __init__(self, window: int = 32, use_best: int = 3, max_age: float = 10.0) -> None:
        if window < 1 or not 1 <= use_best <= window or not max_age > 0:
            raise ValueError(f"need window >= 1, 1 <= use_best <= window, max_age > 0; "
                             f"got {window}, {use_best}, {max_age}")
        self.use_best = use_best
        self.max_age = max_age
        self._samples: deque[ClockSample] = deque(maxlen=window)
        self._offset = 0.0
        self._best: ClockSample | None = None

    def add(self, t0: float, t1: float, t2: float, t3: float) -> bool:
        """Record one exchange; False (and ignored) if its RTT is negative, i.e. bogus."""
        sample = clock_sample(t0, t1, t2, t3)
        if sample.rtt < 0.0:
            return False
        self._samples.append(sample)
        while self._samples[0].t_local < sample.t_local - self.max_age:
            self._samples.popleft()
        best = sorted(self._samples, key=lambda s: s.rtt)[:self.use_best]
        offsets = sorted(s.offset for s in best)
        mid = len(offsets) // 2
        median = offsets[mid] if len(offsets) % 2 else (offsets[mid - 1]
                                                         + offsets[mid]) / 2.0
        self._offset = self._within_every_bound(median)
        self._best = best[0]
        return True

    def _within_every_bound(self, median: float) -> float:
        """``median``, or the middle of the offsets every sample allows (each within
        its rtt / 2) where the median lies outside them: a sample delayed on one way
        (a peer stalled before reading its Pong) can outnumber the good ones among the
        best few, as at the start of a session on a loaded machine (-132 ms in a demo
        over a 40 ms link). Samples that allow no common offset (a clock stepped within
        the window) leave the median."""
        lo = max(s.offset - s.rtt / 2.0 for s in self._samples)
        hi = min(s.offset + s.rtt / 2.0 for s in self._samples)
        if lo <= median <= hi or lo > hi:
            return median
        return (lo + hi) / 2.0

    def reset(self) -> None:
        """Forget every sample (after a reconnect, say)."""
        self._samples.clear()
        self._offset = 0.0
        self._best = None

    def add_pong(self, pong: Pong, t3: float) -> bool:
        """Record the exchange of a Pong received at local time t3."""
        return self.add(pong.t0, pong.t1, pong.t2, t3)

    @property
    def synced(self) -> bool:
        """True once at least one sample is in the window."""
        return bool(self._samples)

    @property
    def offset(self) -> float:
        """Server clock minus local clock, seconds (0.0 until synced)."""
        return self._offset

    @property
    def rtt(self) -> float:
        """Smallest RTT in the window, seconds (inf until synced)."""
        return self._best.rtt if self._best is not None else math.inf

    @property
    def error_bound(self) -> float:
        """Worst-case error of the best sample's offset: rtt / 2 (inf until synced)."""
        return self.rtt / 2.0

    @property
    def samples(self) -> tuple[ClockSample, ...]:
        """The samples in the window, oldest first."""
        return tuple(self._samples)

    def __len__(self) -> int:
        return len(self._samples)

    def to_server(self, t_local: float) -> float:
        return t_local + self._offset

    def to_local(self, t_server: float) -> float:
        return t_server - self._offset
