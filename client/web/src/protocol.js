// posecast's wire protocol in the browser: the messages a spectator sends and reads
// (protocol/messages.py, protocol/batch.py, protocol/codec.py). msgpack maps with a
// string `type`; float arrays as packed little-endian bytes; rotations in 5 bytes.
//
// Everything from the server is checked before use, as the Python viewer checks it:
// a message that fails throws ProtocolError, and the page drops it and counts it.

import { decode as unpack, encode as pack } from "@msgpack/msgpack";
import { dequantizeRotations, QUATERNION_BITS, RotationError, unpackFrame } from "./quantize.js";

// 4: a roster gives each solved avatar a coding; its frames carry its driven joints,
// packed by their limits, and their times as float32 ages before t_sent
export const PROTOCOL_VERSION = 4;
export const MAX_AGE_S = 1e6; // protocol.sizes.MAX_AGE_S
const MAX_PARAMETER_BITS = 16;
export const MAX_MESSAGE_BYTES = 1 << 20; // what a viewer accepts (protocol.validation)
export const MAX_JOINTS = 256;
export const MAX_AVATARS = 1024;
export const MAX_POSITION_M = 1000.0;
export const MAX_REPORT_ROWS = 128; // protocol.messages.MAX_REPORT_ROWS
export const MAX_REPORT_POSES = 4; // protocol.messages.MAX_REPORT_POSES
const QUAT_LEVELS = 32767; // protocol.validation.POSE_QUAT_SCALE
// 1-64 letters, digits, '-', '_' or '.', starting with a letter or digit
const ROOM_NAME = /^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$/;
export const ROOM_NAME_RULE = "room names are 1-64 letters, digits, '-', '_' or '.', " +
  "starting with a letter or digit";

// protocol/roles.py's DEVICE_ROLES: bit i of a batch's `lost` is DEVICE_ROLES[i]
export const DEVICE_ROLES = Object.freeze(["head", "hip", "left_hand", "right_hand",
  "left_forearm", "right_forearm", "left_foot", "right_foot", "left_knee", "right_knee",
  "chest"]);
const LOST_BITS_LIMIT = 1 << DEVICE_ROLES.length;

export class ProtocolError extends Error {}

/** The roles whose bits are set, in DEVICE_ROLES order (protocol.roles.roles_of_bits). */
export function rolesOfBits(bits) {
  return DEVICE_ROLES.filter((_, i) => (bits >> i) & 1);
}

const LIMITS = {
  maxStrLength: 4096, maxBinLength: MAX_MESSAGE_BYTES, maxArrayLength: 4096,
  maxMapLength: 64, maxExtLength: 0,
};

export function validRoomName(name) {
  return typeof name === "string" && ROOM_NAME.test(name);
}

// ------------------------------------------------------------------ client -> server
export function encodeHello(room, name, token) {
  const hello = { type: "hello", protocol_version: PROTOCOL_VERSION, role: "spectator",
    room, display_name: name };
  if (token) hello.token = token;
  return pack(hello);
}

export function encodePing(t0) {
  return pack({ type: "ping", t0 });
}

export function encodeLeave(reason = "") {
  return pack({ type: "leave", reason });
}

/** A ViewerReport: three equal columns of server-clock seconds (0..MAX_REPORT_ROWS),
 * and up to MAX_REPORT_POSES avatars as shown ({ id, t (server clock), root,
 * rotations }) in playout `mode`, for the server's display error; one of them at least. */
export function encodeViewerReport(tCapture, tReceived, tPresented, shown = [], mode = null) {
  const n = tCapture.length;
  if (n > MAX_REPORT_ROWS || tReceived.length !== n || tPresented.length !== n ||
      shown.length > MAX_REPORT_POSES || (n < 1 && !shown.length)) {
    throw new RangeError(`a report holds 0-${MAX_REPORT_ROWS} rows of three equal columns ` +
      `and 0-${MAX_REPORT_POSES} shown poses, one of them at least`);
  }
  const report = { type: "viewer_report", t_capture: packF64(tCapture),
    t_received: packF64(tReceived), t_presented: packF64(tPresented), viewer: "browser" };
  if (shown.length) {
    report.shown = shown.map((s) => ({ avatar_id: s.id, t_presented: s.t,
      root: packF64(s.root), rotations: packLevels(s.rotations) }));
    report.mode = mode;
  }
  return pack(report);
}

// a quaternion's components as int16 levels round(q 32767), as the server reads them
function packLevels(values) {
  const levels = new Int16Array(values.length);
  values.forEach((v, i) => {
    levels[i] = Math.round(Math.min(Math.max(v, -1), 1) * QUAT_LEVELS);
  });
  return new Uint8Array(levels.buffer); // little-endian on every browser's hardware
}

function packF64(values) {
  const out = new Uint8Array(8 * values.length);
  const view = new DataView(out.buffer);
  values.forEach((v, i) => view.setFloat64(8 * i, v, true));
  return out;
}

// ------------------------------------------------------------------ server -> client
/** Bytes -> a checked message: {type: "welcome" | "avatar_roster" | "avatar_batch" |
 * "pong" | "error", ...}. A batch unpacks with `codings` (avatar id -> its roster's
 * coding, or null: 5 bytes a joint), which `learnCodings` keeps. Throws ProtocolError. */
export function decodeMessage(data, codings = new Map()) {
  const bytes = data instanceof Uint8Array ? data : new Uint8Array(data);
  if (bytes.length > MAX_MESSAGE_BYTES) {
    throw new ProtocolError(`message of ${bytes.length} bytes; the limit is ${MAX_MESSAGE_BYTES}`);
  }
  let msg;
  try {
    msg = unpack(bytes, LIMITS);
  } catch (err) {
    throw new ProtocolError(`not a msgpack message (${err.message})`);
  }
  if (!isMap(msg) || typeof msg.type !== "string") {
    throw new ProtocolError("expected a map with a string 'type'");
  }
  const read = READERS[msg.type];
  if (!read) throw new ProtocolError(`unknown message type ${JSON.stringify(msg.type)}`);
  return read(msg, codings);
}

/** What a roster says of its avatars' codings, into `codings` (protocol.pose_coding's
 * RosterCodings.learn); any other message: nothing. */
export function learnCodings(codings, msg) {
  if (msg.type !== "avatar_roster") return;
  for (const id of msg.removed) codings.delete(id);
  for (const info of msg.avatars) codings.set(info.avatarId, info.coding);
}

const READERS = {
  welcome(m) {
    need(m.protocol_version === PROTOCOL_VERSION,
      `welcome: protocol version ${m.protocol_version}; this page speaks ${PROTOCOL_VERSION}`);
    return { type: "welcome", connectionId: count(m.connection_id, "welcome.connection_id"),
      serverTime: time(m.server_time, "welcome.server_time") };
  },
  pong(m) {
    const t = [time(m.t0, "pong.t0"), time(m.t1, "pong.t1"), time(m.t2, "pong.t2")];
    need(t[2] >= t[1], "pong: t2 is before t1");
    return { type: "pong", t0: t[0], t1: t[1], t2: t[2] };
  },
  error(m) {
    return { type: "error", code: text(m.code, "error.code", 64),
      message: text(m.message, "error.message", 1024) };
  },
  avatar_roster(m) {
    const avatars = list(m.avatars ?? [], "avatar_roster.avatars", MAX_AVATARS).map(avatarInfo);
    const removed = list(m.removed ?? [], "avatar_roster.removed", MAX_AVATARS)
      .map((id, i) => count(id, `avatar_roster.removed[${i}]`));
    return { type: "avatar_roster", avatars, removed };
  },
  avatar_batch: avatarBatch,
};

function avatarInfo(a, index) {
  const where = `avatar_roster.avatars[${index}]`;
  need(isMap(a), `${where}: not a map`);
  const names = list(a.joint_names, `${where}.joint_names`, MAX_JOINTS)
    .map((n, j) => text(n, `${where}.joint_names[${j}]`, 64));
  const J = names.length;
  need(J >= 1 && new Set(names).size === J, `${where}.joint_names: empty or repeated`);
  const parents = list(a.parents, `${where}.parents`, MAX_JOINTS);
  need(parents.length === J && parents[0] === -1 &&
    parents.every((p, j) => j === 0 || (Number.isInteger(p) && p >= 0 && p < j)),
  `${where}.parents: must list each joint's parent before it, the root first (-1)`);
  const offsets = f64(a.rest_offsets, `${where}.rest_offsets`);
  need(offsets.length === 3 * J && offsets.every((v) => Math.abs(v) <= MAX_POSITION_M),
    `${where}.rest_offsets: ${J} finite rows of 3 expected`);
  return { avatarId: count(a.avatar_id, `${where}.avatar_id`),
    displayName: text(a.display_name, `${where}.display_name`, 64),
    jointNames: names, parents, restOffsets: offsets, devices: devices(a.devices, where),
    coding: a.coding === undefined || a.coding === null ? null : coding(a.coding, J, where) };
}

/** A roster entry's PoseCoding (protocol/pose_coding.py), checked as Python checks it. */
function coding(c, J, where) {
  where = `${where}.coding`;
  need(isMap(c), `${where}: not a map`);
  const driven = list(c.driven, `${where}.driven`, J);
  const K = driven.length;
  need(K >= 1 && driven.every((j, k) => Number.isInteger(j) && j >= 0 && j < J &&
    (k === 0 || j > driven[k - 1])), `${where}.driven: expected 1 to ${J} ascending joints`);
  const bits = list(c.bits, `${where}.bits`, K);
  const rows = (name, width) => {
    const out = f32(c[name], `${where}.${name}`);
    need(out.length === width * K, `${where}.${name}: ${K} rows of ${width} expected`);
    return out;
  };
  const lo = rows("lo", 3);
  const hi = rows("hi", 3);
  const pre = rows("pre", 4);
  const post = rows("post", 4);
  need(bits.length === K && bits.every((b, k) => Array.isArray(b) && b.length === 3 &&
    b.every((n, i) => Number.isInteger(n) && n >= 0 && n <= MAX_PARAMETER_BITS &&
      (n === 0 || (lo[3 * k + i] < hi[3 * k + i] && Math.abs(lo[3 * k + i]) <= 2 * Math.PI &&
        Math.abs(hi[3 * k + i]) <= 2 * Math.PI)))),
  `${where}.bits: each joint's three bits (0 to ${MAX_PARAMETER_BITS}) agree with lo < hi`);
  need([pre, post].every((q) => q.every(Number.isFinite)), `${where}: frames not finite`);
  need(c.rest instanceof Uint8Array && c.rest.length === 5 * J, `${where}.rest: ${J} rotations expected`);
  let rest;
  try {
    rest = dequantizeRotations(c.rest);
  } catch (err) {
    if (err instanceof RotationError) throw new ProtocolError(`${where}.rest: ${err.message}`);
    throw err;
  }
  const total = bits.reduce((a, b) => a + (b[0] + b[1] + b[2] || QUATERNION_BITS), 0);
  return { driven, bits, lo, hi, pre, post, rest, numJoints: J, nbytes: Math.ceil(total / 8) };
}

/** A roster entry's devices: distinct known roles; absent (an older recording): none. */
function devices(v, where) {
  const roles = v === undefined ? [] : list(v, `${where}.devices`, DEVICE_ROLES.length);
  need(roles.every((r) => DEVICE_ROLES.includes(r)) && new Set(roles).size === roles.length,
    `${where}.devices: expected distinct device roles (${DEVICE_ROLES.join(", ")})`);
  return roles;
}

const BATCH_COLUMNS = { avatar_ids: 8, seqs: 8, roots: 12, joint_counts: 2, capture_age: 4,
  receive_age: 4, solved_age: 4 };

/** An AvatarBatch checked whole: columns of one row per avatar; rotations (J_b per avatar,
 * 4 numbers each) in one Float64Array, each avatar's unpacked by its coding. */
function avatarBatch(m, codings) {
  for (const name of [...Object.keys(BATCH_COLUMNS), "rotations"]) {
    need(m[name] instanceof Uint8Array, `avatar_batch.${name}: expected packed bytes`);
  }
  const n = m.avatar_ids.length / 8;
  need(Number.isInteger(n) && n <= MAX_AVATARS, "avatar_batch.avatar_ids: bad length");
  for (const [name, size] of Object.entries(BATCH_COLUMNS)) {
    need(m[name].length === n * size, `avatar_batch.${name}: ${m[name].length} bytes ` +
      `for ${n} avatars`);
  }
  const ids = ints(m.avatar_ids, "avatar_batch.avatar_ids");
  need(new Set(ids).size === n, "avatar_batch.avatar_ids: an avatar appears twice");
  const seqs = ints(m.seqs, "avatar_batch.seqs");
  const counts = Array.from({ length: n }, (_, b) => view(m.joint_counts).getUint16(2 * b, true));
  need(counts.every((c) => c >= 1 && c <= MAX_JOINTS), "avatar_batch.joint_counts: out of 1-256");
  const rootBytes = view(m.roots);
  const roots = Float64Array.from({ length: 3 * n }, (_, i) => rootBytes.getFloat32(4 * i, true));
  need(roots.every((v) => Math.abs(v) <= MAX_POSITION_M), "avatar_batch.roots: not finite " +
    `or beyond ${MAX_POSITION_M} m`);
  const codes = ids.map((id, b) => {
    const c = codings.get(id) ?? null;
    need(c === null || c.numJoints === counts[b], `avatar_batch: avatar ${b} (id ${id}): ` +
      `${counts[b]} joints, but its roster's coding has ${c?.numJoints}`);
    return c;
  });
  const sizes = codes.map((c, b) => (c === null ? 5 * counts[b] : c.nbytes));
  const need_ = sizes.reduce((a, s) => a + s, 0);
  need(m.rotations.length === need_, `avatar_batch.rotations: ${m.rotations.length} bytes of ` +
    `rotations; the avatars' joint counts and codings need ${need_}`);
  const total = counts.reduce((a, c) => a + c, 0);
  const rotations = new Float64Array(4 * total);
  let offset = 0;
  let first = 0;
  codes.forEach((c, b) => {
    try {
      if (c === null) {
        rotations.set(dequantizeRotations(m.rotations.subarray(offset, offset + sizes[b])), 4 * first);
      } else {
        unpackFrame(m.rotations, offset, c, rotations, first);
      }
    } catch (err) {
      if (err instanceof RotationError) {
        throw new ProtocolError(`avatar_batch.rotations: avatar ${b}: ${err.message}`);
      }
      throw err;
    }
    offset += sizes[b];
    first += counts[b];
  });
  const tSent = time(m.t_sent, "avatar_batch.t_sent");
  const times = (name) => f32(m[name], `avatar_batch.${name}`).map((age) => {
    need(Math.abs(age) <= MAX_AGE_S, `avatar_batch.${name}: ages are within ${MAX_AGE_S} s`);
    return tSent - age;
  });
  return { type: "avatar_batch", avatarIds: ids, seqs, counts, roots, rotations,
    tCapture: Float64Array.from(times("capture_age")),
    tServerReceive: Float64Array.from(times("receive_age")),
    tSolved: Float64Array.from(times("solved_age")), tSent, lost: lostBits(m.lost, n) };
}

/** The `lost` column: one uint16 of DEVICE_ROLES bits per avatar. */
function lostBits(bytes, n) {
  need(bytes instanceof Uint8Array && bytes.length === 2 * n,
    `avatar_batch.lost: expected ${2 * n} bytes of packed <u2 for ${n} avatars`);
  const v = view(bytes);
  const out = Uint16Array.from({ length: n }, (_, b) => v.getUint16(2 * b, true));
  need(out.every((bits) => bits < LOST_BITS_LIMIT),
    `avatar_batch.lost: bits beyond the ${DEVICE_ROLES.length} device roles`);
  return out;
}

// ------------------------------------------------------------------ field checks
function need(ok, why) {
  if (!ok) throw new ProtocolError(why);
}

function isMap(v) {
  return v !== null && typeof v === "object" && !Array.isArray(v) && !(v instanceof Uint8Array);
}

function view(bytes) {
  return new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
}

function time(v, where) {
  need(typeof v === "number" && Number.isFinite(v), `${where}: expected a finite time`);
  return v;
}

function count(v, where) {
  need(Number.isSafeInteger(v) && v >= 0, `${where}: expected an integer >= 0`);
  return v;
}

function text(v, where, max) {
  need(typeof v === "string" && v.length <= max, `${where}: expected text of <= ${max} chars`);
  return v;
}

function list(v, where, max) {
  need(Array.isArray(v) && v.length <= max, `${where}: expected a list of <= ${max} items`);
  return v;
}

function f64(bytes, where) {
  need(bytes instanceof Uint8Array && bytes.length % 8 === 0, `${where}: expected packed <f8`);
  const v = view(bytes);
  const out = Float64Array.from({ length: bytes.length / 8 }, (_, i) => v.getFloat64(8 * i, true));
  need(out.every(Number.isFinite), `${where}: times must be finite`);
  return out;
}

function f32(bytes, where) {
  need(bytes instanceof Uint8Array && bytes.length % 4 === 0, `${where}: expected packed <f4`);
  const v = view(bytes);
  return Float64Array.from({ length: bytes.length / 4 }, (_, i) => v.getFloat32(4 * i, true));
}

function ints(bytes, where) {
  const v = view(bytes);
  return Array.from({ length: bytes.length / 8 }, (_, i) => {
    const value = v.getBigInt64(8 * i, true);
    need(value >= 0n && value <= BigInt(Number.MAX_SAFE_INTEGER), `${where}[${i}]: out of range`);
    return Number(value);
  });
}
