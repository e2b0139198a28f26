"""Text over the 3D view: a name label above each avatar and the HUD (latency, fps, mode,
the devices each avatar has lost now).

Text is drawn by Pillow into small RGBA images, one per distinct string and colour,
uploaded once as textures and drawn as alpha-blended quads in the same framebuffer as the
scene, so the window and the headless PNGs show exactly the same thing, and nothing is
re-rasterised while the text does not change (a label only when its avatar's lost
devices do; the HUD a few times a second). The wording is pure functions (``hud_lines``,
``label_text``), tested without GL.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import moderngl
import numpy as np
from PIL import Image, ImageDraw, ImageFont

from posecast.client.viewer.camera import Camera
from posecast.client.viewer.renderer import uniform
from posecast.protocol import AvatarFrame, AvatarInfo
from posecast.protocol.roles import roles_of_bits

# the stages the HUD lists, in the order a pose travels (those present are shown)
HUD_STAGES = ("capture_to_server", "server", "network_to_spectator", "capture_to_spectator",
              "receive_to_render", "capture_to_render")
_CACHE_SIZE = 256  # textures kept; labels and a few HUD versions fit many times over
_PAD = 4

_VS = """
#version 330
in vec2 in_corner;  // (0,0) top-left .. (1,1) bottom-right of the text
uniform vec4 u_rect;  // x0, y0, x1, y1 in clip coordinates (y0 the top edge)
out vec2 v_uv;
void main() {
    v_uv = in_corner;  // texture row 0 is the image's top row
    gl_Position = vec4(mix(u_rect.x, u_rect.z, in_corner.x),
                       mix(u_rect.y, u_rect.w, in_corner.y), 0.0, 1.0);
}
"""

_FS = """
#version 330
in vec2 v_uv;
uniform sampler2D u_text;
out vec4 f_color;
void main() {
    f_color = texture(u_text, v_uv);
}
"""


@dataclass(frozen=True)
class TextItem:
    text: str
    x: float  # pixels from the left
    y: float  # pixels from the top
    color: tuple[float, float, float] = (1.0, 1.0, 1.0)
    anchor: str = "lt"  # "lt": (x, y) is the top-left corner; "mb": the middle of the bottom


# a monospaced font lines up the HUD's columns; Debian/Ubuntu ship DejaVu (fonts-dejavu-core)
MONO_FONTS = ("/usr/share/fonts/truetype/dejavu/DejaVuSansMono.ttf",
              "/usr/share/fonts/dejavu/DejaVuSansMono.ttf", "DejaVuSansMono.ttf")


def _load_font(size: int) -> ImageFont.FreeTypeFont | ImageFont.ImageFont:
    for path in MONO_FONTS:
        try:
            return ImageFont.truetype(path, size)
        except (OSError, ImportError):
            continue
    try:
        return ImageFont.load_default(size=size)  # Pillow >= 10.1 with FreeType
    except (TypeError, ImportError, OSError):
        return ImageFont.load_default()


def text_image(text: str, color: tuple[float, float, float],
               font: ImageFont.FreeTypeFont | ImageFont.ImageFont) -> Image.Image:
    """``text`` (may hold newlines) in ``color`` on a translucent dark box, RGBA."""
    probe = ImageDraw.Draw(Image.new("RGBA", (1, 1)))
    left, top, right, bottom = probe.multiline_textbbox((0, 0), text, font=font, spacing=3)
    w, h = int(right - left) + 2 * _PAD, int(bottom - top) + 2 * _PAD
    img = Image.new("RGBA", (max(w, 1), max(h, 1)), (0, 0, 0, 0))
    draw = ImageDraw.Draw(img)
    draw.rounded_rectangle((0, 0, w - 1, h - 1), radius=4, fill=(10, 12, 16, 170))
    rgb = tuple(round(255 * min(max(c, 0.0), 1.0)) for c in color)
    draw.multiline_text((_PAD - left, _PAD - top), text, font=font, spacing=3,
                        fill=(*rgb, 255))
    return img


class TextOverlay:
    """Draws TextItems into the current framebuffer of ``ctx``."""

    def __init__(self, ctx: moderngl.Context, font_size: int = 15) -> None:
        self.ctx = ctx
        self.font = _load_font(font_size)
        self._prog = ctx.program(vertex_shader=_VS, fragment_shader=_FS)
        corners = np.array([0, 0, 1, 0, 0, 1, 1, 1], dtype="f4")
        self._vbo = ctx.buffer(corners.tobytes())
        self._vao = ctx.vertex_array(self._prog, [(self._vbo, "2f", "in_corner")])
        self._cache: OrderedDict[tuple[str, tuple[float, float, float]],
                                 moderngl.Texture] = OrderedDict()

    def _texture(self, text: str, color: tuple[float, float, float]) -> moderngl.Texture:
        key = (text, color)
        tex = self._cache.get(key)
        if tex is not None:
            self._cache.move_to_end(key)
            return tex
        img = text_image(text, color, self.font)
        tex = self.ctx.texture(img.size, 4, img.tobytes())
        tex.filter = (moderngl.NEAREST, moderngl.NEAREST)  # pixel-exact text
        self._cache[key] = tex
        while len(self._cache) > _CACHE_SIZE:
            self._cache.popitem(last=False)[1].release()
        return tex

    def draw(self, items: Sequence[TextItem], width: int, height: int) -> None:
        ctx = self.ctx
        ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
        ctx.enable(moderngl.BLEND)
        ctx.blend_func = moderngl.SRC_ALPHA, moderngl.ONE_MINUS_SRC_ALPHA
        try:
            for item in items:
                tex = self._texture(item.text, item.color)
                w, h = tex.size
                x0, y0 = item.x, item.y
                if item.anchor == "mb":
                    x0, y0 = item.x - w / 2.0, item.y - h
                x0, y0 = round(x0), round(y0)  # whole pixels: crisp text
                uniform(self._prog, "u_rect").value = (
                    2.0 * x0 / width - 1.0, 1.0 - 2.0 * y0 / height,
                    2.0 * (x0 + w) / width - 1.0, 1.0 - 2.0 * (y0 + h) / height)
                tex.use(0)
                self._vao.render(moderngl.TRIANGLE_STRIP)
        finally:
            ctx.disable(moderngl.BLEND)

    def release(self) -> None:
        for tex in self._cache.values():
            tex.release()
        self._cache.clear()
        self._vao.release()
        self._vbo.release()
        self._prog.release()


def label_items(names: Sequence[str], colors: Sequence[tuple[float, float, float]],
                anchors: np.ndarray, camera: Camera, width: int,
                height: int) -> list[TextItem]:
    """Name labels centred above world points ``anchors`` (N, 3), those in view, the
    farthest first (so nearer labels are drawn over farther ones)."""
    px, front = camera.project(anchors, width, height)
    distance = np.linalg.norm(np.asarray(anchors, dtype=np.float64).reshape(-1, 3)
                              - camera.eye, axis=1)
    out = []
    for i in np.argsort(-distance, kind="stable"):
        x, y = px[i]
        if front[i] and -200 < x < width + 200 and -50 < y < height + 50:
            out.append(TextItem(names[i], float(x), float(y), colors[i], "mb"))
    return out


def label_text(name: str, lost: int) -> str:
    """An avatar's label: its name, and under it the devices its newest frame lacked
    (``lost``: protocol.roles bits), so that a guessed limb is seen as one."""
    roles = roles_of_bits(lost)
    return f"{name}\nlost {', '.join(roles)}" if roles else name


def device_lines(avatars: Iterable[tuple[AvatarInfo, AvatarFrame]]) -> list[str]:
    """A line per avatar whose newest frame lacks some of its devices: its name, how many
    devices it has, the ones lost ("player 2 (10 devices): lost left_foot, hip")."""
    out = []
    for info, frame in avatars:
        lost = frame.lost_roles
        if lost:
            count = f" ({len(info.devices)} devices)" if info.devices else ""
            out.append(f"{info.display_name}{count}: lost {', '.join(lost)}")
    return out


def hud_lines(latency_ms: Mapping[str, Mapping[str, float]], fps: float, avatars: int,
              mode: str, delay_ms: float | None, view: str,
              devices: Iterable[tuple[AvatarInfo, AvatarFrame]] = ()) -> list[str]:
    """The HUD's text: per-stage latency p50/p99 (ms), frame rate, avatar count, mode;
    then the avatars (each with its newest frame) that have lost devices now."""
    mode_text = mode if delay_ms is None else f"{mode} (buffer {delay_ms:.0f} ms)"
    lines = [f"{avatars} avatar{'s' if avatars != 1 else ''}   {fps:.0f} fps   "
             f"{mode_text}   view: {view}",
             "latency ms        p50     p99"]
    for stage in HUD_STAGES:
        s = latency_ms.get(stage)
        if s is not None:
            lines.append(f"{stage:<21}{s['p50']:6.1f}  {s['p99']:6.1f}")
    return lines + device_lines(devices)
