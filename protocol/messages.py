"""Every message of a posecast session, as frozen pydantic models.

Client -> server: Hello, TrackerFrame, Calibrate, Ping, Leave.
Server -> client: Welcome, AvatarRoster (of AvatarInfo), AvatarBatch (of AvatarFrame),
Pong, Error.

Each message has a ``type`` literal that names it on the wire. AvatarInfo and AvatarFrame
are records inside a roster or a batch, not messages: frames always travel in an
AvatarBatch (of one when alone), so a viewer has one way to receive them.

Arrays are read-only float64 numpy arrays in Python and packed little-endian bytes on the
wire (``model_dump()`` gives the wire form; ``protocol.codec`` adds msgpack). Times are
float seconds. Quaternions are x, y, z, w.

Time of a tracker frame: it carries ``t_capture`` on the *client's* clock plus the
client's current ``clock_offset`` estimate (server = client + offset), rather than one
pre-converted time. The raw capture time is the measurement; the offset is an estimate
that gets refined. Sending both keeps the measurement intact, lets the server check or
log the client's offset (a jump in it shows up), and costs 9 bytes.
``TrackerFrame.t_capture_server`` gives the server-clock time.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Annotated, Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    Strict,
    ValidationInfo,
    field_serializer,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from protocol.quantize import BYTES_PER_ROTATION, dequantize_rotations, quantize_rotations
from protocol.roles import CALIBRATION_ROLES, DEVICE_ROLES, DeviceRole
from protocol.validation import (
    MAX_AVATARS,
    MAX_JOINTS,
    Int,
    Name,
    RateHz,
    RoomName,
    Text,
    Time,
    Token,
    as_rows,
    check_positions,
    device_poses,
    is_wire,
    readonly,
    unit_quaternions,
)

PROTOCOL_VERSION = 1
SUPPORTED_VERSIONS = frozenset({PROTOCOL_VERSION})

Array = NDArray[np.float64]


def _check_version(version: int) -> int:
    if version not in SUPPORTED_VERSIONS:
        raise PydanticCustomError(
            "unsupported_version",
            "protocol version {got} is not supported; this side speaks {ours}",
            {"got": version, "ours": sorted(SUPPORTED_VERSIONS)})
    return version


Version = Annotated[int, Strict(), AfterValidator(_check_version)]


def _first_duplicate(items: tuple[Any, ...] | list[Any]) -> Any:
    """The first item that appears a second time, or None."""
    if len(set(items)) == len(items):  # the common case, in one C call
        return None
    seen: set[Any] = set()
    for item in items:
        if item in seen:
            return item
        seen.add(item)
    return None


class _Model(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid", arbitrary_types_allowed=True)

    def __eq__(self, other: object) -> bool:
        # pydantic's own __eq__ would ask numpy for the truth value of an array
        if type(other) is not type(self):
            return NotImplemented
        return all(_same(getattr(self, name), getattr(other, name))
                   for name in type(self).model_fields)

    __hash__ = None  # type: ignore[assignment]  # arrays are unhashable anyway


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return bool(np.array_equal(a, b))
    return bool(a == b)


# --------------------------------------------------------------------------- handshake
class Hello(_Model):
    """First message of every connection: who joins which room, as what."""

    type: Literal["hello"] = "hello"
    protocol_version: Version
    role: Literal["player", "spectator"]
    room: RoomName
    display_name: Name
    # opaque to the protocol; the server may use it to authenticate, and to give a player
    # who reconnects the avatar they had
    token: Token | None = None
    # spectators only: deliver at most this many batches per second
    max_rate_hz: RateHz | None = None

    @model_validator(mode="after")
    def _rate_for_spectators(self) -> Hello:
        if self.role == "player" and self.max_rate_hz is not None:
            raise ValueError(f"max_rate_hz: only a spectator may ask for a rate "
                             f"(got {self.max_rate_hz!r} from a player)")
        return self


class Welcome(_Model):
    type: Literal["welcome"] = "welcome"
    protocol_version: Version
    connection_id: Int
    avatar_id: Int | None  # the player's own avatar; None for a spectator
    server_time: Time  # server clock when sent; a first guess before ping/pong


# --------------------------------------------------------------------------- skeletons
class AvatarInfo(_Model):
    """One avatar's calibrated skeleton: sent when it joins or is recalibrated."""

    avatar_id: Int
    display_name: Name
    joint_names: tuple[Name, ...] = Field(min_length=1, max_length=MAX_JOINTS)
    parents: tuple[Annotated[int, Strict()], ...] = Field(min_length=1, max_length=MAX_JOINTS)
    rest_offsets: Array  # (J, 3) metres from the parent joint, float64 on the wire

    @field_validator("rest_offsets", mode="plain")
    @classmethod
    def _offsets(cls, value: Any, info: ValidationInfo) -> Array:
        offsets = as_rows(value, 3, is_wire(info))
        check_positions(offsets, info.data.get("joint_names"))
        return readonly(offsets)

    @field_serializer("rest_offsets")
    def _offsets_wire(self, offsets: Array) -> bytes:
        return np.ascontiguousarray(offsets, dtype="<f8").tobytes()

    @model_validator(mode="after")
    def _skeleton(self) -> AvatarInfo:
        n = len(self.joint_names)
        if len(self.parents) != n or self.rest_offsets.shape[0] != n:
            raise ValueError(f"{n} joint_names but {len(self.parents)} parents and "
                             f"{self.rest_offsets.shape[0]} rest_offsets rows")
        dup = _first_duplicate(self.joint_names)
        if dup is not None:
            raise ValueError(f"joint_names: {dup!r} appears twice")
        # parents first, one root: the order forward kinematics walks (solver.Skeleton)
        if self.parents[0] != -1:
            raise ValueError(f"parents[0] is {self.parents[0]}: joint 0 must be the root (-1)")
        for j, p in enumerate(self.parents[1:], start=1):
            if not 0 <= p < j:
                raise ValueError(f"parents[{j}] is {p}: must be a joint before {j} "
                                 f"(0..{j - 1})")
        return self

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)


class AvatarRoster(_Model):
    """Avatars added or updated (recalibrated), and avatars removed (left)."""

    type: Literal["avatar_roster"] = "avatar_roster"
    avatars: tuple[AvatarInfo, ...] = Field(default=(), max_length=MAX_AVATARS)
    removed: tuple[Int, ...] = Field(default=(), max_length=MAX_AVATARS)

    @model_validator(mode="after")
    def _distinct(self) -> AvatarRoster:
        dup = _first_duplicate([a.avatar_id for a in self.avatars] + list(self.removed))
        if dup is not None:
            raise ValueError(f"avatar_id {dup} appears more than once in avatars/removed")
        return self


# --------------------------------------------------------------------------- tracking
class _DevicePoses(_Model):
    """Poses of tracked devices: one row per role, position (3) + quaternion x y z w (4)."""

    roles: tuple[DeviceRole, ...] = Field(min_length=1, max_length=len(DEVICE_ROLES))
    poses: Array  # (D, 7) float64; positions in metres, quaternions normalised
    t_capture: Time  # client clock, seconds: when the poses were read
    clock_offset: Time  # the client's estimate of server clock - client clock

    @field_validator("roles")
    @classmethod
    def _distinct_roles(cls, roles: tuple[str, ...]) -> tuple[str, ...]:
        dup = _first_duplicate(roles)
        if dup is not None:
            raise ValueError(f"device role {dup!r} appears twice")
        return roles

    @field_validator("poses", mode="plain")
    @classmethod
    def _poses(cls, value: Any, info: ValidationInfo) -> Array:
        roles = info.data.get("roles")
        poses = as_rows(value, 7, is_wire(info))
        if roles is not None and len(roles) != poses.shape[0]:
            raise ValueError(f"{poses.shape[0]} pose rows for {len(roles)} roles")
        return readonly(device_poses(poses, roles))

    @field_serializer("poses")
    def _poses_wire(self, poses: Array) -> bytes:
        return np.ascontiguousarray(poses, dtype="<f8").tobytes()

    @property
    def t_capture_server(self) -> float:
        return self.t_capture + self.clock_offset

    @property
    def positions(self) -> Array:
        return self.poses[:, :3]

    @property
    def rotations(self) -> Array:
        return self.poses[:, 3:]

    def pose(self, role: str) -> Array | None:
        """The (7,) pose of one device, or None when this frame lacks it."""
        return self.poses[self.roles.index(role)] if role in self.roles else None


class TrackerFrame(_DevicePoses):
    """A player's device poses at one instant."""

    type: Literal["tracker_frame"] = "tracker_frame"
    seq: Int  # per connection, increasing; echoed in the AvatarFrame solved from it


class Calibrate(_DevicePoses):
    """The player stands in a T-pose; the server calibrates the avatar from these poses."""

    type: Literal["calibrate"] = "calibrate"

    @model_validator(mode="after")
    def _required(self) -> Calibrate:
        missing = [r for r in CALIBRATION_ROLES if r not in self.roles]
        if missing:
            raise ValueError(f"roles: calibration needs {', '.join(CALIBRATION_ROLES)}; "
                             f"missing {', '.join(missing)}")
        return self


# --------------------------------------------------------------------------- solved poses
# the order of an AvatarFrame's fields on the wire: inside a batch a frame is an array,
# not a map, since the field names would be ~18% of its bytes
FRAME_FIELDS = ("avatar_id", "seq", "root", "rotations", "t_capture", "t_server_receive",
                "t_solved", "t_sent")


class AvatarFrame(_Model):
    """One avatar's solved pose and every timestamp of its way, all on the server clock.

    A viewer records its own receive and presented times (converted with its clock
    estimator); ``latencies`` gives the stages.
    """

    avatar_id: Int
    seq: Int  # seq of the TrackerFrame this was solved from
    root: Array  # (3,) root joint position, metres; float32 on the wire
    rotations: Array  # (J, 4) local joint rotations; 5 bytes each on the wire (quantize.py)
    t_capture: Time  # TrackerFrame.t_capture_server
    t_server_receive: Time
    t_solved: Time
    t_sent: Time

    @field_validator("root", mode="plain")
    @classmethod
    def _root(cls, value: Any, info: ValidationInfo) -> Array:
        if isinstance(value, _Prechecked):
            return value.array
        rows = as_rows(value, 3, is_wire(info), wire_dtype="<f4")
        if rows.shape[0] != 1:
            raise ValueError(f"expected one position (3 numbers), got {rows.shape[0]} rows")
        check_positions(rows)
        return readonly(rows[0])

    @field_validator("rotations", mode="plain")
    @classmethod
    def _rotations(cls, value: Any, info: ValidationInfo) -> Array:
        if isinstance(value, _Prechecked):
            return value.array
        if isinstance(value, bytes | bytearray | memoryview):
            if not 0 < len(value) <= MAX_JOINTS * BYTES_PER_ROTATION:
                raise ValueError(f"{len(value)} bytes: 1 to {MAX_JOINTS} joints of "
                                 f"{BYTES_PER_ROTATION} bytes expected")
            return readonly(dequantize_rotations(bytes(value)))
        q = as_rows(value, 4, is_wire(info))
        if not 1 <= q.shape[0] <= MAX_JOINTS:
            raise ValueError(f"{q.shape[0]} joints; 1 to {MAX_JOINTS} allowed")
        return readonly(unit_quaternions(q))

    def latencies(self, t_received: float | None = None,
                  t_presented: float | None = None) -> dict[str, float]:
        """Stage durations in seconds; pass viewer times already on the server clock."""
        out = {"capture_to_server": self.t_server_receive - self.t_capture,
               "solve": self.t_solved - self.t_server_receive,
               "server": self.t_sent - self.t_server_receive}
        if t_received is not None:
            out["capture_to_spectator"] = t_received - self.t_capture
            out["network_to_spectator"] = t_received - self.t_sent
        if t_presented is not None:
            out["capture_to_presented"] = t_presented - self.t_capture
            if t_received is not None:
                out["receive_to_presented"] = t_presented - t_received
        return out


class _Prechecked:
    """An array AvatarBatch has already validated, for the whole batch in one pass."""

    __slots__ = ("array",)

    def __init__(self, array: Array) -> None:
        self.array = array


class AvatarBatch(_Model):
    """Avatar frames solved together, sent together."""

    type: Literal["avatar_batch"] = "avatar_batch"
    frames: tuple[AvatarFrame, ...] = Field(max_length=MAX_AVATARS)

    @model_validator(mode="before")
    @classmethod
    def _from_wire(cls, data: Any, info: ValidationInfo) -> Any:
        frames = data.get("frames") if isinstance(data, dict) else None
        if not is_wire(info) or not isinstance(frames, list | tuple):
            return data
        for i, f in enumerate(frames):
            if not isinstance(f, list | tuple) or len(f) != len(FRAME_FIELDS):
                got = f"{len(f)} items" if isinstance(f, list | tuple) else type(f).__name__
                raise ValueError(f"frames[{i}]: expected an array of the {len(FRAME_FIELDS)} "
                                 f"fields {', '.join(FRAME_FIELDS)}; got {got}")
        return {**data, "frames": _decode_together(frames)}

    @classmethod
    def from_arrays(cls, avatar_ids: Sequence[int], seqs: Sequence[int], roots: ArrayLike,
                    rotations: ArrayLike | Sequence[ArrayLike], t_capture: Sequence[float],
                    t_server_receive: Sequence[float], t_solved: float, t_sent: float,
                    ) -> AvatarBatch:
        """A batch straight from the solver's arrays, checked in one pass per array.

        ``roots`` (B, 3); ``rotations`` (B, J, 4), or a sequence of (J_i, 4) arrays when
        the avatars' skeletons differ. Same checks as building each AvatarFrame, faster.
        """
        n = len(avatar_ids)
        root_rows = as_rows(roots, 3, wire=False)
        if isinstance(rotations, np.ndarray) and rotations.ndim == 3:
            if rotations.shape[2] != 4:
                raise ValueError(f"from_arrays: rotations of shape {rotations.shape}; "
                                 f"(B, J, 4) expected")
            counts = [rotations.shape[1]] * rotations.shape[0]
            # a copy: the frames must not change when the solver reuses its buffers
            flat = np.array(rotations, dtype=np.float64).reshape(-1, 4)
        else:
            parts = [as_rows(r, 4, wire=False) for r in rotations]  # type: ignore[union-attr]
            counts = [len(p) for p in parts]
            flat = np.concatenate(parts) if parts else np.zeros((0, 4))
        if not (len(seqs) == len(t_capture) == len(t_server_receive) == len(root_rows)
                == len(counts) == n):
            raise ValueError(f"from_arrays: {n} avatar_ids but {len(seqs)} seqs, "
                             f"{len(root_rows)} roots, {len(counts)} rotation sets, "
                             f"{len(t_capture)} t_capture, {len(t_server_receive)} "
                             f"t_server_receive")
        if any(not 1 <= c <= MAX_JOINTS for c in counts):
            raise ValueError(f"from_arrays: joint counts {counts}; 1 to {MAX_JOINTS} allowed")
        check_positions(root_rows)
        unit = readonly(unit_quaternions(flat))
        rows = [{"avatar_id": int(avatar_ids[i]), "seq": int(seqs[i]),
                 "t_capture": float(t_capture[i]),
                 "t_server_receive": float(t_server_receive[i]),
                 "t_solved": float(t_solved), "t_sent": float(t_sent)} for i in range(n)]
        _set_prechecked(rows, readonly(root_rows), unit, counts)
        return cls(frames=tuple(rows))  # type: ignore[arg-type]

    @model_validator(mode="after")
    def _distinct(self) -> AvatarBatch:
        dup = _first_duplicate([f.avatar_id for f in self.frames])
        if dup is not None:
            raise ValueError(f"frames: avatar_id {dup} appears more than once")
        return self

    @field_serializer("frames")
    def _frames_wire(self, frames: tuple[AvatarFrame, ...]) -> list[list[Any]]:
        # quantize every rotation and convert every root in one call each, then cut the
        # bytes per avatar
        if not frames:
            return []
        packed = quantize_rotations(np.concatenate([f.rotations for f in frames]))
        roots = np.array([f.root for f in frames], dtype="<f4").tobytes()
        out, start = [], 0
        for i, f in enumerate(frames):
            end = start + BYTES_PER_ROTATION * f.rotations.shape[0]
            out.append([f.avatar_id, f.seq, roots[12 * i:12 * i + 12], packed[start:end],
                        f.t_capture, f.t_server_receive, f.t_solved, f.t_sent])
            start = end
        return out

    def stamped(self, t_sent: float) -> AvatarBatch:
        """A copy with every frame's t_sent set (the server stamps just before sending)."""
        return self.model_copy(update={"frames": tuple(
            f.model_copy(update={"t_sent": float(t_sent)}) for f in self.frames)})


def _decode_together(frames: Sequence[Sequence[Any]]) -> list[dict[str, Any]]:
    """Wire frames (arrays in FRAME_FIELDS order) -> dicts for per-frame validation.

    Checks every root and dequantizes every rotation of the batch in one call each, not
    one per avatar. Only the clean case is handled so; otherwise the raw fields go on to
    per-frame validation, which reports the problem with its frame index.
    """
    dicts = [dict(zip(FRAME_FIELDS, f, strict=True)) for f in frames]
    roots = [f[2] for f in frames]
    rotations = [f[3] for f in frames]
    if not frames or not all(isinstance(r, bytes) and len(r) == 12 for r in roots) or not all(
            isinstance(r, bytes) and 0 < len(r) <= MAX_JOINTS * BYTES_PER_ROTATION
            and len(r) % BYTES_PER_ROTATION == 0 for r in rotations):
        return dicts
    root_rows = np.frombuffer(b"".join(roots), "<f4").reshape(-1, 3)
    try:
        check_positions(root_rows)
        every = dequantize_rotations(b"".join(rotations))
    except ValueError:
        return dicts
    _set_prechecked(dicts, readonly(root_rows.astype(np.float64)), readonly(every),
                    [len(r) // BYTES_PER_ROTATION for r in rotations])
    return dicts


def _set_prechecked(frames: Sequence[dict[str, Any]], roots: Array, rotations: Array,
                    counts: Sequence[int]) -> None:
    """Give each frame dict its root and rotation rows, sliced from whole-batch arrays."""
    start = 0
    for i, (f, n) in enumerate(zip(frames, counts, strict=True)):
        f["root"] = _Prechecked(roots[i])
        f["rotations"] = _Prechecked(rotations[start:start + n])
        start += n


# --------------------------------------------------------------------------- clock, errors
class Ping(_Model):
    type: Literal["ping"] = "ping"
    t0: Time  # client clock when sent


class Pong(_Model):
    type: Literal["pong"] = "pong"
    t0: Time  # echoed from the Ping
    t1: Time  # server clock when the Ping arrived
    t2: Time  # server clock when this Pong left

    @model_validator(mode="after")
    def _order(self) -> Pong:
        if self.t2 < self.t1:
            raise ValueError(f"t2 {self.t2!r} is before t1 {self.t1!r}: the server cannot "
                             f"send before it receives")
        return self


class Error(_Model):
    """Why a message was rejected (``code`` from protocol.errors.ErrorCode)."""

    type: Literal["error"] = "error"
    code: Annotated[str, Strict(), Field(min_length=1, max_length=64)]
    message: Text


class Leave(_Model):
    type: Literal["leave"] = "leave"
    reason: Text = ""


ClientMessage = Hello | TrackerFrame | Calibrate | Ping | Leave
ServerMessage = Welcome | AvatarRoster | AvatarBatch | Pong | Error
Message = ClientMessage | ServerMessage

CLIENT_MESSAGES: tuple[type[_Model], ...] = (Hello, TrackerFrame, Calibrate, Ping, Leave)
SERVER_MESSAGES: tuple[type[_Model], ...] = (Welcome, AvatarRoster, AvatarBatch, Pong, Error)
MESSAGE_TYPES: dict[str, type[_Model]] = {
    cls.model_fields["type"].default: cls for cls in CLIENT_MESSAGES + SERVER_MESSAGES}

__all__ = ["PROTOCOL_VERSION", "SUPPORTED_VERSIONS", "AvatarBatch", "AvatarFrame",
           "AvatarInfo", "AvatarRoster", "Calibrate", "ClientMessage", "Error", "Hello",
           "Leave", "Message", "Ping", "Pong", "ServerMessage", "TrackerFrame", "Welcome"]
