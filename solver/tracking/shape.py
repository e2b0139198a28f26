"""An avatar's body as the body model needs it (``layout`` S_*): proportions from its
canonical pose, heights and heading from its calibration pose."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from posecast.solver import rotations as R
from posecast.solver.rig import Rig, global_pose
from posecast.solver.tracking.body_model import SHIPPED, BodyModel
from posecast.solver.tracking.devices import BONES
from posecast.solver.tracking.layout import (
    S_ANKLE,
    S_ARM,
    S_FEET0,
    S_FLAT_FOOT,
    S_FLOOR,
    S_G0_HEAD,
    S_G0_PELVIS,
    S_HAND_DOWN,
    S_HEAD_TO_PELVIS,
    S_HIP,
    S_LEG,
    S_NAIVE,
    S_SHOULDER,
    S_STAND_HEAD,
    S_STAND_PELVIS,
    S_YAW0,
    SHAPE_SIZE,
)

Array = NDArray[np.float64]
# the turn that lowers each arm from the T-pose to hanging at the side (body axes)
_ARM_DOWN = (R.between([1.0, 0.0, 0.0], [0.0, -1.0, 0.0]),
             R.between([-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]))


def body_shape(rig: Rig, offsets: Array, pose: Array, root: Array, floor: float = 0.0,
               naive: bool = False, model: BodyModel = SHIPPED) -> Array:
    """The body constants of an avatar with these bone ``offsets`` calibrated in ``pose``
    (local rotations) at ``root``, standing on a floor at height ``floor``, moving as
    ``model`` says; ``naive``: the baseline model (pelvis straight under the head, legs
    straight down)."""
    sk = rig.skeleton.with_offsets(offsets)
    cq, cp = global_pose(sk, rig.canonical, np.zeros(3))
    gq, gp = global_pose(sk, pose, root)
    role = rig.role
    s = np.zeros(SHAPE_SIZE)
    s[S_G0_HEAD:S_G0_HEAD + 4] = cq[role("head")]
    s[S_G0_PELVIS:S_G0_PELVIS + 4] = cq[role("pelvis")]
    pelvis, head = cp[role("pelvis")], cp[role("head")]
    s[S_HEAD_TO_PELVIS:S_HEAD_TO_PELVIS + 3] = pelvis - head
    lowest = cp[:, 1].min()
    yaw0 = _heading(gq[role("pelvis")], cq[role("pelvis")])
    turn0 = R.from_axis_angle([0.0, 1.0, 0.0], yaw0)
    for k, side in enumerate("lr"):
        thigh, shin, foot = (role(f"{r}_{side}") for r in ("thigh", "shin", "foot"))
        upper, fore, hand = (role(f"{r}_{side}") for r in ("upperarm", "forearm", "hand"))
        s[S_FLAT_FOOT + 4 * k:S_FLAT_FOOT + 4 * k + 4] = cq[foot]
        s[S_HAND_DOWN + 4 * k:S_HAND_DOWN + 4 * k + 4] = R.mul(_ARM_DOWN[k], cq[hand])
        s[S_HIP + 3 * k:S_HIP + 3 * k + 3] = cp[thigh] - pelvis
        s[S_SHOULDER + 3 * k:S_SHOULDER + 3 * k + 3] = cp[upper] - head
        # where each foot stands at calibration: under its hip, on the floor
        hip_at = gp[role("pelvis")] + R.rotate(turn0, cp[thigh] - pelvis)
        s[S_FEET0 + 3 * k:S_FEET0 + 3 * k + 3] = [hip_at[0], floor + cp[foot, 1] - lowest,
                                                  hip_at[2]]
        if k == 0:
            s[S_LEG] = (np.linalg.norm(cp[shin] - cp[thigh])
                        + np.linalg.norm(cp[foot] - cp[shin]))
            s[S_ARM] = (np.linalg.norm(cp[fore] - cp[upper])
                        + np.linalg.norm(cp[hand] - cp[fore]))
            s[S_ANKLE] = cp[foot, 1] - lowest
    s[S_FLOOR] = floor
    s[S_STAND_HEAD] = gp[role("head"), 1]
    s[S_STAND_PELVIS] = floor + pelvis[1] - lowest
    s[S_YAW0] = yaw0
    s[S_NAIVE] = 1.0 if naive else 0.0
    model.write(s)
    return s


def bone_poses(rig: Rig, offsets: Array, pose: Array, root: Array) -> Array:
    """(ND, 7): the global pose of each device's bone in this pose (position, rotation)."""
    gq, gp = global_pose(rig.skeleton.with_offsets(offsets), pose, root)
    joints = [rig.role(b) for b in BONES]
    return np.concatenate([gp[joints], gq[joints]], axis=-1)


def _heading(q: Array, g0: Array) -> float:
    f = R.rotate(R.mul(q, R.conjugate(g0)), [0.0, 0.0, 1.0])
    return float(np.arctan2(f[0], f[2]))
