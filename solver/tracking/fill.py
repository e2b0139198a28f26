"""From the devices a frame has to the solver's targets, for any tracker set.

Per avatar and frame (``fill_targets``):
- A tracked device is its own target. One that comes back after a loss (or first appears)
  starts from where its target was and blends to the device over RETURN_S, so that the
  avatar never jumps.
- A lost device is carried on: held to the body part it hangs from (a hand to the
  pelvis, the hip to the head, an elbow to its hand, a knee to its foot, the chest to the
  head), moved on briefly by the velocity it had (EXTRAPOLATE_S), and after HOLD_S faded
  over FADE_S to the body model's estimate. A lost foot is the model's foot, which
  carries on from the tracked one (``legs``).
- A body part without a device is the body model's: the pelvis under the head
  (``pelvis``), the feet planted and stepping (``legs``), a hand hanging at the side.
- Elbow, knee and chest trackers only steer the solve (the elbow's and knee's swivel,
  the torso's turn), with a weight that fades out when they are lost and in when back.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from posecast.solver.kernels import tconj, tmul, trotate
from posecast.solver.tracking.devices import (
    CHEST,
    ELBOW_L,
    FOOT_L,
    FOOT_R,
    HAND_L,
    HEAD,
    HIP,
    KNEE_L,
    MAIN,
)
from posecast.solver.tracking.layout import (
    D_BACK,
    D_BLEND,
    D_HELD,
    D_LOST,
    D_MEAS,
    D_OFF,
    D_OUT,
    D_SEEN,
    D_VEL,
    DEV_STRIDE,
    K_DEV,
    K_INIT,
    K_PEL_PREV,
    K_PEL_YAW,
    K_T,
    ND,
    S_ARM,
    S_G0_PELVIS,
    S_HAND_DOWN,
    S_HIP,
    S_SHOULDER,
    S_YAW0,
)
from posecast.solver.tracking.legs import (
    flat_foot,
    foot_target,
    lose_foot,
    step_feet,
    track_foot,
)
from posecast.solver.tracking.pelvis import adapted, learn_pelvis, model_pelvis
from posecast.solver.tracking.poses import (
    add,
    arc,
    compose,
    lerp3,
    nlerp,
    read3,
    read4,
    read_pose,
    relative,
    scale,
    smoothstep,
    sub,
    write_pose,
    yaw_quat,
)

RETURN_S = 0.3  # a device back after a loss blends in over this (s) at least ...
# ... and longer for a larger offset: at most this speed (m/s) and turn (rad/s). A hand
# whose carried rotation was half a turn off swung its elbow 0.2 m a frame over 0.3 s.
RETURN_SPEED = 1.0
RETURN_TURN = 3.0
EXTRAPOLATE_S = 0.05  # a lost device moves on by its velocity, decaying this fast (s)
HOLD_S = 0.2  # a lost device is held where it was this long (s) ...
FADE_S = 1.0  # ... then handed over to the body model's estimate over this (s)
STEER_FADE_S = 0.2  # a lost elbow, knee or chest tracker stops steering over this (s)
VEL_S = 0.03  # a device's velocity is smoothed over this (s)
MAX_DT = 0.25  # longer gaps between frames count as this (s)
SETTLED = 1e9  # D_BACK of a device that is not blending in
HAND_FORWARD = 0.05  # m: a hanging hand sits this far in front of its shoulder
STEER_GAIN = 1.0  # how much of the way a tracked elbow, knee or chest steers


@njit(cache=True, inline="always")
def _base(d):
    return K_DEV + d * DEV_STRIDE


@njit(cache=True)
def _bookkeeping(dev, present, has, state, d, dt):
    """Note whether device d is tracked, lost or back, before its target is made."""
    b = _base(d)
    if present[d]:
        mp, mq = read_pose(dev[d], 0)
        if state[b + D_LOST] > 0.0 or state[b + D_SEEN] == 0.0:  # back, or new
            op, oq = read_pose(state, b + D_OUT)
            off_p, off_q = sub(op, mp), tmul(oq, tconj(mq))
            write_pose(state, b + D_OFF, off_p, off_q)
            state[b + D_BACK] = 0.0
            dist = math.sqrt(off_p[0] ** 2 + off_p[1] ** 2 + off_p[2] ** 2)
            turn = 2.0 * math.acos(min(abs(off_q[3]), 1.0))
            state[b + D_BLEND] = max(RETURN_S, dist / RETURN_SPEED, turn / RETURN_TURN)
            for i in range(3):
                state[b + D_VEL + i] = 0.0
        else:
            state[b + D_BACK] += dt
            if dt > 0.0:
                a = 1.0 - math.exp(-dt / VEL_S)
                for i in range(3):
                    v = (mp[i] - state[b + D_MEAS + i]) / dt
                    state[b + D_VEL + i] += a * (v - state[b + D_VEL + i])
        write_pose(state, b + D_MEAS, mp, mq)
        state[b + D_LOST] = 0.0
        state[b + D_SEEN] = 1.0
    elif has[d]:
        if state[b + D_LOST] == 0.0 and d < MAIN:  # lost now: it was last where it was
            # shown (blending in, maybe), which may not be where it was last measured
            for i in range(7):
                state[b + D_MEAS + i] = state[b + D_OUT + i]
        state[b + D_LOST] += max(dt, 1e-6)  # > 0 from the first frame it is missing


@njit(cache=True)
def _measured(dev, state, d, pivot, around):
    """A tracked device's target: its pose, plus what is left of its return blend. With
    ``around``, the blend's path swings about ``pivot`` (the shoulder of a hand, the hip
    of a foot), its distance from it changing evenly: a straight path from where a lost
    hand was carried to where it is passed by the shoulder, where the elbow has no side
    and swung from one to the other."""
    b = _base(d)
    p, q = read_pose(dev[d], 0)
    k = 1.0 - smoothstep(state[b + D_BACK] / state[b + D_BLEND])
    if k <= 0.0:
        return p, q
    op, oq = read_pose(state, b + D_OFF)
    if not around:
        return add(p, scale(op, k)), tmul(nlerp((0.0, 0.0, 0.0, 1.0), oq, k), q)
    return arc(pivot, p, q, add(p, op), tmul(oq, q), k)


@njit(cache=True)
def _carried(state, d, anchor_p, anchor_q):
    """A lost device: held to its anchor as it was when last seen, moved on briefly by
    its velocity; and the weight (1 -> 0) it keeps against the model's estimate."""
    b = _base(d)
    lost = state[b + D_LOST]
    hp, hq = read_pose(state, b + D_HELD)
    p, q = compose(anchor_p, anchor_q, hp, hq)
    drift = EXTRAPOLATE_S * (1.0 - math.exp(-lost / EXTRAPOLATE_S))
    p = add(p, scale(read3(state, b + D_VEL), drift))
    return p, q, 1.0 - smoothstep((lost - HOLD_S) / FADE_S)


@njit(cache=True)
def _blend(ap, aq, bp, bq, wa):
    """wa of pose a and the rest of pose b."""
    return lerp3(bp, ap, wa), nlerp(bq, aq, wa)


@njit(cache=True)
def _blend_about(pivot, ap, aq, bp, bq, wa):
    """``_blend`` on a path about ``pivot`` (``poses.arc``)."""
    return arc(pivot, bp, bq, ap, aq, wa)


@njit(cache=True)
def _hold(state, d, anchor_p, anchor_q, p, q):
    """Remember a tracked device relative to its anchor, for when it is lost."""
    hp, hq = relative(anchor_p, anchor_q, p, q)
    write_pose(state, _base(d) + D_HELD, hp, hq)


@njit(cache=True)
def _hanging_hand(shape, side, head_p, yaw):
    """The model's hand: the arm hanging relaxed at the side of the body."""
    Y = yaw_quat(yaw)
    shoulder = add(head_p, trotate(Y, read3(shape, S_SHOULDER + 3 * side)))
    front = trotate(Y, (0.0, 0.0, HAND_FORWARD))
    p = (shoulder[0] + front[0], shoulder[1] - shape[S_ARM], shoulder[2] + front[2])
    return p, tmul(Y, read4(shape, S_HAND_DOWN + 4 * side))


@njit(cache=True)
def fill_targets(dev, present, has, t, shape, state, targets, weights):
    """One avatar's targets (ND, 7) and weights (ND,) for one frame: ``dev`` (ND, 7) the
    bone poses its devices give, ``present`` (ND,) which it has this frame, ``has``
    (ND,) which it uses, ``t`` the frame's time (s); ``shape``, ``state``: its rows."""
    dt = 0.0
    if state[K_INIT] > 0.0:
        dt = min(max(t - state[K_T], 0.0), MAX_DT)
        state[K_T] = max(t, state[K_T])
    else:
        state[K_T] = t
        state[K_INIT] = 1.0
    for d in range(ND):
        _bookkeeping(dev, present, has, state, d, dt)
    lost = np.empty(ND, dtype=np.bool_)
    for d in range(ND):
        lost[d] = has[d] and not present[d]
    # the head: always a target; a lost headset is held where it was
    b = _base(HEAD)
    if present[HEAD]:
        hp, hq = _measured(dev, state, HEAD, (0.0, 0.0, 0.0), False)
    else:
        hp, hq = read_pose(state, b + D_MEAS)
        drift = EXTRAPOLATE_S * (1.0 - math.exp(-state[b + D_LOST] / EXTRAPOLATE_S))
        hp = add(hp, scale(read3(state, b + D_VEL), drift))
    write_pose(targets[HEAD], 0, hp, hq)
    head_frame = yaw_quat(state[K_PEL_YAW])
    # the pelvis
    mp, mq = model_pelvis(shape, state, hp, hq, dt)
    b = _base(HIP)
    # a tracked device is held as its target shows it (blending in, maybe): lost again
    # before the blend ends, it carries on from where it was shown, not from the device
    if present[HIP]:
        pp, pq = _measured(dev, state, HIP, (0.0, 0.0, 0.0), False)
        learn_pelvis(state, mp, read3(dev[HIP], 0), dt)
        _hold(state, HIP, hp, head_frame, pp, pq)
    elif lost[HIP] and state[b + D_SEEN] > 0.0:
        cp, cq, w = _carried(state, HIP, hp, head_frame)
        pp, pq = _blend(cp, cq, adapted(state, mp), mq, w)
    else:
        pp, pq = mp, mq
    write_pose(targets[HIP], 0, pp, pq)
    body_yaw = state[K_PEL_YAW]
    # the hands
    for side in range(2):
        d = HAND_L + side
        shoulder = add(hp, trotate(yaw_quat(body_yaw), read3(shape, S_SHOULDER + 3 * side)))
        if present[d]:
            p, q = _measured(dev, state, d, shoulder, True)
            _hold(state, d, pp, pq, p, q)
        else:
            p, q = _hanging_hand(shape, side, hp, body_yaw)
            if lost[d] and state[_base(d) + D_SEEN] > 0.0:
                cp, cq, w = _carried(state, d, pp, pq)
                p, q = _blend_about(shoulder, cp, cq, p, q, w)
        write_pose(targets[d], 0, p, q)
    # the feet: the model follows the tracked ones (as shown), and carries on for the
    # others
    turn = tmul(pq, tconj(read4(shape, S_G0_PELVIS)))
    for side in range(2):
        d = FOOT_L + side
        if present[d]:
            hip = add(pp, trotate(turn, read3(shape, S_HIP + 3 * side)))
            p, q = _measured(dev, state, d, hip, True)
            track_foot(shape, state, side, p, q)
        elif lost[d] and state[_base(d) + D_LOST] <= dt + 1e-6:  # lost this frame
            v = read3(state, _base(d) + D_VEL)
            lose_foot(shape, state, side, t, math.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2))
    step_feet(shape, state, pp, pq, t, dt, present[FOOT_L], present[FOOT_R])
    for side in range(2):
        p, q = foot_target(shape, state, side, t)  # a tracked foot's: as tracked above
        write_pose(targets[FOOT_L + side], 0, p, q)
    for d in range(MAIN):
        weights[d] = 1.0
        for i in range(7):
            state[_base(d) + D_OUT + i] = targets[d, i]
    # elbows, knees, chest: steer while tracked, held to their anchor while fading out.
    # An elbow's or knee's row holds the device's position and its mount (``rows``)
    for d in range(MAIN, ND):
        anchor = HEAD if d == CHEST else (HAND_L + d - ELBOW_L if d < KNEE_L
                                          else FOOT_L + d - KNEE_L)
        ap, aq = read_pose(targets[anchor], 0)
        b = _base(d)
        w = 0.0
        for i in range(7):
            targets[d, i] = dev[d, i] if present[d] else state[b + D_MEAS + i]
        if present[d]:
            held_q = read4(dev[d], 3) if d == CHEST else (0.0, 0.0, 0.0, 1.0)
            _hold(state, d, ap, aq, read3(dev[d], 0), held_q)
            w = STEER_GAIN * smoothstep(state[b + D_BACK] / state[b + D_BLEND])
            state[b + D_OUT] = w  # a steering device's D_OUT holds its weight
        elif lost[d] and state[b + D_SEEN] > 0.0:
            hp2, hq2 = read_pose(state, b + D_HELD)
            p, q = compose(ap, aq, hp2, hq2)
            for i in range(3):
                targets[d, i] = p[i]
            if d == CHEST:
                for i in range(4):
                    targets[d, 3 + i] = q[i]
            w = (1.0 - smoothstep(state[b + D_LOST] / STEER_FADE_S)) * state[b + D_OUT]
        weights[d] = w


@njit(cache=True)
def fill_batch(rows, filled, dev, present, has, t, shape, state, targets, weights):
    """``fill_targets`` for the avatars at ``rows`` of the arrays (one row per avatar)
    not ``filled`` since their frame was staged; marks them filled."""
    for i in range(rows.shape[0]):
        r = rows[i]
        if filled[r]:
            continue
        fill_targets(dev[r], present[r], has[r], t[r], shape[r], state[r], targets[r],
                     weights[r])
        filled[r] = True


def new_state(shape: np.ndarray, calibration: np.ndarray, has: np.ndarray) -> np.ndarray:
    """A tracking state for an avatar just calibrated: ``calibration`` (ND, 7) the bone
    poses of every slot at the T-pose (the devices' where it had them), ``has`` (ND,)
    which it had. Each device starts held to its anchor as it was then, so that one lost
    from the first frame on is carried from there."""
    from posecast.solver.tracking.layout import (
        F_POS,
        F_ROT,
        F_YAW,
        FOOT_STRIDE,
        K_FEET,
        S_FEET0,
        STATE_SIZE,
    )
    state = np.zeros(STATE_SIZE)
    state[K_PEL_YAW] = shape[S_YAW0]
    for side in range(2):
        base = K_FEET + side * FOOT_STRIDE
        state[base + F_POS: base + F_POS + 3] = shape[S_FEET0 + 3 * side: S_FEET0 + 3 * side + 3]
        state[base + F_YAW] = shape[S_YAW0]
        state[base + F_ROT: base + F_ROT + 4] = flat_foot(shape, side, shape[S_YAW0])
    state[K_PEL_PREV: K_PEL_PREV + 3] = calibration[HIP, :3]
    head_frame = np.concatenate([calibration[HEAD, :3], yaw_quat(shape[S_YAW0])])
    anchors = {HIP: head_frame, HAND_L: calibration[HIP], HAND_L + 1: calibration[HIP],
               CHEST: calibration[HEAD]}
    for side in range(2):
        anchors[ELBOW_L + side] = calibration[HAND_L + side]
        anchors[KNEE_L + side] = calibration[FOOT_L + side]
    for d in range(ND):
        b = K_DEV + d * DEV_STRIDE
        state[b + D_BACK] = SETTLED
        state[b + D_BLEND] = RETURN_S
        if not has[d]:
            continue
        state[b + D_SEEN] = 1.0
        state[b + D_MEAS: b + D_MEAS + 7] = calibration[d]
        if d < MAIN:
            state[b + D_OUT: b + D_OUT + 7] = calibration[d]
        # a steering device's D_OUT holds its weight: none until it is seen
        if d in anchors:
            a = anchors[d]
            p, q = relative((a[0], a[1], a[2]), (a[3], a[4], a[5], a[6]),
                            tuple(calibration[d, :3]), tuple(calibration[d, 3:]))
            state[b + D_HELD: b + D_HELD + 3] = p
            state[b + D_HELD + 3: b + D_HELD + 7] = q if d in (HIP, HAND_L, HAND_L + 1,
                                                                CHEST) else (0, 0, 0, 1)
    return state
