"""Devices lost and found, live: a player streams over a real websocket on 127.0.0.1 while
its trackers drop out for 0.2 to 5 s (a foot, a hand, both feet), as the OpenVR source
leaves out a device that is not tracked. No Error, no disconnect, and the room sees the
avatar in every frame the player sent, with the lost devices named."""

from __future__ import annotations

import asyncio

import numpy as np
from conftest import serving

from posecast.client.builtin import builtin_motion_path
from posecast.client.session.player import Player
from posecast.client.session.spectator import Spectator
from posecast.client.sources.base import DeviceSample, PoseSource
from posecast.client.sources.bvh_source import BvhSource
from posecast.client.sources.tracker_set import TrackerSetSource
from posecast.protocol import AvatarBatch, ClockEstimator
from posecast.server.app import Session
from posecast.solver.tracking.devices import PRESETS

# (start, end) seconds from the first frame: the device is left out of the frames between
GAPS: dict[str, list[tuple[float, float]]] = {
    "left_foot": [(0.5, 0.7), (1.0, 2.0), (8.0, 11.0)],  # 0.2 s, 1 s; both feet 3 s
    "right_foot": [(2.5, 7.5), (8.0, 11.0)],  # 5 s
    "left_hand": [(3.0, 4.0)],  # 1 s, behind the back
}
SECONDS = 11.5


class ScriptedLosses:
    """A source whose devices vanish from the frames during their GAPS."""

    def __init__(self, source: PoseSource) -> None:
        self.source = source
        self.rate_hz = source.rate_hz
        self.t0: float | None = None
        self.sent: list[tuple[float, tuple[str, ...]]] = []  # (t from start, roles)
        self.heads: list[np.ndarray] = []  # the headset's position in each frame

    def calibration(self) -> DeviceSample:
        return self.source.calibration()

    def read(self) -> DeviceSample | None:
        sample = self.source.read()
        if sample is None:
            return None
        if self.t0 is None:
            self.t0 = sample.t_capture
        t = sample.t_capture - self.t0
        keep = [i for i, r in enumerate(sample.roles)
                if not any(a <= t < b for a, b in GAPS.get(r, ()))]
        out = DeviceSample(sample.t_capture, tuple(sample.roles[i] for i in keep),
                           sample.poses[np.array(keep, dtype=np.intp)])
        self.sent.append((t, out.roles))
        self.heads.append(sample.poses[sample.roles.index("head"), :3].copy())
        return out

    def close(self) -> None:
        self.source.close()


class Watcher(Spectator):
    """A spectator that keeps, per received avatar-frame, its seq, lost bits and root."""

    def __init__(self, url: str) -> None:
        super().__init__(url, "drops", "watcher")
        self.frames: list[tuple[int, int, tuple[float, ...]]] = []

    def on_batch(self, batch: AvatarBatch, t_local: float, clock: ClockEstimator) -> None:
        super().on_batch(batch, t_local, clock)
        for i in range(batch.size):
            self.frames.append((int(batch.seqs[i]), int(batch.lost[i]),
                                tuple(batch.roots[i].tolist())))


def test_devices_lost_for_a_while_never_freeze_the_avatar_or_end_the_session() -> None:
    session = Session(reconnect_grace=5.0)
    source = ScriptedLosses(TrackerSetSource(
        BvhSource(builtin_motion_path(), loop=True, rate_hz=90.0), PRESETS["6"]))

    async def main() -> tuple[Player, list[Watcher]]:
        async with serving(session) as url:
            watchers = [Watcher(url) for _ in range(2)]
            tasks = [asyncio.create_task(w.run()) for w in watchers]
            player = Player(url, "drops", "pat", source)
            await player.run(seconds=SECONDS)
            for _ in range(100):  # the last frames reach the spectators
                if all(len(w.frames) >= player.stats.frames_sent for w in watchers):
                    break
                await asyncio.sleep(0.05)
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            return player, watchers

    player, watchers = asyncio.run(main())
    stats, m = player.stats, session.metrics
    assert stats.ended_by == "time" and not stats.errors, stats.errors  # no Error, no close
    assert m.frames_rejected == 0 and not m.rejected
    # every frame sent was solved (none refused): superseded only if a newer came first
    assert m.frames_solved + m.frames_superseded == stats.frames_sent
    sent = {seq for seq in range(stats.frames_sent)}
    for w in watchers:
        seen = {seq for seq, _, _ in w.frames}
        missing = sent - seen
        # a spectator misses only what latest-wins dropped for it (none on an idle machine)
        assert len(missing) <= m.frames_dropped + m.frames_superseded, sorted(missing)[:10]
    # the losses are counted by role, once each, and shown in the frames
    assert m.device_losses["left_foot"] == 3 and m.device_losses["right_foot"] == 2
    assert m.device_losses["left_hand"] == 1 and m.device_losses["hip"] == 0
    assert stats.losses["left_foot"] == 3 and stats.losses["left_hand"] == 1
    t_of = {seq: t for seq, (t, _) in enumerate(source.sent)}
    frames = watchers[0].frames
    for role, bit in (("left_foot", 1 << 6), ("right_foot", 1 << 7), ("left_hand", 1 << 2)):
        for a, b in GAPS[role]:
            inside = [lost for seq, lost, _ in frames if a + 0.05 < t_of.get(seq, -1) < b - 0.05]
            assert inside and all(lost & bit for lost in inside), (role, a, b)
    outside = [lost for seq, lost, _ in frames if 0.1 < t_of.get(seq, -1) < 0.45]
    assert outside and not any(outside)
    # and the avatar kept moving through the longest gap: the walk carries it along
    during = [(seq, root) for seq, _, root in frames if 3.0 < t_of.get(seq, -1) < 7.0]
    roots = np.array([root for _, root in during])
    assert np.linalg.norm(roots[-1] - roots[0]) > 0.5
    # and never jumped, but where the looping clip itself jumps back to its start
    heads = np.array([source.heads[seq] for seq, _ in during])
    steps = np.linalg.norm(np.diff(roots, axis=0), axis=1)
    seam = np.linalg.norm(np.diff(heads, axis=0), axis=1) > 0.3
    assert steps[~seam].max() < 0.1
