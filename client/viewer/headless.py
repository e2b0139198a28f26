"""Headless viewing: render a room through EGL (no display, no GPU) to PNG files.

- ``run_headless_viewer(url, room, frames, out_dir)``: connect as a spectator, render
  ``frames`` frames (those that show at least one avatar) at ``interval_ms``, write them
  as PNGs, return the ``ViewerStats`` (``capture_to_render`` and ``receive_to_render``
  latencies, per-frame draw time) with the spectator's own stats attached.
- ``render_spectator(spectator, out_dir, ...)``: the same for a ``Spectator`` that is
  already running (``posecast demo --render DIR``), until ``stop`` is set.
- ``HeadlessViewerProcess``: ``run_headless_viewer`` in a process of its own. moderngl
  holds the GIL while the GPU (here: llvmpipe, on the CPU) draws, so a viewer in the demo's
  client process would stall the other spectators' receive loops for each frame and
  inflate their latency; in its own process it only costs CPU time.

The render loop runs on the event loop's thread (a GL context belongs to one thread,
and a worker thread would gain nothing while moderngl holds the GIL); the spectator
receives between frames. PNG encoding goes to a worker thread (Pillow's zlib releases
the GIL), with at most a few files pending.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import multiprocessing as mp
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from PIL import Image

from posecast.client.session.spectator import Spectator, SpectatorStats
from posecast.client.sources.base import now
from posecast.client.viewer.camera import OrbitCamera
from posecast.client.viewer.core import Viewer, ViewerStats
from posecast.client.viewer.interpolation import Interpolator, Mode
from posecast.client.viewer.renderer import Renderer
from posecast.client.viewer.scene import SpectatorScene, ViewerSpectator, ViewMode

DEFAULT_INTERVAL_MS = 1000.0 / 30.0
PNG_COMPRESS_LEVEL = 1  # zlib level: fast (~10 ms a 720p frame), files ~2x level 6's
_MAX_PENDING_FILES = 4


@dataclass
class HeadlessStats(ViewerStats):
    spectator: SpectatorStats | None = None


class _PngWriter:
    """Writes frames as ``frame_00000.png`` ... in a worker thread, a few at a time."""

    def __init__(self, out_dir: Path | None) -> None:
        self.out_dir = out_dir
        if out_dir is not None:
            out_dir.mkdir(parents=True, exist_ok=True)
        self._pool = concurrent.futures.ThreadPoolExecutor(1, "posecast-png")
        self._pending: list[concurrent.futures.Future[None]] = []

    async def save(self, pixels: NDArray[np.uint8], index: int) -> Path | None:
        if self.out_dir is None:
            return None
        path = self.out_dir / f"frame_{index:05d}.png"
        image = Image.fromarray(np.ascontiguousarray(pixels), "RGB")  # a copy: the
        # renderer's buffer is reused by the next frame
        self._pending.append(self._pool.submit(image.save, path,
                                               compress_level=PNG_COMPRESS_LEVEL))
        while len(self._pending) > _MAX_PENDING_FILES:
            await asyncio.wrap_future(self._pending.pop(0))
        return path

    async def close(self) -> None:
        for f in self._pending:
            await asyncio.wrap_future(f)
        self._pending.clear()
        self._pool.shutdown()


async def render_spectator(spectator: Spectator, out_dir: str | Path | None, *,
                           frames: int | None = None,
                           interval_ms: float = DEFAULT_INTERVAL_MS,
                           stop: asyncio.Event | None = None, width: int = 1280,
                           height: int = 720, mode: Mode = Mode.INTERPOLATE,
                           view: ViewMode = ViewMode.ORBIT, player: int | None = None,
                           orbit: OrbitCamera | None = None, renderer: Renderer | None = None,
                           wait_for_avatars: bool = True,
                           timeout: float | None = None,
                           marker: str | None = None) -> HeadlessStats:
    """Render ``spectator``'s room every ``interval_ms`` into ``out_dir`` (None: render
    and measure, write nothing) until ``frames`` frames are done, ``stop`` is set or
    ``timeout`` seconds pass. With ``wait_for_avatars`` a frame with no avatar is neither
    written nor counted. ``marker``: a joint name for view --marker (marker.py). Raises
    GLUnavailableError without a usable EGL."""
    own_renderer = renderer is None
    r = renderer or Renderer.standalone(width, height)
    scene = SpectatorScene(spectator)
    scene.interpolator.mode = mode
    viewer = Viewer(r, scene, orbit=orbit, view=view, player=player, marker=marker)
    viewer.warm_up()
    writer = _PngWriter(Path(out_dir) if out_dir is not None else None)
    stats = HeadlessStats()
    viewer.stats = stats
    interval = interval_ms / 1e3
    t_end = None if timeout is None else now() + timeout
    next_t = now()
    try:
        while not (stop is not None and stop.is_set()):
            if frames is not None and stats.frames >= frames:
                break
            if t_end is not None and now() >= t_end:
                break
            await scene.spectator.catch_up()  # the newest poses, not a backlog
            drawn = viewer.draw(now())
            pixels = r.read()  # waits for the GPU: the frame is complete
            t_present = now()
            if len(drawn.scene) or not wait_for_avatars:
                viewer.presented(drawn, t_present)
                path = await writer.save(pixels, stats.frames - 1)
                if path is not None:
                    stats.files.append(path)
            next_t = max(next_t + interval, now())  # behind: do not try to catch up
            await _sleep_until(next_t, stop)
    finally:
        await writer.close()
        viewer.release()
        if own_renderer:
            r.release()
            r.ctx.release()
    return stats


async def _sleep_until(t: float, stop: asyncio.Event | None) -> None:
    delay = t - now()
    if stop is None:
        await asyncio.sleep(max(delay, 0.0))
        return
    with contextlib.suppress(TimeoutError):  # the usual case: time is up, not stopped
        await asyncio.wait_for(stop.wait(), timeout=max(delay, 0.0))


async def run_headless_viewer(url: str, room: str, frames: int | None,
                              out_dir: str | Path | None, width: int = 1280,
                              height: int = 720, *, interval_ms: float = DEFAULT_INTERVAL_MS,
                              mode: Mode = Mode.INTERPOLATE, view: ViewMode = ViewMode.ORBIT,
                              player: int | None = None, name: str = "viewer",
                              max_rate_hz: float | None = None, token: str | None = None,
                              cafile: Path | None = None, timeout: float | None = None,
                              stop: asyncio.Event | None = None,
                              on_spectator: Callable[[Spectator], None] | None = None,
                              marker: str | None = None) -> HeadlessStats:
    """Join ``room`` at ``url`` as a spectator and render ``frames`` frames (None: until
    ``stop`` or ``timeout``) to PNGs in ``out_dir``; see ``render_spectator``.
    ``on_spectator`` gets the spectator before it connects (the CLI reports on it).

    Raises SessionError if the server cannot be reached or goes away, GLUnavailableError
    without EGL. The renderer is made before connecting, so a missing EGL fails fast.
    """
    renderer = Renderer.standalone(width, height)
    renderer.warm_up()  # before connecting: no frames queue up while shaders compile
    spectator = ViewerSpectator(url, room, name, Interpolator(mode), max_rate_hz=max_rate_hz,
                                token=token, cafile=cafile)
    if on_spectator is not None:
        on_spectator(spectator)
    done = asyncio.Event()
    receiving = asyncio.create_task(spectator.run(stop=done), name="posecast-view")
    receiving.add_done_callback(lambda _: done.set())  # the server went away: stop too
    relay = None
    if stop is not None:
        relay = asyncio.create_task(stop.wait())
        relay.add_done_callback(lambda _: done.set())
    try:
        stats = await render_spectator(spectator, out_dir, frames=frames,
                                       interval_ms=interval_ms, stop=done, width=width,
                                       height=height, mode=mode, view=view, player=player,
                                       renderer=renderer, timeout=timeout, marker=marker)
    finally:
        done.set()
        if relay is not None:
            relay.cancel()
        renderer.release()
        renderer.ctx.release()
        spectator_stats = await receiving  # raises its SessionError, if any
    stats.spectator = spectator_stats
    return stats


# ---------------------------------------------------------------------------- process


def _viewer_process(pipe: Connection, url: str, room: str, out_dir: str | None,
                    options: dict[str, Any]) -> None:
    async def main() -> HeadlessStats:
        stop = asyncio.Event()
        asyncio.get_running_loop().add_reader(pipe.fileno(), stop.set)
        pipe.send("ready")
        return await run_headless_viewer(url, room, None, out_dir, stop=stop, **options)

    try:
        stats = asyncio.run(main())
    except Exception as err:  # reported to the parent, which raises it
        pipe.send({"error": f"{type(err).__name__}: {err}"})
        return
    pipe.send({"json": stats.as_json(),
               "samples": {s: stats.latency.samples(s).copy() for s in stats.latency.stages},
               "files": [str(p) for p in stats.files]})


class ViewerProcessError(RuntimeError):
    """The headless viewer process failed (its error message is this one's)."""


class HeadlessViewerProcess:
    """``run_headless_viewer`` in its own process for the length of a ``with`` block.

    After the block: ``result["json"]`` (ViewerStats.as_json), ``result["samples"]``
    (stage -> seconds, e.g. ``capture_to_render``, to merge into a LatencyRecorder with
    ``add_values``) and ``result["files"]``. Inside an event loop use ``async with``: the
    waits for the process to start and to finish then do not block the loop (and the
    players and spectators it runs).
    """

    def __init__(self, url: str, room: str, out_dir: str | Path | None,
                 interval_ms: float = DEFAULT_INTERVAL_MS, width: int = 1280,
                 height: int = 720, mode: Mode = Mode.INTERPOLATE,
                 view: ViewMode = ViewMode.ORBIT, name: str = "viewer") -> None:
        ctx = mp.get_context("spawn")  # a fresh interpreter: no inherited loop or GL state
        self._pipe, child = ctx.Pipe()
        options = {"width": width, "height": height, "interval_ms": interval_ms,
                   "mode": mode, "view": view, "name": name}
        self._process = ctx.Process(
            target=_viewer_process, daemon=True,
            args=(child, url, room, None if out_dir is None else str(out_dir), options))
        self.result: dict[str, Any] = {}

    def __enter__(self) -> HeadlessViewerProcess:
        self._process.start()
        if not self._pipe.poll(60):
            self._process.kill()
            raise ViewerProcessError("the headless viewer did not start within 60 s")
        first = self._pipe.recv()
        if isinstance(first, dict) and "error" in first:
            raise ViewerProcessError(first["error"])
        return self

    def __exit__(self, *exc: object) -> None:
        self._pipe.send("stop")
        if self._pipe.poll(60):
            self.result = self._pipe.recv()
        self._process.join(10)
        if self._process.is_alive():
            self._process.kill()
        if "error" in self.result and exc[0] is None:
            raise ViewerProcessError(self.result["error"])

    async def __aenter__(self) -> HeadlessViewerProcess:
        return await asyncio.to_thread(self.__enter__)

    async def __aexit__(self, *exc: object) -> None:
        await asyncio.to_thread(self.__exit__, *exc)
