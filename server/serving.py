"""Serving a session: the websockets server around ``Session`` (``run_server``), its
connections' class (arrival stamps, the accept-time drop, the cut-off after a failure),
and the stop that drains before it closes."""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import signal
import ssl
from collections.abc import Callable, Sequence
from typing import cast

from websockets.asyncio.server import Server, ServerConnection, serve

from posecast.protocol.arrivals import ArrivalStamps
from posecast.server.app import CLOSE_TIMEOUT_S, DRAIN_TIMEOUT, FLOOD_CLOSE_S, Session
from posecast.server.auth import is_loopback
from posecast.server.clock import now
from posecast.server.http_routes import session_routes
from posecast.server.tls import allowed_origins

log = logging.getLogger("posecast.server")

async def run_server(host: str, port: int, session: Session | None = None,
                     stop: asyncio.Event | None = None,
                     ready: Callable[[int], None] | None = None,
                     handle_signals: bool = False,
                     drain_timeout: float = DRAIN_TIMEOUT,
                     tls: ssl.SSLContext | None = None,
                     origins: Sequence[str] | None = None) -> Session:
    """Serve until ``stop`` is set (or SIGINT/SIGTERM with ``handle_signals``), then
    drain (``Session.drain``) and close every connection cleanly; ``ready(port)`` once
    listening (port 0 picks a free one). ``tls``: serve wss:// (``server.tls``);
    ``origins``: the browser origins allowed (requests without an Origin header too)."""
    session = session or Session()
    await session.start_cluster()  # ClusterError (one line) when Redis cannot be used
    _say_access(session, host)
    stop = stop or asyncio.Event()
    loop = asyncio.get_running_loop()
    if handle_signals:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
    server: Server
    async with serve(session.handle, host, port, compression=None,
                     create_connection=_connection_class(session),
                     # GET /healthz, /metrics; upgrades within their address's budget
                     process_request=session_routes(session),
                     max_size=session.limits.max_message_bytes,
                     max_queue=session.limits.max_queue, ssl=tls,
                     close_timeout=CLOSE_TIMEOUT_S,
                     origins=allowed_origins(origins)) as server:
        bound = next(iter(server.sockets)).getsockname()[1]
        if session.cluster is not None and not session.cluster.public_url:
            # where the others send this process's players: as it listens (loopback
            # and one-machine set-ups; behind a proxy, serve --public-url)
            shown = "127.0.0.1" if host in ("", "0.0.0.0", "::") else host
            session.cluster.public_url = (f"{'ws' if tls is None else 'wss'}://"
                                          f"{shown}:{bound}")
        log.info("posecast server on %s://%s:%d", "ws" if tls is None else "wss", host, bound)
        log.info("health and metrics on the same port: %s://%s:%d/healthz and /metrics",
                 "http" if tls is None else "https", host, bound)
        # what start-up made (modules, kernels, the solver) is kept for good: a full
        # collection then walks only what the rooms make, not ~10^6 objects
        gc.freeze()
        if ready is not None:
            ready(bound)
        poller = (loop.create_task(session.busy.run(stop))
                  if session.busy is not None else None)
        watchdog = loop.create_task(session.watch())
        measuring = loop.create_task(session.measure())
        try:
            await stop.wait()
        finally:
            watchdog.cancel()
            measuring.cancel()
            if poller is not None:
                poller.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await poller
        if not await session.drain(drain_timeout):
            await session.close_stalled()
        server.close(close_connections=True)
        await server.wait_closed()
    for room in session.rooms.values():  # a burst opened while the connections closed
        room.discard_pending()
    session.avatars.close()
    if session.cluster is not None:  # its rooms' keys go: others may take them at once
        await session.cluster.close()
    return session


def _say_access(session: Session, host: str) -> None:
    """Who may join, said once at start: an open server beyond loopback is a warning."""
    if session.tokens is not None:
        log.info("join tokens required: only tokens signed with this server's secret join")
        return
    log.info("open: anyone can join any room; --secret-file to require tokens")
    if not is_loopback(host):
        log.warning("listening on %s without a secret: anyone who reaches this port can "
                    "join any room (posecast serve --secret-file F)", host or "every address")




class TimestampedServerConnection(ArrivalStamps, ServerConnection):
    """A frame is received when its bytes reach this process (``protocol.arrivals``),
    not when its handler gets to it: time spent behind the rest of a burst or a solve is
    the server's. A player's tracker frames take its ``fast_path`` (set once joined):
    no queue and no task switch, ~10 us of the server's time per frame."""

    clock = staticmethod(now)
    _cut_off = False
    _dropped = False  # at accept (``accepts``): websockets never sees this connection
    # a TCP connection's peer address -> whether to go on with it (``Session.accepts``)
    accepts: Callable[[object], bool] | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        if self.accepts is not None and not self.accepts(transport.get_extra_info("peername")):
            self._dropped = True  # no handler task is made: nothing else refers to it
            cast(asyncio.Transport, transport).abort()  # (uvloop's is not a subclass)
            return
        super().connection_made(transport)

    def connection_lost(self, exc: Exception | None) -> None:
        if not self._dropped:
            super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        # the server failed the connection (1009: a frame over max_size; 1002, 1007): it
        # sent its close frame and its EOF, and websockets would read and discard what
        # the client still sends until its close timeout (a client sending 1 MiB frames
        # pushed ~56 GB through loopback that way). Reading stops now; the socket goes
        # once the close frame has had FLOOD_CLOSE_S to reach the client
        protocol = self.protocol  # (a close the client began also ends in an EOF)
        if protocol.eof_sent and protocol.close_rcvd is None and not self._cut_off:
            self._cut_off = True
            cut_off(self.transport, FLOOD_CLOSE_S)


def _connection_class(session: Session) -> type[TimestampedServerConnection]:
    """The connections of ``session``'s server: each asks it whether to go on as it
    is accepted."""
    return type("SessionConnection", (TimestampedServerConnection,),
                {"accepts": staticmethod(session.accepts)})


def cut_off(transport: asyncio.Transport, grace_s: float) -> None:
    """Read nothing more from ``transport`` and abort it after ``grace_s`` (what it has
    written meanwhile reaches the peer, unless the peer does not read)."""
    with contextlib.suppress(AttributeError, RuntimeError):  # closing already
        transport.pause_reading()
    asyncio.get_running_loop().call_later(grace_s, transport.abort)


def install_fast_loop() -> bool:
    """uvloop when installed: a faster event loop for the same code."""
    try:
        import uvloop
    except ImportError:
        return False
    asyncio.set_event_loop_policy(uvloop.EventLoopPolicy())
    return True
