"""`posecast bench protocol`: wire sizes, the worst quantization error, codec timings."""

from __future__ import annotations

import numpy as np

from posecast.protocol import (
    MAX_ANGLE_ERROR_DEG,
    dequantize_rotations,
    quantize_rotations,
    rotation_angle,
)
from posecast.protocol.measure import (
    MAKEHUMAN_JOINTS,
    bytes_per_avatar_frame,
    spectator_bytes_per_s,
    time_avatar_batch,
    time_decode_tracker_frame,
    tracker_frame_bytes,
    tracker_frame_error,
)
from posecast.protocol.pose_coding import PoseCoding
from posecast.server.avatars import rig_coding
from posecast.solver import rotations as R
from posecast.solver.readers.gltf import load_makehuman
from posecast.solver.rig import Rig, build_rig


def worst_quantization_deg(samples: int = 1_000_000, seed: int = 0) -> float:
    """Largest angle between random unit quaternions and their wire form, degrees."""
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(samples, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    back = dequantize_rotations(quantize_rotations(q))
    return float(np.degrees(rotation_angle(q, back).max()))


def coded_worst_deg(coding: PoseCoding, rig: Rig, frames: int = 50_000, seed: int = 0
                    ) -> float:
    """Largest angle between driven joints at random parameters within their limits
    (half of the frames at the limit box's corners, where clamping could bite) and
    their wire form under ``coding``, degrees."""
    rng = np.random.default_rng(seed)
    poses = np.broadcast_to(coding.rest, (frames, coding.num_joints, 4)).copy()
    for j in coding.driven:
        u = rng.random((frames, 3))
        u[frames // 2:] = np.round(u[frames // 2:])  # the corners
        p = rig.lo[j] + u * (rig.hi[j] - rig.lo[j])
        swing = R.from_rotvec(np.stack([p[:, 0], np.zeros(frames), p[:, 2]], -1))
        twist = R.from_rotvec(np.stack([np.zeros(frames), p[:, 1], np.zeros(frames)], -1))
        poses[:, j] = R.mul(R.mul(rig.pre[j], R.mul(swing, twist)), rig.post[j])
    back = coding.unpack(coding.pack(poses))
    return float(np.degrees(rotation_angle(poses, back).max()))


def bench_protocol() -> dict[str, object]:
    # a MakeHuman avatar as the server codes it; the coding is the same whatever devices
    # the player has (3 to 11: the body model moves what they do not)
    rig = build_rig(load_makehuman().skeleton)
    coding = rig_coding(rig)
    batch = time_avatar_batch(16, coding=coding)
    tracker = time_decode_tracker_frame()
    model = time_decode_tracker_frame(model=True)
    position_um, rotation_deg = tracker_frame_error()
    return {"joints": MAKEHUMAN_JOINTS, "driven_joints": len(coding.driven),
            "bytes_per_avatar_frame": round(bytes_per_avatar_frame(coding=coding), 1),
            # a replay's avatar, or protocol 3's: every joint in 5 bytes, float64 times
            "bytes_per_avatar_frame_every_joint": round(bytes_per_avatar_frame(), 1),
            # a spectator's downlink at 90 Hz, of a room of 4 and of 16 players
            "spectator_bytes_per_s": {str(n): round(spectator_bytes_per_s(n, coding=coding))
                                      for n in (4, 16)},
            "tracker_frame_bytes": tracker_frame_bytes(),
            "tracker_frame_wire_worst": {"position_um": round(position_um, 3),
                                            "rotation_deg": float(f"{rotation_deg:.2g}")},
            "quantization_worst_deg_measured": round(worst_quantization_deg(), 4),
            # protocol 4's driven joints, packed by their limits (10^6 joints)
            "coded_worst_deg_measured": round(coded_worst_deg(coding, rig), 4),
            "quantization_bound_deg": round(MAX_ANGLE_ERROR_DEG, 4),
            "decode_tracker_frame_us": {"p50": round(tracker.median_us, 2),
                                        "p99": round(tracker.p99_us, 2)},
            "decode_tracker_frame_model_us": {"p50": round(model.median_us, 2),
                                              "p99": round(model.p99_us, 2)},
            "batch16_build_encode_us": {"p50": round(batch["build_encode"].median_us, 1),
                                        "p99": round(batch["build_encode"].p99_us, 1)},
            "batch16_decode_us": {"p50": round(batch["decode"].median_us, 1),
                                  "p99": round(batch["decode"].p99_us, 1)}}


def format_protocol_table(result: dict[str, object]) -> str:
    rows = [(k.replace("_", " "), str(v)) for k, v in result.items()]
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k.ljust(width)}  {v}" for k, v in rows)
