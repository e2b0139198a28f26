"""The desktop viewer: a GLFW window drawing the room live (``posecast view``).

GLFW (the ``glfw`` package: ctypes bindings with the library bundled in its wheels) is the
lightest standard way to get an OpenGL context in a window: moderngl draws into the
window's own framebuffer with the same Renderer and Viewer as the headless path, so a
window frame and a headless PNG are the same picture. Its calls go through ctypes, which
releases the GIL, and the loop yields to asyncio between frames, so the spectator keeps
receiving while the window waits for the next frame.

Where there is no display (Linux without $DISPLAY or $WAYLAND_DISPLAY) ``open_window``
raises ``NoDisplayError`` with one line pointing to ``--headless``, before any window
toolkit is imported.

Controls: drag with the left button to orbit, scroll to zoom, 1/2/3 orbit / first-person
/ mirror view, Tab the next player (first-person and mirror), I interpolation,
zero-buffer or predict (in turn), F frame every avatar again, P save a screenshot
(posecast_<time>.png in the working directory), Esc or Q to quit.
"""

from __future__ import annotations

import asyncio
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import moderngl
import numpy as np
from PIL import Image

from posecast.client.session.spectator import Spectator
from posecast.client.sources.base import now
from posecast.client.viewer.core import Viewer, ViewerStats
from posecast.client.viewer.interpolation import Interpolator, Mode
from posecast.client.viewer.renderer import Renderer
from posecast.client.viewer.scene import SpectatorScene, ViewerSpectator, ViewMode

DEFAULT_FPS = 60.0
_VIEW_KEYS = {"1": ViewMode.ORBIT, "2": ViewMode.FIRST_PERSON, "3": ViewMode.MIRROR}


class NoDisplayError(RuntimeError):
    """No display to open a window on."""


def check_display() -> None:
    """Raise NoDisplayError when a window cannot be opened (Linux and other X11/Wayland
    systems without a display). macOS and Windows always have one."""
    if sys.platform.startswith(("darwin", "win", "cygwin")):
        return
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise NoDisplayError("no display ($DISPLAY and $WAYLAND_DISPLAY are unset): "
                             "use --headless --frames N --out DIR to render to PNG files")


def _import_glfw() -> ModuleType:
    check_display()  # before the import: glfw's import itself may probe the display
    try:
        import glfw
    except ImportError as err:
        raise NoDisplayError(f"the window needs the glfw package ({err}): pip install glfw, "
                             f"or use --headless --frames N --out DIR") from None
    return glfw


class Window:
    """A GLFW window with a moderngl context; ``run`` draws a Viewer until closed."""

    def __init__(self, width: int = 1280, height: int = 720,
                 title: str = "posecast") -> None:
        glfw = self.glfw = _import_glfw()
        if not glfw.init():
            raise NoDisplayError("cannot open a window (GLFW failed to initialise on this "
                                 "display): use --headless --frames N --out DIR")
        glfw.window_hint(glfw.CONTEXT_VERSION_MAJOR, 3)
        glfw.window_hint(glfw.CONTEXT_VERSION_MINOR, 3)
        glfw.window_hint(glfw.OPENGL_PROFILE, glfw.OPENGL_CORE_PROFILE)
        glfw.window_hint(glfw.OPENGL_FORWARD_COMPAT, True)  # macOS wants it
        self.handle = None
        if sys.platform.startswith("linux"):
            # EGL first, as the headless renderer uses: once a process has made an EGL
            # context current, a GLX one cannot be (X error BadAccess, fatal), and Mesa
            # and NVIDIA both offer EGL on X11 and Wayland; GLX if EGL fails
            glfw.window_hint(glfw.CONTEXT_CREATION_API, glfw.EGL_CONTEXT_API)
            try:
                self.handle = glfw.create_window(width, height, title, None, None)
            except glfw.GLFWError:  # raised instead of warned when so configured
                self.handle = None
            glfw.window_hint(glfw.CONTEXT_CREATION_API, glfw.NATIVE_CONTEXT_API)
        if not self.handle:
            self.handle = glfw.create_window(width, height, title, None, None)
        if not self.handle:
            glfw.terminate()
            raise NoDisplayError("cannot open an OpenGL 3.3 window on this display: "
                                 "use --headless --frames N --out DIR")
        glfw.make_context_current(self.handle)
        glfw.swap_interval(0)  # paced by the loop, not by vsync (which would hold it)
        self.ctx = moderngl.create_context()
        self.viewer: Viewer | None = None
        self._shot: Path | None = None  # save the next frame here
        self._drag: tuple[float, float] | None = None
        glfw.set_key_callback(self.handle, self._on_key)
        glfw.set_mouse_button_callback(self.handle, self._on_button)
        glfw.set_cursor_pos_callback(self.handle, self._on_cursor)
        glfw.set_scroll_callback(self.handle, self._on_scroll)

    def framebuffer_size(self) -> tuple[int, int]:
        w, h = self.glfw.get_framebuffer_size(self.handle)
        return max(int(w), 1), max(int(h), 1)

    @property
    def should_close(self) -> bool:
        return bool(self.glfw.window_should_close(self.handle))

    # ------------------------------------------------------------------ input
    def _on_key(self, handle: Any, key: int, scancode: int, action: int, mods: int) -> None:
        glfw, v = self.glfw, self.viewer
        if action != glfw.PRESS or v is None:
            return
        name = glfw.get_key_name(key, scancode) or ""
        if key in (glfw.KEY_ESCAPE, glfw.KEY_Q):
            glfw.set_window_should_close(handle, True)
        elif name in _VIEW_KEYS:
            v.view = _VIEW_KEYS[name]
        elif key == glfw.KEY_TAB:
            ids = sorted(v.scene.interpolator.buffers)
            if ids:
                i = ids.index(v.player) + 1 if v.player in ids else 1
                v.player = ids[i % len(ids)]
        elif key == glfw.KEY_I:
            v.scene.interpolator.toggle()
        elif key == glfw.KEY_F:
            v.auto_frame = True
        elif key == glfw.KEY_P:
            self._shot = Path(f"posecast_{time.strftime('%Y%m%d_%H%M%S')}.png")

    def _on_button(self, handle: Any, button: int, action: int, mods: int) -> None:
        if button == self.glfw.MOUSE_BUTTON_LEFT:
            self._drag = self.glfw.get_cursor_pos(handle) if action == self.glfw.PRESS \
                else None

    def _on_cursor(self, handle: Any, x: float, y: float) -> None:
        if self._drag is None or self.viewer is None:
            return
        dx, dy = x - self._drag[0], y - self._drag[1]
        self._drag = (x, y)
        orbit = self.viewer.orbit
        orbit.yaw -= 0.3 * dx
        orbit.pitch = min(max(orbit.pitch + 0.3 * dy, -5.0), 89.0)
        self.viewer.auto_frame = False

    def _on_scroll(self, handle: Any, dx: float, dy: float) -> None:
        if self.viewer is not None:
            self.viewer.orbit.distance = max(0.5, self.viewer.orbit.distance * 0.9 ** dy)
            self.viewer.auto_frame = False

    # ------------------------------------------------------------------ loop
    async def run(self, scene: SpectatorScene, fps: float = DEFAULT_FPS,
                  stop: asyncio.Event | None = None, view: ViewMode = ViewMode.ORBIT,
                  frames: int | None = None,
                  screenshot: str | Path | None = None,
                  marker: str | None = None) -> ViewerStats:
        """Draw ``scene`` at up to ``fps`` until the window closes, ``stop`` is set or
        ``frames`` frames were shown; ``screenshot``: save the last of ``frames`` there."""
        glfw = self.glfw
        w, h = self.framebuffer_size()
        renderer = Renderer(self.ctx, w, h, target=self.ctx.detect_framebuffer())
        viewer = self.viewer = Viewer(renderer, scene, view=view, marker=marker)
        viewer.warm_up()
        interval = 1.0 / fps
        next_t = now()
        try:
            while not self.should_close and not (stop is not None and stop.is_set()):
                if frames is not None and viewer.stats.frames >= frames:
                    break
                glfw.poll_events()
                size = self.framebuffer_size()
                if size != (renderer.width, renderer.height):
                    renderer.width, renderer.height = size  # the screen resizes itself
                await scene.spectator.catch_up()  # the newest poses, not a backlog
                drawn = viewer.draw(now())
                last = frames is not None and viewer.stats.frames == frames - 1
                if self._shot is not None or (last and screenshot is not None):
                    path = self._shot or Path(str(screenshot))
                    Image.fromarray(np.ascontiguousarray(renderer.read()), "RGB").save(path)
                    self._shot = None
                glfw.swap_buffers(self.handle)
                self.ctx.finish()  # the frame is on screen only when the GPU is done
                viewer.presented(drawn, now())
                next_t = max(next_t + interval, now())
                await asyncio.sleep(max(next_t - now(), 0.0))
        finally:
            viewer.release()
            renderer.release()
        return viewer.stats

    def close(self) -> None:
        self.glfw.destroy_window(self.handle)
        self.glfw.terminate()


async def run_window_viewer(url: str, room: str, width: int = 1280, height: int = 720, *,
                            fps: float = DEFAULT_FPS, mode: Mode = Mode.INTERPOLATE,
                            view: ViewMode = ViewMode.ORBIT, name: str = "viewer",
                            max_rate_hz: float | None = None, token: str | None = None,
                            cafile: Path | None = None, frames: int | None = None,
                            screenshot: str | Path | None = None,
                            stop: asyncio.Event | None = None,
                            on_spectator: Callable[[Spectator], None] | None = None,
                            marker: str | None = None) -> ViewerStats:
    """``posecast view``: a window on ``room`` at ``url`` until it is closed, ``stop``
    is set, or ``frames`` frames were shown (``screenshot`` saves the last one).
    ``on_spectator`` gets the spectator before it connects (the CLI reports on it).

    Raises NoDisplayError (one line, pointing to --headless) where no window can be
    opened, SessionError if the server cannot be reached or goes away.
    """
    window = Window(width, height, f"posecast: {room} at {url}")
    spectator = ViewerSpectator(url, room, name, Interpolator(mode), max_rate_hz=max_rate_hz,
                                token=token, cafile=cafile)
    if on_spectator is not None:
        on_spectator(spectator)
    done = asyncio.Event()
    receiving = asyncio.create_task(spectator.run(stop=done), name="posecast-view")
    receiving.add_done_callback(lambda _: done.set())
    relay = None
    if stop is not None:
        relay = asyncio.create_task(stop.wait())
        relay.add_done_callback(lambda _: done.set())
    try:
        stats = await window.run(SpectatorScene(spectator), fps, stop=done, view=view,
                                 frames=frames, screenshot=screenshot, marker=marker)
    finally:
        done.set()
        if relay is not None:
            relay.cancel()
        window.close()
        await receiving  # raises its SessionError, if any
    return stats
