"""protocol/: every message survives encode -> decode, and bad input of every kind is
rejected with a ProtocolError whose message names the field and the value."""

from __future__ import annotations

import math
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from protocol_cases import (
    RNG,
    poses,
    poses_wire,
    rejects,
    skeleton_info,
    tpose,
    unit_quaternions,
    wire,
    wire_poses,
)
from pydantic import BaseModel, ValidationError

from posecast.protocol import (
    CALIBRATION_ROLES,
    DEVICE_ROLES,
    MAX_ANGLE_ERROR_DEG,
    MAX_CLIENT_MESSAGE_BYTES,
    MESSAGE_TYPES,
    PROTOCOL_VERSION,
    AvatarBatch,
    AvatarFrame,
    AvatarInfo,
    AvatarRoster,
    Calibrate,
    Error,
    ErrorCode,
    Hello,
    Leave,
    Ping,
    Pong,
    ProtocolError,
    TrackerFrame,
    Welcome,
    decode,
    decode_client,
    encode,
    rotation_angle,
)
from posecast.protocol.codec import decode_tracker_poses
from posecast.protocol.measure import sample_avatar_batch, sample_tracker_frame
from posecast.protocol.messages import tracker_poses_from_wire
from posecast.protocol.validation import (
    QUAT_NORM_TOLERANCE,
)
from posecast.solver.calibration import CALIBRATION_DEVICES
from posecast.solver.motion import VIVE_DEVICES
from posecast.solver.tracking.devices import DEVICES


# --------------------------------------------------------------------------- vocabulary
def test_device_roles_are_the_solver_devices() -> None:
    assert DEVICE_ROLES == VIVE_DEVICES
    assert set(DEVICE_ROLES) == set(DEVICES)
    assert CALIBRATION_ROLES == CALIBRATION_DEVICES


def test_every_message_type_is_registered_once() -> None:
    assert sorted(MESSAGE_TYPES) == ["avatar_batch", "avatar_roster", "calibrate", "error",
                                     "hello", "leave", "ping", "pong", "redirect",
                                     "tracker_frame", "viewer_report", "welcome"]


# --------------------------------------------------------------------------- round trips
@pytest.mark.parametrize("message", [
    Hello(protocol_version=PROTOCOL_VERSION, role="player", room="lab-1", display_name="Ada",
          token="s3cret"),
    Hello(protocol_version=PROTOCOL_VERSION, role="spectator", room="lab-1",
          display_name="Zoë 観客", max_rate_hz=30.0),
    Welcome(protocol_version=PROTOCOL_VERSION, connection_id=7, avatar_id=3,
            server_time=1.7e9 + 0.123456789),
    Welcome(protocol_version=PROTOCOL_VERSION, connection_id=8, avatar_id=None,
            server_time=5.0),
    Ping(t0=123.000001),
    Pong(t0=123.000001, t1=456.5, t2=456.5001),
    Error(code=ErrorCode.NOT_ALLOWED, message="spectators cannot send tracker_frame"),
    Leave(), Leave(reason="bye"),
    AvatarRoster(removed=(4, 5)),
], ids=lambda m: m.type)
def test_scalar_messages_round_trip_exactly(message: BaseModel) -> None:
    back = decode(encode(message))
    assert type(back) is type(message)
    assert back.model_dump() == message.model_dump()


def test_tracker_frame_round_trips_exactly() -> None:
    frame = TrackerFrame(seq=2**40, t_capture=1.7e9 + 1e-6, clock_offset=-0.25,
                         roles=DEVICE_ROLES, poses=poses(len(DEVICE_ROLES)))
    back = decode_client(encode(frame))
    assert isinstance(back, TrackerFrame)
    assert (back.seq, back.t_capture, back.clock_offset, back.roles) == (
        2**40, 1.7e9 + 1e-6, -0.25, DEVICE_ROLES)
    np.testing.assert_array_equal(back.poses, frame.poses)  # float64 on the wire: exact
    assert back == frame
    assert back != frame.model_copy(update={"poses": frame.poses[::-1]})
    assert back != frame.model_copy(update={"seq": 1})
    assert back.t_capture_server == 1.7e9 + 1e-6 - 0.25
    np.testing.assert_array_equal(back.pose("right_knee"), frame.poses[9])


def test_tracker_frame_with_some_devices() -> None:
    frame = TrackerFrame(seq=0, t_capture=0.0, clock_offset=0.0, roles=("hip", "head"),
                         poses=poses(2))
    back = decode_client(encode(frame))
    assert isinstance(back, TrackerFrame)
    assert back.roles == ("hip", "head")
    assert back.pose("left_hand") is None
    np.testing.assert_array_equal(back.pose("head"), frame.poses[1])


def test_calibrate_round_trips() -> None:
    message = tpose()
    back = decode_client(encode(message))
    assert isinstance(back, Calibrate)
    np.testing.assert_array_equal(back.poses, message.poses)


def test_roster_round_trips_the_real_makehuman_skeleton() -> None:
    from posecast.solver.readers.gltf import load_makehuman

    skeleton = load_makehuman().skeleton
    info = AvatarInfo(avatar_id=1, display_name="Ada", joint_names=skeleton.names,
                      parents=tuple(int(p) for p in skeleton.parents),
                      rest_offsets=skeleton.offsets)
    roster = AvatarRoster(avatars=(info, skeleton_info(2)), removed=(9,))
    back = decode(encode(roster))
    assert isinstance(back, AvatarRoster)
    assert back == roster
    assert back.removed == (9,)
    got = back.avatars[0]
    assert got.num_joints == 53
    assert got.joint_names == skeleton.names
    assert got.parents == tuple(skeleton.parents.tolist())
    np.testing.assert_array_equal(got.rest_offsets, skeleton.offsets)
    assert back.avatars[1].joint_names == ("root", "spine", "head")


def _frames() -> list[AvatarFrame]:
    """Three avatars of different skeletons, as the viewer would compare them."""
    return [AvatarFrame(avatar_id=avatar_id, seq=avatar_id * 100, root=RNG.uniform(-3, 3, 3),
                        rotations=unit_quaternions(joints), t_capture=1.0 + avatar_id,
                        t_server_receive=1.001 + avatar_id, t_solved=1.0012 + avatar_id,
                        t_sent=1.0013)
            for avatar_id, joints in ((5, 53), (6, 3), (9, 60))]


def test_avatar_batch_round_trips_within_quantization() -> None:
    frames = _frames()
    batch = AvatarBatch.from_frames(frames, t_sent=1.0013)
    back = decode(encode(batch))
    assert isinstance(back, AvatarBatch)
    assert back.size == 3 and back.joint_counts.tolist() == [53, 3, 60]
    for got, sent in zip(back.frames, frames, strict=True):
        assert (got.avatar_id, got.seq, got.t_sent) == (sent.avatar_id, sent.seq, sent.t_sent)
        # times travel as float32 ages before t_sent: within half a float32 step of each
        for name in ("t_capture", "t_server_receive", "t_solved"):
            age = sent.t_sent - getattr(sent, name)
            assert getattr(got, name) == pytest.approx(getattr(sent, name),
                                                       rel=0, abs=abs(age) * 2.0**-24 + 1e-15)
            assert getattr(got, name) != getattr(sent, name) or age == np.float32(age)
        assert got.rotations.shape == sent.rotations.shape
        worst = np.degrees(rotation_angle(got.rotations, sent.rotations).max())
        assert 0 < worst <= MAX_ANGLE_ERROR_DEG
        # the root travels as float32: within one float32 step at a few metres
        np.testing.assert_allclose(got.root, sent.root, rtol=0, atol=3 * 2.0**-22)
        np.testing.assert_array_equal(got.root, sent.root.astype(np.float32))
    # frame(i) alone gives what frames gives, from its own slice of the columns
    assert back.frame(2) == back.frames[2] and back.frame(0) == back.frames[0]


def test_batch_arrays_are_read_only() -> None:
    batch = decode(encode(AvatarBatch.from_frames(_frames(), t_sent=2.0)))
    assert isinstance(batch, AvatarBatch)
    for array in (batch.avatar_ids, batch.roots, batch.rotations, batch.t_capture,
                  batch.frame(1).rotations):
        with pytest.raises(ValueError, match="read-only"):
            array[0] = 0


def test_empty_batch_round_trips() -> None:
    back = decode(encode(AvatarBatch.from_frames([], t_sent=1.0)))
    assert isinstance(back, AvatarBatch) and back.size == 0 and back.frames == ()


def test_from_arrays_matches_frame_by_frame() -> None:
    roots = RNG.uniform(-2, 2, (4, 3))
    rotations = unit_quaternions(4 * 53).reshape(4, 53, 4) * 1.0005  # normalised on entry
    batch = AvatarBatch.from_arrays([10, 11, 12, 13], [1, 2, 3, 4], roots, rotations,
                                    [0.1] * 4, [0.2] * 4, t_solved=0.3, t_sent=0.4)
    alone = [AvatarFrame(avatar_id=10 + i, seq=i + 1, root=roots[i], rotations=rotations[i],
                         t_capture=0.1, t_server_receive=0.2, t_solved=0.3, t_sent=0.4)
             for i in range(4)]
    for frame, one in zip(batch.frames, alone, strict=True):
        assert frame.avatar_id == one.avatar_id and frame.seq == one.seq
        np.testing.assert_array_equal(frame.root, one.root)
        np.testing.assert_allclose(frame.rotations, one.rotations, rtol=0, atol=1e-15)
        np.testing.assert_allclose(np.linalg.norm(frame.rotations, axis=1), 1.0, atol=1e-15)
    assert encode(batch) == encode(AvatarBatch.from_frames(alone, t_sent=0.4))


def test_from_arrays_rejects_mismatched_inputs_and_bad_rotations() -> None:
    with pytest.raises(ValueError, match=r"(?s)seqs.*1 rows for 2 avatar_ids"):
        AvatarBatch.from_arrays([1, 2], [1], np.zeros((2, 3)), unit_quaternions(6).reshape(2, 3, 4),
                                [0.0] * 2, [0.0] * 2, 0.0, 0.0)
    with pytest.raises(ValueError, match=r"(?s)rotations.*expected shape \(n, 4\), got \(4, 3\)"):
        AvatarBatch.from_arrays([1, 2], [1, 1], np.zeros((2, 3)), np.ones((2, 2, 3)),
                                [0.0] * 2, [0.0] * 2, 0.0, 0.0)
    bad = unit_quaternions(6).reshape(2, 3, 4)
    bad[1, 2] *= 2.0
    with pytest.raises(ValueError, match=r"avatar 1 \(joint 2\): quaternion .* has norm 2"):
        AvatarBatch.from_arrays([1, 2], [1, 1], np.zeros((2, 3)), bad, [0.0] * 2, [0.0] * 2,
                                0.0, 0.0)
    with pytest.raises(ValueError, match="avatar_id 4 appears more than once"):
        AvatarBatch.from_arrays([4, 4], [1, 1], np.zeros((2, 3)),
                                unit_quaternions(6).reshape(2, 3, 4), [0.0] * 2, [0.0] * 2,
                                0.0, 0.0)
    with pytest.raises(ValueError, match=r"(?s)t_capture.*row 1 is nan"):
        AvatarBatch.from_arrays([1, 2], [1, 1], np.zeros((2, 3)),
                                unit_quaternions(6).reshape(2, 3, 4), [0.0, math.nan],
                                [0.0] * 2, 0.0, 0.0)
    with pytest.raises(ValueError, match=r"(?s)avatar_ids.*integers"):
        AvatarBatch.from_arrays([1.5, 2], [1, 1], np.zeros((2, 3)),  # type: ignore[list-item]
                                unit_quaternions(6).reshape(2, 3, 4), [0.0] * 2, [0.0] * 2,
                                0.0, 0.0)


def test_from_arrays_copies_the_solver_buffers() -> None:
    rotations = np.tile([0.0, 0.0, 0.0, 1.0], (2, 3, 1))
    roots = np.zeros((2, 3))
    batch = AvatarBatch.from_arrays([1, 2], [1, 1], roots, rotations, [0.0] * 2, [0.0] * 2,
                                    0.0, 0.0)
    rotations[:] = [1.0, 0.0, 0.0, 0.0]  # the solver writes its next result
    roots[:] = 5.0
    np.testing.assert_array_equal(batch.frames[1].rotations[2], [0, 0, 0, 1.0])
    np.testing.assert_array_equal(batch.frames[1].root, [0, 0, 0])


def test_stamped_sets_t_sent_on_every_frame() -> None:
    batch = sample_avatar_batch(3, 5).stamped(1.7e9 + 42.5)
    assert [f.t_sent for f in batch.frames] == [1.7e9 + 42.5] * 3
    assert [f.t_sent for f in decode(encode(batch)).frames] == [1.7e9 + 42.5] * 3  # type: ignore[union-attr]


def test_batch_latencies_equal_each_frames() -> None:
    batch = AvatarBatch.from_frames(_frames(), t_sent=20.0)
    got = batch.latencies(t_received=20.5)
    for i, frame in enumerate(batch.frames):
        one = frame.latencies(t_received=20.5)
        assert set(got) == set(one)
        for stage, seconds in one.items():
            assert got[stage][i] == pytest.approx(seconds, abs=1e-12)


def test_latencies_name_the_design_stages() -> None:
    frame = AvatarFrame(avatar_id=0, seq=0, root=np.zeros(3),
                        rotations=np.array([[0, 0, 0, 1.0]]),
                        t_capture=10.0, t_server_receive=10.002, t_solved=10.0025,
                        t_sent=10.003)
    got = frame.latencies(t_received=10.004, t_presented=10.010)
    expected = {"capture_to_server": 0.002, "solve": 0.0005, "server": 0.001,
                "capture_to_spectator": 0.004, "network_to_spectator": 0.001,
                "capture_to_presented": 0.010, "receive_to_presented": 0.006}
    assert got.keys() == expected.keys()
    for key, value in expected.items():
        assert got[key] == pytest.approx(value, abs=1e-12), key


def test_arrays_are_read_only() -> None:
    frame = decode_client(encode(sample_tracker_frame()))
    assert isinstance(frame, TrackerFrame)
    with pytest.raises(ValueError, match="read-only"):
        frame.poses[0, 0] = 1.0


def test_quaternions_within_tolerance_are_normalised() -> None:
    p = poses(2)
    p[1, 3:] *= 1.0009
    frame = decode_client(encode(TrackerFrame(seq=1, t_capture=0, clock_offset=0,
                                              roles=("head", "hip"), poses=p)))
    assert isinstance(frame, TrackerFrame)
    # normalised, then rounded to int16 levels: unit within their rounding
    norms = np.linalg.norm(frame.rotations, axis=1)
    np.testing.assert_allclose(norms, 1.0, atol=3.1e-5)
    assert abs(norms[1] - 1.0009) > 8e-4


# --------------------------------------------------------------------------- fuzzing
GOOD = [encode(sample_tracker_frame()), encode(tpose()),
        encode(Hello(protocol_version=PROTOCOL_VERSION, role="player", room="r", display_name="a")),
        encode(sample_avatar_batch(2, 3)), encode(AvatarRoster(avatars=(skeleton_info(),)))]


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_random_bytes_raise_only_protocol_errors(data: bytes) -> None:
    try:
        decode(data)
    except ProtocolError as err:
        assert err.code in {c.value for c in ErrorCode}
        assert err.message


@settings(max_examples=500, deadline=None)
@given(st.sampled_from(GOOD), st.data())
def test_corrupted_messages_raise_only_protocol_errors(good: bytes, data: st.DataObject) -> None:
    raw = bytearray(good)
    for _ in range(data.draw(st.integers(1, 4))):
        raw[data.draw(st.integers(0, len(raw) - 1))] = data.draw(st.integers(0, 255))
    try:
        decode(bytes(raw))
    except ProtocolError as err:
        assert err.message


def test_direct_batch_encoder_gives_the_model_bytes() -> None:
    from posecast.protocol.codec import encode_avatar_batch
    rng = np.random.default_rng(3)
    q = rng.normal(size=(5, 53, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    args = ([1, 2, 3, 4, 5], [9, 8, 7, 6, 5], rng.uniform(-2, 2, (5, 3)), q,
            [0.1] * 5, [0.2] * 5, 0.3, 0.4)
    assert encode_avatar_batch(*args) == encode(AvatarBatch.from_arrays(*args))
    with pytest.raises(ValueError, match="finite"):
        bad = q.copy()
        bad[2, 7, 1] = np.nan
        encode_avatar_batch(*args[:3], bad, *args[4:])



# --------------------------------------------------------------------------- the server's
# one-pass tracker frame check: never accepts what TrackerFrame refuses, and gives its values
_POSE_SPECIAL = [math.nan, math.inf, -math.inf, 1001.0, -999.0, 0.0, 1.0, 1.0 + 1e-4,
                 1.0 + 3e-3, 0.5]
# a quaternion component's int16 level: the extremes, zero, a unit axis, and levels that
# put a row just inside or outside the tolerance
_LEVEL_SPECIAL = [-32768, 32767, 0, 23170, 23171, 16384, 16400, 16401, 32800]


@st.composite
def corrupted_tracker_frames(draw: st.DrawFn) -> dict[str, Any]:
    """The wire map of a valid tracker frame, left alone or corrupted in one of many ways."""
    roles = tuple(draw(st.permutations(DEVICE_ROLES))[:draw(st.integers(1, len(DEVICE_ROLES)))])
    obj = wire(sample_tracker_frame(roles, seed=draw(st.integers(0, 3))))
    kind = draw(st.sampled_from(["none", "pose", "bytes", "length", "roles", "duplicate",
                                 "type", "keys", "seq", "time"]))
    n = len(roles)
    if kind == "pose":
        poses = wire_poses(obj["poses"])
        column = draw(st.integers(0, 6))
        poses[draw(st.integers(0, n - 1)), column] = draw(
            st.sampled_from(_POSE_SPECIAL if column < 3 else _LEVEL_SPECIAL))
        obj["poses"] = poses_wire(poses)
    elif kind == "duplicate" and n > 1:  # a role twice, the pose rows still matching
        i, j = draw(st.lists(st.integers(0, n - 1), min_size=2, max_size=2, unique=True))
        obj["roles"][i] = obj["roles"][j]
    elif kind == "bytes":
        obj["poses"] = draw(st.binary(min_size=20 * n, max_size=20 * n))
    elif kind == "length":
        obj["poses"] = obj["poses"][:draw(st.integers(0, 20 * n - 1))]
    elif kind == "roles":  # one role replaced (the pose rows still match), or odd lists
        changed = list(obj["roles"])
        changed[draw(st.integers(0, n - 1))] = draw(st.sampled_from(
            [*range(len(DEVICE_ROLES)), 11, -1, "head", "", 1.0, True, None, [0], b"\x01"]))
        obj["roles"] = draw(st.sampled_from([
            changed, [], [*obj["roles"], 1], 0, [*range(len(DEVICE_ROLES)), 0],
            list(reversed(obj["roles"]))]))
    elif kind == "type":
        obj[draw(st.sampled_from(["roles", "poses", "seq", "t_capture", "clock_offset",
                                  "type"]))] = draw(st.sampled_from(
                                      [None, 7, 7.5, "x", True, [1.0], b"\x00" * 28]))
    elif kind == "keys":
        if draw(st.booleans()):
            del obj[draw(st.sampled_from(sorted(obj)))]
        else:
            obj["extra"] = 1
    elif kind == "seq":
        obj["seq"] = draw(st.sampled_from([-1, 0, 2**63 - 1, 2**63, True, 1.0]))
    elif kind == "time":
        obj[draw(st.sampled_from(["t_capture", "clock_offset"]))] = draw(
            st.sampled_from([math.nan, math.inf, -math.inf, 3, "1.0", -2.5, 1e300]))
    return obj


def _tracker_check_agrees(obj: dict[str, Any]) -> bool:
    """True when the one-pass check accepted: then the model accepts too, equal."""
    fast = tracker_poses_from_wire(dict(obj))
    try:
        slow: TrackerFrame | None = TrackerFrame.model_validate(obj, context={"wire": True})
    except ValidationError:
        slow = None
    if fast is None:
        return False
    assert slow is not None
    assert (fast.seq, fast.roles, fast.t_capture, fast.clock_offset) == \
        (slow.seq, slow.roles, slow.t_capture, slow.clock_offset)
    assert fast.t_capture_server == slow.t_capture_server
    assert np.array_equal(fast.poses, slow.poses) and not fast.poses.flags.writeable
    return True


@settings(max_examples=500, deadline=None)
@given(corrupted_tracker_frames())
def test_one_pass_tracker_check_accepts_only_what_the_model_accepts(obj: dict[str, Any],
                                                                    ) -> None:
    _tracker_check_agrees(obj)


def test_one_pass_tracker_check_takes_every_usual_frame() -> None:
    """Whatever a player sends (any roles, quaternions a little off unit) takes the hot
    path; a frame it refuses still reaches decode_client, which names the fault."""
    for k in range(1, len(DEVICE_ROLES) + 1):
        frame = sample_tracker_frame(DEVICE_ROLES[-k:], seed=k)
        assert _tracker_check_agrees(wire(frame))
        fast = decode_tracker_poses(encode(frame))
        assert fast is not None and fast.roles == frame.roles
    obj = wire(sample_tracker_frame())
    poses = wire_poses(obj["poses"])
    poses[2, 3:] *= 1.0 + 0.4 * QUAT_NORM_TOLERANCE  # off unit within tolerance: normalised
    obj["poses"] = poses_wire(poses)
    assert _tracker_check_agrees(obj)
    norms = np.linalg.norm(tracker_poses_from_wire(obj).poses[:, 3:], axis=1)
    assert np.allclose(norms, 1.0, atol=3.1e-5)
    poses[2, 0] = math.nan
    bad = msgpack.packb({**obj, "poses": poses_wire(poses)})
    assert decode_tracker_poses(bad) is None
    rejects(bad, "tracker_frame.poses", "row 2 (left_hand) position[0] is nan")
    for other in (b"\xc1", msgpack.packb([1, 2]), encode(Ping(t0=1.0)),
                  b"\x00" * (MAX_CLIENT_MESSAGE_BYTES + 1)):
        assert decode_tracker_poses(other) is None
