"""When each message reached this process, for both ends of a websockets connection.

A connection class that mixes in ``ArrivalStamps`` notes the time each complete data
message is handed over by the event loop, before the message waits for the task that
reads it; ``arrival_time`` pairs a message just read with its stamp. Both ends measure
"received" at that same point: a server whose loop is busy (reading the rest of a burst,
solving a batch) counts the wait as its own time, and in a demo where many spectators
share one process, one spectator's decoding does not count as another's network latency.
A connection may also take a hot message type straight from there (``fast_path``):
it then skips websockets' queue and the reading task's turn; and, when a read is exactly
one whole binary frame while websockets' parser waits between frames, its parser too
(``protocol.framing.lone_binary_payload``): ~2 us less of each such read's time, a
player's tracker frame on the server, a batch on a spectator's end
(``scripts/frame_reads.py``).
No I/O here: it only observes the bytes and frames websockets is given.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import Any

from websockets.frames import DATA_OPCODES, Frame, Opcode
from websockets.protocol import SERVER, Event, Protocol, State
from websockets.streams import StreamReader

from posecast.protocol.framing import lone_binary_payload

Data = bytes | bytearray | memoryview
# where websockets' parser waits when it has read every frame it was given: its loop
# asks whether the stream ended before it parses the next frame, never within one
_BETWEEN_FRAMES = StreamReader.at_eof.__code__
_DEPTH = 8  # the chain's depth (a client's or server's parse, the frames' loop, at_eof)


def lone_payload(protocol: Protocol, data: bytes) -> bytes | None:
    """The payload of ``data``, read from the connection of ``protocol``, when it is one
    whole binary frame (``framing.lone_binary_payload``) that websockets' parser would
    read as a message of its own; else None, and websockets reads it."""
    waiting, limit = _between_frames(protocol)
    return lone_binary_payload(data, protocol.side is SERVER, limit) if waiting else None


def _between_frames(protocol: Protocol) -> tuple[bool, int | None]:
    """Whether the parser of ``protocol`` waits between frames, with nothing buffered,
    the connection open, no extension and no fragmented message begun; and the largest
    payload it takes then. Attributes an older websockets lacks read as "not waiting":
    its reads all take websockets' way."""
    if protocol.state is not State.OPEN or protocol.extensions:
        return False, None
    reader = protocol.reader
    if reader.buffer or reader.eof or getattr(protocol, "current_size", 0) is not None:
        return False, None
    waiting = protocol.parser  # the generator it waits in: the innermost of the chain
    for _ in range(_DEPTH):
        inner = getattr(waiting, "gi_yieldfrom", None)
        if inner is None:
            break
        waiting = inner
    if getattr(waiting, "gi_code", None) is not _BETWEEN_FRAMES:
        return False, None
    limit = getattr(protocol, "max_message_size", 0)
    fragment = getattr(protocol, "max_fragment_size", 0)
    if limit == 0 or fragment == 0:  # not this websockets' attributes
        return False, None
    if fragment is not None:
        limit = fragment if limit is None else min(limit, fragment)
    return True, limit


class ArrivalStamps:
    """Mix in before a websockets ``ClientConnection`` or ``ServerConnection``; set
    ``clock`` to the end's clock.

    ``fast_path``, when set, sees each whole binary message as it is read, with its
    arrival time, and returns True if it handled it; the reading task gets the rest.
    Only while nothing waits in the queue, so messages are handled in the order they
    came. It must not raise: a message it cannot handle goes the usual way.
    """

    clock: Callable[[], float]
    fast_path: Callable[[Data, float], bool] | None = None

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.arrivals: deque[float] = deque()
        self._declined = False  # the fast path saw the frame websockets reads now

    def data_received(self, data: bytes) -> None:
        fast = self.fast_path
        if fast is not None and not self.arrivals:
            payload = lone_payload(self.protocol, data)  # type: ignore[attr-defined]
            if payload is not None:
                if fast(payload, self.clock()):
                    return  # websockets' parser still waits between frames
                self._declined = True  # it reads the frame now: once is enough
        super().data_received(data)  # type: ignore[misc]

    def process_event(self, event: Event) -> None:
        if isinstance(event, Frame) and event.opcode in DATA_OPCODES and event.fin:
            t = self.clock()
            declined, self._declined = self._declined, False
            if (self.fast_path is not None and event.opcode is Opcode.BINARY
                    and not declined and not self.arrivals and self.fast_path(event.data, t)):
                return
            self.arrivals.append(t)
        super().process_event(event)  # type: ignore[misc]


def arrival_time(connection: object, clock: Callable[[], float]) -> float:
    """When the message just read from ``connection`` arrived: its stamp (every message
    read must be paired, in order), or ``clock()`` for a connection without stamps."""
    arrivals: deque[float] | None = getattr(connection, "arrivals", None)
    return arrivals.popleft() if arrivals else clock()
