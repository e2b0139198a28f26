"""Measurements of the protocol for bench commands and the docs: sizes and timings.

Nothing here prints; callers (``posecast bench``, tests) format the results. Timings time
each call on its own with ``perf_counter_ns`` and report the median, which a busy
machine's preemptions move far less than the mean.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from posecast.protocol.codec import (
    decode,
    decode_client,
    decode_tracker_poses,
    encode,
    encode_avatar_batch,
)
from posecast.protocol.messages import AvatarBatch, TrackerFrame
from posecast.protocol.pose_coding import PoseCoding, RosterCodings
from posecast.protocol.roles import DEVICE_ROLES, DeviceRole

# what a tracker frame is measured with: a full Vive rig, the ten roles of the paper
# authors' recordings (a chest tracker is rare)
VIVE_RIG: tuple[DeviceRole, ...] = tuple(r for r in DEVICE_ROLES if r != "chest")

# The MakeHuman rig the project ships (solver/assets) has 53 joints; DESIGN calls it "60+".
MAKEHUMAN_JOINTS = 53


@dataclass(frozen=True)
class Timing:
    median_us: float
    p99_us: float
    runs: int


def time_calls(fn: Callable[[], object], runs: int = 20000, warmup: int = 200) -> Timing:
    """Time ``runs`` calls of ``fn`` one by one: median and 99th percentile, microseconds."""
    for _ in range(warmup):
        fn()
    samples = np.empty(runs)
    clock = time.perf_counter_ns
    for i in range(runs):
        start = clock()
        fn()
        samples[i] = clock() - start
    return Timing(float(np.median(samples)) / 1e3, float(np.percentile(samples, 99)) / 1e3,
                  runs)


def _unit_quaternions(rng: np.random.Generator, n: int) -> NDArray[np.float64]:
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def sample_tracker_frame(roles: tuple[DeviceRole, ...] = VIVE_RIG,
                         seed: int = 0) -> TrackerFrame:
    """A plausible tracker frame: every device within 2 m, random orientations."""
    rng = np.random.default_rng(seed)
    poses = np.concatenate([rng.uniform(-2.0, 2.0, (len(roles), 3)),
                            _unit_quaternions(rng, len(roles))], axis=1)
    return TrackerFrame(seq=123456, t_capture=1.7e9, clock_offset=-0.0123, roles=roles,
                        poses=poses)


def sample_avatar_batch(avatars: int, num_joints: int = MAKEHUMAN_JOINTS,
                        seed: int = 0) -> AvatarBatch:
    rng = np.random.default_rng(seed)
    now = 1.7e9
    return AvatarBatch.from_arrays(
        avatar_ids=list(range(avatars)), seqs=[1000 + i for i in range(avatars)],
        roots=rng.uniform(-2.0, 2.0, (avatars, 3)),
        rotations=_unit_quaternions(rng, avatars * num_joints).reshape(avatars, num_joints, 4),
        t_capture=[now] * avatars, t_server_receive=[now + 1e-3] * avatars,
        t_solved=now + 1.2e-3, t_sent=now + 1.3e-3)


def tracker_frame_error(samples: int = 1_000_000, reach_m: float = 10.0,
                        seed: int = 0) -> tuple[float, float]:
    """What the uplink's encoding costs (protocol 4: float32 positions, int16 quaternion
    components): the largest position error (micrometres,
    positions anywhere within ``reach_m``) and rotation error (degrees) of ``samples``
    random device poses against what the server reads back (``checked_poses``)."""
    from posecast.protocol.validation import checked_poses

    rng = np.random.default_rng(seed)
    poses = np.empty((samples, 7))
    direction = rng.normal(size=(samples, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    poses[:, :3] = direction * reach_m * rng.uniform(0.0, 1.0, (samples, 1)) ** (1 / 3)
    poses[:, 3:] = _unit_quaternions(rng, samples)
    back = np.empty_like(poses)
    if not checked_poses(poses, back):
        raise AssertionError("a random pose within the limits was refused")
    position_um = float(np.linalg.norm(back[:, :3] - poses[:, :3], axis=1).max()) * 1e6
    dot = np.abs(np.einsum("ij,ij->i", back[:, 3:], poses[:, 3:]))
    dot /= np.linalg.norm(back[:, 3:], axis=1)
    rotation_deg = float(np.degrees(2.0 * np.arccos(np.clip(dot, 0.0, 1.0))).max())
    return position_um, rotation_deg


def tracker_frame_bytes(roles: tuple[DeviceRole, ...] = VIVE_RIG) -> int:
    return len(encode(sample_tracker_frame(roles)))


def _codings(avatars: int, coding: PoseCoding | None) -> RosterCodings:
    """Every avatar's coding as a viewer holds them (learnt from rosters)."""
    codings = RosterCodings()
    codings.update({i: coding for i in range(avatars)})
    return codings


def bytes_per_avatar_frame(num_joints: int = MAKEHUMAN_JOINTS, avatars: int = 16,
                           coding: PoseCoding | None = None) -> float:
    """Wire bytes one avatar adds to a batch of ``avatars`` (batch header excluded),
    packed by ``coding`` (protocol 4's, from the roster), else every joint in 5 bytes."""
    if coding is not None:
        num_joints = coding.num_joints
    full = len(encode(sample_avatar_batch(avatars, num_joints), _codings(avatars, coding)))
    empty = len(encode(AvatarBatch.from_frames([], t_sent=0.0)))
    return (full - empty) / avatars


def spectator_bytes_per_s(players: int, rate_hz: float = 90.0,
                          num_joints: int = MAKEHUMAN_JOINTS,
                          coding: PoseCoding | None = None) -> float:
    """What one spectator of a room of ``players`` receives a second: a batch of every
    avatar per tick, each in a websocket frame (2 bytes of header under 126 bytes of
    payload, 4 under 64 KiB: the server's frames are unmasked); TCP/IP's own headers not
    counted. ``coding``: as ``bytes_per_avatar_frame``."""
    if coding is not None:
        num_joints = coding.num_joints
    payload = len(encode(sample_avatar_batch(players, num_joints),
                         _codings(players, coding)))
    header = 2 if payload < 126 else 4 if payload < 65536 else 10
    return (payload + header) * rate_hz


def time_decode_tracker_frame(runs: int = 20000,
                              roles: tuple[DeviceRole, ...] = VIVE_RIG,
                              model: bool = False) -> Timing:
    """decode + validate one tracker frame as the server does (``decode_tracker_poses``),
    or with ``model`` into the pydantic TrackerFrame (``decode_client``, what the server
    falls back to for anything unusual)."""
    data = encode(sample_tracker_frame(roles))
    if model:
        return time_calls(lambda: decode_client(data), runs)
    frame = decode_tracker_poses(data)
    assert frame is not None, "a well-formed frame takes the server's hot path"
    return time_calls(lambda: decode_tracker_poses(data), runs)


def time_avatar_batch(avatars: int = 16, num_joints: int = MAKEHUMAN_JOINTS,
                      runs: int = 2000, coding: PoseCoding | None = None
                      ) -> dict[str, Timing]:
    """Server side: encode a batch from the solver's arrays (``encode_avatar_batch``, as
    the server does); viewer side: decode + validate it. ``coding``: every avatar's."""
    if coding is not None:
        num_joints = coding.num_joints
    codings = _codings(avatars, coding)
    batch = sample_avatar_batch(avatars, num_joints)
    rng = np.random.default_rng(1)
    roots = rng.uniform(-2.0, 2.0, (avatars, 3))
    rotations = _unit_quaternions(rng, avatars * num_joints).reshape(avatars, -1, 4)
    ids = list(range(avatars))
    times = [1.7e9] * avatars

    def build_and_encode() -> bytes:
        return encode_avatar_batch(ids, ids, roots, rotations, times, times, 1.7e9, 1.7e9,
                                   codings=codings)

    data = encode(batch, codings)
    return {"build_encode": time_calls(build_and_encode, runs),
            "decode": time_calls(lambda: decode(data, codings=codings), runs)}
