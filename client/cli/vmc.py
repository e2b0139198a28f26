"""``posecast vmc``: one avatar of a room to a VMC receiver, with a word on where it
joined, a progress line and a summary."""

from __future__ import annotations

import asyncio
import sys
import time
from pathlib import Path

from posecast.client.cli.console import REFRESH_S, StatusLine, run_until_signal
from posecast.client.interop.vmc import VmcStats, run_vmc


def run_vmc_command(url: str, room: str, avatar: str | None, host: str, port: int,
                    seconds: float | None, rate_hz: float, token: str | None,
                    cafile: Path | None) -> int:
    """Send until the time is up or a signal; the exit status. Raises SessionError (the
    server cannot be reached, refuses or goes away) and VmcError (no such avatar, a host
    that does not resolve)."""
    status = StatusLine("posecast vmc")
    stats = VmcStats()
    where = (f"of room {room!r} on {url} to {host}:{port} as VMC, at most {rate_hz:g} Hz; "
             "Ctrl-C stops")

    async def send() -> tuple[VmcStats | None, int]:
        stop = asyncio.Event()
        progress = asyncio.create_task(_report(stats, status, where))
        try:
            return await run_until_signal(
                run_vmc(url, room, avatar, host, port, seconds, rate_hz, token, cafile,
                        stop, stats=stats), stop)
        finally:
            progress.cancel()
            status.clear()

    done, signum = asyncio.run(send())
    stats = done or stats
    if avatar is not None and stats.avatar_name is None and not signum:
        print(f"posecast vmc: no avatar named {avatar!r} came to room {room!r} in "
              f"{stats.seconds:.1f} s", file=sys.stderr)
        return 1
    rate = stats.bundles_sent / stats.seconds if stats.seconds > 0 else 0.0
    print(f"sent {stats.bundles_sent} bundles of {stats.avatar_name!r} in "
          f"{stats.seconds:.1f} s ({rate:.1f}/s)" if stats.avatar_name is not None
          else f"sent nothing in {stats.seconds:.1f} s: no avatar came to room {room!r}")
    if stats.send_errors:
        print(f"{stats.send_errors} bundles the network refused (is {host}:{port} "
              "reachable?)")
    return 128 + signum if signum else 0


async def _report(stats: VmcStats, status: StatusLine, where: str) -> None:
    """Say which avatar goes where once it is found (not before: a server that cannot be
    reached is then the only line), then a progress line."""
    while stats.avatar_name is None:
        await asyncio.sleep(0.05)
    status.say(f"sending {stats.avatar_name!r} {where}")
    t0 = time.monotonic()
    while True:
        await asyncio.sleep(REFRESH_S)
        status.progress(f"{stats.avatar_name!r}: {stats.bundles_sent} bundles, "
                        f"{time.monotonic() - t0:.0f} s")
