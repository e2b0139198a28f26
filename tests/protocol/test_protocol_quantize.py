"""protocol.quantize: joint rotations in 5 bytes with a proven worst-case angle error.

The analytic bound (protocol/quantize.py docstring) is 4 sqrt(3) e with e half a
quantization step: 0.0686 degree. These tests check that no rotation exceeds it, that it
is nearly reached (so the analysis is tight, not just loose), and that it meets the
0.1 degree requirement.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from posecast.protocol.quantize import (
    BYTES_PER_ROTATION,
    MAX_ANGLE_ERROR_DEG,
    MAX_ANGLE_ERROR_RAD,
    dequantize_rotations,
    quantize_rotations,
    rotation_angle,
)

REQUIRED_DEG = 0.1
# the bound is first order in e; second-order terms are ~e^2 = 3e-8 rad, far below this
SLACK = 1e-6


def round_trip_angle(q: NDArray[np.float64]) -> NDArray[np.float64]:
    return rotation_angle(q, dequantize_rotations(quantize_rotations(q)))


def test_analytic_bound_meets_the_requirement() -> None:
    step = (1 / math.sqrt(2)) / 2047
    bound_rad, bound_deg = MAX_ANGLE_ERROR_RAD, MAX_ANGLE_ERROR_DEG
    assert bound_rad == pytest.approx(4 * math.sqrt(3) * step / 2, rel=1e-12)
    assert bound_deg == pytest.approx(0.06856, abs=1e-5)
    assert bound_deg < REQUIRED_DEG


components = st.floats(-1.0, 1.0, allow_nan=False)


@settings(max_examples=2000, deadline=None)
@given(st.tuples(components, components, components, components)
       .filter(lambda c: math.hypot(*c) > 1e-3))
@example((0.5, 0.5, 0.5, 0.5))
@example((0.0, 0.0, 0.0, -1.0))
@example((1.0, 1.0, 0.0, 0.0))  # a tie for the largest component
@example((1.0, 1.0, 1.0, 1.0 - 1e-12))
def test_any_rotation_within_the_bound(c: tuple[float, float, float, float]) -> None:
    q = np.array([c]) / math.hypot(*c)
    angle = float(round_trip_angle(q)[0])
    assert angle <= MAX_ANGLE_ERROR_RAD + SLACK * MAX_ANGLE_ERROR_RAD
    assert math.degrees(angle) <= REQUIRED_DEG


def test_million_random_rotations_worst_case() -> None:
    rng = np.random.default_rng(0)
    q = rng.normal(size=(1_000_000, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    worst = float(round_trip_angle(q).max())
    assert worst <= MAX_ANGLE_ERROR_RAD
    assert worst > 0.85 * MAX_ANGLE_ERROR_RAD  # the bound is nearly reached: it is tight


def test_bound_is_nearly_reached_at_the_analysed_corner() -> None:
    # around (1/2, 1/2, 1/2, 1/2), the quantization errors of the three sent components
    # take every value in [-e, e]; the worst of them approaches 4 sqrt(3) e
    rng = np.random.default_rng(1)
    q = 0.5 + rng.uniform(-2e-3, 2e-3, size=(200_000, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    worst = float(round_trip_angle(q).max())
    assert 0.95 * MAX_ANGLE_ERROR_RAD < worst <= MAX_ANGLE_ERROR_RAD * (1 + SLACK)


def test_size_and_sign() -> None:
    rng = np.random.default_rng(2)
    q = rng.normal(size=(53, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    data = quantize_rotations(q)
    assert len(data) == 53 * BYTES_PER_ROTATION == 265
    assert quantize_rotations(-q) == data  # q and -q are one rotation
    back = dequantize_rotations(data)
    np.testing.assert_allclose(np.linalg.norm(back, axis=1), 1.0, atol=1e-15)
    assert (back[np.arange(53), np.abs(back).argmax(axis=1)] > 0).all()


def test_axis_rotations_and_identity_are_exact_in_their_zeros() -> None:
    q = np.array([[0, 0, 0, 1.0], [0, 0, 0, -1.0], [0.6, 0, 0, 0.8], [0, 0.8, 0, -0.6]])
    back = dequantize_rotations(quantize_rotations(q))
    np.testing.assert_array_equal(back[0], [0, 0, 0, 1.0])
    np.testing.assert_array_equal(back[1], [0, 0, 0, 1.0])
    assert back[2, 1] == back[2, 2] == 0.0 and back[3, 0] == back[3, 2] == 0.0


def test_batch_equals_one_by_one() -> None:
    rng = np.random.default_rng(3)
    q = rng.normal(size=(40, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    assert quantize_rotations(q) == b"".join(quantize_rotations(row) for row in q)
    assert quantize_rotations(np.zeros((0, 4))) == b""
    assert dequantize_rotations(b"").shape == (0, 4)
    # what arrives: read-only arrays (a decoded message's) and any bytes-like buffer
    q.flags.writeable = False
    data = quantize_rotations(q)
    for buffer in (data, bytearray(data), memoryview(data)):
        np.testing.assert_array_equal(dequantize_rotations(buffer), dequantize_rotations(data))


def test_unnormalised_input_is_normalised_first() -> None:
    q = np.array([[0.1, 0.2, 0.3, 0.9]])
    unit = q / np.linalg.norm(q)
    assert quantize_rotations(q * 3.0) == quantize_rotations(unit)


@pytest.mark.parametrize(("data", "message"), [
    (b"\x00" * 6, "6 bytes is not a multiple of 5"),
    (bytes([0, 0, 0, 0, 0x40]), "joint 0: unused bits 38-39 are set"),
    (bytes(5) + bytes(5), "joint 0: the three sent components have squares summing to 1.5000"),
])
def test_corrupt_bytes(data: bytes, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        dequantize_rotations(data)


def test_rotation_angle_is_precise_for_small_angles() -> None:
    angle = 1e-6
    q = np.array([0.0, 0.0, math.sin(angle / 2), math.cos(angle / 2)])
    assert float(rotation_angle(q, [0, 0, 0, 1.0])) == pytest.approx(angle, rel=1e-9)
    assert float(rotation_angle(-q, [0, 0, 0, 1.0])) == pytest.approx(angle, rel=1e-9)
    assert float(rotation_angle([1.0, 0, 0, 0], [0, 0, 0, 1.0])) == pytest.approx(math.pi)


def _reference_word(q: NDArray[np.float64]) -> int:
    """The format of the module docstring, read literally, one rotation in plain Python."""
    largest = max(range(4), key=lambda i: (abs(q[i]), -i))  # the first of equal magnitudes
    scale = (-1.0 if q[largest] < 0 else 1.0) / math.sqrt(sum(c * c for c in q))
    word = largest << 36
    for shift, i in zip((24, 12, 0), [i for i in range(4) if i != largest], strict=True):
        c = q[i] * scale  # normalised, the dropped component made positive
        k = min(max(math.floor(c * (2047 / (1 / math.sqrt(2))) + 0.5), -2047), 2047) + 2047
        word |= k << shift
    return word


def test_compiled_kernel_matches_the_format_read_literally() -> None:
    rng = np.random.default_rng(11)
    q = rng.normal(size=(500, 4))
    q[:50, 1] = 0.0  # zeros and ties of magnitude
    q[50:60] = [0.5, -0.5, 0.5, -0.5]
    data = quantize_rotations(q)
    for j, row in enumerate(q):
        chunk = data[j * BYTES_PER_ROTATION:(j + 1) * BYTES_PER_ROTATION]
        assert int.from_bytes(chunk, "little") == _reference_word(row)
    assert np.array_equal(dequantize_rotations(data)[:50, 1], np.zeros(50))
