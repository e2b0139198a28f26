"""Quaternions over time as Euler angles whose curves stay continuous (for BVH).

Euler angles are what BVH stores, and an animation tool interpolates and filters each
angle's curve on its own, so a curve must not jump where the rotation does not: every
rotation has two Euler solutions, each angle is defined up to whole turns, and at the
singularity (the middle angle at +-90 deg, gimbal lock) only the sum or difference of the
outer two is defined. Per frame this module takes, of the equivalent angle triples, the
one nearest the previous frame's; at the singularity it keeps the previous frame's third
angle and solves the first. The first frame takes the principal solution (middle angle
in [-90, 90] deg, outer ones in (-180, 180]).

Only the order Z, X, Y is implemented (``R = Rz(z) @ Rx(x) @ Ry(y)``, BVH channels
"Zrotation Xrotation Yrotation", the most common order in BVH files): one order is all the
writer needs, and ``rotations.from_euler(angles, "zxy")`` is the inverse.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from posecast.solver import rotations as R

Array = NDArray[np.float64]

ORDER = "zxy"
# cos(middle angle) below this is the singularity: the outer angles' own atan2 arguments
# are then ~1e-7 and would carry ~1e-9 rad of rounding into each, so one is fixed instead
GIMBAL_COS = 1e-7
TURN = 2.0 * np.pi


def euler_zxy(q: Array) -> Array:
    """Angles (F, ..., 3) in radians, (z, x, y) per rotation, continuous along axis 0,
    from unit quaternions (F, ..., 4)."""
    q = R.normalize(np.asarray(q, dtype=np.float64))
    m = R.to_matrix(q)
    # R = Rz(a) Rx(b) Ry(c): R[2,1] = sin b, R[0,1] = -sin a cos b, R[1,1] = cos a cos b,
    # R[2,0] = -cos b sin c, R[2,2] = cos b cos c
    cos_b = np.hypot(m[..., 2, 0], m[..., 2, 2])
    b = np.arctan2(m[..., 2, 1], cos_b)
    a = np.arctan2(-m[..., 0, 1], m[..., 1, 1])
    c = np.arctan2(-m[..., 2, 0], m[..., 2, 2])
    # at the singularity R[1,0], R[0,0] give a + c (b = +90) or a - c (b = -90)
    locked = cos_b < GIMBAL_COS
    sum_or_diff = np.arctan2(m[..., 1, 0], m[..., 0, 0])
    sign = np.sign(b)
    first = np.stack([a, b, c], axis=-1)
    first[0] = np.where(locked[0, ..., None],
                        np.stack([sum_or_diff[0], b[0], np.zeros_like(b[0])], axis=-1),
                        first[0])
    out = np.empty_like(first)
    out[0] = first[0]
    for f in range(1, first.shape[0]):  # each frame depends on the one chosen before
        prev = out[f - 1]
        principal = first[f]
        other = principal + np.array([np.pi, 0.0, np.pi])
        other[..., 1] = np.pi - principal[..., 1]
        near_p = _nearest_turn(principal, prev)
        near_o = _nearest_turn(other, prev)
        use_other = (np.sum((near_o - prev) ** 2, axis=-1)
                     < np.sum((near_p - prev) ** 2, axis=-1))
        chosen = np.where(use_other[..., None], near_o, near_p)
        if np.any(locked[f]):
            held_c = prev[..., 2]
            lock_a = _nearest_turn(sum_or_diff[f] - sign[f] * held_c, prev[..., 0])
            lock_b = _nearest_turn(b[f], prev[..., 1])
            lock = np.stack([lock_a, lock_b, held_c], axis=-1)
            chosen = np.where(locked[f][..., None], lock, chosen)
        out[f] = chosen
    return out


def _nearest_turn(angles: Array, reference: Array) -> Array:
    """Each angle plus the whole turns that bring it nearest its reference."""
    return angles + TURN * np.round((reference - angles) / TURN)
