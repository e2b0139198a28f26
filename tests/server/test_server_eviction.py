"""Clients that hold the server's resources and give nothing back, over real sockets on
127.0.0.1 (issue 14, items 7 and 8): frames out of order, idle players, spectators that
stop reading or read slowly, and a stop that must not wait behind them."""

from __future__ import annotations

import asyncio
import contextlib
import socket
import threading
import time
from collections.abc import AsyncIterator

import numpy as np
import pytest
from stream_decode import decode
from test_server import receive_type
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed

from posecast.client.bench.demo import ROOM, run_players
from posecast.client.builtin import builtin_motion_path
from posecast.client.session.spectator import Spectator
from posecast.client.sources.bvh_source import tracker_recording
from posecast.protocol import (
    PROTOCOL_VERSION,
    AvatarBatch,
    AvatarRoster,
    Calibrate,
    Error,
    Hello,
    Ping,
    Pong,
    TrackerFrame,
    Welcome,
    encode,
)
from posecast.server.app import Session
from posecast.server.clock import now
from posecast.server.limits import ServerLimits
from posecast.server.serving import run_server
from posecast.solver.motion import ViveRecording

TIMEOUT = 10.0


@pytest.fixture(scope="module")
def motion() -> ViveRecording:
    return tracker_recording(builtin_motion_path(), 2.0)


@contextlib.asynccontextmanager
async def server(session: Session) -> AsyncIterator[tuple[str, asyncio.Event,
                                                          asyncio.Task[Session]]]:
    """A real server on a free port; the test may stop it itself (and time the stop)."""
    stop = asyncio.Event()
    ready: asyncio.Future[int] = asyncio.get_running_loop().create_future()
    task = asyncio.create_task(run_server("127.0.0.1", 0, session, stop, ready.set_result))
    port = await asyncio.wait_for(ready, TIMEOUT)
    try:
        yield f"ws://127.0.0.1:{port}", stop, task
    finally:
        stop.set()
        await asyncio.wait_for(task, 3 * TIMEOUT)


async def join(url: str, role: str, room: str = ROOM, resume: str | None = None,
               rcvbuf: int | None = None) -> ClientConnection:
    """``join_welcomed`` without the Welcome."""
    return (await join_welcomed(url, role, room, resume, rcvbuf))[0]


async def join_welcomed(url: str, role: str, room: str = ROOM, resume: str | None = None,
                        rcvbuf: int | None = None) -> tuple[ClientConnection, Welcome]:
    """A raw client; ``rcvbuf``: a small kernel receive buffer and a one-message queue,
    so that what it has not read waits on the server's side (a slow link, not a client
    hoarding megabytes)."""
    sock = None
    if rcvbuf is not None:
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        port = int(url.rsplit(":", 1)[1])
        await asyncio.get_running_loop().sock_connect(sock, ("127.0.0.1", port))
    ws = await connect(url, sock=sock, compression=None, max_size=None,
                       max_queue=1 if rcvbuf is not None else 16)
    await ws.send(encode(Hello(protocol_version=PROTOCOL_VERSION, role=role, room=room,
                               display_name=role, resume=resume)))
    welcome = decode(await asyncio.wait_for(ws.recv(), TIMEOUT))
    assert isinstance(welcome, Welcome)
    return ws, welcome



def frame(rec: ViveRecording, seq: int) -> bytes:
    i = 1 + seq % (len(rec.positions) - 1)
    poses = np.concatenate([rec.positions[i], rec.rotations[i]], axis=1)
    return encode(TrackerFrame(seq=seq, roles=rec.devices, poses=poses,
                               t_capture=now(), clock_offset=0.0))


def calibrate(rec: ViveRecording) -> bytes:
    poses = np.concatenate([rec.positions[0], rec.rotations[0]], axis=1)
    return encode(Calibrate(roles=rec.devices, poses=poses, t_capture=now(),
                            clock_offset=0.0))


async def closed(ws: ClientConnection) -> ConnectionClosed:
    """Read until the server closes the connection; its close."""
    try:
        while True:
            await asyncio.wait_for(ws.recv(), TIMEOUT)
    except ConnectionClosed as closing:
        return closing


# ------------------------------------------------------------------ item 7: seq
def test_frames_out_of_order_are_refused_and_a_reconnect_starts_again(
        motion: ViveRecording) -> None:
    session = Session(reconnect_grace=5.0)

    async def main() -> None:
        async with server(session) as (url, _, _):
            viewer = await join(url, "spectator")
            player, welcome = await join_welcomed(url, "player")
            await player.send(calibrate(motion))
            for seq in (0, 1, 2, 5):
                await player.send(frame(motion, seq))
            for seq in (5, 3):  # repeated, then going back
                await player.send(frame(motion, seq))
                error = await receive_type(player, Error)
                assert isinstance(error, Error)
                assert error.code == "out_of_order" and f"seq: {seq} " in error.message
            await player.send(frame(motion, 6))  # and on it goes
            await player.send(encode(Ping(t0=0.0)))
            assert isinstance(await receive_type(player, Pong), Pong)  # no error came before
            seen: set[int] = set()
            while 6 not in seen:
                batch = await receive_type(viewer, AvatarBatch)
                assert isinstance(batch, AvatarBatch)
                seen.update(int(s) for s in batch.seqs)
            assert 3 not in seen  # the refused frame was never solved
            player.transport.abort()  # dropped: its avatar waits for it
            # the same avatar on a new connection counts from 0 again
            again, back = await join_welcomed(url, "player", resume=welcome.resume)
            assert back.resumed and back.avatar_id == welcome.avatar_id
            await again.send(frame(motion, 0))
            await again.send(encode(Ping(t0=0.0)))
            assert isinstance(await receive_type(again, Pong), Pong)
            await again.close()
            await viewer.close()
        assert session.metrics.rejected["out_of_order"] == 2

    asyncio.run(main())


def test_the_projects_own_players_never_trip_the_seq_check() -> None:
    session = Session(reconnect_grace=0.0)

    async def main() -> None:
        async with server(session) as (url, _, _):
            stats = await run_players(url, 3, 2.0, builtin_motion_path())
            assert all(s.frames_sent > 100 and not s.errors for s in stats), stats
        assert session.metrics.rejected["out_of_order"] == 0
        assert session.metrics.frames_rejected == 0

    asyncio.run(main())


# ------------------------------------------------------------------ item 7: idle players
def test_an_idle_player_is_closed_and_its_avatar_leaves(motion: ViveRecording) -> None:
    limits = ServerLimits(idle_player_s=1.0)
    session = Session(reconnect_grace=0.5, limits=limits)

    async def main() -> None:
        async with server(session) as (url, _, _):
            viewer = await join(url, "spectator")
            player = await join(url, "player")
            await player.send(calibrate(motion))
            roster = await receive_type(viewer, AvatarRoster)
            while isinstance(roster, AvatarRoster) and not roster.avatars:  # the one at join
                roster = await receive_type(viewer, AvatarRoster)
            assert isinstance(roster, AvatarRoster) and len(roster.avatars) == 1
            avatar_id = roster.avatars[0].avatar_id
            for seq in range(3):
                await player.send(frame(motion, seq))

            async def ping_only() -> None:  # alive, but sending no frame
                with contextlib.suppress(ConnectionClosed):
                    while True:
                        await player.send(encode(Ping(t0=0.0)))
                        await asyncio.sleep(0.2)

            pinger = asyncio.create_task(ping_only())
            closing = await closed(player)
            pinger.cancel()
            assert closing.rcvd is not None and closing.rcvd.code == 1008
            assert "idle" in closing.rcvd.reason
            while True:  # then, after the reconnect grace, its avatar leaves the roster
                roster = await receive_type(viewer, AvatarRoster)
                assert isinstance(roster, AvatarRoster)
                if avatar_id in roster.removed:
                    break
            await viewer.close()
        assert session.metrics.limited["idle_player_s"] == 1

    asyncio.run(main())


def test_players_that_keep_sending_are_not_idle() -> None:
    session = Session(reconnect_grace=0.0, limits=ServerLimits(idle_player_s=0.5))

    async def main() -> None:
        async with server(session) as (url, _, _):
            stats = await run_players(url, 2, 2.0, builtin_motion_path())
            assert all(s.ended_by == "time" and not s.errors for s in stats), stats
        assert session.metrics.limited["idle_player_s"] == 0

    asyncio.run(main())


# ------------------------------------------------------------------ item 7: stalled viewers
def test_a_spectator_that_stops_reading_is_closed_and_others_carry_on() -> None:
    # A send to a slow link ends only when the kernel's send buffer wakes the writer,
    # which takes ~0.5 s of this reader's 20 messages a second (~1 s at 10): the limit
    # is 4x that, not at it, or a loaded machine evicts the slow one too.
    session = Session(reconnect_grace=0.0, limits=ServerLimits(backlog_evict_s=2.0))

    async def main() -> None:
        async with server(session) as (url, _, _):
            stuck = await join(url, "spectator", rcvbuf=4096)  # and never reads
            slow = await join(url, "spectator", rcvbuf=4096)
            batches = 0

            async def read_slowly() -> None:  # a slow link still takes frames: it stays
                nonlocal batches
                while True:
                    if isinstance(decode(await slow.recv()), AvatarBatch):
                        batches += 1
                    await asyncio.sleep(0.05)  # 20 a second, of 90 offered

            reader = asyncio.create_task(read_slowly())
            await run_players(url, 4, 4.0, builtin_motion_path())
            assert session.metrics.limited["backlog_evict_s"] == 1
            assert len(session.rooms[ROOM].spectators) == 1  # the slow one
            assert batches > 10 and not reader.done()
            reader.cancel()
            closing = await closed(stuck)  # behind its backlog: the close, or a reset
            assert closing.rcvd is None or closing.rcvd.code == 1013
            await slow.close()

    asyncio.run(main())


def test_a_stop_does_not_wait_behind_a_stuck_spectator() -> None:
    # eviction far off: the stop itself meets the stuck spectator
    session = Session(reconnect_grace=0.0, limits=ServerLimits(backlog_evict_s=600.0))

    async def main() -> None:
        async with server(session) as (url, stop, task):
            stuck = await join(url, "spectator", rcvbuf=4096)
            players = asyncio.create_task(run_players(url, 4, 30.0, builtin_motion_path()))
            room = None
            while room is None or all(s.outbox.idle for s in room.spectators.values()):
                await asyncio.sleep(0.5)  # until its backlog is full
                room = session.rooms.get(ROOM)
            await asyncio.sleep(1.0)
            t0 = time.monotonic()
            stop.set()
            await asyncio.wait_for(task, 3 * TIMEOUT)
            took = time.monotonic() - t0
            players.cancel()
            with contextlib.suppress(BaseException):
                await players
            await closed(stuck)
        # the drain (2 s) and a 1 s close, not websockets' 10 s close timeout or worse
        assert took < 8.0, took

    asyncio.run(main())


# ------------------------------------------------------------------ item 8: slow viewers
def test_a_slow_viewer_sees_recent_frames_not_seconds_of_old_ones() -> None:
    session = Session(reconnect_grace=0.0)
    players, seconds, read_every = 8, 5.0, 0.075

    async def main() -> list[float]:
        async with server(session) as (url, _, _):
            # a receive buffer of ~4 batches: 2048 bytes (Linux doubles it) of protocol 4's
            # ~1 KB batches of 8 players, as 4096 held ~4 of protocol 3's 2.7 KB ones
            viewer = await join(url, "spectator", rcvbuf=2048)
            lags: list[float] = []

            async def read_slowly() -> None:
                while True:
                    msg = decode(await viewer.recv())
                    if isinstance(msg, AvatarBatch) and len(msg.t_capture):
                        # how old the newest pose in it is: the player captured a newer
                        # one every 11 ms, so this is how far behind the viewer is
                        lags.append(now() - float(np.max(msg.t_capture)))
                    await asyncio.sleep(read_every)

            reader = asyncio.create_task(read_slowly())
            await run_players(url, players, seconds, builtin_motion_path())
            reader.cancel()
            await viewer.close()
            return lags

    lags = asyncio.run(main())
    assert len(lags) > 20
    settled = lags[len(lags) // 3:]  # once every buffer on the way is as full as it gets
    print(f"slow viewer, {players} players, one batch per {read_every * 1000:.0f} ms: "
          f"behind by {np.median(settled):.2f} s (median), {max(settled):.2f} s (max)")
    # ~0.45-0.6 s measured (its own receive buffer and queue hold ~4 batches: the server
    # cannot see them; the two tests below are the remedies); with the kernel's default
    # buffers on the server it was 3-7 s behind
    assert max(settled) < 1.0, [round(x, 3) for x in settled]
    assert session.metrics.frames_dropped > 0  # latest wins: old frames were replaced


def test_a_viewer_that_draws_slowly_shows_poses_a_draw_old_not_seconds() -> None:
    """posecast's own viewer loop (client/viewer/window.py): a draw holds the loop, then
    the spectator's reader takes everything that arrived meanwhile and the next draw shows
    the newest. Here a draw takes 75 ms (13 fps): the newest pose drawn is one draw old."""
    session = Session(reconnect_grace=0.0)
    players, seconds, draw_s = 8, 5.0, 0.075
    lags: list[float] = []
    stop = threading.Event()

    def slow_viewer(url: str) -> None:  # its own thread and loop, like a viewer process
        async def view() -> None:
            spectator = Spectator(url, ROOM, "slow viewer")
            receiving = asyncio.create_task(spectator.run())
            while not stop.is_set():
                newest = [b.t_capture[r] for b, r, _ in spectator.latest.values()]
                if newest:
                    lags.append(now() - float(max(newest)))
                time.sleep(draw_s)  # the draw: nothing else runs in this loop meanwhile
                await spectator.catch_up()  # as the viewers do before each draw
            receiving.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await receiving
        asyncio.run(view())

    async def main() -> None:
        async with server(session) as (url, _, _):
            viewer = threading.Thread(target=slow_viewer, args=(url,))
            viewer.start()
            try:
                await run_players(url, players, seconds, builtin_motion_path())
            finally:
                stop.set()
                await asyncio.to_thread(viewer.join)

    asyncio.run(main())
    assert len(lags) > 20
    settled = lags[len(lags) // 3:]
    print(f"viewer drawing every {draw_s * 1000:.0f} ms, {players} players: newest pose "
          f"drawn {np.median(settled) * 1000:.0f} ms old (median), "
          f"{max(settled) * 1000:.0f} ms (max)")
    # a draw plus a frame interval or two: never the backlog of its buffers
    assert max(settled) < 0.2, [round(x, 3) for x in settled]


def test_a_slow_reader_that_asks_for_its_rate_gets_recent_frames() -> None:
    """A client that reads every message in order, slowly (one per 75 ms), and says so
    in its hello (``max_rate_hz``): the server sends it no more than it reads, so nothing
    queues on the way and each batch it reads is fresh."""
    session = Session(reconnect_grace=0.0)
    players, seconds, read_every = 8, 5.0, 0.075

    async def main() -> list[float]:
        async with server(session) as (url, _, _):
            viewer = await connect(url, compression=None)
            await viewer.send(encode(Hello(
                protocol_version=PROTOCOL_VERSION, role="spectator", room=ROOM,
                display_name="slow reader", max_rate_hz=0.5 / read_every)))
            assert isinstance(decode(await asyncio.wait_for(viewer.recv(), TIMEOUT)),
                              Welcome)
            lags: list[float] = []

            async def read_slowly() -> None:
                while True:
                    msg = decode(await viewer.recv())
                    if isinstance(msg, AvatarBatch) and len(msg.t_capture):
                        lags.append(now() - float(np.max(msg.t_capture)))
                    await asyncio.sleep(read_every)

            reader = asyncio.create_task(read_slowly())
            await run_players(url, players, seconds, builtin_motion_path())
            reader.cancel()
            await viewer.close()
            return lags

    lags = asyncio.run(main())
    assert len(lags) > 20
    settled = lags[len(lags) // 3:]
    print(f"reader asking for {0.5 / read_every:.1f} Hz, reading every "
          f"{read_every * 1000:.0f} ms: {np.median(settled) * 1000:.0f} ms behind "
          f"(median), {max(settled) * 1000:.0f} ms (max)")
    assert max(settled) < 0.2, [round(x, 3) for x in settled]
