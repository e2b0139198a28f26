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
tests/protocol/test_protocol_quantize.py checks it with hypothesis and at that corner.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, types
from numpy.typing import ArrayLike, NDArray

BYTES_PER_ROTATION = 5
_HALF = 2047  # k = _HALF + round(c * _SCALE) spans 0..4094 in 12 bits
_RANGE = 1.0 / math.sqrt(2.0)
_SCALE = _HALF / _RANGE

# analytic worst case, derived in the module docstring
MAX_COMPONENT_ERROR = 0.5 / _SCALE
MAX_ANGLE_ERROR_RAD = 4.0 * math.sqrt(3.0) * MAX_COMPONENT_ERROR
MAX_ANGLE_ERROR_DEG = math.degrees(MAX_ANGLE_ERROR_RAD)

# a decoded sum of squares above 3/4 (+ quantization slack) cannot come from a unit
# quaternion: its three smallest components have squares summing to at most 3/4
_MAX_KEPT_SQUARES = 0.75 + 1e-3


@njit(cache=True, inline="always")
def quat_word(x: float, y: float, z: float, w: float) -> int:
    """One quaternion's 38 bits (the module's layout): also a PoseCoding's quaternion."""
    q = (x, y, z, w)
    largest = 0
    for i in range(1, 4):
        if abs(q[i]) > abs(q[largest]):
            largest = i  # the first of equal magnitudes, as np.argmax
    inv_norm = 1.0 / math.sqrt(x * x + y * y + z * z + w * w)
    # normalise, and flip so that the dropped (largest) component is positive
    scale = -inv_norm if q[largest] < 0.0 else inv_norm
    word = largest << 36
    shift = 24
    for i in range(4):
        if i == largest:
            continue
        k = math.floor(q[i] * scale * _SCALE + 0.5)
        k = min(max(k, -_HALF), _HALF) + _HALF
        word |= int(k) << shift
        shift -= 12
    return word


@njit(cache=True, inline="always")
def word_quat(word: int, out: NDArray[np.float64]) -> float:
    """38 bits -> out (4,); returns the kept components' sum of squares, or minus it
    when no unit quaternion has them."""
    largest = word >> 36
    squares = 0.0
    shift = 24
    for i in range(4):
        if i == largest:
            continue
        c = (((word >> shift) & 0xFFF) - _HALF) * (1.0 / _SCALE)
        out[i] = c
        squares += c * c
        shift -= 12
    # (4095, which no encoder writes, decodes to just over 1/sqrt(2): harmless)
    if squares > _MAX_KEPT_SQUARES:
        return -squares
    out[largest] = math.sqrt(1.0 - squares)
    return squares


# Compiled (numba): the server encodes and every spectator decodes ~850 rotations a batch
# of 16, where numpy's dozen whole-array passes cost far more than one compiled pass.
# Explicit signatures compile (or load from the cache) at import: a compile at the first
# frame would stall a spectator's first frames.
@njit(types.void(types.Array(types.float64, 2, "C", readonly=True), types.uint8[::1]),
      cache=True)
def _quantize(q: NDArray[np.float64], out: NDArray[np.uint8]) -> None:
    for j in range(q.shape[0]):
        word = quat_word(q[j, 0], q[j, 1], q[j, 2], q[j, 3])
        for b in range(BYTES_PER_ROTATION):
            out[j * BYTES_PER_ROTATION + b] = (word >> (8 * b)) & 0xFF


@njit(types.Tuple((types.int64, types.int64, types.float64))(
    types.Array(types.uint8, 1, "C", readonly=True), types.float64[:, ::1]), cache=True)
def _dequantize(data: NDArray[np.uint8], out: NDArray[np.float64]
                ) -> tuple[int, int, float]:
    """Fills out; returns (0, -1, 0), or (1, joint, 0) for set spare bits, or
    (2, joint, sum of squares) for components no unit quaternion has."""
    for j in range(out.shape[0]):
        word = 0
        for b in range(BYTES_PER_ROTATION):
            word |= int(data[j * BYTES_PER_ROTATION + b]) << (8 * b)
        if word >> 38:
            return 1, j, 0.0
        squares = word_quat(word, out[j])
        if squares < 0.0:
            return 2, j, -squares
    return 0, -1, 0.0


def quantize_rotations(q: ArrayLike) -> bytes:
    """(J, 4) quaternions x, y, z, w -> J * 5 bytes. Normalises first."""
    rows = np.ascontiguousarray(q, dtype=np.float64).reshape(-1, 4)
    out = np.empty(BYTES_PER_ROTATION * rows.shape[0], dtype=np.uint8)
    _quantize(rows, out)
    return out.tobytes()


def dequantize_rotations(data: bytes | bytearray | memoryview) -> NDArray[np.float64]:
    """J * 5 bytes -> (J, 4) unit quaternions, largest component positive.

    Raises ValueError (with the joint index) for bytes no quantized rotation can give.
    """
    if len(data) % BYTES_PER_ROTATION:
        raise ValueError(f"{len(data)} bytes is not a multiple of {BYTES_PER_ROTATION} "
                         f"bytes per rotation")
    out = np.empty((len(data) // BYTES_PER_ROTATION, 4))
    problem, j, squares = _dequantize(np.frombuffer(data, dtype=np.uint8), out)
    if problem == 1:
        raise ValueError(f"joint {j}: unused bits 38-39 are set")
    if problem == 2:
        raise ValueError(f"joint {j}: the three sent components have squares summing to "
                         f"{squares:.4f} > 0.75, not a unit quaternion")
    return out


def rotation_angle(a: ArrayLike, b: ArrayLike) -> NDArray[np.float64]:
    """Angle in radians of the rotation between unit quaternions a and b (..., 4).

    Uses the chord |a - b| (sign-aligned) instead of acos(|a.b|), which loses half its
    digits near zero, where quantization errors live.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    chord = np.minimum(np.linalg.norm(a - b, axis=-1), np.linalg.norm(a + b, axis=-1))
    return 4.0 * np.arcsin(np.minimum(chord / 2.0, 1.0))
