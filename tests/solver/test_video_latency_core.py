"""solver.video_latency on synthetic traces: smoothing keeps peaks where they are, turns
are found to a fraction of a frame, pairing skips a missed swing, and both estimates find
known delays, whole and fractional, through noise, in a mirror, across lost frames."""

from __future__ import annotations

import numpy as np
import pytest

from posecast.solver.video_latency import (
    Peaks,
    VideoLatencyError,
    best_lag,
    cross_correlation,
    fill_gaps,
    find_peaks,
    gaussian_smooth,
    match_peaks,
    measure,
)

FPS = 240.0


def wandering_swing(frames: int, amplitude: float = 100.0) -> np.ndarray:
    """A swing whose rate wanders between 1 and 2 per second, in pixels."""
    t = np.arange(frames) / FPS
    rate = 1.5 + 0.5 * np.sin(2.0 * np.pi * t / 2.3)
    return 160.0 + amplitude * np.sin(np.cumsum(2.0 * np.pi * rate / FPS))


def delayed(x: np.ndarray, frames: float) -> np.ndarray:
    """``x`` seen ``frames`` later (fractional: linear interpolation)."""
    idx = np.arange(len(x), dtype=np.float64)
    return np.interp(idx - frames, idx, x)


def test_gaussian_smoothing_keeps_level_and_peak() -> None:
    assert np.allclose(gaussian_smooth(np.full(50, 7.0), 3.0), 7.0)  # reflected ends
    bump = np.exp(-0.5 * ((np.arange(101) - 40.0) / 6.0) ** 2)
    smooth = gaussian_smooth(bump, 4.0)
    assert smooth.argmax() == 40 and smooth.max() < bump.max()
    assert len(smooth) == len(bump)


def test_gaps_are_filled_linearly() -> None:
    x = np.array([np.nan, 1.0, np.nan, np.nan, 4.0, np.nan])
    assert np.allclose(fill_gaps(x), [1.0, 1.0, 2.0, 3.0, 4.0, 4.0])


def test_turns_are_found_between_frames_and_alternate() -> None:
    # cos(2 pi (i - 10.3) / 80): maxima at 10.3 + 80 k, minima at 50.3 + 80 k
    i = np.arange(400)
    x = np.cos(2.0 * np.pi * (i - 10.3) / 80.0)
    peaks = find_peaks(x, swing=0.5)
    assert list(peaks.kinds) == [1, -1, 1, -1, 1, -1, 1, -1, 1, -1]
    expected = 10.3 + 40.0 * np.arange(10)
    assert np.abs(peaks.frames - expected).max() < 0.05


def test_noise_smaller_than_the_swing_makes_no_turn() -> None:
    rng = np.random.default_rng(3)
    x = np.sin(np.arange(600) * 2.0 * np.pi / 200.0) + rng.uniform(-0.2, 0.2, 600)
    peaks = find_peaks(x, swing=0.5)
    assert len(peaks) == 6  # three periods: three maxima, three minima
    assert find_peaks(rng.uniform(-0.2, 0.2, 600), swing=0.5).frames.size == 0


def test_pairing_skips_a_swing_the_avatar_missed() -> None:
    tracker = Peaks(np.array([10.0, 50.0, 90.0, 130.0]), np.array([1, -1, 1, -1], np.int8))
    # the avatar's maximum after 50 is missing: its minimum at 57 pairs with 50, and the
    # tracker's maximum at 90 must not take the avatar's next maximum (none) or a minimum
    avatar = Peaks(np.array([17.0, 57.0, 137.0]), np.array([1, -1, -1], np.int8))
    assert match_peaks(tracker, avatar, max_lag=30) == [(10.0, 17.0), (50.0, 57.0),
                                                        (130.0, 137.0)]
    # the maximum at 10 does not take 95: the tracker's next maximum (90) comes first
    late = Peaks(np.array([95.0]), np.array([1], np.int8))
    assert match_peaks(tracker, late, max_lag=200) == [(90.0, 95.0)]


def test_cross_correlation_finds_a_fractional_delay() -> None:
    x = wandering_swing(960)
    lags, r = cross_correlation(x, delayed(x, 7.4), 40)
    lag, peak = best_lag(lags, r)
    assert abs(lag - 7.4) < 0.1 and peak > 0.99


@pytest.mark.parametrize("delay", [3.0, 7.5, 8.0, 15.0, 40.0])
def test_measure_finds_delays_through_noise(delay: float) -> None:
    rng = np.random.default_rng(int(delay * 10))
    x = wandering_swing(960)
    tracker = x + rng.normal(0.0, 2.0, len(x))
    avatar = 0.5 * delayed(x, delay) + 300.0 + rng.normal(0.0, 2.0, len(x))  # smaller
    result = measure(tracker, avatar, FPS)
    assert abs(result.frames - delay) < 0.5
    assert abs(result.xcorr_frames - delay) < 0.5
    assert abs(result.latency_ms - delay * 1000.0 / FPS) < 0.5 * 1000.0 / FPS
    assert len(result.pairs) >= 8 and not result.mirrored
    doc = result.as_json()
    assert doc["peaks"] == len(result.pairs) and doc["fps"] == FPS
    assert doc["latency_std_ms"] < 1000.0 / FPS  # the turns agree within a frame


def test_a_mirrored_avatar_and_lost_frames() -> None:
    x = wandering_swing(960)
    avatar = 600.0 - delayed(x, 10.0)  # a mirror view: the avatar moves the other way
    avatar[200:230] = np.nan  # the box was lost for 30 frames
    result = measure(x, avatar, FPS)
    assert result.mirrored
    assert abs(result.frames - 10.0) < 0.5 and abs(result.xcorr_frames - 10.0) < 0.5


def test_what_gives_no_latency_says_why() -> None:
    x = wandering_swing(960)
    with pytest.raises(VideoLatencyError, match="avatar box does not move"):
        measure(x, np.full(960, 200.0), FPS)
    with pytest.raises(VideoLatencyError, match="tracker box was lost in every frame"):
        measure(np.full(960, np.nan), x, FPS)
    with pytest.raises(VideoLatencyError, match="--fps"):
        measure(x, x, 0.0)
    with pytest.raises(VideoLatencyError, match="turn"):  # half a swing: one turn at most
        measure(x[:100], delayed(x, 5.0)[:100], FPS)
