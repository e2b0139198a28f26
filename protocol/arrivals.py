"""When each message reached this process, for both ends of a websockets connection.

A connection class that mixes in ``ArrivalStamps`` notes the time each complete data
message is handed over by the event loop, before the message waits for the task that
reads it; ``arrival_time`` pairs a message just read with its stamp. Both ends measure
"received" at that same point: a server whose loop is busy (reading the rest of a burst,
solving a batch) counts the wait as its own time, and in a demo where many spectators
share one process, one spectator's decoding does not count as another's network latency.
A connection may also take a hot message type straight from there (``fast_path``):
it then skips websockets' queue and the reading task's turn.
No I/O here: it only observes the frames websockets has parsed.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import Any

from websockets.frames import DATA_OPCODES, Frame, Opcode
from websockets.protocol import Event

Data = bytes | bytearray | memoryview


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

    def process_event(self, event: Event) -> None:
        if isinstance(event, Frame) and event.opcode in DATA_OPCODES and event.fin:
            t = self.clock()
            if (self.fast_path is not None and event.opcode is Opcode.BINARY
                    and not self.arrivals and self.fast_path(event.data, t)):
                return
            self.arrivals.append(t)
        super().process_event(event)  # type: ignore[misc]


def arrival_time(connection: object, clock: Callable[[], float]) -> float:
    """When the message just read from ``connection`` arrived: its stamp (every message
    read must be paired, in order), or ``clock()`` for a connection without stamps."""
    arrivals: deque[float] | None = getattr(connection, "arrivals", None)
    return arrivals.popleft() if arrivals else clock()
