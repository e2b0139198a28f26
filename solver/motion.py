"""Motion data as read from files: a skeleton animated over frames, and Vive device
recordings."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from posecast.solver import rotations as R
from posecast.solver.choices import VIVE_DEVICES as VIVE_DEVICES
from posecast.solver.skeleton import Skeleton

# Vive device names, as DESIGN.md's eval contract spells them (and a chest tracker)
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


def drop_static_root(motion: Motion) -> Motion:
    """The motion rooted at the root's only child, when the root never moves.

    Such a root (Bandai's joint_Root, at the origin in every frame) is the world frame,
    not part of the body, which walks away from it. An avatar is a root position, joint
    rotations and fixed bones, so it follows the body only if the body's top joint (Hips)
    is its root; that joint's per-frame translation, taken through the static root,
    becomes its global position. Any other motion comes back unchanged.
    """
    sk, rot, trans = motion.skeleton, motion.rotations, motion.translations
    static = bool(np.all(rot[:, 0] == rot[0, 0]) and np.all(trans[:, 0] == trans[0, 0]))
    if not static or sk.children(0) != [1]:
        return motion
    q0, t0 = rot[0, 0], trans[0, 0]
    rot = rot[:, 1:].copy()
    trans = trans[:, 1:].copy()
    rot[:, 0] = R.mul(q0, rot[:, 0])
    trans[:, 0] = t0 + R.rotate(q0, trans[:, 0])
    first = motion.first_frame
    # as read_bvh does: the offsets are the first motion frame's translations
    skeleton = Skeleton(sk.names[1:], sk.parents[1:] - 1, trans[first], sk.tips[1:],
                        sk.role_names)
    return Motion(skeleton=skeleton, rotations=rot, translations=trans, fps=motion.fps,
                  source=motion.source, first_frame=first)


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
