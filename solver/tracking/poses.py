"""Compiled helpers over poses held as tuples: a position (3) and a rotation (4), read
from and written to flat rows, composed, blended and turned about the vertical."""

from __future__ import annotations

import math

from numba import njit

from posecast.solver.kernels import tbetween, tconj, tmul, tnormalize, trotate

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]


@njit(cache=True, inline="always")
def read_pose(a, i):
    """The pose stored at a[i:i + 7] (position, rotation x y z w)."""
    return (a[i], a[i + 1], a[i + 2]), (a[i + 3], a[i + 4], a[i + 5], a[i + 6])


@njit(cache=True, inline="always")
def write_pose(a, i, p, q):
    a[i], a[i + 1], a[i + 2] = p[0], p[1], p[2]
    a[i + 3], a[i + 4], a[i + 5], a[i + 6] = q[0], q[1], q[2], q[3]


@njit(cache=True, inline="always")
def read3(a, i):
    return (a[i], a[i + 1], a[i + 2])


@njit(cache=True, inline="always")
def write3(a, i, v):
    a[i], a[i + 1], a[i + 2] = v[0], v[1], v[2]


@njit(cache=True, inline="always")
def write4(a, i, q):
    a[i], a[i + 1], a[i + 2], a[i + 3] = q[0], q[1], q[2], q[3]


@njit(cache=True, inline="always")
def read4(a, i):
    return (a[i], a[i + 1], a[i + 2], a[i + 3])


@njit(cache=True, inline="always")
def add(a, b):
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


@njit(cache=True, inline="always")
def sub(a, b):
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


@njit(cache=True, inline="always")
def scale(a, k):
    return (a[0] * k, a[1] * k, a[2] * k)


@njit(cache=True, inline="always")
def lerp3(a, b, t):
    return (a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t, a[2] + (b[2] - a[2]) * t)


@njit(cache=True)
def nlerp(a, b, t):
    """Rotations blended along the shorter arc (t = 0: a, 1: b)."""
    if a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3] < 0.0:
        b = (-b[0], -b[1], -b[2], -b[3])
    return tnormalize((a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t,
                       a[2] + (b[2] - a[2]) * t, a[3] + (b[3] - a[3]) * t))


@njit(cache=True)
def relative(ap, aq, p, q):
    """The pose (p, q) in the frame of the pose (ap, aq)."""
    inv = tconj(aq)
    return trotate(inv, sub(p, ap)), tmul(inv, q)


@njit(cache=True)
def compose(ap, aq, p, q):
    """The pose (p, q), given in the frame of (ap, aq), in world."""
    return add(ap, trotate(aq, p)), tmul(aq, q)


@njit(cache=True, inline="always")
def yaw_quat(angle):
    """A turn about +y."""
    return (0.0, math.sin(0.5 * angle), 0.0, math.cos(0.5 * angle))


@njit(cache=True)
def heading(q, g0):
    """The heading (rad about +y, 0 = facing +z) of a joint's rotation q whose canonical
    rotation (facing +z) is g0."""
    f = trotate(tmul(q, tconj(g0)), (0.0, 0.0, 1.0))
    if f[0] * f[0] + f[2] * f[2] < 1e-12:  # facing straight up or down: any heading
        return 0.0
    return math.atan2(f[0], f[2])


@njit(cache=True, inline="always")
def wrap(a):
    """An angle in (-pi, pi]."""
    return math.atan2(math.sin(a), math.cos(a))


@njit(cache=True, inline="always")
def smoothstep(x):
    x = min(max(x, 0.0), 1.0)
    return x * x * (3.0 - 2.0 * x)


@njit(cache=True)
def arc(pivot, a, qa, b, qb, t):
    """A pose from (a, qa) at t = 0 to (b, qb) at t = 1 on a path that swings about
    ``pivot``, its distance from it changing evenly (a straight path may pass through the
    pivot), its rotation turning with the swing (so that a hand keeps its turn relative
    to the arm, and the elbow, which follows it, does not swing about)."""
    ua, ub = sub(a, pivot), sub(b, pivot)
    la = math.sqrt(ua[0] ** 2 + ua[1] ** 2 + ua[2] ** 2)
    lb = math.sqrt(ub[0] ** 2 + ub[1] ** 2 + ub[2] ** 2)
    if la < 1e-6 or lb < 1e-6:
        return lerp3(a, b, t), nlerp(qa, qb, t)
    whole = tbetween(ua, ub)
    turn = nlerp((0.0, 0.0, 0.0, 1.0), whole, t)
    q = tmul(turn, nlerp(qa, tmul(tconj(whole), qb), t))
    return add(pivot, scale(trotate(turn, ua), (la + (lb - la) * t) / la)), q
