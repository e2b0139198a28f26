"""Reads before decodes: the messages a process's connections read are decoded once its
event loop has gone a pass without reading more (or SETTLE_MAX_S after the first).

Each message is stamped when its bytes are read (``protocol.arrivals``). Where many
connections share a process (the demo's spectators, the fan-out bench's probes), a
server writes a batch to them one after the other over a few hundred microseconds; a
decode run between two of those reads (a batch's first decode took ~200 us there, its
code cold) made every connection read after it late by as much, counted as their
network time, which they would not pay on machines of their own. A process with one
connection pays two passes of its loop, microseconds, before each decode.
"""

from __future__ import annotations

import asyncio
import weakref
from collections.abc import Callable

from posecast.client.sources.base import now

# the longest a decode waits for the reads to settle: well over a server's writes of one
# batch to a process's connections (16 in ~0.3 ms in the demo), well under a headset
# frame (11 ms), so that a stream of reads that never pauses does not starve decoding
SETTLE_MAX_S = 0.0005


class ReadsFirst:
    """One event loop's decoders waiting for its reads to settle (``of``)."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._waiting: list[Callable[[], None]] = []
        self._reads = 0  # messages read on this loop
        self._seen = -1  # as counted at the last pass; -1: no pass yet since the first
        self._first = 0.0  # when the first of the waiting messages was read

    def read(self, decode: Callable[[], None] | None) -> None:
        """A message was read; ``decode`` (once per batch of reads of a connection: None
        when it is already waiting) takes it and those that follow."""
        self._reads += 1
        if decode is None:
            return
        if not self._waiting:
            self._first = now()
            self._seen = -1
            self._loop.call_soon(self._pass)
        self._waiting.append(decode)

    def _pass(self) -> None:
        # call_soon callbacks run between the loop's polls: a count that moved since the
        # last one means this pass read something, and the next may read more
        if self._reads != self._seen and now() - self._first < SETTLE_MAX_S:
            self._seen = self._reads
            self._loop.call_soon(self._pass)
            return
        waiting, self._waiting = self._waiting, []
        for decode in waiting:
            try:
                decode()
            except Exception as exc:  # one connection's bug: the others still decode
                self._loop.call_exception_handler({
                    "message": "a connection's decoding failed", "exception": exc})


_LOOPS: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, ReadsFirst] = (
    weakref.WeakKeyDictionary())


def of(loop: asyncio.AbstractEventLoop) -> ReadsFirst:
    """The running loop's ``ReadsFirst`` (one per loop: every connection of the process
    that reads on it)."""
    reads = _LOOPS.get(loop)
    if reads is None:
        reads = _LOOPS[loop] = ReadsFirst(loop)
    return reads
