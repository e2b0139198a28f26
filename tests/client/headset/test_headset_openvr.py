"""``play --hmd`` against the real ``openvr`` package, without a headset.

The IVRSystem and IVRCompositor function tables are filled with ctypes callbacks
(tests/openvr_fake.py): WaitGetPoses hands out a body's poses, GetProjectionMatrix and
GetEyeToHeadTransform a Vive's values (110 degrees, IPD 63 mm), Submit receives the
eyes' texture names, which the test reads back through moderngl on the thread that
submits them. A real server on 127.0.0.1 takes the player's stream and, for the last
test, another player's; the frame loop, the local solve, the spectator connection, the
mirror and the reports all run as they do with SteamVR.

Each picture is checked against an independent projection: the expected pixel of a
world point comes from the fake's own matrices (projection x inverse(head x
eye-to-head)), not from the code under test.
"""

from __future__ import annotations

import asyncio
import threading
from dataclasses import dataclass, field

import moderngl
import numpy as np
import openvr
import pytest
from conftest import serving
from numpy.typing import NDArray
from openvr_fake import (
    RIG_ROLES,
    STRUCT_RETURN,
    FakeCompositor,
    FakeVR,
    Submitted,
    d3d_projection,
    pose_matrix,
    rig_devices,
)

from posecast.client.builtin import builtin_motion_path
from posecast.client.headset.compositor import Compositor
from posecast.client.headset.displays import CompositorDisplay
from posecast.client.headset.room import hud_anchor
from posecast.client.headset.session import Headset
from posecast.client.headset.stereo import heading_of, headset_from_device
from posecast.client.session.player import Player
from posecast.client.sources.base import DeviceSample, now
from posecast.client.sources.bvh_source import BvhSource
from posecast.client.sources.openvr_source import OpenVRSource
from posecast.client.viewer.renderer import avatar_color, create_headless_context
from posecast.client.viewer.skinning import skin
from posecast.server.app import Session
from posecast.solver import rotations as R
from posecast.solver.readers.gltf import load_makehuman

pytestmark = pytest.mark.skipif(not STRUCT_RETURN, reason="the fake's struct-returning "
                                "callbacks follow the x86-64 calling convention")

SIZE = (504, 560)  # a third of the Vive's recommended 1512x1680: the same optics
ROLES_6 = ("head", "hip", "left_hand", "right_hand", "left_foot", "right_foot")
# the solved wrist joint to its controller: the T-pose's mount puts this clip's
# controller 11 cm from the avatar's wrist, and the solver reaches this synthetic pose
# within ~10 cm more (what the headset draws is the solver's, checked to 2 px)
HAND_REACH_M = 0.25
NECK_BELOW_EYES_M, NECK_BEHIND_EYES_M = 0.12, 0.09
TIMEOUT = 120.0


@pytest.fixture(scope="module", autouse=True)
def needs_gl() -> None:
    try:
        create_headless_context().release()
    except Exception as err:  # GLUnavailableError, or EGL's own
        pytest.skip(f"no headless OpenGL: {err}")


# --------------------------------------------------------------------------- a body
@dataclass(frozen=True)
class Body:
    """A person's device poses by role: positions (3,), rotations (x y z w)."""

    positions: dict[str, NDArray[np.float64]]
    rotations: dict[str, NDArray[np.float64]]

    def moved(self, **poses: tuple[NDArray[np.float64], NDArray[np.float64]]) -> Body:
        pos, rot = dict(self.positions), dict(self.rotations)
        for role, (p, q) in poses.items():
            pos[role], rot[role] = p, q
        return Body(pos, rot)

    def sample(self, roles: tuple[str, ...]) -> DeviceSample:
        return DeviceSample.of(now(), roles, np.stack([self.positions[r] for r in roles]),
                               np.stack([self.rotations[r] for r in roles]))


def tpose_facing_minus_z(at: tuple[float, float] = (0.0, 0.0)) -> Body:
    """The built-in clip's T-pose (BvhSource), turned to face -z (a headset's forward)
    with its head device over ``at`` (x, z), the head device turned into a headset
    (its -z forward)."""
    source = BvhSource(builtin_motion_path())
    t = source.calibration()
    pos = {r: t.positions[i] for i, r in enumerate(t.roles)}
    rot = {r: t.rotations[i] for i, r in enumerate(t.roles)}
    heading = heading_of(pos)
    turn_head = headset_from_device(rot["head"], heading)
    yaw = R.between(heading, np.array([0.0, 0.0, -1.0]))
    shift = np.array([at[0], 0.0, at[1]]) - R.rotate(yaw, pos["head"]) * [1, 0, 1]
    positions = {r: R.rotate(yaw, p) + shift for r, p in pos.items()}
    rotations = {r: R.mul(yaw, q) for r, q in rot.items()}
    rotations["head"] = R.mul(rotations["head"], turn_head)
    return Body(positions, rotations)


def looking_down_hands_forward(body: Body, pitch_deg: float = 60.0) -> Body:
    """The same person looking down by ``pitch_deg``, hands held before the waist, the
    left foot a step forward (standing square, the chest hides the feet from the eyes,
    as it does a person's)."""
    eyes = body.positions["head"]
    pitch = R.from_axis_angle([1.0, 0.0, 0.0], np.radians(-pitch_deg))
    # a head nods about the neck, behind and below the eyes: they move forward and down
    neck = eyes + np.array([0.0, -NECK_BELOW_EYES_M, NECK_BEHIND_EYES_M])
    head = neck + R.rotate(pitch, eyes - neck)
    moved = {"head": (head, R.mul(pitch, body.rotations["head"]))}
    for role, side in (("left_hand", -1.0), ("right_hand", 1.0)):
        p = head + np.array([0.22 * side, -0.6, -0.3])
        # the arm that pointed sideways now points forward: turned a quarter about +y
        turn = R.from_axis_angle([0.0, 1.0, 0.0], np.radians(90.0 * side))
        moved[role] = (p, R.mul(turn, body.rotations[role]))
    moved["left_foot"] = (body.positions["left_foot"] + [0.0, 0.0, -0.45],
                          body.rotations["left_foot"])
    return body.moved(**moved)


def set_devices(vr: FakeVR, body: Body) -> None:
    for role, index in RIG_ROLES.items():
        if role in body.positions and index in vr.devices:
            vr.devices[index].matrix = pose_matrix(body.rotations[role],
                                                   body.positions[role])


def six_point_vr(body: Body) -> FakeVR:
    """An HMD, two controllers, a waist and two feet trackers at ``body``'s poses."""
    keep = {RIG_ROLES[r] for r in ROLES_6}
    devices = {i: d for i, d in enumerate(rig_devices()) if i in keep}
    vr = FakeVR(devices)
    set_devices(vr, body)
    return vr


class StaticSource:
    """Another player standing still: ``body``'s poses, freshly stamped."""

    rate_hz = 90.0

    def __init__(self, body: Body) -> None:
        self.body = body

    def calibration(self) -> DeviceSample:
        return self.body.sample(ROLES_6)

    def read(self) -> DeviceSample | None:
        return self.body.sample(ROLES_6)

    def close(self) -> None:
        pass


# --------------------------------------------------------------------------- a run
@dataclass
class Shot:
    """One frame as submitted: both eyes' pixels (top row first) and what was drawn."""

    wait: int
    eyes: list[NDArray[np.uint8]] = field(default_factory=list)
    textures: list[int] = field(default_factory=list)
    drawn: object = None


def read_texture(ctx: moderngl.Context, name: int, size: tuple[int, int]) -> NDArray[np.uint8]:
    tex = ctx.external_texture(name, size, 4, 0, "f1")
    pixels = np.frombuffer(tex.read(alignment=1), np.uint8).reshape(size[1], size[0], 4)
    return pixels[::-1, :, :3].copy()


def run_headset(body_after: Body, *, mirror: float | None, shots: int = 2,
                other: Body | None = None, session: Session | None = None
                ) -> tuple[FakeCompositor, Headset, list[Shot], list[int]]:
    """A player on a fake Vive, calibrated from the T-pose, then standing as
    ``body_after``; ``shots`` frames after that (and after ``other``, another player,
    is drawn) are read back. Returns the fake, the headset, the shots, and the
    avatar ids [own, other]."""
    tpose = tpose_facing_minus_z()
    vr = six_point_vr(tpose)
    fake = FakeCompositor(vr, size=SIZE)
    source = OpenVRSource(system=vr.system)
    shots_taken: list[Shot] = []
    ids: list[int] = []
    calibrated = threading.Event()
    wanted_others = 1 if other is not None else 0
    ready_from: list[int] = []  # the first wait whose frame is to be kept

    async def scenario() -> Headset:
        async with serving(session or Session()) as url:
            others: list[asyncio.Task[object]] = []
            if other is not None:
                them = Player(url, "room", "them", StaticSource(other))
                others.append(asyncio.create_task(them.run(seconds=60)))
                while them.stats.avatar_id is None:
                    await asyncio.sleep(0.02)
                ids.append(them.stats.avatar_id)
            player = Player(url, "room", "me", source)
            display = CompositorDisplay(Compositor(vr.system, fake.compositor),
                                        source.sample_of)
            stop = asyncio.Event()
            headset = Headset(player, display, None, stop=stop, mirror_distance=mirror)
            original = headset.link._calibrated

            def on_calibration(sample: DeviceSample) -> None:
                original(sample)
                calibrated.set()
            player.on_calibration = on_calibration

            def on_wait(n: int) -> None:
                if calibrated.is_set():
                    set_devices(vr, body_after)
                    last = headset.view.last
                    if not ready_from and last is not None and last.own == 1 \
                            and len(last.others) >= wanted_others:
                        ready_from.append(n + 2)  # the devices have moved by then

            def on_submit(s: Submitted) -> None:
                if not ready_from or s.wait < ready_from[0]:
                    return
                if not shots_taken or shots_taken[-1].wait != s.wait:
                    if len(shots_taken) >= shots:
                        return
                    shots_taken.append(Shot(s.wait))
                shot = shots_taken[-1]
                ctx = headset.view.ctx
                assert ctx is not None
                shot.eyes.append(read_texture(ctx, s.texture, SIZE))
                shot.textures.append(s.texture)
                shot.drawn = headset.view.last
                if len(shots_taken) == shots and len(shot.eyes) == 2:
                    loop.call_soon_threadsafe(shots_done.set)

            loop = asyncio.get_running_loop()
            fake.on_wait = on_wait
            fake.on_submit = on_submit
            shots_done = asyncio.Event()

            async def until_reported() -> None:  # the shots, and a report at the server
                await shots_done.wait()
                while session is not None and headset.reports.sent < 1:
                    await asyncio.sleep(0.05)
                stop.set()
            waiter = asyncio.create_task(until_reported())
            async with headset:
                await asyncio.wait_for(player.run(stop=stop), TIMEOUT)
            waiter.cancel()
            ids.insert(0, player.stats.avatar_id or 0)
            for task in others:
                task.cancel()
            return headset

    headset = asyncio.run(scenario())
    assert len(shots_taken) == shots, "the headset never drew the calibrated body"
    return fake, headset, shots_taken, ids


# --------------------------------------------------------------------------- pictures
def expected_camera(fake: FakeCompositor, head: NDArray[np.float64],
                    eye: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The fake's own view (4x4) and projection (4x4) of ``eye`` (0 left, 1 right)."""
    e = openvr.Eye_Left if eye == 0 else openvr.Eye_Right
    eye_to_head = np.eye(4)
    eye_to_head[:3] = fake.eye_to_head(e)
    view = np.asarray(np.linalg.inv(head @ eye_to_head), dtype=np.float64)
    return view, d3d_projection(*fake.eye_tangents(e), 0.02, 100.0)


def project(points: NDArray[np.float64], view: NDArray[np.float64],
            projection: NDArray[np.float64]) -> tuple[NDArray[np.float64],
                                                      NDArray[np.bool_]]:
    """Pixel x (right), y (down) of world points, and whether each is before the eye."""
    p = np.concatenate([points, np.ones((len(points), 1))], axis=1) @ view.T
    clip = p @ projection.T
    front = -p[:, 2] > 0.02
    ndc = clip[:, :2] / np.where(front, clip[:, 3], 1.0)[:, None]
    px = np.stack([(ndc[:, 0] + 1) * 0.5 * SIZE[0], (1 - ndc[:, 1]) * 0.5 * SIZE[1]], axis=1)
    return px, front


def painted(image: NDArray[np.uint8], color: tuple[float, float, float]) -> NDArray[np.bool_]:
    """Pixels of an avatar drawn in ``color``: its hue (lit and shaded it varies in
    brightness, not in hue), with enough colour not to be the grey floor."""
    rgb = image.astype(np.float64) / 255.0
    chroma = rgb - rgb.mean(axis=2, keepdims=True)
    c = np.asarray(color) - np.mean(color)
    norm = np.linalg.norm(chroma, axis=2)
    cos = (chroma @ c) / np.maximum(norm * np.linalg.norm(c), 1e-9)
    return (cos > 0.97) & (norm > 0.06)


def near(mask: NDArray[np.bool_], xy: NDArray[np.float64], radius: int) -> bool:
    x, y = round(float(xy[0])), round(float(xy[1]))
    window = mask[max(y - radius, 0):y + radius + 1, max(x - radius, 0):x + radius + 1]
    return bool(window.any())


def inside(xy: NDArray[np.float64], margin: float = 4.0) -> bool:
    return bool(margin <= xy[0] < SIZE[0] - margin and margin <= xy[1] < SIZE[1] - margin)


def _hmd(body: Body) -> NDArray[np.float64]:
    m = np.eye(4)
    m[:3, :] = pose_matrix(body.rotations["head"], body.positions["head"])
    return m


MESH = load_makehuman()


def skinned(drawn: object, index: int, heads: bool = False) -> NDArray[np.float64]:
    """The world positions of avatar ``index``'s vertices as drawn (numpy reference
    skinning of the drawn joint matrices; ``heads``: with the head, as in a mirror)."""
    scene = drawn.posed if heads else drawn.seen  # type: ignore[attr-defined]
    return skin(MESH.positions, MESH.joints, MESH.weights, scene.matrices[index])


# --------------------------------------------------------------------------- the tests
def test_each_frame_submits_both_eyes_with_the_eye_offset_and_the_hands_at_the_controllers(
        ) -> None:
    tpose = tpose_facing_minus_z()
    body = looking_down_hands_forward(tpose)
    fake, headset, shots, ids = run_headset(body, mirror=None, shots=2)
    own_color = avatar_color(ids[0])
    # every frame drawn: a left then a right eye, two textures, the whole texture, GL
    by_wait: dict[int, list[Submitted]] = {}
    for s in fake.submitted:
        by_wait.setdefault(s.wait, []).append(s)
    assert len(by_wait) == headset.stats.frames >= 4
    for subs in by_wait.values():
        assert [s.eye for s in subs] == [openvr.Eye_Left, openvr.Eye_Right]
        assert len({s.texture for s in subs}) == 2 and all(s.texture > 0 for s in subs)
        assert all(s.kind == openvr.TextureType_OpenGL for s in subs)
        assert all(s.bounds == (0.0, 0.0, 1.0, 1.0) for s in subs)
    # the projection was asked of SteamVR for both eyes
    assert {e for e, _, _ in fake.projection_calls} == {openvr.Eye_Left, openvr.Eye_Right}

    head = _hmd(body)
    for shot in shots:
        drawn = shot.drawn
        assert drawn.own == 1  # type: ignore[attr-defined]
        vertices = skinned(drawn, 0)
        boxes = []
        for eye in range(2):
            view, projection = expected_camera(fake, head, eye)
            mask = painted(shot.eyes[eye], own_color)
            assert mask.sum() > 500, f"eye {eye}: the own body is not drawn"
            # the body's silhouette where the fake's projection puts it: each edge of
            # its bounding box that is inside the picture, within 2 px
            px, front = project(vertices, view, projection)
            px = px[front]
            ys, xs = np.nonzero(mask)
            want = (px[:, 0].min(), px[:, 0].max(), px[:, 1].min(), px[:, 1].max())
            got = (xs.min(), xs.max() + 1, ys.min(), ys.max() + 1)
            for name, w, g, limit in zip(("left", "right", "top", "bottom"), want, got,
                                         (SIZE[0], SIZE[0], SIZE[1], SIZE[1]), strict=True):
                if 4 < w < limit - 4:
                    assert abs(w - g) <= 2.0, f"eye {eye} {name} edge: {g} px, projected {w:.1f}"
            boxes.append(want)
            # the hands where the controllers are: each hand drawn at its solved place
            # (2 px), which is the controller's (within the solver's own reach)
            gp = drawn.posed.global_pos[0]  # type: ignore[attr-defined]
            for role, joint in (("left_hand", "hand_l"), ("right_hand", "hand_r")):
                hand = gp[MESH.skeleton.index(joint)]
                assert np.linalg.norm(hand - body.positions[role]) < HAND_REACH_M
                c, ok = project(np.stack([hand, body.positions[role]]), view, projection)
                assert ok.all() and inside(c[0]) and inside(c[1]), f"{role} out of view"
                assert near(mask, c[0], 2), f"eye {eye}: no hand drawn at {joint}"
            # looking down shows the legs: the foot a step forward, and its knee
            for joint in ("calf_l", "foot_l"):
                c, ok = project(gp[MESH.skeleton.index(joint)][None, :], view, projection)
                assert ok[0] and inside(c[0]), f"{joint} is out of eye {eye}'s view"
                assert near(mask, c[0], 2), f"eye {eye}: no leg at {joint}"
        # the two eyes differ by the eye offset: the nearer the point, the more
        assert boxes[0][0] > boxes[1][0] + 5.0


def test_the_mirror_shows_the_whole_avatar_head_and_all() -> None:
    tpose = tpose_facing_minus_z()
    fake, _, shots, ids = run_headset(tpose, mirror=2.0, shots=1)
    shot = shots[0]
    own_color = avatar_color(ids[0])
    head = _hmd(tpose)
    drawn = shot.drawn
    gp = drawn.posed.global_pos[0]  # type: ignore[attr-defined]
    # the mirror: 2 m ahead of the T-pose's head, facing back (+z), on the floor
    plane_z = tpose.positions["head"][2] - 2.0
    for eye in range(2):
        view, projection = expected_camera(fake, head, eye)
        mask = painted(shot.eyes[eye], own_color)
        # the reflection of the body's own head (hidden in first person) is in the mirror
        j = MESH.skeleton.index("head")
        image = gp[j].copy()
        image[2] = 2 * plane_z - image[2]
        c, ok = project(image[None, :], view, projection)
        assert ok[0] and inside(c[0])
        assert near(mask, c[0], 3), f"eye {eye}: no head in the mirror"
        # and the reflected body fills the mirror where it should: its silhouette's
        # top edge (the crown) within 2 px of the reflected vertices' projection
        vertices = skinned(drawn, 0, heads=True)
        vertices[:, 2] = 2 * plane_z - vertices[:, 2]
        px, front = project(vertices, view, projection)
        ys, _ = np.nonzero(mask)
        assert abs(px[front, 1].min() - ys.min()) <= 2.0
        # the HUD: white text just above where its anchor (ahead, below the eyes) lands
        c, ok = project(hud_anchor(head)[None, :], view, projection)
        assert ok[0] and inside(c[0])
        x, y = round(float(c[0, 0])), round(float(c[0, 1]))
        box = shot.eyes[eye][max(y - 60, 0):y, max(x - 80, 0):x + 80]
        assert (box.min(axis=2) > 200).sum() > 30, f"eye {eye}: no HUD text"


def test_another_player_standing_in_front_is_drawn_where_they_stand() -> None:
    tpose = tpose_facing_minus_z()
    other = tpose_facing_minus_z(at=(0.3, -1.6))
    session = Session()
    fake, _, shots, ids = run_headset(tpose, mirror=None, shots=1, other=other,
                                      session=session)
    shot = shots[0]
    drawn = shot.drawn
    assert drawn.others == [ids[1]]  # type: ignore[attr-defined]
    their_color = avatar_color(ids[1])
    head = _hmd(tpose)
    vertices = skinned(drawn, 1)
    for eye in range(2):
        view, projection = expected_camera(fake, head, eye)
        mask = painted(shot.eyes[eye], their_color)
        assert mask.sum() > 500, f"eye {eye}: the other player is not drawn"
        px, front = project(vertices, view, projection)
        ys, xs = np.nonzero(mask)
        # their whole body is in view: its sides and feet where the projection says
        top = px[front, 1].min()
        body = ys > top - 1.0  # above the crown is their name, in their colour
        want = (px[front, 0].min(), px[front, 0].max(), px[front, 1].max())
        got = (xs[body].min(), xs[body].max() + 1, ys[body].max() + 1)
        for w, g in zip(want, got, strict=True):
            assert abs(w - g) <= 2.0, f"eye {eye}: an edge at {g} px, projected {w:.1f}"
        assert abs(ys[body].min() - top) <= 2.0
        # and named: their label a little above the crown
        assert (ys < top - 5.0).sum() > 20, f"eye {eye}: no name above the other player"
    # the headset's reports reached the server: its poses-to-submit in /metrics' stage,
    # and the other's frames as it presented them
    m = session.metrics
    assert m.viewer_reports >= 1
    assert m.headset_latency.count("pose_to_submit") >= 1
    assert m.viewer_latency.count("capture_to_presented") >= 1


def test_a_blocked_compositor_never_stalls_the_players_stream() -> None:
    """WaitGetPoses held for a second (as when another application has the focus): the
    frame loop waits in it, and the player's 90 Hz stream goes on meanwhile."""
    tpose = tpose_facing_minus_z()
    vr = six_point_vr(tpose)
    fake = FakeCompositor(vr, size=(64, 72))
    source = OpenVRSource(system=vr.system)
    held = threading.Event()
    release = threading.Event()
    counts: list[int] = []

    async def scenario() -> None:
        async with serving(Session()) as url:
            player = Player(url, "room", "me", source)
            display = CompositorDisplay(Compositor(vr.system, fake.compositor),
                                        source.sample_of)
            stop = asyncio.Event()
            headset = Headset(player, display, None, stop=stop, mirror_distance=None,
                              spectate=False)

            def on_wait(n: int) -> None:
                if n == 3:  # a few frames in: hold this wait until the test lets go
                    held.set()
                    release.wait(TIMEOUT)

            fake.on_wait = on_wait

            async def hold_for_a_second() -> None:
                while not held.is_set():
                    await asyncio.sleep(0.01)
                before = player.stats.frames_sent
                await asyncio.sleep(1.0)
                counts.extend([before, player.stats.frames_sent, headset.stats.frames])
                release.set()
                stop.set()
            holder = asyncio.create_task(hold_for_a_second())
            async with headset:
                await asyncio.wait_for(player.run(stop=stop), TIMEOUT)
            await holder

    asyncio.run(scenario())
    before, after, frames = counts
    assert frames <= 3  # the loop was in WaitGetPoses the whole second
    assert after - before >= 45, f"{after - before} frames sent in the second it waited"
