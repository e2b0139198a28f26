"""Fitting the template mesh to an avatar's skeleton, joint matrices, and reference skinning.

The viewer draws every avatar with one mesh, the CC0 MakeHuman rig, whose bones have the
template's lengths; each avatar arrives with its own calibrated bone offsets (a body
scale, arms scaled apart: ``solver.calibration``). The mesh is fitted per joint with a
3x3 linear map ``F_j`` in the bone's rest frame, chosen so that each bone's child offsets
map onto the avatar's:

    F_j = argmin  sum_c |F t_c - a_c|^2  +  lam |F - s I|^2

(t_c: template offset of child c, a_c: the avatar's, s: the avatar's overall body scale,
lam: 0.1% of sum |t_c|^2). A bone with one child stretches along its own length to the
avatar's bone length and keeps the body scale across it: a long-armed person gets long
arms, not fat ones; a tall person gets a uniformly larger body. Joints with several
children (pelvis, chest) get the least-squares map of all their child offsets, so
shoulders and hips widen with the skeleton. Leaf joints (head, toes, finger ends) take
their parent's map. Because each ``F_j`` carries its bone's child offsets onto the
avatar's, the parent's and child's joint matrices agree at the joint, and vertices blended
between them do not tear.

The template here is the *bind skeleton* (``bind_offsets``): the mesh's rig with its
hips and knees moved to where calibration puts every avatar's, so that a calibrated
avatar at rest wears the mesh merely scaled. A vertex bound to joint j then goes to
(column vectors, rest rotations are identity; b_j the bind skeleton's joint)

    v' = p_j + R_j F_j (v - b_j)  =  M_j v,   M_j = [R_j F_j | p_j + R_j F_j d_j] @ IB_j

where R_j, p_j are the joint's global rotation and position from forward kinematics on the
*avatar's* offsets, IB_j the mesh's inverse bind matrix (a translation by -rest_j) and
d_j = rest_j - b_j. ``skin`` is the numpy linear blend skinning the GPU's vertex shader is checked
against: v' = sum_k w_k M_{j_k} v. Normals use the same matrices' 3x3 part, renormalised
(exact for rotations and uniform scales; off by the stretch for stretched bones, a
shading nuance).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from posecast.protocol import AvatarInfo
from posecast.solver import rotations as R
from posecast.solver.calibration import EYE_FROM_HEAD_JOINT, leg_joints, raise_leg_pivots
from posecast.solver.fk import forward_kinematics
from posecast.solver.readers.gltf import SkinnedMesh
from posecast.solver.rig import build_rig, global_pose
from posecast.solver.skeleton import Skeleton

Array = NDArray[np.float64]

# regularisation of the fit, relative to the bone's squared child lengths: small enough
# that child offsets map to within 0.1% of their length, large enough to pin the
# directions no child constrains to the body scale
_FIT_LAMBDA = 1e-3


class SkeletonMismatchError(ValueError):
    """An avatar whose skeleton is not the mesh's rig (other joint names or parents)."""


def body_scale(template: Array, offsets: Array) -> float:
    """The avatar's overall scale: the median ratio of its bone lengths to the template's
    (robust to the arms, which calibration scales apart)."""
    t = np.linalg.norm(template, axis=1)
    a = np.linalg.norm(offsets, axis=1)
    ok = t[1:] > 1e-6  # the root's offset is a position, not a bone
    if not np.any(ok):
        return 1.0
    return float(np.median(a[1:][ok] / t[1:][ok]))


def bind_offsets(skeleton: Skeleton) -> Array:
    """The template's offsets with its hips and knees where calibration puts every
    avatar's (``raise_leg_pivots`` at calibration's T-pose, scale 1): the skeleton the
    mesh's flesh is bound to. Fitted to the template's own joints instead, the flesh of
    each thigh moved up with its raised hip while the pelvis' stayed, and the skin between
    them stretched into sheets. A new array each call."""
    return _bind(skeleton)[0].offsets.copy()


# per mesh skeleton (hashed by identity): building its rig takes milliseconds, and every
# avatar that joins is fitted to the same bind skeleton
@functools.lru_cache(maxsize=4)
def _bind(skeleton: Skeleton) -> tuple[Skeleton, Array]:
    """The bind skeleton (see ``bind_offsets``) and FittedAvatar.bind_shift for it."""
    rig = build_rig(skeleton)
    gq, _ = global_pose(skeleton, rig.canonical)  # calibration's T-pose, facing +z
    offsets = skeleton.offsets.copy()
    raise_leg_pivots(skeleton.parents, leg_joints(rig), offsets, gq, [0.0, 1.0, 0.0])
    bind = skeleton.with_offsets(offsets)
    shift = skeleton.rest_positions() - bind.rest_positions()
    offsets.flags.writeable = shift.flags.writeable = False  # shared by every avatar
    return bind, shift


def fit_matrices(skeleton: Skeleton, offsets: Array) -> Array:
    """Per-joint 3x3 maps (J, 3, 3) fitting the template ``skeleton``'s flesh to bone
    ``offsets`` (J, 3) of the same hierarchy; see the module docstring."""
    J = skeleton.num_joints
    s = body_scale(skeleton.offsets, offsets)
    fit = np.empty((J, 3, 3))
    for j in range(J):  # parents first, so a leaf can copy its parent's map
        kids = skeleton.children(j)
        if not kids:
            fit[j] = fit[skeleton.parents[j]] if j > 0 else s * np.eye(3)
            continue
        t = skeleton.offsets[kids]  # (C, 3)
        a = offsets[kids]
        lam = _FIT_LAMBDA * float(np.sum(t * t))
        if lam <= 0.0:
            fit[j] = s * np.eye(3)
            continue
        lhs = a.T @ t + lam * s * np.eye(3)  # sum a t^T + lam s I
        rhs = t.T @ t + lam * np.eye(3)  # sum t t^T + lam I
        fit[j] = np.linalg.solve(rhs.T, lhs.T).T  # lhs @ inv(rhs)
    return fit


@dataclass(frozen=True, eq=False)
class FittedAvatar:
    """An avatar's skeleton prepared for drawing with the template mesh.

    ``order`` maps mesh joint j to the avatar's joint index (identity when the server sends
    the rig's own order), so ``rotations[order]`` are a frame's rotations in mesh order.
    """

    info: AvatarInfo
    offsets: Array  # (J, 3) the avatar's bone offsets, mesh joint order
    fit: Array  # (J, 3, 3) see fit_matrices
    order: NDArray[np.intp]  # (J,)
    scale: float  # body scale relative to the template
    eye: Array  # (3,) the eyes in the head joint's frame (first-person camera)
    # (J, 3) the mesh's rest joints less the bind skeleton's (``bind_offsets``): the
    # skinning matrices bind the flesh to the latter
    bind_shift: Array


def fit_avatar(mesh: SkinnedMesh, info: AvatarInfo) -> FittedAvatar:
    """Match ``info``'s joints to the mesh's by name and fit the mesh to its offsets.

    Raises SkeletonMismatchError when the avatar's skeleton is not the mesh's rig.
    """
    sk = mesh.skeleton
    index = {name: i for i, name in enumerate(info.joint_names)}
    missing = [n for n in sk.names if n not in index]
    if missing:
        raise SkeletonMismatchError(
            f"avatar {info.avatar_id} ({info.display_name!r}): its skeleton lacks the mesh "
            f"joints {', '.join(missing[:5])}{' ...' if len(missing) > 5 else ''}")
    order = np.array([index[n] for n in sk.names], dtype=np.intp)
    parents = np.asarray(info.parents)[order]
    expected = np.where(sk.parents >= 0, order[np.maximum(sk.parents, 0)], -1)
    if not np.array_equal(parents, expected):
        raise SkeletonMismatchError(
            f"avatar {info.avatar_id} ({info.display_name!r}): its joint hierarchy differs "
            f"from the mesh's rig")
    offsets = np.asarray(info.rest_offsets, dtype=np.float64)[order]
    bind, shift = _bind(sk)
    scale = body_scale(bind.offsets, offsets)
    return FittedAvatar(info, offsets, fit_matrices(bind, offsets), order, scale,
                        EYE_FROM_HEAD_JOINT * scale, shift)


def template_avatar(mesh: SkinnedMesh, avatar_id: int = 0, name: str = "template",
                    offsets: Array | None = None) -> FittedAvatar:
    """A FittedAvatar for the mesh's own rig (tests, benches), optionally re-boned."""
    sk = mesh.skeleton
    info = AvatarInfo(avatar_id=avatar_id, display_name=name, joint_names=sk.names,
                      parents=tuple(int(p) for p in sk.parents),
                      rest_offsets=bind_offsets(sk) if offsets is None else offsets)
    return fit_avatar(mesh, info)


def joint_matrices(global_rot: Array, global_pos: Array, fit: Array,
                   inverse_bind: NDArray[np.floating], bind_shift: Array | None = None,
                   ) -> Array:
    """Skinning matrices (..., J, 4, 4): M_j = [R_j F_j | p_j + R_j F_j d_j] @ IB_j.

    ``global_rot`` (..., J, 4), ``global_pos`` (..., J, 3), ``fit`` (..., J, 3, 3) (the
    avatars' fit_matrices; identity for the template), ``inverse_bind`` (J, 4, 4) (the
    mesh's: a translation by -rest_j), ``bind_shift`` (..., J, 3) d_j = rest_j - bind_j
    (FittedAvatar.bind_shift; zero by default): the flesh turns about the bind joints.
    """
    rot = R.to_matrix(global_rot)  # (..., J, 3, 3)
    m = np.zeros((*rot.shape[:-2], 4, 4))
    m[..., :3, :3] = rot @ fit
    m[..., :3, 3] = global_pos
    if bind_shift is not None:
        m[..., :3, 3] += np.einsum("...ij,...j->...i", m[..., :3, :3], bind_shift)
    m[..., 3, 3] = 1.0
    return m @ np.asarray(inverse_bind, dtype=np.float64)


def skin(positions: NDArray[np.floating], joints: NDArray[np.integer],
         weights: NDArray[np.floating], matrices: Array) -> Array:
    """Linear blend skinning, the reference for the GPU: (V, 3) positions from bind-pose
    ``positions`` (V, 3), ``joints``/``weights`` (V, 4) and joint ``matrices`` (J, 4, 4)."""
    p = np.asarray(positions, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    m = matrices[np.asarray(joints, dtype=np.intp)]  # (V, 4, 4, 4)
    blended = np.einsum("vk,vkij->vij", w, m)  # (V, 4, 4)
    return np.einsum("vij,vj->vi", blended[:, :3, :3], p) + blended[:, :3, 3]


def pose_matrices(avatars: Sequence[FittedAvatar], mesh: SkinnedMesh,
                  rotations: Sequence[Array] | Array,
                  roots: Sequence[Array] | Array) -> tuple[Array, Array, Array]:
    """Everything a frame needs for B avatars: skinning matrices (B, J, 4, 4) and global
    rotations/positions (B, J, 4)/(B, J, 3); inputs in the avatars' own joint order."""
    rot = np.stack([np.asarray(rotations[b])[a.order] for b, a in enumerate(avatars)])
    offsets = np.stack([a.offsets for a in avatars])
    # one FK call for every avatar: they share the mesh's hierarchy, not its bone lengths
    gq, gp = forward_kinematics(mesh.skeleton, rot, np.asarray(roots), offsets)
    fit = np.stack([a.fit for a in avatars])
    shift = np.stack([a.bind_shift for a in avatars])
    return joint_matrices(gq, gp, fit, mesh.inverse_bind, shift), gq, gp
