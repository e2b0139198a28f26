// The page's connection to the server, run in a worker of its own (network.js): the
// websocket on the page's host and port, hello as a spectator, clock sync
// (client/session/connection.py's schedule: 5 pings 20 ms apart, then one a second), and
// reconnects after a loss a reconnect can mend.

import { ClockEstimator, eventTime, now } from "./clock.js";
import {
  decodeMessage, encodeHello, learnCodings, encodeLeave, encodePing, encodeViewerReport, ProtocolError,
} from "./protocol.js";

const SYNC_BURST = 5;
const SYNC_BURST_INTERVAL_MS = 20;
const SYNC_INTERVAL_MS = 1000;
const RECONNECT_FIRST_MS = 250;
const RECONNECT_MAX_MS = 2000;
// close codes after which trying again can help: going away, lost, the server's trouble
const RETRY_CLOSE_CODES = new Set([1001, 1006, 1011, 1012, 1013, 1014]);

export class Connection {
  /** `post(message)`: what the page hears: {type: "welcome"}, {type: "message", msg,
   * tArrival}, {type: "clock", offset, rtt}, {type: "status", text, kind},
   * {type: "bad_message", text}. */
  constructor(url, room, name, token, post) {
    this.url = url;
    this.room = room;
    this.name = name;
    this.token = token;
    this.post = post;
    this.clock = new ClockEstimator();
    this.codings = new Map(); // the rosters' codings: how the batches after them unpack
    this.ws = null;
    this.welcomed = false;
    this.wait = RECONNECT_FIRST_MS;
    this.timers = [];
    this.lastError = null;
  }

  open() {
    const ws = new WebSocket(this.url);
    ws.binaryType = "arraybuffer";
    this.ws = ws;
    this.welcomed = false;
    ws.onopen = () => ws.send(encodeHello(this.room, this.name, this.token));
    ws.onmessage = (event) => this.receive(event);
    ws.onclose = (event) => this.closed(event);
  }

  send(bytes) {
    if (this.ws && this.ws.readyState === WebSocket.OPEN && this.welcomed) {
      this.ws.send(bytes);
      return true;
    }
    return false;
  }

  /** A report of presented frames (three columns: server, local, local clocks) and of
   * avatars as shown (their times local), in playout `mode`. */
  report(tCapture, tReceived, tPresented, shown, mode) {
    if (!this.clock.synced) return false;
    const offset = this.clock.offset; // one offset for all: presented stays after received
    return this.send(encodeViewerReport(tCapture, tReceived.map((t) => t + offset),
      tPresented.map((t) => t + offset), shown.map((s) => ({ ...s, t: s.t + offset })), mode));
  }

  receive(event) {
    // "received" as the Python clients mean it: when the message reached the page (the
    // event's creation, in this worker, which nothing else keeps busy); a browser that
    // gives no such stamp gets the handler's time
    const t = now();
    const stamped = event.timeStamp > 0 ? eventTime(event) : t;
    const tArrival = stamped <= t ? stamped : t;
    let msg;
    try {
      msg = decodeMessage(event.data, this.codings);
      learnCodings(this.codings, msg);
    } catch (err) {
      if (err instanceof ProtocolError) {
        this.post({ type: "bad_message", text: err.message });
        return;
      }
      throw err;
    }
    if (msg.type === "pong") {
      if (this.clock.add(msg.t0, msg.t1, msg.t2, tArrival)) {
        this.post({ type: "clock", offset: this.clock.offset, rtt: this.clock.rtt });
      }
      return;
    }
    if (msg.type === "welcome") {
      this.codings.clear(); // a new session: its roster follows, whole
      this.welcomed = true;
      this.wait = RECONNECT_FIRST_MS;
      this.clock.reset();
      this.startSync();
      this.post({ type: "welcome" });
      return;
    }
    if (msg.type === "error") this.lastError = msg;
    this.post({ type: "message", msg, tArrival });
  }

  startSync() {
    this.stopSync();
    for (let i = 0; i < SYNC_BURST; i++) {
      this.timers.push(setTimeout(() => this.ping(), i * SYNC_BURST_INTERVAL_MS));
    }
    this.timers.push(setInterval(() => this.ping(), SYNC_INTERVAL_MS));
  }

  stopSync() {
    for (const t of this.timers) { clearTimeout(t); clearInterval(t); }
    this.timers = [];
  }

  ping() {
    this.send(encodePing(now()));
  }

  closed(event) {
    this.stopSync();
    const refused = !this.welcomed; // an Error instead of a Welcome: asking again repeats it
    const why = this.lastError ? `${this.lastError.code}: ${this.lastError.message}`
      : `closed (${event.code}${event.reason ? ` ${event.reason}` : ""})`;
    if ((refused && this.lastError) || !RETRY_CLOSE_CODES.has(event.code)) {
      this.post({ type: "status", text: `The server ended the session: ${why}`, kind: "error" });
      return;
    }
    this.post({ type: "status", text: `Connection lost (${why}); reconnecting...`, kind: "warn" });
    this.lastError = null;
    setTimeout(() => this.open(), this.wait * (0.8 + 0.4 * Math.random()));
    this.wait = Math.min(2 * this.wait, RECONNECT_MAX_MS);
  }

  leave() {
    this.stopSync();
    if (this.ws && this.ws.readyState === WebSocket.OPEN) {
      this.ws.send(encodeLeave("page closed"));
      this.ws.close(1000, "bye");
    }
  }
}
