"""An avatar's skeleton as the solver's code takes it: a roster's ``AvatarInfo`` (joint
names, parents, calibrated rest offsets) as a ``Skeleton``, for the tools that pose it
(``posecast export``, ``posecast vmc``)."""

from __future__ import annotations

import numpy as np

from posecast.protocol import AvatarInfo
from posecast.solver.skeleton import Skeleton


def skeleton_of(info: AvatarInfo) -> Skeleton:
    return Skeleton(tuple(info.joint_names), np.array(info.parents, dtype=np.int32),
                    np.asarray(info.rest_offsets, dtype=np.float64))
