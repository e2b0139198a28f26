"""Messages and checks the protocol tests share (tests/protocol)."""

from __future__ import annotations

from typing import Any

import msgpack
import numpy as np
import pytest
from numpy.typing import NDArray
from pydantic import BaseModel

from posecast.protocol import (
    AvatarInfo,
    Calibrate,
    ErrorCode,
    ProtocolError,
    decode,
    decode_client,
    encode,
)

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


def wire_poses(data: bytes) -> NDArray[np.float64]:
    """A tracker frame's wire poses as (D, 7) numbers to corrupt: the float32 positions
    and the quaternions' int16 levels (k, not k / 32767)."""
    n = len(data) // 20
    out = np.empty((n, 7))
    out[:, :3] = np.frombuffer(data, "<f4", 3 * n).reshape(n, 3)
    out[:, 3:] = np.frombuffer(data, "<i2", 4 * n, 12 * n).reshape(n, 4)
    return out


def poses_wire(rows: NDArray[np.float64]) -> bytes:
    """``wire_poses``' rows back to bytes (levels rounded and clipped to int16)."""
    with np.errstate(invalid="ignore", over="ignore"):
        levels = np.clip(np.rint(rows[:, 3:]), -32768, 32767).astype("<i2")
        return rows[:, :3].astype("<f4").tobytes() + levels.tobytes()


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


