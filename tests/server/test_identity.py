"""Who is who, decided by the server (issue 15): a player's avatar comes back only with the
random resume secret its Welcome gave it, names are unique in a room, and a player that
says goodbye leaves at once while a dropped one is waited for. Real sockets on 127.0.0.1."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable

import pytest
from conftest import serving
from test_server import calibration, joined, receive, receive_type, tracker
from websockets.asyncio.client import connect

from posecast.protocol import (
    PROTOCOL_VERSION,
    AvatarBatch,
    AvatarRoster,
    Error,
    Hello,
    Leave,
    Welcome,
    encode,
)
from posecast.server.app import Session
from posecast.solver.motion import ViveRecording

TIMEOUT = 10.0


@pytest.fixture(scope="module")
def session() -> Session:
    return Session(reconnect_grace=30.0)  # the production grace


def run(test: Callable[[str], Awaitable[None]], session: Session) -> None:
    async def main() -> None:
        async with serving(session) as url:
            await asyncio.wait_for(test(url), 60)
    asyncio.run(main())


def test_the_resume_secret_is_random_and_issued_by_the_server(session: Session) -> None:
    async def test(url: str) -> None:
        async with joined(url, "player", "secrets") as (_, a), \
                joined(url, "player", "secrets") as (_, b), \
                joined(url, "spectator", "secrets") as (_, viewer):
            assert a.resume is not None and b.resume is not None
            assert a.resume != b.resume and min(len(a.resume), len(b.resume)) >= 32
            assert not a.resumed and not b.resumed
            assert viewer.resume is None and viewer.avatar_id is None  # nothing to resume

    run(test, session)


def test_a_guessed_or_chosen_secret_never_reaches_anothers_avatar(
        session: Session, recording: ViveRecording) -> None:
    """Guesses get an avatar of their own; the owner keeps streaming, undisturbed."""
    async def test(url: str) -> None:
        async with joined(url, "spectator", "guess") as (viewer, _), \
                joined(url, "player", "guess", name="alice") as (alice, welcome):
            await alice.send(calibration(recording))
            await receive_type(viewer, AvatarRoster)
            assert welcome.avatar_id is not None and welcome.resume is not None
            guesses = ["1", "alice", str(welcome.avatar_id), welcome.resume[:-1] + "A"
                       if welcome.resume[-1] != "A" else welcome.resume[:-1] + "B"]
            for guess in guesses:
                async with joined(url, "player", "guess", resume=guess) as (_, other):
                    assert other.avatar_id != welcome.avatar_id and not other.resumed
            # the real secret, in another room: nothing there either
            async with joined(url, "player", "elsewhere", resume=welcome.resume) as (_, o):
                assert o.avatar_id != welcome.avatar_id and not o.resumed
            # alice's connection was never touched: her frames still go out as hers
            await alice.send(tracker(recording, 1))
            batch = await receive_type(viewer, AvatarBatch)
            assert isinstance(batch, AvatarBatch)
            assert welcome.avatar_id in batch.avatar_ids.tolist()

    run(test, session)


def test_display_names_are_unique_in_a_room(session: Session,
                                            recording: ViveRecording) -> None:
    async def test(url: str) -> None:
        async with joined(url, "player", "names", name="alice") as (a, first), \
                joined(url, "player", "names", name="alice") as (b, second), \
                joined(url, "player", "names", name="alice") as (c, third), \
                joined(url, "player", "other", name="alice") as (_, elsewhere):
            assert (first.display_name, second.display_name, third.display_name) == (
                "alice", "alice 2", "alice 3")
            assert elsewhere.display_name == "alice"  # another room: no clash
            for ws in (a, b, c):
                await ws.send(calibration(recording))
            async with joined(url, "spectator", "names") as (viewer, _):
                names: set[str] = set()
                while len(names) < 3:
                    roster = await receive_type(viewer, AvatarRoster)
                    assert isinstance(roster, AvatarRoster)
                    names |= {info.display_name for info in roster.avatars}
                assert names == {"alice", "alice 2", "alice 3"}
            # a name at the protocol's 64 characters still gets its number
            async with joined(url, "player", "names", name="alice" + "x" * 59) as (_, w1), \
                    joined(url, "player", "names", name="alice" + "x" * 59) as (_, w2):
                assert w1.display_name == "alice" + "x" * 59
                assert w2.display_name is not None and len(w2.display_name) == 64
                assert w2.display_name.endswith(" 2")

    run(test, session)


def test_a_dropped_player_resumes_calibrated_and_one_that_leaves_is_gone(
        session: Session, recording: ViveRecording) -> None:
    async def test(url: str) -> None:
        async with joined(url, "spectator", "back") as (viewer, _):
            await receive(viewer)  # the empty roster
            async with joined(url, "player", "back", name="bob") as (bob, first):
                await bob.send(calibration(recording))
                await receive_type(viewer, AvatarRoster)
                bob.transport.abort()  # the network went: no close
            async with joined(url, "player", "back", name="bob 2",
                              resume=first.resume) as (bob, again):
                assert again.resumed and again.avatar_id == first.avatar_id
                assert again.display_name == "bob"  # its name, not the new hello's
                assert again.resume == first.resume
                await bob.send(tracker(recording, 1))  # no new T-pose needed
                batch = await receive_type(viewer, AvatarBatch)
                assert isinstance(batch, AvatarBatch)
                assert batch.avatar_ids.tolist() == [first.avatar_id]
                await bob.send(encode(Leave()))
                gone = await receive_type(viewer, AvatarRoster)
                assert isinstance(gone, AvatarRoster) and gone.removed == (first.avatar_id,)
            # it left: its secret brings back nothing
            async with joined(url, "player", "back", resume=first.resume) as (bob, late):
                assert not late.resumed and late.avatar_id != first.avatar_id
                await bob.send(tracker(recording, 1))
                error = await receive_type(bob, Error)
                assert isinstance(error, Error) and error.code == "not_calibrated"

    run(test, session)


def test_a_player_that_reconnects_takes_over_from_its_old_connection(
        session: Session, recording: ViveRecording) -> None:
    """The old connection of a resumed avatar is closed: one avatar, one stream."""
    async def test(url: str) -> None:
        async with joined(url, "player", "twice") as (old, first), \
                joined(url, "player", "twice", resume=first.resume) as (_, second):
            assert isinstance(second, Welcome) and second.resumed
            await asyncio.wait_for(old.wait_closed(), TIMEOUT)
            assert old.close_code == 1000 and "reconnected" in (old.close_reason or "")

    run(test, session)


def test_clients_gone_right_after_their_hello_leave_nothing_behind(
        session: Session, caplog: pytest.LogCaptureFixture) -> None:
    """A hello and a close in one go: the welcome then meets a closed connection. Before,
    that raised out of the handler (a traceback) and left the player's avatar connected
    for good."""
    async def test(url: str) -> None:
        for role in ("player", "spectator") * 10:
            ws = await connect(url, compression=None)
            hello = Hello(protocol_version=PROTOCOL_VERSION, role=role, room="gone",
                          display_name=role)
            await asyncio.gather(ws.send(encode(hello)), ws.close())
        room = session.rooms.get("gone")
        t_end = asyncio.get_running_loop().time() + TIMEOUT
        while room is not None and any(a.connected for a in room.avatars.values()):
            assert asyncio.get_running_loop().time() < t_end, "an avatar stays connected"
            await asyncio.sleep(0.05)
        assert room is None or not room.spectators

    with caplog.at_level(logging.ERROR):
        run(test, session)
    assert not [r for r in caplog.records if r.exc_info], caplog.text
