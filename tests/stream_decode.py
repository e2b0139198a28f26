"""``decode`` for tests that read a server's websocket themselves: each message decoded as
a viewer decodes its stream, batches unpacked with the codings of the rosters read
before them (``protocol.codec.decode_stream``). One set of codings for a test (conftest
clears it before each): avatar ids are unique per server, every spectator gets an
avatar's roster before its frames, and a later server's roster replaces an earlier
one's."""

from __future__ import annotations

from posecast.protocol import Message
from posecast.protocol.codec import decode_stream
from posecast.protocol.pose_coding import RosterCodings
from posecast.protocol.validation import MAX_MESSAGE_BYTES

CODINGS = RosterCodings()


def decode(data: bytes | bytearray | memoryview | str, *,
           max_bytes: int = MAX_MESSAGE_BYTES) -> Message:
    return decode_stream(data, CODINGS, max_bytes=max_bytes)
