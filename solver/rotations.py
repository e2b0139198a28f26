"""Quaternion and rotation math over numpy arrays.

Quaternions are stored (..., 4) in the order x, y, z, w (the order of the Vive recordings,
glTF and OpenVR's HmdQuaternion_t reordered). Every function broadcasts over leading axes.
Rotations act on column vectors: ``rotate(q, v)`` is R(q) @ v, and ``mul(a, b)`` applies b
first, then a (so a parent's global rotation times a child's local rotation gives the
child's global rotation).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

IDENTITY = np.array([0.0, 0.0, 0.0, 1.0])


def asarray(q: ArrayLike) -> Array:
    return np.asarray(q, dtype=np.float64)


def identity(shape: tuple[int, ...] = ()) -> Array:
    out = np.zeros((*shape, 4))
    out[..., 3] = 1.0
    return out


def normalize(q: ArrayLike) -> Array:
    q = asarray(q)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    return q / np.where(n > 0.0, n, 1.0)


def canonical(q: ArrayLike) -> Array:
    """The same rotation with w >= 0 (q and -q are one rotation)."""
    q = asarray(q)
    return np.where(q[..., 3:4] < 0.0, -q, q)


def conjugate(q: ArrayLike) -> Array:
    q = asarray(q)
    return q * np.array([-1.0, -1.0, -1.0, 1.0])


inverse = conjugate  # for unit quaternions


def mul(a: ArrayLike, b: ArrayLike) -> Array:
    a = asarray(a)
    b = asarray(b)
    ax, ay, az, aw = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bx, by, bz, bw = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        axis=-1,
    )


def rotate(q: ArrayLike, v: ArrayLike) -> Array:
    """Rotate vectors v (..., 3) by unit quaternions q (..., 4)."""
    q = asarray(q)
    v = asarray(v)
    u = q[..., :3]
    w = q[..., 3:4]
    t = 2.0 * _cross(u, v)
    return v + w * t + _cross(u, t)


def _cross(a: Array, b: Array) -> Array:
    """np.cross for (..., 3) arrays without its axis juggling (3x faster on small arrays)."""
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    bx, by, bz = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], axis=-1)


def from_axis_angle(axis: ArrayLike, angle: ArrayLike) -> Array:
    axis = asarray(axis)
    angle = asarray(angle)
    n = np.linalg.norm(axis, axis=-1, keepdims=True)
    unit = axis / np.where(n > 0.0, n, 1.0)
    half = 0.5 * angle[..., None]
    return np.concatenate([unit * np.sin(half), np.cos(half)], axis=-1)


def from_rotvec(rv: ArrayLike) -> Array:
    """Exponential map: rotation vector (axis * angle) to quaternion."""
    rv = asarray(rv)
    angle = np.linalg.norm(rv, axis=-1)
    half = 0.5 * angle
    # sin(x/2)/x, with its Taylor series near zero
    small = angle < 1e-8
    safe = np.where(small, 1.0, angle)
    k = np.where(small, 0.5 - angle**2 / 48.0, np.sin(half) / safe)
    return np.concatenate([rv * k[..., None], np.cos(half)[..., None]], axis=-1)


def to_rotvec(q: ArrayLike) -> Array:
    """Logarithm map: unit quaternion to rotation vector, angle in [0, pi]."""
    q = canonical(normalize(q))
    s = np.linalg.norm(q[..., :3], axis=-1)
    angle = 2.0 * np.arctan2(s, q[..., 3])
    small = s < 1e-12
    k = np.where(small, 2.0, angle / np.where(small, 1.0, s))
    return q[..., :3] * k[..., None]


def angle(q: ArrayLike) -> Array:
    """Rotation angle of each quaternion, in [0, pi]."""
    q = asarray(q)
    s = np.linalg.norm(q[..., :3], axis=-1)
    return 2.0 * np.arctan2(s, np.abs(q[..., 3]))


def angle_between(a: ArrayLike, b: ArrayLike) -> Array:
    """Angle of the rotation that takes a to b, in [0, pi]."""
    return angle(mul(conjugate(a), b))


def between(u: ArrayLike, v: ArrayLike) -> Array:
    """Shortest-arc rotation taking direction u onto direction v."""
    u, v = np.broadcast_arrays(normalize_vec(u), normalize_vec(v))
    d = np.sum(u * v, axis=-1)
    c = np.cross(u, v)
    q = np.concatenate([c, (1.0 + d)[..., None]], axis=-1)
    # opposite vectors: any axis perpendicular to u. The cross-product axis is good to
    # ~1e-16/|c| and the fixed axis lands |c| away from v: switch where both are ~sqrt(eps).
    opposite = (d < 0.0) & (np.linalg.norm(c, axis=-1) < 3e-8)
    if np.any(opposite):
        perp = np.cross(u, np.array([1.0, 0.0, 0.0]))
        weak = np.linalg.norm(perp, axis=-1) < 1e-6
        perp = np.where(weak[..., None], np.cross(u, np.array([0.0, 1.0, 0.0])), perp)
        flip = np.concatenate([normalize_vec(perp), np.zeros((*d.shape, 1))], axis=-1)
        q = np.where(opposite[..., None], flip, q)
    return normalize(q)


def normalize_vec(v: ArrayLike) -> Array:
    v = asarray(v)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0.0, n, 1.0)


def to_matrix(q: ArrayLike) -> Array:
    """Rotation matrices (..., 3, 3); eq. 1 of the paper."""
    q = asarray(q)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def from_matrix(m: ArrayLike) -> Array:
    """Unit quaternions from rotation matrices (..., 3, 3) (Shepperd's method)."""
    m = asarray(m)
    shape = m.shape[:-2]
    m = m.reshape(-1, 3, 3)
    out = np.empty((m.shape[0], 4))
    tr = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    diag = np.stack([m[:, 0, 0], m[:, 1, 1], m[:, 2, 2], tr], axis=-1)
    case = np.argmax(diag, axis=-1)
    for i, row in enumerate(m):
        c = case[i]
        if c == 3:
            s = 2.0 * np.sqrt(max(1.0 + tr[i], 1e-300))
            out[i] = [(row[2, 1] - row[1, 2]) / s, (row[0, 2] - row[2, 0]) / s,
                      (row[1, 0] - row[0, 1]) / s, 0.25 * s]
        elif c == 0:
            s = 2.0 * np.sqrt(max(1.0 + row[0, 0] - row[1, 1] - row[2, 2], 1e-300))
            out[i] = [0.25 * s, (row[0, 1] + row[1, 0]) / s, (row[0, 2] + row[2, 0]) / s,
                      (row[2, 1] - row[1, 2]) / s]
        elif c == 1:
            s = 2.0 * np.sqrt(max(1.0 + row[1, 1] - row[0, 0] - row[2, 2], 1e-300))
            out[i] = [(row[0, 1] + row[1, 0]) / s, 0.25 * s, (row[1, 2] + row[2, 1]) / s,
                      (row[0, 2] - row[2, 0]) / s]
        else:
            s = 2.0 * np.sqrt(max(1.0 + row[2, 2] - row[0, 0] - row[1, 1], 1e-300))
            out[i] = [(row[0, 2] + row[2, 0]) / s, (row[1, 2] + row[2, 1]) / s, 0.25 * s,
                      (row[1, 0] - row[0, 1]) / s]
    return canonical(normalize(out)).reshape(*shape, 4)


_AXES = {"x": np.array([1.0, 0.0, 0.0]), "y": np.array([0.0, 1.0, 0.0]),
         "z": np.array([0.0, 0.0, 1.0])}


def from_euler(angles: ArrayLike, order: str) -> Array:
    """Quaternions from intrinsic Euler angles in radians.

    ``order`` names the axes in the order they are written, e.g. "zxy" for BVH channels
    "Zrotation Xrotation Yrotation": R = Rz(a0) @ Rx(a1) @ Ry(a2).
    """
    angles = asarray(angles)
    q = identity(angles.shape[:-1])
    for i, name in enumerate(order.lower()):
        q = mul(q, from_axis_angle(_AXES[name], angles[..., i]))
    return q


def slerp(a: ArrayLike, b: ArrayLike, t: ArrayLike) -> Array:
    """Spherical linear interpolation along the shorter arc; t=0 gives a, t=1 gives b."""
    a = asarray(a)
    b = asarray(b)
    t = asarray(t)[..., None]  # t broadcasts against the leading axes of a and b
    d = np.sum(a * b, axis=-1, keepdims=True)
    b = np.where(d < 0.0, -b, b)
    d = np.abs(d)
    theta = np.arccos(np.clip(d, -1.0, 1.0))
    s = np.sin(theta)
    near = s < 1e-9
    safe = np.where(near, 1.0, s)
    wa = np.where(near, 1.0 - t, np.sin((1.0 - t) * theta) / safe)
    wb = np.where(near, t, np.sin(t * theta) / safe)
    return normalize(wa * a + wb * b)


def swing_twist(q: ArrayLike, axis: int = 1) -> tuple[Array, Array]:
    """Split q = swing * twist, where twist turns about the given coordinate axis and
    swing about an axis perpendicular to it. Returns (swing rotation vector, twist angle)."""
    q = canonical(normalize(q))
    tw = np.zeros_like(q)
    tw[..., axis] = q[..., axis]
    tw[..., 3] = q[..., 3]
    n = np.linalg.norm(tw, axis=-1, keepdims=True)
    degenerate = n[..., 0] < 1e-12  # 180 degree swing: twist undefined, take none
    tw = np.where(degenerate[..., None], IDENTITY, tw / np.where(n > 0, n, 1.0))
    twist_angle = 2.0 * np.arctan2(tw[..., axis], tw[..., 3])
    swing = mul(q, conjugate(tw))
    return to_rotvec(swing), twist_angle
