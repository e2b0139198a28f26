"""Each eye's camera from a headset's pose, as a SteamVR scene application draws it.

OpenVR gives, per eye, an eye-to-head transform (the eye's offset: half the IPD sideways,
and any canting) and a projection; the compositor gives the headset's pose for when the
frame reaches the eyes. An eye's view is then inverse(head @ eye_to_head) and its camera
the projection times that (openvr.h: "Model * View * Eye^-1 * Projection").

Conventions as OpenVR's and OpenGL's: right-handed, +y up, the headset looks along its
-z, metres, the standing universe's floor at y = 0 (posecast's world too).

Without SteamVR (``play --hmd-out``) a Vive's own values stand in (``vive_setup``), and
the head device of the pose source stands in for the headset (``headset_from_device``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from posecast.client.viewer.camera import Camera
from posecast.solver import rotations as R

Array = NDArray[np.float64]

# an HTC Vive as SteamVR reports it: the recommended render target per eye (at 100%
# supersampling), the lens' half-angle tangents of the left eye (left, right, down, up:
# asymmetric, wider outwards; the right eye's are its mirror image, ~110 degrees across
# both), and the default IPD
VIVE_RECOMMENDED_SIZE = (1512, 1680)
VIVE_LEFT_TANGENTS = (1.3962, 1.2475, 1.4688, 1.4654)  # left, right, down, up
VIVE_IPD_M = 0.063
NEAR_M = 0.02  # the near plane: a hand held to the face is still drawn
FAR_M = 100.0


@dataclass(frozen=True)
class EyeSetup:
    """Both eyes of a headset: render size (each eye), projections and eye-to-head
    transforms, (2, 4, 4) each, left eye first."""

    width: int
    height: int
    projection: Array
    eye_to_head: Array

    def scaled(self, scale: float) -> EyeSetup:
        """The same eyes at ``scale`` times the render size (at least 16 px a side)."""
        return EyeSetup(max(16, round(self.width * scale)), max(16, round(self.height * scale)),
                        self.projection, self.eye_to_head)


def frustum(left: float, right: float, down: float, up: float, near: float = NEAR_M,
            far: float = FAR_M) -> Array:
    """An OpenGL projection (depth to -1..1) from the tangents of the half-angles to
    each side of the view axis (all positive: ``left`` is tan of the angle to the left)."""
    m = np.zeros((4, 4))
    m[0, 0] = 2.0 / (left + right)
    m[0, 2] = (right - left) / (left + right)
    m[1, 1] = 2.0 / (up + down)
    m[1, 2] = (up - down) / (up + down)
    m[2, 2] = (far + near) / (near - far)
    m[2, 3] = 2.0 * far * near / (near - far)
    m[3, 2] = -1.0
    return m


def opengl_depth(projection: NDArray[np.floating]) -> Array:
    """A projection that maps depth to 0..1 (Direct3D's, which IVRSystem's
    GetProjectionMatrix returns) remapped to OpenGL's -1..1: z' = 2 z - w. x and y,
    where every point lands, are untouched."""
    m = np.array(projection, dtype=np.float64)
    m[2] = 2.0 * m[2] - m[3]
    return m


def vive_setup(ipd: float = VIVE_IPD_M) -> EyeSetup:
    """A Vive's eyes (``VIVE_*``), for rendering without SteamVR."""
    left, right, down, up = VIVE_LEFT_TANGENTS
    projection = np.stack([frustum(left, right, down, up), frustum(right, left, down, up)])
    eye_to_head = np.stack([np.eye(4), np.eye(4)])
    eye_to_head[0, 0, 3], eye_to_head[1, 0, 3] = -ipd / 2.0, ipd / 2.0
    return EyeSetup(*VIVE_RECOMMENDED_SIZE, projection, eye_to_head)


def pose_matrix(position: ArrayLike, rotation: ArrayLike) -> Array:
    """The 4x4 device-to-world matrix of a pose (position, quaternion x y z w)."""
    m = np.eye(4)
    m[:3, :3] = R.to_matrix(np.asarray(rotation, dtype=np.float64))
    m[:3, 3] = position
    return m


def eye_cameras(head: NDArray[np.floating], setup: EyeSetup) -> tuple[Camera, Camera]:
    """The left and right eyes' cameras for the headset at ``head`` (4x4, headset to
    world)."""
    cams = []
    for e in range(2):
        eye_to_world = np.asarray(head, dtype=np.float64) @ setup.eye_to_head[e]
        view = np.linalg.inv(eye_to_world)
        cams.append(Camera(view, setup.projection[e], eye_to_world[:3, 3].copy()))
    return cams[0], cams[1]


def reflected(camera: Camera, plane: NDArray[np.floating]) -> Camera:
    """What ``camera`` sees in a mirror lying in ``plane`` (a, b, c, d with a unit
    normal): the scene reflected through the plane, drawn with the same projection,
    so a pixel of the mirror's surface on screen shows what the same pixel of this
    image does."""
    n, d = np.asarray(plane[:3], dtype=np.float64), float(plane[3])
    reflect = np.eye(4)
    reflect[:3, :3] -= 2.0 * np.outer(n, n)
    reflect[:3, 3] = -2.0 * d * n
    eye = reflect[:3, :3] @ camera.eye + reflect[:3, 3]
    return Camera(camera.view @ reflect, camera.projection, eye, mirrored=True)


def heading_of(sample_positions: dict[str, NDArray[np.floating]]) -> Array:
    """The horizontal direction a person in a T-pose faces: square to the line from the
    left hand to the right (up x (right - left)), unit length."""
    across = np.asarray(sample_positions["right_hand"], dtype=np.float64) - \
        np.asarray(sample_positions["left_hand"], dtype=np.float64)
    forward = np.cross([0.0, 1.0, 0.0], across)
    forward[1] = 0.0
    n = float(np.linalg.norm(forward))
    return forward / n if n > 1e-6 else np.array([0.0, 0.0, -1.0])


def headset_from_device(device_rotation: NDArray[np.floating],
                        heading: NDArray[np.floating]) -> Array:
    """The turn (a quaternion in the device's frame) that makes a head device a headset:
    one about the device's own up axis, so that its -z points where the person faced
    (``heading``) when the device had ``device_rotation`` (the T-pose).

    A real headset needs none (its -z is its view; the turn comes out ~0). A head device
    of another make, or a motion-capture head joint (+z forward), needs up to half a
    turn; with it, --hmd-out looks where the player looks, whatever the source."""
    local = R.rotate(R.conjugate(np.asarray(device_rotation, dtype=np.float64)),
                     np.asarray(heading, dtype=np.float64))
    angle = math.atan2(-float(local[0]), -float(local[2]))  # from -z to local, about +y
    return R.from_axis_angle(np.array([0.0, 1.0, 0.0]), angle)
