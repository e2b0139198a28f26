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

__all__ = [
    "BYTES_PER_ROTATION", "CALIBRATION_ROLES", "CLIENT_MESSAGES", "DEVICE_ROLES",
    "MAX_ANGLE_ERROR_DEG", "MAX_CLIENT_MESSAGE_BYTES", "MAX_JOINTS",
    "MAX_MESSAGE_BYTES", "MESSAGE_TYPES", "PROTOCOL_VERSION", "SERVER_MESSAGES",
    "SUPPORTED_VERSIONS",
    "AvatarBatch", "AvatarFrame", "AvatarInfo", "AvatarRoster", "Calibrate", "ClientMessage",
    "ClockEstimator", "ClockSample", "DeviceRole", "Error", "ErrorCode", "Hello", "Leave",
    "Message", "Ping", "Pong", "ProtocolError", "Redirect", "ServerMessage", "TrackerFrame",
    "ViewerReport", "Welcome",
    "clock_sample", "decode", "decode_client", "dequantize_rotations", "encode",
    "encode_tracker_frame", "quantize_rotations", "rotation_angle",
]
