"""The browser spectator in a real browser: Debian's Chromium, headless, driven by
playwright, against a real server on 127.0.0.1 whose players replay the built-in walk.
The page must draw both avatars skinned (their colours on screen), each name above its
avatar, the avatars moving between two screenshots, and the server's /metrics must then
hold the page's capture_to_presented; a device a player loses must be named under its
avatar's name and in the HUD while it is lost, and no longer once found. Every wait is
for a condition, with a generous bound only for failing; nothing asserts a duration.

POSECAST_SCREENSHOTS=DIR keeps the two screenshots there (docs/browser_spectator*.png
come from this test).
"""

from __future__ import annotations

import colorsys
import io
import json
import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from browser_room import LiveRoom, chromium_or_skip

from posecast.client.bench.browser import CHROMIUM_ARGS
from posecast.client.builtin import builtin_motion_path
from posecast.client.sources.bvh_source import BvhSource
from posecast.server.web import STATIC_DIR

WAIT_S = 90.0  # a bound for failing only: a loaded machine is slow, never this slow
VIEW_W, VIEW_H = 800, 450
AVATAR_FRAMES_APART = 45  # solved frames per avatar between the screenshots: 0.5 s of walk
# a pixel of an avatar: saturated (the palette's colours; grid, background, text are grey)
SATURATION = 60
# frames a mode's pose time is the median of: enough to see every mode pose and time all
# 16 avatars (the figure is `bench page`'s, with 20 and more turns)
POSE_FRAMES = 6
HUE_TOLERANCE_DEG = 20.0


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    chromium = chromium_or_skip()
    if not (STATIC_DIR / "index.html").exists():
        pytest.fail("server/static holds no built page: run make setup")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
        yield b
        b.close()


@pytest.fixture(scope="module")
def room() -> Iterator[LiveRoom]:
    with LiveRoom("lab", players=2) as r:
        yield r


class Page:
    """A page of the browser, with what it said on its console."""

    def __init__(self, browser: Any, url: str) -> None:
        self.page = browser.new_page(viewport={"width": VIEW_W, "height": VIEW_H})
        self.errors: list[str] = []
        self.page.on("console", lambda m: self.errors.append(m.text)
                     if m.type == "error" else None)
        self.page.on("pageerror", lambda e: self.errors.append(str(e)))
        self.page.goto(url)

    def stats(self) -> dict[str, Any]:
        # evaluate: the page's CSP forbids the eval that wait_for_function would need
        return dict(self.page.evaluate("() => ({...window.posecast})") or {})

    def until(self, what: str, ok: Callable[[dict[str, Any]], bool]) -> dict[str, Any]:
        deadline = time.monotonic() + WAIT_S
        while True:
            stats = self.stats()
            if ok(stats):
                return stats
            assert time.monotonic() < deadline, f"the page never got {what}: {stats}"
            time.sleep(0.05)

    def status(self) -> str:
        return str(self.page.evaluate("() => document.getElementById('status').textContent"))

    def hud(self) -> str:
        return str(self.page.evaluate("() => document.getElementById('hud').textContent"))

    def labels(self) -> list[dict[str, Any]]:
        """Each name label: the name, the line under it (its devices; "" when hidden),
        where it is and its colour."""
        return list(self.page.evaluate("""() => [...document.querySelectorAll('.name')].map(e => {
            const r = e.getBoundingClientRect();
            const devices = e.querySelector('.devices');
            return {text: e.querySelector('.who').textContent,
                    devices: devices.hidden ? '' : devices.textContent,
                    shown: getComputedStyle(e).display !== 'none',
                    left: r.left, right: r.right, top: r.top, bottom: r.bottom,
                    color: getComputedStyle(e).borderTopColor};
        })"""))

    def devices(self) -> dict[str, str]:
        """Each name label's device line, by name."""
        return {label["text"]: label["devices"] for label in self.labels()}

    def until_seen(self, what: str, read: Callable[[], Any],
                   ok: Callable[[Any], bool]) -> Any:
        deadline = time.monotonic() + WAIT_S
        while not ok(got := read()):
            assert time.monotonic() < deadline, f"the page never showed {what}: {got!r}"
            time.sleep(0.02)
        return got

    def shot(self) -> np.ndarray:
        from PIL import Image

        png = self.page.screenshot()
        return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)

    def steady_shot(self) -> tuple[np.ndarray, list[dict[str, Any]]]:
        """A screenshot with both names in view, and where they were: taken paused (Space
        freezes the page's view; a screenshot takes a second under llvmpipe, and a walker
        moves 50-90 px meanwhile), again a few frames later while a name is out of view
        (a walker looping back 3.6 m, the camera following)."""
        deadline = time.monotonic() + WAIT_S
        while True:
            self.page.keyboard.press("Space")
            self.until("paused", lambda s: s["paused"])
            before = self.labels()
            image = self.shot()
            after = self.labels()
            self.page.keyboard.press("Space")
            self.until("going on", lambda s: not s["paused"])
            assert before == after  # paused: nothing moved
            if all(in_view(label) for label in after):
                return image, after
            assert time.monotonic() < deadline, f"names never in view: {after}"
            mark = self.stats()["framesPresented"]
            self.until("frames", lambda s, mark=mark: s["framesPresented"] >= mark + 4)

    def close(self) -> None:
        self.page.close()


def in_view(label: dict[str, Any]) -> bool:
    return bool(label["shown"] and label["left"] >= 0 and label["right"] <= VIEW_W
                and label["top"] >= 0 and label["bottom"] <= VIEW_H)


def hue(rgb: np.ndarray) -> np.ndarray:
    """Hue in degrees of (..., 3) colours 0-255."""
    r, g, b = (rgb[..., i] / 255.0 for i in range(3))
    mx, mn = np.maximum(np.maximum(r, g), b), np.minimum(np.minimum(r, g), b)
    d = np.where(mx - mn > 0, mx - mn, 1.0)
    h = np.where(mx == r, ((g - b) / d) % 6, np.where(mx == g, (b - r) / d + 2, (r - g) / d + 4))
    return 60.0 * h


def avatar_pixels(image: np.ndarray, color: str) -> np.ndarray:
    """Where the avatar of a label's colour ('rgb(r, g, b)') is drawn: saturated pixels of
    its hue (the lighting changes brightness, not hue)."""
    rgb = [int(v) / 255 for v in color.removeprefix("rgb(").rstrip(")").split(",")]
    want = 360.0 * colorsys.rgb_to_hsv(*rgb)[0]
    saturated = image.max(axis=2) - image.min(axis=2) > SATURATION
    off = np.abs((hue(image) - want + 180.0) % 360.0 - 180.0)
    return saturated & (off < HUE_TOLERANCE_DEG)


def test_the_page_draws_names_and_moves_every_avatar_and_reports_it(
        browser: Any, room: LiveRoom) -> None:
    page = Page(browser, f"{room.http}/?room={room.room}")
    try:
        first = page.until("both avatars drawn", lambda s: s.get("drawn") == 2)
        load_ms = 1e3 * first["firstAvatarS"] - page.page.evaluate("performance.timeOrigin")
        print(f"\npage load to both avatars drawn: {load_ms:.0f} ms")
        # a few frames in, so that the camera has framed them
        page.until("frames", lambda s: s["framesPresented"] >= first["framesPresented"] + 8)
        a, labels = page.steady_shot()
        check_named_avatars(a, labels)
        # the second picture: after half a second more of the walk has been solved, a
        # frame received since then on the screen
        solved = solved_frames(room)
        while solved_frames(room) < solved + 2 * AVATAR_FRAMES_APART:
            time.sleep(0.1)
        mark = page.stats()
        page.until("newer frames", lambda s: s["framesReceived"] > mark["framesReceived"]
                   and s["framesPresented"] >= mark["framesPresented"] + 2)
        b, labels_b = page.steady_shot()
        check_named_avatars(b, labels_b)
        moved = check_moved(a, b, labels)
        keep(a, b)
        # the page reports what it presented; /metrics shows it beside the server's stages
        page.until("a report sent", lambda s: s["reportsSent"] >= 1)
        deadline = time.monotonic() + WAIT_S
        while (count := scraped_stage(room, "capture_to_presented")[0]) == 0:
            assert time.monotonic() < deadline, "no report reached the server"
            time.sleep(0.2)
        count, p50, p99 = scraped_stage(room, "capture_to_presented")
        assert count >= 1 and 0 < p50 <= p99 < 10.0
        _, r50, r99 = scraped_stage(room, "capture_to_spectator")
        hud = page.page.evaluate("() => document.getElementById('hud').textContent")
        print(f"moved: {moved:.0%} of the avatars' pixels; /metrics, {count} frames: "
              f"capture_to_spectator p50 {1e3 * r50:.1f} ms p99 {1e3 * r99:.1f} ms, "
              f"capture_to_presented p50 {1e3 * p50:.1f} ms p99 {1e3 * p99:.1f} ms; "
              f"HUD:\n{hud}")
        assert page.stats()["badMessages"] == 0
        assert page.errors == []
    finally:
        page.close()


def test_a_lost_device_is_named_under_its_avatar_and_in_the_hud(browser: Any) -> None:
    # player 2's left foot is lost for a second, found for one, and so on
    with LiveRoom("drops", players=2, lose={1: ("left_foot",)}) as room:
        page = Page(browser, f"{room.http}/?room={room.room}")
        try:
            page.until("both avatars drawn", lambda s: s.get("drawn") == 2)
            whole = f"{len(walk_devices())} devices"
            lost = page.until_seen("player 2's foot lost", page.devices,
                                   lambda d: "lost" in d.get("player 2", ""))
            assert lost == {"player 1": whole, "player 2": f"{whole} — lost: left_foot"}
            hud = page.until_seen("the loss in the HUD", page.hud,
                                  lambda h: "player 2" in h)
            assert hud.splitlines()[-1] == f"player 2 ({whole}): lost left_foot", hud
            found = page.until_seen("player 2's foot found", page.devices,
                                    lambda d: d.get("player 2") == whole)
            assert found == {"player 1": whole, "player 2": whole}
            page.until_seen("no loss in the HUD", page.hud, lambda h: "lost" not in h)
            assert page.stats()["badMessages"] == 0
            assert page.errors == []
        finally:
            page.close()


def walk_devices() -> tuple[str, ...]:
    """The devices the built-in walk's players have (their avatars' tracker set)."""
    source = BvhSource(builtin_motion_path())
    try:
        return source.calibration().roles
    finally:
        source.close()


def check_named_avatars(image: np.ndarray, labels: list[dict[str, Any]]) -> None:
    """Both players' names are shown, and below each is its avatar, drawn in its colour."""
    assert sorted(label["text"] for label in labels) == ["player 1", "player 2"]
    for label in labels:
        assert in_view(label), label
        mine = avatar_pixels(image, label["color"])
        x0, x1 = int(label["left"]) - 80, int(label["right"]) + 80
        y0 = int(label["bottom"])
        below = mine[y0:y0 + VIEW_H // 2, max(x0, 0):x1]
        # a body in view: hundreds of pixels of its colour (~1,500 at this size) below
        assert below.sum() > 400, (label, int(below.sum()), int(mine.sum()))
        above = mine[:max(int(label["top"]), 0), max(x0, 0):x1]
        assert above.sum() < below.sum() / 10, label  # the name is above the body


def check_moved(a: np.ndarray, b: np.ndarray, labels: list[dict[str, Any]]) -> float:
    """The avatars' pixels changed between the pictures: their share that did."""
    where = np.zeros(a.shape[:2], dtype=bool)
    for label in labels:
        where |= avatar_pixels(a, label["color"]) | avatar_pixels(b, label["color"])
    changed = np.abs(a - b).sum(axis=2) > 60
    share = float(changed[where].mean())
    # a still avatar changes none of its pixels; a walking one, followed by the camera,
    # 25-90% of them half a stride later
    assert share > 0.05, share
    return share


def solved_frames(room: LiveRoom) -> float:
    return room.metrics()["posecast_frames_solved_total"][()]


def scraped_stage(room: LiveRoom, stage: str) -> tuple[float, float, float]:
    """A stage of /metrics' latency histogram: count, and p50 and p99 read off its
    buckets (seconds, linear within a bucket, as Prometheus' histogram_quantile)."""
    samples = room.metrics()["posecast_latency_seconds_bucket"]
    buckets = sorted((float(dict(labels)["le"]), n) for labels, n in samples.items()
                     if dict(labels)["stage"] == stage)
    count = buckets[-1][1]

    def quantile(q: float) -> float:
        rank, low, below = q * count, 0.0, 0.0
        for le, n in buckets:
            if n >= rank:
                return le if le == float("inf") else low + (le - low) * (rank - below) / (
                    (n - below) or 1)
            low, below = le, n
        return float("nan")

    return count, quantile(0.5), quantile(0.99)


def keep(*images: np.ndarray) -> None:
    folder = os.environ.get("POSECAST_SCREENSHOTS")
    if not folder:
        return
    from PIL import Image

    for i, image in enumerate(images):
        name = "browser_spectator.png" if i == 0 else f"browser_spectator_{i + 1}.png"
        Image.fromarray(image.astype(np.uint8)).save(Path(folder) / name, optimize=True)


def test_an_empty_room_a_bad_name_and_no_name_each_say_so(
        browser: Any, room: LiveRoom) -> None:
    page = Page(browser, f"{room.http}/?room=nobody-here")
    try:
        page.until("joined", lambda s: s.get("phase") == "joined")
        deadline = time.monotonic() + WAIT_S
        while "has no players yet" not in page.status():
            assert time.monotonic() < deadline, page.status()
            time.sleep(0.05)
        assert page.stats()["drawn"] == 0 and page.labels() == []
        assert page.errors == []
    finally:
        page.close()
    time.sleep(1.0)  # /metrics is made again once its last is a second old
    connections = room.metrics()["posecast_connections_total"][()]
    page = Page(browser, f"{room.http}/?room=no%20such%20room!")
    try:
        page.until("its refusal", lambda s: s.get("phase") == "bad room")
        assert page.status().startswith('Cannot join "no such room!": room names are 1-64')
        time.sleep(1.0)  # /metrics is made again once its last is a second old
        assert room.metrics()["posecast_connections_total"][()] == connections  # none tried
        assert page.errors == []
    finally:
        page.close()
    page = Page(browser, room.http + "/")
    try:
        page.until("its question", lambda s: s.get("phase") == "no room")
        assert "Which room?" in page.status()
        assert page.page.evaluate("() => !!document.querySelector('#status input[name=room]')")
    finally:
        page.close()


def test_bench_page_times_each_playout_mode_at_16_avatars() -> None:
    """`posecast bench page`: sampling and posing 16 avatars in each mode, on one page in
    alternated turns, against zero-buffer (the page's drawing before it had a playout).
    What it costs is the bench's to say (a timing on a shared machine is no test's): here,
    that every mode posed all 16 avatars for its frames and timed them, printed."""
    chromium_or_skip()
    done = subprocess.run([sys.executable, "-m", "posecast.client.cli", "bench", "page",
                           "--avatars", "16", "--frames", str(POSE_FRAMES), "--turns", "1",
                           "--json"], capture_output=True, text=True, timeout=600,
                          env={**os.environ, "PYTHONWARNINGS": "ignore"})
    assert done.returncode == 0, done.stderr
    doc = json.loads(done.stdout)
    from posecast.client.bench.page import format_page_table

    print("\n" + format_page_table(doc))
    assert doc["avatars"] == 16 and doc["frames"] == POSE_FRAMES
    assert set(doc["modes"]) == {"zero-buffer", "interpolate", "predict"}
    for m in doc["modes"].values():
        # timed: a p99 above zero (a median may round to 0 where the page's clock is
        # coarse and posing is fast)
        assert len(m["turns_ms"]) == 1 and 0.0 <= m["median_ms"] <= m["p99_ms"]
        assert m["p99_ms"] > 0.0
    assert set(doc["over_zero_buffer_ms"]) == {"interpolate", "predict"}
    # one line per turn and mode as it ends
    assert done.stderr.count("turn 1/1") == 3
