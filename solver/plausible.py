"""Is a T-pose sample a human body? The checks a calibration passes before it is solved.

Each device is valid on its own (the protocol checks positions and quaternions), but a
T-pose whose devices are a kilometre apart calibrates bones a kilometre long, and the
avatar's root is then solved far outside the world. A body's devices are within a few
metres of its head, and its feet are below it (y is up).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

FEET = ("left_foot", "right_foot")


def check_t_pose(roles: Sequence[str], positions: NDArray[np.float64],
                 max_extent_m: float) -> None:
    """ValueError naming the device and the reason unless every device is within
    ``max_extent_m`` of the head and the feet are below it; nothing without a head (the
    calibration itself then says which devices it needs)."""
    if "head" not in roles:
        return
    head = positions[list(roles).index("head")]
    distance = np.linalg.norm(positions - head, axis=1)
    if not distance.max(initial=0.0) <= max_extent_m:  # NaN lands here too
        row = int(np.argmax(~(distance <= max_extent_m)))
        raise ValueError(f"calibrate: {roles[row]} is {distance[row]:.4g} m from the head; "
                         f"a T-pose's devices are within {max_extent_m:g} m of it")
    for row, role in enumerate(roles):
        if role in FEET and not positions[row, 1] < head[1]:
            raise ValueError(f"calibrate: {role} (y = {positions[row, 1]:.4g} m) is not "
                             f"below the head (y = {head[1]:.4g} m); stand upright, y up")
