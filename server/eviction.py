"""Closing connections that hold the server's resources and give nothing back.

A spectator that stopped reading keeps its outbox's send blocked on a full socket: latest
wins bounds its memory, but it would stay listed forever, and closing it politely waits
behind its full buffer. A player that stopped sending keeps its avatar in the roster.
``Watchdog`` looks at both once per interval (no cost on the frame path: it reads counters
the frame path keeps anyway) and ``close_now`` closes a connection whatever its buffers
hold.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Iterable
from dataclasses import dataclass

from websockets.asyncio.server import ServerConnection

from posecast.server.fanout import Spectator
from posecast.server.room import Avatar

# a close frame queued behind a full buffer may never be read: after this long the
# socket is dropped (the close code is still recorded on the server's side)
CLOSE_TIMEOUT_S = 1.0


async def close_now(ws: ServerConnection, code: int, reason: str,
                    timeout: float = CLOSE_TIMEOUT_S) -> None:
    """Close with ``code`` and ``reason``; abort the socket if the handshake cannot end
    within ``timeout`` (a peer that does not read never sees the close frame)."""
    with contextlib.suppress(Exception):  # TimeoutError, or the connection already went
        await asyncio.wait_for(ws.close(code, reason), timeout)
    if ws.transport is not None:  # a no-op after a clean close
        ws.transport.abort()


@dataclass
class _Progress:
    delivered: int  # the spectator's outbox.delivered when last seen moving
    since: float  # when that was


class Watchdog:
    """Which spectators are stalled and which players idle, checked now and then."""

    def __init__(self, backlog_evict_s: float, idle_player_s: float) -> None:
        self.backlog_evict_s = backlog_evict_s
        self.idle_player_s = idle_player_s
        self._progress: dict[Spectator, _Progress] = {}
        self._player_since: dict[int, float] = {}  # avatar id -> its join or calibration

    @property
    def interval(self) -> float:
        """How often to look: a fraction of the shortest limit, at most once a second."""
        return min(1.0, self.backlog_evict_s / 4, self.idle_player_s / 4)

    def player_active(self, avatar_id: int, t: float) -> None:
        """A sign of life other than a frame (a join, a calibration) at ``t``."""
        self._player_since[avatar_id] = t

    def stalled(self, spectators: Iterable[Spectator], t: float) -> list[Spectator]:
        """Of all the server's spectators, those that took no frame for backlog_evict_s
        while frames waited for them (their outbox holding or sending some): the socket
        stays full."""
        progress = self._progress
        seen = set()
        out = []
        for s in spectators:
            seen.add(s)
            delivered = s.outbox.delivered
            p = progress.get(s)
            if p is None or s.outbox.idle or p.delivered != delivered:
                progress[s] = _Progress(delivered, t)
            elif t - p.since >= self.backlog_evict_s:
                out.append(s)
        for s in [s for s in progress if s not in seen]:  # gone
            del progress[s]
        return out

    def idle(self, avatars: Iterable[Avatar], t: float) -> list[Avatar]:
        """Of all the server's avatars, the connected ones with no tracker frame for
        idle_player_s, counted from their last frame, join or calibration."""
        since = self._player_since
        out = []
        seen = set()
        for a in avatars:
            seen.add(a.avatar_id)
            if not a.connected:
                continue
            last = max(a.cadence.last, since.get(a.avatar_id, t))
            if a.avatar_id not in since:
                since[a.avatar_id] = t  # first seen now: a frame is not due yet
            if t - last >= self.idle_player_s:
                out.append(a)
        for avatar_id in [i for i in since if i not in seen]:  # removed
            del since[avatar_id]
        return out
