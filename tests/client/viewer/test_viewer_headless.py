"""The headless viewer over real sockets: a server on 127.0.0.1, a player replaying the
built-in motion, and the viewer rendering PNGs through EGL; plus the no-display error."""

from __future__ import annotations

import asyncio
import os
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import TypeVar

import numpy as np
import pytest
from conftest import serving
from PIL import Image

from posecast.client.builtin import builtin_motion_path
from posecast.client.session.player import run_player
from posecast.client.session.spectator import Spectator
from posecast.client.sources.bvh_source import BvhSource
from posecast.client.viewer.core import ViewerStats
from posecast.client.viewer.headless import HeadlessStats, render_spectator, run_headless_viewer
from posecast.client.viewer.interpolation import Mode
from posecast.client.viewer.renderer import BACKGROUND
from posecast.client.viewer.window import NoDisplayError, check_display, run_window_viewer
from posecast.server.app import Session

T = TypeVar("T")
TIMEOUT = 5.0
W, H = 480, 270


@pytest.fixture(scope="module")
def session() -> Session:
    return Session()


def with_player(test: Callable[[str], Awaitable[T]], session: Session) -> T:
    """Serve on a free port, stream the built-in walk as one player, run ``test(url)``."""
    async def main() -> T:
        async with serving(session) as url:
            source = BvhSource(builtin_motion_path(), loop=True, rate_hz=90.0)
            player_stop = asyncio.Event()
            player = asyncio.create_task(run_player(url, "viewing", "walker", source,
                                                    stop=player_stop))
            try:
                return await asyncio.wait_for(test(url), 60)
            finally:
                player_stop.set()
                await asyncio.wait_for(player, TIMEOUT)
    return asyncio.run(main())


def avatar_pixels(path: Path) -> float:
    """Fraction of pixels that are neither background nor grey grid: the avatar."""
    img = np.asarray(Image.open(path).convert("RGB")).astype(int)
    bg = np.round(np.asarray(BACKGROUND) * 255)
    colourful = (img.max(axis=2) - img.min(axis=2)) > 60  # the avatar's colour, not greys
    return float((colourful & (np.abs(img - bg).max(axis=2) > 8)).mean())


@pytest.mark.parametrize("mode", [Mode.INTERPOLATE, Mode.LATEST, Mode.PREDICT])
def test_headless_viewer_renders_the_moving_avatar(egl: None, session: Session,
                                                   tmp_path: Path, mode: Mode) -> None:
    async def test(url: str) -> HeadlessStats:
        return await run_headless_viewer(url, "viewing", 6, tmp_path, W, H,
                                         interval_ms=50.0, mode=mode, timeout=30.0)

    t_start = time.monotonic()
    stats = with_player(test, session)
    seconds = time.monotonic() - t_start
    files = sorted(tmp_path.glob("frame_*.png"))
    assert len(files) == 6 and stats.frames == 6
    assert Image.open(files[0]).size == (W, H)
    assert all(avatar_pixels(f) > 0.002 for f in files)  # the avatar is in every frame
    first, last = (np.asarray(Image.open(f)) for f in (files[0], files[-1]))
    assert np.any(first != last)  # it moved
    latency = stats.latency.summary()
    assert "capture_to_render" in latency and "receive_to_render" in latency
    c2r = latency["capture_to_render"]
    # one process, one clock: every pose drawn was captured and presented within the
    # test (tens of milliseconds apart on an idle machine; interpolation adds its delay)
    assert 0.0 < c2r["p50"] <= c2r["p99"] < seconds * 1e3
    assert stats.spectator is not None
    assert stats.spectator.frames_received > 0


def test_a_viewer_reports_what_it_presented_to_the_servers_metrics(egl: None,
                                                                    tmp_path: Path) -> None:
    """Like the browser page and a headset, the desktop and headless viewers send
    ViewerReports: /metrics holds every spectator's presentation latency."""
    fresh = Session()  # counts from zero

    async def test(url: str) -> HeadlessStats:
        return await run_headless_viewer(url, "viewing", 30, None, W, H, interval_ms=50.0,
                                         timeout=30.0)

    stats = with_player(test, fresh)
    assert stats.frames == 30  # 1.5 s: reports go twice a second once the clock syncs
    m = fresh.metrics
    assert m.viewer_reports >= 1
    presented = m.viewer_latency.count("capture_to_presented")
    # each avatar-frame once, at its first presentation; no more than were received
    assert stats.spectator is not None
    assert 1 <= presented <= stats.spectator.frames_received
    # and avatars as it showed them, for the server's display error (measured a tick
    # later, once the room keeps a history: some may still wait at the stop)
    offered = sum(m.display_samples.values()) + len(fresh.display.reservoir.held)
    assert offered >= 1
    assert {v for v, _ in m.display_error.by_label} <= {"desktop"}
    assert {s.viewer for _, s in fresh.display.reservoir.held} <= {"desktop"}


def test_render_a_running_plain_spectator(egl: None, session: Session,
                                          tmp_path: Path) -> None:
    """``posecast demo --render DIR``: a Spectator already running, polled."""
    async def test(url: str) -> HeadlessStats:
        spectator = Spectator(url, "viewing", "demo spectator")
        stop = asyncio.Event()
        receiving = asyncio.create_task(spectator.run(stop=stop))
        try:
            return await render_spectator(spectator, tmp_path, frames=3, interval_ms=40.0,
                                          width=W, height=H, timeout=30.0)
        finally:
            stop.set()
            await receiving

    stats = with_player(test, session)
    files = sorted(tmp_path.glob("frame_*.png"))
    assert len(files) == 3 == stats.frames
    assert avatar_pixels(files[-1]) > 0.002


def test_no_display_error_points_to_headless(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr("sys.platform", "linux")
    with pytest.raises(NoDisplayError, match="--headless"):
        check_display()
    with pytest.raises(NoDisplayError, match="--headless") as info:
        asyncio.run(run_window_viewer("ws://127.0.0.1:9", "room"))
    assert "\n" not in str(info.value)  # one line


def test_window_shows_the_room(session: Session, tmp_path: Path) -> None:
    """The desktop window, where there is a display (e.g. under ``xvfb-run``)."""
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        pytest.skip("no display: run under xvfb-run to test the window")
    pytest.importorskip("glfw", reason="the window needs the glfw package")
    shot = tmp_path / "window.png"

    async def test(url: str) -> ViewerStats:
        return await run_window_viewer(url, "viewing", W, H, frames=10, screenshot=shot)

    stats = with_player(test, session)
    assert stats.frames == 10
    assert Image.open(shot).size == (W, H)
    assert avatar_pixels(shot) > 0.002
