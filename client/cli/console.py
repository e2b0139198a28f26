"""What `posecast play` and `posecast view` tell the person who runs them.

Where they joined, that a viewer waits for players, a progress line while a player
streams, a summary at the end, and Ctrl-C (SIGINT) or SIGTERM as a clean stop that still
prints the summary. Status goes to stderr: one line redrawn in place on a terminal, plain
lines at most every PLAIN_EVERY_S seconds elsewhere (a log file must not fill up);
summaries go to stdout.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import signal
import sys
import time
from collections.abc import Coroutine
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO, TypeVar

if TYPE_CHECKING:  # play must not load the viewer's GL modules
    from posecast.client.headset.view import HeadsetStats
    from posecast.client.session.player import Player, PlayerStats
    from posecast.client.session.spectator import Spectator, SpectatorStats
    from posecast.client.viewer.core import ViewerStats

T = TypeVar("T")

REFRESH_S = 1.0  # a terminal's progress line changes this often
PLAIN_EVERY_S = 5.0  # at most one progress line this often when stderr is not a terminal
WAITING_EVERY_S = 10.0  # a viewer of an empty room says it still waits this often
POLL_S = 0.05  # how often the reporters look whether the session has opened
STOP_GRACE_S = 3.0  # after Ctrl-C, how long a command may take to end on its own


class StatusLine:
    """Messages and a progress line on ``stream`` (stderr): on a terminal the progress
    line is redrawn in place, elsewhere it is printed at most every ``plain_every`` s."""

    def __init__(self, prefix: str, stream: TextIO | None = None,
                 plain_every: float = PLAIN_EVERY_S) -> None:
        self.prefix = prefix
        self.stream = stream or sys.stderr
        self.live = self.stream.isatty()
        self.plain_every = plain_every
        self._drawn = 0  # characters of the live line on screen
        self._printed_at = -math.inf

    def say(self, text: str) -> None:
        """A line of its own (the live line, if any, is cleared first)."""
        self.clear()
        self.stream.write(f"{self.prefix}: {text}\n")
        self.stream.flush()

    def progress(self, text: str, now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        line = f"{self.prefix}: {text}"
        if self.live:
            self.stream.write("\r" + line.ljust(self._drawn))
            self._drawn = len(line)
        elif now - self._printed_at >= self.plain_every:
            self._printed_at = now
            self.stream.write(line + "\n")
        else:
            return
        self.stream.flush()

    def clear(self) -> None:
        if self._drawn:
            self.stream.write("\r" + " " * self._drawn + "\r")
            self.stream.flush()
            self._drawn = 0


# --------------------------------------------------------------------------- play
async def report_player(player: Player, status: StatusLine, source: str) -> None:
    """Say where the player joined, then a progress line until cancelled."""
    while player.session is None:
        await asyncio.sleep(POLL_S)
    hello = player.hello
    avatar = player.stats.avatar_id
    status.say(f"joined room {hello.room!r} on {player.url} as {hello.display_name!r}"
               + (f" (avatar {avatar})" if avatar is not None else "")
               + f", streaming {source} at {player.source.rate_hz:g} Hz; Ctrl-C stops")
    t_last, sent_last = time.monotonic(), player.stats.frames_sent
    while True:
        await asyncio.sleep(REFRESH_S)
        t, stats = time.monotonic(), player.stats
        rate = (stats.frames_sent - sent_last) / (t - t_last) if t > t_last else 0.0
        t_last, sent_last = t, stats.frames_sent
        errors = sum(stats.errors.values())
        status.progress(f"sent {stats.frames_sent} frames, {rate:.1f} frames/s, "
                        f"{stats.seconds:.0f} s, {len(stats.devices)} devices"
                        + (f", lost now: {', '.join(stats.lost_now)}" if stats.lost_now
                           else "")
                        + (f", losses {sum(stats.losses.values())}" if stats.losses else "")
                        + (f", {errors} server errors (last: {stats.last_error})"
                           if errors else ""), t)


def player_summary(stats: PlayerStats) -> str:
    rate = stats.frames_sent / stats.seconds if stats.seconds > 0 else 0.0
    lost = ", ".join(f"{role} {stats.losses[role]}x ({stats.lost_frames[role]} frames)"
                     for role in stats.devices if stats.losses[role])
    return (f"sent {stats.frames_sent} frames in {stats.seconds:.1f} s ({rate:.1f} frames/s)"
            f" from {len(stats.devices)} devices ({', '.join(stats.devices)})"
            + (f"; lost: {lost}" if lost else "; no device lost")
            + (f"; server errors: {dict(stats.errors)}" if stats.errors else ""))


def headset_summary(stats: HeadsetStats, out_dir: Path | None) -> str:
    """One line on what the headset showed, with its poses-to-submit latency."""
    summary = stats.latency.summary().get("pose_to_submit")
    timing = (f"; pose to submit p50 {summary['p50']:.1f} ms, p99 "
              f"{summary['p99']:.1f} ms" if summary else "")
    errors = (f"; compositor refused {sum(stats.errors.values())} calls "
              f"({', '.join(sorted(stats.errors))})" if stats.errors else "")
    files = f"; written to {out_dir}/" if out_dir is not None and stats.frames else ""
    return (f"headset: {stats.frames} frames, {stats.width}x{stats.height} an eye"
            f"{timing}{errors}{files}")


# --------------------------------------------------------------------------- view
async def report_spectator(spectator: Spectator, status: StatusLine) -> None:
    """Say where the viewer joined; while the room shows nobody, that it waits (again
    every WAITING_EVERY_S); and how many players it shows when that changes."""
    while spectator.session is None:
        await asyncio.sleep(POLL_S)
    room, url = spectator.hello.room, spectator.url
    status.say(f"joined room {room!r} on {url} as a spectator; Ctrl-C stops")
    shown: int | None = None
    waiting_said = -math.inf
    reconnects = spectator.stats.reconnects

    def say_players(players: int) -> None:
        status.say(f"{players} player{'s' if players != 1 else ''} in room {room!r}")

    try:
        while True:
            players = len(spectator.latest)
            t = time.monotonic()
            if spectator.stats.reconnects != reconnects:  # a new session: say the room again
                reconnects, shown = spectator.stats.reconnects, None
            if players == 0 and t - waiting_said >= WAITING_EVERY_S:
                waiting_said = t
                status.say(f"waiting for players in room {room!r} on {url} "
                           f"(nobody is playing there yet; room names are case-sensitive)")
            elif players and players != shown:
                waiting_said = -math.inf
                say_players(players)
            shown = players
            await asyncio.sleep(POLL_S)
    finally:
        # a short view (--frames N) can end between two looks: its log still names
        # the players it showed
        players = len(spectator.latest)
        if players and players != shown:
            say_players(players)


def view_summary(viewer: ViewerStats | None, spectator: SpectatorStats | None,
                 out: Path | None) -> list[str]:
    """Round figures for people: counts, rates, latencies in ms with 2 decimals."""
    lines = []
    if spectator is not None:
        rate = spectator.frames_received / spectator.seconds if spectator.seconds > 0 else 0.0
        lines.append(f"received {spectator.frames_received} avatar-frames in "
                     f"{spectator.seconds:.1f} s ({rate:.1f}/s)")
    if viewer is not None:
        frame = viewer.frame_ms()
        lines.append(f"drew {viewer.frames} frames" + (
            f" (draw time p50 {frame['p50']:.2f} ms, p99 {frame['p99']:.2f} ms)"
            if frame else ""))
        for stage, p in viewer.latency.summary().items():
            lines.append(f"{stage}: p50 {p['p50']:.2f} ms, p99 {p['p99']:.2f} ms")
        if out is not None:
            written = len(viewer.files)
            lines.append(f"wrote {written} frames to {out}" if written
                         else f"wrote no frames to {out}: no player was seen")
    return lines


# --------------------------------------------------------------------------- signals
async def run_until_signal(main: Coroutine[Any, Any, T], stop: asyncio.Event,
                           grace: float = STOP_GRACE_S) -> tuple[T | None, int]:
    """Run ``main``; SIGINT or SIGTERM sets ``stop``, for ``main`` to end on its own and
    return what it did. If it has not ended ``grace`` s later (it was connecting, say),
    or at a second signal, it is cancelled and the result is None. Returns the result
    and the number of the signal that stopped it (0: none)."""
    loop = asyncio.get_running_loop()
    task = asyncio.ensure_future(main)
    caught = 0

    def on_signal(number: int) -> None:
        nonlocal caught
        if caught:
            task.cancel()  # asked twice: do not wait
            return
        caught = number
        stop.set()
        loop.call_later(grace, task.cancel)

    installed = []
    for number in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError):  # not on Windows
            loop.add_signal_handler(number, on_signal, int(number))
            installed.append(number)
    try:
        return await task, caught
    except asyncio.CancelledError:
        if not caught or not task.cancelled():
            raise  # a cancel of our own caller, not of the signal
        return None, caught
    finally:
        for number in installed:
            loop.remove_signal_handler(number)
