"""Reconstruct recordings with a solver and score them (the `posecast eval` contract).

- Vive recording: calibrate at frame 0; drive the avatar from head, hip, hands and feet
  only; predict every recorded device (forearms and knees too, which the solver never
  sees) through the mounts fixed at calibration; error = distance to the recorded device.
- BVH: the performer's own skeleton is the avatar; the head, hips, hand and foot joints
  of the file are 6-DoF trackers; every joint of the body is scored against the file. A
  static root above the pelvis (Bandai's joint_Root) is the world frame, not the body:
  the avatar is rooted at the pelvis instead (``drop_static_root``).

Frames are solved one at a time in order, each warm-started from the last, exactly as
the server does live. Frame 0 of a Vive file (the calibration pose) is not scored.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from posecast.solver.calibration import calibrate
from posecast.solver.fk import forward_kinematics
from posecast.solver.ik import PoseBatch, Solver, SolverOptions
from posecast.solver.metrics import lag_frames, position_error_mm, rotation_error_deg
from posecast.solver.motion import (
    DRIVING_DEVICES,
    HELDOUT_DEVICES,
    Motion,
    ViveRecording,
    drop_static_root,
)
from posecast.solver.naming import roles as role_map
from posecast.solver.readers.gltf import load_makehuman
from posecast.solver.rig import Rig, build_rig
from posecast.solver.smoothing import SlerpSmoother

Progress = Callable[[int, int], None]


@dataclass
class ClipResult:
    file: str
    kind: str  # "vive" | "bvh"
    frames: int
    position_error_mm: dict[str, float]
    mean_error_mm: float
    heldout_error_mm: float
    rotation_error_deg: float
    solve_us_p50: float
    lag_ms: float
    extra: dict[str, float] = field(default_factory=dict)

    def as_json(self) -> dict[str, object]:
        return {"file": self.file, "kind": self.kind, "frames": self.frames,
                "position_error_mm": {k: round(v, 2) for k, v in
                                      self.position_error_mm.items()},
                "mean_error_mm": round(self.mean_error_mm, 2),
                "heldout_error_mm": round(self.heldout_error_mm, 2),
                "rotation_error_deg": round(self.rotation_error_deg, 2),
                "solve_us_p50": round(self.solve_us_p50, 2),
                "lag_ms": round(self.lag_ms, 2)}


@dataclass(frozen=True)
class EvalOptions:
    solver: str = "analytic"
    solver_options: SolverOptions = field(default_factory=SolverOptions)
    calibration: str = "fit"
    smoothing: float = 0.0  # SLERP smoothing factor, 0 = off


def _solve_sequence(solver: Solver, targets: NDArray[np.float64], state: PoseBatch,
                    offsets: NDArray[np.float64], smoothing: float,
                    progress: Progress | None) -> tuple[NDArray[np.float64],
                                                        NDArray[np.float64],
                                                        NDArray[np.float64]]:
    """Solve frame by frame; local rotations (F, J, 4), roots (F, 3), solve times (F,)."""
    F = targets.shape[0]
    J = state.rotations.shape[1]
    rots = np.empty((F, J, 4))
    roots = np.empty((F, 3))
    times = np.empty(F)
    smoother = SlerpSmoother(smoothing) if smoothing > 0 else None
    for f in range(F):
        t0 = time.perf_counter()
        solver.solve(targets[f: f + 1], state, offsets)
        times[f] = time.perf_counter() - t0
        out_q, out_r = state.rotations[0], state.root[0]
        if smoother is not None:
            out_q, out_r = smoother.update(out_q, out_r)
        rots[f] = out_q
        roots[f] = out_r
        if progress is not None and (f % 200 == 0 or f == F - 1):
            progress(f + 1, F)
    return rots, roots, times


def evaluate_vive(rec: ViveRecording, options: EvalOptions = EvalOptions(),
                  rig: Rig | None = None, progress: Progress | None = None) -> ClipResult:
    rig = rig or build_rig(load_makehuman().skeleton)
    pos0 = {name: rec.positions[0, d] for d, name in enumerate(rec.devices)}
    rot0 = {name: rec.rotations[0, d] for d, name in enumerate(rec.devices)}
    cal = calibrate(rig, pos0, rot0, options.calibration)
    targets = cal.targets(rec.positions[1:], rec.rotations[1:], rec.devices)
    solver = Solver(rig, options.solver, options.solver_options)
    state = PoseBatch(cal.pose[None].copy(), cal.root[None].copy())
    offsets = cal.offsets[None]
    rots, roots, times = _solve_sequence(solver, targets, state, offsets, options.smoothing,
                                         progress)
    gq, gp = forward_kinematics(rig.skeleton, rots, roots, np.broadcast_to(
        cal.offsets, (rots.shape[0], *cal.offsets.shape)))
    pred_p, pred_q = cal.predict(gq, gp, rec.devices)
    pos_err = position_error_mm(pred_p, rec.positions[1:])  # (F, D)
    rot_err = rotation_error_deg(pred_q, rec.rotations[1:])
    per_device = {name: float(pos_err[:, d].mean()) for d, name in enumerate(rec.devices)}
    held = [rec.device(n) for n in HELDOUT_DEVICES if n in rec.devices]
    lags = [lag_frames(pred_p[:, rec.device(h)], rec.positions[1:, rec.device(h)])
            for h in ("left_hand", "right_hand")]
    drive = [rec.device(n) for n in DRIVING_DEVICES]
    return ClipResult(
        file=rec.source, kind="vive", frames=int(targets.shape[0]),
        position_error_mm=per_device, mean_error_mm=float(pos_err.mean()),
        heldout_error_mm=float(pos_err[:, held].mean()) if held else float("nan"),
        rotation_error_deg=float(rot_err.mean()),
        solve_us_p50=float(np.median(times) * 1e6),
        lag_ms=float(np.mean(lags) / rec.fps * 1000.0),
        extra={"driving_error_mm": float(pos_err[:, drive].mean()),
               "scale": cal.scale})


def _reference_pose(motion: Motion) -> NDArray[np.float64] | None:
    """The rest pose is the canonical pose's reference when it stands upright (+y);
    otherwise (Bandai's rest pose lies along +x) the first motion frame is."""
    r = role_map(motion.skeleton)
    rest = motion.skeleton.rest_positions()
    up = rest[r["head"][0]] - rest[r["pelvis"][0]]
    if up[1] > 0.8 * np.linalg.norm(up):
        return None
    return np.asarray(motion.rotations[motion.first_frame])


def evaluate_bvh(motion: Motion, options: EvalOptions = EvalOptions(),
                 progress: Progress | None = None) -> ClipResult:
    if role_map(motion.skeleton)["pelvis"][0] != 0:
        # the avatar is rooted at the body: a static root above the pelvis is the world
        motion = drop_static_root(motion)
    frames = slice(motion.first_frame, motion.num_frames)
    rot = motion.rotations[frames]
    trans = motion.translations[frames]
    F = rot.shape[0]
    sk = motion.skeleton.with_offsets(trans[0])
    rig = build_rig(sk, _reference_pose(motion))
    gt_q, gt_p = forward_kinematics(sk, rot, trans[:, 0], trans)
    eff = rig.effectors
    targets = np.concatenate([gt_p[:, eff], gt_q[:, eff]], axis=-1)
    solver = Solver(rig, options.solver, options.solver_options)
    # the avatar starts in its canonical pose, placed on the first frame's pelvis
    state = PoseBatch.canonical(rig, 1)
    rots, roots, times = _solve_sequence(solver, targets, state, sk.offsets[None],
                                         options.smoothing, progress)
    q, p = forward_kinematics(sk, rots, roots)
    pos_err = position_error_mm(p, gt_p)  # (F, J)
    rot_err = rotation_error_deg(q, gt_q)
    tracked = set(int(j) for j in eff)
    held = [j for j in range(sk.num_joints) if j not in tracked]
    per_joint = {name: float(pos_err[:, j].mean()) for j, name in enumerate(sk.names)}
    lags = [lag_frames(p[:, rig.role(h)], gt_p[:, rig.role(h)]) for h in ("hand_l", "hand_r")]
    return ClipResult(
        file=motion.source, kind="bvh", frames=F, position_error_mm=per_joint,
        mean_error_mm=float(pos_err.mean()), heldout_error_mm=float(pos_err[:, held].mean()),
        rotation_error_deg=float(rot_err.mean()), solve_us_p50=float(np.median(times) * 1e6),
        lag_ms=float(np.mean(lags) / motion.fps * 1000.0))


def summarize(clips: list[ClipResult]) -> dict[str, float]:
    keys = ("mean_error_mm", "heldout_error_mm", "rotation_error_deg", "solve_us_p50")
    return {k: round(float(np.nanmean([getattr(c, k) for c in clips])), 2) for k in keys}

