"""End-to-end latency from two horizontal traces of a video (the paper's section 3.2).

A camera films the real tracker and the screen that shows its avatar; the I/O edge
(``client.latency_video``) follows both with OpenCV and hands over each one's horizontal
position per video frame. Here, pure numpy:

1. gaps where a tracker lost its box are filled linearly;
2. each trace is smoothed with a Gaussian (one sigma for both, scaled to the swing) and
   normalised (zero mean, unit deviation);
3. peaks, minima and maxima, are found with a hysteresis (a turn counts once the trace
   has come back by ``swing`` of its spread), placed to a fraction of a frame by a parabola;
4. each tracker peak is paired with the avatar's next peak of the same kind, and the mean
   frame difference, times 1000 / fps, is the latency (eq. 15), with its spread;
5. beside it, the lag that maximises the cross-correlation of the two traces, refined
   between frames by a parabola: it uses every frame, not just the turns.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

DEFAULT_SMOOTHING_MS = 8.0  # Gaussian sigma: ~2 frames at 240 fps, below any turn's width
SWING_SIGMAS = 8.0  # the Gaussian's sigma: half a swing over this, if wider than the above
DEFAULT_SWING = 0.5  # a turn: the trace came back by half its standard deviation
DEFAULT_MAX_LAG_MS = 500.0  # longer than any interactive latency worth measuring
MIN_MOTION_PX = 3.0  # a box whose x spans less than this (smoothed) did not move
MIN_PAIRS = 2


class VideoLatencyError(ValueError):
    """The traces cannot give a latency; the message says why in one line."""


@dataclass(frozen=True)
class Peaks:
    """Turns of one trace: sub-frame positions and +1 (maximum) or -1 (minimum)."""

    frames: Array
    kinds: NDArray[np.int8]

    def __len__(self) -> int:
        return len(self.frames)


@dataclass
class VideoLatency:
    """The result; ``as_json`` is ``posecast latency-video --json``."""

    fps: float
    frames: float  # mean frame difference avatar - tracker, over the pairs (eq. 15)
    frames_std: float
    pairs: list[tuple[float, float]]  # (tracker peak, avatar peak), frames
    tracker_peaks: Peaks
    avatar_peaks: Peaks
    xcorr_frames: float  # the lag of best cross-correlation, sub-frame
    xcorr_r: float  # the correlation at that lag (1: identical shapes)
    mirrored: bool  # the avatar moves the other way on screen (a mirror view)
    tracker: Array  # the smoothed, normalised traces (plots)
    avatar: Array
    xcorr_lags: Array = field(default_factory=lambda: np.empty(0))
    xcorr_curve: Array = field(default_factory=lambda: np.empty(0))

    @property
    def latency_ms(self) -> float:
        return self.frames * 1000.0 / self.fps

    def as_json(self) -> dict[str, object]:
        to_ms = 1000.0 / self.fps
        lags = [a - t for t, a in self.pairs]
        return {"latency_ms": self.latency_ms, "frames": self.frames,
                "peaks": len(self.pairs), "fps": self.fps,
                "latency_std_ms": self.frames_std * to_ms,
                "latency_median_ms": float(np.median(lags)) * to_ms,
                "latency_min_ms": min(lags) * to_ms, "latency_max_ms": max(lags) * to_ms,
                "xcorr_latency_ms": self.xcorr_frames * to_ms,
                "xcorr_frames": self.xcorr_frames, "xcorr_r": self.xcorr_r,
                "tracker_peaks": len(self.tracker_peaks),
                "avatar_peaks": len(self.avatar_peaks), "mirrored": self.mirrored,
                "pairs": [[round(t, 3), round(a, 3)] for t, a in self.pairs]}


def fill_gaps(x: Array) -> Array:
    """``x`` with NaNs (frames where the box was lost) linearly interpolated; the ends
    held at the nearest known value."""
    x = np.asarray(x, dtype=np.float64)
    known = np.isfinite(x)
    if known.all() or not known.any():
        return x.copy()
    idx = np.arange(len(x))
    return np.interp(idx, idx[known], x[known])


def gaussian_smooth(x: Array, sigma: float) -> Array:
    """``x`` convolved with a normalised Gaussian of ``sigma`` samples; the ends are
    reflected so that they are not pulled towards zero. Symmetric: moves no peak."""
    x = np.asarray(x, dtype=np.float64)
    if sigma <= 0.0 or len(x) < 2:
        return x.copy()
    radius = max(1, math.ceil(3.0 * sigma))
    radius = min(radius, len(x) - 1)
    k = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
    padded = np.pad(x, radius, mode="reflect")
    return np.convolve(padded, k / k.sum(), mode="valid")


def half_swing_frames(x: Array) -> float:
    """The median number of frames between crossings of the trace's mean: half a swing
    (0 with fewer than two crossings)."""
    centred = np.asarray(x, dtype=np.float64) - float(np.mean(x))
    crossings = np.flatnonzero(np.signbit(centred[1:]) != np.signbit(centred[:-1]))
    return float(np.median(np.diff(crossings))) if len(crossings) > 2 else 0.0


def normalise(x: Array) -> Array:
    """Zero mean, unit standard deviation (a flat trace stays all zeros)."""
    x = np.asarray(x, dtype=np.float64)
    std = float(x.std())
    return (x - x.mean()) / std if std > 0.0 else np.zeros_like(x)


def _parabola_vertex(y0: float, y1: float, y2: float) -> float:
    """Offset in (-0.5, 0.5) of the vertex of the parabola through (-1, y0), (0, y1),
    (1, y2), where y1 is the extreme sample."""
    denom = y0 - 2.0 * y1 + y2
    if denom == 0.0:
        return 0.0
    return float(np.clip(0.5 * (y0 - y2) / denom, -0.5, 0.5))


def find_peaks(x: Array, swing: float = DEFAULT_SWING) -> Peaks:
    """Maxima and minima of ``x`` that the trace leaves by at least ``swing`` on both
    sides (hysteresis: noise smaller than ``swing`` makes no turn). They alternate."""
    x = np.asarray(x, dtype=np.float64)
    frames: list[float] = []
    kinds: list[int] = []
    if len(x) < 3:
        return Peaks(np.empty(0), np.empty(0, dtype=np.int8))
    # the first turn decides the direction; until then track both extremes (the first
    # frame is no turn: the trace may be on its way anywhere)
    hi = lo = 0
    direction = 0
    for i in range(1, len(x)):
        v = x[i]
        if direction >= 0 and v > x[hi]:
            hi = i
        if direction <= 0 and v < x[lo]:
            lo = i
        if direction >= 0 and x[hi] - v >= swing and (direction > 0 or hi > 0):
            frames.append(hi)
            kinds.append(1)
            direction, lo = -1, i
        elif direction <= 0 and v - x[lo] >= swing and (direction < 0 or lo > 0):
            frames.append(lo)
            kinds.append(-1)
            direction, hi = 1, i
    sub = [float(f) + (_parabola_vertex(x[int(f) - 1], x[int(f)], x[int(f) + 1])
                       if 0 < f < len(x) - 1 else 0.0) for f in frames]
    return Peaks(np.asarray(sub, dtype=np.float64), np.asarray(kinds, dtype=np.int8))


def match_peaks(tracker: Peaks, avatar: Peaks, max_lag: float,
                tolerance: float = 1.0) -> list[tuple[float, float]]:
    """Pairs (tracker peak, avatar peak): each tracker turn with the avatar's first turn
    of the same kind at most ``max_lag`` frames later (``tolerance`` frames earlier
    allowed, for noise), each avatar turn used once and the order kept. A tracker turn
    whose next turn of the same kind comes before that avatar turn has no partner (the
    avatar missed a swing); it is skipped, not paired one swing late."""
    pairs: list[tuple[float, float]] = []
    j = 0
    for i in range(len(tracker)):
        t, kind = float(tracker.frames[i]), int(tracker.kinds[i])
        while j < len(avatar) and avatar.frames[j] < t - tolerance:
            j += 1
        k = j
        while k < len(avatar) and int(avatar.kinds[k]) != kind:
            k += 1
        if k >= len(avatar) or avatar.frames[k] - t > max_lag:
            continue
        later = tracker.frames[i + 1:][tracker.kinds[i + 1:] == kind]
        if len(later) and later[0] - tolerance <= avatar.frames[k]:
            continue
        pairs.append((t, float(avatar.frames[k])))
        j = k + 1
    return pairs


def cross_correlation(a: Array, b: Array, max_lag: int) -> tuple[Array, Array]:
    """Pearson correlation of ``a[t]`` with ``b[t + lag]`` over their overlap, for every
    whole lag in [-max_lag, max_lag] (positive: ``b`` comes later)."""
    n = len(a)
    max_lag = max(0, min(max_lag, n - 3))
    lags = np.arange(-max_lag, max_lag + 1)
    r = np.empty(len(lags))
    for i, lag in enumerate(lags):
        x, y = (a[:n - lag], b[lag:]) if lag >= 0 else (a[-lag:], b[:n + lag])
        x = x - x.mean()
        y = y - y.mean()
        denom = math.sqrt(float(x @ x) * float(y @ y))
        r[i] = float(x @ y) / denom if denom > 0.0 else 0.0
    return lags.astype(np.float64), r


def best_lag(lags: Array, r: Array) -> tuple[float, float]:
    """The lag of the highest correlation, between frames by a parabola, and its r."""
    i = int(np.argmax(r))
    offset = _parabola_vertex(r[i - 1], r[i], r[i + 1]) if 0 < i < len(r) - 1 else 0.0
    return float(lags[i] + offset), float(r[i])


def measure(tracker_x: Array, avatar_x: Array, fps: float, *,
            smoothing_ms: float = DEFAULT_SMOOTHING_MS, swing: float = DEFAULT_SWING,
            max_lag_ms: float = DEFAULT_MAX_LAG_MS) -> VideoLatency:
    """The latency of ``avatar_x`` behind ``tracker_x`` (horizontal positions in pixels,
    one per video frame, NaN where lost) filmed at ``fps``; VideoLatencyError if the
    traces do not show it."""
    if not (math.isfinite(fps) and fps > 0.0):
        raise VideoLatencyError(f"the video's frame rate is {fps}: give it with --fps")
    raw = {"tracker": np.asarray(tracker_x, dtype=np.float64),
           "avatar": np.asarray(avatar_x, dtype=np.float64)}
    if len(raw["tracker"]) != len(raw["avatar"]):
        raise ValueError("the traces must have one value per frame each")
    light = smoothing_ms * fps / 1000.0
    filled: dict[str, Array] = {}
    for name, x in raw.items():
        if not np.isfinite(x).any():
            raise VideoLatencyError(f"the {name} box was lost in every frame")
        filled[name] = fill_gaps(x)
    # one kernel for both traces keeps their delay exact, however wide it is: wide enough
    # to flatten noise on the slow, flat turns of a swing, narrow enough to keep each turn
    sigma = max(light, half_swing_frames(gaussian_smooth(filled["tracker"], light))
                / SWING_SIGMAS)
    smooth: dict[str, Array] = {}
    for name, x in filled.items():
        s = gaussian_smooth(x, sigma)
        span = float(s.max() - s.min())
        if span < MIN_MOTION_PX:
            raise VideoLatencyError(
                f"the {name} box does not move (its x spans {span:.1f} px): swing the "
                "tracker left and right in front of the camera")
        smooth[name] = s
    t_norm, a_norm = normalise(smooth["tracker"]), normalise(smooth["avatar"])
    max_lag = max(1, round(max_lag_ms * fps / 1000.0))
    lags, r = cross_correlation(t_norm, a_norm, max_lag)
    # a mirror view moves the avatar the other way: its best correlation is negative
    mirrored = bool(-r.min() > r.max())
    if mirrored:
        a_norm, r = -a_norm, -r
    xcorr_frames, xcorr_r = best_lag(lags, r)
    t_peaks, a_peaks = find_peaks(t_norm, swing), find_peaks(a_norm, swing)
    pairs = match_peaks(t_peaks, a_peaks, max_lag)
    if len(pairs) < MIN_PAIRS:
        raise VideoLatencyError(
            f"only {len(pairs)} turn(s) of the tracker matched one of the avatar "
            f"({len(t_peaks)} tracker and {len(a_peaks)} avatar turns found): film "
            "several swings, and check that the boxes hold the tracker and its avatar")
    diffs = np.array([a - t for t, a in pairs])
    return VideoLatency(fps=fps, frames=float(diffs.mean()), frames_std=float(diffs.std()),
                        pairs=pairs, tracker_peaks=t_peaks, avatar_peaks=a_peaks,
                        xcorr_frames=xcorr_frames, xcorr_r=xcorr_r, mirrored=mirrored,
                        tracker=t_norm, avatar=a_norm, xcorr_lags=lags, xcorr_curve=r)
