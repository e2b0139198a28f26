"""Compiled building blocks of the solvers: quaternion math on array views, forward
kinematics, joint limits, chain Jacobians and damped least squares.

Why compiled (numba): a solve walks joint chains and iterates, sequential work on
4-element arrays where each numpy call would cost about a microsecond of overhead. Every
function here works on one avatar's arrays and writes into preallocated outputs, so a
solve allocates almost nothing; the batched drivers in ``solver/ik/`` loop over avatars
inside compiled code. The numpy versions in ``solver/rotations.py`` are the reference:
the tests check these against them.

Conventions: quaternions x, y, z, w; a joint's local rotation is ``pre * D * post`` with
D its deviation from the canonical pose (see ``solver/rig.py``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

EPS = 1e-12


# --- quaternions and vectors on array views ---------------------------------------------

@njit(cache=True, inline="always")
def qmul(a, b, out):
    ax, ay, az, aw = a[0], a[1], a[2], a[3]
    bx, by, bz, bw = b[0], b[1], b[2], b[3]
    out[0] = aw * bx + ax * bw + ay * bz - az * by
    out[1] = aw * by - ax * bz + ay * bw + az * bx
    out[2] = aw * bz + ax * by - ay * bx + az * bw
    out[3] = aw * bw - ax * bx - ay * by - az * bz


@njit(cache=True, inline="always")
def qconj(a, out):
    out[0] = -a[0]
    out[1] = -a[1]
    out[2] = -a[2]
    out[3] = a[3]


@njit(cache=True, inline="always")
def qmul_conj_left(a, b, out):
    """out = conj(a) * b"""
    ax, ay, az, aw = -a[0], -a[1], -a[2], a[3]
    bx, by, bz, bw = b[0], b[1], b[2], b[3]
    out[0] = aw * bx + ax * bw + ay * bz - az * by
    out[1] = aw * by - ax * bz + ay * bw + az * bx
    out[2] = aw * bz + ax * by - ay * bx + az * bw
    out[3] = aw * bw - ax * bx - ay * by - az * bz


@njit(cache=True, inline="always")
def qmul_conj_right(a, b, out):
    """out = a * conj(b)"""
    ax, ay, az, aw = a[0], a[1], a[2], a[3]
    bx, by, bz, bw = -b[0], -b[1], -b[2], b[3]
    out[0] = aw * bx + ax * bw + ay * bz - az * by
    out[1] = aw * by - ax * bz + ay * bw + az * bx
    out[2] = aw * bz + ax * by - ay * bx + az * bw
    out[3] = aw * bw - ax * bx - ay * by - az * bz


@njit(cache=True, inline="always")
def qnormalize(q):
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if n > EPS:
        q[0] /= n
        q[1] /= n
        q[2] /= n
        q[3] /= n


@njit(cache=True, inline="always")
def qrotate(q, v, out):
    """out = R(q) v  (out may not alias v)"""
    ux, uy, uz, w = q[0], q[1], q[2], q[3]
    tx = 2.0 * (uy * v[2] - uz * v[1])
    ty = 2.0 * (uz * v[0] - ux * v[2])
    tz = 2.0 * (ux * v[1] - uy * v[0])
    out[0] = v[0] + w * tx + (uy * tz - uz * ty)
    out[1] = v[1] + w * ty + (uz * tx - ux * tz)
    out[2] = v[2] + w * tz + (ux * ty - uy * tx)


@njit(cache=True, inline="always")
def qrotate_inv(q, v, out):
    """out = R(q)^T v"""
    ux, uy, uz, w = -q[0], -q[1], -q[2], q[3]
    tx = 2.0 * (uy * v[2] - uz * v[1])
    ty = 2.0 * (uz * v[0] - ux * v[2])
    tz = 2.0 * (ux * v[1] - uy * v[0])
    out[0] = v[0] + w * tx + (uy * tz - uz * ty)
    out[1] = v[1] + w * ty + (uz * tx - ux * tz)
    out[2] = v[2] + w * tz + (ux * ty - uy * tx)


@njit(cache=True, inline="always")
def qfrom_rotvec(x, y, z, out):
    a = math.sqrt(x * x + y * y + z * z)
    if a < 1e-8:
        k = 0.5 - a * a / 48.0
        out[3] = 1.0 - a * a / 8.0
    else:
        k = math.sin(0.5 * a) / a
        out[3] = math.cos(0.5 * a)
    out[0] = x * k
    out[1] = y * k
    out[2] = z * k


@njit(cache=True, inline="always")
def qto_rotvec(q, out):
    """Rotation vector of q (shorter way round, angle in [0, pi])."""
    x, y, z, w = q[0], q[1], q[2], q[3]
    if w < 0.0:
        x, y, z, w = -x, -y, -z, -w
    s = math.sqrt(x * x + y * y + z * z)
    k = 2.0 if s < 1e-12 else 2.0 * math.atan2(s, w) / s
    out[0] = x * k
    out[1] = y * k
    out[2] = z * k


@njit(cache=True, inline="always")
def qaxis_angle(ax, ay, az, angle, out):
    """Rotation about a unit axis."""
    s = math.sin(0.5 * angle)
    out[0] = ax * s
    out[1] = ay * s
    out[2] = az * s
    out[3] = math.cos(0.5 * angle)


@njit(cache=True, inline="always")
def qbetween(u, v, out):
    """Shortest-arc rotation taking direction u onto direction v (need not be unit)."""
    nu = math.sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2])
    nv = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    if nu < EPS or nv < EPS:
        out[0] = 0.0
        out[1] = 0.0
        out[2] = 0.0
        out[3] = 1.0
        return
    ux, uy, uz = u[0] / nu, u[1] / nu, u[2] / nu
    vx, vy, vz = v[0] / nv, v[1] / nv, v[2] / nv
    d = ux * vx + uy * vy + uz * vz
    if d < -1.0 + 1e-10:  # opposite: half turn about any perpendicular axis
        px, py, pz = 0.0, -uz, uy  # u x (1,0,0)
        if py * py + pz * pz < 1e-8:
            px, py, pz = uz, 0.0, -ux  # u x (0,1,0)
        n = math.sqrt(px * px + py * py + pz * pz)
        out[0] = px / n
        out[1] = py / n
        out[2] = pz / n
        out[3] = 0.0
        return
    out[0] = uy * vz - uz * vy
    out[1] = uz * vx - ux * vz
    out[2] = ux * vy - uy * vx
    out[3] = 1.0 + d
    qnormalize(out)


# --- forward kinematics ----------------------------------------------------------------

@njit(cache=True)
def fk(parents, offsets, q, root, gq, gp):
    """Global rotations gq (J,4) and positions gp (J,3) of one avatar."""
    tmp = np.empty(3)
    gq[0, :] = q[0]
    gp[0, :] = root
    for j in range(1, parents.shape[0]):
        p = parents[j]
        qmul(gq[p], q[j], gq[j])
        qrotate(gq[p], offsets[j], tmp)
        gp[j, 0] = gp[p, 0] + tmp[0]
        gp[j, 1] = gp[p, 1] + tmp[1]
        gp[j, 2] = gp[p, 2] + tmp[2]


@njit(cache=True)
def fk_joints(parents, offsets, q, gq, gp, joints, n):
    """Update globals of the first n listed joints, in order (a chain, parents first)."""
    tmp = np.empty(3)
    for i in range(n):
        j = joints[i]
        p = parents[j]
        qmul(gq[p], q[j], gq[j])
        qrotate(gq[p], offsets[j], tmp)
        gp[j, 0] = gp[p, 0] + tmp[0]
        gp[j, 1] = gp[p, 1] + tmp[1]
        gp[j, 2] = gp[p, 2] + tmp[2]


@njit(cache=True)
def fk_batch(parents, offsets, q, root, gq, gp):
    """offsets (B,J,3) or (1,J,3) shared; q (B,J,4); root (B,3)."""
    shared = offsets.shape[0] == 1
    for b in range(q.shape[0]):
        fk(parents, offsets[0] if shared else offsets[b], q[b], root[b], gq[b], gp[b])


# --- joint limits ----------------------------------------------------------------------

@njit(cache=True)
def clamp_joint(q, pre, post, lo, hi, tmp4a, tmp4b):
    """Clamp one local rotation q (in place) to its limits: D = pre^-1 q post^-1 split
    into swing (x, z) and twist about y, each clamped, recomposed. Returns True when
    anything was clamped."""
    qmul_conj_left(pre, q, tmp4a)
    qmul_conj_right(tmp4a, post, tmp4b)  # tmp4b = D
    x, y, z, w = tmp4b[0], tmp4b[1], tmp4b[2], tmp4b[3]
    if w < 0.0:
        x, y, z, w = -x, -y, -z, -w
    # twist about y: (0, y, 0, w) normalised; swing = D * twist^-1
    tn = math.sqrt(y * y + w * w)
    if tn < 1e-12:
        ty_c, tw_c = 0.0, 1.0
    else:
        ty_c, tw_c = y / tn, w / tn
    twist = 2.0 * math.atan2(ty_c, tw_c)
    # swing = D * conj(twist), twist = (0, ty_c, 0, tw_c)
    sx = w * 0.0 + x * tw_c + y * 0.0 - z * (-ty_c)
    sy = w * (-ty_c) - x * 0.0 + y * tw_c + z * 0.0
    sz = w * 0.0 + x * (-ty_c) - y * 0.0 + z * tw_c
    sw = w * tw_c - x * 0.0 - y * (-ty_c) - z * 0.0
    # swing rotation vector (its y part is zero up to rounding)
    s = math.sqrt(sx * sx + sy * sy + sz * sz)
    if sw < 0.0:
        sx, sy, sz, sw = -sx, -sy, -sz, -sw
    k = 2.0 if s < 1e-12 else 2.0 * math.atan2(s, sw) / s
    rx, rz = sx * k, sz * k
    cx = min(max(rx, lo[0]), hi[0])
    ct = min(max(twist, lo[1]), hi[1])
    cz = min(max(rz, lo[2]), hi[2])
    if cx == rx and ct == twist and cz == rz and abs(sy * k) < 1e-9:
        return False
    qfrom_rotvec(cx, 0.0, cz, tmp4a)
    qaxis_angle(0.0, 1.0, 0.0, ct, tmp4b)
    qmul(tmp4a, tmp4b, q)  # q = D'
    qmul(pre, q, tmp4a)
    qmul(tmp4a, post, q)
    return True


@njit(cache=True)
def compose_joint(pre, post, sx, ty, sz, out, tmp4a, tmp4b):
    """out = pre * (exp(sx, 0, sz) * Ry(ty)) * post"""
    qfrom_rotvec(sx, 0.0, sz, tmp4a)
    qaxis_angle(0.0, 1.0, 0.0, ty, tmp4b)
    qmul(tmp4a, tmp4b, out)
    qmul(pre, out, tmp4a)
    qmul(tmp4a, post, out)


# --- chains: error, Jacobian, damped least squares ---------------------------------------

@njit(cache=True)
def effector_error(gq, gp, eff, target, w_rot, e):
    """6-vector [target position - position; w_rot * rotation vector to target]; returns
    its norm."""
    tq = np.empty(4)
    tq[0] = target[3]
    tq[1] = target[4]
    tq[2] = target[5]
    tq[3] = target[6]
    d = np.empty(4)
    qmul_conj_right(tq, gq[eff], d)
    rv = np.empty(3)
    qto_rotvec(d, rv)
    e[0] = target[0] - gp[eff, 0]
    e[1] = target[1] - gp[eff, 1]
    e[2] = target[2] - gp[eff, 2]
    e[3] = w_rot * rv[0]
    e[4] = w_rot * rv[1]
    e[5] = w_rot * rv[2]
    return math.sqrt(e[0] ** 2 + e[1] ** 2 + e[2] ** 2 + e[3] ** 2 + e[4] ** 2 + e[5] ** 2)


@njit(cache=True)
def joint_axis_world(gq, post, j, axis, out, tmp4):
    """World direction of limit-frame axis (0 x, 1 y, 2 z) of joint j: R(G_j post^-1) e_axis."""
    qmul_conj_right(gq[j], post, tmp4)
    e = np.zeros(3)
    e[axis] = 1.0
    qrotate(tmp4, e, out)


@njit(cache=True)
def jacobian_column(gq, gp, post, j, axis, eff, w_rot, col):
    """Column of eq. 7: [a x (p_eff - p_j); w_rot * a] for limit axis `axis` of joint j."""
    a = np.empty(3)
    tmp4 = np.empty(4)
    joint_axis_world(gq, post, j, axis, a, tmp4)
    rx = gp[eff, 0] - gp[j, 0]
    ry = gp[eff, 1] - gp[j, 1]
    rz = gp[eff, 2] - gp[j, 2]
    col[0] = a[1] * rz - a[2] * ry
    col[1] = a[2] * rx - a[0] * rz
    col[2] = a[0] * ry - a[1] * rx
    col[3] = w_rot * a[0]
    col[4] = w_rot * a[1]
    col[5] = w_rot * a[2]


@njit(cache=True)
def solve_spd(A, b, n, x):
    """Solve A x = b for a small symmetric positive definite n x n A (Cholesky, in place
    on a copy). Returns False if A is not positive definite."""
    L = np.zeros((n, n))
    for i in range(n):
        for k in range(i + 1):
            s = A[i, k]
            for m in range(k):
                s -= L[i, m] * L[k, m]
            if i == k:
                if s <= 0.0:
                    return False
                L[i, i] = math.sqrt(s)
            else:
                L[i, k] = s / L[k, k]
    y = np.empty(n)
    for i in range(n):
        s = b[i]
        for m in range(i):
            s -= L[i, m] * y[m]
        y[i] = s / L[i, i]
    for i in range(n - 1, -1, -1):
        s = y[i]
        for m in range(i + 1, n):
            s -= L[m, i] * x[m]
        x[i] = s / L[i, i]
    return True


@njit(cache=True)
def apply_deviation_step(q, pre, post, dx, dy, dz, tmp4a, tmp4b):
    """q = pre * (D * exp(dx, dy, dz)) * post, with D = pre^-1 q post^-1: turn the joint
    by a small rotation about its own limit-frame axes."""
    qmul_conj_left(pre, q, tmp4a)
    qmul_conj_right(tmp4a, post, tmp4b)  # D
    qfrom_rotvec(dx, dy, dz, tmp4a)
    qmul(tmp4b, tmp4a, q)  # D'
    qmul(pre, q, tmp4a)
    qmul(tmp4a, post, q)
    qnormalize(q)


@njit(cache=True)
def dls_chain(parents, offsets, q, gq, gp, pre, post, lo, hi, dofmask,
              chain, n, target, w_rot, lam, max_iter, eps):
    """Damped least squares over every degree of freedom of a chain (parents first, the
    effector last): dtheta = J^T (J J^T + lam^2 I)^-1 e, then clamp to the limits.
    Returns the number of iterations used."""
    eff = chain[n - 1]
    e = np.empty(6)
    m_max = 3 * n
    Jm = np.empty((6, m_max))
    col = np.empty(6)
    cols_joint = np.empty(m_max, dtype=np.int64)
    cols_axis = np.empty(m_max, dtype=np.int64)
    A = np.empty((6, 6))
    y = np.empty(6)
    dtheta = np.empty(3)
    t4a = np.empty(4)
    t4b = np.empty(4)
    it = 0
    while it < max_iter:
        fk_joints(parents, offsets, q, gq, gp, chain, n)
        err = effector_error(gq, gp, eff, target, w_rot, e)
        if err < eps:
            break
        m = 0
        for i in range(n):
            j = chain[i]
            for ax in range(3):
                if dofmask[j, ax]:
                    jacobian_column(gq, gp, post[j], j, ax, eff, w_rot, col)
                    for r in range(6):
                        Jm[r, m] = col[r]
                    cols_joint[m] = j
                    cols_axis[m] = ax
                    m += 1
        for r in range(6):
            for c in range(r + 1):
                s = 0.0
                for k in range(m):
                    s += Jm[r, k] * Jm[c, k]
                A[r, c] = s
                A[c, r] = s
            A[r, r] += lam * lam
        if not solve_spd(A, e, 6, y):
            break
        k = 0
        while k < m:
            j = cols_joint[k]
            dtheta[0] = 0.0
            dtheta[1] = 0.0
            dtheta[2] = 0.0
            while k < m and cols_joint[k] == j:
                s = 0.0
                for r in range(6):
                    s += Jm[r, k] * y[r]
                dtheta[cols_axis[k]] = s
                k += 1
            apply_deviation_step(q[j], pre[j], post[j], dtheta[0], dtheta[1], dtheta[2],
                                 t4a, t4b)
            clamp_joint(q[j], pre[j], post[j], lo[j], hi[j], t4a, t4b)
        it += 1
    return it


@njit(cache=True)
def set_effector_rotation(parents, q, gq, pre, post, lo, hi, j, target):
    """Turn joint j so that its global rotation is the target's (x y z w at target[3:7]),
    within its limits."""
    tq = np.empty(4)
    tq[0] = target[3]
    tq[1] = target[4]
    tq[2] = target[5]
    tq[3] = target[6]
    qmul_conj_left(gq[parents[j]], tq, q[j])
    qnormalize(q[j])
    t4a = np.empty(4)
    t4b = np.empty(4)
    clamp_joint(q[j], pre[j], post[j], lo[j], hi[j], t4a, t4b)
    qmul(gq[parents[j]], q[j], gq[j])


@njit(cache=True)
def place_root(parents, offsets, q, root, gq, gp, pelvis, target):
    """Drive the pelvis from its target pose: its global rotation and position become the
    target's; joints above it (a static root) keep their rotations, the root moves."""
    fk(parents, offsets, q, root, gq, gp)
    if pelvis == 0:
        for i in range(4):
            q[0, i] = target[3 + i]
        qnormalize(q[0])
    else:
        tq = np.empty(4)
        for i in range(4):
            tq[i] = target[3 + i]
        qmul_conj_left(gq[parents[pelvis]], tq, q[pelvis])
        qnormalize(q[pelvis])
    # root moves by the difference between where the pelvis is and where it should be
    for i in range(3):
        root[i] += target[i] - gp[pelvis, i]
    fk(parents, offsets, q, root, gq, gp)
