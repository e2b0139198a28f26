"""Snapshot interpolation (pure: no GL, no sockets)."""

from __future__ import annotations

import numpy as np
import pytest

from posecast.client.viewer.interpolation import (
    Interpolator,
    JitterEstimator,
    Mode,
    Snapshot,
    SnapshotBuffer,
)
from posecast.protocol import AvatarFrame
from posecast.solver import rotations as R

J = 5
RATE = 90.0


def snap(seq: int, t_capture: float, t_arrival: float, angle: float = 0.0,
         root: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Snapshot:
    """Every joint turned ``angle`` about +y."""
    q = R.from_axis_angle(np.array([0.0, 1.0, 0.0]), angle)
    return Snapshot(seq, t_capture, t_arrival, np.tile(q, (J, 1)), np.array(root))


def frame(avatar_id: int, seq: int, t_capture: float, angle: float = 0.0) -> AvatarFrame:
    q = R.from_axis_angle(np.array([0.0, 1.0, 0.0]), angle)
    return AvatarFrame(avatar_id=avatar_id, seq=seq, root=np.zeros(3),
                       rotations=np.tile(q, (J, 1)), t_capture=t_capture,
                       t_server_receive=t_capture, t_solved=t_capture, t_sent=t_capture)


def test_slerp_midpoint_of_two_frames() -> None:
    buf = SnapshotBuffer()
    buf.add(snap(1, 10.0, 10.001, angle=0.0, root=(0.0, 1.0, 0.0)))
    buf.add(snap(2, 10.1, 10.101, angle=np.pi / 2, root=(1.0, 1.0, 2.0)))
    s = buf.sample_at(10.05)
    assert s is not None and not s.held
    # halfway between 0 and 90 degrees about y is 45 degrees, on every joint
    expected = R.from_axis_angle(np.array([0.0, 1.0, 0.0]), np.pi / 4)
    assert np.allclose(np.abs(np.sum(s.rotations * expected, axis=1)), 1.0, atol=1e-12)
    assert np.allclose(s.root, [0.5, 1.0, 1.0])
    assert s.t_capture == pytest.approx(10.05)
    assert s.newest.seq == 2


def test_slerp_takes_the_short_way_round() -> None:
    buf = SnapshotBuffer()
    a = snap(1, 0.0, 0.0, angle=0.2)
    b = snap(2, 1.0, 1.0, angle=0.4)
    buf.add(a)
    buf.add(Snapshot(2, 1.0, 1.0, -b.rotations, b.root))  # same rotation, other sign
    s = buf.sample_at(0.5)
    assert s is not None
    assert np.allclose(R.angle(s.rotations), 0.3, atol=1e-9)


def test_zero_buffer_mode_returns_the_newest_frame() -> None:
    buf = SnapshotBuffer()
    for i in range(5):
        buf.add(snap(i, i / RATE, i / RATE + 0.002, angle=0.1 * i))
    s = buf.sample(now=0.0, mode=Mode.LATEST)  # whatever the time: the newest as it is
    assert s is not None and s.newest.seq == 4
    assert np.array_equal(s.rotations, buf.frames[-1].rotations)
    assert s.t_capture == buf.frames[-1].t_capture


def test_interpolating_renders_behind_the_newest_frame_and_holds_on_underrun() -> None:
    buf = SnapshotBuffer()
    for i in range(20):
        buf.add(snap(i, i / RATE, i / RATE + 0.003))  # steady: no jitter
    newest = buf.frames[-1]
    s = buf.sample(now=newest.t_arrival, mode=Mode.INTERPOLATE)
    assert s is not None and not s.held
    # one frame interval behind the newest capture (no jitter: the delay is one interval)
    assert buf.delay == pytest.approx(1 / RATE)
    assert s.t_capture == pytest.approx(newest.t_capture - 1 / RATE)
    late = buf.sample(now=newest.t_arrival + 0.1, mode=Mode.INTERPOLATE)
    assert late is not None and late.held and late.newest is newest
    assert buf.underruns == 1


def test_adaptive_delay_grows_with_jitter_and_shrinks_back() -> None:
    rng = np.random.default_rng(1)
    buf = SnapshotBuffer(window=128)
    t = 0.0
    for i in range(200):  # steady arrivals
        t = i / RATE
        buf.add(snap(i, t, t + 0.002))
    calm = buf.delay
    for i in range(200, 400):  # up to 30 ms of extra delay on arrival
        t = i / RATE
        buf.add(snap(i, t, t + 0.002 + rng.uniform(0.0, 0.030)))
    jittery = buf.delay
    for i in range(400, 600):
        t = i / RATE
        buf.add(snap(i, t, t + 0.002))
    assert calm == pytest.approx(1 / RATE, abs=1e-6)
    assert jittery > calm + 0.020  # p95 of U(0, 30 ms) is 28.5 ms
    assert jittery <= 1 / RATE + 0.030 + 1e-9
    assert buf.delay == pytest.approx(calm, abs=1e-6)  # the window forgot the jitter


def test_delay_is_clamped() -> None:
    buf = SnapshotBuffer(max_delay=0.05)
    for i in range(100):
        buf.add(snap(i, i / RATE, i / RATE + (0.5 if i % 2 else 0.0)))
    assert buf.delay == 0.05


def test_jitter_is_independent_of_the_clock_offset() -> None:
    a, b = JitterEstimator(), JitterEstimator()
    rng = np.random.default_rng(2)
    for i in range(100):
        extra = rng.uniform(0, 0.01)
        a.add(i / RATE, i / RATE + extra)
        b.add(i / RATE, i / RATE + extra + 1234.5)  # the viewer's clock is elsewhere
    assert a.jitter_p95 == pytest.approx(b.jitter_p95, abs=1e-9)
    assert a.interval == pytest.approx(1 / RATE)


def test_late_and_duplicate_frames_are_dropped() -> None:
    buf = SnapshotBuffer()
    buf.add(snap(2, 2.0, 2.0))
    buf.add(snap(1, 1.0, 2.1))  # older than the newest: arrived out of order
    buf.add(snap(2, 2.0, 2.2))  # a duplicate
    assert [f.seq for f in buf.frames] == [2]
    assert buf.dropped == 2


def test_interpolator_per_avatar_and_mode_toggle() -> None:
    interp = Interpolator()
    for i in range(3):
        interp.push(frame(7, i, i / RATE, angle=0.1 * i), i / RATE + 0.001)
        interp.push(frame(9, i, i / RATE), i / RATE + 0.001)
    assert set(interp.sample(now=1.0)) == {7, 9}
    assert interp.toggle() is Mode.LATEST
    assert interp.sample(now=1.0)[7].newest.seq == 2
    assert interp.delays() == {7: 0.0, 9: 0.0}
    interp.remove(9)
    assert set(interp.sample(now=1.0)) == {7}
