"""`posecast bench page`: what the browser page's playout costs a frame, per mode.

A server and N players walking (the demo's) on this machine, the page in headless
Chromium: each frame the page samples its playout and poses every avatar, and times that
(``window.posecast.poseMs``, the median of a mode's frames, and its p99). The modes are
measured in alternated turns on one page (zero-buffer, interpolate, predict, and again),
so that a busy minute weighs on all of them; each mode's cost against zero-buffer (the
page before it had a playout: the newest frame, posed when it is new) is taken within a
turn, then the median over the turns.
"""

from __future__ import annotations

import asyncio
import multiprocessing as mp
import statistics
import time
from collections.abc import Callable
from typing import Any

from posecast.client.bench.browser import CHROMIUM_ARGS, START_TIMEOUT_S, find_chromium
from posecast.client.bench.demo import ROOM, EmbeddedServer, run_players
from posecast.client.builtin import builtin_motion_path

MODES = ("zero-buffer", "interpolate", "predict")
PLAYERS_CAP_S = 3600.0  # the players walk until the bench stops them
VIEWPORT = {"width": 800, "height": 450}


def _walk(url: str, players: int) -> None:
    asyncio.run(run_players(url, players, PLAYERS_CAP_S, builtin_motion_path()))


def bench_page(avatars: int = 16, frames: int = 20, turns: int = 3,
               progress: Callable[[str], None] = lambda _: None) -> dict[str, Any]:
    """Per mode: each turn's median and p99 ms a frame to sample and pose ``avatars``
    avatars, over ``frames`` frames or more; their medians; and the median over the turns
    of each mode's cost minus zero-buffer's in the same turn."""
    chromium = find_chromium()
    from playwright.sync_api import sync_playwright

    runs: dict[str, list[tuple[float, float]]] = {m: [] for m in MODES}
    with EmbeddedServer() as server:
        walkers = mp.get_context("spawn").Process(target=_walk, args=(server.url, avatars),
                                                  daemon=True)
        walkers.start()
        try:
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
                page = browser.new_page(viewport=VIEWPORT)  # type: ignore[arg-type]
                page.goto(f"http://127.0.0.1:{server.port}/?room={ROOM}&mode={MODES[0]}")
                progress(f"waiting for {avatars} avatars drawn")
                _until(page, lambda s: s.get("drawn") == avatars, f"{avatars} avatars drawn")
                # once round the modes: a switch empties the page's window of frame times,
                # which still holds those drawn before the avatars were (next to nothing)
                _next_mode(page)
                for turn in range(turns):
                    for mode in MODES:
                        while _stats(page)["mode"] != mode:
                            _next_mode(page)
                        s = _until(page, lambda s: s["poseFrames"] >= frames
                                   and s["poseMs"] is not None, f"{frames} frames")
                        runs[mode].append((float(s["poseMs"]), float(s["poseMsP99"])))
                        progress(f"turn {turn + 1}/{turns} {mode}: {s['poseMs']:.2f} ms "
                                 f"(p99 {s['poseMsP99']:.2f})")
                browser.close()
        finally:
            walkers.terminate()
            walkers.join(10)
    return {"avatars": avatars, "frames": frames, "turns": turns,
            "modes": {m: {"median_ms": round(statistics.median(r[0] for r in runs[m]), 3),
                          "p99_ms": round(statistics.median(r[1] for r in runs[m]), 3),
                          "turns_ms": [round(r[0], 3) for r in runs[m]]} for m in MODES},
            "over_zero_buffer_ms": {
                m: round(statistics.median(a[0] - z[0] for a, z in zip(runs[m],
                                                                      runs[MODES[0]],
                                                                      strict=True)), 3)
                for m in MODES[1:]}}


def format_page_table(doc: dict[str, Any]) -> str:
    lines = [f"browser page, {doc['avatars']} avatars: ms a frame to sample the playout and "
             f"pose them ({doc['turns']} alternated turns of {doc['frames']}+ frames)",
             f"{'mode':<12} {'median':>8} {'p99':>8} {'over zero-buffer':>17}  turns"]
    for mode, m in doc["modes"].items():
        over = doc["over_zero_buffer_ms"].get(mode)
        lines.append(f"{mode:<12} {m['median_ms']:8.2f} {m['p99_ms']:8.2f} "
                     f"{'' if over is None else f'{over:+.2f}':>17}  "
                     + " ".join(f"{t:.2f}" for t in m["turns_ms"]))
    return "\n".join(lines)


def _next_mode(page: Any) -> None:
    before = _stats(page)["mode"]
    page.keyboard.press("KeyM")
    _until(page, lambda s: s["mode"] != before, "the next mode")


def _stats(page: Any) -> dict[str, Any]:
    # evaluate: the page's CSP forbids the eval that wait_for_function would need
    return dict(page.evaluate("() => ({...window.posecast})") or {})


def _until(page: Any, ok: Callable[[dict[str, Any]], bool], what: str) -> dict[str, Any]:
    deadline = time.monotonic() + START_TIMEOUT_S * 2
    while not ok(stats := _stats(page)):
        if time.monotonic() > deadline:
            raise RuntimeError(f"the page never got {what}: {stats}")
        page.wait_for_timeout(50)
    return stats
