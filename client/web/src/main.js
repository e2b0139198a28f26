// posecast's browser spectator: /?room=NAME joins the room as a spectator over the
// websocket protocol, draws every avatar skinned with the desktop viewer's mesh, names
// them and their devices lost now, shows a latency HUD and reports what it presented to
// the server's /metrics. Poses are played out as the desktop viewer plays them
// (playout.js): interpolated a little behind (the default), the newest frame, or
// predicted to the present; &mode=NAME picks one, the M key or the button switches.

import "./style.css";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { now } from "./clock.js";
import { lostLines } from "./devices.js";
import { ROOM_NAME_RULE, validRoomName } from "./protocol.js";
import { DEFAULT_MODE, MODES, Playout } from "./playout.js";
import { Recording } from "./recording.js";
import { LatencyWindow, Reporter } from "./report.js";
import { Scene } from "./scene.js";
import { SkeletonMismatch, bindSkeleton, fitAvatar } from "./skinning.js";

const HUD_REFRESH_S = 0.25;
const STATUS_ERROR_S = 5; // a server's Error stays on screen this long

const params = new URLSearchParams(location.search);
const room = params.get("room");
const view = document.getElementById("view");
const statusBox = document.getElementById("status");
const hudBox = document.getElementById("hud");
const modeButton = document.getElementById("mode");

// what the page has done, for people (the HUD) and for tests (window.posecast)
const stats = { phase: "loading", avatars: 0, drawn: 0, framesReceived: 0, framesPresented: 0,
  badMessages: 0, reportsSent: 0, firstAvatarS: null, lastError: null, paused: false,
  mode: null, poseMs: null, poseMsP99: null };
window.posecast = stats;

function say(text, kind = "info") {
  statusBox.textContent = text;
  statusBox.className = kind;
  statusBox.hidden = !text;
}

function askForRoom() {
  say("Which room? Type its name, or open /?room=NAME.", "info");
  const form = document.createElement("form");
  form.method = "get";
  const input = Object.assign(document.createElement("input"),
    { name: "room", placeholder: "room name", required: true, autofocus: true });
  form.append(input, Object.assign(document.createElement("button"), { textContent: "Watch" }));
  statusBox.append(form);
  stats.phase = "no room";
}

async function loadMesh() {
  const reply = await fetch("/avatar.json");
  if (!reply.ok) throw new Error(`/avatar.json: HTTP ${reply.status}`);
  const doc = await reply.json();
  const gltf = await new GLTFLoader().loadAsync(doc.mesh);
  let mesh = null;
  gltf.scene.traverse((o) => { if (o.isSkinnedMesh && !mesh) mesh = o; });
  if (!mesh) throw new Error(`${doc.mesh} holds no skinned mesh`);
  return { mesh, bind: bindSkeleton(doc) };
}

class Spectator {
  constructor(scene, bind, mode) {
    this.scene = scene;
    this.bind = bind;
    this.playout = new Playout(mode);
    this.reported = new Map(); // avatar id -> the seq of its newest frame presented
    this.posed = new Map(); // avatar id -> the rotations it is drawn with now
    this.refused = new Set(); // avatars whose skeleton cannot wear the mesh
    this.reporter = new Reporter();
    this.received = new LatencyWindow();
    this.presented = new LatencyWindow();
    this.poseTimes = new LatencyWindow(240); // ms to sample and pose every avatar, a frame
    this.presents = [];
    // &record=1 (posecast demo --browser): what the playout got and gave, for the demo
    this.recording = params.get("record") === "1" ? new Recording() : null;
    this.hudAt = -Infinity;
    this.errorUntil = -Infinity;
    this.paused = false;
    this.clock = { synced: false, offset: 0, rtt: Infinity }; // the worker's, as it says
    const url = document.querySelector('meta[name="posecast-network"]').content;
    this.net = new Worker(url, { type: "module" });
    this.net.onmessage = ({ data }) => this.onNetwork(data);
    this.net.onerror = (event) => {
      stats.phase = "failed";
      say(`The page's network worker failed: ${event.message}`, "error");
    };
    const ws = `${location.protocol === "https:" ? "wss:" : "ws:"}//${location.host}/`;
    this.net.postMessage({ type: "open", url: ws, room, name: "browser",
      token: params.get("token") });
  }

  onNetwork(data) {
    if (data.type === "message") this.onMessage(data.msg, data.tArrival);
    else if (data.type === "clock") this.clock = { synced: true, offset: data.offset, rtt: data.rtt };
    else if (data.type === "welcome") {
      // (again, after a reconnect): the server's roster follows, whole
      for (const id of [...this.scene.avatars.keys()]) this.forget(id);
      stats.phase = "joined";
      this.clock = { synced: false, offset: 0, rtt: Infinity };
    } else if (data.type === "status") {
      stats.phase = data.kind === "error" ? "ended" : "reconnecting";
      say(data.text, data.kind);
    } else if (data.type === "bad_message") {
      stats.badMessages += 1;
      console.warn("posecast: dropped a message:", data.text);
    }
  }

  leave() {
    this.net.postMessage({ type: "leave" });
  }

  onMessage(msg, tArrival) {
    if (msg.type === "avatar_roster") {
      for (const id of msg.removed) this.forget(id);
      for (const info of msg.avatars) this.adopt(info);
    } else if (msg.type === "avatar_batch") {
      this.onBatch(msg, tArrival);
    } else if (msg.type === "error") {
      stats.lastError = `${msg.code}: ${msg.message}`;
      if (msg.code === "unknown_type") this.reporter.enabled = false; // an older server
      say(`The server says ${stats.lastError}`, "error");
      this.errorUntil = now() + STATUS_ERROR_S;
    }
  }

  adopt(info) {
    try {
      this.scene.setAvatar(fitAvatar(this.bind, info));
      this.refused.delete(info.avatarId);
    } catch (err) {
      if (!(err instanceof SkeletonMismatch)) throw err;
      this.scene.removeAvatar(info.avatarId);
      if (!this.refused.has(info.avatarId)) console.warn(`posecast: not drawing: ${err.message}`);
      this.refused.add(info.avatarId);
    }
    // a recalibrated avatar waits for its new frames (of its new skeleton)
    this.playout.remove(info.avatarId);
  }

  forget(id) {
    this.scene.removeAvatar(id);
    this.playout.remove(id);
    this.reported.delete(id);
    this.posed.delete(id);
    this.refused.delete(id);
  }

  onBatch(batch, tArrival) {
    const clock = this.clock;
    let start = 0;
    batch.avatarIds.forEach((id, b) => {
      const avatar = this.scene.avatars.get(id);
      stats.framesReceived += 1;
      if (clock.synced) this.received.push(tArrival + clock.offset - batch.tCapture[b]);
      if (avatar && avatar.fitted.jointCount === batch.counts[b]) {
        const count = batch.counts[b];
        const frame = { seq: batch.seqs[b], tCapture: batch.tCapture[b], tArrival,
          rotations: batch.rotations.subarray(4 * start, 4 * (start + count)),
          root: batch.roots.subarray(3 * b, 3 * b + 3), lost: batch.lost[b] };
        this.playout.push(id, frame);
        this.recording?.push(id, frame, clock.synced ? clock.offset : null);
      }
      start += batch.counts[b];
    });
  }

  // Space freezes the view (frames still arrive; the newest is drawn on going on): a
  // spectator can look at a pose, and a screenshot shows what the names say
  togglePause() {
    this.paused = !this.paused;
    stats.paused = this.paused;
    this.updateHud();
  }

  /** The next playout mode (M, or the button), shown on the button and in the HUD. */
  toggleMode() {
    this.playout.toggle();
    this.posed.clear(); // every avatar posed again in the new mode
    this.poseTimes = new LatencyWindow(240);
    stats.poseMs = null;
    stats.poseMsP99 = null;
    this.showMode();
  }

  showMode() {
    stats.mode = this.playout.mode;
    modeButton.textContent = `${this.playout.mode} (M)`;
    this.updateHud();
  }

  frame() {
    if (this.paused) return;
    const clock = this.clock;
    const t0 = now();
    const offset = clock.synced ? clock.offset : null;
    const sampled = this.playout.sample(t0, offset);
    this.recording?.present(t0, offset, sampled);
    const fresh = []; // each avatar-frame once, at its first presentation (as the viewer)
    for (const [id, s] of sampled) {
      // a frame already on screen is not posed again (zero-buffer, or a held one);
      // interpolated and predicted poses are new arrays every time
      if (this.posed.get(id) !== s.rotations) {
        this.scene.poseAvatar(id, s.rotations, 0, s.root);
        this.posed.set(id, s.rotations);
      }
      this.scene.setLost(id, s.newest.lost); // its newest frame's, whatever is drawn
      if (this.reported.get(id) !== s.newest.seq) {
        this.reported.set(id, s.newest.seq);
        fresh.push(s.newest);
      }
    }
    const posing = now() - t0;
    this.scene.render();
    const t = now(); // handed to the compositor: the page's "presented"
    for (const f of fresh) {
      this.reporter.add(f.tCapture, f.tArrival, t);
      if (clock.synced) this.presented.push(t + clock.offset - f.tCapture);
    }
    // every avatar shown may be one of the report's poses: timed with the posing (the
    // page's cost a frame beside the renderer's, `bench page`)
    for (const [id, s] of sampled) this.reporter.show(this.playout.mode, id, s.root, s.rotations, t);
    this.poseTimes.push(1000 * (posing + now() - t));
    stats.framesPresented += fresh.length;
    stats.poseFrames = this.poseTimes.count;
    stats.avatars = this.scene.avatars.size;
    stats.drawn = [...this.scene.avatars.values()].filter((a) => a.mesh.visible).length;
    if (stats.drawn && stats.firstAvatarS === null) stats.firstAvatarS = t;
    const report = clock.synced ? this.reporter.take(t) : null;
    if (report) {
      this.net.postMessage({ type: "report", ...report });
      stats.reportsSent = this.reporter.sent;
    }
    this.presents.push(t);
    while (this.presents.length > 1 && this.presents[0] < t - 1) this.presents.shift();
    this.updateStatus(t);
    if (t - this.hudAt >= HUD_REFRESH_S) {
      this.hudAt = t;
      stats.poseMs = this.poseTimes.percentile(50); // (a sort: not every frame)
      stats.poseMsP99 = this.poseTimes.percentile(99);
      this.updateHud();
    }
  }

  updateStatus(t) {
    if (t < this.errorUntil || stats.phase === "ended" || stats.phase === "reconnecting") return;
    if (stats.phase !== "joined") say(`Joining room ${room}...`);
    else if (!stats.drawn) say(`Room ${room} has no players yet: waiting for someone to join.`);
    else say("");
  }

  /** The interpolation delay of the avatars, their median (seconds). */
  delay() {
    const delays = [...this.playout.buffers.values()].map((b) => b.delay).sort((a, b) => a - b);
    return delays.length ? delays[Math.floor(delays.length / 2)] : 0;
  }

  updateHud() {
    const clock = this.clock;
    const ms = (w, p) => (w.count ? (1000 * w.percentile(p)).toFixed(1).padStart(7) : "      -");
    const fps = this.presents.length > 1 ? (this.presents.length - 1) /
      (this.presents[this.presents.length - 1] - this.presents[0]) : 0;
    const shown = [...this.scene.avatars].filter(([, a]) => a.mesh.visible)
      .sort(([x], [y]) => x - y)
      .map(([, a]) => ({ name: a.fitted.info.displayName, devices: a.fitted.info.devices,
        lost: a.lost }));
    const text = [
      `room ${room}   ${stats.drawn} avatar${stats.drawn === 1 ? "" : "s"}   ` +
        (this.paused ? "paused (Space: go on)" : `${fps.toFixed(0)} fps`),
      clock.synced ? `clock synced to the server's within ${(500 * clock.rtt).toFixed(2)} ms`
        : "clock: syncing with the server",
      `playout: ${this.playout.mode}${this.playout.mode === "interpolate"
        ? `, ${(1000 * this.delay()).toFixed(0)} ms behind` : ""}   (M: switch)`,
      "latency ms             p50      p99",
      `capture->received  ${ms(this.received, 50)}  ${ms(this.received, 99)}`,
      `capture->presented ${ms(this.presented, 50)}  ${ms(this.presented, 99)}`,
      ...lostLines(shown),
    ].join("\n");
    if (hudBox.textContent !== text) hudBox.textContent = text;
  }
}

async function main() {
  if (!room) {
    askForRoom();
    return;
  }
  if (!validRoomName(room)) {
    say(`Cannot join "${room.slice(0, 80)}": ${ROOM_NAME_RULE}.`, "error");
    stats.phase = "bad room";
    return;
  }
  const mode = params.get("mode") ?? DEFAULT_MODE;
  if (!MODES.includes(mode)) {
    say(`Unknown playout mode "${mode.slice(0, 40)}": use one of ${MODES.join(", ")}.`, "error");
    stats.phase = "bad mode";
    return;
  }
  document.title = `posecast: ${room}`;
  say(`Loading the avatar for room ${room}...`);
  const { mesh, bind } = await loadMesh();
  const scene = new Scene(view, mesh, bind);
  const spectator = new Spectator(scene, bind, mode);
  window.posecastRecording = () => spectator.recording?.dump() ?? null;
  stats.phase = "joining";
  spectator.showMode();
  modeButton.hidden = false;
  modeButton.addEventListener("click", () => spectator.toggleMode());
  window.addEventListener("pagehide", () => spectator.leave());
  window.addEventListener("keydown", (e) => {
    if (e.repeat) return;
    if (e.code === "Space") {
      e.preventDefault();
      spectator.togglePause();
    } else if (e.code === "KeyM") {
      spectator.toggleMode();
    }
  });
  const loop = () => {
    spectator.frame();
    requestAnimationFrame(loop);
  };
  requestAnimationFrame(loop);
}

main().catch((err) => {
  stats.phase = "failed";
  say(`The page failed: ${err.message}`, "error");
  console.error(err);
});
