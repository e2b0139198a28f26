"""Motion data as read from files: a skeleton animated over frames, and Vive device
recordings."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from solver.skeleton import Skeleton

# Vive device names, as DESIGN.md's eval contract spells them
VIVE_DEVICES = ("head", "hip", "left_hand", "right_hand", "left_forearm", "right_forearm",
                "left_foot", "right_foot", "left_knee", "right_knee")
DRIVING_DEVICES = ("head", "hip", "left_hand", "right_hand", "left_foot", "right_foot")
HELDOUT_DEVICES = ("left_forearm", "right_forearm", "left_knee", "right_knee")


@dataclass(frozen=True, eq=False)
class Motion:
    """A skeleton animated over F frames (from a BVH file)."""

    skeleton: Skeleton
    rotations: NDArray[np.float64]  # (F, J, 4) local rotations, x y z w
    translations: NDArray[np.float64]  # (F, J, 3) local translations; root: global position
    fps: float
    source: str
    # frames before this one are a calibration/bind pose, not part of the motion
    first_frame: int = 0

    @property
    def num_frames(self) -> int:
        return int(self.rotations.shape[0])


@dataclass(frozen=True, eq=False)
class ViveRecording:
    """Device poses over F frames, in SteamVR standing-universe coordinates (metres, +y up)."""

    devices: tuple[str, ...]  # names from VIVE_DEVICES, in file order
    positions: NDArray[np.float64]  # (F, D, 3)
    rotations: NDArray[np.float64]  # (F, D, 4) unit quaternions x y z w
    fps: float
    source: str

    @property
    def num_frames(self) -> int:
        return int(self.positions.shape[0])

    def device(self, name: str) -> int:
        return self.devices.index(name)
