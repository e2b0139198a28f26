// What the page measures of the frames it shows: the HUD's latency percentiles, and the
// ViewerReports that put them in the server's /metrics.
//
// Each avatar-frame counts once, when it is first presented: its capture time (server
// clock, from the batch), when its batch reached the page and when the frame was handed
// to the compositor (after renderer.render(), local clock). The network worker converts
// the local times to the server clock as it sends the report, both with the same offset,
// so presented never comes before received. A report goes every REPORT_INTERVAL_S with
// at most MAX_REPORT_ROWS
// rows; a busier room is sampled (reservoir), so that every frame is equally likely to
// be in the server's histograms however many avatars there are. A report also carries a
// few avatars as shown (a reservoir of MAX_REPORT_POSES over every avatar of every
// frame), from which the server measures the display error in its /metrics.

import { MAX_REPORT_POSES, MAX_REPORT_ROWS } from "./protocol.js";

export const REPORT_INTERVAL_S = 0.5; // 2 a second; the server takes 4 (reports_per_s)
const HUD_WINDOW = 2000; // samples per stage the HUD's percentiles look back over

export class Reporter {
  constructor() {
    this.rows = []; // [tCaptureServer, tReceivedLocal, tPresentedLocal]
    this.seen = 0; // rows offered since the last report (the reservoir's count)
    this.lastSent = -Infinity;
    this.enabled = true; // false once a server says it does not know viewer_report
    this.sent = 0;
    this.shown = []; // { id, t (local), root, rotations } of avatars as presented
    this.shownSeen = 0;
    this.mode = null; // the playout mode they were shown in
  }

  /** An avatar presented at `t` (local) in playout `mode`: each equally likely to be one
   * of the report's shown poses (copied when kept: a held frame's arrays are shared). */
  show(mode, id, root, rotations, t) {
    if (mode !== this.mode) { // poses of the old mode are not this report's
      this.mode = mode;
      this.shown = [];
      this.shownSeen = 0;
    }
    this.shownSeen += 1;
    const k = this.shown.length < MAX_REPORT_POSES ? this.shown.length
      : Math.floor(Math.random() * this.shownSeen);
    if (k < MAX_REPORT_POSES) {
      this.shown[k] = { id, t, root: Float64Array.from(root),
        rotations: Float64Array.from(rotations) };
    }
  }

  add(tCapture, tReceived, tPresented) {
    this.seen += 1;
    if (this.rows.length < MAX_REPORT_ROWS) {
      this.rows.push([tCapture, tReceived, tPresented]);
      return;
    }
    const k = Math.floor(Math.random() * this.seen);
    if (k < MAX_REPORT_ROWS) this.rows[k] = [tCapture, tReceived, tPresented];
  }

  /** The rows of a report when one is due (columns), else null. */
  take(tLocal) {
    if (!this.enabled || !(this.rows.length || this.shown.length) ||
        tLocal - this.lastSent < REPORT_INTERVAL_S) {
      return null;
    }
    const rows = this.rows;
    const shown = this.shown;
    this.rows = [];
    this.seen = 0;
    this.shown = [];
    this.shownSeen = 0;
    this.lastSent = tLocal;
    this.sent += 1;
    return { tCapture: rows.map((r) => r[0]), tReceived: rows.map((r) => r[1]),
      tPresented: rows.map((r) => r[2]), shown, mode: this.mode };
  }
}

/** The last HUD_WINDOW samples of a stage, in seconds. */
export class LatencyWindow {
  constructor(size = HUD_WINDOW) {
    this.values = new Float64Array(size);
    this.count = 0;
  }

  push(value) {
    this.values[this.count % this.values.length] = value;
    this.count += 1;
  }

  /** p-th percentile (0-100) of the window, linear between samples as numpy's. */
  percentile(p) {
    const n = Math.min(this.count, this.values.length);
    if (!n) return NaN;
    const sorted = this.values.slice(0, n).sort();
    const x = (p / 100) * (n - 1);
    const lo = Math.floor(x);
    const hi = Math.min(lo + 1, n - 1);
    return sorted[lo] + (x - lo) * (sorted[hi] - sorted[lo]);
  }
}
