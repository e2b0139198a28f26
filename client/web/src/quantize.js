// Joint rotations off the wire: 5 bytes each, "smallest three" (protocol/quantize.py).
//
// Bit-for-bit the Python decoder: bits 36-37 name the dropped (largest) component, the
// other three are 12-bit k at bits 24, 12 and 0 (x, y, z, w order, skipping the dropped
// one), c = (k - 2047) / (2047 sqrt 2); the dropped one is sqrt(1 - sum c^2). The 40-bit
// word is read as a low 32-bit half and a high byte: JS bit operators are 32-bit.

export const BYTES_PER_ROTATION = 5;
const HALF = 2047;
const RANGE = 1.0 / Math.sqrt(2.0);
const SCALE = HALF / RANGE;
const STEP = 1.0 / SCALE; // Python multiplies by (1.0 / _SCALE): the same double
// the three smallest components of a unit quaternion have squares summing to <= 3/4
const MAX_KEPT_SQUARES = 0.75 + 1e-3;

export class RotationError extends Error {}

/** J * 5 bytes -> Float64Array of J * 4 (x, y, z, w), largest component positive.
 * Throws RotationError naming the joint, as Python's ValueError does. */
export function dequantizeRotations(bytes) {
  if (bytes.length % BYTES_PER_ROTATION) {
    throw new RotationError(`${bytes.length} bytes is not a multiple of ` +
      `${BYTES_PER_ROTATION} bytes per rotation`);
  }
  const n = bytes.length / BYTES_PER_ROTATION;
  const out = new Float64Array(4 * n);
  for (let j = 0; j < n; j++) {
    const b = j * BYTES_PER_ROTATION;
    const lo = (bytes[b] | (bytes[b + 1] << 8) | (bytes[b + 2] << 16) |
      (bytes[b + 3] << 24)) >>> 0;
    const hi = bytes[b + 4];
    if (hi >> 6) throw new RotationError(`joint ${j}: unused bits 38-39 are set`);
    const largest = (hi >> 4) & 3;
    const fields = [(lo >>> 24) | ((hi & 0xf) << 8), (lo >>> 12) & 0xfff, lo & 0xfff];
    let squares = 0.0;
    let f = 0;
    for (let i = 0; i < 4; i++) {
      if (i === largest) continue;
      const c = (fields[f++] - HALF) * STEP;
      out[4 * j + i] = c;
      squares += c * c;
    }
    if (squares > MAX_KEPT_SQUARES) {
      throw new RotationError(`joint ${j}: the three sent components have squares ` +
        `summing to ${squares.toFixed(4)} > 0.75, not a unit quaternion`);
    }
    out[4 * j + largest] = Math.sqrt(1.0 - squares);
  }
  return out;
}

// ------------------------------------------------------------------ protocol 4's codings
// protocol/pose_coding.py: an avatar's frame is one little-endian bit stream. A joint
// with bits (0, 0, 0) is a 38-bit quaternion as above; else each parameter with bits
// (x swing, twist y, z swing) is a level k of its limits, p = lo + k (hi - lo) / top,
// and q = pre · swing(x, 0, z) · twist_y(t) · post.
export const QUATERNION_BITS = 38;

/** n <= 38 bits at bit `at` of `bytes` (lowest first), as a Number (exact below 2^53). */
function readBits(bytes, at, n) {
  let value = 0;
  let scale = 1;
  let got = 0;
  while (got < n) {
    const bit = at + got;
    const shift = bit & 7;
    const take = Math.min(8 - shift, n - got);
    value += ((bytes[bit >> 3] >> shift) & ((1 << take) - 1)) * scale;
    scale *= 2 ** take;
    got += take;
  }
  return value;
}

function mul(a, b) { // quaternions x, y, z, w: protocol/pose_coding.py's _mul
  return [a[3] * b[0] + a[0] * b[3] + a[1] * b[2] - a[2] * b[1],
    a[3] * b[1] - a[0] * b[2] + a[1] * b[3] + a[2] * b[0],
    a[3] * b[2] + a[0] * b[1] - a[1] * b[0] + a[2] * b[3],
    a[3] * b[3] - a[0] * b[0] - a[1] * b[1] - a[2] * b[2]];
}

/** One avatar's frame (`coding.nbytes` bytes at `offset`) -> its J rotations into `out`
 * at joint `first`: the driven joints decoded, the others the coding's rest. Throws
 * RotationError for bits no encoder writes. */
export function unpackFrame(bytes, offset, coding, out, first) {
  out.set(coding.rest, 4 * first);
  let at = 8 * offset;
  coding.driven.forEach((j, k) => {
    const o = 4 * (first + j);
    const bits = coding.bits[k];
    if (bits[0] + bits[1] + bits[2] === 0) {
      const word = readBits(bytes, at, QUATERNION_BITS);
      at += QUATERNION_BITS;
      const largest = Math.floor(word / 2 ** 36);
      const fields = [Math.floor(word / 2 ** 24) % 4096, Math.floor(word / 2 ** 12) % 4096,
        word % 4096];
      let squares = 0.0;
      let f = 0;
      for (let i = 0; i < 4; i++) {
        if (i === largest) continue;
        const c = (fields[f++] - HALF) * STEP;
        out[o + i] = c;
        squares += c * c;
      }
      if (squares > MAX_KEPT_SQUARES) {
        throw new RotationError(`joint ${j}: the three sent components are not those of a ` +
          "unit quaternion");
      }
      out[o + largest] = Math.sqrt(1.0 - squares);
      return;
    }
    const p = [0.0, 0.0, 0.0];
    for (let i = 0; i < 3; i++) {
      if (!bits[i]) continue;
      const top = 2 ** bits[i] - 1;
      const lo = coding.lo[3 * k + i];
      p[i] = lo + readBits(bytes, at, bits[i]) * ((coding.hi[3 * k + i] - lo) / top);
      at += bits[i];
    }
    const [x, t, z] = p;
    const angle = Math.sqrt(x * x + z * z);
    const half = angle < 1e-12 ? 0.5 : Math.sin(0.5 * angle) / angle;
    const d = mul([x * half, 0.0, z * half, Math.cos(0.5 * angle)],
      [0.0, Math.sin(0.5 * t), 0.0, Math.cos(0.5 * t)]);
    const q = mul(mul(coding.pre.subarray(4 * k, 4 * k + 4), d),
      coding.post.subarray(4 * k, 4 * k + 4));
    // pre and post are float32 values, unit within ~1e-7: the rotation is, exactly
    const inv = 1.0 / Math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    out.set(q.map((v) => v * inv), o);
  });
  if (at < 8 * (offset + coding.nbytes) && readBits(bytes, at, 8 * (offset + coding.nbytes) - at)) {
    throw new RotationError("padding bits after the last joint are set");
  }
}
