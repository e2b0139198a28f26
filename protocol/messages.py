"""Every message of a posecast session, as frozen pydantic models.

Client -> server: Hello, TrackerFrame, Calibrate, Ping, Leave, ViewerReport.
Server -> client: Welcome (or Redirect), AvatarRoster (of AvatarInfo), AvatarBatch (of
AvatarFrame), Pong, Error.

Each message has a ``type`` literal that names it on the wire. AvatarInfo is a record
inside a roster; solved poses always travel in an AvatarBatch (of one when alone; see
``protocol/batch.py``), so a viewer has one way to receive them.

Arrays are read-only numpy arrays (float64, and int64 for ids) in Python and packed
little-endian bytes on the wire (``model_dump()`` gives the wire form; ``protocol.codec``
adds msgpack). Times are float seconds. Quaternions are x, y, z, w.

Time of a tracker frame: it carries ``t_capture`` on the *client's* clock plus the
client's current ``clock_offset`` estimate (server = client + offset), rather than one
pre-converted time. The raw capture time is the measurement; the offset is an estimate
that gets refined. Sending both keeps the measurement intact, lets the server check or
log the client's offset (a jump in it shows up), and costs 9 bytes.
``TrackerFrame.t_capture_server`` gives the server-clock time.
"""

from __future__ import annotations

import functools
import math
import reprlib
from typing import Annotated, Any, Literal, NamedTuple

import numpy as np
from numpy.typing import NDArray
from pydantic import (
    AfterValidator,
    Field,
    Strict,
    ValidationInfo,
    field_serializer,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from posecast.protocol.batch import AvatarBatch, AvatarFrame
from posecast.protocol.model import Model, first_duplicate
from posecast.protocol.pose_coding import PoseCoding
from posecast.protocol.roles import CALIBRATION_ROLES, DEVICE_ROLES, DeviceRole
from posecast.protocol.validation import (
    MAX_AVATARS,
    MAX_INT,
    MAX_JOINTS,
    POSE_QUAT_SCALE,
    Int,
    Name,
    RateHz,
    RoomName,
    Text,
    Time,
    Token,
    as_rows,
    check_positions,
    checked_wire_poses,
    device_poses,
    is_wire,
    one_position,
    pose_wire,
    readonly,
    time_column,
    unit_quaternions,
)

# 2: rosters name each avatar's devices, batches say which of them are lost (any
# tracker set); 3: tracker frames and calibrations carry float32 poses and their roles
# as indices into DEVICE_ROLES (745 -> ~340 bytes for 11 devices); 4: a roster gives each
# solved avatar a PoseCoding and its frames carry only its driven joints, packed by
# their limits (protocol.pose_coding), and their times as float32 ages before t_sent
# (319 -> ~115 bytes an avatar-frame). An older peer is refused with a clear error
PROTOCOL_VERSION = 4
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


# --------------------------------------------------------------------------- handshake
class Hello(Model):
    """First message of every connection: who joins which room, as what."""

    type: Literal["hello"] = "hello"
    protocol_version: Version
    # replay: a recording's avatars, published into the room (posecast replay; it sends
    # their rosters and avatar batches, and is admitted with a player's token)
    role: Literal["player", "spectator", "replay"]
    room: RoomName
    display_name: Name
    # the join token (server.auth) where the server has a secret: opaque here
    token: Token | None = None
    # a player coming back: the ``resume`` of its last Welcome gives it the avatar (and
    # calibration) it had, within the server's reconnect grace; anything else, a new one
    resume: Token | None = None
    # a spectator: deliver at most this many batches per second; a player: the rate it
    # sends tracker frames at (the server then takes that plus slack, not its maximum)
    max_rate_hz: RateHz | None = None


class Welcome(Model):
    type: Literal["welcome"] = "welcome"
    protocol_version: Version
    connection_id: Int
    avatar_id: Int | None  # the player's own avatar; None for a spectator
    server_time: Time  # server clock when sent; a first guess before ping/pong
    # a player's: the secret to send as ``hello.resume`` after a drop (random, issued by
    # the server: no client-chosen value reaches an avatar), whether this join got the
    # avatar back (calibrated: no new T-pose), and its name in the room (made unique)
    resume: Token | None = None
    resumed: Annotated[bool, Strict()] = False
    display_name: Name | None = None


# --------------------------------------------------------------------------- skeletons
class AvatarInfo(Model):
    """One avatar's calibrated skeleton: sent when it joins or is recalibrated."""

    avatar_id: Int
    display_name: Name
    joint_names: tuple[Name, ...] = Field(min_length=1, max_length=MAX_JOINTS)
    parents: tuple[Annotated[int, Strict()], ...] = Field(min_length=1, max_length=MAX_JOINTS)
    rest_offsets: Array  # (J, 3) metres from the parent joint, float64 on the wire
    # the devices that drive it (its player's tracker set, grown by devices switched on
    # later); AvatarBatch.lost says which of them are lost now
    devices: tuple[DeviceRole, ...] = Field(default=(), max_length=len(DEVICE_ROLES))
    # how its frames carry its rotations; None (a recording's or a replay's avatar): every
    # joint, 5 bytes each
    coding: PoseCoding | None = None

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
        dup = first_duplicate(self.joint_names)
        if dup is not None:
            raise ValueError(f"joint_names: {dup!r} appears twice")
        dup = first_duplicate(self.devices)
        if dup is not None:
            raise ValueError(f"devices: {dup!r} appears twice")
        if self.coding is not None and self.coding.num_joints != n:
            raise ValueError(f"coding: rest has {self.coding.num_joints} rows for {n} "
                             f"joints")
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


class AvatarRoster(Model):
    """Avatars added or updated (recalibrated), and avatars removed (left)."""

    type: Literal["avatar_roster"] = "avatar_roster"
    avatars: tuple[AvatarInfo, ...] = Field(default=(), max_length=MAX_AVATARS)
    removed: tuple[Int, ...] = Field(default=(), max_length=MAX_AVATARS)

    @model_validator(mode="after")
    def _distinct(self) -> AvatarRoster:
        dup = first_duplicate([a.avatar_id for a in self.avatars] + list(self.removed))
        if dup is not None:
            raise ValueError(f"avatar_id {dup} appears more than once in avatars/removed")
        return self


# --------------------------------------------------------------------------- tracking
class _DevicePoses(Model):
    """Poses of tracked devices: one row per role, position (3) + quaternion x y z w (4).

    On the wire (protocol 4) the roles are indices into DEVICE_ROLES and the poses
    packed little-endian: every position as float32, then every quaternion as int16
    levels k = round(q 32767); in Python the roles are names and the poses float64
    holding those values (``checked_poses``), so a message round-trips exactly.
    """

    roles: tuple[DeviceRole, ...] = Field(min_length=1, max_length=len(DEVICE_ROLES))
    poses: Array  # (D, 7) positions in metres (float32), quaternions (k / 32767)
    t_capture: Time  # client clock, seconds: when the poses were read
    clock_offset: Time  # the client's estimate of server clock - client clock

    @field_validator("roles", mode="before")
    @classmethod
    def _role_indices(cls, value: Any, info: ValidationInfo) -> Any:
        if not is_wire(info):
            return value
        if not isinstance(value, list | tuple):
            raise ValueError(f"expected a list of device indices, got {type(value).__name__}")
        names = []
        for i, index in enumerate(value):
            if type(index) is not int or not 0 <= index < len(DEVICE_ROLES):
                raise ValueError(f"roles[{i}]: {reprlib.repr(index)} is not a device index "
                                 f"(0 to {len(DEVICE_ROLES) - 1}: {', '.join(DEVICE_ROLES)})")
            names.append(DEVICE_ROLES[index])
        return tuple(names)

    @field_validator("roles")
    @classmethod
    def _distinct_roles(cls, roles: tuple[str, ...]) -> tuple[str, ...]:
        dup = first_duplicate(roles)
        if dup is not None:
            raise ValueError(f"device role {dup!r} appears twice")
        return roles

    @field_serializer("roles")
    def _roles_wire(self, roles: tuple[str, ...]) -> list[int]:
        return list(role_indices(roles))

    @field_validator("poses", mode="plain")
    @classmethod
    def _poses(cls, value: Any, info: ValidationInfo) -> Array:
        roles = info.data.get("roles")
        if isinstance(value, bytes | bytearray | memoryview):
            if len(value) % _POSE_ROW_BYTES:
                raise ValueError(f"{len(value)} bytes is not a whole number of poses "
                                 f"({_POSE_ROW_BYTES} bytes each: 3 x <f4, 4 x <i2)")
            n = len(value) // _POSE_ROW_BYTES
            poses: NDArray[np.floating] = np.empty((n, 7))
            with np.errstate(invalid="ignore"):  # a signalling NaN: the checks refuse it
                poses[:, :3] = np.frombuffer(value, "<f4", 3 * n).reshape(n, 3)
            poses[:, 3:] = np.frombuffer(value, "<i2", 4 * n, 12 * n).reshape(n, 4) \
                / POSE_QUAT_SCALE
        elif is_wire(info):
            raise ValueError(f"expected packed poses (3 x <f4, 4 x <i2 each), got "
                             f"{type(value).__name__}")
        else:
            poses = as_rows(value, 7, False)
        if roles is not None and len(roles) != poses.shape[0]:
            raise ValueError(f"{poses.shape[0]} pose rows for {len(roles)} roles")
        return readonly(device_poses(poses, roles))

    @field_serializer("poses")
    def _poses_wire(self, poses: Array) -> bytes:
        return pose_wire(poses)

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


class TrackerPoses(NamedTuple):
    """A tracker frame checked exactly as TrackerFrame checks it, without building the
    model (``tracker_poses_from_wire``): what a server's hot path reads."""

    seq: int
    roles: tuple[str, ...]
    poses: Array  # (D, 7) read-only, quaternions normalised, as TrackerFrame.poses
    t_capture: float
    clock_offset: float

    @property
    def t_capture_server(self) -> float:
        return self.t_capture + self.clock_offset


_TRACKER_FIELDS = frozenset(TrackerFrame.model_fields)
_POSE_ROW_BYTES = 3 * 4 + 4 * 2  # a position's float32, a quaternion's int16 levels
_ROLE_INDEX: dict[str, int] = {role: i for i, role in enumerate(DEVICE_ROLES)}
_INT_ONLY = {int}


@functools.lru_cache(maxsize=256)  # bounded: role tuples come from callers' sources
def role_indices(roles: tuple[str, ...]) -> tuple[int, ...]:
    """Each role's index into DEVICE_ROLES: how a frame's roles travel."""
    return tuple(_ROLE_INDEX[r] for r in roles)


# bounded: the roles come from clients; a player sends the same ones every frame
@functools.lru_cache(maxsize=256)
def _role_names(indices: tuple[int, ...]) -> tuple[str, ...] | None:
    """TrackerFrame's rules for roles: known device indices, distinct, one to
    len(DEVICE_ROLES); their names, or None."""
    if not 1 <= len(indices) <= len(DEVICE_ROLES) or len(set(indices)) != len(indices):
        return None
    if not all(0 <= i < len(DEVICE_ROLES) for i in indices):
        return None
    return tuple(DEVICE_ROLES[i] for i in indices)


def tracker_poses_from_wire(obj: dict[str, Any]) -> TrackerPoses | None:
    """The wire map of a well-formed TrackerFrame checked in one pass, or None when
    anything is unusual; ``TrackerFrame.model_validate`` then says what. It accepts only
    what the model accepts, with the same values: a property test holds the two equal.
    Every frame a server reads comes this way: it costs about half the model's check.
    """
    if obj.keys() != _TRACKER_FIELDS or obj["type"] != "tracker_frame":
        return None
    seq, roles, data = obj["seq"], obj["roles"], obj["poses"]
    t_capture, clock_offset = obj["t_capture"], obj["clock_offset"]
    if (type(seq) is not int or not 0 <= seq <= MAX_INT or type(t_capture) is not float
            or type(clock_offset) is not float or not math.isfinite(t_capture)
            or not math.isfinite(clock_offset) or type(roles) is not list
            or type(data) is not bytes or len(data) != _POSE_ROW_BYTES * len(roles)):
        return None
    # ints only, before the cache: 1.0 and True hash and compare equal to 1
    if set(map(type, roles)) != _INT_ONLY:
        return None
    role_tuple = _role_names(tuple(roles))
    if role_tuple is None:
        return None
    n = len(roles)
    poses = np.empty((n, 7))
    if not checked_wire_poses(np.frombuffer(data, "<f4", 3 * n),
                              np.frombuffer(data, "<i2", 4 * n, 12 * n), poses):
        return None
    return TrackerPoses(seq, role_tuple, readonly(poses), t_capture, clock_offset)


class Calibrate(_DevicePoses):
    """The player stands in a T-pose; the server calibrates the avatar from these poses:
    the head and both hands at least, and every other device the player has."""

    type: Literal["calibrate"] = "calibrate"

    @model_validator(mode="after")
    def _required(self) -> Calibrate:
        missing = [r for r in CALIBRATION_ROLES if r not in self.roles]
        if missing:
            raise ValueError(f"roles: calibration needs {', '.join(CALIBRATION_ROLES)}; "
                             f"missing {', '.join(missing)}")
        return self


# --------------------------------------------------------------------------- viewer reports
# rows of one ViewerReport: 3 x 8 bytes each, so 128 fill 3 KiB, within a client message
MAX_REPORT_ROWS = 128
# a headset frame's poses-to-submit beyond this is no frame a person saw (and no value
# for a histogram of milliseconds)
MAX_POSE_TO_SUBMIT_S = 1.0


# poses a report may carry (ShownPose, ~450 bytes each for 53 joints): with 128 rows, a
# report stays within MAX_CLIENT_MESSAGE_BYTES
MAX_REPORT_POSES = 4


class ShownPose(Model):
    """One avatar as a viewer presented it: the pose its playout gave at ``t_presented``
    (server clock), for the server's display error (``server.display_error``). The
    rotations travel as int16 levels round(q 32767), as a tracker frame's quaternions:
    ~0.003 deg, nothing beside a display error of millimetres."""

    avatar_id: Int
    t_presented: Time
    root: Array  # (3,) metres, float64 on the wire
    rotations: Array  # (J, 4) local joint rotations, x y z w

    @field_validator("root", mode="plain")
    @classmethod
    def _root(cls, value: Any, info: ValidationInfo) -> Array:
        return one_position(value, is_wire(info))

    @field_validator("rotations", mode="plain")
    @classmethod
    def _rotations(cls, value: Any, info: ValidationInfo) -> Array:
        if isinstance(value, bytes | bytearray | memoryview):
            if len(value) % 8:
                raise ValueError(f"{len(value)} bytes is not a whole number of rotations "
                                 "(4 x <i2 each)")
            q = np.frombuffer(value, "<i2").reshape(-1, 4) / POSE_QUAT_SCALE
        elif is_wire(info):
            raise ValueError(f"expected packed rotations (4 x <i2 each), got "
                             f"{type(value).__name__}")
        else:
            q = as_rows(value, 4, False)
        if not 1 <= q.shape[0] <= MAX_JOINTS:
            raise ValueError(f"{q.shape[0]} rotations; 1 to {MAX_JOINTS} allowed")
        return readonly(unit_quaternions(q))

    @field_serializer("root")
    def _root_wire(self, root: Array) -> bytes:
        return np.ascontiguousarray(root, dtype="<f8").tobytes()

    @field_serializer("rotations")
    def _rotations_wire(self, q: Array) -> bytes:
        return np.rint(np.clip(q, -1.0, 1.0) * POSE_QUAT_SCALE).astype("<i2").tobytes()


class ViewerReport(Model):
    """A spectator's own stages of avatar-frames it presented, for the server's metrics.

    One row per avatar-frame, each drawn for the first time: its ``t_capture`` as the
    batch gave it, when the batch reached the viewer's process and when the frame was
    presented, both converted to the server clock with the viewer's current offset (one
    offset for both, so that presented never precedes received). Added in protocol
    version 1: a server that predates it answers ``unknown_type``, and a viewer then
    stops reporting.

    ``pose_to_submit`` (a headset viewer's, ``play --hmd``): seconds from the poses a
    headset frame was drawn with to its submission to the compositor, one per frame, on
    the viewer's own clock (no clock offset in it). A report may carry only these, with
    no avatar-frame rows. A server that predates the field refuses the report (unknown
    field), and the viewer then stops reporting.

    ``shown``: a few avatars as presented (a sample of every avatar at every frame), for
    the server's display error; ``viewer`` and ``mode`` label it in /metrics. A server
    that predates them refuses the report like one that predates pose_to_submit.
    """

    type: Literal["viewer_report"] = "viewer_report"
    t_capture: Array  # (n,) float64 on the wire, 0 <= n <= MAX_REPORT_ROWS
    t_received: Array  # (n,)
    t_presented: Array  # (n,)
    pose_to_submit: Array | None = None  # (m,) seconds, 0 <= each <= MAX_POSE_TO_SUBMIT_S
    shown: tuple[ShownPose, ...] = Field(default=(), max_length=MAX_REPORT_POSES)
    viewer: Literal["browser", "desktop", "headset"] | None = None
    mode: Literal["zero-buffer", "interpolate", "predict"] | None = None

    @field_validator("t_capture", "t_received", "t_presented", mode="plain")
    @classmethod
    def _times(cls, value: Any, info: ValidationInfo) -> Array:
        column = time_column(value, is_wire(info))
        if column.shape[0] > MAX_REPORT_ROWS:
            raise ValueError(f"{column.shape[0]} rows; at most {MAX_REPORT_ROWS} allowed")
        first = info.data.get("t_capture")
        if first is not None and column.shape[0] != first.shape[0]:
            raise ValueError(f"{column.shape[0]} rows for {first.shape[0]} t_capture rows")
        return readonly(column)

    @field_validator("pose_to_submit", mode="plain")
    @classmethod
    def _durations(cls, value: Any, info: ValidationInfo) -> Array | None:
        if value is None:
            return None
        column = time_column(value, is_wire(info))
        if column.shape[0] > MAX_REPORT_ROWS:
            raise ValueError(f"{column.shape[0]} rows; at most {MAX_REPORT_ROWS} allowed")
        off = np.flatnonzero(~((column >= 0.0) & (column <= MAX_POSE_TO_SUBMIT_S)))
        if off.size:
            row = int(off[0])
            raise ValueError(f"row {row}: {float(column[row])!r} s is not within 0 to "
                             f"{MAX_POSE_TO_SUBMIT_S:g} s")
        return readonly(column)

    @field_serializer("t_capture", "t_received", "t_presented")
    def _times_wire(self, times: Array) -> bytes:
        return np.ascontiguousarray(times, dtype="<f8").tobytes()

    @field_serializer("pose_to_submit")
    def _durations_wire(self, times: Array | None) -> bytes | None:
        return None if times is None else np.ascontiguousarray(times, dtype="<f8").tobytes()

    @model_validator(mode="after")
    def _presented_after_received(self) -> ViewerReport:
        if self.t_capture.shape[0] == 0 and not self.shown and (
                self.pose_to_submit is None or self.pose_to_submit.shape[0] == 0):
            raise ValueError("an empty report: at least one row of avatar-frames or of "
                             "pose_to_submit, or a shown pose")
        early = np.flatnonzero(self.t_presented < self.t_received)
        if early.size:
            row = int(early[0])
            raise ValueError(f"row {row}: t_presented {float(self.t_presented[row])!r} is "
                             f"before t_received {float(self.t_received[row])!r}")
        return self

    @property
    def size(self) -> int:
        return int(self.t_capture.shape[0])


# --------------------------------------------------------------------------- clock, errors
class Ping(Model):
    type: Literal["ping"] = "ping"
    t0: Time  # client clock when sent


class Pong(Model):
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


class Error(Model):
    """Why a message was rejected (``code`` from protocol.errors.ErrorCode)."""

    type: Literal["error"] = "error"
    code: Annotated[str, Strict(), Field(min_length=1, max_length=64)]
    message: Text


class Leave(Model):
    type: Literal["leave"] = "leave"
    reason: Text = ""


def _websocket_url(url: str) -> str:
    if not url.startswith(("ws://", "wss://")):
        raise ValueError(f"must be a ws:// or wss:// URL, got {url[:40]!r}")
    return url


class Redirect(Model):
    """Server -> client, in place of a Welcome: the room is served by another process of
    the service (``posecast serve --redis``); join there with the same Hello."""

    type: Literal["redirect"] = "redirect"
    url: Annotated[str, Strict(), Field(min_length=6, max_length=512),
                   AfterValidator(_websocket_url)]


ClientMessage = Hello | TrackerFrame | Calibrate | Ping | Leave | ViewerReport
ServerMessage = Welcome | AvatarRoster | AvatarBatch | Pong | Error | Redirect
Message = ClientMessage | ServerMessage

CLIENT_MESSAGES: tuple[type[Model], ...] = (Hello, TrackerFrame, Calibrate, Ping, Leave,
                                             ViewerReport)
SERVER_MESSAGES: tuple[type[Model], ...] = (Welcome, AvatarRoster, AvatarBatch, Pong, Error,
                                             Redirect)
MESSAGE_TYPES: dict[str, type[Model]] = {
    cls.model_fields["type"].default: cls for cls in CLIENT_MESSAGES + SERVER_MESSAGES}

__all__ = [
    "PROTOCOL_VERSION",
    "SUPPORTED_VERSIONS",
    "AvatarBatch",
    "AvatarFrame",
    "AvatarInfo",
    "AvatarRoster",
    "Calibrate",
    "ClientMessage",
    "Error",
    "Hello",
    "Leave",
    "Message",
    "Ping",
    "Pong",
    "Redirect",
    "ServerMessage",
    "ShownPose",
    "TrackerFrame",
    "ViewerReport",
    "Welcome",
]
