"""Device roles: the names of the tracked devices a player streams.

They equal ``solver.motion.VIVE_DEVICES`` (a test keeps them equal); they are spelled out
here because protocol/ may import only numpy, pydantic and msgpack.
"""

from __future__ import annotations

from typing import Literal

DeviceRole = Literal["head", "hip", "left_hand", "right_hand", "left_forearm", "right_forearm",
                     "left_foot", "right_foot", "left_knee", "right_knee"]

DEVICE_ROLES: tuple[DeviceRole, ...] = (
    "head", "hip", "left_hand", "right_hand", "left_forearm", "right_forearm",
    "left_foot", "right_foot", "left_knee", "right_knee")

# The devices a T-pose calibration needs: the ones that drive the solver
# (solver.motion.DRIVING_DEVICES). Forearms and knees are optional.
CALIBRATION_ROLES: tuple[DeviceRole, ...] = (
    "head", "hip", "left_hand", "right_hand", "left_foot", "right_foot")
