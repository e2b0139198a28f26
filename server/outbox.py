"""Latest-wins delivery to one connection, so a slow or stalled receiver delays no one.

The room offers every solved batch to every spectator's outbox and moves on at once; the
outbox keeps at most one pending frame per avatar (a newer frame replaces an unsent one,
which is counted as dropped) and its own task sends whatever is pending when the socket
is free, no faster than the receiver asked for. Memory per connection is bounded by the
number of avatars, whatever the receiver does.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from typing import Generic, TypeVar

Frame = TypeVar("Frame")


class Outbox(Generic[Frame]):
    def __init__(self, send: Callable[[list[Frame]], Awaitable[None]],
                 max_rate_hz: float | None = None) -> None:
        self._send = send
        self._min_interval = 1.0 / max_rate_hz if max_rate_hz else 0.0
        self._pending: dict[int, Frame] = {}
        self._wake = asyncio.Event()
        self._closed = False
        self._sending = False
        self._last = -1e9  # loop time of the last send
        # every frame offered is exactly one of: pending, delivered (handed to the
        # socket) or dropped (replaced by a newer one of its avatar, forgotten, or still
        # held when the outbox closed or a send failed)
        self.delivered = 0
        self.dropped = 0

    def offer(self, frames: dict[int, Frame]) -> None:
        """Queue the newest frame of each avatar; never blocks."""
        if self._closed:
            self.dropped += len(frames)
            return
        for avatar_id, frame in frames.items():
            if avatar_id in self._pending:
                self.dropped += 1
            self._pending[avatar_id] = frame
        self._wake.set()

    def ready(self, t: float) -> bool:
        """Whether a send now would jump no queue and break no rate limit: then the room
        may write straight to the socket (``sent_directly``) instead of waking the task."""
        return (not self._sending and not self._pending and not self._closed
                and t - self._last >= self._min_interval)

    def sent_directly(self, frames: int, t: float) -> None:
        self.delivered += frames
        self._last = t

    def forget(self, avatar_id: int) -> None:
        """An avatar left: do not send its last frame after its removal notice."""
        if self._pending.pop(avatar_id, None) is not None:
            self.dropped += 1

    @property
    def pending(self) -> int:
        return len(self._pending)

    @property
    def idle(self) -> bool:
        """Nothing held and nothing being sent."""
        return not self._pending and not self._sending

    def close(self) -> None:
        self._closed = True
        self.dropped += len(self._pending)  # never to be sent
        self._pending.clear()
        self._wake.set()

    async def run(self) -> None:
        """Send pending frames until closed (run as the connection's sender task)."""
        loop = asyncio.get_running_loop()
        while True:
            await self._wake.wait()
            if self._closed:
                return
            wait = self._last + self._min_interval - loop.time()
            if wait > 0:  # a spectator that asked for a lower rate
                await asyncio.sleep(wait)
                if self._closed:
                    return
            self._wake.clear()
            frames = list(self._pending.values())
            self._pending.clear()
            if not frames:
                continue
            self._last = loop.time()
            self._sending = True
            try:
                await self._send(frames)
            except BaseException:  # the connection went (or the task was cancelled)
                self.dropped += len(frames)
                raise
            finally:
                self._sending = False
            self.delivered += len(frames)
