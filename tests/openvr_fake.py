"""Test helper: an OpenVR system without hardware, through the real ``openvr`` package.

An ``openvr.IVRSystem`` is built without ``openvr.init`` and its function table filled
with ctypes callbacks of the table's own prototypes, so the package's real wrapper code
(buffers, error codes, the pose array) and our role mapping and pose conversion run.
Used by tests/client/sources/test_sources_openvr.py (the source alone) and
tests/client/sources/test_openvr_live.py (the source streaming to a real server).
"""

from __future__ import annotations

import ctypes
import platform
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import openvr
from numpy.typing import NDArray

from posecast.solver import rotations as R

TABLE_TYPES = dict(openvr.IVRSystem_FnTable._fields_)
# getStringTrackedDeviceProperty's table prototype passes the buffer as c_char_p, which a
# Python callback receives as a bytes copy it cannot write to. The same C signature with
# the buffer as void* gives us its address; the callback is cast to the table's type.
STRING_PROTO = openvr.OPENVR_FNTABLE_CALLTYPE(
    ctypes.c_uint32, openvr.TrackedDeviceIndex_t, openvr.ETrackedDeviceProperty,
    ctypes.c_void_p, ctypes.c_uint32, ctypes.POINTER(openvr.ETrackedPropertyError))

HMD = openvr.TrackedDeviceClass_HMD
CONTROLLER = openvr.TrackedDeviceClass_Controller
TRACKER = openvr.TrackedDeviceClass_GenericTracker
LEFT = openvr.TrackedControllerRole_LeftHand
RIGHT = openvr.TrackedControllerRole_RightHand


def pose_matrix(q: NDArray[np.float64], p: Any) -> NDArray[np.float64]:
    """The 3x4 device-to-absolute matrix of rotation ``q`` (x y z w) at position ``p``."""
    m = np.zeros((3, 4))
    m[:, :3] = R.to_matrix(q)
    m[:, 3] = p
    return m


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
    """An IVRSystem whose function table answers from ``devices`` (index -> Device).

    ``on_read``, when set, is called with the number of the pose read (0, 1, ...) at
    each read, before the poses are copied out: a script that moves the devices or
    switches them off and on. (An exception in it cannot cross the ctypes callback: it
    would be printed and ignored, so a script should be simple.)
    """

    def __init__(self, devices: dict[int, Device], display_hz: float | None = 90.0) -> None:
        self.devices = devices
        self.display_hz = display_hz
        self.events: list[tuple[int, int]] = []  # (event type, device index) to deliver
        self.origins: list[int] = []
        self.scans = 0
        self.reads = 0  # calls of getDeviceToAbsoluteTrackingPose
        self.on_read: Callable[[int], None] | None = None
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
        n = self.reads
        self.reads += 1
        if self.on_read is not None:
            self.on_read(n)
        self.write_poses(poses, count)

    def write_poses(self, poses: Any, count: int) -> None:
        """The devices' poses into a caller's TrackedDevicePose_t array."""
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


def rig_devices() -> list[Device]:
    """A full SteamVR rig, by device index: an HMD, two controllers, seven role trackers,
    a base station and a chest tracker (index 11), all at the default pose."""
    return [
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


# the role SteamVR gives each device of rig_devices (the base station, 10, has none)
RIG_ROLES = {"head": 0, "hip": 3, "left_hand": 1, "right_hand": 2, "left_forearm": 8,
             "right_forearm": 9, "left_foot": 4, "right_foot": 5, "left_knee": 6,
             "right_knee": 7, "chest": 11}


# ------------------------------------------------------------------------- compositor
# IVRSystem's GetProjectionMatrix and GetEyeToHeadTransform return a 64- and a 48-byte
# struct by value, which a ctypes callback cannot. On x86-64 (System V and Windows alike)
# such a struct is returned through a hidden pointer the caller passes first, and the
# function returns that pointer: a callback of that C signature, cast to the table's
# type, answers the real wrapper's call exactly as the runtime would.
STRUCT_RETURN = platform.machine().lower() in ("x86_64", "amd64")
PROJECTION_PROTO = openvr.OPENVR_FNTABLE_CALLTYPE(
    ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint32, ctypes.c_float, ctypes.c_float)
EYE_TO_HEAD_PROTO = openvr.OPENVR_FNTABLE_CALLTYPE(
    ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint32)
COMPOSITOR_TYPES = dict(openvr.IVRCompositor_FnTable._fields_)
# a Vive's left-eye half-angle tangents (left, right, down, up) as GetProjectionRaw gives
# them, its recommended size and its default IPD (the headset tests' "real headset")
VIVE_TANGENTS = (1.3962, 1.2475, 1.4688, 1.4654)
VIVE_SIZE = (1512, 1680)
VIVE_IPD = 0.063


def d3d_projection(left: float, right: float, down: float, up: float, near: float,
                   far: float) -> NDArray[np.float64]:
    """The matrix SteamVR's GetProjectionMatrix returns for these tangents: openvr's own
    ComposeProjection, depth to 0..1 (Direct3D's convention)."""
    m = np.zeros((4, 4))
    m[0, 0] = 2.0 / (left + right)
    m[0, 2] = (right - left) / (left + right)
    m[1, 1] = 2.0 / (up + down)
    m[1, 2] = (up - down) / (up + down)
    m[2, 2] = -far / (far - near)
    m[2, 3] = -far * near / (far - near)
    m[3, 2] = -1.0
    return m


@dataclass
class Submitted:
    eye: int
    texture: int  # the GL texture name
    kind: int  # ETextureType
    bounds: tuple[float, float, float, float]
    wait: int  # the WaitGetPoses it follows (0, 1, ...)


class FakeCompositor:
    """A headset: ``vr`` (a FakeVR, whose system gains the render size, projections and
    eye transforms of a Vive) and an IVRCompositor whose WaitGetPoses hands out
    ``vr``'s devices (``on_wait(n)`` first moves them, as ``on_read`` does) and whose
    Submit records each texture and calls ``on_submit(submitted)`` on the submitting
    thread, its GL context current (read the texture back there)."""

    def __init__(self, vr: FakeVR, size: tuple[int, int] = VIVE_SIZE,
                 tangents: tuple[float, float, float, float] = VIVE_TANGENTS,
                 ipd: float = VIVE_IPD) -> None:
        self.vr = vr
        self.size = size
        self.tangents = tangents
        self.ipd = ipd
        self.waits = 0
        self.submitted: list[Submitted] = []
        self.on_wait: Callable[[int], None] | None = None
        self.on_submit: Callable[[Submitted], None] | None = None
        self.projection_calls: list[tuple[int, float, float]] = []
        table = vr.system.function_table
        vr._fill(table, "getRecommendedRenderTargetSize", self._size)
        for name, proto, fn in (("getProjectionMatrix", PROJECTION_PROTO, self._projection),
                                ("getEyeToHeadTransform", EYE_TO_HEAD_PROTO,
                                 self._eye_to_head)):
            cb = proto(fn)
            vr._keep.append(cb)
            setattr(table, name, ctypes.cast(cb, TABLE_TYPES[name]))
        ctable = openvr.IVRCompositor_FnTable()
        for name, fn in (("waitGetPoses", self._wait), ("submit", self._submit)):
            cb = COMPOSITOR_TYPES[name](fn)
            vr._keep.append(cb)
            setattr(ctable, name, cb)
        self.compositor = object.__new__(openvr.IVRCompositor)
        self.compositor.function_table = ctable

    def eye_tangents(self, eye: int) -> tuple[float, float, float, float]:
        left, right, down, up = self.tangents
        return (left, right, down, up) if eye == openvr.Eye_Left else (right, left, down, up)

    def eye_to_head(self, eye: int) -> NDArray[np.float64]:
        m = np.zeros((3, 4))
        m[:, :3] = np.eye(3)
        m[0, 3] = -self.ipd / 2 if eye == openvr.Eye_Left else self.ipd / 2
        return m

    def _size(self, width: Any, height: Any) -> None:
        width[0], height[0] = self.size

    def _projection(self, out: int, eye: int, near: float, far: float) -> int:
        self.projection_calls.append((eye, near, far))
        m = d3d_projection(*self.eye_tangents(eye), near, far)
        ctypes.memmove(out, np.ascontiguousarray(m, dtype=np.float32).ctypes.data, 64)
        return out

    def _eye_to_head(self, out: int, eye: int) -> int:
        m = np.ascontiguousarray(self.eye_to_head(eye), dtype=np.float32)
        ctypes.memmove(out, m.ctypes.data, 48)
        return out

    def _wait(self, render: Any, count: int, _game: Any, _game_count: int) -> int:
        n = self.waits
        self.waits += 1
        if self.on_wait is not None:
            self.on_wait(n)
        self.vr.write_poses(render, count)
        return openvr.VRCompositorError_None

    def _submit(self, eye: int, texture: Any, bounds: Any, _flags: int) -> int:
        t, b = texture[0], bounds[0]
        s = Submitted(eye, int(t.handle or 0), int(t.eType),
                      (b.uMin, b.vMin, b.uMax, b.vMax), self.waits - 1)
        self.submitted.append(s)
        if self.on_submit is not None:
            self.on_submit(s)
        return openvr.VRCompositorError_None
