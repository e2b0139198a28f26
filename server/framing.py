"""A batch framed once for every spectator (issue 30: frame once, write to many).

websockets' ``broadcast`` builds each connection's frame anew (its header, a copy of the
payload, the protocol's bookkeeping) before writing it. A server's frame (RFC 6455 5.2)
is the same for every connection: unmasked, no extension (``serve(compression=None)``),
a binary opcode, the payload's length. So the room builds those bytes once per batch and
writes them to each transport (``server.fanout``), which is all websockets itself
would do for a connection that is open and not in the middle of a fragmented message.
"""

from __future__ import annotations

import struct

_FIN_BINARY = 0x82


def binary_frame(payload: bytes) -> bytes:
    """A whole binary message as a server sends it: header and payload."""
    n = len(payload)
    if n < 126:
        header = struct.pack("!BB", _FIN_BINARY, n)
    elif n < 1 << 16:
        header = struct.pack("!BBH", _FIN_BINARY, 126, n)
    else:
        header = struct.pack("!BBQ", _FIN_BINARY, 127, n)
    return header + payload
