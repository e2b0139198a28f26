"""Reconstruct recordings with a solver and score them (the `posecast eval` contract).

- Vive recording: calibrate at frame 0; drive the avatar from the devices of the tracker
  set (``EvalOptions.devices``; default head, hip, hands and feet); predict every recorded
  device (the others too, which the solver never sees) through the mounts fixed at
  calibration; error = distance to the recorded device.
- BVH: the performer's own skeleton is the avatar; the joints of the file that stand in
  for the set's devices (head, hips, hands, feet; forearm, shin and chest joints for
  elbow, knee and chest trackers) are 6-DoF trackers; every joint of the body is scored
  against the file. A static root above the pelvis (Bandai's joint_Root) is the world
  frame, not the body: the avatar is rooted at the pelvis instead (``drop_static_root``).
  The performer is calibrated as a player would be: standing upright under the first
  frame's head, on a floor at the first frame's lowest joint.

Frames go through ``solver.tracking`` as a live avatar's do: body parts without a device
come from the body model, and with ``--dropouts`` devices are lost at random (absent from
the frame, as ``play --source openvr`` leaves out an untracked device). ``max_step_mm`` is
the largest frame-to-frame move of any scored point; ``dropout_error_mm`` the mean error,
while lost, of the lost devices' own points.

Frames are solved one at a time in order, each warm-started from the last, exactly as
the server does live. Frame 0 of a Vive file (the calibration pose) is not scored.

With a delay D (``EvalOptions.delay_ms``, ``posecast eval --delay-ms D``) each solved frame
is what a viewer shows D ms after its capture, scored against the recording at that
instant (interpolated between frames when D is not a whole number of them); with a
predictor it is first carried forward by D (``solver.prediction``), on the solved joint
rotations as the viewer does (or on the trackers before the solve, to compare). Jitter is
the mean jerk of what is shown (m/s^3), so that accuracy bought with shaking shows.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from posecast.solver import rotations as R
from posecast.solver.calibration import DEVICE_BONES, Calibration, Mount, calibrate
from posecast.solver.fk import forward_kinematics
from posecast.solver.ik import PoseBatch, Solver, SolverOptions
from posecast.solver.metrics import lag_frames, position_error_mm, rotation_error_deg
from posecast.solver.motion import Motion, ViveRecording, drop_static_root
from posecast.solver.naming import roles as role_map
from posecast.solver.prediction import (
    PredictorParams,
    SequenceDeltas,
    lags_needed,
    predict_sequence,
)
from posecast.solver.readers.gltf import load_makehuman
from posecast.solver.rig import Rig, build_rig, global_pose
from posecast.solver.smoothing import SlerpSmoother
from posecast.solver.tracking.body_model import SHIPPED, BodyModel
from posecast.solver.tracking.devices import BONES, DEFAULT_SET, DEVICES, PRESETS, SLOT
from posecast.solver.tracking.dropouts import DropoutSpec, dropout_mask
from posecast.solver.tracking.rows import TrackingRows, slots_of

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
    # the worst 1% of frames: each device's (joint's) 99th percentile error over frames
    p99_error_mm: dict[str, float] = field(default_factory=dict)

    def as_json(self) -> dict[str, object]:
        out: dict[str, object] = {
            "file": self.file, "kind": self.kind, "frames": self.frames,
            "position_error_mm": {k: round(v, 2) for k, v in self.position_error_mm.items()},
            "mean_error_mm": round(self.mean_error_mm, 2),
            "heldout_error_mm": round(self.heldout_error_mm, 2),
            "rotation_error_deg": round(self.rotation_error_deg, 2),
            "solve_us_p50": round(self.solve_us_p50, 2),
            "lag_ms": round(self.lag_ms, 2)}
        if "jitter_m_s3" in self.extra:  # a delayed run (--delay-ms) adds what was shown
            out["jitter_m_s3"] = round(self.extra["jitter_m_s3"], 1)
        if self.p99_error_mm:  # tails: the worst 1% of frames beside the means
            out["p99_error_mm"] = {k: round(v, 2) for k, v in self.p99_error_mm.items()}
            out["p99_frame_error_mm"] = round(self.extra["p99_frame_error_mm"], 2)
        if "rotation_error_tracked_deg" in self.extra:
            out["rotation_error_tracked_deg"] = round(self.extra["rotation_error_tracked_deg"], 2)
        for key in ("max_step_mm", "dropout_error_mm"):
            if key in self.extra:
                out[key] = round(self.extra[key], 2)
        if "dropout_frames" in self.extra:
            out["dropout_frames"] = int(self.extra["dropout_frames"])
        return out


@dataclass(frozen=True)
class EvalOptions:
    solver: str = "analytic"
    solver_options: SolverOptions = field(default_factory=SolverOptions)
    calibration: str = "fit"
    smoothing: float = 0.0  # SLERP smoothing factor, 0 = off
    delay_ms: float | None = None  # what a viewer shows this late (None: as solved)
    predictor: PredictorParams | None = None  # carry it forward by the delay
    predict_on: str = "joints"  # "joints": solved rotations (the viewer); "trackers"
    devices: tuple[str, ...] = PRESETS[DEFAULT_SET]  # the tracker set that drives
    dropouts: DropoutSpec | None = None  # devices lost at random
    naive: bool = False  # the baseline body model: pelvis under the head, legs straight
    body: BodyModel = SHIPPED  # the body model's constants


@dataclass
class Stream:
    """What drives a reconstruction: the poses of the set's devices over F frames, and
    which of them are lost in which frame."""

    names: tuple[str, ...]  # the devices, a subset of the set
    poses: NDArray[np.float64]  # (F, D, 7) position | rotation, as the devices give them
    lost: NDArray[np.bool_]  # (F, D)
    fps: float


def device_stream(names: tuple[str, ...], positions: NDArray[np.float64],
                  rotations: NDArray[np.float64], fps: float, options: EvalOptions
                  ) -> Stream:
    """The devices of ``names`` (positions (F, N, 3), rotations (F, N, 4)) that are in
    the options' tracker set, with the losses of their dropout spec."""
    keep = [i for i, n in enumerate(names) if n in options.devices]
    used = tuple(names[i] for i in keep)
    poses = np.concatenate([positions[:, keep], rotations[:, keep]], axis=-1)
    F = poses.shape[0]
    lost = (dropout_mask(options.dropouts, used, F, fps) if options.dropouts is not None
            else np.zeros((F, len(used)), dtype=bool))
    return Stream(used, poses, lost, fps)


def _solve_sequence(solver: Solver, cal: Calibration, stream: Stream, state: PoseBatch,
                    options: EvalOptions, floor: float, first: NDArray[np.float64] | None,
                    progress: Progress | None) -> tuple[NDArray[np.float64],
                                                        NDArray[np.float64],
                                                        NDArray[np.float64]]:
    """Solve frame by frame as a server does (the set's devices, less the lost ones,
    through ``solver.tracking``); local rotations (F, J, 4), roots (F, 3), solve times
    (F,), each with the making of its targets from the staged frame."""
    F = stream.poses.shape[0]
    J = state.rotations.shape[1]
    rows = TrackingRows(1)
    rows.calibrate(0, cal, stream.names, floor, options.naive, first, options.body)
    slots = slots_of(stream.names)
    row = np.zeros(1, dtype=np.intp)
    offsets = cal.offsets[None]
    rots = np.empty((F, J, 4))
    roots = np.empty((F, 3))
    times = np.empty(F)
    smoother = SlerpSmoother(options.smoothing) if options.smoothing > 0 else None
    for f in range(F):
        seen = ~stream.lost[f]
        rows.stage(0, slots[seen], stream.poses[f, seen], f / stream.fps)
        t0 = time.perf_counter()
        rows.fill(row)
        solver.solve(rows.targets[:1], state, offsets, rows.weights[:1])
        times[f] = time.perf_counter() - t0
        out_q, out_r = state.rotations[0], state.root[0]
        if smoother is not None:
            out_q, out_r = smoother.update(out_q, out_r)
        rots[f] = out_q
        roots[f] = out_r
        if progress is not None and (f % 200 == 0 or f == F - 1):
            progress(f + 1, F)
    return rots, roots, times


Points = Callable[[NDArray[np.float64], NDArray[np.float64]],
                  tuple[NDArray[np.float64], NDArray[np.float64]]]
Resolve = Callable[[NDArray[np.float64], NDArray[np.float64]],
                   tuple[NDArray[np.float64], NDArray[np.float64]]]


@dataclass
class Reconstruction:
    """A recording solved once, with all it takes to score what a viewer shows at any
    delay, with or without prediction, without solving again (``score``)."""

    file: str
    kind: str
    fps: float
    names: list[str]  # the scored points: Vive devices or BVH joints
    held: list[int]  # the held-out ones
    rots: NDArray[np.float64]  # (F, J, 4) solved local rotations
    roots: NDArray[np.float64]  # (F, 3)
    truth_p: NDArray[np.float64]  # (F, P, 3) the recording's points
    truth_q: NDArray[np.float64]  # (F, P, 4)
    tracker_p: NDArray[np.float64]  # (F, E, 3) what drives the solve
    tracker_q: NDArray[np.float64]  # (F, E, 4)
    points: Points  # solved (rots, roots) -> the scored points' (positions, rotations)
    resolve: Resolve  # tracker poses (F, E, 3/4) -> solved (rots, roots), solved afresh
    solve_us_p50: float
    lag_ms: float
    extra: dict[str, float] = field(default_factory=dict)
    _deltas: SequenceDeltas | None = None
    # BVH: the joints on the paths from the root to the trackers, whose rotations the
    # trackers constrain (MPJRE over them: rotation_error_tracked_deg)
    chain: list[int] = field(default_factory=list)
    lost: NDArray[np.bool_] | None = None  # (F, D) which driving device was lost when
    lost_points: list[int] = field(default_factory=list)  # (D,) each one's scored point
    driving: tuple[str, ...] = ()  # (D,) the driving devices, in the order of ``lost``

    def deltas(self, lags: int) -> SequenceDeltas:
        """The solved rotations' and roots' deltas, computed once for every predictor."""
        if self._deltas is None or self._deltas.dq.shape[0] < lags:
            self._deltas = SequenceDeltas.of(self.rots, self.roots[:, None], self.fps, lags)
        return self._deltas

    def shown(self, delay_s: float, predictor: PredictorParams | None, predict_on: str
              ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Solved rotations and roots as shown ``delay_s`` after capture."""
        if predictor is None or delay_s <= 0.0:
            return self.rots, self.roots
        if predict_on == "trackers":
            tq, tp = predict_sequence(self.tracker_q, self.tracker_p, self.fps, delay_s,
                                      predictor)
            return self.resolve(tp, tq)
        rots, roots = self.deltas(lags_needed(predictor, self.fps)).predict(predictor, delay_s)
        return rots, roots[:, 0]


def _at_offset(p: NDArray[np.float64], q: NDArray[np.float64], shift: float
               ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Points (F, P, 3/4) at frame g + shift for every g that has a frame after it:
    positions linearly, rotations by SLERP."""
    F = p.shape[0]
    whole = int(np.floor(shift))
    frac = shift - whole
    n = F - whole - (1 if frac > 1e-9 else 0)
    a = np.arange(n) + whole
    if frac <= 1e-9:
        return p[a], q[a]
    return (p[a] + frac * (p[a + 1] - p[a]),
            R.slerp(q[a], q[a + 1], np.full(q[a].shape[:-1], frac)))


def score(recon: Reconstruction, delay_ms: float = 0.0,
          predictor: PredictorParams | None = None, predict_on: str = "joints",
          with_jitter: bool = True) -> ClipResult:
    """What a viewer shows ``delay_ms`` after each capture, against the recording then."""
    delay_s = max(delay_ms, 0.0) / 1000.0
    rots, roots = recon.shown(delay_s, predictor, predict_on)
    pred_p, pred_q = recon.points(rots, roots)
    true_p, true_q = _at_offset(recon.truth_p, recon.truth_q, delay_s * recon.fps)
    n = true_p.shape[0]
    pos_err = position_error_mm(pred_p[:n], true_p)  # (n, P)
    rot_err = rotation_error_deg(pred_q[:n], true_q)
    extra = dict(recon.extra)
    extra["max_step_mm"] = max_step_mm(pred_p[:n])
    if recon.lost is not None and recon.lost_points:
        lost = recon.lost[:n]
        extra["dropout_frames"] = float(lost.sum())
        if lost.any():
            errors = pos_err[:, recon.lost_points]
            extra["dropout_error_mm"] = float(errors[lost].mean())
    extra["p99_frame_error_mm"] = float(np.percentile(pos_err.mean(axis=1), 99))
    if recon.chain:
        extra["rotation_error_tracked_deg"] = float(rot_err[:, recon.chain].mean())
    if with_jitter:
        extra["jitter_m_s3"] = jitter(pred_p[:n], recon.fps)
    return ClipResult(
        file=recon.file, kind=recon.kind, frames=n,
        position_error_mm={name: float(pos_err[:, i].mean())
                           for i, name in enumerate(recon.names)},
        mean_error_mm=float(pos_err.mean()),
        heldout_error_mm=(float(pos_err[:, recon.held].mean()) if recon.held
                          else float("nan")),
        rotation_error_deg=float(rot_err.mean()), solve_us_p50=recon.solve_us_p50,
        lag_ms=recon.lag_ms, extra=extra,
        p99_error_mm={name: float(np.percentile(pos_err[:, i], 99))
                      for i, name in enumerate(recon.names)})


def max_step_mm(positions: NDArray[np.float64]) -> float:
    """The largest move (mm) of any point (F, P, 3) from one frame to the next."""
    if positions.shape[0] < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(positions, axis=0), axis=-1).max() * 1000.0)


def jitter(positions: NDArray[np.float64], fps: float) -> float:
    """Mean jerk (m/s^3) of trajectories (F, P, 3): the third difference per frame^3."""
    if positions.shape[0] < 4:
        return float("nan")
    jerk = np.diff(positions, 3, axis=0) * fps ** 3
    return float(np.linalg.norm(jerk, axis=-1).mean())


def _evaluate(recon: Reconstruction, options: EvalOptions) -> ClipResult:
    if options.delay_ms is None:
        return score(recon, with_jitter=False)
    return score(recon, options.delay_ms, options.predictor, options.predict_on)


def reconstruct_vive(rec: ViveRecording, options: EvalOptions = EvalOptions(),
                     rig: Rig | None = None, progress: Progress | None = None
                     ) -> Reconstruction:
    rig = rig or build_rig(load_makehuman().skeleton)
    pos0 = {name: rec.positions[0, d] for d, name in enumerate(rec.devices)}
    rot0 = {name: rec.rotations[0, d] for d, name in enumerate(rec.devices)}
    cal = calibrate(rig, pos0, rot0, options.calibration)
    solver = Solver(rig, options.solver, options.solver_options)
    stream = device_stream(rec.devices, rec.positions[1:], rec.rotations[1:], rec.fps,
                           options)

    def solve(positions: NDArray[np.float64], rotations: NDArray[np.float64],
              progress: Progress | None = None) -> tuple[NDArray[np.float64],
                                                         NDArray[np.float64],
                                                         NDArray[np.float64]]:
        driven = dataclasses.replace(stream, poses=np.concatenate([positions, rotations], -1))
        state = PoseBatch(cal.pose[None].copy(), cal.root[None].copy())
        return _solve_sequence(solver, cal, driven, state, options, 0.0, None, progress)

    def points(rots: NDArray[np.float64], roots: NDArray[np.float64]
               ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        gq, gp = forward_kinematics(rig.skeleton, rots, roots, np.broadcast_to(
            cal.offsets, (rots.shape[0], *cal.offsets.shape)))
        return cal.predict(gq, gp, rec.devices)

    def resolve(tp: NDArray[np.float64], tq: NDArray[np.float64]
                ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        rots, roots, _ = solve(tp, tq)
        return rots, roots

    rots, roots, times = solve(stream.poses[..., :3], stream.poses[..., 3:], progress)
    pred_p, _ = points(rots, roots)
    lags = [lag_frames(pred_p[:, rec.device(h)], rec.positions[1:, rec.device(h)])
            for h in ("left_hand", "right_hand")]
    drive = [rec.device(n) for n in stream.names]
    driving_error = position_error_mm(pred_p[:, drive], rec.positions[1:, drive])
    return Reconstruction(
        file=rec.source, kind="vive", fps=rec.fps, names=list(rec.devices),
        held=[d for d, n in enumerate(rec.devices) if n not in stream.names],
        rots=rots, roots=roots, truth_p=rec.positions[1:], truth_q=rec.rotations[1:],
        tracker_p=stream.poses[..., :3], tracker_q=stream.poses[..., 3:], points=points,
        resolve=resolve, solve_us_p50=float(np.median(times) * 1e6),
        lag_ms=float(np.mean(lags) / rec.fps * 1000.0),
        extra={"driving_error_mm": float(driving_error.mean()), "scale": cal.scale},
        lost=stream.lost if options.dropouts is not None else None, lost_points=drive,
        driving=stream.names)


def evaluate_vive(rec: ViveRecording, options: EvalOptions = EvalOptions(),
                  rig: Rig | None = None, progress: Progress | None = None) -> ClipResult:
    return _evaluate(reconstruct_vive(rec, options, rig, progress), options)


def _reference_pose(motion: Motion) -> NDArray[np.float64] | None:
    """The rest pose is the canonical pose's reference when it stands upright (+y);
    otherwise (Bandai's rest pose lies along +x) the first motion frame is."""
    r = role_map(motion.skeleton)
    rest = motion.skeleton.rest_positions()
    up = rest[r["head"][0]] - rest[r["pelvis"][0]]
    if up[1] > 0.8 * np.linalg.norm(up):
        return None
    return np.asarray(motion.rotations[motion.first_frame])


def reconstruct_bvh(motion: Motion, options: EvalOptions = EvalOptions(),
                    progress: Progress | None = None) -> Reconstruction:
    if role_map(motion.skeleton)["pelvis"][0] != 0:
        # the avatar is rooted at the body: a static root above the pelvis is the world
        motion = drop_static_root(motion)
    frames = slice(motion.first_frame, motion.num_frames)
    rot = motion.rotations[frames]
    trans = motion.translations[frames]
    sk = motion.skeleton.with_offsets(trans[0])
    rig = build_rig(sk, _reference_pose(motion))
    gt_q, gt_p = forward_kinematics(sk, rot, trans[:, 0], trans)
    joints = np.array([rig.role(b) for b in BONES], dtype=np.intp)
    stream = device_stream(DEVICES, gt_p[:, joints], gt_q[:, joints], motion.fps, options)
    eff = np.array([rig.role(BONES[SLOT[n]]) for n in stream.names], dtype=np.intp)
    solver = Solver(rig, options.solver, options.solver_options)
    floor = float(gt_p[0, :, 1].min())
    cal = performer_calibration(rig, sk.offsets, gt_p[0, rig.role("head")],
                                gt_q[0, rig.role("head")], floor)
    first = np.concatenate([gt_p[0, joints], gt_q[0, joints]], axis=-1)

    def solve(tp: NDArray[np.float64], tq: NDArray[np.float64],
              progress: Progress | None = None) -> tuple[NDArray[np.float64],
                                                         NDArray[np.float64],
                                                         NDArray[np.float64]]:
        # the avatar starts in its canonical pose, placed on the first frame's pelvis
        state = PoseBatch.canonical(rig, 1)
        driven = dataclasses.replace(stream, poses=np.concatenate([tp, tq], axis=-1))
        return _solve_sequence(solver, cal, driven, state, options, floor, first, progress)

    def points(rots: NDArray[np.float64], roots: NDArray[np.float64]
               ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        q, p = forward_kinematics(sk, rots, roots)
        return p, q

    def resolve(tp: NDArray[np.float64], tq: NDArray[np.float64]
                ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        rots, roots, _ = solve(tp, tq)
        return rots, roots

    rots, roots, times = solve(gt_p[:, eff], gt_q[:, eff], progress)
    p, _ = points(rots, roots)
    tracked = set(int(j) for j in eff)
    lags = [lag_frames(p[:, rig.role(h)], gt_p[:, rig.role(h)]) for h in ("hand_l", "hand_r")]
    return Reconstruction(
        file=motion.source, kind="bvh", fps=motion.fps, names=list(sk.names),
        held=[j for j in range(sk.num_joints) if j not in tracked], rots=rots, roots=roots,
        truth_p=gt_p, truth_q=gt_q, tracker_p=gt_p[:, eff], tracker_q=gt_q[:, eff],
        points=points, resolve=resolve, solve_us_p50=float(np.median(times) * 1e6),
        lag_ms=float(np.mean(lags) / motion.fps * 1000.0),
        chain=tracked_chain(sk.parents, eff),
        lost=stream.lost if options.dropouts is not None else None,
        lost_points=[int(j) for j in eff], driving=stream.names)


def performer_calibration(rig: Rig, offsets: NDArray[np.float64], head_p: NDArray[np.float64],
                          head_q: NDArray[np.float64], floor: float) -> Calibration:
    """A mocap performer calibrated as a player would be from head and hands: their own
    skeleton standing upright in its canonical pose, turned to the head's heading, the
    head where it is; every device role a joint of theirs (identity mounts)."""
    sk = rig.skeleton.with_offsets(offsets)
    pose = rig.canonical.copy()
    cq, _ = global_pose(sk, pose, np.zeros(3))
    head = rig.role("head")
    fwd = R.rotate(R.mul(head_q, R.conjugate(cq[head])), [0.0, 0.0, 1.0])
    yaw = R.from_axis_angle([0.0, 1.0, 0.0], float(np.arctan2(fwd[0], fwd[2])))
    pose[0] = R.mul(yaw, pose[0])
    _, gp = global_pose(sk, pose, np.zeros(3))
    root = head_p - gp[head]
    mounts = {name: Mount(rig.role(DEVICE_BONES[name]), np.zeros(3), R.IDENTITY.copy())
              for name in DEVICES}
    return Calibration(rig, offsets, pose, root, mounts, 1.0)


def tracked_chain(parents: NDArray[np.integer], trackers: NDArray[np.integer]) -> list[int]:
    """The joints from the root to each tracker's joint, trackers included."""
    on: set[int] = set()
    for j in (int(t) for t in trackers):
        while j >= 0 and j not in on:
            on.add(j)
            j = int(parents[j])
    return sorted(on)


def evaluate_bvh(motion: Motion, options: EvalOptions = EvalOptions(),
                 progress: Progress | None = None) -> ClipResult:
    return _evaluate(reconstruct_bvh(motion, options, progress), options)


def summarize(clips: list[ClipResult]) -> dict[str, float]:
    keys = ("mean_error_mm", "heldout_error_mm", "rotation_error_deg", "solve_us_p50")
    out = {k: _mean_of_given([getattr(c, k) for c in clips]) for k in keys}
    if all("jitter_m_s3" in c.extra for c in clips):
        out["jitter_m_s3"] = round(float(np.nanmean([c.extra["jitter_m_s3"] for c in clips])), 1)
    # tails and tracked-chain rotations, averaged over the clips that have them
    for key in ("p99_frame_error_mm", "rotation_error_tracked_deg", "dropout_error_mm"):
        have = [c.extra[key] for c in clips if key in c.extra]
        if have:
            out[key] = round(float(np.mean(have)), 2)
    steps = [c.extra["max_step_mm"] for c in clips if "max_step_mm" in c.extra]
    if steps:  # the largest of any clip
        out["max_step_mm"] = round(float(max(steps)), 2)
    lost = [c.extra["dropout_frames"] for c in clips if "dropout_frames" in c.extra]
    if lost:
        out["dropout_frames"] = int(sum(lost))
    return out


def _mean_of_given(values: list[float]) -> float:
    """The mean of the values that are numbers (NaN: a clip without any, e.g. no held-out
    device when every device drives); NaN when none is."""
    given = [v for v in values if not np.isnan(v)]
    return round(float(np.mean(given)), 2) if given else float("nan")


def summarize_p99(clips: list[ClipResult]) -> dict[str, float]:
    """Each Vive device's p99 error (mm), averaged over the Vive clips."""
    vive = [c for c in clips if c.kind == "vive" and c.p99_error_mm]
    names = sorted({n for c in vive for n in c.p99_error_mm})
    return {n: round(float(np.mean([c.p99_error_mm[n] for c in vive if n in c.p99_error_mm])), 2)
            for n in names}

