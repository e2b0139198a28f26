"""Device roles: the names of the tracked devices a player streams.

They equal ``solver.motion.VIVE_DEVICES`` (a test keeps them equal); they are spelled out
here because protocol/ may import only numpy, pydantic and msgpack.
"""

from __future__ import annotations

from typing import Literal

DeviceRole = Literal["head", "hip", "left_hand", "right_hand", "left_forearm", "right_forearm",
                     "left_foot", "right_foot", "left_knee", "right_knee", "chest"]

DEVICE_ROLES: tuple[DeviceRole, ...] = (
    "head", "hip", "left_hand", "right_hand", "left_forearm", "right_forearm",
    "left_foot", "right_foot", "left_knee", "right_knee", "chest")

# The devices a T-pose calibration needs (solver.calibration.CALIBRATION_DEVICES): the
# head and hands give the height, arm span and heading; every other device is optional.
CALIBRATION_ROLES: tuple[DeviceRole, ...] = ("head", "left_hand", "right_hand")

# A frame's lost devices as bits (``AvatarBatch.lost``): bit i is DEVICE_ROLES[i]
LOST_BITS_LIMIT = 1 << len(DEVICE_ROLES)


def role_bits(roles: tuple[str, ...] | list[str]) -> int:
    """The bits of these roles (unknown names are ignored)."""
    return sum(1 << DEVICE_ROLES.index(r) for r in set(roles) if r in DEVICE_ROLES)


def roles_of_bits(bits: int) -> tuple[DeviceRole, ...]:
    """The roles whose bits are set, in DEVICE_ROLES order."""
    return tuple(r for i, r in enumerate(DEVICE_ROLES) if bits >> i & 1)
