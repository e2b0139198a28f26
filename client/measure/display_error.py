"""Display error: how far the avatar a spectator shows is from the player's body now.

Latency in milliseconds is not what people see; they see a hand in the wrong place. At
each presentation instant T (a display's rate, 60 Hz) this compares

- the pose the spectator presents at T: its snapshot buffers (``viewer.interpolation``)
  sampled at T in each viewer mode, fed with the frames it had received by T, exactly as
  ``SpectatorScene.frame`` does; and
- the player's true pose at T: the player's own tracker samples around T (interpolated
  between the two that bracket it), solved with the server's solver and the avatar's own
  calibration, so that the solver's own error (``posecast eval``) is not counted here;

both through the same forward kinematics, as the mean distance over the body's joints.

The spectator only records what arrived (one list append per batch) and the player what
it captured; everything above is computed after the session, so measuring costs the
session nothing. Players, spectators and the server share ``time.perf_counter``, one
clock on one machine, so T means the same instant to all of them.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from posecast.client.sources.base import DeviceSample, PoseSource
from posecast.client.viewer.interpolation import Interpolator, Mode
from posecast.protocol import AvatarBatch, AvatarFrame
from posecast.server.avatars import AvatarSolver
from posecast.solver import rotations as R
from posecast.solver.fk import forward_kinematics
from posecast.solver.rig import Rig

Array = NDArray[np.float64]

PRESENT_HZ = 60.0  # a desktop display's refresh: how often a viewer presents
SETTLE_S = 1.0  # skipped after an avatar's first frame: the jitter window fills first
# a looping clip jumps back to its start: a device that moves this far between two samples
# (27 m/s at 90 Hz) was teleported, and the instants up to JUMP_SKIP_S later are left out
# (a viewer shows the jump up to its latency + playout delay late, the predictor's
# history holds it a while: that is the clip's seam, not the network)
JUMP_M = 0.3
JUMP_SKIP_S = 0.5


@dataclass
class CaptureLog:
    """What one player captured: its T-pose and every sample it sent (local clock)."""

    avatar_id: int
    roles: tuple[str, ...]
    calibration: Array  # (D, 7) position | quaternion
    times: Array  # (F,) capture instants, seconds
    poses: Array  # (F, D, 7)

    def at(self, t: Array) -> Array:
        """Tracker poses (N, D, 7) at instants ``t`` (N,) within the log: position lerp
        and quaternion slerp between the two samples that bracket each instant."""
        k = np.clip(np.searchsorted(self.times, t, side="right") - 1, 0, len(self.times) - 2)
        t0, t1 = self.times[k], self.times[k + 1]
        alpha = np.clip((t - t0) / np.maximum(t1 - t0, 1e-9), 0.0, 1.0)
        a, b = self.poses[k], self.poses[k + 1]
        out = np.empty_like(a)
        out[..., :3] = a[..., :3] + alpha[:, None, None] * (b[..., :3] - a[..., :3])
        out[..., 3:] = R.slerp(a[..., 3:], b[..., 3:], alpha[:, None])
        return out

    def near_jump(self, t: Array, after_s: float = JUMP_SKIP_S) -> NDArray[np.bool_]:
        """Which instants ``t`` lie within ``after_s`` after a jump (see JUMP_M)."""
        step = np.linalg.norm(np.diff(self.poses[..., :3], axis=0), axis=-1).max(axis=1)
        jumps = self.times[1:][step > JUMP_M]
        if len(jumps) == 0:
            return np.zeros(len(t), dtype=np.bool_)
        k = np.searchsorted(jumps, t, side="right") - 1  # the last jump at or before t
        last = np.where(k >= 0, jumps[np.maximum(k, 0)], -np.inf)
        return t - last < after_s


class RecordingSource:
    """A pose source whose calibration and samples are kept for ``CaptureLog``."""

    def __init__(self, source: PoseSource) -> None:
        self.source = source
        self.rate_hz = source.rate_hz
        self._calibration: DeviceSample | None = None
        # capture times and pose arrays, not the samples: floats and arrays are no work
        # for Python's cycle collector, and 16 players' samples kept as objects made its
        # pauses show in the demo's p99 (docs/performance.md)
        self._times: list[float] = []
        self._poses: list[np.ndarray] = []

    def calibration(self) -> DeviceSample:
        self._calibration = self.source.calibration()
        return self._calibration

    def read(self) -> DeviceSample | None:
        sample = self.source.read()
        if sample is not None:
            self._times.append(sample.t_capture)
            self._poses.append(sample.poses)
        return sample

    def close(self) -> None:
        self.source.close()

    def log(self, avatar_id: int | None) -> CaptureLog | None:
        """The log, or None with no avatar, no T-pose or fewer than two samples."""
        if avatar_id is None or self._calibration is None or len(self._times) < 2:
            return None
        return CaptureLog(avatar_id, self._calibration.roles, self._calibration.poses.copy(),
                          np.array(self._times), np.stack(self._poses))


class Received(Protocol):
    """What a viewer was given in one arrival: an AvatarBatch, or the browser page's
    frames as it recorded them (client/bench/browser.py)."""

    @property
    def avatar_ids(self) -> NDArray[np.int64]: ...

    @property
    def joint_counts(self) -> NDArray[np.int64]: ...

    @property
    def frames(self) -> Sequence[AvatarFrame]: ...


@dataclass
class Arrival:
    """A batch as a spectator received it: its local time and clock offset then."""

    t_local: float
    offset: float | None  # server - local, seconds; None before the clock synced
    batch: AvatarBatch | Received


@dataclass
class DisplayError:
    """Per viewer mode, one error per (presentation instant, avatar), mm; and the
    interpolating buffer's playout delay at each of those, ms."""

    errors_mm: dict[str, Array] = field(default_factory=dict)
    playout_delay_ms: Array = field(default_factory=lambda: np.zeros(0))

    def as_json(self) -> dict[str, dict[str, float]]:
        return {mode: percentiles(e) for mode, e in self.errors_mm.items()}

    def delay_json(self) -> dict[str, float]:
        return percentiles(self.playout_delay_ms)


def clock_error_ms(arrivals: list[Arrival]) -> float | None:
    """The median clock offset (server minus local, ms) a viewer had as its batches came,
    None before it synced. In the demo both clocks are this machine's perf_counter, so
    the true offset is 0 and this is the error of the viewer's estimate."""
    offsets = [a.offset for a in arrivals if a.offset is not None]
    return round(float(np.median(offsets)) * 1e3, 3) if offsets else None


def percentiles(values: Array) -> dict[str, float]:
    if len(values) == 0:
        return {"p50": 0.0, "p95": 0.0, "n": 0}
    p50, p95 = np.percentile(values, [50.0, 95.0])
    return {"p50": round(float(p50), 2), "p95": round(float(p95), 2), "n": len(values)}


def measure_display_error(captures: list[CaptureLog], arrivals: list[Arrival], rig: Rig,
                          solver: str = "analytic", rate_hz: float = PRESENT_HZ,
                          settle_s: float = SETTLE_S,
                          modes: tuple[Mode, ...] = tuple(Mode),
                          instants: Array | None = None,
                          instant_offsets: Array | None = None,
                          pushed_before: NDArray[np.int64] | None = None) -> DisplayError:
    """The display error of one spectator's ``arrivals`` against the players' ``captures``
    (see the module docstring), in every viewer mode: at ``rate_hz``, or at the viewer's
    own presentation ``instants`` (its local clock, ascending; the browser page's), each
    sampled with its clock offset then (``instant_offsets``; NaN: not synced) and having
    been given the first ``pushed_before`` arrivals (see ``replay_playout``)."""
    result = DisplayError({m.value: np.zeros(0) for m in modes})
    logs = {c.avatar_id: c for c in captures}
    first: dict[int, float] = {}
    for a in arrivals:
        for avatar_id in a.batch.avatar_ids.tolist():
            first.setdefault(avatar_id, a.t_local)
    ids = [i for i in logs if i in first]
    if not ids or not arrivals:
        return result
    start = min(first[i] for i in ids) + settle_s
    if instants is None:
        instants = np.arange(start, arrivals[-1].t_local, 1.0 / rate_hz)
    else:
        within = (instants >= start) & (instants <= arrivals[-1].t_local)
        instants = instants[within]
        if instant_offsets is not None:
            instant_offsets = instant_offsets[within]
        if pushed_before is not None:
            pushed_before = pushed_before[within]
        if not len(instants):
            return result
    presented = replay_playout(arrivals, instants, ids, modes, instant_offsets,
                               pushed_before)
    truth_solver = AvatarSolver(rig, solver)
    skeleton, body = rig.skeleton, rig.body
    errors: dict[str, list[Array]] = {m.value: [] for m in modes}
    delays = []
    for avatar_id in ids:
        log = logs[avatar_id]
        # presented from its first frame + settle, true up to its last capture
        keep = (instants >= first[avatar_id] + settle_s) & (instants <= log.times[-1])
        keep &= presented.valid[avatar_id] & ~log.near_jump(instants)
        if not keep.any():
            continue
        t = instants[keep]
        cal = truth_solver.calibrate(avatar_id, log.roles, log.calibration[:, :3],
                                     log.calibration[:, 3:])
        tracked = log.at(t)
        rot = np.empty((len(t), skeleton.num_joints, 4))
        root = np.empty((len(t), 3))
        for n in range(len(t)):  # in time order: warm-started as the server's solves are
            pose = truth_solver.solve([(avatar_id, log.roles, tracked[n])], float(t[n]))
            rot[n], root[n] = pose.rotations[0], pose.root[0]
        offsets = np.broadcast_to(cal.offsets, (len(t), *cal.offsets.shape))
        _, true_p = forward_kinematics(skeleton, rot, root, offsets)
        for mode in modes:
            shown_rot = presented.rotations[mode.value][avatar_id][keep]
            shown_root = presented.roots[mode.value][avatar_id][keep]
            _, shown_p = forward_kinematics(skeleton, shown_rot, shown_root, offsets)
            dist = np.linalg.norm(shown_p[:, body] - true_p[:, body], axis=-1).mean(axis=1)
            errors[mode.value].append(dist * 1e3)
        delays.append(presented.delays[avatar_id][keep] * 1e3)
    for mode in modes:
        if errors[mode.value]:
            result.errors_mm[mode.value] = np.concatenate(errors[mode.value])
    if delays:
        result.playout_delay_ms = np.concatenate(delays)
    return result


@dataclass
class Presented:
    rotations: dict[str, dict[int, Array]]  # mode -> avatar -> (N, J, 4)
    roots: dict[str, dict[int, Array]]  # mode -> avatar -> (N, 3)
    valid: dict[int, NDArray[np.bool_]]  # avatar -> (N,): every mode had a pose
    delays: dict[int, Array]  # avatar -> (N,) interpolation's playout delay, s


def replay_playout(arrivals: list[Arrival], instants: Array, ids: list[int],
                   modes: tuple[Mode, ...], instant_offsets: Array | None = None,
                   pushed_before: NDArray[np.int64] | None = None) -> Presented:
    """What a viewer in each mode presents at each instant, having received the batches
    that arrived by then (the buffers are pure: the same inputs, the same poses); with
    the clock offset of the newest arrival, or the instant's own (``instant_offsets``,
    NaN: not synced), as the browser page samples with its clock's latest. The browser
    page is given a frame when its message event runs, which may come a frame after its
    arrival stamp: ``pushed_before[k]`` arrivals had been given by instant k."""
    viewers = {m: Interpolator(mode=m) for m in modes}
    # every viewer is fed alike, so any one's buffers have interpolation's playout delay
    delay_of = next(iter(viewers.values()))
    joints = arrivals[0].batch.joint_counts[0]
    n = len(instants)
    rotations = {m.value: {i: np.tile([0.0, 0.0, 0.0, 1.0], (n, joints, 1)) for i in ids}
                 for m in modes}
    roots = {m.value: {i: np.zeros((n, 3)) for i in ids} for m in modes}
    valid = {i: np.ones(n, dtype=np.bool_) for i in ids}
    delays = {i: np.zeros(n) for i in ids}
    next_arrival, offset = 0, None
    for k, now in enumerate(instants.tolist()):
        given = len(arrivals) if pushed_before is None else int(pushed_before[k])
        while next_arrival < given and (pushed_before is not None
                                        or arrivals[next_arrival].t_local <= now):
            a = arrivals[next_arrival]
            next_arrival += 1
            offset = a.offset if a.offset is not None else offset
            for frame in a.batch.frames:
                for v in viewers.values():
                    v.push(frame, a.t_local)
        if instant_offsets is not None:
            offset = None if np.isnan(instant_offsets[k]) else float(instant_offsets[k])
        to_server = _shifted(offset) if offset is not None else None
        for mode, viewer in viewers.items():
            shown = viewer.sample(now, to_server)
            for i in ids:
                s = shown.get(i)
                if s is None or s.rotations.shape[0] != joints:
                    valid[i][k] = False
                    continue
                rotations[mode.value][i][k] = s.rotations
                roots[mode.value][i][k] = s.root
        for i in ids:
            buf = delay_of.buffers.get(i)
            delays[i][k] = buf.delay if buf is not None else 0.0
    return Presented(rotations, roots, valid, delays)


def _shifted(offset: float) -> Callable[[float], float]:
    """Local time to server time with the spectator's clock offset at that moment."""
    return lambda t: t + offset
