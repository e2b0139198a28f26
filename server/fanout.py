"""A room's batches to its spectators' sockets: framed once, written to many, and when
the writes outgrow the time between batches, several batches to a spectator in one write.

A batch goes straight to the socket of every spectator that keeps up (nothing in its
outbox, nothing unsent in its transport); the others get it through their outbox, latest
wins (server.outbox). One loopback write costs ~10 us of kernel time on its own
(scripts/loopback_writes.py), so one write per spectator per batch fills a core at
~1,000 spectators of a 90 Hz room, and past that a process lost frames.

So the writes go in rounds over the spectators, a slice at a time (SLICE_S): between
slices the event loop reads the players' frames and solves them. Each spectator keeps
the number of the last batch written to it; a batch that comes while a round is under
way joins it, and a spectator the round has not reached yet gets both in one write (the
batches since its mark, joined once for all who share that mark). A room its process
serves in time has every round done before the next batch; a larger one pays a little
latency instead of a write per batch, and latest wins only past MAX_LAG_S. A
spectator's batches always go out in order, and all are written before a roster
(``flush``: a batch unpacks by the rosters before it). Nothing here costs per spectator
when a batch comes: only the visits of a round do. A round that outlasted its slice is
followed by one starting a place further along the room, so that in a large room the
last to join do not wait longest at every batch.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from websockets.asyncio.server import ServerConnection
from websockets.protocol import State
from websockets.server import ServerProtocol

from posecast.server.metrics import Metrics
from posecast.server.outbox import Outbox

if TYPE_CHECKING:
    from posecast.server.room import Delivery, SharedBatch

# a spectator whose socket holds more unsent bytes than this is slow: its frames go
# through its outbox (latest wins) instead of piling up in the kernel and the transport.
# The kernel's share is capped (ServerLimits.send_unsent_bytes): a byte left in the
# transport means the viewer is behind
DIRECT_WRITE_LIMIT = 1
# the writes of one pass of the event loop (~40): shorter than a burst's window
# (server.room.COALESCE_MAX_S), so that the frames of a burst that opened before a slice
# are read before its window closes, and the burst is not split into more batches
SLICE_S = 0.0005
# the clock is read once per this many writes (a read costs about a tenth of a write)
CHECK_EVERY = 16
# how old a batch may be and still be written to a spectator that is owed newer ones:
# older ones are dropped (latest wins). Counted in time, not batches: a burst split in
# several batches is not older for it. About two headset frames more than the 25 ms a
# viewer's interpolation hides (``bench fanout``'s budget)
MAX_LAG_S = 0.05
# batches whose avatar-frame counts are kept, for the frames a spectator is owed from its
# mark: more than a round can take, however many spectators (~11 s at 90 Hz)
FRAMES_KEPT = 1024


@dataclass(eq=False)
class Spectator:
    outbox: Outbox[Delivery]
    send_bytes: Callable[[bytes], Awaitable[None]]
    task: asyncio.Task[None] | None = None
    # the socket, for writing a batch straight from the solve (``FanOut``); its
    # transport and protocol looked up once here, not for every batch
    connection: ServerConnection | None = None
    transport: asyncio.Transport | None = field(default=None, init=False)
    protocol: ServerProtocol | None = field(default=None, init=False)
    mark: int = field(default=0, init=False)  # the last batch it was given (FanOut)

    def __post_init__(self) -> None:
        if self.connection is not None:
            self.transport = self.connection.transport
            self.protocol = self.connection.protocol


def deliveries(shared: SharedBatch) -> dict[int, Delivery]:
    """A batch as an outbox takes it: each avatar's row."""
    return {a: (shared, i) for i, a in enumerate(shared.avatar_ids)}


class FanOut:
    """Writes a room's batches to its spectators (``spectators``: the room's, live; each
    added with ``add``). A room's batches are numbered from 1 in the order they come."""

    def __init__(self, spectators: dict[int, Spectator], metrics: Metrics,
                 slice_s: float | None = None) -> None:
        self.spectators = spectators
        self.metrics = metrics
        self.slice_s = SLICE_S if slice_s is None else slice_s
        self.latest = 0  # the number of the newest batch (the first is 1)
        # the batches of the last MAX_LAG_S (and the newest) by number, the first of
        # them, when each came (loop time), and the avatar-frames of all batches up to
        # each number (the frames owed from a mark: a difference of two)
        self._batches: dict[int, SharedBatch] = {}
        self._oldest = 1
        self._came: dict[int, float] = {}
        self._frames_to: dict[int, int] = {0: 0}
        self._offers: dict[int, dict[int, Delivery]] = {}  # a kept batch, as outboxes take it
        # what a spectator marked at k is written: the batches after k, joined (once
        # per batch for all spectators marked at k), and their avatar-frames
        self._owed: dict[int, tuple[bytes, int, int]] = {}
        self._round: list[Spectator] = []  # the spectators of the round under way
        self._turn = 0  # where the room's order starts in it
        self._sliced = False  # the round under way took more than a slice
        self._at = 0  # the next one's index in it
        self._again = False  # a batch came during the round: another round follows
        self._next_slice: asyncio.Handle | None = None

    def add(self, conn_id: int, spectator: Spectator) -> None:
        """A spectator joins: it is owed the batches from the next one on."""
        spectator.mark = self.latest
        self.spectators[conn_id] = spectator

    @property
    def idle(self) -> bool:
        """Every spectator has every batch (written, or in its outbox)."""
        return self._at >= len(self._round) and not self._again

    def deliver(self, shared: SharedBatch) -> None:
        """The batch to every spectator: the round under way takes it on; else a round
        starts, the first slice now."""
        t = asyncio.get_running_loop().time()
        k = self.latest = self.latest + 1
        self._batches[k] = shared
        self._came[k] = t
        self._frames_to[k] = self._frames_to[k - 1] + shared.size
        self._owed.clear()
        if self._at < len(self._round):
            self._again = True
            if self._next_slice is None:  # else the round goes on at its next slice
                self._write(t, time.perf_counter() + self.slice_s)
        else:
            self._start_round()
            self._write(t, time.perf_counter() + self.slice_s)
        self._forget_old(t, k)

    def _forget_old(self, t: float, k: int) -> None:
        """Batches older than MAX_LAG_S are let go (a spectator behind skips them). After
        the first slice: freeing a batch is not what the newest one should wait for."""
        self._frames_to.pop(k - FRAMES_KEPT, None)
        while self._oldest < k and t - self._came[self._oldest] > MAX_LAG_S:
            del self._batches[self._oldest], self._came[self._oldest]
            self._offers.pop(self._oldest, None)
            self._oldest += 1

    def flush(self) -> None:
        """Every batch written now (before a roster, which must follow them)."""
        if self._next_slice is not None:
            self._next_slice.cancel()
            self._next_slice = None
        self._write(asyncio.get_running_loop().time(), math.inf)

    def forget(self, spectator: Spectator) -> int:
        """A spectator left: the avatar-frames it was still owed (now dropped)."""
        if spectator.mark >= self.latest:
            return 0
        owed = self._frames_after(spectator.mark)
        spectator.mark = self.latest  # a round that still lists it skips it
        return owed

    def _frames_after(self, mark: int) -> int:
        """The avatar-frames of the batches after ``mark``."""
        frames_to = self._frames_to
        before = frames_to.get(mark)
        if before is None:  # older than those kept (FRAMES_KEPT batches: seconds)
            before = frames_to[max(0, self.latest - FRAMES_KEPT + 1)]
        return frames_to[self.latest] - before

    # ------------------------------------------------------------------ writing
    def _start_round(self) -> None:
        """The next round's order: the room's, and after a round that took more than a
        slice, turned by one place more, so that no spectator (the last to join) waits
        for a whole round at every batch: over as many rounds as spectators, each has
        had every place. One place and no more: a spectator's visits stay a round apart
        (turned by more, the rounds of a busy room wrote later on average: bench fanout,
        1,100 spectators). A room written within a slice keeps its order (the demo's
        16 spectators, whose tails rose a quarter when turned)."""
        spectators = list(self.spectators.values())
        n = len(spectators)
        if n > 1:
            self._turn = (self._turn + (1 if self._sliced else 0)) % n
            if self._turn:
                spectators = spectators[self._turn:] + spectators[:self._turn]
        self._sliced = False
        self._round = spectators
        self._at = 0
        self._again = False

    def _span(self, mark: int) -> tuple[int, int, int]:
        """For a spectator marked at ``mark``: the first batch it is still owed (those
        of the last MAX_LAG_S), the avatar-frames from there on, and those skipped."""
        first = max(mark + 1, self._oldest)
        frames = self._frames_to[self.latest] - self._frames_to[first - 1]
        return first, frames, self._frames_after(mark) - frames

    def _since(self, mark: int) -> tuple[bytes, int, int]:
        """What a spectator marked at ``mark`` is written (``_span``): the bytes of its
        batches, joined once for all who share the mark, their frames, and those skipped."""
        owed = self._owed.get(mark)
        if owed is None:
            first, frames, skipped = self._span(mark)
            data = b"".join(self._batches[k].framed() for k in range(first, self.latest + 1))
            owed = self._owed[mark] = (data, frames, skipped)
        return owed

    def _write(self, t: float, deadline: float) -> None:
        """The round's visits until it ends (and the next, if a batch came meanwhile)
        or the slice does; then the next slice is scheduled."""
        self._next_slice = None
        latest, metrics, clock = self.latest, self.metrics, time.perf_counter
        is_open, limit, check = State.OPEN, DIRECT_WRITE_LIMIT, CHECK_EVERY
        frame: bytes | None = None
        size = written = delivered = 0
        while True:
            spectators, at = self._round, self._at
            # once per spectator per batch (1,000 spectators at 90 Hz: every object
            # touched counts), so the checks are inline: the outbox has nothing queued
            # and no rate to keep, the socket keeps up, and the connection is open and
            # not closing. (No send to a spectator is fragmented, so none can be in the
            # middle of a message.)
            while at < len(spectators):
                s = spectators[at]
                at += 1
                mark = s.mark
                if mark >= latest:  # it has them all (joined late, or left)
                    continue
                tr = s.transport
                if (tr is not None and s.outbox.ready(t)
                        and tr.get_write_buffer_size() < limit
                        and s.protocol.state is is_open  # type: ignore[union-attr]
                        and not tr.is_closing()):
                    if mark == latest - 1:  # the usual case: the newest batch alone
                        if frame is None:
                            frame = self._batches[latest].framed()
                            size = self._batches[latest].size
                        tr.write(frame)
                        n = size
                    else:
                        data, n, skipped = self._since(mark)
                        tr.write(data)
                        metrics.writes_merged += 1
                        metrics.frames_dropped += skipped
                    s.mark = latest
                    s.outbox.sent_directly(n, t)
                    delivered += n
                    written += 1
                    if not written % check and clock() > deadline:
                        self._sliced = self._sliced or at < len(spectators)
                        break
                else:
                    self._to_outbox(s)
                    s.mark = latest
            self._at = at
            if at < len(spectators) or not self._again:
                break
            self._start_round()  # a batch came during the round: those before it lack it
        metrics.frames_delivered += delivered
        if not self.idle:
            self._next_slice = asyncio.get_running_loop().call_soon(self._slice)

    def _to_outbox(self, s: Spectator) -> None:
        """A spectator behind: its outbox takes what it is owed (latest wins there)."""
        first, _, skipped = self._span(s.mark)
        self.metrics.frames_dropped += skipped
        for k in range(first, self.latest + 1):
            offered = self._offers.get(k)
            if offered is None:  # once per batch for all the spectators behind
                offered = self._offers[k] = deliveries(self._batches[k])
            s.outbox.offer(offered)

    def _slice(self) -> None:
        self._write(asyncio.get_running_loop().time(), time.perf_counter() + self.slice_s)
