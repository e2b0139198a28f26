"""server/fanout.py on a real server's sockets: when the writes of a batch outlast their
slice, the spectators not reached yet get it with the next one, in one write, in order,
with no frame lost and none counted twice; a roster waits behind them; batches older
than MAX_LAG_S go (latest wins)."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest
from stream_decode import decode
from test_server_eviction import TIMEOUT, join, server
from websockets.asyncio.client import ClientConnection

from posecast.client.bench.demo import ROOM, run_players
from posecast.client.builtin import builtin_motion_path
from posecast.protocol import AvatarBatch, AvatarRoster, encode
from posecast.server import fanout
from posecast.server.app import Session
from posecast.server.clock import now
from posecast.server.room import Room, SharedBatch

SPECTATORS = 12
AVATAR = 7  # no player of the room: a batch of it unpacks without a roster coding
JOINTS = 53


def batch(seq: int) -> SharedBatch:
    rotations = np.zeros((1, JOINTS, 4))
    rotations[..., 3] = 1.0
    t = now()
    return SharedBatch([AVATAR], [seq], np.zeros((1, 3)), rotations, [t], [t], t)


async def room_with(session: Session, url: str, n: int) -> tuple[Room, list[ClientConnection]]:
    clients = [await join(url, "spectator") for _ in range(n)]
    room = session.rooms[ROOM]
    while len(room.spectators) < n:  # the last join is in once its roster is written
        await asyncio.sleep(0.01)
    return room, clients


async def messages(ws: ClientConnection, count: int) -> list[object]:
    """The next ``count`` batches and rosters (a roster of the room's own joins aside)."""
    got: list[object] = []
    while len(got) < count:
        msg = decode(await asyncio.wait_for(ws.recv(), TIMEOUT))
        if isinstance(msg, AvatarBatch):
            got.append(("batch", int(msg.seqs[0])))
        elif isinstance(msg, AvatarRoster) and msg.removed:
            got.append(("removed", msg.removed))
    return got


async def settle(room: Room) -> None:
    while not room.fanout.idle:
        await asyncio.sleep(0.001)


@pytest.fixture
def one_write_a_slice(monkeypatch: pytest.MonkeyPatch) -> None:
    """A slice of one write: every batch outlasts its slice."""
    monkeypatch.setattr(fanout, "SLICE_S", 0.0)
    monkeypatch.setattr(fanout, "CHECK_EVERY", 1)


@pytest.mark.usefixtures("one_write_a_slice")
def test_batches_that_outlast_their_slice_go_out_merged_whole_and_in_order() -> None:
    session = Session()

    async def main() -> None:
        async with server(session) as (url, _, _):
            room, clients = await room_with(session, url, SPECTATORS)
            m = session.metrics
            delivered = m.frames_delivered
            # three batches in one pass of the loop: the first reaches one spectator in
            # its slice; the others wait, and the next two join the round under way ...
            for seq in range(3):
                room.fanout.deliver(batch(seq))
            # ... and a roster after them: written behind every queued batch
            room.send_roster(encode(AvatarRoster(removed=(AVATAR,))))
            assert room.fanout.idle
            for ws in clients:
                assert await messages(ws, 4) == [("batch", 0), ("batch", 1), ("batch", 2),
                                                 ("removed", (AVATAR,))]
            # the first got batch 0 alone, then 1 and 2 in one write (a second round);
            # every other one its three in one write
            assert m.writes_merged == SPECTATORS
            assert m.frames_delivered - delivered == 3 * SPECTATORS
            assert m.frames_dropped == 0
            for ws in clients:
                await ws.close()

    asyncio.run(main())


@pytest.mark.usefixtures("one_write_a_slice")
def test_batches_older_than_max_lag_are_dropped_and_counted(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # every batch but the newest too old, whatever the clock's resolution (uvloop's
    # time() is the same for the whole pass of the loop that delivers them)
    monkeypatch.setattr(fanout, "MAX_LAG_S", -1.0)
    session = Session()
    sent = 6

    async def main() -> None:
        async with server(session) as (url, _, _):
            room, clients = await room_with(session, url, SPECTATORS)
            m = session.metrics
            for seq in range(sent):
                room.fanout.deliver(batch(seq))
            await settle(room)
            dropped = 0
            for ws in clients:
                seqs = []
                while not seqs or seqs[-1][1] != sent - 1:  # the newest always comes
                    seqs += await messages(ws, 1)
                got = [s for _, s in seqs]
                assert got == sorted(set(got))  # in order, none twice
                dropped += sent - len(got)
            assert dropped > 0
            assert m.frames_dropped == dropped
            assert m.frames_delivered + m.frames_dropped == sent * SPECTATORS
            for ws in clients:
                await ws.close()

    asyncio.run(main())


@pytest.mark.usefixtures("one_write_a_slice")
def test_a_room_written_a_spectator_a_slice_loses_no_frame_of_its_players() -> None:
    # players streaming for real: every solved frame reaches every spectator, in order,
    # though each batch now takes a dozen passes of the loop
    session = Session()

    async def main() -> None:
        async with server(session) as (url, _, _):
            room, clients = await room_with(session, url, 8)
            counts = [0] * len(clients)
            last: list[dict[int, int]] = [{} for _ in clients]

            async def read(i: int, ws: ClientConnection) -> None:
                async for data in ws:
                    msg = decode(data)
                    if isinstance(msg, AvatarBatch):
                        for a, seq in zip(msg.avatar_ids.tolist(), msg.seqs.tolist(),
                                          strict=True):
                            assert seq > last[i].get(a, -1)  # in order
                            last[i][a] = seq
                        counts[i] += msg.size

            readers = [asyncio.create_task(read(i, ws)) for i, ws in enumerate(clients)]
            await run_players(url, 4, 2.0, builtin_motion_path())
            await settle(room)
            m = session.metrics
            deadline = now() + TIMEOUT  # the last writes, read
            while counts != [m.frames_solved] * len(clients) and now() < deadline:
                await asyncio.sleep(0.01)
            assert m.frames_solved > 4 * 90
            assert counts == [m.frames_solved] * len(clients)
            assert m.frames_dropped == 0
            for task in readers:
                task.cancel()
            for ws in clients:
                await ws.close()

    asyncio.run(main())


@pytest.mark.usefixtures("one_write_a_slice")
def test_a_spectator_that_leaves_before_its_turn_has_its_frames_counted_dropped() -> None:
    session = Session()

    async def main() -> None:
        async with server(session) as (url, _, _):
            room, clients = await room_with(session, url, SPECTATORS)
            m = session.metrics
            room.fanout.deliver(batch(0))  # written to the first only; the rest wait
            assert not room.fanout.idle
            room.fanout._next_slice.cancel()  # type: ignore[union-attr]  # they keep waiting
            leaving = clients[-3:]
            for ws in leaving:
                await ws.close()
            while len(room.spectators) > SPECTATORS - len(leaving):
                await asyncio.sleep(0.01)
            room.fanout.flush()
            assert room.fanout.idle
            assert (m.frames_delivered, m.frames_dropped) == (SPECTATORS - 3, 3)
            for ws in clients[:-3]:
                assert await messages(ws, 1) == [("batch", 0)]
                await ws.close()

    asyncio.run(main())


@pytest.mark.usefixtures("one_write_a_slice")
def test_each_round_starts_a_place_further_so_no_spectator_always_waits_longest() -> None:
    # one write a slice: a batch is written to the round's first spectator at once, the
    # others at later passes of the loop. Over as many rounds as spectators (a turn of
    # one place a round), each was first once
    session = Session()

    async def main() -> None:
        async with server(session) as (url, _, _):
            room, clients = await room_with(session, url, SPECTATORS)
            firsts = []
            for seq in range(SPECTATORS):
                room.fanout.deliver(batch(seq))
                firsts += [c for c, s in room.spectators.items()
                           if s.mark == room.fanout.latest]
                await settle(room)
            assert sorted(firsts) == sorted(room.spectators)
            for ws in clients:  # and every spectator still got every batch, in order
                assert await messages(ws, SPECTATORS) == [
                    ("batch", k) for k in range(SPECTATORS)]
                await ws.close()

    asyncio.run(main())
