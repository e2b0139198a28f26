"""``posecast record`` and ``replay``: a room to a recording file and back into a room,
with a progress line and a summary."""

from __future__ import annotations

import asyncio
import sys
import time
from pathlib import Path

from posecast.client.cli.console import REFRESH_S, StatusLine, run_until_signal
from posecast.client.interop.recorder import RecordingSpectator, RecordStats, record_room
from posecast.client.interop.recording import read_recording
from posecast.client.interop.replay import ReplayStats, replay_recording
from posecast.client.session.connection import Reconnect, stop_task
from posecast.solver.readers.errors import FormatError


def run_record(url: str, room: str, out: Path, seconds: float | None, token: str | None,
               cafile: Path | None, reconnect: bool) -> int:
    """Record until the time is up or a signal; the exit status. Raises SessionError (the
    server cannot be reached or refuses) and OSError (the file cannot be made)."""
    status = StatusLine("posecast record")
    stats, signum = asyncio.run(_record(url, room, out, seconds, token, cafile, reconnect,
                                        status))
    if stats is not None:
        print(record_summary(stats, room))
    return 128 + signum if signum else 0


async def _record(url: str, room: str, out: Path, seconds: float | None, token: str | None,
                  cafile: Path | None, reconnect: bool,
                  status: StatusLine) -> tuple[RecordStats | None, int]:
    stop = asyncio.Event()
    reporters: list[asyncio.Task[None]] = []

    def on_spectator(spectator: RecordingSpectator) -> None:
        reporters.append(asyncio.create_task(_report(spectator, room, out, status)))

    policy = Reconnect(say=status.say) if reconnect else None
    try:
        return await run_until_signal(
            record_room(url, room, out, seconds, stop, token, cafile, policy, on_spectator),
            stop)
    finally:
        for task in reporters:
            await stop_task(task)
        status.clear()


async def _report(spectator: RecordingSpectator, room: str, out: Path,
                  status: StatusLine) -> None:
    while spectator.session is None:
        await asyncio.sleep(0.05)
    status.say(f"recording room {room!r} on {spectator.url} to {out}; Ctrl-C stops")
    t0 = time.monotonic()
    while True:
        await asyncio.sleep(REFRESH_S)
        w, stats = spectator.writer, spectator.stats
        n = len(spectator.seen)
        status.progress(f"{stats.frames_received} avatar-frames of {n} "
                        f"avatar{'s' if n != 1 else ''}, {w.bytes / 1e6:.1f} MB, "
                        f"{time.monotonic() - t0:.0f} s")


def record_summary(stats: RecordStats, room: str) -> str:
    if stats.avatar_frames == 0:
        return (f"recorded {stats.seconds:.1f} s of room {room!r} but no avatar-frames: "
                f"nobody played there ({stats.path}, {stats.records} records)")
    return (f"recorded {stats.seconds:.1f} s of room {room!r}: {stats.avatar_frames} "
            f"avatar-frames of {stats.avatars} avatar{'s' if stats.avatars != 1 else ''}, "
            f"{stats.bytes / 1e6:.2f} MB in {stats.path}")


def run_replay(path: Path, url: str, room: str, speed: float, loop: bool, token: str | None,
               cafile: Path | None) -> int:
    """Replay a recording with a progress line and a summary; the exit status. Raises
    SessionError (the server cannot be reached, refuses or goes away)."""
    try:
        rec = read_recording(path)
    except FormatError as err:
        print(f"posecast replay: {err}", file=sys.stderr)
        return 1
    if rec.warning is not None:
        print(f"posecast replay: warning: {rec.warning}", file=sys.stderr)
    if not rec.frames():
        print(f"posecast replay: {path}: the recording holds no avatar-frames",
              file=sys.stderr)
        return 1
    status = StatusLine("posecast replay")
    stats = ReplayStats()
    status.say(f"playing {path} ({rec.seconds:.1f} s, {rec.frames()} avatar-frames of room "
               f"{rec.room!r}) into room {room!r} on {url}"
               + (f" at {speed:g}x" if speed != 1.0 else "") + ("; looping" if loop else "")
               + "; Ctrl-C stops")

    async def play() -> tuple[ReplayStats | None, int]:
        stop = asyncio.Event()
        reporter = asyncio.create_task(_report_replay(stats, status))
        try:
            return await run_until_signal(
                replay_recording(url, room, rec, speed, loop, token=token, cafile=cafile,
                                 stop=stop, stats=stats), stop)
        finally:
            await stop_task(reporter)
            status.clear()

    _, signum = asyncio.run(play())
    errors = sum(stats.errors.values())
    print(f"played {stats.frames_sent} avatar-frames in {stats.seconds:.1f} s"
          + (f", {stats.loops} times through" if stats.loops > 1 else "")
          + (f"; left out {stats.frames_skipped} recorded before their avatar's skeleton"
             if stats.frames_skipped else "")
          + (f"; server errors: {dict(stats.errors)} (last: {stats.last_error})"
             if errors else ""))
    return 128 + signum if signum else (1 if errors else 0)


async def _report_replay(stats: ReplayStats, status: StatusLine) -> None:
    while True:
        await asyncio.sleep(REFRESH_S)
        status.progress(f"sent {stats.frames_sent} avatar-frames, {stats.seconds:.0f} s"
                        + (f", loop {stats.loops + 1}" if stats.loops else ""))
