"""The headset's parts: stereo cameras, the mirror's geometry, the local body against the
server's, the reports, and ``play --hmd`` / ``--hmd-out`` through the real command."""

from __future__ import annotations

import asyncio
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from commands import CLIP
from conftest import serving
from PIL import Image

from posecast.client.builtin import builtin_motion_path
from posecast.client.headset.local_body import LocalBody
from posecast.client.headset.room import hud_anchor, place_mirror
from posecast.client.headset.stereo import (
    VIVE_RECOMMENDED_SIZE,
    eye_cameras,
    frustum,
    heading_of,
    headset_from_device,
    opengl_depth,
    pose_matrix,
    reflected,
    vive_setup,
)
from posecast.client.headset.view import HeadsetFrameDone
from posecast.client.measure.reports import Reports
from posecast.client.session.spectator import Spectator
from posecast.client.sources.bvh_source import BvhSource
from posecast.protocol import ClockEstimator
from posecast.protocol.messages import MAX_REPORT_POSES
from posecast.server.app import Session
from posecast.server.avatars import AvatarSolver
from posecast.solver import rotations as R


# --------------------------------------------------------------------------- stereo
def test_a_d3d_projection_remapped_lands_every_point_where_opengl_does() -> None:
    near, far = 0.1, 50.0
    gl = frustum(1.39, 1.24, 1.47, 1.46, near, far)
    d3d = gl.copy()  # openvr's ComposeProjection: depth 0..1
    d3d[2] = [0.0, 0.0, -far / (far - near), -far * near / (far - near)]
    np.testing.assert_allclose(opengl_depth(d3d), gl, atol=1e-12)
    # a point at the near plane is at depth -1, at the far plane +1
    for z, want in ((-near, -1.0), (-far, 1.0)):
        clip = gl @ [0.0, 0.0, z, 1.0]
        assert clip[2] / clip[3] == pytest.approx(want)


def test_the_eyes_sit_an_ipd_apart_and_see_a_point_with_its_disparity() -> None:
    setup = vive_setup()
    assert (setup.width, setup.height) == VIVE_RECOMMENDED_SIZE
    head = pose_matrix([0.3, 1.6, 0.2], R.from_axis_angle([0.0, 1.0, 0.0], 0.7))
    left, right = eye_cameras(head, setup)
    assert np.linalg.norm(left.eye - right.eye) == pytest.approx(0.063)
    # the left eye is to the head's left (its -x)
    assert (R.to_matrix(R.from_axis_angle([0.0, 1.0, 0.0], 0.7)).T
            @ (left.eye - right.eye))[0] < 0
    # a point 1 m ahead of the head: the left eye sees it right of where the right
    # eye does, by f * IPD / depth, plus the lenses' asymmetry (each eye sees more
    # outwards: its view's centre is off the picture's)
    ahead = head[:3, 3] - head[:3, 2]
    (xl, _), (xr, _) = (c.project(ahead[None, :], setup.width, setup.height)[0][0]
                        for c in (left, right))
    f = setup.projection[0][0, 0] * setup.width / 2
    skew = (setup.projection[1][0, 2] - setup.projection[0][0, 2]) * setup.width / 2
    assert skew > 0.0
    assert xl - xr == pytest.approx(f * 0.063 + skew, rel=1e-6)


def test_a_mirror_camera_sees_each_point_at_its_reflection() -> None:
    setup = vive_setup()
    cam, _ = eye_cameras(pose_matrix([0.0, 1.6, 0.0], R.IDENTITY), setup)
    plane = np.array([0.0, 0.0, 1.0, 2.0])  # z = -2, facing +z (the player)
    mirrored = reflected(cam, plane)
    p = np.array([[0.2, 1.2, -0.5]])
    image = p.copy()
    image[0, 2] = -4.0 - p[0, 2]  # behind the mirror, as far as p is before it
    got, _ = mirrored.project(p, setup.width, setup.height)
    want, _ = cam.project(image, setup.width, setup.height)
    np.testing.assert_allclose(got, want, atol=1e-9)
    assert mirrored.mirrored and mirrored.eye[2] == pytest.approx(-4.0)


def test_a_head_device_is_turned_to_look_where_the_person_faced() -> None:
    source = BvhSource(builtin_motion_path())  # a mocap head joint: +z forward
    t = source.calibration()
    pos = {r: t.positions[i] for i, r in enumerate(t.roles)}
    q = t.rotations[t.roles.index("head")]
    heading = heading_of(pos)
    turn = headset_from_device(q, heading)
    forward = R.rotate(R.mul(q, turn), [0.0, 0.0, -1.0])
    forward[1] = 0.0
    assert np.degrees(np.arccos(forward @ heading / np.linalg.norm(forward))) < 1.0
    # a real headset (its -z already forward) needs no turn
    vive = R.mul(R.between([0.0, 0.0, -1.0], heading), R.IDENTITY)
    assert np.degrees(R.angle(headset_from_device(vive, heading))) < 1e-6


def test_the_mirror_stands_ahead_facing_back_and_the_hud_below_the_eyes() -> None:
    m = place_mirror(np.array([1.0, 1.7, 1.0]), np.array([0.0, 0.0, -1.0]), 2.0)
    np.testing.assert_allclose(m.centre[[0, 2]], [1.0, -1.0])
    np.testing.assert_allclose(m.normal, [0.0, 0.0, 1.0])
    assert m.corners()[:, 1].min() > 0.0  # on the floor, not through it
    assert m.plane @ [1.0, 1.7, 1.0, 1.0] == pytest.approx(2.0)  # the player's side: +
    head = pose_matrix([0.0, 1.7, 0.0], R.from_axis_angle([1.0, 0.0, 0.0], -0.6))
    anchor = hud_anchor(head)  # looking down does not sink the HUD into the floor
    assert anchor[1] == pytest.approx(1.7 - 0.5) and anchor[2] == pytest.approx(-1.2)


# --------------------------------------------------------------------------- the body
def test_the_local_body_is_the_servers_body() -> None:
    """From the same T-pose and frames, the headset's solve and the server's are the same
    rotations: the player sees the body everyone else sees."""
    source = BvhSource(builtin_motion_path(), devices=("head", "hip", "left_hand",
                                                       "right_hand", "left_foot",
                                                       "right_foot"))
    tpose = source.calibration()
    local = LocalBody()
    local.calibrate(tpose, 7, "me")
    server = AvatarSolver(local.rig, "analytic")
    cal = server.calibrate(7, tpose.roles, tpose.positions, tpose.rotations)
    assert local.info is not None
    np.testing.assert_array_equal(local.info.rest_offsets, cal.offsets)
    for _ in range(40):
        sample = source.read()
        assert sample is not None
        mine = local.solve(sample)
        theirs = server.solve([(7, sample.roles, sample.poses)], sample.t_capture)
        np.testing.assert_allclose(mine.rotations, theirs.rotations[0], atol=1e-12)
        np.testing.assert_allclose(mine.root, theirs.root[0], atol=1e-12)


def test_reports_carry_the_frames_and_wait_for_a_synced_clock() -> None:
    reports = Reports("headset")
    clock = ClockEstimator()
    reports.add(0.012, [(100.0, 5.0)], 5.004)
    assert reports.take(clock) is None  # not synced: kept
    clock.add(1.0, 96.001, 96.001, 1.002)  # server 95 s ahead, 2 ms round trip
    assert clock.synced
    report = reports.take(clock)
    assert report is not None and report.pose_to_submit is not None
    assert report.pose_to_submit.tolist() == [0.012]
    offset = clock.offset
    assert report.t_received.tolist() == [pytest.approx(5.0 + offset)]
    assert report.t_presented.tolist() == [pytest.approx(5.004 + offset)]
    assert reports.take(clock) is None  # taken once
    # a screen's frames carry no pose_to_submit; the rows alone make a report
    reports.add(None, [(101.0, 6.0)], 6.01)
    screen = reports.take(clock)
    assert screen is not None and screen.pose_to_submit is None
    assert screen.t_capture.tolist() == [101.0]
    # a server that refuses reports: said once, then no more are sent
    assert not reports.stop_if_refused("rate_limited: too many pings")
    assert reports.stop_if_refused("unknown_type: type: unknown message type "
                                   "'viewer_report'") and not reports.enabled


def test_reports_carry_a_few_avatars_as_shown_from_every_frame() -> None:
    """Shown poses for the server's display error: a reservoir of MAX_REPORT_POSES over
    every avatar of every frame, on the server clock, in the mode they were shown in."""
    reports = Reports("headset", seed=4)
    clock = ClockEstimator()
    clock.add(1.0, 96.001, 96.001, 1.002)
    rest = np.tile([0.0, 0.0, 0.0, 1.0], (53, 1))
    kept = set()
    for _ in range(20):
        for frame in range(100):  # 3 others a frame
            t = 10.0 + frame / 90
            shown = [(a, np.array([float(a), 1.0, t]), rest) for a in (1, 2, 3)]
            reports.headset_frame(HeadsetFrameDone(0.01, [], shown, "predict", t))
        report = reports.take(clock)
        assert report is not None and (report.viewer, report.mode) == ("headset", "predict")
        assert len(report.shown) == MAX_REPORT_POSES
        for p in report.shown:  # each the pose it was shown with, at its instant
            assert p.root[0] == p.avatar_id
            assert p.t_presented == pytest.approx(p.root[2] + clock.offset)
        kept |= {(p.avatar_id, round(p.root[2], 6)) for p in report.shown}
    # uniform over the 300 (avatar, frame) pairs: 80 draws land nearly all on new pairs,
    # where keeping the first ones only would repeat the same 4
    assert len(kept) >= 60
    # a mode switched mid-report: the old mode's poses are not the report's
    reports.show("predict", [1], [np.zeros(3)], [rest], 20.0)
    reports.show("interpolate", [2], [np.zeros(3)], [rest], 20.1)
    report = reports.take(clock)
    assert report is not None and report.mode == "interpolate"
    assert [p.avatar_id for p in report.shown] == [2]


# --------------------------------------------------------------------------- the command
def run(*args: str, timeout: float = 120.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "posecast.client.cli", *args],
                          capture_output=True, text=True, timeout=timeout)


def test_hmd_without_steamvr_says_so_in_one_line() -> None:
    done = run("play", "--server", "ws://127.0.0.1:9", "--room", "r", "--hmd")
    assert done.returncode == 1
    assert done.stderr.count("\n") == 1 and "Traceback" not in done.stderr
    assert "--hmd" in done.stderr and "--hmd-out DIR" in done.stderr
    wrong = run("play", "--server", "ws://127.0.0.1:9", "--room", "r", "--hmd",
                "--source", CLIP)
    assert wrong.returncode == 1 and "needs --source openvr" in wrong.stderr
    stray = run("play", "--server", "ws://127.0.0.1:9", "--room", "r", "--hmd-frames", "3")
    assert stray.returncode == 1 and "are for --hmd or --hmd-out" in stray.stderr


def test_hmd_out_writes_both_eyes_side_by_side(tmp_path: Path) -> None:
    out = tmp_path / "eyes"

    async def main() -> tuple[int, str, str, int]:
        async with serving(Session()) as url:
            watcher = Spectator(url, "hmd", "watcher")
            watching = asyncio.create_task(watcher.run(seconds=60))
            proc = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "posecast.client.cli", "play", "--server", url,
                "--room", "hmd", "--source", CLIP, "--hmd-out", str(out),
                "--hmd-frames", "4", "--hmd-scale", "0.25",
                stdout=subprocess.PIPE, stderr=subprocess.PIPE)
            stdout, stderr = await asyncio.wait_for(proc.communicate(), 120)
            watching.cancel()
            return proc.returncode or 0, stdout.decode(), stderr.decode(), \
                watcher.stats.frames_received

    code, stdout, stderr, seen = asyncio.run(main())
    assert code == 0, stderr
    files = sorted(out.glob("frame_*.png"))
    assert len(files) == 4
    w, h = round(1512 * 0.25), round(1680 * 0.25)
    with Image.open(files[-1]) as image:
        assert image.size == (2 * w, h)  # left eye | right eye
        pixels = np.asarray(image.convert("RGB"))
    assert (pixels[:, :w] != pixels[:, w:]).any()  # two eyes, not one picture twice
    assert "headset: 4 frames, 378x420 an eye; pose to submit p50" in stdout
    assert seen > 0  # and the player streamed to the room meanwhile


def test_the_mirror_is_drawn_only_when_an_eye_sees_its_face() -> None:
    from posecast.client.headset.room import Mirror
    from posecast.client.viewer.renderer import create_headless_context

    try:
        ctx = create_headless_context()
    except Exception as err:
        pytest.skip(f"no headless OpenGL: {err}")
    try:
        mirror = Mirror(ctx, place_mirror(np.array([0.0, 1.7, 0.0]),
                                          np.array([0.0, 0.0, -1.0]), 2.0))
        setup = vive_setup()
        facing = pose_matrix([0.0, 1.7, 0.0], R.IDENTITY)  # looking at it
        away = pose_matrix([0.0, 1.7, 0.0], R.from_axis_angle([0.0, 1.0, 0.0], np.pi))
        behind = pose_matrix([0.0, 1.7, -3.0], R.from_axis_angle([0.0, 1.0, 0.0], np.pi))
        assert all(mirror.visible(c) for c in eye_cameras(facing, setup))
        assert not any(mirror.visible(c) for c in eye_cameras(away, setup))
        assert not any(mirror.visible(c) for c in eye_cameras(behind, setup))
        mirror.release()
    finally:
        ctx.release()


def test_the_hud_says_the_countdown_then_the_connection(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """What the headset's HUD reads (PlayerLink.status): connecting, a line the terminal
    says (the T-pose countdown, a lost connection) for NOTE_S, then the room's state."""
    from types import SimpleNamespace

    from posecast.client.headset import session as headset_session
    from posecast.client.session.player import Player

    t = [100.0]
    monkeypatch.setattr(headset_session, "now", lambda: t[0])
    source = BvhSource(builtin_motion_path())
    player = Player("ws://127.0.0.1:9", "lobby", "ana", source)
    link = headset_session.PlayerLink(player, None)
    assert link.status == "connecting to ws://127.0.0.1:9"
    link.say("stand in a T-pose, arms out sideways: calibrating in 3 s")
    assert link.status == "stand in a T-pose, arms out sideways: calibrating in 3 s"
    t[0] += headset_session.NOTE_S + 0.1  # the line has had its time
    player.session = SimpleNamespace()  # type: ignore[assignment]  # connected
    assert link.status == "room lobby: stand in a T-pose"
    assert player.on_calibration is not None
    player.on_calibration(source.calibration())  # the T-pose went out
    assert link.status == "room lobby: streaming" and link.tpose is not None
    player.stats.reconnects = 2
    assert link.status == "room lobby: streaming, 2 reconnects"
