"""The session server over real sockets on 127.0.0.1: rooms, players, spectators, bad input."""

from __future__ import annotations

import asyncio
import gc
import itertools
import math
import os
from collections import deque
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager
from pathlib import Path
from types import SimpleNamespace

import msgpack
import numpy as np
import pytest
from conftest import serving
from stream_decode import decode
from websockets.asyncio.client import ClientConnection, connect

from posecast.client.session.connection import SEND_BUFFER_LIMIT, make_hello, open_session
from posecast.protocol import (
    MAX_ANGLE_ERROR_DEG,
    PROTOCOL_VERSION,
    AvatarBatch,
    AvatarRoster,
    Calibrate,
    Error,
    Hello,
    TrackerFrame,
    Welcome,
    decode_client,
    encode,
    rotation_angle,
)
from posecast.protocol.validation import device_poses, pose_wire
from posecast.server.app import Session
from posecast.server.avatars import AvatarSolver, rig_coding
from posecast.server.clock import now
from posecast.server.metrics import Metrics
from posecast.server.outbox import Outbox
from posecast.server.room import Avatar, Room
from posecast.solver.calibration import calibrate
from posecast.solver.ik import PoseBatch, Solver
from posecast.solver.motion import ViveRecording
from posecast.solver.tracking.rows import TrackingRows, slots_of

TIMEOUT = 5.0


@pytest.fixture(scope="module")
def session() -> Session:
    return Session(reconnect_grace=5.0)  # building the rig and warming the solver: once


def run(test: Callable[[str], Awaitable[None]], session: Session) -> None:
    """Serve on a free port of 127.0.0.1, run the test against it, shut down cleanly."""
    async def main() -> None:
        async with serving(session) as url:
            await asyncio.wait_for(test(url), 60)
    asyncio.run(main())


@asynccontextmanager
async def joined(url: str, role: str, room: str, token: str | None = None,
                 resume: str | None = None, name: str | None = None,
                 ) -> AsyncIterator[tuple[ClientConnection, Welcome]]:
    async with connect(url, compression=None) as ws:
        await ws.send(encode(Hello(protocol_version=PROTOCOL_VERSION, role=role, room=room,
                                   display_name=name or f"{role}-{room}", token=token,
                                   resume=resume)))
        welcome = await receive(ws)
        assert isinstance(welcome, Welcome)
        yield ws, welcome


async def receive(ws: ClientConnection) -> object:
    return decode(await asyncio.wait_for(ws.recv(), TIMEOUT))


async def receive_type(ws: ClientConnection, kind: type) -> object:
    """The next message of a kind, skipping others (e.g. batches before an error reply)."""
    while True:
        msg = await receive(ws)
        if isinstance(msg, kind):
            return msg


def poses(rec: ViveRecording, frame: int) -> np.ndarray:
    return np.concatenate([rec.positions[frame], rec.rotations[frame]], axis=1)


def tracker(rec: ViveRecording, frame: int) -> bytes:
    # captured now on the server's clock (this process's): the server refuses a capture
    # time far from its clock (ServerLimits.capture_skew_s)
    return encode(TrackerFrame(seq=frame, roles=rec.devices, poses=poses(rec, frame),
                               t_capture=now(), clock_offset=0.0))


def calibration(rec: ViveRecording) -> bytes:
    return encode(Calibrate(roles=rec.devices, poses=poses(rec, 0), t_capture=0.0,
                            clock_offset=0.0))


def test_one_batch_of_avatars_equals_each_solved_alone(session: Session,
                                                      recording: ViveRecording) -> None:
    rec, n = recording, 5
    batched, alone = AvatarSolver(session.rig), AvatarSolver(session.rig)
    for solver in (batched, alone):
        for a in range(n):  # each avatar calibrated on its own T-pose row
            solver.calibrate(a, rec.devices, rec.positions[0], rec.rotations[0])
    reordered = tuple(reversed(rec.devices))
    for f in range(1, 7):
        frames = [(a, rec.devices, poses(rec, f + 20 * a)) for a in range(n)]
        if f % 2:  # one client sends its roles in another order
            frames[3] = (3, reordered, poses(rec, f + 60)[::-1])
        together = batched.solve(frames)
        for b, frame in enumerate(frames):
            one = alone.solve([frame])
            np.testing.assert_array_equal(together.rotations[b], one.rotations[0])
            np.testing.assert_array_equal(together.root[b], one.root[0])
        # and the batch moved: five different poses, not one pose five times
        assert np.abs(together.rotations[0] - together.rotations[1]).max() > 1e-3


def test_solving_in_place_or_gathered_gives_the_same_poses(session: Session,
                                                          recording: ViveRecording) -> None:
    """A batch in slot order is solved where its rows are, any other order is gathered
    and scattered: the same poses either way, and new arrays the next solve leaves be."""
    rec, n = recording, 4
    in_place, gathered = AvatarSolver(session.rig), AvatarSolver(session.rig)
    for solver in (in_place, gathered):
        for a in range(n):
            solver.calibrate(a, rec.devices, rec.positions[0], rec.rotations[0])
    for f in range(1, 5):
        for solver in (in_place, gathered):
            for a in range(n):
                solver.stage(a, rec.devices, poses(rec, f + 15 * a))
        a_state = in_place.solve_staged(list(range(n)))
        g_state = gathered.solve_staged(list(reversed(range(n))))
        np.testing.assert_array_equal(a_state.rotations, g_state.rotations[::-1])
        np.testing.assert_array_equal(a_state.root, g_state.root[::-1])
    before = a_state.rotations.copy()
    in_place.stage(0, rec.devices, poses(rec, 200))
    in_place.solve_staged(list(range(n)))
    np.testing.assert_array_equal(a_state.rotations, before)  # not a view of the state


@pytest.mark.parametrize("busy,helper", [(False, False), (True, False), (True, True)],
                         ids=["idle", "busy-poll", "busy-poll+helper"])
def test_spectator_receives_the_offline_solution(session: Session, recording: ViveRecording,
                                                 busy: bool, helper: bool) -> None:
    """Also with busy polling: between frames the server runs the latest frame's path on
    a twin avatar (server.busy), and the avatar's own poses must not feel it; and with
    the solver helper thread on the core the server is not pinned to."""
    frames = 40
    received: list[AvatarBatch] = []
    cores = os.sched_getaffinity(0)
    if helper:
        if len(cores) < 2:
            pytest.skip("the solver helper needs a second core")
        os.sched_setaffinity(0, {min(cores)})  # the server's core; the helper gets the rest
    if busy:
        session = Session(session.rig, reconnect_grace=5.0, busy=True, helper=helper)
        assert (session.avatars.helper() is not None) == helper

    async def test(url: str) -> None:
        async with joined(url, "spectator", "solo") as (spec, _), \
                joined(url, "player", "solo") as (player, welcome):
            assert isinstance(await receive(spec), AvatarRoster)  # empty room at first
            await player.send(calibration(recording))
            roster = await receive(spec)
            assert isinstance(roster, AvatarRoster)
            assert roster.avatars[0].avatar_id == welcome.avatar_id
            for f in range(1, frames + 1):  # one at a time: every frame is delivered
                await player.send(tracker(recording, f))
                batch = await receive(spec)
                assert isinstance(batch, AvatarBatch)
                received.append(batch)
                if busy:  # leave the server idle a moment: the twin's turn
                    await asyncio.sleep(0.002)
            if busy:  # as many turns as frames, however few a loaded machine gave it
                assert session.busy is not None
                async with asyncio.timeout(30):
                    while session.busy.warm.steps <= frames:
                        await asyncio.sleep(0.002)

    try:
        run(test, session)
    finally:
        os.sched_setaffinity(0, cores)
    if busy:
        assert session.busy is not None
        assert session.busy.warm.steps > frames  # it ran while idle, on the frames' data
        assert session.busy.bursts.count == 0
    # the same recording solved offline, frame by frame, warm-started, from the poses as
    # they travel (protocol 3: float32)
    rig = session.rig
    rec = recording
    tpose = device_poses(poses(rec, 0))
    cal = calibrate(rig, dict(zip(rec.devices, tpose[:, :3], strict=True)),
                    dict(zip(rec.devices, tpose[:, 3:], strict=True)))
    solver = Solver(rig, session.solver_name)
    state = PoseBatch(cal.pose[None].copy(), cal.root[None].copy())
    rows = TrackingRows(1)  # every device drives, as on the server
    rows.calibrate(0, cal)
    coding = rig_coding(rig, cal.pose)  # as the roster gave it

    for f, batch in enumerate(received):
        rows.stage(0, slots_of(rec.devices), device_poses(poses(rec, f + 1)), 0.0)
        rows.fill(np.zeros(1, dtype=np.intp))
        solver.solve(rows.targets[:1], state, cal.offsets[None], rows.weights[:1])
        (frame,) = batch.frames
        assert frame.seq == f + 1
        # exactly the offline rotations as the roster's coding carries them, within its
        # bound of them
        wire = coding.unpack(coding.pack(state.rotations[:1]))[0]
        np.testing.assert_array_equal(frame.rotations, wire)
        assert np.degrees(rotation_angle(frame.rotations, state.rotations[0]).max()) \
            <= MAX_ANGLE_ERROR_DEG * (1 + 1e-6)
        np.testing.assert_allclose(frame.root, state.root[0], atol=1e-5)  # float32 root


def test_join_leave_and_rooms_are_isolated(session: Session,
                                           recording: ViveRecording) -> None:
    async def test(url: str) -> None:
        async with joined(url, "spectator", "a") as (spec_a, _), \
                joined(url, "spectator", "b") as (spec_b, _):
            for ws in (spec_a, spec_b):
                assert (await receive(ws)).avatars == ()  # type: ignore[attr-defined]
            async with joined(url, "player", "a") as (player, welcome):
                await player.send(calibration(recording))
                await receive_type(spec_a, AvatarRoster)
                await player.send(tracker(recording, 1))
                batch = await receive_type(spec_a, AvatarBatch)
                assert [f.avatar_id for f in batch.frames] == [welcome.avatar_id]
            # the player closed the connection itself: the avatar goes at once
            gone = await receive_type(spec_a, AvatarRoster)
            assert gone.removed == (welcome.avatar_id,)  # type: ignore[attr-defined]
            # room b heard nothing of room a
            with pytest.raises(TimeoutError):
                await asyncio.wait_for(spec_b.recv(), 0.3)

    run(test, session)


def test_reconnecting_player_keeps_its_avatar(session: Session,
                                              recording: ViveRecording) -> None:
    async def test(url: str) -> None:
        async with joined(url, "spectator", "r") as (spec, _):
            await receive(spec)
            async with joined(url, "player", "r") as (player, first):
                assert first.resume is not None and not first.resumed
                await player.send(calibration(recording))
                await receive_type(spec, AvatarRoster)
                player.transport.abort()  # dropped, not closed: the avatar waits
            async with joined(url, "player", "r", resume=first.resume) as (player, second):
                assert second.avatar_id == first.avatar_id and second.resumed
                # still calibrated: frames are solved without a new T-pose
                await player.send(tracker(recording, 2))
                batch = await receive_type(spec, AvatarBatch)
                assert batch.frames[0].avatar_id == first.avatar_id  # type: ignore[attr-defined]

    run(test, session)


def _bad_messages(rec: ViveRecording) -> list[tuple[str, bytes, str]]:
    frame = msgpack.unpackb(tracker(rec, 3))
    wrong_type = {**frame, "seq": "three"}
    nan = poses(rec, 3).copy()
    nan[2, 1] = math.nan
    nan_frame = {**frame, "poses": pose_wire(nan)}
    # over the protocol's 8 KiB, within websockets' bound (which closes with 1009)
    huge = {**frame, "padding": b"x" * 8000}
    old = {"type": "hello", "protocol_version": 99, "role": "player", "room": "x",
           "display_name": "old"}
    return [("not_msgpack", b"\xc1 not msgpack", "msgpack"),
            ("invalid", msgpack.packb(wrong_type), "seq"),
            ("invalid", msgpack.packb(nan_frame), "nan"),
            ("too_large", msgpack.packb(huge), "bytes"),
            ("unsupported_version", msgpack.packb(old), "99")]


def test_bad_messages_are_rejected_and_others_carry_on(session: Session,
                                                       recording: ViveRecording) -> None:
    async def test(url: str) -> None:
        async with joined(url, "spectator", "bad") as (spec, _), \
                joined(url, "player", "bad") as (good, good_welcome), \
                joined(url, "player", "bad") as (bad, _):
            await receive(spec)
            await good.send(calibration(recording))
            await bad.send(calibration(recording))
            await receive_type(spec, AvatarRoster)
            await receive_type(spec, AvatarRoster)
            for i, (code, data, words) in enumerate(_bad_messages(recording)):
                await bad.send(data)
                err = await receive_type(bad, Error)
                assert err.code == code, err  # type: ignore[attr-defined]
                assert words in err.message.lower(), err  # type: ignore[attr-defined]
                # the good player's next frame still reaches the spectator
                await good.send(tracker(recording, 10 + i))
                batch = await receive_type(spec, AvatarBatch)
                assert good_welcome.avatar_id in [f.avatar_id for f in batch.frames]  # type: ignore[attr-defined]
            # a spectator may not send tracker frames
            await spec.send(tracker(recording, 5))
            err = await receive_type(spec, Error)
            assert err.code == "not_allowed"  # type: ignore[attr-defined]
            # the bad player is still connected and still served
            await bad.send(tracker(recording, 30))
            await receive_type(spec, AvatarBatch)
        assert session.metrics.rejected["not_msgpack"] >= 1

    run(test, session)


def test_every_frame_is_counted_once_whatever_became_of_it(session: Session,
                                                          recording: ViveRecording) -> None:
    """Each tracker frame received is solved, superseded, discarded or rejected, and
    each solved avatar-frame is delivered to the spectator or dropped: exactly, however
    the frames happened to batch."""
    counted = Session(session.rig, reconnect_grace=0.0)  # counts of its own

    async def test(url: str) -> None:
        async with joined(url, "spectator", "count") as (spec, _):
            await receive(spec)
            async with joined(url, "player", "count") as (player, welcome):
                await player.send(tracker(recording, 1))  # before its T-pose: rejected
                await receive_type(player, Error)
                await player.send(calibration(recording))
                await receive_type(spec, AvatarRoster)
                for f in range(2, 40):  # back to back: some supersede others
                    await player.send(tracker(recording, f))
                await player.send(calibration(recording))  # discards a frame pending
                await receive_type(spec, AvatarRoster)
                for f in range(40, 60):
                    await player.send(tracker(recording, f))
            # the player left (its frame pending then, if any, is discarded); once the
            # spectator hears it, nothing more is solved for it
            while True:
                roster = await receive_type(spec, AvatarRoster)
                if welcome.avatar_id in roster.removed:  # type: ignore[attr-defined]
                    break

    run(test, counted)
    m = counted.metrics
    assert (m.frames_received, m.frames_rejected) == (59, 1)
    assert m.frames_solved > 0
    assert m.frames_received == (m.frames_solved + m.frames_superseded
                                 + m.frames_discarded + m.frames_rejected
                                 + m.frames_unsendable)
    assert m.frames_delivered + m.frames_dropped == m.frames_solved


def test_unknown_version_is_refused_at_hello(session: Session) -> None:
    async def test(url: str) -> None:
        async with connect(url, compression=None) as ws:
            await ws.send(msgpack.packb({"type": "hello", "protocol_version": 99,
                                         "role": "spectator", "room": "v",
                                         "display_name": "x"}))
            err = await receive(ws)
            assert isinstance(err, Error) and err.code == "unsupported_version"
            assert "99" in err.message

    run(test, session)


def test_a_burst_waits_for_a_frame_read_but_not_yet_handled(session: Session,
                                                          recording: ViveRecording) -> None:
    """The handlers of frames read in one pass of the event loop run in the next: a
    batch stays open while a player's frame is read (its arrival stamped) but not yet
    submitted, so that a burst is solved as one batch, and closes at the window's end
    even if that frame never comes."""
    rec = recording

    async def burst(submit_second: bool) -> tuple[int, int]:
        # a window no loaded machine outlasts in the passes below; ended by hand after
        room = Room("r", AvatarSolver(session.rig), Metrics(), coalesce_max_s=60.0)
        for a in (1, 2):
            room.avatars[a] = avatar = Avatar(a, f"player {a}", f"resume-{a}")
            room.calibrate(avatar, rec.devices, poses(rec, 0))
        # what a connection holds once the second player's frame is read from its socket
        room.avatars[2].connection = SimpleNamespace(arrivals=deque([now()]))
        room.submit(1, decode_client(tracker(rec, 5)), now())
        for _ in range(5):  # passes of the loop: the read frame keeps the batch open
            await asyncio.sleep(0)
        open_then = room.metrics.batches
        if submit_second:  # its handler runs: the burst is complete
            room.avatars[2].connection.arrivals.popleft()
            room.submit(2, decode_client(tracker(rec, 6)), now())
            for _ in range(3):
                await asyncio.sleep(0)
        else:
            room.coalesce_max_s = 0.0  # the window is over (not waited out)
            for _ in range(3):
                await asyncio.sleep(0)
        assert room.metrics.batches == 1
        return open_then, room.metrics.frames_solved

    assert asyncio.run(burst(True)) == (0, 2)  # one batch of both
    assert asyncio.run(burst(False)) == (0, 1)  # the window ended it


def test_a_player_drops_frames_rather_than_queue_them_behind_a_stalled_server(
        session: Session, recording: ViveRecording) -> None:
    """send_now writes at once while the server keeps up; when the server stops reading,
    the frames wait in the kernel, then in the transport, and past SEND_BUFFER_LIMIT the
    player drops new frames instead of queueing stale poses; after close, nothing is
    sent."""
    async def test(url: str) -> None:
        player = await open_session(url, make_hello(url, "player", "stall", "p"))
        assert player.send_now(calibration(recording))
        assert player.avatar_id is not None
        server_side = session._owners[player.avatar_id]
        assert server_side.transport is not None
        server_side.transport.pause_reading()  # a server that stops reading this player
        frame = tracker(recording, 5)
        sent = 0
        while player.send_now(frame):  # the kernel's buffers fill, then the transport's
            sent += 1
            if sent % 100 == 0:
                await asyncio.sleep(0)
            assert sent < 100_000, "the player never noticed the stalled server"
        assert player.ws.transport.get_write_buffer_size() > SEND_BUFFER_LIMIT
        assert not player.send_now(frame)
        server_side.transport.resume_reading()
        await player.close()
        assert not player.send_now(frame)

    run(test, session)


def test_start_up_objects_are_frozen_once_a_session_is_open(session: Session) -> None:
    """A client's full collections walk only what its session makes: what start-up made
    is moved to the permanent generation when a session opens (gc.freeze)."""
    async def test(url: str) -> None:
        gc.unfreeze()
        assert gc.get_freeze_count() == 0
        viewer = await open_session(url, make_hello(url, "spectator", "frozen", "v"))
        assert gc.get_freeze_count() > 10_000
        await viewer.close()

    run(test, session)


def test_outbox_keeps_the_latest_frame_per_avatar_for_a_stalled_receiver() -> None:
    async def main() -> tuple[list[list[str]], int, int, int]:
        release = asyncio.Event()
        sending = asyncio.Event()
        sent: list[list[str]] = []

        async def send(frames: list[str]) -> None:
            sent.append(frames)
            sending.set()
            await release.wait()  # a receiver that stops reading

        box: Outbox[str] = Outbox(send)
        task = asyncio.create_task(box.run())
        box.offer({1: "a1", 2: "b1"})
        await asyncio.wait_for(sending.wait(), 30)  # the first send is under way, stalled
        for k in range(2, 100):
            box.offer({1: f"a{k}", 2: f"b{k}"})
        pending = box.pending
        sending.clear()
        release.set()
        await asyncio.wait_for(sending.wait(), 30)  # the second send
        box.close()
        await task
        return sent, pending, box.delivered, box.dropped

    sent, pending, delivered, dropped = asyncio.run(main())
    assert pending == 2  # bounded by the avatars, not by the frames offered
    assert sent == [["a1", "b1"], ["a99", "b99"]]  # then only the newest
    assert (delivered, dropped) == (4, 2 * 97)  # each of the 198 frames offered: one


def test_outbox_counts_every_frame_it_never_sends() -> None:
    """Offered frames are delivered or dropped, never lost uncounted: replaced by a
    newer one, forgotten with their avatar, held at close, offered after it, or in a
    send that failed."""
    async def main() -> tuple[int, int]:
        async def send(frames: list[str]) -> None:
            raise ConnectionError("the receiver went away")

        box: Outbox[str] = Outbox(send)
        box.offer({1: "a1", 2: "b1", 3: "c1"})
        box.offer({1: "a2"})  # replaces a1
        box.forget(2)  # b1 with its avatar
        box.close()  # a2 and c1 still held
        box.offer({1: "a3"})  # after close
        failing: Outbox[str] = Outbox(send)
        task = asyncio.create_task(failing.run())
        failing.offer({1: "a1", 2: "b1"})
        with pytest.raises(ConnectionError):
            await asyncio.wait_for(task, 30)
        assert failing.idle and (failing.delivered, failing.dropped) == (0, 2)
        return box.delivered, box.dropped

    assert asyncio.run(main()) == (0, 5)


def test_spectator_rate_limit() -> None:
    """Sends are never closer than the rate asked for, however the loop runs; each sends
    the newest frame, the last one offered included; the rest are counted as dropped."""
    async def main() -> tuple[list[tuple[float, list[int]]], int, int]:
        loop = asyncio.get_running_loop()
        sends: list[tuple[float, list[int]]] = []

        async def send(frames: list[int]) -> None:
            sends.append((loop.time(), frames))

        box: Outbox[int] = Outbox(send, max_rate_hz=20.0)
        task = asyncio.create_task(box.run())
        for k in range(50):  # 90 Hz offers for about half a second
            box.offer({1: k})
            await asyncio.sleep(1 / 90)
        async with asyncio.timeout(30):
            while sends[-1][1] != [49]:
                await asyncio.sleep(0.01)
        box.close()
        await task
        return sends, box.delivered, box.dropped

    sends, delivered, dropped = asyncio.run(main())
    times = [t for t, _ in sends]
    # uvloop keeps loop time in whole milliseconds: a gap may read 1 ms short
    assert min(b - a for a, b in itertools.pairwise(times)) >= 1 / 20 - 0.002
    frames = [f for _, f in sends]
    assert all(len(f) == 1 for f in frames) and frames == sorted(frames)
    assert delivered == len(sends) and delivered + dropped == 50


def test_shared_batch_is_encoded_once_and_parts_match_it() -> None:
    from posecast.server.room import SharedBatch
    rotations = np.tile([0.0, 0.0, 0.0, 1.0], (2, 3, 1))
    shared = SharedBatch([7, 9], [1, 2], np.zeros((2, 3)), rotations, [0.5, 0.6],
                         [1.0, 1.1], 1.2)
    data = shared.encoded()
    assert data is shared.encoded()
    whole = decode(data)
    assert isinstance(whole, AvatarBatch)
    assert [f.avatar_id for f in whole.frames] == [7, 9]
    # a spectator that gets part of the batch gets the same frame, t_sent aside
    part = shared.frame(1)
    assert part.avatar_id == 9 and part.seq == 2 and part.t_capture == 0.6
    np.testing.assert_array_equal(part.rotations, whole.frames[1].rotations)


def test_serve_shuts_down_cleanly_on_sigterm(tmp_path: Path) -> None:
    import json
    import signal
    import socket
    import subprocess
    import sys
    import time

    with socket.socket() as s:  # a free port
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen([sys.executable, "-m", "posecast.client.cli", "serve", "--port",
                             str(port)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:  # until it listens
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", port)) == 0:
                    break
            time.sleep(0.1)
        else:
            pytest.fail("posecast serve did not start listening")

        async def spectate() -> None:
            async with joined(f"ws://127.0.0.1:{port}", "spectator", "sig") as (ws, _):
                await receive(ws)
                proc.send_signal(signal.SIGTERM)
                # the server closes our connection as it goes
                await asyncio.wait_for(ws.wait_closed(), TIMEOUT)

        asyncio.run(spectate())
        out, err = proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    counters = json.loads(out.strip().splitlines()[-1])
    assert counters["connections"] == 1 and counters["rejected"] == {}
