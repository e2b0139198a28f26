"""Any common rig: a BVH skeleton is mapped onto the canonical roles by its names (DAZ,
Mixamo, Unity/VRM, VRoid, SMPL and the shared files' styles), by its shape where names say
nothing, or by ``eval --map FILE``; ``eval`` scores every file it can, names each one it
cannot in one line, and exits non-zero at the end. The rigs are the shipped CMU clip
renamed (tests/bvh_rig.py): the same motion, so the same figures."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from bvh_rig import DAZ, RIGS, rename_bvh

from posecast.client.builtin import builtin_motion_path
from posecast.solver import naming, structure
from posecast.solver.readers.bvh import read_bvh
from posecast.solver.readers.gltf import load_makehuman
from posecast.solver.skeleton import Skeleton, SkeletonError

CMU = builtin_motion_path()  # CMU 02_01, MotionBuilder names
TOES = frozenset({"LeftToeBase", "RightToeBase"})
TIMEOUT = 300  # seconds for one eval process on a loaded machine


def _named_roles(path: Path) -> dict[str, list[str]]:
    sk = read_bvh(path).skeleton
    return {role: [sk.names[j] for j in js] for role, js in naming.roles(sk).items()}


def _write(tmp_path: Path, name: str, rename: dict[str, str],
           cut: frozenset[str] = frozenset()) -> Path:
    path = tmp_path / f"{name}.bvh"
    path.write_text(rename_bvh(CMU.read_text(), rename, cut))
    return path


def _anonymous(tmp_path: Path) -> tuple[Path, dict[str, str]]:
    names = re.findall(r"(?:ROOT|JOINT) (\S+)", CMU.read_text())
    rename = {n: f"Bone_{i:02d}" for i, n in enumerate(names)}
    return _write(tmp_path, "anonymous", rename), rename


def eval_json(*argv: str) -> tuple[subprocess.CompletedProcess[str], dict]:
    proc = subprocess.run([sys.executable, "-m", "posecast.client.cli", "eval", *argv,
                           "--json"], capture_output=True, text=True, timeout=TIMEOUT)
    return proc, json.loads(proc.stdout)


@pytest.mark.parametrize("rig", sorted(RIGS))
def test_each_rig_maps_every_role_onto_the_same_joints(rig: str, tmp_path: Path) -> None:
    rename = RIGS[rig]
    cut = TOES if rig == "daz" else frozenset()  # DAZ exports have no toe joints
    path = _write(tmp_path, rig, rename, cut)
    sk = read_bvh(path).skeleton
    # Mixamo's limbs carry CMU MotionBuilder's names: either table maps them alike
    assert naming.detect_style(sk) in ({rig, "cmu_motionbuilder"} if rig == "mixamo"
                                       else {rig})
    expected = {role: [rename.get(n, n) for n in names]
                for role, names in _named_roles(CMU).items()
                if not (cut and role.startswith("toes"))}
    assert _named_roles(path) == expected


def test_names_are_compared_without_case_separators_or_namespace() -> None:
    assert naming.normalise("mixamorig:LeftUpLeg") == "leftupleg"
    assert naming.normalise("mixamorig_LeftUpLeg") == "leftupleg"
    assert naming.normalise("Armature|Left Upper Arm") == "leftupperarm"
    assert naming.normalise("J_Bip_L_UpperArm") == "jbiplupperarm"
    assert naming.normalise("left_shoulder") == "leftshoulder"


def test_shape_alone_finds_the_roles_names_would(tmp_path: Path) -> None:
    path, rename = _anonymous(tmp_path)
    sk = read_bvh(path).skeleton
    assert naming.detect_style(sk) == "shape"
    expected = {role: [rename[n] for n in names] for role, names in _named_roles(CMU).items()}
    assert _named_roles(path) == expected
    by_shape = structure.infer_roles(read_bvh(CMU).skeleton)
    assert by_shape == naming.roles(read_bvh(CMU).skeleton)


def test_shape_reads_the_makehuman_rig_with_its_fingers() -> None:
    sk = load_makehuman().skeleton  # 53 joints: fifteen per hand, toes, a root
    assert structure.infer_roles(sk) == naming.roles(sk)


def test_a_skeleton_that_is_no_body_names_the_way_out(tmp_path: Path) -> None:
    path = _write(tmp_path, "legless", {}, frozenset({"LeftUpLeg", "RightUpLeg"}))
    with pytest.raises(SkeletonError) as err:
        naming.roles(read_bvh(path).skeleton)
    message = str(err.value)
    assert "thigh_l" in message and "--map FILE" in message and "\n" not in message


def test_shape_refuses_arms_without_clavicles() -> None:
    # Unity's humanoid makes the shoulders optional: an upper arm straight on the chest
    sk = read_bvh(CMU).skeleton
    gone = {sk.index("LeftShoulder"), sk.index("RightShoulder")}
    keep = [j for j in range(sk.num_joints) if j not in gone]
    new_index = {j: k for k, j in enumerate(keep)}
    parents = [sk.parents[sk.parents[j]] if sk.parents[j] in gone else sk.parents[j]
               for j in keep]
    offsets = [sk.offsets[j] + (sk.offsets[sk.parents[j]] if sk.parents[j] in gone else 0)
               for j in keep]
    short = Skeleton(tuple(f"Bone_{k}" for k in range(len(keep))),
                     np.array([new_index.get(int(p), -1) for p in parents]),
                     np.array(offsets), sk.tips[keep])
    with pytest.raises(SkeletonError, match="has no clavicle before its upper arm"):
        naming.roles(short)


def test_renamed_rigs_score_as_the_original_through_the_real_command(tmp_path: Path
                                                                     ) -> None:
    files = [_write(tmp_path, rig, rename, TOES if rig == "daz" else frozenset())
             for rig, rename in sorted(RIGS.items())]
    proc, doc = eval_json(str(CMU), *map(str, files))
    assert proc.returncode == 0, proc.stderr
    original, *others = doc["clips"]
    assert [Path(c["file"]).stem for c in others] == sorted(RIGS)
    for clip in others:
        if Path(clip["file"]).stem == "daz":  # no toes: fewer joints, the same body
            shared = {DAZ.get(n, n): e for n, e in original["position_error_mm"].items()}
            for joint, error in clip["position_error_mm"].items():
                assert abs(error - shared[joint]) < 5.0, joint
            assert clip["mean_error_mm"] < original["mean_error_mm"] + 2.0
            continue
        for key in ("frames", "mean_error_mm", "heldout_error_mm", "rotation_error_deg"):
            assert clip[key] == original[key], (clip["file"], key)


def test_a_bad_file_among_good_ones_is_one_line_and_the_others_are_scored(
        tmp_path: Path) -> None:
    broken = tmp_path / "broken.bvh"
    broken.write_text("HIERARCHY\nROOT x\n{\n")
    legless = _write(tmp_path, "legless", {}, frozenset({"LeftUpLeg", "RightUpLeg"}))
    daz = _write(tmp_path, "daz", DAZ, TOES)
    proc, doc = eval_json(str(CMU), str(broken), str(daz), str(legless))
    assert proc.returncode == 1
    assert [Path(c["file"]).name for c in doc["clips"]] == [CMU.name, "daz.bvh"]
    assert doc["summary"]["mean_error_mm"] > 0.0
    lines = proc.stderr.splitlines()
    assert len(lines) == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert lines[0].startswith(f"posecast eval: {broken}:3: ")
    assert lines[1].startswith(f"posecast eval: {legless}: cannot map this skeleton")
    assert [f["file"] for f in doc["failures"]] == [str(broken), str(legless)]
    assert doc["failures"][1]["error"] == lines[1].removeprefix("posecast eval: ")


def test_a_joint_map_names_what_shape_and_names_cannot(tmp_path: Path) -> None:
    path, rename = _anonymous(tmp_path)
    roles = _named_roles(CMU)
    # the map moves the head one joint down: Neck1 plays the head, Head no role
    joint_map = {rename[n]: role for role, names in roles.items() for n in names}
    joint_map[rename["Neck1"]], joint_map[rename["Head"]] = "head", ""
    joint_map[rename["Neck"]] = "neck"
    toml = tmp_path / "map.toml"
    toml.write_text("".join(f'"{k}" = "{v}"\n' for k, v in joint_map.items()))
    sk = read_bvh(path).skeleton
    mapped = naming.roles(type(sk)(sk.names, sk.parents, sk.offsets, sk.tips, joint_map))
    assert sk.names[mapped["head"][0]] == rename["Neck1"]
    assert [sk.names[j] for j in mapped["neck"]] == [rename["Neck"]]
    proc, doc = eval_json(str(path), "--map", str(toml))
    assert proc.returncode == 0, proc.stderr
    _, auto = eval_json(str(path))
    # the tracker is on another joint: the figures differ from the shape's mapping
    assert doc["clips"][0]["mean_error_mm"] != auto["clips"][0]["mean_error_mm"]


def test_a_full_map_scores_as_the_names_do(tmp_path: Path) -> None:
    path, rename = _anonymous(tmp_path)
    joint_map = {rename[n]: role for role, names in _named_roles(CMU).items()
                 for n in names}
    as_json = tmp_path / "map.json"
    as_json.write_text(json.dumps(joint_map))
    proc, doc = eval_json(str(CMU), str(path), "--map", str(as_json))
    assert proc.returncode == 0, proc.stderr
    named, mapped = doc["clips"]
    assert mapped["mean_error_mm"] == named["mean_error_mm"]
    assert mapped["rotation_error_deg"] == named["rotation_error_deg"]


@pytest.mark.parametrize("content, why", [
    ('{"Bone_20": "hand_q"}', "role 'hand_q' is none of"),
    ('{"Bone_20": ', "not JSON"),
    ('["hand_l"]', "expected a table"),
])
def test_a_bad_map_is_one_line_and_exit_2(content: str, why: str, tmp_path: Path) -> None:
    bad = tmp_path / "map.json"
    bad.write_text(content)
    proc = subprocess.run([sys.executable, "-m", "posecast.client.cli", "eval", str(CMU),
                           "--map", str(bad)], capture_output=True, text=True,
                          timeout=TIMEOUT)
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.count("\n") == 1 and why in proc.stderr and str(bad) in proc.stderr


# ------------------------------------------------------------------ the shared clips

MOCAP = ["cmu_01_01_playground_jumps.bvh", "cmu_02_01_walk.bvh",
         "cmu_131_03_start_hop_stop.bvh", "bandai1_walk_normal_001.bvh"]
OLD_TABLES = {  # role -> joints as the tables alone gave them before shape placed the torso
    "cmu_131_03_start_hop_stop.bvh": {"spine": ["lowerback", "Chest"], "chest": ["Chest2"],
                                      "neck": ["lowerneck", "Neck"]},
    "bandai1_walk_normal_001.bvh": {"spine": ["Spine"], "chest": ["Chest"],
                                    "neck": ["Neck"]},
    "cmu_02_01_walk.bvh": {"spine": ["LowerBack", "Spine"], "chest": ["Spine1"],
                           "neck": ["Neck", "Neck1"]},
}


@pytest.mark.parametrize("name", MOCAP)
def test_shared_clips_keep_their_roles(name: str, shared_data: Callable[[str], Path]
                                       ) -> None:
    roles = _named_roles(shared_data(f"mocap/{name}"))
    for role, joints in OLD_TABLES.get(name, {}).items():
        assert roles[role] == joints


def test_a_rest_pose_in_a_line_needs_a_map_for_its_sides(
        tmp_path: Path, shared_data: Callable[[str], Path]) -> None:
    # Bandai's rest pose lies in a line: with anonymous names, shape finds every role but
    # cannot tell the arms' sides; a map of the arms alone puts them right
    source = shared_data("mocap/bandai1_walk_normal_001.bvh")
    names = re.findall(r"(?:ROOT|JOINT) (\S+)", source.read_text())
    rename = {n: f"Bone_{i:02d}" for i, n in enumerate(names)}
    path = tmp_path / "anonymous_bandai.bvh"
    path.write_text(rename_bvh(source.read_text(), rename))
    arms = {rename[f"{j}_{s.upper()}"]: f"{r}_{s}" for s in "lr" for j, r in (
        ("Shoulder", "clavicle"), ("UpperArm", "upperarm"), ("LowerArm", "forearm"),
        ("Hand", "hand"))}
    joint_map = tmp_path / "arms.json"
    joint_map.write_text(json.dumps(arms))
    proc, doc = eval_json(str(source), str(path), "--map", str(joint_map))
    assert proc.returncode == 0, proc.stderr
    named, mapped = doc["clips"]
    for key in ("mean_error_mm", "heldout_error_mm", "rotation_error_deg"):
        assert mapped[key] == named[key], key
