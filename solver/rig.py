"""A skeleton prepared for the solvers: canonical pose, limit frames, effectors, chains.

``build_rig`` maps the limit table of ``solver/limits.py`` onto any skeleton. It first
builds the skeleton's *canonical pose*: the reference pose (the rest pose, or a given
standing frame when the rest pose is not upright, as in the Bandai files) turned to face
+z with +y up, with arms straightened out sideways and legs straight down. Each canonical
joint then gets a limit frame (y along the bone, x from the table; mirrored on the right
side; an elbow or knee that the reference pose bends hinges about the axis it bends
about there) and the local rotation of a joint is

    q_local = pre @ D @ post,   pre = c @ L,  post = L^-1

where c is the canonical local rotation, L turns the limit frame into the joint's local
frame and D is the deviation from the canonical pose whose swing/twist components are
clamped to the limits. Joints without a role (fingers, CMU's hip joints, a static root)
have no degrees of freedom: solvers leave them as they are.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from posecast.solver import rotations as R
from posecast.solver.fk import forward_kinematics
from posecast.solver.limits import spec_for
from posecast.solver.naming import roles as role_map
from posecast.solver.skeleton import Skeleton, SkeletonError

# The six driven bones, in the order of every targets array: (B, 6, 7) = pos + quat
EFFECTORS = ("head", "pelvis", "hand_l", "hand_r", "foot_l", "foot_r")

# the child role that gives each role's bone direction
_BONE_CHILD = {"clavicle": "upperarm", "upperarm": "forearm", "forearm": "hand",
               "thigh": "shin", "shin": "foot", "foot": "toes"}


@dataclass(frozen=True, eq=False)
class Rig:
    skeleton: Skeleton
    roles: dict[str, list[int]]
    canonical: NDArray[np.float64]  # (J, 4) local rotations of the canonical pose
    pre: NDArray[np.float64]  # (J, 4)
    post: NDArray[np.float64]  # (J, 4)
    lo: NDArray[np.float64]  # (J, 3) limits of (x, twist y, z), radians
    hi: NDArray[np.float64]  # (J, 3)
    movable: NDArray[np.bool_]  # (J,) joints a solver may turn
    effectors: NDArray[np.int32]  # (6,) joint index of each effector in EFFECTORS order

    def role(self, name: str) -> int:
        return self.roles[name][0]

    @property
    def body(self) -> list[int]:
        """The joints of the body's named parts (every role's joints): where a display
        error is measured, fingers and the rest left out."""
        return sorted({j for js in self.roles.values() for j in js})

    @property
    def num_dof(self) -> int:
        return int(np.count_nonzero(self.hi - self.lo))


def global_pose(skeleton: Skeleton, local: NDArray[np.float64],
                root: NDArray[np.float64] | None = None) -> tuple[NDArray[np.float64],
                                                                   NDArray[np.float64]]:
    """Global rotations (J,4) and positions (J,3) of one pose: the batched compiled
    forward kinematics for one avatar (set-up code calls this often; a Python loop over
    the joints made calibrating one player take 14 ms of the server's event loop)."""
    root_p = skeleton.offsets[0] if root is None else root
    gq, gp = forward_kinematics(skeleton, np.asarray(local)[None], np.asarray(root_p)[None])
    return gq[0], gp[0]


def _bone_dir(skeleton: Skeleton, roles: dict[str, list[int]], role: str, j: int,
              gq: NDArray[np.float64], gp: NDArray[np.float64]) -> NDArray[np.float64] | None:
    base = role[:-2] if role.endswith(("_l", "_r")) else role
    if base == "hand":
        # the hand twists with the forearm (the wrist has no twist): its limit frame runs
        # along the forearm, so that forearm and hand frames agree in the canonical pose
        forearm = roles["forearm" + role[-2:]][0]
        return R.normalize_vec(gp[j] - gp[forearm])
    child_role = _BONE_CHILD.get(base)
    if child_role is not None and child_role + role[-2:] in roles:  # toes are optional
        child = roles[child_role + role[-2:]][0]
        return R.normalize_vec(gp[child] - gp[j])
    kids = skeleton.children(j)
    if kids:  # e.g. the hand: towards the mean of its children (the fingers)
        return R.normalize_vec(np.mean(gp[kids], axis=0) - gp[j])
    if np.linalg.norm(skeleton.tips[j]) > 1e-9:
        return R.normalize_vec(R.rotate(gq[j], skeleton.tips[j]))
    return None


def _body_frame(roles: dict[str, list[int]], gp: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation (quaternion) taking body axes (x left, y up, z forward) to world."""
    left = gp[roles["thigh_l"][0]] - gp[roles["thigh_r"][0]]
    up = gp[roles["head"][0]] - gp[roles["pelvis"][0]]
    x = R.normalize_vec(left)
    y = R.normalize_vec(up - np.dot(up, x) * x)
    z = np.cross(x, y)
    return R.from_matrix(np.stack([x, y, z], axis=1))


def canonical_pose(skeleton: Skeleton, roles: dict[str, list[int]],
                   reference: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
    """Local rotations of the canonical pose (see the module docstring)."""
    J = skeleton.num_joints
    local = R.identity((J,)) if reference is None else np.array(reference, dtype=np.float64)
    gq, gp = global_pose(skeleton, local)
    # face +z, +y up: turn the root so that the body frame becomes the world frame
    body = _body_frame(roles, gp)
    local[0] = R.mul(R.conjugate(body), local[0])
    role_of = {j[0]: r for r, j in roles.items() if len(j) == 1}
    for j in range(J):  # parents first: straighten each limb bone in turn
        gq, gp = global_pose(skeleton, local)
        role = role_of.get(j)
        if role is None:
            continue
        spec = spec_for(role)
        if not spec.straighten or spec.bone is None:
            continue
        target = np.array(spec.bone) * (np.array([-1.0, 1, 1]) if role.endswith("_r") else 1)
        cur = _bone_dir(skeleton, roles, role, j, gq, gp)
        assert cur is not None
        new_global = R.mul(R.between(cur, target), gq[j])
        parent_q = gq[skeleton.parents[j]] if j > 0 else R.IDENTITY
        local[j] = R.mul(R.conjugate(parent_q), new_global)
    return R.canonical(local)


def _limit_frame(role: str, bone: NDArray[np.float64] | None,
                 hinge: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
    """World rotation of a joint's limit frame in the canonical pose (body = world);
    ``hinge``: the x axis, where the rig shows it (``_hinge_axes``)."""
    spec = spec_for(role)
    right = role.endswith("_r")
    mirror = np.array([-1.0, 1.0, 1.0])
    if bone is not None:
        y = -bone if right else bone  # mirrored frames keep one set of limits for both sides
    else:
        y = np.array(spec.bone if spec.bone is not None else (0.0, 1.0, 0.0))
        y = -(mirror * y) if right else y
    x_ref = -(mirror * np.array(spec.x_ref)) if right else np.array(spec.x_ref)
    if hinge is not None and np.dot(hinge, x_ref) > 0.0:  # else: bent backwards, not a hinge
        x_ref = hinge
    y = R.normalize_vec(y)
    x = x_ref - np.dot(x_ref, y) * y
    if np.linalg.norm(x) < 1e-6:
        raise SkeletonError(f"limit frame of {role}: reference axis runs along the bone")
    x = R.normalize_vec(x)
    z = np.cross(x, y)
    return R.from_matrix(np.stack([x, y, z], axis=1))


def _is_limb_bone(role: str) -> bool:
    base = role[:-2] if role.endswith(("_l", "_r")) else role
    return base in _BONE_CHILD or base in ("hand", "toes")


# A reference pose's elbow (knee) bent less than this may be its carrying angle (elbow,
# 5-20 deg) or the knee's valgus (5-10 deg), not flexion: the default axis stays.
MIN_HINGE_BEND = np.radians(30.0)
_HINGES = {"forearm": ("upperarm", "hand"), "shin": ("thigh", "foot")}  # mid: (upper, end)


def _hinge_axes(skeleton: Skeleton, roles: dict[str, list[int]],
                reference: NDArray[np.float64] | None,
                canon_gq: NDArray[np.float64]) -> dict[str, NDArray[np.float64]]:
    """Elbow and knee hinge axes (world, canonical pose) where the reference pose shows
    them: a bent elbow (knee) bends about its hinge, which is fixed in the upper arm's
    (thigh's) frame. A mocap rig's elbow axis is its own (Bandai's lies 10-40 deg from
    the default, and the default put that much twist in every upper arm)."""
    local = R.identity((skeleton.num_joints,)) if reference is None else np.asarray(reference)
    gq, gp = global_pose(skeleton, local)
    out = {}
    for mid_role, (upper_role, end_role) in _HINGES.items():
        for side in ("_l", "_r"):
            if mid_role + side not in roles:
                continue
            u, m, e = (roles[r + side][0] for r in (upper_role, mid_role, end_role))
            a, b = gp[m] - gp[u], gp[e] - gp[m]
            n = np.cross(a, b)
            if np.arctan2(np.linalg.norm(n), np.dot(a, b)) < MIN_HINGE_BEND:
                continue
            n_upper = R.rotate(R.conjugate(gq[u]), n / np.linalg.norm(n))
            out[mid_role + side] = R.rotate(canon_gq[u], n_upper)
    return out


def build_rig(skeleton: Skeleton, reference: NDArray[np.float64] | None = None,
              style: str | None = None) -> Rig:
    roles = role_map(skeleton, style)
    J = skeleton.num_joints
    canon = canonical_pose(skeleton, roles, reference)
    gq, gp = global_pose(skeleton, canon)
    pre = R.identity((J,))
    post = R.identity((J,))
    lo = np.zeros((J, 3))
    hi = np.zeros((J, 3))
    movable = np.zeros(J, dtype=bool)
    hinges = _hinge_axes(skeleton, roles, reference, gq)
    for role, joints in roles.items():
        for j in joints:
            spec = spec_for(role)
            bone = _bone_dir(skeleton, roles, role, j, gq, gp) if _is_limb_bone(role) else None
            F = _limit_frame(role, bone, hinges.get(role))
            L = R.mul(R.conjugate(gq[j]), F)  # limit frame in the joint's local frame
            pre[j] = R.mul(canon[j], L)
            post[j] = R.conjugate(L)
            lo[j], hi[j] = spec.lo, spec.hi
            movable[j] = True
    effectors = np.array([roles[name][0] for name in EFFECTORS], dtype=np.int32)
    return Rig(skeleton, roles, canon, pre, post, lo, hi, movable, effectors)


def deviation(rig: Rig, local: NDArray[np.float64]) -> NDArray[np.float64]:
    """Per joint (x, twist y, z) of the deviation D from the canonical pose, (..., J, 3)."""
    D = R.mul(R.mul(R.conjugate(rig.pre), local), R.conjugate(rig.post))
    swing, twist = R.swing_twist(D, axis=1)
    return np.stack([swing[..., 0], twist, swing[..., 2]], axis=-1)


def within_limits(rig: Rig, local: NDArray[np.float64], tol: float = 1e-6) -> NDArray[np.bool_]:
    """Which joints of a pose (..., J, 4) respect their limits."""
    d = deviation(rig, local)
    ok = (d >= rig.lo - tol) & (d <= rig.hi + tol)
    return np.all(ok, axis=-1) | ~rig.movable
