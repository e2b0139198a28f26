"""The protocol's refusals: every malformed or out-of-bounds message raises a
ProtocolError naming what was wrong (split from test_protocol.py)."""


from __future__ import annotations

import math
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from protocol_cases import poses_wire, rejects, skeleton_info, tpose, wire, wire_poses
from pydantic import ValidationError

from posecast.protocol import (
    CALIBRATION_ROLES,
    DEVICE_ROLES,
    MAX_CLIENT_MESSAGE_BYTES,
    MAX_JOINTS,
    PROTOCOL_VERSION,
    AvatarBatch,
    AvatarRoster,
    Calibrate,
    Error,
    ErrorCode,
    Hello,
    Ping,
    Pong,
    ProtocolError,
    TrackerFrame,
    Welcome,
    decode,
    decode_client,
    encode,
)
from posecast.protocol.batch import avatar_batch_from_wire
from posecast.protocol.codec import encode as encode_with
from posecast.protocol.measure import sample_avatar_batch, sample_tracker_frame
from posecast.protocol.model import construct_whole
from posecast.protocol.pose_coding import Codings, PoseCoding, RosterCodings
from posecast.protocol.validation import (
    MAX_AVATARS,
    MAX_POSITION_M,
    QUAT_NORM_TOLERANCE,
    device_poses,
)
from posecast.server.avatars import rig_coding
from posecast.solver.readers.gltf import load_makehuman
from posecast.solver.rig import build_rig


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
    rejects(msgpack.packb({**frame, "roles": "head"}), "tracker_frame.roles",
            "expected a list of device indices, got str")
    # protocol 2's role names are refused naming the index wanted
    rejects(msgpack.packb({**frame, "roles": ["head", *frame["roles"][1:]]}),
            "tracker_frame.roles", "roles[0]: 'head' is not a device index (0 to 10: head")
    rejects(msgpack.packb({**frame, "roles": [11, *frame["roles"][1:]]}),
            "tracker_frame.roles", "roles[0]: 11 is not a device index")
    rejects(msgpack.packb({**frame, "poses": [[0.0] * 7] * 10}), "tracker_frame.poses",
            "expected packed poses (3 x <f4, 4 x <i2 each), got list")
    # protocol 3's float32 rows (28 bytes each): 14 rows of 20 for the 10 roles
    f4 = np.zeros((10, 7), "<f4").tobytes()
    rejects(msgpack.packb({**frame, "poses": f4}), "tracker_frame.poses",
            "14 pose rows for 10 roles")
    rejects(msgpack.packb({**frame, "t_capture": msgpack.ExtType(5, b"x")}),
            "tracker_frame.t_capture", "ExtType")
    rejects(msgpack.packb({**frame, "bogus": 1}), "tracker_frame.bogus",
            "Extra inputs are not permitted")
    del frame["seq"]
    rejects(msgpack.packb(frame), "tracker_frame.seq", "Field required")


def test_nan_and_infinity_name_the_device() -> None:
    frame = wire(sample_tracker_frame())
    p = wire_poses(frame["poses"])
    p[2, 0] = np.nan
    rejects(msgpack.packb({**frame, "poses": poses_wire(p)}), "tracker_frame.poses",
            "row 2 (left_hand) position[0] is nan")
    p = wire_poses(frame["poses"])
    p[5, 1] = -np.inf
    rejects(msgpack.packb({**frame, "poses": poses_wire(p)}), "tracker_frame.poses",
            "row 5 (right_forearm) position[1] is -inf")
    # quaternions travel as int16 levels: only a player's own arrays can hold NaN there
    poses = sample_tracker_frame().poses.copy()
    for row, col, value in ((7, 4, np.inf), (9, 6, np.nan)):
        bad = poses.copy()
        bad[row, col] = value
        with pytest.raises(ValidationError, match=rf"row {row} \(\w+\) quaternion\["
                                                  rf"{col - 3}\] is {value}"):
            TrackerFrame(seq=1, roles=sample_tracker_frame().roles, poses=bad,
                         t_capture=1.0, clock_offset=0.0)
    rejects(msgpack.packb({**frame, "t_capture": float("nan")}), "tracker_frame.t_capture",
            "finite", "nan")
    rejects(msgpack.packb({**frame, "clock_offset": float("-inf")}),
            "tracker_frame.clock_offset", "finite", "-inf")


def test_non_unit_quaternion_names_the_device_and_norm() -> None:
    frame = wire(sample_tracker_frame())
    p = wire_poses(frame["poses"])
    p[3, 3:] *= 1.01
    rejects(msgpack.packb({**frame, "poses": poses_wire(p)}), "tracker_frame.poses",
            "row 3 (right_hand) quaternion", "norm 1.01", "within 0.001")
    p[3, 3:] = 0.0
    rejects(msgpack.packb({**frame, "poses": poses_wire(p)}), "row 3 (right_hand)",
            "norm 0")


_POSE_VALUES = st.one_of(st.floats(-2.0, 2.0), st.sampled_from(
    [0.0, 1.0, -1.0, 0.5, 1.0005, 0.9995, 999.9, 1000.1, -1e300, float("nan"),
     float("inf")]))


@settings(max_examples=400, deadline=None)
@given(st.lists(st.lists(_POSE_VALUES, min_size=7, max_size=7), min_size=1, max_size=10),
       st.booleans())
def test_device_poses_follow_their_definition(rows: list[list[float]], unit: bool) -> None:
    """Accepted exactly when every position is within MAX_POSITION_M and every quaternion
    within QUAT_NORM_TOLERANCE of unit norm (as squared norms, 2x the tolerance); the
    result is what travels: float32 positions, quaternions normalised (unless all are
    within int16 rounding of unit) and rounded to levels k / 32767."""
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
    # every value as it travels (protocol 4): float32 positions, int16 quaternion levels
    np.testing.assert_array_equal(out[:, :3], poses[:, :3].astype(np.float32))
    levels = out[:, 3:] * 32767.0
    np.testing.assert_allclose(levels, np.rint(levels), rtol=0, atol=1e-9)
    if np.abs(q2 - 1.0).max() > 1e-4:  # normalised, then rounded
        np.testing.assert_allclose(out[:, 3:], poses[:, 3:] / np.sqrt(q2)[:, None],
                                   rtol=0, atol=0.5 / 32767 + 1e-12)
    else:  # within int16's own rounding of unit: rounded as it is
        np.testing.assert_allclose(out[:, 3:], poses[:, 3:], rtol=0,
                                   atol=0.5 / 32767 + 1e-12)
    np.testing.assert_allclose(np.linalg.norm(out[:, 3:], axis=1), 1.0, atol=1e-4)
    # and what travels comes back as it went: decode(encode(m)) == m
    np.testing.assert_array_equal(device_poses(out), out)


def test_positions_beyond_the_limit() -> None:
    frame = wire(sample_tracker_frame())
    p = wire_poses(frame["poses"])
    p[0, :3] = [1e30, 0, 0]  # a float32 can hold it; the limit cannot
    rejects(msgpack.packb({**frame, "poses": poses_wire(p)}), "tracker_frame.poses",
            "row 0 (head) position", "1e+30 m from the origin", "limit is 1000 m")


def test_device_roles_are_checked() -> None:
    frame = wire(sample_tracker_frame(("head", "hip")))
    assert frame["roles"] == [0, 1]  # indices into DEVICE_ROLES on the wire
    rejects(msgpack.packb({**frame, "roles": [0, "tail"]}), "tracker_frame.roles",
            "roles[1]: 'tail' is not a device index", "left_forearm")
    rejects(msgpack.packb({**frame, "roles": [1, 1]}), "tracker_frame.roles",
            "'hip' appears twice")
    rejects(msgpack.packb({**frame, "roles": [1]}), "tracker_frame.poses",
            "2 pose rows for 1 roles")
    rejects(msgpack.packb({**frame, "roles": [], "poses": b""}), "tracker_frame.roles",
            "at least 1")
    rejects(msgpack.packb({**frame, "roles": [*range(len(DEVICE_ROLES)), 0]}),
            "tracker_frame.roles", "at most 11")
    rejects(msgpack.packb({**frame, "poses": frame["poses"][:-4]}), "tracker_frame.poses",
            "36 bytes is not a whole number of poses (20 bytes each: 3 x <f4, 4 x <i2)")


def test_calibration_needs_head_and_hands_and_takes_any_more() -> None:
    message = wire(tpose())
    p = wire_poses(message["poses"])
    index = {r: i for i, r in enumerate(DEVICE_ROLES)}
    rejects(msgpack.packb({**message, "roles": [index[r] for r in ("head", "hip",
                                                                    "right_hand")],
                           "poses": poses_wire(p[[0, 1, 3]])}),
            "calibrate", "missing left_hand")
    three = decode_client(msgpack.packb({**message, "roles": [index[r] for r in
                                                              CALIBRATION_ROLES],
                                         "poses": poses_wire(p[[0, 2, 3]])}))
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
            "57 bytes of rotations; the avatars' joint counts and codings need 60",
            client=False)
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
    rejects(changed(solved_age=np.array([1.0, 2.0, np.inf], "<f4").tobytes()), "avatar_batch",
            "solved_age: row 2 is inf", client=False)
    rejects(changed(capture_age=[1.0, 2.0, 3.0]), "avatar_batch",
            "capture_age: expected packed <f4 bytes, got list", client=False)
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
           "capture_age": "<f4", "receive_age": "<f4", "solved_age": "<f4", "lost": "<u2"}


@st.composite
def corrupted_batches(draw: st.DrawFn, coding: PoseCoding | None = None) -> dict[str, Any]:
    """The wire map of a valid batch (every avatar packed by ``coding`` if given), left
    alone or corrupted in one of many ways."""
    # 70: past 64 avatars, where the compiled check finds a duplicate id by sorting
    n = draw(st.sampled_from([0, 1, 2, 3, 4, 70]))
    joints = coding.num_joints if coding is not None else draw(st.integers(1, 6))
    batch = sample_avatar_batch(n, joints, seed=draw(st.integers(0, 3)))
    obj = msgpack.unpackb(encode_with(batch, {i: coding for i in range(n)}))
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


def _check_agree(obj: dict[str, Any], codings: Codings | None = None) -> AvatarBatch | None:
    """The whole-batch check accepts only what field validation accepts, equal."""
    fast = avatar_batch_from_wire(dict(obj), codings)
    try:
        slow: AvatarBatch | None = AvatarBatch.model_validate(
            obj, context={"wire": True, "codings": codings})
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


_MAKEHUMAN = rig_coding(build_rig(load_makehuman().skeleton))


@settings(max_examples=200, deadline=None)
@given(corrupted_batches(_MAKEHUMAN), st.booleans(), st.booleans())
def test_whole_batch_check_agrees_on_coded_batches(obj: dict[str, Any], every: bool,
                                                   stream: bool) -> None:
    """Protocol 4's avatars, packed by their rosters' codings: the two checks still
    agree, also where an avatar's roster has no coding or a different joint count, and
    with a stream's RosterCodings (its one-call path for a room of one kind)."""
    n = len(obj["avatar_ids"]) // 8 if isinstance(obj.get("avatar_ids"), bytes) else 0
    codings: dict[int, PoseCoding | None] = RosterCodings() if stream else {}
    codings.update({i: _MAKEHUMAN for i in range(n)})
    if not every and n:
        codings[n - 1] = None
    _check_agree(obj, codings)


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




def test_a_decoded_batch_is_the_model_whole() -> None:
    """The decoder builds its AvatarBatch without pydantic's per-field walk: the model
    it gives is the validated one in every respect a caller sees, and values that are
    not exactly the fields take pydantic's way."""
    obj = wire(sample_avatar_batch(3, 4))
    fast = avatar_batch_from_wire(dict(obj))
    slow = AvatarBatch.model_validate(obj, context={"wire": True})
    assert fast is not None and fast == slow
    assert fast.model_fields_set == slow.model_fields_set
    assert fast.model_dump().keys() == slow.model_dump().keys()
    assert encode(fast) == encode(slow)
    values = dict(fast.__dict__)
    del values["lost"]
    partial = construct_whole(AvatarBatch, values)  # lost defaults, as model_construct
    assert partial.lost is None and partial.model_fields_set == set(values)
