"""The headless spectator: receives every avatar of a room and keeps per-stage latency.

It holds what a viewer needs to draw (the roster of skeletons, the latest frame of each
avatar) and what a report needs (frames received per avatar, a ``LatencyRecorder`` of the
stages of ``AvatarFrame.latencies``). Receive time is taken right after ``recv`` returns,
before decoding, and put on the server clock with this connection's clock estimate;
stages that need it are recorded only once the clock is synced (an offset of 0.0 would
make them garbage), the server-side ones always.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections import Counter
from dataclasses import dataclass, field
from functools import partial
from itertools import count, repeat
from pathlib import Path
from typing import Any

from posecast.client.measure.latency import LatencyRecorder
from posecast.client.session.connection import (
    Reconnect,
    Session,
    SessionError,
    make_hello,
    open_session,
    stop_task,
)
from posecast.client.sources.base import now
from posecast.protocol import (
    AvatarBatch,
    AvatarFrame,
    AvatarInfo,
    AvatarRoster,
    ClockEstimator,
    Error,
    Message,
    ProtocolError,
)

log = logging.getLogger(__name__)

# An avatar's latest frame: row ``row`` of ``batch``, and when it arrived (local clock:
# ``client.sources.now``). A plain tuple: 16 are made per batch (``frame_of`` builds the
# AvatarFrame, which a headless spectator never needs).
ReceivedFrame = tuple[AvatarBatch, int, float]


def frame_of(received: ReceivedFrame) -> AvatarFrame:
    """The AvatarFrame of a ReceivedFrame."""
    batch, row, _ = received
    return batch.frame(row)


@dataclass
class SpectatorStats:
    """What one spectator received. ``frames_received`` counts avatar-frames."""

    frames_received: int = 0
    batches_received: int = 0
    bytes_received: int = 0
    frames_per_avatar: Counter[int] = field(default_factory=Counter)
    latency: LatencyRecorder = field(default_factory=LatencyRecorder)
    errors: Counter[str] = field(default_factory=Counter)  # Error codes from the server
    last_error: str | None = None
    connection_id: int | None = None
    clock_offset: float = 0.0  # server - local, seconds, at the end
    clock_rtt: float = math.inf  # best round trip, seconds
    seconds: float = 0.0  # connected time
    reconnects: int = 0  # sessions opened again after one was lost


class Spectator:
    """One spectator connection; ``run`` receives until time is up or ``stop`` is set.

    ``roster`` (avatar id -> skeleton) and ``latest`` (avatar id -> ReceivedFrame) are
    live while it runs, for a viewer to render from; ``stats`` too.
    """

    def __init__(self, url: str, room: str, name: str, max_rate_hz: float | None = None,
                 token: str | None = None, cafile: Path | None = None,
                 reconnect: Reconnect | None = None) -> None:
        self.url = url
        self.cafile = cafile  # a wss:// server's private CA (``open_session``)
        self.hello = make_hello(url, "spectator", room, name, token, max_rate_hz)
        self.roster: dict[int, AvatarInfo] = {}
        self.latest: dict[int, ReceivedFrame] = {}
        self.stats = SpectatorStats()
        self.session: Session | None = None
        self.reconnect = reconnect  # with a policy, a lost session is opened again

    async def run(self, seconds: float | None = None,
                  stop: asyncio.Event | None = None) -> SpectatorStats:
        """Receive until ``seconds`` pass or ``stop`` is set (neither: until cancelled).

        Raises SessionError if the server cannot be reached, refuses, or goes away
        (with ``reconnect``: once it gives up); ``stats`` keeps what was received.
        """
        session = await open_session(self.url, self.hello, cafile=self.cafile)
        deadline = None if seconds is None else now() + seconds
        while True:
            try:
                await self._run_session(session, None if deadline is None
                                        else max(deadline - now(), 0.0), stop)
                return self.stats
            except SessionError as lost:
                if self.reconnect is None or not lost.retry:
                    raise
                again = await self.reconnect.again(lost, self.hello, cafile=self.cafile,
                                                   stop=stop, url=self.url)
                if again is None:
                    return self.stats
                session = again
                self.stats.reconnects += 1
                # the room comes again from the new session's roster: ids from a
                # restarted server mean other avatars
                self.forget_room()

    async def _run_session(self, session: Session, seconds: float | None,
                           stop: asyncio.Event | None) -> None:
        self.session = session
        self.stats.connection_id = session.connection_id
        t_start = now()
        reader = asyncio.create_task(self._read_loop(session), name="posecast-spectate")
        session.deliver(partial(self._handle, session), self._undecodable)
        try:
            session.start_clock_sync()
            await _until(reader, seconds, stop)
        finally:
            await stop_task(reader)  # its SessionError, if any, was raised by _until
            session.hand_over()  # the last messages read
            self.stats.seconds += now() - t_start
            self.stats.bytes_received += session.bytes_received
            self.stats.clock_offset = session.clock.offset
            self.stats.clock_rtt = session.clock.rtt
            await session.close()

    def forget_room(self) -> None:
        """Drop every avatar: a new session sends the room's roster again."""
        self.on_roster(AvatarRoster(avatars=(), removed=tuple(self.roster)))
        self.latest.clear()

    async def catch_up(self) -> None:
        """Take every message that has arrived before drawing (``Session.catch_up``)."""
        if self.session is not None:
            await self.session.catch_up()
        else:  # still connecting: the connecting task needs the loop
            await asyncio.sleep(0)

    async def _read_loop(self, session: Session) -> None:
        """What ``Session.deliver`` does not hand over (what came before it), and the
        connection's end."""
        while True:
            try:
                msg, t = await session.receive()
            except ProtocolError as err:
                self._undecodable(err)
                continue
            self._handle(session, msg, t)

    def _handle(self, session: Session, msg: Message, t: float) -> None:
        if isinstance(msg, AvatarBatch):
            self.on_batch(msg, t, session.clock)
        elif isinstance(msg, AvatarRoster):
            self.on_roster(msg)
        elif isinstance(msg, Error):
            self._count_error(msg.code, msg.message)

    def _undecodable(self, err: ProtocolError) -> None:  # count, carry on
        self._count_error(f"client:{err.code}", err.message)

    def on_batch(self, batch: AvatarBatch, t_local: float, clock: ClockEstimator) -> None:
        """Record a batch received at ``t_local`` (this process's clock)."""
        stats = self.stats
        # receive-side stages only with a synced clock; server-side ones need no clock
        t_server = clock.to_server(t_local) if clock.synced else None
        ids = batch.avatar_ids.tolist()
        # (batch, row, t_local) of each avatar, the tuples made in C: building a
        # NamedTuple each was a twelfth of the demo's spectators' time
        self.latest.update(zip(ids, zip(repeat(batch), count(), repeat(t_local)), strict=False))
        stats.frames_per_avatar.update(ids)
        t_decoded = clock.to_server(now()) if clock.synced else None
        stats.latency.add_batch(batch.t_capture, batch.t_server_receive, batch.t_solved,
                                batch.t_sent, t_server, t_decoded)
        stats.frames_received += len(ids)
        stats.batches_received += 1

    def on_roster(self, roster: AvatarRoster) -> None:
        """Avatars joined or recalibrated (new skeletons), or left."""
        for info in roster.avatars:
            self.roster[info.avatar_id] = info
        for avatar_id in roster.removed:
            self.roster.pop(avatar_id, None)
            self.latest.pop(avatar_id, None)

    def _count_error(self, code: str, message: str) -> None:
        self.stats.errors[code] += 1
        self.stats.last_error = f"{code}: {message}"
        level = logging.WARNING if self.stats.errors[code] == 1 else logging.DEBUG
        log.log(level, "%s: %s", self.url, self.stats.last_error)


async def _until(reader: asyncio.Task[None], seconds: float | None,
                 stop: asyncio.Event | None) -> None:
    """Return when time is up or ``stop`` is set; re-raise if ``reader`` failed first."""
    waits: set[asyncio.Task[Any]] = {reader}
    stopper = asyncio.create_task(stop.wait()) if stop is not None else None
    if stopper is not None:
        waits.add(stopper)
    try:
        await asyncio.wait(waits, timeout=seconds, return_when=asyncio.FIRST_COMPLETED)
    finally:
        if stopper is not None:
            stopper.cancel()
    if reader.done():
        reader.result()  # raises the SessionError of a server that went away


async def run_spectator(url: str, room: str, name: str, seconds: float | None = None,
                        stop: asyncio.Event | None = None, max_rate_hz: float | None = None,
                        token: str | None = None) -> SpectatorStats:
    """Spectate ``room`` at ``url`` headless; see ``Spectator.run``."""
    return await Spectator(url, room, name, max_rate_hz=max_rate_hz, token=token).run(
        seconds, stop)


