"""Snapshot interpolation: show each avatar slightly in the past, smoothly.

Frames arrive unevenly (network, batching, the server's and the viewer's own scheduling).
Drawing the newest frame as it is ("zero-buffer" mode, ``Mode.LATEST``) has the least
latency but shows that unevenness as stutter. In ``Mode.INTERPOLATE`` each avatar is drawn
at a capture instant a little behind the newest frame, between the two frames that
bracket it: SLERP of every joint rotation, linear interpolation of the root.

How far behind, per avatar, from its own arrivals (no clock sync needed):

- transit_i = t_arrival_i (viewer clock) - t_capture_i (server clock). It holds the clock
  offset, which is constant, plus the real delay, which varies. Over a sliding window,
  base = min(transit) and jitter = transit - base >= 0.
- A frame captured at c arrives at c + base + jitter. Rendering, at local time ``now``,
  the capture instant  t = now - base - delay  needs the frame after t, captured at most
  one frame interval later, to have arrived: true when jitter <= delay - interval. So

      delay = clamp(k * jitter_p95 + interval, min_delay, max_delay)

  (interval: the median spacing of capture times; k = 1 covers 95% of frames). The delay
  grows when arrivals get jittery and shrinks back when they calm down.
- When the frame after t has not arrived (an underrun) the newest frame is held (no
  extrapolation: a wrong guess at a limb looks worse than a brief pause); underruns are
  counted.

In ``Mode.PREDICT`` each avatar's newest frame is carried forward by its capture-to-render
latency (present time on the server clock - its capture time, through the connection's
clock offset) with ``solver.prediction``: the pose drawn stands for the present instant.

``Sampled.t_capture`` is the capture instant the drawn pose stands for, so
present time - t_capture is the honest capture-to-render latency in either mode.
Pure: no GL, no sockets.
"""

from __future__ import annotations

import enum
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from posecast.protocol import AvatarFrame
from posecast.solver import prediction
from posecast.solver import rotations as R

Array = NDArray[np.float64]

DEFAULT_CAPACITY = 64  # frames kept per avatar: 0.7 s at 90 Hz, more than max_delay
DEFAULT_WINDOW = 128  # arrivals the jitter statistics look back over (~1.4 s at 90 Hz)
DEFAULT_K = 1.0
DEFAULT_MIN_DELAY = 0.0
DEFAULT_MAX_DELAY = 0.25  # seconds; beyond this a viewer would rather stutter than lag
FALLBACK_INTERVAL = 1.0 / 90.0  # before two frames have arrived: a headset's rate


class Mode(enum.Enum):
    INTERPOLATE = "interpolate"
    LATEST = "zero-buffer"
    PREDICT = "predict"


@dataclass(frozen=True)
class Snapshot:
    seq: int
    t_capture: float  # server clock
    t_arrival: float  # the viewer's local clock
    rotations: Array  # (J, 4)
    root: Array  # (3,)


@dataclass(frozen=True)
class Sampled:
    """The pose to draw for one avatar."""

    rotations: Array  # (J, 4)
    root: Array  # (3,)
    t_capture: float  # the capture instant this pose stands for (server clock)
    newest: Snapshot  # the newest frame received (its arrival time, its seq)
    held: bool  # the target instant was past the newest frame: newest frame shown


class JitterEstimator:
    """Transit times over a sliding window: their minimum (base), the 95th percentile of
    their excess over it (jitter) and the median capture interval."""

    def __init__(self, window: int = DEFAULT_WINDOW) -> None:
        self._transit: deque[float] = deque(maxlen=window)
        self._capture: deque[float] = deque(maxlen=window)
        self._dirty = True
        self._base = 0.0
        self._jitter = 0.0
        self._interval = FALLBACK_INTERVAL

    def add(self, t_capture: float, t_arrival: float) -> None:
        self._transit.append(t_arrival - t_capture)
        self._capture.append(t_capture)
        self._dirty = True

    def _update(self) -> None:
        if not self._dirty:
            return
        self._dirty = False
        if not self._transit:
            return
        transit = np.fromiter(self._transit, np.float64, len(self._transit))
        self._base = float(transit.min())
        self._jitter = float(np.percentile(transit - self._base, 95.0))
        if len(self._capture) >= 2:
            gaps = np.diff(np.fromiter(self._capture, np.float64, len(self._capture)))
            gaps = gaps[gaps > 0.0]
            if len(gaps):
                self._interval = float(np.median(gaps))

    @property
    def base(self) -> float:
        """Least transit seen (clock offset + the fastest delivery), seconds."""
        self._update()
        return self._base

    @property
    def jitter_p95(self) -> float:
        self._update()
        return self._jitter

    @property
    def interval(self) -> float:
        self._update()
        return self._interval


class SnapshotBuffer:
    """One avatar's recent frames, in capture order, and its playout delay."""

    def __init__(self, capacity: int = DEFAULT_CAPACITY, window: int = DEFAULT_WINDOW,
                 k: float = DEFAULT_K, min_delay: float = DEFAULT_MIN_DELAY,
                 max_delay: float = DEFAULT_MAX_DELAY) -> None:
        self.frames: deque[Snapshot] = deque(maxlen=capacity)
        self.jitter = JitterEstimator(window)
        self.k, self.min_delay, self.max_delay = k, min_delay, max_delay
        self.underruns = 0  # samples that had to hold the newest frame
        self.dropped = 0  # frames that arrived out of order (older than the newest)

    def push(self, frame: AvatarFrame, t_arrival: float) -> None:
        self.add(Snapshot(frame.seq, frame.t_capture, t_arrival,
                          np.asarray(frame.rotations, np.float64),
                          np.asarray(frame.root, np.float64)))

    def add(self, snap: Snapshot) -> None:
        if self.frames and snap.t_capture <= self.frames[-1].t_capture:
            self.dropped += 1  # a duplicate or a late one: the newer frame already came
            return
        self.frames.append(snap)
        self.jitter.add(snap.t_capture, snap.t_arrival)

    @property
    def newest(self) -> Snapshot | None:
        return self.frames[-1] if self.frames else None

    @property
    def delay(self) -> float:
        """Playout delay beyond the least transit, seconds."""
        d = self.k * self.jitter.jitter_p95 + self.jitter.interval
        return float(min(max(d, self.min_delay), self.max_delay))

    def target(self, now: float) -> float:
        """The capture instant (server clock) to show at local time ``now``."""
        return now - self.jitter.base - self.delay

    def sample(self, now: float, mode: Mode = Mode.INTERPOLATE,
               server_now: float | None = None,
               predictor: prediction.PredictorParams = prediction.DEFAULT) -> Sampled | None:
        """``server_now``: ``now`` on the server clock (PREDICT mode; when unknown, the
        least transit stands in for the clock offset and the fastest delivery)."""
        newest = self.newest
        if newest is None:
            return None
        if mode is Mode.LATEST:
            return Sampled(newest.rotations, newest.root, newest.t_capture, newest, False)
        if mode is Mode.PREDICT:
            return self.predict_at(now - self.jitter.base if server_now is None
                                   else server_now, predictor)
        return self.sample_at(self.target(now))

    def predict_at(self, t: float, predictor: prediction.PredictorParams = prediction.DEFAULT
                   ) -> Sampled | None:
        """The newest frame carried forward to capture instant ``t`` (server clock)."""
        frames = self.frames
        if not frames:
            return None
        newest = frames[-1]
        if len(frames) < 2:  # no motion known yet: the frame as it is
            return Sampled(newest.rotations, newest.root, newest.t_capture, newest, False)
        # the frames the predictor's window reaches, and one spare for an uneven spacing
        n = min(len(frames), prediction.lags_needed(predictor, 1.0 / self.jitter.interval) + 2)
        recent = [frames[i] for i in range(len(frames) - n, len(frames))]
        times = np.array([f.t_capture for f in recent])
        rot, root = prediction.predict_latest(
            times, np.stack([f.rotations for f in recent]),
            np.stack([f.root for f in recent])[:, None], t, predictor)
        shown = min(max(t, newest.t_capture), newest.t_capture + predictor.max_horizon_s)
        return Sampled(rot, root[0], shown, newest, False)

    def sample_at(self, t: float) -> Sampled | None:
        """The pose at capture instant ``t``: interpolated between the bracketing frames,
        the oldest frame before them all, the newest (held) after them all."""
        frames = self.frames
        if not frames:
            return None
        newest = frames[-1]
        if t >= newest.t_capture:
            if t > newest.t_capture:
                self.underruns += 1
            return Sampled(newest.rotations, newest.root, newest.t_capture, newest,
                           t > newest.t_capture)
        if t <= frames[0].t_capture:
            a = frames[0]
            return Sampled(a.rotations, a.root, a.t_capture, newest, False)
        # newest first: the target is usually among the last few frames
        for i in range(len(frames) - 1, 0, -1):
            a, b = frames[i - 1], frames[i]
            if a.t_capture <= t:
                alpha = (t - a.t_capture) / (b.t_capture - a.t_capture)
                rot = R.slerp(a.rotations, b.rotations, alpha)
                root = a.root + alpha * (b.root - a.root)
                return Sampled(rot, root, t, newest, False)
        raise AssertionError("unreachable: t lies between the oldest and newest frames")


class Interpolator:
    """Snapshot buffers of every avatar, sampled together at one instant."""

    def __init__(self, mode: Mode = Mode.INTERPOLATE, capacity: int = DEFAULT_CAPACITY,
                 window: int = DEFAULT_WINDOW, k: float = DEFAULT_K,
                 min_delay: float = DEFAULT_MIN_DELAY,
                 max_delay: float = DEFAULT_MAX_DELAY,
                 predictor: prediction.PredictorParams = prediction.DEFAULT) -> None:
        self.mode = mode
        self.predictor = predictor
        self._settings = (capacity, window, k, min_delay, max_delay)
        self.buffers: dict[int, SnapshotBuffer] = {}

    def buffer(self, avatar_id: int) -> SnapshotBuffer:
        buf = self.buffers.get(avatar_id)
        if buf is None:
            buf = self.buffers[avatar_id] = SnapshotBuffer(*self._settings)
        return buf

    def push(self, frame: AvatarFrame, t_arrival: float) -> None:
        self.buffer(frame.avatar_id).push(frame, t_arrival)

    def remove(self, avatar_id: int) -> None:
        self.buffers.pop(avatar_id, None)

    def sample(self, now: float, to_server: Callable[[float], float] | None = None
               ) -> dict[int, Sampled]:
        """Every avatar at local time ``now``; ``to_server`` converts a local time to the
        server clock (the connection's offset), which PREDICT mode uses when given."""
        server_now = to_server(now) if to_server is not None else None
        out = {}
        for avatar_id, buf in self.buffers.items():
            s = buf.sample(now, self.mode, server_now, self.predictor)
            if s is not None:
                out[avatar_id] = s
        return out

    def delays(self) -> dict[int, float]:
        """Each avatar's current playout delay (0 in zero-buffer and predict modes), seconds."""
        if self.mode is not Mode.INTERPOLATE:
            return dict.fromkeys(self.buffers, 0.0)
        return {a: b.delay for a, b in self.buffers.items()}

    def toggle(self) -> Mode:
        """The next mode: interpolate, zero-buffer, predict, and round again."""
        order = [Mode.INTERPOLATE, Mode.LATEST, Mode.PREDICT]
        self.mode = order[(order.index(self.mode) + 1) % len(order)]
        return self.mode
