"""Display error in ``/metrics``: how far the avatars viewers presented were from the
avatars as solved at the same instant.

A viewer's ViewerReport carries a few avatars as it presented them (ShownPose: its
playout's pose at ``t_presented``, server clock). A room that receives such samples
keeps each avatar's solved poses of the last few seconds (``PoseHistory``, one row per
solved frame, by capture time); the truth at ``t_presented`` is the solved pose of the
frames captured either side of it, interpolated. Both go through forward kinematics with
the avatar's calibrated offsets, and the error is the mean distance over the body's
joints: the demo's display error (``client/measure/display_error.py``), with the poses
the server solved in place of a re-solve of the player's samples.

Nothing of this runs on the frame path: a batch's rows are copied into the history with
one fancy-indexed assignment per array, and samples wait in a bounded reservoir that a
tick evaluates in one forward-kinematics call.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from posecast.protocol import ShownPose, ViewerReport
from posecast.server.latency import StageHistograms
from posecast.solver.fk import forward_kinematics
from posecast.solver.rig import Rig

if TYPE_CHECKING:
    from posecast.server.room import Room

Array = NDArray[np.float64]

# rows of history per avatar (434 KB of 53 joints, only while viewers send samples):
# 2.8 s at 90 Hz, longer than a report's age when a tick
# takes it (a report interval 0.5 s + a tick 0.25 s + the link)
HISTORY_ROWS = 256
# two solved frames further apart than this around an instant: the avatar was not
# tracked then (its player paused or lost its link); the sample says nothing of a viewer
MAX_GAP_S = 0.25
TICK_S = 0.25
# samples evaluated per tick at most (a reservoir: every sample equally likely): 1,000
# spectators send ~8,000 a second, a few hundred a second give steady percentiles
SAMPLES_PER_TICK = 64
# Prometheus' buckets, metres: a predicted pose over a fair link is ~30 mm off, a
# zero-buffer one ~130 mm
BUCKET_BOUNDS_M: tuple[float, ...] = (0.002, 0.005, 0.01, 0.015, 0.02, 0.03, 0.04, 0.05,
                                      0.075, 0.1, 0.15, 0.2, 0.3, 0.5, 1.0)
UNKNOWN = "unknown"  # a viewer that did not say what it is, or its mode
_STAGE = ("display_error",)  # each label pair's histogram has this one row
# a room nobody sent samples of for this long stops keeping its history
HISTORY_IDLE_S = 10.0


class PoseHistory:
    """The last HISTORY_ROWS solved poses of each avatar of a room: a ring per avatar."""

    def __init__(self, joints: int, rows: int = HISTORY_ROWS) -> None:
        self.joints, self.rows = joints, rows
        self._slot: dict[int, int] = {}
        self._free: list[int] = []
        self.times: Array  # (slots, rows) capture times, -inf where none
        self.roots: Array  # (slots, rows, 3)
        self.rotations: Array  # (slots, rows, J, 4)
        self.head: NDArray[np.int64]  # (slots,) each ring's next row
        self._last: tuple[tuple[int, ...], NDArray[np.int64]]  # the last batch's slots
        self._grow(8)

    def _grow(self, slots: int) -> None:
        old = self.times if hasattr(self, "times") else None
        times = np.full((slots, self.rows), -np.inf)
        roots = np.zeros((slots, self.rows, 3))
        rotations = np.zeros((slots, self.rows, self.joints, 4))
        head = np.zeros(slots, dtype=np.int64)
        if old is not None:
            n = old.shape[0]
            times[:n], roots[:n], rotations[:n], head[:n] = (
                old, self.roots, self.rotations, self.head)
        self._free += list(range(slots - 1, 0 if old is None else old.shape[0] - 1, -1))
        self.times, self.roots, self.rotations, self.head = times, roots, rotations, head
        self._last = ((), np.zeros(0, dtype=np.int64))

    def _slots(self, avatar_ids: list[int]) -> NDArray[np.int64]:
        key = tuple(avatar_ids)
        if key == self._last[0]:  # a room's batches mostly hold the same avatars
            return self._last[1]
        slot = self._slot
        for a in avatar_ids:
            if a not in slot:
                if not self._free:
                    self._grow(2 * self.times.shape[0])
                slot[a] = self._free.pop()
        slots = np.array([slot[a] for a in avatar_ids], dtype=np.int64)
        self._last = (key, slots)
        return slots

    def add(self, avatar_ids: list[int], t_capture: Array, roots: Array,
            rotations: Array) -> None:
        """A batch's solved rows: ids (B), capture times (B,) on the server clock, roots
        (B, 3) and rotations (B, J, 4): each into its avatar's ring, one indexed
        assignment per array for the whole batch."""
        if rotations.shape[1] != self.joints:
            return  # another skeleton (a replay's): not this room's solver's
        slots = self._slots(avatar_ids)
        rows = self.head[slots]
        self.times[slots, rows] = t_capture
        self.roots[slots, rows] = roots
        self.rotations[slots, rows] = rotations
        self.head[slots] = (rows + 1) % self.rows

    def forget(self, avatar_id: int) -> None:
        s = self._slot.pop(avatar_id, None)
        if s is not None:
            self.times[s] = -np.inf
            self.head[s] = 0
            self._free.append(s)
            self._last = ((), np.zeros(0, dtype=np.int64))

    def around(self, avatar_id: int, t: float) -> tuple[int, int, int, float] | None:
        """The slot and rows of the frames captured last at or before ``t`` and first
        after it, and how far between them ``t`` lies; None when ``t`` is outside the
        history or between frames more than MAX_GAP_S apart."""
        s = self._slot.get(avatar_id)
        if s is None:
            return None
        times = self.times[s]
        before = np.where(times <= t, times, -np.inf)
        after = np.where(times > t, times, np.inf)
        k0, k1 = int(np.argmax(before)), int(np.argmin(after))
        t0, t1 = float(times[k0]), float(times[k1])
        if not (t0 <= t < t1) or t1 - t0 > MAX_GAP_S:
            return None
        return s, k0, k1, (t - t0) / (t1 - t0)


@dataclass
class Sample:
    viewer: str
    mode: str
    pose: ShownPose


@dataclass
class DisplayErrorHistograms:
    """One histogram of display errors (``server.latency.StageHistograms``, metres) per
    (viewer, mode) label pair, made when the pair is first seen."""

    by_label: dict[tuple[str, str], StageHistograms] = field(default_factory=dict)

    def observe(self, viewer: str, mode: str, errors_m: Array) -> None:
        h = self.by_label.get((viewer, mode))
        if h is None:
            h = self.by_label[(viewer, mode)] = StageHistograms(_STAGE, BUCKET_BOUNDS_M)
        h.observe(errors_m[None, :])

    def cumulative(self, key: tuple[str, str]) -> tuple[list[tuple[str, float]], float]:
        return self.by_label[key].cumulative(_STAGE[0])

    def count(self, viewer: str, mode: str) -> int:
        h = self.by_label.get((viewer, mode))
        return 0 if h is None else h.count(_STAGE[0])

    def quantile_mm(self, key: tuple[str, str], q: float) -> float:
        """The q-quantile as Prometheus' histogram_quantile reads it off the buckets:
        linear within the bucket it falls in (the last bound, in the +Inf bucket)."""
        counts = self.by_label[key].counts[0]
        cumulative = np.cumsum(counts)
        rank = q * cumulative[-1]
        b = int(np.searchsorted(cumulative, rank, side="left"))
        if b >= len(BUCKET_BOUNDS_M):
            return BUCKET_BOUNDS_M[-1] * 1e3
        lo = BUCKET_BOUNDS_M[b - 1] if b else 0.0
        below = cumulative[b - 1] if b else 0
        within = (rank - below) / counts[b] if counts[b] else 1.0
        return (lo + within * (BUCKET_BOUNDS_M[b] - lo)) * 1e3

    def as_json(self) -> dict[str, dict[str, float]]:
        """Per "viewer/mode": p50 and p95 (mm, read off the buckets) and the count."""
        return {f"{v}/{m}": {"p50": round(self.quantile_mm((v, m), 0.5), 1),
                             "p95": round(self.quantile_mm((v, m), 0.95), 1),
                             "n": self.count(v, m)} for v, m in sorted(self.by_label)}


class SampleReservoir:
    """At most ``size`` samples between two ticks, each offered one equally likely to be
    kept; how many were offered and how many could not be measured."""

    def __init__(self, size: int = SAMPLES_PER_TICK, seed: int = 0) -> None:
        self.size = size
        self.held: list[tuple[Room, Sample]] = []
        self.offered = 0  # since the last take
        self._random = np.random.default_rng(seed)

    def offer(self, room: Room, sample: Sample) -> None:
        self.offered += 1
        if len(self.held) < self.size:
            self.held.append((room, sample))
            return
        k = int(self._random.integers(self.offered))
        if k < self.size:
            self.held[k] = (room, sample)

    def take(self) -> list[tuple[Room, Sample]]:
        held, self.held, self.offered = self.held, [], 0
        return held


def display_errors(rig: Rig, history: PoseHistory, offsets: dict[int, Array],
                   samples: list[ShownPose]) -> tuple[Array, NDArray[np.bool_]]:
    """Each sample's display error (metres: the mean over the body's joints of the
    distance between the pose shown and the solved one at its instant), and which
    samples could be measured (their avatar calibrated, its history around the instant,
    the viewer's skeleton the room's)."""
    n = len(samples)
    measured = np.zeros(n, dtype=np.bool_)
    J = history.joints
    shown_rot = np.empty((n, J, 4))
    shown_root = np.empty((n, 3))
    rows = np.empty((n, 3), dtype=np.intp)  # slot, before, after
    alpha = np.empty(n)
    off = np.empty((n, J, 3))
    for i, p in enumerate(samples):  # a few dozen a tick, off the frame path
        found = history.around(p.avatar_id, p.t_presented)
        o = offsets.get(p.avatar_id)
        if found is None or o is None or p.rotations.shape[0] != J or o.shape[0] != J:
            continue
        measured[i] = True
        rows[i] = found[:3]
        alpha[i] = found[3]
        shown_rot[i], shown_root[i], off[i] = p.rotations, p.root, o
    m = np.flatnonzero(measured)
    if not len(m):
        return np.zeros(0), measured
    s, k0, k1 = rows[m, 0], rows[m, 1], rows[m, 2]
    rot = np.concatenate([shown_rot[m], history.rotations[s, k0], history.rotations[s, k1]])
    root = np.concatenate([shown_root[m], history.roots[s, k0], history.roots[s, k1]])
    _, pos = forward_kinematics(rig.skeleton, rot, root, np.concatenate([off[m]] * 3))
    shown, before, after = np.split(pos[:, rig.body], 3)
    a = alpha[m][:, None, None]
    truth = before + a * (after - before)
    return np.linalg.norm(shown - truth, axis=-1).mean(axis=1), measured


class DisplayErrorMeter:
    """A server's display error: samples offered as reports come, measured a tick at a
    time into ``histograms``; ``samples`` counts what became of them."""

    def __init__(self, rig: Rig, histograms: DisplayErrorHistograms,
                 samples: Counter[str]) -> None:
        self.rig = rig
        self.histograms = histograms
        self.samples = samples
        self.reservoir = SampleReservoir()

    def offer(self, room: Room, report: ViewerReport, t: float) -> None:
        """A report's shown poses (``t``: its arrival, server clock). The room keeps a
        history from now on: the first samples find none yet, and are not measured."""
        if room.history is None:
            room.history = PoseHistory(self.rig.skeleton.num_joints)
        room.history_used_at = t
        viewer, mode = report.viewer or UNKNOWN, report.mode or UNKNOWN
        for pose in report.shown:
            self.reservoir.offer(room, Sample(viewer, mode, pose))

    def tick(self, rooms: list[Room], t: float) -> None:
        """Measure the samples held; forget the histories nobody samples any more."""
        offered = self.reservoir.offered
        held = self.reservoir.take()
        self.samples["skipped"] += offered - len(held)
        by_room: dict[int, tuple[Room, list[Sample]]] = {}
        for room, sample in held:
            by_room.setdefault(id(room), (room, []))[1].append(sample)
        for room, samples in by_room.values():
            history = room.history
            if history is None:  # gone since (its room closed): not measurable
                self.samples["unmeasured"] += len(samples)
                continue
            offsets = {s.pose.avatar_id: av.info.rest_offsets for s in samples
                       if (av := room.avatars.get(s.pose.avatar_id)) is not None
                       and av.info is not None}
            errors, measured = display_errors(self.rig, history, offsets,
                                              [s.pose for s in samples])
            self.samples["measured"] += len(errors)
            self.samples["unmeasured"] += len(samples) - len(errors)
            kept = [s for s, m in zip(samples, measured.tolist(), strict=True) if m]
            for key in {(s.viewer, s.mode) for s in kept}:
                rows = np.array([s.viewer == key[0] and s.mode == key[1] for s in kept])
                self.histograms.observe(key[0], key[1], errors[rows])
        for room in rooms:
            if room.history is not None and t - room.history_used_at > HISTORY_IDLE_S:
                room.history = None
