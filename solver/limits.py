"""Degrees of freedom and angle limits of the canonical joints, as data (paper, Table 1).

Each joint turns relative to its *canonical pose* (upright, facing +z, arms straight out
sideways, legs straight down; see ``solver/rig.py``) in a *limit frame* whose y axis runs
along the bone and whose x axis is given below. A joint's rotation away from the canonical
pose is split into a swing about an axis perpendicular to the bone, with components
(x, z), and a twist about the bone (y). Limits are boxes on (x, twist y, z) in radians.

Sign conventions, left side (the right side is the mirror image, so the same numbers
mean the same anatomical motion):
- spine, neck, head: +x bends forward, +z bends to the right, +y turns to the left.
- thigh: -x flexes the hip (leg forward), +z adducts. shin: +x flexes the knee.
- foot: +x points the toes down (plantar flexion).
- clavicle: +x moves the shoulder forward, +z raises it.
- hand: x flexes the wrist, z deviates it.
- upper arm, forearm: +x swings forward; upper arm +z raises the arm above horizontal.

The paper fixes which axes each joint has (Table 1, 56 DoF in the MakeHuman rig:
calf 1, lower arm 2, hand 2, clavicle 2, every other joint 3) and one limit (the knee
turns about x only, 0..2 rad). It gives no other numbers; the others here are ranges of
motion from the clinical literature, widened a little because trackers are strapped on
soft tissue and calibration is imperfect. Two go further than the paper:
- the knee flexes to 150 deg, not 115 (2 rad): deep squats, kneeling and a sprinter's
  swing leg pass 140 deg, and 2 rad left those feet short of their trackers;
- the ankle flexes +-90 deg about its reference: the foot tracker measures it, and a
  BVH whose rest pose lies flat takes its reference from the first frame, which may be
  mid-stride (a run's first frame has the foot 50 deg from its median).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

UP = (0.0, 1.0, 0.0)
DOWN = (0.0, -1.0, 0.0)
LEFT = (1.0, 0.0, 0.0)
FORWARD = (0.0, 0.0, 1.0)


@dataclass(frozen=True)
class JointSpec:
    """What one canonical joint may do, and how its limit frame is laid out."""

    dof: str  # which of the axes "x", "y" (twist), "z" turn
    lo_deg: tuple[float, float, float]  # lower limits of (x, y, z) in degrees
    hi_deg: tuple[float, float, float]
    # the bone direction in the canonical pose, in body coordinates (x left, y up,
    # z forward); None: the direction from this joint to its child as the rig has it
    bone: tuple[float, float, float] | None
    x_ref: tuple[float, float, float]  # the limit frame's x axis, before orthogonalising
    straighten: bool = False  # rotate the bone onto `bone` to build the canonical pose

    @property
    def lo(self) -> np.ndarray:
        return np.radians(self.lo_deg) * self.mask

    @property
    def hi(self) -> np.ndarray:
        return np.radians(self.hi_deg) * self.mask

    @property
    def mask(self) -> np.ndarray:
        return np.array([a in self.dof for a in "xyz"], dtype=np.float64)


FREE = 180.0

# Left-side and central joints; right-side joints mirror the left ones.
JOINTS: dict[str, JointSpec] = {
    "pelvis": JointSpec("xyz", (-FREE, -FREE, -FREE), (FREE, FREE, FREE), UP, LEFT),
    "spine": JointSpec("xyz", (-30, -30, -25), (50, 30, 25), UP, LEFT),
    "chest": JointSpec("xyz", (-30, -30, -25), (50, 30, 25), UP, LEFT),
    "neck": JointSpec("xyz", (-45, -60, -40), (60, 60, 40), UP, LEFT),
    "head": JointSpec("xyz", (-45, -60, -40), (45, 60, 40), UP, LEFT),
    "clavicle": JointSpec("xz", (-25, 0, -15), (25, 0, 35), None, DOWN),
    "upperarm": JointSpec("xyz", (-70, -100, -110), (150, 100, 110), LEFT, DOWN, True),
    "forearm": JointSpec("xy", (-5, -100, 0), (155, 100, 0), LEFT, DOWN, True),
    # limit frame along the forearm; x (forward, with the palm down in the canonical
    # T-pose) flexes the wrist, z deviates it towards the thumb or the little finger
    "hand": JointSpec("xz", (-85, 0, -35), (85, 0, 35), None, FORWARD),
    "thigh": JointSpec("xyz", (-135, -50, -55), (35, 50, 35), DOWN, LEFT, True),
    # the paper's axes (the knee turns about x only), a real knee's range (see above)
    "shin": JointSpec("x", (0, 0, 0), (150, 0, 0), DOWN, LEFT, True),
    "foot": JointSpec("xyz", (-90, -40, -35), (90, 40, 35), None, LEFT),
    "toes": JointSpec("xyz", (-60, -15, -15), (45, 15, 15), None, LEFT),
}


def spec_for(role: str) -> JointSpec:
    """The spec of a role such as "thigh_l", "spine" or "head"."""
    return JOINTS[role[:-2] if role.endswith(("_l", "_r")) else role]

