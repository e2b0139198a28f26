"""Where a headset's frames go, and what paces them.

A display hands the frame loop each frame's poses (``next_frame``, which blocks until the
frame is due: the compositor's pacing, never a sleep) and takes the two eyes' textures
(``present``), returning when they were handed over:

- ``CompositorDisplay``: SteamVR (``compositor.Compositor``): WaitGetPoses, Submit.
- ``FileDisplay``: no SteamVR (``play --hmd-out DIR``): each new sample of the player's
  pose source is a frame, its head device standing in for the headset; both eyes are
  written side by side to a PNG file.
- ``NullDisplay``: the same frames, drawn and waited for but kept nowhere (``bench
  headset``).

Without a compositor, "handed over" is when the GPU has finished the frame (glFinish):
a compositor's Submit would have to wait for that too before it could show it.
"""

from __future__ import annotations

import concurrent.futures
import ctypes
import ctypes.util
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import moderngl
import numpy as np
from numpy.typing import NDArray
from PIL import Image

from posecast.client.headset.compositor import Compositor
from posecast.client.headset.stereo import (
    EyeSetup,
    heading_of,
    headset_from_device,
    pose_matrix,
)
from posecast.client.sources.base import DeviceSample, now
from posecast.solver import rotations as R

Array = NDArray[np.float64]
PNG_COMPRESS_LEVEL = 1  # fast: the frame loop must not wait on zlib
MAX_PENDING_FILES = 3
WAIT_SLICE_S = 0.1  # how often a wait for the next sample looks at ``stop``


@dataclass(frozen=True)
class HeadsetFrame:
    """The poses one frame is drawn with: when they were taken (``now()`` clock), the
    headset (4x4, headset to world; None while it is not tracked) and every device
    with a role (None where the display has no body poses)."""

    t_poses: float
    head: Array | None
    sample: DeviceSample | None


class Display(Protocol):
    setup: EyeSetup

    def next_frame(self, stop: threading.Event) -> HeadsetFrame | None:
        """The next frame's poses once it is due; None when ``stop`` was set or the
        display has nothing more (``ended``)."""
        ...

    def present(self, ctx: moderngl.Context, textures: tuple[moderngl.Texture,
                                                              moderngl.Texture]) -> float:
        """Hand both eyes over; when that was done (``now()`` clock)."""
        ...

    @property
    def ended(self) -> bool:
        ...

    def close(self) -> None:
        ...


# ------------------------------------------------------------------------- SteamVR
class CompositorDisplay:
    """Frames paced and shown by SteamVR; ``body`` maps the compositor's pose array to
    the player's devices (``OpenVRSource.sample_of``), None for no own body."""

    def __init__(self, compositor: Compositor,
                 body: Callable[[NDArray[np.void], float], DeviceSample] | None) -> None:
        self.compositor = compositor
        self.setup = compositor.setup()
        self.body = body
        self.ended = False

    def next_frame(self, stop: threading.Event) -> HeadsetFrame | None:
        while not stop.is_set():
            if self.compositor.wait_poses():
                t = now()
                sample = self.body(self.compositor.poses, t) if self.body else None
                return HeadsetFrame(t, self.compositor.head(), sample)
        return None

    def present(self, ctx: moderngl.Context, textures: tuple[moderngl.Texture,
                                                              moderngl.Texture]) -> float:
        gl_call("glFlush", ctx.finish)  # openvr.h: the driver starts on the frame now
        self.compositor.submit((textures[0].glo, textures[1].glo))
        return now()

    def close(self) -> None:
        pass


# ------------------------------------------------------------------------- the source
class SampleFeed:
    """The player's newest sample, from the session's thread to the frame loop's
    (latest wins), and the T-pose the headset turn is taken from."""

    def __init__(self) -> None:
        self._ready = threading.Condition()
        self._sample: DeviceSample | None = None
        self._taken: DeviceSample | None = None
        self.turn = R.IDENTITY.copy()  # headset_from_device of the last T-pose
        self.closed = False

    def put(self, sample: DeviceSample) -> None:
        with self._ready:
            self._sample = sample
            self._ready.notify()

    def put_tpose(self, sample: DeviceSample) -> None:
        if "head" in sample.roles and "left_hand" in sample.roles \
                and "right_hand" in sample.roles:
            pos = {r: sample.positions[i] for i, r in enumerate(sample.roles)}
            self.turn = headset_from_device(sample.rotations[sample.roles.index("head")],
                                            heading_of(pos))

    def close(self) -> None:
        with self._ready:
            self.closed = True
            self._ready.notify()

    def take(self, stop: threading.Event) -> DeviceSample | None:
        """The next sample newer than the last taken; None once stopped or closed."""
        with self._ready:
            while not stop.is_set():
                if self._sample is not None and self._sample is not self._taken:
                    self._taken = self._sample
                    return self._sample
                if self.closed:
                    return None
                self._ready.wait(WAIT_SLICE_S)
        return None

    def head(self, sample: DeviceSample) -> Array | None:
        """The headset the sample's head device stands for (4x4), None without one."""
        if "head" not in sample.roles:
            return None
        i = sample.roles.index("head")
        return pose_matrix(sample.positions[i], R.mul(sample.rotations[i], self.turn))


class FileDisplay:
    """Frames from the player's samples, both eyes side by side into PNG files
    (``frame_00000.png`` ...) in ``out_dir``; None: into no file (``NullDisplay``)."""

    def __init__(self, feed: SampleFeed, setup: EyeSetup, out_dir: Path | None) -> None:
        self.feed = feed
        self.setup = setup
        self.out_dir = out_dir
        if out_dir is not None:
            out_dir.mkdir(parents=True, exist_ok=True)
        self.files: list[Path] = []
        self._pool = concurrent.futures.ThreadPoolExecutor(1, "posecast-hmd-png")
        self._pending: list[concurrent.futures.Future[None]] = []

    @property
    def ended(self) -> bool:
        return self.feed.closed

    def next_frame(self, stop: threading.Event) -> HeadsetFrame | None:
        sample = self.feed.take(stop)
        if sample is None:
            return None
        # the poses count from when the loop has them, as a compositor's do from
        # WaitGetPoses: what the loop adds, not how long the sample waited for it
        return HeadsetFrame(now(), self.feed.head(sample), sample)

    def present(self, ctx: moderngl.Context, textures: tuple[moderngl.Texture,
                                                              moderngl.Texture]) -> float:
        gl_finish(ctx)
        t = now()
        if self.out_dir is not None:
            pixels = side_by_side(textures)
            path = self.out_dir / f"frame_{len(self.files):05d}.png"
            self.files.append(path)
            self._pending.append(self._pool.submit(
                Image.fromarray(pixels, "RGB").save, path, compress_level=PNG_COMPRESS_LEVEL))
            while len(self._pending) > MAX_PENDING_FILES:
                self._pending.pop(0).result()
        return t

    def close(self) -> None:
        for f in self._pending:
            f.result()
        self._pending.clear()
        self._pool.shutdown()


def NullDisplay(feed: SampleFeed, setup: EyeSetup) -> FileDisplay:  # noqa: N802
    """Frames drawn and finished, written nowhere (``bench headset``)."""
    return FileDisplay(feed, setup, None)


def side_by_side(textures: tuple[moderngl.Texture, moderngl.Texture]) -> NDArray[np.uint8]:
    """Both eyes' textures as one RGB image, left eye on the left, top row first."""
    eyes = []
    for tex in textures:
        w, h = tex.size
        raw = np.frombuffer(tex.read(alignment=1), np.uint8).reshape(h, w, tex.components)
        eyes.append(raw[::-1, :, :3])
    return np.ascontiguousarray(np.concatenate(eyes, axis=1))


# moderngl's calls hold the GIL; the driver's own through ctypes do not, so the
# session's thread runs while a software rasterizer finishes the frame
_GL: dict[str, Callable[[], None] | None] = {}
_GL_LOCK = threading.Lock()


def gl_finish(ctx: moderngl.Context) -> None:
    """Wait for the GPU to finish the current context's work, without the GIL."""
    gl_call("glFinish", ctx.finish)


def gl_call(name: str, fallback: Callable[[], None]) -> None:
    """Call the GL function ``name`` (no arguments) of the current context through
    ctypes; ``fallback`` where no GL library can be loaded."""
    with _GL_LOCK:
        if name not in _GL:
            _GL[name] = _load_gl(name)
    fn = _GL[name]
    (fn or fallback)()


def _load_gl(name: str) -> Callable[[], None] | None:
    for lib in ("OpenGL", "GL"):  # GLVND's dispatch library first: it follows EGL
        path = ctypes.util.find_library(lib)
        if path is None:
            continue
        try:
            fn = getattr(ctypes.CDLL(path), name)
        except (OSError, AttributeError):
            continue
        fn.restype, fn.argtypes = None, []
        return fn
    return None
