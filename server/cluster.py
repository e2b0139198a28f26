"""Many server processes as one service, through Redis (``posecast serve --redis URL``).

As Colyseus does with its Redis presence, processes share state only through Redis:
- a room is owned by one process, the one whose key ``posecast:room:NAME:owner`` holds
  its id, its public URL and when it last renewed the key (every RENEW_S; the key
  expires after OWNER_TTL_S). A player who joins elsewhere is sent to the owner (a
  Redirect: the frames then take no extra hop). An owner that stopped renewing for
  STALE_S is dead (SIGKILL, a lost machine): the next process a player of the room
  reaches takes the room over at once instead of waiting for the key to expire;
- the owner publishes each batch and roster once on the room's channel; the other
  processes with spectators of the room subscribe and hand the bytes on (``server.relay``);
- every avatar's record (resume secret, name, T-pose) is in the hash
  ``posecast:room:NAME:avatars``, so the process that takes a room over brings its
  avatars back calibrated;
- avatar ids come in blocks (``posecast:ids``), so ids stay unique across processes.

Redis lost while running: every room carries on in the process that has it, served to
its own clients; the link logs it once, retries every RETRY_S, and when Redis is back
claims its rooms again and rewrites their records (``Cluster.rejoined``).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import secrets
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

import redis.asyncio as aioredis
from redis.asyncio.connection import AbstractConnection
from redis.exceptions import RedisError, ResponseError

from posecast.server.relay import AvatarRecord, relay_envelope

log = logging.getLogger("posecast.cluster")

OWNER_TTL_S = 3.0  # an owner key outlives a dead owner this long at most
RENEW_S = 0.25  # how often an owner renews its keys
STALE_S = 0.8  # an owner silent this long is dead: its rooms may be taken over
RETRY_S = 0.5  # while Redis is lost: how often to try it again
COMMAND_TIMEOUT_S = 1.0  # a command that takes longer means Redis is lost
CLOSE_WAIT_S = 1.0  # on stop, for the link's tasks to end
ID_BLOCK = 1 << 20  # avatar and connection ids per process start (below 2**53 for JS)
PREFIX = "posecast:"

# renew an owner key only if it still names this process (compare-and-set, in Redis)
_RENEW = """
local v = redis.call('GET', KEYS[1])
if v and cjson.decode(v)['id'] == ARGV[1] then
  redis.call('SET', KEYS[1], ARGV[2], 'PX', ARGV[3]) return 1 end
return 0"""
# take a stale owner key over: only if it is still the value that was read
_STEAL = """
if redis.call('GET', KEYS[1]) == ARGV[1] then
  redis.call('SET', KEYS[1], ARGV[2], 'PX', ARGV[3]) return 1 end
return 0"""
_RELEASE = """
local v = redis.call('GET', KEYS[1])
if v and cjson.decode(v)['id'] == ARGV[1] then redis.call('DEL', KEYS[1]) return 1 end
return 0"""


class ClusterError(RuntimeError):
    """Redis cannot be used at start: one line for the user."""


def owner_key(room: str) -> str:
    return f"{PREFIX}room:{room}:owner"


def avatars_key(room: str) -> str:
    return f"{PREFIX}room:{room}:avatars"


def room_channel(room: str) -> str:
    return f"{PREFIX}room:{room}:live"


@dataclass
class ClusterStats:
    published: int = 0  # envelopes handed to Redis
    relayed: int = 0  # envelopes received from other processes' rooms
    unpublished: int = 0  # dropped while Redis was lost
    takeovers: int = 0  # rooms taken over from a dead owner
    redirects: int = 0  # players sent to the owner
    lost: int = 0  # times Redis was lost


class Cluster:
    """This process's link to the others. ``on_message(room, data)``: an envelope
    published by another process on the channel of a room this process watches;
    ``rejoined()``: Redis is back after a loss (the session claims its rooms again)."""

    def __init__(self, url: str, public_url: str) -> None:
        self.url = url
        self.public_url = public_url
        self.process_id = secrets.token_hex(8)
        self.redis: aioredis.Redis = aioredis.from_url(
            url, socket_timeout=COMMAND_TIMEOUT_S, socket_connect_timeout=COMMAND_TIMEOUT_S)
        self.up = False
        self.stats = ClusterStats()
        self.owned: set[str] = set()  # rooms whose key names this process
        self.watched: set[str] = set()  # rooms whose channel this process subscribes to
        self.on_message: Callable[[str, bytes], None] = lambda room, data: None
        self.rejoined: Callable[[], Awaitable[None]] | None = None
        self.lost_room: Callable[[str, str], None] = lambda room, url: None
        self._queue: list[tuple[Any, ...]] = []  # commands for the writer, in order
        self._wake = asyncio.Event()
        self._tasks: list[asyncio.Task[None]] = []
        self._publisher: AbstractConnection | None = None  # see _connect_links
        self._subscriber: AbstractConnection | None = None
        self._release_later: list[str] = []  # rooms given up: their keys go
        self._closed = False
        self._renew = self.redis.register_script(_RENEW)
        self._steal = self.redis.register_script(_STEAL)
        self._release = self.redis.register_script(_RELEASE)

    # ------------------------------------------------------------------ life
    async def start(self) -> int:
        """Connect, or ClusterError naming the URL and why; the first id of this
        process's block."""
        try:
            await self.redis.ping()
            first = int(await self.redis.incrby(f"{PREFIX}ids", ID_BLOCK)) - ID_BLOCK
            await self._connect_links()
        except (RedisError, OSError) as exc:
            await self.redis.aclose()
            raise ClusterError(f"cannot use Redis at {self.url}: {_why(exc)}") from None
        self.up = True
        loop = asyncio.get_running_loop()
        self._tasks += [loop.create_task(self._writer()), loop.create_task(self._renewer())]
        log.info("one of a cluster through Redis at %s, as %s", self.url, self.process_id)
        return first

    async def close(self) -> None:
        """Give up this process's rooms (others may take them at once) and disconnect."""
        self._closed = True
        self._wake.set()
        for task in self._tasks:
            task.cancel()
        # bounded: redis-py may swallow a cancel that lands inside a command, and the
        # loops end on ``_closed`` at their next turn instead
        if self._tasks:
            await asyncio.wait(self._tasks, timeout=CLOSE_WAIT_S)
        if self.up:
            with contextlib.suppress(RedisError, OSError):
                await self._flush()
                for room in list(self.owned):
                    await self._release(keys=[owner_key(room)], args=[self.process_id])
        for link in (self._publisher, self._subscriber):
            if link is not None:
                with contextlib.suppress(RedisError, OSError):
                    await link.disconnect()
        with contextlib.suppress(RedisError, OSError):
            await self.redis.aclose()

    async def _connect_links(self) -> None:
        """Two connections of their own beside the pool: one that publishes (commands
        written in order, replies read by a task of their own) and one subscribed. On
        this machine a hop through them took p50 0.37 / p99 0.55 ms against 0.52 / 1.0
        through the pool and its PubSub object (raw sockets: 0.20 / 0.32)."""
        for link in (self._publisher, self._subscriber):
            if link is not None:
                with contextlib.suppress(RedisError, OSError):
                    await link.disconnect()
        pool = self.redis.connection_pool  # its class: TCP, TLS (rediss://) or unix://
        # no socket timeout: with one, redis-py writes through asyncio.wait_for, a task
        # of its own, whose turn came after the room's whole local fan-out (1-5 ms)
        kwargs = {**pool.connection_kwargs, "socket_timeout": None}
        publisher = pool.connection_class(**kwargs)
        subscriber = pool.connection_class(**kwargs)
        await publisher.connect()
        await subscriber.connect()
        channels = [f"{PREFIX}process:{self.process_id}",
                    *(room_channel(r) for r in self.watched)]
        await subscriber.send_command("SUBSCRIBE", *channels)
        self._publisher, self._subscriber = publisher, subscriber
        loop = asyncio.get_running_loop()
        self._tasks = [t for t in self._tasks if not t.done()]
        self._tasks += [loop.create_task(self._replies(publisher)),
                        loop.create_task(self._listen(subscriber))]

    def _lost(self, exc: BaseException) -> None:
        if self.up and not self._closed:
            self.up = False
            self.stats.lost += 1
            log.warning("Redis at %s lost (%s): every room carries on in its process, "
                        "served to its own clients; retrying every %g s", self.url,
                        _why(exc), RETRY_S)
            self.stats.unpublished += sum(1 for c in self._queue if c[0] == "PUBLISH")
            self._queue.clear()

    # ------------------------------------------------------------------ ownership
    def _owner_value(self) -> str:
        return json.dumps({"id": self.process_id, "url": self.public_url, "at": time.time()})

    async def claim(self, room: str) -> str | None:
        """Own ``room``, or the URL of the live process that owns it. Without Redis the
        room is served here (and claimed again when Redis is back)."""
        if not self.up:
            self.owned.add(room)
            return None
        key = owner_key(room)
        try:
            for _ in range(3):  # a key that expired between two reads: try again
                value = self._owner_value()
                if await self.redis.set(key, value, nx=True, px=int(OWNER_TTL_S * 1000)):
                    self.owned.add(room)
                    return None
                old = await self.redis.get(key)
                if old is None:
                    continue
                owner = _parse_owner(old)
                if owner is None or owner["id"] == self.process_id:
                    await self.redis.set(key, value, px=int(OWNER_TTL_S * 1000))
                    self.owned.add(room)
                    return None
                silent = time.time() - float(owner["at"])
                if silent < STALE_S:
                    self.stats.redirects += 1
                    return str(owner["url"])
                if await self._steal(keys=[key], args=[old, value, int(OWNER_TTL_S * 1000)]):
                    self.stats.takeovers += 1
                    log.warning("room %r taken over from %s (%s), silent for %.1f s",
                                room, owner["id"], owner["url"], silent)
                    self.owned.add(room)
                    return None
        except (RedisError, OSError) as exc:
            self._lost(exc)
        self.owned.add(room)
        return None

    def release(self, room: str) -> None:
        """The room is gone from this process: its key goes (queued, in order)."""
        if room in self.owned:
            self.owned.discard(room)
            self._release_later.append(room)
            self._wake.set()

    async def _renewer(self) -> None:
        """Renew this process's keys; try Redis again while it is lost."""
        while not self._closed:
            await asyncio.sleep(RENEW_S if self.up else RETRY_S)
            if not self.up:
                await self._try_again()
                continue
            rooms = list(self.owned)
            if not rooms:
                continue
            try:
                value = self._owner_value()
                async with self.redis.pipeline(transaction=False) as pipe:
                    for room in rooms:
                        await self._renew(keys=[owner_key(room)],
                                          args=[self.process_id, value,
                                                int(OWNER_TTL_S * 1000)], client=pipe)
                    renewed = await pipe.execute()
            except (RedisError, OSError) as exc:
                self._lost(exc)
                continue
            for room, ok in zip(rooms, renewed, strict=True):
                if not ok and room in self.owned:  # taken while this process was silent
                    await self._reclaim(room)

    async def _reclaim(self, room: str) -> None:
        """A room whose key this process lost: claim it again, or hand it to the owner."""
        self.owned.discard(room)
        url = await self.claim(room)
        if url is not None:
            log.warning("room %r is owned by %s now: its players are sent there", room, url)
            self.lost_room(room, url)

    async def _try_again(self) -> None:
        try:
            await self.redis.ping()
        except (RedisError, OSError):
            return
        try:
            await self._connect_links()
        except (RedisError, OSError):
            return
        self.up = True
        log.warning("Redis at %s is back: claiming this process's rooms again", self.url)
        for room in list(self.owned):
            await self._reclaim(room)
        if self.rejoined is not None:
            await self.rejoined()

    # ------------------------------------------------------------------ avatars
    def save(self, room: str, record: AvatarRecord) -> None:
        self._push(("HSET", avatars_key(room), str(record.avatar_id), record.pack()))

    def forget(self, room: str, avatar_id: int) -> None:
        self._push(("HDEL", avatars_key(room), str(avatar_id)))

    async def records(self, room: str) -> list[AvatarRecord]:
        """The room's avatars as Redis has them (unreadable ones skipped, logged)."""
        if not self.up:
            return []
        try:
            raw = await self.redis.hgetall(avatars_key(room))
        except (RedisError, OSError) as exc:
            self._lost(exc)
            return []
        records = []
        for field, data in raw.items():
            try:
                records.append(AvatarRecord.unpack(data))
            except ValueError as err:
                log.warning("room %r: avatar %r in Redis skipped: %s", room, field, err)
        return sorted(records, key=lambda r: r.avatar_id)

    # ------------------------------------------------------------------ fan-out
    def publish(self, room: str, kind: str, payload: bytes) -> None:
        """A batch or roster of an owned room to the processes watching it; never waits
        (one writer task sends the queue in order, pipelined)."""
        if not self.up:
            self.stats.unpublished += 1
            return
        # the envelope is made as the writer sends it: "published" is when the bytes
        # go to Redis, and the room's own spectators are served first
        self._push(("PUBLISH", room_channel(room), kind, payload))

    def _push(self, command: tuple[Any, ...]) -> None:
        if self.up:
            self._queue.append(command)
            self._wake.set()

    async def _writer(self) -> None:
        while not self._closed:
            await self._wake.wait()
            self._wake.clear()
            try:
                await self._flush()
            except (RedisError, OSError) as exc:
                self._lost(exc)

    async def _flush(self) -> None:
        """The queued commands, written in order on the publishing connection (its
        replies are read by ``_replies``); then the keys of rooms given up."""
        link = self._publisher
        while self._queue and link is not None:
            commands, self._queue = self._queue, []
            packed = link.pack_commands(
                ("PUBLISH", c[1], relay_envelope(c[2], self.process_id, c[3]))
                if c[0] == "PUBLISH" else c for c in commands)
            await link.send_packed_command(packed, check_health=False)
            self.stats.published += sum(1 for c in commands if c[0] == "PUBLISH")
        while self._release_later:
            room = self._release_later.pop()
            if room not in self.owned:
                await self._release(keys=[owner_key(room)], args=[self.process_id])

    async def _replies(self, link: AbstractConnection) -> None:
        """Read the publishing connection's replies (an error reply is logged; a lost
        connection is Redis lost)."""
        try:
            while not self._closed:
                try:
                    await link.read_response(timeout=math.inf, disconnect_on_error=False)
                except ResponseError as refused:  # one command's error, not a lost link
                    log.warning("Redis refused a command: %s", refused)
        except (RedisError, OSError) as exc:
            if link is self._publisher:
                self._lost(exc)

    async def watch(self, room: str) -> None:
        """Receive what the owner of ``room`` publishes (``on_message``)."""
        self.watched.add(room)
        await self._send_subscriber("SUBSCRIBE", room_channel(room))

    async def unwatch(self, room: str) -> None:
        self.watched.discard(room)
        await self._send_subscriber("UNSUBSCRIBE", room_channel(room))

    async def _send_subscriber(self, *command: str) -> None:
        if self.up and self._subscriber is not None:
            try:
                await self._subscriber.send_command(*command)
            except (RedisError, OSError) as exc:
                self._lost(exc)

    async def _listen(self, link: AbstractConnection) -> None:
        """The subscribed connection: each message of a room's channel to
        ``on_message`` (subscribe and unsubscribe replies pass)."""
        prefix, suffix = f"{PREFIX}room:".encode(), b":live"
        try:
            while not self._closed:
                reply = await link.read_response(timeout=math.inf, push_request=True,
                                                 disconnect_on_error=False)
                if not isinstance(reply, list) or len(reply) != 3 or reply[0] != b"message":
                    continue
                channel = reply[1]
                if channel.startswith(prefix) and channel.endswith(suffix):
                    self.stats.relayed += 1
                    room = channel[len(prefix):-len(suffix)].decode(errors="replace")
                    self.on_message(room, reply[2])
        except (RedisError, OSError) as exc:
            if link is self._subscriber:
                self._lost(exc)


def _parse_owner(value: bytes | str) -> dict[str, Any] | None:
    try:
        owner = json.loads(value)
        return owner if isinstance(owner, dict) and {"id", "url", "at"} <= owner.keys() \
            else None
    except ValueError:
        return None


def _why(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def check_redis_url(text: str) -> str:
    """redis://HOST[:PORT][/DB] or rediss:// or unix://; ValueError otherwise."""
    if not text.startswith(("redis://", "rediss://", "unix://")):
        raise ValueError(f"must be a Redis URL such as redis://127.0.0.1:6379, got {text!r}")
    return text
