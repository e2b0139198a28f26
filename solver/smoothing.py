"""SLERP smoothing between frames (paper, section 3.1.4), as an option.

Each new pose is blended towards from the previous output: rotations by spherical linear
interpolation, the root linearly. ``alpha`` is the weight kept from the previous frame
(0 = off, no smoothing); it trades jitter for lag."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from posecast.solver import rotations as R


class SlerpSmoother:
    def __init__(self, alpha: float) -> None:
        if not 0.0 <= alpha < 1.0:
            raise ValueError("smoothing must be in [0, 1)")
        self.alpha = alpha
        self._q: NDArray[np.float64] | None = None
        self._root: NDArray[np.float64] | None = None

    def update(self, q: NDArray[np.float64],
               root: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        if self._q is None or self._root is None:
            self._q, self._root = q.copy(), root.copy()
        else:
            self._q = R.slerp(self._q, q, np.full(q.shape[:-1], 1.0 - self.alpha))
            self._root = self.alpha * self._root + (1.0 - self.alpha) * root
        return self._q, self._root
