"""How the server groups frames into bursts: each player's cadence, the bursts a room
keeps open for the players due, and the count of open bursts that busy polling waits on."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from posecast.protocol import Calibrate, TrackerFrame, decode_client, encode
from posecast.protocol.batch import AvatarBatch
from posecast.protocol.codec import decode
from posecast.protocol.errors import ProtocolError
from posecast.server.app import Session
from posecast.server.avatars import AvatarSolver
from posecast.server.busy import TWIN, OpenBursts, WarmPath
from posecast.server.cadence import MAX_PERIOD_S, Cadence
from posecast.server.metrics import Metrics
from posecast.server.outbox import Outbox
from posecast.server.room import Avatar, Delivery, Room, Spectator
from posecast.solver.motion import ViveRecording

PERIOD = 1 / 90


# --------------------------------------------------------------------------- cadence
def test_cadence_learns_the_period_and_predicts_the_next_frame() -> None:
    c = Cadence()
    assert c.due() is None  # nothing to go by
    c.arrived(10.0)
    assert c.due() is None  # one frame: no period yet
    for k in range(1, 40):  # 90 Hz with +-0.2 ms of jitter
        c.arrived(10.0 + k * PERIOD + (0.0002 if k % 2 else -0.0002))
    assert c.period == pytest.approx(PERIOD, abs=5e-5)
    assert c.due() == pytest.approx(10.0 + 40 * PERIOD, abs=3e-4)
    assert c.due_within(10.0 + 40 * PERIOD - 0.001, 10.0 + 40 * PERIOD + 0.001)
    assert not c.due_within(10.0 + 40 * PERIOD + 0.001, 10.0 + 40 * PERIOD + 0.002)


def test_cadence_ignores_a_skipped_frame_but_follows_a_new_rate() -> None:
    c = Cadence()
    t = 0.0
    for _ in range(20):
        t += PERIOD
        c.arrived(t)
    t += 2 * PERIOD  # one frame lost on the way: not a new rate
    c.arrived(t)
    assert c.period == pytest.approx(PERIOD)
    for _ in range(3):  # the headset now runs at 45 Hz: three such intervals in a row
        t += 2 * PERIOD
        c.arrived(t)
    assert c.period == pytest.approx(2 * PERIOD)
    c.arrived(t + 2 * MAX_PERIOD_S)  # a pause: no interval to learn from
    assert c.period == pytest.approx(2 * PERIOD)


def test_open_bursts_count_and_signal() -> None:
    b = OpenBursts()
    assert b.count == 0 and b.none_open.is_set()
    b.opened()
    b.opened()
    b.closed()
    assert b.count == 1 and not b.none_open.is_set()
    b.closed()
    b.closed()  # one more than opened: stays at zero
    assert b.count == 0 and b.none_open.is_set()


# --------------------------------------------------------------------------- rooms
@pytest.fixture(scope="module")
def session() -> Session:
    return Session()


def _frame(rec: ViveRecording, f: int) -> TrackerFrame:
    poses = np.concatenate([rec.positions[f], rec.rotations[f]], axis=1)
    msg = decode_client(encode(TrackerFrame(seq=f, roles=rec.devices, poses=poses,
                                            t_capture=float(f), clock_offset=0.0)))
    assert isinstance(msg, TrackerFrame)
    return msg


def _room(session: Session, rec: ViveRecording, window: float,
          bursts: OpenBursts | None = None) -> Room:
    room = Room("r", AvatarSolver(session.rig), Metrics(), coalesce_max_s=window,
                bursts=bursts)
    t_pose = np.concatenate([rec.positions[0], rec.rotations[0]], axis=1)
    cal = Calibrate(roles=rec.devices, poses=t_pose, t_capture=0.0, clock_offset=0.0)
    for a in (1, 2):
        room.avatars[a] = avatar = Avatar(a, f"player {a}", f"resume-{a}")
        room.calibrate(avatar, cal.roles, cal.poses)
    return room


def _burst(session: Session, rec: ViveRecording, window: float, due_2: float,
           early: float) -> tuple[set[int], int, int]:
    """Player 1's frame was due at 1.0 and arrives ``early`` seconds before that; player
    2's is due at 1.0 + ``due_2``. Returns the players the burst then waits for, and
    the batches solved and the frames in them after some passes of the loop in which
    player 2 sends nothing."""
    async def main() -> tuple[set[int], int, int]:
        bursts = OpenBursts()
        room = _room(session, rec, window, bursts)
        room.avatars[1].cadence = Cadence(last=1.0 - PERIOD, period=PERIOD)
        room.avatars[2].cadence = Cadence(last=1.0 + due_2 - PERIOD, period=PERIOD)
        room.submit(1, _frame(rec, 5), 1.0 - early)
        awaited = set(room._awaited)
        assert bursts.count == 1  # a busy-polling server now waits for the solve
        for _ in range(5):
            await asyncio.sleep(0)
        batches, solved = room.metrics.batches, room.metrics.frames_solved
        if batches == 0:  # still open: player 2 comes, one batch of both
            room.submit(2, _frame(rec, 6), 1.0 + due_2)
            # solved in the read of the frame the burst waited for, not a pass later
            assert (room.metrics.batches, room.metrics.frames_solved) == (1, 2)
            assert bursts.count == 0
            for _ in range(3):
                await asyncio.sleep(0)
            assert (room.metrics.batches, room.metrics.frames_solved) == (1, 2)
        else:
            await asyncio.sleep(window)  # past the window: nothing else comes
        assert bursts.count == 0
        return awaited, batches, solved

    return asyncio.run(main())


def test_a_burst_waits_for_the_players_due_with_it(session: Session,
                                                   recording: ViveRecording) -> None:
    # player 2 ticks with player 1 (due 0.3 ms after it): the burst waits for its frame
    # (a window no loaded machine outlasts: player 2's frame ends the burst here)
    assert _burst(session, recording, window=60.0, due_2=0.0003, early=0.0) == ({2}, 0, 0)
    # player 2 is out of step (due 5 ms later): player 1's frame is solved at once
    assert _burst(session, recording, window=0.002, due_2=0.005, early=0.0) == (set(), 1, 1)


def test_a_burst_that_fails_to_solve_is_reported_not_blamed_on_its_last_frame(
        session: Session, recording: ViveRecording) -> None:
    """The frame that completes a burst solves it in its own read: a solve that raises
    (a bug) goes to the loop's exception handler, not to that frame's submit, which
    would refuse a good frame."""
    async def main() -> list[dict[str, object]]:
        reported: list[dict[str, object]] = []
        asyncio.get_running_loop().set_exception_handler(lambda _, c: reported.append(c))
        room = _room(session, recording, window=60.0, bursts=OpenBursts())
        for a in (1, 2):
            room.avatars[a].cadence = Cadence(last=1.0 - PERIOD, period=PERIOD)

        def broken(avatar_ids: list[int]) -> None:
            raise RuntimeError("a bug in the solve")

        room.solver.solve_staged = broken  # type: ignore[assignment,method-assign]
        room.submit(1, _frame(recording, 5), 1.0)
        room.submit(2, _frame(recording, 6), 1.0)  # completes the burst: no exception
        assert room.bursts is not None and room.bursts.count == 0  # closed all the same
        return reported

    reported = asyncio.run(main())
    assert len(reported) == 1 and "solving a burst failed" in str(reported[0]["message"])
    assert isinstance(reported[0]["exception"], RuntimeError)


def test_a_tick_early_for_everyone_still_makes_one_burst(session: Session,
                                                         recording: ViveRecording) -> None:
    """Players are compared by when their frames are due, not by when this one came: a
    tick 6 ms early for both players (a timer, a busy client machine) moves both."""
    awaited, _, _ = _burst(session, recording, window=0.004, due_2=0.002, early=0.006)
    assert awaited == {2}


def test_a_burst_with_every_players_frame_in_is_solved_on_the_next_pass(
        session: Session, recording: ViveRecording) -> None:
    """Both players' frames came in during one pass of the loop: nobody is left to wait
    for, so the burst is solved on the next pass (a frame arriving in the pass would
    otherwise keep it open one pass more), well within its window."""
    async def main() -> tuple[int, int, int]:
        room = _room(session, recording, window=60.0)  # not what ends a burst here
        room.submit(1, _frame(recording, 5), 1.0)
        room.submit(2, _frame(recording, 6), 1.0)
        await asyncio.sleep(0)  # one pass: the burst's check runs once
        solved_then = room.metrics.batches
        room.submit(1, _frame(recording, 7), 2.0)  # player 2 has not sent this time
        await asyncio.sleep(0)
        return solved_then, room.metrics.batches, room.metrics.frames_solved

    solved_then, batches, frames = asyncio.run(main())
    assert solved_then == 1
    # player 1 alone, a frame just in: the burst stays open for a pass, then closes
    assert (batches, frames) == (1, 2)


def test_a_room_counts_every_frame_once(session: Session, recording: ViveRecording) -> None:
    """Each frame submitted is solved, superseded or discarded (its player recalibrated
    or left, or the server stopped), and each solved one is delivered to a spectator or
    dropped (here: its avatar left while the spectator's outbox held it)."""
    rec = recording

    async def main() -> tuple[dict[str, object], int, int]:
        async def send(frames: list[Delivery]) -> None:
            raise AssertionError("not sending in this test")

        async def send_bytes(data: bytes) -> None:
            pass

        room = _room(session, rec, window=60.0)
        outbox: Outbox[Delivery] = Outbox(send)  # its task not running: frames wait
        room.spectators[1] = Spectator(outbox, send_bytes)
        room.submit(1, _frame(rec, 5), 1.0)
        room.submit(1, _frame(rec, 6), 1.0)  # supersedes 5
        room.submit(2, _frame(rec, 7), 1.0)
        t_pose = np.concatenate([rec.positions[0], rec.rotations[0]], axis=1)
        room.calibrate(room.avatars[1], rec.devices, t_pose)  # discards 6
        room.solve_pending()  # solves 7, which waits in the outbox
        room.submit(2, _frame(rec, 8), 2.0)
        room.remove_avatar(2)  # discards 8, and 7 leaves the outbox unsent
        room.submit(1, _frame(rec, 9), 3.0)
        room.discard_pending()  # the server stopped: 9 is never solved
        return room.metrics.as_json(), outbox.delivered, outbox.dropped

    metrics, delivered, dropped = asyncio.run(main())
    assert (metrics["frames_solved"], metrics["frames_superseded"],
            metrics["frames_discarded"]) == (1, 1, 3)  # the 5 frames submitted
    assert (delivered, dropped) == (0, 1)


def test_warm_path_runs_a_frame_in_three_short_phases(session: Session,
                                                      recording: ViveRecording) -> None:
    """The twin's path runs a third at a time (decode + stage, solve, encode), so a
    frame that arrives meanwhile waits for one phase at most; nothing runs before the
    server has seen a calibration and a frame."""
    rec = recording
    warm = WarmPath(session.rig, session.solver_name)
    warm.step()
    assert warm.steps == 0 and warm._phase == 0  # nothing to run yet
    t_pose = np.concatenate([rec.positions[0], rec.rotations[0]], axis=1)
    warm.calibrate(rec.devices, t_pose)
    warm.frame = encode(_frame(rec, 7))
    before = warm.solver._rotations[0].copy()
    for phase in (1, 2, 0):
        warm.step()
        assert warm._phase == phase
    assert warm.steps == 1
    assert not np.array_equal(warm.solver._rotations[0], before)  # it did solve the twin
    assert warm.solver.helper() is not None  # through the code the rooms' solves run
    # and sent it as a room sends its avatars: packed with the twin's coding (the code a
    # real batch runs, kept warm), a batch a spectator decodes with that coding
    coding = warm.solver.coding(TWIN)
    assert warm.sent is not None and warm.sent[:2] == b"\x82\x7e"  # binary, 16-bit length
    payload = warm.sent[4:]
    assert int.from_bytes(warm.sent[2:4], "big") == len(payload)
    sent = decode(payload, codings={TWIN: coding})
    assert isinstance(sent, AvatarBatch) and sent.avatar_ids.tolist() == [TWIN]
    driven = list(coding.driven)
    assert np.abs(np.abs(np.sum(sent.frame(0).rotations[driven]
                                * warm.solver._rotations[0][driven], axis=1)) - 1).max() < 1e-5
    with pytest.raises(ProtocolError):  # not the 5 bytes a joint of an uncoded avatar
        decode(payload)
