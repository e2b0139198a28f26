"""Compiled building blocks of the solvers: quaternion math, forward kinematics, joint
limits, chain Jacobians and damped least squares.

Why compiled (numba): a solve walks joint chains and iterates, sequential work on
4-element arrays where each numpy call would cost about a microsecond of overhead. The
batched drivers in ``solver/ik/`` loop over avatars inside compiled code. The numpy
versions in ``solver/rotations.py`` are the reference: the tests check these against them.

Why tuples, row indices and inlining: a small ``np.empty`` costs ~17 ns (malloc and
free), and arrays or views passed to a compiled call cost atomic reference counting; the
two were about 40% of a solve. So the inner loops (FK, Jacobian columns, steps and
clamps per joint) hold quaternions as tuples of floats, which live in registers, index
the (J, 4) arrays by joint instead of taking row views, and the kernels called per joint
or per iteration are inlined (``inline="always"``). The closed-form steps of the
solvers (``solver/ik/analytic.py``) are written the same way.

Conventions: quaternions x, y, z, w; a joint's local rotation is ``pre * D * post`` with
D its deviation from the canonical pose (see ``solver/rig.py``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

EPS = 1e-12

# The batch drivers solve avatars in parallel (numba prange: one avatar per task, each
# with its own work arrays, so results are bit for bit those of a serial loop) from this
# many avatars on (below it, starting the worker threads costs more than it saves). With
# one thread (a server sets that) they run as one serial loop: a parallel loop on one
# thread still allocates every avatar's work arrays.
PARALLEL_MIN_AVATARS = 2

Quat = tuple[float, float, float, float]
Vec3 = tuple[float, float, float]
SwingTwist = tuple[float, float, float, float, float, float, float]  # see swing_twist
Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


# --- quaternions and vectors as tuples --------------------------------------------------

@njit(cache=True, inline="always")
def row4(a: Array, i: int) -> Quat:
    return (a[i, 0], a[i, 1], a[i, 2], a[i, 3])


@njit(cache=True, inline="always")
def row3(a: Array, i: int) -> Vec3:
    return (a[i, 0], a[i, 1], a[i, 2])


@njit(cache=True, inline="always")
def set_row4(a: Array, i: int, t: Quat) -> None:
    a[i, 0] = t[0]
    a[i, 1] = t[1]
    a[i, 2] = t[2]
    a[i, 3] = t[3]


@njit(cache=True)
def tmul(a: Quat, b: Quat) -> Quat:
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz)


@njit(cache=True)
def tconj(a: Quat) -> Quat:
    return (-a[0], -a[1], -a[2], a[3])


@njit(cache=True)
def tnormalize(q: Quat) -> Quat:
    x, y, z, w = q
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if n > EPS:
        return (x / n, y / n, z / n, w / n)
    return q


@njit(cache=True)
def trotate(q: Quat, v: Vec3) -> Vec3:
    """R(q) v"""
    ux, uy, uz, w = q
    vx, vy, vz = v
    tx = 2.0 * (uy * vz - uz * vy)
    ty = 2.0 * (uz * vx - ux * vz)
    tz = 2.0 * (ux * vy - uy * vx)
    return (vx + w * tx + (uy * tz - uz * ty),
            vy + w * ty + (uz * tx - ux * tz),
            vz + w * tz + (ux * ty - uy * tx))


@njit(cache=True)
def tfrom_rotvec(x: float, y: float, z: float) -> Quat:
    a = math.sqrt(x * x + y * y + z * z)
    if a < 1e-8:
        k = 0.5 - a * a / 48.0
        w = 1.0 - a * a / 8.0
    else:
        k = math.sin(0.5 * a) / a
        w = math.cos(0.5 * a)
    return (x * k, y * k, z * k, w)


@njit(cache=True)
def tto_rotvec(q: Quat) -> Vec3:
    """Rotation vector of q (shorter way round, angle in [0, pi])."""
    x, y, z, w = q
    if w < 0.0:
        x, y, z, w = -x, -y, -z, -w
    s = math.sqrt(x * x + y * y + z * z)
    k = 2.0 if s < 1e-12 else 2.0 * math.atan2(s, w) / s
    return (x * k, y * k, z * k)


@njit(cache=True)
def taxis_angle(ax: float, ay: float, az: float, angle: float) -> Quat:
    """Rotation about a unit axis."""
    s = math.sin(0.5 * angle)
    return (ax * s, ay * s, az * s, math.cos(0.5 * angle))


@njit(cache=True)
def tbetween(u: Vec3, v: Vec3) -> Quat:
    """Shortest-arc rotation taking direction u onto direction v (need not be unit)."""
    nu = math.sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2])
    nv = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    if nu < EPS or nv < EPS:
        return (0.0, 0.0, 0.0, 1.0)
    ux, uy, uz = u[0] / nu, u[1] / nu, u[2] / nu
    vx, vy, vz = v[0] / nv, v[1] / nv, v[2] / nv
    d = ux * vx + uy * vy + uz * vz
    if d < -1.0 + 1e-10:  # opposite: half turn about any perpendicular axis
        px, py, pz = 0.0, -uz, uy  # u x (1,0,0)
        if py * py + pz * pz < 1e-8:
            px, py, pz = uz, 0.0, -ux  # u x (0,1,0)
        n = math.sqrt(px * px + py * py + pz * pz)
        return (px / n, py / n, pz / n, 0.0)
    return tnormalize((uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx, 1.0 + d))


# --- forward kinematics ----------------------------------------------------------------

@njit(cache=True, inline="always")
def fk_joint(parents: IntArray, offsets: Array, q: Array, gq: Array, gp: Array,
             j: int) -> None:
    """Global rotation and position of joint j from its parent's."""
    p = parents[j]
    g = row4(gq, p)
    set_row4(gq, j, tmul(g, row4(q, j)))
    t = trotate(g, row3(offsets, j))
    gp[j, 0] = gp[p, 0] + t[0]
    gp[j, 1] = gp[p, 1] + t[1]
    gp[j, 2] = gp[p, 2] + t[2]


@njit(cache=True)
def fk_upto(parents: IntArray, offsets: Array, q: Array, root: Array, gq: Array,
            gp: Array, last: int) -> None:
    """Globals of joints 0..last (parents come before their children)."""
    set_row4(gq, 0, row4(q, 0))
    gp[0, 0] = root[0]
    gp[0, 1] = root[1]
    gp[0, 2] = root[2]
    for j in range(1, last + 1):
        fk_joint(parents, offsets, q, gq, gp, j)


@njit(cache=True)
def fk(parents, offsets, q, root, gq, gp):
    """Global rotations gq (J,4) and positions gp (J,3) of one avatar."""
    fk_upto(parents, offsets, q, root, gq, gp, parents.shape[0] - 1)


@njit(cache=True, inline="always")
def fk_joints(parents, offsets, q, gq, gp, joints, n):
    """Update globals of the first n listed joints, in order (a chain, parents first)."""
    for i in range(n):
        fk_joint(parents, offsets, q, gq, gp, joints[i])


@njit(cache=True)
def fk_batch(parents, offsets, q, root, gq, gp):
    """offsets (B,J,3) or (1,J,3) shared; q (B,J,4); root (B,3)."""
    shared = offsets.shape[0] == 1
    for b in range(q.shape[0]):
        fk(parents, offsets[0] if shared else offsets[b], q[b], root[b], gq[b], gp[b])


# --- joint limits ----------------------------------------------------------------------

@njit(cache=True)
def composed(pre: Quat, post: Quat, sx: float, ty: float, sz: float) -> Quat:
    """pre * (exp(sx, 0, sz) * Ry(ty)) * post"""
    d = tmul(tfrom_rotvec(sx, 0.0, sz), taxis_angle(0.0, 1.0, 0.0, ty))
    return tmul(tmul(pre, d), post)


@njit(cache=True)
def _scaled_within(v: float, kmin: float, kmax: float, lo: float, hi: float) -> bool:
    """Is v * k surely within [lo, hi] for every k in [kmin, kmax] (kmin > 0)? (Rounded
    products are monotonic in k, so checking the two ends is enough; NaN gives False.)"""
    if v >= 0.0:
        return lo <= v * kmin and v * kmax <= hi
    return lo <= v * kmax and v * kmin <= hi


@njit(cache=True)
def surely_within(st: SwingTwist, lo: Vec3, hi: Vec3) -> bool:
    """True only if ``clamped_exactly`` would find nothing to clamp; False when unsure.
    Most clamps change nothing, and this spares them both atan2 calls.

    For a half angle p = atan2(a, c) in [0, pi/2) with r = |(a, c)|: sin p <= p <= tan p,
    so p / a lies in [1 / r, 1 / c], and 1 / r >= 2 / (1 + r^2). The margins (1e-12,
    relative) dwarf the rounding of atan2 and of the products (~1e-16)."""
    sx, sy, sz, sw, s, ty, tw = st
    if s < 1e-12 or not sw > 0.0 or not tw > 0.0:
        return False  # k is exact (no atan2 to spare) or the bounds are useless
    # swing: k = 2 atan2(s, sw) / s, rotation vector (sx k, sy k, sz k)
    kmin = 4.0 / (1.0 + s * s + sw * sw) * (1.0 - 1e-12)
    kmax = 2.0 / sw * (1.0 + 1e-12)
    if not (_scaled_within(sx, kmin, kmax, lo[0], hi[0])
            and _scaled_within(sz, kmin, kmax, lo[2], hi[2])
            and abs(sy) * kmax < 1e-9):
        return False
    # twist = 2 atan2(ty, tw), with tw > 0: exactly +-0 when ty is
    if ty == 0.0:
        return lo[1] <= 0.0 <= hi[1]
    tmin = 4.0 / (1.0 + ty * ty + tw * tw) * (1.0 - 1e-12)
    tmax = 2.0 / tw * (1.0 + 1e-12)
    return _scaled_within(ty, tmin, tmax, lo[1], hi[1])


@njit(cache=True)
def swing_twist(q: Quat, pre: Quat, post: Quat) -> SwingTwist:
    """D = pre^-1 q post^-1 split into twist about y and swing: (sx, sy, sz, sw) the
    swing with sw >= 0, s = |(sx, sy, sz)|, (ty, tw) the twist's y and w, tw >= 0."""
    x, y, z, w = tmul(tmul(tconj(pre), q), tconj(post))  # D
    if w < 0.0:
        x, y, z, w = -x, -y, -z, -w
    # twist about y: (0, y, 0, w) normalised; swing = D * twist^-1
    tn = math.sqrt(y * y + w * w)
    if tn < 1e-12:
        ty_c, tw_c = 0.0, 1.0
    else:
        ty_c, tw_c = y / tn, w / tn
    # swing = D * conj(twist), twist = (0, ty_c, 0, tw_c); kept term by term (zeros
    # included) so that results stay bit for bit those of earlier versions
    sx = w * 0.0 + x * tw_c + y * 0.0 - z * (-ty_c)
    sy = w * (-ty_c) - x * 0.0 + y * tw_c + z * 0.0
    sz = w * 0.0 + x * (-ty_c) - y * 0.0 + z * tw_c
    sw = w * tw_c - x * 0.0 - y * (-ty_c) - z * 0.0
    # swing rotation vector (its y part is zero up to rounding)
    s = math.sqrt(sx * sx + sy * sy + sz * sz)
    if sw < 0.0:
        sx, sy, sz, sw = -sx, -sy, -sz, -sw
    return (sx, sy, sz, sw, s, ty_c, tw_c)


@njit(cache=True)
def clamped_exactly(q: Quat, pre: Quat, post: Quat, lo: Vec3, hi: Vec3,
                    st: SwingTwist) -> tuple[bool, Quat]:
    """``clamped`` without its shortcut: swing (x, z) and twist angles each clamped."""
    sx, sy, sz, sw, s, ty_c, tw_c = st
    twist = 2.0 * math.atan2(ty_c, tw_c)
    k = 2.0 if s < 1e-12 else 2.0 * math.atan2(s, sw) / s
    rx, rz = sx * k, sz * k
    cx = min(max(rx, lo[0]), hi[0])
    ct = min(max(twist, lo[1]), hi[1])
    cz = min(max(rz, lo[2]), hi[2])
    if cx == rx and ct == twist and cz == rz and abs(sy * k) < 1e-9:
        return False, q
    return True, composed(pre, post, cx, ct, cz)


@njit(cache=True)
def clamped(q: Quat, pre: Quat, post: Quat, lo: Vec3, hi: Vec3) -> tuple[bool, Quat]:
    """A local rotation q clamped to its limits: D = pre^-1 q post^-1 split into swing
    (x, z) and twist about y, each clamped, recomposed. Returns (anything clamped, q)."""
    st = swing_twist(q, pre, post)
    if surely_within(st, lo, hi):
        return False, q
    return clamped_exactly(q, pre, post, lo, hi, st)


@njit(cache=True, inline="always")
def clamp_joint_at(q: Array, j: int, pre: Array, post: Array, lo: Array,
                   hi: Array) -> bool:
    """Clamp joint j's local rotation q[j] (in place) to its limits; True if clamped."""
    changed, c = clamped(row4(q, j), row4(pre, j), row4(post, j), row3(lo, j), row3(hi, j))
    if changed:
        set_row4(q, j, c)
    return changed


# --- chains: error, Jacobian, damped least squares ---------------------------------------

@njit(cache=True, inline="always")
def effector_error(gq, gp, eff, target, w_rot, e, r0=0):
    """6-vector [target position - position; w_rot * rotation vector to target] into
    e[r0:r0 + 6]; returns its norm."""
    tq = (target[3], target[4], target[5], target[6])
    rv = tto_rotvec(tmul(tq, tconj(row4(gq, eff))))
    s = 0.0
    for d in range(3):
        e[r0 + d] = target[d] - gp[eff, d]
        e[r0 + 3 + d] = w_rot * rv[d]
        s += e[r0 + d] ** 2 + e[r0 + 3 + d] ** 2
    return math.sqrt(s)


@njit(cache=True, inline="always")
def joint_axis_world(gq: Array, post: Array, j: int, axis: int) -> Vec3:
    """World direction of limit-frame axis (0 x, 1 y, 2 z) of joint j: R(G_j post^-1) e_axis."""
    e = (1.0 if axis == 0 else 0.0, 1.0 if axis == 1 else 0.0, 1.0 if axis == 2 else 0.0)
    return trotate(tmul(row4(gq, j), tconj(row4(post, j))), e)


@njit(cache=True, inline="always")
def jacobian_column(gq: Array, gp: Array, post: Array, j: int, axis: int, eff: int,
                    w_rot: float, Jm: Array, m: int, r0: int = 0) -> None:
    """Rows r0..r0+5 of column m of Jm, eq. 7: [a x (p_eff - p_j); w_rot * a] for limit
    axis `axis` of joint j."""
    a = joint_axis_world(gq, post, j, axis)
    rx = gp[eff, 0] - gp[j, 0]
    ry = gp[eff, 1] - gp[j, 1]
    rz = gp[eff, 2] - gp[j, 2]
    Jm[r0, m] = a[1] * rz - a[2] * ry
    Jm[r0 + 1, m] = a[2] * rx - a[0] * rz
    Jm[r0 + 2, m] = a[0] * ry - a[1] * rx
    Jm[r0 + 3, m] = w_rot * a[0]
    Jm[r0 + 4, m] = w_rot * a[1]
    Jm[r0 + 5, m] = w_rot * a[2]


@njit(cache=True, inline="always")
def solve_spd(A, b, n, x):
    """Solve A x = b for a small symmetric positive definite n x n A by Cholesky. A's
    lower triangle is overwritten with the factor L (no scratch to allocate); x may not
    alias b. Returns False if A is not positive definite."""
    for i in range(n):
        for k in range(i + 1):
            s = A[i, k]
            for m in range(k):
                s -= A[i, m] * A[k, m]
            if i == k:
                if s <= 0.0:
                    return False
                A[i, i] = math.sqrt(s)
            else:
                A[i, k] = s / A[k, k]
    for i in range(n):  # L y = b, y kept in x
        s = b[i]
        for m in range(i):
            s -= A[i, m] * x[m]
        x[i] = s / A[i, i]
    for i in range(n - 1, -1, -1):  # L^T x = y
        s = x[i]
        for m in range(i + 1, n):
            s -= A[m, i] * x[m]
        x[i] = s / A[i, i]
    return True


@njit(cache=True)
def stepped(q: Quat, pre: Quat, post: Quat, dx: float, dy: float, dz: float) -> Quat:
    """pre * (D * exp(dx, dy, dz)) * post, normalised, with D = pre^-1 q post^-1."""
    d = tmul(tmul(tconj(pre), q), tconj(post))
    d = tmul(d, tfrom_rotvec(dx, dy, dz))
    return tnormalize(tmul(tmul(pre, d), post))


@njit(cache=True, inline="always")
def step_joint_at(q: Array, j: int, pre: Array, post: Array, dx: float, dy: float,
                  dz: float) -> None:
    """Turn joint j (in place) by a small rotation about its own limit-frame axes."""
    set_row4(q, j, stepped(row4(q, j), row4(pre, j), row4(post, j), dx, dy, dz))


@njit(cache=True)
def dls_scratch(max_cols: int) -> tuple[Array, IntArray, IntArray, Array, Array, Array]:
    """Work arrays of ``dls_chain`` for chains of up to max_cols degrees of freedom:
    allocated once per avatar, not per chain and iteration."""
    return (np.empty((6, max_cols)), np.empty(max_cols, dtype=np.int64),
            np.empty(max_cols, dtype=np.int64), np.empty((6, 6)), np.empty(6), np.empty(6))


@njit(cache=True, inline="always")
def dls_step(q, pre, post, lo, hi, Jm, cols_joint, cols_axis, m, rows, A, e, y, lam):
    """One damped least squares step from the first ``rows`` x ``m`` of the Jacobian Jm:
    y = (J J^T + lam^2 I)^-1 e, dtheta = J^T y joint by joint, each joint clamped to its
    limits. False when the system cannot be solved (nothing is changed then)."""
    for r in range(rows):
        for c in range(r + 1):
            s = 0.0
            for k in range(m):
                s += Jm[r, k] * Jm[c, k]
            A[r, c] = s
            A[c, r] = s
        A[r, r] += lam * lam
    if not solve_spd(A, e, rows, y):
        return False
    k = 0
    while k < m:  # the columns of one joint are adjacent
        j = cols_joint[k]
        d0 = 0.0
        d1 = 0.0
        d2 = 0.0
        while k < m and cols_joint[k] == j:
            s = 0.0
            for r in range(rows):
                s += Jm[r, k] * y[r]
            if cols_axis[k] == 0:
                d0 = s
            elif cols_axis[k] == 1:
                d1 = s
            else:
                d2 = s
            k += 1
        step_joint_at(q, j, pre, post, d0, d1, d2)
        clamp_joint_at(q, j, pre, post, lo, hi)
    return True


@njit(cache=True)
def dls_chain(parents, offsets, q, gq, gp, pre, post, lo, hi, dofmask,
              chain, n, target, w_rot, lam, max_iter, eps, scratch, keep_closer, qsave):
    """Damped least squares over every degree of freedom of a chain (parents first, the
    effector last): dtheta = J^T (J J^T + lam^2 I)^-1 e, then clamp to the limits.
    ``scratch`` comes from ``dls_scratch``. Leaves the chain's globals current (a later
    chain hangs from them). ``keep_closer``: undo the iterations if they left the
    effector farther from the target's position than they found it (``qsave``: (J, 4)
    work rows): where the limits forbid the target's orientation, the weighted error
    traded position for it, up to 0.8 m. Returns the number of iterations used."""
    Jm, cols_joint, cols_axis, A, y, e = scratch
    eff = chain[n - 1]
    it = 0
    before = 0.0
    while True:
        fk_joints(parents, offsets, q, gq, gp, chain, n)
        err = effector_error(gq, gp, eff, target, w_rot, e)
        if it == 0 and keep_closer:
            before = e[0] * e[0] + e[1] * e[1] + e[2] * e[2]
            for i in range(n):
                set_row4(qsave, chain[i], row4(q, chain[i]))
        if err < eps or it >= max_iter:
            break
        m = 0
        for i in range(n):
            j = chain[i]
            for ax in range(3):
                if dofmask[j, ax]:
                    jacobian_column(gq, gp, post, j, ax, eff, w_rot, Jm, m)
                    cols_joint[m] = j
                    cols_axis[m] = ax
                    m += 1
        if not dls_step(q, pre, post, lo, hi, Jm, cols_joint, cols_axis, m, 6, A, e, y,
                        lam):
            break
        it += 1
    if keep_closer and it > 0 and e[0] * e[0] + e[1] * e[1] + e[2] * e[2] > before:
        for i in range(n):
            set_row4(q, chain[i], row4(qsave, chain[i]))
        fk_joints(parents, offsets, q, gq, gp, chain, n)
    return it


@njit(cache=True)
def dls_tree_scratch(max_cols: int, max_effs: int) -> tuple[Array, IntArray, IntArray,
                                                            Array, Array, Array]:
    """Work arrays of ``dls_tree``: up to max_cols degrees of freedom and max_effs
    effectors, allocated once per avatar."""
    rows = 6 * max_effs
    return (np.empty((rows, max_cols)), np.empty(max_cols, dtype=np.int64),
            np.empty(max_cols, dtype=np.int64), np.empty((rows, rows)), np.empty(rows),
            np.empty(rows))


@njit(cache=True, inline="always")
def drives(parents: IntArray, j: int, eff: int) -> bool:
    """True if joint j is eff or one of its ancestors (turning j moves eff)."""
    k = eff
    while k >= 0:
        if k == j:
            return True
        k = parents[k]
    return False


@njit(cache=True, inline="always")
def tree_error(gq, gp, effs, targets, slots, w_rot, e):
    """``effector_error`` of every effector k (to targets[slots[k]]) stacked into e;
    returns the norm."""
    s = 0.0
    for k in range(effs.shape[0]):
        s += effector_error(gq, gp, effs[k], targets[slots[k]], w_rot, e, 6 * k) ** 2
    return math.sqrt(s)


@njit(cache=True)
def dls_tree(parents, offsets, q, gq, gp, pre, post, lo, hi, dofmask, joints, nj,
             effs, targets, slots, w_rot, lam, max_iter, eps, scratch):
    """``dls_chain`` over a tree of joints (parents first) with several effectors at once:
    effector k (effs[k]) goes to targets[slots[k]], each contributing six rows; a joint's
    columns are zero for effectors it does not move. Returns the iterations used."""
    Jm, cols_joint, cols_axis, A, y, e = scratch
    ne = effs.shape[0]
    rows = 6 * ne
    it = 0
    while it < max_iter:
        fk_joints(parents, offsets, q, gq, gp, joints, nj)
        if tree_error(gq, gp, effs, targets, slots, w_rot, e) < eps:
            break
        m = 0
        for i in range(nj):
            j = joints[i]
            for ax in range(3):
                if not dofmask[j, ax]:
                    continue
                for k in range(ne):
                    if drives(parents, j, effs[k]):
                        jacobian_column(gq, gp, post, j, ax, effs[k], w_rot, Jm, m, 6 * k)
                    else:
                        for r in range(6):
                            Jm[6 * k + r, m] = 0.0
                cols_joint[m] = j
                cols_axis[m] = ax
                m += 1
        if not dls_step(q, pre, post, lo, hi, Jm, cols_joint, cols_axis, m, rows, A, e, y,
                        lam):
            break
        it += 1
    return it


@njit(cache=True, inline="always")
def set_effector_rotation(parents, q, gq, pre, post, lo, hi, j, target):
    """Turn joint j so that its global rotation is the target's (x y z w at target[3:7]),
    within its limits."""
    g = row4(gq, parents[j])
    tq = (target[3], target[4], target[5], target[6])
    set_row4(q, j, tnormalize(tmul(tconj(g), tq)))
    clamp_joint_at(q, j, pre, post, lo, hi)
    set_row4(gq, j, tmul(g, row4(q, j)))


@njit(cache=True)
def place_root(parents, offsets, q, root, gq, gp, pelvis, target):
    """Drive the pelvis from its target pose: its global rotation and position become the
    target's; joints above it (a static root) keep their rotations, the root moves."""
    # only the pelvis and its ancestors (lower indices) are read before the full FK below
    fk_upto(parents, offsets, q, root, gq, gp, pelvis)
    tq = (target[3], target[4], target[5], target[6])
    if pelvis == 0:
        set_row4(q, 0, tnormalize(tq))
    else:
        set_row4(q, pelvis, tnormalize(tmul(tconj(row4(gq, parents[pelvis])), tq)))
    # root moves by the difference between where the pelvis is and where it should be
    for i in range(3):
        root[i] += target[i] - gp[pelvis, i]
    fk(parents, offsets, q, root, gq, gp)


@njit(cache=True, inline="always")
def bone_target_row(device, i, mount_p, mount_q, j, out, k):
    """Row k of ``out``: the bone pose that device row i gives through mount row j: bone
    rotation = device rotation times the mount's inverse, bone position = device
    position minus the mount offset turned into the world."""
    dq = (device[i, 3], device[i, 4], device[i, 5], device[i, 6])
    t = tmul(dq, tconj(row4(mount_q, j)))
    v = trotate(t, row3(mount_p, j))
    for d in range(3):
        out[k, d] = device[i, d] - v[d]
    out[k, 3] = t[0]
    out[k, 4] = t[1]
    out[k, 5] = t[2]
    out[k, 6] = t[3]


@njit(cache=True)
def bone_targets(device, mount_p, mount_q, out):
    """Bone targets from device poses (``bone_target_row`` for each row): device (N, 7)
    pos + quat, mount_p (N, 3), mount_q (N, 4), out (N, 7)."""
    for i in range(device.shape[0]):
        bone_target_row(device, i, mount_p, mount_q, i, out, i)
