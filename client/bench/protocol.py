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


def worst_quantization_deg(samples: int = 1_000_000, seed: int = 0) -> float:
    """Largest angle between random unit quaternions and their wire form, degrees."""
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(samples, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    back = dequantize_rotations(quantize_rotations(q))
    return float(np.degrees(rotation_angle(q, back).max()))


def bench_protocol() -> dict[str, object]:
    batch = time_avatar_batch(16)
    tracker = time_decode_tracker_frame()
    model = time_decode_tracker_frame(model=True)
    position_um, rotation_deg = tracker_frame_error()
    return {"joints": MAKEHUMAN_JOINTS,
            "bytes_per_avatar_frame": round(bytes_per_avatar_frame(), 1),
            # a spectator's downlink at 90 Hz, of a room of 4 and of 16 players
            "spectator_bytes_per_s": {str(n): round(spectator_bytes_per_s(n))
                                      for n in (4, 16)},
            "tracker_frame_bytes": tracker_frame_bytes(),
            "tracker_frame_float32_worst": {"position_um": round(position_um, 3),
                                            "rotation_deg": float(f"{rotation_deg:.2g}")},
            "quantization_worst_deg_measured": round(worst_quantization_deg(), 4),
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
