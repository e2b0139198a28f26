"""SteamVR's compositor, for a scene application: the only module that talks to it.

Per frame: ``wait_poses`` blocks in IVRCompositor::WaitGetPoses until the compositor
wants the next frame ("running start", ~3 ms before the display's vsync) and hands out
every device's pose predicted for when that frame reaches the eyes; ``submit`` gives it
both eyes' OpenGL textures. The call that blocks goes through ctypes, which releases
the GIL, so the asyncio session on the main thread keeps running while it waits.

Tests run this code against the real ``openvr`` package with the IVRSystem and
IVRCompositor function tables filled with ctypes callbacks (tests/openvr_fake.py).
"""

from __future__ import annotations

import ctypes
from collections import Counter

import numpy as np
import openvr
from numpy.typing import NDArray

from posecast.client.headset.stereo import FAR_M, NEAR_M, EyeSetup, opengl_depth
from posecast.client.sources.openvr_source import POSE_DTYPE

EYES = (openvr.Eye_Left, openvr.Eye_Right)


def hmd_matrix(m: NDArray[np.floating]) -> NDArray[np.float64]:
    """A 3x4 device-to-world matrix (OpenVR's HmdMatrix34_t rows) as a 4x4."""
    out = np.eye(4)
    out[:3, :] = m
    return out


class Compositor:
    """IVRCompositor and IVRSystem of a scene application (``openvr.init(
    VRApplication_Scene)``; the caller owns the init)."""

    def __init__(self, system: openvr.IVRSystem, compositor: openvr.IVRCompositor) -> None:
        self.system = system
        self.compositor = compositor
        self.render_poses = (openvr.TrackedDevicePose_t * openvr.k_unMaxTrackedDeviceCount)()
        self.poses = np.frombuffer(self.render_poses, dtype=POSE_DTYPE)  # shares memory
        self._bounds = openvr.VRTextureBounds_t(0.0, 0.0, 1.0, 1.0)
        self.errors: Counter[str] = Counter()  # refused waits and submits, by error

    def setup(self) -> EyeSetup:
        """The headset's eyes: recommended render size, projections (depth remapped to
        OpenGL's), eye-to-head transforms."""
        width, height = self.system.getRecommendedRenderTargetSize()
        projection = np.stack([opengl_depth(np.array(
            self.system.getProjectionMatrix(e, NEAR_M, FAR_M).m, dtype=np.float64))
            for e in EYES])
        eye_to_head = np.stack([hmd_matrix(np.array(
            self.system.getEyeToHeadTransform(e).m, dtype=np.float64)) for e in EYES])
        return EyeSetup(int(width), int(height), projection, eye_to_head)

    def wait_poses(self) -> bool:
        """Block until the next frame is due; its poses are then in ``poses``. False
        when the compositor refused (another application has the focus: it then paces
        us at 10 Hz), counted in ``errors``."""
        try:
            self.compositor.waitGetPoses(self.render_poses, None)
        except openvr.error_code.CompositorError as err:
            self.errors[type(err).__name__] += 1
            return False
        return True

    def head(self) -> NDArray[np.float64] | None:
        """The headset's pose of the last wait (4x4), None while it is not tracked."""
        pose = self.poses[openvr.k_unTrackedDeviceIndex_Hmd]
        if not pose["valid"]:
            return None
        return hmd_matrix(pose["m"])

    def submit(self, textures: tuple[int, int]) -> None:
        """Both eyes' OpenGL texture names (their context current on this thread)."""
        for eye, name in zip(EYES, textures, strict=True):
            texture = openvr.Texture_t(ctypes.c_void_p(name), openvr.TextureType_OpenGL,
                                       openvr.ColorSpace_Gamma)
            try:
                self.compositor.submit(eye, texture, self._bounds)
            except openvr.error_code.CompositorError as err:
                self.errors[type(err).__name__] += 1
