"""The OpenVR source without hardware, through the real ``openvr`` package.

``FakeVR`` (tests/openvr_fake.py) fills a real ``openvr.IVRSystem``'s function table with
ctypes callbacks of the table's own prototypes, so the package's real wrapper code
(buffers, error codes, the pose array) and our role mapping and pose conversion run.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import openvr
import pytest
from numpy.typing import NDArray
from openvr_fake import HMD, LEFT, RIGHT, TRACKER, Device, FakeVR, pose_matrix, rig_devices

from posecast.client.sources import SourceError, open_source
from posecast.client.sources.openvr_source import (
    OUT_OF_RANGE_S,
    OpenVRSource,
    load_serial_roles,
    poses_from_matrices,
)
from posecast.solver import rotations as R


def same_rotation(a: NDArray[np.float64], b: NDArray[np.float64]) -> float:
    """|angle| in radians between two quaternions (q and -q are one rotation)."""
    return float(2.0 * np.arccos(min(1.0, abs(float(np.dot(a, b))))))


# known rotations, 180-degree turns among them (the cases a trace-only conversion breaks)
ROTATIONS = [
    R.from_axis_angle([1.0, 0.0, 0.0], np.pi), R.from_axis_angle([0.0, 1.0, 0.0], np.pi),
    R.from_axis_angle([0.0, 0.0, 1.0], np.pi), R.from_axis_angle([1.0, 1.0, 0.0], np.pi),
    R.from_axis_angle([1.0, -2.0, 3.0], np.pi), R.from_axis_angle([0.0, 1.0, 0.0], 0.5),
    R.from_axis_angle([0.3, 0.2, -0.9], 2.5), R.from_axis_angle([1.0, 0.0, 0.0], -1.2),
    R.IDENTITY, R.from_axis_angle([0.0, 0.0, 1.0], 3.1),
]


def full_rig() -> dict[int, Device]:
    """An HMD, two controllers, seven role trackers, a base station and a chest tracker
    (``rig_devices``); device k stands at (k, 1 + k/10, -k/100) turned by
    ROTATIONS[k % 10]."""
    spec = rig_devices()
    for k, dev in enumerate(spec):
        dev.matrix = pose_matrix(ROTATIONS[k % len(ROTATIONS)], (k, 1 + k / 10, -k / 100))
    return dict(enumerate(spec))


EXPECTED_ROLES = {"head": 0, "hip": 3, "left_hand": 1, "right_hand": 2, "left_forearm": 8,
                  "right_forearm": 9, "left_foot": 4, "right_foot": 5, "left_knee": 6,
                  "right_knee": 7, "chest": 11}


def test_roles_from_device_class_controller_role_and_tracker_role() -> None:
    vr = FakeVR(full_rig())
    src = OpenVRSource(system=vr.system)
    assert src.device_roles == EXPECTED_ROLES  # the chest tracker is the chest now
    assert src.rate_hz == 90.0


def test_poses_match_the_matrices_including_180_degree_turns() -> None:
    devices = full_rig()
    vr = FakeVR(devices)
    sample = OpenVRSource(system=vr.system).read()
    assert sample is not None
    assert vr.origins == [openvr.TrackingUniverseStanding]
    assert sample.roles == ("head", "hip", "left_hand", "right_hand", "left_forearm",
                            "right_forearm", "left_foot", "right_foot", "left_knee",
                            "right_knee", "chest")
    for d, role in enumerate(sample.roles):
        k = EXPECTED_ROLES[role]
        np.testing.assert_allclose(sample.positions[d], (k, 1 + k / 10, -k / 100), atol=1e-6)
        q = sample.rotations[d]
        assert abs(np.linalg.norm(q) - 1.0) < 1e-12
        # float32 matrices
        assert same_rotation(q, ROTATIONS[k % len(ROTATIONS)]) < 1e-6, role
        np.testing.assert_allclose(R.to_matrix(q), devices[k].matrix[:, :3], atol=1e-6)
    assert sample.positions.shape == (11, 3) and sample.rotations.shape == (11, 4)


def test_display_frequency_sets_the_rate() -> None:
    assert OpenVRSource(system=FakeVR(full_rig(), display_hz=144.0).system).rate_hz == 144.0
    # no property: the Vive's 90 Hz
    assert OpenVRSource(system=FakeVR(full_rig(), display_hz=None).system).rate_hz == 90.0


@pytest.mark.parametrize("broken", [
    {"valid": False},
    # never Running_OK before: no IMU grace, left out at once
    {"result": openvr.TrackingResult_Running_OutOfRange},
    {"result": openvr.TrackingResult_Calibrating_InProgress},
    {"result": openvr.TrackingResult_Calibrating_OutOfRange},
    {"connected": False},
])
def test_untracked_poses_are_skipped(broken: dict[str, Any]) -> None:
    devices = full_rig()
    for key, value in broken.items():
        setattr(devices[4], key, value)  # the left foot
        setattr(devices[1], key, value)  # the left controller
    sample = OpenVRSource(system=FakeVR(devices).system).read()
    assert sample is not None
    assert "left_foot" not in sample.roles and "left_hand" not in sample.roles
    assert len(sample.roles) == 9
    hip = sample.roles.index("hip")
    np.testing.assert_allclose(sample.positions[hip], (3, 1.3, -0.03), atol=1e-6)


def test_out_of_range_is_sent_for_a_moment_after_running_ok() -> None:
    """Running_OutOfRange (the IMU alone) with a valid pose is still sent for
    OUT_OF_RANGE_S after the device was last Running_OK, then left out; Running_OK
    again starts the grace afresh. Real sleeps: the source's clock is perf_counter."""
    devices = full_rig()
    src = OpenVRSource(system=FakeVR(devices).system)
    foot, hand = devices[4], devices[1]
    imu_pose = pose_matrix(ROTATIONS[5], (4.5, 0.2, -0.5))  # dead-reckoned: it moves on

    def ok_then_out_of_range() -> tuple[float, float, tuple[str, ...], NDArray[np.float64]]:
        """Read with the foot and hand Running_OK, then OutOfRange at once: (the OK
        read's capture time, the OutOfRange read's, its roles and positions)."""
        foot.result = hand.result = openvr.TrackingResult_Running_OK
        foot.matrix = full_rig()[4].matrix
        ok = src.read()
        assert ok is not None and {"left_foot", "left_hand"} <= set(ok.roles)
        foot.result = hand.result = openvr.TrackingResult_Running_OutOfRange
        foot.matrix = imu_pose
        out = src.read()
        assert out is not None
        return ok.t_capture, out.t_capture, out.roles, out.positions

    # the next read is well within the grace, unless the machine stalled over 0.1 s
    # between two reads: then the rule says left out, and we try again
    for _ in range(5):
        t_ok, t_out, roles, positions = ok_then_out_of_range()
        within = t_out - t_ok <= OUT_OF_RANGE_S
        assert ("left_foot" in roles) == within and ("left_hand" in roles) == within
        if within:
            break
    assert within, "no read came within OUT_OF_RANGE_S of the one before"
    assert len(roles) == 11  # nothing left out yet
    # the pose sent is the one SteamVR reports, the IMU's
    np.testing.assert_allclose(positions[roles.index("left_foot")], (4.5, 0.2, -0.5),
                               atol=1e-6)
    time.sleep(OUT_OF_RANGE_S + 0.05)  # still OutOfRange: too long since Running_OK
    later = src.read()
    assert later is not None
    assert "left_foot" not in later.roles and "left_hand" not in later.roles
    assert len(later.roles) == 9
    # OutOfRange without a valid pose is left out even right after Running_OK
    foot.result = openvr.TrackingResult_Running_OK
    ok = src.read()
    foot.result, foot.valid = openvr.TrackingResult_Running_OutOfRange, False
    out = src.read()
    foot.valid = True
    assert ok is not None and out is not None
    assert "left_foot" in ok.roles and "left_foot" not in out.roles
    # back to Running_OK: sent again, and the grace counts from this Running_OK
    for _ in range(5):
        t_ok, t_out, roles, _ = ok_then_out_of_range()
        within = t_out - t_ok <= OUT_OF_RANGE_S
        assert ("left_foot" in roles) == within
        if within:
            break
    assert within


def test_serial_override_beats_the_steamvr_role(tmp_path: Path) -> None:
    cfg = tmp_path / "trackers.toml"
    # the waist tracker is really on the left knee; the chest tracker is the hip
    cfg.write_text('[serials]\n"LHR-WAIST" = "left_knee"\n"LHR-CHEST" = "hip"\n')
    src = OpenVRSource(cfg, system=FakeVR(full_rig()).system)
    roles = src.device_roles
    assert roles["left_knee"] == 3 and roles["hip"] == 11
    assert 6 not in roles.values()  # the SteamVR left knee lost its role to the override
    assert "chest" not in roles  # the chest tracker's SteamVR role gave way to its serial
    sample = src.read()
    assert sample is not None
    np.testing.assert_allclose(sample.positions[sample.roles.index("hip")],
                               (11, 2.1, -0.11), atol=1e-6)


def test_handed_tracker_takes_its_controller_role() -> None:
    devices = {0: Device(HMD), 1: Device(TRACKER, kind="vive_tracker_handed", hand=RIGHT),
               2: Device(TRACKER, kind="vive_tracker_handed", hand=LEFT),
               3: Device(TRACKER, kind="vive_tracker_camera")}
    assert OpenVRSource(system=FakeVR(devices).system).device_roles == {
        "head": 0, "left_hand": 2, "right_hand": 1}


def test_new_device_found_on_its_activation_event() -> None:
    devices = {0: Device(HMD)}
    vr = FakeVR(devices)
    src = OpenVRSource(system=vr.system)
    scans = vr.scans
    devices[1] = Device(TRACKER, serial="LHR-X", kind="vive_tracker_left_foot")
    s1 = src.read()
    assert s1 is not None and s1.roles == ("head",)  # not rescanned yet: under a second
    assert vr.scans == scans
    vr.events.append((openvr.VREvent_TrackedDeviceActivated, 1))
    s2 = src.read()
    assert s2 is not None and s2.roles == ("head", "left_foot")
    assert vr.scans == scans + 1


def test_steamvr_quitting_ends_the_source() -> None:
    vr = FakeVR(full_rig())
    src = OpenVRSource(system=vr.system)
    assert src.read() is not None
    vr.events.append((openvr.VREvent_Quit, 0))
    assert src.read() is None
    assert src.read() is None


def test_calibration_waits_for_head_and_hands_then_names_the_missing() -> None:
    devices = full_rig()
    src = OpenVRSource(system=FakeVR(devices).system, calibration_timeout=0.05)
    sample = src.calibration()
    assert set(sample.roles) == set(EXPECTED_ROLES)  # every device tracked then
    # the feet untracked: calibrated without them (mounted when they come)
    devices[4].valid = False
    devices[5].result = openvr.TrackingResult_Calibrating_OutOfRange
    sample = src.calibration()
    assert set(sample.roles) == set(EXPECTED_ROLES) - {"left_foot", "right_foot"}
    # a hand untracked: no calibration, and the message names it (not the feet)
    devices[1].connected = False
    # (once calibrated, a recalibration does not wait: the stream goes on meanwhile)
    with pytest.raises(SourceError, match=r"calibration needs left_hand tracked, not "
                                          r"tracked now") as info:
        src.calibration()
    assert "foot" not in str(info.value)
    devices[2].valid = False
    with pytest.raises(SourceError, match=r"calibration needs left_hand, right_hand tracked"):
        src.calibration()
    devices[0].result = openvr.TrackingResult_Calibrating_InProgress
    with pytest.raises(SourceError, match=r"needs head, left_hand, right_hand tracked"):
        src.calibration()


def test_calibration_waits_until_the_hands_are_tracked() -> None:
    devices = full_rig()
    devices[1].valid = devices[2].valid = False
    vr = FakeVR(devices)

    def hands_on(n: int) -> None:  # the controllers come on at the fourth read
        if n == 3:
            devices[1].valid = devices[2].valid = True

    vr.on_read = hands_on
    sample = OpenVRSource(system=vr.system, calibration_timeout=30.0).calibration()
    assert vr.reads == 4
    assert {"head", "left_hand", "right_hand"} <= set(sample.roles)
    assert len(sample.roles) == 11


@pytest.mark.parametrize(("text", "message"), [
    ('[serials]\n"LHR-1" = "left_toe"\n', r"unknown role 'left_toe'"),
    ('[serials]\n"LHR-1" = left_foot\n', r"not valid TOML"),
    ('serials = "LHR-1"\n', r"'serials' must be a table"),
    ('[trackers]\n"LHR-1" = "hip"\n', r"unknown section\(s\) trackers"),
    ('[serials]\n"LHR-1" = "hip"\n"LHR-2" = "hip"\n', r"role 'hip' is given to both"),
    ('[serials]\n"LHR-1" = 3\n', r"unknown role 3"),
])
def test_bad_config_names_the_file(tmp_path: Path, text: str, message: str) -> None:
    cfg = tmp_path / "bad.toml"
    cfg.write_text(text)
    with pytest.raises(SourceError, match=message) as info:
        OpenVRSource(cfg, system=FakeVR(full_rig()).system)
    assert str(info.value).startswith(f"{cfg}: ")


def test_missing_config_names_the_file(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match=r"nope.toml: cannot read the OpenVR config"):
        load_serial_roles(tmp_path / "nope.toml")


def test_good_config_reads(tmp_path: Path) -> None:
    cfg = tmp_path / "ok.toml"
    cfg.write_text('[serials]\n"LHR-1" = "left_foot"\n"LHR-2" = "right_forearm"\n')
    assert load_serial_roles(cfg) == {"LHR-1": "left_foot", "LHR-2": "right_forearm"}


def test_without_steamvr_one_clear_line() -> None:
    if openvr.isRuntimeInstalled() and openvr.isHmdPresent():
        pytest.skip("this machine has SteamVR and a headset")
    for make in (OpenVRSource, lambda: open_source("openvr")):
        with pytest.raises(SourceError) as info:
            make()
        message = str(info.value)
        assert "\n" not in message
        assert message.startswith("SteamVR is not ")
        assert "(OpenVR init failed: VRInitError_Init_" in message
        assert message.endswith("start SteamVR, or replay a recording with --source vive:FILE")


def test_conversion_of_random_and_drifting_matrices() -> None:
    rng = np.random.default_rng(7)
    q = R.normalize(rng.normal(size=(500, 4)))
    m = np.concatenate([R.to_matrix(q), rng.normal(size=(500, 3, 1))], axis=2)
    pos, rot = poses_from_matrices(m.astype(np.float32))
    np.testing.assert_allclose(pos, m[:, :, 3], atol=1e-6)
    err = 2 * np.arccos(np.clip(np.abs(np.sum(rot * q, axis=-1)), 0, 1))
    assert err.max() < 1e-6
    # a matrix 1% off orthonormal still gives a unit quaternion of the nearest rotation
    drift = m.copy()
    drift[:, :, :3] *= 1.01
    drift[:, 0, 1] += 0.003
    _, rot2 = poses_from_matrices(drift)
    np.testing.assert_allclose(np.linalg.norm(rot2, axis=-1), 1.0, atol=1e-12)
    err2 = 2 * np.arccos(np.clip(np.abs(np.sum(rot2 * q, axis=-1)), 0, 1))
    assert 1e-5 < err2.max() < 0.005
    assert poses_from_matrices(np.zeros((0, 3, 4)))[1].shape == (0, 4)
