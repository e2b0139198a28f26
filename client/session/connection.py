"""One client connection to a posecast server: connect, hello/welcome, clock sync, leave.

Players and spectators share this layer (like the thin I/O layers of the websockets
library over its sans-I/O core): ``open_session`` connects and does the handshake, a
``Session`` sends and receives protocol messages, answers its own Pongs into a
``ClockEstimator`` and pings on a schedule (a quick burst at start, then one a second).
Every way a session can fail for the user (refused, unknown host, no answer, an Error
in reply to Hello, the server going away) becomes one ``SessionError`` whose message is
a single line naming the URL and the reason.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import gc
import logging
import random
import socket
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from secrets import token_bytes
from types import TracebackType
from typing import Literal
from urllib.parse import urlsplit

from pydantic import ValidationError
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import (
    ConnectionClosed,
    InvalidHandshake,
    InvalidMessage,
    InvalidStatus,
    InvalidURI,
)
from websockets.protocol import State

from posecast.client.session import reads_first
from posecast.client.session.tls import CAFileError, client_tls_context, tls_failure
from posecast.client.sources.base import now
from posecast.protocol import (
    MAX_MESSAGE_BYTES,
    PROTOCOL_VERSION,
    AvatarBatch,
    AvatarRoster,
    ClientMessage,
    ClockEstimator,
    Error,
    Hello,
    Leave,
    Message,
    Ping,
    Pong,
    ProtocolError,
    Redirect,
    Welcome,
    decode,
    encode,
)
from posecast.protocol.arrivals import ArrivalStamps, Data, arrival_time
from posecast.protocol.codec import decode_stream
from posecast.protocol.framing import masked_binary_frame
from posecast.protocol.pose_coding import RosterCodings
from posecast.protocol.validation import protocol_error, safe_text

# unsent bytes beyond which a player's frames are dropped rather than queued: ~20 frames
SEND_BUFFER_LIMIT = 16 * 1024

log = logging.getLogger(__name__)

# seconds for TCP + websocket handshake, and again for the Welcome (generous: a server's
# first room may stall while its solver compiles)
OPEN_TIMEOUT = 10.0
CLOSE_TIMEOUT = 1.0  # a peer that does not answer our close is not worth a longer wait
# close codes after which a client tries again: going away (a server stopping), lost
# (1006), internal error, service restart, try again later, bad gateway (a proxy)
RETRY_CLOSE_CODES = frozenset({1001, 1006, 1011, 1012, 1013, 1014})
# reconnecting: the first wait, doubling up to the longest, each +-20% so that the
# players of a restarted server do not all come back in the same millisecond
RECONNECT_FIRST_S = 0.25
RECONNECT_MAX_S = 2.0
RECONNECT_GIVE_UP_S = 600.0  # a server down for ten minutes is not restarting
# how long a viewer may spend taking a backlog before it draws (``Session.catch_up``):
# a 90 Hz room's backlog of a 75 ms draw is taken in well under a millisecond
CATCH_UP_S = 0.010

# clock sync: a burst of pings at start so the first frames carry a good offset, then a
# slow refresh so the estimate follows drift (ClockEstimator keeps 10 s of samples).
# Synced once SYNC_MIN_SAMPLES are in: the estimator takes the median of its best 3.
SYNC_MIN_SAMPLES = 3
SYNC_BURST = 5
SYNC_BURST_INTERVAL = 0.02
SYNC_INTERVAL = 1.0


TOO_MANY_REQUESTS = 429  # a server's answer to too many joins from one address
MAX_REDIRECTS = 3  # a room's owner is one hop away; more means processes disagree


def server_urls(url: str) -> list[str]:
    """``--server`` may name several processes of one service, comma-separated: a
    client tries them in turn (``serve --redis``)."""
    return [u.strip() for u in url.split(",") if u.strip()]


class SessionError(Exception):
    """A session could not start or ended unasked; ``str()`` is one line for the user."""

    def __init__(self, url: str, reason: str, code: str | None = None,
                 reached: bool = True, retry: bool = False) -> None:
        super().__init__(f"{url}: {reason}")
        self.url = url
        self.reason = reason
        self.code = code  # the server's ErrorCode when it refused us, else None
        self.reached = reached  # False: no websocket to the server opened at all
        # worth trying again (``Reconnect``): the server went away, restarts or is not
        # up yet; not when it refused us, told us to go, or is not a posecast server
        self.retry = retry


def _connect_reason(exc: BaseException, url: str = "") -> str:
    """Why connecting failed, in words for the user."""
    tls = tls_failure(exc, urlsplit(url).scheme == "wss")
    if tls is not None:  # before OSError: ssl.SSLError is one
        return tls
    # with several addresses (localhost: ::1 and 127.0.0.1) asyncio raises a plain
    # OSError("Multiple exceptions: ...") rather than ConnectionRefusedError
    if isinstance(exc, ConnectionRefusedError) or (
            isinstance(exc, OSError) and f"[Errno {errno.ECONNREFUSED}]" in str(exc)):
        return "connection refused (is a posecast server running there?)"
    if isinstance(exc, socket.gaierror):
        return f"cannot resolve the host name ({exc.strerror or exc})"
    if isinstance(exc, InvalidURI):
        return "not a websocket URL (expected ws://HOST:PORT)"
    if isinstance(exc, InvalidStatus) and exc.response.status_code == TOO_MANY_REQUESTS:
        wait = exc.response.headers.get("Retry-After", "?")
        return (f"the server refuses new connections from this address for now (too "
                f"many, HTTP 429); it asks to wait {safe_text(wait, 16)} s")
    if isinstance(exc, InvalidStatus):
        return (f"not a posecast server: HTTP {exc.response.status_code} instead of a "
                f"websocket upgrade")
    if isinstance(exc, InvalidMessage) and urlsplit(url).scheme == "ws":
        # a TLS server drops a plain HTTP request without a word
        return (f"no websocket reply ({exc}); if the server uses TLS, use wss:// "
                f"instead of ws://")
    if isinstance(exc, InvalidHandshake):
        return f"websocket handshake failed ({exc})"
    if isinstance(exc, TimeoutError):
        return "no answer (timed out)"
    if isinstance(exc, OSError):
        return f"cannot connect ({exc.strerror or exc})"
    return f"{type(exc).__name__}: {exc}"


def _worth_retrying(exc: BaseException, url: str) -> bool:
    """Connecting failed in a way that may pass: refused or unreachable (a server that
    restarts), timed out, or a proxy's 5xx while the server behind it is down; not a TLS
    failure, a bad URL or something that is not a posecast server."""
    if tls_failure(exc, urlsplit(url).scheme == "wss") is not None:
        return False
    if isinstance(exc, InvalidStatus):  # 429: joins from this address paused a while
        code = exc.response.status_code
        return code >= 500 or code == TOO_MANY_REQUESTS
    if isinstance(exc, InvalidURI | InvalidHandshake):
        return False
    return isinstance(exc, OSError | TimeoutError)


def _retry_after_close(exc: ConnectionClosed) -> bool:
    """The connection ended in a way a reconnect can mend: lost without a close, or
    closed by a server going away, restarting or asking us to come back later; not a
    goodbye, a takeover ("reconnected elsewhere", 1000) or a policy close (1008)."""
    return exc.rcvd is None or exc.rcvd.code in RETRY_CLOSE_CODES


def _closed_reason(exc: ConnectionClosed, last_error: Error | None) -> str:
    """Why the server ended the connection: its close code/reason and its last Error."""
    frame = exc.rcvd
    if frame is None:
        why = "the connection to the server was lost"
    else:
        why = f"the server closed the connection: {frame}"  # "1001 (going away)"
    if last_error is not None:
        why += f"; last error: {last_error.code}: {last_error.message}"
    return why


def make_hello(url: str, role: Literal["player", "spectator", "replay"], room: str, name: str,
               token: str | None = None, max_rate_hz: float | None = None) -> Hello:
    """The Hello to join with; SessionError (one line, naming the field) if it is invalid,
    e.g. a room name the protocol does not allow."""
    try:
        return Hello(protocol_version=PROTOCOL_VERSION, role=role, room=room,
                     display_name=name, token=token, max_rate_hz=max_rate_hz)
    except ValidationError as exc:
        raise SessionError(url, f"cannot join: {protocol_error(exc, 'hello').message}",
                           ) from None


class TimestampedConnection(ArrivalStamps, ClientConnection):
    """A client connection that notes when each message reached this process
    (``protocol.arrivals``)."""

    clock = staticmethod(now)


class RedirectedError(SessionError):
    """The server sent us to the process that owns the room (``Redirect``)."""

    def __init__(self, url: str, target: str) -> None:
        super().__init__(url, f"sent to {target}, which serves the room")
        self.target = target


async def open_session(url: str, hello: Hello, *, timeout: float = OPEN_TIMEOUT,
                       max_size: int = MAX_MESSAGE_BYTES,
                       cafile: Path | None = None) -> Session:
    """Connect to ``url``, send ``hello``, wait for the Welcome; raise SessionError if not.
    ``url``: one server, or several of one service comma-separated, tried in turn
    while they cannot be reached; a server's Redirect to the room's owner is followed.
    A wss:// server's certificate must be vouched for by ``cafile`` (PEM CA
    certificates) if given, else by the system's trust store."""
    urls = server_urls(url) or [url]
    for i, one in enumerate(urls):
        try:
            session = await _open_following(one, hello, timeout, max_size, cafile)
        except SessionError as err:
            if not err.retry or i == len(urls) - 1:
                raise
        else:
            # what start-up made (modules, kernels, rigs: ~10^6 objects) is kept for
            # good: a full collection then walks only the session's own objects, not
            # all of them (130 ms in the demo's spectators, their p99)
            gc.freeze()
            return session
    raise AssertionError("unreachable")


async def _open_following(url: str, hello: Hello, timeout: float, max_size: int,
                          cafile: Path | None) -> Session:
    """``_open_one``, following the Redirects of a service's processes (same scheme
    only: a wss:// server cannot send us to plain ws://)."""
    first = url
    for _ in range(MAX_REDIRECTS + 1):
        try:
            return await _open_one(url, hello, timeout, max_size, cafile)
        except RedirectedError as moved:
            if urlsplit(moved.target).scheme != urlsplit(first).scheme:
                raise SessionError(url, f"the server sent us to {moved.target}: not "
                                   f"{urlsplit(first).scheme}:// as asked") from None
            url = moved.target
    raise SessionError(first, f"sent on more than {MAX_REDIRECTS} times (do the servers "
                       f"share one Redis?)", retry=True)


async def _open_one(url: str, hello: Hello, timeout: float, max_size: int,
                    cafile: Path | None) -> Session:
    try:
        tls = client_tls_context(cafile) if urlsplit(url).scheme == "wss" else None
    except CAFileError as exc:
        raise SessionError(url, str(exc), reached=False) from None
    try:
        # compression off: poses are packed floats that deflate barely shrinks, and it
        # costs latency; no proxy: a real-time stream should not detour through one
        ws = await connect(url, compression=None, max_size=max_size, open_timeout=timeout,
                           close_timeout=CLOSE_TIMEOUT, proxy=None, ssl=tls,
                           create_connection=TimestampedConnection)
    except (OSError, InvalidURI, InvalidHandshake, TimeoutError) as exc:
        raise SessionError(url, _connect_reason(exc, url),
                           reached=isinstance(exc, InvalidHandshake),
                           retry=_worth_retrying(exc, url)) from None
    try:
        welcome = await _handshake(url, ws, hello, timeout)
    except BaseException:  # SessionError, or a cancel mid-handshake: do not leak the socket
        await ws.close()
        raise
    return Session(url, ws, welcome)


async def _handshake(url: str, ws: ClientConnection, hello: Hello, timeout: float) -> Welcome:
    try:
        await ws.send(encode(hello))
        async with asyncio.timeout(timeout):
            data = await ws.recv()
        arrival_time(ws, now)  # the welcome's stamp: receive() pairs the rest in order
        reply = decode(data)
    except TimeoutError:
        raise SessionError(url, f"no welcome from the server within {timeout:g} s",
                           retry=True) from None
    except ConnectionClosed as exc:
        raise SessionError(url, _closed_reason(exc, None) + " during the handshake",
                           retry=_retry_after_close(exc)) from None
    except ProtocolError as exc:
        raise SessionError(url, f"not a posecast server reply ({exc})") from None
    if isinstance(reply, Error):
        raise SessionError(url, f"the server refused to join: {reply.code}: {reply.message}",
                           code=reply.code)
    if isinstance(reply, Redirect):
        raise RedirectedError(url, reply.url)
    if not isinstance(reply, Welcome):
        raise SessionError(url, f"expected a welcome from the server, got {reply.type!r}")
    return reply


async def stop_task(task: asyncio.Task[None]) -> None:
    """Cancel ``task`` and wait for it to end, dropping whatever it raised.

    Not ``suppress(CancelledError): await task``: that would also swallow a cancel of
    the caller itself, which arrives as the same exception.
    """
    task.cancel()
    await asyncio.wait([task])
    if not task.cancelled():
        task.exception()  # retrieved, so asyncio does not log it as never retrieved


class Session:
    """An open, welcomed connection: typed send/receive, clock estimate, leave.

    Use it as ``async with await open_session(...) as s:``; leaving the block sends
    Leave and closes. Call ``start_clock_sync`` once a task reads ``receive`` (Pongs are
    consumed there), then ``await wait_synced()`` before sending times.
    """

    def __init__(self, url: str, ws: ClientConnection, welcome: Welcome) -> None:
        self.url = url
        self.ws = ws
        self.welcome = welcome
        self.clock = ClockEstimator()
        self.last_error: Error | None = None  # latest Error from the server, for messages
        self.bytes_received = 0
        # the rosters' codings: how the batches that follow them unpack
        self.codings = RosterCodings()
        self.sent_codings = RosterCodings()  # a replay's: the rosters it sent
        self._synced = asyncio.Event()
        self._pinger: asyncio.Task[None] | None = None
        self._leaving = False
        self._decoding = False  # a message read, its decoding one loop pass away
        # ``deliver``: the handlers, the messages read and not yet handed over, and what
        # a handler raised (it ends the session)
        self._handlers: tuple[Callable[[Message, float], None],
                              Callable[[ProtocolError], None]] | None = None
        self._read: list[tuple[Data, float]] = []
        self._failed: BaseException | None = None

    @property
    def connection_id(self) -> int:
        return self.welcome.connection_id

    @property
    def avatar_id(self) -> int | None:
        return self.welcome.avatar_id

    # ------------------------------------------------------------------ messages
    async def send(self, message: ClientMessage | AvatarRoster | AvatarBatch) -> None:
        """Send one message (a replay sends rosters and batches); SessionError if the
        server is gone."""
        try:
            await self.ws.send(encode(message, self.sent_codings))
            self.sent_codings.learn(message)
        except ConnectionClosed as exc:
            raise SessionError(self.url, _closed_reason(exc, self.last_error),
                               retry=not self._leaving and _retry_after_close(exc)) from None

    def send_now(self, data: bytes) -> bool:
        """Write a message already encoded at once, without waiting (a player's frame
        goes out the moment its pose is read); False if it was dropped because the
        connection is not open or the server has not read the frames before (over
        SEND_BUFFER_LIMIT unsent bytes: a newer frame is worth more than a queued one)."""
        ws = self.ws
        transport = ws.transport
        if transport is None or transport.get_write_buffer_size() > SEND_BUFFER_LIMIT \
                or ws.protocol.state is not State.OPEN or transport.is_closing() \
                or ws.send_in_progress is not None:  # never, as no send is fragmented
            return False
        # framed here and written at once (no await, no lock): what websockets would
        # write, without its per-frame objects (``protocol.framing``)
        transport.write(masked_binary_frame(data, token_bytes(4)))
        return True

    def caught_up(self) -> bool:
        """Whether the reading task has taken every message that reached this machine:
        none in hand, none in websockets' queue, no byte in the kernel's receive buffer."""
        return (not self._decoding and not self._read
                and not getattr(self.ws, "arrivals", None) and unread_bytes(self.ws) == 0)

    async def catch_up(self, max_s: float = CATCH_UP_S) -> None:
        """Give the event loop to the reading task until it has taken everything that
        arrived (``caught_up``), for at most ``max_s``. A viewer calls it before each
        draw: a draw holds the loop while frames keep coming, and drawing without taking
        them first would show a backlog that grows by every draw (seconds behind at
        13 fps; one draw behind with it, docs/performance.md "Slow viewers")."""
        deadline = now() + max_s
        # two passes at least: the first reads the socket, the second runs the reader
        for _ in range(2):
            await asyncio.sleep(0)
        while not self.caught_up() and now() < deadline:
            await asyncio.sleep(0)

    async def receive(self) -> tuple[Message, float]:
        """The next message other than a Pong, and ``now()`` right when it arrived.

        Pongs go into ``clock``. Raises SessionError when the connection ends (stop the
        reading task before ``close``: the server answers our Leave by closing) and
        ProtocolError for bytes that do not decode, which the caller counts and survives.
        """
        while True:
            try:
                data = await self.ws.recv()
            except ConnectionClosed as exc:
                if self._failed is not None:  # a handler of ``deliver`` raised
                    raise self._failed from None
                why = ("the session was closed" if self._leaving
                       else _closed_reason(exc, self.last_error))
                raise SessionError(self.url, why, retry=not self._leaving
                                   and _retry_after_close(exc)) from None
            t = arrival_time(self.ws, now)  # when the bytes reached this process
            if not getattr(self.ws, "arrivals", None):
                # decode on the loop's next pass: when many connections share a process
                # (the demo's spectators), the reads that came in meanwhile are taken
                # (and stamped) first, so one connection's decoding does not count as
                # the next one's network time. Not while more of ours wait: a backlog
                # (a viewer's long draw) is taken in one go, not one message per pass
                self._decoding = True
                await asyncio.sleep(0)
                self._decoding = False
            msg = self._take(data, t)
            if msg is not None:
                return msg, t

    def _take(self, data: Data | str, t: float) -> Message | None:
        """A message read at ``t``, decoded (a text frame: ProtocolError); None for a
        Pong (it goes to the clock)."""
        self.bytes_received += len(data)
        msg = decode_stream(data, self.codings)
        if isinstance(msg, Pong):
            self._add_pong(msg, t)
            return None
        if isinstance(msg, Error):
            self.last_error = msg
        return msg

    def deliver(self, on_message: Callable[[Message, float], None],
                on_error: Callable[[ProtocolError], None]) -> None:
        """Hand each binary message over as the loop reads it, not through ``receive``.

        It is stamped when read, decoded once the loop has read (and stamped) whatever
        else came (``reads_first``), and given to ``on_message`` with its arrival time
        (Pongs go to the clock; bytes that do not decode, to ``on_error``). websockets' queue and
        a reading task's turn per message were a sixth of the demo's spectators' time.
        A task must still await ``receive``: it takes what came before this call (and
        any text frame) and raises when the connection ends, or what a handler raised.
        """
        self._handlers = (on_message, on_error)
        self.ws.fast_path = self._arrived  # type: ignore[attr-defined]

    def _arrived(self, data: Data, t: float) -> bool:
        # decoded once the loop's reads settle (``reads_first``), not between them
        reads_first.of(asyncio.get_running_loop()).read(
            None if self._read else self.hand_over)
        self._read.append((data, t))
        return True

    def hand_over(self) -> None:
        """Decode the messages read so far and give them to ``deliver``'s handlers
        (``reads_first`` calls it once the loop's reads settle; call it at the end of a
        session to take the last ones)."""
        read, self._read = self._read, []
        if self._handlers is None or self._failed is not None:
            return
        on_message, on_error = self._handlers
        for data, t in read:
            msg: Message | ProtocolError | None
            try:
                msg = self._take(data, t)
            except ProtocolError as err:
                msg = err
            try:
                if isinstance(msg, ProtocolError):
                    on_error(msg)
                elif msg is not None:
                    on_message(msg, t)
            except Exception as exc:  # a handler's bug: the reading task raises it
                self._failed = exc
                self.ws.fast_path = None  # type: ignore[attr-defined]
                if self.ws.transport is not None:
                    self.ws.transport.abort()
                return

    # ------------------------------------------------------------------ clock
    def _add_pong(self, pong: Pong, t3: float) -> None:
        if self.clock.add_pong(pong, t3) and len(self.clock) >= SYNC_MIN_SAMPLES:
            self._synced.set()

    async def _ping_loop(self, burst: int, burst_interval: float, interval: float) -> None:
        k = 0
        while True:
            try:
                await self.ws.send(encode(Ping(t0=now())))
            except ConnectionClosed:
                return  # receive() reports it; a ping has nothing to add
            k += 1
            await asyncio.sleep(burst_interval if k < burst else interval)

    def start_clock_sync(self, burst: int = SYNC_BURST, burst_interval: float =
                         SYNC_BURST_INTERVAL, interval: float = SYNC_INTERVAL) -> None:
        """Ping ``burst`` times ``burst_interval`` apart, then every ``interval`` s."""
        if self._pinger is None:
            self._pinger = asyncio.create_task(
                self._ping_loop(burst, burst_interval, interval), name="posecast-ping")

    async def wait_synced(self, timeout: float = 1.0) -> bool:
        """Wait until SYNC_MIN_SAMPLES Pongs are in; False on timeout (then the offset is
        whatever the samples so far give, 0.0 with none)."""
        try:
            async with asyncio.timeout(timeout):
                await self._synced.wait()
        except TimeoutError:
            log.warning("%s: clock sync incomplete after %g s (%d samples)", self.url,
                        timeout, len(self.clock))
            return False
        return True

    # ------------------------------------------------------------------ leave
    async def close(self, reason: str = "") -> None:
        """Send Leave (if the connection is still open) and close; never raises."""
        if self._pinger is not None:
            await stop_task(self._pinger)
        if self._leaving:
            return
        self._leaving = True
        with contextlib.suppress(ConnectionClosed, OSError):
            await self.ws.send(encode(Leave(reason=reason)))
        with contextlib.suppress(ConnectionClosed, OSError):
            await self.ws.close()

    async def __aenter__(self) -> Session:
        return self

    async def __aexit__(self, exc_type: type[BaseException] | None,
                        exc: BaseException | None, tb: TracebackType | None) -> None:
        await self.close()


def unread_bytes(ws: ClientConnection) -> int:
    """Bytes that reached the kernel's receive buffer of ``ws`` and were not read yet (0
    where the platform cannot tell)."""
    transport = ws.transport
    sock = transport.get_extra_info("socket") if transport is not None else None
    if sock is None:
        return 0
    try:
        import fcntl  # POSIX only: elsewhere a viewer catches up with what was read
        import termios
        return struct.unpack("i", fcntl.ioctl(sock.fileno(), termios.FIONREAD,
                                               b"\0\0\0\0"))[0]
    except (ImportError, OSError, ValueError):  # not POSIX, closed, or not a socket
        return 0


@dataclass
class Reconnect:
    """How a player or viewer comes back after its session was lost (``SessionError``
    with ``retry``): waits that double from ``first_s`` to ``max_s``, one line through
    ``say`` when the session is lost and one when it is back, and a SessionError when
    ``give_up_s`` passed or the server refuses us."""

    say: Callable[[str], None] = log.warning
    first_s: float = RECONNECT_FIRST_S
    max_s: float = RECONNECT_MAX_S
    give_up_s: float = RECONNECT_GIVE_UP_S
    count: int = 0  # sessions opened again

    async def again(self, lost: SessionError, hello: Hello, *, cafile: Path | None = None,
                    stop: asyncio.Event | None = None, url: str | None = None
                    ) -> Session | None:
        """A new session after ``lost`` (the same ``hello``; a player's carries its
        resume secret), or None if ``stop`` was set meanwhile. ``url``: the servers to
        try (``--server``, maybe several): the one lost is tried last."""
        urls = server_urls(url or lost.url) or [lost.url]
        if lost.url in urls and len(urls) > 1:
            urls.remove(lost.url)
            urls.append(lost.url)
        url = ",".join(urls)
        self.say(f"connection lost ({lost.reason}); reconnecting")
        t0, delay = now(), self.first_s
        while True:
            if stop is None:
                await asyncio.sleep(delay * random.uniform(0.8, 1.2))
            else:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stop.wait(), delay * random.uniform(0.8, 1.2))
                if stop.is_set():
                    return None
            try:
                session = await open_session(url, hello, cafile=cafile)
            except SessionError as err:
                if not err.retry:
                    raise
                if now() - t0 >= self.give_up_s:
                    raise SessionError(url, f"gave up reconnecting after {self.give_up_s:g} "
                                       f"s: {err.reason}") from None
                delay = min(2.0 * delay, self.max_s)
                continue
            self.count += 1
            welcome = session.welcome
            what = (f"back in room {hello.room!r}" if welcome.avatar_id is None
                    else "avatar resumed, still calibrated" if welcome.resumed
                    else "a new avatar (the server had lost the old one): calibrating again")
            self.say(f"reconnected after {now() - t0:.1f} s; {what}")
            return session
