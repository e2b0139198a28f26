// What the page's playout was given and when it was sampled (&record=1, asked by
// `posecast demo --browser`): every frame pushed, with its arrival and the clock offset
// then, and every presentation instant with the offset the playout was sampled with, how
// many frames it had been given by then and the roots it drew. The demo reads it back at the end (dump) and replays it through the
// Python playout (which the parity test holds equal to this page's) against the players'
// capture logs: the browser's display error, measured on what the page really showed.

const FRAME_FIELDS = 6; // tArrival, offset (NaN: not synced), avatar id, seq, tCapture, joints
const PRESENT_FIELDS = 4; // t, offset, frames pushed before, avatars drawn

/** A growable Float64Array: a long session's columns without one JS number per object. */
class Column {
  constructor() {
    this.data = new Float64Array(4096);
    this.length = 0;
  }

  push(...values) {
    this.reserve(values.length);
    for (const v of values) this.data[this.length++] = v;
  }

  pushArray(values) {
    this.reserve(values.length);
    this.data.set(values, this.length);
    this.length += values.length;
  }

  reserve(n) {
    if (this.length + n <= this.data.length) return;
    let size = this.data.length * 2;
    while (size < this.length + n) size *= 2;
    const data = new Float64Array(size);
    data.set(this.data.subarray(0, this.length));
    this.data = data;
  }

  /** The column's bytes (little-endian float64, as every page's platform is) in base64. */
  base64() {
    const bytes = new Uint8Array(this.data.buffer, 0, 8 * this.length);
    let text = "";
    for (let i = 0; i < bytes.length; i += 0x8000) {
      text += String.fromCharCode.apply(null, bytes.subarray(i, i + 0x8000));
    }
    return btoa(text);
  }
}

export class Recording {
  constructor() {
    this.frames = new Column(); // FRAME_FIELDS a frame
    this.rotations = new Column(); // 4 a joint, the frames' in turn
    this.roots = new Column(); // 3 a frame
    // t, offset (NaN: not synced), frames pushed before it, avatars drawn: the page pushes
    // a frame when its message event runs, which may be a frame after its arrival stamp
    this.presents = new Column();
    this.pushed = 0;
    this.drawn = new Column(); // avatar id and root x, y, z of each drawn, a present's in turn
  }

  push(avatarId, frame, offset) {
    this.frames.push(frame.tArrival, offset ?? NaN, avatarId, frame.seq, frame.tCapture,
      frame.rotations.length / 4);
    this.pushed += 1;
    this.rotations.pushArray(frame.rotations);
    this.roots.pushArray(frame.root);
  }

  present(t, offset, sampled) {
    this.presents.push(t, offset ?? NaN, this.pushed, sampled.size);
    for (const [id, s] of sampled) this.drawn.push(id, s.root[0], s.root[1], s.root[2]);
  }

  /** Everything recorded, each column as base64 float64s (see FRAME_FIELDS). */
  dump() {
    return { frameFields: FRAME_FIELDS, presentFields: PRESENT_FIELDS, frames: this.frames.base64(),
      rotations: this.rotations.base64(), roots: this.roots.base64(),
      presents: this.presents.base64(), drawn: this.drawn.base64() };
  }
}
