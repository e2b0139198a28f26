"""A room recorded (``posecast record``) and played back into another room (``replay``):
the spectators there receive the recorded poses."""

from __future__ import annotations

import asyncio
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import serving

from posecast.client.builtin import builtin_motion_path
from posecast.client.interop.recorder import RecordingSpectator, record_room
from posecast.client.interop.recording import Recording, RecordingWriter, read_recording
from posecast.client.interop.replay import replay_recording, split
from posecast.client.session.player import Ticker, run_player
from posecast.client.sources.base import OffsetSource
from posecast.client.sources.bvh_source import BvhSource
from posecast.protocol import MAX_CLIENT_MESSAGE_BYTES, AvatarBatch, AvatarRoster, encode
from posecast.server.app import Session

PLAYERS = 4


async def record_players(url: str, path: Path, seconds: float) -> Recording:
    """Four players walk in room "live" while it is recorded for ``seconds``."""
    stop = asyncio.Event()
    ticker = Ticker(90.0)  # their frames leave together: batches of four
    players = [asyncio.create_task(run_player(
        url, "live", f"walker {k}", OffsetSource(BvhSource(builtin_motion_path(), loop=True,
                                                           rate_hz=90.0), (1.0 * k, 0.0)),
        ticker=ticker, stop=stop)) for k in range(PLAYERS)]
    try:
        await asyncio.sleep(0.5)  # calibrated and streaming
        await record_room(url, "live", path, seconds)
    finally:
        stop.set()
        await asyncio.gather(*players)
    return read_recording(path)


def test_a_room_replayed_reaches_another_rooms_spectators_with_the_same_poses(
        tmp_path: Path) -> None:
    path = tmp_path / "live.pcrec"

    async def main() -> Recording:
        async with serving(Session()) as url:
            rec = await record_players(url, path, 2.0)
            # a spectator of the other room keeps what it receives, in a recording too
            with RecordingWriter(tmp_path / "seen.pcrec", "again", url) as writer:
                seen = RecordingSpectator(writer, url, "again", "watcher")
                stop = asyncio.Event()
                watching = asyncio.create_task(seen.run(stop=stop))
                await asyncio.sleep(0.3)
                await replay_recording(url, "again", rec)
                await asyncio.sleep(0.3)  # the last frames' way
                stop.set()
                await watching
            return rec

    rec = asyncio.run(main())
    names = {i.display_name for m in rec.messages if isinstance(m, AvatarRoster)
             for i in m.avatars}
    assert names == {f"walker {k}" for k in range(PLAYERS)}
    assert rec.frames() >= PLAYERS * 90 * 1.5  # 2 s at 90 Hz, with slack for a busy host
    recorded = [m for m in rec.messages if isinstance(m, AvatarBatch)]
    got = read_recording(tmp_path / "seen.pcrec")
    name_of = {i.avatar_id: i.display_name for m in got.messages
               if isinstance(m, AvatarRoster) for i in m.avatars}
    assert set(name_of.values()) == names  # the room was empty: the names are kept
    by_name = [{name_of_rec(rec, b.avatar_ids[i]): b.frame(i) for i in range(b.size)}
               for b in recorded]
    compared = 0
    for batch in (m for m in got.messages if isinstance(m, AvatarBatch)):
        for i in range(batch.size):
            frame = batch.frame(i)
            original = by_name[frame.seq][name_of[frame.avatar_id]]  # seq: the batch's
            assert np.array_equal(frame.root, original.root)  # float32 both ways
            dots = np.abs(np.sum(frame.rotations * original.rotations, axis=-1))
            # quantized again on the way: within 0.05 deg (the 5-byte code's step)
            assert np.degrees(2 * np.arccos(np.clip(dots, -1, 1))).max() < 0.05
            compared += 1
    assert compared >= 0.9 * rec.frames()  # latest-wins may drop a frame or two


def name_of_rec(rec: Recording, avatar_id: int) -> str:
    for m in rec.messages:
        if isinstance(m, AvatarRoster):
            for info in m.avatars:
                if info.avatar_id == avatar_id:
                    return info.display_name
    raise KeyError(avatar_id)


def test_large_messages_are_split_to_what_a_client_may_send(tmp_path: Path) -> None:
    async def main() -> Recording:
        async with serving(Session()) as url:
            return await record_players(url, tmp_path / "r.pcrec", 0.5)

    rec = asyncio.run(main())
    roster = AvatarRoster(avatars=tuple(i for m in rec.messages
                                        if isinstance(m, AvatarRoster) for i in m.avatars))
    batch = next(m for m in rec.messages if isinstance(m, AvatarBatch) and m.size > 1)
    wide = AvatarBatch.from_frames([batch.frame(i % batch.size).model_copy(
        update={"avatar_id": 100 + i}) for i in range(40)], t_sent=1.0)
    assert len(encode(roster)) > MAX_CLIENT_MESSAGE_BYTES
    assert len(encode(wide)) > MAX_CLIENT_MESSAGE_BYTES
    parts = list(split(roster, 0))
    assert [p.avatars[0].display_name for p in parts] == [
        i.display_name for i in roster.avatars]
    halves = list(split(wide, 7))
    assert sum(p.size for p in halves) == 40 and len(halves) > 1
    for part in parts + halves:
        assert len(encode(part)) <= MAX_CLIENT_MESSAGE_BYTES
    assert all(p.seqs.tolist() == [7] * p.size for p in halves)


@pytest.mark.parametrize(("argv", "why"), [
    (["replay", "missing.pcrec"], "no such file"),
    (["replay", "{bad}"], "not a posecast recording"),
    (["replay", "{cut}"], "holds no avatar-frames"),
])
def test_replay_of_a_bad_file_is_one_line(tmp_path: Path, argv: list[str], why: str) -> None:
    bad = tmp_path / "bad.pcrec"
    bad.write_text("tag rawPosX rawPosY\n")
    cut = tmp_path / "cut.pcrec"
    RecordingWriter(cut, "r", "ws://x").close()
    argv = [a.format(bad=bad, cut=cut) for a in argv]
    out = subprocess.run([sys.executable, "-m", "posecast.client.cli", *argv, "--server",
                          "ws://127.0.0.1:9", "--room", "r"], capture_output=True, text=True,
                         cwd=tmp_path)
    assert out.returncode in (1, 2) and why in out.stderr, out.stderr
    assert "Traceback" not in out.stderr and out.stderr.count("\n") == 1


def test_a_replay_is_checked_and_its_avatars_leave_with_it(tmp_path: Path) -> None:
    """Poses before their skeleton are refused in one Error; a spectator sees the replayed
    avatars arrive, and leave as soon as the replay's connection ends."""
    from posecast.client.session.connection import make_hello, open_session
    from posecast.client.session.spectator import Spectator
    from posecast.protocol import Error

    async def main() -> tuple[Error, int, int]:
        async with serving(Session()) as url:
            rec = await record_players(url, tmp_path / "r.pcrec", 0.5)
            roster = next(m for m in rec.messages if isinstance(m, AvatarRoster))
            batch = next(m for m in rec.messages if isinstance(m, AvatarBatch))
            watcher = Spectator(url, "again", "watcher")
            stop = asyncio.Event()
            watching = asyncio.create_task(watcher.run(stop=stop))
            session = await open_session(url, make_hello(url, "replay", "again", "r"))
            await session.send(batch)  # no roster yet
            error, _ = await session.receive()
            assert isinstance(error, Error)
            for part in split(roster, 0):
                await session.send(part)
            await session.send(next(split(batch, 0)))
            for _ in range(100):  # the roster's way to the watcher
                if len(watcher.roster) == len(roster.avatars):
                    break
                await asyncio.sleep(0.02)
            during = len(watcher.roster)
            await session.close()
            for _ in range(100):
                if not watcher.roster:
                    break
                await asyncio.sleep(0.02)
            stop.set()
            await watching
            return error, during, len(watcher.roster)

    error, during, after = asyncio.run(main())
    assert error.code == "invalid" and "send its skeleton first" in error.message
    assert during == PLAYERS and after == 0


def test_a_server_with_a_secret_admits_a_replay_with_a_players_token() -> None:
    from posecast.client.session.connection import SessionError, make_hello, open_session
    from posecast.server.auth import JoinTokens

    tokens = JoinTokens(b"s" * 32)

    async def join(url: str, role: str) -> str:
        token = tokens.mint("again", role, 60.0)  # type: ignore[arg-type]
        try:
            session = await open_session(url, make_hello(url, "replay", "again", "r", token))
        except SessionError as err:
            return str(err)
        await session.close()
        return "admitted"

    async def main() -> tuple[str, str]:
        async with serving(Session(tokens=tokens)) as url:
            return await join(url, "player"), await join(url, "spectator")

    as_player, as_spectator = asyncio.run(main())
    assert as_player == "admitted"
    assert "auth_failed" in as_spectator


def test_an_exported_bvh_reads_back_as_the_recording_moved(tmp_path: Path) -> None:
    """``posecast export``: one BVH per avatar; read back by posecast's own reader, its
    joints lie within 0.5 mm of the recording's (forward kinematics of the recorded poses
    at the file's frame instants: rotations slerped, roots lerped between the two
    recorded frames around each)."""
    from posecast.client.interop.recording import avatar_takes
    from posecast.client.skeletons import skeleton_of
    from posecast.solver import rotations as R
    from posecast.solver.fk import forward_kinematics
    from posecast.solver.readers.bvh import read_bvh

    path = tmp_path / "live.pcrec"

    async def main() -> Recording:
        async with serving(Session()) as url:
            return await record_players(url, path, 1.5)

    rec = asyncio.run(main())
    out = subprocess.run([sys.executable, "-m", "posecast.client.cli", "export", str(path),
                          "--bvh", str(tmp_path / "bvh")], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    takes = avatar_takes(rec)
    assert len(takes) == PLAYERS and out.stdout.count(".bvh:") == PLAYERS
    worst = 0.0
    for take in takes:
        motion = read_bvh(tmp_path / "bvh" / f"{take.info.display_name.replace(' ', '_')}.bvh")
        assert motion.num_frames >= 90  # ~1.5 s at the recording's 90 fps
        _, read = forward_kinematics(motion.skeleton, motion.rotations,
                                     motion.translations[:, 0], motion.translations)
        times = np.array(take.times)
        t = times[0] + np.arange(motion.num_frames) / motion.fps
        i = np.clip(np.searchsorted(times, t, side="right") - 1, 0, times.size - 2)
        u = np.clip((t - times[i]) / (times[i + 1] - times[i]), 0.0, 1.0)
        rot, roots = np.array(take.rotations), np.array(take.roots)
        sk = skeleton_of(take.info)
        _, recorded = forward_kinematics(
            sk, R.slerp(rot[i], rot[i + 1], u[:, None]), roots[i] + u[:, None] * (
                roots[i + 1] - roots[i]))
        index = [motion.skeleton.names.index(n) for n in sk.names]
        worst = max(worst, float(np.abs(read[:, index] - recorded).max()))
    assert worst < 0.0005


def test_poses_recorded_before_their_skeleton_are_left_out(tmp_path: Path) -> None:
    """A server may send a new avatar's first pose before its roster: the replay leaves
    that pose out (no spectator could draw it) instead of having it refused."""
    from test_recording import batch, skeleton

    path = tmp_path / "early.pcrec"
    with RecordingWriter(path, "r", "ws://x") as w:
        w.add(0.0, AvatarRoster(avatars=(skeleton(1, "ann"),)))
        w.add(0.01, batch([1, 2], 10.0))  # bob's pose before bob's skeleton
        w.add(0.02, AvatarRoster(avatars=(skeleton(2, "bob"),)))
        w.add(0.03, batch([1, 2], 10.01))
        w.add(0.04, batch([2], 10.02))
    rec = read_recording(path)

    server = Session()

    async def main() -> tuple[int, int]:
        async with serving(server) as url:
            stats = await replay_recording(url, "r", rec)
            return stats.frames_sent, stats.frames_skipped

    assert asyncio.run(main()) == (4, 1)
    assert server.metrics.frames_replayed == 4 and not server.metrics.rejected
