"""Joint rotations on the wire: unit quaternions in 5 bytes ("smallest three").

A unit quaternion q (x, y, z, w) and -q are the same rotation, so we flip q until its
largest-magnitude component is positive, drop that component and send the other three
with the 2-bit index of the dropped one. Since the dropped component m is the largest,
each kept one satisfies |c| <= m and c^2 + m^2 <= 1, so |c| <= 1/sqrt(2): each is sent as
a 12-bit k = 2047 + round(c * 2047 sqrt(2)) in 0..4094 (zero is exact, so the identity and
every rotation about a coordinate axis' zero components survive unchanged).
2 + 3 x 12 = 38 bits fill a 5-byte little-endian word (bits 38-39 zero). The receiver
recomputes m = sqrt(1 - sum(c^2)).

Worst-case angle error (analytic; ``MAX_ANGLE_ERROR_RAD``):
  step  s = (1/sqrt(2)) / 2047,  per-component error |d_i| <= e = s / 2 = 1.7272e-4.
  The rebuilt m' moves by |dm| ~ |sum(c_i d_i)| / m <= sum|d_i| <= 3e  (|c_i| <= m),
  so the quaternion moves by |q' - q| <= sqrt(3 e^2 + (3 e)^2) = sqrt(12) e.
  The rotation angle between q and q' is 4 asin(|q' - q| / 2) ~ 2 |q' - q|, hence
  angle <= 4 sqrt(3) e = 1.1966e-3 rad = 0.06856 degrees  (required: <= 0.1 degree).
The bound is reached near q = (1/2, 1/2, 1/2, 1/2) with every d_i near +e;
tests/test_protocol_quantize.py checks it with hypothesis and at that corner.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

BYTES_PER_ROTATION = 5
_HALF = 2047  # k = _HALF + round(c * _SCALE) spans 0..4094 in 12 bits
_RANGE = 1.0 / math.sqrt(2.0)
_SCALE = _HALF / _RANGE
_MASK = np.uint64(0xFFF)

# analytic worst case, derived in the module docstring
MAX_COMPONENT_ERROR = 0.5 / _SCALE
MAX_ANGLE_ERROR_RAD = 4.0 * math.sqrt(3.0) * MAX_COMPONENT_ERROR
MAX_ANGLE_ERROR_DEG = math.degrees(MAX_ANGLE_ERROR_RAD)

# for a dropped index i, the indices of the three kept components, in wire order
_KEPT = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]], dtype=np.intp)
_PACK = np.array([2.0**24, 2.0**12, 1.0])  # float products stay exact below 2^53
_SHIFTS = np.array([24, 12, 0], dtype=np.uint64)
# a decoded sum of squares above 3/4 (+ quantization slack) cannot come from a unit
# quaternion: its three smallest components have squares summing to at most 3/4
_MAX_KEPT_SQUARES = 0.75 + 1e-3


# Gathers use flat .take/.put: on (J, 4) arrays they are several times faster than
# fancy indexing, and these two functions run for every avatar of every frame.
def quantize_rotations(q: ArrayLike) -> bytes:
    """(J, 4) quaternions x, y, z, w -> J * 5 bytes. Normalises first."""
    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    n = len(q)
    flat = q.ravel()
    base = np.arange(0, 4 * n, 4)
    largest = np.abs(q).argmax(axis=1)
    inv_norm = 1.0 / np.sqrt(np.einsum("ij,ij->i", q, q))
    # normalise, and flip so that the dropped (largest) component is positive
    scale = np.where(flat.take(base + largest) < 0.0, -inv_norm, inv_norm)
    idx = _KEPT.take(largest, axis=0)
    idx += base[:, None]
    kept = flat.take(idx) * scale[:, None]
    k = np.clip(np.floor(kept * _SCALE + 0.5), -_HALF, _HALF) + _HALF
    word = k @ _PACK + largest * 2.0**36
    return word.astype("<u8").view(np.uint8).reshape(n, 8)[:, :BYTES_PER_ROTATION].tobytes()


def dequantize_rotations(data: bytes) -> NDArray[np.float64]:
    """J * 5 bytes -> (J, 4) unit quaternions, largest component positive.

    Raises ValueError (with the joint index) for bytes no quantized rotation can give.
    """
    if len(data) % BYTES_PER_ROTATION:
        raise ValueError(f"{len(data)} bytes is not a multiple of {BYTES_PER_ROTATION} "
                         f"bytes per rotation")
    n = len(data) // BYTES_PER_ROTATION
    padded = np.zeros((n, 8), dtype=np.uint8)
    padded[:, :BYTES_PER_ROTATION] = np.frombuffer(data, dtype=np.uint8).reshape(
        n, BYTES_PER_ROTATION)
    word = padded.view("<u8")[:, 0]
    spare = word >> np.uint64(38)
    if np.any(spare):
        raise ValueError(f"joint {int(np.flatnonzero(spare)[0])}: unused bits 38-39 are set")
    largest = (word >> np.uint64(36)).astype(np.intp)
    # (4095, which no encoder writes, decodes to just over 1/sqrt(2): harmless)
    kept = (((word[:, None] >> _SHIFTS) & _MASK).astype(np.float64) - _HALF) * (1.0 / _SCALE)
    squares = np.einsum("ij,ij->i", kept, kept)
    if np.any(squares > _MAX_KEPT_SQUARES):
        j = int(np.flatnonzero(squares > _MAX_KEPT_SQUARES)[0])
        raise ValueError(f"joint {j}: the three sent components have squares summing to "
                         f"{squares[j]:.4f} > 0.75, not a unit quaternion")
    out = np.empty(4 * n)
    base = np.arange(0, 4 * n, 4)
    idx = _KEPT.take(largest, axis=0)
    idx += base[:, None]
    out.put(idx, kept)
    out.put(base + largest, np.sqrt(1.0 - squares))
    return out.reshape(n, 4)


def rotation_angle(a: ArrayLike, b: ArrayLike) -> NDArray[np.float64]:
    """Angle in radians of the rotation between unit quaternions a and b (..., 4).

    Uses the chord |a - b| (sign-aligned) instead of acos(|a.b|), which loses half its
    digits near zero, where quantization errors live.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    chord = np.minimum(np.linalg.norm(a - b, axis=-1), np.linalg.norm(a + b, axis=-1))
    return 4.0 * np.arcsin(np.minimum(chord / 2.0, 1.0))
