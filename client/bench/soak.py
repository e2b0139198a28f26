"""`posecast bench soak --minutes M`: does the server hold steady over time?

A server process, N players replaying the built-in walk at 90 Hz (a process of their
own, as in the demo) and M headless spectators (here), for M minutes. Every few seconds:
the server's RSS (VmRSS of /proc/PID/status), its open file descriptors (/proc/PID/fd)
and the avatar-frames per second it solved, handed to spectators and dropped (its own
counters, asked for over its pipe). Reported: start, middle, end, min, max and the slope
of each over time (RSS per minute is the leak figure), and a PNG plot.
"""

from __future__ import annotations

import asyncio
import multiprocessing as mp
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from posecast.client.bench.demo import ROOM, run_players
from posecast.client.bench.target import TargetServer
from posecast.client.builtin import builtin_motion_path
from posecast.client.measure.plot import Panel, Series, line_chart
from posecast.client.session.spectator import Spectator
from posecast.client.sources.base import now

JOIN_TIMEOUT = 60.0
RSS_PLOT_SPAN_MB = 30.0  # the RSS budget: growth within it looks small
FIGURES = ("rss_mb", "fds", "solved_hz", "delivered_hz", "dropped_hz")


def _players_process(pipe: Connection, url: str, players: int, seconds: float) -> None:
    pipe.recv()  # go: the spectators are in the room
    stats = asyncio.run(run_players(url, players, seconds, builtin_motion_path()))
    pipe.send({"frames_sent": sum(p.frames_sent for p in stats),
               "errors": sum(sum(p.errors.values()) for p in stats)})


def slope_per_minute(ts: list[float], ys: list[float]) -> float:
    """Least-squares slope of ys over ts (seconds), per minute; 0 with fewer than 2."""
    n = len(ts)
    if n < 2:
        return 0.0
    mt, my = sum(ts) / n, sum(ys) / n
    var = sum((t - mt) ** 2 for t in ts)
    if var == 0.0:
        return 0.0
    return 60.0 * sum((t - mt) * (y - my) for t, y in zip(ts, ys, strict=True)) / var


def summarize(samples: list[dict[str, float]]) -> dict[str, dict[str, float]]:
    """Per figure: start, middle, end, min, max, slope per minute (all samples) and
    slope per minute over the second half (after any warm-up)."""
    out: dict[str, dict[str, float]] = {}
    if not samples:
        return out
    ts = [s["t_s"] for s in samples]
    half = len(samples) // 2
    for name in FIGURES:
        ys = [s[name] for s in samples]
        out[name] = {"start": ys[0], "middle": ys[half], "end": ys[-1], "min": min(ys),
                     "max": max(ys), "slope_per_min": round(slope_per_minute(ts, ys), 3),
                     "slope_per_min_second_half": round(
                         slope_per_minute(ts[half:], ys[half:]), 3)}
    return out


async def _soak(server: TargetServer, minutes: float, players: int, spectators: int,
                interval: float) -> dict[str, Any]:
    seconds = minutes * 60.0
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    watchers = [Spectator(server.url, ROOM, f"spectator {i + 1}") for i in range(spectators)]
    watching = [asyncio.create_task(w.run(stop=stop)) for w in watchers]
    ctx = mp.get_context("spawn")
    pipe, child = ctx.Pipe()
    process = ctx.Process(target=_players_process,
                          args=(child, server.url, players, seconds), daemon=True)
    process.start()
    samples: list[dict[str, float]] = []
    try:
        deadline = loop.time() + JOIN_TIMEOUT
        while any(w.session is None for w in watchers) and loop.time() < deadline:
            await asyncio.sleep(0.05)
        pipe.send("go")
        t_start = now()
        last_t, last = t_start, await loop.run_in_executor(None, server.metrics)
        while True:
            await asyncio.sleep(interval)
            if pipe.poll():  # the players are done: a partial interval would read low
                break
            t = now()
            metrics = await loop.run_in_executor(None, server.metrics)
            dt = max(t - last_t, 1e-9)

            def rate(key: str, metrics: dict[str, Any] = metrics,
                     last: dict[str, Any] = last, dt: float = dt) -> float:
                return round((int(metrics.get(key, 0)) - int(last.get(key, 0))) / dt, 1)

            samples.append({"t_s": round(t - t_start, 2), "rss_mb": round(server.rss_mb(), 1),
                            "fds": server.open_fds(), "solved_hz": rate("frames_solved"),
                            "delivered_hz": rate("frames_delivered"),
                            "dropped_hz": rate("frames_dropped")})
            last_t, last = t, metrics
        played = await asyncio.wait_for(loop.run_in_executor(None, pipe.recv), JOIN_TIMEOUT)
    finally:
        stop.set()
        results = await asyncio.gather(*watching, return_exceptions=True)
        process.join(5)
        if process.is_alive():
            process.kill()
    final = await loop.run_in_executor(None, server.metrics)
    failed = [r for r in results if isinstance(r, BaseException)]
    return {"minutes": minutes, "players": players, "spectators": spectators,
            "interval_s": interval, "frames_sent": played.get("frames_sent", 0),
            "frames_solved": final.get("frames_solved", 0),
            "frames_delivered": final.get("frames_delivered", 0),
            "frames_dropped": final.get("frames_dropped", 0),
            "frames_received": sum(w.stats.frames_received for w in watchers),
            "spectators_failed": len(failed),
            "summary": summarize(samples), "samples": samples}


def bench_soak(minutes: float, players: int = 8, spectators: int = 8,
               interval: float | None = None, solver: str = "analytic") -> dict[str, Any]:
    """The soak; ``interval``: seconds between samples (default: 5 s, or a twentieth of
    a run shorter than 100 s)."""
    step = interval if interval is not None else min(5.0, max(0.5, minutes * 60.0 / 20))
    with TargetServer(solver) as server:
        return asyncio.run(_soak(server, minutes, players, spectators, step))


def plot_soak(doc: dict[str, Any], path: Path) -> None:
    """RSS (and fds) and rates over time, as a PNG."""
    samples = doc["samples"]
    xs = [s["t_s"] / 60.0 for s in samples]
    line_chart(path, [
        Panel("server memory", "RSS MB", [Series("RSS", xs, [s["rss_mb"] for s in samples])],
              min_span=RSS_PLOT_SPAN_MB),
        Panel("server file descriptors", "open", [Series("fds", xs,
                                                         [s["fds"] for s in samples])]),
        Panel("avatar-frames per second", "Hz", [
            Series("solved", xs, [s["solved_hz"] for s in samples]),
            Series("delivered", xs, [s["delivered_hz"] for s in samples]),
            Series("dropped", xs, [s["dropped_hz"] for s in samples])]),
    ], x_label="minutes")


def format_soak_table(doc: dict[str, Any]) -> str:
    lines = [f"soak: {doc['players']} players, {doc['spectators']} spectators, "
             f"{doc['minutes']:g} min, a sample every {doc['interval_s']:g} s "
             f"({len(doc['samples'])} samples)",
             f"  {'figure':<13} {'start':>9} {'middle':>9} {'end':>9} {'min':>9} "
             f"{'max':>9} {'slope/min':>10} {'2nd half':>9}"]
    for name, s in doc["summary"].items():
        lines.append(f"  {name:<13} {s['start']:>9g} {s['middle']:>9g} {s['end']:>9g} "
                     f"{s['min']:>9g} {s['max']:>9g} {s['slope_per_min']:>10g} "
                     f"{s['slope_per_min_second_half']:>9g}")
    lines.append(f"  avatar-frames: sent {doc['frames_sent']}, solved {doc['frames_solved']}, "
                 f"delivered {doc['frames_delivered']}, dropped {doc['frames_dropped']}; "
                 f"spectators that failed: {doc['spectators_failed']}")
    return "\n".join(lines)
