"""Which devices drive an avatar: the roles, the solver slot of each, and tracker sets.

A player owns any set of devices from head and both hands (every VR owner) up to all
eleven roles. Each role has one slot in the solver's target arrays, the same slot for
every avatar, so that a batch of avatars with different sets is one array: the first
MAIN slots (head, pelvis, hands, feet) always hold a target, from the device or from the
body model when the device is absent; the others (elbows, knees, chest) only steer the
solve, with a weight that is zero when the device is absent.
"""

from __future__ import annotations

# slot order: a device's slot is its index here; BONES[i] is the rig role it is mounted on
DEVICES = ("head", "hip", "left_hand", "right_hand", "left_foot", "right_foot",
           "left_forearm", "right_forearm", "left_knee", "right_knee", "chest")
BONES = ("head", "pelvis", "hand_l", "hand_r", "foot_l", "foot_r", "forearm_l", "forearm_r",
         "shin_l", "shin_r", "chest")
SLOT = {name: i for i, name in enumerate(DEVICES)}
MAIN = 6  # slots 0..5 are rig.EFFECTORS: always a target
HEAD, HIP, HAND_L, HAND_R, FOOT_L, FOOT_R = range(MAIN)
ELBOW_L, ELBOW_R, KNEE_L, KNEE_R, CHEST = range(MAIN, len(DEVICES))

MINIMUM = ("head", "left_hand", "right_hand")  # what a calibration needs
PRESETS: dict[str, tuple[str, ...]] = {
    "3": MINIMUM,
    "4": (*MINIMUM, "hip"),
    "6": (*MINIMUM, "hip", "left_foot", "right_foot"),
    "10": (*MINIMUM, "hip", "left_foot", "right_foot", "left_forearm", "right_forearm",
           "left_knee", "right_knee"),
}
DEFAULT_SET = "6"


def parse_devices(spec: str) -> tuple[str, ...]:
    """A tracker set: a preset ("3", "4", "6", "10"), a comma list of roles, or both
    ("6,chest"), in slot order. ValueError (one line) for anything else or a set without
    head and hands."""
    items = [n.strip() for n in spec.split(",") if n.strip()]
    names: list[str] = [r for n in items for r in PRESETS.get(n, (n,))]
    unknown = [n for n in names if n not in SLOT]
    if unknown or not names:
        raise ValueError(
            f"--devices {spec!r}: expected a preset ({', '.join(PRESETS)}) or a comma "
            f"list of {', '.join(DEVICES)}" + (f"; unknown: {', '.join(unknown)}"
                                               if unknown else ""))
    lacking = [n for n in MINIMUM if n not in names]
    if lacking:
        raise ValueError(f"--devices {spec!r}: head and both hands are the minimum; "
                         f"add {', '.join(lacking)}")
    return tuple(sorted(set(names), key=SLOT.__getitem__))
