"""``posecast replay``: a recording played back into a room, at its original timing.

The client joins as a "replay" (``server.replay``) and sends the recording's rosters and
avatar batches at the times they were received (divided by ``speed``); the server gives
each recorded avatar an avatar of the room and hands its poses to the spectators. A
message larger than a client may send is split (a roster into one avatar per message, a
batch into smaller batches): the server reads client messages of at most
``MAX_CLIENT_MESSAGE_BYTES``. With ``loop`` the recording starts again when it ends.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from posecast.client.interop.recording import RecordedMessage, Recording
from posecast.client.session.connection import Session, make_hello, open_session, stop_task
from posecast.client.sources.base import now
from posecast.protocol import (
    MAX_CLIENT_MESSAGE_BYTES,
    AvatarBatch,
    AvatarRoster,
    Error,
    ProtocolError,
    encode,
)

log = logging.getLogger(__name__)


@dataclass
class ReplayStats:
    rosters_sent: int = 0
    batches_sent: int = 0
    frames_sent: int = 0  # avatar-frames
    # avatar-frames recorded before their avatar's roster (a server may send a new
    # avatar's first pose before its skeleton): a spectator could not draw them either
    frames_skipped: int = 0
    loops: int = 0  # times the recording was played to its end
    seconds: float = 0.0
    errors: Counter[str] = field(default_factory=Counter)  # Error codes from the server
    last_error: str | None = None


async def replay_recording(url: str, room: str, rec: Recording, speed: float = 1.0,
                           loop: bool = False, name: str = "replay",
                           token: str | None = None, cafile: Path | None = None,
                           stop: asyncio.Event | None = None,
                           stats: ReplayStats | None = None) -> ReplayStats:
    """Play ``rec`` into ``room`` once (forever with ``loop``) until ``stop`` is set.
    Raises SessionError if the server cannot be reached, refuses, or goes away."""
    if not rec.messages:
        raise ValueError(f"{rec.path}: the recording holds no messages")
    stats = stats if stats is not None else ReplayStats()
    session = await open_session(url, make_hello(url, "replay", room, name, token),
                                 cafile=cafile)
    reader = asyncio.create_task(_read(session, stats), name="posecast-replay-read")
    t_start = now()
    try:
        seq = 0
        known: set[int] = set()  # recorded avatars whose roster was sent
        while True:
            t0, first = now(), rec.times[0]
            for t, message in zip(rec.times, rec.messages, strict=True):
                wait = t0 + (t - first) / speed - now()
                if wait > 0:
                    await _sleep(wait, stop)
                if stop is not None and stop.is_set():
                    return stats
                if reader.done():
                    reader.result()  # the server went away: its SessionError
                sendable = _known_rows(message, known, stats)
                for part in split(sendable, seq) if sendable is not None else ():
                    await session.send(part)
                    if isinstance(part, AvatarBatch):
                        stats.batches_sent += 1
                        stats.frames_sent += part.size
                    else:
                        stats.rosters_sent += 1
                seq += isinstance(message, AvatarBatch)
                stats.seconds = now() - t_start
            stats.loops += 1
            if not loop:
                return stats
    finally:
        stats.seconds = now() - t_start
        await stop_task(reader)
        await session.close()


def _known_rows(message: RecordedMessage, known: set[int],
                stats: ReplayStats) -> RecordedMessage | None:
    """A roster as it is (noting its avatars in ``known``); a batch without the rows of
    avatars whose roster has not been sent (counted as skipped), None if none is left."""
    if isinstance(message, AvatarRoster):
        known.update(info.avatar_id for info in message.avatars)
        known.difference_update(message.removed)
        return message
    rows = [i for i, a in enumerate(message.avatar_ids.tolist()) if a in known]
    stats.frames_skipped += message.size - len(rows)
    if len(rows) == message.size:
        return message
    if not rows:
        return None
    return AvatarBatch.from_frames([message.frame(i) for i in rows],
                                   t_sent=float(message.t_sent))


def split(message: RecordedMessage, seq: int) -> Iterator[RecordedMessage]:
    """A recorded message as messages a client may send: a roster one avatar at a time
    (a removal list whole), a batch renumbered ``seq`` and halved until each part fits."""
    if isinstance(message, AvatarRoster):
        for info in message.avatars:
            yield AvatarRoster(avatars=(info,))
        if message.removed:
            yield AvatarRoster(removed=message.removed)
        return
    frames = [message.frame(i).model_copy(update={"seq": seq})
              for i in range(message.size)]
    parts = [frames]
    while parts:
        part = parts.pop(0)
        batch = AvatarBatch.from_frames(part, t_sent=float(message.t_sent))
        if len(part) > 1 and len(encode(batch)) > MAX_CLIENT_MESSAGE_BYTES:
            half = len(part) // 2
            parts[:0] = [part[:half], part[half:]]
        else:  # one avatar over the bound: the server says so (too_large)
            yield batch


async def _read(session: Session, stats: ReplayStats) -> None:
    """Count the server's Error replies (a refused roster or batch); ignore the rest."""
    while True:
        try:
            msg, _ = await session.receive()
        except ProtocolError as err:
            stats.errors[f"client:{err.code}"] += 1
            continue
        if isinstance(msg, Error):
            stats.errors[msg.code] += 1
            stats.last_error = f"{msg.code}: {msg.message}"
            level = logging.WARNING if stats.errors[msg.code] == 1 else logging.DEBUG
            log.log(level, "%s: %s", session.url, stats.last_error)


async def _sleep(seconds: float, stop: asyncio.Event | None) -> None:
    if stop is None:
        await asyncio.sleep(seconds)
        return
    with contextlib.suppress(TimeoutError):
        await asyncio.wait_for(stop.wait(), seconds)
