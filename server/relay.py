"""What server processes tell each other through Redis, as bytes (no I/O here).

The owner of a room publishes each encoded batch and roster once, in an envelope that
says who sent it and when (``relay_envelope``); every other process with spectators of
the room unpacks it (``open_envelope``) and hands the owner's bytes to its spectators
unchanged. A process's clock is ``time.perf_counter`` (``server.clock``), which means
nothing on another machine: the envelope carries the sender's wall-minus-monotonic
offset, so a receiver can move the times of a batch onto its own clock
(``clock_shift``); on one machine the shift is ~0 and the bytes go on as they are.

Each player's avatar is also kept in Redis as an ``avatar_record``: its resume secret,
name and T-pose, so that the process that takes a room over calibrates it again
exactly as before (calibration is a pure function of the T-pose).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np

from posecast.protocol import (
    AvatarBatch,
    AvatarInfo,
    AvatarRoster,
    ErrorCode,
    ProtocolError,
    decode,
    encode,
)
from posecast.protocol.pose_coding import Codings
from posecast.server.clock import now

BATCH = "b"
ROSTER = "r"
# clocks closer than this are taken as one (the same machine): no re-encoding
SAME_CLOCK_S = 0.0005


def wall_minus_clock() -> float:
    """This process's offset from its clock to wall time (NTP-synced across machines)."""
    return time.time() - now()


def relay_envelope(kind: str, sender: str, payload: bytes) -> bytes:
    """A batch or roster of the owner, stamped when it is published."""
    return msgpack.packb((kind, sender, now(), wall_minus_clock(), payload),
                         use_bin_type=True)


@dataclass(frozen=True)
class Envelope:
    kind: str
    sender: str
    t_published: float  # on the receiver's clock (shifted)
    shift: float  # add to the sender's times to put them on the receiver's clock
    payload: bytes


def open_envelope(data: bytes) -> Envelope:
    """An envelope from Redis -> its parts, times on this process's clock. ValueError if
    it is not one (a process of another version, or something else on the channel)."""
    try:
        kind, sender, t_published, offset, payload = msgpack.unpackb(data, raw=False)
    except Exception as exc:  # msgpack's several error types, or the wrong shape
        raise ValueError(f"not a relay envelope ({type(exc).__name__})") from None
    if kind not in (BATCH, ROSTER) or not isinstance(payload, bytes) \
            or not isinstance(t_published, float) or not isinstance(offset, float):
        raise ValueError("not a relay envelope (unexpected fields)")
    shift = clock_shift(offset)
    return Envelope(kind, str(sender), t_published + shift, shift, payload)


def clock_shift(sender_offset: float) -> float:
    """Seconds to add to a sender's clock reading to get this process's."""
    shift = sender_offset - wall_minus_clock()
    return 0.0 if abs(shift) < SAME_CLOCK_S else shift


def relayed_batch(envelope: Envelope, codings: Codings) -> tuple[bytes, AvatarBatch]:
    """The batch of an envelope, checked as any viewer checks one (unpacked with the
    room's codings), its times moved onto this process's clock when the owner's is
    another machine's. ProtocolError if bad."""
    batch = decode(envelope.payload, codings=codings)
    if not isinstance(batch, AvatarBatch):
        raise ProtocolError(ErrorCode.INVALID, f"expected an avatar batch, got {batch.type}")
    if envelope.shift == 0.0:
        return envelope.payload, batch
    s = envelope.shift
    frames = batch.frames
    moved = AvatarBatch.from_arrays(
        batch.avatar_ids.tolist(), batch.seqs.tolist(), batch.roots,
        [f.rotations for f in frames], batch.t_capture + s, batch.t_server_receive + s,
        batch.t_solved + s, batch.t_sent + s, batch.lost)
    data = encode(moved, codings)  # and as its spectators read it (float32 ages)
    read = decode(data, codings=codings)
    assert isinstance(read, AvatarBatch)
    return data, read


def relayed_roster(envelope: Envelope) -> AvatarRoster:
    roster = decode(envelope.payload)
    if not isinstance(roster, AvatarRoster):
        raise ProtocolError(ErrorCode.INVALID, f"expected an avatar roster, got {roster.type}")
    return roster


# ------------------------------------------------------------------ avatar records
@dataclass(frozen=True)
class AvatarRecord:
    """A room's avatar as Redis keeps it: enough to bring it back on another process."""

    avatar_id: int
    display_name: str
    resume: str | None  # None: a replay's avatar, which leaves with its connection
    info: AvatarInfo | None  # the calibrated skeleton (what spectators are sent)
    roles: tuple[str, ...] | None = None  # the T-pose it was calibrated from
    poses: np.ndarray | None = None  # (D, 7)

    def pack(self) -> bytes:
        poses = None if self.poses is None else np.ascontiguousarray(
            self.poses, dtype="<f8").tobytes()
        info = None if self.info is None else encode(AvatarRoster(avatars=(self.info,)))
        return msgpack.packb({"id": self.avatar_id, "name": self.display_name,
                              "resume": self.resume, "info": info,
                              "roles": None if self.roles is None else list(self.roles),
                              "poses": poses}, use_bin_type=True)

    @classmethod
    def unpack(cls, data: bytes | str) -> AvatarRecord:
        """ValueError for anything that is not a record this version wrote."""
        try:
            obj: dict[str, Any] = msgpack.unpackb(data, raw=False)
            info = None
            if obj["info"] is not None:
                roster = decode(obj["info"])
                if not isinstance(roster, AvatarRoster) or len(roster.avatars) != 1:
                    raise ValueError("its info is not one avatar")
                info = roster.avatars[0]
            poses = None
            if obj["poses"] is not None:
                poses = np.frombuffer(obj["poses"], dtype="<f8").reshape(-1, 7).copy()
            roles = None if obj["roles"] is None else tuple(str(r) for r in obj["roles"])
            return cls(int(obj["id"]), str(obj["name"]), obj["resume"], info, roles, poses)
        except (KeyError, TypeError, ValueError, ProtocolError, msgpack.UnpackException) as exc:
            raise ValueError(f"not an avatar record ({exc})") from None
