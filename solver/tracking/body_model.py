"""The body model's constants: the numbers that say how a body moves where it has no
device (how far the hips go back as the head drops, when and how a foot steps).

They live in each avatar's ``shape`` row (``write``), not in the compiled kernels, so
that leave-one-clip-out (``solver.tracking.crossval``) can score candidates without a
recompile. ``SHIPPED`` holds the values every avatar gets; docs/accuracy.md gives the
figures they reach on clips that did not choose them.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import numpy as np
from numpy.typing import NDArray

from posecast.solver.tracking.layout import S_MODEL


@dataclass(frozen=True)
class BodyModel:
    # How far (m) the pelvis moves back, per metre the head is below its standing
    # height: squatting and sitting down push the hips back while the head stays over
    # the feet.
    drop_back: float = 0.5
    # The pelvis turns to the head's heading only where the head is turned more than
    # ``yaw_slack`` (rad) from it, closing that excess at ``yaw_rate`` (1/s): a glance
    # at a hand or over the shoulder turns the head, not the hips.
    yaw_slack: float = 0.0
    yaw_rate: float = 20.0
    # How far (m) below the head joint the head nods and tilts: the base of the neck.
    neck: float = 0.1
    # A planted foot steps when the hip's footprint is this far (m) from it.
    step_dist: float = 0.35
    # s a step takes: the clips would choose ever quicker steps (feet that are where they
    # should be sooner), but below a quick side step's 0.25 s a step is a twitch
    step_time: float = 0.25
    lead: float = 0.5  # a step lands this share of a step's time ahead of the moving hips
    # Below this share of its standing height the pelvis is crouched or seated: the feet
    # stay planted unless the hips are ``reach`` leg lengths away from one.
    crouch: float = 0.9
    reach: float = 0.5

    def write(self, shape: NDArray[np.float64]) -> None:
        """Into an avatar's shape row, at the slots the kernels read (``layout``)."""
        shape[S_MODEL:S_MODEL + len(FIELDS)] = [getattr(self, f) for f in FIELDS]

    def moved(self) -> dict[str, float]:
        """The constants that differ from the shipped ones."""
        return {k: v for k, v in asdict(self).items() if v != getattr(SHIPPED, k)}


FIELDS = tuple(f.name for f in fields(BodyModel))
SHIPPED = BodyModel()

# Leave-one-clip-out's candidates: the shipped value and a neighbour either side, about as
# far apart as the clips can tell (step_time: no quicker than the shipped, see above).
CANDIDATES: dict[str, tuple[float, ...]] = {
    "drop_back": (0.3, 0.5, 0.7),
    "yaw_slack": (0.0, 0.3, 0.6),
    "yaw_rate": (5.0, 20.0, 50.0),
    "neck": (0.0, 0.1, 0.2),
    "step_dist": (0.25, 0.35, 0.45),
    "step_time": (0.25, 0.3, 0.35),
    "lead": (0.25, 0.5, 1.0),
    "crouch": (0.85, 0.9, 0.95),
    "reach": (0.3, 0.5, 0.8),
}
