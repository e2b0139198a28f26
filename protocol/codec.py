"""Bytes <-> messages: msgpack maps, float arrays as packed little-endian bin.

A message is a msgpack map of its fields with a string ``type``; nested records (the
avatars of a roster, the frames of a batch) are maps without one. Float arrays are msgpack
bin (tracker poses float32, their roles device indices; skeleton offsets float64; an
avatar's root float32), joint rotations as each avatar's roster coding packs them
(protocol.pose_coding; none: 5 bytes each, protocol.quantize). ``decode``
checks the size before parsing and raises only ``ProtocolError``, whatever the bytes.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence
from typing import Any

import msgpack
import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ValidationError

from posecast.protocol.batch import AvatarBatch, avatar_batch_from_wire, avatar_batch_wire
from posecast.protocol.errors import ErrorCode, ProtocolError
from posecast.protocol.messages import (
    CLIENT_MESSAGES,
    MESSAGE_TYPES,
    ClientMessage,
    Message,
    TrackerFrame,
    TrackerPoses,
    role_indices,
    tracker_poses_from_wire,
)
from posecast.protocol.pose_coding import Codings, RosterCodings, pack_batch
from posecast.protocol.validation import (
    MAX_CLIENT_MESSAGE_BYTES,
    MAX_MESSAGE_BYTES,
    _short_repr,
    checked_pose_wire,
    protocol_error,
    safe_text,
)

_WIRE = {"wire": True}  # validation context: arrays must arrive as bytes
_CLIENT_TYPES = frozenset(cls.model_fields["type"].default for cls in CLIENT_MESSAGES)


def encode(message: BaseModel, codings: Codings | None = None) -> bytes:
    """A message -> msgpack bytes. An AvatarBatch's rotations are packed as ``codings``
    (avatar id -> its roster's PoseCoding) say; without one, 5 bytes a joint."""
    context = {"codings": codings} if codings is not None else None
    return msgpack.packb(message.model_dump(context=context), use_bin_type=True)


def decode(data: bytes | bytearray | memoryview | str, *,
           max_bytes: int = MAX_MESSAGE_BYTES, codings: Codings | None = None) -> Message:
    """msgpack bytes -> a validated message. Raises ProtocolError and nothing else. An
    AvatarBatch is unpacked with ``codings``, the rosters' (``RosterCodings`` keeps them
    for a stream of messages)."""
    return _decode(data, max_bytes, None, codings)  # type: ignore[return-value]


def decode_stream(data: bytes | bytearray | memoryview | str, codings: RosterCodings, *,
                  max_bytes: int = MAX_MESSAGE_BYTES) -> Message:
    """``decode`` one message of a stream (a connection, a recording): its batches
    unpacked with the codings its rosters gave, which it learns from as it goes.

    Streams of one process that get the same bytes under the same codings (spectators
    of one room: the server frames each batch once for all of them) share the decoded
    AvatarBatch, frozen with read-only arrays, instead of decoding it again each. The
    demo's 16 spectators stand for 16 machines, each decoding its own copy at the same
    time; one after the other in one process, a batch's decoding (~45 us) held up
    every spectator after it, as network time."""
    key = None
    if isinstance(data, bytes | bytearray) and len(data) <= max_bytes:
        token = codings.decoding_key()
        if token is not None:
            key = (token, bytes(data))  # websockets hands frames over as bytearrays
            shared = _SHARED_BATCHES.get(key)
            if shared is not None:
                return shared
    message = decode(data, max_bytes=max_bytes, codings=codings)
    codings.learn(message)
    if key is not None and type(message) is AvatarBatch:
        _SHARED_BATCHES[key] = message
        while len(_SHARED_BATCHES) > SHARED_BATCHES_KEPT:
            try:  # the oldest goes; one C call, so a viewer's thread cannot come between
                _SHARED_BATCHES.popitem(last=False)
            except KeyError:
                break
    return message


# the latest batches decode_stream decoded, by (RosterCodings.decoding_key, their bytes):
# enough for a process's rooms, whose spectators all get a batch within milliseconds
SHARED_BATCHES_KEPT = 8
_SHARED_BATCHES: OrderedDict[tuple[int, bytes], AvatarBatch] = OrderedDict()


def decode_client(data: bytes | bytearray | memoryview | str) -> ClientMessage:
    """What a server reads: a client message, at most MAX_CLIENT_MESSAGE_BYTES."""
    return _decode(data, MAX_CLIENT_MESSAGE_BYTES, _CLIENT_TYPES)  # type: ignore[return-value]


def decode_tracker_poses(data: bytes | bytearray | memoryview) -> TrackerPoses | None:
    """A server's hot path: the bytes of a well-formed tracker frame -> its checked
    content (``tracker_poses_from_wire``), or None for anything else (another message,
    anything wrong or unusual); ``decode_client`` then reads it, or says what is wrong.
    """
    if len(data) > MAX_CLIENT_MESSAGE_BYTES:
        return None
    try:
        obj = msgpack.unpackb(data, raw=False, strict_map_key=True)
    except Exception:  # any of msgpack's errors: decode_client names it
        return None
    return tracker_poses_from_wire(obj) if type(obj) is dict else None


def _decode(data: Any, max_bytes: int, allowed: frozenset[str] | None,
            codings: Codings | None = None) -> BaseModel:
    if isinstance(data, str):  # websockets hands a text frame over as str
        raise ProtocolError(ErrorCode.NOT_MSGPACK,
                            "got a text frame; messages are binary msgpack")
    if not isinstance(data, bytes | bytearray | memoryview):
        raise ProtocolError(ErrorCode.NOT_MSGPACK,
                            f"expected bytes, got {type(data).__name__}")
    if len(data) > max_bytes:
        raise ProtocolError(ErrorCode.TOO_LARGE,
                            f"message of {len(data)} bytes; the limit is {max_bytes}")
    try:
        obj = msgpack.unpackb(data, raw=False, strict_map_key=True)
    except Exception as exc:  # msgpack raises several types; any of them means "not msgpack"
        why = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
        raise ProtocolError(ErrorCode.NOT_MSGPACK,
                            safe_text(f"not a msgpack message ({why})")) from None
    if not isinstance(obj, dict) or "type" not in obj:
        got = "a map without 'type'" if isinstance(obj, dict) else type(obj).__name__
        raise ProtocolError(ErrorCode.MALFORMED,
                            f"expected a map with a string 'type', got {got}")
    kind = obj.get("type")
    cls = MESSAGE_TYPES.get(kind) if isinstance(kind, str) else None
    if cls is None or (allowed is not None and kind not in allowed):
        known = sorted(MESSAGE_TYPES if allowed is None else allowed)
        raise ProtocolError(ErrorCode.UNKNOWN_TYPE,
                            f"type: unknown message type {_short(kind)}; expected one of "
                            f"{', '.join(known)}")
    if cls is AvatarBatch:  # the hot path of every viewer: checked whole when well-formed
        batch = avatar_batch_from_wire(obj, codings)
        if batch is not None:
            return batch
    try:
        return cls.model_validate(obj, context=_WIRE if codings is None
                                  else {"wire": True, "codings": codings})
    except ValidationError as exc:
        raise protocol_error(exc, kind) from None  # type: ignore[arg-type]


def _short(value: object) -> str:
    return _short_repr(value, 60)  # depth-bounded and escaped: the value is the client's


def encode_avatar_batch(avatar_ids: Sequence[int], seqs: Sequence[int], roots: NDArray[Any],
                        rotations: NDArray[Any], t_capture: Sequence[float],
                        t_server_receive: Sequence[float], t_solved: float,
                        t_sent: float, lost: Sequence[int] | int = 0,
                        codings: Codings | None = None, rows_checked: bool = False) -> bytes:
    """An AvatarBatch's bytes straight from the solver's arrays (B, 3) and (B, J, 4),
    each avatar's rotations packed as ``codings`` say.

    The server's hot path: the same bytes as ``encode(AvatarBatch.from_arrays(...),
    codings)`` (a test holds them equal) without the checks meant for input from
    outside. The arrays come from the solver: only shapes and finiteness are checked,
    and finiteness not where every row passed ``validation.sendable_rows`` already
    (``rows_checked``: four numpy calls, a tenth of a batch's encoding in place).
    """
    roots = np.asarray(roots, dtype=np.float64)
    rotations = np.asarray(rotations, dtype=np.float64)
    B = len(avatar_ids)
    if roots.shape != (B, 3) or rotations.ndim != 3 or rotations.shape[0] != B \
            or rotations.shape[2] != 4:
        raise ValueError(f"encode_avatar_batch: {B} avatars, roots {roots.shape}, "
                         f"rotations {rotations.shape}")
    if not rows_checked and not (np.isfinite(roots).all() and np.isfinite(rotations).all()):
        raise ValueError("encode_avatar_batch: roots and rotations must be finite")
    wire = avatar_batch_wire(avatar_ids, seqs, roots, rotations.shape[1],
                             pack_batch(list(avatar_ids), rotations, codings),
                             t_capture, t_server_receive, t_solved, t_sent, lost)
    return msgpack.packb(wire, use_bin_type=True)


def encode_tracker_frame(seq: int, roles: Sequence[str], poses: NDArray[Any],
                         t_capture: float, clock_offset: float) -> bytes:
    """A TrackerFrame's bytes straight from a player's arrays: the same bytes as
    ``encode(TrackerFrame(...))`` (a test holds them equal) at a fifth of the cost, for a
    player's send path (its capture-to-send time). The poses get the message's own
    compiled check (and normalisation); poses it refuses go through building the message,
    which names the device and what is wrong. Other mistakes (roles) come back as the
    server's Error.
    """
    poses = np.asarray(poses, dtype=np.float64)
    wire = checked_pose_wire(poses) if poses.shape == (len(roles), 7) else None
    try:
        indices = list(role_indices(tuple(roles)))
    except KeyError:  # an unknown role: the message says which
        wire = None
    if wire is None:
        return encode(TrackerFrame(seq=seq, roles=tuple(roles), poses=poses,  # type: ignore[arg-type]
                                   t_capture=t_capture, clock_offset=clock_offset))
    return msgpack.packb({"roles": indices, "poses": wire,
                          "t_capture": float(t_capture), "clock_offset": float(clock_offset),
                          "type": "tracker_frame", "seq": int(seq)}, use_bin_type=True)
