"""`posecast serve`'s session: every room of one server process, and its connections.

One connection = one handler task. The first message must be a Hello; a player then owns
one avatar (kept across reconnects with the resume secret of its Welcome), a spectator
only receives. Every message is decoded and validated by protocol/; a bad one is answered
with an Error naming what was wrong, counted, and the connection carries on. Spectators
receive through their own latest-wins outbox task, so a slow one never delays the room.

``Session`` is here with its admission and its players; its neighbours: ``spectating``
(spectators and replays), ``cluster_rooms`` (rooms shared through Redis), ``peers``
(who is at the other end), ``serving`` (``run_server``: the websockets server around it).
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import http
import itertools
import logging
import math
import secrets
from collections.abc import Coroutine, Sequence
from typing import Any

import numba
from websockets.asyncio.server import ServerConnection
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request
from websockets.protocol import State

from posecast.protocol import (
    PROTOCOL_VERSION,
    Calibrate,
    Error,
    ErrorCode,
    Hello,
    Leave,
    Ping,
    Pong,
    ProtocolError,
    Redirect,
    TrackerFrame,
    Welcome,
    decode_client,
    encode,
)
from posecast.protocol.arrivals import ArrivalStamps, arrival_time
from posecast.protocol.codec import decode_tracker_poses
from posecast.protocol.validation import safe_text
from posecast.server.address_budgets import (
    AddressBudgets,
    address_key,
    forwarded_client,
    normalized_ip,
)
from posecast.server.auth import JoinTokens, TokenError
from posecast.server.avatars import AvatarSolver
from posecast.server.busy import BusyPoll
from posecast.server.clock import now
from posecast.server.cluster import Cluster
from posecast.server.cluster_rooms import ClusterRooms
from posecast.server.display_error import TICK_S as DISPLAY_TICK_S
from posecast.server.display_error import DisplayErrorMeter
from posecast.server.eviction import Watchdog, close_now
from posecast.server.helper import spare_cores
from posecast.server.http_routes import Reply
from posecast.server.limits import (
    Budget,
    ServerLimits,
    frame_budget,
    player_frames_per_s,
)
from posecast.server.metrics import Metrics
from posecast.server.peers import (
    cap_send_buffers,
    client_address,
    closed_by_client,
    closed_words,
    peer,
    safe_name,
)
from posecast.server.prometheus import session_registry
from posecast.server.rejection_log import LineBudget, RejectionLog
from posecast.server.room import (
    Avatar,
    Room,
)
from posecast.server.spectating import SpectatingConnections
from posecast.solver.readers.gltf import load_makehuman
from posecast.solver.rig import Rig, build_rig

log = logging.getLogger("posecast.server")

HELLO_TIMEOUT = 5.0  # seconds a new connection has to say who it is
RECONNECT_GRACE = 30.0  # seconds a dropped player's avatar waits for its resume secret
# on stop, how long the open bursts and the spectators' outboxes get to empty before the
# connections close (a spectator that stopped reading would hold the stop forever)
DRAIN_TIMEOUT = 2.0
FLOOD_CLOSE_S = 1.0  # a flooding client's close handshake gets this long, then its socket goes
# an address refused this many upgrades (429) in its join window, and connecting still, is
# dropped as its TCP connection is accepted: a 429 costs ~0.6 ms of websockets' handshake
# code, a drop ~0.1 ms, and a client that honours Retry-After never gets this far
DROP_AFTER_REFUSALS = 16
DRAIN_POLL_S = 0.001
# a close the server began waits this long for the client's close frame, then drops the
# socket (websockets' default, 10 s, let a client that never answers hold its socket and
# keep being read that long); an honest client answers within a round trip
CLOSE_TIMEOUT_S = 2.0


class Session(ClusterRooms, SpectatingConnections):
    """All rooms of one server process."""

    def __init__(self, rig: Rig | None = None, solver: str = "analytic",
                 reconnect_grace: float = RECONNECT_GRACE, busy: bool = False,
                 helper: bool | None = None, limits: ServerLimits | None = None,
                 tokens: JoinTokens | None = None, cluster: Cluster | None = None,
                 trusted_proxies: Sequence[str] = ()) -> None:
        """``limits``: every cap and rate of the server (``server.limits``).
        ``cluster``: one of many processes sharing rooms through Redis (``server.cluster``;
        ``run_server`` starts it).
        ``trusted_proxies``: the addresses of reverse proxies in front; a connection
        from one counts as the client its X-Forwarded-For names, for every per-address
        limit and in the log.
        ``tokens``: admit only Hellos with a join token signed with its secret
        (``server.auth``); None: anyone joins any room.
        ``busy``: poll without sleeping and keep the frame path warm between bursts
        (``server.busy``); it takes a whole core. ``helper``: solve each batch with a
        helper thread on the cores this process is not pinned to (``server.helper``);
        by default with busy polling, where there are such cores."""
        self.rig = rig or build_rig(load_makehuman().skeleton)
        self.solver_name = solver
        self.reconnect_grace = reconnect_grace
        self.rooms: dict[str, Room] = {}
        self.limits = limits or ServerLimits()  # and the per-address budgets (setter)
        self.tokens = tokens
        self.trusted_proxies = frozenset(normalized_ip(a) for a in trusted_proxies)
        self._open_from: dict[str, int] = {}  # remote address -> its open connections
        self._errors: dict[ServerConnection, Budget] = {}  # each connection's error budget
        self._pings: dict[ServerConnection, Budget] = {}  # and its ping budget
        self._closing: set[asyncio.Task[None]] = set()
        self.metrics = Metrics()
        self.started = now()  # uptime, for /healthz and /metrics
        # GET /metrics: this session's figures, read when scraped (server.prometheus)
        self.registry = session_registry(self)
        self._ids = itertools.count(1)
        self._owners: dict[int, ServerConnection] = {}  # avatar id -> its live connection
        # log lines about rejections: sampled per connection, capped for the server
        self.log_budget = LineBudget(self.limits.log_lines_per_interval,
                                     self.limits.log_interval_s)
        # and the joined/left lines: a join-and-leave loop must not write two per
        # connection; what is left out is counted in the next line written
        self.join_log = LineBudget(self.limits.log_lines_per_interval,
                                   self.limits.log_interval_s)
        # stalled spectators and idle players, looked at once a second (``watch``)
        self.watchdog = Watchdog(self.limits.backlog_evict_s, self.limits.idle_player_s)
        # what viewers showed against what was solved, measured a tick at a time (``measure``)
        self.display = DisplayErrorMeter(self.rig, self.metrics.display_error,
                                         self.metrics.display_samples)
        self._rejection_logs: dict[ServerConnection, RejectionLog] = {}
        self.busy = BusyPoll(self.rig, solver) if busy else None
        # every room's avatars in one solver (avatar ids are the session's), so that one
        # helper thread serves them all; room for 32 before its arrays grow (and its
        # helper restarts)
        self.avatars = AvatarSolver(self.rig, solver, capacity=32, helper_cores=(
            spare_cores() if (busy if helper is None else helper) else ()))
        # before serving: a first join must not wait for the compiled solver (and the
        # helper) to load
        self.avatars.warm_up()
        # solve on the event loop's own thread: waking a worker thread costs more in a VM
        # than it saves on a batch of tens of avatars; scale out with processes instead
        numba.set_num_threads(1)
        self.cluster = cluster
        self._claiming: dict[str, asyncio.Lock] = {}  # one claim of a room at a time
        if cluster is not None:
            cluster.on_message = self._relayed
            cluster.lost_room = self._hand_over
            cluster.rejoined = self._rejoined

    @property
    def limits(self) -> ServerLimits:
        return self._limits

    @limits.setter
    def limits(self, limits: ServerLimits) -> None:
        self._limits = limits
        # per remote address (an IPv6 /64), kept after its connections close: a client
        # that reconnects gets no fresh budget (server.address_budgets)
        self._address_calibrations = AddressBudgets(
            limits.address_calibrations_per_s, limits.address_calibration_burst,
            limits.addresses_remembered)
        self._address_joins = AddressBudgets(
            limits.address_joins_per_s, limits.address_join_burst,
            limits.addresses_remembered)

    async def start_cluster(self) -> None:
        """Join the other processes (``ClusterError`` if Redis cannot be used): ids from
        this process's block, unique across the service."""
        if self.cluster is not None:
            first = await self.cluster.start()
            self._ids = itertools.count(first + 1)

    def room(self, name: str, relayed: bool = False) -> Room:
        if name not in self.rooms:  # rooms are created on first join
            self.rooms[name] = Room(name, self.avatars, self.metrics,
                                    bursts=self.busy.bursts if self.busy else None,
                                    limits=self.limits, cluster=self.cluster,
                                    relayed=relayed)
        return self.rooms[name]

    def _drop_room(self, room: Room) -> None:
        """An empty room leaves this process: its key in Redis, or its channel, goes."""
        if self.rooms.get(room.name) is room:
            room.flush_roster()  # its last removals, to the other processes' spectators
            del self.rooms[room.name]
            lock = self._claiming.get(room.name)
            if lock is not None and not lock.locked():  # one per room this process has
                del self._claiming[room.name]
            if self.cluster is not None:
                if room.relayed:
                    self._later(self.cluster.unwatch(room.name))
                else:
                    self.cluster.release(room.name)

    def _later(self, aw: Coroutine[Any, Any, None]) -> None:
        task = asyncio.get_running_loop().create_task(aw)
        self._closing.add(task)  # held until done: the loop keeps only weak references
        task.add_done_callback(self._closing.discard)

    @property
    def open_connections(self) -> int:
        """Websocket connections open now (admitted within the caps)."""
        return sum(self._open_from.values())

    def admit(self, connection: ServerConnection, request: Request) -> Reply | None:
        """A websocket upgrade, before the handshake: None lets it through; over its
        address's join budget, a 429 reply (``HttpRoutes``), the cheapest refusal there
        is: no websocket, no handler, no close handshake. Through a trusted proxy, the
        client is the one its X-Forwarded-For names (kept on the connection)."""
        peer = connection.remote_address
        if self._trusted_proxy(peer):
            client = forwarded_client(request.headers.get_all("X-Forwarded-For"))
            if client is not None:
                connection.forwarded_for = client  # type: ignore[attr-defined]
        t = now()
        joins = self._address_joins.get(address_key(client_address(connection)), t)
        if joins.take(t):
            return None
        self.metrics.limited["address_joins"] += 1
        self.metrics.rejected[ErrorCode.RATE_LIMITED.value] += 1
        wait = max(1, math.ceil(joins.refill_at - t))
        return Reply(f"too many new connections from your address: limit "
                     f"address_joins_per_s = {self.limits.address_joins_per_s:g} (burst "
                     f"{self.limits.address_join_burst}); retry in {wait} s\n".encode(),
                     "text/plain; charset=utf-8", http.HTTPStatus.TOO_MANY_REQUESTS,
                     headers=(("Retry-After", str(wait)),))

    def _trusted_proxy(self, peer: object) -> bool:
        """The peer (host, port) is a reverse proxy named by ``trusted_proxies``."""
        return isinstance(peer, tuple) and bool(peer) and str(peer[0]) in self.trusted_proxies

    def accepts(self, peername: object) -> bool:
        """A TCP connection as it is accepted, before websockets reads a byte: False
        (drop it, no reply) when its address keeps connecting with its join budget spent
        (``DROP_AFTER_REFUSALS``)."""
        if self._trusted_proxy(peername):
            return True  # its clients are told apart by their X-Forwarded-For, later
        joins = self._address_joins.peek(address_key(peername))
        if joins is None or joins.refused < DROP_AFTER_REFUSALS or joins.would_take(now()):
            return True
        self.metrics.limited["address_joins"] += 1
        self.metrics.rejected[ErrorCode.RATE_LIMITED.value] += 1
        return False

    async def handle(self, ws: ServerConnection) -> None:
        """A connection, admitted within the caps on connections (``ServerLimits``)."""
        try:
            await self._admitted(ws)
        except Exception as exc:  # a bug met by a connection: one line, budgeted
            # (a traceback per connection, at the connection rate, floods the log)
            self.metrics.internal_errors += 1
            if self.log_budget.take(now()):
                log.error("failed to handle a connection from %s: %s: %s", peer(ws),
                          type(exc).__name__, safe_text(str(exc), 160))
            log.debug("the failure in full", exc_info=True)
            with contextlib.suppress(Exception):
                await close_now(ws, 1011, "internal error")

    async def _admitted(self, ws: ServerConnection) -> None:
        address = address_key(client_address(ws))
        limits = self.limits
        if sum(self._open_from.values()) >= limits.connections:
            await self._refuse(ws, "connections", "the server is full")
            return
        if self._open_from.get(address, 0) >= limits.connections_per_address:
            await self._refuse(ws, "connections_per_address",
                               "too many connections from your address")
            return
        self._open_from[address] = self._open_from.get(address, 0) + 1
        self._errors[ws] = Budget(limits.errors_per_s, limits.error_burst)
        self._pings[ws] = Budget(limits.pings_per_s, limits.ping_burst)
        cap_send_buffers(ws, limits)
        try:
            await self._connection(ws)
        finally:
            self._errors.pop(ws, None)
            self._pings.pop(ws, None)
            self._open_from[address] -= 1
            if not self._open_from[address]:
                del self._open_from[address]

    async def _refuse(self, ws: ServerConnection, limit: str, words: str) -> None:
        """Refused at join: an Error naming the cap, then close 1008."""
        self.metrics.limited[limit] += 1
        self.metrics.rejected[ErrorCode.FULL] += 1
        with contextlib.suppress(ConnectionClosed):
            await ws.send(encode(Error(code=ErrorCode.FULL, message=(
                f"{words}: limit {limit} = {getattr(self.limits, limit)}"))))
            await ws.close(1008, f"limit {limit}")

    async def _connection(self, ws: ServerConnection) -> None:
        self.metrics.connections += 1
        conn_id = next(self._ids)
        try:
            hello = await self._hello(ws)
        except (ConnectionClosed, TimeoutError):
            return
        if hello is None:
            return
        if hello.room not in self.rooms and len(self.rooms) >= self.limits.rooms:
            await self._refuse(ws, "rooms", "no room for a new room")
            return
        if self.cluster is not None:  # where the room is owned
            if hello.role == "spectator":
                await self._watch(hello.room)
            else:
                url = await self._own(hello.room)
                if url is not None:
                    await self._redirect(ws, url)
                    return
        if hello.role == "player" and self._players_full(hello):
            await self._refuse(ws, "players_per_room", "the room is full")
            return
        room = self.room(hello.room)
        # who is who in the log: role, name, room and address on join and on leave
        who = (f"{hello.role} {safe_name(hello.display_name)} in room {safe_name(hello.room)} "
               f"from {peer(ws)}")
        self._log_join("%s joined (connection %d)", who, conn_id)
        t_joined = now()
        try:
            if hello.role == "player":
                await self._player(ws, conn_id, room, hello)
            elif hello.role == "replay":
                await self._replay(ws, conn_id, room)
            else:
                await self._spectator(ws, conn_id, room, hello)
        finally:
            self._log_join("%s left after %.1f s (%s)", who, now() - t_joined,
                           closed_words(ws))
            rejections = self._rejection_logs.pop(ws, None)
            if rejections is not None:
                rejections.summary()
        if room.empty:
            self._drop_room(room)

    def _log_join(self, text: str, *args: object) -> None:
        """A joined/left line, within ``join_log``; the first after some were left out
        says how many."""
        budget = self.join_log
        left_out = budget.suppressed
        if not budget.take(now()):
            return
        if left_out:
            budget.suppressed = 0
            log.info("(%d joined/left lines not logged: over %d per %g s)", left_out,
                     budget.lines, budget.interval)
        log.info(text, *args)

    async def _redirect(self, ws: ServerConnection, url: str) -> None:
        """A player of a room another process owns: sent there, to stream without a hop
        (``serve --redis``)."""
        with contextlib.suppress(ConnectionClosed):
            await ws.send(encode(Redirect(url=url)))
            await ws.close(1000, "redirected")

    def _players_full(self, hello: Hello) -> bool:
        """A new player would pass the room's cap (a reconnect keeps its place)."""
        room = self.rooms.get(hello.room)
        if room is None or room.find_by_resume(hello.resume) is not None:
            return False
        connected = sum(a.connected for a in room.avatars.values())
        return connected >= self.limits.players_per_room

    async def _hello(self, ws: ServerConnection) -> Hello | None:
        """The first message; anything else gets an Error and the connection is closed."""
        data = await asyncio.wait_for(ws.recv(), HELLO_TIMEOUT)
        arrival_time(ws, now)  # its stamp: the handlers pair the rest in order
        try:
            msg = decode_client(data)
            if not isinstance(msg, Hello):
                raise ProtocolError(ErrorCode.NOT_ALLOWED,
                                    f"the first message must be hello, got {msg.type}")
            if self.tokens is not None:  # with a secret: its tokens only, for this room
                try:
                    # a replay publishes avatars: a player's token admits it
                    role = "player" if msg.role == "replay" else msg.role
                    self.tokens.verify(msg.token, msg.room, role, msg.display_name)
                except TokenError as refused:
                    raise ProtocolError(ErrorCode.AUTH_FAILED, str(refused)) from None
        except ProtocolError as err:
            self.metrics.rejected[err.code] += 1
            if self.log_budget.take(now()):  # one line per connection: capped too
                log.info("refused a connection from %s: %s: %s", peer(ws), err.code,
                         safe_text(err.message, 160))
            await ws.send(encode(Error(code=err.code, message=safe_text(err.message))))
            await ws.close(1008, err.code)
            return None
        return msg

    # ------------------------------------------------------------------ players
    async def _player(self, ws: ServerConnection, conn_id: int, room: Room,
                      hello: Hello) -> None:
        avatar = room.find_by_resume(hello.resume)
        resumed = avatar is not None
        if avatar is None:
            self._make_room_for_an_avatar(room)
            # the resume secret comes from here, never from the client: 192 random bits
            avatar = Avatar(next(self._ids), room.unique_name(hello.display_name),
                            secrets.token_urlsafe(24))
            room.avatars[avatar.avatar_id] = avatar
        else:  # a reconnect: same avatar, same calibration; the old connection goes
            old = self._owners.get(avatar.avatar_id)
            if old is not None and old is not ws:
                await old.close(1000, "reconnected elsewhere")
        avatar.connected = True
        avatar.last_seq = -1  # seq counts per connection: a reconnect starts again
        self.watchdog.player_active(avatar.avatar_id, now())
        avatar.connection = ws if isinstance(ws, ArrivalStamps) else None
        self._owners[avatar.avatar_id] = ws
        limits = self.limits
        frames_per_s = player_frames_per_s(limits, hello.max_rate_hz)
        frames = frame_budget(limits, frames_per_s)
        # refusals in one window that only a flood makes: the connection is closed
        flood_at = math.floor(limits.frame_flood_factor * frames.burst) + 1
        calibrations = Budget(limits.calibrations_per_s, limits.calibration_burst)
        address = address_key(client_address(ws))
        if isinstance(ws, ArrivalStamps):
            ws.fast_path = functools.partial(self._tracker_frame_now, room, avatar, frames)
        said_bye = False
        try:  # the welcome too: a client gone right after its hello still leaves its avatar
            await ws.send(encode(Welcome(protocol_version=PROTOCOL_VERSION,
                                         connection_id=conn_id, avatar_id=avatar.avatar_id,
                                         server_time=now(), resume=avatar.resume,
                                         resumed=resumed, display_name=avatar.display_name)))
            async for data in ws:
                t_received = arrival_time(ws, now)
                try:
                    msg = decode_client(data)
                    if isinstance(msg, TrackerFrame):
                        self.metrics.frames_received += 1
                        try:
                            if not frames.take(t_received):
                                if frames.refused == 1:
                                    raise self._limited("frames", frames_per_s, "" if (
                                        hello.max_rate_hz is None) else (
                                        f"; {limits.frame_rate_slack:g} x the "
                                        f"{hello.max_rate_hz:g} Hz of hello.max_rate_hz"))
                                # told once per window: the clump a network stall
                                # delivers costs one Error, not one each; a flood ends
                                self.metrics.frames_rejected += 1
                                self.metrics.limited["frames"] += 1
                                if frames.refused == flood_at:
                                    self._close_soon(ws, 1008, f"flooding: over "
                                                     f"{frames_per_s:g} frames per second")
                                continue
                            if not room.is_calibrated(avatar.avatar_id):
                                raise ProtocolError(ErrorCode.NOT_CALIBRATED,
                                                    "send a calibrate message (T-pose) "
                                                    "before tracker frames")
                            if msg.seq <= avatar.last_seq:
                                raise ProtocolError(
                                    ErrorCode.OUT_OF_ORDER,
                                    f"tracker_frame.seq: {msg.seq} is not above the last "
                                    f"one, {avatar.last_seq}")
                            room.submit(avatar.avatar_id, msg, t_received)
                            avatar.last_seq = msg.seq
                        except (ProtocolError, ValueError):  # replied to below
                            self.metrics.frames_rejected += 1
                            raise
                    elif isinstance(msg, Calibrate):
                        if not calibrations.take(t_received):
                            raise self._limited("calibrations", limits.calibrations_per_s)
                        if not self._address_calibrations.take(address, t_received):
                            raise self._limited("address_calibrations",
                                                limits.address_calibrations_per_s)
                        room.calibrate(avatar, msg.roles, msg.poses)
                        self.metrics.calibrations += 1
                        self.watchdog.player_active(avatar.avatar_id, t_received)
                        if self.busy is not None:
                            self.busy.warm.calibrate(msg.roles, msg.poses)
                    else:
                        said_bye = isinstance(msg, Leave)
                        await self._common(ws, msg, t_received, "player")
                except ProtocolError as err:
                    await self._reject(ws, err)
                except ValueError as err:  # refused: a capture time off the clock, a bad T-pose
                    await self._reject(ws, ProtocolError(ErrorCode.INVALID, str(err)))
                except ConnectionClosed:
                    raise
                except Exception:  # a bug met by one message: it is answered, the rest goes on
                    await self._internal_error(ws)
        except ConnectionClosed:
            pass
        finally:
            if isinstance(ws, ArrivalStamps):
                ws.fast_path = None
            if self._owners.get(avatar.avatar_id) is ws:
                del self._owners[avatar.avatar_id]
                avatar.connected = False
                avatar.connection = None
                self._forget_later(room, avatar, at_once=said_bye or closed_by_client(ws))

    def _tracker_frame_now(self, room: Room, avatar: Avatar, frames: Budget,
                           data: bytes | bytearray | memoryview,
                           t_received: float) -> bool:
        """A player's message as its bytes are read (``ArrivalStamps.fast_path``): a
        valid tracker frame of a calibrated avatar goes to the room at once, without
        waiting for the handler task's turn. Anything else (other messages, anything
        wrong) returns False and takes the handler's way, which replies to it."""
        frame = decode_tracker_poses(data)
        # out of order: the handler's way refuses it
        if frame is None or frame.seq <= avatar.last_seq \
                or not room.is_calibrated(avatar.avatar_id):
            return False
        if not frames.would_take(t_received):  # over the rate: the handler's way refuses it
            return False
        try:
            room.submit(avatar.avatar_id, frame, t_received)
        except ValueError:  # the solver refused the poses: the handler's way explains
            return False
        frames.take(t_received)
        avatar.last_seq = frame.seq
        self.metrics.frames_received += 1
        if self.busy is not None:
            self.busy.warm.frame = data
        return True

    def _make_room_for_an_avatar(self, room: Room) -> None:
        """At the room's cap of avatars, the oldest of those whose player left goes now
        rather than after its reconnect grace: joins and leaves cannot grow a room."""
        cap = self.limits.avatars_per_room
        gone = [a for a in room.avatars.values() if not a.connected]  # in join order
        for avatar in gone[:max(0, len(room.avatars) - cap + 1)]:
            self.metrics.limited["avatars_per_room"] += 1
            room.remove_avatar(avatar.avatar_id)

    def _close_soon(self, ws: ServerConnection, code: int, reason: str) -> None:
        """Close a connection that floods the server: stop reading it at once (what it
        has queued would cost everyone else the time to read and reject it), send the
        close frame with the reason, and drop the socket if the close has not finished
        within FLOOD_CLOSE_S (its close reply waits behind its flood, unread)."""
        with contextlib.suppress(AttributeError, RuntimeError):
            ws.transport.pause_reading()
        task = asyncio.get_running_loop().create_task(self._close_or_drop(ws, code, reason))
        self._closing.add(task)  # held until done: the loop keeps only weak references
        task.add_done_callback(self._closing.discard)

    @staticmethod
    async def _close_or_drop(ws: ServerConnection, code: int, reason: str) -> None:
        try:
            await asyncio.wait_for(ws.close(code, reason), FLOOD_CLOSE_S)
        except TimeoutError:
            ws.transport.abort()

    def _limited(self, limit: str, per_s: float, detail: str = "") -> ProtocolError:
        self.metrics.limited[limit] += 1
        return ProtocolError(ErrorCode.RATE_LIMITED,
                             f"over {per_s:g} {limit} per second (limit {limit}_per_s"
                             f"{detail})")

    def _forget_later(self, room: Room, avatar: Avatar, at_once: bool = False) -> None:
        """Keep a dropped player's avatar for a while in case it reconnects; one that
        said goodbye (Leave) goes ``at_once``."""
        def forget() -> None:
            if not avatar.connected and room.avatars.get(avatar.avatar_id) is avatar:
                room.remove_avatar(avatar.avatar_id)
                if room.empty:
                    self._drop_room(room)
        if at_once or self.reconnect_grace <= 0:
            forget()
        else:
            asyncio.get_running_loop().call_later(self.reconnect_grace, forget)

    # ------------------------------------------------------------------ stopping
    async def drain(self, timeout: float = DRAIN_TIMEOUT) -> bool:
        """Wait until no burst is open and every spectator's outbox has sent what it
        holds: then each frame counted as solved was delivered to every spectator or
        counted as dropped. False if ``timeout`` passed first (a stalled spectator)."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while not all(room.settled for room in self.rooms.values()):
            if loop.time() >= deadline:
                return False
            await asyncio.sleep(DRAIN_POLL_S)
        return True

    # ------------------------------------------------------------------ both
    async def _common(self, ws: ServerConnection, msg: object, t_received: float,
                      role: str) -> None:
        if isinstance(msg, Ping):
            pings = self._pings.get(ws)
            if pings is not None and not pings.take(t_received):
                raise self._limited("pings", self.limits.pings_per_s)
            await ws.send(encode(Pong(t0=msg.t0, t1=t_received, t2=now())))
        elif isinstance(msg, Leave):
            await ws.close(1000, "bye")
        else:
            kind = getattr(msg, "type", type(msg).__name__)
            raise ProtocolError(ErrorCode.NOT_ALLOWED, f"{kind} is not for a {role} to send")

    async def _reject(self, ws: ServerConnection, err: ProtocolError) -> None:
        self.metrics.rejected[err.code] += 1
        budget = self._errors.get(ws)
        if budget is not None and not budget.take(now()):
            # errors keep coming: the client is not listening to them, so stop talking
            self.metrics.limited["errors"] += 1
            if ws.state is State.OPEN:  # once; and not awaited: while the handler
                # waits, websockets stops reading at max_queue and never sees the reply
                self._close_soon(ws, 1008, f"too many errors (over "
                                 f"{self.limits.errors_per_s:g}/s)")
            return
        rejections = self._rejection_logs.get(ws)
        if rejections is None:
            rejections = self._rejection_logs[ws] = RejectionLog(
                log, peer(ws), self.log_budget, now, self.limits.log_first_rejections,
                self.limits.log_interval_s)
        rejections.rejected(err.code, err.message)
        with contextlib.suppress(ConnectionClosed):
            # escaped and cut: whatever went into the text, the reply can be built
            await ws.send(encode(Error(code=err.code, message=safe_text(err.message))))

    # ------------------------------------------------------------------ eviction
    async def watch(self) -> None:
        """Run while serving: close the spectators whose backlog stays full and the
        players that stopped sending (``server.eviction``)."""
        while True:
            await asyncio.sleep(self.watchdog.interval)
            self.evict(now())

    async def measure(self) -> None:
        """Run while serving: the display error of the samples viewers sent
        (``server.display_error``), off the frame path."""
        while True:
            await asyncio.sleep(DISPLAY_TICK_S)
            self.display.tick(list(self.rooms.values()), now())

    def evict(self, t: float) -> None:
        dog, rooms = self.watchdog, self.rooms.values()
        for s in dog.stalled([s for r in rooms for s in r.spectators.values()], t):
            if s.connection is not None and s.connection.state is State.OPEN:
                self._evict(s.connection, "backlog_evict_s", 1013,
                            f"too slow: took no frame for {dog.backlog_evict_s:g} s")
        for avatar in dog.idle([a for r in rooms for a in r.avatars.values()], t):
            ws = self._owners.get(avatar.avatar_id)
            if ws is not None and ws.state is State.OPEN:
                self._evict(ws, "idle_player_s", 1008,
                            f"idle: no tracker frame for {dog.idle_player_s:g} s")

    def _evict(self, ws: ServerConnection, limit: str, code: int, reason: str) -> None:
        self.metrics.limited[limit] += 1
        if self.log_budget.take(now()):
            log.info("closing %s: %s", peer(ws), reason)
        task = asyncio.get_running_loop().create_task(close_now(ws, code, reason))
        self._closing.add(task)  # held until done: the loop keeps only weak references
        task.add_done_callback(self._closing.discard)

    async def close_stalled(self) -> None:
        """On stop, after the drain: a spectator whose outbox still holds frames is not
        reading; its close must not wait behind its full buffer."""
        stalled = [s.connection for room in self.rooms.values()
                   for s in room.spectators.values()
                   if not s.outbox.idle and s.connection is not None]
        if stalled:
            await asyncio.gather(*(close_now(ws, 1001, "server stopping") for ws in stalled))

    async def _internal_error(self, ws: ServerConnection) -> None:
        self.metrics.internal_errors += 1
        if self.log_budget.take(now()):  # a client that found a bug must not flood the log
            log.exception("failed to handle a message from %s", peer(ws))
        await self._reject(ws, ProtocolError(ErrorCode.INTERNAL,
                                             "the server failed to handle this message"))
