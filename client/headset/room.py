"""The room around the player in the headset: a mirror before them, and text anchored in
the world (names above the others' heads; the HUD a metre before the eyes).

The mirror is the paper's set-up (its Fig. 3: the player sees their avatar in a mirror).
Each eye draws the scene once more, reflected through the mirror's plane and cut at it
(``stereo.reflected``), into a texture; the mirror's quad then shows that texture at the
very pixels it covers, so the reflection has each eye's own parallax, as a real
mirror's has. Placed when the player calibrates: ``distance`` metres ahead of where they
stood, facing them, standing on the floor.
"""

from __future__ import annotations

from dataclasses import dataclass

import moderngl
import numpy as np
from numpy.typing import NDArray

from posecast.client.viewer.camera import Camera
from posecast.client.viewer.overlay import TextItem
from posecast.client.viewer.renderer import uniform

Array = NDArray[np.float64]

MIRROR_WIDTH_M = 1.4
MIRROR_HEIGHT_M = 2.1
MIRROR_BOTTOM_M = 0.02  # just above the floor: no z-fighting with the grid
MIRROR_SCALE = 0.5  # the reflection's resolution, of the eye's: a mirror seen from ~2 m
MIRROR_FRAME = (0.30, 0.28, 0.26)
HUD_AHEAD_M = 1.2  # the HUD floats this far before the eyes ...
HUD_BELOW_M = 0.5  # ... and this far below them: read with a glance down


@dataclass(frozen=True)
class MirrorPlacement:
    centre: Array  # (3,) the middle of its surface
    normal: Array  # (3,) unit, horizontal, facing the player
    right: Array  # (3,) unit, along its width
    width: float = MIRROR_WIDTH_M
    height: float = MIRROR_HEIGHT_M

    @property
    def plane(self) -> Array:
        """(a, b, c, d): positive on the player's side."""
        return np.array([*self.normal, -float(self.normal @ self.centre)])

    def corners(self) -> Array:
        """(4, 3): bottom-left, bottom-right, top-left, top-right, seen from the front."""
        half_w = 0.5 * self.width * self.right
        half_h = 0.5 * self.height * np.array([0.0, 1.0, 0.0])
        c = self.centre
        return np.stack([c - half_w - half_h, c + half_w - half_h, c - half_w + half_h,
                         c + half_w + half_h])


def place_mirror(head: NDArray[np.floating], heading: NDArray[np.floating],
                 distance: float) -> MirrorPlacement:
    """A mirror ``distance`` m ahead (along ``heading``, horizontal) of the head, facing
    back at it, on the floor."""
    h = np.array([heading[0], 0.0, heading[2]], dtype=np.float64)
    h /= max(float(np.linalg.norm(h)), 1e-9)
    centre = np.array([head[0], MIRROR_BOTTOM_M + MIRROR_HEIGHT_M / 2.0, head[2]]) \
        + distance * h
    normal = -h
    right = np.cross([0.0, 1.0, 0.0], normal)  # seen from the front, +x of its image
    return MirrorPlacement(centre, normal, right / np.linalg.norm(right))


def hud_anchor(head: NDArray[np.floating]) -> Array:
    """Where the HUD floats: ahead of the headset (4x4, headset to world) and below its
    eyes, following the head's heading and height but not its tilt."""
    m = np.asarray(head, dtype=np.float64)
    forward = -m[:3, 2]
    forward[1] = 0.0
    n = float(np.linalg.norm(forward))
    forward = forward / n if n > 1e-6 else np.array([0.0, 0.0, -1.0])
    return m[:3, 3] + HUD_AHEAD_M * forward - np.array([0.0, HUD_BELOW_M, 0.0])


def anchored_text(text: str, anchor: NDArray[np.floating], camera: Camera, width: int,
                  height: int, color: tuple[float, float, float] = (1.0, 1.0, 1.0)
                  ) -> TextItem | None:
    """``text`` centred on the world point ``anchor`` in this eye, or None when the point
    is behind it: each eye places it where it sees the point, so it is at that depth."""
    px, front = camera.project(np.asarray(anchor)[None, :], width, height)
    if not front[0]:
        return None
    return TextItem(text, float(px[0, 0]), float(px[0, 1]), color, anchor="mb")


_VS = """
#version 330
in vec3 in_position;
in vec2 in_uv;
uniform mat4 u_view_projection;
out vec2 v_uv;
void main() {
    v_uv = in_uv;
    gl_Position = u_view_projection * vec4(in_position, 1.0);
}
"""

_FS = """
#version 330
in vec2 v_uv;
uniform sampler2D u_reflection;
uniform vec2 u_viewport;
uniform vec3 u_frame;
out vec4 f_color;
void main() {
    // the reflection was drawn with this eye's projection: the same pixel shows it
    vec3 seen = texture(u_reflection, gl_FragCoord.xy / u_viewport).rgb;
    vec2 edge = min(v_uv, 1.0 - v_uv) * vec2(MIRROR_WIDTH, MIRROR_HEIGHT);
    float frame = step(min(edge.x, edge.y), 0.03);  // a 3 cm frame
    f_color = vec4(mix(0.92 * seen, u_frame, frame), 1.0);
}
"""


class Mirror:
    """Draws a placed mirror: ``target(size)`` is where the reflected pass goes,
    ``draw(camera, size)`` the mirror's quad in the eye's framebuffer."""

    def __init__(self, ctx: moderngl.Context, placement: MirrorPlacement) -> None:
        self.ctx = ctx
        self.placement = placement
        fs = _FS.replace("MIRROR_WIDTH", repr(float(placement.width))).replace(
            "MIRROR_HEIGHT", repr(float(placement.height)))
        self._prog = ctx.program(vertex_shader=_VS, fragment_shader=fs)
        uv = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], dtype=np.float64)
        data = np.concatenate([placement.corners(), uv], axis=1).astype("f4")
        self._vbo = ctx.buffer(data.tobytes())
        self._vao = ctx.vertex_array(self._prog, [(self._vbo, "3f 2f", "in_position",
                                                   "in_uv")])
        self._size: tuple[int, int] | None = None
        self._texture: moderngl.Texture | None = None
        self._depth: moderngl.Renderbuffer | None = None
        self._fbo: moderngl.Framebuffer | None = None

    def target(self, eye_size: tuple[int, int]) -> tuple[moderngl.Framebuffer,
                                                          tuple[int, int]]:
        """The reflected pass's framebuffer and size for an eye of ``eye_size``."""
        size = (max(1, round(eye_size[0] * MIRROR_SCALE)),
                max(1, round(eye_size[1] * MIRROR_SCALE)))
        if size != self._size:
            self._release_target()
            self._texture = self.ctx.texture(size, 4)
            self._texture.filter = (moderngl.LINEAR, moderngl.LINEAR)
            self._depth = self.ctx.depth_renderbuffer(size)
            self._fbo = self.ctx.framebuffer(color_attachments=[self._texture],
                                             depth_attachment=self._depth)
            self._size = size
        assert self._fbo is not None
        return self._fbo, size

    def visible(self, camera: Camera) -> bool:
        """Whether the eye sees the mirror's face: in front of it (from behind it is a
        wall) and with the mirror in its view (else its pass is skipped: a third of a
        frame's drawing)."""
        p = self.placement
        if float(p.plane[:3] @ camera.eye + p.plane[3]) <= 0.0:
            return False
        radius = 0.5 * float(np.hypot(p.width, p.height))
        return bool(camera.spheres_visible(p.centre[None, :], np.array([radius]))[0])

    def draw(self, camera: Camera, eye_size: tuple[int, int]) -> None:
        """The mirror's quad, showing the reflected pass, into the bound framebuffer."""
        assert self._texture is not None
        ctx = self.ctx
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.disable(moderngl.CULL_FACE)
        vp = np.ascontiguousarray(camera.view_projection.T, dtype="f4").tobytes()
        uniform(self._prog, "u_view_projection").write(vp)
        uniform(self._prog, "u_viewport").value = (float(eye_size[0]), float(eye_size[1]))
        uniform(self._prog, "u_frame").value = MIRROR_FRAME
        uniform(self._prog, "u_reflection").value = 0
        self._texture.use(0)
        self._vao.render(moderngl.TRIANGLE_STRIP)

    def _release_target(self) -> None:
        for obj in (self._fbo, self._texture, self._depth):
            if obj is not None:
                obj.release()
        self._fbo = self._texture = self._depth = None
        self._size = None

    def release(self) -> None:
        self._release_target()
        self._vao.release()
        self._vbo.release()
        self._prog.release()
