"""The body model's pelvis when no hip tracker says where it is: under the head, the
torso leaning back as the head drops (a squat, sitting down; ``BodyModel.drop_back``),
turned to a heading that follows the head's without its quick glances."""

from __future__ import annotations

import math

from numba import njit

from posecast.solver.kernels import taxis_angle, tconj, tmul, trotate
from posecast.solver.tracking.layout import (
    K_PEL_ADAPT,
    K_PEL_YAW,
    S_DROP_BACK,
    S_G0_HEAD,
    S_G0_PELVIS,
    S_HEAD_TO_PELVIS,
    S_NAIVE,
    S_NECK,
    S_STAND_HEAD,
    S_YAW_RATE,
    S_YAW_SLACK,
)
from posecast.solver.tracking.poses import add, heading, read3, read4, wrap, yaw_quat

# the most the torso leans (share of its length the pelvis may move back)
MAX_LEAN = 0.9
ADAPT_S = 2.0  # how fast (s) the offset a seen hip tracker shows is learned


@njit(cache=True)
def model_pelvis(shape, state, head_p, head_q, dt):
    """The model's pelvis pose (position, rotation) for the head's pose. Advances the
    heading filter."""
    g0 = read4(shape, S_G0_HEAD)
    head_yaw = heading(head_q, g0)
    h2p = read3(shape, S_HEAD_TO_PELVIS)
    pelvis0 = read4(shape, S_G0_PELVIS)
    if shape[S_NAIVE] > 0.0:  # the baseline: straight under the head, facing its way
        state[K_PEL_YAW] = head_yaw
        Y = yaw_quat(head_yaw)
        return (head_p[0], head_p[1] + h2p[1], head_p[2]), tmul(Y, pelvis0)
    off = wrap(head_yaw - state[K_PEL_YAW])
    excess = math.copysign(max(abs(off) - shape[S_YAW_SLACK], 0.0), off)
    yaw = state[K_PEL_YAW] + (1.0 - math.exp(-dt * shape[S_YAW_RATE])) * excess
    state[K_PEL_YAW] = wrap(yaw)
    Y = yaw_quat(yaw)
    # the head nods and tilts about the base of the neck: that point, not the head
    # joint, sits on the torso (looking down at a hand moves the head forward, not the
    # hips back)
    neck = shape[S_NECK]
    base = add(head_p, trotate(tmul(head_q, tconj(g0)), (0.0, -neck, 0.0)))
    rest = (h2p[0], h2p[1] + neck, h2p[2])  # the neck's base to the pelvis, upright
    length = max(-rest[1], 1e-3)
    drop = max(shape[S_STAND_HEAD] - neck - base[1], 0.0)
    back = min(shape[S_DROP_BACK] * drop, MAX_LEAN * length)
    lean = math.asin(back / length)
    left = trotate(Y, (1.0, 0.0, 0.0))
    tilt = taxis_angle(left[0], left[1], left[2], lean)  # the torso bends forward
    turn = tmul(tilt, Y)
    return add(base, trotate(turn, rest)), tmul(turn, pelvis0)


@njit(cache=True)
def adapted(state, model_p):
    """The model's pelvis moved by the offset learned while a hip tracker was seen."""
    return add(model_p, trotate(yaw_quat(state[K_PEL_YAW]), read3(state, K_PEL_ADAPT)))


@njit(cache=True)
def learn_pelvis(state, model_p, measured_p, dt):
    """While a hip tracker is seen: learn how far the person's pelvis sits from the
    model's (body axes), for the time it is lost."""
    Y = yaw_quat(state[K_PEL_YAW])
    rel = trotate(tconj(Y), (measured_p[0] - model_p[0], measured_p[1] - model_p[1],
                             measured_p[2] - model_p[2]))
    a = 1.0 - math.exp(-dt / ADAPT_S)
    for i in range(3):
        state[K_PEL_ADAPT + i] += a * (rel[i] - state[K_PEL_ADAPT + i])

