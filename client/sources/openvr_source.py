"""The OpenVR (SteamVR) pose source: the player's headset, controllers and trackers, live.

Devices get roles the way SteamVR users already set them up: the headset is the head, the
controllers are the hands (by their controller role), and generic trackers take the role
chosen in SteamVR's "Manage Trackers" page, which OpenVR reports as the tracker's
``Prop_ControllerType_String`` (``vive_tracker_waist``, ``vive_tracker_left_foot`` ...).
A TOML file may override any device by serial number::

    [serials]
    "LHR-12345678" = "left_foot"

Poses are read in SteamVR's standing universe (metres, +y up, floor at y=0), which is the
frame of the Vive recordings and of every DeviceSample.

A device that is not tracked is left out of the frame, and the server carries it on
(``solver.tracking``). ``Running_OutOfRange`` (the base stations lost it; SteamVR
dead-reckons from the IMU) counts as tracked for OUT_OF_RANGE_S after it was last
``Running_OK``, then as lost: integrated accelerometer positions drift by centimetres
within a few tenths of a second, further than the server's carry-on does.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import time
import tomllib
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import openvr
from numpy.typing import NDArray

from posecast.client.sources.base import ROLES, DeviceSample, SourceError, now
from posecast.solver import rotations as R
from posecast.solver.calibration import CALIBRATION_DEVICES

DEFAULT_RATE_HZ = 90.0  # Vive and Vive Pro run at 90 Hz; used when the HMD does not say
RESCAN_SECONDS = 1.0  # re-read device roles this often, besides on device events
CALIBRATION_TIMEOUT = 30.0  # seconds to wait for every calibration device to be tracked
# how long (s) an IMU-only pose (Running_OutOfRange) is still sent, after Running_OK
OUT_OF_RANGE_S = 0.1

# SteamVR tracker roles as OpenVR reports them (Prop_ControllerType_String, lower-cased:
# some drivers write e.g. "vive_tracker_left_Shoulder")
TRACKER_ROLES = {
    "vive_tracker_waist": "hip",
    "vive_tracker_left_foot": "left_foot", "vive_tracker_right_foot": "right_foot",
    "vive_tracker_left_knee": "left_knee", "vive_tracker_right_knee": "right_knee",
    "vive_tracker_left_elbow": "left_forearm", "vive_tracker_right_elbow": "right_forearm",
    "vive_tracker_chest": "chest",
}
HANDED_TRACKER = "vive_tracker_handed"  # "held in hand": its controller role says which
HAND_ROLES = {openvr.TrackedControllerRole_LeftHand: "left_hand",
              openvr.TrackedControllerRole_RightHand: "right_hand"}
RESCAN_EVENTS = {openvr.VREvent_TrackedDeviceActivated, openvr.VREvent_TrackedDeviceDeactivated,
                 openvr.VREvent_TrackedDeviceUpdated, openvr.VREvent_TrackedDeviceRoleChanged}

# init errors that mean "nothing to talk to" rather than "SteamVR not started"
_NOT_INSTALLED = ("PathRegistryNotFound", "InstallationNotFound", "InstallationCorrupt")
_NO_HMD = ("HmdNotFound",)


def _pose_dtype() -> np.dtype[np.void]:
    """A numpy view of openvr.TrackedDevicePose_t, laid out from the ctypes fields."""
    T = openvr.TrackedDevicePose_t
    return np.dtype({
        "names": ["m", "valid", "connected", "result"],
        "formats": [("=f4", (3, 4)), "u1", "u1", "=u4"],
        "offsets": [T.mDeviceToAbsoluteTracking.offset, T.bPoseIsValid.offset,
                    T.bDeviceIsConnected.offset, T.eTrackingResult.offset],
        "itemsize": ctypes.sizeof(T)})


POSE_DTYPE = _pose_dtype()


def load_serial_roles(path: Path) -> dict[str, str]:
    """Serial number -> role from a TOML config (``[serials]`` table); SourceError naming
    the file for anything wrong."""
    try:
        with open(path, "rb") as f:
            doc = tomllib.load(f)
    except OSError as err:
        raise SourceError(f"{path}: cannot read the OpenVR config: {err.strerror}") from None
    except tomllib.TOMLDecodeError as err:
        raise SourceError(f"{path}: not valid TOML: {err}") from None
    unknown = sorted(set(doc) - {"serials"})
    if unknown:
        raise SourceError(f"{path}: unknown section(s) {', '.join(unknown)}; expected "
                          f"[serials]")
    serials = doc.get("serials", {})
    if not isinstance(serials, dict):
        raise SourceError(f"{path}: 'serials' must be a table of \"SERIAL\" = \"role\"")
    out: dict[str, str] = {}
    seen: dict[str, str] = {}
    for serial, role in serials.items():
        if role not in ROLES:
            raise SourceError(f"{path}: serial {serial!r} has unknown role {role!r}; roles: "
                              f"{', '.join(ROLES)}")
        if role in seen:
            raise SourceError(f"{path}: role {role!r} is given to both {seen[role]!r} and "
                              f"{serial!r}")
        seen[role] = serial
        out[serial] = role
    return out


def poses_from_matrices(m: NDArray[np.floating]) -> tuple[NDArray[np.float64],
                                                           NDArray[np.float64]]:
    """Positions (D, 3) and unit quaternions x y z w (D, 4) from 3x4 pose matrices (D, 3, 4).

    The rotation part arrives as float32 and drifts off orthonormal; it is first replaced
    by the nearest rotation (polar decomposition by SVD), then converted with Shepperd's
    method, which branches on the largest diagonal term and so stays exact at 180 degrees.
    """
    m64 = np.asarray(m, dtype=np.float64)
    u, _, vt = np.linalg.svd(m64[:, :, :3])
    flip = np.linalg.det(u @ vt) < 0.0  # a reflection is no pose: take the nearest rotation
    u[flip, :, -1] *= -1.0
    rot = R.from_matrix(u @ vt) if len(m64) else np.zeros((0, 4))
    return m64[:, :, 3].copy(), rot


class OpenVRSource:
    """Poses of the player's SteamVR devices; see the module docstring."""

    def __init__(self, config_path: Path | None = None, system: openvr.IVRSystem | None = None,
                 calibration_timeout: float = CALIBRATION_TIMEOUT,
                 application: int = openvr.VRApplication_Background) -> None:
        """``system``: an IVRSystem already open (tests fill one's function table);
        else OpenVR is opened as ``application``: a background app, or a scene app
        when the same process draws into the headset (``play --hmd``: one init per
        process, and a scene app's IVRSystem reads poses as well)."""
        self.serial_roles = load_serial_roles(config_path) if config_path is not None else {}
        self.calibration_timeout = calibration_timeout
        self._owns_runtime = system is None
        self.system = _init_openvr(application) if system is None else system
        self._poses = (openvr.TrackedDevicePose_t * openvr.k_unMaxTrackedDeviceCount)()
        self._view = np.frombuffer(self._poses, dtype=POSE_DTYPE)  # shares the ctypes memory
        self._event = openvr.VREvent_t()
        # (roles, their device indices), replaced whole by a rescan: a headset's frame
        # loop (play --hmd) maps the compositor's poses on its own thread meanwhile
        self._mapping: tuple[tuple[str, ...], NDArray[np.intp]] = ((), np.zeros(0, np.intp))
        self._next_scan = 0.0
        self._ended = False
        # when each device index was last Running_OK (for Running_OutOfRange)
        self._last_ok = np.full(openvr.k_unMaxTrackedDeviceCount, -np.inf)
        self.rate_hz = self._display_rate()
        self.rescan()

    # ----------------------------------------------------------------- device roles
    def rescan(self) -> None:
        """Re-read which device plays which role (serial overrides win)."""
        sys_ = self.system
        auto: dict[str, int] = {}
        override: dict[str, int] = {}
        for i in range(openvr.k_unMaxTrackedDeviceCount):
            cls = sys_.getTrackedDeviceClass(i)
            if cls == openvr.TrackedDeviceClass_Invalid or not sys_.isTrackedDeviceConnected(i):
                continue
            role = self.serial_roles.get(self._string(i, openvr.Prop_SerialNumber_String))
            if role is not None:
                override.setdefault(role, i)
                continue
            role = self._auto_role(i, cls)
            if role is not None:
                auto.setdefault(role, i)  # lowest index wins a contested role
        found = {**auto, **override}
        roles = tuple(r for r in ROLES if r in found)
        self._mapping = (roles, np.array([found[r] for r in roles], dtype=np.intp))
        self._next_scan = now() + RESCAN_SECONDS

    @property
    def device_roles(self) -> dict[str, int]:
        """Role -> OpenVR device index, as of the last scan."""
        roles, indices = self._mapping
        return dict(zip(roles, (int(i) for i in indices), strict=True))

    def _auto_role(self, i: int, cls: int) -> str | None:
        if cls == openvr.TrackedDeviceClass_HMD:
            return "head"
        if cls == openvr.TrackedDeviceClass_Controller:
            return HAND_ROLES.get(self.system.getControllerRoleForTrackedDeviceIndex(i))
        if cls == openvr.TrackedDeviceClass_GenericTracker:
            kind = self._string(i, openvr.Prop_ControllerType_String).lower()
            if kind == HANDED_TRACKER:
                return HAND_ROLES.get(self.system.getControllerRoleForTrackedDeviceIndex(i))
            return TRACKER_ROLES.get(kind)
        return None  # base stations and the like

    def _string(self, i: int, prop: int) -> str:
        try:
            return str(self.system.getStringTrackedDeviceProperty(i, prop))
        except openvr.error_code.TrackedPropertyError:
            return ""  # a device that does not report it: no role from it

    def _display_rate(self) -> float:
        try:
            hz = float(self.system.getFloatTrackedDeviceProperty(
                openvr.k_unTrackedDeviceIndex_Hmd, openvr.Prop_DisplayFrequency_Float))
        except openvr.error_code.TrackedPropertyError:
            return DEFAULT_RATE_HZ
        return hz if np.isfinite(hz) and hz > 0.0 else DEFAULT_RATE_HZ

    # ----------------------------------------------------------------- poses
    def _drain_events(self) -> None:
        while self.system.pollNextEvent(self._event):
            kind = self._event.eventType
            if kind == openvr.VREvent_Quit:
                self._ended = True
            elif kind in RESCAN_EVENTS:
                self._next_scan = 0.0

    def read(self) -> DeviceSample | None:
        """The poses of every tracked device with a role now; None once SteamVR quits."""
        if self._ended:
            return None
        self._drain_events()
        if self._ended:
            self.close()
            return None
        if now() >= self._next_scan:
            self.rescan()
        self.system.getDeviceToAbsoluteTrackingPose(openvr.TrackingUniverseStanding, 0.0,
                                                    self._poses)
        return self.sample_of(self._view, now())  # the capture: right after the read

    def sample_of(self, poses: NDArray[np.void], t: float) -> DeviceSample:
        """The sample of a pose array (``POSE_DTYPE`` over k_unMaxTrackedDeviceCount
        TrackedDevicePose_t, as read here or as the compositor's WaitGetPoses hands it to
        a headset's frame) with this source's roles, captured at ``t``."""
        roles, indices = self._mapping  # one mapping for the whole sample
        sel = poses[indices]
        valid = (sel["valid"] != 0) & (sel["connected"] != 0)
        running = valid & (sel["result"] == openvr.TrackingResult_Running_OK)
        self._last_ok[indices[running]] = t
        imu_only = valid & (sel["result"] == openvr.TrackingResult_Running_OutOfRange)
        ok = running | (imu_only & (t - self._last_ok[indices] <= OUT_OF_RANGE_S))
        pos, rot = poses_from_matrices(sel["m"][ok])
        kept = tuple(r for r, keep in zip(roles, ok, strict=True) if keep)
        return DeviceSample.of(t, kept, pos, rot)

    def calibration(self) -> DeviceSample:
        """The current sample, once the head and both hands are tracked: every device
        tracked then is calibrated (those switched on later are mounted when they
        appear)."""
        deadline = time.monotonic() + self.calibration_timeout
        while True:
            sample = self.read()
            if sample is None:
                raise SourceError("SteamVR quit before calibration")
            missing = [r for r in CALIBRATION_DEVICES if r not in sample.roles]
            if not missing:
                # a later recalibration (Enter, mid-session) must not block the stream
                # waiting for a hand behind the back: it says so at once instead
                self.calibration_timeout = 0.0
                return sample
            if time.monotonic() >= deadline:
                waited = (f"still missing after {self.calibration_timeout:g} s"
                          if self.calibration_timeout > 0.0 else "not tracked now")
                raise SourceError(
                    f"calibration needs {', '.join(missing)} tracked, {waited}: switch "
                    f"them on and assign their roles in SteamVR (or by serial in the "
                    f"config file)")
            time.sleep(1.0 / self.rate_hz)

    def close(self) -> None:
        if self._owns_runtime:
            self._owns_runtime = False
            openvr.shutdown()


def open_scene_source(config_path: Path | None = None) -> OpenVRSource:
    """The player's devices through OpenVR opened as a scene application, whose
    IVRSystem also serves the compositor (``play --hmd``); SourceError without SteamVR."""
    return OpenVRSource(config_path, application=openvr.VRApplication_Scene)


@contextlib.contextmanager
def _native_stderr_quiet() -> Iterator[None]:
    """The native OpenVR library prints its own diagnostics to file descriptor 2 (e.g.
    "Unable to read VR Path Registry"); our one-line SourceError says it better."""
    try:
        saved = os.dup(2)
    except OSError:  # no stderr to silence
        yield
        return
    try:
        with open(os.devnull, "wb") as devnull:
            os.dup2(devnull.fileno(), 2)
            yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def _init_openvr(application: int = openvr.VRApplication_Background) -> openvr.IVRSystem:
    """openvr.init as ``application`` (neither a background nor a scene app starts
    SteamVR itself), or SourceError."""
    try:
        with _native_stderr_quiet():
            return openvr.init(application)
    except openvr.error_code.OpenVRError as err:
        code = getattr(err, "error_value", None)
        name = (openvr.getVRInitErrorAsSymbol(code) if code is not None
                else type(err).__name__)
        if any(s in name for s in _NOT_INSTALLED):
            what = "SteamVR is not installed"
        elif any(s in name for s in _NO_HMD):
            what = "no VR headset found"
        else:
            what = "SteamVR is not running"
        instead = ("see the view without it with --hmd-out DIR"
                   if application == openvr.VRApplication_Scene
                   else "replay a recording with --source vive:FILE")
        raise SourceError(f"{what} (OpenVR init failed: {name}): start SteamVR, or "
                          f"{instead}") from None
