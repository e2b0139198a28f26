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
import itertools
import math
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import msgpack
import numpy as np
from numba import njit, types
from numpy.typing import NDArray
from pydantic import (
    ValidationInfo,
    ValidatorFunctionWrapHandler,
    field_serializer,
    field_validator,
    model_validator,
)

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
        # whole arrays: every spectator validates every avatar's coding as players join
        bits = np.array(self.bits, dtype=np.int64).reshape(-1, 3)
        bad = ((bits < 0) | (bits > MAX_PARAMETER_BITS)
               | ((bits > 0) & ~(self.lo < self.hi))).any(axis=1)
        if bad.any():
            k = int(np.argmax(bad))
            raise ValueError(f"joint {self.driven[k]}: bits {self.bits[k]} and limits do "
                             f"not agree (an axis sent: 1 to {MAX_PARAMETER_BITS} bits, "
                             f"lo < hi)")
        return self

    @model_validator(mode="wrap")
    @classmethod
    def _known(cls, value: Any, handler: ValidatorFunctionWrapHandler,
               info: ValidationInfo) -> PoseCoding:
        """A coding whose bytes came over the wire before is taken as validated then (it
        is frozen). A process of many viewers (the demo's 16) reads every avatar's coding
        once per viewer: at ~0.2 ms each, the rosters of 16 players joining held its
        loop ~100 ms. (Defined after ``_consistent``, so that it wraps that check too.)"""
        if not is_wire(info) or type(value) is not dict:
            return handler(value)
        try:
            key = msgpack.packb(value, use_bin_type=True)
        except (TypeError, ValueError, OverflowError):
            return handler(value)
        known = _DECODED.get(key)
        if known is None:
            known = handler(value)
            if len(_DECODED) >= _DECODED_MAX:  # codings come from servers: bounded
                _DECODED.clear()
            _DECODED[key] = known
        return known

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

    def unpack_args(self) -> tuple[NDArray[Any], ...]:
        """driven, axes, bits, lo, step (a level's width), pre, post as the decoder takes
        them: the steps divided out and the frames made unit once, not per joint."""
        cached = self.__dict__.get("_unpack_args")
        if cached is None:
            driven, axes, bits, lo, hi, pre, post = self.kernel_args()
            levels = np.maximum((1 << bits.astype(np.int64)) - 1, 1)
            cached = (driven, axes, bits, lo, np.where(bits > 0, (hi - lo) / levels, 0.0),
                      pre / np.linalg.norm(pre, axis=1, keepdims=True),
                      post / np.linalg.norm(post, axis=1, keepdims=True))
            self.__dict__["_unpack_args"] = cached
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
                               rest_rows, *self.unpack_args(), self.nbytes,  # type: ignore[arg-type]
                               out)
        _raise_for(status, f"frame {b}", j)
        return out


_DECODED: dict[bytes, PoseCoding] = {}  # a coding's msgpack bytes -> its validated model
_DECODED_MAX = 256


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


_SERIES_MAX_U = 2.5  # |h| <= 1.58 rad: the series below are exact to ~2e-17 there
_TERMS = 11
_COS = tuple((-1) ** n / math.factorial(2 * n) for n in range(_TERMS))  # of u^n
_SINC = tuple((-1) ** n / math.factorial(2 * n + 1) for n in range(_TERMS))


@njit(cache=True, inline="always")
def _cos_sinc(u: float) -> tuple[float, float]:
    """cos(h) and sin(h)/h for u = h^2. Their Taylor series to u^10 where u is small
    (every angle of a joint coded within its limits): two polynomials cost a third of
    libm's sin and cos, which were half of a spectator's decoding. math's beyond."""
    if u > _SERIES_MAX_U:
        h = math.sqrt(u)
        return math.cos(h), math.sin(h) / h
    c = 0.0
    sinc = 0.0
    for n in range(_TERMS - 1, -1, -1):  # Horner, both at once
        c = c * u + _COS[n]
        sinc = sinc * u + _SINC[n]
    return c, sinc


@njit(cache=True, inline="always")
def _rotation(x: float, twist: float, z: float, pre: NDArray[np.float64],
              post: NDArray[np.float64], out: NDArray[np.float64]) -> None:
    # swing exp(x, 0, z): half-angle h = |(x, z)| / 2; twist about y: half-angle twist / 2
    c, sinc = _cos_sinc(0.25 * (x * x + z * z))
    ct, sinct = _cos_sinc(0.25 * twist * twist)
    half = 0.5 * sinc
    d = _mul(x * half, 0.0, z * half, c, 0.0, 0.5 * twist * sinct, 0.0, ct)
    q = _mul(pre[0], pre[1], pre[2], pre[3], d[0], d[1], d[2], d[3])
    q = _mul(q[0], q[1], q[2], q[3], post[0], post[1], post[2], post[3])
    for i in range(4):  # unit: pre and post were made unit (``unpack_args``)
        out[i] = q[i]


@njit(cache=True, inline="always")
def _level(value: float, lo: float, hi: float, bits: int) -> int:
    """A parameter's level: clamped to its limits, rounded to the nearest of 2^bits."""
    top = (1 << bits) - 1
    v = min(max(value, lo), hi)
    return min(math.floor((v - lo) / (hi - lo) * top + 0.5), top)


@njit(cache=True, inline="always")
def _value(acc: int, held: int, bits: int, lo: float, step: float
           ) -> tuple[float, int, int]:
    """The next parameter off the bit stream (0 where ``bits`` is 0: the axis is absent)."""
    if bits == 0:
        return 0.0, acc, held
    return lo + (acc & ((1 << bits) - 1)) * step, acc >> bits, held - bits


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


@njit(cache=True, inline="always")
def _unpack_frame(data: NDArray[np.uint8], at: int, rest: NDArray[np.float64], r: int,
                  driven: NDArray[np.int64], axes: NDArray[np.uint8], bits: NDArray[np.uint8],
                  lo: NDArray[np.float64], step: NDArray[np.float64], pre: NDArray[np.float64],
                  post: NDArray[np.float64], out: NDArray[np.float64], b: int
                  ) -> tuple[int, int]:
    """Frame b (from byte ``at``) into out[b], its undriven joints from rest[r]: (0, 0),
    (1, 0) for padding bits set, (2, joint) for a quaternion no encoder writes."""
    for j in range(out.shape[1]):  # element by element: a slice copy cost ~0.5 us
        for i in range(4):
            out[b, j, i] = rest[r, j, i]
    acc = 0
    held = 0
    for k in range(driven.shape[0]):
        need = 38 if axes[k] == 0 else bits[k, 0] + bits[k, 1] + bits[k, 2]
        while held < need:
            acc |= int(data[at]) << held
            held += 8
            at += 1
        j = driven[k]
        if axes[k] == 0:
            if word_quat(acc & ((1 << 38) - 1), out[b, j]) < 0.0:
                return 2, j
            acc >>= 38
            held -= 38
            continue
        x, acc, held = _value(acc, held, bits[k, 0], lo[k, 0], step[k, 0])
        twist, acc, held = _value(acc, held, bits[k, 1], lo[k, 1], step[k, 1])
        z, acc, held = _value(acc, held, bits[k, 2], lo[k, 2], step[k, 2])
        _rotation(x, twist, z, pre[k], post[k], out[b, j])
    return (1, 0) if acc else (0, 0)


_RO_I8 = types.Array(types.int64, 1, "A", readonly=True)
_RO_U8 = types.Array(types.uint8, 1, "C", readonly=True)
_STATUS = types.UniTuple(types.int64, 3)


@njit(_STATUS(_RO_U8, _RO_A[3], _RO_I8, *_KERNEL_CODING, types.float64[:, :, ::1]),
      cache=True)
def _unpack(data: NDArray[np.uint8], rest: NDArray[np.float64], rest_rows: NDArray[np.int64],
            driven: NDArray[np.int64], axes: NDArray[np.uint8], bits: NDArray[np.uint8],
            lo: NDArray[np.float64], step: NDArray[np.float64], pre: NDArray[np.float64],
            post: NDArray[np.float64], nbytes: int, out: NDArray[np.float64]
            ) -> tuple[int, int, int]:
    """Fills out (frame b's undriven joints from rest[rest_rows[b]]); (0, 0, 0), (1,
    frame, 0) for padding bits set, (2, frame, joint) for a quaternion no encoder
    writes."""
    for b in range(out.shape[0]):
        status, j = _unpack_frame(data, b * nbytes, rest, rest_rows[b], driven, axes, bits,
                                  lo, step, pre, post, out, b)
        if status:
            return status, b, j
    return 0, 0, 0


@njit(_STATUS(_RO_U8, types.Array(types.int64, 1, "C", readonly=True),
              types.Array(types.uint16, 1, "C", readonly=True), _RO_I8, _RO_A[3],
              *_KERNEL_CODING, types.float64[:, :, ::1]), cache=True)
def _unpack_known(data: NDArray[np.uint8], ids: NDArray[np.int64],
                  counts: NDArray[np.uint16], known_ids: NDArray[np.int64],
                  rest: NDArray[np.float64], driven: NDArray[np.int64],
                  axes: NDArray[np.uint8], bits: NDArray[np.uint8], lo: NDArray[np.float64],
                  step: NDArray[np.float64], pre: NDArray[np.float64],
                  post: NDArray[np.float64], nbytes: int, out: NDArray[np.float64]
                  ) -> tuple[int, int, int]:
    """``_unpack`` of a batch whose avatars (``ids``, ``counts`` joints each) are all in
    a table (``known_ids`` sorted, the rest of each in the same row of ``rest``): ids to
    rows here, not in Python (a viewer decodes every batch). (3, frame, 0) for an avatar
    not in the table or of another joint count: the caller takes the general path."""
    rows = np.empty(ids.shape[0], dtype=np.int64)
    for b in range(ids.shape[0]):
        i = np.searchsorted(known_ids, ids[b])
        if i == known_ids.shape[0] or known_ids[i] != ids[b] or counts[b] != out.shape[1]:
            return 3, b, 0
        rows[b] = i
    return _unpack(data, rest, rows, driven, axes, bits, lo, step, pre, post, nbytes, out)


# ------------------------------------------------------------------ a batch's avatars
Codings = Mapping[int, "PoseCoding | None"]  # avatar id -> its roster's coding
_STRUCTURES: dict[tuple[Any, ...], tuple[NDArray[Any], ...]] = {}


def _kernel_key(coding: PoseCoding) -> tuple[bytes, ...]:
    """What a coding's kernel arrays hold (its rest aside): alike codings, alike keys."""
    return tuple(a.tobytes() for a in coding.kernel_args())


def _structure(coding: PoseCoding) -> tuple[NDArray[Any], ...]:
    """The kernel arrays of codings alike but for their rest: one object for all of a
    room's avatars, so that a batch decodes in one call per kind of skeleton."""
    shared = coding.__dict__.get("_structure")
    if shared is None:
        key = _kernel_key(coding)
        shared = _STRUCTURES.get(key)
        if shared is None:
            if len(_STRUCTURES) > 64:  # codings come from servers: bounded
                _STRUCTURES.clear()
            shared = _STRUCTURES[key] = coding.kernel_args()
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
        first = codings.get(avatar_ids[0])
        if first is not None and _one_kind(first, avatar_ids, codings):
            return first.pack(rotations)
    parts = []
    for avatar_id, rows in zip(avatar_ids, rotations, strict=True):
        coding = codings.get(avatar_id) if codings is not None else None
        parts.append(quantize_rotations(rows) if coding is None else coding.pack(rows[None]))
    return b"".join(parts)


def _one_kind(first: PoseCoding, avatar_ids: Sequence[int], codings: Codings) -> bool:
    """Whether every avatar's coding packs as ``first`` does (``_structure``), stopping
    at the first that does not."""
    kind = _structure(first)
    for avatar_id in avatar_ids:
        c = codings.get(avatar_id)
        if c is None or _structure(c) is not kind:
            return False
    return True


# the content of each RosterCodings.decoding_key given out, and the next key (never one
# given out before, even after the map is cleared)
_DECODINGS: dict[tuple[Any, ...], int] = {}
_DECODING_KEYS = itertools.count()


class RosterCodings(dict[int, "PoseCoding | None"]):
    """Each avatar's PoseCoding, as a stream's rosters give them: what a viewer needs to
    unpack the batches that follow (``codec.decode(..., codings=...)``). It remembers
    how the last batches of each set of avatars unpack: a room's batches repeat it."""

    def __init__(self) -> None:
        super().__init__()
        self.plans: dict[tuple[bytes, bytes], _Plan] = {}
        self._table: _Table | bool | None = False
        self._key: int | bool | None = False

    def clear(self) -> None:
        super().clear()
        self.plans.clear()
        self._table = self._key = False

    def learn(self, message: object) -> None:
        """Take a roster's avatars and removals (any other message: nothing)."""
        if getattr(message, "type", None) != "avatar_roster":
            return
        for avatar_id in message.removed:  # type: ignore[attr-defined]
            self.pop(avatar_id, None)
        for info in message.avatars:  # type: ignore[attr-defined]
            self[info.avatar_id] = info.coding
        self.plans.clear()
        self._table = self._key = False

    def decoding_key(self) -> int | None:
        """A number two RosterCodings share exactly when they decode every batch alike
        (the same avatars, each with the same coding and rest): the spectators of a room
        in one process decode each batch once (``codec.decode_stream``). None unless
        every avatar has a coding of one kind (``table``)."""
        if self._key is False:
            table = self.table()
            if table is None:
                self._key = None
            else:
                content = (_kernel_key(table.coding), table.ids.tobytes(),
                           table.rests.shape, table.rests.tobytes())
                key = _DECODINGS.get(content)
                if key is None:
                    if len(_DECODINGS) > 256:  # rosters come from servers: bounded
                        _DECODINGS.clear()
                    key = _DECODINGS[content] = next(_DECODING_KEYS)
                self._key = key
        return self._key

    def table(self) -> _Table | None:
        """When every avatar has a coding of one kind (a room solved on one rig: the
        usual case): that kind and every avatar's rest, by sorted id; else None. A batch
        of any of them then unpacks in one call, whichever avatars it holds (a room's
        bursts split into batches of varying avatars)."""
        if self._table is False:
            codings = list(self.values())
            kinds = {id(_structure(c)) if c is not None else 0 for c in codings}
            if not codings or len(kinds) != 1 or 0 in kinds:
                self._table = None
            else:
                ids = np.array(sorted(self), dtype=np.int64)
                rests = np.stack([self[a].rest for a in ids.tolist()])  # type: ignore[union-attr]
                self._table = _Table(codings[0], readonly(ids), readonly(rests))  # type: ignore[arg-type]
        return self._table  # type: ignore[return-value]


class _Table(NamedTuple):
    """A RosterCodings' avatars when they share one kind of coding."""

    coding: PoseCoding
    ids: NDArray[np.int64]  # sorted
    rests: Array  # (avatars, J, 4): the rest of ids[i] in row i

    def unpack(self, ids: NDArray[np.int64], counts: NDArray[np.uint16], data: bytes
               ) -> Array | None:
        """(sum of counts, 4) rotations, or None when an avatar is not in the table or
        has another joint count, or the bytes are not whole frames: the general path
        then says what is wrong. ValueError (naming the avatar) for bits no encoder
        writes."""
        coding = self.coding
        if len(data) != ids.shape[0] * coding.nbytes:
            return None
        out = np.empty((ids.shape[0], coding.num_joints, 4))
        status, b, j = _unpack_known(np.frombuffer(data, dtype=np.uint8), ids, counts,  # type: ignore[call-arg]
                                     self.ids, self.rests,
                                     *coding.unpack_args(), coding.nbytes, out)  # type: ignore[arg-type]
        if status == 3:
            return None
        _raise_for(status, f"avatar {b}", j)
        return out.reshape(-1, 4)


def _raise_for(status: int, frame: str, joint: int) -> None:
    """A kernel's status as the ValueError it stands for (0: none)."""
    if status == 1:
        raise ValueError(f"{frame}: padding bits after the last joint are set")
    if status == 2:
        raise ValueError(f"{frame} (joint {joint}): the three sent components are not "
                         f"those of a unit quaternion")


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


def unpack_batch(avatar_ids: Sequence[int] | NDArray[np.int64],
                 joint_counts: Sequence[int] | NDArray[np.uint16],
                 data: bytes, codings: Codings | None) -> Array:
    """A batch's rotations -> (sum of joint counts, 4), each avatar decoded by its
    coding; ValueError naming the avatar for anything no encoder writes."""
    if isinstance(codings, RosterCodings) and len(avatar_ids):
        table = codings.table()
        if table is not None:  # one kind of coding for all: one call, no plan
            decoded = table.unpack(np.ascontiguousarray(avatar_ids, dtype=np.int64),
                                   np.ascontiguousarray(joint_counts, dtype=np.uint16), data)
            if decoded is not None:
                return decoded
    ids, counts = list(avatar_ids), list(joint_counts)
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
