"""An avatar's joint rotations in as few bits as its joints' limits allow (protocol 4).

The roster gives each solved avatar a PoseCoding: which joints its frames carry (the
*driven* ones: the solver never turns the others, whose rotations the roster carries
once, in ``rest``) and how each is packed, in one bit stream per avatar padded to a byte:

- ``bits == (0, 0, 0)``: a quaternion, smallest three, 38 bits (``protocol.quantize``);
- else the joint's deviation from its canonical pose in its limit frame, the solver's
  own parameters (``solver.rig``): q = pre D post, D = swing(x, 0, z) twist_y(t). Each
  parameter with bits (x, twist y, z; 0: fixed at 0) is sent as a level k of its limit
  range, p = lo + k (hi - lo) / (2^bits - 1).

Error bound of a parameter-coded joint: pre and post are exact and rotations compose
isometrically, so the angle between q and its decoding is that between D and D'. The
exponential map is 1-Lipschitz from rotation vectors to angles and each parameter is off
by at most half its step, so angle <= |(dx, dz)| + |dt| <= s/2 (sqrt(#swing) + #twist),
with s a joint's largest step. ``coding_steps`` picks the bits so that this stays within
the quaternion's own bound (MAX_ANGLE_ERROR_RAD, 0.0686 degree); a joint whose swing
limits reach pi (a rotation vector there has two names) or that would need more bits
than a quaternion stays a quaternion. A MakeHuman avatar's 20 driven joints take 566
bits (71 bytes) instead of 53 x 5 bytes.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from numba import njit, types
from numpy.typing import NDArray
from pydantic import ValidationInfo, field_serializer, field_validator, model_validator

from posecast.protocol.model import Model
from posecast.protocol.quantize import (
    BYTES_PER_ROTATION,
    MAX_ANGLE_ERROR_RAD,
    dequantize_rotations,
    quantize_rotations,
    quat_word,
    word_quat,
)
from posecast.protocol.validation import MAX_JOINTS, as_rows, is_wire, readonly, unit_quaternions

Array = NDArray[np.float64]
QUATERNION_BITS = 38
MAX_PARAMETER_BITS = 16


def coding_bits(lo: Array, hi: Array, target_rad: float = MAX_ANGLE_ERROR_RAD
                ) -> tuple[int, int, int]:
    """A joint's bits per parameter (x, twist, z; 0: not sent) from its limits (radians,
    ``solver.rig`` order), or (0, 0, 0): a quaternion. See the module's bound."""
    present = [bool(h > low) for low, h in zip(lo, hi, strict=True)]
    if not any(present):
        return 0, 0, 0
    swing_reach = math.hypot(*(max(abs(lo[i]), abs(hi[i])) if present[i] else 0.0
                               for i in (0, 2)))
    if swing_reach >= math.pi or (present[1] and hi[1] - lo[1] > 2.0 * math.pi):
        return 0, 0, 0
    factor = math.sqrt(present[0] + present[2]) + present[1]
    step = 2.0 * target_rad / factor  # every parameter's step at most this
    bits = tuple(math.ceil(math.log2((hi[i] - lo[i]) / step + 1.0)) if present[i] else 0
                 for i in range(3))
    if max(bits) > MAX_PARAMETER_BITS or sum(bits) >= QUATERNION_BITS:
        return 0, 0, 0
    return bits  # type: ignore[return-value]


class PoseCoding(Model):
    """How one avatar's frames carry its rotations; see the module docstring."""

    driven: tuple[int, ...]  # (K,) joints each frame carries, ascending
    # (K,) bits of x, twist, z (0: absent); all three 0: a quaternion (38 bits)
    bits: tuple[tuple[int, int, int], ...]
    # (K, 3) limits of x, twist, z, radians; (K, 4) q = pre D post. float32 on the wire,
    # and held as that float32 here: sender and receiver pack with the same numbers
    lo: Array
    hi: Array
    pre: Array
    post: Array
    rest: Array  # (J, 4) every joint's rotation; the frames replace the driven ones

    @field_validator("lo", "hi", mode="plain")
    @classmethod
    def _limits(cls, value: Any, info: ValidationInfo) -> Array:
        rows = as_rows(value, 3, is_wire(info), wire_dtype="<f4")
        if not np.all(np.abs(rows) <= 2.0 * math.pi):  # NaN fails too
            raise ValueError("limits must be finite radians within +-2 pi")
        return readonly(rows.astype(np.float32).astype(np.float64))

    @field_validator("pre", "post", mode="plain")
    @classmethod
    def _frames(cls, value: Any, info: ValidationInfo) -> Array:
        q = unit_quaternions(as_rows(value, 4, is_wire(info), wire_dtype="<f4"))
        return readonly(q.astype(np.float32).astype(np.float64))

    @field_validator("rest", mode="plain")
    @classmethod
    def _rest(cls, value: Any, info: ValidationInfo) -> Array:
        if isinstance(value, bytes | bytearray | memoryview):
            return readonly(dequantize_rotations(value))
        if is_wire(info):
            raise ValueError(f"expected packed rotations, got {type(value).__name__}")
        # held as the wire carries it (5 bytes a joint): a decoded roster equals its model
        q = unit_quaternions(as_rows(value, 4, False))
        return readonly(dequantize_rotations(quantize_rotations(q)))

    @field_serializer("lo", "hi", "pre", "post")
    def _f4_wire(self, rows: Array) -> bytes:
        return np.ascontiguousarray(rows, dtype="<f4").tobytes()

    @field_serializer("rest")
    def _rest_wire(self, rows: Array) -> bytes:
        return quantize_rotations(rows)

    @model_validator(mode="after")
    def _consistent(self) -> PoseCoding:
        K, J = len(self.driven), self.rest.shape[0]
        if not 1 <= J <= MAX_JOINTS:
            raise ValueError(f"rest: {J} joints; 1 to {MAX_JOINTS} allowed")
        if not 1 <= K <= J or any(not 0 <= j < J for j in self.driven) \
                or any(b <= a for a, b in zip(self.driven, self.driven[1:], strict=False)):
            raise ValueError(f"driven: expected 1 to {J} ascending joints below {J}")
        shapes = (len(self.bits), self.lo.shape[0], self.hi.shape[0], self.pre.shape[0],
                  self.post.shape[0])
        if any(n != K for n in shapes):
            raise ValueError(f"bits, lo, hi, pre and post need a row per driven joint ({K})")
        for k, bits in enumerate(self.bits):
            ok = all(0 <= b <= MAX_PARAMETER_BITS for b in bits) and all(
                self.lo[k, i] < self.hi[k, i] for i in range(3) if bits[i])
            if not ok:
                raise ValueError(f"joint {self.driven[k]}: bits {bits} and limits do not "
                                 f"agree (an axis sent: 1 to {MAX_PARAMETER_BITS} bits, "
                                 f"lo < hi)")
        return self

    @property
    def num_joints(self) -> int:
        return int(self.rest.shape[0])

    @functools.cached_property
    def nbytes(self) -> int:
        """Bytes of one frame's rotations."""
        total = sum(sum(b) or QUATERNION_BITS for b in self.bits)
        return (total + 7) // 8

    def kernel_args(self) -> tuple[NDArray[Any], ...]:
        """driven, axes (0: a quaternion), bits, lo, hi, pre, post as the compiled
        kernels take them."""
        cached = self.__dict__.get("_kernel_args")
        if cached is None:
            bits = np.array(self.bits, dtype=np.uint8).reshape(-1, 3)
            cached = (np.array(self.driven, dtype=np.int64),
                      (bits.sum(axis=1) > 0).astype(np.uint8), bits,
                      np.ascontiguousarray(self.lo), np.ascontiguousarray(self.hi),
                      np.ascontiguousarray(self.pre), np.ascontiguousarray(self.post))
            self.__dict__["_kernel_args"] = cached  # frozen model: a private cache
        return cached

    def pack(self, rotations: Array) -> bytes:
        """(B, J, 4) rotations -> B frames of ``nbytes`` each."""
        rotations = np.asarray(rotations, dtype=np.float64)
        if rotations.ndim != 3 or rotations.shape[1:] != (self.num_joints, 4):
            raise ValueError(f"rotations {rotations.shape}; ({self.num_joints}, 4) an "
                             f"avatar expected")
        out = np.empty(rotations.shape[0] * self.nbytes, dtype=np.uint8)
        _pack(rotations, *self.kernel_args(), self.nbytes, out)  # type: ignore[call-arg, arg-type]
        return out.tobytes()

    def unpack(self, data: bytes | memoryview, rest: Array | None = None,
               rest_rows: NDArray[np.int64] | None = None) -> Array:
        """B frames -> (B, J, 4) rotations: the driven joints decoded, the others from
        ``rest`` (default this coding's): frame b's from rest[rest_rows[b]] (default b).
        ValueError for bits no encoder writes, naming the frame and joint."""
        n = len(data) // self.nbytes if self.nbytes else 0
        if n * self.nbytes != len(data):
            raise ValueError(f"{len(data)} bytes is not a whole number of frames of "
                             f"{self.nbytes} bytes")
        if rest is None:
            rest, rest_rows = self.rest[None], np.zeros(n, dtype=np.int64)
        elif rest_rows is None:
            rest_rows = np.arange(n, dtype=np.int64)
        out = np.empty((n, self.num_joints, 4))
        status, b, j = _unpack(np.frombuffer(data, dtype=np.uint8), rest,  # type: ignore[call-arg]
                               rest_rows, *self.kernel_args(), self.nbytes,  # type: ignore[arg-type]
                               out)
        if status == 1:
            raise ValueError(f"frame {b}: padding bits after the last joint are set")
        if status == 2:
            raise ValueError(f"frame {b} (joint {j}): the three sent components are not "
                             f"those of a unit quaternion")
        return out


# ----------------------------------------------------------------------- kernels
@njit(cache=True, inline="always")
def _mul(a0: float, a1: float, a2: float, a3: float, b0: float, b1: float, b2: float,
         b3: float) -> tuple[float, float, float, float]:
    return (a3 * b0 + a0 * b3 + a1 * b2 - a2 * b1,
            a3 * b1 - a0 * b2 + a1 * b3 + a2 * b0,
            a3 * b2 + a0 * b1 - a1 * b0 + a2 * b3,
            a3 * b3 - a0 * b0 - a1 * b1 - a2 * b2)


@njit(cache=True)
def _parameters(q: NDArray[np.float64], pre: NDArray[np.float64], post: NDArray[np.float64]
                ) -> tuple[float, float, float]:
    """(x, twist, z) of D = pre^-1 q post^-1: solver.rig.deviation for one joint."""
    d = _mul(-pre[0], -pre[1], -pre[2], pre[3], q[0], q[1], q[2], q[3])
    d = _mul(d[0], d[1], d[2], d[3], -post[0], -post[1], -post[2], post[3])
    norm = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2] + d[3] * d[3])
    sign = -1.0 / norm if d[3] < 0.0 else 1.0 / norm
    d0, d1, d2, d3 = d[0] * sign, d[1] * sign, d[2] * sign, d[3] * sign
    n = math.sqrt(d1 * d1 + d3 * d3)
    if n < 1e-12:  # a half-turn swing: no twist
        t1, t3 = 0.0, 1.0
    else:
        t1, t3 = d1 / n, d3 / n
    twist = 2.0 * math.atan2(t1, t3)
    s = _mul(d0, d1, d2, d3, 0.0, -t1, 0.0, t3)  # swing = D twist^-1, w >= 0
    v = math.sqrt(s[0] * s[0] + s[2] * s[2])
    scale = 2.0 if v < 1e-12 else 2.0 * math.atan2(v, s[3]) / v
    return s[0] * scale, twist, s[2] * scale


@njit(cache=True)
def _rotation(x: float, twist: float, z: float, pre: NDArray[np.float64],
              post: NDArray[np.float64], out: NDArray[np.float64]) -> None:
    angle = math.sqrt(x * x + z * z)
    half = 0.5 if angle < 1e-12 else math.sin(0.5 * angle) / angle
    s = (x * half, 0.0, z * half, math.cos(0.5 * angle))
    d = _mul(s[0], s[1], s[2], s[3], 0.0, math.sin(0.5 * twist), 0.0, math.cos(0.5 * twist))
    q = _mul(pre[0], pre[1], pre[2], pre[3], d[0], d[1], d[2], d[3])
    q = _mul(q[0], q[1], q[2], q[3], post[0], post[1], post[2], post[3])
    # pre and post are float32 values, unit within ~1e-7: the rotation is, exactly
    inv = 1.0 / math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    for i in range(4):
        out[i] = q[i] * inv


@njit(cache=True, inline="always")
def _level(value: float, lo: float, hi: float, bits: int) -> int:
    """A parameter's level: clamped to its limits, rounded to the nearest of 2^bits."""
    top = (1 << bits) - 1
    v = min(max(value, lo), hi)
    return min(math.floor((v - lo) / (hi - lo) * top + 0.5), top)


@njit(cache=True, inline="always")
def _value(acc: int, held: int, bits: int, lo: float, hi: float) -> tuple[float, int, int]:
    """The next parameter off the bit stream (0 where ``bits`` is 0: the axis is absent)."""
    if bits == 0:
        return 0.0, acc, held
    top = (1 << bits) - 1
    return lo + (acc & top) * ((hi - lo) / top), acc >> bits, held - bits


_RO_A = {n: types.Array(types.float64, n, "A", readonly=True) for n in (2, 3)}
_KERNEL_CODING = (types.Array(types.int64, 1, "A", readonly=True),
                  types.Array(types.uint8, 1, "A", readonly=True),
                  types.Array(types.uint8, 2, "A", readonly=True),
                  _RO_A[2], _RO_A[2], _RO_A[2], _RO_A[2], types.int64)


@njit(types.void(_RO_A[3], *_KERNEL_CODING, types.uint8[::1]), cache=True)
def _pack(rotations: NDArray[np.float64], driven: NDArray[np.int64],
          axes: NDArray[np.uint8], bits: NDArray[np.uint8], lo: NDArray[np.float64],
          hi: NDArray[np.float64], pre: NDArray[np.float64], post: NDArray[np.float64],
          nbytes: int, out: NDArray[np.uint8]) -> None:
    for b in range(rotations.shape[0]):
        acc = 0  # bits not yet written, lowest first
        held = 0
        at = b * nbytes
        for k in range(driven.shape[0]):
            q = rotations[b, driven[k]]
            if axes[k] == 0:
                acc |= quat_word(q[0], q[1], q[2], q[3]) << held
                held += 38
            else:
                x, twist, z = _parameters(q, pre[k], post[k])
                for i, value in ((0, x), (1, twist), (2, z)):
                    n = bits[k, i]
                    if n:
                        acc |= _level(value, lo[k, i], hi[k, i], n) << held
                        held += n
            while held >= 8:
                out[at] = acc & 0xFF
                acc >>= 8
                held -= 8
                at += 1
        if held:
            out[at] = acc & 0xFF


@njit(types.UniTuple(types.int64, 3)(types.Array(types.uint8, 1, "C", readonly=True),
                                     _RO_A[3], types.Array(types.int64, 1, "A", readonly=True),
                                     *_KERNEL_CODING, types.float64[:, :, ::1]),
      cache=True)
def _unpack(data: NDArray[np.uint8], rest: NDArray[np.float64], rest_rows: NDArray[np.int64],
            driven: NDArray[np.int64], axes: NDArray[np.uint8], bits: NDArray[np.uint8],
            lo: NDArray[np.float64], hi: NDArray[np.float64], pre: NDArray[np.float64],
            post: NDArray[np.float64], nbytes: int, out: NDArray[np.float64]
            ) -> tuple[int, int, int]:
    """Fills out (frame b's undriven joints from rest[rest_rows[b]]); (0, 0, 0), (1,
    frame, 0) for padding bits set, (2, frame, joint) for a quaternion no encoder
    writes."""
    for b in range(out.shape[0]):
        r = rest_rows[b]
        for j in range(out.shape[1]):  # element by element: a slice copy cost ~0.5 us
            for i in range(4):
                out[b, j, i] = rest[r, j, i]
        acc = 0
        held = 0
        at = b * nbytes
        for k in range(driven.shape[0]):
            need = 38 if axes[k] == 0 else bits[k, 0] + bits[k, 1] + bits[k, 2]
            while held < need:
                acc |= int(data[at]) << held
                held += 8
                at += 1
            j = driven[k]
            if axes[k] == 0:
                if word_quat(acc & ((1 << 38) - 1), out[b, j]) < 0.0:
                    return 2, b, j
                acc >>= 38
                held -= 38
                continue
            x, acc, held = _value(acc, held, bits[k, 0], lo[k, 0], hi[k, 0])
            twist, acc, held = _value(acc, held, bits[k, 1], lo[k, 1], hi[k, 1])
            z, acc, held = _value(acc, held, bits[k, 2], lo[k, 2], hi[k, 2])
            _rotation(x, twist, z, pre[k], post[k], out[b, j])
        if acc:
            return 1, b, 0
    return 0, 0, 0


# ------------------------------------------------------------------ a batch's avatars
Codings = Mapping[int, "PoseCoding | None"]  # avatar id -> its roster's coding
_STRUCTURES: dict[tuple[Any, ...], tuple[NDArray[Any], ...]] = {}


def _structure(coding: PoseCoding) -> tuple[NDArray[Any], ...]:
    """The kernel arrays of codings alike but for their rest: one object for all of a
    room's avatars, so that a batch decodes in one call per kind of skeleton."""
    shared = coding.__dict__.get("_structure")
    if shared is None:
        args = coding.kernel_args()
        key = tuple(a.tobytes() for a in args)
        shared = _STRUCTURES.get(key)
        if shared is None:
            if len(_STRUCTURES) > 64:  # codings come from servers: bounded
                _STRUCTURES.clear()
            shared = _STRUCTURES[key] = args
        coding.__dict__["_structure"] = shared
    return shared


def frame_sizes(avatar_ids: Sequence[int], joint_counts: Sequence[int],
                codings: Codings | None) -> list[int]:
    """Bytes of each avatar's rotations in a batch; ValueError where a joint count
    disagrees with the avatar's coding."""
    sizes = []
    for b, (avatar_id, joints) in enumerate(zip(avatar_ids, joint_counts, strict=True)):
        coding = codings.get(avatar_id) if codings is not None else None
        if coding is None:
            sizes.append(BYTES_PER_ROTATION * joints)
        elif coding.num_joints != joints:
            raise ValueError(f"avatar {b} (id {avatar_id}): {joints} joints, but its "
                             f"roster's coding has {coding.num_joints}")
        else:
            sizes.append(coding.nbytes)
    return sizes


def pack_batch(avatar_ids: Sequence[int], rotations: Sequence[Array] | Array,
               codings: Codings | None) -> bytes:
    """Each avatar's (J_b, 4) rotations as its coding packs them (none: 5 bytes a joint),
    one after the other. A (B, J, 4) array of avatars sharing one coding's structure
    packs in one call."""
    if not codings and isinstance(rotations, np.ndarray) and rotations.ndim == 3:
        return quantize_rotations(rotations.reshape(-1, 4))
    if codings and isinstance(rotations, np.ndarray) and rotations.ndim == 3 \
            and avatar_ids:
        kinds = {id(_structure(c)) if (c := codings.get(a)) is not None else None
                 for a in avatar_ids}
        first = codings.get(avatar_ids[0])
        if len(kinds) == 1 and first is not None:
            return first.pack(rotations)
    parts = []
    for avatar_id, rows in zip(avatar_ids, rotations, strict=True):
        coding = codings.get(avatar_id) if codings is not None else None
        parts.append(quantize_rotations(rows) if coding is None else coding.pack(rows[None]))
    return b"".join(parts)


class RosterCodings(dict[int, "PoseCoding | None"]):
    """Each avatar's PoseCoding, as a stream's rosters give them: what a viewer needs to
    unpack the batches that follow (``codec.decode(..., codings=...)``). It remembers
    how the last batches of each set of avatars unpack: a room's batches repeat it."""

    def __init__(self) -> None:
        super().__init__()
        self.plans: dict[tuple[bytes, bytes], _Plan] = {}
        self._table: tuple[PoseCoding, Array, dict[int, int]] | bool | None = False

    def learn(self, message: object) -> None:
        """Take a roster's avatars and removals (any other message: nothing)."""
        if getattr(message, "type", None) != "avatar_roster":
            return
        for avatar_id in message.removed:  # type: ignore[attr-defined]
            self.pop(avatar_id, None)
        for info in message.avatars:  # type: ignore[attr-defined]
            self[info.avatar_id] = info.coding
        self.plans.clear()
        self._table = False

    def table(self) -> tuple[PoseCoding, Array, dict[int, int]] | None:
        """When every avatar has a coding of one kind (a room solved on one rig: the
        usual case): that kind, every avatar's rest stacked, and each one's row in it;
        else None. A batch of any of them then unpacks in one call, whichever avatars it
        holds (a room's bursts split into batches of varying avatars)."""
        if self._table is False:
            codings = list(self.values())
            kinds = {id(_structure(c)) if c is not None else 0 for c in codings}
            if not codings or len(kinds) != 1 or 0 in kinds:
                self._table = None
            else:
                rests = np.stack([c.rest for c in codings])  # type: ignore[union-attr]
                self._table = (codings[0], rests,  # type: ignore[assignment]
                               {a: r for r, a in enumerate(self)})
        return self._table  # type: ignore[return-value]


class _Plan:
    """How a batch of given avatars and joint counts unpacks under given codings."""

    def __init__(self, avatar_ids: list[int], joint_counts: list[int],
                 codings: Codings | None) -> None:
        self.sizes = frame_sizes(avatar_ids, joint_counts, codings)
        self.total_bytes = sum(self.sizes)
        self.total_joints = sum(joint_counts)
        self.starts = np.concatenate(([0], np.cumsum(self.sizes))).astype(int).tolist()
        self.rows = np.concatenate(([0], np.cumsum(joint_counts))).astype(int).tolist()
        # avatars by kind of coding (None: 5 bytes a joint), each kind with its rests
        groups: dict[int, list[int]] = {}
        for b, avatar_id in enumerate(avatar_ids):
            coding = codings.get(avatar_id) if codings is not None else None
            groups.setdefault(id(_structure(coding)) if coding is not None else 0,
                              []).append(b)
        self.groups: list[tuple[PoseCoding | None, list[int], Array | None]] = []
        for key, members in groups.items():
            if key == 0:
                self.groups.append((None, members, None))
                continue
            assert codings is not None
            kind = codings[avatar_ids[members[0]]]
            rest = np.stack([codings[avatar_ids[b]].rest for b in members])  # type: ignore[union-attr]
            self.groups.append((kind, members, rest))
        self.whole = len(self.groups) == 1


def unpack_batch(avatar_ids: Sequence[int], joint_counts: Sequence[int],
                 data: bytes, codings: Codings | None) -> Array:
    """A batch's rotations -> (sum of joint counts, 4), each avatar decoded by its
    coding; ValueError naming the avatar for anything no encoder writes."""
    ids, counts = list(avatar_ids), list(joint_counts)
    if isinstance(codings, RosterCodings) and ids:
        table = codings.table()
        if table is not None:  # one kind of coding for all: one call, no plan
            only, rests, row_of = table
            rows = [row_of.get(a, -1) for a in ids]
            if -1 not in rows and len(data) == len(ids) * only.nbytes \
                    and counts.count(only.num_joints) == len(counts):
                try:
                    decoded = only.unpack(data, rests, np.array(rows, dtype=np.int64))
                except ValueError as exc:
                    raise ValueError(_frame_to_avatar(str(exc), range(len(ids)))) from None
                return decoded.reshape(-1, 4)
    if isinstance(codings, RosterCodings):
        key = (np.asarray(ids, dtype=np.int64).tobytes(),
               np.asarray(counts, dtype=np.uint16).tobytes())
        plan = codings.plans.get(key)
        if plan is None:
            if len(codings.plans) > 64:
                codings.plans.clear()
            plan = codings.plans[key] = _Plan(ids, counts, codings)
    else:
        plan = _Plan(ids, counts, codings)
    if plan.total_bytes != len(data):
        raise ValueError(f"{len(data)} bytes of rotations; the avatars' joint counts and "
                         f"codings need {plan.total_bytes}")
    if not ids or (plan.whole and plan.groups[0][0] is None):  # 5 bytes a joint
        try:
            return dequantize_rotations(data)
        except ValueError as exc:
            raise ValueError(_joint_to_avatar(str(exc), counts)) from None
    out = np.empty((plan.total_joints, 4))
    starts, rows = plan.starts, plan.rows
    view = memoryview(data)
    for kind, members, rest in plan.groups:
        if kind is None:  # avatars without a coding: 5 bytes a joint
            for b in members:
                try:
                    out[rows[b]:rows[b + 1]] = dequantize_rotations(
                        view[starts[b]:starts[b + 1]])
                except ValueError as exc:
                    raise ValueError(_joint_to_avatar(str(exc), [counts[b]], b)) from None
            continue
        chunk = data if plan.whole else b"".join(view[starts[b]:starts[b + 1]]
                                                 for b in members)
        try:
            decoded = kind.unpack(chunk, rest)
        except ValueError as exc:
            raise ValueError(_frame_to_avatar(str(exc), members)) from None
        if plan.whole:
            return decoded.reshape(-1, 4)
        for i, b in enumerate(members):
            out[rows[b]:rows[b + 1]] = decoded[i]
    return out


def _frame_to_avatar(message: str, members: Sequence[int]) -> str:
    """'frame 2 (joint 5): why' (the kernel's, frame 2 of the ones unpacked) -> 'avatar 7
    (joint 5): why', given which avatar of the batch each frame was."""
    frame, _, why = message.removeprefix("frame ").partition(" ")
    sep = ": " if frame.endswith(":") else " "
    return f"avatar {members[int(frame.rstrip(':'))]}{sep}{why}"


def _joint_to_avatar(message: str, counts: list[int], first: int = 0) -> str:
    """'joint 106: why' (a row of 5-byte rotations) -> 'avatar 2 (joint 0): why'."""
    head, _, why = message.partition(": ")
    if not head.startswith("joint ") or not head[6:].isdigit():
        return message
    row = int(head[6:])
    for b, n in enumerate(counts):
        if row < n:
            return f"avatar {first + b} (joint {row}): {why}"
        row -= n
    return message
