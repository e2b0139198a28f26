"""Tests of the Vive and BVH readers: the real files of ../shared/data (frame counts, rates,
units, plausible bodies) and broken files, which must raise FormatError at the right line."""

from __future__ import annotations

import contextlib
import random
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray

from posecast.solver import naming
from posecast.solver import rotations as rot
from posecast.solver.motion import Motion
from posecast.solver.readers.bvh import CMU_UNIT, read_bvh
from posecast.solver.readers.errors import FormatError
from posecast.solver.readers.vive import read_vive

SharedData = Callable[[str], Path]

# ------------------------------------------------------------------ real Vive recordings

# file, frames (../shared/data/vive/README.md), has knee trackers
VIVE_FILES = [
    ("kicking.csv", 2510, True),
    ("punching.csv", 2159, True),
    ("sitting.csv", 2643, True),
    ("squats.csv", 1797, True),
    ("elbow_flexion.csv", 1949, True),
    ("hand_pronation.csv", 1419, True),
    ("knee_flexion.csv", 1280, True),
    ("shoulder_abduction.csv", 2850, True),
    ("walking.csv", 678, False),
    ("yoga1.csv", 524, True),
]
BODY_DEVICES = ("head", "hip", "left_hand", "left_forearm", "right_hand", "right_forearm",
                "left_foot", "right_foot")


@pytest.mark.parametrize(("name", "frames", "knees"), VIVE_FILES)
def test_vive_real_files(shared_data: SharedData, name: str, frames: int,
                         knees: bool) -> None:
    rec = read_vive(shared_data(f"vive/{name}"))
    assert rec.num_frames == frames
    assert rec.fps == 90.0
    assert rec.devices == BODY_DEVICES + (("left_knee", "right_knee") if knees else ())
    assert rec.positions.shape == (frames, len(rec.devices), 3)
    assert np.allclose(np.linalg.norm(rec.rotations, axis=-1), 1.0, atol=1e-12)
    assert np.all(np.isfinite(rec.positions))
    head = rec.positions[0, rec.device("head")]
    assert 1.4 <= head[1] <= 2.0
    for foot in ("left_foot", "right_foot"):  # frame 0 is the calibration pose: standing
        assert rec.positions[0, rec.device(foot), 1] < rec.positions[0, rec.device("hip"), 1]


def test_vive_reads_the_largest_file_fast(shared_data: SharedData) -> None:
    path = shared_data("vive/shoulder_abduction.csv")  # 28,501 lines
    start = time.thread_time()  # CPU time: a loaded machine stretches only the wall clock
    read_vive(path)
    assert time.thread_time() - start < 1.0


# ------------------------------------------------------------------- real BVH files

# file, frames, fps, joints (../shared/data/mocap/README.md), first motion frame, unit
BVH_FILES = [
    ("cmu_01_01_playground_jumps.bvh", 2752, 120.0, 31, 1, CMU_UNIT),
    ("cmu_02_01_walk.bvh", 343, 120.0, 31, 0, CMU_UNIT),
    ("cmu_131_03_start_hop_stop.bvh", 1102, 120.0, 31, 0, CMU_UNIT),
    ("bandai1_walk_normal_001.bvh", 195, 30.0, 22, 0, 0.01),
    ("bandai1_run_active_001.bvh", 72, 30.0, 22, 0, 0.01),
    ("bandai1_punch_normal_002.bvh", 284, 30.0, 22, 0, 0.01),
    ("bandai1_kick_normal_001.bvh", 358, 30.0, 22, 0, 0.01),
    ("bandai1_bow_normal_001.bvh", 138, 30.0, 22, 0, 0.01),
    ("bandai1_dance-short_normal_001.bvh", 1901, 30.0, 22, 0, 0.01),
    ("bandai2_raise-up-both-hands_normal_001.bvh", 51, 30.0, 22, 0, 0.01),
]
BVH_IDS = [row[0].split("_normal")[0].split("_active")[0] for row in BVH_FILES]


def global_positions(motion: Motion, frame: int) -> NDArray[np.float64]:
    """Forward kinematics of one frame, parents first: (J, 3) global joint positions."""
    sk = motion.skeleton
    rotation = np.zeros((sk.num_joints, 3, 3))
    position = np.zeros((sk.num_joints, 3))
    local_r = rot.to_matrix(motion.rotations[frame])
    local_t = motion.translations[frame]
    for j in range(sk.num_joints):
        p = sk.parents[j]
        if p < 0:
            rotation[j], position[j] = local_r[j], local_t[j]
        else:
            rotation[j] = rotation[p] @ local_r[j]
            position[j] = position[p] + rotation[p] @ local_t[j]
    return position


@pytest.mark.parametrize(("name", "frames", "fps", "joints", "first", "unit"), BVH_FILES,
                         ids=BVH_IDS)
def test_bvh_real_files(shared_data: SharedData, name: str, frames: int, fps: float,
                        joints: int, first: int, unit: float) -> None:
    path = shared_data(f"mocap/{name}")
    motion = read_bvh(path)
    assert motion.num_frames == frames
    assert motion.fps == fps
    assert motion.skeleton.num_joints == joints
    assert motion.first_frame == first  # only CMU 01_01 opens with a T-pose
    assert motion.rotations.shape == (frames, joints, 4)
    assert motion.translations.shape == (frames, joints, 3)
    assert np.allclose(np.linalg.norm(motion.rotations, axis=-1), 1.0)
    assert np.array_equal(motion.skeleton.offsets, motion.translations[first])
    # the inferred unit is the one the README gives
    explicit = read_bvh(path, scale=unit)
    assert np.allclose(explicit.translations, motion.translations)
    assert np.allclose(explicit.skeleton.tips, motion.skeleton.tips)


@pytest.mark.parametrize("name", [row[0] for row in BVH_FILES], ids=BVH_IDS)
def test_bvh_real_bodies_stand_upright(shared_data: SharedData, name: str) -> None:
    motion = read_bvh(shared_data(f"mocap/{name}"))
    roles = naming.roles(motion.skeleton)  # every naming style maps onto the roles
    pos = global_positions(motion, motion.first_frame)
    hips = pos[roles["pelvis"][0], 1]
    head = pos[roles["head"][0], 1]
    feet = pos[[roles["foot_l"][0], roles["foot_r"][0]], 1]
    assert 0.7 <= hips <= 1.2  # metres, whatever the file's unit
    assert head > hips + 0.3
    assert np.all(feet < hips)
    assert hips - feet.min() > 0.6  # the standing foot is near the floor
    assert feet.min() < 0.25


def test_bvh_bandai_static_root_and_moving_hips(shared_data: SharedData) -> None:
    motion = read_bvh(shared_data("mocap/bandai1_walk_normal_001.bvh"))
    assert motion.skeleton.names[:2] == ("joint_Root", "Hips")
    assert np.ptp(motion.translations[:, 0], axis=0).max() == 0.0
    # the Hips' position channels carry the walk (metres), not its OFFSET line
    assert np.ptp(motion.translations[:, 1, 2]) > 5.0


def test_bvh_reads_the_largest_file_fast(shared_data: SharedData) -> None:
    path = shared_data("mocap/bandai1_dance-short_normal_001.bvh")  # 2.4 MB
    start = time.thread_time()  # CPU time: a loaded machine stretches only the wall clock
    read_bvh(path)
    assert time.thread_time() - start < 1.0


# ------------------------------------------------------------ synthetic Vive files

VIVE_HEADER = "tag rawPosX rawPosY rawPosZ rawRotX rawRotY rawRotZ rawRotW scale"
VIVE_TAGS = ("head", "hip", "lHand", "lForeArm", "rHand", "rForeArm", "lFoot", "rFoot")


def vive_lines(frames: int = 3) -> list[str]:
    """A valid recording: header on line 1, frame k device d on line 2 + 8k + d."""
    lines = [VIVE_HEADER]
    for k in range(frames):
        for d, tag in enumerate(VIVE_TAGS):
            lines.append(f"{tag} {0.1 * d} {1.7 - 0.2 * d} {0.01 * k} 0 0 0.6 0.8 1")
    return lines


def write(tmp_path: Path, name: str, lines: list[str]) -> Path:
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def vive_error(tmp_path: Path, lines: list[str], line: int) -> FormatError:
    path = write(tmp_path, "broken_rec.csv", lines)
    with pytest.raises(FormatError) as info:
        read_vive(path)
    err = info.value
    assert "broken_rec.csv" in str(err)
    assert f":{line}:" in str(err)
    assert err.line == line
    return err


def test_vive_synthetic_file(tmp_path: Path) -> None:
    rec = read_vive(write(tmp_path, "ok.csv", vive_lines(3)))
    assert rec.num_frames == 3
    assert rec.devices == BODY_DEVICES
    assert np.allclose(rec.positions[2, 1], [0.1, 1.5, 0.02])
    assert np.allclose(rec.rotations[0, 0], [0.0, 0.0, 0.6, 0.8])


def test_vive_normalises_quaternions(tmp_path: Path) -> None:
    lines = vive_lines(1)
    lines[1] = "head 0 1.7 0 0 0 0.6 0.81 1"  # norm 1.0060: rounding, not an error
    rec = read_vive(write(tmp_path, "ok.csv", lines))
    assert np.isclose(np.linalg.norm(rec.rotations[0, 0]), 1.0)


def test_vive_truncated_mid_frame(tmp_path: Path) -> None:
    lines = vive_lines(3)[:-3]  # frame 2 keeps 5 of its 8 devices; last line is 22
    err = vive_error(tmp_path, lines, 22)
    assert "middle of a frame" in err.message
    assert "5 of its 8" in err.message


def test_vive_non_numeric_value(tmp_path: Path) -> None:
    lines = vive_lines(3)
    lines[11] = "lHand 0.2 abc 0 0 0 0.6 0.8 1"  # frame 1, device 2: line 12
    err = vive_error(tmp_path, lines, 12)
    assert "'abc'" in err.message
    assert "rawPosY" in err.message


def test_vive_non_finite_value(tmp_path: Path) -> None:
    lines = vive_lines(3)
    lines[4] = "lForeArm 0.3 nan 0 0 0 0.6 0.8 1"
    assert "'nan'" in vive_error(tmp_path, lines, 5).message


def test_vive_wrong_field_count(tmp_path: Path) -> None:
    lines = vive_lines(3)
    lines[4] = "lForeArm 0.3 1.1 0 0 0 0.6 0.8"
    err = vive_error(tmp_path, lines, 5)
    assert "expected 9" in err.message
    assert "found 8" in err.message


def test_vive_blank_line_inside(tmp_path: Path) -> None:
    lines = vive_lines(2)
    lines[6] = ""
    assert "empty line" in vive_error(tmp_path, lines, 7).message


def test_vive_unknown_tag(tmp_path: Path) -> None:
    lines = vive_lines(3)
    lines[6] = lines[6].replace("rForeArm", "rElbow")
    assert "'rElbow'" in vive_error(tmp_path, lines, 7).message


def test_vive_device_order_broken(tmp_path: Path) -> None:
    lines = vive_lines(3)
    lines[19], lines[20] = lines[20], lines[19]  # frame 2: lForeArm before lHand
    err = vive_error(tmp_path, lines, 20)
    assert "expected 'lHand'" in err.message
    assert "found 'lForeArm'" in err.message


def test_vive_frame_missing_a_device(tmp_path: Path) -> None:
    lines = vive_lines(3)
    del lines[16]  # frame 1 loses rFoot: frame 2's head comes early on line 17
    err = vive_error(tmp_path, lines, 17)
    assert "expected 'rFoot'" in err.message


def test_vive_non_unit_quaternion(tmp_path: Path) -> None:
    lines = vive_lines(2)
    lines[3] = "lHand 0.2 1.3 0 0 0 1.2 1.6 1"
    assert "norm 2" in vive_error(tmp_path, lines, 4).message


def test_vive_zero_quaternion(tmp_path: Path) -> None:
    lines = vive_lines(2)
    lines[3] = "lHand 0.2 1.3 0 0 0 0 0 1"
    assert "norm 0" in vive_error(tmp_path, lines, 4).message


def test_vive_wrong_header(tmp_path: Path) -> None:
    lines = vive_lines(1)
    lines[0] = "tag x y z qx qy qz qw scale"
    assert "expected the header" in vive_error(tmp_path, lines, 1).message


def test_vive_empty_file_and_no_frames(tmp_path: Path) -> None:
    empty = tmp_path / "empty.csv"
    empty.write_text("")
    with pytest.raises(FormatError, match=r"empty\.csv:1: the file is empty"):
        read_vive(empty)
    assert "no frames" in vive_error(tmp_path, [VIVE_HEADER], 2).message


def test_vive_earliest_problem_is_reported(tmp_path: Path) -> None:
    lines = vive_lines(3)
    lines[20] = "lForeArm 0.3"  # wrong field count on line 21 ...
    lines[14] = "lFoot 0.6 0.5 0 0 0 0.6 0.8 x"  # ... a bad number earlier, on line 15
    vive_error(tmp_path, lines, 15)


# -------------------------------------------------------------- synthetic BVH files

BVH_TEXT = """\
HIERARCHY
ROOT Hips
{
  OFFSET 7 7 7
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Spine
  {
    OFFSET 0 10 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 180 0
    }
  }
}
MOTION
Frames: 3
Frame Time: 0.0333333
0 90 0 0 0 0 10 20 30
1 90 0 0 0 0 10 20 30
2 90 0 0 0 0 10 20 30
"""
FRAMES_LINE = 17  # "Frames: 3"; the frame lines are 19, 20, 21


def bvh_lines() -> list[str]:
    return BVH_TEXT.splitlines()


def bvh_error(tmp_path: Path, lines: list[str], line: int) -> FormatError:
    path = write(tmp_path, "broken_take.bvh", lines)
    with pytest.raises(FormatError) as info:
        read_bvh(path)
    err = info.value
    assert "broken_take.bvh" in str(err)
    assert f":{line}:" in str(err)
    assert err.line == line
    return err


def test_bvh_synthetic_file(tmp_path: Path) -> None:
    motion = read_bvh(write(tmp_path, "ok.bvh", bvh_lines()))  # 180 units: centimetres
    sk = motion.skeleton
    assert sk.names == ("Hips", "Spine")
    assert list(sk.parents) == [-1, 0]
    assert motion.fps == 30.0
    assert motion.first_frame == 0
    # position channels replace the OFFSET (7 7 7), they are not added to it
    assert np.allclose(motion.translations[:, 0], [[0, 0.9, 0], [0.01, 0.9, 0],
                                                   [0.02, 0.9, 0]])
    assert np.allclose(motion.translations[:, 1], [0.0, 0.1, 0.0])
    assert np.allclose(sk.tips, np.array([[0, 0, 0], [0, 1.8, 0]]))  # End Site: a tip, not a joint
    expected = rot.from_euler(np.radians([10.0, 20.0, 30.0]), "zxy")
    assert np.allclose(motion.rotations[:, 1], expected)
    assert np.allclose(motion.rotations[:, 0], rot.IDENTITY)


def test_bvh_channel_order_and_child_positions(tmp_path: Path) -> None:
    lines = bvh_lines()
    lines[8] = "    CHANNELS 6 Yrotation Xposition Yposition Zposition Xrotation Zrotation"
    lines[18:21] = ["0 90 0 0 0 0 10 1 2 3 20 30"] * 3
    motion = read_bvh(write(tmp_path, "ok.bvh", lines))
    assert np.allclose(motion.translations[:, 1], [0.01, 0.02, 0.03])
    expected = rot.from_euler(np.radians([10.0, 20.0, 30.0]), "yxz")
    assert np.allclose(motion.rotations[:, 1], expected)


@pytest.mark.parametrize(("tip", "unit"), [(1.8, 1.0), (32.0, CMU_UNIT), (175.0, 0.01)])
def test_bvh_unit_inferred_from_skeleton_size(tmp_path: Path, tip: float,
                                              unit: float) -> None:
    lines = bvh_lines()
    lines[11] = f"      OFFSET 0 {tip} 0"
    motion = read_bvh(write(tmp_path, "size.bvh", lines))
    assert np.allclose(motion.skeleton.tips[1], [0.0, tip * unit, 0.0])
    explicit = read_bvh(write(tmp_path, "size.bvh", lines), scale=2.0)
    assert np.allclose(explicit.skeleton.tips[1], [0.0, tip * 2.0, 0.0])


def test_bvh_unit_that_fits_no_human(tmp_path: Path) -> None:
    lines = bvh_lines()
    lines[11] = "      OFFSET 0 90000 0"
    with pytest.raises(FormatError, match="pass scale="):
        read_bvh(write(tmp_path, "giant.bvh", lines))
    with pytest.raises(ValueError, match="scale"):
        read_bvh(write(tmp_path, "giant.bvh", lines), scale=-1.0)


@pytest.mark.parametrize(("frame_time", "fps"), [("0.008333", 120.0), (".0083333", 120.0),
                                                 ("0.0333333", 30.0), ("0.04", 25.0),
                                                 ("0.015", 1 / 0.015)])
def test_bvh_fps_rounding(tmp_path: Path, frame_time: str, fps: float) -> None:
    lines = bvh_lines()
    lines[17] = f"Frame Time: {frame_time}"
    assert read_bvh(write(tmp_path, "fps.bvh", lines)).fps == pytest.approx(fps, rel=1e-12)


def test_bvh_bind_pose_first_frame(tmp_path: Path) -> None:
    lines = bvh_lines()
    lines[18] = "0 90 0 0 0 0 0 0 0"  # all non-root rotations exactly zero: a bind pose
    assert read_bvh(write(tmp_path, "tpose.bvh", lines)).first_frame == 1
    lines[19] = "0 90 0 0 0 0 0 0 0"  # a later frame at rest too: just a motion
    assert read_bvh(write(tmp_path, "tpose.bvh", lines)).first_frame == 0


def test_bvh_truncated_motion(tmp_path: Path) -> None:
    lines = bvh_lines()
    lines[16] = "Frames: 5"
    err = bvh_error(tmp_path, lines, FRAMES_LINE)
    assert "truncated" in err.message
    assert "5 frames" in err.message
    assert "only 3" in err.message


def test_bvh_frame_line_missing_a_value(tmp_path: Path) -> None:
    lines = bvh_lines()
    lines[19] = "1 90 0 0 0 0 10 20"
    err = bvh_error(tmp_path, lines, 20)
    assert "expected 9 values" in err.message
    assert "found 8" in err.message


def test_bvh_garbage_in_hierarchy(tmp_path: Path) -> None:
    lines = bvh_lines()
    lines.insert(7, "    FOO bar baz")  # becomes line 8
    assert "unknown keyword 'FOO'" in bvh_error(tmp_path, lines, 8).message


def test_bvh_non_numeric_offset(tmp_path: Path) -> None:
    lines = bvh_lines()
    lines[7] = "    OFFSET 0 ten 0"
    assert "'ten'" in bvh_error(tmp_path, lines, 8).message


@pytest.mark.parametrize(("index", "text", "line", "words"), [
    (0, "HIERARCHI", 1, "expected HIERARCHY"),
    (1, "JOINT Hips", 2, "expected ROOT"),
    (8, "    CHANNELS 4 Zrotation Xrotation Yrotation", 9, "declares 4 channels but names 3"),
    (8, "    CHANNELS 3 Zrotation Wrotation Yrotation", 9, "unknown channel 'Wrotation'"),
    (8, "    CHANNELS three Zrotation Xrotation Yrotation", 9, "channel count"),
    (7, "    OFFSET 0 10", 8, "expected 3 numbers"),
    (7, "    OFFSET 0 inf 0", 8, "finite number"),
    (13, "", 16, "a '}' is missing"),
    (14, "} }", 15, "an extra '}'"),
    (15, "MOTON", 16, "expected MOTION"),
    (16, "Frames 3", 17, "expected 'Frames: <value>'"),
    (16, "Frames: 0", 17, "positive whole number"),
    (17, "Frame Time: 0", 18, "above 0"),
    (17, "Frame Time: soon", 18, "'soon'"),
    (20, "2 90 0 0 0 0 10 x 30", 21, "'x'"),
    (19, "1 90 0 0 0 0 10 nan 30", 20, "'nan'"),
    (18, "", 19, "found 0"),
])
def test_bvh_bad_lines(tmp_path: Path, index: int, text: str, line: int,
                       words: str) -> None:
    lines = bvh_lines()
    lines[index] = text
    assert words in bvh_error(tmp_path, lines, line).message


def test_bvh_more_frames_than_declared(tmp_path: Path) -> None:
    lines = [*bvh_lines(), "3 90 0 0 0 0 10 20 30"]
    assert "more frame lines" in bvh_error(tmp_path, lines, 22).message


def test_bvh_missing_motion_and_empty_file(tmp_path: Path) -> None:
    assert "no MOTION" in bvh_error(tmp_path, bvh_lines()[:15], 15).message
    assert "HIERARCHY" in bvh_error(tmp_path, [""], 1).message


# --------------------------------------------- nothing but FormatError, whatever the input

CORRUPTIONS = ["", " ", "x", "{", "}", "-", ".", "e", "0", "\n", "\t", "9" * 400]


def assert_reads_or_format_error(read: Callable[[Path], object], path: Path) -> None:
    with contextlib.suppress(FormatError):  # anything else fails the test
        read(path)


def test_cut_and_corrupted_files_raise_only_format_error(tmp_path: Path) -> None:
    """Every prefix of a valid file, and random one-character edits of it, either read or
    raise FormatError: no IndexError, ValueError or the like escapes."""
    rng = random.Random(1234)
    cases: list[tuple[Callable[[Path], object], str]] = [
        (read_bvh, BVH_TEXT), (read_vive, "\n".join(vive_lines(2)) + "\n")]
    path = tmp_path / "fuzz.txt"
    for read, text in cases:
        for cut in range(len(text)):
            path.write_text(text[:cut])
            assert_reads_or_format_error(read, path)
        for _ in range(400):
            k = rng.randrange(len(text))
            path.write_text(text[:k] + rng.choice(CORRUPTIONS) + text[k + 1:])
            assert_reads_or_format_error(read, path)
