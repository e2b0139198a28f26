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
from numpy.typing import NDArray
from pydantic import BaseModel, ValidationError

from posecast.protocol import (
    CALIBRATION_ROLES,
    DEVICE_ROLES,
    MAX_ANGLE_ERROR_DEG,
    MAX_CLIENT_MESSAGE_BYTES,
    MAX_JOINTS,
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
from posecast.protocol.batch import avatar_batch_from_wire
from posecast.protocol.codec import decode_tracker_poses
from posecast.protocol.measure import sample_avatar_batch, sample_tracker_frame
from posecast.protocol.messages import tracker_poses_from_wire
from posecast.protocol.validation import (
    MAX_AVATARS,
    MAX_POSITION_M,
    QUAT_NORM_TOLERANCE,
    device_poses,
)
from posecast.solver.calibration import CALIBRATION_DEVICES
from posecast.solver.motion import VIVE_DEVICES
from posecast.solver.tracking.devices import DEVICES

RNG = np.random.default_rng(7)


def unit_quaternions(n: int) -> NDArray[np.float64]:
    q = RNG.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def poses(n: int) -> NDArray[np.float64]:
    return np.concatenate([RNG.uniform(-2, 2, (n, 3)), unit_quaternions(n)], axis=1)


SIX = ("head", "hip", "left_hand", "right_hand", "left_foot", "right_foot")


def tpose() -> Calibrate:
    return Calibrate(roles=SIX, poses=poses(6), t_capture=10.0, clock_offset=0.5)


def skeleton_info(avatar_id: int = 3) -> AvatarInfo:
    return AvatarInfo(avatar_id=avatar_id, display_name="Ada",
                      joint_names=("root", "spine", "head"), parents=(-1, 0, 1),
                      rest_offsets=np.array([[0, 1, 0], [0, 0.2, 0], [0, 0.3, 0.01]]))


def wire(message: BaseModel) -> dict[str, Any]:
    """The msgpack map a message becomes, to corrupt one field at a time."""
    return msgpack.unpackb(encode(message))


def rejects(data: bytes, *fragments: str, code: str = ErrorCode.INVALID,
            client: bool = True) -> ProtocolError:
    """Decoding ``data`` raises ProtocolError(code) whose message contains every fragment."""
    with pytest.raises(ProtocolError) as info:
        (decode_client if client else decode)(data)
    err = info.value
    assert err.code == code, err
    for fragment in fragments:
        assert fragment in err.message, (fragment, err.message)
    return err


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
        assert (got.avatar_id, got.seq, got.t_capture, got.t_server_receive, got.t_solved,
                got.t_sent) == (sent.avatar_id, sent.seq, sent.t_capture,
                                sent.t_server_receive, sent.t_solved, sent.t_sent)
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
    batch = sample_avatar_batch(3, 5).stamped(42.5)
    assert [f.t_sent for f in batch.frames] == [42.5] * 3
    assert [f.t_sent for f in decode(encode(batch)).frames] == [42.5] * 3  # type: ignore[union-attr]


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
    np.testing.assert_allclose(np.linalg.norm(frame.rotations, axis=1), 1.0, atol=1e-15)


# --------------------------------------------------------------------------- rejections
def test_bytes_that_are_not_msgpack() -> None:
    rejects(b"\xc1", "not a msgpack message", code=ErrorCode.NOT_MSGPACK)
    rejects(b"", "not a msgpack message", code=ErrorCode.NOT_MSGPACK)
    rejects(encode(Ping(t0=1.0))[:-3], "not a msgpack message", code=ErrorCode.NOT_MSGPACK)
    rejects(encode(Ping(t0=1.0)) + b"\x00", "ExtraData", code=ErrorCode.NOT_MSGPACK)
    rejects(b"\x91" * 100_000 + b"\xc0", "not a msgpack", code=ErrorCode.NOT_MSGPACK,
            client=False)  # nesting deeper than msgpack's stack


def test_text_frames_are_rejected() -> None:
    rejects("hello", "text frame", code=ErrorCode.NOT_MSGPACK)  # type: ignore[arg-type]


def test_msgpack_that_is_not_a_message() -> None:
    rejects(msgpack.packb([1, 2, 3]), "got list", code=ErrorCode.MALFORMED)
    rejects(msgpack.packb({"t0": 1.0}), "without 'type'", code=ErrorCode.MALFORMED)
    rejects(msgpack.packb({1: 2}), "int is not allowed for map key",
            code=ErrorCode.NOT_MSGPACK)


def test_unknown_message_type() -> None:
    rejects(msgpack.packb({"type": "teleport", "x": 1}), "'teleport'",
            "expected one of calibrate, hello, leave, ping, tracker_frame",
            code=ErrorCode.UNKNOWN_TYPE)
    rejects(msgpack.packb({"type": 5}), "unknown message type 5", code=ErrorCode.UNKNOWN_TYPE)


def test_server_messages_are_not_client_messages() -> None:
    data = encode(Welcome(protocol_version=PROTOCOL_VERSION, connection_id=1, avatar_id=1,
                          server_time=0.0))
    rejects(data, "unknown message type 'welcome'", code=ErrorCode.UNKNOWN_TYPE)
    assert isinstance(decode(data), Welcome)


def test_huge_frame_is_rejected_before_parsing() -> None:
    data = msgpack.packb({"type": "tracker_frame", "poses": b"\x00" * 10_000})
    err = rejects(data, f"{len(data)} bytes", f"limit is {MAX_CLIENT_MESSAGE_BYTES}",
                  code=ErrorCode.TOO_LARGE)
    assert str(len(data)) in str(err)
    rejects(b"\x00" * 2_000_000, "limit is 1048576", code=ErrorCode.TOO_LARGE, client=False)


def test_unknown_protocol_version() -> None:
    hello = wire(Hello(protocol_version=PROTOCOL_VERSION, role="player", room="r",
                       display_name="a"))
    rejects(msgpack.packb({**hello, "protocol_version": 99}), "hello.protocol_version",
            "version 99 is not supported", f"[{PROTOCOL_VERSION}]",
            code=ErrorCode.UNSUPPORTED_VERSION)
    # a version-1 peer (no tracker sets) is told so, not misread
    rejects(msgpack.packb({**hello, "protocol_version": 1}), "version 1 is not supported",
            code=ErrorCode.UNSUPPORTED_VERSION)
    welcome = wire(Welcome(protocol_version=PROTOCOL_VERSION, connection_id=1, avatar_id=None,
                           server_time=0.0))
    rejects(msgpack.packb({**welcome, "protocol_version": 0}), "welcome.protocol_version",
            code=ErrorCode.UNSUPPORTED_VERSION, client=False)


def test_wrong_types_name_the_field_and_value() -> None:
    frame = wire(sample_tracker_frame())
    rejects(msgpack.packb({**frame, "seq": "12"}), "tracker_frame.seq",
            "valid integer", "'12'")
    rejects(msgpack.packb({**frame, "seq": True}), "tracker_frame.seq", "True")
    rejects(msgpack.packb({**frame, "seq": -1}), "tracker_frame.seq", "-1")
    rejects(msgpack.packb({**frame, "t_capture": "now"}), "tracker_frame.t_capture", "'now'")
    rejects(msgpack.packb({**frame, "roles": "head"}), "tracker_frame.roles", "'head'")
    rejects(msgpack.packb({**frame, "poses": [[0.0] * 7] * 10}), "tracker_frame.poses",
            "expected packed <f8 bytes, got list")
    rejects(msgpack.packb({**frame, "t_capture": msgpack.ExtType(5, b"x")}),
            "tracker_frame.t_capture", "ExtType")
    rejects(msgpack.packb({**frame, "bogus": 1}), "tracker_frame.bogus",
            "Extra inputs are not permitted")
    del frame["seq"]
    rejects(msgpack.packb(frame), "tracker_frame.seq", "Field required")


def test_nan_and_infinity_name_the_device() -> None:
    frame = wire(sample_tracker_frame())
    p = np.frombuffer(frame["poses"], "<f8").reshape(-1, 7).copy()
    p[2, 0] = np.nan
    rejects(msgpack.packb({**frame, "poses": p.tobytes()}), "tracker_frame.poses",
            "row 2 (left_hand) position[0] is nan")
    p = np.frombuffer(frame["poses"], "<f8").reshape(-1, 7).copy()
    p[7, 4] = np.inf
    rejects(msgpack.packb({**frame, "poses": p.tobytes()}), "tracker_frame.poses",
            "row 7 (right_foot) quaternion[1] is inf")
    p = np.frombuffer(frame["poses"], "<f8").reshape(-1, 7).copy()
    p[9, 6] = np.nan
    rejects(msgpack.packb({**frame, "poses": p.tobytes()}), "tracker_frame.poses",
            "row 9 (right_knee) quaternion[3] is nan")
    rejects(msgpack.packb({**frame, "t_capture": float("nan")}), "tracker_frame.t_capture",
            "finite", "nan")
    rejects(msgpack.packb({**frame, "clock_offset": float("-inf")}),
            "tracker_frame.clock_offset", "finite", "-inf")


def test_non_unit_quaternion_names_the_device_and_norm() -> None:
    frame = wire(sample_tracker_frame())
    p = np.frombuffer(frame["poses"], "<f8").reshape(-1, 7).copy()
    p[3, 3:] *= 1.01
    rejects(msgpack.packb({**frame, "poses": p.tobytes()}), "tracker_frame.poses",
            "row 3 (right_hand) quaternion", "norm 1.01", "within 0.001")
    p[3, 3:] = 0.0
    rejects(msgpack.packb({**frame, "poses": p.tobytes()}), "row 3 (right_hand)", "norm 0")


_POSE_VALUES = st.one_of(st.floats(-2.0, 2.0), st.sampled_from(
    [0.0, 1.0, -1.0, 0.5, 1.0005, 0.9995, 999.9, 1000.1, -1e300, float("nan"),
     float("inf")]))


@settings(max_examples=400, deadline=None)
@given(st.lists(st.lists(_POSE_VALUES, min_size=7, max_size=7), min_size=1, max_size=10),
       st.booleans())
def test_device_poses_follow_their_definition(rows: list[list[float]], unit: bool) -> None:
    """Accepted exactly when every position is within MAX_POSITION_M and every quaternion
    within QUAT_NORM_TOLERANCE of unit norm (as squared norms, 2x the tolerance); the
    result has every quaternion normalised, bit for bit the input when all are unit."""
    poses = np.array(rows, dtype=np.float64)
    with np.errstate(all="ignore"):
        if unit:  # mostly valid rows, some already unit to the last bit
            q = poses[:, 3:] + 0.1
            poses[:, 3:] = q / np.linalg.norm(q, axis=1, keepdims=True)
        p2 = (poses[:, :3] ** 2).sum(axis=1)
        q2 = (poses[:, 3:] ** 2).sum(axis=1)
        valid = bool(np.all(p2 <= MAX_POSITION_M**2)
                     and np.all(np.abs(q2 - 1.0) <= 2 * QUAT_NORM_TOLERANCE))
    if not valid:
        with pytest.raises(ValueError):
            device_poses(poses)
        return
    out = device_poses(poses)
    np.testing.assert_array_equal(out[:, :3], poses[:, :3])
    np.testing.assert_allclose(np.linalg.norm(out[:, 3:], axis=1), 1.0, atol=1e-15)
    np.testing.assert_allclose(out[:, 3:], poses[:, 3:] / np.sqrt(q2)[:, None], atol=1e-15)
    if np.abs(q2 - 1.0).max() <= 1e-12:
        np.testing.assert_array_equal(out, poses)


def test_positions_beyond_the_limit() -> None:
    frame = wire(sample_tracker_frame())
    p = np.frombuffer(frame["poses"], "<f8").reshape(-1, 7).copy()
    p[0, :3] = [1e300, 0, 0]
    rejects(msgpack.packb({**frame, "poses": p.tobytes()}), "tracker_frame.poses",
            "row 0 (head) position", "1e+300 m from the origin", "limit is 1000 m")


def test_device_roles_are_checked() -> None:
    frame = wire(sample_tracker_frame(("head", "hip")))
    rejects(msgpack.packb({**frame, "roles": ["head", "tail"]}), "tracker_frame.roles[1]",
            "'tail'", "'left_forearm'")
    rejects(msgpack.packb({**frame, "roles": ["hip", "hip"]}), "tracker_frame.roles",
            "'hip' appears twice")
    rejects(msgpack.packb({**frame, "roles": ["hip"]}), "tracker_frame.poses",
            "2 pose rows for 1 roles")
    rejects(msgpack.packb({**frame, "roles": [], "poses": b""}), "tracker_frame.roles",
            "at least 1")
    rejects(msgpack.packb({**frame, "roles": [*DEVICE_ROLES, "head"]}),
            "tracker_frame.roles", "at most 11")
    rejects(msgpack.packb({**frame, "poses": frame["poses"][:-8]}), "tracker_frame.poses",
            "104 bytes is not a whole number of rows of 7 x <f8 (56 bytes)")


def test_calibration_needs_head_and_hands_and_takes_any_more() -> None:
    message = wire(tpose())
    p = np.frombuffer(message["poses"], "<f8").reshape(6, 7)
    rejects(msgpack.packb({**message, "roles": ["head", "hip", "right_hand"],
                           "poses": p[[0, 1, 3]].tobytes()}),
            "calibrate", "missing left_hand")
    three = decode_client(msgpack.packb({**message, "roles": list(CALIBRATION_ROLES),
                                         "poses": p[[0, 2, 3]].tobytes()}))
    assert isinstance(three, Calibrate) and three.roles == CALIBRATION_ROLES


def test_hello_fields_are_checked() -> None:
    hello = wire(Hello(protocol_version=PROTOCOL_VERSION, role="spectator", room="r",
                       display_name="a"))
    rejects(msgpack.packb({**hello, "role": "god"}), "hello.role", "'god'")
    rejects(msgpack.packb({**hello, "room": "my room"}), "hello.room", "'my room'")
    rejects(msgpack.packb({**hello, "display_name": "x" * 65}), "hello.display_name",
            "at most 64")
    rejects(msgpack.packb({**hello, "display_name": "a\x07b"}), "hello.display_name",
            "control characters")
    rejects(msgpack.packb({**hello, "max_rate_hz": 0.0}), "hello.max_rate_hz", "greater than 0")
    rejects(msgpack.packb({**hello, "role": "player", "max_rate_hz": 1e4}),
            "hello.max_rate_hz", "less than or equal to 1000")
    rejects(msgpack.packb({**hello, "token": "t" * 1100}), "hello.token", "at most 1024")


def test_skeleton_checks() -> None:
    info = wire(AvatarRoster(avatars=(skeleton_info(),)))
    avatar = info["avatars"][0]

    def roster(**change: Any) -> bytes:
        return msgpack.packb({**info, "avatars": [{**avatar, **change}]})

    rejects(roster(parents=[-1, 0, 2]), "avatar_roster.avatars[0]", "parents[2] is 2",
            client=False)
    rejects(roster(parents=[0, 0, 1]), "parents[0] is 0", "root", client=False)
    rejects(roster(parents=[-1, 0]), "3 joint_names but 2 parents", client=False)
    rejects(roster(joint_names=["a", "b", "a"]), "joint_names: 'a' appears twice", client=False)
    rejects(roster(rest_offsets=np.full((3, 3), np.nan).tobytes()),
            "avatar_roster.avatars[0].rest_offsets", "row 0 (root) position[0] is nan",
            client=False)
    too_many = [f"j{i}" for i in range(MAX_JOINTS + 1)]
    rejects(roster(joint_names=too_many), "avatar_roster.avatars[0].joint_names",
            "at most 256", client=False)
    rejects(msgpack.packb({**info, "removed": [3]}), "avatar_id 3 appears more than once",
            client=False)


def test_avatar_batch_checks_name_the_column_and_avatar() -> None:
    batch = wire(sample_avatar_batch(3, 4))

    def changed(**change: Any) -> bytes:
        return msgpack.packb({**batch, **change})

    rotations = bytearray(batch["rotations"])
    spare = bytearray(rotations)
    spare[5 * 9 + 4] |= 0x40  # bit 38 of row 9: avatar 2, joint 1
    rejects(changed(rotations=bytes(spare)), "avatar_batch.rotations",
            "avatar 2 (joint 1): unused bits 38-39", client=False)
    big = bytearray(rotations)
    big[0:5] = bytes(5)  # three components at -1/sqrt(2): squares sum to 1.5
    rejects(changed(rotations=bytes(big)), "avatar_batch.rotations", "avatar 0 (joint 0)",
            "1.5000 > 0.75", client=False)
    rejects(changed(rotations=bytes(rotations[:-3])), "avatar_batch.rotations",
            "57 bytes is not a multiple of 5", client=False)
    rejects(changed(rotations=bytes(rotations[:-5])), "avatar_batch.rotations",
            "11 rotations for joint_counts summing to 12", client=False)
    rejects(changed(joint_counts=np.array([4, 0, 8], "<u2").tobytes()),
            "avatar_batch.joint_counts", "avatar 1 has 0 joints", client=False)
    rejects(changed(joint_counts=np.array([4, 4], "<u2").tobytes()),
            "avatar_batch.joint_counts", "2 rows for 3 avatar_ids", client=False)
    nan_root = np.array([[0, 0, 0], [np.nan, 0, 0], [0, 0, 0]], "<f4").tobytes()
    rejects(changed(roots=nan_root), "avatar_batch.roots", "row 1 position[0] is nan",
            client=False)
    rejects(changed(avatar_ids=np.array([0, 1, 0], "<i8").tobytes()), "avatar_batch.avatar_ids",
            "avatar_id 0 appears more than once", client=False)
    rejects(changed(seqs=np.array([1, -2, 3], "<i8").tobytes()), "avatar_batch.seqs",
            "row 1 is -2; must be >= 0", client=False)
    rejects(changed(t_solved=np.array([1.0, 2.0, np.inf]).tobytes()), "avatar_batch.t_solved",
            "row 2 is inf", client=False)
    rejects(changed(t_capture=[1.0, 2.0, 3.0]), "avatar_batch.t_capture",
            "expected packed <f8 bytes, got list", client=False)
    rejects(changed(avatar_ids=b"\x00" * 7), "avatar_batch.avatar_ids",
            "7 bytes is not a whole number of <i8", client=False)
    too_many = np.arange(MAX_AVATARS + 1, dtype="<i8").tobytes()
    rejects(changed(avatar_ids=too_many), "avatar_batch.avatar_ids",
            f"{MAX_AVATARS + 1} avatars; at most {MAX_AVATARS}", client=False)


# a value to write into one row of a packed column, by the column's dtype: the edges of
# every check (negative, zero, the joint limit, NaN, infinities, the position limit)
_SPECIAL = {"<i8": [-1, 0, 2**63 - 1], "<u2": [0, 1, MAX_JOINTS, MAX_JOINTS + 1, 65535],
            "<f8": [math.nan, math.inf, -math.inf, 1e308, 0.0],
            "<f4": [math.nan, math.inf, 999.0, 1001.0, -600.0]}
_DTYPES = {"avatar_ids": "<i8", "seqs": "<i8", "joint_counts": "<u2", "roots": "<f4",
           "t_capture": "<f8", "t_server_receive": "<f8", "t_solved": "<f8"}


@st.composite
def corrupted_batches(draw: st.DrawFn) -> dict[str, Any]:
    """The wire map of a valid batch, left alone or corrupted in one of many ways."""
    obj = wire(sample_avatar_batch(draw(st.integers(0, 4)), draw(st.integers(1, 6)),
                                   seed=draw(st.integers(0, 3))))
    kind = draw(st.sampled_from(["none", "value", "bytes", "length", "type", "keys",
                                 "duplicate", "t_sent"]))
    column = draw(st.sampled_from(sorted(_DTYPES)))
    n = len(obj["avatar_ids"]) // 8
    if kind == "value" and n:
        array = np.frombuffer(obj[column], _DTYPES[column]).copy()
        array.reshape(n, -1)[draw(st.integers(0, n - 1)), 0] = draw(
            st.sampled_from(_SPECIAL[_DTYPES[column]]))
        obj[column] = array.tobytes()
    elif kind == "bytes":  # random bytes of the right length, also in the rotations
        name = draw(st.sampled_from([column, "rotations"]))
        obj[name] = draw(st.binary(min_size=len(obj[name]), max_size=len(obj[name])))
    elif kind == "length":
        name = draw(st.sampled_from([column, "rotations"]))
        obj[name] = obj[name][:draw(st.integers(0, max(len(obj[name]) - 1, 0)))]
    elif kind == "type":
        obj[column] = draw(st.sampled_from([list(obj[column]), 7, "x", None]))
    elif kind == "keys":
        if draw(st.booleans()):
            del obj[column]
        else:
            obj["extra"] = 1
    elif kind == "duplicate" and n > 1:
        ids = np.frombuffer(obj["avatar_ids"], "<i8").copy()
        ids[-1] = ids[0]
        obj["avatar_ids"] = ids.tobytes()
    elif kind == "t_sent":
        obj["t_sent"] = draw(st.sampled_from([math.nan, math.inf, 3, "1.0", True, -2.5]))
    return obj


def _check_agree(obj: dict[str, Any]) -> AvatarBatch | None:
    """The whole-batch check accepts only what field validation accepts, equal."""
    fast = avatar_batch_from_wire(dict(obj))
    try:
        slow: AvatarBatch | None = AvatarBatch.model_validate(obj, context={"wire": True})
    except ValidationError:
        slow = None
    if fast is not None:
        assert slow is not None and fast == slow
        for array in (fast.avatar_ids, fast.roots, fast.rotations, fast.t_solved):
            assert not array.flags.writeable
    elif slow is not None:  # the fast path may only pass over unusual but valid input
        assert type(obj["t_sent"]) is not float
    return fast


@settings(max_examples=400, deadline=None)
@given(corrupted_batches())
def test_whole_batch_check_accepts_only_what_validation_accepts(obj: dict[str, Any]) -> None:
    _check_agree(obj)


@pytest.mark.parametrize("column", sorted(_DTYPES))
def test_whole_batch_check_at_every_edge(column: str) -> None:
    assert _check_agree(wire(sample_avatar_batch(3, 4))) is not None
    for value in _SPECIAL[_DTYPES[column]]:
        for row, col in ((0, 0), (2, -1)):
            obj = wire(sample_avatar_batch(3, 4))
            array = np.frombuffer(obj[column], _DTYPES[column]).copy().reshape(3, -1)
            array[row, col] = value
            obj[column] = array.tobytes()
            _check_agree(obj)


def test_pong_times_must_be_ordered() -> None:
    pong = wire(Pong(t0=1.0, t1=2.0, t2=2.5))
    rejects(msgpack.packb({**pong, "t2": 1.5}), "pong", "t2 1.5 is before t1 2.0",
            client=False)


def test_error_message_round_trips_a_protocol_error() -> None:
    with pytest.raises(ProtocolError) as info:
        decode_client(b"\xc1")
    reply = Error(code=info.value.code, message=info.value.message)
    back = decode(encode(reply))
    assert isinstance(back, Error)
    assert back.code == "not_msgpack" and "not a msgpack message" in back.message


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


@st.composite
def corrupted_tracker_frames(draw: st.DrawFn) -> dict[str, Any]:
    """The wire map of a valid tracker frame, left alone or corrupted in one of many ways."""
    roles = tuple(draw(st.permutations(DEVICE_ROLES))[:draw(st.integers(1, len(DEVICE_ROLES)))])
    obj = wire(sample_tracker_frame(roles, seed=draw(st.integers(0, 3))))
    kind = draw(st.sampled_from(["none", "pose", "bytes", "length", "roles", "duplicate",
                                 "type", "keys", "seq", "time"]))
    n = len(roles)
    if kind == "pose":
        poses = np.frombuffer(obj["poses"], "<f8").copy().reshape(n, 7)
        poses[draw(st.integers(0, n - 1)), draw(st.integers(0, 6))] = draw(
            st.sampled_from(_POSE_SPECIAL))
        obj["poses"] = poses.tobytes()
    elif kind == "duplicate" and n > 1:  # a role twice, the pose rows still matching
        i, j = draw(st.lists(st.integers(0, n - 1), min_size=2, max_size=2, unique=True))
        obj["roles"][i] = obj["roles"][j]
    elif kind == "bytes":
        obj["poses"] = draw(st.binary(min_size=56 * n, max_size=56 * n))
    elif kind == "length":
        obj["poses"] = obj["poses"][:draw(st.integers(0, 56 * n - 1))]
    elif kind == "roles":  # one role replaced (the pose rows still match), or odd lists
        changed = list(obj["roles"])
        changed[draw(st.integers(0, n - 1))] = draw(st.sampled_from(
            [*DEVICE_ROLES, "tail", "", 1, None, ["head"], b"hip"]))
        obj["roles"] = draw(st.sampled_from([
            changed, [], [*obj["roles"], "hip"], "head", [*DEVICE_ROLES, "head"],
            list(reversed(obj["roles"]))]))
    elif kind == "type":
        obj[draw(st.sampled_from(["roles", "poses", "seq", "t_capture", "clock_offset",
                                  "type"]))] = draw(st.sampled_from(
                                      [None, 7, 7.5, "x", True, [1.0], b"\x00" * 56]))
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
    poses = np.frombuffer(obj["poses"], "<f8").copy().reshape(-1, 7)
    poses[2, 3:] *= 1.0 + 0.4 * QUAT_NORM_TOLERANCE  # off unit within tolerance: normalised
    obj["poses"] = poses.tobytes()
    assert _tracker_check_agrees(obj)
    assert np.allclose(np.linalg.norm(tracker_poses_from_wire(obj).poses[:, 3:], axis=1), 1.0)
    poses[2, 0] = math.nan
    bad = msgpack.packb({**obj, "poses": poses.tobytes()})
    assert decode_tracker_poses(bad) is None
    rejects(bad, "tracker_frame.poses", "row 2 (left_hand) position[0] is nan")
    for other in (b"\xc1", msgpack.packb([1, 2]), encode(Ping(t0=1.0)),
                  b"\x00" * (MAX_CLIENT_MESSAGE_BYTES + 1)):
        assert decode_tracker_poses(other) is None
