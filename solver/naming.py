"""Name tables: which joint of a skeleton plays which canonical role.

The canonical joints are those of the paper's Table 1: pelvis, spine (one or more
joints), chest (the spine joint that carries the clavicles), neck (one or more), head,
and per side clavicle, upperarm, forearm, hand, thigh, shin, foot, toes (optional). Every
rig names them differently; each style is one explicit table (MakeHuman, CMU's two, Bandai,
Mixamo, DAZ/Poser, Unity/VRM, VRoid, SMPL), compared after ``normalise`` (no case,
separators or namespace), checked by the tests against real and hand-written files. Where
names fail, the shape does (``solver/structure.py``); ``Skeleton.role_names`` (``eval
--map``) overrides both. Joints that play no role (CMU's LHipJoint, fingers, a static
root) are held fixed by the solvers.
"""

from __future__ import annotations

import itertools
import re

from posecast.solver import structure
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
    # Mixamo (mixamorig:Hips, ...; the prefix goes in normalising): CMU-like, 3 spines
    "mixamo": _sided({
        "Hips": "pelvis", "Spine": "spine", "Spine1": "spine", "Spine2": "chest",
        "Neck": "neck", "Head": "head", "{}Shoulder": "clavicle", "{}Arm": "upperarm",
        "{}ForeArm": "forearm", "{}Hand": "hand", "{}UpLeg": "thigh", "{}Leg": "shin",
        "{}Foot": "foot", "{}ToeBase": "toes",
    }, "Left", "Right"),
    # DAZ/Poser (Genesis 1, Poser figures): hip is the pelvis, no toes in many exports
    "daz": _sided({
        "hip": "pelvis", "abdomen": "spine", "abdomen2": "spine", "chest": "chest",
        "neck": "neck", "head": "head", "{}Collar": "clavicle", "{}Shldr": "upperarm",
        "{}ForeArm": "forearm", "{}Hand": "hand", "{}Thigh": "thigh", "{}Shin": "shin",
        "{}Foot": "foot", "{}Toe": "toes",
    }, "l", "r"),
    # Unity's humanoid avatar and VRM (UpperChest, Neck and Toes are optional there)
    "unity": _sided({
        "Hips": "pelvis", "Spine": "spine", "Chest": "spine", "UpperChest": "chest",
        "Neck": "neck", "Head": "head", "{}Shoulder": "clavicle", "{}UpperArm": "upperarm",
        "{}LowerArm": "forearm", "{}Hand": "hand", "{}UpperLeg": "thigh",
        "{}LowerLeg": "shin", "{}Foot": "foot", "{}Toes": "toes",
    }, "Left", "Right"),
    # VRoid Studio's VRM export
    "vroid": _sided({
        "J_Bip_C_Hips": "pelvis", "J_Bip_C_Spine": "spine", "J_Bip_C_Chest": "spine",
        "J_Bip_C_UpperChest": "chest", "J_Bip_C_Neck": "neck", "J_Bip_C_Head": "head",
        "J_Bip_{}_Shoulder": "clavicle", "J_Bip_{}_UpperArm": "upperarm",
        "J_Bip_{}_LowerArm": "forearm", "J_Bip_{}_Hand": "hand",
        "J_Bip_{}_UpperLeg": "thigh", "J_Bip_{}_LowerLeg": "shin", "J_Bip_{}_Foot": "foot",
        "J_Bip_{}_ToeBase": "toes",
    }, "L", "R"),
    # SMPL / SMPL-X joint names: here "shoulder" is the upper arm and "foot" the toes
    "smpl": _sided({
        "pelvis": "pelvis", "spine1": "spine", "spine2": "spine", "spine3": "chest",
        "neck": "neck", "head": "head", "{}_collar": "clavicle", "{}_shoulder": "upperarm",
        "{}_elbow": "forearm", "{}_wrist": "hand", "{}_hip": "thigh", "{}_knee": "shin",
        "{}_ankle": "foot", "{}_foot": "toes",
    }, "left", "right"),
}

ROLES = ("pelvis", "spine", "chest", "neck", "head", *(
    f"{r}_{s}" for s in "lr" for r in ("clavicle", "upperarm", "forearm", "hand", "thigh",
                                       "shin", "foot", "toes")))
OPTIONAL = {"neck", "toes_l", "toes_r"}  # every other role must be played
TORSO = ("spine", "chest", "neck")  # placed by the path from pelvis to head
_LIMBS = (("clavicle", "upperarm", "forearm", "hand"), ("thigh", "shin", "foot", "toes"))


def normalise(name: str) -> str:
    """A joint name as the tables compare it: no namespace (``mixamorig:``,
    ``Armature|``), no case, no separators: 'mixamorig:LeftUpLeg' -> 'leftupleg'."""
    name = re.split(r"[:|]", name)[-1]
    key = re.sub(r"[\s_\-.]", "", name).lower()
    return re.sub(r"^mixamorig\d*", "", key)  # 'mixamorig_Hips' has no colon


_KEYS = {style: {normalise(n): role for n, role in table.items()}
         for style, table in STYLES.items()}


def roles(skeleton: Skeleton, style: str | None = None) -> dict[str, list[int]]:
    """Canonical role -> joint indices (root-most first). Single roles have one index.

    The joints named in ``skeleton.role_names`` (``--map``) play those roles; the others
    are matched by name, trying the naming styles that cover most joints first, and then
    by shape (``structure.infer_roles``). The spine, chest and neck are placed by
    structure in every case: the joints on the way from the pelvis to the head, the chest
    being the one the clavicles hang from (Unity's UpperChest is optional; SMPL's spine3,
    Mixamo's Spine2 and CMU's Spine1 all carry them). SkeletonError when nothing fits.
    """
    explicit = _explicit(skeleton)
    names = [normalise(n) for n in skeleton.names]
    styles = [style] if style else sorted(
        _KEYS, key=lambda s: -sum(n in _KEYS[s] for n in names))
    problems: list[str] = []
    for s in styles:
        found = {j: _KEYS[s][n] for j, n in enumerate(names) if n in _KEYS[s]}
        try:
            return _complete(skeleton, found, explicit)
        except SkeletonError as err:
            problems.append(f"names ({s}): {err}" if found or explicit
                            else "names: none that a naming table knows")
    if style is None:
        try:
            shape = structure.infer_roles(skeleton)
            found = {js[k]: r for r, js in shape.items() for k in range(len(js))}
            return _complete(skeleton, found, explicit)
        except SkeletonError as err:
            problems.append(f"shape: {err}")
    shown = "; ".join(dict.fromkeys((problems[0], problems[-1])))  # best names, shape
    raise SkeletonError(f"cannot map this skeleton onto the canonical joints: {shown}; "
                        f"map its joints with --map FILE")


def detect_style(skeleton: Skeleton) -> str:
    """The naming style that maps the skeleton, or "shape" when only its shape does."""
    names = [normalise(n) for n in skeleton.names]
    for s in sorted(_KEYS, key=lambda s: -sum(n in _KEYS[s] for n in names)):
        try:
            roles(skeleton, s)
            return s
        except SkeletonError:
            continue
    roles(skeleton)  # raises with the reasons when nothing maps it
    return "shape"


def _explicit(skeleton: Skeleton) -> dict[int, str]:
    out: dict[int, str] = {}
    for name, role in (skeleton.role_names or {}).items():
        if name not in skeleton.names:
            continue  # one map may serve several exports of a rig
        if role and role not in ROLES:
            raise SkeletonError(f"the joint map gives {name!r} the role {role!r}: expected "
                                f"one of {', '.join(ROLES)} (or \"\" for none)")
        out[skeleton.names.index(name)] = role
    return out


def _complete(skeleton: Skeleton, found: dict[int, str],
              explicit: dict[int, str]) -> dict[str, list[int]]:
    """Roles from matched names overridden by the explicit map, the torso placed by
    structure, checked: one joint per single role, limbs that hang together."""
    claimed = {r for r in explicit.values() if r}
    by_joint = {j: r for j, r in found.items() if j not in explicit and r not in claimed}
    by_joint.update({j: r for j, r in explicit.items() if r})
    if not claimed & set(TORSO):  # the map leaves the torso to structure
        by_joint = {j: r for j, r in by_joint.items() if r not in TORSO}
    out: dict[str, list[int]] = {}
    for j in sorted(by_joint):
        out.setdefault(by_joint[j], []).append(j)
    for role, joints in out.items():
        if role not in CHAIN_ROLES and len(joints) != 1:
            raise SkeletonError(f"role {role!r} is played by several joints: "
                                f"{', '.join(skeleton.names[j] for j in joints)}")
    missing = [r for r in ("pelvis", "head", *(f"{r}_{s}" for s in "lr" for r in (
        *_LIMBS[0], *_LIMBS[1][:3]))) if r not in out]
    if missing:
        raise SkeletonError(f"no joint for {', '.join(missing)}")
    for side in "lr":  # optional toes that are not the foot's child play no role
        toes, foot = out.get(f"toes_{side}"), out[f"foot_{side}"]
        if toes is not None and skeleton.parents[toes[0]] != foot[0]:
            del out[f"toes_{side}"]
    if not claimed & set(TORSO):
        _place_torso(skeleton, out)
    _check(skeleton, out)
    return {r: out[r] for r in sorted(out, key=lambda r: out[r][0])}


def _place_torso(skeleton: Skeleton, out: dict[str, list[int]]) -> None:
    """spine, chest and neck: the joints between pelvis and head, split at the joint the
    clavicles hang from."""
    parents = skeleton.parents
    pelvis, head = out["pelvis"][0], out["head"][0]
    path: list[int] = []
    j = int(parents[head])
    while j != pelvis:
        if j < 0:
            raise SkeletonError(f"the head {skeleton.names[head]!r} does not hang from "
                                f"the pelvis {skeleton.names[pelvis]!r}")
        path.insert(0, j)
        j = int(parents[j])
    carriers = {int(parents[out[f"clavicle_{s}"][0]]) for s in "lr"}
    if len(carriers) != 1 or next(iter(carriers)) not in path:
        raise SkeletonError("the clavicles do not hang from one joint of the spine")
    k = path.index(next(iter(carriers)))
    if k == 0:
        raise SkeletonError(f"no spine joint between the pelvis {skeleton.names[pelvis]!r} "
                            f"and the chest {skeleton.names[path[0]]!r}")
    out["spine"], out["chest"] = path[:k], [path[k]]
    if path[k + 1:]:
        out["neck"] = path[k + 1:]


def _check(skeleton: Skeleton, out: dict[str, list[int]]) -> None:
    """Each limb's joints hang one from the next, as the solvers' chains need."""
    parents = skeleton.parents
    for side in "lr":
        for limb in _LIMBS:
            chain = [out[f"{r}_{side}"][0] for r in limb if f"{r}_{side}" in out]
            for a, b in itertools.pairwise(chain):
                if parents[b] != a:
                    raise SkeletonError(f"{skeleton.names[b]!r} does not hang from "
                                        f"{skeleton.names[a]!r}")


