#!/usr/bin/env python3
"""What reading one whole binary frame costs: websockets' parser against the fast path's
(``protocol.arrivals.lone_payload``), for a player's tracker frame and a 16-avatar batch.

    python scripts/frame_reads.py [--repeat 5]

Each is timed warm, back to back (``timeit``, the best of ``--repeat`` rounds of 20,000):
websockets' sans-I/O server or client side fed the frame and asked for its events, and
the fast path's check of the parser's state and the frame's header, and its unmasking.
"""

from __future__ import annotations

import argparse
import secrets
import timeit

from websockets.frames import Frame, Opcode
from websockets.protocol import CLIENT, SERVER, Event, Protocol, State

from posecast.protocol.arrivals import lone_payload
from posecast.protocol.framing import binary_frame, masked_binary_frame

SIZES = {"tracker frame (295 B, a player's, masked)": (295, SERVER),
         "batch of 16 avatars (~2 kB, a spectator's)": (1840, CLIENT)}
NUMBER = 20_000


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    if args.repeat < 1:
        parser.error("--repeat must be >= 1")
    print(f"{'frame':45s} {'websockets':>11s} {'fast path':>10s}")
    for label, (size, side) in SIZES.items():
        payload = secrets.token_bytes(size)
        data = masked_binary_frame(payload, secrets.token_bytes(4)) if side is SERVER \
            else binary_frame(payload)
        ws = Protocol(side, state=State.OPEN, max_size=1 << 20)

        def websockets_reads(ws: Protocol = ws, data: bytes = data) -> list[Event]:
            ws.receive_data(data)
            events = ws.events_received()
            ws.data_to_send()
            return events

        (frame,) = websockets_reads()
        assert isinstance(frame, Frame) and frame.opcode is Opcode.BINARY
        assert frame.data == payload and lone_payload(ws, data) == payload
        times = [min(timeit.repeat(f, number=NUMBER, repeat=args.repeat)) / NUMBER * 1e6
                 for f in (websockets_reads, lambda ws=ws, data=data: lone_payload(ws, data))]
        print(f"{label:45s} {times[0]:9.2f} us {times[1]:8.2f} us")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
