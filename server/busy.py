"""Busy polling: a server on a core of its own never sleeps and keeps its path warm.

An idle server blocks in the kernel until the next burst of tracker frames. On this VM
the core then halts and other work runs on it, so the burst starts with a wake-up and
finds the server's code and data gone from the caches: the same 16 frames took twice as
long 11 ms after the last burst (90 Hz) as back to back (decode, stage, solve and encode:
1190 against 485 us median, one core). With busy polling the event loop never blocks.
Between bursts it re-runs the path of the latest tracker frame on a twin avatar (decode,
stage, solve, encode; one step per pass of the loop, so a frame that arrives waits at
most one step, ~50 us), which keeps that path in the caches; reads are taken without a
wake-up. While a burst is open it waits like an idle server: the burst's own passes of
the loop decide when it ends (``server.room``).

It costs a whole core, all the time: use it where the server has a core to itself.
"""

from __future__ import annotations

import asyncio
import logging

import numpy as np

from protocol import TrackerFrame, decode_client
from protocol.codec import encode_avatar_batch
from server.avatars import AvatarSolver
from solver.rig import Rig

log = logging.getLogger("posecast.server")

TWIN = 0  # the twin's avatar id in its own solver


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
        self.solver = AvatarSolver(rig, solver, capacity=1)
        self.frame: bytes | bytearray | memoryview | None = None  # the latest one seen
        self.steps = 0

    @property
    def calibrated(self) -> bool:
        return TWIN in self.solver.calibrations

    def calibrate(self, roles: tuple[str, ...], poses: np.ndarray) -> None:
        if not self.calibrated:  # one body is enough: it only has to run the code
            self.solver.calibrate(TWIN, roles, poses[:, :3], poses[:, 3:])

    def step(self) -> None:
        """One frame's path on the twin: what a real frame of a lone avatar costs."""
        if self.frame is None or not self.calibrated:
            return
        msg = decode_client(self.frame)
        if not isinstance(msg, TrackerFrame):
            return
        self.solver.stage(TWIN, msg.roles, msg.poses)
        solved = self.solver.solve_staged([TWIN])
        t = msg.t_capture_server
        encode_avatar_batch([TWIN], [msg.seq], solved.root, solved.rotations, [t], [t], t,
                            t_sent=t)
        self.steps += 1


async def busy_poll(warm: WarmPath, bursts: OpenBursts, stop: asyncio.Event) -> None:
    """Keep the event loop polling, and ``warm`` stepping, until ``stop``; pause while a
    burst is open. A step that fails (it cannot, short of a bug) turns warming off and
    leaves the polling."""
    warming = True
    while not stop.is_set():
        if bursts.count:
            await bursts.none_open.wait()
            continue
        if warming:
            try:
                warm.step()
            except Exception:  # never let the warm-up hurt the server
                log.exception("busy polling: the warm-up step failed; polling on without it")
                warming = False
        await asyncio.sleep(0)  # one pass of the loop: reads, timers, other tasks
