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

The readers' twin: ``lone_binary_payload`` takes a read that is exactly one such frame
(``protocol.arrivals``: a player's tracker frame, a spectator's batch, each its own
write), where websockets' parser costs ~3 us a frame (its generators, ``Frame``).
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


def lone_binary_payload(data: bytes, masked: bool, max_size: int | None) -> bytes | None:
    """The payload of ``data`` if it is exactly one whole binary frame of fewer than
    65,536 bytes, with no reserved bit, masked if ``masked`` (what a server reads) and
    within ``max_size``; else None (a part of a frame, several, text, control frames, a
    fragment: what websockets reads). Masking and lengths as ``websockets.frames``."""
    n = len(data)
    if n < 2 or data[0] != _FIN_BINARY or (data[1] & _MASKED != 0) != masked:
        return None
    length, head = data[1] & 0x7F, 2
    if length == 126:
        if n < 4:
            return None
        length, head = (data[2] << 8) | data[3], 4
    elif length == 127:
        return None
    if max_size is not None and length > max_size:
        return None
    if not masked:
        return bytes(data[head:]) if n == head + length else None
    if n != head + 4 + length:
        return None
    return apply_mask(data[head + 4:], data[head:head + 4])
