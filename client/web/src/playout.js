// The page's playout: which pose of each avatar to draw at a given instant, in the
// desktop viewer's three modes and with its constants (client/viewer/interpolation.py
// and solver/prediction.py, whose docstrings say why). One algorithm, two languages:
// tests/client/web/test_playout_parity.py runs this module and the Python one on the same
// frames and arrival times and holds their poses equal at every presentation instant.
//
// - "interpolate": each avatar shown a little in the past, SLERP between the two frames
//   that bracket the instant; how far behind adapts to the jitter of its arrivals.
// - "zero-buffer": the newest frame as it is.
// - "predict": the newest frame carried forward to the present instant (server clock) by
//   a weighted least-squares fit through its last samples.
//
// Frames are plain objects { seq, tCapture (server clock), tArrival (local clock),
// rotations (Float64Array, 4 per joint), root (Float64Array of 3) }, and whatever else
// the page keeps with a frame (its lost devices): a sample's `newest` is that object.

export const MODES = ["interpolate", "zero-buffer", "predict"];
export const DEFAULT_MODE = "interpolate"; // `posecast view`'s default

export const DEFAULT_CAPACITY = 64; // frames kept per avatar: 0.7 s at 90 Hz
export const DEFAULT_WINDOW = 128; // arrivals the jitter statistics look back over
export const DEFAULT_K = 1.0;
export const DEFAULT_MIN_DELAY = 0.0;
export const DEFAULT_MAX_DELAY = 0.25; // seconds: beyond, a viewer would rather stutter
export const FALLBACK_INTERVAL = 1.0 / 90.0; // before two frames: a headset's rate

// solver/prediction.py's shipped predictor (PredictorParams()): "posecast", one window
export const PREDICTOR = { windowS: 0.12, decayS: 0.02, accelGain: 0.0, maxHorizonS: 0.25 };

// ------------------------------------------------------------------ numpy's statistics
/** numpy.percentile's default (linear between the closest ranks). */
export function percentile(values, p) {
  const sorted = Float64Array.from(values).sort();
  const x = (p / 100) * (sorted.length - 1);
  const lo = Math.floor(x);
  const hi = Math.min(lo + 1, sorted.length - 1);
  return sorted[lo] + (x - lo) * (sorted[hi] - sorted[lo]);
}

export function median(values) {
  return percentile(values, 50);
}

/** Python's round(): halves to even. */
function roundHalfEven(x) {
  const r = Math.round(x);
  return Math.abs(x % 1) === 0.5 && r % 2 !== 0 ? r - 1 : r;
}

// ------------------------------------------------------------------ quaternions (x y z w)
// (norms as the square root of the sum of squares, as numpy takes them: Math.hypot
// guards against overflow at ~10x the cost, and predict takes ~10^4 norms a frame)
function mul(a, i, b, j, out, o) {
  const ax = a[i], ay = a[i + 1], az = a[i + 2], aw = a[i + 3];
  const bx = b[j], by = b[j + 1], bz = b[j + 2], bw = b[j + 3];
  out[o] = aw * bx + ax * bw + ay * bz - az * by;
  out[o + 1] = aw * by - ax * bz + ay * bw + az * bx;
  out[o + 2] = aw * bz + ax * by - ay * bx + az * bw;
  out[o + 3] = aw * bw - ax * bx - ay * by - az * bz;
}

function normalizeAt(q, o) {
  const n = Math.sqrt(q[o] * q[o] + q[o + 1] * q[o + 1] + q[o + 2] * q[o + 2] + q[o + 3] * q[o + 3]);
  if (n > 0) for (let c = 0; c < 4; c++) q[o + c] /= n;
}

/** Every joint of a and b (4 per joint), SLERP'd at t along the shorter arc. */
export function slerpRows(a, b, t) {
  const out = new Float64Array(a.length);
  for (let o = 0; o < a.length; o += 4) {
    let d = a[o] * b[o] + a[o + 1] * b[o + 1] + a[o + 2] * b[o + 2] + a[o + 3] * b[o + 3];
    const sign = d < 0 ? -1 : 1;
    d = Math.abs(d);
    const theta = Math.acos(Math.min(Math.max(d, -1), 1));
    const s = Math.sin(theta);
    const near = s < 1e-9;
    const wa = near ? 1 - t : Math.sin((1 - t) * theta) / s;
    const wb = (near ? t : Math.sin(t * theta) / s) * sign;
    for (let c = 0; c < 4; c++) out[o + c] = wa * a[o + c] + wb * b[o + c];
    normalizeAt(out, o);
  }
  return out;
}

/** log(q) as a rotation vector, angle in [0, pi] (solver.rotations.to_rotvec). */
function toRotvec(q, o, out, k) {
  let n = Math.sqrt(q[o] * q[o] + q[o + 1] * q[o + 1] + q[o + 2] * q[o + 2] + q[o + 3] * q[o + 3]);
  if (!(n > 0)) n = 1;
  const f = (q[o + 3] / n < 0 ? -1 : 1) / n;
  const x = q[o] * f, y = q[o + 1] * f, z = q[o + 2] * f, w = q[o + 3] * f;
  const s = Math.sqrt(x * x + y * y + z * z);
  const scale = s < 1e-12 ? 2 : (2 * Math.atan2(s, w)) / s;
  out[k] = x * scale;
  out[k + 1] = y * scale;
  out[k + 2] = z * scale;
}

/** exp of a rotation vector (solver.rotations.from_rotvec). */
function fromRotvec(rx, ry, rz, out, o) {
  const angle = Math.sqrt(rx * rx + ry * ry + rz * rz);
  const k = angle < 1e-8 ? 0.5 - angle ** 2 / 48 : Math.sin(0.5 * angle) / angle;
  out[o] = rx * k;
  out[o + 1] = ry * k;
  out[o + 2] = rz * k;
  out[o + 3] = Math.cos(0.5 * angle);
}

// ------------------------------------------------------------------ prediction
/** The fit's offset weights (K) at horizon h for lags at tau (K, < 0, newest first):
 * a line through the newest sample (one lag), else a quadratic whose acceleration counts
 * accelGain times, least squares weighted exp(tau / decayS) (prediction.fit_weights). */
export function fitWeights(tau, h, accelGain, decayS) {
  const K = tau.length;
  if (K === 1) return [h / tau[0]];
  // P = pinv(A sw) sw: A's columns tau and tau^2 / 2, full rank: (M'M)^-1 M' by hand
  const m0 = new Float64Array(K), m1 = new Float64Array(K), sw = new Float64Array(K);
  let s00 = 0, s01 = 0, s11 = 0;
  for (let k = 0; k < K; k++) {
    sw[k] = Math.sqrt(Math.exp(tau[k] / decayS));
    m0[k] = tau[k] * sw[k];
    m1[k] = 0.5 * tau[k] * tau[k] * sw[k];
    s00 += m0[k] * m0[k];
    s01 += m0[k] * m1[k];
    s11 += m1[k] * m1[k];
  }
  const det = s00 * s11 - s01 * s01;
  const w = new Array(K);
  for (let k = 0; k < K; k++) {
    const v = ((s11 * m0[k] - s01 * m1[k]) / det) * sw[k];
    const a = ((s00 * m1[k] - s01 * m0[k]) / det) * sw[k];
    w[k] = h * v + accelGain * 0.5 * h * h * a;
  }
  return w;
}

/** The newest of recent frames (ascending capture times) carried forward to instant t
 * (prediction.predict_latest with the shipped predictor): { rotations, root }. */
export function predictLatest(frames, t, params = PREDICTOR) {
  const S = frames.length;
  const newest = frames[S - 1];
  const h = Math.min(t - newest.tCapture, params.maxHorizonS);
  if (S < 2 || h <= 0) return { rotations: newest.rotations, root: newest.root };
  const gaps = [];
  for (let i = 1; i < S; i++) gaps.push(frames[i].tCapture - frames[i - 1].tCapture);
  const dt = median(gaps);
  const K = Math.min(dt > 0 ? Math.max(1, roundHalfEven(params.windowS / dt)) : 1, S - 1);
  const tau = [];
  for (let k = 0; k < K; k++) tau.push(frames[S - 2 - k].tCapture - newest.tCapture);
  if (tau.some((x) => x >= 0)) return { rotations: newest.rotations, root: newest.root };
  const w = fitWeights(tau, h, params.accelGain, params.decayS);
  const q0 = newest.rotations;
  const rotations = new Float64Array(q0.length);
  const past = [];
  const weights = [];
  for (let k = 0; k < K; k++) {
    if (w[k] === 0) continue; // (the baselines weigh one lag each)
    past.push(frames[S - 2 - k].rotations);
    weights.push(w[k]);
  }
  // per joint: sum_k w_k log(q0^-1 q_-k), then q0 exp(that). Written out: ~10^4 of
  // these a frame for 16 avatars, where calls and temporaries cost more than the maths
  for (let o = 0; o < q0.length; o += 4) {
    const ax = -q0[o], ay = -q0[o + 1], az = -q0[o + 2], aw = q0[o + 3];
    let x = 0, y = 0, z = 0;
    for (let k = 0; k < past.length; k++) {
      const b = past[k];
      const bx = b[o], by = b[o + 1], bz = b[o + 2], bw = b[o + 3];
      let rx = aw * bx + ax * bw + ay * bz - az * by;
      let ry = aw * by - ax * bz + ay * bw + az * bx;
      let rz = aw * bz + ax * by - ay * bx + az * bw;
      let rw = aw * bw - ax * bx - ay * by - az * bz;
      if (rw < 0) { // the same rotation with w >= 0 (a product of unit ones: unit)
        rx = -rx; ry = -ry; rz = -rz; rw = -rw;
      }
      const s2 = rx * rx + ry * ry + rz * rz;
      const u = s2 / (rw * rw); // tan^2 of half the angle
      let scale;
      if (u < 0.01) { // 2 atan(t) / (t w), t^2 = u: its series, exact to ~1e-19 here
        scale = (2 / rw) * (1 + u * (-1 / 3 + u * (1 / 5 + u * (-1 / 7 + u * (1 / 9
          + u * (-1 / 11 + u * (1 / 13 + u * (-1 / 15 + u / 17))))))));
      } else {
        const sn = Math.sqrt(s2);
        scale = sn < 1e-12 ? 2 : (2 * Math.atan2(sn, rw)) / sn;
      }
      scale *= weights[k];
      x += rx * scale;
      y += ry * scale;
      z += rz * scale;
    }
    // q0 exp(x, y, z), normalised
    const angle = Math.sqrt(x * x + y * y + z * z);
    const c = angle < 1e-8 ? 0.5 - angle ** 2 / 48 : Math.sin(0.5 * angle) / angle;
    const ex = x * c, ey = y * c, ez = z * c, ew = Math.cos(0.5 * angle);
    const px = -ax, py = -ay, pz = -az, pw = aw;
    const qx = pw * ex + px * ew + py * ez - pz * ey;
    const qy = pw * ey - px * ez + py * ew + pz * ex;
    const qz = pw * ez + px * ey - py * ex + pz * ew;
    const qw = pw * ew - px * ex - py * ey - pz * ez;
    const m = Math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw);
    const g = m > 0 ? 1 / m : 1;
    rotations[o] = qx * g;
    rotations[o + 1] = qy * g;
    rotations[o + 2] = qz * g;
    rotations[o + 3] = qw * g;
  }
  const root = Float64Array.from(newest.root);
  for (let k = 0; k < K; k++) {
    const past = frames[S - 2 - k].root;
    for (let c = 0; c < 3; c++) root[c] += w[k] * (past[c] - newest.root[c]);
  }
  return { rotations, root };
}

/** prediction.lags_needed for the shipped predictor at fps. */
function lagsNeeded(params, fps) {
  return Math.max(1, roundHalfEven(params.windowS / (1 / fps)));
}

// ------------------------------------------------------------------ the snapshot buffer
/** Transit times over a sliding window: their least (base), the 95th percentile of their
 * excess over it (jitter) and the median capture interval. Kept sorted as frames come
 * and go (numpy sorts the window at each update: 16 avatars' sorts were ~0.15 ms of a
 * frame here); percentile(transit - base) = percentile(transit) - base. */
export class JitterEstimator {
  constructor(window = DEFAULT_WINDOW) {
    this.window = window;
    this.transit = []; // in arrival order
    this.capture = [];
    this.sortedTransit = [];
    this.sortedGaps = []; // the positive gaps between consecutive captures
    this.intervalS = FALLBACK_INTERVAL;
  }

  add(tCapture, tArrival) {
    const transit = tArrival - tCapture;
    if (this.capture.length) {
      const gap = tCapture - this.capture[this.capture.length - 1];
      if (gap > 0) insertSorted(this.sortedGaps, gap);
    }
    this.transit.push(transit);
    this.capture.push(tCapture);
    insertSorted(this.sortedTransit, transit);
    if (this.transit.length > this.window) {
      removeSorted(this.sortedTransit, this.transit.shift());
      const first = this.capture.shift();
      const gap = this.capture[0] - first;
      if (gap > 0) removeSorted(this.sortedGaps, gap);
    }
    if (this.sortedGaps.length) this.intervalS = sortedPercentile(this.sortedGaps, 50);
  }

  get base() {
    return this.sortedTransit.length ? this.sortedTransit[0] : 0;
  }

  get jitterP95() {
    return this.sortedTransit.length ? sortedPercentile(this.sortedTransit, 95) - this.base : 0;
  }

  get interval() {
    return this.intervalS;
  }
}

function sortedPercentile(sorted, p) {
  const x = (p / 100) * (sorted.length - 1);
  const lo = Math.floor(x);
  const hi = Math.min(lo + 1, sorted.length - 1);
  return sorted[lo] + (x - lo) * (sorted[hi] - sorted[lo]);
}

function lowerBound(sorted, value) {
  let lo = 0, hi = sorted.length;
  while (lo < hi) {
    const mid = (lo + hi) >> 1;
    if (sorted[mid] < value) lo = mid + 1;
    else hi = mid;
  }
  return lo;
}

function insertSorted(sorted, value) {
  sorted.splice(lowerBound(sorted, value), 0, value);
}

function removeSorted(sorted, value) {
  sorted.splice(lowerBound(sorted, value), 1); // the same double went in
}

/** One avatar's recent frames, in capture order, and its playout delay. */
export class SnapshotBuffer {
  constructor({ capacity = DEFAULT_CAPACITY, window = DEFAULT_WINDOW, k = DEFAULT_K,
    minDelay = DEFAULT_MIN_DELAY, maxDelay = DEFAULT_MAX_DELAY } = {}) {
    this.capacity = capacity;
    this.frames = [];
    this.jitter = new JitterEstimator(window);
    this.k = k;
    this.minDelay = minDelay;
    this.maxDelay = maxDelay;
    this.underruns = 0; // samples that had to hold the newest frame
    this.dropped = 0; // frames older than the newest (late or duplicated)
  }

  add(frame) {
    const newest = this.newest;
    if (newest && frame.tCapture <= newest.tCapture) {
      this.dropped += 1;
      return;
    }
    this.frames.push(frame);
    if (this.frames.length > this.capacity) this.frames.shift();
    this.jitter.add(frame.tCapture, frame.tArrival);
  }

  get newest() {
    return this.frames.length ? this.frames[this.frames.length - 1] : null;
  }

  /** Playout delay beyond the least transit, seconds. */
  get delay() {
    const d = this.k * this.jitter.jitterP95 + this.jitter.interval;
    return Math.min(Math.max(d, this.minDelay), this.maxDelay);
  }

  /** The capture instant (server clock) to show at local time now. */
  target(now) {
    return now - this.jitter.base - this.delay;
  }

  /** { rotations, root, tCapture (the instant the pose stands for), newest, held }, or
   * null before any frame. serverNow: now on the server clock (predict; when unknown,
   * the least transit stands in for the clock offset and the fastest delivery). */
  sample(now, mode, serverNow = null, predictor = PREDICTOR) {
    const newest = this.newest;
    if (!newest) return null;
    if (mode === "zero-buffer") return this.shown(newest, newest.tCapture, newest, false);
    if (mode === "predict") {
      return this.predictAt(serverNow === null ? now - this.jitter.base : serverNow, predictor);
    }
    return this.sampleAt(this.target(now));
  }

  shown(frame, tCapture, newest, held) {
    return { rotations: frame.rotations, root: frame.root, tCapture, newest, held };
  }

  predictAt(t, predictor = PREDICTOR) {
    const frames = this.frames;
    const newest = this.newest;
    if (frames.length < 2) return this.shown(newest, newest.tCapture, newest, false);
    const n = Math.min(frames.length, lagsNeeded(predictor, 1 / this.jitter.interval) + 2);
    const { rotations, root } = predictLatest(frames.slice(frames.length - n), t, predictor);
    const shownAt = Math.min(Math.max(t, newest.tCapture), newest.tCapture + predictor.maxHorizonS);
    return { rotations, root, tCapture: shownAt, newest, held: false };
  }

  sampleAt(t) {
    const frames = this.frames;
    const newest = this.newest;
    if (t >= newest.tCapture) {
      if (t > newest.tCapture) this.underruns += 1;
      return this.shown(newest, newest.tCapture, newest, t > newest.tCapture);
    }
    if (t <= frames[0].tCapture) return this.shown(frames[0], frames[0].tCapture, newest, false);
    for (let i = frames.length - 1; i > 0; i--) {
      const a = frames[i - 1], b = frames[i];
      if (a.tCapture <= t) {
        const alpha = (t - a.tCapture) / (b.tCapture - a.tCapture);
        const root = new Float64Array(3);
        for (let c = 0; c < 3; c++) root[c] = a.root[c] + alpha * (b.root[c] - a.root[c]);
        return { rotations: slerpRows(a.rotations, b.rotations, alpha), root, tCapture: t,
          newest, held: false };
      }
    }
    throw new Error("unreachable: t lies between the oldest and newest frames");
  }
}

/** Every avatar's snapshot buffer, sampled together at one instant. */
export class Playout {
  constructor(mode = DEFAULT_MODE, settings = {}) {
    if (!MODES.includes(mode)) throw new Error(`playout mode ${mode}: one of ${MODES.join(", ")}`);
    this.mode = mode;
    this.settings = settings;
    this.buffers = new Map();
  }

  push(avatarId, frame) {
    let buffer = this.buffers.get(avatarId);
    if (!buffer) this.buffers.set(avatarId, buffer = new SnapshotBuffer(this.settings));
    buffer.add(frame);
  }

  remove(avatarId) {
    this.buffers.delete(avatarId);
  }

  /** Map avatar id -> sample at local time now; serverOffset: the clock's offset
   * (server = local + offset) when synced, else null. */
  sample(now, serverOffset = null) {
    const serverNow = serverOffset === null ? null : now + serverOffset;
    const out = new Map();
    for (const [id, buffer] of this.buffers) {
      const s = buffer.sample(now, this.mode, serverNow);
      if (s) out.set(id, s);
    }
    return out;
  }

  /** The next mode: interpolate, zero-buffer, predict, and round again. */
  toggle() {
    this.mode = MODES[(MODES.indexOf(this.mode) + 1) % MODES.length];
    return this.mode;
  }
}
