"""solver/prediction.py: carrying poses forward by a known delay (pure, numpy only)."""

from __future__ import annotations

import numpy as np
import pytest

from posecast.solver import prediction as P
from posecast.solver import rotations as R

FPS = 90.0
AXIS = np.array([0.3, 1.0, -0.2]) / np.linalg.norm([0.3, 1.0, -0.2])
TURN = 3.0  # rad/s
SPEED = np.array([0.5, -0.2, 1.1])  # m/s
PARAMS = [P.DEFAULT, P.BASELINES["velocity"], P.BASELINES["slimevr"],
          P.DEFAULT.with_(accel_gain=0.5, fast_speed=1.0, fast_turn=5.0)]


def steady(frames: int = 60) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two joints turning steadily (one of them the other way) and a root moving steadily."""
    t = np.arange(frames) / FPS
    q = np.stack([R.from_axis_angle(AXIS, TURN * t), R.from_axis_angle(AXIS, -TURN * t)], 1)
    p = (SPEED * t[:, None])[:, None]
    return t, q, p


@pytest.mark.parametrize("params", PARAMS, ids=lambda p: p.kind)
def test_steady_motion_is_carried_forward_exactly(params: P.PredictorParams) -> None:
    t, q, p = steady()
    h = 0.05
    qh, ph = P.predict_sequence(q, p, FPS, h, params)
    late = 20  # once every predictor has its window of past frames
    want_q = np.stack([R.from_axis_angle(AXIS, TURN * (t + h)),
                       R.from_axis_angle(AXIS, -TURN * (t + h))], 1)
    assert np.degrees(R.angle_between(qh[late:], want_q[late:])).max() < 1e-6
    assert np.allclose(ph[late:, 0], SPEED * (t[late:, None] + h), atol=1e-9)
    # 50 ms late without prediction: 8.6 deg and 61 mm behind
    assert np.degrees(R.angle_between(q[late:], want_q[late:])).min() == pytest.approx(
        np.degrees(TURN * h))


def test_no_delay_changes_nothing() -> None:
    _, q, p = steady()
    for params in PARAMS:
        qh, ph = P.predict_sequence(q, p, FPS, 0.0, params)
        assert qh is q and ph is p
        ql, pl = P.predict_latest(np.arange(5) / FPS, q[:5], p[:5], 4 / FPS, params)
        assert np.array_equal(ql, q[4]) and np.array_equal(pl, p[4])


def test_only_the_past_is_used() -> None:
    """Frame f's prediction is the same whatever comes after f: a viewer has no future."""
    rng = np.random.default_rng(3)
    q = R.normalize(rng.normal(size=(80, 4, 4)))
    p = rng.normal(size=(80, 2, 3))
    q2, p2 = q.copy(), p.copy()
    q2[41:] = R.normalize(rng.normal(size=(39, 4, 4)))
    p2[41:] += 5.0
    a = P.predict_sequence(q, p, FPS, 0.05)
    b = P.predict_sequence(q2, p2, FPS, 0.05)
    assert np.allclose(a[0][:41], b[0][:41]) and np.allclose(a[1][:41], b[1][:41])


def test_latest_matches_the_sequence() -> None:
    """The viewer's one-pose path and the eval's whole-recording path agree."""
    rng = np.random.default_rng(5)
    t = np.arange(50) / FPS
    q = R.normalize(R.identity((50, 3)) + 0.1 * np.cumsum(rng.normal(size=(50, 3, 4)), 0))
    p = np.cumsum(rng.normal(size=(50, 1, 3)), 0) * 0.01
    for params in PARAMS:
        qs, ps = P.predict_sequence(q, p, FPS, 0.04, params)
        ql, pl = P.predict_latest(t[:40], q[:40], p[:40], t[39] + 0.04, params)
        assert np.allclose(np.abs(np.sum(ql * qs[39], -1)), 1.0, atol=1e-9)
        assert np.allclose(pl, ps[39], atol=1e-12)


def test_slimevr_averages_its_last_six_deltas() -> None:
    p = np.zeros((10, 1, 3))
    p[:, 0, 0] = [0, 0, 0, 0, 1, 2, 3, 4, 5, 12]  # the newest delta is 7, the six average 2
    _, ph = P.predict_sequence(R.identity((10, 1)), p, FPS, 1.0 / FPS, P.BASELINES["slimevr"])
    assert ph[9, 0, 0] == pytest.approx(12 + 2.0)
    _, pv = P.predict_sequence(R.identity((10, 1)), p, FPS, 1.0 / FPS,
                               P.BASELINES["velocity"])
    assert pv[9, 0, 0] == pytest.approx(12 + 7.0)


def test_the_horizon_is_capped() -> None:
    t, q, p = steady()
    _, far = P.predict_latest(t[:30], q[:30], p[:30], t[29] + 10.0)
    assert np.allclose(far[0], SPEED * (t[29] + P.MAX_HORIZON_S))
