"""Forward kinematics batched over avatars: one call computes B avatars."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from posecast.solver.kernels import fk_batch
from posecast.solver.skeleton import Skeleton


def forward_kinematics(skeleton: Skeleton, rotations: NDArray[np.float64],
                       root: NDArray[np.float64],
                       offsets: NDArray[np.float64] | None = None
                       ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Global rotations (B, J, 4) and positions (B, J, 3) from local rotations (B, J, 4)
    and root positions (B, 3). ``offsets`` (B, J, 3) overrides the skeleton's bone
    offsets per avatar (calibrated people, or files whose bones change length)."""
    rotations = np.ascontiguousarray(rotations, dtype=np.float64)
    root = np.ascontiguousarray(root, dtype=np.float64)
    B, J = rotations.shape[:2]
    if skeleton.num_joints != J:
        raise ValueError(f"pose has {J} joints, skeleton {skeleton.num_joints}")
    off = skeleton.offsets[None] if offsets is None else np.ascontiguousarray(offsets,
                                                                               np.float64)
    gq = np.empty((B, J, 4))
    gp = np.empty((B, J, 3))
    fk_batch(skeleton.parents.astype(np.int64), off, rotations, root, gq, gp)
    return gq, gp
