"""Poses as Unity humanoid bones: the rotations the VMC protocol and VRM avatars expect.

A VRM avatar's normalised rest pose is a T-pose (facing +z, arms straight out sideways,
legs straight down) in which every humanoid bone's rotation is identity, so a bone's
local rotation there is its turn away from the T-pose relative to its humanoid parent's
turn. posecast's canonical pose (``rig.canonical_pose``) is that T-pose for any skeleton
whose roles ``naming.roles`` finds, so for joint j with world rotation G_j in a frame and
G0_j in the canonical pose:

    D_j = G_j G0_j^-1          its turn away from the T-pose, in world axes
    L_b = D_parent(b)^-1 D_b   the Unity bone b's local rotation (Hips: L = D)

Joints between two humanoid bones (a third spine joint, CMU's LHipJoint, Neck1) need no
care: their turns are inside D of the next humanoid bone. Humanoid bones a skeleton lacks
(UpperChest with a two-joint spine, Neck, Toes) are left out, and Chest then carries the
shoulders and neck. Fingers play no role in posecast (the solver never moves them).

Axes: posecast's are right-handed, a body in the canonical pose having x to its left, y
up, z forward; Unity's are left-handed with x to the avatar's right. The map between them
is the mirror x -> -x: positions (-x, y, z), and a rotation R becomes M R M, which for a
quaternion is (x, -y, -z, w). A left arm lowered from the T-pose turns -90 deg about
posecast's z and +90 deg about Unity's z, as Unity users know it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from posecast.solver import rotations as R
from posecast.solver.fk import forward_kinematics
from posecast.solver.naming import roles as role_map
from posecast.solver.rig import canonical_pose, global_pose
from posecast.solver.skeleton import Skeleton

Array = NDArray[np.float64]

# posecast position or vector -> Unity; a quaternion's (x, y, z, w) -> Unity's
MIRROR_POSITION = np.array([-1.0, 1.0, 1.0])
MIRROR_QUATERNION = np.array([1.0, -1.0, -1.0, 1.0])

_SIDES = (("Left", "_l"), ("Right", "_r"))
_ARM = (("Shoulder", "clavicle"), ("UpperArm", "upperarm"), ("LowerArm", "forearm"),
        ("Hand", "hand"))
_LEG = (("UpperLeg", "thigh"), ("LowerLeg", "shin"), ("Foot", "foot"), ("Toes", "toes"))


@dataclass(frozen=True, eq=False)
class HumanoidMap:
    """Which joint of a skeleton each Unity humanoid bone is, parents first."""

    skeleton: Skeleton
    bones: tuple[str, ...]  # Unity HumanBodyBones names: "Hips", "Spine", ...
    joints: NDArray[np.intp]  # (H,) the skeleton joint of each bone
    parents: NDArray[np.intp]  # (H,) the humanoid parent's index in ``bones``, -1 for Hips
    rest_inverse: Array  # (H, 4) G0^-1: each bone's world rotation in the T-pose, inverted
    # (H, 3) each bone's position relative to its humanoid parent in the T-pose, Unity
    # axes, metres (the local position a VRM of these proportions has); Hips: zeros
    rest_local_positions: Array

    def index(self, bone: str) -> int:
        return self.bones.index(bone)


@dataclass(frozen=True, eq=False)
class HumanoidPose:
    """Poses (..., one per frame) as Unity humanoid bones, Unity axes."""

    rotations: Array  # (..., H, 4) each bone's local rotation, x y z w, w >= 0
    hips: Array  # (..., 3) the Hips' world position, metres


def humanoid_map(skeleton: Skeleton) -> HumanoidMap:
    """The Unity humanoid bones of any skeleton ``naming.roles`` maps (SkeletonError,
    naming what is missing, when it cannot)."""
    roles = role_map(skeleton)
    pairs = _bone_joints(roles)
    bones = tuple(name for name, _, _ in pairs)
    joints = np.array([j for _, j, _ in pairs], dtype=np.intp)
    parents = np.array([-1 if p is None else bones.index(p) for _, _, p in pairs],
                       dtype=np.intp)
    gq, gp = global_pose(skeleton, canonical_pose(skeleton, roles))
    rest_pos = gp[joints]
    local = np.where(parents[:, None] >= 0, rest_pos - rest_pos[np.maximum(parents, 0)], 0.0)
    return HumanoidMap(skeleton, bones, joints, parents, R.conjugate(gq[joints]),
                       local * MIRROR_POSITION)


def humanoid_pose(hmap: HumanoidMap, rotations: Array, root: Array) -> HumanoidPose:
    """Local rotations (..., J, 4) and root positions (..., 3) of ``hmap.skeleton``
    as Unity humanoid bones, for one frame or a batch of them."""
    rotations = np.asarray(rotations, dtype=np.float64)
    root = np.asarray(root, dtype=np.float64)
    lead = rotations.shape[:-2]
    gq, gp = forward_kinematics(hmap.skeleton, rotations.reshape(-1, *rotations.shape[-2:]),
                                root.reshape(-1, 3))
    turn = R.mul(gq[:, hmap.joints], hmap.rest_inverse)  # D, (B, H, 4)
    parent_turn = np.where((hmap.parents >= 0)[:, None], turn[:, np.maximum(hmap.parents, 0)],
                           R.IDENTITY)
    local = R.canonical(R.mul(R.conjugate(parent_turn), turn)) * MIRROR_QUATERNION
    hips = gp[:, hmap.joints[0]] * MIRROR_POSITION
    return HumanoidPose(local.reshape(*lead, len(hmap.bones), 4), hips.reshape(*lead, 3))


def _bone_joints(roles: dict[str, list[int]]) -> list[tuple[str, int, str | None]]:
    """(Unity bone, joint, Unity parent) for every humanoid bone the roles give."""
    spine, chest = roles["spine"], roles["chest"][0]
    out: list[tuple[str, int, str | None]] = [("Hips", roles["pelvis"][0], None),
                                              ("Spine", spine[0], "Hips")]
    if len(spine) > 1:  # Unity's UpperChest is the joint that carries the clavicles
        out += [("Chest", spine[-1], "Spine"), ("UpperChest", chest, "Chest")]
    else:
        out.append(("Chest", chest, "Spine"))
    top = out[-1][0]
    head_parent = top
    if "neck" in roles:
        out.append(("Neck", roles["neck"][0], top))
        head_parent = "Neck"
    out.append(("Head", roles["head"][0], head_parent))
    for unity_side, side in _SIDES:
        parent = top
        for unity, role in _ARM:
            out.append((unity_side + unity, roles[role + side][0], parent))
            parent = unity_side + unity
        parent = "Hips"
        for unity, role in _LEG:
            if role + side in roles:  # toes are optional
                out.append((unity_side + unity, roles[role + side][0], parent))
                parent = unity_side + unity
    return out
