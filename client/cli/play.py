"""`posecast play`: join a room as a tracked player and stream a source's poses."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from posecast.client.cli.common import cafile_without_tls, fail, session_words

if TYPE_CHECKING:

    from posecast.client.session.player import Player


def _play(args: argparse.Namespace) -> int:
    from posecast.client.cli.console import player_summary
    from posecast.client.session.connection import SessionError
    from posecast.client.session.player import Player
    from posecast.client.sources import open_source
    from posecast.client.sources.base import SourceError
    from posecast.solver.readers.errors import FormatError

    if (status := cafile_without_tls("play", args)) is not None:
        return status
    if isinstance(args.devices, Path):  # the old spelling of --roles FILE.toml
        print(f"posecast play: --devices {args.devices} is a roles file: say --roles "
              f"{args.devices} (--devices now names a tracker set)", file=sys.stderr)
        args.roles, args.devices = args.devices, None
    try:
        source = open_source(args.source, args.roles, loop=args.loop, offset=args.offset)
    except (SourceError, FormatError) as err:
        return fail("play", err)
    if args.devices is not None or args.dropouts is not None:
        from posecast.client.sources.tracker_set import TrackerSetSource
        source = TrackerSetSource(source, args.devices, args.dropouts)
    recording = None
    if args.record is not None:
        from posecast.client.sources.recording_source import RecordingSource
        try:
            source = recording = RecordingSource(source, args.record)
        except OSError as err:
            source.close()
            return fail("play", f"--record {args.record}: {err.strerror or err}")
    delay = args.calibrate_in if args.calibrate_in is not None else (
        3.0 if args.source == "openvr" else 0.0)
    try:
        player = Player(args.server, args.room, args.name, source, token=args.token,
                        cafile=args.cafile)
        signum = asyncio.run(_play_live(player, delay, args.seconds, args.source,
                                        args.reconnect))
    except SessionError as err:
        return fail("play", session_words(err))
    finally:
        source.close()
    print(player_summary(player.stats))
    if recording is not None:
        print(f"kept {recording.frames} frames in {recording.path}"
              + (f" ({recording.skipped} left out: a device of the first frame was "
                 "missing)" if recording.skipped else ""))
    return 128 + signum if signum else 0


async def _play_live(player: Player, delay: float, seconds: float | None,
                     source: str, reconnect: bool = True) -> int:
    """Stream with a word on stderr about where it joined and a progress line, until
    the source or the time ends or a signal stops it (its number is returned)."""
    from posecast.client.cli.console import StatusLine, report_player, run_until_signal
    from posecast.client.session.connection import Reconnect, stop_task

    status = StatusLine("posecast play")
    if reconnect:  # a word on stderr when the session is lost and when it is back
        player.reconnect = Reconnect(say=status.say)
    stop = asyncio.Event()
    reporter = asyncio.create_task(report_player(player, status, source))
    try:
        _, signum = await run_until_signal(_calibrate_and_stream(player, delay, seconds, stop),
                                           stop)
    finally:
        await stop_task(reporter)
        status.clear()
    return signum


async def _calibrate_and_stream(player: Player, delay: float, seconds: float | None,
                                stop: asyncio.Event) -> None:
    """Count the player into the T-pose, then stream; Enter on a terminal recalibrates."""
    for left in range(math.ceil(delay), 0, -1):
        print(f"stand in a T-pose, arms out sideways: calibrating in {left} s", flush=True)
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), min(1.0, delay - (left - 1)))
        if stop.is_set():
            return
    loop = asyncio.get_running_loop()
    interactive = sys.stdin.isatty()
    if interactive:
        def recalibrate() -> None:
            sys.stdin.readline()
            print("recalibrating: hold the T-pose", flush=True)
            player.recalibrate()
        loop.add_reader(sys.stdin.fileno(), recalibrate)
    try:
        await player.run(seconds, stop)
    finally:
        if interactive:
            loop.remove_reader(sys.stdin.fileno())
