"""Trackers that drop out and come back, live through OpenVR (issue 26's acceptance test).

A SteamVR rig without hardware (``FakeVR``, tests/openvr_fake.py: the real ``openvr``
package's function table filled with callbacks) walks the built-in CMU walk, one clip
frame per pose read, and a script switches trackers off and on by read number. The real
player (``OpenVRSource`` in a ``Player``, and ``posecast play --source openvr`` through
the CLI) streams it to a real server on 127.0.0.1 and a spectator watches. What is
asserted is what happened, counted (frames, seqs, losses, mounts, errors), never how fast:
the script runs by reads, not by the clock, so a loaded machine plays the same scenario.
"""

from __future__ import annotations

import asyncio
import contextlib
import queue
import re
import threading
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np
import openvr
import pytest
from conftest import serving
from numpy.typing import NDArray
from openvr_fake import RIG_ROLES, FakeVR, rig_devices

from posecast.client.builtin import builtin_motion_path
from posecast.client.cli import main
from posecast.client.session.player import Player, PlayerStats
from posecast.client.session.spectator import Spectator
from posecast.client.sources.bvh_source import tracker_recording
from posecast.client.sources.openvr_source import OpenVRSource
from posecast.protocol import AvatarBatch, AvatarFrame, AvatarInfo, AvatarRoster, ClockEstimator
from posecast.server.app import Session
from posecast.server.metrics import Metrics
from posecast.solver import rotations as R
from posecast.solver.motion import ViveRecording

TIMEOUT = 60.0  # generous: conditions are awaited, never timed
GAP_READS = 90  # a tracker lost for 1 s at the Vive's 90 Hz


@pytest.fixture(scope="module")
def base() -> Session:
    return Session()  # the rig and the warmed solver, built once for every test's server


@pytest.fixture(scope="module")
def walk() -> ViveRecording:
    """The built-in walk's trackers: frame 0 the T-pose, then 3 s of walking at 90 Hz."""
    return tracker_recording(builtin_motion_path(), seconds=3.0)


# ------------------------------------------------------------------ the walking rig
@dataclass
class Trouble:
    """A device of ``role`` with these pose fields (``Device``'s) from read ``first`` to
    read ``end`` (excluded); tracked again after."""

    role: str
    first: int
    end: int
    fields: dict[str, object]


class WalkingRig:
    """The devices of ``rig_devices`` that the walk has (and the base station), at the
    walk's poses: read 0 (the calibration) the T-pose, read n the n-th frame of the
    walk (back and forth past its end). ``troubles`` take devices off tracking for a
    while; ``switch_on`` (read -> role) adds a device, absent until then, with SteamVR's
    activation event. A device with no pose in the walk (the chest) stands between the
    hip and the head, turned as the hip."""

    BASE_STATION = 10

    def __init__(self, walk: ViveRecording, troubles: tuple[Trouble, ...] = (),
                 switch_on: dict[int, str] | None = None) -> None:
        self.troubles = troubles
        self.switch_on = switch_on or {}
        everything = dict(enumerate(rig_devices()))
        later = {RIG_ROLES[r] for r in self.switch_on.values()}
        self.roles = {i: r for r, i in RIG_ROLES.items()
                      if r in walk.devices or i in later}  # index -> role
        self.spare = {i: everything[i] for i in later}
        devices = {i: everything[i] for i in self.roles if i not in later}
        devices[self.BASE_STATION] = everything[self.BASE_STATION]
        pos, rot = walk.positions, walk.rotations
        hip, head = walk.device("hip"), walk.device("head")
        # device index -> (F, 3, 4): its pose matrix in every frame of the walk
        self.matrices: dict[int, NDArray[np.float64]] = {}
        for i, role in self.roles.items():
            if role in walk.devices:
                d = walk.device(role)
                p, q = pos[:, d], rot[:, d]
            else:
                p, q = pos[:, hip] + 0.45 * (pos[:, head] - pos[:, hip]), rot[:, hip]
            m = np.zeros((len(p), 3, 4))
            m[:, :, :3] = R.to_matrix(q)
            m[:, :, 3] = p
            self.matrices[i] = m
        self.frames = walk.num_frames
        self.vr = FakeVR(devices, display_hz=90.0)
        self.vr.on_read = self._on_read
        self.failures: list[BaseException] = []  # a ctypes callback cannot raise

    def frame(self, n: int) -> int:
        """The walk's frame at read n: 0 (the T-pose), then 1, 2, ... F-1, F-2, ... 1, 2..."""
        if n == 0:
            return 0
        period = 2 * (self.frames - 2)
        k = (n - 1) % period
        return 1 + (k if k < self.frames - 1 else period - k)

    def _on_read(self, n: int) -> None:
        try:
            devices = self.vr.devices
            if n in self.switch_on:
                i = RIG_ROLES[self.switch_on[n]]
                devices[i] = self.spare[i]
                self.vr.events.append((openvr.VREvent_TrackedDeviceActivated, i))
            f = self.frame(n)
            for i in self.roles:
                if i in devices:
                    devices[i].matrix = self.matrices[i][f]
            for trouble in self.troubles:
                dev = devices[RIG_ROLES[trouble.role]]
                dev.valid, dev.connected = True, True
                dev.result = openvr.TrackingResult_Running_OK
            for trouble in self.troubles:
                if trouble.first <= n < trouble.end:
                    dev = devices[RIG_ROLES[trouble.role]]
                    for name, value in trouble.fields.items():
                        setattr(dev, name, value)
        except BaseException as err:
            self.failures.append(err)


# ------------------------------------------------------------------ the spectator side
class Watcher(Spectator):
    """A spectator that keeps every frame it receives and every roster entry."""

    def __init__(self, url: str, room: str) -> None:
        super().__init__(url, room, "watcher")
        self.frames: dict[int, dict[int, AvatarFrame]] = defaultdict(dict)  # avatar, seq
        self.counts: Counter[tuple[int, int]] = Counter()  # (avatar, seq) -> frames
        self.infos: list[AvatarInfo] = []  # every roster entry, as they came

    def on_batch(self, batch: AvatarBatch, t_local: float, clock: ClockEstimator) -> None:
        super().on_batch(batch, t_local, clock)
        for i in range(batch.size):
            frame = batch.frame(i)
            self.frames[frame.avatar_id][frame.seq] = frame
            self.counts[frame.avatar_id, frame.seq] += 1

    def on_roster(self, roster: AvatarRoster) -> None:
        super().on_roster(roster)
        self.infos.extend(roster.avatars)


async def until(condition: Callable[[], bool], what: str) -> None:
    t_end = time.monotonic() + TIMEOUT
    while not condition():
        assert time.monotonic() < t_end, f"timed out waiting for {what}"
        await asyncio.sleep(0.02)


@dataclass
class Run:
    """What one streaming run left: the player's stats, the server's counters, what the
    spectator received of the player's avatar, and the rig's pose reads."""

    player: PlayerStats
    metrics: Metrics
    frames: dict[int, AvatarFrame]  # the avatar's frames by seq
    counts: Counter[int]  # frames received per seq
    infos: list[AvatarInfo]  # the avatar's roster entries, in order
    watcher_errors: Counter[str]
    watcher_reconnects: int
    reads: int
    failures: list[BaseException] = field(default_factory=list)

    def missing(self) -> list[int]:
        """The seqs the player sent that the spectator did not get (bar the last two,
        which may be in flight as the player stops)."""
        return [s for s in range(self.player.frames_sent - 2) if s not in self.counts]

    def lost_seqs(self, role: str) -> list[int]:
        return sorted(s for s, f in self.frames.items() if role in f.lost_roles)


def stream(rig: WalkingRig, session: Session, room: str, reads: int) -> Run:
    """The player streams the rig to a real server until the rig has been read ``reads``
    times, a spectator watching from before the player joined."""
    async def run() -> Run:
        async with serving(session) as url:
            watcher = Watcher(url, room)
            watched = asyncio.Event()
            watching = asyncio.create_task(watcher.run(stop=watched))
            await until(lambda: watcher.session is not None or watching.done(),
                        "the spectator to join")
            player = Player(url, room, "pat", OpenVRSource(system=rig.vr.system))
            stop = asyncio.Event()
            playing = asyncio.create_task(player.run(stop=stop))
            try:
                await until(lambda: rig.vr.reads >= reads or playing.done(),
                            f"{reads} pose reads")
            finally:
                stop.set()
                stats = await asyncio.wait_for(playing, TIMEOUT)
            avatar = stats.avatar_id
            assert avatar is not None
            # the last frames solved: the spectator has them before it leaves
            last = stats.frames_sent - 3
            await until(lambda: max(watcher.frames[avatar], default=-1) >= last
                        or watching.done(), "the spectator to get the last frames")
            watched.set()
            await asyncio.wait_for(watching, TIMEOUT)
        return Run(stats, session.metrics, dict(watcher.frames[avatar]),
                   Counter({s: n for (a, s), n in watcher.counts.items() if a == avatar}),
                   [info for info in watcher.infos if info.avatar_id == avatar],
                   watcher.stats.errors, watcher.stats.reconnects, rig.vr.reads,
                   rig.failures)

    return asyncio.run(run())


def check_delivery(run: Run) -> None:
    """Every frame the player sent reached the spectator once, and nothing failed: no
    Error reply, no lost connection, nothing refused by the server."""
    assert not run.failures, run.failures
    stats, m = run.player, run.metrics
    assert not stats.errors and stats.last_error is None
    assert stats.ended_by == "stop" and stats.reconnects == 0  # streamed until told to stop
    assert not run.watcher_errors and run.watcher_reconnects == 0
    assert m.frames_rejected == 0 and not m.rejected and not m.limited
    assert stats.frames_sent > 0 and run.counts
    assert max(run.counts.values()) == 1  # each seq once
    missing = run.missing()
    # a frame is not delivered only where the server says why: superseded by the
    # player's next before it was solved, or dropped for a slow spectator (on loopback
    # neither happens, but the server's own count is the bound, not the machine's speed)
    assert len(missing) <= m.frames_superseded + m.frames_dropped, missing


# ------------------------------------------------------------------ a: lost and back
LEFT_FOOT_OFF = Trouble("left_foot", 60, 60 + GAP_READS, {"valid": False})
RIGHT_KNEE_IMU = Trouble("right_knee", 120, 120 + GAP_READS,
                         {"result": openvr.TrackingResult_Running_OutOfRange})
GAP_RUN_READS = 300


@pytest.fixture(scope="module")
def gap_run(base: Session, walk: ViveRecording) -> Run:
    """The left foot's pose invalid for 1 s from read 60, the right knee Running_OutOfRange
    for 1 s from read 120 (overlapping), then both tracked again."""
    rig = WalkingRig(walk, (LEFT_FOOT_OFF, RIGHT_KNEE_IMU))
    return stream(rig, Session(base.rig, reconnect_grace=5.0), "gap", GAP_RUN_READS)


def test_trackers_lost_for_a_second_the_player_streams_on(gap_run: Run) -> None:
    run = gap_run
    check_delivery(run)
    stats, m = run.player, run.metrics
    walk_roles = ("head", "hip", "left_hand", "right_hand", "left_forearm", "right_forearm",
                  "left_foot", "right_foot", "left_knee", "right_knee")
    assert stats.devices == walk_roles
    # each lost once and back: the player's count, and the server's
    assert stats.losses == {"left_foot": 1, "right_knee": 1} and stats.lost_now == ()
    assert m.device_losses == {"left_foot": 1, "right_knee": 1}
    # every frame the player sent without a device reached the server and was counted
    assert m.device_lost_frames == stats.lost_frames
    # the foot: one frame per read of its gap, less any the socket did not take
    assert GAP_READS - stats.frames_dropped <= stats.lost_frames["left_foot"] <= GAP_READS
    # the knee on its IMU: sent for the first 0.1 s (OUT_OF_RANGE_S), then lost
    assert 1 <= stats.lost_frames["right_knee"] <= GAP_READS
    assert not m.devices_mounted
    # the spectator: every frame of the gaps, with the lost bit of its device
    missing = set(run.missing())
    for role in ("left_foot", "right_knee"):
        seqs = run.lost_seqs(role)
        assert stats.lost_frames[role] - len(missing) <= len(seqs) <= stats.lost_frames[role]
        assert set(range(seqs[0], seqs[-1] + 1)) - set(seqs) <= missing  # one gap
    lost_anything = {r for f in run.frames.values() for r in f.lost_roles}
    assert lost_anything == {"left_foot", "right_knee"}
    # the frames after the gaps have every device again
    last = max(run.frames)
    assert run.frames[last].lost_roles == ()
    # the roster named the devices once, at calibration: a loss changes no skeleton
    assert [info.devices for info in run.infos] == [walk_roles]


# ------------------------------------------------------------------ c: it keeps moving
def test_the_avatar_keeps_walking_while_a_foot_is_lost(gap_run: Run) -> None:
    run = gap_run
    gap = [run.frames[s] for s in run.lost_seqs("left_foot")]
    assert len(gap) > GAP_READS // 2
    roots = np.array([f.root for f in gap])
    # the walk goes on at ~1.3 m/s: the root travels through the gap, frame by frame
    assert np.linalg.norm(roots[-1] - roots[0]) > 0.3
    steps = np.linalg.norm(np.diff(roots, axis=0), axis=1)
    assert (steps > 0.0).all()
    # and the body moves: joints turn between any two frames of the gap 10 frames apart
    rotations = np.array([f.rotations for f in gap])
    for a, b in zip(rotations[:-10:10], rotations[10::10], strict=True):
        angle = 2.0 * np.arccos(np.clip(np.abs(np.sum(a * b, axis=-1)), 0.0, 1.0))
        assert angle.max() > np.radians(2.0)
    # no jump where the foot was lost or came back: the root's step there is a step of
    # the walk (clip frames are read for read, so this is the motion, not the timing)
    before, after = seq_root(run, run.lost_seqs("left_foot")[0] - 1), roots[0]
    assert np.linalg.norm(after - before) < 5.0 * np.median(steps)
    back = seq_root(run, run.lost_seqs("left_foot")[-1] + 1)
    assert np.linalg.norm(back - roots[-1]) < 5.0 * np.median(steps)


def seq_root(run: Run, seq: int) -> NDArray[np.float64]:
    return np.asarray(run.frames[seq].root)


# ------------------------------------------------------------------ b: switched on later
def test_trackers_switched_on_after_calibration_are_mounted(base: Session,
                                                            walk: ViveRecording) -> None:
    rig = WalkingRig(walk, switch_on={60: "left_knee", 120: "chest"})
    run = stream(rig, Session(base.rig, reconnect_grace=5.0), "later", 200)
    check_delivery(run)
    stats, m = run.player, run.metrics
    assert "left_knee" in stats.devices and "chest" in stats.devices
    assert not stats.losses and not m.device_losses  # a new device is no lost one
    assert m.devices_mounted == {"left_knee": 1, "chest": 1}
    # the roster: calibrated without them, then a new entry as each was mounted
    calibrated = ("head", "hip", "left_hand", "right_hand", "left_forearm",
                  "right_forearm", "left_foot", "right_foot", "right_knee")
    assert [info.devices for info in run.infos] == [
        calibrated, (*calibrated[:8], "left_knee", "right_knee"),
        (*calibrated[:8], "left_knee", "right_knee", "chest")]
    assert all(f.lost_roles == () for f in run.frames.values())


# ------------------------------------------------------------------ d: the real CLI
@contextlib.contextmanager
def server_thread(session: Session) -> Iterator[str]:
    """A real server in a thread of its own, with its own event loop: this thread is
    left to a command that runs its own (``posecast play``: asyncio.run, and signal
    handlers, which only the main thread may install)."""
    started: queue.Queue[tuple[str, asyncio.AbstractEventLoop, asyncio.Event]] = queue.Queue()
    failed: list[BaseException] = []

    async def serve() -> None:
        stop = asyncio.Event()
        async with serving(session) as url:
            started.put((url, asyncio.get_running_loop(), stop))
            await stop.wait()

    def run() -> None:
        try:
            asyncio.run(serve())
        except BaseException as err:
            failed.append(err)

    thread = threading.Thread(target=run, name="posecast-test-server", daemon=True)
    thread.start()
    try:
        url, loop, stop = started.get(timeout=TIMEOUT)
    except queue.Empty:
        thread.join(TIMEOUT)
        raise AssertionError(f"the server did not start: {failed}") from None
    try:
        yield url
    finally:
        loop.call_soon_threadsafe(stop.set)
        thread.join(TIMEOUT)
    assert not thread.is_alive(), "the server did not stop"
    assert not failed, failed


def test_play_source_openvr_through_the_cli(base: Session, walk: ViveRecording,
                                            monkeypatch: pytest.MonkeyPatch,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    """``posecast play --source openvr`` with the headset's runtime replaced at the
    openvr library's boundary: ``openvr.init`` gives the fake system."""
    rig = WalkingRig(walk, (Trouble("left_foot", 90, 90 + GAP_READS, {"valid": False}),))
    inits: list[int] = []
    shutdowns: list[bool] = []

    def init(application_type: int, startup_info: object = None) -> openvr.IVRSystem:
        inits.append(application_type)
        return rig.vr.system

    monkeypatch.setattr(openvr, "init", init)
    monkeypatch.setattr(openvr, "shutdown", lambda: shutdowns.append(True))
    session = Session(base.rig, reconnect_grace=5.0)
    with server_thread(session) as url:
        status = main(["play", "--server", url, "--room", "cli", "--name", "pat",
                       "--source", "openvr", "--calibrate-in", "0", "--seconds", "3"])
    out, err = capsys.readouterr()
    assert status == 0, err
    assert not rig.failures, rig.failures
    assert inits == [openvr.VRApplication_Background] and shutdowns == [True]
    summary = out.strip().splitlines()[-1]
    assert summary.startswith("sent "), out
    assert "from 10 devices (head, hip, left_hand, right_hand, left_forearm, " \
           "right_forearm, left_foot, right_foot, left_knee, right_knee)" in summary
    lost = re.search(r"; lost: left_foot 1x \((\d+) frames\)", summary)
    assert lost is not None, summary
    assert 1 <= int(lost.group(1)) <= GAP_READS
    assert "server errors" not in summary
    for word in ("Traceback", "connection lost", "server error", "WARNING", "ERROR"):
        assert word not in err, err
    m = session.metrics
    assert m.device_losses == {"left_foot": 1}
    assert m.device_lost_frames == {"left_foot": int(lost.group(1))}
    assert m.frames_rejected == 0 and not m.rejected and not m.limited
    assert m.frames_received > GAP_READS  # it streamed on past the gap's start
