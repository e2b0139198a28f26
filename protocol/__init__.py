"""Wire protocol of posecast: message models, codec and clock math (pure, no I/O).

Like the sans-I/O core of the websockets library, this package only turns bytes into
validated messages and back; server/ and client/ own the sockets. Modules:
- ``roles``: device role names
- ``messages``: pydantic models of every message; PROTOCOL_VERSION
- ``quantize``: joint rotations in 5 bytes (worst case 0.0685 degree)
- ``validation``: size limits and array checks
- ``codec``: ``encode`` / ``decode`` / ``decode_client`` (msgpack)
- ``clock``: NTP-style offset estimation
- ``errors``: ``ProtocolError`` and ``ErrorCode``
- ``measure``: bytes per avatar frame and decode timings, for bench commands
"""

import importlib
from typing import TYPE_CHECKING, Any

# Loaded on first use (PEP 562): a light module of the package (``sizes``, ``roles``) must
# not pull in pydantic, numpy and numba, which the command line's parser does not need.
# Type checkers read the imports below as they are.
if TYPE_CHECKING:
    from posecast.protocol.clock import ClockEstimator, ClockSample, clock_sample
    from posecast.protocol.codec import decode, decode_client, encode, encode_tracker_frame
    from posecast.protocol.errors import ErrorCode, ProtocolError
    from posecast.protocol.messages import (
        CLIENT_MESSAGES,
        MESSAGE_TYPES,
        PROTOCOL_VERSION,
        SERVER_MESSAGES,
        SUPPORTED_VERSIONS,
        AvatarBatch,
        AvatarFrame,
        AvatarInfo,
        AvatarRoster,
        Calibrate,
        ClientMessage,
        Error,
        Hello,
        Leave,
        Message,
        Ping,
        Pong,
        Redirect,
        ServerMessage,
        ShownPose,
        TrackerFrame,
        ViewerReport,
        Welcome,
    )
    from posecast.protocol.quantize import (
        BYTES_PER_ROTATION,
        MAX_ANGLE_ERROR_DEG,
        dequantize_rotations,
        quantize_rotations,
        rotation_angle,
    )
    from posecast.protocol.roles import CALIBRATION_ROLES, DEVICE_ROLES, DeviceRole
    from posecast.protocol.validation import MAX_CLIENT_MESSAGE_BYTES, MAX_JOINTS, MAX_MESSAGE_BYTES

_SOURCE = {
    "ClockEstimator": "clock",
    "ClockSample": "clock",
    "clock_sample": "clock",
    "decode": "codec",
    "decode_client": "codec",
    "encode": "codec",
    "encode_tracker_frame": "codec",
    "ErrorCode": "errors",
    "ProtocolError": "errors",
    "CLIENT_MESSAGES": "messages",
    "MESSAGE_TYPES": "messages",
    "PROTOCOL_VERSION": "messages",
    "SERVER_MESSAGES": "messages",
    "SUPPORTED_VERSIONS": "messages",
    "AvatarBatch": "messages",
    "AvatarFrame": "messages",
    "AvatarInfo": "messages",
    "AvatarRoster": "messages",
    "Calibrate": "messages",
    "ClientMessage": "messages",
    "Error": "messages",
    "Hello": "messages",
    "Leave": "messages",
    "Message": "messages",
    "Ping": "messages",
    "Pong": "messages",
    "Redirect": "messages",
    "ServerMessage": "messages",
    "ShownPose": "messages",
    "TrackerFrame": "messages",
    "ViewerReport": "messages",
    "Welcome": "messages",
    "BYTES_PER_ROTATION": "quantize",
    "MAX_ANGLE_ERROR_DEG": "quantize",
    "dequantize_rotations": "quantize",
    "quantize_rotations": "quantize",
    "rotation_angle": "quantize",
    "CALIBRATION_ROLES": "roles",
    "DEVICE_ROLES": "roles",
    "DeviceRole": "roles",
    "MAX_CLIENT_MESSAGE_BYTES": "validation",
    "MAX_JOINTS": "validation",
    "MAX_MESSAGE_BYTES": "validation",
}


def __getattr__(name: str) -> Any:
    module = _SOURCE.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value  # found directly from now on
    return value


__all__ = [
    "BYTES_PER_ROTATION", "CALIBRATION_ROLES", "CLIENT_MESSAGES", "DEVICE_ROLES",
    "MAX_ANGLE_ERROR_DEG", "MAX_CLIENT_MESSAGE_BYTES", "MAX_JOINTS",
    "MAX_MESSAGE_BYTES", "MESSAGE_TYPES", "PROTOCOL_VERSION", "SERVER_MESSAGES",
    "SUPPORTED_VERSIONS",
    "AvatarBatch", "AvatarFrame", "AvatarInfo", "AvatarRoster", "Calibrate", "ClientMessage",
    "ClockEstimator", "ClockSample", "DeviceRole", "Error", "ErrorCode", "Hello", "Leave",
    "Message", "Ping", "Pong", "ProtocolError", "Redirect", "ServerMessage", "ShownPose",
    "TrackerFrame", "ViewerReport", "Welcome",
    "clock_sample", "decode", "decode_client", "dequantize_rotations", "encode",
    "encode_tracker_frame", "quantize_rotations", "rotation_angle",
]
