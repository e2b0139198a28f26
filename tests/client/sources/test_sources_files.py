"""The file pose sources (a Vive recording, simulated trackers from BVH) and open_source."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from posecast.client.builtin import builtin_motion_path
from posecast.client.sources import SPEC_FORMS, SourceError, open_source
from posecast.client.sources.base import ROLES as ALL_ROLES
from posecast.client.sources.bvh_source import (
    ROLES,  # a Vive rig: the BVH source simulates no chest
    BvhSource,
)
from posecast.client.sources.vive_source import ViveFileSource
from posecast.solver import rotations as R
from posecast.solver.calibration import calibrate
from posecast.solver.fk import forward_kinematics
from posecast.solver.ik import PoseBatch, Solver
from posecast.solver.readers.bvh import read_bvh
from posecast.solver.readers.errors import FormatError
from posecast.solver.readers.gltf import load_makehuman
from posecast.solver.readers.vive import read_vive
from posecast.solver.rig import build_rig

SharedData = Callable[[str], Path]
HEADER = "tag rawPosX rawPosY rawPosZ rawRotX rawRotY rawRotZ rawRotW scale\n"
DRIVING = ("head", "hip", "left_hand", "right_hand", "left_foot", "right_foot")


def small_vive(tmp_path: Path) -> Path:
    """Three frames, lHand before head in ROLES order terms reversed on purpose."""
    path = tmp_path / "small.csv"
    lines = [HEADER]
    for f in range(3):
        lines.append(f"head 0 1.7 {f / 10} 0 0 0 1 1\n")
        lines.append(f"lHand 0.5 1.{f} 0 0 0.6 0 0.8 1\n")
    path.write_text("".join(lines))
    return path


# --------------------------------------------------------------------- Vive recordings

def test_vive_real_file_replays_frame_by_frame(shared_data: SharedData) -> None:
    path = shared_data("vive/walking.csv")
    rec = read_vive(path)
    src = ViveFileSource(path)
    assert src.rate_hz == 90.0 and src.num_frames == rec.num_frames == 678
    cal = src.calibration()
    assert cal.roles == tuple(r for r in ALL_ROLES if r in rec.devices)  # no knees in this file
    assert len(cal.roles) == 8
    order = [rec.device(r) for r in cal.roles]
    np.testing.assert_array_equal(cal.positions, rec.positions[0, order])
    np.testing.assert_array_equal(cal.rotations, rec.rotations[0, order])
    seen = 0
    times = []
    while (sample := src.read()) is not None:
        seen += 1
        times.append(sample.t_capture)
        if seen in (1, 400, 677):
            np.testing.assert_array_equal(sample.positions, rec.positions[seen, order])
            np.testing.assert_array_equal(sample.rotations, rec.rotations[seen, order])
    assert seen == 677  # frames 1..677: frame 0 is the T-pose
    assert np.all(np.diff(times) >= 0.0)
    assert src.read() is None


def test_vive_loop_wraps_to_frame_one(tmp_path: Path) -> None:
    src = ViveFileSource(small_vive(tmp_path), loop=True, rate_hz=30.0)
    assert src.rate_hz == 30.0
    assert src.calibration().roles == ("head", "left_hand")
    heads = []
    for _ in range(5):
        sample = src.read()
        assert sample is not None
        heads.append(round(float(sample.positions[0, 2]), 6))
    assert heads == [0.1, 0.2, 0.1, 0.2, 0.1]  # frame 0 (z = 0) never replayed
    assert sample is not None
    np.testing.assert_allclose(sample.rotations[1], np.array([0, 0.6, 0, 0.8]))


def test_vive_samples_are_copies(tmp_path: Path) -> None:
    src = ViveFileSource(small_vive(tmp_path))
    a = src.calibration()
    a.positions[:] = 99.0
    assert src.calibration().positions[0, 1] == 1.7


def test_vive_errors(tmp_path: Path) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text(HEADER + "head 0 1.7 oops 0 0 0 1 1\n")
    with pytest.raises(FormatError, match=r"bad.csv:2"):
        ViveFileSource(bad)
    with pytest.raises(SourceError, match=r"missing.csv: cannot read the recording"):
        ViveFileSource(tmp_path / "missing.csv")
    one = tmp_path / "one.csv"
    one.write_text(HEADER + "head 0 1.7 0 0 0 0 1 1\n")
    with pytest.raises(SourceError, match=r"needs a calibration frame and at least one more"):
        ViveFileSource(one)


# --------------------------------------------------------------------- BVH

@pytest.fixture(scope="module")
def walker() -> BvhSource:
    return BvhSource(builtin_motion_path())


def test_bvh_devices_are_the_joints_of_the_file(walker: BvhSource) -> None:
    motion = read_bvh(builtin_motion_path())
    assert walker.rate_hz == 120.0 and walker.num_frames == motion.num_frames == 343
    sk = motion.skeleton
    gq, gp = forward_kinematics(sk, motion.rotations, motion.translations[:, 0],
                                motion.translations)
    names = {"hip": "Hips", "left_hand": "LeftHand", "right_foot": "RightFoot",
             "left_knee": "LeftLeg"}
    up = np.array([0.0, 0.0, 0.0])
    up[1] = lift = walker.poses[0, ROLES.index("hip"), 1] - gp[0, sk.index("Hips"), 1]
    # the floor: the lowest joint of frame 0 ends up on y = 0
    assert abs(gp[0, :, 1].min() + lift) < 1e-9
    assert lift < -0.005  # this file's lowest joint is 12 mm above its y = 0
    for f in (0, 100, 342):
        for role, joint in names.items():
            d, j = ROLES.index(role), sk.index(joint)
            np.testing.assert_allclose(walker.poses[f, d, :3], gp[f, j] + up,
                                       atol=1e-9)
            assert R.angle_between(walker.poses[f, d, 3:], gq[f, j]) < 1e-6
    # forearm halfway from elbow to wrist; the headset at the eyes, in front of the head
    d = ROLES.index("right_forearm")
    mid = (gp[:, sk.index("RightForeArm")] + gp[:, sk.index("RightHand")]) / 2
    np.testing.assert_allclose(walker.poses[:, d, :3], mid + up, atol=1e-9)
    hmd = walker.poses[:, ROLES.index("head"), :3] - gp[:, sk.index("Head")] - up
    np.testing.assert_allclose(np.linalg.norm(hmd, axis=-1), np.hypot(0.06, 0.09),
                               atol=1e-9)


def test_bvh_read_order_and_loop(walker: BvhSource) -> None:
    src = BvhSource(builtin_motion_path(), loop=True)
    first = src.read()
    assert first is not None and first.roles == ROLES
    np.testing.assert_array_equal(first.poses, walker.poses[0])
    for _ in range(src.num_frames - 1):
        last = src.read()
    assert last is not None
    np.testing.assert_array_equal(last.poses, walker.poses[-1])
    again = src.read()
    assert again is not None
    np.testing.assert_array_equal(again.poses, walker.poses[0])
    once = BvhSource(builtin_motion_path())
    once.next_frame = once.num_frames
    assert once.read() is None


def test_bvh_smooth_reads_lerp_between_frames_and_wrap(walker: BvhSource) -> None:
    """Read at 90 Hz from a 120 Hz clip, a sample lies between two frames: positions
    lerped, rotations lerped on one hemisphere and normalised; the last frame's next is
    the first."""
    src = BvhSource(builtin_motion_path(), loop=True, rate_hz=90.0, smooth=True)
    poses, n = walker.poses, walker.num_frames
    at = 0.0
    for _ in range(n + 5):  # past the loop
        sample = src.read()
        assert sample is not None
        i = int(at % n)  # a read just before the wrap lies between the last and first
        w = at % n - i
        a, b = poses[i], poses[(i + 1) % n].copy()
        b[:, 3:] *= np.where(np.sum(a[:, 3:] * b[:, 3:], axis=1) < 0.0, -1.0, 1.0)[:, None]
        want = a + w * (b - a)
        want[:, 3:] /= np.linalg.norm(want[:, 3:], axis=1, keepdims=True)
        np.testing.assert_allclose(sample.poses, want, rtol=0, atol=1e-12)
        at += 120.0 / 90.0
        if round(at) >= n:
            at -= n


def test_bvh_tpose_stands_where_the_clip_starts(walker: BvhSource) -> None:
    cal = walker.calibration()
    assert cal.roles == ROLES
    p = dict(zip(cal.roles, cal.positions, strict=True))
    first = dict(zip(ROLES, walker.poses[0, :, :3], strict=True))
    span = p["left_hand"] - p["right_hand"]
    assert abs(span[1]) < 0.02  # arms out sideways, hands level
    assert 1.2 < np.linalg.norm(span) < 1.8
    assert abs(p["left_foot"][1] - p["right_foot"][1]) < 0.02  # legs straight
    assert 0.0 <= min(p["left_foot"][1], p["right_foot"][1]) < 0.08
    assert p["head"][1] - p["hip"][1] > 0.4
    np.testing.assert_allclose(p["hip"][[0, 2]], first["hip"][[0, 2]], atol=1e-9)
    # facing the first frame's way: straight legs put the knees under the hip joints, and
    # knee to knee runs along the first frame's hip joints (LeftUpLeg - RightUpLeg)
    motion = read_bvh(builtin_motion_path())
    _, gp = forward_kinematics(motion.skeleton, motion.rotations[:1],
                               motion.translations[:1, 0], motion.translations[:1])
    hips = (gp[0, motion.skeleton.index("LeftUpLeg")] - gp[0, motion.skeleton.index(
        "RightUpLeg")])[[0, 2]]
    knees = (p["left_knee"] - p["right_knee"])[[0, 2]]
    cos = np.dot(knees, hips) / np.linalg.norm(knees) / np.linalg.norm(hips)
    assert cos > 0.999
    # this clip starts turned 22 degrees from +z: the canonical pose alone would face +z
    assert np.degrees(np.arctan2(abs(hips[1]), hips[0])) > 15.0


def test_calibration_raises_the_hips_and_knees_and_keeps_the_ankles(
        walker: BvhSource, monkeypatch: pytest.MonkeyPatch) -> None:
    """The legs pivot HIP_PIVOT_RAISE and bend KNEE_PIVOT_RAISE (scaled) higher than the
    template's joints; the T-pose ankles stay where the template's would be."""
    from posecast.solver import calibration
    from posecast.solver.rig import global_pose

    rig = build_rig(load_makehuman().skeleton)
    tpose = walker.calibration()
    devices = (dict(zip(tpose.roles, tpose.positions, strict=True)),
               dict(zip(tpose.roles, tpose.rotations, strict=True)))
    cal = calibrate(rig, *devices)
    lifts = (("thigh", calibration.HIP_PIVOT_RAISE), ("shin", calibration.KNEE_PIVOT_RAISE),
             ("foot", 0.0))
    monkeypatch.setattr(calibration, "HIP_PIVOT_RAISE", 0.0)
    monkeypatch.setattr(calibration, "KNEE_PIVOT_RAISE", 0.0)
    template = calibrate(rig, *devices)
    _, raised = global_pose(rig.skeleton.with_offsets(cal.offsets), cal.pose, cal.root)
    _, plain = global_pose(rig.skeleton.with_offsets(template.offsets), template.pose,
                           template.root)
    s = cal.scale
    for side in "lr":
        for bone, lift in lifts:
            j = rig.role(f"{bone}_{side}")
            np.testing.assert_allclose(raised[j] - plain[j], [0.0, lift * s, 0.0], atol=1e-9)


def test_bvh_calibrates_makehuman_and_solves_close_to_the_devices(walker: BvhSource) -> None:
    rig = build_rig(load_makehuman().skeleton)
    tpose = walker.calibration()
    cal = calibrate(rig, dict(zip(tpose.roles, tpose.positions, strict=True)),
                    dict(zip(tpose.roles, tpose.rotations, strict=True)))
    assert 0.85 < cal.scale < 1.0  # the CMU walker is a little smaller than the template
    solver = Solver(rig, "analytic")
    state = PoseBatch(cal.pose[None].copy(), cal.root[None].copy())
    src = BvhSource(builtin_motion_path())
    errors = []
    for _ in range(100):
        sample = src.read()
        assert sample is not None
        targets = cal.targets(sample.positions[None], sample.rotations[None], sample.roles)
        solver.solve(targets, state, cal.offsets[None])
        gq, gp = forward_kinematics(rig.skeleton, state.rotations, state.root,
                                    cal.offsets[None])
        pred, _ = cal.predict(gq, gp, DRIVING)
        want = sample.positions[[sample.roles.index(d) for d in DRIVING]]
        errors.append(np.linalg.norm(pred[0] - want, axis=-1))
    err = np.array(errors)  # (100, 6) metres
    assert err.max() < 0.02, dict(zip(DRIVING, err.max(axis=0), strict=True))
    assert err.mean() < 0.005
    # the avatar walked: its pelvis moved with the hip device
    assert np.linalg.norm(state.root[0, [0, 2]] - cal.root[[0, 2]]) > 0.3


@pytest.mark.parametrize(("name", "frames", "fps"), [
    ("bandai1_walk_normal_001.bvh", 195, 30.0),
    ("cmu_01_01_playground_jumps.bvh", 2751, 120.0),  # frame 0 is a bind pose, skipped
])
def test_bvh_real_files(shared_data: SharedData, name: str, frames: int, fps: float) -> None:
    src = BvhSource(shared_data(f"mocap/{name}"))
    assert src.num_frames == frames and src.rate_hz == fps
    cal = src.calibration()
    feet = [ROLES.index("left_foot"), ROLES.index("right_foot")]
    assert 0.0 <= cal.positions[feet, 1].min() < 0.15
    assert 0.0 <= src.poses[0, feet, 1].min() < 0.15
    head = cal.positions[ROLES.index("head"), 1]
    assert 1.3 < head < 1.9  # an adult's eyes


def test_bvh_errors(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match=r"missing.bvh: cannot read the motion file"):
        BvhSource(tmp_path / "missing.bvh")
    bad = tmp_path / "bad.bvh"
    bad.write_text("HIERARCHY\nROOT Hips\n{\n  OFFSET 0 0\n")
    with pytest.raises(FormatError, match=r"bad.bvh:4"):
        BvhSource(bad)


# --------------------------------------------------------------------- open_source

def test_open_source_specs(tmp_path: Path) -> None:
    vive = small_vive(tmp_path)
    src = open_source(f"vive:{vive}", loop=True)
    assert isinstance(src, ViveFileSource) and src.loop
    bvh = open_source(f"bvh:{builtin_motion_path()}")
    assert isinstance(bvh, BvhSource) and not bvh.loop and bvh.rate_hz == 120.0


@pytest.mark.parametrize("spec", ["", "vive", "vive:", "openvr:x", "bvh", "csv:a.csv",
                                  "OpenVR"])
def test_open_source_bad_spec_lists_the_forms(spec: str) -> None:
    with pytest.raises(SourceError, match=r"unknown pose source") as info:
        open_source(spec)
    assert str(info.value).endswith("use one of openvr, vive:FILE, bvh:FILE")
    assert SPEC_FORMS == ("openvr", "vive:FILE", "bvh:FILE")


def test_open_source_config_is_for_openvr_only(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match=r"config file is for the openvr source"):
        open_source(f"vive:{small_vive(tmp_path)}", config=tmp_path / "x.toml")
