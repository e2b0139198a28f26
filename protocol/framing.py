"""WebSocket frames (RFC 6455 5.2) built once, for the two hot writers.

websockets builds each frame anew per connection (a ``Frame``, its checks, a buffer, the
protocol's bookkeeping). For a whole binary message with no extension (both ends connect
with ``compression=None``) a frame is a header, for a client a mask, and the payload:

- the server frames a batch once and writes those bytes to every spectator's transport
  (``server.fanout``; issue 30: frame once, write to many);
- a player frames its tracker frame itself (``client.session.connection``): 16 demo
  players share one core, and websockets' framing was a sixth of a player's tick.

Both are what websockets would write for a connection that is open and not in the middle
of a fragmented message; the writers check that before they write.
"""

from __future__ import annotations

import struct

from websockets.speedups import apply_mask

_FIN_BINARY = 0x82
_MASKED = 0x80  # the length byte's high bit: a client's frame carries a masking key


def _header(n: int, masked: int) -> bytes:
    if n < 126:
        return struct.pack("!BB", _FIN_BINARY, masked | n)
    if n < 1 << 16:
        return struct.pack("!BBH", _FIN_BINARY, masked | 126, n)
    return struct.pack("!BBQ", _FIN_BINARY, masked | 127, n)


def binary_frame(payload: bytes) -> bytes:
    """A whole binary message as a server sends it: header and payload."""
    return _header(len(payload), 0) + payload


def masked_binary_frame(payload: bytes, mask: bytes) -> bytes:
    """A whole binary message as a client sends it: header, the 4-byte masking key and
    the payload masked with it. The key must be unpredictable (RFC 6455 10.3: the caller
    draws it from ``secrets``, as websockets does)."""
    if len(mask) != 4:
        raise ValueError(f"a masking key is 4 bytes, not {len(mask)}")
    return _header(len(payload), _MASKED) + mask + apply_mask(payload, mask)
