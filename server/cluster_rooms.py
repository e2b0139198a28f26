"""The part of a session that shares rooms with other processes through Redis (``serve
--redis``, ``server.cluster``): owning a room or watching another's, taking a dead
owner's avatars over, handing a room on, and mirroring what its owner publishes.
``Session`` inherits it; it holds no state of its own."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Coroutine
from typing import Any

from websockets.asyncio.server import ServerConnection

from posecast.protocol import (
    AvatarBatch,
    ProtocolError,
    encode,
)
from posecast.server.clock import now
from posecast.server.cluster import Cluster
from posecast.server.metrics import Metrics
from posecast.server.rejection_log import LineBudget
from posecast.server.relay import BATCH, ROSTER, open_envelope, relayed_batch, relayed_roster
from posecast.server.room import (
    Avatar,
    RelayedBatch,
    Room,
)

log = logging.getLogger("posecast.server")


class ClusterRooms:
    """Session's rooms as one of many processes (its methods read the session's state)."""

    rooms: dict[str, Room]
    cluster: Cluster | None
    metrics: Metrics
    log_budget: LineBudget
    _claiming: dict[str, asyncio.Lock]
    _owners: dict[int, ServerConnection]

    def room(self, name: str, relayed: bool = False) -> Room:
        raise NotImplementedError

    def _forget_later(self, room: Room, avatar: Avatar, at_once: bool = False) -> None:
        raise NotImplementedError

    def _evict(self, ws: ServerConnection, limit: str, code: int, reason: str) -> None:
        raise NotImplementedError

    def _later(self, aw: Coroutine[Any, Any, None]) -> None:
        raise NotImplementedError

    async def _own(self, name: str) -> str | None:
        """A player or replay joins ``name``: own the room (taking it over, with its
        avatars, from a dead owner), or the URL of the live process that owns it."""
        assert self.cluster is not None
        lock = self._claiming.setdefault(name, asyncio.Lock())
        async with lock:
            room = self.rooms.get(name)
            if room is not None and not room.relayed and name in self.cluster.owned:
                return None
            url = await self.cluster.claim(name)
            if url is None:
                room = self.room(name)
                if room.relayed:  # its spectators stay; the mirror makes way for avatars
                    room.relayed = False
                    await self.cluster.unwatch(name)
                await self._restore(room)
        if url is not None and name not in self.rooms and not lock.locked():
            self._claiming.pop(name, None)  # clients name rooms: this must not grow
        return url

    async def _restore(self, room: Room) -> None:
        """The room's avatars as Redis has them, calibrated from their T-poses as by the
        process that had them; their players resume within the reconnect grace."""
        assert self.cluster is not None
        mirror = {a for a, avatar in room.avatars.items()
                  if self._owners.get(a) is None and not avatar.connected}
        records = await self.cluster.records(room.name)
        restored = 0
        for record in records:
            if record.avatar_id in room.avatars and record.avatar_id not in mirror:
                continue  # a live avatar of this process: it knows better
            mirror.discard(record.avatar_id)
            room.avatars.pop(record.avatar_id, None)
            if record.resume is None:  # a replay's: gone with its connection
                room.remove_avatar(record.avatar_id)
                continue
            avatar = Avatar(record.avatar_id, record.display_name, record.resume,
                            connected=False)
            room.avatars[avatar.avatar_id] = avatar
            if record.roles is not None and record.poses is not None:
                try:
                    room.calibrate(avatar, record.roles, record.poses)
                except ValueError as err:
                    log.warning("room %r: avatar %d not calibrated again: %s", room.name,
                                avatar.avatar_id, err)
            self._forget_later(room, avatar)
            restored += 1
        for avatar_id in mirror:  # on the spectators' screens, and no longer anywhere
            room.remove_avatar(avatar_id)
        if restored:
            log.info("room %r: %d avatars back from Redis, calibrated", room.name, restored)

    async def _watch(self, name: str) -> None:
        """A spectator joins ``name``: where another process owns it, this process
        receives its batches and rosters through Redis and keeps a mirror of its avatars."""
        assert self.cluster is not None
        if name in self.rooms:
            return
        room = self.room(name, relayed=True)
        await self.cluster.watch(name)
        await self._mirror(room)

    async def _mirror(self, room: Room) -> None:
        assert self.cluster is not None
        for record in await self.cluster.records(room.name):
            if record.info is not None and room.relayed:
                room.avatars[record.avatar_id] = Avatar(
                    record.avatar_id, record.display_name, "", info=record.info,
                    connected=False)

    def _relayed(self, name: str, data: bytes) -> None:
        """What the owner of a room published, for this process's spectators of it."""
        room = self.rooms.get(name)
        if room is None or not room.relayed:
            return
        try:
            envelope = open_envelope(data)
            if envelope.sender == self.cluster.process_id:  # type: ignore[union-attr]
                return
            t = now()
            self.metrics.relay_latency.add(t - envelope.t_published)
            if envelope.kind == BATCH:
                codings = room.codings(list(room.avatars))  # the mirror's rosters'
                payload, batch = relayed_batch(envelope, codings)
                known = [a in room.avatars for a in batch.avatar_ids.tolist()]
                if not all(known):  # before its roster (a snapshot being read): skipped
                    self.metrics.frames_unsendable += known.count(False)
                    if not any(known):
                        return
                    keep = [i for i, k in enumerate(known) if k]
                    batch = AvatarBatch.from_frames([batch.frame(i) for i in keep],
                                                    t_sent=batch.t_sent)
                    payload = encode(batch, codings)
                self.metrics.frames_relayed += batch.size
                room.deliver(RelayedBatch(payload, batch, codings))
            elif envelope.kind == ROSTER:
                roster = relayed_roster(envelope)
                for info in roster.avatars:
                    avatar = room.avatars.get(info.avatar_id)
                    if avatar is None:
                        avatar = room.avatars[info.avatar_id] = Avatar(
                            info.avatar_id, info.display_name, "", connected=False)
                    avatar.info = info
                for avatar_id in roster.removed:
                    room.avatars.pop(avatar_id, None)
                    for s in room.spectators.values():
                        s.outbox.forget(avatar_id)
                room.send_roster(envelope.payload)
        except (ValueError, ProtocolError) as err:
            self.metrics.rejected["relay"] += 1
            if self.log_budget.take(now()):
                log.warning("room %r: a message from Redis skipped: %s", name, err)

    def _hand_over(self, name: str, url: str) -> None:
        """Another process owns the room now (Redis was lost and another took it): its
        players go there, its spectators stay and receive the owner's frames."""
        room = self.rooms.get(name)
        if room is None:
            return
        room.relayed = True  # first: nothing below goes to Redis
        room.discard_pending()
        for avatar_id in list(room.avatars):
            ws = self._owners.get(avatar_id)
            if ws is not None:
                self._evict(ws, "room_moved", 1012, f"the room moved to {url[:60]}")
            room.remove_avatar(avatar_id)

        async def watch() -> None:
            assert self.cluster is not None
            await self.cluster.watch(name)
            await self._mirror(room)
        self._later(watch())

    async def _rejoined(self) -> None:
        """Redis is back: the owned rooms' records again (made while it was lost too),
        the relayed rooms' mirrors again."""
        assert self.cluster is not None
        for room in list(self.rooms.values()):
            if room.relayed:
                await self._mirror(room)
                continue
            for avatar in room.avatars.values():
                room.keep(avatar, resumable=avatar.avatar_id in self._owners
                          or avatar.tpose is not None)

