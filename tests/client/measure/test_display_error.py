"""Display error (client/measure/display_error.py): the pose a viewer presents against the
player's true pose at that instant. Here with frames that arrive a known time after
capture, so the expected error follows from the motion; the demo's run over the real
emulator is in test_demo_network.py."""

from __future__ import annotations

import numpy as np
import pytest

from posecast.client.bench.demo import _server_rig
from posecast.client.builtin import builtin_motion_path
from posecast.client.measure.display_error import (
    Arrival,
    CaptureLog,
    DisplayError,
    measure_display_error,
)
from posecast.client.sources.bvh_source import ROLES, BvhSource
from posecast.client.viewer.interpolation import Mode
from posecast.protocol import AvatarBatch
from posecast.server.avatars import AvatarSolver

RATE = 90.0


def _log(times: np.ndarray, poses: np.ndarray) -> CaptureLog:
    return CaptureLog(1, ROLES, poses[0], times, poses)


def test_the_true_pose_is_interpolated_between_samples() -> None:
    times = np.array([0.0, 0.1, 0.2])
    poses = np.zeros((3, len(ROLES), 7))
    poses[..., 6] = 1.0
    poses[:, :, 0] = [[0.0], [1.0], [3.0]]  # x of every device
    half = np.array([0.0, np.sin(np.pi / 4), 0.0, np.cos(np.pi / 4)])  # 90 deg about y
    poses[2, :, 3:] = half
    at = _log(times, poses).at(np.array([0.05, 0.1, 0.15, 0.2]))
    assert at[:, 0, 0] == pytest.approx([0.5, 1.0, 2.0, 3.0])
    # halfway between identity and 90 degrees about y: 45 degrees
    assert at[2, 0, 3:] == pytest.approx([0.0, np.sin(np.pi / 8), 0.0, np.cos(np.pi / 8)])


def test_a_looping_clip_s_seam_is_left_out() -> None:
    times = np.arange(10) * 0.1
    poses = np.zeros((10, len(ROLES), 7))
    poses[5:, :, 2] = -3.6  # the walker jumps back to the start of the clip at t = 0.5
    near = _log(times, poses).near_jump(np.array([0.45, 0.5, 0.9, 0.99, 1.0, 1.2]), 0.5)
    assert near.tolist() == [False, True, True, True, False, False]


def _arrivals(seconds: float, late: float) -> tuple[list[CaptureLog], list[Arrival]]:
    """The built-in walk captured at 90 Hz, solved as the server solves it, each frame
    arriving ``late`` seconds after its capture (the clock offset 0: one clock)."""
    source = BvhSource(builtin_motion_path(), loop=True, rate_hz=RATE, smooth=True)
    n = int(seconds * RATE)
    times = 100.0 + np.arange(n) / RATE
    poses = np.stack([source.read().poses for _ in range(n)])  # type: ignore[union-attr]
    tpose = np.concatenate([source.tpose_positions, source.tpose_rotations], axis=1)
    solver = AvatarSolver(_server_rig(), "analytic")
    solver.calibrate(7, ROLES, tpose[:, :3], tpose[:, 3:])
    arrivals = []
    for k in range(n):
        pose = solver.solve([(7, ROLES, poses[k])])
        batch = AvatarBatch.from_arrays([7], [k], pose.root, pose.rotations,
                                        [times[k]], [times[k]], times[k], t_sent=times[k])
        arrivals.append(Arrival(times[k] + late, 0.0, batch))
    return [CaptureLog(7, ROLES, tpose, times, poses)], arrivals


def _measure(seconds: float, late: float) -> DisplayError:
    captures, arrivals = _arrivals(seconds, late)
    return measure_display_error(captures, arrivals, _server_rig())


def test_display_error_grows_with_the_delay_and_the_buffer() -> None:
    p50 = {late: {m: float(np.median(e)) for m, e in _measure(2.5, late).errors_mm.items()}
           for late in (0.0, 0.05, 0.1)}
    zero = [p50[late][Mode.LATEST.value] for late in (0.0, 0.05, 0.1)]
    # frames on time: the newest frame is at most one capture interval (11 ms) old
    assert zero[0] < 15.0
    # the walker's body moves at ~1.3 m/s: 50 ms late is some 60 mm, 100 ms twice that
    assert 30.0 < zero[1] < 120.0 and 1.6 * zero[1] < zero[2] < 2.4 * zero[1]
    # interpolation shows the past by its playout delay on top: one capture interval
    # with no jitter
    for late in (0.0, 0.05, 0.1):
        assert p50[late][Mode.INTERPOLATE.value] > p50[late][Mode.LATEST.value]
    predict = getattr(Mode, "PREDICT", None)  # part of the viewer since issue 16
    if predict is not None:  # carried forward by the delay, the pose is nearer the truth
        for late in (0.05, 0.1):
            assert p50[late][predict.value] < 0.5 * p50[late][Mode.LATEST.value]


def test_a_smooth_source_samples_between_the_clip_s_frames() -> None:
    nearest = BvhSource(builtin_motion_path(), loop=True, rate_hz=90.0)
    smooth = BvhSource(builtin_motion_path(), loop=True, rate_hz=90.0, smooth=True)
    rows = [smooth.read().poses for _ in range(4)]  # type: ignore[union-attr]
    frames = [nearest.read().poses for _ in range(4)]  # type: ignore[union-attr]
    # 120 fps at 90 Hz: frames 0, 1.33, 2.67, 4; nearest gives 0, 1, 3, 4
    assert np.allclose(rows[0], frames[0]) and np.allclose(rows[3], frames[3])
    hip = ROLES.index("hip")
    want = nearest.poses[1, hip, :3] + (nearest.poses[2, hip, :3] - nearest.poses[1, hip, :3]) / 3
    assert rows[1][hip, :3] == pytest.approx(want, abs=1e-9)
    # evenly spaced in time, the hip moves evenly: no 1-2-1 frame steps
    steps = np.linalg.norm(np.diff(np.array(rows)[:, hip, :3], axis=0), axis=1)
    assert steps.max() < 1.2 * steps.min()


def test_the_playout_delay_is_reported_per_instant() -> None:
    result = _measure(2.5, 0.02)
    # steady arrivals: the buffer holds one capture interval (11.1 ms) and no more
    assert result.delay_json()["p50"] == pytest.approx(1e3 / RATE, abs=0.5)
    assert set(result.as_json()) == {m.value for m in Mode}
    assert all(e["n"] > 0 for e in result.as_json().values())


def test_a_pose_on_time_is_the_true_pose() -> None:
    """Presented just as each frame arrives, with no delay, the received pose is the true
    one: the truth is the server's solve of the same samples (these batches are not
    encoded, so not even the wire's quantization of the rotations is left)."""
    captures, arrivals = _arrivals(2.5, 0.0)
    # instants 1 us after each capture (90 Hz from the first frame + 1 s): that frame is in
    result = measure_display_error(captures, arrivals, _server_rig(), rate_hz=RATE,
                                   settle_s=1.0 + 1e-6)
    on_time = result.errors_mm[Mode.LATEST.value]
    assert len(on_time) > 60
    assert float(np.percentile(on_time, 95)) < 0.1, np.percentile(on_time, [50, 95, 100])
