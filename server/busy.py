"""Busy polling: a server on a core of its own never sleeps and keeps its path warm.

An idle server blocks in the kernel until the next burst of tracker frames; on a VM the
core then halts and other work evicts the server's code and data from the caches, so
every burst runs cold, at about twice its back-to-back cost. With busy polling the event
loop never blocks. Between bursts it re-runs the path of the latest tracker frame on a
twin avatar (decode, stage, solve, check and encode; a third of it at a time, every
WARM_PHASE_INTERVAL_S, so that a frame that arrives waits one phase at most, 25-100 us),
which keeps that path in the caches; reads are taken without a wake-up. It must be the
rooms' own code: the twin is solved by their compiled solve and packed with a coding as
their avatars are (a twin run through other code left theirs cold: the server's p99 10%
higher, docs/performance.md). While a burst is open it
waits like an idle server: the burst's own passes of the loop decide when it ends
(``server.room``).

It costs a whole core, all the time: use it where the server has a core to itself.
"""

from __future__ import annotations

import asyncio
import logging
import time

import numpy as np

from posecast.protocol.codec import decode_tracker_poses, encode_avatar_batch
from posecast.protocol.framing import binary_frame
from posecast.protocol.messages import TrackerPoses
from posecast.protocol.pose_coding import PoseCoding
from posecast.protocol.validation import sendable_rows
from posecast.server.avatars import AvatarSolver
from posecast.solver.ik import PoseBatch
from posecast.solver.rig import Rig

log = logging.getLogger("posecast.server")

TWIN = 0  # the twin's avatar id in its own solver
# a phase of the warm-up every 0.3 ms, polling in between: run back to back it slowed
# the processes on the other core (on a VM the two may share a physical core)
WARM_PHASE_INTERVAL_S = 0.0003


class OpenBursts:
    """How many rooms have a burst of frames open, and an event set while none has."""

    def __init__(self) -> None:
        self.count = 0
        self.none_open = asyncio.Event()
        self.none_open.set()

    def opened(self) -> None:
        self.count += 1
        self.none_open.clear()

    def closed(self) -> None:
        self.count = max(self.count - 1, 0)
        if self.count == 0:
            self.none_open.set()


class WarmPath:
    """A twin of one player's avatar, in a solver of its own: it is calibrated from the
    first calibration the server accepts and fed the latest tracker frame's bytes, so
    each ``step`` runs the code a real frame runs, on real data, and changes nothing
    else."""

    def __init__(self, rig: Rig, solver: str) -> None:
        # solved by the compiled code the rooms' solves run (their helper's), no thread
        self.solver = AvatarSolver(rig, solver, capacity=1, shared=True)
        self.frame: bytes | bytearray | memoryview | None = None  # the latest one seen
        self.steps = 0  # whole frames run
        self.sent: bytes | None = None  # the twin's last batch, as a spectator gets it
        self._phase = 0
        self._msg: TrackerPoses | None = None
        self._solved: PoseBatch | None = None
        self._codings: dict[int, PoseCoding | None] = {}

    @property
    def calibrated(self) -> bool:
        return TWIN in self.solver.calibrations

    def calibrate(self, roles: tuple[str, ...], poses: np.ndarray) -> None:
        if not self.calibrated:  # one body is enough: it only has to run the code
            self.solver.calibrate(TWIN, roles, poses[:, :3], poses[:, 3:])
            self._codings = {TWIN: self.solver.coding(TWIN)}

    def step(self) -> None:
        """A third of one frame's path on the twin, in turn: decode and stage, solve,
        encode (~30 us each, measured back to back), so that whatever else the loop has
        to do (a frame that arrives, a spectator's send) waits for one short phase at
        most."""
        if self._phase == 0:
            if self.frame is None or not self.calibrated:
                return
            msg = decode_tracker_poses(self.frame)  # the server's own hot path
            if msg is None:
                return
            self.solver.stage(TWIN, msg.roles, msg.poses, msg.t_capture_server)
            self._msg = msg
        elif self._phase == 1:
            self._solved = self.solver.solve_staged([TWIN])
        else:  # what a room does from the solve to the first write (Room._solve_and_deliver)
            frame, solved = self._msg, self._solved
            assert frame is not None and solved is not None
            t = frame.t_capture_server
            times, keep = np.array([t]), np.empty(1, dtype=np.bool_)
            if not sendable_rows(solved.root, solved.rotations, times, times, t, keep):
                # packed with the twin's coding, as a room packs its avatars': warming
                # another encoder left the real one cold at every batch
                self.sent = binary_frame(encode_avatar_batch(
                    [TWIN], [frame.seq], solved.root, solved.rotations, [t], [t], t,
                    t_sent=t, lost=[0], codings=self._codings, rows_checked=True))
            self.steps += 1
        self._phase = (self._phase + 1) % 3


class BusyPoll:
    """A server's busy polling: the count of open bursts its rooms keep, the twin it
    warms, and the loop that does both (``run``)."""

    def __init__(self, rig: Rig, solver: str) -> None:
        self.bursts = OpenBursts()
        self.warm = WarmPath(rig, solver)

    async def run(self, stop: asyncio.Event) -> None:
        """Keep the event loop polling, and the twin stepping, until ``stop``; pause
        while a burst is open. A step that fails (it cannot, short of a bug) turns
        warming off and leaves the polling."""
        warming = True
        next_phase = 0.0
        while not stop.is_set():
            if self.bursts.count:
                await self.bursts.none_open.wait()
                continue
            t = time.perf_counter()
            if warming and t >= next_phase:
                next_phase = t + WARM_PHASE_INTERVAL_S
                try:
                    self.warm.step()
                except Exception:  # never let the warm-up hurt the server
                    log.exception("busy polling: the warm-up step failed; polling on "
                                  "without it")
                    warming = False
            await asyncio.sleep(0)  # one pass of the loop: reads, timers, other tasks
