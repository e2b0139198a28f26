"""VMC protocol out: poses as Unity humanoid bones, and ``run_vmc`` against a real server.

Conversion cases are worked on paper in Unity's axes (x right, y up, z forward,
left-handed; ``Quaternion.Euler(0, 0, 90)`` turns +x onto +y, ``Euler(90, 0, 0)``
pitches forward down, ``Euler(0, 90, 0)`` turns to the right): a VRM's T-pose is identity
for every bone, so a bone's local rotation is its turn away from that pose.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from typing import Any

import numpy as np
import pytest
from conftest import serving
from pythonosc.dispatcher import Dispatcher
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_server import AsyncIOOSCUDPServer

from posecast.client.bench.demo import HEADSET_HZ
from posecast.client.builtin import builtin_motion_path
from posecast.client.interop.vmc import (
    VmcError,
    check_target,
    parse_target,
    run_vmc,
    vmc_bundle,
)
from posecast.client.session.connection import SessionError
from posecast.client.session.player import Player
from posecast.client.skeletons import skeleton_of
from posecast.client.sources.bvh_source import BvhSource
from posecast.client.sources.tracker_set import TrackerSetSource
from posecast.client.viewer.bench import Clip
from posecast.server.app import Session
from posecast.solver import rotations as R
from posecast.solver.humanoid import HumanoidMap, humanoid_map, humanoid_pose
from posecast.solver.naming import roles
from posecast.solver.readers.bvh import read_bvh
from posecast.solver.readers.gltf import load_makehuman
from posecast.solver.rig import canonical_pose, global_pose
from posecast.solver.skeleton import Skeleton
from posecast.solver.tracking.devices import PRESETS

X, Y, Z = np.eye(3)
S45 = np.sin(np.pi / 4)
MAKEHUMAN_BONES = ("Hips", "Spine", "Chest", "UpperChest", "Neck", "Head", *(
    side + bone for side in ("Left", "Right") for bone in (
        "Shoulder", "UpperArm", "LowerArm", "Hand", "UpperLeg", "LowerLeg", "Foot",
        "Toes")))


def unity_tpose_skeleton() -> Skeleton:
    """A small rig with Unity names, one spine joint, no neck and no toes."""
    joints = [("Hips", None, (0, 1.0, 0)), ("Spine", "Hips", (0, 0.1, 0)),
              ("Chest", "Spine", (0, 0.25, 0)), ("Head", "Chest", (0, 0.3, 0))]
    for side, sign in (("Left", 1.0), ("Right", -1.0)):
        joints += [(f"{side}Shoulder", "Chest", (sign * 0.05, 0.2, 0)),
                   (f"{side}UpperArm", f"{side}Shoulder", (sign * 0.12, 0, 0)),
                   (f"{side}LowerArm", f"{side}UpperArm", (sign * 0.28, 0, 0)),
                   (f"{side}Hand", f"{side}LowerArm", (sign * 0.25, 0, 0)),
                   (f"{side}UpperLeg", "Hips", (sign * 0.1, -0.05, 0)),
                   (f"{side}LowerLeg", f"{side}UpperLeg", (0, -0.42, 0)),
                   (f"{side}Foot", f"{side}LowerLeg", (0, -0.4, 0))]
    names = tuple(n for n, _, _ in joints)
    parents = np.array([-1 if p is None else names.index(p) for _, p, _ in joints])
    return Skeleton(names, parents, np.array([o for _, _, o in joints], dtype=float))


@pytest.fixture(scope="module")
def makehuman() -> HumanoidMap:
    return humanoid_map(load_makehuman().skeleton)


def tpose(hmap: HumanoidMap) -> np.ndarray:
    sk = hmap.skeleton
    return canonical_pose(sk, roles(sk))


def turned(hmap: HumanoidMap, turns: dict[str, np.ndarray],
           local: np.ndarray | None = None) -> np.ndarray:
    """The T-pose (or ``local``) with each named joint turned by a world rotation (its
    children go with it), parents first."""
    sk = hmap.skeleton
    local = tpose(hmap) if local is None else local.copy()
    for name in sorted(turns, key=sk.index):
        j = sk.index(name)
        gq, _ = global_pose(sk, local)
        parent = gq[sk.parents[j]] if j > 0 else R.IDENTITY
        local[j] = R.mul(R.conjugate(parent), R.mul(turns[name], gq[j]))
    return local


def unity_locals(hmap: HumanoidMap, local: np.ndarray) -> dict[str, np.ndarray]:
    pose = humanoid_pose(hmap, local, hmap.skeleton.offsets[0])
    return dict(zip(hmap.bones, pose.rotations, strict=True))


def assert_only(bones: dict[str, np.ndarray], expected: dict[str, np.ndarray]) -> None:
    """The expected bones have those rotations (either sign), every other is identity."""
    for name, q in bones.items():
        want = np.asarray(expected.get(name, R.IDENTITY), dtype=float)
        assert np.degrees(R.angle_between(q, want)) < 1e-6, (name, q, want)


def about(axis: np.ndarray, degrees: float) -> np.ndarray:
    return R.from_axis_angle(axis, np.radians(degrees))


def test_the_t_pose_is_identity_for_every_bone_of_any_rig(clip: Clip) -> None:
    rigs = {"makehuman": load_makehuman().skeleton, "calibrated": skeleton_of(clip.info),
            "cmu": read_bvh(builtin_motion_path()).skeleton, "unity": unity_tpose_skeleton()}
    for name, sk in rigs.items():
        hmap = humanoid_map(sk)
        assert_only(unity_locals(hmap, tpose(hmap)), {})
        assert hmap.bones[0] == "Hips" and np.all(hmap.parents[1:] < np.arange(1, len(
            hmap.bones))), name
    assert humanoid_map(rigs["makehuman"]).bones == MAKEHUMAN_BONES
    assert humanoid_map(rigs["cmu"]).bones == MAKEHUMAN_BONES  # Neck1 folds into Neck
    small = humanoid_map(rigs["unity"])
    assert "UpperChest" not in small.bones and "Neck" not in small.bones
    assert "LeftToes" not in small.bones
    chest = small.index("Chest")
    assert small.parents[small.index("Head")] == chest
    assert small.parents[small.index("LeftShoulder")] == chest


def test_a_lowered_arm_turns_about_unity_z_and_mirrors(makehuman: HumanoidMap) -> None:
    # posecast: the left arm points +x (the body's left); lowering it turns -90 deg
    # about z. Unity: it points -x, and Euler(0, 0, 90) takes -x onto -y.
    bones = unity_locals(makehuman, turned(makehuman, {"upperarm_l": about(Z, -90)}))
    assert_only(bones, {"LeftUpperArm": [0, 0, S45, S45]})
    assert np.allclose(R.rotate(bones["LeftUpperArm"], -X), -Y)
    bones = unity_locals(makehuman, turned(makehuman, {"upperarm_r": about(Z, 90)}))
    assert_only(bones, {"RightUpperArm": [0, 0, -S45, S45]})
    assert np.allclose(R.rotate(bones["RightUpperArm"], X), -Y)


def test_a_twist_stays_on_its_bone_and_children_follow(makehuman: HumanoidMap) -> None:
    # the left forearm twisted 60 deg about its own axis (posecast +x): Unity's x too;
    # the hand goes with it, so its local rotation stays identity
    bones = unity_locals(makehuman, turned(makehuman, {"lowerarm_l": about(X, 60)}))
    assert_only(bones, {"LeftLowerArm": about(X, 60)})
    # the forearm bent 90 deg forward after the upper arm twisted 30 deg: the forearm's
    # local turn is the bend alone, in the twisted upper arm's frame
    twist = about(X, 30)
    pose = turned(makehuman, {"upperarm_l": twist})
    bend_world = R.mul(twist, R.mul(about(Y, -90), R.conjugate(twist)))
    bones = unity_locals(makehuman, turned(makehuman, {"lowerarm_l": bend_world}, pose))
    assert_only(bones, {"LeftUpperArm": about(X, 30), "LeftLowerArm": about(Y, 90)})
    # Unity: bent forward, the forearm's -x runs to +z (forward) in its parent's frame
    assert np.allclose(R.rotate(bones["LeftLowerArm"], -X), Z)


def test_the_head_nods_down_about_plus_x_and_turns_left_about_minus_y(
        makehuman: HumanoidMap) -> None:
    bones = unity_locals(makehuman, turned(makehuman, {"head": about(X, 30)}))
    assert_only(bones, {"Head": about(X, 30)})
    assert R.rotate(bones["Head"], Z)[1] < -0.4  # the face looks down
    bones = unity_locals(makehuman, turned(makehuman, {"head": about(Y, 40)}))
    assert_only(bones, {"Head": about(Y, -40)})
    assert R.rotate(bones["Head"], Z)[0] < -0.6  # to the avatar's left: Unity's -x


def test_a_turned_body_turns_only_the_hips(makehuman: HumanoidMap) -> None:
    sk = makehuman.skeleton
    local = turned(makehuman, {sk.names[0]: about(Y, 90)})  # the whole body faces +x
    root = np.array([0.3, 0.0, -1.2])
    pose = humanoid_pose(makehuman, local, root)
    assert_only(dict(zip(makehuman.bones, pose.rotations, strict=True)),
                {"Hips": about(Y, -90)})
    _, gp = global_pose(sk, local, root)
    assert np.allclose(pose.hips, gp[sk.index("pelvis")] * [-1, 1, 1])


def test_left_and_right_mirror_each_other(makehuman: HumanoidMap) -> None:
    rng = np.random.default_rng(5)
    for _ in range(20):
        turns = {}
        for joint in ("upperarm", "thigh", "hand"):
            q = R.normalize(rng.normal(size=4))
            turns[f"{joint}_l"] = q
            turns[f"{joint}_r"] = q * [1, -1, -1, 1]  # the mirror image across x
        bones = unity_locals(makehuman, turned(makehuman, turns))
        for bone in ("UpperArm", "LowerArm", "Hand", "UpperLeg", "LowerLeg", "Foot"):
            left, right = bones["Left" + bone], bones["Right" + bone]
            assert np.degrees(R.angle_between(right, left * [1, -1, -1, 1])) < 1e-6, bone


def test_a_batch_converts_as_its_frames(clip: Clip) -> None:
    hmap = humanoid_map(skeleton_of(clip.info))
    batch = humanoid_pose(hmap, clip.rotations[:10], clip.roots[:10])
    for f in range(10):
        one = humanoid_pose(hmap, clip.rotations[f], clip.roots[f])
        assert np.allclose(one.rotations, batch.rotations[f])
        assert np.allclose(one.hips, batch.hips[f])
    assert np.allclose(np.linalg.norm(batch.rotations, axis=-1), 1.0)
    assert np.all(batch.rotations[..., 3] >= 0.0)


def type_tags(dgram: bytes) -> str:
    """An OSC message's type tag string (after its 4-byte aligned address)."""
    end = dgram.index(b"\0")
    start = (end // 4 + 1) * 4
    return dgram[start:dgram.index(b"\0", start)].decode()


def test_a_bundle_holds_the_messages_the_spec_defines(clip: Clip) -> None:
    hmap = humanoid_map(skeleton_of(clip.info))
    bundle = vmc_bundle(hmap, clip.rotations[50], clip.roots[50], 12.5)
    parsed = OscBundle(bundle.dgram)
    assert OscBundle.dgram_is_bundle(bundle.dgram)
    messages = list(parsed)
    assert [(m.address, type_tags(m.dgram)) for m in messages[:3]] == [
        ("/VMC/Ext/OK", ",iii"), ("/VMC/Ext/T", ",f"), ("/VMC/Ext/Root/Pos", ",sfffffff")]
    assert messages[0].params == [1, 3, 0]
    assert messages[1].params == [12.5]
    bones = messages[3:]
    assert all((m.address, type_tags(m.dgram)) == ("/VMC/Ext/Bone/Pos", ",sfffffff")
               for m in bones)
    assert tuple(m.params[0] for m in bones) == MAKEHUMAN_BONES
    _, gp = global_pose(hmap.skeleton, clip.rotations[50], clip.roots[50])
    pelvis = gp[hmap.skeleton.index("pelvis")]
    root = messages[2].params
    assert root[0] == "root" and root[4:] == [0.0, 0.0, 0.0, 1.0]
    assert np.allclose(root[1:4], [-pelvis[0], 0.0, pelvis[2]], atol=1e-6)
    assert np.allclose(bones[0].params[1:4], [0.0, pelvis[1], 0.0], atol=1e-6)
    arm = bones[MAKEHUMAN_BONES.index("LeftUpperArm")].params[1:4]
    assert arm[0] < -0.1  # the upper arm sits to the left of its shoulder: Unity's -x


# ------------------------------------------------------------------ over the network

@pytest.fixture(scope="module")
def session() -> Session:
    return Session(reconnect_grace=5.0)  # the rig built and the solver warmed once


class Receiver:
    """A VMC receiver on python-osc's asyncio server: messages grouped into bundles
    (each of ours opens with /VMC/Ext/OK), with their arrival times."""

    def __init__(self) -> None:
        self.bundles: list[tuple[float, list[tuple[str, tuple[object, ...]]]]] = []
        self.port = 0
        self.stray: list[str] = []
        self._transport: asyncio.DatagramTransport | None = None

    def _on_message(self, address: str, *args: object) -> None:
        if address == "/VMC/Ext/OK":
            self.bundles.append((time.perf_counter(), []))
        if not self.bundles:
            self.stray.append(address)
            return
        self.bundles[-1][1].append((address, args))

    async def __aenter__(self) -> Receiver:
        dispatcher = Dispatcher()
        dispatcher.set_default_handler(self._on_message)
        server = AsyncIOOSCUDPServer(("127.0.0.1", 0), dispatcher, asyncio.get_running_loop())
        self._transport, _ = await server.create_serve_endpoint()
        self.port = self._transport.get_extra_info("sockname")[1]
        return self

    async def __aexit__(self, *exc: object) -> None:
        assert self._transport is not None
        self._transport.close()


def with_player(session: Session, test: Callable[[str, Player], Awaitable[None]]) -> None:
    """A server on 127.0.0.1 and a player replaying the built-in walk in room 'stage' at
    a headset's 90 Hz, for the length of ``test(url, player)``."""
    async def main() -> None:
        async with serving(session) as url:
            # the six driving devices: the thigh's swing is then the walk's, not the
            # simulated knee tracker's steering (which this test is not about)
            source = TrackerSetSource(BvhSource(builtin_motion_path(), loop=True,
                                                rate_hz=HEADSET_HZ), PRESETS["6"])
            player = Player(url, "stage", "ana", source)
            stop = asyncio.Event()
            playing = asyncio.create_task(player.run(stop=stop))
            try:
                await asyncio.wait_for(test(url, player), 60)
            finally:
                stop.set()
                await playing
                source.close()
    asyncio.run(main())


def test_run_vmc_streams_the_walking_avatar(session: Session) -> None:
    """At the 200 Hz cap every frame of the 90 Hz player may go: the receiver gets the
    player's rate (measured 90 a second alone, 90 beside two busy-looping processes,
    86-90 beside four). The bound, 60 a second, keeps that margin. It streams 6 s: under
    the suite's two workers joining took 1.6 s of 4, leaving 2.4 s of bundles."""
    found: dict[str, Any] = {}

    async def test(url: str, player: Player) -> None:
        async with Receiver() as rx:
            stats = await run_vmc(url, "stage", None, "127.0.0.1", rx.port, seconds=6.0,
                                  rate_hz=200.0)
            await asyncio.sleep(0.1)  # the last datagrams in flight
        found.update(stats=stats, rx=rx, avatar=player.stats.avatar_id)

    with_player(session, test)
    stats, rx = found["stats"], found["rx"]
    assert stats.avatar_name == "ana" and stats.avatar_id == found["avatar"]
    assert stats.send_errors == 0
    assert rx.stray == []
    assert len(rx.bundles) == stats.bundles_sent
    times = np.array([t for t, _ in rx.bundles])
    window = times[-1] - times[0]
    assert window > 2.5
    assert (len(times) - 1) / window >= 60.0
    assert np.diff(times).min() >= 0.0
    leg, clock = [], []
    for _, messages in rx.bundles:
        addresses = [a for a, _ in messages]
        assert addresses[:3] == ["/VMC/Ext/OK", "/VMC/Ext/T", "/VMC/Ext/Root/Pos"]
        assert messages[0][1] == (1, 3, 0)
        clock.append(messages[1][1][0])
        root = messages[2][1]
        assert root[0] == "root" and all(isinstance(v, float) for v in root[1:])
        bones = {args[0]: np.array(args[1:], dtype=float) for a, args in messages[3:]}
        assert addresses[3:] == ["/VMC/Ext/Bone/Pos"] * len(MAKEHUMAN_BONES)
        assert tuple(bones) == MAKEHUMAN_BONES
        quats = np.array([b[3:] for b in bones.values()])
        assert np.allclose(np.linalg.norm(quats, axis=1), 1.0, atol=1e-5)
        assert 0.7 < bones["Hips"][1] < 1.1  # the hips' height, metres
        leg.append(bones["LeftUpperLeg"][3:])
    assert np.all(np.diff(clock) > 0.0)
    leg_q = np.array(leg)
    swing = np.degrees(R.angle_between(leg_q[:, None], leg_q[None]))
    assert swing.max() > 25.0  # the thigh swings as the avatar walks
    # walking, a thigh swings forward and back: about Unity's x more than y or z
    axes = np.abs(R.to_rotvec(R.mul(R.conjugate(leg_q[0]), leg_q))).sum(axis=0)
    assert axes[0] > axes[1] and axes[0] > axes[2]


def test_run_vmc_keeps_to_its_rate_and_finds_avatars_by_name(session: Session) -> None:
    found: dict[str, Any] = {}

    async def test(url: str, player: Player) -> None:
        async with Receiver() as rx:
            limited = await run_vmc(url, "stage", "ANA", "127.0.0.1", rx.port,
                                    seconds=3.0, rate_hz=30.0)
            await asyncio.sleep(0.1)
        with pytest.raises(VmcError) as absent:
            await run_vmc(url, "stage", "bob", "127.0.0.1", rx.port, seconds=5.0,
                          find_timeout=1.0)
        found.update(limited=limited, rx=rx, absent=str(absent.value))

    with_player(session, test)
    limited, rx = found["limited"], found["rx"]
    assert limited.avatar_name == "ana"
    times = np.array([t for t, _ in rx.bundles])
    # 30 a second at most (a slot may come one period early after a late one)
    assert len(times) <= 3.0 * 30 + 2
    assert len(times) >= 2.0 * 30  # and the 90 Hz player fills most slots
    assert limited.frames_skipped > limited.bundles_sent
    assert found["absent"] == "no avatar named 'bob' in room 'stage'; avatars present: 'ana'"


def test_bad_targets_and_options_are_refused_in_one_line() -> None:
    assert parse_target("127.0.0.1:39540") == ("127.0.0.1", 39540)
    assert parse_target("vseeface.local") == ("vseeface.local", 39539)
    assert parse_target("[::1]:9000") == ("::1", 9000)
    assert parse_target("::1") == ("::1", 39539)
    for text, words in (("host:http", "is not a number"), ("host:0", "from 1 to 65535"),
                        ("host:70000", "from 1 to 65535"), (":9000", "bad VMC receiver host"),
                        ("[::1", "expected [IPv6]:PORT"), ("a host:1", "host")):
        with pytest.raises(VmcError, match=words.replace("[", r"\[")):
            parse_target(text)
    with pytest.raises(VmcError, match="port True"):
        check_target("localhost", True)  # type: ignore[arg-type]

    async def refused(**options: object) -> str:
        with pytest.raises(VmcError) as err:
            await run_vmc("ws://127.0.0.1:1", "stage", **options)  # type: ignore[arg-type]
        return str(err.value)

    async def main() -> None:
        assert "at most 200 Hz" in await refused(rate_hz=500.0)
        assert "at most 200 Hz" in await refused(rate_hz=0.0)
        assert "positive number of seconds" in await refused(seconds=-1.0)
        assert "avatar name is empty" in await refused(avatar=" ")
        assert "port" in await refused(port=0)
        with pytest.raises(SessionError):  # nothing listens on port 1
            await run_vmc("ws://127.0.0.1:1", "stage", seconds=1.0)

    asyncio.run(main())
