"""A room: its avatars, its spectators, and the batching of solves.

Frames are solved as they arrive, a burst at a time: the first tracker frame after a solve
opens a burst and schedules its solve with ``call_soon``. When that runs, the burst stays
open for one more pass of the event loop while frames are still coming: one came in
during the pass, a player's frame has been read from its socket but not yet handled, or
a player whose headset ticks with the first frame's is due and has not sent yet (each
player's ``Cadence``: its frames come one period apart). It is solved as soon as none
of these holds, or at the latest COALESCE_MAX_S after its first frame. There is no fixed
tick to wait for: a lone frame, or one whose player is out of step with the others, is
solved on the next pass. The batch is solved in one call, turned into one AvatarBatch,
encoded once and written to the spectators (``server.fanout``).
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import math
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, TypeVar

import numpy as np
from websockets.asyncio.server import broadcast

from posecast.protocol import (
    AvatarBatch,
    AvatarFrame,
    AvatarInfo,
    AvatarRoster,
    TrackerFrame,
    encode,
)
from posecast.protocol.arrivals import ArrivalStamps
from posecast.protocol.codec import encode_avatar_batch
from posecast.protocol.framing import binary_frame
from posecast.protocol.messages import TrackerPoses
from posecast.protocol.pose_coding import Codings, PoseCoding
from posecast.protocol.roles import DEVICE_ROLES
from posecast.protocol.validation import MAX_AVATARS, MAX_NAME_CHARS, sendable_rows
from posecast.server.avatars import AvatarSolver
from posecast.server.busy import OpenBursts
from posecast.server.cadence import Cadence
from posecast.server.clock import now
from posecast.server.display_error import PoseHistory
from posecast.server.fanout import FanOut, Spectator
from posecast.server.limits import ServerLimits
from posecast.server.metrics import Metrics
from posecast.server.relay import BATCH, ROSTER, AvatarRecord
from posecast.solver.calibration import Calibration
from posecast.solver.plausible import check_t_pose

if TYPE_CHECKING:
    from posecast.server.cluster import Cluster


class SharedBatch:
    """One solved batch, encoded at most once however many spectators receive it whole;
    its pydantic form is built only for a spectator that needs part of it."""

    def __init__(self, avatar_ids: list[int], seqs: list[int], roots: np.ndarray,
                 rotations: np.ndarray, t_capture: list[float],
                 t_server_receive: list[float], t_solved: float,
                 lost: list[int] | None = None, codings: Codings | None = None,
                 rows_checked: bool = False) -> None:
        self.args = (avatar_ids, seqs, roots, rotations, t_capture, t_server_receive,
                     t_solved)
        # every row passed the spectators' own checks (validation.sendable_rows): the
        # encoder need not look for non-finite values again
        self.rows_checked = rows_checked
        self.lost = lost if lost is not None else [0] * len(avatar_ids)
        # how each avatar's rotations are packed: its roster's coding (Room.codings)
        self.codings: Codings = codings if codings is not None else {}
        self.size = len(avatar_ids)
        self._encoded: bytes | None = None
        self._framed: bytes | None = None
        self.t_sent: float | None = None  # when first encoded: its bytes went out
        self._batch: AvatarBatch | None = None

    @property
    def avatar_ids(self) -> list[int]:
        return self.args[0]

    def encoded(self) -> bytes:
        if self._encoded is None:  # t_sent: now, as the bytes go to the sockets
            self.t_sent = now()
            self._encoded = encode_avatar_batch(*self.args, t_sent=self.t_sent,
                                                lost=self.lost, codings=self.codings,
                                                rows_checked=self.rows_checked)
        return self._encoded

    def framed(self) -> bytes:
        """The encoded batch as one websocket frame, built once for every spectator that
        takes it whole (``protocol.framing``)."""
        if self._framed is None:
            self._framed = binary_frame(self.encoded())
        return self._framed

    def solved_rows(self) -> tuple[list[int], np.ndarray, np.ndarray, np.ndarray]:
        """Ids, capture times (B,), roots (B, 3) and rotations (B, J, 4): what a room's
        PoseHistory keeps (server.display_error)."""
        ids, _, roots, rotations, t_capture = self.args[:5]
        return ids, np.asarray(t_capture), roots, rotations

    def frame(self, index: int) -> AvatarFrame:
        if self._batch is None:
            self._batch = AvatarBatch.from_arrays(*self.args, t_sent=self.args[-1],
                                                  lost=self.lost)
        return self._batch.frame(index)


class RelayedBatch(SharedBatch):
    """A batch another process solved, as this one hands it on (``serve --redis``): its
    bytes go to every spectator that takes it whole; one behind gets what it lacks."""

    def __init__(self, data: bytes, batch: AvatarBatch, codings: Codings) -> None:
        self.args = (batch.avatar_ids.tolist(),)  # type: ignore[assignment]
        self.lost = batch.lost.tolist()
        self.codings = codings
        self.rows_checked = True  # decoded: every row passed the checks
        self.size = batch.size
        self._encoded = data
        self._framed = None
        self.t_sent = batch.t_sent
        self._batch = batch

    def solved_rows(self) -> tuple[list[int], np.ndarray, np.ndarray, np.ndarray]:
        b = self._batch
        assert b is not None
        counts = b.joint_counts
        joints = int(counts[0]) if len(counts) else 0
        if not len(counts) or (counts != joints).any():  # mixed skeletons: none kept
            return [], np.zeros(0), np.zeros((0, 3)), np.zeros((0, joints, 4))
        return (b.avatar_ids.tolist(), b.t_capture, b.roots,
                b.rotations.reshape(len(counts), joints, 4))


T = TypeVar("T")
Delivery = tuple[SharedBatch, int]  # a batch and the index of one avatar in it

# the longest a burst may keep a batch open: long enough that most of a tick's frames
# make one batch, one message per spectator; short enough that a large room's first
# frames do not wait long. The demo's 16 players on one core spread a tick's frames over
# ~1.6 ms (1.8-1.9 batches a tick); a 1.6 ms window made one batch a tick but raised the
# server's p99 from ~1.6 to 2.1-2.4 ms (docs/performance.md, "Bursts", "eighth stop")
COALESCE_MAX_S = 0.0007


@dataclass
class Avatar:
    avatar_id: int
    display_name: str
    resume: str  # the random secret its player reconnects with (Welcome.resume)
    info: AvatarInfo | None = None  # the calibrated skeleton, once calibrated
    connected: bool = True
    # its player's live connection: its arrival stamps tell that a frame of this avatar
    # reached the process and waits for its handler (see Room._solve_when_burst_ends)
    connection: ArrivalStamps | None = None
    cadence: Cadence = field(default_factory=Cadence)  # when its next frame is due
    last_seq: int = -1  # of its player's last frame taken on this connection
    # the T-pose it was calibrated from (roles, poses (D, 7)): what Redis keeps of it
    tpose: tuple[tuple[str, ...], np.ndarray] | None = None
    lost_bits: int = 0  # its devices its newest frame lacks (protocol.roles bits)


@dataclass
class Room:
    name: str
    solver: AvatarSolver
    metrics: Metrics
    avatars: dict[int, Avatar] = field(default_factory=dict)
    spectators: dict[int, Spectator] = field(default_factory=dict)
    _pending: dict[int, tuple[TrackerFrame | TrackerPoses, float]] = field(default_factory=dict)
    coalesce_max_s: float = COALESCE_MAX_S
    # the server's count of open bursts, when it busy-polls (server.busy): it pauses
    # while one is open
    bursts: OpenBursts | None = None
    # the capture-time window and a T-pose's extent (derived values checked on input)
    limits: ServerLimits = field(default_factory=ServerLimits)
    _scheduled: bool = False
    _arrived: bool = False  # a frame came in during the current pass of the event loop
    _burst_start: float = 0.0
    _awaited: set[int] = field(default_factory=set)  # players due within the open burst
    _next_pass: asyncio.Handle | None = None  # the open burst's look in the next pass
    # the codings of its calibrated avatars (their rosters'), for its batches: replaced,
    # never changed, when one changes, so that a batch keeps the one it was solved with
    _codings: Codings = field(default_factory=dict)
    # with ``serve --redis``: the link to the other processes (server.cluster). An owned
    # room publishes its batches and rosters and keeps its avatars' records in Redis; a
    # relayed one is owned by another process: its avatars are a mirror of the owner's
    # rosters, and its spectators get the owner's batches as they come through Redis
    cluster: Cluster | None = None
    relayed: bool = False
    # roster changes not yet sent, merged (``broadcast_roster``): avatars added or given a
    # new skeleton, and avatars removed, in the order they came
    _roster_infos: dict[int, AvatarInfo] = field(default_factory=dict)
    _roster_removed: dict[int, None] = field(default_factory=dict)
    _roster_timer: asyncio.TimerHandle | None = None
    _roster_sent_at: float = -math.inf  # loop time of the last roster sent
    # its avatars' solved poses of the last seconds, kept while viewers send samples of
    # what they showed (server.display_error); None while no one does
    history: PoseHistory | None = None
    history_used_at: float = -math.inf  # server clock of the last sample taken
    fanout: FanOut = field(init=False)  # the writes of its batches to its spectators

    def __post_init__(self) -> None:
        self.fanout = FanOut(self.spectators, self.metrics)

    # ------------------------------------------------------------------ players
    def find_by_resume(self, resume: str | None) -> Avatar | None:
        """The avatar whose player reconnects with this secret (Welcome.resume)."""
        if resume is None:
            return None
        # as bytes: compare_digest refuses a str with a character beyond ASCII (a
        # TypeError that closed the connection with 1011 and logged a traceback)
        wanted = resume.encode("utf-8", "surrogatepass")
        return next((a for a in self.avatars.values()
                     if hmac.compare_digest(a.resume.encode(), wanted)), None)

    def unique_name(self, name: str) -> str:
        """``name``, or "name 2", "name 3", ... if an avatar of the room has it: viewers
        label avatars by name, and two alike would be told apart by nothing."""
        taken = {a.display_name for a in self.avatars.values()}
        candidate, k = name, 1
        while candidate in taken:
            k += 1
            suffix = f" {k}"
            candidate = name[:MAX_NAME_CHARS - len(suffix)] + suffix
        return candidate

    def calibrate(self, avatar: Avatar, frame_roles: tuple[str, ...],
                  poses: np.ndarray) -> Calibration:
        # before anything changes: a refused T-pose leaves the last calibration in place
        check_t_pose(frame_roles, poses[:, :3], self.limits.body_extent_m)
        cal = self.solver.calibrate(avatar.avatar_id, frame_roles, poses[:, :3], poses[:, 3:])
        avatar.lost_bits = 0
        info = self._describe(avatar, cal.offsets)
        if self._pending.pop(avatar.avatar_id, None) is not None:  # of the old T-pose
            self.metrics.frames_discarded += 1
        avatar.tpose = (frame_roles, np.array(poses))
        self.keep(avatar)
        self.broadcast_roster(AvatarRoster(avatars=(info,)))
        return cal

    def _describe(self, avatar: Avatar, offsets: np.ndarray) -> AvatarInfo:
        """The avatar's roster entry: its calibrated skeleton and its devices."""
        sk = self.solver.rig.skeleton
        devices = self.solver.devices(avatar.avatar_id)
        avatar.info = AvatarInfo(
            avatar_id=avatar.avatar_id, display_name=avatar.display_name,
            joint_names=sk.names, parents=tuple(int(p) for p in sk.parents),
            rest_offsets=offsets, devices=tuple(r for r in DEVICE_ROLES if r in devices),
            coding=self.solver.coding(avatar.avatar_id))
        self._codings = {**self._codings, avatar.avatar_id: avatar.info.coding}
        return avatar.info

    def keep(self, avatar: Avatar, resumable: bool = True) -> None:
        """The avatar's record into Redis (an owned room's, with ``serve --redis``): with
        its T-pose, the process that takes the room over calibrates it as here. Not
        ``resumable``: a replay's avatar, which leaves with its connection."""
        if self.cluster is not None and not self.relayed:
            roles, poses = avatar.tpose if avatar.tpose is not None else (None, None)
            self.cluster.save(self.name, AvatarRecord(
                avatar.avatar_id, avatar.display_name,
                avatar.resume if resumable else None, avatar.info, roles, poses))

    def is_calibrated(self, avatar_id: int) -> bool:
        return avatar_id in self.solver.calibrations

    def submit(self, avatar_id: int, frame: TrackerFrame | TrackerPoses,
               t_received: float) -> None:
        """Queue a player's frame (latest wins) and make sure a solve is coming. It is
        staged now, while the rest of the burst is still arriving; a ValueError (a
        capture time that is not near the server's clock) rejects this frame alone. A
        frame may lack any of the avatar's devices: they are carried on
        (``solver.tracking``) and counted, never refused."""
        t_capture = frame.t_capture_server  # the client's sum: it may overflow
        if not abs(t_capture - t_received) <= self.limits.capture_skew_s:  # NaN, inf fail
            raise ValueError(f"tracker_frame.t_capture + clock_offset = {t_capture!r} is "
                             f"not within {self.limits.capture_skew_s:g} s of the server's "
                             f"clock ({t_received:.3f}): sync the clock with pings first")
        lost, new = self.solver.stage(avatar_id, frame.roles, frame.poses, t_capture)
        avatar = self.avatars.get(avatar_id)
        if avatar is not None:
            if lost or avatar.lost_bits:
                self.metrics.count_losses(avatar.lost_bits, lost)
            avatar.lost_bits = lost
            if new and avatar.info is not None:  # devices switched on since calibration
                self.metrics.devices_mounted.update(new)
                info = self._describe(avatar, avatar.info.rest_offsets)
                self.keep(avatar)
                self.broadcast_roster(AvatarRoster(avatars=(info,)))
        if avatar_id in self._pending:
            self.metrics.frames_superseded += 1
        self._pending[avatar_id] = (frame, t_received)
        self._arrived = True
        awaited = self._awaited
        last_awaited = len(awaited) == 1 and avatar_id in awaited
        awaited.discard(avatar_id)
        due = None
        if avatar is not None:
            if not self._scheduled:  # this frame opens a burst: when was it due?
                due = avatar.cadence.due()
            avatar.cadence.arrived(t_received)
        if not self._scheduled:
            self._scheduled = True
            if self.bursts is not None:
                self.bursts.opened()
            # the window counts from when the burst's first frame is handled, not from
            # its arrival: a frame that queued behind a solve would otherwise close it
            # at once and split the burst into more, smaller batches
            self._burst_start = now()
            # the players whose next frame is due about when this one's was: their
            # headsets tick with its, and the burst waits for them (within the window).
            # Compared with when this frame was due, not when it came, so that a tick
            # that is early or late for every player alike changes nothing
            w = self.coalesce_max_s
            anchor = due if due is not None else t_received
            self._awaited = {a.avatar_id for a in self.avatars.values()
                             if a.connected and a.avatar_id not in self._pending
                             and a.cadence.due_within(anchor - w, anchor + w)}
            if self._awaited or not self._everyone_in():
                self._next_pass = asyncio.get_running_loop().call_soon(
                    self._solve_when_burst_ends)
                return
        elif not last_awaited or not self._everyone_in():
            return
        # the frame every player of the burst is in with: solved now, in its read, not a
        # pass of the loop later (17-26 us at the median in the demo, a frame's every
        # other handler and callback of that pass)
        self._solve_now()

    def _solve_now(self) -> None:
        if self._next_pass is not None:
            self._next_pass.cancel()
            self._next_pass = None
        self._arrived = False
        self._awaited.clear()
        try:
            self.solve_pending()
        except Exception as exc:  # not the fault of the frame that closed the burst
            asyncio.get_running_loop().call_exception_handler(
                {"message": f"room {self.name!r}: solving a burst failed", "exception": exc})

    def _everyone_in(self) -> bool:
        """Every connected, calibrated player has a frame in the open burst: no one is
        left to join it."""
        pending = self._pending
        return all(a.avatar_id in pending for a in self.avatars.values()
                   if a.connected and self.is_calibrated(a.avatar_id))

    def _solve_when_burst_ends(self) -> None:
        # a frame still arriving: submitted in this pass, read from its socket and
        # waiting for its handler's turn (the handlers run a pass after the reads), or
        # due from a player in step with the burst; unless every player's is in already
        # (that saves the pass that would find nothing more)
        arriving = bool(self._awaited) or (
            not self._everyone_in() if self._arrived else any(
                a.connection is not None and a.connection.arrivals
                for a in self.avatars.values()))
        if arriving and now() - self._burst_start < self.coalesce_max_s:
            self._arrived = False
            self._next_pass = asyncio.get_running_loop().call_soon(
                self._solve_when_burst_ends)
            return
        self._next_pass = None
        self._arrived = False
        self._awaited.clear()
        self.solve_pending()

    def remove_avatar(self, avatar_id: int) -> None:
        if self.cluster is not None and not self.relayed:
            self.cluster.forget(self.name, avatar_id)
        avatar = self.avatars.pop(avatar_id, None)
        self.solver.remove(avatar_id)
        if avatar_id in self._codings:
            self._codings = {a: c for a, c in self._codings.items() if a != avatar_id}
        if self._pending.pop(avatar_id, None) is not None:
            self.metrics.frames_discarded += 1
        for s in self.spectators.values():
            s.outbox.forget(avatar_id)
        if self.history is not None:
            self.history.forget(avatar_id)
        # a player that never calibrated was never in a roster: its leaving costs the
        # spectators nothing (a join-and-leave loop made ~1,300 rosters a second)
        if avatar is None or avatar.info is not None:
            self.broadcast_roster(AvatarRoster(removed=(avatar_id,)))

    # ------------------------------------------------------------------ solving
    def solve_pending(self) -> None:
        # the whole burst in one call: solving its frames while it is still open puts the
        # reads of the rest of the burst behind (docs/performance.md, "Bursts")
        closes = self._scheduled and self.bursts is not None
        self._scheduled = False
        try:
            self._solve_and_deliver()
        finally:
            if closes:  # after the batch is out: the busy poller it wakes can wait
                assert self.bursts is not None
                self.bursts.closed()

    def _solve_and_deliver(self) -> None:
        calibrated, slot = self.solver.calibrations, self.solver.slot_order
        pending = [(a, f, t) for a, (f, t) in self._pending.items() if a in calibrated]
        self.metrics.frames_discarded += len(self._pending) - len(pending)
        self._pending.clear()
        if not pending:
            return
        pending.sort(key=lambda p: slot(p[0]))  # solved in place
        ids = [a for a, _, _ in pending]
        # the batch's rows but its poses, before the solve: after it, this Python runs
        # with the caches full of the solve's (the demo's solve-to-send time)
        avatars = self.avatars
        seqs = [f.seq for _, f, _ in pending]
        t_capture = [f.t_capture_server for _, f, _ in pending]
        t_received = [t for _, _, t in pending]
        lost = [avatars[a].lost_bits if a in avatars else 0 for a in ids]
        captured, arrived = np.array(t_capture), np.array(t_received)
        keep = np.empty(len(pending), dtype=np.bool_)
        solved = self.solver.solve_staged(ids)
        t_solved = now()
        roots, rotations = solved.root, solved.rotations
        # the spectators' own row checks: a row they would refuse is dropped alone,
        # never the batch (one compiled pass over the batch)
        unsendable = sendable_rows(roots, rotations, captured, arrived, t_solved, keep)
        if unsendable:
            self.metrics.frames_unsendable += unsendable
            if not keep.any():
                return
            rows = keep.tolist()
            ids, seqs, lost = _kept(ids, rows), _kept(seqs, rows), _kept(lost, rows)
            t_capture, t_received = _kept(t_capture, rows), _kept(t_received, rows)
            roots, rotations = roots[keep], rotations[keep]
            captured, arrived = captured[keep], arrived[keep]
        shared = SharedBatch(ids, seqs, roots, rotations, t_capture, t_received, t_solved,
                             lost, self._codings, rows_checked=True)
        self.metrics.frames_solved += len(ids)
        self.metrics.batches += 1
        self.deliver(shared)
        # after the batch is out, so that it waits for nothing: a few numpy calls for the
        # whole batch. Sent: when its bytes went to a socket, else now (in the outboxes)
        self.metrics.latency.batch(captured, arrived, t_solved,
                                   shared.t_sent if shared.t_sent is not None else now())

    def deliver(self, shared: SharedBatch) -> None:
        """Every spectator gets the batch: written to the socket at once when it is idle
        and keeping up (one encoding, no task switch), else through its outbox. With
        other processes (``serve --redis``) it goes to Redis first: the writer's turn
        comes before this process's spectators, so that the far ones do not wait for
        this process's whole fan-out (which doubled their p99 in ``bench fanout``)."""
        if self._roster_infos and any(a in self._roster_infos for a in shared.avatar_ids):
            self.flush_roster()  # a spectator learns an avatar before its first frame
        if self.cluster is not None and not self.relayed:
            self.cluster.publish(self.name, BATCH, shared.encoded())
            if self.spectators:
                asyncio.get_running_loop().call_soon(self.deliver_here, shared)
            return
        self.deliver_here(shared)

    def deliver_here(self, shared: SharedBatch) -> None:
        """The batch to this process's spectators (``deliver``; ``server.fanout``)."""
        self.fanout.deliver(shared)
        if self.history is not None:  # after the sends: the truth for display errors
            ids, t_capture, roots, rotations = shared.solved_rows()
            if ids:
                self.history.add(ids, t_capture, roots, rotations)

    def codings(self, avatar_ids: list[int]) -> dict[int, PoseCoding | None]:
        """How these avatars' rotations are packed: their rosters' codings (a replay's
        avatars have none)."""
        avatars = self.avatars
        return {a: info.coding if (av := avatars.get(a)) is not None
                and (info := av.info) is not None else None for a in avatar_ids}

    # ------------------------------------------------------------------ spectators
    def roster(self) -> AvatarRoster:
        return AvatarRoster(avatars=tuple(a.info for a in self.avatars.values()
                                          if a.info is not None))

    def roster_messages(self, max_avatars: int, max_bytes: int) -> list[bytes]:
        """The roster as encoded messages of at most ``max_avatars`` avatars and
        ``max_bytes`` bytes each: a viewer merges them (each adds avatars), and however
        many avatars the room holds no message nears a viewer's size limit."""
        infos = [a.info for a in self.avatars.values() if a.info is not None]
        return roster_parts(infos, [], max_avatars, max_bytes)

    def broadcast_roster(self, roster: AvatarRoster) -> None:
        """Roster changes to every spectator, merged per room: the first change after
        a quiet spell goes out at once, the ones that follow within
        ``limits.roster_interval_s`` together when it has passed (an avatar's newest
        skeleton; one added and removed meanwhile, as removed)."""
        for info in roster.avatars:
            self._roster_infos[info.avatar_id] = info
            self._roster_removed.pop(info.avatar_id, None)
        for avatar_id in roster.removed:
            self._roster_infos.pop(avatar_id, None)
            self._roster_removed[avatar_id] = None
        if self._roster_timer is not None:  # a send is coming: it takes these too
            return
        loop = asyncio.get_running_loop()
        wait = self._roster_sent_at + self.limits.roster_interval_s - loop.time()
        if wait <= 0:
            self.flush_roster()
        else:
            self._roster_timer = loop.call_later(wait, self.flush_roster)

    def flush_roster(self) -> None:
        """The roster changes not sent yet, now."""
        if self._roster_timer is not None:
            self._roster_timer.cancel()
            self._roster_timer = None
        if not self._roster_infos and not self._roster_removed:
            return
        infos, removed = list(self._roster_infos.values()), list(self._roster_removed)
        self._roster_infos.clear()
        self._roster_removed.clear()
        self._roster_sent_at = asyncio.get_running_loop().time()
        limits = self.limits
        for data in roster_parts(infos, removed, limits.roster_avatars_per_message,
                                 limits.roster_message_bytes):
            self.metrics.rosters += 1
            if self.cluster is not None and not self.relayed:
                self.cluster.publish(self.name, ROSTER, data)
            self.send_roster(data)

    def send_roster(self, data: bytes) -> None:
        """An encoded roster to every spectator of this process, written now: whatever
        batch follows must find it there first (a batch's rotations unpack by the
        rosters' codings)."""
        self.fanout.flush()
        sockets = [s.connection for s in self.spectators.values() if s.connection is not None]
        if sockets:
            broadcast(sockets, data)
        for s in self.spectators.values():
            if s.connection is None:  # a test's spectator without a socket
                asyncio.get_running_loop().create_task(_quiet(s.send_bytes(data)))

    @property
    def empty(self) -> bool:
        """Nothing left of the room here (a relayed room's avatars are the owner's)."""
        return not self.spectators and (self.relayed or not self.avatars)

    @property
    def settled(self) -> bool:
        """No burst open, no roster change waiting, no batch waiting for its slice, and
        no spectator's outbox holding or sending a frame."""
        return not self._scheduled and not self._pending and self._roster_timer is None \
            and self.fanout.idle and all(
            s.outbox.idle for s in self.spectators.values())

    def discard_pending(self) -> None:
        """The server stopped with a burst open: its frames will never be solved."""
        self.metrics.frames_discarded += len(self._pending)
        self._pending.clear()


def _kept(values: list[T], keep: list[bool]) -> list[T]:
    return [v for v, k in zip(values, keep, strict=True) if k]


def roster_parts(infos: list[AvatarInfo], removed: list[int], max_avatars: int,
                 max_bytes: int) -> list[bytes]:
    """Encoded rosters of at most ``max_avatars`` avatars and ``max_bytes`` bytes each
    (the removals ride in the first): a viewer merges them, and however many avatars
    change no message nears a viewer's size limit."""
    chunks = [infos[i:i + max_avatars] for i in range(0, len(infos), max_avatars)] or [[]]
    parts: list[bytes] = []
    while chunks:
        chunk = chunks.pop(0)
        gone = tuple(removed[:MAX_AVATARS]) if not parts else ()
        data = encode(AvatarRoster(avatars=tuple(chunk), removed=gone))
        if len(data) > max_bytes and len(chunk) > 1:  # large skeletons: halve it
            half = len(chunk) // 2
            chunks[:0] = [chunk[:half], chunk[half:]]
        else:  # one avatar over the bound is still sent: within the protocol's own
            parts.append(data)
    parts += [encode(AvatarRoster(removed=tuple(removed[i:i + MAX_AVATARS])))
              for i in range(MAX_AVATARS, len(removed), MAX_AVATARS)]
    return parts


async def send_deliveries(send_bytes: Callable[[bytes], Awaitable[None]],
                          deliveries: list[Delivery]) -> None:
    """What a spectator's outbox sends: the shared encoding when it is one whole batch,
    else the frames it has (the newest of each avatar) as a batch of their own."""
    first = deliveries[0][0]
    if all(d[0] is first for d in deliveries) and len(deliveries) == first.size:
        await send_bytes(first.encoded())
        return
    batch = AvatarBatch.from_frames([b.frame(i) for b, i in deliveries], t_sent=now())
    codings = {(a := b.avatar_ids[i]): b.codings.get(a) for b, i in deliveries}
    await send_bytes(encode(batch, codings))


async def _quiet(aw: Awaitable[None]) -> None:
    """A send to a connection that is closing fails; its own handler cleans up."""
    with contextlib.suppress(Exception):  # websockets' ConnectionClosed variants
        await aw
