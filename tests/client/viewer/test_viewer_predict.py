"""The viewer's predict mode: each avatar's newest frame carried forward by its
capture-to-render latency (pure: no GL, no sockets)."""

from __future__ import annotations

import numpy as np
import pytest

from posecast.client.viewer.interpolation import Interpolator, Mode
from posecast.protocol import AvatarFrame
from posecast.solver import rotations as R

J = 5
RATE = 90.0
TURN = 2.0  # rad/s about +y, every joint
SPEED = np.array([0.8, 0.0, -0.3])  # m/s, the root
OFFSET = 1000.0  # server clock - viewer clock, seconds
TRANSIT = 0.030  # capture to arrival


def frame(seq: int, t_capture: float) -> AvatarFrame:
    q = R.from_axis_angle(np.array([0.0, 1.0, 0.0]), TURN * t_capture)
    return AvatarFrame(avatar_id=3, seq=seq, root=SPEED * t_capture,
                       rotations=np.tile(q, (J, 1)), t_capture=t_capture,
                       t_server_receive=t_capture, t_solved=t_capture, t_sent=t_capture)


def fill(interp: Interpolator, frames: int = 40) -> float:
    """Frames captured at 90 Hz (server clock), each arriving TRANSIT later; returns the
    newest capture time."""
    for i in range(frames):
        t = 1.0 + i / RATE
        interp.push(frame(i, t), t + TRANSIT - OFFSET)
    return 1.0 + (frames - 1) / RATE


def test_predict_shows_where_the_avatar_is_now() -> None:
    interp = Interpolator(Mode.PREDICT)
    newest = fill(interp)
    latency = 0.060  # the present instant is 60 ms after the newest capture
    now = newest + latency - OFFSET  # the viewer's clock
    s = interp.sample(now, lambda t: t + OFFSET)[3]
    truth = R.from_axis_angle(np.array([0.0, 1.0, 0.0]), TURN * (newest + latency))
    # steady motion is carried forward exactly; the newest frame would be 6.9 deg behind
    assert np.degrees(R.angle_between(s.rotations, truth)).max() < 0.01
    assert np.allclose(s.root, SPEED * (newest + latency), atol=1e-6)
    assert s.t_capture == pytest.approx(newest + latency)
    assert s.newest.seq == 39 and not s.held
    latest = interp.buffers[3].sample(now, Mode.LATEST)
    assert latest is not None
    assert np.degrees(R.angle_between(latest.rotations, truth)).max() == pytest.approx(
        np.degrees(TURN * latency), abs=1e-6)


def test_predict_without_a_clock_uses_the_least_transit() -> None:
    """Before clock sync the least transit stands in for offset + delivery: the pose is
    carried to (now - base), i.e. TRANSIT short of the true present."""
    interp = Interpolator(Mode.PREDICT)
    newest = fill(interp)
    now = newest + 0.050 - OFFSET
    s = interp.sample(now)[3]
    assert s.t_capture == pytest.approx(newest + 0.050 - TRANSIT)
    assert np.allclose(s.root, SPEED * (newest + 0.050 - TRANSIT), atol=1e-6)


def test_predict_holds_a_single_frame_and_caps_the_horizon() -> None:
    interp = Interpolator(Mode.PREDICT)
    interp.push(frame(0, 1.0), 1.0)
    s = interp.sample(5.0, lambda t: t)[3]
    assert np.allclose(s.root, SPEED * 1.0) and s.newest.seq == 0
    fill(interp := Interpolator(Mode.PREDICT))
    far = interp.sample(100.0, lambda t: t + OFFSET)[3]  # minutes late: no flinging
    newest = 1.0 + 39 / RATE
    assert far.t_capture == pytest.approx(newest + interp.predictor.max_horizon_s)
    assert np.allclose(far.root, SPEED * far.t_capture, atol=1e-6)


def test_mode_cycle_and_no_playout_delay() -> None:
    interp = Interpolator()
    fill(interp)
    assert [interp.toggle() for _ in range(3)] == [Mode.LATEST, Mode.PREDICT,
                                                   Mode.INTERPOLATE]
    interp.mode = Mode.PREDICT
    assert interp.delays() == {3: 0.0}
    assert Mode("predict") is Mode.PREDICT
