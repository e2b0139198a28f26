"""Poses at irregular instants resampled to a fixed rate, for formats that need one.

Recorded frames arrive when the network delivers them (a player's 90 Hz with jitter, gaps
where a frame was lost); BVH, like most animation formats, has one frame time. Rotations
are interpolated by slerp and root positions linearly between the two recorded frames
that bracket each output instant; output instants run from the first recorded instant
to the last, every 1/fps seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from posecast.solver import rotations as R

Array = NDArray[np.float64]

SINGLE_FRAME_FPS = 30.0  # the frame rate given to a one-frame take (any rate fits it)
MAX_FPS = 1000.0  # above this a rate is a mistake (a period passed for a rate)
TIME_EPS = 1e-9  # seconds: an instant this close to the last recorded one is inside


@dataclass(frozen=True, eq=False)
class Resampled:
    """Poses at ``times[0] + k / fps``: roots (F, 3), rotations (F, J, 4)."""

    times: Array  # (F,)
    roots: Array  # (F, 3)
    rotations: Array  # (F, J, 4)
    fps: float


def default_fps(times: Array) -> float:
    """The recording's own rate: the median interval between distinct instants, as a
    whole number of frames per second (a 90 Hz headset with jitter gives 90)."""
    steps = np.diff(np.unique(np.asarray(times, dtype=np.float64)))
    if steps.size == 0:
        return SINGLE_FRAME_FPS
    return float(max(1, round(1.0 / float(np.median(steps)))))


def resample(times: Array, roots: Array, rotations: Array,
             fps: float | None = None) -> Resampled:
    """The poses at a fixed rate (``fps``; None: ``default_fps``). ValueError names the
    problem: arrays of disagreeing length, instants that go back, non-finite values."""
    times, roots, rotations = _checked(times, roots, rotations)
    rate = default_fps(times) if fps is None else float(fps)
    if not (math.isfinite(rate) and 0.0 < rate <= MAX_FPS):
        raise ValueError(f"fps must be a number of frames per second in (0, {MAX_FPS:g}], "
                         f"got {fps}")
    # instants recorded twice: the later frame is the newer pose of that instant
    keep = np.append(np.diff(times) > 0.0, True)
    times, roots, rotations = times[keep], roots[keep], rotations[keep]
    if times.size == 1:
        return Resampled(times.copy(), roots.copy(), rotations.copy(), rate)
    count = math.floor((times[-1] - times[0]) * rate + TIME_EPS) + 1
    out_t = times[0] + np.arange(count) / rate
    i = np.clip(np.searchsorted(times, out_t, side="right") - 1, 0, times.size - 2)
    u = np.clip((out_t - times[i]) / (times[i + 1] - times[i]), 0.0, 1.0)
    out_roots = roots[i] + u[:, None] * (roots[i + 1] - roots[i])
    out_rot = R.slerp(rotations[i], rotations[i + 1], u[:, None])
    return Resampled(out_t, out_roots, out_rot, rate)


def _checked(times: Array, roots: Array, rotations: Array) -> tuple[Array, Array, Array]:
    times = np.asarray(times, dtype=np.float64)
    roots = np.asarray(roots, dtype=np.float64)
    rotations = np.asarray(rotations, dtype=np.float64)
    if times.ndim != 1 or times.size == 0:
        raise ValueError(f"times must be a non-empty 1-D array, got shape {times.shape}")
    frames = times.size
    if roots.shape != (frames, 3):
        raise ValueError(f"roots must be ({frames}, 3) for {frames} instants, "
                         f"got {roots.shape}")
    if rotations.ndim != 3 or rotations.shape[0] != frames or rotations.shape[2] != 4:
        raise ValueError(f"rotations must be ({frames}, J, 4) quaternions, "
                         f"got {rotations.shape}")
    for name, values in (("times", times), ("roots", roots), ("rotations", rotations)):
        if not np.all(np.isfinite(values)):
            raise ValueError(f"{name} hold a value that is not a finite number")
    back = np.flatnonzero(np.diff(times) < 0.0)
    if back.size:
        k = int(back[0]) + 1
        raise ValueError(f"times must not go back: frame {k} at {times[k]:.6f} s comes "
                         f"after {times[k - 1]:.6f} s")
    norms = np.linalg.norm(rotations, axis=-1)
    if np.any(norms < 1e-6):
        raise ValueError("rotations hold a zero quaternion")
    return times, roots, rotations / norms[..., None]
