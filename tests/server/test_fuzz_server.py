"""Fuzzing a live server on 127.0.0.1 (issue 14, "Fuzz in CI").

Random bytes, truncated and mutated real messages, deep nesting and long keys, oversize
messages and valid-but-extreme values, each sent on a fresh connection. Every one must get
an Error reply or a close with a clear code (1008/1009 where a limit applies), never 1011
(an internal error); afterwards a new client still joins and gets a roster, and a
bystander spectator in another room still receives its player's frames.

The server and the bystanders run on one event loop in a thread of their own for the whole
module: hypothesis calls each example synchronously and hands it to that loop.
Reproducible in CI: derandomized, no example database.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Coroutine, Iterator
from dataclasses import dataclass, field
from typing import Any, TypeVar

import msgpack
import numpy as np
import pytest
from conftest import serving
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from stream_decode import decode
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed

from posecast.client.builtin import builtin_motion_path
from posecast.client.session.player import calibrate_message
from posecast.client.sources.bvh_source import BvhSource
from posecast.protocol import (
    PROTOCOL_VERSION,
    AvatarRoster,
    Hello,
    Leave,
    Ping,
    ProtocolError,
    Welcome,
    decode_client,
    encode,
)
from posecast.protocol.codec import encode_tracker_frame
from posecast.protocol.sizes import MAX_CLIENT_MESSAGE_BYTES
from posecast.protocol.validation import pose_wire
from posecast.server.app import Session
from posecast.server.clock import now
from posecast.server.limits import ServerLimits

T = TypeVar("T")
TIMEOUT = 10.0  # generous: the machine is shared; a wait that passes it is a hang
FUZZ_ROOM, BYSTANDER_ROOM = "fuzz", "bystander"
LIMIT_CLOSES = frozenset({1008, 1009})  # policy violation, message too big
CLEAN_CLOSES = LIMIT_CLOSES | {1000}  # 1000: the fuzz message was a valid Leave
FUZZ = settings(max_examples=120, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture,
                                       HealthCheck.too_slow])


# --------------------------------------------------------------------------- messages
def _hello(role: str, room: str, name: str) -> bytes:
    return encode(Hello(protocol_version=PROTOCOL_VERSION, role=role,  # type: ignore[arg-type]
                        room=room, display_name=name))


def _samples(n: int) -> list[tuple[tuple[str, ...], np.ndarray, float]]:
    source = BvhSource(builtin_motion_path(), loop=True, rate_hz=90.0)
    try:
        out = []
        for _ in range(n):
            s = source.read()
            assert s is not None
            out.append((tuple(s.roles), np.array(s.poses), float(s.t_capture)))
        return out
    finally:
        source.close()


def _calibration() -> bytes:
    source = BvhSource(builtin_motion_path(), loop=True, rate_hz=90.0)
    try:
        return encode(calibrate_message(source.calibration(), 0.0))
    finally:
        source.close()


SAMPLES = _samples(90)
CALIBRATION = _calibration()
TRACKER = encode_tracker_frame(7, *SAMPLES[0], 0.0)
REAL = [_hello("player", FUZZ_ROOM, "fuzzer"), CALIBRATION, TRACKER,
        encode(Ping(t0=12.5)), encode(Leave(reason="bye"))]


def _nested(depth: int, leaf: object = 0) -> bytes:
    """``depth`` one-element arrays around ``leaf``, packed by hand: msgpack's own packer
    refuses to nest deeper than ~500, a hostile client need not use it."""
    return b"\x91" * depth + msgpack.packb(leaf)


def _map_with(fields: dict[str, object], key: str, packed_value: bytes) -> bytes:
    """A msgpack map of ``fields`` plus ``key`` whose value is already packed."""
    assert len(fields) < 15
    body = b"".join(msgpack.packb(k) + msgpack.packb(v) for k, v in fields.items())
    return bytes([0x80 | (len(fields) + 1)]) + body + msgpack.packb(key) + packed_value


# --------------------------------------------------------------------------- strategies
@st.composite
def _mutated(draw: st.DrawFn) -> bytes:
    """A real message with bytes flipped, cut, inserted or deleted."""
    data = bytearray(draw(st.sampled_from(REAL)))
    for _ in range(draw(st.integers(1, 4))):
        kind = draw(st.sampled_from(("flip", "cut", "insert", "delete")))
        at = draw(st.integers(0, max(0, len(data) - 1)))
        if kind == "flip" and data:
            data[at] ^= 1 << draw(st.integers(0, 7))
        elif kind == "cut":
            del data[at:]
        elif kind == "insert":
            data[at:at] = draw(st.binary(min_size=1, max_size=16))
        elif data:
            del data[at:at + draw(st.integers(1, 16))]
    return bytes(data)


_truncated = st.sampled_from(REAL).flatmap(
    lambda m: st.integers(0, len(m) - 1).map(lambda n: m[:n]))
_random = st.one_of(st.binary(max_size=600), st.text(max_size=200))  # text: a text frame
ANY_BYTES = st.one_of(_random, _truncated, _mutated())

_weird = st.one_of(st.none(), st.booleans(), st.text(max_size=30), st.binary(max_size=64),
                   st.integers(-(2**63), 2**64 - 1),
                   st.floats(allow_nan=True, allow_infinity=True),
                   st.lists(st.integers(-(2**63), 2**63 - 1), max_size=4),
                   st.dictionaries(st.text(max_size=5), st.integers(-9, 9), max_size=3))
_extreme_number = st.one_of(
    st.sampled_from([1e308, -1e308, float("inf"), float("-inf"), float("nan"), 0.0, -1.0,
                     5e-324, 2.0**63, -(2.0**63), 1e15]),
    st.floats(allow_nan=True, allow_infinity=True))


@st.composite
def _extreme(draw: st.DrawFn) -> bytes:
    """A tracker frame or calibration, valid but for one or two extreme or wrong fields."""
    roles, poses, t = draw(st.sampled_from(SAMPLES))
    raw: dict[str, Any] = msgpack.unpackb(encode_tracker_frame(1, roles, poses, t, 0.0))
    if draw(st.booleans()):
        raw["type"] = "calibrate"
        raw.pop("seq")
    for _ in range(draw(st.integers(1, 2))):
        what = draw(st.sampled_from(("seq", "t_capture", "clock_offset", "positions",
                                     "quaternions", "poses", "roles", "type")))
        if what == "seq":
            raw["seq"] = draw(st.one_of(st.integers(-(2**64) + 1, 2**64 - 1),
                                        st.sampled_from([2**63 - 1, 2**63, 2**64 - 1]),
                                        _weird))
        elif what in ("t_capture", "clock_offset"):
            raw[what] = draw(st.one_of(_extreme_number, _weird))
        elif what in ("positions", "quaternions"):
            p = poses.copy()
            cols = slice(0, 3) if what == "positions" else slice(3, 7)
            p[:, cols] *= draw(_extreme_number)
            # positions to float32's infinity, quaternion levels clipped: refused as such
            raw["poses"] = pose_wire(p)
        elif what == "poses":
            raw["poses"] = draw(st.one_of(st.binary(max_size=600), _weird))
        elif what == "roles":
            raw["roles"] = draw(st.one_of(
                st.lists(st.sampled_from([*range(len(roles)), 11, -1, "head", ""]),
                         max_size=12), _weird))
        else:
            raw["type"] = draw(st.one_of(st.sampled_from(["hello", "welcome", "pong",
                                                          "avatar_batch", "error"]),
                                         _weird))
    return msgpack.packb(raw)


@st.composite
def _deep_or_long(draw: st.DrawFn) -> bytes:
    """Deep nesting or a long (or control-character) key, in a message that is otherwise
    a ping (issue 14, item 4: building the Error reply raised on these)."""
    if draw(st.booleans()):
        depth = draw(st.integers(50, 3000))
        leaf = draw(st.sampled_from([0, {}, "x"]))
        if draw(st.booleans()):  # the nested value in a known field
            return _map_with({"type": "ping"}, "t0", _nested(depth, leaf))
        return _map_with({"type": "ping", "t0": 1.0}, "extra", _nested(depth, leaf))
    key = draw(st.sampled_from(["k", "\n", "\x1b[2J", "é"])) * draw(st.integers(500, 3000))
    return msgpack.packb({"type": "ping", "t0": 1.0,
                          key: draw(st.sampled_from([1, "v" * 500]))})


# --------------------------------------------------------------------------- live server
@dataclass
class Outcome:
    errors: list[str] = field(default_factory=list)  # Error codes received
    ponged: bool = False  # the connection answered a Ping after the fuzz message
    welcomed: bool = False
    close_code: int | None = None
    close_reason: str = ""


class LiveServer:
    """The server, a bystander player and a bystander spectator in a thread's loop."""

    def __init__(self) -> None:
        # every example is a new connection from 127.0.0.1: the join budget per address
        # (tested in test_limits) would refuse most of them with a 429 before any message
        self.session = Session(reconnect_grace=0.0, limits=ServerLimits(
            address_joins_per_s=1e6, address_join_burst=10**6))
        self.url = ""
        self.bystander_frames = 0
        self.bystander_ends: list[str] = []  # how a bystander's connection ended, if it did
        self._ready = threading.Event()
        self._failed: BaseException | None = None  # why the thread's loop ended early
        self._thread = threading.Thread(target=self._run, daemon=True)
        self.loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None

    def start(self) -> None:
        self._thread.start()
        assert self._ready.wait(60), "the fuzz server did not start"
        if self._failed is not None:
            raise RuntimeError("the fuzz server did not start") from self._failed

    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as exc:  # for start() to raise, not a silent thread
            self._failed = exc
            self._ready.set()

    def stop(self) -> None:
        assert self.loop is not None and self._stop is not None
        self.loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(30)

    def call(self, coro: Coroutine[Any, Any, T], timeout: float = 4 * TIMEOUT) -> T:
        assert self.loop is not None
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    async def _main(self) -> None:
        self.loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        async with serving(self.session) as url:
            self.url = url
            tasks = [asyncio.create_task(self._bystander_player()),
                     asyncio.create_task(self._bystander_spectator())]
            self._ready.set()
            await self._stop.wait()
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

    async def _bystander_player(self) -> None:
        try:
            await self._play()
        except ConnectionClosed as exc:
            self.bystander_ends.append(f"player: {exc}")

    async def _bystander_spectator(self) -> None:
        try:
            await self._watch()
        except ConnectionClosed as exc:
            self.bystander_ends.append(f"spectator: {exc}")

    async def _play(self) -> None:
        async with connect(self.url, compression=None) as ws:
            await ws.send(_hello("player", BYSTANDER_ROOM, "bystander"))
            await ws.recv()
            await ws.send(CALIBRATION)
            reader = asyncio.create_task(_discard(ws))
            seq = 0
            try:
                while True:
                    roles, poses, _ = SAMPLES[seq % len(SAMPLES)]
                    # captured now: SAMPLES' times are from import, and a frame over
                    # capture_skew_s (60 s) from the server's clock is refused
                    await ws.send(encode_tracker_frame(seq, roles, poses, now(), 0.0))
                    seq += 1
                    await asyncio.sleep(1 / 90.0)
            finally:
                reader.cancel()

    async def _watch(self) -> None:
        async with connect(self.url, compression=None, max_size=None) as ws:
            await ws.send(_hello("spectator", BYSTANDER_ROOM, "watcher"))
            async for data in ws:
                if isinstance(data, bytes) and data[:64].find(b"avatar_batch") >= 0:
                    self.bystander_frames += 1
            self.bystander_ends.append(f"spectator: closed {ws.close_code} {ws.close_reason}")


async def _discard(ws: ClientConnection) -> None:
    async for _ in ws:
        pass


async def _probe(url: str, data: bytes | str, first: bool = False) -> Outcome:
    """Send ``data`` on a fresh connection (as the first message, or as a calibrated
    player's next one followed by a Ping) and collect what comes back until the Pong or
    the close."""
    out = Outcome()
    async with connect(url, compression=None, max_size=None, open_timeout=TIMEOUT,
                       close_timeout=TIMEOUT) as ws:
        try:
            if not first:
                await ws.send(_hello("player", FUZZ_ROOM, "fuzzer"))
                assert isinstance(decode(await asyncio.wait_for(ws.recv(), TIMEOUT)),
                                  Welcome)
                await ws.send(CALIBRATION)
            await ws.send(data)
            if not first:
                await ws.send(encode(Ping(t0=99.0)))
            while not out.ponged:
                reply = await asyncio.wait_for(ws.recv(), TIMEOUT)
                raw = msgpack.unpackb(reply) if isinstance(reply, bytes) else {}
                kind = raw.get("type") if isinstance(raw, dict) else None
                if kind == "error":
                    out.errors.append(str(raw.get("code")))
                    if first:
                        await asyncio.wait_for(ws.wait_closed(), TIMEOUT)
                elif kind == "pong" and raw.get("t0") == 99.0:
                    out.ponged = True
                elif kind == "welcome" and first:
                    out.welcomed = True
                    break
        except ConnectionClosed:
            pass
        out.close_code = ws.close_code
        out.close_reason = ws.close_reason or ""
    return out


def _is_invalid(data: bytes | str) -> bool:
    try:
        decode_client(data)
    except ProtocolError:
        return True
    return False


def _check(outcome: Outcome, data: bytes | str) -> None:
    """The issue's rule for one message: an Error reply, or a clear close where a limit
    applies; never an internal error; an invalid message never passes in silence."""
    assert outcome.close_code != 1011, f"internal error (1011) on {data[:80]!r}"
    assert "internal" not in outcome.errors, f"internal error reply on {data[:80]!r}"
    closed = outcome.close_code is not None and not outcome.ponged and not outcome.welcomed
    if closed:
        assert outcome.close_code in CLEAN_CLOSES, (outcome, data[:80])
        if outcome.close_code in LIMIT_CLOSES:
            assert outcome.close_reason, f"close {outcome.close_code} without a reason"
    if _is_invalid(data):
        assert outcome.errors or (closed and outcome.close_code in LIMIT_CLOSES), \
            f"no Error and no close for {data[:80]!r}: {outcome}"


@pytest.fixture(scope="module")
def live() -> Iterator[LiveServer]:
    server = LiveServer()
    server.start()
    try:
        yield server
    finally:
        server.stop()


def _unharmed(live: LiveServer) -> None:
    """The server still serves: a new spectator joins and gets its roster, and the
    bystander spectator in another room receives new frames (loosely: some, in time)."""
    async def join() -> None:
        async with connect(live.url, compression=None, max_size=None) as ws:
            await ws.send(_hello("spectator", "check", "checker"))
            assert isinstance(decode(await asyncio.wait_for(ws.recv(), TIMEOUT)), Welcome)
            assert isinstance(decode(await asyncio.wait_for(ws.recv(), TIMEOUT)),
                              AvatarRoster)

    async def frames_flow() -> None:
        before = live.bystander_frames
        while live.bystander_frames < before + 10:
            await asyncio.sleep(0.05)

    live.call(join())
    try:
        live.call(asyncio.wait_for(frames_flow(), 3 * TIMEOUT))
    except TimeoutError:
        raise AssertionError(f"the bystander received no frames for {3 * TIMEOUT:g} s; "
                             f"its connections: {live.bystander_ends or 'open'}") from None


# --------------------------------------------------------------------------- the tests
def test_random_truncated_and_mutated_messages(live: LiveServer) -> None:
    @FUZZ
    @given(data=ANY_BYTES, first=st.booleans())
    def one(data: bytes | str, first: bool) -> None:
        _check(live.call(_probe(live.url, data, first)), data)

    one()
    _unharmed(live)


def test_valid_but_extreme_values(live: LiveServer) -> None:
    @settings(FUZZ, max_examples=100)
    @given(data=_extreme())
    def one(data: bytes) -> None:
        _check(live.call(_probe(live.url, data)), data)

    one()
    _unharmed(live)


def test_deep_nesting_and_long_keys(live: LiveServer) -> None:
    """Issue 14, item 4: these made building the Error reply raise (close 1011)."""
    @settings(FUZZ, max_examples=40)
    @given(data=_deep_or_long(), first=st.booleans())
    def one(data: bytes, first: bool) -> None:
        _check(live.call(_probe(live.url, data, first)), data)

    try:
        one()
    finally:
        _unharmed(live)


@pytest.mark.parametrize("size", [MAX_CLIENT_MESSAGE_BYTES + 1, 60_000, (1 << 20) + 1,
                                  3 << 20])
@pytest.mark.parametrize("first", [False, True])
def test_oversize_messages(live: LiveServer, size: int, first: bool) -> None:
    """Over the protocol's 8 KiB: an Error (too_large) or a close 1009; never a 1011."""
    data = msgpack.packb({"type": "ping", "t0": 1.0, "pad": b"x" * size})
    outcome = live.call(_probe(live.url, data, first))
    _check(outcome, data)
    # (the probe's own calibration may be refused too: the server limits them per room)
    assert "too_large" in outcome.errors or outcome.close_code == 1009, outcome
    _unharmed(live)
