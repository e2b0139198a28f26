"""Strict validation: size limits, field types, and the array checks shared by the messages.

The limits bound what one peer can make another allocate or compute. Array checks turn
packed little-endian bytes (or, when a message is built in Python, array-likes) into
read-only float64 numpy arrays and reject NaN, infinities, absurd positions and
non-unit quaternions, naming the row. ``protocol_error`` turns a pydantic
``ValidationError`` into the one ``ProtocolError`` with the field path and the value.
"""

from __future__ import annotations

import math
import re
import reprlib
from collections.abc import Sequence
from typing import Annotated, Any, TypeVar

import numpy as np
from numba import njit, types
from numpy.typing import NDArray
from pydantic import AfterValidator, Field, Strict, ValidationError, ValidationInfo

from posecast.protocol.errors import ErrorCode, ProtocolError
from posecast.protocol.sizes import (
    MAX_AGE_S as MAX_AGE_S,
)
from posecast.protocol.sizes import (
    MAX_AVATARS as MAX_AVATARS,
)
from posecast.protocol.sizes import (
    MAX_CLIENT_MESSAGE_BYTES as MAX_CLIENT_MESSAGE_BYTES,
)
from posecast.protocol.sizes import (
    MAX_INT as MAX_INT,
)
from posecast.protocol.sizes import (
    MAX_JOINTS as MAX_JOINTS,
)
from posecast.protocol.sizes import (  # re-exported: the protocol's limits live there
    MAX_MESSAGE_BYTES as MAX_MESSAGE_BYTES,
)
from posecast.protocol.sizes import (
    MAX_NAME_CHARS as MAX_NAME_CHARS,
)
from posecast.protocol.sizes import (
    MAX_POSITION_M as MAX_POSITION_M,
)
from posecast.protocol.sizes import (
    MAX_RATE_HZ as MAX_RATE_HZ,
)
from posecast.protocol.sizes import (
    MAX_TEXT_CHARS as MAX_TEXT_CHARS,
)
from posecast.protocol.sizes import (
    MAX_TOKEN_CHARS as MAX_TOKEN_CHARS,
)
from posecast.protocol.sizes import (
    QUAT_NORM_TOLERANCE as QUAT_NORM_TOLERANCE,
)
from posecast.protocol.sizes import (
    ROOM_NAME_RULE as ROOM_NAME_RULE,
)

A = TypeVar("A", bound=NDArray[Any])

# --------------------------------------------------------------------------- scalar types
# Strict: msgpack gives real ints, floats and strings; never coerce "12" or True.
# (A strict float still accepts an int: some msgpack encoders write 0.0 as 0.)
Int = Annotated[int, Strict(), Field(ge=0, le=MAX_INT)]
Time = Annotated[float, Strict(), Field(allow_inf_nan=False)]


def _printable(value: str) -> str:
    if not value.isprintable():
        raise ValueError(f"{value!r} contains control characters")
    return value


Name = Annotated[str, Strict(), Field(min_length=1, max_length=MAX_NAME_CHARS),
                 AfterValidator(_printable)]
_ROOM_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")


def check_room_name(value: str) -> str:
    """``value`` if it is a valid room name, else ValueError stating the rule."""
    if not _ROOM_NAME.fullmatch(value):
        raise ValueError(f"{ROOM_NAME_RULE}, got {_short_repr(value)}")
    return value


RoomName = Annotated[str, Strict(), AfterValidator(check_room_name)]
Token = Annotated[str, Strict(), Field(min_length=1, max_length=MAX_TOKEN_CHARS)]
Text = Annotated[str, Strict(), Field(max_length=MAX_TEXT_CHARS)]
RateHz = Annotated[float, Strict(), Field(gt=0.0, le=MAX_RATE_HZ, allow_inf_nan=False)]


# --------------------------------------------------------------------------- arrays
def is_wire(info: ValidationInfo) -> bool:
    """True while the codec validates decoded msgpack (arrays must then be bytes)."""
    return isinstance(info.context, dict) and bool(info.context.get("wire"))


def as_rows(value: Any, width: int, wire: bool, wire_dtype: str = "<f8",
            ) -> NDArray[np.float64]:
    """Packed little-endian bytes, or (in Python) an array-like -> float64 (n, width).

    Only converts and checks the shape: the range checks below also catch NaN and
    infinities (every comparison with NaN is false), so finiteness costs no extra pass.
    """
    if isinstance(value, bytes | bytearray | memoryview):
        row_bytes = np.dtype(wire_dtype).itemsize * width
        if len(value) % row_bytes:
            raise ValueError(f"{len(value)} bytes is not a whole number of rows of "
                             f"{width} x {wire_dtype} ({row_bytes} bytes)")
        array = np.frombuffer(value, dtype=wire_dtype).reshape(-1, width)
        if array.dtype == np.float64:
            return array
        with np.errstate(invalid="ignore"):  # a signalling NaN: refused by the checks next
            return array.astype(np.float64)
    if wire:
        raise ValueError(f"expected packed {wire_dtype} bytes, got {type(value).__name__}")
    if isinstance(value, str):
        raise ValueError(f"expected an array of numbers, got str {value[:40]!r}")
    try:
        array = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"expected an array of numbers: {exc}") from None
    if array.ndim == 1 and array.shape[0] == width:
        array = array.reshape(1, width)
    if array.ndim != 2 or array.shape[1] != width:
        raise ValueError(f"expected shape (n, {width}), got {array.shape}")
    return array


IntArray = NDArray[np.int64]


def int_column(value: Any, wire: bool, wire_dtype: str) -> IntArray:
    """Packed little-endian integers, or (in Python) a 1-D array-like of ints -> an int64
    (n,) array of values in 0..MAX_INT (a new one, or a view of the bytes)."""
    if isinstance(value, bytes | bytearray | memoryview):
        size = np.dtype(wire_dtype).itemsize
        if len(value) % size:
            raise ValueError(f"{len(value)} bytes is not a whole number of {wire_dtype} "
                             f"({size} bytes)")
        column = np.frombuffer(value, dtype=wire_dtype)
        if column.dtype != np.int64:
            column = column.astype(np.int64)
    elif wire:
        raise ValueError(f"expected packed {wire_dtype} bytes, got {type(value).__name__}")
    else:
        array = np.asarray(value)
        if array.ndim != 1 or (array.size and array.dtype.kind not in "iu"):
            raise ValueError(f"expected a 1-D array of integers, got {array.dtype} of "
                             f"shape {array.shape}")
        if array.size and array.max() > MAX_INT:
            raise ValueError(f"integers must be within 0..{MAX_INT}")
        column = array.astype(np.int64)  # a copy
    if column.shape[0] and column.min() < 0:
        row = int(np.flatnonzero(column < 0)[0])
        raise ValueError(f"row {row} is {column[row]}; must be >= 0")
    return column


def time_column(value: Any, wire: bool) -> NDArray[np.float64]:
    """Packed little-endian float64, or (in Python) a 1-D array-like -> a float64 (n,)
    array of finite times, seconds (a new one, or a view of the bytes)."""
    if isinstance(value, bytes | bytearray | memoryview):
        if len(value) % 8:
            raise ValueError(f"{len(value)} bytes is not a whole number of <f8 (8 bytes)")
        column = np.frombuffer(value, dtype="<f8")
    elif wire:
        raise ValueError(f"expected packed <f8 bytes, got {type(value).__name__}")
    else:
        try:
            column = np.array(value, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"expected an array of numbers: {exc}") from None
        if column.ndim != 1:
            raise ValueError(f"expected a 1-D array of times, got shape {column.shape}")
    # one pass: the sum is finite when every time is (unless huge ones overflow it,
    # which the exact check below then clears)
    if not np.isfinite(column.sum()) and not np.isfinite(column).all():
        row = int(np.flatnonzero(~np.isfinite(column))[0])
        raise ValueError(f"row {row} is {float(column[row])!r}: times must be finite")
    return column


_MAX_POSITION2 = MAX_POSITION_M**2
# |norm - 1| <= tol is checked as |norm^2 - 1| <= 2 tol (the same to first order), which
# needs no square root. Below _UNIT_EXACT we do not renormalise: normalising an already
# normalised row can move it by an ulp, and decode(encode(m)) should give m back exactly.
_NORM2_TOL = 2.0 * QUAT_NORM_TOLERANCE
_UNIT_EXACT = 1e-12
# Device poses travel as float32 positions and int16 quaternion components k = round(q
# 32767) (protocol 4): a row is kept as the values it travels as. A unit quaternion's
# components rounded so are off unit by at most ~6.2e-5 in norm^2, so rows within
# _POSE_UNIT_EXACT are not renormalised: decode(encode(m)) gives m exactly
POSE_QUAT_SCALE = 32767.0
_POSE_UNIT_EXACT = 1e-4


def check_positions(positions: NDArray[np.float64], labels: Sequence[str] | None = None,
                    ) -> None:
    """Finite and within MAX_POSITION_M of the origin; the error names the row."""
    dist2 = np.einsum("ij,ij->i", positions, positions)
    if dist2.max(initial=0.0) <= _MAX_POSITION2:  # False for NaN too
        return
    _check_finite(positions, labels, "position")
    row = int(np.flatnonzero(dist2 > _MAX_POSITION2)[0])
    raise ValueError(f"row {row}{_label(labels, row)} position {positions[row].tolist()} is "
                     f"{math.hypot(*positions[row]):.6g} m from the origin; the limit is "
                     f"{MAX_POSITION_M:g} m")


def one_position(value: Any, wire: bool) -> NDArray[np.float64]:
    """A root position: one row of three numbers within MAX_POSITION_M."""
    rows = as_rows(value, 3, wire)
    if rows.shape[0] != 1:
        raise ValueError(f"expected one position (3 numbers), got {rows.shape[0]} rows")
    check_positions(rows)
    return readonly(rows[0])


def unit_quaternions(q: NDArray[np.float64], labels: Sequence[str] | None = None,
                     ) -> NDArray[np.float64]:
    """(n, 4) x y z w within QUAT_NORM_TOLERANCE of unit norm -> normalised."""
    norm2 = np.einsum("ij,ij->i", q, q)
    deviation = np.abs(norm2 - 1.0).max(initial=0.0)
    if not deviation <= _NORM2_TOL:  # NaN lands here too
        _explain_quaternions(q, norm2, labels)
    return q / np.sqrt(norm2)[:, None] if deviation > _UNIT_EXACT else q


def _explain_quaternions(q: NDArray[np.float64], norm2: NDArray[np.float64],
                         labels: Sequence[str] | None) -> None:
    _check_finite(q, labels, "quaternion")
    row = int(np.argmax(np.abs(norm2 - 1.0) > _NORM2_TOL))
    raise ValueError(f"row {row}{_label(labels, row)} quaternion {q[row].tolist()} has "
                     f"norm {np.sqrt(norm2[row]):.6g}; a unit quaternion (x, y, z, w) "
                     f"within {QUAT_NORM_TOLERANCE:g} is required")


_REFUSED, _AS_THEY_ARE, _NORMALISED = -1, 0, 1  # what _rows_check finds


@njit(cache=True)
def _rows_check(poses: NDArray[np.floating]) -> int:
    """The check shared by every pose writer: _REFUSED if a position is beyond
    MAX_POSITION_M or a quaternion off unit by more than the tolerance (NaN fails both);
    _AS_THEY_ARE when every quaternion is unit to _POSE_UNIT_EXACT, else _NORMALISED
    (all rows, so that one frame's rows are coded alike)."""
    worst = 0.0
    for i in range(poses.shape[0]):
        x, y, z = float(poses[i, 0]), float(poses[i, 1]), float(poses[i, 2])
        qx, qy, qz = float(poses[i, 3]), float(poses[i, 4]), float(poses[i, 5])
        qw = float(poses[i, 6])
        deviation = abs(qx * qx + qy * qy + qz * qz + qw * qw - 1.0)
        if not (x * x + y * y + z * z <= _MAX_POSITION2 and deviation <= _NORM2_TOL):
            return _REFUSED
        worst = max(worst, deviation)
    return _NORMALISED if worst > _POSE_UNIT_EXACT else _AS_THEY_ARE


@njit(cache=True)
def _quaternion_scale(poses: NDArray[np.floating], i: int, found: int) -> float:
    """What row i's quaternion is divided by before it is coded (``_rows_check``)."""
    if found != _NORMALISED:
        return 1.0
    return math.sqrt(float(poses[i, 3]) ** 2 + float(poses[i, 4]) ** 2
                     + float(poses[i, 5]) ** 2 + float(poses[i, 6]) ** 2)


@njit(cache=True)
def _quaternion_level(component: float, scale: float) -> float:
    """A quaternion component as its int16 level (k of POSE_QUAT_SCALE), rounded."""
    level = math.floor(component / scale * POSE_QUAT_SCALE + 0.5)
    return min(max(level, -POSE_QUAT_SCALE), POSE_QUAT_SCALE)


@njit(cache=True)
def _checked_rows(poses: NDArray[np.floating], out: NDArray[np.float64]) -> bool:
    """``checked_poses``'s work, for any row type (it may write over ``poses``: a row's
    scale is taken before the row is written, each value read before its own write)."""
    found = _rows_check(poses)
    if found == _REFUSED:
        return False
    for i in range(poses.shape[0]):
        scale = _quaternion_scale(poses, i, found)
        for k in range(3):
            out[i, k] = np.float32(float(poses[i, k]))
        for k in range(3, 7):
            out[i, k] = _quaternion_level(float(poses[i, k]), scale) / POSE_QUAT_SCALE
    return True


# read-only, any layout: writable arrays convert to it, wire buffers are it
# float64 rows (a player's own arrays) or float32 rows, read as they are: a numpy cast
# first cost a copy and, for NaN, a warning to silence (~3 us a frame)
@njit([types.boolean(types.Array(dtype, 2, "A", readonly=True), types.float64[:, ::1])
       for dtype in (types.float64, types.float32)], cache=True)
def checked_poses(poses: NDArray[np.floating], out: NDArray[np.float64]) -> bool:
    """Copy (D, 7) pose rows into ``out`` as they travel (positions float32, quaternion
    components int16 levels k / 32767), normalising the quaternions first (all rows, when
    any is off unit by more than _POSE_UNIT_EXACT), or return False if a position is
    beyond MAX_POSITION_M or a quaternion off unit by more than the tolerance (NaN fails
    both). Compiled: numpy took 6 us for this in small calls, on every tracker frame."""
    return _checked_rows(poses, out)


@njit(types.boolean(types.Array(types.float32, 1, "C", readonly=True),
                    types.Array(types.int16, 1, "C", readonly=True), types.float64[:, ::1]),
      cache=True)
def checked_wire_poses(positions: NDArray[np.float32], levels: NDArray[np.int16],
                       out: NDArray[np.float64]) -> bool:
    """A tracker frame's poses as they travel (positions (3D,) float32, quaternion levels
    (4D,) int16) -> ``out`` (D, 7), checked exactly as ``checked_poses`` checks the same
    numbers: one compiled pass, no array built on the way."""
    rows = out.shape[0]
    if positions.shape[0] != 3 * rows or levels.shape[0] != 4 * rows:
        return False
    for i in range(rows):
        for k in range(3):
            out[i, k] = float(positions[3 * i + k])
        for k in range(4):
            out[i, 3 + k] = float(levels[4 * i + k]) / POSE_QUAT_SCALE
    return _checked_rows(out, out)


@njit([types.boolean(types.Array(types.float64, 2, "A", readonly=True), types.float32[::1],
                     types.int16[::1])], cache=True)
def _checked_wire(poses: NDArray[np.float64], positions: NDArray[np.float32],
                  levels: NDArray[np.int16]) -> bool:
    """``checked_poses``, written straight as the rows travel: positions (3D,) float32,
    then quaternion levels (4D,) int16."""
    found = _rows_check(poses)
    if found == _REFUSED:
        return False
    for i in range(poses.shape[0]):
        scale = _quaternion_scale(poses, i, found)
        for k in range(3):
            positions[3 * i + k] = poses[i, k]
        for k in range(4):
            levels[4 * i + k] = int(_quaternion_level(float(poses[i, 3 + k]), scale))
    return True


def checked_pose_wire(poses: NDArray[np.float64]) -> bytes | None:
    """(D, 7) float64 rows, checked and coded as they travel (``checked_poses``' numbers,
    as ``pose_wire`` lays them out), in one compiled pass; None if ``checked_poses``
    would refuse them. A player's send path: 16 demo players share one core, and every
    call there spreads a tick's frames over more of the server's bursts."""
    n = poses.shape[0]
    out = np.empty(20 * n, dtype=np.uint8)
    if not _checked_wire(poses, out[:12 * n].view(np.float32), out[12 * n:].view(np.int16)):
        return None
    return out.tobytes()


def pose_wire(poses: NDArray[np.float64]) -> bytes:
    """(D, 7) poses as they travel: the positions as float32, then the quaternions' int16
    levels (rounded; clipped, and NaN as 0, for a tool that forges frames)."""
    with np.errstate(invalid="ignore", over="ignore"):
        levels = np.clip(np.nan_to_num(np.rint(np.asarray(poses)[:, 3:] * POSE_QUAT_SCALE)),
                         -32768, 32767).astype("<i2")
        positions = np.ascontiguousarray(poses[:, :3], dtype="<f4")
    return positions.tobytes() + levels.tobytes()


def wire_pose_rows(data: bytes) -> NDArray[np.float64]:
    """``pose_wire``'s bytes -> (D, 7) rows as they travel, unchecked (a tool that forges
    frames changes them and writes them back)."""
    n = len(data) // 20
    rows = np.empty((n, 7))
    rows[:, :3] = np.frombuffer(data, "<f4", 3 * n).reshape(n, 3)
    rows[:, 3:] = np.frombuffer(data, "<i2", 4 * n, 12 * n).reshape(n, 4) / POSE_QUAT_SCALE
    return rows


def device_poses(poses: NDArray[np.floating], labels: Sequence[str] | None = None,
                 ) -> NDArray[np.float64]:
    """(D, 7) position + quaternion rows -> a new array with normalised quaternions, each
    value as it travels (``checked_poses``: float32 positions, int16 quaternion levels).

    The hot path of a server (every tracker frame): both checks in one compiled pass;
    on failure the row-by-row checks explain what was wrong.
    """
    out = np.empty((poses.shape[0], 7))  # new: the wire buffer is read-only, and callers
    if not checked_poses(poses, out):  # keep their arrays
        with np.errstate(invalid="ignore"):  # float32 rows: widened to say what is wrong
            wide = np.asarray(poses, dtype=np.float64)
        check_positions(wide[:, :3], labels)
        q = wide[:, 3:]
        _explain_quaternions(q, np.einsum("ij,ij->i", q, q), labels)
    return out


def _check_finite(array: NDArray[np.float64], labels: Sequence[str] | None, what: str,
                  ) -> None:
    """Raise naming the first NaN or infinity: 'row 2 (left_hand) quaternion[1] is nan'."""
    if np.isfinite(array).all():
        return
    row, col = (int(i) for i in np.argwhere(~np.isfinite(array))[0])
    raise ValueError(f"row {row}{_label(labels, row)} {what}[{col}] is "
                     f"{float(array[row, col])!r}: numbers must be finite")


def _label(labels: Sequence[str] | None, row: int) -> str:
    return f" ({labels[row]})" if labels is not None and row < len(labels) else ""


def readonly(array: A) -> A:
    array.flags.writeable = False
    return array


_RO = {name: types.Array(dtype, 1, "C", readonly=True) for name, dtype in
       (("i8", types.int64), ("u2", types.uint16), ("f8", types.float64),
        ("f4", types.float32))}


@njit(types.boolean(types.int64, types.int64, types.int64, types.float64, types.float64,
                    types.float64, types.float64, types.float64, types.float64), cache=True)
def row_ok(avatar_id: int, seq: int, joints: int, x: float, y: float, z: float,
           capture_age: float, receive_age: float, solved_age: float) -> bool:
    """One AvatarBatch row as a spectator checks it: the one definition of a valid row,
    for the decoder (``batch_columns_ok``) and the server's last look before it sends
    (``sendable_rows``). The root and the times' ages before t_sent are the wire's
    (float32, widened): ids and seqs >= 0, joints in 1..MAX_JOINTS, the root within
    MAX_POSITION_M, the ages within MAX_AGE_S (NaN fails every comparison)."""
    return (avatar_id >= 0 and seq >= 0 and 1 <= joints <= MAX_JOINTS
            and x * x + y * y + z * z <= _MAX_POSITION2
            and abs(capture_age) <= MAX_AGE_S and abs(receive_age) <= MAX_AGE_S
            and abs(solved_age) <= MAX_AGE_S)


@njit(types.boolean(_RO["i8"], _RO["i8"], _RO["u2"], _RO["f4"], _RO["f4"], _RO["u2"],
                    types.int64, types.float64, types.float64[::1], types.int64[::1]),
      cache=True)
def batch_columns(ids: IntArray, seqs: IntArray, counts: NDArray[np.uint16],
                  ages: NDArray[np.float32], roots: NDArray[np.float32],
                  lost: NDArray[np.uint16], lost_limit: int, t_sent: float,
                  wide: NDArray[np.float64], joints: IntArray) -> bool:
    """Every check of an AvatarBatch's packed columns but the rotations
    (``protocol.pose_coding.unpack_batch``), and their conversion, in one compiled pass
    (numpy and Python took ~15 us a batch, which every spectator decodes): ``row_ok`` for
    each row (``ages``: the capture, receive and solved ages one after the other),
    distinct ids, lost bits below ``lost_limit``. Fills ``wide`` (6n) with the roots
    (3n) then t_sent minus each age (3n), and ``joints`` with the counts. Pass/fail only:
    the field validators explain a failure."""
    n = ids.shape[0]
    if ages.shape[0] != 3 * n or roots.shape[0] != 3 * n or lost.shape[0] != n:
        return False
    for b in range(n):
        if not row_ok(ids[b], seqs[b], int(counts[b]), float(roots[3 * b]),
                      float(roots[3 * b + 1]), float(roots[3 * b + 2]), float(ages[b]),
                      float(ages[n + b]), float(ages[2 * n + b])) or lost[b] >= lost_limit:
            return False
        joints[b] = counts[b]
    if n <= 64:  # a room's batch: pairs are quicker than sorting
        for b in range(n):
            for c in range(b):
                if ids[b] == ids[c]:
                    return False
    else:
        ordered = np.sort(ids)
        for b in range(1, n):
            if ordered[b] == ordered[b - 1]:
                return False
    for i in range(3 * n):
        wide[i] = roots[i]
        wide[3 * n + i] = t_sent - float(ages[i])
    return True


@njit(types.int64(types.Array(types.float64, 2, "A", readonly=True),
                  types.Array(types.float64, 3, "A", readonly=True),
                  types.Array(types.float64, 1, "A", readonly=True),
                  types.Array(types.float64, 1, "A", readonly=True), types.float64,
                  types.boolean[::1]), cache=True)
def sendable_rows(roots: NDArray[np.float64], rotations: NDArray[np.float64],
                  t_capture: NDArray[np.float64], t_server_receive: NDArray[np.float64],
                  t_solved: float, out: NDArray[np.bool_]) -> int:
    """Which rows of a solved batch (roots (B, 3), rotations (B, J, 4)) a spectator would
    accept, into ``out``; returns how many it would refuse. ``row_ok`` on the root and
    ages as the wire carries them (float32; ages taken before t_solved, which the batch
    is sent right after), and rotations that pack to what a decoder takes (finite, unit
    within the tolerance). The server's ids and seqs are valid by construction. One
    compiled pass over the batch: no Python per row."""
    bad = 0
    joints = rotations.shape[1]
    for b in range(roots.shape[0]):
        ok = math.isfinite(t_solved) and row_ok(
            0, 0, joints, float(np.float32(roots[b, 0])), float(np.float32(roots[b, 1])),
            float(np.float32(roots[b, 2])), float(np.float32(t_solved - t_capture[b])),
            float(np.float32(t_solved - t_server_receive[b])), 0.0)
        for j in range(joints):
            if not ok:
                break
            q = rotations[b, j]
            ok = abs(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3] - 1.0) \
                <= _NORM2_TOL  # NaN fails too
        out[b] = ok
        bad += not ok
    return bad


# --------------------------------------------------------------------------- errors
_CODES = {code.value for code in ErrorCode}


def protocol_error(error: ValidationError, message_type: str) -> ProtocolError:
    """The first error of a pydantic ValidationError, as 'type.field[i].sub: why (got x)'."""
    details = error.errors(include_url=False)
    first = details[0]
    path = message_type
    for part in first["loc"]:
        path += f"[{part}]" if isinstance(part, int) else f".{field_name(str(part))}"
    why = str(first["msg"]).removeprefix("Value error, ")
    kind = str(first["type"])
    # our own checks put the value in the message; pydantic's own ones get it appended
    if kind not in ("value_error", "missing") and kind not in _CODES:
        why += f" (got {_short_repr(first.get('input'))})"
    if len(details) > 1:
        why += f" [and {len(details) - 1} more error(s)]"
    code = kind if kind in _CODES else ErrorCode.INVALID
    return ProtocolError(code, safe_text(f"{path}: {why}"))


# the longest error text the protocol builds: an Error reply (MAX_TEXT_CHARS) always fits
MAX_ERROR_CHARS = 400
FIELD_NAME_CHARS = 40  # of a client's field name quoted in an error


def safe_text(text: str, limit: int = MAX_ERROR_CHARS) -> str:
    """Client-influenced text for an Error reply or a log line: control characters
    escaped (no forged log lines, no terminal escapes) and cut to ``limit`` characters."""
    if not text.isprintable():
        text = "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def field_name(name: str) -> str:
    """A client's field name in an error: escaped, and a long one as its first
    characters and its length (a 1000-character name must not fill the reply)."""
    shown = safe_text(name, FIELD_NAME_CHARS + 3)
    return shown if len(name) <= FIELD_NAME_CHARS else f"{shown} ({len(name)} chars)"


# depth-bounded: a value nested 1000 deep would exceed the interpreter's recursion limit
_REPR = reprlib.Repr()
_REPR.maxlevel, _REPR.maxstring, _REPR.maxother, _REPR.maxlong = 3, 60, 60, 40


def _short_repr(value: object, limit: int = 80) -> str:
    return safe_text(_REPR.repr(value), limit + 3)
