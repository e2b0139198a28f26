"""Server limits over real sockets on 127.0.0.1 (issue 14, items 1, 3 and 6): message
rates, the websocket frame bound, caps on rooms, players and connections, split rosters."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import itertools
from collections.abc import AsyncIterator, Awaitable, Callable

import pytest
from conftest import serving
from stream_decode import decode
from test_server import calibration, receive, receive_type, tracker
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed
from websockets.protocol import State

from posecast.client.cli import main
from posecast.client.session.spectator import Spectator
from posecast.protocol import (
    PROTOCOL_VERSION,
    AvatarBatch,
    AvatarRoster,
    Error,
    Hello,
    Ping,
    Pong,
    Welcome,
    encode,
)
from posecast.server.app import Session
from posecast.server.limits import Budget, ServerLimits
from posecast.solver.motion import ViveRecording

TIMEOUT = 10.0  # generous: the machine is shared


@pytest.fixture(scope="module")
def session() -> Session:
    # the production grace: a leaving player's avatar lingers
    return Session(reconnect_grace=30.0, limits=ServerLimits())


def run(test: Callable[[str], Awaitable[None]], session: Session,
        limits: ServerLimits | None = None) -> None:
    session.limits = limits or ServerLimits()

    async def main_() -> None:
        async with serving(session) as url:
            await asyncio.wait_for(test(url), 120)
    asyncio.run(main_())


def hello(role: str, room: str, token: str | None = None) -> bytes:
    return encode(Hello(protocol_version=PROTOCOL_VERSION, role=role, room=room,
                        display_name=f"{role}-{room}", token=token))


@contextlib.asynccontextmanager
async def joined(url: str, role: str, room: str, token: str | None = None
                 ) -> AsyncIterator[ClientConnection]:
    async with connect(url, compression=None) as ws:
        await ws.send(hello(role, room, token))
        assert isinstance(await receive(ws), Welcome)
        yield ws


async def refused(url: str, role: str, room: str) -> tuple[Error, int | None]:
    """Join and expect an Error then a close: (the error, the close code)."""
    async with connect(url, compression=None) as ws:
        with contextlib.suppress(ConnectionClosed):  # a cap on connections: no hello read
            await ws.send(hello(role, room))
        err = await receive(ws)
        assert isinstance(err, Error), err
        await asyncio.wait_for(ws.wait_closed(), TIMEOUT)
        return err, ws.close_code


async def closed_code(ws: ClientConnection) -> int | None:
    """Read (and drop) everything until the server closes; its close code."""
    with contextlib.suppress(ConnectionClosed):
        while True:
            await asyncio.wait_for(ws.recv(), TIMEOUT)
    return ws.close_code


class Bystander:
    """A player and a spectator in a room of their own: the spectator's batch times."""

    def __init__(self, url: str, rec: ViveRecording, room: str = "calm") -> None:
        self.url, self.rec, self.room = url, rec, room
        self.times: list[float] = []
        self.ready = asyncio.Event()

    async def run(self, stop: asyncio.Event) -> None:
        loop = asyncio.get_running_loop()
        async with joined(self.url, "spectator", self.room) as spec, \
                joined(self.url, "player", self.room) as player:
            await player.send(calibration(self.rec))

            async def play() -> None:
                i = 1
                while not stop.is_set():
                    await player.send(tracker(self.rec, i % len(self.rec.positions)))
                    i += 1
                    await asyncio.sleep(1 / 90)
            playing = loop.create_task(play())
            try:
                while not stop.is_set():
                    with contextlib.suppress(TimeoutError):
                        msg = decode(await asyncio.wait_for(spec.recv(), 0.2))
                        if isinstance(msg, AvatarBatch):
                            self.times.append(loop.time())
                            self.ready.set()
            finally:
                playing.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await playing

    def frames_between(self, t0: float, t1: float) -> list[float]:
        return [t for t in self.times if t0 <= t <= t1]


def max_gap(times: list[float], t0: float, t1: float) -> float:
    edges = [t0, *times, t1]
    return max(b - a for a, b in itertools.pairwise(edges))


# ---------------------------------------------------------------- item 1: calibrate flood
def test_a_calibrate_flood_is_limited_and_other_rooms_keep_receiving(
        session: Session, recording: ViveRecording) -> None:
    async def test(url: str) -> None:
        loop = asyncio.get_running_loop()
        stop = asyncio.Event()
        bystander = Bystander(url, recording)
        task = loop.create_task(bystander.run(stop))
        await asyncio.wait_for(bystander.ready.wait(), TIMEOUT)
        async with joined(url, "spectator", "hostile"), \
                joined(url, "player", "hostile") as flooder:
            t0 = loop.time()
            data = calibration(recording)
            with contextlib.suppress(ConnectionClosed):
                for _ in range(1000):  # back to back: ~1 ms of solve and a roster each
                    await flooder.send(data)
            code = await closed_code(flooder)
            t1 = loop.time()
            await asyncio.sleep(0.3)
        stop.set()
        await task
        assert code == 1008  # the bucket stayed empty: closed with a reason
        assert session.metrics.limited["calibrations"] >= 1
        # the other room never stalled (loose: the flood took ~1,000 ms of loop time
        # and gaps of 600+ ms before the limit)
        assert max_gap(bystander.times, t0, t1 + 0.3) < 0.5
        assert len(bystander.frames_between(t0, t1 + 0.3)) >= 0.2 * 90 * (t1 + 0.3 - t0)

    run(test, session)


def test_errors_that_keep_coming_close_the_connection(session: Session) -> None:
    async def test(url: str) -> None:
        async with joined(url, "player", "noisy") as ws:
            with contextlib.suppress(ConnectionClosed):
                for _ in range(200):
                    await ws.send(b"\xc1 not msgpack")
            errors = 0
            with contextlib.suppress(ConnectionClosed):
                while True:
                    msg = decode(await asyncio.wait_for(ws.recv(), TIMEOUT))
                    errors += isinstance(msg, Error)
            assert ws.close_code == 1008
            assert ws.close_reason and "errors" in ws.close_reason
            assert 1 <= errors <= ServerLimits().error_burst
        assert session.metrics.limited["errors"] >= 1

    run(test, session)


def test_tracker_frames_over_the_rate_are_refused(session: Session,
                                                  recording: ViveRecording) -> None:
    limits = ServerLimits(frames_per_s=20.0, frame_window_s=0.25)  # 5 per window

    async def test(url: str) -> None:
        async with joined(url, "player", "fast") as ws:
            await ws.send(calibration(recording))
            for i in range(1, 10):  # more than a window's 5, at once
                await ws.send(tracker(recording, i))
            err = await receive_type(ws, Error)
            assert err.code == "rate_limited", err  # type: ignore[attr-defined]
            assert "frames" in err.message  # type: ignore[attr-defined]
        assert session.metrics.limited["frames"] >= 1

    run(test, session, limits)


def test_a_player_is_held_to_the_rate_it_declared(session: Session,
                                                   recording: ViveRecording) -> None:
    """A player that says it sends 10 Hz gets 15 frames/s (slack 1.5), not the server's
    240: sending at 240 is refused and the reason names the declared rate."""
    limits = ServerLimits(frame_window_s=10 / 15)  # 10 frames per window at 15/s

    async def test(url: str) -> None:
        async with connect(url, compression=None) as ws:
            await ws.send(encode(Hello(protocol_version=PROTOCOL_VERSION, role="player",
                                       room="declared", display_name="ten",
                                       max_rate_hz=10.0)))
            assert isinstance(await receive(ws), Welcome)
            await ws.send(calibration(recording))
            for i in range(1, 13):  # 12 at once: over the window's 10
                await ws.send(tracker(recording, i))
            err = await receive_type(ws, Error)
            assert err.code == "rate_limited", err  # type: ignore[attr-defined]
            assert "over 15 frames per second" in err.message, err  # type: ignore[attr-defined]
            assert "10 Hz of hello.max_rate_hz" in err.message  # type: ignore[attr-defined]
        # the window: 10 frames per 10 / 15 s. The two over it were refused, not solved
        assert session.metrics.limited["frames"] >= 1

    run(test, session, limits)


def test_a_stalls_clump_costs_one_error_and_a_flood_ends_the_connection(
        session: Session, recording: ViveRecording) -> None:
    """Frames a network stall held arrive at once: the ones over the window's budget are
    dropped with one Error, and the player streams on. Ten times the budget at once is
    no stall: the connection is closed (1008)."""
    limits = ServerLimits(frame_window_s=10 / 15)  # a 10 Hz player: 10 per window

    async def player(url: str, room: str) -> ClientConnection:
        ws = await connect(url, compression=None)
        await ws.send(encode(Hello(protocol_version=PROTOCOL_VERSION, role="player",
                                   room=room, display_name="clump", max_rate_hz=10.0)))
        assert isinstance(await receive(ws), Welcome)
        await ws.send(calibration(recording))
        return ws

    async def test(url: str) -> None:
        rejected = session.metrics.frames_rejected
        ws = await player(url, "stall")
        for i in range(1, 26):  # 2.5 windows' worth at once: 15 over
            await ws.send(tracker(recording, i))
        await ws.send(encode(Ping(t0=0.0)))
        errors = []  # what came before the Pong, which comes after every frame
        while not isinstance(msg := await receive(ws), Pong):
            errors += [msg] if isinstance(msg, Error) else []
        assert len(errors) == 1 and errors[0].code == "rate_limited", errors
        assert session.metrics.frames_rejected - rejected == 15
        await asyncio.sleep(10 / 15)  # the next window: it streams on
        await ws.send(tracker(recording, 26))
        await ws.send(encode(Ping(t0=0.0)))
        assert isinstance(await receive_type(ws, Pong), Pong)
        assert ws.state is State.OPEN
        await ws.close()

        flood = await player(url, "flood")
        for i in range(1, 101):  # 10 windows' worth at once
            with contextlib.suppress(ConnectionClosed):
                await flood.send(tracker(recording, i))
        assert await closed_code(flood) == 1008
        assert "flooding" in (flood.close_reason or "")

    run(test, session, limits)


def test_calibrations_add_up_per_address(session: Session,
                                         recording: ViveRecording) -> None:
    """Many connections from one address cannot add up to a calibrate flood."""
    limits = ServerLimits(calibration_burst=3, address_calibrations_per_s=0.1,
                          address_calibration_burst=4)

    async def test(url: str) -> None:
        async with joined(url, "player", "a") as p1, joined(url, "player", "b") as p2:
            for ws in (p1, p2, p1, p2, p1):  # the fifth from 127.0.0.1
                await ws.send(calibration(recording))
            # whichever connection's turn came fifth gets the Error
            waits = [asyncio.ensure_future(receive_type(ws, Error)) for ws in (p1, p2)]
            done, pending = await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
            for w in pending:
                w.cancel()
            err = done.pop().result()
            assert err.code == "rate_limited", err
            assert "address_calibrations" in err.message

    run(test, session, limits)


def test_pings_over_the_rate_are_refused(session: Session) -> None:
    async def test(url: str) -> None:
        async with joined(url, "spectator", "pinger") as ws:
            for _ in range(10):
                await ws.send(encode(Ping(t0=0.0)))
            err = await receive_type(ws, Error)
            assert err.code == "rate_limited", err  # type: ignore[attr-defined]
            assert "pings_per_s" in err.message  # type: ignore[attr-defined]

    run(test, session, ServerLimits(pings_per_s=1.0, ping_burst=5))


def test_a_budget_refills_whole_each_window() -> None:
    b = Budget(per_s=10.0, burst=5)  # 0.5 s windows
    assert [b.take(0.0) for _ in range(6)] == [True] * 5 + [False]
    assert not b.take(0.49)
    assert b.take(0.5)


# ---------------------------------------------------------------- item 3: crowded rooms
async def join_calibrate_drop(url: str, rec: ViveRecording) -> int:
    """A player that joins, calibrates and drops (no close): its avatar lingers for the
    reconnect grace. Its avatar id."""
    async with connect(url, compression=None) as ws:
        await ws.send(hello("player", "crowd"))
        welcome = await receive(ws)
        assert isinstance(welcome, Welcome) and welcome.avatar_id is not None
        await ws.send(calibration(rec))
        await ws.send(encode(Ping(t0=0.0)))  # its Pong: the calibration was handled
        await receive_type(ws, Pong)
        ws.transport.abort()
        return welcome.avatar_id


def test_join_calibrate_leave_cycles_cannot_grow_the_roster(
        session: Session, recording: ViveRecording) -> None:
    # 700 players, each from its own address in the world; here all from 127.0.0.1,
    # so the per-address budgets (tested on their own) are lifted
    limits = ServerLimits(address_joins_per_s=1e6, address_join_burst=10**6,
                          address_calibrations_per_s=1e6, address_calibration_burst=10**6)

    async def test(url: str) -> None:
        ids = [await join_calibrate_drop(url, recording) for _ in range(700)]
        room = session.rooms["crowd"]
        assert len(room.avatars) <= limits.avatars_per_room
        # a new spectator still joins, and gets the roster in several bounded messages
        viewer = Spectator(url, "crowd", "late")
        async with joined(url, "spectator", "crowd") as ws:
            sizes: list[int] = []
            with contextlib.suppress(TimeoutError):
                while True:
                    data = await asyncio.wait_for(ws.recv(), 1.0)
                    msg = decode(data)
                    if isinstance(msg, AvatarRoster):
                        sizes.append(len(data))
                        assert len(msg.avatars) <= limits.roster_avatars_per_message
                        viewer.on_roster(msg)  # the client's own merge of the parts
        assert len(sizes) >= 2
        assert max(sizes) <= limits.roster_message_bytes
        assert len(viewer.roster) == len(room.avatars) == limits.avatars_per_room
        # the newest lingering avatars are the ones kept
        assert ids[-1] in room.avatars

    run(test, session, limits)


def test_caps_on_rooms_players_and_connections(session: Session,
                                               recording: ViveRecording) -> None:
    limits = ServerLimits(rooms=2, players_per_room=2, connections_per_address=5)

    async def test(url: str) -> None:
        async with joined(url, "player", "r1"), joined(url, "player", "r1"):
            err, code = await refused(url, "player", "r1")
            assert (err.code, code) == ("full", 1008)
            assert "players_per_room" in err.message
            async with joined(url, "spectator", "r1"), joined(url, "spectator", "r2"):
                err, code = await refused(url, "spectator", "r3")
                assert (err.code, code) == ("full", 1008)
                assert "rooms" in err.message
                async with joined(url, "spectator", "r2"):  # the fifth from 127.0.0.1
                    err, code = await refused(url, "spectator", "r2")
                    assert "connections_per_address" in err.message
            # the caps count live connections: room again once they closed
            async with joined(url, "spectator", "r3"):
                pass
        assert session.metrics.limited["rooms"] >= 1
        assert session.metrics.limited["players_per_room"] >= 1
        assert session.metrics.limited["connections_per_address"] >= 1

    run(test, session, limits)


# ---------------------------------------------------------------- item 6: big frames
def test_a_1_mib_frame_is_refused_at_its_header(session: Session,
                                                recording: ViveRecording) -> None:
    async def test(url: str) -> None:
        loop = asyncio.get_running_loop()
        stop = asyncio.Event()
        bystander = Bystander(url, recording)
        task = loop.create_task(bystander.run(stop))
        await asyncio.wait_for(bystander.ready.wait(), TIMEOUT)
        async with connect(url, compression=None, max_size=None) as ws:
            await ws.send(hello("player", "big"))
            assert isinstance(await receive(ws), Welcome)
            with contextlib.suppress(ConnectionClosed):
                await ws.send(b"\x00" * (1 << 20))
            assert await closed_code(ws) == 1009  # by websockets, before reading it
        seen = len(bystander.times)
        await asyncio.sleep(0.3)
        stop.set()
        await task
        assert len(bystander.times) > seen  # the others carry on

    run(test, session)


# ---------------------------------------------------------------- the command line
def test_serve_takes_limits_by_name_and_refuses_bad_ones(
        capsys: pytest.CaptureFixture[str]) -> None:
    for bad, words in (("nope=1", "unknown limit 'nope'"), ("rooms=many", "integer"),
                       ("rooms", "NAME=VALUE"), ("rooms=0", "positive"),
                       ("avatars_per_room=8", "at least players_per_room")):
        with pytest.raises(SystemExit):
            main(["serve", "--limit", bad])
        assert words in capsys.readouterr().err
    assert ServerLimits().with_text(["rooms=3", "errors_per_s=2.5"]) == dataclasses.replace(
        ServerLimits(), rooms=3, errors_per_s=2.5)
