"""Test helper: the same motion under another rig's joint names, written as BVH text.

``rename_bvh`` renames the joints of a BVH file and can cut joints away (a DAZ export
has no toes): a cut joint becomes an End Site of its parent at its offset, and its
channels (and its descendants') leave every frame line. The motion of the joints kept
is untouched, so the renamed file must score exactly as the original.
"""

from __future__ import annotations

CMU_BODY = ("Hips", "LowerBack", "Spine", "Spine1", "Neck", "Neck1", "Head")

# the CMU MotionBuilder joints of client/assets/cmu_02_01_walk.bvh in other rigs' names
DAZ = {"Hips": "hip", "LowerBack": "abdomen", "Spine": "abdomen2", "Spine1": "chest",
       "Neck": "neck", "Neck1": "neck2", "Head": "head",
       **{f"{side}{cmu}": f"{s}{daz}" for side, s in (("Left", "l"), ("Right", "r"))
          for cmu, daz in (("Shoulder", "Collar"), ("Arm", "Shldr"), ("ForeArm", "ForeArm"),
                           ("Hand", "Hand"), ("UpLeg", "Thigh"), ("Leg", "Shin"),
                           ("Foot", "Foot"))}}
MIXAMO = {"Hips": "mixamorig:Hips", "LowerBack": "mixamorig:Spine",
          "Spine": "mixamorig:Spine1", "Spine1": "mixamorig:Spine2", "Neck": "mixamorig:Neck",
          "Neck1": "mixamorig:Neck1", "Head": "mixamorig:Head",
          **{f"{side}{j}": f"mixamorig:{side}{j}" for side in ("Left", "Right")
             for j in ("Shoulder", "Arm", "ForeArm", "Hand", "UpLeg", "Leg", "Foot",
                       "ToeBase")}}
VRM = {"Hips": "Hips", "LowerBack": "Spine", "Spine": "Chest", "Spine1": "UpperChest",
       "Neck": "Neck", "Neck1": "Neck1", "Head": "Head",
       **{f"{side}{cmu}": f"{side}{vrm}" for side in ("Left", "Right")
          for cmu, vrm in (("Shoulder", "Shoulder"), ("Arm", "UpperArm"),
                           ("ForeArm", "LowerArm"), ("Hand", "Hand"), ("UpLeg", "UpperLeg"),
                           ("Leg", "LowerLeg"), ("Foot", "Foot"), ("ToeBase", "Toes"))}}

VROID = {cmu: f"J_Bip_C_{vrm}" for cmu, vrm in VRM.items() if cmu in CMU_BODY} | {
    cmu: f"J_Bip_{vrm[0]}_{vrm[4:] if vrm.startswith('Left') else vrm[5:]}"
    for cmu, vrm in VRM.items() if cmu not in CMU_BODY} | {
    f"{side}ToeBase": f"J_Bip_{side[0]}_ToeBase" for side in ("Left", "Right")}
SMPL = {"Hips": "pelvis", "LowerBack": "spine1", "Spine": "spine2", "Spine1": "spine3",
        "Neck": "neck", "Neck1": "neck1", "Head": "head",
        **{f"{side}{cmu}": f"{side.lower()}_{smpl}" for side in ("Left", "Right")
           for cmu, smpl in (("Shoulder", "collar"), ("Arm", "shoulder"), ("ForeArm", "elbow"),
                             ("Hand", "wrist"), ("UpLeg", "hip"), ("Leg", "knee"),
                             ("Foot", "ankle"), ("ToeBase", "foot"))}}
RIGS = {"daz": DAZ, "mixamo": MIXAMO, "unity": VRM, "vroid": VROID, "smpl": SMPL}


def rename_bvh(text: str, rename: dict[str, str], cut: frozenset[str] = frozenset()) -> str:
    """The BVH text with joints renamed (old -> new) and the joints in ``cut`` removed."""
    lines = text.splitlines()
    out: list[str] = []
    drop_cols: list[int] = []
    col = 0
    depth = 0
    cut_depth: int | None = None  # brace depth at which the cut joint's block opened
    cut_offset = ""
    i = 0
    while i < len(lines):
        line = lines[i]
        words = line.split()
        if words and words[0] == "MOTION":
            break
        if cut_depth is None and words[:1] in (["ROOT"], ["JOINT"]) and words[1] in cut:
            cut_depth = depth
            cut_offset = ""
        if words[:1] == ["{"]:
            depth += 1
        elif words[:1] == ["}"]:
            depth -= 1
        if words[:1] == ["CHANNELS"]:
            n = int(words[1])
            if cut_depth is not None:
                drop_cols.extend(range(col, col + n))
            col += n
        if cut_depth is not None:
            if words[:1] == ["OFFSET"] and not cut_offset:
                cut_offset = line.strip()
            if words[:1] == ["}"] and depth == cut_depth:
                indent = line[: len(line) - len(line.lstrip())]
                out += [f"{indent}End Site", f"{indent}{{", f"{indent}  {cut_offset}",
                        f"{indent}}}"]
                cut_depth = None
            i += 1
            continue
        if words[:1] in (["ROOT"], ["JOINT"]) and words[1] in rename:
            line = line.replace(words[1], rename[words[1]])
        out.append(line)
        i += 1
    out += lines[i:i + 3]  # MOTION, Frames:, Frame Time:
    keep = [c for c in range(col) if c not in set(drop_cols)]
    for row in lines[i + 3:]:
        values = row.split()
        out.append(" ".join(values[c] for c in keep))
    return "\n".join(out) + "\n"
