"""Devices lost and found in any pattern (hypothesis): the walk's devices, each of any
set absent in runs of frames drawn at random, the head and hands too. The targets stay
finite and move without jumps, the weights stay in [0, 1], and the solved body is a
body: what real trackers do a few times a minute, in every combination."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from posecast.client.builtin import builtin_motion_path
from posecast.solver.evaluation import performer_calibration
from posecast.solver.fk import forward_kinematics
from posecast.solver.ik import PoseBatch, Solver, SolverOptions
from posecast.solver.readers.bvh import read_bvh
from posecast.solver.rig import build_rig
from posecast.solver.tracking.devices import BONES, DEVICES, MAIN, MINIMUM
from posecast.solver.tracking.rows import TrackingRows, slots_of

FRAMES = 150  # 1.25 s of the 120 fps walk
# the most a target may move in a frame (m): the walk's devices move <= 3 cm; a return
# blends at <= 1 m/s (x1.5 at the smoothstep's peak, along an arc), a fade over 1 s, a
# model step of a leg's length in 0.25 s (x1.5) ~8 cm at 120 fps
MAX_STEP_M = 0.12

_MOTION = read_bvh(builtin_motion_path())
_RIG = build_rig(_MOTION.skeleton)
_ROT = _MOTION.rotations[_MOTION.first_frame:]
_TRANS = _MOTION.translations[_MOTION.first_frame:]
_GQ, _GP = forward_kinematics(_MOTION.skeleton, _ROT, _TRANS[:, 0], _TRANS)
_JOINTS = [_RIG.role(b) for b in BONES]
_POSES = np.concatenate([_GP[:, _JOINTS], _GQ[:, _JOINTS]], axis=-1)  # (F, ND, 7)
_FLOOR = float(_GP[0, :, 1].min())
_HEAD = _RIG.role("head")
_CAL = performer_calibration(_RIG, _MOTION.skeleton.offsets, _GP[0, _HEAD], _GQ[0, _HEAD],
                             _FLOOR)
_SOLVER = Solver(_RIG, "analytic", SolverOptions())
_OPTIONAL = tuple(d for d in DEVICES if d not in MINIMUM)


def _runs(frames: int) -> st.SearchStrategy[list[bool]]:
    """Present / absent in runs of 1 to 60 frames, starting either way."""
    return st.lists(st.tuples(st.booleans(), st.integers(1, 60)), min_size=1,
                    max_size=12).map(
        lambda runs: ([on for on, n in runs for _ in range(n)] * frames)[:frames])


@st.composite
def _scenario(draw: st.DrawFn) -> tuple[tuple[str, ...], np.ndarray]:
    extra = draw(st.lists(st.sampled_from(_OPTIONAL), unique=True, max_size=8))
    devices = tuple(d for d in DEVICES if d in MINIMUM or d in extra)
    present = np.array([draw(_runs(FRAMES)) for _ in devices]).T  # (F, D)
    return devices, present


@settings(max_examples=60, deadline=None)
@given(_scenario())
def test_any_pattern_of_losses_moves_the_targets_without_jumps(
        scenario: tuple[tuple[str, ...], np.ndarray]) -> None:
    devices, present = scenario
    rows = TrackingRows(1)
    rows.calibrate(0, _CAL, devices, _FLOOR)
    slots = slots_of(devices)
    state = PoseBatch.canonical(_RIG, 1)
    offsets = _MOTION.skeleton.offsets[None]
    row = np.zeros(1, dtype=np.intp)
    fps = float(_MOTION.fps)
    last = None
    for f in range(FRAMES):
        seen = present[f]
        rows.stage(0, slots[seen], _POSES[f, slots[seen]], f / fps)
        rows.fill(row)
        targets, weights = rows.targets[0], rows.weights[0]
        assert np.isfinite(targets).all() and np.isfinite(weights).all(), f
        assert ((weights >= 0.0) & (weights <= 1.0)).all(), (f, weights)
        assert np.allclose(np.linalg.norm(targets[:MAIN, 3:], axis=1), 1.0, atol=1e-6)
        if last is not None:
            step = np.linalg.norm(targets[:MAIN, :3] - last, axis=1)
            assert step.max() < MAX_STEP_M, (f, devices, DEVICES[int(step.argmax())],
                                             float(step.max()))
        last = targets[:MAIN, :3].copy()
        _SOLVER.solve(rows.targets[:1], state, offsets, rows.weights[:1])
        assert np.isfinite(state.rotations).all() and np.isfinite(state.root).all()
        assert np.allclose(np.linalg.norm(state.rotations, axis=-1), 1.0, atol=1e-6)
