"""The one exception of the protocol, and the error codes shared by server and client.

Every rejection of bad input raises ``ProtocolError(code, message)``; the message names the
field path and the offending value, so the server can send it back verbatim in an
``Error`` message and the sender knows what to fix.
"""

from __future__ import annotations

from enum import StrEnum


class ErrorCode(StrEnum):
    # raised by protocol/ while decoding
    NOT_MSGPACK = "not_msgpack"  # bytes that msgpack cannot parse, or a text frame
    TOO_LARGE = "too_large"  # over the size limit, checked before parsing
    MALFORMED = "malformed"  # msgpack, but not a map with a string "type"
    UNKNOWN_TYPE = "unknown_type"
    INVALID = "invalid"  # a field of a known message is wrong (type, range, NaN, ...)
    UNSUPPORTED_VERSION = "unsupported_version"
    # for the server to use: valid messages that are not acceptable in this state
    NOT_ALLOWED = "not_allowed"  # e.g. a spectator sending tracker frames, frames before hello
    NOT_CALIBRATED = "not_calibrated"
    AUTH_FAILED = "auth_failed"
    RATE_LIMITED = "rate_limited"  # over a per-connection message rate (server.limits)
    FULL = "full"  # a cap of the server is reached: rooms, players, connections
    OUT_OF_ORDER = "out_of_order"  # a tracker frame whose seq is not above the last one
    INTERNAL = "internal"


class ProtocolError(Exception):
    """A message was rejected; ``message`` says which field and value, and why."""

    def __init__(self, code: ErrorCode | str, message: str) -> None:
        super().__init__(f"{code}: {message}")
        self.code = str(code)
        self.message = message
