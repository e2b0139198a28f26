"""Name tables: which joint of a skeleton plays which canonical role.

The canonical joints are those of the paper's Table 1: pelvis, spine (one or more
joints), chest (the spine joint that carries the clavicles), neck (one or more), head,
and per side clavicle, upperarm, forearm, hand, thigh, shin, foot, toes. Every rig we read
names them differently; each style is one explicit table, checked by the tests against
the real files. Joints that play no role (CMU's LHipJoint, fingers, a static root) are
held fixed by the solvers.
"""

from __future__ import annotations

from posecast.solver.skeleton import Skeleton, SkeletonError

CHAIN_ROLES = ("spine", "neck")  # one or more joints each, root-most first


def _sided(table: dict[str, str], left: str, right: str) -> dict[str, str]:
    """Expand a table written for the left side with '{}' placeholders."""
    out: dict[str, str] = {}
    for name, role in table.items():
        if "{}" in name:
            out[name.format(left)] = f"{role}_l"
            out[name.format(right)] = f"{role}_r"
        else:
            out[name] = role
    return out


STYLES: dict[str, dict[str, str]] = {
    # MakeHuman game-engine rig (../shared/assets), the paper's bone names
    "makehuman": _sided({
        "pelvis": "pelvis", "spine_01": "spine", "spine_02": "spine", "spine_03": "chest",
        "neck_01": "neck", "head": "head", "clavicle_{}": "clavicle",
        "upperarm_{}": "upperarm", "lowerarm_{}": "forearm", "hand_{}": "hand",
        "thigh_{}": "thigh", "calf_{}": "shin", "foot_{}": "foot", "ball_{}": "toes",
    }, "l", "r"),
    # CMU MotionBuilder style (CMU 01_xx, 02_xx; the MakeHuman cmu_mb rig)
    "cmu_motionbuilder": _sided({
        "Hips": "pelvis", "LowerBack": "spine", "Spine": "spine", "Spine1": "chest",
        "Neck": "neck", "Neck1": "neck", "Head": "head", "{}Shoulder": "clavicle",
        "{}Arm": "upperarm", "{}ForeArm": "forearm", "{}Hand": "hand",
        "{}UpLeg": "thigh", "{}Leg": "shin", "{}Foot": "foot", "{}ToeBase": "toes",
    }, "Left", "Right"),
    # CMU 3ds Max style (CMU 131_xx): LeftShoulder is the upper arm here
    "cmu_3dsmax": _sided({
        "Hips": "pelvis", "lowerback": "spine", "Chest": "spine", "Chest2": "chest",
        "lowerneck": "neck", "Neck": "neck", "Head": "head", "{}Collar": "clavicle",
        "{}Shoulder": "upperarm", "{}Elbow": "forearm", "{}Wrist": "hand",
        "{}Hip": "thigh", "{}Knee": "shin", "{}Ankle": "foot", "{}Toe": "toes",
    }, "Left", "Right"),
    # Bandai Namco Research Motiondataset
    "bandai": _sided({
        "Hips": "pelvis", "Spine": "spine", "Chest": "chest", "Neck": "neck",
        "Head": "head", "Shoulder_{}": "clavicle", "UpperArm_{}": "upperarm",
        "LowerArm_{}": "forearm", "Hand_{}": "hand", "UpperLeg_{}": "thigh",
        "LowerLeg_{}": "shin", "Foot_{}": "foot", "Toes_{}": "toes",
    }, "L", "R"),
}


def detect_style(skeleton: Skeleton) -> str:
    """The naming style whose table covers the most joints of the skeleton; every role
    must be present."""
    names = set(skeleton.names)
    best = max(STYLES, key=lambda s: len(names & STYLES[s].keys()))
    table = STYLES[best]
    missing = sorted({role for role in table.values()} - {table[n] for n in names & table.keys()})
    if missing:
        raise SkeletonError(
            f"cannot map this skeleton onto the canonical joints: closest naming style "
            f"{best!r} lacks {', '.join(missing)}")
    return best


def roles(skeleton: Skeleton, style: str | None = None) -> dict[str, list[int]]:
    """Canonical role -> joint indices (root-most first). Single roles have one index."""
    table = STYLES[style or detect_style(skeleton)]
    out: dict[str, list[int]] = {}
    for j, name in enumerate(skeleton.names):
        role = table.get(name)
        if role is not None:
            out.setdefault(role, []).append(j)
    for role, joints in out.items():
        if role not in CHAIN_ROLES and len(joints) != 1:
            raise SkeletonError(f"role {role!r} is played by several joints: {joints}")
    return out
