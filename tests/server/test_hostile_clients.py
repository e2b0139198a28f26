"""Hostile clients, second round (issue 27), each through a real socket on 127.0.0.1.

1. Any characters in any string field of a Hello get an Error or a Welcome, never a
   1011, and write no traceback to the server's log.
2. An address's calibration budget outlives its connections; joins per address are a
   budget of their own, refused with a 429 before any websocket exists.
3. A player that never calibrates costs the room's spectators no roster, and the
   rosters of many changes at once are merged.
4. A connection refused for its size (1009) is read no more.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import socket
from collections.abc import AsyncIterator, Awaitable, Callable

import msgpack
import pytest
from conftest import serving
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from stream_decode import decode
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed, InvalidMessage, InvalidStatus

from posecast.client.builtin import builtin_motion_path
from posecast.client.session.connection import SessionError, open_session
from posecast.client.session.player import calibrate_message
from posecast.client.sources.bvh_source import BvhSource
from posecast.protocol import (
    PROTOCOL_VERSION,
    AvatarRoster,
    Error,
    Hello,
    Ping,
    Pong,
    Welcome,
    encode,
)
from posecast.server.app import DROP_AFTER_REFUSALS, Session
from posecast.server.auth import JoinTokens
from posecast.server.limits import ServerLimits

TIMEOUT = 10.0  # generous: the machine is shared; a wait that passes it is a hang
STRING_FIELDS = ("room", "display_name", "token", "resume")
# what an attacker puts in a string: beyond ASCII, control characters and terminal
# escapes, a forged log line, very long, empty, and a lone surrogate's escape
HOSTILE_STRINGS = ("é", "\U0001f600 emoji", "\x00\x07\x1b[31mred", "a\nINFO forged line",
                   "\u00e9" * 1000, "x" * 10_000, "", "\u202etxt.exe", "\ud800")
# many joins from one address is what these tests do: the join budget has its own test
MANY_JOINS = {"address_joins_per_s": 1e6, "address_join_burst": 10**6}


def _calibration() -> bytes:
    source = BvhSource(builtin_motion_path(), loop=True, rate_hz=90.0)
    try:
        return encode(calibrate_message(source.calibration(), 0.0))
    finally:
        source.close()


CALIBRATION = _calibration()


def _hello(role: str, room: str, name: str, **fields: object) -> bytes:
    raw: dict[str, object] = {"type": "hello", "protocol_version": PROTOCOL_VERSION,
                              "role": role, "room": room, "display_name": name}
    raw.update(fields)
    # a lone surrogate is not UTF-8: sent as the bytes a client could put on the wire
    return msgpack.packb({k: v.encode("utf-8", "surrogatepass") if isinstance(v, str)
                          and _has_surrogate(v) else v for k, v in raw.items()})


def _has_surrogate(text: str) -> bool:
    return any(0xD800 <= ord(c) <= 0xDFFF for c in text)


def run(session: Session, test: Callable[[str], Awaitable[None]]) -> None:
    async def main() -> None:
        async with serving(session) as url:
            await asyncio.wait_for(test(url), 120)
    asyncio.run(main())


@contextlib.asynccontextmanager
async def player(url: str, room: str, name: str = "p") -> AsyncIterator[ClientConnection]:
    async with connect(url, compression=None) as ws:
        await ws.send(encode(Hello(protocol_version=PROTOCOL_VERSION, role="player",
                                   room=room, display_name=name)))
        assert isinstance(decode(await ws.recv()), Welcome)
        yield ws


async def handled(ws: ClientConnection) -> None:
    """Everything sent before is handled: a Ping's Pong comes back after it."""
    await ws.send(encode(Ping(t0=0.0)))
    while not isinstance(decode(await asyncio.wait_for(ws.recv(), TIMEOUT)), Pong):
        pass


async def reply_and_close(url: str, hello: bytes) -> tuple[str, int | None]:
    """The first reply to ``hello`` ("welcome", "error") and the close code, if the
    server closed the connection."""
    async with connect(url, compression=None, max_size=None) as ws:
        await ws.send(hello)
        try:
            first = msgpack.unpackb(await asyncio.wait_for(ws.recv(), TIMEOUT))
        except ConnectionClosed:
            return "closed", ws.close_code
        kind = str(first.get("type")) if isinstance(first, dict) else repr(first)
        if kind == "error":
            await asyncio.wait_for(ws.wait_closed(), TIMEOUT)
            return kind, ws.close_code
        return kind, None


def _assert_no_traceback(caplog: pytest.LogCaptureFixture) -> None:
    bad = [r for r in caplog.records if r.exc_info or r.levelno >= logging.ERROR]
    assert not bad, [r.getMessage() for r in bad]


# ------------------------------------------------------------------ 1: Hello's strings
@pytest.mark.parametrize("secret", [False, True], ids=["open", "with-secret"])
def test_every_string_of_a_hello_gets_an_error_or_a_welcome(
        secret: bool, caplog: pytest.LogCaptureFixture) -> None:
    """Each string field of Hello, as player and as spectator, with each hostile value,
    against a room that holds an avatar (the resume secret is compared with its own):
    an Error and a 1008, or a Welcome; never a 1011, and no traceback in the log."""
    tokens = JoinTokens(b"s" * 32) if secret else None
    session = Session(reconnect_grace=0.0, tokens=tokens, limits=ServerLimits(**MANY_JOINS))
    caplog.set_level(logging.DEBUG, logger="posecast.server")

    async def test(url: str) -> None:
        good = {"token": tokens.mint("r", "player", ttl_s=600) if tokens else None}
        async with contextlib.AsyncExitStack() as stack:
            if tokens is None:  # an avatar in the room: find_by_resume has one to compare
                await stack.enter_async_context(player(url, "r", "owner"))
            seen: set[str] = set()
            for role in ("player", "spectator"):
                for name in STRING_FIELDS:
                    for value in HOSTILE_STRINGS:
                        fields = {"room": "r", "display_name": "x",
                                  "token": good["token"], name: value}
                        room, shown = fields.pop("room"), fields.pop("display_name")
                        message = _hello(role, str(room), str(shown), **{
                            k: v for k, v in fields.items() if v is not None})
                        kind, code = await reply_and_close(url, message)
                        seen.add(kind)
                        if len(message) > session.limits.max_message_bytes:
                            assert (kind, code) == ("closed", 1009)  # refused at its header
                            continue
                        assert kind in ("welcome", "error"), (role, name, value, kind)
                        assert code in (None, 1008), (role, name, value, code)
            assert seen == {"welcome", "error", "closed"}  # every answer met: a real test

    run(session, test)
    _assert_no_traceback(caplog)


HELLO_VALUES = st.one_of(st.text(max_size=80), st.binary(max_size=40), st.none(),
                         st.integers(), st.floats(), st.lists(st.text(max_size=4),
                                                                max_size=3))
FUZZ = settings(max_examples=60, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture,
                                       HealthCheck.too_slow])


class _Live:
    """One server with an avatar in room "r", on a loop of its own thread: hypothesis
    calls each example synchronously."""

    def __init__(self) -> None:
        self.session = Session(reconnect_grace=0.0, limits=ServerLimits(**MANY_JOINS))
        self.loop = asyncio.new_event_loop()
        self.url = ""

    def __enter__(self) -> _Live:
        import threading

        started = threading.Event()
        self._stop = asyncio.Event()

        async def main() -> None:
            async with serving(self.session) as url, player(url, "r", "owner"):
                self.url = url
                started.set()
                await self._stop.wait()
        self._thread = threading.Thread(target=self.loop.run_until_complete,
                                        args=(main(),), daemon=True)
        self._thread.start()
        assert started.wait(60)
        return self

    def call(self, aw: Awaitable[tuple[str, int | None]]) -> tuple[str, int | None]:
        return asyncio.run_coroutine_threadsafe(aw, self.loop).result(60)  # type: ignore[arg-type]

    def __exit__(self, *exc: object) -> None:
        self.loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(30)


def test_fuzzed_hello_fields_never_crash_the_handler(
        caplog: pytest.LogCaptureFixture) -> None:
    """Hypothesis: any value (text of any characters, bytes, numbers, lists, none) in
    any field of a Hello, as any role: an Error or a Welcome, never a 1011."""
    caplog.set_level(logging.DEBUG, logger="posecast.server")
    with _Live() as live:
        @FUZZ
        @given(role=st.sampled_from(["player", "spectator", "replay", "x"]),
               field=st.sampled_from([*STRING_FIELDS, "max_rate_hz", "extra"]),
               value=HELLO_VALUES)
        def check(role: str, field: str, value: object) -> None:
            raw: dict[str, object] = {"type": "hello", "protocol_version": PROTOCOL_VERSION,
                                      "role": role, "room": "r", "display_name": "f",
                                      field: value}
            kind, code = live.call(reply_and_close(live.url, msgpack.packb(raw)))
            assert kind in ("welcome", "error") and code in (None, 1008), (
                role, field, value, kind, code)
        check()
    _assert_no_traceback(caplog)


# ------------------------------------------------------------------ 2: per-address budgets
def test_the_calibration_budget_of_an_address_outlives_its_connections() -> None:
    """The loop of issue 27: connect, three calibrations, drop. Each connection has a
    fresh per-connection budget, but the address's is the same one: 4 taken in all."""
    session = Session(reconnect_grace=0.0, limits=ServerLimits(
        calibration_burst=3, address_calibration_burst=4, address_calibrations_per_s=0.01,
        **MANY_JOINS))

    async def test(url: str) -> None:
        errors = 0
        for i in range(5):
            async with player(url, "loop", f"p{i}") as ws:
                for _ in range(3):
                    await ws.send(CALIBRATION)
                await ws.send(encode(Ping(t0=0.0)))
                while not isinstance(msg := decode(await ws.recv()), Pong):
                    assert isinstance(msg, Error) and "address_calibrations" in msg.message
                    errors += 1
        assert session.metrics.calibrations == 4
        assert errors == 15 - 4 == session.metrics.limited["address_calibrations"]

    run(session, test)


def test_joins_over_an_address_budget_get_a_429_that_the_client_explains() -> None:
    session = Session(reconnect_grace=0.0, limits=ServerLimits(
        address_join_burst=3, address_joins_per_s=0.05))

    async def test(url: str) -> None:
        for _ in range(3):  # the burst: joined, and left
            async with player(url, "j"):
                pass
        with pytest.raises(InvalidStatus) as refused:
            await connect(url, compression=None)
        response = refused.value.response
        assert response.status_code == 429
        assert int(response.headers["Retry-After"]) >= 1
        assert b"address_joins_per_s" in response.body
        # the client's own words, and a reconnect loop keeps trying later
        hello = Hello(protocol_version=PROTOCOL_VERSION, role="spectator", room="j",
                      display_name="v")
        with pytest.raises(SessionError) as lost:
            await open_session(url, hello)
        assert "HTTP 429" in lost.value.reason and lost.value.retry
        assert session.metrics.limited["address_joins"] == 2
        # /healthz is no join: still answered
        reader, writer = await asyncio.open_connection("127.0.0.1", int(url.rsplit(":", 1)[1]))
        writer.write(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
        assert (await reader.readline()).startswith(b"HTTP/1.1 200")
        writer.close()

    run(session, test)


def test_an_address_that_keeps_connecting_is_dropped_as_it_is_accepted() -> None:
    """After DROP_AFTER_REFUSALS 429s in its window, the address's connections are
    dropped before websockets reads them; once the window has passed it joins again."""
    session = Session(reconnect_grace=0.0, limits=ServerLimits(
        address_join_burst=2, address_joins_per_s=1.0))  # a window of 2 s

    async def test(url: str) -> None:
        for _ in range(2):
            async with player(url, "d"):
                pass
        for _ in range(DROP_AFTER_REFUSALS):
            with pytest.raises(InvalidStatus):
                await connect(url, compression=None)
        with pytest.raises((InvalidMessage, OSError)):  # no reply at all
            await connect(url, compression=None)
        assert session.metrics.limited["address_joins"] == DROP_AFTER_REFUSALS + 1
        await asyncio.sleep(2.5)  # the window has passed: a full budget again
        async with player(url, "d"):
            pass

    run(session, test)


@pytest.mark.parametrize("trusted", [True, False], ids=["trusted-proxy", "no-proxy"])
def test_behind_a_trusted_proxy_each_forwarded_client_has_its_own_budgets(
        trusted: bool, caplog: pytest.LogCaptureFixture) -> None:
    """nginx in front (docs/deploy.md) appends the client's address to X-Forwarded-For:
    with the proxy trusted, each client has its own join budget (the entries a client
    wrote itself before it prove nothing); without, the header is ignored."""
    caplog.set_level(logging.INFO, logger="posecast.server")
    session = Session(reconnect_grace=0.0, limits=ServerLimits(
        address_join_burst=2, address_joins_per_s=0.01),
        trusted_proxies=["127.0.0.1"] if trusted else [])

    async def join(url: str, forwarded: str) -> bool:
        try:
            async with connect(url, compression=None,
                               additional_headers={"X-Forwarded-For": forwarded}) as ws:
                await ws.send(encode(Hello(protocol_version=PROTOCOL_VERSION,
                                           role="spectator", room="p", display_name="v")))
                assert isinstance(decode(await ws.recv()), Welcome)
                return True
        except InvalidStatus as refused:
            assert refused.response.status_code == 429
            return False

    async def test(url: str) -> None:
        a, b = "203.0.113.5", "203.0.113.6"
        joined = [await join(url, a), await join(url, f"{b}, {a}"),  # spoofed: a's
                  await join(url, a), await join(url, b), await join(url, b)]
        assert joined == ([True, True, False, True, True] if trusted
                          else [True, True, False, False, False])

    run(session, test)
    shown = "203.0.113.5 via 127.0.0.1:" if trusted else "from 127.0.0.1:"
    assert any(shown in r.getMessage() for r in caplog.records)


# ------------------------------------------------------------------ 3: rosters
async def _rosters(ws: ClientConnection, seconds: float) -> list[AvatarRoster]:
    """The rosters that reach a spectator within ``seconds``."""
    got: list[AvatarRoster] = []
    with contextlib.suppress(TimeoutError):
        async with asyncio.timeout(seconds):
            while True:
                msg = decode(await ws.recv())
                if isinstance(msg, AvatarRoster):
                    got.append(msg)
    return got


@contextlib.asynccontextmanager
async def spectator(url: str, room: str) -> AsyncIterator[ClientConnection]:
    async with connect(url, compression=None, max_size=None) as ws:
        await ws.send(encode(Hello(protocol_version=PROTOCOL_VERSION, role="spectator",
                                   room=room, display_name="watcher")))
        assert isinstance(decode(await ws.recv()), Welcome)
        assert isinstance(decode(await ws.recv()), AvatarRoster)  # the room as it is
        yield ws


def test_players_that_never_calibrate_cost_spectators_no_roster() -> None:
    session = Session(reconnect_grace=0.0, limits=ServerLimits(**MANY_JOINS))

    async def test(url: str) -> None:
        async with spectator(url, "quiet") as ws:
            for i in range(30):  # join and leave, cleanly and by a drop
                async with player(url, "quiet", f"lurker {i}") as p:
                    if i % 2:
                        p.transport.abort()
            assert await _rosters(ws, 0.5) == []
            async with player(url, "quiet", "real") as p:  # one that calibrates: shown
                await p.send(CALIBRATION)
                await handled(p)
                (roster,) = await _rosters(ws, 0.5)
                assert [a.display_name for a in roster.avatars] == ["real"]
            (gone,) = await _rosters(ws, 0.5)  # and its leaving too
            assert gone.removed == (roster.avatars[0].avatar_id,)

    run(session, test)


def test_the_rosters_of_many_changes_at_once_are_merged() -> None:
    """Ten players calibrate together: the first change goes out at once, the nine
    within the interval in one roster after it; then they leave, merged alike."""
    session = Session(reconnect_grace=0.0, limits=ServerLimits(
        roster_interval_s=5.0, address_calibration_burst=100, **MANY_JOINS))

    async def test(url: str) -> None:
        async with spectator(url, "crowd") as ws, contextlib.AsyncExitStack() as stack:
            players = [await stack.enter_async_context(player(url, "crowd", f"p{i}"))
                       for i in range(10)]
            for p in players:
                await p.send(CALIBRATION)
            for p in players:
                await handled(p)
            first = await _rosters(ws, 1.0)
            assert [len(r.avatars) for r in first] == [1]  # at once; the rest wait
            later = await _rosters(ws, 6.0)
            assert [len(r.avatars) for r in later] == [9]
            ids = {a.avatar_id for r in first + later for a in r.avatars}
            await stack.aclose()  # all ten leave
            left = await _rosters(ws, 6.0)
            assert {a for r in left for a in r.removed} == ids
            assert len(left) <= 2
            assert session.metrics.rosters == 2 + len(left)

    run(session, test)


# ------------------------------------------------------------------ 4: closes
# a masked binary frame (clients mask theirs) of 1 MiB, over max_message_bytes: 1009
BIG_FRAME = b"\x82\xff" + (1 << 20).to_bytes(8, "big") + bytes(4) + bytes(1 << 20)
# and of 4,000 bytes, within it
SMALL_FRAME = b"\x82\xfe" + (4000).to_bytes(2, "big") + bytes(4) + bytes(4000)
DROPPED_WITHIN_S = 8.0  # websockets' own close timeout, 10 s, would pass it


@pytest.mark.parametrize("first, then", [(None, BIG_FRAME), (b"\xc1 not a hello",
                                                             SMALL_FRAME)],
                         ids=["1009-then-big-frames", "refused-hello-then-frames"])
def test_a_connection_the_server_closes_is_read_no_more(first: bytes | None,
                                                        then: bytes) -> None:
    """A client that goes on writing after the server closed it (a 1 MiB frame: 1009; a
    refused Hello: 1008) and never answers the close: the server reads no more than its
    buffers hold (the client's writes soon block; before, a 1009'd client pushed
    3.3 GB in 10 s) and drops the socket within seconds."""
    session = Session(reconnect_grace=0.0)

    async def test(url: str) -> None:
        if first is None:
            ws = await connect(url, compression=None)
            await ws.send(encode(Hello(protocol_version=PROTOCOL_VERSION, role="player",
                                       room="big", display_name="big")))
            assert isinstance(decode(await ws.recv()), Welcome)
        else:
            ws = await connect(url, compression=None)
            await ws.send(first)
        ws.transport.pause_reading()  # our side reads nothing either: a raw writer
        raw = socket.socket(fileno=os.dup(ws.transport.get_extra_info("socket").fileno()))
        raw.setblocking(False)
        pushed, ended = 0, None
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        while loop.time() < t0 + DROPPED_WITHIN_S:
            try:
                pushed += raw.send(then)
            except BlockingIOError:
                await asyncio.sleep(0.01)
            except OSError as err:  # the server dropped the socket
                ended = err
                break
        raw.close()
        ws.transport.abort()
        assert ended is not None, f"still open after {DROPPED_WITHIN_S:g} s, " \
                                  f"{pushed >> 20} MiB in"
        # what the kernel's buffers hold on both sides, not what a reader takes
        assert pushed < 64 << 20, f"{pushed >> 20} MiB were read after the close"

    run(session, test)
