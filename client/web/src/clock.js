// The offset from this page's clock to the server's, NTP style (protocol/clock.py).
//
// A Ping carries t0 (here), the Pong the server's t1 (received) and t2 (sent); t3 is its
// arrival here. offset = ((t1 - t0) + (t2 - t3)) / 2 errs by at most half the round
// trip, so of the last 32 samples (10 s at most) the median offset of the 3 with the
// lowest round trip is taken, kept within what every sample allows. server time = local
// time + offset. Local time is seconds since the epoch at performance.now()'s
// resolution: the same clock in the page and in its network worker (each has its own
// performance.now() origin).

export class ClockEstimator {
  constructor(window = 32, useBest = 3, maxAge = 10.0) {
    this.window = window;
    this.useBest = useBest;
    this.maxAge = maxAge;
    this.samples = [];
    this.offset = 0.0;
    this.rtt = Infinity;
  }

  /** Record one exchange; false (and ignored) for a negative round trip. */
  add(t0, t1, t2, t3) {
    if (![t0, t1, t2, t3].every(Number.isFinite)) return false;
    const sample = { offset: ((t1 - t0) + (t2 - t3)) / 2.0, rtt: (t3 - t0) - (t2 - t1), t: t3 };
    if (sample.rtt < 0.0) return false;
    this.samples.push(sample);
    if (this.samples.length > this.window) this.samples.shift();
    while (this.samples[0].t < sample.t - this.maxAge) this.samples.shift();
    const best = [...this.samples].sort((a, b) => a.rtt - b.rtt).slice(0, this.useBest);
    const offsets = best.map((s) => s.offset).sort((a, b) => a - b);
    const mid = offsets.length >> 1;
    const median = offsets.length % 2 ? offsets[mid] : (offsets[mid - 1] + offsets[mid]) / 2.0;
    this.offset = this.withinEveryBound(median);
    this.rtt = best[0].rtt;
    return true;
  }

  /** The median, or the middle of the offsets every sample allows (each within its
   * rtt / 2) where the median lies outside them: Pongs read late by a stalled page cannot
   * outvote a tighter sample. Samples that allow no common offset leave the median. */
  withinEveryBound(median) {
    let lo = -Infinity;
    let hi = Infinity;
    for (const s of this.samples) {
      lo = Math.max(lo, s.offset - s.rtt / 2.0);
      hi = Math.min(hi, s.offset + s.rtt / 2.0);
    }
    if ((lo <= median && median <= hi) || lo > hi) return median;
    return (lo + hi) / 2.0;
  }

  reset() {
    this.samples = [];
    this.offset = 0.0;
    this.rtt = Infinity;
  }

  get synced() {
    return this.samples.length > 0;
  }

  toServer(tLocal) {
    return tLocal + this.offset;
  }
}

/** Seconds on this page's clock. */
export function now() {
  return (performance.timeOrigin + performance.now()) / 1000;
}

/** An event's timeStamp (milliseconds since its context's origin) on that clock. */
export function eventTime(event) {
  return (performance.timeOrigin + event.timeStamp) / 1000;
}
