"""`posecast bench headset`: the headset's poses-to-submit on this machine, per eye size.

For each size (a fraction of a Vive's recommended 1512x1680 an eye): a server in this
process, ``others`` players replaying the built-in walk a few metres ahead, and a
headset player doing what ``play --hmd`` does (own body solved locally, the others
through its spectator connection in predict mode, the mirror, names and HUD, both eyes),
each frame finished on the GPU (glFinish) where a compositor's Submit would take it.
Without SteamVR the frames are paced by the player's samples (120 Hz), latest wins.

On a software renderer (llvmpipe, as here) the figure is the CPU's rasterizing; a GPU's
is left to a machine that has one (docs/headset.md).
"""

from __future__ import annotations

import asyncio
import sys
from collections.abc import Callable, Sequence

import numpy as np

from posecast.client.builtin import builtin_motion_path
from posecast.client.headset.displays import NullDisplay, SampleFeed
from posecast.client.headset.session import Headset
from posecast.client.headset.stereo import vive_setup
from posecast.client.session.player import Player
from posecast.client.sources.base import OffsetSource
from posecast.client.sources.bvh_source import BvhSource
from posecast.server.app import Session
from posecast.server.serving import run_server

WARMUP_FRAMES = 10  # shaders, levels of detail and the mirror's target are made first
JOIN_TIMEOUT_S = 60.0


async def _one_size(scale: float, frames: int, others: int) -> dict[str, object]:
    stop_server = asyncio.Event()
    ready: asyncio.Future[int] = asyncio.get_running_loop().create_future()
    server = asyncio.create_task(run_server("127.0.0.1", 0, Session(), stop_server,
                                            ready.set_result))
    port = await asyncio.wait_for(ready, JOIN_TIMEOUT_S)
    url = f"ws://127.0.0.1:{port}"
    stop = asyncio.Event()
    tasks = []
    for k in range(others):  # in a row 2.5 m ahead of the headset's T-pose, apart
        src = OffsetSource(BvhSource(builtin_motion_path(), loop=True,
                                     start_frame=40 * k), (1.2 * (k - others / 2), 2.5))
        tasks.append(asyncio.create_task(Player(url, "bench", f"other {k + 1}", src)
                                         .run(stop=stop)))
    source = BvhSource(builtin_motion_path(), loop=True)
    feed = SampleFeed()
    setup = vive_setup().scaled(scale)
    player = Player(url, "bench", "headset", source)
    headset = Headset(player, NullDisplay(feed, setup), feed, stop=stop,
                      frames=frames + WARMUP_FRAMES)
    try:
        async with headset:
            await player.run(stop=stop)
    finally:
        stop.set()
        await asyncio.gather(*tasks, return_exceptions=True)
        stop_server.set()
        await server
    stats = headset.stats
    row: dict[str, object] = {"scale": scale, "eye_size": [setup.width, setup.height],
                              "frames": max(stats.frames - WARMUP_FRAMES, 0),
                              "others": others}
    for stage, key in (("pose_to_submit", "pose_to_submit_ms"), ("frame", "frame_ms")):
        values = stats.latency.samples(stage)[WARMUP_FRAMES:] * 1e3 \
            if stage in stats.latency.stages else np.empty(0)
        row[key] = ({"p50": float(np.percentile(values, 50)),
                     "p99": float(np.percentile(values, 99))} if len(values) else {})
    drawn = stats.frames - WARMUP_FRAMES
    pts = stats.latency.samples("pose_to_submit")[WARMUP_FRAMES:] \
        if "pose_to_submit" in stats.latency.stages else np.empty(0)
    row["fps"] = float(drawn / pts.sum()) if drawn > 0 and pts.sum() > 0 else 0.0
    return row


def bench_headset(scales: Sequence[float] = (1.0, 0.5), frames: int = 120, others: int = 3,
                  progress: Callable[[str], None] | None = None) -> dict[str, object]:
    """One row per scale: poses-to-submit and frame time p50/p99 (ms)."""
    rows = []
    for scale in scales:
        if progress is not None:
            progress(f"headset at {scale:g} x 1512x1680 an eye: {frames} frames ...")
        rows.append(asyncio.run(_one_size(scale, frames, others)))
    return {"renderer": _renderer(), "rows": rows}


def _renderer() -> str:
    from posecast.client.viewer.renderer import create_headless_context

    ctx = create_headless_context()
    try:
        return str(ctx.info.get("GL_RENDERER", "?"))
    finally:
        ctx.release()


def format_headset_table(doc: dict[str, object]) -> str:
    rows = doc["rows"]
    assert isinstance(rows, list)
    lines = [f"headset frames on {doc['renderer']} (poses to submit: from the frame's "
             "poses to both eyes handed over)",
             f"{'eye size':>11}  {'frames':>6}  {'pose->submit p50':>16}  {'p99':>7}  "
             f"{'frame p50':>9}  {'p99':>7}"]
    for r in rows:
        w, h = r["eye_size"]
        pts, frame = r["pose_to_submit_ms"], r["frame_ms"]
        lines.append(f"{w:>5}x{h:<5}  {r['frames']:>6}  {pts.get('p50', 0):>13.1f} ms  "
                     f"{pts.get('p99', 0):>4.1f} ms  {frame.get('p50', 0):>6.1f} ms  "
                     f"{frame.get('p99', 0):>4.1f} ms")
    return "\n".join(lines)


def say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)
