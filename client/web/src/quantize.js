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
