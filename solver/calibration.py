"""Calibration from a T-pose frame: the person's bone lengths and each device's mounting.

Two methods:
- ``uniform``: the paper's (eqs. 1-5): one scale s = HMD height / head-bone height,
  the avatar turned to the user's heading and moved under the HMD.
- ``fit`` (default): the body scaled so that its eyes meet the HMD, the arms scaled
  separately so that the wrists meet the controllers (arm span varies independently of
  height), the arms aimed at the controllers, the pelvis under the head, the hip joints
  and the knees raised to where the legs pivot and bend as the trackers see it (the
  ankles kept in place).

Only the head and hands shape the body; every device then gets a *mount*: its pose in
the frame of the bone it is strapped to, fixed at this frame (a forearm tracker follows
only part of its bone's twist: ``FOREARM_TWIST_SHARE``; a knee tracker rides around the
knee as it bends: ``KNEE_BEND_SHARE``, and turns outwards: ``KNEE_TURN_OUT``). The
devices of the avatar's tracker set give the solver its targets through their mounts
(``solver.tracking``); the others (held out in an evaluation) are only predicted.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from posecast.solver import rotations as R
from posecast.solver.kernels import bone_targets
from posecast.solver.rig import EFFECTORS, Rig, global_pose

# device -> the bone (role) it is mounted on. A forearm tracker is on the forearm whatever
# the template's elbow says (it keeps its distance to the wrist; a nearest-bone rule put
# it on the upper arm and lost the elbow's bend). A knee tracker is mounted at the knee
# joint and rides around it (KNEE_BEND_SHARE).
DEVICE_BONES: dict[str, str] = {
    "head": "head", "hip": "pelvis", "left_hand": "hand_l", "right_hand": "hand_r",
    "left_foot": "foot_l", "right_foot": "foot_r",
    "left_forearm": "forearm_l", "right_forearm": "forearm_r",
    "left_knee": "shin_l", "right_knee": "shin_r", "chest": "chest",
}
# driving device of each effector, in rig.EFFECTORS order
EFFECTOR_DEVICES = ("head", "hip", "left_hand", "right_hand", "left_foot", "right_foot")
# what a calibration cannot do without: the height, the arm span and the heading
CALIBRATION_DEVICES = ("head", "left_hand", "right_hand")

# Priors of the fit, in body coordinates (x left, y up, z forward), metres
EYE_FROM_HEAD_JOINT = np.array([0.0, 0.06, 0.09])  # HMD origin sits at the eyes
# How far a held controller's origin lies past the wrist, along the arm (metres): it sets
# the arm length fitted to the controllers. Too long an arm keeps the model's elbow
# straighter than the real one when reaching
# (docs/decisions/0024-calibration-fits-the-person.md).
CONTROLLER_BEYOND_WRIST = 0.12

METHODS = ("fit", "uniform")
GRIP_TWIST = 0.0  # radians; the recordings give no clear winner
# How far above the template's hip joints (metres, before scaling) the legs pivot in the
# hip tracker's frame: the belt tracker turns with the lower back, not the pelvis, so the
# pivot it sees lies above the anatomical joint
# (docs/decisions/0024-calibration-fits-the-person.md).
HIP_PIVOT_RAISE = 0.06
# How far above the template's knees (metres, before scaling) the legs bend as the knee
# trackers see it: their strap on the thigh's soft tissue turns as if the knee bent there.
# Shins lengthen and thighs shorten to match, the ankles stay; the avatar's knee bends there.
KNEE_PIVOT_RAISE = 0.12
# How the arm is rolled in the T-pose (radians): the upper arm turned outwards (elbow
# crease up) and the forearm pronated as much, palm down either way. The hand does not
# tell these apart; the forearm trackers do, and disagree with the template's roll.
ARM_ROLL = float(np.radians(90.0))
# Share of the forearm's twist that a forearm tracker follows: strapped just below the
# elbow, it turns with the skin, not with the wrist.
FOREARM_TWIST_SHARE = 0.5
TWIST_SHARE_DEVICES = ("left_forearm", "right_forearm")
# Share of the knee's bend that a knee tracker's position follows: strapped on the thigh
# above the knee, it turns with the thigh but rides around the joint with the soft tissue
# as the knee flexes. Its rotation stays the thigh's (following the knee was worse).
KNEE_BEND_SHARE = 0.25
BEND_SHARE_DEVICES = ("left_knee", "right_knee")
# How far (radians) a knee tracker turns outwards about the hip-ankle line as the knee
# bends, growing with the bend up to KNEE_TURN_FULL_BEND. Mocap shows no such turn of the
# bones, so it is the strap's, and lives in the tracker's mount, not in the solver.
KNEE_TURN_OUT = float(np.radians(8.0))
KNEE_TURN_FULL_BEND = float(np.radians(60.0))


@dataclass(frozen=True)
class Mount:
    """A device rigidly attached to a bone: device = bone * (rotation, position)."""

    joint: int
    position: NDArray[np.float64]  # (3,) in the bone's frame
    rotation: NDArray[np.float64]  # (4,)
    # share of the bone's twist (about its limit y axis) the device follows: a tracker
    # strapped along a forearm turns with the skin under it, not with the wrist
    twist_share: float = 1.0
    # > 0: the device is strapped on the parent bone near this joint and rides around it;
    # its position (about the joint) follows this share of the joint's rotation away
    # from the canonical pose, its rotation (then in the parent bone's frame) the
    # parent's (KNEE_BEND_SHARE)
    bend_share: float = 0.0
    # with bend_share: how far (radians, signed for its side) the device turns about the
    # hip-ankle line once the knee is bent KNEE_TURN_FULL_BEND or more (KNEE_TURN_OUT)
    turn_out: float = 0.0


@dataclass(frozen=True, eq=False)
class Calibration:
    rig: Rig
    offsets: NDArray[np.float64]  # (J, 3) the person's bone offsets
    pose: NDArray[np.float64]  # (J, 4) local rotations at the calibration frame
    root: NDArray[np.float64]  # (3,) root position at the calibration frame
    mounts: dict[str, Mount]
    scale: float  # overall body scale against the template

    def targets(self, positions: NDArray[np.float64], rotations: NDArray[np.float64],
                devices: tuple[str, ...]) -> NDArray[np.float64]:
        """Bone targets (F, 6, 7) for the solver from device poses (F, D, 3/4)."""
        idx = [devices.index(name) for name in EFFECTOR_DEVICES]
        F, E = positions.shape[0], len(EFFECTORS)
        device = np.concatenate([positions[:, idx], rotations[:, idx]], axis=-1)
        mount_p, mount_q = self.effector_mounts()
        out = np.empty((F, E, 7))
        bone_targets(device.reshape(F * E, 7), np.tile(mount_p, (F, 1)),
                     np.tile(mount_q, (F, 1)), out.reshape(F * E, 7))
        return out

    def effector_mounts(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The driving devices' mount positions (6, 3) and rotations (6, 4), in
        EFFECTOR_DEVICES order."""
        mounts = [self.mounts[d] for d in EFFECTOR_DEVICES]
        return (np.array([m.position for m in mounts]), np.array([m.rotation for m in mounts]))

    def predict(self, gq: NDArray[np.float64], gp: NDArray[np.float64],
                devices: tuple[str, ...]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Device positions (F, D, 3) and rotations (F, D, 4) implied by global bone poses
        (F, J, 4) and (F, J, 3)."""
        pos = np.empty((gq.shape[0], len(devices), 3))
        rot = np.empty((gq.shape[0], len(devices), 4))
        for d, name in enumerate(devices):
            m = self.mounts[name]
            bq = gq[:, m.joint]
            if m.bend_share > 0.0:
                parent_q = gq[:, self.rig.skeleton.parents[m.joint]]
                frame = _partly_bent(self.rig, m.joint, parent_q, bq, m.bend_share)
                pos[:, d] = gp[:, m.joint] + R.rotate(frame, m.position)
                rot[:, d] = R.mul(parent_q, m.rotation)
                if m.turn_out != 0.0:
                    pos[:, d], rot[:, d] = _turned_out(self.rig, m, gq, gp, pos[:, d],
                                                       rot[:, d])
                continue
            if m.twist_share != 1.0:
                parent = self.rig.skeleton.parents[m.joint]
                bq = _partly_twisted(self.rig, m.joint, gq[:, parent], bq, m.twist_share)
            pos[:, d] = gp[:, m.joint] + R.rotate(bq, m.position)
            rot[:, d] = R.mul(bq, m.rotation)
        return pos, rot


def _heading(positions: dict[str, NDArray[np.float64]]) -> NDArray[np.float64]:
    """Rotation from body axes to world at the T-pose: left from the right hand to the
    left hand, up +y, forward = left x up... (x left, y up, z forward)."""
    left = positions["left_hand"] - positions["right_hand"]
    left[1] = 0.0
    x = R.normalize_vec(left)
    y = np.array([0.0, 1.0, 0.0])
    z = np.cross(x, y)
    return R.from_matrix(np.stack([x, y, z], axis=1))


def _aim(rig: Rig, offsets: NDArray[np.float64], pose: NDArray[np.float64],
         root: NDArray[np.float64], upper: int, end: int,
         target: NDArray[np.float64]) -> None:
    """Turn the upper bone so that the end joint points at the target (straight limb)."""
    gq, gp = global_pose(rig.skeleton.with_offsets(offsets), pose, root)
    rot = R.between(gp[end] - gp[upper], target - gp[upper])
    parent = rig.skeleton.parents[upper]
    pose[upper] = R.mul(R.conjugate(gq[parent]), R.mul(rot, gq[upper]))


def calibrate(rig: Rig, positions: dict[str, NDArray[np.float64]],
              rotations: dict[str, NDArray[np.float64]], method: str = "fit") -> Calibration:
    """Calibrate from one T-pose frame of device poses (world metres, +y up, floor y=0).
    The head and hands shape the body (its height, arm span and heading); every device
    given gets a mount."""
    if method not in METHODS:
        raise ValueError(f"unknown calibration {method!r}: choose one of {', '.join(METHODS)}")
    missing = [d for d in CALIBRATION_DEVICES if d not in positions]
    if missing:
        raise ValueError(f"calibration needs the devices {', '.join(missing)}")
    sk = rig.skeleton
    head_j = rig.role("head")
    yaw = _heading(positions)
    _canon_gq, canon_gp = global_pose(sk, rig.canonical)
    floor = canon_gp[:, 1].min() if method == "fit" else 0.0
    hmd = positions["head"]
    offsets = sk.offsets.copy()
    if method == "uniform":
        # eqs. 1-5: s = HMD height / head height; turned to the user; under the HMD
        s = hmd[1] / canon_gp[head_j, 1]
        offsets *= s
        pose = rig.canonical.copy()
        pose[0] = R.mul(yaw, pose[0])
        root = np.array([hmd[0], offsets[0][1], hmd[2]])  # eq. 2: under the HMD
    else:
        eye_height = canon_gp[head_j, 1] - floor + EYE_FROM_HEAD_JOINT[1]
        s = (hmd[1] - 0.0) / eye_height
        offsets *= s
        # arms: scale upper arm and forearm so that the wrists reach the controllers
        span = np.linalg.norm((positions["left_hand"] - positions["right_hand"])[[0, 2]])
        wl, wr = rig.role("hand_l"), rig.role("hand_r")
        span_model = abs(canon_gp[wl, 0] - canon_gp[wr, 0]) * s
        arm_model = 0.0
        for side in "lr":
            for role in ("forearm", "hand"):
                arm_model += float(np.linalg.norm(offsets[rig.role(f"{role}_{side}")]))
        wrist_span = span - 2.0 * CONTROLLER_BEYOND_WRIST
        k = 1.0 + (wrist_span - span_model) / arm_model
        k = float(np.clip(k, 0.8, 1.25))
        for side in "lr":
            for role in ("forearm", "hand"):
                offsets[rig.role(f"{role}_{side}")] *= k
        pose = rig.canonical.copy()
        pose[0] = R.mul(yaw, pose[0])
        # place the avatar: its eyes at the HMD, feet on the floor
        root = np.zeros(3)
        gq, gp = global_pose(sk.with_offsets(offsets), pose, root)
        eye = gp[head_j] + R.rotate(yaw, EYE_FROM_HEAD_JOINT * s)
        root = np.array([hmd[0] - eye[0], -gp[:, 1].min(), hmd[2] - eye[2]])
        # arms: aim each straight arm at its controller's wrist point
        for side, dev in (("l", "left_hand"), ("r", "right_hand")):
            upper, end = rig.role(f"upperarm_{side}"), rig.role(f"hand_{side}")
            gq, gp = global_pose(sk.with_offsets(offsets), pose, root)
            out = R.normalize_vec(gp[end] - gp[rig.role(f"upperarm_{side}")])
            _aim(rig, offsets, pose, root, upper, end,
                 positions[dev] - CONTROLLER_BEYOND_WRIST * out)
        # the grip: the forearm twist of the calibration pose (palm down = 0), and the
        # roll of the upper arm (ARM_ROLL), which the forearm undoes
        for side in "lr":
            j = rig.role(f"forearm_{side}")
            t4 = R.from_axis_angle([0.0, 1.0, 0.0], GRIP_TWIST + ARM_ROLL)
            pose[j] = R.mul(R.mul(rig.pre[j], t4), rig.post[j])
            u = rig.role(f"upperarm_{side}")
            roll = R.from_axis_angle([0.0, 1.0, 0.0], -ARM_ROLL)
            pose[u] = R.mul(pose[u], R.mul(R.conjugate(rig.post[u]), R.mul(roll, rig.post[u])))
        # the legs pivot and bend higher in the trackers' frames than the template's
        # hip joints and knees (HIP_PIVOT_RAISE, KNEE_PIVOT_RAISE): raise both, the
        # T-pose ankles staying where they were
        gq, gp = global_pose(sk.with_offsets(offsets), pose, root)
        raise_leg_pivots(sk.parents, leg_joints(rig), offsets, gq,
                         R.rotate(yaw, [0.0, s, 0.0]))
    mounts = {name: mount_device(rig, offsets, pose, root, name, p, rotations[name])
              for name, p in positions.items()}
    return Calibration(rig, offsets, pose, root, mounts, float(s))


def mount_device(rig: Rig, offsets: NDArray[np.float64], pose: NDArray[np.float64],
                 root: NDArray[np.float64], name: str, position: NDArray[np.float64],
                 rotation: NDArray[np.float64]) -> Mount:
    """The mount of a device seen at ``position``, ``rotation`` while the body is in
    ``pose`` at ``root``: at the calibration, or, for a device switched on later, in the
    body's pose as last solved."""
    sk = rig.skeleton
    gq, gp = global_pose(sk.with_offsets(offsets), pose, root)
    joint = rig.role(DEVICE_BONES[name])
    if name in BEND_SHARE_DEVICES:
        parent_q = gq[sk.parents[joint]]
        frame = _partly_bent(rig, joint, parent_q, gq[joint], KNEE_BEND_SHARE)
        return Mount(joint, R.rotate(R.conjugate(frame), position - gp[joint]),
                     R.mul(R.conjugate(parent_q), rotation), bend_share=KNEE_BEND_SHARE,
                     turn_out=KNEE_TURN_OUT * (-1.0 if name == "left_knee" else 1.0))
    share = FOREARM_TWIST_SHARE if name in TWIST_SHARE_DEVICES else 1.0
    bq = gq[joint]
    if share != 1.0:
        bq = _partly_twisted(rig, joint, gq[sk.parents[joint]], bq, share)
    inv = R.conjugate(bq)
    return Mount(joint, R.rotate(inv, position - gp[joint]), R.mul(inv, rotation), share)


def leg_joints(rig: Rig) -> list[tuple[int, int, int]]:
    """Each leg's (thigh, shin, foot) joints, left then right: ``raise_leg_pivots``'s legs."""
    return [(rig.role(f"thigh_{side}"), rig.role(f"shin_{side}"), rig.role(f"foot_{side}"))
            for side in "lr"]


def raise_leg_pivots(parents: NDArray[np.integer], legs: list[tuple[int, int, int]],
                     offsets: NDArray[np.float64], gq: NDArray[np.float64],
                     up: ArrayLike) -> None:
    """Move each leg's (thigh, shin, foot) hip joint HIP_PIVOT_RAISE and knee
    KNEE_PIVOT_RAISE along ``up`` (world; its length is the body scale), the ankle staying:
    ``offsets`` (J, 3) change in place, ``gq`` (J, 4) are the pose's global rotations.
    Calibration does it to the person's T-pose; the viewer to the template's (scale 1), so
    that its flesh binds to the joints the avatars move."""
    hip_lift = HIP_PIVOT_RAISE * np.asarray(up, dtype=np.float64)
    knee_lift = KNEE_PIVOT_RAISE * np.asarray(up, dtype=np.float64)
    for thigh, shin, foot in legs:
        offsets[thigh] += R.rotate(R.conjugate(gq[parents[thigh]]), hip_lift)
        offsets[shin] += R.rotate(R.conjugate(gq[thigh]), knee_lift - hip_lift)
        offsets[foot] -= R.rotate(R.conjugate(gq[shin]), knee_lift)


def _from_canonical(rig: Rig, j: int, parent_q: NDArray[np.float64],
                    joint_q: NDArray[np.float64]) -> NDArray[np.float64]:
    """Joint j's rotation away from the canonical pose, in its limit frame (local =
    pre D post)."""
    local = R.mul(R.conjugate(parent_q), joint_q)
    return R.mul(R.mul(R.conjugate(rig.pre[j]), local), R.conjugate(rig.post[j]))


def _partly_bent(rig: Rig, j: int, parent_q: NDArray[np.float64],
                 joint_q: NDArray[np.float64], share: float) -> NDArray[np.float64]:
    """Global rotation(s) of joint j turned only `share` of the way from the canonical
    pose (a straight knee) to its rotation (the shorter way, about the same axis)."""
    D = _from_canonical(rig, j, parent_q, joint_q)
    part = R.mul(rig.pre[j], R.mul(R.from_rotvec(share * R.to_rotvec(D)), rig.post[j]))
    return R.mul(parent_q, part)


def _partly_twisted(rig: Rig, j: int, parent_q: NDArray[np.float64],
                    joint_q: NDArray[np.float64], share: float) -> NDArray[np.float64]:
    """Global rotation(s) of joint j with only `share` of its twist (about its limit y
    axis, away from the canonical pose) kept."""
    _swing, twist = R.swing_twist(_from_canonical(rig, j, parent_q, joint_q), axis=1)
    undo = R.from_axis_angle([0.0, 1.0, 0.0], -(1.0 - share) * np.asarray(twist))
    return R.mul(joint_q, R.mul(R.conjugate(rig.post[j]), R.mul(undo, rig.post[j])))


def _turned_out(rig: Rig, m: Mount, gq: NDArray[np.float64], gp: NDArray[np.float64],
                pos: NDArray[np.float64], rot: NDArray[np.float64]
                ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A knee tracker's poses (F, 3) and (F, 4) turned about each frame's hip-ankle line
    by m.turn_out, in proportion to the knee's bend up to KNEE_TURN_FULL_BEND."""
    hip = rig.skeleton.parents[m.joint]
    ankle = int(np.flatnonzero(rig.skeleton.parents == m.joint)[0])
    bend = R.angle(_from_canonical(rig, m.joint, gq[:, hip], gq[:, m.joint]))
    share = np.minimum(bend / KNEE_TURN_FULL_BEND, 1.0)
    turn = R.from_axis_angle(R.normalize_vec(gp[:, ankle] - gp[:, hip]), m.turn_out * share)
    return gp[:, hip] + R.rotate(turn, pos - gp[:, hip]), R.mul(turn, rot)
