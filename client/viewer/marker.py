"""``posecast view --marker JOINT``: a high-contrast marker on one joint of every avatar,
for ``posecast latency-video`` to follow in a phone video of the tracker and the screen.

The marker is a fixed 4x4 pattern of black and white cells in a black border and a white
quiet zone (as an ArUco marker): KCF follows texture, and loses a plain square, whose
inside has none. It keeps one size in pixels (an eighth of the frame's height) and is
drawn over everything, so the box the user picks in the first video frame fits it in
every frame, whatever the avatar's depth or pose. It is a texture drawn as a quad, with
``overlay``'s shaders, so the window and the headless PNGs show exactly the same marker.
"""

from __future__ import annotations

import moderngl
import numpy as np
from numpy.typing import NDArray

from posecast.client.viewer.camera import Camera
from posecast.client.viewer.overlay import _FS, _VS
from posecast.client.viewer.renderer import PosedScene, uniform

# the joints a person straps a tracker to, by the Vive device names of DESIGN.md
MARKER_JOINTS = {"head": "head", "hip": "pelvis", "left_hand": "hand_l",
                 "right_hand": "hand_r", "left_forearm": "lowerarm_l",
                 "right_forearm": "lowerarm_r", "left_foot": "foot_l", "right_foot": "foot_r",
                 "left_knee": "calf_l", "right_knee": "calf_r"}
DEFAULT_MARKER = "right_hand"
# not symmetric under any rotation or mirror: a tracker cannot lock onto a shifted copy
BITS = np.array([[1, 0, 1, 1],
                 [0, 0, 1, 0],
                 [1, 1, 0, 0],
                 [0, 1, 0, 1]], dtype=np.uint8)
CELLS = BITS.shape[0] + 4  # a black border and a white quiet zone around the bits
MIN_SIZE_PX = 24


def marker_size(height: int) -> int:
    """The marker's side in pixels for a frame ``height`` pixels tall: an eighth of it,
    a whole number of pixels per cell."""
    return max(MIN_SIZE_PX, height // 8) // CELLS * CELLS


def marker_image(size: int) -> NDArray[np.uint8]:
    """The marker, ``size`` x ``size`` RGBA (opaque), ``size`` a multiple of CELLS."""
    cells = np.ones((CELLS, CELLS), dtype=np.uint8)  # white quiet zone
    cells[1:-1, 1:-1] = 0  # black border
    cells[2:-2, 2:-2] = BITS
    gray = np.kron(cells, np.ones((size // CELLS, size // CELLS), dtype=np.uint8)) * 255
    return np.dstack([gray, gray, gray, np.full_like(gray, 255)])


def marker_centres(scene: PosedScene, joint: int, camera: Camera, width: int,
                   height: int) -> list[tuple[float, float]]:
    """Pixel positions of ``joint`` (mesh order) of every avatar in front of the camera."""
    if not len(scene):
        return []
    px, front = camera.project(scene.global_pos[:, joint], width, height)
    return [(float(x), float(y)) for (x, y), ok in zip(px, front, strict=True) if ok]


class MarkerOverlay:
    """Draws the marker centred on given pixels of the current framebuffer."""

    def __init__(self, ctx: moderngl.Context) -> None:
        self.ctx = ctx
        self._prog = ctx.program(vertex_shader=_VS, fragment_shader=_FS)
        corners = np.array([0, 0, 1, 0, 0, 1, 1, 1], dtype="f4")
        self._vbo = ctx.buffer(corners.tobytes())
        self._vao = ctx.vertex_array(self._prog, [(self._vbo, "2f", "in_corner")])
        self._texture: moderngl.Texture | None = None

    def _texture_of(self, size: int) -> moderngl.Texture:
        if self._texture is None or self._texture.size != (size, size):
            if self._texture is not None:
                self._texture.release()
            self._texture = self.ctx.texture((size, size), 4, marker_image(size).tobytes())
            self._texture.filter = (moderngl.NEAREST, moderngl.NEAREST)  # crisp cells
        return self._texture

    def draw(self, centres: list[tuple[float, float]], width: int, height: int) -> None:
        if not centres:
            return
        size = marker_size(height)
        texture = self._texture_of(size)
        self.ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)  # over the body too
        texture.use(0)
        for x, y in centres:
            x0, y0 = round(x - size / 2), round(y - size / 2)  # whole pixels: crisp edges
            uniform(self._prog, "u_rect").value = (
                2.0 * x0 / width - 1.0, 1.0 - 2.0 * y0 / height,
                2.0 * (x0 + size) / width - 1.0, 1.0 - 2.0 * (y0 + size) / height)
            self._vao.render(moderngl.TRIANGLE_STRIP)

    def release(self) -> None:
        if self._texture is not None:
            self._texture.release()
        self._vao.release()
        self._vbo.release()
        self._prog.release()
