"""A connection's ends: who is at the other end, in words for the log (its address,
through a trusted proxy the client's; client text escaped and cut), how it ended, and the
small socket buffers that keep a slow viewer's backlog where latest-wins can act."""

from __future__ import annotations

import contextlib
import socket

from websockets.asyncio.server import ServerConnection
from websockets.frames import CloseCode

from posecast.server.limits import ServerLimits
from posecast.server.tls import tcp_under_tls


def closed_by_client(ws: ServerConnection) -> bool:
    """The client ended the connection on purpose (it sent a normal close first), not a
    drop: its avatar need not wait for a reconnect."""
    protocol = ws.protocol
    return (protocol.close_rcvd is not None and bool(protocol.close_rcvd_then_sent)
            and protocol.close_rcvd.code == CloseCode.NORMAL_CLOSURE)


def client_address(ws: ServerConnection) -> object:
    """Who the per-address limits count: the peer, or through a trusted proxy the client
    its X-Forwarded-For names (``Session.admit``), as a (host, port) tuple."""
    forwarded = getattr(ws, "forwarded_for", None)
    return (forwarded, 0) if forwarded is not None else ws.remote_address


def peer(ws: ServerConnection) -> str:
    """The client's address as host:port ([host]:port for IPv6), for log lines; through
    a trusted proxy, "client via proxy:port"."""
    address = ws.remote_address
    if not isinstance(address, tuple) or len(address) < 2:
        return "?"
    host, port = address[0], address[1]
    shown = f"[{host}]:{port}" if ":" in str(host) else f"{host}:{port}"
    forwarded = getattr(ws, "forwarded_for", None)
    return shown if forwarded is None else f"{forwarded} via {shown}"


def safe_name(text: str, limit: int = 40) -> str:
    """Client text for a log line: quoted with control characters escaped (repr), cut
    to ``limit`` characters, so that no client can forge or flood log lines."""
    return repr(text[:limit]) + ("..." if len(text) > limit else "")


def closed_words(ws: ServerConnection) -> str:
    """How the connection ended, e.g. "close 1000 'bye'" (1006: lost without a close)."""
    if ws.close_code is None:
        return "still open"
    reason = f" {safe_name(ws.close_reason)}" if ws.close_reason else ""
    return f"close {ws.close_code}{reason}"


def cap_send_buffers(ws: ServerConnection, limits: ServerLimits) -> None:
    """Small kernel and transport buffers, so that a viewer's backlog shows at once in
    the event loop (Spectator.direct), where latest-wins replaces stale frames: with
    the kernel's defaults a stalled viewer's queue grew to ~3.9 MB, seconds of stale
    frames (docs/performance.md, "Slow viewers")."""
    transport = ws.transport
    sock = transport.get_extra_info("socket") if transport is not None else None
    if sock is None:
        return
    with contextlib.suppress(OSError, AttributeError):  # not TCP, or no such option
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, limits.send_buffer_bytes)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NOTSENT_LOWAT,
                        limits.send_unsent_bytes)
    # a send waits until the transport has handed everything to the kernel
    if transport.get_extra_info("ssl_object") is None:
        transport.set_write_buffer_limits(high=0)
        return
    # TLS: the TLS layer pauses at a size >= its mark (plain transports at >), so 0
    # would pause its every send for good; 1 means what 0 means elsewhere. Its TCP
    # transport below holds 64 KiB unless told otherwise: a slow viewer fell 1.85 s behind
    # instead of 0.69 s (tests/server/test_tls.py)
    transport.set_write_buffer_limits(high=1)
    below = tcp_under_tls(transport)
    if below is not None:
        below.set_write_buffer_limits(high=0)
