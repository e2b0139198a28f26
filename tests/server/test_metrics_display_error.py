"""The display error in /metrics (server.display_error): viewers' shown poses against the
poses the server solved, pure parts with exact figures and a real server over sockets."""

from __future__ import annotations

import asyncio
import contextlib

import numpy as np
import pytest
from conftest import serving
from stream_decode import decode
from test_http_metrics import TIMEOUT, http_get, samples

from posecast.client.bench.demo import run_players
from posecast.client.builtin import builtin_motion_path
from posecast.protocol import AvatarBatch, Error, ShownPose, ViewerReport, decode_client, encode
from posecast.server.app import Session
from posecast.server.clock import now
from posecast.server.display_error import (
    BUCKET_BOUNDS_M,
    MAX_GAP_S,
    DisplayErrorHistograms,
    PoseHistory,
    SampleReservoir,
    display_errors,
)
from posecast.solver.readers.gltf import load_makehuman
from posecast.solver.rig import Rig, build_rig

RATE = 90.0


@pytest.fixture(scope="module")
def rig() -> Rig:
    return build_rig(load_makehuman().skeleton)


def walking(rig: Rig, frames: int, avatar_id: int = 1) -> PoseHistory:
    """An avatar in its rest pose gliding along x at 1 m/s, solved at 90 Hz from t = 0."""
    history = PoseHistory(rig.skeleton.num_joints)
    rest = np.tile([0.0, 0.0, 0.0, 1.0], (1, rig.skeleton.num_joints, 1))
    for k in range(frames):
        history.add([avatar_id], np.array([k / RATE]), np.array([[k / RATE, 1.0, 0.0]]), rest)
    return history


def shown(rig: Rig, t: float, x: float, avatar_id: int = 1) -> ShownPose:
    return ShownPose(avatar_id=avatar_id, t_presented=t, root=[x, 1.0, 0.0],
                     rotations=np.tile([0.0, 0.0, 0.0, 1.0], (rig.skeleton.num_joints, 1)))


def offsets(rig: Rig) -> dict[int, np.ndarray]:
    return {1: rig.skeleton.offsets}


def test_the_truth_is_the_solved_pose_at_the_instant_shown(rig: Rig) -> None:
    history = walking(rig, 90)
    t = 0.5 + 0.3 / RATE  # between two frames: the solved roots interpolated
    errors, measured = display_errors(rig, history, offsets(rig), [
        shown(rig, t, t),  # where the avatar was then: no error
        shown(rig, t, t - 0.1),  # 100 ms late at 1 m/s: every joint 100 mm behind
        shown(rig, 5.0, 5.0),  # after its last frame: nothing to compare with
        shown(rig, t, t, avatar_id=2),  # an avatar the room has no history of
    ])
    assert measured.tolist() == [True, True, False, False]
    assert errors[0] == pytest.approx(0.0, abs=1e-9)
    assert errors[1] == pytest.approx(0.1, abs=1e-9)


def test_a_shown_pose_travels_as_int16_levels_within_a_fraction_of_a_millimetre(
        rig: Rig) -> None:
    history = walking(rig, 90)
    rng = np.random.default_rng(3)
    q = rng.normal(size=(rig.skeleton.num_joints, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    rest = np.tile([0.0, 0.0, 0.0, 1.0], (1, rig.skeleton.num_joints, 1))
    history.add([1], np.array([1.0]), np.array([[1.0, 1.0, 0.0]]), q[None])
    history.add([1], np.array([1.0 + 1 / RATE]), np.array([[1.0, 1.0, 0.0]]), rest)
    pose = ShownPose(avatar_id=1, t_presented=1.0, root=[1.0, 1.0, 0.0], rotations=q)
    back = decode_client(encode(ViewerReport(t_capture=[], t_received=[], t_presented=[],
                                             shown=(pose,))))
    assert isinstance(back, ViewerReport)
    errors, measured = display_errors(rig, history, offsets(rig), [pose, back.shown[0]])
    assert measured.all() and errors[0] == pytest.approx(0.0, abs=1e-6)
    assert 0.0 < errors[1] < 0.0005  # ~0.003 deg a component, over a body's lengths


def test_the_history_keeps_its_last_rows_and_no_gap(rig: Rig) -> None:
    history = walking(rig, 300)  # more than its 256 rows: the oldest are gone
    first_kept = (300 - history.rows) / RATE
    assert history.around(1, first_kept - 0.5 / RATE) is None
    assert history.around(1, first_kept + 0.5 / RATE) is not None
    history.add([1], np.array([300 / RATE + MAX_GAP_S + 0.01]),
                np.zeros((1, 3)), np.tile([0.0, 0.0, 0.0, 1.0], (1, history.joints, 1)))
    assert history.around(1, 300 / RATE) is None  # frames too far apart around it
    history.forget(1)
    assert history.around(1, 2.0) is None
    for avatar in range(2, 40):  # slots grow, and a forgotten one is taken again
        history.add([avatar], np.array([0.0]), np.zeros((1, 3)),
                    np.tile([0.0, 0.0, 0.0, 1.0], (1, history.joints, 1)))
    assert history.times.shape[0] >= 38 and history.around(39, 0.0) is None


def test_histogram_quantiles_are_read_off_the_buckets_as_prometheus_does() -> None:
    h = DisplayErrorHistograms()
    h.observe("browser", "predict", np.array([0.025] * 10 + [0.045] * 10))
    assert h.count("browser", "predict") == 20 and h.count("desktop", "predict") == 0
    buckets, total = h.cumulative(("browser", "predict"))
    assert total == pytest.approx(0.7)
    assert dict(buckets)["0.03"] == 10 and dict(buckets)["0.05"] == 20
    # the 10th of 20 is the last in (20, 30] mm: the bucket's top; the 15th halfway
    # through (40, 50]
    assert h.quantile_mm(("browser", "predict"), 0.5) == pytest.approx(30.0)
    assert h.quantile_mm(("browser", "predict"), 0.75) == pytest.approx(45.0)
    h.observe("browser", "predict", np.array([2.0] * 80))  # beyond every bound
    assert h.quantile_mm(("browser", "predict"), 0.95) == BUCKET_BOUNDS_M[-1] * 1e3


def test_a_reservoir_holds_its_size_whatever_comes() -> None:
    r = SampleReservoir(size=4)
    for k in range(1000):
        r.offer(None, k)  # type: ignore[arg-type]
    assert r.offered == 1000 and len(r.held) == 4
    kept = r.take()
    assert len({s for _, s in kept}) == 4 and r.offered == 0 and not r.held


# ------------------------------------------------------------------ over a real server
def test_metrics_hold_the_display_error_of_what_viewers_showed() -> None:
    """Two viewers report the frames they received as shown: one at their capture
    instants (only the wire's rounding apart), one 50 ms after (behind a moving body).
    The server measures both, and refuses a shown pose from another hour."""
    session = Session(reconnect_grace=0.0)
    text = b""

    async def scenario() -> None:
        nonlocal text
        async with serving(session) as url:
            from test_server_eviction import join

            exact = await join(url, "spectator")
            late = await join(url, "spectator")
            errors: list[str] = []

            async def report(ws, delay: float, viewer: str) -> None:  # type: ignore[no-untyped-def]
                last = -1.0
                while True:
                    msg = decode(await ws.recv())
                    if isinstance(msg, Error):
                        errors.append(msg.message)
                    # every batch read, one reported every 0.3 s (within the reports' rate)
                    if isinstance(msg, AvatarBatch) and now() - last >= 0.3:
                        last = now()
                        poses = tuple(ShownPose(avatar_id=f.avatar_id,
                                                t_presented=f.t_capture + delay,
                                                root=f.root, rotations=f.rotations)
                                      for f in msg.frames[:2])
                        await ws.send(encode(ViewerReport(
                            t_capture=[], t_received=[], t_presented=[], shown=poses,
                            viewer=viewer, mode="zero-buffer")))

            tasks = [asyncio.create_task(report(exact, 0.0, "desktop")),
                     asyncio.create_task(report(late, 0.05, "browser"))]
            await run_players(url, 2, 4.0, builtin_motion_path())
            await asyncio.sleep(0.6)  # a tick or two after the last report
            bad = ShownPose(avatar_id=1, t_presented=-3600.0, root=[0, 0, 0],
                            rotations=[[0, 0, 0, 1]])
            await exact.send(encode(ViewerReport(t_capture=[], t_received=[],
                                                 t_presented=[], shown=(bad,))))
            for _ in range(50):
                if any("shown.t_presented[0]" in e for e in errors):
                    break
                await asyncio.sleep(0.1)
            _, _, text = await http_get(url, "/metrics")
            for task in tasks:
                task.cancel()
            with contextlib.suppress(Exception):
                await asyncio.gather(*tasks, return_exceptions=True)
            assert any("viewer_report.shown.t_presented[0]" in e for e in errors), errors

    asyncio.run(asyncio.wait_for(scenario(), 6 * TIMEOUT))
    scraped = samples(text.decode())
    name = "posecast_display_error_meters"
    h = session.metrics.display_error
    for viewer in ("desktop", "browser"):
        labels = (("mode", "zero-buffer"), ("viewer", viewer))
        count = scraped[(f"{name}_count", labels)]
        assert count == h.count(viewer, "zero-buffer") >= 10
    exact_p50 = h.quantile_mm(("desktop", "zero-buffer"), 0.5)
    late_p50 = h.quantile_mm(("browser", "zero-buffer"), 0.5)
    assert exact_p50 <= 2.0  # the downlink's rounding: ~0.07 deg a joint
    assert late_p50 >= 10.0  # 50 ms behind a walking body: centimetres
    assert scraped[("posecast_display_samples_total", (("outcome", "measured"),))] >= 20


def test_a_relayed_batch_gives_the_history_the_rows_it_carries(rig: Rig) -> None:
    """serve --redis: a process that relays a room keeps the owner's batches as they
    arrived (decoded, to the wire's rounding) as its history."""
    from posecast.protocol import decode
    from posecast.server.room import RelayedBatch, SharedBatch

    rng = np.random.default_rng(7)
    J = rig.skeleton.num_joints
    q = rng.normal(size=(2, J, 4))
    q /= np.linalg.norm(q, axis=2, keepdims=True)
    roots = np.array([[0.5, 1.0, 0.0], [-0.5, 1.0, 2.0]])
    t0 = now() - 0.03  # times travel as float32 ages before t_sent (now): milliseconds
    captured = [t0, t0 + 0.004]
    solved = SharedBatch([4, 9], [1, 1], roots, q, captured, [t0 + 0.01, t0 + 0.012],
                         t0 + 0.02)
    batch = decode(solved.encoded())
    assert isinstance(batch, AvatarBatch)
    ids, t, r, rot = RelayedBatch(solved.encoded(), batch, {}).solved_rows()
    assert ids == [4, 9] and rot.shape == (2, J, 4)
    np.testing.assert_allclose(t, captured, atol=1e-6)
    np.testing.assert_allclose(r, roots, atol=1e-6)
    history = PoseHistory(J)
    history.add(ids, t, r, rot)
    history.add(ids, t + 1 / RATE, r, rot)
    offsets = {4: rig.skeleton.offsets, 9: rig.skeleton.offsets}
    errors, measured = display_errors(rig, history, offsets, [
        ShownPose(avatar_id=9, t_presented=float(t[1]), root=roots[1], rotations=q[1])])
    assert measured.all() and errors[0] < 0.002  # the downlink's rounding, millimetres
