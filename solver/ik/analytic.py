"""The default solver: closed-form limbs and spine, then a short damped refinement.

- Pelvis: the hip tracker's pose, exactly.
- Spine: the head's rotation relative to the pelvis is spread over the spine, neck and
  head joints by range of motion. The neck then hangs from the head: it keeps its share
  of the head's turn away from the chest, which places the neck's base, and the torso
  (spine to chest) bends until the chest carries the neck's base there (each joint
  taking its share of the remaining swing); a few rounds settle the share as the chest
  moves. The head joint takes the exact orientation. (Bending every joint up to the head
  instead bent the neck for what the torso did: the chest, and the shoulders on it, lay
  40 mm off in a leaning mocap clip.)
- Arms and legs: the elbow (knee) angle follows from the shoulder-wrist (hip-ankle)
  distance in closed form, through the hinge's own axis and the real bone offsets. The
  elbow's swivel about the shoulder-wrist line puts the forearm where the hand's
  orientation says it should be with a neutral wrist, as the canonical pose holds it
  (the paper's subjects complained of twisted elbows, which is what a position-only
  solver gives); a bent arm's elbow then turns a tenth of the way down to the lowest
  point of its circle (ELBOW_DOWN_SHARE). Both are continuous through the poses where
  they lose their meaning (no flips in a frame): a neutral-wrist elbow near the
  shoulder-wrist line is trusted in proportion to its distance from it (SWIVEL_TRUST,
  else the last frame's swivel stays), and the pull down fades out towards a vertical
  line and towards the top of the circle (DOWN_FADE). The knee's swivel shares the
  foot's turn between hip and ankle by their ranges of twist (all of it on the hip
  twisted the thighs of a yoga pose's turned-out foot to their limit). The forearm takes
  the hand's twist (pronation), the wrist and ankle the rest; a nearly straight arm
  instead keeps the forearm's twist and turns the hand with the shoulder (its elbow
  cannot tell the two apart). The clavicles stay neutral (CLAVICLE_SHARE).
- Every joint is clamped to its limits; where that holds a hand or foot off a target
  it could reach, the swivel nearest the chosen one that reaches it is taken instead.
  Where a clamp or an unreachable target leaves an error, a few damped least squares
  iterations over the whole chain finish the job, kept unless they move the chain's end
  away from its target's position.
- A hand still short of a target beyond its straight arm (the spine's share left the
  shoulder too far) gets a damped least squares pass over the spine, neck and both arms
  at once, towards the head and both hands, kept if it brings them closer.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from posecast.solver.calibration import FOREARM_TWIST_SHARE, KNEE_BEND_SHARE
from posecast.solver.kernels import (
    PARALLEL_MIN_AVATARS,
    Quat,
    clamp_joint_at,
    composed,
    dls_chain,
    dls_scratch,
    dls_tree,
    dls_tree_scratch,
    fk_joint,
    fk_joints,
    place_root,
    row3,
    row4,
    set_effector_rotation,
    set_row4,
    swing_twist,
    taxis_angle,
    tbetween,
    tconj,
    tmul,
    tnormalize,
    trotate,
)
from posecast.solver.tracking.devices import CHEST as STEER_CHEST
from posecast.solver.tracking.devices import ELBOW_L as STEER_ELBOW
from posecast.solver.tracking.devices import KNEE_L as STEER_KNEE
from posecast.solver.tracking.poses import nlerp

# share of the arm's turn away from the T-pose that the clavicle takes: in the mocap the
# clavicles stay within ~5 deg of neutral, and a share dropped the shoulder with the arms
# down. Kept as a knob for an elevation-only rule above the horizontal.
CLAVICLE_SHARE = 0.0
# Elbow bends (radians) over which a nearly straight arm's swivel hands over from keeping
# the forearm's twist (the upper arm rolls with the hand) to the bend's own swivel (see
# solve_limb); the exact range matters little.
BEND_LO = math.radians(10.0)
BEND_HI = math.radians(45.0)
# Share of its angle from the lowest point of the elbow circle by which a bent arm's
# elbow is turned down from where a neutral wrist puts it: the Vive forearm trackers ask
# for more, the optical mocap for about this much
# (docs/decisions/0026-solver-rules-where-no-tracker-looks.md).
ELBOW_DOWN_SHARE = 0.1
# How far from the shoulder-wrist line (share of the elbow circle's radius) the elbow a
# neutral wrist implies must lie for its swivel to be taken whole; nearer, the swivel
# keeps the last frame's in proportion (no flips through the line).
SWIVEL_TRUST = 0.5
# Swivel (radians) before the top of the elbow's circle over which the pull down fades.
DOWN_FADE = math.radians(30.0)


@njit(cache=True)
def _turn_by_share(parents, q, gq, pre, post, lo, hi, j, rot, share):
    """Turn joint j by `share` of the world rotation `rot`, within its limits:
    G_j <- rot' * G_j (its local rotation updated; G_j itself is not)."""
    if rot[3] < 0.0:
        rot = (-rot[0], -rot[1], -rot[2], -rot[3])
    sa = math.sqrt(rot[0] ** 2 + rot[1] ** 2 + rot[2] ** 2)
    if sa < 1e-12:
        return
    angle = 2.0 * math.atan2(sa, rot[3]) * share
    turn = taxis_angle(rot[0] / sa, rot[1] / sa, rot[2] / sa, angle)
    g = tmul(turn, row4(gq, j))
    set_row4(q, j, tnormalize(tmul(tconj(row4(gq, parents[j])), g)))
    clamp_joint_at(q, j, pre, post, lo, hi)


@njit(cache=True)
def _range_of_motion(lo, hi, j):
    return (hi[j, 0] - lo[j, 0]) + (hi[j, 1] - lo[j, 1]) + (hi[j, 2] - lo[j, 2])


# Rounds of settling the neck's share of the head's turn against the chest's bend (see
# solve_spine): the second gains 0.1 mm on the Vive recordings, a third nothing (and
# each costs ~0.8 us a solve).
NECK_ROUNDS = 2
# A hand or foot this far (metres) beyond what its bent limb can reach anyway counts as
# held off its target by the limits, and the swivel search (_swivel_within_limits) tries
# other swivels, SWIVEL_STEP apart on either side of the rule's.
REACHED = 0.001
SWIVEL_STEP = math.radians(15.0)


@njit(cache=True)
def _spread(parents, q, gq, canon, pre, post, lo, hi, chain, first, n, tq):
    """Local rotations of chain[first..n-1]: the turn from chain[first]'s parent to the
    global rotation tq, less the canonical one, spread over them by range of motion (the
    neck turns and bends far more than a lumbar segment, limits.py); within limits."""
    crel = row4(canon, chain[first])
    for i in range(first + 1, n):
        crel = tmul(crel, row4(canon, chain[i]))
    rel = tmul(tconj(row4(gq, parents[chain[first]])), tq)
    dev = tmul(tconj(crel), rel)  # deviation, in the last joint's canonical frame
    if dev[3] < 0.0:
        dev = (-dev[0], -dev[1], -dev[2], -dev[3])
    s = math.sqrt(dev[0] ** 2 + dev[1] ** 2 + dev[2] ** 2)
    ang = 2.0 * math.atan2(s, dev[3])
    k = 0.0 if s < 1e-12 else ang / s
    total = 0.0
    for i in range(first, n):
        total += _range_of_motion(lo, hi, chain[i])
    for i in range(first, n):
        j = chain[i]
        share = _range_of_motion(lo, hi, j) / total
        rx = dev[0] * k * share
        ry = dev[1] * k * share
        rz = dev[2] * k * share
        rot = taxis_angle(0.0, 0.0, 1.0, 0.0)
        a = math.sqrt(rx ** 2 + ry ** 2 + rz ** 2)
        if a > 1e-12:
            rot = taxis_angle(rx / a, ry / a, rz / a, a)
        set_row4(q, j, tmul(row4(canon, j), rot))
        clamp_joint_at(q, j, pre, post, lo, hi)


@njit(cache=True)
def solve_spine(parents, offsets, q, gq, gp, canon, pre, post, lo, hi, chain, n, nt,
                target, tg, chest_w, qsave):
    """The spine chain (pelvis's child .. head, n joints): chain[:nt] is the torso (up to
    the chest), chain[nt:n - 1] the neck. A chest tracker (``tg[STEER_CHEST]``, weight ``chest_w``
    > 0) turns the torso towards its rotation, that share of the way."""
    head = chain[n - 1]
    tq = (target[3], target[4], target[5], target[6])
    _spread(parents, q, gq, canon, pre, post, lo, hi, chain, 0, n, tq)
    fk_joints(parents, offsets, q, gq, gp, chain, n)
    if chest_w > 0.0:
        _steer_torso(parents, offsets, q, gq, gp, canon, pre, post, lo, hi, chain, n, nt,
                     tq, tg, chest_w, qsave)
        return
    base = chain[nt]  # the neck's base (the head itself on a rig without a neck)
    g = tq
    for r in range(NECK_ROUNDS):
        if r > 0:  # the neck and head share the head's turn away from the chest as it is
            _spread(parents, q, gq, canon, pre, post, lo, hi, chain, nt, n, tq)
        # the neck hanging from the head on its target: where its base is, how it turns
        g = tq
        px, py, pz = target[0], target[1], target[2]
        for i in range(n - 1, nt, -1):
            g = tmul(g, tconj(row4(q, chain[i])))
            o = trotate(g, row3(offsets, chain[i]))
            px, py, pz = px - o[0], py - o[1], pz - o[2]
        # the torso bends to carry the neck's base there: each joint its share (one
        # sweep a round: a second changed nothing but the time)
        for i in range(nt):
            j = chain[i]
            r1 = (gp[base, 0] - gp[j, 0], gp[base, 1] - gp[j, 1], gp[base, 2] - gp[j, 2])
            r2 = (px - gp[j, 0], py - gp[j, 1], pz - gp[j, 2])
            _turn_by_share(parents, q, gq, pre, post, lo, hi, j, tbetween(r1, r2),
                           1.0 / (nt - i))
            fk_joints(parents, offsets, q, gq, gp, chain[i:], nt + 1 - i)
    if nt < n - 1:
        set_row4(q, base, tnormalize(tmul(tconj(row4(gq, parents[base])), g)))
        clamp_joint_at(q, base, pre, post, lo, hi)
        fk_joints(parents, offsets, q, gq, gp, chain[nt:], n - nt)
    set_effector_rotation(parents, q, gq, pre, post, lo, hi, head, target)


@njit(cache=True)
def _steer_torso(parents, offsets, q, gq, gp, canon, pre, post, lo, hi, chain, n, nt, tq,
                 tg, w, qsave):
    """The torso turned to the chest tracker's rotation (share w of the way from the
    head's spread), the neck and head taking the rest of the head's turn."""
    for i in range(nt):
        j = chain[i]
        for k in range(4):
            qsave[j, k] = q[j, k]
    _spread(parents, q, gq, canon, pre, post, lo, hi, chain, 0, nt,
            (tg[STEER_CHEST, 3], tg[STEER_CHEST, 4], tg[STEER_CHEST, 5], tg[STEER_CHEST, 6]))
    for i in range(nt):
        j = chain[i]
        set_row4(q, j, nlerp(row4(qsave, j), row4(q, j), w))
    fk_joints(parents, offsets, q, gq, gp, chain, nt)
    _spread(parents, q, gq, canon, pre, post, lo, hi, chain, nt, n, tq)
    fk_joints(parents, offsets, q, gq, gp, chain, n)
    set_effector_rotation(parents, q, gq, pre, post, lo, hi, chain[n - 1],
                          (0.0, 0.0, 0.0, tq[0], tq[1], tq[2], tq[3]))


@njit(cache=True)
def _hinge_angle(offsets, pre, post, lo, hi, mid, end, dist, current):
    """Hinge angle (about the mid joint's limit x axis) that makes the distance from the
    upper joint to the end joint equal `dist`, nearest the allowed range and `current`."""
    o1 = row3(offsets, mid)
    u = trotate(tconj(row4(pre, mid)), o1)
    v = trotate(row4(post, mid), row3(offsets, end))
    A = u[1] * v[1] + u[2] * v[2]
    Bc = u[2] * v[1] - u[1] * v[2]
    l1s = o1[0] ** 2 + o1[1] ** 2 + o1[2] ** 2
    l2s = v[0] ** 2 + v[1] ** 2 + v[2] ** 2
    K = 0.5 * (dist * dist - l1s - l2s) - u[0] * v[0]
    Rr = math.sqrt(A * A + Bc * Bc)
    if Rr < 1e-12:
        return min(max(current, lo[mid, 0]), hi[mid, 0])
    phi = math.atan2(Bc, A)
    c = min(max(K / Rr, -1.0), 1.0)
    alpha = math.acos(c)
    best = current
    best_cost = 1e30
    for sgn in (-1.0, 1.0):
        th = phi + sgn * alpha
        th = math.atan2(math.sin(th), math.cos(th))
        cl = min(max(th, lo[mid, 0]), hi[mid, 0])
        cost = abs(cl - th) * 10.0 + abs(cl - current)
        if cost < best_cost:
            best_cost = cost
            best = cl
    return best


@njit(cache=True)
def _perp_angle(ax, ay, az, bx, by, bz, nx, ny, nz):
    """Signed angle about n from a to b, both projected onto the plane normal to n."""
    da = ax * nx + ay * ny + az * nz
    db = bx * nx + by * ny + bz * nz
    ax, ay, az = ax - da * nx, ay - da * ny, az - da * nz
    bx, by, bz = bx - db * nx, by - db * ny, bz - db * nz
    cx = ay * bz - az * by
    cy = az * bx - ax * bz
    cz = ax * by - ay * bx
    return math.atan2(cx * nx + cy * ny + cz * nz, ax * bx + ay * by + az * bz)


@njit(cache=True)
def _swivel(Gu, offsets, pre, post, canon, lo, hi, mid, end, tq, dvec, nx, ny, nz,
            arm, parents, gq):
    """Angle to turn the aimed limb about the upper-end line.

    Leg: the knee's hinge axis turns from where the hip leaves it unrotated towards
    where the foot's orientation puts it with a neutral ankle, by the hip's share of the
    two joints' range of twist (the ankle turns the foot the rest of the way). Arm: the
    point of the elbow circle nearest to where a neutral wrist would put the elbow, i.e.
    the wrist bent as little as it can be (demanding no wrist deviation at all is worse:
    real wrists deviate, and the elbow moved with them)."""
    if not arm:
        ex = (1.0, 0.0, 0.0)
        # the knee's hinge axis where the foot's orientation puts it with a neutral ankle
        # (the canonical one: a rig's knee axis need not be the foot's flexion axis)
        x_end = trotate(tmul(tmul(tq, tconj(row4(canon, end))), tconj(row4(post, mid))), ex)
        a = trotate(tmul(Gu, row4(pre, mid)), ex)  # the knee's hinge axis, world
        psi_foot = _perp_angle(a[0], a[1], a[2], x_end[0], x_end[1], x_end[2], nx, ny, nz)
        # ...but the hip and the ankle share that turn of the foot by their ranges of
        # twist, as the spine shares the head's: from the knee's axis with the hip not
        # rotated (the aimed thigh's twist undone), the hip's share of the way
        upper = parents[mid]
        hip = hi[upper, 1] - lo[upper, 1]
        share = hip / (hip + hi[end, 1] - lo[end, 1])
        Gp = row4(gq, parents[upper])
        st = swing_twist(tmul(tconj(Gp), Gu), row4(pre, upper), row4(post, upper))
        G0 = tmul(Gp, tmul(tmul(row4(pre, upper), (st[0], st[1], st[2], st[3])),
                           row4(post, upper)))
        a0 = trotate(tmul(G0, row4(pre, mid)), ex)
        psi0 = _perp_angle(a[0], a[1], a[2], a0[0], a0[1], a0[2], nx, ny, nz)
        dp = psi_foot - psi0
        return psi0 + share * math.atan2(math.sin(dp), math.cos(dp))
    E = trotate(Gu, row3(offsets, mid))  # elbow, relative to the shoulder
    e2 = E[0] ** 2 + E[1] ** 2 + E[2] ** 2
    de = E[0] * nx + E[1] * ny + E[2] * nz
    if e2 - de * de < 0.05 ** 2 * e2:
        return 0.0  # (nearly) straight arm: the swivel means little, keep the current one
    # forearm as a neutral wrist would have it
    g = trotate(tmul(tq, tconj(row4(canon, end))), row3(offsets, end))
    # the swivel of the neutral-wrist elbow W - g about the line (every point of the
    # circle is as near when that elbow lies on the line: the angle then comes out 0)
    wx, wy, wz = dvec[0] - g[0], dvec[1] - g[1], dvec[2] - g[2]
    psi = _perp_angle(E[0], E[1], E[2], wx, wy, wz, nx, ny, nz)
    # near the line that elbow's direction about it is noise and flipped the elbow to
    # the far side of its circle in a frame: trust it in proportion to its distance
    # from the line (SWIVEL_TRUST of the circle's radius), else keep the last swivel
    dw = wx * nx + wy * ny + wz * nz
    off2 = wx * wx + wy * wy + wz * wz - dw * dw
    trust = math.sqrt(max(off2, 0.0) / (SWIVEL_TRUST ** 2 * (e2 - de * de)))
    return psi * min(trust, 1.0)


@njit(cache=True)
def _below(Gu, offsets, mid, psi, nx, ny, nz):
    """Signed angle about the shoulder-wrist line n from the lowest point of the elbow
    circle to the elbow turned by psi (fading to 0 as n turns vertical: no lowest point)."""
    # faded out towards a vertical line, not cut: a cut turned the elbow in one frame
    fade = min(max((0.99 - abs(ny)) / 0.19, 0.0), 1.0)
    if fade == 0.0:
        return 0.0
    E = trotate(Gu, row3(offsets, mid))
    Er = trotate(taxis_angle(nx, ny, nz, psi), E)
    b = _perp_angle(0.0, -1.0, 0.0, Er[0], Er[1], Er[2], nx, ny, nz)
    # an elbow near the top of its circle has no "down" side: the pull fades to 0 over
    # the last DOWN_FADE of the circle instead of flipping sign at +-180 deg (which
    # turned the elbow ~30 deg in a frame)
    if abs(b) > math.pi - DOWN_FADE:
        b = math.copysign((math.pi - DOWN_FADE) * (math.pi - abs(b)) / DOWN_FADE, b)
    return fade * b


@njit(cache=True)
def _forearm_twist(Gm: Quat, pre, post, mid, end, tq: Quat) -> float:
    """Twist of the forearm (about its limit y axis) that leaves the wrist no twist, for
    a forearm whose global rotation Gm has none: X = (Gm post^-1)^-1 T post_end^-1 =
    Ry(tau) K D_end, tau the twist (about y) of X less that of K."""
    lim = tmul(Gm, tconj(row4(post, mid)))
    X = tmul(tmul(tconj(lim), tq), tconj(row4(post, end)))
    # twist-first split X = Ry(t) * S gives t = 2 atan2(X_y, X_w); K = post_mid *
    # pre_end is a pure turn about the shared y axis (the hand's limit frame runs
    # along the forearm), so tau = t - twist(K)
    K = tmul(row4(post, mid), row4(pre, end))
    tau = 2.0 * math.atan2(X[1], X[3]) - 2.0 * math.atan2(K[1], K[3])
    return math.atan2(math.sin(tau), math.cos(tau))


@njit(cache=True)
def _place_upper(parents, offsets, q, gq, gp, pre, post, lo, hi, upper, mid, end, dvec,
                 Gu, nx, ny, nz, psi):
    """Set the upper bone to the aimed Gu turned by psi about the upper-end line, within
    its limits; returns how far (squared) the end joint then lies from the target. A
    clamped twist turns the plane the limb bends in, so the clamped bone is aimed at the
    target again (twice, as far as its swing limits allow)."""
    g = tmul(taxis_angle(nx, ny, nz, psi), Gu)
    for _ in range(3):
        set_row4(q, upper, tnormalize(tmul(tconj(row4(gq, parents[upper])), g)))
        clamped = clamp_joint_at(q, upper, pre, post, lo, hi)
        fk_joint(parents, offsets, q, gq, gp, upper)
        fk_joint(parents, offsets, q, gq, gp, mid)
        fk_joint(parents, offsets, q, gq, gp, end)
        if not clamped:
            break
        cur = (gp[end, 0] - gp[upper, 0], gp[end, 1] - gp[upper, 1], gp[end, 2] - gp[upper, 2])
        g = tmul(tbetween(cur, dvec), row4(gq, upper))
    return ((gp[end, 0] - gp[upper, 0] - dvec[0]) ** 2 + (gp[end, 1] - gp[upper, 1] - dvec[1]) ** 2
            + (gp[end, 2] - gp[upper, 2] - dvec[2]) ** 2)


@njit(cache=True)
def _swivel_within_limits(parents, offsets, q, gq, gp, pre, post, lo, hi, upper, mid, end,
                          dvec, Gu, nx, ny, nz, psi, short):
    """The upper bone turned by psi, or, where its limits then hold the end joint off the
    target (a dancer's hand 0.2 m off its tracker), by the swivel nearest psi that they
    let reach it (in SWIVEL_STEP steps either way), or else the one that comes nearest.
    ``short``: how far the bent limb falls short of the target (or beyond) anyway."""
    ok = (short + REACHED) ** 2
    miss = _place_upper(parents, offsets, q, gq, gp, pre, post, lo, hi, upper, mid, end,
                        dvec, Gu, nx, ny, nz, psi)
    if miss <= ok:
        return
    best, best_miss = psi, miss
    k = 1
    while k * SWIVEL_STEP <= math.pi and best_miss > ok:
        for sgn in (1.0, -1.0):
            cand = psi + sgn * k * SWIVEL_STEP
            m = _place_upper(parents, offsets, q, gq, gp, pre, post, lo, hi, upper, mid,
                             end, dvec, Gu, nx, ny, nz, cand)
            if m < best_miss:
                best, best_miss = cand, m
                if m <= ok:
                    break
        k += 1
    _place_upper(parents, offsets, q, gq, gp, pre, post, lo, hi, upper, mid, end, dvec, Gu,
                 nx, ny, nz, best)


@njit(cache=True)
def _steered(Gu, offsets, pre, post, mid, theta, tau_prev, tg, ss, gp, upper, nx, ny, nz,
             psi, arm):
    """How far (radians) to turn the aimed limb about the upper-end line, from ``psi``,
    to bring an elbow or knee tracker where it is seen: ``tg[ss]`` holds its position and
    its mount (position in the mid bone's frame). Its position is compared, not the joint
    it implies: the mount's rotation follows the skin, and a joint inferred through it
    lay off the limb's line by more than the swivel's own error. The mount frame turns
    with the hinge (an elbow tracker with part of the forearm's last twist, a knee tracker
    with part of the knee's bend, as calibration models them)."""
    if arm:
        frame = composed(row4(pre, mid), row4(post, mid), theta,
                         FOREARM_TWIST_SHARE * tau_prev, 0.0)
    else:
        frame = composed(row4(pre, mid), row4(post, mid), KNEE_BEND_SHARE * theta, 0.0, 0.0)
    E = trotate(Gu, row3(offsets, mid))
    m = trotate(tmul(Gu, frame), (tg[ss, 3], tg[ss, 4], tg[ss, 5]))
    P = (E[0] + m[0], E[1] + m[1], E[2] + m[2])
    to = (tg[ss, 0] - gp[upper, 0], tg[ss, 1] - gp[upper, 1], tg[ss, 2] - gp[upper, 2])
    d = _perp_angle(P[0], P[1], P[2], to[0], to[1], to[2], nx, ny, nz) - psi
    return math.atan2(math.sin(d), math.cos(d))


@njit(cache=True)
def solve_limb(parents, offsets, q, gq, gp, canon, pre, post, lo, hi, upper, mid, end,
               target, twist_in_mid, tg, ss, steer_w):
    """Two-bone limb: upper (upper arm / thigh), mid (forearm / shin, hinge about its limit
    x axis, with a twist about the bone when twist_in_mid), end (hand / foot). An elbow
    or knee tracker (``tg[ss]``: its position and its mount on the mid bone, weight
    ``steer_w`` > 0) turns the limb about the upper-end line towards it, that share of the
    way (``_steered``)."""
    tq = (target[3], target[4], target[5], target[6])
    dvec = (target[0] - gp[upper, 0], target[1] - gp[upper, 1], target[2] - gp[upper, 2])
    dist = math.sqrt(dvec[0] ** 2 + dvec[1] ** 2 + dvec[2] ** 2)
    if dist < 1e-9:
        return
    # current hinge angle, for choosing between the two solutions
    d = tmul(tmul(tconj(row4(pre, mid)), row4(q, mid)), tconj(row4(post, mid)))
    cur = 2.0 * math.atan2(d[0], d[3])
    # the forearm's twist of the last frame (D = swing * Ry(twist)); none for a leg
    tau_prev = 2.0 * math.atan2(d[1], d[3]) if twist_in_mid else 0.0
    tau_prev = math.atan2(math.sin(tau_prev), math.cos(tau_prev))
    theta = _hinge_angle(offsets, pre, post, lo, hi, mid, end, dist, cur)
    set_row4(q, mid, composed(row4(pre, mid), row4(post, mid), theta, 0.0, 0.0))
    # aim the limb: end joint in upper-local coordinates, then shortest arc to target
    t = trotate(row4(q, mid), row3(offsets, end))
    w = (offsets[mid, 0] + t[0], offsets[mid, 1] + t[1], offsets[mid, 2] + t[2])
    cur_dir = trotate(row4(gq, upper), w)
    Gu = tmul(tbetween(cur_dir, dvec), row4(gq, upper))
    # swivel about the upper-end line
    nx, ny, nz = dvec[0] / dist, dvec[1] / dist, dvec[2] / dist
    psi = _swivel(Gu, offsets, pre, post, canon, lo, hi, mid, end, tq, dvec, nx, ny, nz,
                  twist_in_mid, parents, gq)
    if twist_in_mid:
        # a (nearly) straight arm turns the hand about its length with the shoulder as
        # well as the forearm, and its elbow says nothing about which: keep the forearm's
        # twist of the last frame and let the upper arm roll, handing over to the swivel
        # the elbow's bend dictates as it grows
        wb = min(max((theta - BEND_LO) / (BEND_HI - BEND_LO), 0.0), 1.0)
        if wb < 1.0:
            Gm = tmul(Gu, row4(q, mid))  # forearm, hinge only (no twist), psi = 0
            tau0 = _forearm_twist(Gm, pre, post, mid, end, tq)
            # which way the forearm's twist axis runs along the shoulder-wrist line
            yw = trotate(tmul(Gm, tconj(row4(post, mid))), (0.0, 1.0, 0.0))
            sgn = 1.0 if yw[0] * nx + yw[1] * ny + yw[2] * nz >= 0.0 else -1.0
            keep = sgn * (tau0 - tau_prev)
            keep = math.atan2(math.sin(keep), math.cos(keep))
            dpsi = psi - keep
            psi = keep + wb * math.atan2(math.sin(dpsi), math.cos(dpsi))
        # people keep their elbows low: turn a bent arm's elbow part of the way down
        if wb > 0.0:
            psi -= ELBOW_DOWN_SHARE * wb * _below(Gu, offsets, mid, psi, nx, ny, nz)
    if steer_w > 0.0:
        psi += steer_w * _steered(Gu, offsets, pre, post, mid, theta, tau_prev, tg, ss, gp,
                                  upper, nx, ny, nz, psi, twist_in_mid)
    short = abs(dist - math.sqrt(w[0] ** 2 + w[1] ** 2 + w[2] ** 2))
    _swivel_within_limits(parents, offsets, q, gq, gp, pre, post, lo, hi, upper, mid, end,
                          dvec, Gu, nx, ny, nz, psi, short)
    if twist_in_mid:
        tau = _forearm_twist(row4(gq, mid), pre, post, mid, end, tq)
        set_row4(q, mid, composed(row4(pre, mid), row4(post, mid), theta, tau, 0.0))
        clamp_joint_at(q, mid, pre, post, lo, hi)
        fk_joint(parents, offsets, q, gq, gp, mid)
    fk_joint(parents, offsets, q, gq, gp, mid)
    fk_joint(parents, offsets, q, gq, gp, end)
    set_effector_rotation(parents, q, gq, pre, post, lo, hi, end, target)


@njit(cache=True)
def aim_clavicle(parents, offsets, q, gq, gp, canon, pre, post, lo, hi, clav, upper, mid,
                 end, target, share):
    """Turn the clavicle a share of the way from where the straight canonical arm points
    to where the hand target is, seen from the shoulder."""
    set_row4(q, clav, row4(canon, clav))
    fk_joint(parents, offsets, q, gq, gp, clav)
    fk_joint(parents, offsets, q, gq, gp, upper)
    if share == 0.0:  # the default: the clavicle stays neutral
        return
    # canonical arm direction in the clavicle's frame: c_u (o_mid + c_m o_end)
    v = trotate(row4(canon, mid), row3(offsets, end))
    v = (v[0] + offsets[mid, 0], v[1] + offsets[mid, 1], v[2] + offsets[mid, 2])
    a0 = trotate(row4(gq, clav), trotate(row4(canon, upper), v))
    t = (target[0] - gp[upper, 0], target[1] - gp[upper, 1], target[2] - gp[upper, 2])
    _turn_by_share(parents, q, gq, pre, post, lo, hi, clav, tbetween(a0, t), share)
    fk_joint(parents, offsets, q, gq, gp, clav)
    fk_joint(parents, offsets, q, gq, gp, upper)


@njit(cache=True)
def _arm_out_of_reach(offsets, gp, chains, tg, eps):
    """True if a hand missed its target (after the refinement) because the target lies
    beyond the straight arm from where the spine put the shoulder."""
    for c in (1, 2):
        ch = chains[c]
        hand = ch[3]
        miss = 0.0
        dist = 0.0
        for d in range(3):
            miss += (tg[c + 1, d] - gp[hand, d]) ** 2
            dist += (tg[c + 1, d] - gp[ch[1], d]) ** 2
        if miss < eps * eps:
            continue
        reach = 0.0
        for j in (ch[2], ch[3]):
            reach += math.sqrt(offsets[j, 0] ** 2 + offsets[j, 1] ** 2 + offsets[j, 2] ** 2)
        # beyond the straight arm only: a margin ran the fallback more often, to no gain
        if math.sqrt(dist) > reach:
            return True
    return False


@njit(cache=True, inline="always")
def _position_miss(gp, effs, tg, slots):
    """Sum of the squared distances of the effectors effs from their targets' positions."""
    s = 0.0
    for k in range(effs.shape[0]):
        for d in range(3):
            s += (tg[slots[k], d] - gp[effs[k], d]) ** 2
    return s


@njit(cache=True)
def _reach_with_spine(parents, offsets, q, gq, gp, pre, post, lo, hi, dofmask, upper,
                      effs, slots, tg, w_rot, lam, refine, eps, tree, qsave):
    """Refine the spine, neck and both arms together towards the head and both hands:
    the spine's closed-form share can leave a shoulder too far from its hand, which the
    arm chains alone cannot make up. Kept if it brings them closer to their targets'
    positions (keeping it only when it reached all three left reaching hands 40-70 mm
    short, in frames the pass could not finish in its few iterations; judging it by the
    weighted error let it pull hands off for orientations the limits forbid)."""
    qsave[:] = q
    before = _position_miss(gp, effs, tg, slots)
    it = dls_tree(parents, offsets, q, gq, gp, pre, post, lo, hi, dofmask, upper,
                  upper.shape[0], effs, tg, slots, w_rot, lam, refine, eps, tree)
    fk_joints(parents, offsets, q, gq, gp, upper, upper.shape[0])
    if _position_miss(gp, effs, tg, slots) >= before:
        q[:] = qsave
        fk_joints(parents, offsets, q, gq, gp, upper, upper.shape[0])
    return it


@njit(cache=True)
def analytic_work(J, chains, lengths):
    """Work arrays for solving avatars one after the other (``solve_analytic_one``)."""
    gq = np.empty((J, 4))
    gp = np.empty((J, 3))
    scratch = dls_scratch(3 * chains.shape[1])
    # the upper body as one tree (spine to head, both arms) for _reach_with_spine
    nu = lengths[0] + lengths[1] + lengths[2]
    upper = np.empty(nu, dtype=np.int64)
    upper[:lengths[0]] = chains[0, :lengths[0]]
    upper[lengths[0]:lengths[0] + lengths[1]] = chains[1, :lengths[1]]
    upper[lengths[0] + lengths[1]:] = chains[2, :lengths[2]]
    effs = np.empty(3, dtype=np.int64)
    slots = np.empty(3, dtype=np.int64)
    for c in range(3):
        effs[c] = chains[c, lengths[c] - 1]
        slots[c] = 0 if c == 0 else c + 1
    tree = dls_tree_scratch(3 * nu, 3)
    qsave = np.empty((J, 4))
    return gq, gp, scratch, upper, effs, slots, tree, qsave


@njit(cache=True, inline="always")
def _neck_start(parents, chains):
    """Where the neck starts in the spine chain (chains[0]): just above the chest, the
    joint the clavicles (chains[1, 0]) hang from."""
    chest = parents[chains[1, 0]]
    for i in range(chains.shape[1]):
        if chains[0, i] == chest:
            return i + 1
    return 1


@njit(cache=True)
def solve_analytic_one(parents, off, canon, pre, post, lo, hi, dofmask, pelvis, chains,
                       lengths, tg, w, qb, rootb, w_rot, lam, refine, eps, work):
    """One avatar (its bone offsets, targets (ND, 7) and weights (ND,) in the slot order
    of ``solver.tracking.devices``, pose and root), in place; returns the refinement's
    iterations. ``work``: from ``analytic_work``."""
    gq, gp, scratch, upper, effs, slots, tree, qsave = work
    place_root(parents, off, qb, rootb, gq, gp, pelvis, tg[1])
    solve_spine(parents, off, qb, gq, gp, canon, pre, post, lo, hi, chains[0],
                lengths[0], _neck_start(parents, chains), tg[0], tg,
                w[STEER_CHEST], qsave)
    for c in (1, 2):  # arms: clavicle, upper arm, forearm, hand
        ch = chains[c]
        aim_clavicle(parents, off, qb, gq, gp, canon, pre, post, lo, hi, ch[0], ch[1],
                     ch[2], ch[3], tg[c + 1], CLAVICLE_SHARE)
        solve_limb(parents, off, qb, gq, gp, canon, pre, post, lo, hi, ch[1], ch[2],
                   ch[3], tg[c + 1], True, tg, STEER_ELBOW + c - 1, w[STEER_ELBOW + c - 1])
    for c in (3, 4):  # legs: thigh, shin, foot
        ch = chains[c]
        fk_joints(parents, off, qb, gq, gp, ch, 1)
        solve_limb(parents, off, qb, gq, gp, canon, pre, post, lo, hi, ch[0], ch[1],
                   ch[2], tg[c + 1], False, tg, STEER_KNEE + c - 3, w[STEER_KNEE + c - 3])
    total = 0
    if refine > 0:
        for c in range(chains.shape[0]):
            eff_slot = 0 if c == 0 else c + 1
            total += dls_chain(parents, off, qb, gq, gp, pre, post, lo, hi, dofmask,
                               chains[c], lengths[c], tg[eff_slot], w_rot, lam, refine, eps,
                               scratch, True, qsave)
        if _arm_out_of_reach(off, gp, chains, tg, eps):
            total += _reach_with_spine(parents, off, qb, gq, gp, pre, post, lo, hi,
                                       dofmask, upper, effs, slots, tg, w_rot, lam,
                                       refine, eps, tree, qsave)
    return total


@njit(cache=True)
def solve_analytic_range(parents, offsets, canon, pre, post, lo, hi, dofmask, pelvis,
                         chains, lengths, targets, weights, q, root, w_rot, lam, refine,
                         eps, iterations, first, last):
    """Avatars first..last-1 of the batch, one after the other."""
    shared = offsets.shape[0] == 1
    work = analytic_work(q.shape[1], chains, lengths)
    for b in range(first, last):
        iterations[b] = solve_analytic_one(
            parents, offsets[0] if shared else offsets[b], canon, pre, post, lo, hi,
            dofmask, pelvis, chains, lengths, targets[b], weights[b], q[b], root[b], w_rot,
            lam, refine, eps, work)


@njit(cache=True, parallel=True)
def solve_analytic_batch(parents, offsets, canon, pre, post, lo, hi, dofmask, pelvis,
                         chains, lengths, targets, weights, q, root, w_rot, lam, refine, eps,
                         iterations, serial):
    # avatars are independent: spread over the cores (see PARALLEL_MIN_AVATARS); the
    # bounds are int64 in both calls so that they share one compiled version
    B = q.shape[0]
    if serial or B < PARALLEL_MIN_AVATARS:
        solve_analytic_range(parents, offsets, canon, pre, post, lo, hi, dofmask, pelvis,
                             chains, lengths, targets, weights, q, root, w_rot, lam, refine,
                             eps, iterations, np.int64(0), B)
    else:
        for b in prange(B):
            first = np.int64(b)
            solve_analytic_range(parents, offsets, canon, pre, post, lo, hi, dofmask,
                                 pelvis, chains, lengths, targets, weights, q, root, w_rot,
                                 lam, refine, eps, iterations, first, first + 1)
