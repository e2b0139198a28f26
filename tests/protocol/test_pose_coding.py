"""Protocol 4's joint coding (protocol/pose_coding.py): the bound it states, held on
random poses within the limits and on real solves, and what it refuses."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from posecast.protocol import AvatarBatch, AvatarInfo, AvatarRoster, ProtocolError, encode
from posecast.protocol.codec import SHARED_BATCHES_KEPT, decode_stream
from posecast.protocol.pose_coding import (
    QUATERNION_BITS,
    PoseCoding,
    RosterCodings,
    _cos_sinc,
    coding_bits,
)
from posecast.protocol.quantize import MAX_ANGLE_ERROR_DEG, MAX_ANGLE_ERROR_RAD, rotation_angle
from posecast.server.avatars import AvatarSolver, rig_coding
from posecast.solver import rotations as R
from posecast.solver.motion import ViveRecording
from posecast.solver.readers.gltf import load_makehuman
from posecast.solver.rig import Rig, build_rig


@pytest.fixture(scope="module")
def rig() -> Rig:
    return build_rig(load_makehuman().skeleton)


def _coding(rig: Rig) -> PoseCoding:
    return rig_coding(rig)


def _within_limits(rig: Rig, coding: PoseCoding, rng: np.random.Generator, n: int,
                   at_limits: bool = False) -> np.ndarray:
    """(n, J, 4) poses: each driven joint at random parameters within its limits (at
    the corners of the limit box if asked), the others at rest."""
    poses = np.broadcast_to(coding.rest, (n, coding.num_joints, 4)).copy()
    for j in coding.driven:
        lo, hi = rig.lo[j], rig.hi[j]
        u = rng.integers(0, 2, (n, 3)) if at_limits else rng.random((n, 3))
        p = lo + u * (hi - lo)
        swing = R.from_rotvec(np.stack([p[:, 0], np.zeros(n), p[:, 2]], -1))
        twist = R.from_rotvec(np.stack([np.zeros(n), p[:, 1], np.zeros(n)], -1))
        poses[:, j] = R.mul(R.mul(rig.pre[j], R.mul(swing, twist)), rig.post[j])
    return poses


def test_makehuman_frames_carry_twenty_joints_in_71_bytes(rig: Rig) -> None:
    coding = _coding(rig)
    names = [rig.skeleton.names[j] for j in coding.driven]
    assert len(names) == 20 and "pelvis" in names and not any("ball" in n for n in names)
    quaternions = [n for n, b in zip(names, coding.bits, strict=True) if b == (0, 0, 0)]
    # the pelvis turns freely, an upper arm's swing reaches past pi: quaternions
    assert sorted(quaternions) == ["pelvis", "upperarm_l", "upperarm_r"]
    assert coding.nbytes == 71  # against 53 x 5 = 265 before


def test_the_bound_holds_within_the_limits_and_at_their_corners(rig: Rig) -> None:
    coding = _coding(rig)
    rng = np.random.default_rng(7)
    for corners in (False, True):
        poses = _within_limits(rig, coding, rng, 4000, at_limits=corners)
        back = coding.unpack(coding.pack(poses))
        err = rotation_angle(poses, back)
        assert err.max() <= MAX_ANGLE_ERROR_RAD * (1 + 1e-9)
        # unit, though the frames are float32 values (a non-unit one read as an angle
        # through acos of a dot product looked 0.05 deg off)
        assert np.abs(np.linalg.norm(back, axis=-1) - 1.0).max() < 1e-12
        # and the coding is not loose: it uses most of what the bound allows
        assert err.max() > 0.3 * MAX_ANGLE_ERROR_RAD
        undriven = np.setdiff1d(np.arange(coding.num_joints), coding.driven)
        rest = np.broadcast_to(coding.rest[undriven], back[:, undriven].shape)
        np.testing.assert_array_equal(back[:, undriven], rest)


@settings(max_examples=300, deadline=None)
@given(lo=st.floats(-2.5, 0.0), width=st.floats(1e-3, 2.5), twist=st.booleans(),
       z=st.booleans())
def test_chosen_bits_keep_any_joint_within_the_bound(lo: float, width: float, twist: bool,
                                                     z: bool) -> None:
    low = np.array([lo, -width / 2 if twist else 0.0, lo / 2 if z else 0.0])
    high = np.array([lo + width, width / 2 if twist else 0.0, (lo / 2 + 0.4) if z else 0.0])
    bits = coding_bits(low, high)
    if bits == (0, 0, 0):  # a quaternion: only where the swing reaches pi
        assert math.hypot(max(abs(low[0]), abs(high[0])), max(abs(low[2]), abs(high[2]))) \
            >= math.pi
        return
    steps = [(high[i] - low[i]) / ((1 << b) - 1) if b else 0.0 for i, b in enumerate(bits)]
    bound = 0.5 * (math.hypot(steps[0], steps[2]) + steps[1])
    assert bound <= MAX_ANGLE_ERROR_RAD * (1 + 1e-12)
    assert sum(bits) < QUATERNION_BITS


def test_real_solves_decode_within_the_bound_and_undriven_joints_never_move(
        rig: Rig, recording: ViveRecording) -> None:
    """The walking clip through the server's solver: what spectators rebuild is within
    0.0686 degree of what it solved, and the joints a frame leaves out are the ones it
    was calibrated with (the roster's rest)."""
    solver = AvatarSolver(rig)
    solver.calibrate(1, recording.devices, recording.positions[0], recording.rotations[0])
    coding = solver.coding(1)
    solved = []
    for f in range(1, recording.positions.shape[0], 3):
        poses = np.concatenate([recording.positions[f], recording.rotations[f]], -1)
        solved.append(solver.solve([(1, recording.devices, poses)], f / 90).rotations[0])
    rotations = np.array(solved)
    back = coding.unpack(coding.pack(rotations))
    err = np.degrees(rotation_angle(rotations, back))
    assert err.max() <= MAX_ANGLE_ERROR_DEG * (1 + 1e-9)
    undriven = np.setdiff1d(np.arange(coding.num_joints), coding.driven)
    np.testing.assert_allclose(rotations[:, undriven],
                               np.broadcast_to(solver.calibrations[1].pose[undriven],
                                               rotations[:, undriven].shape), atol=1e-12)
    # and as the roster carries them: within the quaternion's bound
    rest_err = rotation_angle(coding.rest, solver.calibrations[1].pose)
    assert rest_err.max() <= MAX_ANGLE_ERROR_RAD * (1 + 1e-9)


def test_bits_no_encoder_writes_are_refused_with_the_frame(rig: Rig) -> None:
    coding = _coding(rig)
    data = bytearray(coding.pack(coding.rest[None]))
    data[-1] |= 0x80  # past the last joint's 566 bits
    with pytest.raises(ValueError, match="frame 0: padding bits"):
        coding.unpack(bytes(data))
    data = bytearray(coding.pack(coding.rest[None]))
    data[0:5] = bytes([0xFF, 0xFF, 0xFF, 0xFF, 0x0F])  # the pelvis: all three at +max
    with pytest.raises(ValueError, match=r"frame 0 \(joint 1\): .* unit quaternion"):
        coding.unpack(bytes(data))
    with pytest.raises(ValueError, match="not a whole number of frames"):
        coding.unpack(bytes(70))


@pytest.mark.parametrize(("change", "words"), [
    ({"driven": (3, 2)}, "ascending"),
    ({"bits": ((0, 0, 0),)}, "row per driven"),
    ({"bits": ((17, 0, 0),) * 20}, "1 to 16 bits"),
])
def test_inconsistent_codings_are_refused(rig: Rig, change: dict[str, object],
                                          words: str) -> None:
    fields = {**rig_coding(rig).model_dump(), **change}
    with pytest.raises(ValueError, match=words):
        PoseCoding.model_validate(fields, context={"wire": True})


def test_a_roster_carries_the_coding_and_a_stream_unpacks_what_follows(rig: Rig) -> None:
    """A viewer's way: the roster (its coding exactly as sent), then batches unpacked
    with what it learnt; a removed avatar's frames no longer decode as coded."""
    sk = rig.skeleton
    coding = rig_coding(rig)
    info = AvatarInfo(avatar_id=4, display_name="p", joint_names=sk.names,
                      parents=tuple(int(p) for p in sk.parents), rest_offsets=sk.offsets,
                      coding=coding)
    roster = AvatarRoster(avatars=(info,))
    codings = RosterCodings()
    back = decode_stream(encode(roster), codings)
    assert back == roster and codings == {4: coding}
    assert len(encode(roster)) < 4096  # a replay uploads a roster per avatar
    poses = _within_limits(rig, coding, np.random.default_rng(3), 2)
    batch = AvatarBatch.from_arrays([4], [9], np.zeros((1, 3)), poses[:1], [1.0], [1.0],
                                    1.0, 1.001)
    data = encode(batch, codings)
    assert len(data) < len(encode(batch)) - 180  # 71 bytes of rotations, not 265
    got = decode_stream(data, codings)
    assert isinstance(got, AvatarBatch)
    assert rotation_angle(got.rotations, poses[0]).max() <= MAX_ANGLE_ERROR_RAD * (1 + 1e-6)
    decode_stream(encode(AvatarRoster(removed=(4,))), codings)
    with pytest.raises(ProtocolError, match="bytes of rotations; the avatars' joint counts "
                                            "and codings need 265"):
        decode_stream(data, codings)


def test_streams_with_the_same_codings_share_a_batch_decoded_once(rig: Rig) -> None:
    """Spectators of one room in one process get the same bytes of each batch: the
    second stream gets the first one's AvatarBatch (frozen, read-only arrays), from
    bytes or a bytearray (websockets' frames). A stream whose rosters differ in any way
    (another rest, another avatar, none yet), other bytes, or a smaller size limit,
    decodes for itself, and gets what a decode of its own gives."""
    sk = rig.skeleton
    coding = rig_coding(rig)

    def roster(rest_scale: float = 1.0, ids: tuple[int, ...] = (4, 5)) -> AvatarRoster:
        return AvatarRoster(avatars=tuple(AvatarInfo(
            avatar_id=a, display_name="p", joint_names=sk.names,
            parents=tuple(int(p) for p in sk.parents), rest_offsets=sk.offsets * rest_scale,
            coding=coding) for a in ids))

    def stream(r: AvatarRoster | None) -> RosterCodings:
        codings = RosterCodings()
        if r is not None:
            decode_stream(encode(r), codings)
        return codings

    poses = _within_limits(rig, coding, np.random.default_rng(8), 2)
    batch = AvatarBatch.from_arrays([4, 5], [9, 3], np.zeros((2, 3)), poses, [1.0, 1.0],
                                    [1.0, 1.0], 1.0, 1.001)
    data = encode(batch, stream(roster()))
    a, b = stream(roster()), stream(roster())
    first = decode_stream(data, a)
    assert decode_stream(bytearray(data), b) is first
    assert decode_stream(data, a) is first  # the same stream, a batch sent again
    assert not first.rotations.flags.writeable and not first.roots.flags.writeable
    other_rest = stream(roster(rest_scale=1.1))  # a coding's rest is not in the roster
    assert other_rest.decoding_key() == a.decoding_key()  # ... of joint offsets: alike
    for codings in (stream(roster(ids=(4, 5, 6))), stream(roster(ids=(5, 4, 7)))):
        assert codings.decoding_key() != a.decoding_key()
        got = decode_stream(data, codings)
        assert got is not first and got == first  # decoded again, the same batch
    assert stream(None).decoding_key() is None
    with pytest.raises(ProtocolError, match="bytes of rotations"):
        decode_stream(data, stream(None))  # 5 bytes a joint without a coding
    changed = bytearray(data)
    changed[-1] ^= 1  # the last avatar's lost devices, the map's last value
    got = decode_stream(bytes(changed), b)
    assert got is not first and got.lost.tolist() == [0, 256]
    with pytest.raises(ProtocolError, match="limit is 100"):
        decode_stream(data, b, max_bytes=100)
    b.clear()  # forgetting the room forgets how it decodes
    assert b.decoding_key() is None
    for k in range(SHARED_BATCHES_KEPT):  # newer batches push the first one out
        decode_stream(encode(batch.model_copy(update={"t_sent": 2.0 + k}), a), a)
    assert decode_stream(data, a) is not first


def test_a_coding_is_refused_for_another_skeleton(rig: Rig) -> None:
    sk = rig.skeleton
    with pytest.raises(ValueError, match="coding: rest has 53 rows for 2 joints"):
        AvatarInfo(avatar_id=4, display_name="p", joint_names=sk.names[:2], parents=(-1, 0),
                   rest_offsets=sk.offsets[:2], coding=rig_coding(rig))


def test_the_decoders_cos_and_sinc_are_exact_over_every_half_angle() -> None:
    """The decoder's cos(h) and sin(h)/h: series where h <= ~1.58 (every joint coded
    within limits the encoder accepts), math's functions beyond; either way within a few
    ulps of the library's."""
    for h in np.linspace(0.0, 2.0 * math.pi, 2001):
        c, sinc = _cos_sinc(h * h)
        assert abs(c - math.cos(h)) <= 4e-16
        assert abs(sinc - (math.sin(h) / h if h else 1.0)) <= 4e-16


def test_a_coding_seen_before_is_taken_as_validated_then(rig: Rig) -> None:
    """Viewers in one process (the demo's) share each coding they read; bytes not seen
    before are validated in full, so a changed coding is still refused."""
    coding = rig_coding(rig)
    wire = coding.model_dump()
    first = PoseCoding.model_validate(wire, context={"wire": True})
    again = PoseCoding.model_validate(dict(wire), context={"wire": True})
    assert again is first and first == coding
    bad = {**wire, "bits": ((17, 0, 0),) * len(coding.driven)}
    for _ in range(2):  # refused, and not remembered as anything
        with pytest.raises(ValueError, match="1 to 16 bits"):
            PoseCoding.model_validate(bad, context={"wire": True})
    other = {**wire, "rest": coding._rest_wire(np.roll(coding.rest, 1, axis=1))}
    assert PoseCoding.model_validate(other, context={"wire": True}) is not first
