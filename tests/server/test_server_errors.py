"""Hostile messages over real sockets on 127.0.0.1 (issue 14, items 4 and 5): every bad
message gets an Error that could be built, the connection carries on, and the log stays
bounded and unforgeable however many bad messages come."""

from __future__ import annotations

import asyncio
import logging
import re
from collections.abc import Awaitable, Callable

import msgpack
import pytest
from conftest import serving
from stream_decode import decode
from test_server import receive_type
from websockets.asyncio.client import ClientConnection, connect

from posecast.protocol import (
    PROTOCOL_VERSION,
    Error,
    Hello,
    Ping,
    Pong,
    Welcome,
    encode,
)
from posecast.protocol.validation import MAX_TEXT_CHARS
from posecast.server.app import Session
from posecast.server.limits import ServerLimits

TIMEOUT = 10.0
LIMITS = ServerLimits(errors_per_s=1e9, error_burst=10**9)
LOG_FIRST_REJECTIONS = LIMITS.log_first_rejections


@pytest.fixture(scope="module")
def session() -> Session:
    # errors are not rate-limited here: these tests are about each reply and the log
    return Session(reconnect_grace=0.0, limits=LIMITS)


def run(test: Callable[[str], Awaitable[None]], session: Session) -> None:
    async def main() -> None:
        async with serving(session) as url:
            await asyncio.wait_for(test(url), 60)
    asyncio.run(main())


async def join(url: str, role: str) -> ClientConnection:
    ws = await connect(url, compression=None, max_size=None)
    await ws.send(encode(Hello(protocol_version=PROTOCOL_VERSION, role=role, room="errors",
                               display_name=role)))
    assert isinstance(decode(await asyncio.wait_for(ws.recv(), TIMEOUT)), Welcome)
    return ws



def nested(depth: int, innermost: bytes = b"\x01") -> bytes:
    """msgpack bytes of a value nested ``depth`` arrays deep (msgpack-python itself will
    not pack more than 512 levels; a hostile client writes the bytes)."""
    return b"\x91" * depth + innermost


def ping_with(key: bytes, value: bytes) -> bytes:
    """A ping map with one more (raw msgpack) key and value."""
    return b"\x83" + msgpack.packb("type") + msgpack.packb("ping") + msgpack.packb("t0") \
        + msgpack.packb(0.0) + key + value


HOSTILE = {
    "field name of 970 chars": msgpack.packb({"type": "ping", "t0": 0.0, "x" * 970: 1}),
    "field name of 3000 chars": msgpack.packb({"type": "ping", "t0": 0.0, "y" * 3000: 1}),
    "field name with a newline": msgpack.packb(
        {"type": "ping", "t0": 0.0, "a\n2026-01-01 INFO forged line": 1}),
    "value nested 1000 deep": ping_with(msgpack.packb("deep"), nested(1000)),
    "value nested 3000 deep": ping_with(msgpack.packb("deep"), nested(3000)),
    "t0 nested 1000 deep": b"\x82" + msgpack.packb("type") + msgpack.packb("ping")
    + msgpack.packb("t0") + nested(1000),
    "type nested 1000 deep": b"\x81" + msgpack.packb("type") + nested(1000),
    "type of 3000 chars": msgpack.packb({"type": "z" * 3000}),
    "nested 1000 deep alone": nested(1000),
    "control characters in the type": msgpack.packb({"type": "\x1b[31m\r\nred"}),
}


@pytest.mark.parametrize("role", ["player", "spectator"])
def test_every_hostile_message_gets_an_error_and_the_connection_carries_on(
        session: Session, role: str) -> None:
    async def test(url: str) -> None:
        ws = await join(url, role)
        for what, data in HOSTILE.items():
            await ws.send(data)
            error = await receive_type(ws, Error)
            assert isinstance(error, Error), what
            assert 0 < len(error.message) <= MAX_TEXT_CHARS, what
            assert error.message.isprintable(), (what, error.message)
            # and the connection is still there: a ping is answered
            await ws.send(encode(Ping(t0=1.0)))
            assert isinstance(await receive_type(ws, Pong), Pong), what
        long_name = HOSTILE["field name of 3000 chars"]
        await ws.send(long_name)
        error = await receive_type(ws, Error)
        assert isinstance(error, Error)
        assert "(3000 chars)" in error.message  # the name shown as its start and length
        await ws.close()
    run(test, session)


def test_rejections_are_logged_sampled_and_escaped(session: Session,
                                                   caplog: pytest.LogCaptureFixture) -> None:
    messages = 10_000
    bad = [msgpack.packb({"type": "ping", "t0": 0.0, "n\n2026 INFO\rforged": 1}),
           msgpack.packb({"type": "nope\nINFO forged"}), b"\xc1not msgpack"]

    async def test(url: str) -> None:
        ws = await join(url, "player")
        replies = 0

        async def read() -> None:
            nonlocal replies
            while replies < messages:
                if isinstance(decode(await asyncio.wait_for(ws.recv(), TIMEOUT)), Error):
                    replies += 1

        reader = asyncio.create_task(read())
        for i in range(messages):
            await ws.send(bad[i % len(bad)])
        await reader
        await ws.close()

    with caplog.at_level(logging.INFO, logger="posecast.server"):
        run(test, session)
    lines = [r for r in caplog.records if r.name == "posecast.server"]
    rejections = [r for r in lines if "rejected" in r.getMessage()]
    # the first few one by one, then summaries (one at most per interval, one at the end)
    assert LOG_FIRST_REJECTIONS <= len(rejections) <= LOG_FIRST_REJECTIONS + 3, \
        [r.getMessage() for r in rejections]
    summarised = [re.search(r"rejected (\d+) more messages", r.getMessage())
                  for r in rejections[LOG_FIRST_REJECTIONS:]]
    assert sum(int(m.group(1)) for m in summarised if m) == messages - LOG_FIRST_REJECTIONS
    for r in lines:
        assert "\n" not in r.getMessage() and "\r" not in r.getMessage(), r.getMessage()
    assert session.metrics.rejected["invalid"] >= messages // 3
