"""The body model's feet when no foot tracker says where they are: planted on the floor
until the body moves away from them, then stepping, one foot at a time, to where the hips
are heading. Crouched or seated (the pelvis well below its standing height) the feet stay
where they are unless the body has left them behind; the knees bend as the pelvis drops
because the solver keeps the feet planted. A tracked foot is the model's foot too, so
that a foot lost carries on from where it was: planted if it stood, landing if it moved.
"""

from __future__ import annotations

import math

from numba import njit

from posecast.solver.kernels import tmul, trotate
from posecast.solver.tracking.layout import (
    F_LEN,
    F_POS,
    F_ROT,
    F_ROT0,
    F_START,
    F_SWING,
    F_T0,
    F_YAW,
    F_YAW0,
    FOOT_STRIDE,
    K_FEET,
    K_PEL_PREV,
    K_PEL_VEL,
    S_ANKLE,
    S_CROUCH,
    S_FLAT_FOOT,
    S_FLOOR,
    S_G0_PELVIS,
    S_HIP,
    S_LEAD,
    S_LEG,
    S_NAIVE,
    S_REACH,
    S_STAND_PELVIS,
    S_STEP_DIST,
    S_STEP_TIME,
)
from posecast.solver.tracking.poses import (
    heading,
    lerp3,
    nlerp,
    read3,
    read4,
    smoothstep,
    wrap,
    write3,
    write4,
    yaw_quat,
)

# A planted foot steps when the hip's footprint is BodyModel.step_dist (m) from it, or the
# body has turned STEP_YAW (rad) away from it (a turn counts as step_dist / STEP_YAW m a
# radian); the rest of the stepping's constants are BodyModel's too (shape[S_MODEL:]).
STEP_YAW = 0.6
STEP_HEIGHT = 0.06  # m the foot rises mid-step
VEL_TAU = 0.1  # s: the hips' velocity is smoothed over this
MOVING = 0.3  # m/s: a foot lost faster than this was stepping, and lands
AIR = 0.05  # m: a foot lost this high above its standing height lands


@njit(cache=True)
def footprint(shape, side, pel_p, yaw):
    """Where a foot stands under its hip joint."""
    hip = trotate(yaw_quat(yaw), read3(shape, S_HIP + 3 * side))
    return (pel_p[0] + hip[0], shape[S_FLOOR] + shape[S_ANKLE], pel_p[2] + hip[2])


@njit(cache=True)
def flat_foot(shape, side, yaw):
    """A foot's rotation standing flat, facing ``yaw``."""
    return tmul(yaw_quat(yaw), read4(shape, S_FLAT_FOOT + 4 * side))


@njit(cache=True)
def foot_target(shape, state, side, t):
    """The model's foot pose now (position, rotation)."""
    base = K_FEET + side * FOOT_STRIDE
    return read3(state, base + F_POS), read4(state, base + F_ROT)


@njit(cache=True)
def track_foot(shape, state, side, p, q):
    """A tracked foot: the model's foot is where it is, turned as it is."""
    base = K_FEET + side * FOOT_STRIDE
    write3(state, base + F_POS, p)
    write4(state, base + F_ROT, q)
    state[base + F_YAW] = heading(q, read4(shape, S_FLAT_FOOT + 4 * side))
    state[base + F_SWING] = 0.0


@njit(cache=True)
def _start_step(state, side, t, length):
    base = K_FEET + side * FOOT_STRIDE
    state[base + F_SWING] = 1.0
    for i in range(3):
        state[base + F_START + i] = state[base + F_POS + i]
    state[base + F_YAW0] = state[base + F_YAW]
    for i in range(4):
        state[base + F_ROT0 + i] = state[base + F_ROT + i]
    state[base + F_T0] = t
    state[base + F_LEN] = length


@njit(cache=True)
def lose_foot(shape, state, side, t, speed):
    """A foot tracker just lost: a foot that moved or stood in the air lands."""
    base = K_FEET + side * FOOT_STRIDE
    standing = shape[S_FLOOR] + shape[S_ANKLE]
    if speed > MOVING or state[base + F_POS + 1] > standing + AIR:
        _start_step(state, side, t, shape[S_STEP_TIME])


@njit(cache=True)
def step_feet(shape, state, pel_p, pel_q, t, dt, tracked_l, tracked_r):
    """Advance the model's feet by one frame, for the pelvis pose of this frame; the
    tracked feet were set with ``track_foot``."""
    yaw = heading(pel_q, read4(shape, S_G0_PELVIS))
    # the hips' velocity, smoothed
    if dt > 0.0:
        a = 1.0 - math.exp(-dt / VEL_TAU)
        for i in range(3):
            v = (pel_p[i] - state[K_PEL_PREV + i]) / dt
            state[K_PEL_VEL + i] += a * (v - state[K_PEL_VEL + i])
    write3(state, K_PEL_PREV, pel_p)
    naive = shape[S_NAIVE] > 0.0
    tracked = (tracked_l, tracked_r)
    moving = False
    for side in range(2):
        if tracked[side]:
            continue
        base = K_FEET + side * FOOT_STRIDE
        home = footprint(shape, side, pel_p, yaw)
        if naive:  # the baseline: straight down from the hip, always
            write3(state, base + F_POS, home)
            state[base + F_YAW] = yaw
            write4(state, base + F_ROT, flat_foot(shape, side, yaw))
            continue
        if state[base + F_SWING] > 0.0:
            length = state[base + F_LEN]
            x = (t - state[base + F_T0]) / length
            ahead = shape[S_LEAD] * length * max(1.0 - x, 0.0)
            goal = (home[0] + state[K_PEL_VEL] * ahead, home[1],
                    home[2] + state[K_PEL_VEL + 2] * ahead)
            if x >= 1.0:
                write3(state, base + F_POS, goal)
                state[base + F_YAW] = yaw
                write4(state, base + F_ROT, flat_foot(shape, side, yaw))
                state[base + F_SWING] = 0.0
            else:
                k = smoothstep(x)
                p = lerp3(read3(state, base + F_START), goal, k)
                write3(state, base + F_POS, (p[0], p[1] + STEP_HEIGHT * math.sin(math.pi * x),
                                             p[2]))
                y0 = state[base + F_YAW0]
                state[base + F_YAW] = y0 + wrap(yaw - y0) * k
                # from the rotation it had (a tracked foot's, pointed or tilted) to flat
                write4(state, base + F_ROT, nlerp(read4(state, base + F_ROT0),
                                                  flat_foot(shape, side, yaw), k))
                moving = True
    if naive or moving:
        return
    # one planted, untracked foot at a time steps: the one the hips left furthest
    crouched = pel_p[1] < shape[S_CROUCH] * shape[S_STAND_PELVIS]
    worst, which, far = 0.0, -1, False
    for side in range(2):
        if tracked[side]:
            continue
        base = K_FEET + side * FOOT_STRIDE
        home = footprint(shape, side, pel_p, yaw)
        gap = math.hypot(home[0] - state[base + F_POS], home[2] - state[base + F_POS + 2])
        far = far or gap > shape[S_REACH] * shape[S_LEG]
        gap += abs(wrap(yaw - state[base + F_YAW])) * shape[S_STEP_DIST] / STEP_YAW
        if gap > worst:
            worst, which = gap, side
    if which >= 0 and ((worst > shape[S_STEP_DIST] and not crouched) or far):
        _start_step(state, which, t, shape[S_STEP_TIME])
