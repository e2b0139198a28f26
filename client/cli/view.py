"""`posecast view`: a spectator window (or headless frames) of a room."""

from __future__ import annotations

import argparse
import asyncio
import json
from typing import TYPE_CHECKING

from posecast.client.cli.common import cafile_without_tls, fail, session_words

if TYPE_CHECKING:

    from posecast.client.session.spectator import Spectator
    from posecast.client.viewer import ViewerStats


def _view(args: argparse.Namespace) -> int:
    from posecast.client.cli.console import view_summary
    from posecast.client.session.connection import SessionError
    from posecast.client.viewer import GLUnavailableError, NoDisplayError

    if (status := cafile_without_tls("view", args)) is not None:
        return status
    watched: list[Spectator] = []
    try:
        stats, signum = asyncio.run(_view_live(args, watched))
    except (NoDisplayError, GLUnavailableError) as err:
        return fail("view", err)
    except SessionError as err:
        return fail("view", session_words(err))
    spectator = watched[0].stats if watched else None
    if args.json:
        print(json.dumps(stats.as_json() if stats is not None else {}))
    else:
        for line in view_summary(stats, spectator, args.out if args.headless else None):
            print(line)
    return 128 + signum if signum else 0


async def _view_live(args: argparse.Namespace, watched: list[Spectator]
                     ) -> tuple[ViewerStats | None, int]:
    """The viewer, with a word on stderr about where it joined and whom it waits for,
    until its frames are done, its window closes or a signal stops it."""
    from posecast.client.cli.console import StatusLine, report_spectator, run_until_signal
    from posecast.client.session.connection import Reconnect, stop_task
    from posecast.client.viewer import Mode, ViewMode, run_headless_viewer, run_window_viewer

    status = StatusLine("posecast view")
    stop = asyncio.Event()
    reporters: list[asyncio.Task[None]] = []

    def on_spectator(spectator: Spectator) -> None:
        if args.reconnect:  # a word on stderr when the session is lost and when it is back
            spectator.reconnect = Reconnect(say=status.say)
        watched.append(spectator)
        reporters.append(asyncio.create_task(report_spectator(spectator, status)))

    width, height = args.size
    mode, view = Mode(args.mode), ViewMode(args.view)
    run = (run_headless_viewer(args.server, args.room, args.frames or 100, args.out, width,
                               height, interval_ms=1000.0 / args.fps, mode=mode, view=view,
                               max_rate_hz=args.max_rate, token=args.token,
                               cafile=args.cafile, stop=stop,
                               on_spectator=on_spectator, marker=args.marker)
           if args.headless else
           run_window_viewer(args.server, args.room, width, height, fps=args.fps, mode=mode,
                             view=view, max_rate_hz=args.max_rate, frames=args.frames,
                             screenshot=args.screenshot, token=args.token,
                             cafile=args.cafile, stop=stop,
                             on_spectator=on_spectator, marker=args.marker))
    try:
        return await run_until_signal(run, stop)
    finally:
        for task in reporters:
            await stop_task(task)
        status.clear()
