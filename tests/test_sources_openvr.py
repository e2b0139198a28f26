"""The OpenVR source without hardware, through the real ``openvr`` package.

An ``openvr.IVRSystem`` is built without ``openvr.init`` and its function table filled
with ctypes callbacks of the table's own prototypes, so the package's real wrapper code
(buffers, error codes, the pose array) and our role mapping and pose conversion run.
"""

from __future__ import annotations

import ctypes
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import openvr
import pytest
from numpy.typing import NDArray

from posecast.client.sources import SourceError, open_source
from posecast.client.sources.openvr_source import (
    OpenVRSource,
    load_serial_roles,
    poses_from_matrices,
)
from posecast.solver import rotations as R

TABLE_TYPES = dict(openvr.IVRSystem_FnTable._fields_)
# getStringTrackedDeviceProperty's table prototype passes the buffer as c_char_p, which a
# Python callback receives as a bytes copy it cannot write to. The same C signature with
# the buffer as void* gives us its address; the callback is cast to the table's type.
STRING_PROTO = openvr.OPENVR_FNTABLE_CALLTYPE(
    ctypes.c_uint32, openvr.TrackedDeviceIndex_t, openvr.ETrackedDeviceProperty,
    ctypes.c_void_p, ctypes.c_uint32, ctypes.POINTER(openvr.ETrackedPropertyError))


def pose_matrix(q: NDArray[np.float64], p: tuple[float, float, float]) -> NDArray[np.float64]:
    m = np.zeros((3, 4))
    m[:, :3] = R.to_matrix(q)
    m[:, 3] = p
    return m


def same_rotation(a: NDArray[np.float64], b: NDArray[np.float64]) -> float:
    """|angle| in radians between two quaternions (q and -q are one rotation)."""
    return float(2.0 * np.arccos(min(1.0, abs(float(np.dot(a, b))))))


@dataclass
class Device:
    cls: int
    matrix: NDArray[np.float64] = field(default_factory=lambda: pose_matrix(R.IDENTITY,
                                                                            (0, 1, 0)))
    serial: str = ""
    kind: str = ""  # Prop_ControllerType_String
    hand: int = openvr.TrackedControllerRole_Invalid
    valid: bool = True
    result: int = openvr.TrackingResult_Running_OK
    connected: bool = True


class FakeVR:
    """An IVRSystem whose function table answers from ``devices`` (index -> Device)."""

    def __init__(self, devices: dict[int, Device], display_hz: float | None = 90.0) -> None:
        self.devices = devices
        self.display_hz = display_hz
        self.events: list[tuple[int, int]] = []  # (event type, device index) to deliver
        self.origins: list[int] = []
        self.scans = 0
        self._keep: list[Any] = []  # the callbacks must outlive the table
        table = openvr.IVRSystem_FnTable()
        self._fill(table, "getDeviceToAbsoluteTrackingPose", self._poses)
        self._fill(table, "getTrackedDeviceClass", self._class)
        self._fill(table, "isTrackedDeviceConnected", self._connected)
        self._fill(table, "getControllerRoleForTrackedDeviceIndex", self._hand)
        self._fill(table, "getFloatTrackedDeviceProperty", self._float)
        self._fill(table, "pollNextEvent", self._event)
        cb = STRING_PROTO(self._string)
        self._keep.append(cb)
        table.getStringTrackedDeviceProperty = ctypes.cast(
            cb, TABLE_TYPES["getStringTrackedDeviceProperty"])
        self.system = object.__new__(openvr.IVRSystem)
        self.system.function_table = table

    def _fill(self, table: openvr.IVRSystem_FnTable, name: str,
              fn: Callable[..., Any]) -> None:
        cb = TABLE_TYPES[name](fn)
        self._keep.append(cb)
        setattr(table, name, cb)

    def _poses(self, origin: int, _predict: float, poses: Any, count: int) -> None:
        self.origins.append(origin)
        for i in range(count):
            pose = poses[i]  # a view into the caller's array
            dev = self.devices.get(i)
            if dev is None:
                pose.bPoseIsValid = pose.bDeviceIsConnected = 0
                pose.eTrackingResult = openvr.TrackingResult_Uninitialized
                continue
            for r in range(3):
                for c in range(4):
                    pose.mDeviceToAbsoluteTracking.m[r][c] = dev.matrix[r, c]
            pose.bPoseIsValid = int(dev.valid)
            pose.bDeviceIsConnected = int(dev.connected)
            pose.eTrackingResult = dev.result

    def _class(self, i: int) -> int:
        if i == 0:
            self.scans += 1
        dev = self.devices.get(i)
        return openvr.TrackedDeviceClass_Invalid if dev is None else dev.cls

    def _connected(self, i: int) -> int:
        dev = self.devices.get(i)
        return int(dev is not None and dev.connected)

    def _hand(self, i: int) -> int:
        dev = self.devices.get(i)
        return openvr.TrackedControllerRole_Invalid if dev is None else dev.hand

    def _float(self, i: int, prop: int, err: Any) -> float:
        if i == 0 and prop == openvr.Prop_DisplayFrequency_Float and self.display_hz:
            err[0] = openvr.TrackedProp_Success
            return self.display_hz
        err[0] = openvr.TrackedProp_UnknownProperty
        return 0.0

    def _string(self, i: int, prop: int, buf: int | None, size: int, err: Any) -> int:
        dev = self.devices.get(i)
        value = None
        if dev is not None:
            value = {openvr.Prop_SerialNumber_String: dev.serial,
                     openvr.Prop_ControllerType_String: dev.kind}.get(prop) or None
        if value is None:
            err[0] = (openvr.TrackedProp_InvalidDevice if dev is None
                      else openvr.TrackedProp_ValueNotProvidedByDevice)
            return 0
        data = value.encode() + b"\0"
        if buf is None or size < len(data):
            err[0] = openvr.TrackedProp_BufferTooSmall
            return len(data)
        ctypes.memmove(buf, data, len(data))
        err[0] = openvr.TrackedProp_Success
        return len(data)

    def _event(self, event: Any, _size: int) -> int:
        if not self.events:
            return 0
        kind, index = self.events.pop(0)
        event[0].eventType = kind
        event[0].trackedDeviceIndex = index
        return 1


HMD = openvr.TrackedDeviceClass_HMD
CONTROLLER = openvr.TrackedDeviceClass_Controller
TRACKER = openvr.TrackedDeviceClass_GenericTracker
LEFT = openvr.TrackedControllerRole_LeftHand
RIGHT = openvr.TrackedControllerRole_RightHand

# known rotations, 180-degree turns among them (the cases a trace-only conversion breaks)
ROTATIONS = [
    R.from_axis_angle([1.0, 0.0, 0.0], np.pi), R.from_axis_angle([0.0, 1.0, 0.0], np.pi),
    R.from_axis_angle([0.0, 0.0, 1.0], np.pi), R.from_axis_angle([1.0, 1.0, 0.0], np.pi),
    R.from_axis_angle([1.0, -2.0, 3.0], np.pi), R.from_axis_angle([0.0, 1.0, 0.0], 0.5),
    R.from_axis_angle([0.3, 0.2, -0.9], 2.5), R.from_axis_angle([1.0, 0.0, 0.0], -1.2),
    R.IDENTITY, R.from_axis_angle([0.0, 0.0, 1.0], 3.1),
]


def full_rig() -> dict[int, Device]:
    """An HMD, two controllers, seven role trackers, a base station and a chest tracker;
    device k stands at (k, 1 + k/10, -k/100) turned by ROTATIONS[k % 10]."""
    spec = [
        Device(HMD, serial="HMD-1"),
        Device(CONTROLLER, serial="CTRL-L", hand=LEFT),
        Device(CONTROLLER, serial="CTRL-R", hand=RIGHT),
        Device(TRACKER, serial="LHR-WAIST", kind="vive_tracker_waist"),
        Device(TRACKER, serial="LHR-LFOOT", kind="vive_tracker_left_foot"),
        Device(TRACKER, serial="LHR-RFOOT", kind="vive_tracker_right_foot"),
        Device(TRACKER, serial="LHR-LKNEE", kind="vive_tracker_left_knee"),
        Device(TRACKER, serial="LHR-RKNEE", kind="vive_tracker_right_knee"),
        Device(TRACKER, serial="LHR-LELB", kind="vive_tracker_left_elbow"),
        Device(TRACKER, serial="LHR-RELB", kind="vive_tracker_right_elbow"),
        Device(openvr.TrackedDeviceClass_TrackingReference, serial="LHB-1"),
        Device(TRACKER, serial="LHR-CHEST", kind="vive_tracker_chest"),
    ]
    for k, dev in enumerate(spec):
        dev.matrix = pose_matrix(ROTATIONS[k % len(ROTATIONS)], (k, 1 + k / 10, -k / 100))
    return dict(enumerate(spec))


EXPECTED_ROLES = {"head": 0, "hip": 3, "left_hand": 1, "right_hand": 2, "left_forearm": 8,
                  "right_forearm": 9, "left_foot": 4, "right_foot": 5, "left_knee": 6,
                  "right_knee": 7}


def test_roles_from_device_class_controller_role_and_tracker_role() -> None:
    vr = FakeVR(full_rig())
    src = OpenVRSource(system=vr.system)
    assert src.device_roles == EXPECTED_ROLES
    assert src.rate_hz == 90.0


def test_poses_match_the_matrices_including_180_degree_turns() -> None:
    devices = full_rig()
    vr = FakeVR(devices)
    sample = OpenVRSource(system=vr.system).read()
    assert sample is not None
    assert vr.origins == [openvr.TrackingUniverseStanding]
    assert sample.roles == ("head", "hip", "left_hand", "right_hand", "left_forearm",
                            "right_forearm", "left_foot", "right_foot", "left_knee",
                            "right_knee")
    for d, role in enumerate(sample.roles):
        k = EXPECTED_ROLES[role]
        np.testing.assert_allclose(sample.positions[d], (k, 1 + k / 10, -k / 100), atol=1e-6)
        q = sample.rotations[d]
        assert abs(np.linalg.norm(q) - 1.0) < 1e-12
        assert same_rotation(q, ROTATIONS[k]) < 1e-6, role  # float32 matrices
        np.testing.assert_allclose(R.to_matrix(q), devices[k].matrix[:, :3], atol=1e-6)
    assert sample.positions.shape == (10, 3) and sample.rotations.shape == (10, 4)


def test_display_frequency_sets_the_rate() -> None:
    assert OpenVRSource(system=FakeVR(full_rig(), display_hz=144.0).system).rate_hz == 144.0
    # no property: the Vive's 90 Hz
    assert OpenVRSource(system=FakeVR(full_rig(), display_hz=None).system).rate_hz == 90.0


@pytest.mark.parametrize("broken", [
    {"valid": False},
    {"result": openvr.TrackingResult_Running_OutOfRange},
    {"result": openvr.TrackingResult_Calibrating_InProgress},
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
    assert len(sample.roles) == 8
    hip = sample.roles.index("hip")
    np.testing.assert_allclose(sample.positions[hip], (3, 1.3, -0.03), atol=1e-6)


def test_serial_override_beats_the_steamvr_role(tmp_path: Path) -> None:
    cfg = tmp_path / "trackers.toml"
    # the waist tracker is really on the left knee; the chest tracker is the hip
    cfg.write_text('[serials]\n"LHR-WAIST" = "left_knee"\n"LHR-CHEST" = "hip"\n')
    src = OpenVRSource(cfg, system=FakeVR(full_rig()).system)
    roles = src.device_roles
    assert roles["left_knee"] == 3 and roles["hip"] == 11
    assert 6 not in roles.values()  # the SteamVR left knee lost its role to the override
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


def test_calibration_waits_for_the_driving_devices_then_names_the_missing() -> None:
    devices = full_rig()
    src = OpenVRSource(system=FakeVR(devices).system, calibration_timeout=0.05)
    sample = src.calibration()
    assert {"head", "hip", "left_hand", "right_hand", "left_foot", "right_foot"} <= set(
        sample.roles)
    devices[4].valid = False
    devices[5].result = openvr.TrackingResult_Running_OutOfRange
    with pytest.raises(SourceError, match=r"calibration needs left_foot, right_foot tracked"):
        src.calibration()


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
