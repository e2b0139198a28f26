"""One definition of a valid batch row for both ends (issue 14, item 2): what the server's
``sendable_rows`` lets out is what a spectator's decoder takes, and a T-pose must fit a
body (``solver.plausible``)."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from posecast.client.builtin import builtin_motion_path
from posecast.client.sources.bvh_source import BvhSource
from posecast.protocol import AvatarBatch, ProtocolError, decode
from posecast.protocol.batch import avatar_batch_wire
from posecast.protocol.quantize import quantize_rotations
from posecast.protocol.validation import MAX_POSITION_M, sendable_rows
from posecast.solver.plausible import check_t_pose

J = 5
_edge = MAX_POSITION_M
_coordinate = st.one_of(
    st.floats(-2.0, 2.0),
    # around the world's bound, where the wire's float32 rounding decides
    st.floats(_edge - 1e-3, _edge + 1e-3), st.floats(-_edge - 1e-3, -_edge + 1e-3),
    st.sampled_from([math.nan, math.inf, -math.inf, 1e308, np.nextafter(_edge, 2e3)]))
_time = st.one_of(st.floats(-1e6, 1e6),
                  st.sampled_from([math.nan, math.inf, -math.inf, 1e308, -1.7e308]))


def _decoder_takes(root: np.ndarray, rotations: np.ndarray, times: tuple[float, ...]
                   ) -> bool:
    # sent at its solve's time, as the server sends a batch right after solving it
    with np.errstate(over="ignore", invalid="ignore"):  # 1e308 as the wire's float32: inf
        wire = avatar_batch_wire([7], [3], root.reshape(1, 3), [J],
                                 quantize_rotations(rotations), [times[0]], [times[1]],
                                 [times[2]], times[2])
    try:
        decode(msgpack.packb(wire, use_bin_type=True))
    except ProtocolError:
        return False
    return True


@settings(max_examples=300, deadline=None)
@given(root=st.tuples(_coordinate, _coordinate, _coordinate),
       times=st.tuples(_time, _time, _time))
def test_the_server_sends_a_row_exactly_when_a_spectator_takes_it(
        root: tuple[float, float, float], times: tuple[float, float, float]) -> None:
    r = np.array([root])
    rotations = np.tile([0.0, 0.0, 0.0, 1.0], (1, J, 1))
    keep = np.empty(1, dtype=np.bool_)
    bad = sendable_rows(r, rotations, np.array(times[:1]), np.array(times[1:2]),
                        times[2], keep)
    assert bad == (0 if keep[0] else 1)
    assert bool(keep[0]) == _decoder_takes(r[0], rotations[0], times)


@settings(max_examples=200, deadline=None)
@given(scale=st.one_of(st.floats(0.0, 3.0), st.sampled_from([math.nan, math.inf])),
       joint=st.integers(0, J - 1))
def test_a_row_the_server_sends_passes_both_of_a_spectators_ways(scale: float,
                                                                 joint: int) -> None:
    """Rotations: what goes out quantizes to what the decoder takes, and (for a
    spectator served from its outbox) builds a checked AvatarBatch."""
    rotations = np.tile([0.0, 0.0, 0.0, 1.0], (1, J, 1))
    with np.errstate(invalid="ignore"):  # inf x 0
        rotations[0, joint] *= scale
    keep = np.empty(1, dtype=np.bool_)
    sendable_rows(np.zeros((1, 3)), rotations, np.zeros(1), np.zeros(1), 0.0, keep)
    assert bool(keep[0]) == (abs(scale**2 - 1.0) <= 2e-3)
    if keep[0]:
        assert _decoder_takes(np.zeros(3), rotations[0], (0.0, 0.0, 0.0))
        AvatarBatch.from_arrays([7], [3], np.zeros((1, 3)), rotations, [0.0], [0.0],
                                0.0, 1.0)


def test_a_bad_row_is_one_of_many() -> None:
    roots = np.zeros((4, 3))
    roots[2] = (0.0, -(MAX_POSITION_M + 0.5), 0.0)
    rotations = np.tile([0.0, 0.0, 0.0, 1.0], (4, J, 1))
    keep = np.empty(4, dtype=np.bool_)
    t = np.array([1.0, 1.0, 1.0, math.inf])
    assert sendable_rows(roots, rotations, t, np.ones(4), 2.0, keep) == 2
    assert keep.tolist() == [True, True, False, False]


@pytest.fixture(scope="module")
def t_pose() -> tuple[tuple[str, ...], np.ndarray]:
    source = BvhSource(builtin_motion_path(), offset=(3.0, 0.0))
    try:
        sample = source.calibration()
    finally:
        source.close()
    return tuple(sample.roles), np.array(sample.poses[:, :3])


def test_a_body_passes(t_pose: tuple[tuple[str, ...], np.ndarray]) -> None:
    roles, positions = t_pose
    check_t_pose(roles, positions, 3.0)


def test_a_t_pose_hundreds_of_metres_wide_is_refused_naming_a_device(
        t_pose: tuple[tuple[str, ...], np.ndarray]) -> None:
    roles, positions = t_pose
    with pytest.raises(ValueError, match=r"calibrate: \w+ is [\d.]+ m from the head; a "
                                         r"T-pose's devices are within 3 m"):
        check_t_pose(roles, positions * 300.0, 3.0)


def test_feet_above_the_head_are_refused(t_pose: tuple[tuple[str, ...], np.ndarray]
                                         ) -> None:
    roles, positions = t_pose
    upside_down = positions.copy()
    upside_down[:, 1] *= -1.0
    with pytest.raises(ValueError, match=r"left_foot .* is not below the head"):
        check_t_pose(roles, upside_down, 3.0)


def test_a_nan_position_is_refused(t_pose: tuple[tuple[str, ...], np.ndarray]) -> None:
    roles, positions = t_pose
    bad = positions.copy()
    bad[3, 0] = math.nan
    with pytest.raises(ValueError, match="from the head"):
        check_t_pose(roles, bad, 3.0)
