"""``posecast record``: a spectator that writes every roster and avatar batch of a room to
a recording file (``client.recording``) as it arrives."""

from __future__ import annotations

import asyncio
from dataclasses import dataclass
from pathlib import Path

from posecast.client.interop.recording import RecordingWriter
from posecast.client.session.connection import Reconnect
from posecast.client.session.spectator import Spectator, SpectatorStats
from posecast.client.sources.base import now
from posecast.protocol import AvatarBatch, AvatarRoster, ClockEstimator


@dataclass
class RecordStats:
    path: Path
    records: int
    bytes: int
    avatar_frames: int
    avatars: int  # distinct avatars seen
    seconds: float
    spectator: SpectatorStats


class RecordingSpectator(Spectator):
    """A spectator whose every roster and batch also goes to ``writer``."""

    def __init__(self, writer: RecordingWriter, *args: object, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self.writer = writer
        self.seen: set[int] = set()

    def on_batch(self, batch: AvatarBatch, t_local: float, clock: ClockEstimator) -> None:
        super().on_batch(batch, t_local, clock)
        self.writer.add(t_local, batch)
        self.seen.update(batch.avatar_ids.tolist())

    def on_roster(self, roster: AvatarRoster) -> None:
        super().on_roster(roster)
        if roster.avatars or roster.removed:  # a new session's empty roster says nothing
            self.writer.add(now(), roster)


async def record_room(url: str, room: str, path: Path, seconds: float | None = None,
                      stop: asyncio.Event | None = None, token: str | None = None,
                      cafile: Path | None = None, reconnect: Reconnect | None = None,
                      on_spectator: object = None) -> RecordStats:
    """Record ``room`` into ``path`` (a new file) until ``seconds`` pass or ``stop`` is
    set; raises FileExistsError before connecting if the file exists, SessionError if
    the server cannot be reached or refuses."""
    with RecordingWriter(path, room, url) as writer:
        spectator = RecordingSpectator(writer, url, room, "recorder", token=token,
                                       cafile=cafile, reconnect=reconnect)
        if callable(on_spectator):
            on_spectator(spectator)
        stats = await spectator.run(seconds, stop)
    return RecordStats(path, writer.records, writer.bytes, stats.frames_received,
                       len(spectator.seen), stats.seconds, stats)
