"""Solved poses on their way to viewers: AvatarBatch, a set of columns with one row per
avatar, and AvatarFrame, one avatar's row.

A batch is checked whole: field by field when built in Python or when its wire form is
unusual (each error names the column and the avatar), and in one compiled pass when a
well-formed one arrives (``avatar_batch_from_wire``; a property test holds the two
equal). ``stage_latencies`` is the one definition of the latency stages.
"""

from __future__ import annotations

import math
import re
import struct
from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import (
    Field,
    SerializationInfo,
    ValidationInfo,
    field_validator,
    model_serializer,
    model_validator,
)

from posecast.protocol.model import Model, construct_whole, first_duplicate
from posecast.protocol.pose_coding import Codings, pack_batch, unpack_batch
from posecast.protocol.roles import DEVICE_ROLES, LOST_BITS_LIMIT, roles_of_bits
from posecast.protocol.validation import (
    MAX_AGE_S,
    MAX_AVATARS,
    MAX_JOINTS,
    Int,
    IntArray,
    Time,
    as_rows,
    batch_columns,
    check_positions,
    int_column,
    is_wire,
    one_position,
    readonly,
    time_column,
    unit_quaternions,
)

Array = NDArray[np.float64]


def stage_latencies(t_capture: Any, t_server_receive: Any, t_solved: Any, t_sent: Any,
                    t_received: Any = None, t_presented: Any = None,
                    t_decoded: Any = None) -> dict[str, Any]:
    """Stage durations in seconds, for one frame's times (floats) or a batch's columns
    (arrays, one value per avatar): the one definition of the stages. Pass viewer times
    already on the server clock (received: the bytes reached the viewer's process;
    decoded: the viewer has the poses, checked)."""
    out = {"capture_to_server": t_server_receive - t_capture,
           "solve": t_solved - t_server_receive,
           "server": t_sent - t_server_receive}
    if t_received is not None:
        out["capture_to_spectator"] = t_received - t_capture
        out["network_to_spectator"] = t_received - t_sent
    if t_decoded is not None:
        out["capture_to_decoded"] = t_decoded - t_capture
    if t_presented is not None:
        out["capture_to_presented"] = t_presented - t_capture
        if t_received is not None:
            out["receive_to_presented"] = t_presented - t_received
    return out


class AvatarFrame(Model):
    """One avatar's solved pose and every timestamp of its way, all on the server clock.

    On the wire it travels as a row of an AvatarBatch (``AvatarBatch.frame``). A viewer
    records its own receive and presented times (converted with its clock estimator);
    ``latencies`` gives the stages.
    """

    avatar_id: Int
    seq: Int  # seq of the TrackerFrame this was solved from
    root: Array  # (3,) root joint position, metres
    rotations: Array  # (J, 4) local joint rotations
    t_capture: Time  # TrackerFrame.t_capture_server
    t_server_receive: Time
    t_solved: Time
    t_sent: Time
    lost: int = Field(default=0, ge=0, lt=LOST_BITS_LIMIT)  # AvatarBatch.lost's bits

    @property
    def lost_roles(self) -> tuple[str, ...]:
        """The avatar's devices that this frame lacked (solved from the body model or
        carried on)."""
        return roles_of_bits(self.lost)

    @field_validator("root", mode="plain")
    @classmethod
    def _root(cls, value: Any) -> Array:
        return one_position(value, wire=False)

    @field_validator("rotations", mode="plain")
    @classmethod
    def _rotations(cls, value: Any) -> Array:
        q = as_rows(value, 4, wire=False)
        if not 1 <= q.shape[0] <= MAX_JOINTS:
            raise ValueError(f"{q.shape[0]} joints; 1 to {MAX_JOINTS} allowed")
        return readonly(unit_quaternions(q))

    def latencies(self, t_received: float | None = None,
                  t_presented: float | None = None) -> dict[str, float]:
        """Stage durations in seconds; pass viewer times already on the server clock."""
        return stage_latencies(self.t_capture, self.t_server_receive, self.t_solved,
                               self.t_sent, t_received, t_presented)


class AvatarBatch(Model):
    """Avatar poses solved together and sent together, as columns.

    Row b of every per-avatar column is avatar b; its joint rotations are the next
    ``joint_counts[b]`` rows of ``rotations``. Columns rather than a list of per-avatar
    records: a receiver checks and converts a whole batch in a few numpy calls however
    many avatars it holds (a record cost ~8 us to validate, and a spectator of 16 players
    gets 16 avatars 90 times a second). ``frame(b)`` gives avatar b as an AvatarFrame.
    """

    type: Literal["avatar_batch"] = "avatar_batch"
    avatar_ids: IntArray  # (B,) distinct; int64 on the wire
    seqs: IntArray  # (B,) seq of the TrackerFrame each pose was solved from; int64
    roots: Array  # (B, 3) root joint positions, metres; float32 on the wire
    joint_counts: IntArray  # (B,) joints of each avatar, 1..MAX_JOINTS; uint16
    # (sum of joint_counts, 4) local joint rotations. On the wire each avatar's as its
    # roster's PoseCoding packs them (its driven joints), else 5 bytes a joint: decoding
    # takes the codings (codec.decode's ``codings``)
    rotations: Array
    # (B,) TrackerFrame.t_capture_server of each. On the wire these three are float32
    # ages before t_sent (capture_age, receive_age, solved_age): within ~0.1 us
    t_capture: Array
    t_server_receive: Array  # (B,)
    t_solved: Array  # (B,)
    t_sent: Time  # when the server sent the batch
    # (B,) uint16: which of each avatar's devices its frame lacked, as bits of
    # DEVICE_ROLES (protocol.roles.role_bits); absent (a version-1 recording): none
    lost: IntArray = Field(default=None)  # type: ignore[arg-type]

    @model_validator(mode="before")
    @classmethod
    def _ages(cls, value: Any, info: ValidationInfo) -> Any:
        """The wire's float32 ages before t_sent -> the model's times."""
        if not is_wire(info) or not isinstance(value, dict) or "t_capture" in value:
            return value
        obj = dict(value)
        if "lost" not in obj:  # only protocol 2 and 3 had float64 times and no lost
            raise ValueError("lost: missing")
        t_sent = obj.get("t_sent")
        if type(t_sent) is not float or not math.isfinite(t_sent):
            return obj  # the t_sent field says what is wrong
        for age, name in _AGES.items():
            data = obj.pop(age, None)
            if data is None:
                raise ValueError(f"{age}: missing")
            if not isinstance(data, bytes) or len(data) % 4:
                raise ValueError(f"{age}: expected packed <f4 bytes, got "
                                 f"{type(data).__name__}")
            with np.errstate(invalid="ignore"):  # a signalling NaN: refused just below
                ages = np.frombuffer(data, "<f4").astype(np.float64)
            bad = ~(np.abs(ages) <= MAX_AGE_S)  # NaN too
            if bad.any():
                row = int(np.flatnonzero(bad)[0])
                raise ValueError(f"{age}: row {row} is {float(ages[row])!r}: ages are "
                                 f"within {MAX_AGE_S:g} s")
            obj[name] = (t_sent - ages).tobytes()
        return obj

    @field_validator("avatar_ids", mode="plain")
    @classmethod
    def _ids(cls, value: Any, info: ValidationInfo) -> IntArray:
        ids = int_column(value, is_wire(info), "<i8")
        if ids.shape[0] > MAX_AVATARS:
            raise ValueError(f"{ids.shape[0]} avatars; at most {MAX_AVATARS} per batch")
        if len(set(ids.tolist())) != ids.shape[0]:
            raise ValueError(f"avatar_id {first_duplicate(ids.tolist())} appears more "
                             f"than once")
        return readonly(ids)

    @field_validator("seqs", "t_capture", "t_server_receive", "t_solved", "lost",
                     mode="plain")
    @classmethod
    def _per_avatar(cls, value: Any, info: ValidationInfo) -> Array | IntArray:
        column: NDArray[Any]
        if info.field_name == "seqs":
            column = int_column(value, is_wire(info), "<i8")
        elif info.field_name == "lost":
            column = int_column(value, is_wire(info), "<u2")
            if column.shape[0] and column.max() >= LOST_BITS_LIMIT:
                raise ValueError(f"bits beyond the {len(DEVICE_ROLES)} device roles")
        else:
            column = time_column(value, is_wire(info))
        _same_length(column, info)
        return readonly(column)

    @field_validator("roots", mode="plain")
    @classmethod
    def _roots(cls, value: Any, info: ValidationInfo) -> Array:
        roots = as_rows(value, 3, is_wire(info), wire_dtype="<f4")
        _same_length(roots, info)
        check_positions(roots)
        return readonly(roots)

    @field_validator("joint_counts", mode="plain")
    @classmethod
    def _counts(cls, value: Any, info: ValidationInfo) -> IntArray:
        counts = int_column(value, is_wire(info), "<u2")
        _same_length(counts, info)
        if counts.shape[0] and (counts.min() < 1 or counts.max() > MAX_JOINTS):
            bad = np.flatnonzero((counts < 1) | (counts > MAX_JOINTS))
            raise ValueError(f"avatar {bad[0]} has {counts[bad[0]]} joints; 1 to "
                             f"{MAX_JOINTS} allowed")
        return readonly(counts)

    @field_validator("rotations", mode="plain")
    @classmethod
    def _rotations(cls, value: Any, info: ValidationInfo) -> Array:
        counts = info.data.get("joint_counts")
        try:
            if isinstance(value, bytes | bytearray | memoryview):
                ids = info.data.get("avatar_ids")
                if ids is None or counts is None:
                    raise ValueError("needs valid avatar_ids and joint_counts")
                codings = info.context.get("codings") if isinstance(info.context, dict) \
                    else None
                q = unpack_batch(ids.tolist(), counts.tolist(), bytes(value), codings)
            else:
                q = unit_quaternions(as_rows(value, 4, is_wire(info)))
        except ValueError as exc:  # "joint 106: ..." -> "avatar 2 (joint 0): ..."
            raise ValueError(_name_avatar(str(exc), counts)) from None
        if counts is not None and q.shape[0] != int(counts.sum()):
            raise ValueError(f"{q.shape[0]} rotations for joint_counts summing to "
                             f"{int(counts.sum())}")
        return readonly(q)

    @model_validator(mode="after")
    def _no_losses_said(self) -> AvatarBatch:
        if self.lost is None:  # a version-1 batch: no device lost
            object.__setattr__(self, "lost", readonly(np.zeros(self.size, dtype=np.int64)))
        return self

    @model_serializer(mode="plain")
    def _wire(self, info: SerializationInfo) -> dict[str, Any]:
        """The wire form; ``model_dump(context={"codings": ...})`` packs each avatar's
        rotations as its roster's coding says (none: 5 bytes a joint)."""
        codings = info.context.get("codings") if isinstance(info.context, dict) else None
        ids = self.avatar_ids.tolist()
        ends = np.cumsum(self.joint_counts).tolist()
        parts = [self.rotations[end - n:end]
                 for end, n in zip(ends, self.joint_counts.tolist(), strict=True)]
        return avatar_batch_wire(ids, self.seqs, self.roots, self.joint_counts,
                                 pack_batch(ids, parts, codings), self.t_capture,
                                 self.t_server_receive, self.t_solved, self.t_sent, self.lost)

    @classmethod
    def from_arrays(cls, avatar_ids: Sequence[int], seqs: Sequence[int], roots: ArrayLike,
                    rotations: ArrayLike | Sequence[ArrayLike], t_capture: ArrayLike,
                    t_server_receive: ArrayLike, t_solved: ArrayLike, t_sent: float,
                    lost: ArrayLike | None = None) -> AvatarBatch:
        """A batch from the solver's arrays: ``roots`` (B, 3); ``rotations`` (B, J, 4),
        or a sequence of (J_b, 4) arrays when the skeletons differ; ``t_solved`` one time
        for all or one per avatar; ``lost`` each avatar's lost devices (bits; default
        none). Copies: the solver may reuse its buffers."""
        n = len(avatar_ids)
        if isinstance(rotations, np.ndarray) and rotations.ndim == 3:
            counts = [rotations.shape[1]] * rotations.shape[0]
            flat = rotations.reshape(-1, rotations.shape[2])
        else:
            parts = [np.asarray(r, dtype=np.float64) for r in rotations]  # type: ignore[union-attr]
            counts = [len(p) for p in parts]
            flat = np.concatenate(parts) if parts else np.zeros((0, 4))
        return cls.model_validate({
            "avatar_ids": avatar_ids, "seqs": seqs, "roots": np.reshape(roots, (-1, 3)),
            "joint_counts": counts, "rotations": flat, "t_capture": t_capture,
            "t_server_receive": t_server_receive,
            "t_solved": np.broadcast_to(np.asarray(t_solved, dtype=np.float64), (n,)),
            "t_sent": float(t_sent),
            "lost": np.zeros(n, dtype=np.int64) if lost is None else lost})

    @classmethod
    def from_frames(cls, frames: Sequence[AvatarFrame], t_sent: float) -> AvatarBatch:
        """The frames (each avatar at most once) as one batch sent at ``t_sent``."""
        return cls.from_arrays([f.avatar_id for f in frames], [f.seq for f in frames],
                               np.array([f.root for f in frames]).reshape(-1, 3),
                               [f.rotations for f in frames],
                               [f.t_capture for f in frames],
                               [f.t_server_receive for f in frames],
                               [f.t_solved for f in frames], t_sent,
                               [f.lost for f in frames])

    @property
    def size(self) -> int:
        """The number of avatars."""
        return int(self.avatar_ids.shape[0])

    def frame(self, index: int) -> AvatarFrame:
        """Avatar ``index`` of the batch (its arrays are views of the batch's)."""
        start = int(self.joint_counts[:index].sum())
        return self._frame(index, start)

    @property
    def frames(self) -> tuple[AvatarFrame, ...]:
        starts = np.concatenate(([0], np.cumsum(self.joint_counts)))
        return tuple(self._frame(i, int(starts[i])) for i in range(self.size))

    def _frame(self, i: int, start: int) -> AvatarFrame:
        # the columns were validated as a whole: the frame needs no second check
        return AvatarFrame.model_construct(
            avatar_id=int(self.avatar_ids[i]), seq=int(self.seqs[i]), root=self.roots[i],
            rotations=self.rotations[start:start + int(self.joint_counts[i])],
            t_capture=float(self.t_capture[i]),
            t_server_receive=float(self.t_server_receive[i]),
            t_solved=float(self.t_solved[i]), t_sent=self.t_sent,
            lost=int(self.lost[i]))

    def latencies(self, t_received: float | None = None) -> dict[str, NDArray[np.float64]]:
        """Stage durations of every avatar (arrays, seconds); see ``stage_latencies``."""
        t_sent = np.full(self.size, self.t_sent)  # so that every stage has a row per avatar
        return stage_latencies(self.t_capture, self.t_server_receive, self.t_solved,
                               t_sent, t_received)

    def stamped(self, t_sent: float) -> AvatarBatch:
        """A copy with t_sent set (the server stamps just before sending)."""
        return self.model_copy(update={"t_sent": float(t_sent)})


_AGES = {"capture_age": "t_capture", "receive_age": "t_server_receive",
         "solved_age": "t_solved"}
_BATCH_FIELDS = frozenset(AvatarBatch.model_fields) - set(_AGES.values()) | set(_AGES)
# bytes per avatar of each packed column (rotations: by the codings, checked apart)
_ROW_BYTES = {"avatar_ids": 8, "seqs": 8, "roots": 12, "joint_counts": 2, "capture_age": 4,
              "receive_age": 4, "solved_age": 4, "lost": 2}


def avatar_batch_from_wire(obj: dict[str, Any], codings: Codings | None = None
                           ) -> AvatarBatch | None:
    """The wire form of a well-formed AvatarBatch checked whole, in one compiled pass
    (~2x faster than field-by-field validation: every spectator decodes every batch), or
    None when anything is unusual; ``AvatarBatch.model_validate`` then says what. It
    accepts only what the model's own validation accepts, with the same result: a
    property test holds the two equal.
    """
    if obj.keys() != _BATCH_FIELDS or obj["type"] != "avatar_batch":
        return None
    t_sent = obj["t_sent"]
    if type(t_sent) is not float or not math.isfinite(t_sent):
        return None
    columns = [obj[name] for name in _ROW_BYTES]
    if any(type(c) is not bytes for c in columns) or type(obj["rotations"]) is not bytes:
        return None
    n = len(obj["avatar_ids"]) // 8
    if n > MAX_AVATARS or any(len(c) != n * size
                              for c, size in zip(columns, _ROW_BYTES.values(), strict=True)):
        return None
    ids = np.frombuffer(obj["avatar_ids"], "<i8")
    seqs = np.frombuffer(obj["seqs"], "<i8")
    counts = np.frombuffer(obj["joint_counts"], "<u2")
    ages = np.frombuffer(obj["capture_age"] + obj["receive_age"] + obj["solved_age"], "<f4")
    lost = np.frombuffer(obj["lost"], "<u2")
    wide, joints = np.empty(6 * n), np.empty(n, dtype=np.int64)
    if not batch_columns(ids, seqs, counts, ages, np.frombuffer(obj["roots"], "<f4"), lost,
                         LOST_BITS_LIMIT, t_sent, wide, joints):
        return None
    try:
        rotations = unpack_batch(ids, counts, obj["rotations"], codings)
    except ValueError:
        return None
    wide.flags.writeable = joints.flags.writeable = False  # and so every view of them
    return construct_whole(AvatarBatch, {
        "type": "avatar_batch", "avatar_ids": ids, "seqs": seqs,
        "roots": wide[:3 * n].reshape(n, 3), "joint_counts": joints,
        "rotations": readonly(rotations), "t_capture": wide[3 * n:4 * n],
        "t_server_receive": wide[4 * n:5 * n], "t_solved": wide[5 * n:], "t_sent": t_sent,
        "lost": lost})


def avatar_batch_wire(avatar_ids: ArrayLike, seqs: ArrayLike, roots: ArrayLike,
                      joint_counts: ArrayLike, rotations: bytes, t_capture: ArrayLike,
                      t_server_receive: ArrayLike, t_solved: ArrayLike, t_sent: float,
                      lost: ArrayLike = 0) -> dict[str, Any]:
    """An AvatarBatch's wire map from its columns (for msgpack), its rotations already
    packed (``protocol.pose_coding.pack_batch``), unchecked: the serializer of a
    validated batch, and the server's direct encoder
    (``protocol.codec.encode_avatar_batch``), which checks its solver arrays itself.
    A column is an array, a list (the server's) or a scalar standing for every row."""
    n = len(avatar_ids) if isinstance(avatar_ids, list) else np.shape(avatar_ids)[0]
    return {"type": "avatar_batch", "avatar_ids": _column(avatar_ids, n, "q"),
            "seqs": _column(seqs, n, "q"),
            "roots": np.ascontiguousarray(roots, dtype="<f4").tobytes(),
            "joint_counts": _column(joint_counts, n, "H"), "rotations": rotations,
            "capture_age": _ages(t_capture, t_sent, n),
            "receive_age": _ages(t_server_receive, t_sent, n),
            "solved_age": _ages(t_solved, t_sent, n), "t_sent": float(t_sent),
            "lost": _column(lost, n, "H")}


# the struct codes of the wire's little-endian columns, as numpy names them
_DTYPES = {"q": "<i8", "H": "<u2", "f": "<f4"}


def _column(column: ArrayLike, n: int, code: str) -> bytes:
    """A column's bytes: a list (the server's hot path: a batch's columns are a dozen
    small lists, and struct packs each in a tenth of a numpy round trip) or an array,
    each with the same bytes (float32 rounded to nearest both ways); a scalar for all
    ``n`` rows."""
    try:
        if isinstance(column, list):
            return struct.pack(f"<{len(column)}{code}", *column)
        if isinstance(column, int | float):
            return struct.pack(f"<{n}{code}", *[column] * n)
    except OverflowError:  # a float beyond float32's range: numpy's inf, as the wire's
        pass
    array = np.asarray(column, dtype=_DTYPES[code])
    return (array if array.ndim else np.full(n, array, dtype=_DTYPES[code])).tobytes()


def _ages(column: ArrayLike, t_sent: float, n: int) -> bytes:
    """How long before ``t_sent`` each row's time was, as float32."""
    if isinstance(column, list):
        return _column([t_sent - t for t in column], n, "f")
    if isinstance(column, int | float):
        return _column(t_sent - column, n, "f")
    return _column(t_sent - np.asarray(column, dtype=np.float64), n, "f")


def _same_length(column: NDArray[Any], info: ValidationInfo) -> None:
    ids = info.data.get("avatar_ids")
    if ids is not None and column.shape[0] != ids.shape[0]:
        raise ValueError(f"{column.shape[0]} rows for {ids.shape[0]} avatar_ids")


def _name_avatar(message: str, counts: IntArray | None) -> str:
    """'joint 106: why' or 'row 106 why' (a row of ``rotations``) -> 'avatar 2 (joint 0):
    why', given the avatars' joint counts."""
    found = re.match(r"(?:joint|row) (\d+):? (.*)", message, re.DOTALL)
    if counts is None or found is None:
        return message
    row = int(found.group(1))
    ends = np.cumsum(counts)
    avatar = int(np.searchsorted(ends, row, side="right"))
    if avatar >= counts.shape[0]:
        return message
    first = int(ends[avatar] - counts[avatar])
    return f"avatar {avatar} (joint {row - first}): {found.group(2)}"
