"""Cameras: view and projection matrices (numpy, column vectors, OpenGL clip space).

Three ways to look at a room:
- ``OrbitCamera``: yaw/pitch/distance around a target point, the spectator's default.
- ``first_person``: at a player's eyes, looking where their head looks (the paper's
  Figure 3); the renderer hides that player's head so it does not fill the screen.
- ``mirror``: what the player would see in a mirror standing ``distance`` metres in front
  of them: the camera is the eyes reflected in the mirror plane, looking back, and the
  image is flipped left-right (``Camera.mirrored``), so raising the right hand raises the
  hand on the image's right, as in a real mirror.

World: metres, +y up, the floor at y = 0 (the solver's convention).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from posecast.solver import rotations as R

Array = NDArray[np.float64]
UP = np.array([0.0, 1.0, 0.0])


@dataclass(frozen=True)
class Camera:
    view: Array  # (4, 4) world -> eye
    projection: Array  # (4, 4) eye -> clip
    eye: Array  # (3,) camera position, world
    mirrored: bool = False  # image flipped left-right: front faces wind the other way

    @property
    def view_projection(self) -> Array:
        return self.projection @ self.view

    def project(self, points: NDArray[np.floating], width: int,
                height: int) -> tuple[Array, NDArray[np.bool_]]:
        """Pixel coordinates (N, 2) (x right, y down, pixel centres at +0.5) of world
        ``points`` (N, 3), and whether each is in front of the camera."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        clip = np.concatenate([p, np.ones((len(p), 1))], axis=1) @ self.view_projection.T
        w = clip[:, 3]
        front = w > 1e-6
        ndc = clip[:, :2] / np.where(front, w, 1.0)[:, None]
        px = np.empty((len(p), 2))
        px[:, 0] = (ndc[:, 0] + 1.0) * 0.5 * width
        px[:, 1] = (1.0 - ndc[:, 1]) * 0.5 * height
        return px, front


    def spheres_visible(self, centres: NDArray[np.floating],
                        radii: NDArray[np.floating]) -> NDArray[np.bool_]:
        """Whether each sphere (centres (N, 3), radii (N,)) may be in the view: False only
        for spheres wholly outside one of the frustum's six planes."""
        m = self.view_projection
        planes = np.stack([m[3] + m[0], m[3] - m[0], m[3] + m[1], m[3] - m[1],
                           m[3] + m[2], m[3] - m[2]])  # Gribb-Hartmann, inside >= 0
        planes /= np.linalg.norm(planes[:, :3], axis=1, keepdims=True)
        c = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
        dist = c @ planes[:, :3].T + planes[:, 3]  # (N, 6)
        return np.all(dist >= -np.asarray(radii, dtype=np.float64).reshape(-1, 1), axis=1)


def perspective(fov_y_deg: float, aspect: float, near: float = 0.05,
                far: float = 200.0) -> Array:
    f = 1.0 / math.tan(math.radians(fov_y_deg) / 2.0)
    m = np.zeros((4, 4))
    m[0, 0] = f / aspect
    m[1, 1] = f
    m[2, 2] = (far + near) / (near - far)
    m[2, 3] = 2.0 * far * near / (near - far)
    m[3, 2] = -1.0
    return m


def look_at(eye: NDArray[np.floating], target: NDArray[np.floating],
            up: NDArray[np.floating] = UP) -> Array:
    eye = np.asarray(eye, dtype=np.float64)
    f = np.asarray(target, dtype=np.float64) - eye
    f /= max(float(np.linalg.norm(f)), 1e-12)
    s = np.cross(f, up)
    if np.linalg.norm(s) < 1e-9:  # looking straight up or down: any side will do
        s = np.cross(f, np.array([0.0, 0.0, 1.0]))
    s /= np.linalg.norm(s)
    u = np.cross(s, f)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = s, u, -f
    m[:3, 3] = -m[:3, :3] @ eye
    return m


@dataclass
class OrbitCamera:
    """Orbit around ``target``: yaw about +y (0 looks along -z, from +z), pitch above the
    horizon, both in degrees."""

    yaw: float = 20.0
    pitch: float = 15.0
    distance: float = 6.0
    target: tuple[float, float, float] = (0.0, 1.0, 0.0)
    fov_y: float = 50.0

    def camera(self, aspect: float) -> Camera:
        yaw, pitch = math.radians(self.yaw), math.radians(self.pitch)
        direction = np.array([math.sin(yaw) * math.cos(pitch), math.sin(pitch),
                              math.cos(yaw) * math.cos(pitch)])
        target = np.asarray(self.target, dtype=np.float64)
        eye = target + self.distance * direction
        far = max(200.0, 4.0 * self.distance)
        return Camera(look_at(eye, target), perspective(self.fov_y, aspect, 0.05, far), eye)

    def frame(self, points: NDArray[np.floating]) -> None:
        """Aim at and back off to see every point (N, 3), e.g. all avatars' joints."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if len(p) == 0:
            return
        lo, hi = p.min(axis=0), p.max(axis=0)
        centre = 0.5 * (lo + hi)
        radius = max(0.5 * float(np.linalg.norm(hi - lo)), 1.0)
        self.target = (float(centre[0]), float(centre[1]), float(centre[2]))
        self.distance = 1.1 * radius / math.sin(math.radians(self.fov_y) / 2.0)


def first_person(head_rot: NDArray[np.floating], head_pos: NDArray[np.floating],
                 eye_offset: NDArray[np.floating], aspect: float,
                 fov_y: float = 90.0) -> Camera:
    """At the eyes (``eye_offset`` in the head joint's frame: x left, y up, z forward),
    looking along the head's +z with its +y up; an HMD-like wide field of view."""
    eye = np.asarray(head_pos, dtype=np.float64) + R.rotate(head_rot, eye_offset)
    forward = R.rotate(head_rot, np.array([0.0, 0.0, 1.0]))
    up = R.rotate(head_rot, UP)
    return Camera(look_at(eye, eye + forward, up), perspective(fov_y, aspect, 0.02), eye)


def mirror(head_rot: NDArray[np.floating], head_pos: NDArray[np.floating],
           eye_offset: NDArray[np.floating], aspect: float, distance: float = 1.5,
           fov_y: float = 60.0) -> Camera:
    """The player's view of themself in a vertical mirror ``distance`` m ahead of their
    eyes (facing them: its normal is their horizontal heading)."""
    eye = np.asarray(head_pos, dtype=np.float64) + R.rotate(head_rot, eye_offset)
    heading = R.rotate(head_rot, np.array([0.0, 0.0, 1.0]))
    heading[1] = 0.0
    n = float(np.linalg.norm(heading))
    heading = heading / n if n > 1e-6 else np.array([0.0, 0.0, 1.0])
    reflected = eye + 2.0 * distance * heading  # the eyes' image behind the mirror
    view = look_at(reflected, eye)
    flip = np.diag([-1.0, 1.0, 1.0, 1.0])  # a mirror swaps left and right
    return Camera(view, flip @ perspective(fov_y, aspect, 0.05), reflected, mirrored=True)
