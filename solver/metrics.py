"""Accuracy metrics: position and rotation errors, and the lag between two trajectories."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from posecast.solver import rotations as R


def position_error_mm(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Euclidean distance in millimetres, over the last axis."""
    return np.asarray(np.linalg.norm(a - b, axis=-1) * 1000.0)


def rotation_error_deg(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Angle of the rotation between two orientations, degrees."""
    return np.asarray(np.degrees(R.angle_between(a, b)))


def lag_frames(solved: NDArray[np.float64], recorded: NDArray[np.float64],
               max_shift: int = 45) -> float:
    """Time shift (frames, > 0: solved lags behind) that best aligns two trajectories
    (F, 3), from the mean distance at each whole shift refined by a parabola through the
    best three."""
    F = solved.shape[0]
    max_shift = min(max_shift, F // 3)
    shifts = np.arange(-max_shift, max_shift + 1)
    cost = np.empty(len(shifts))
    for i, k in enumerate(shifts):
        if k >= 0:
            a, b = solved[k:], recorded[: F - k]
        else:
            a, b = solved[: F + k], recorded[-k:]
        cost[i] = np.mean(np.sum((a - b) ** 2, axis=-1))
    i = int(np.argmin(cost))
    if 0 < i < len(shifts) - 1:
        c0, c1, c2 = cost[i - 1], cost[i], cost[i + 1]
        denom = c0 - 2.0 * c1 + c2
        frac = 0.5 * (c0 - c2) / denom if denom > 0 else 0.0
        return float(shifts[i] + frac)
    return float(shifts[i])
