// The page's protocol, clock, skinning and device wording against Python's:
// tests/client/web/test_browser_js.py writes what Python encodes and computes to POSECAST_JS_FIXTURE,
// runs this file with node --test, then decodes in Python what this file writes to
// POSECAST_JS_OUT.
import assert from "node:assert/strict";
import { readFileSync, writeFileSync } from "node:fs";
import { test } from "node:test";
import { ClockEstimator } from "../src/clock.js";
import { deviceText, lostLines } from "../src/devices.js";
import {
  decodeMessage, encodeHello, encodeLeave, encodePing, encodeViewerReport, learnCodings,
  ProtocolError, rolesOfBits,
} from "../src/protocol.js";
import { dequantizeRotations, RotationError } from "../src/quantize.js";
import { bindSkeleton, boneMatrices, fitAvatar, labelAnchor, pose } from "../src/skinning.js";

const path = process.env.POSECAST_JS_FIXTURE;
const fixture = path ? JSON.parse(readFileSync(path, "utf8")) : null;
const skip = fixture ? false : "run by pytest tests/client/web/test_browser_js.py (it writes the fixture)";
const bytes = (hex) => Uint8Array.from(Buffer.from(hex, "hex"));

test("rotations decode bit for bit as protocol/quantize.py decodes them", { skip }, () => {
  for (const { wire, rotations } of fixture.rotations) {
    const got = dequantizeRotations(bytes(wire));
    assert.deepEqual(Array.from(got), rotations); // exact: the same double operations
  }
  for (const { wire, error } of fixture.bad_rotations) {
    assert.throws(() => dequantizeRotations(bytes(wire)),
      (err) => err instanceof RotationError && err.message === error);
  }
});

test("server messages decode to Python's values", { skip }, () => {
  const batch = decodeMessage(bytes(fixture.batch.wire));
  const want = fixture.batch.values;
  assert.equal(batch.type, "avatar_batch");
  assert.deepEqual(batch.avatarIds, want.avatar_ids);
  assert.deepEqual(batch.seqs, want.seqs);
  assert.deepEqual(batch.counts, want.joint_counts);
  assert.deepEqual(Array.from(batch.roots), want.roots);
  assert.deepEqual(Array.from(batch.rotations), want.rotations);
  for (const [js, py] of [["tCapture", "t_capture"], ["tServerReceive", "t_server_receive"],
    ["tSolved", "t_solved"]]) {
    assert.deepEqual(Array.from(batch[js]), want[py]);
  }
  assert.equal(batch.tSent, want.t_sent);
  assert.deepEqual(Array.from(batch.lost), want.lost);
  assert.deepEqual(Array.from(batch.lost, rolesOfBits), want.lost_roles);
  const roster = decodeMessage(bytes(fixture.roster.wire));
  assert.deepEqual(roster.removed, fixture.roster.removed);
  assert.equal(roster.avatars.length, 1);
  const [info] = roster.avatars;
  assert.equal(info.displayName, fixture.roster.display_name);
  assert.deepEqual(info.jointNames, fixture.roster.joint_names);
  assert.deepEqual(info.parents, fixture.roster.parents);
  assert.deepEqual(Array.from(info.restOffsets), fixture.roster.rest_offsets);
  assert.deepEqual(info.devices, fixture.roster.devices);
  assert.deepEqual(decodeMessage(bytes(fixture.roster.old_wire)).avatars[0].devices, []);
  assert.throws(() => decodeMessage(bytes(fixture.roster.bad_wire)),
    (err) => err instanceof ProtocolError && err.message.includes("avatars[0].devices"));
  assert.deepEqual(decodeMessage(bytes(fixture.pong)), { type: "pong", t0: 1.5, t1: 2.25, t2: 2.5 });
  assert.deepEqual(decodeMessage(bytes(fixture.error)),
    { type: "error", code: "invalid", message: "hello.room: no" });
  assert.equal(decodeMessage(bytes(fixture.welcome)).type, "welcome");
});

test("protocol 4: a batch unpacks by its roster's coding as Python unpacks it", { skip }, () => {
  const codings = new Map();
  const roster = decodeMessage(bytes(fixture.coded.roster), codings);
  learnCodings(codings, roster);
  assert.equal(codings.get(21).nbytes, fixture.coded.nbytes);
  const batch = decodeMessage(bytes(fixture.coded.wire), codings);
  const want = fixture.coded.rotations;
  assert.equal(batch.rotations.length, want.length);
  // the same double operations but sin, cos and sqrt, whose last bit may differ
  batch.rotations.forEach((v, i) => assert.ok(Math.abs(v - want[i]) < 1e-12, `${i}: ${v} vs ${want[i]}`));
  assert.deepEqual(Array.from(batch.tCapture), fixture.coded.t_capture);
  assert.throws(() => decodeMessage(bytes(fixture.coded.spoiled.padding), codings),
    (err) => err instanceof ProtocolError && err.message.includes("avatar 0: padding bits"));
  assert.throws(() => decodeMessage(bytes(fixture.coded.spoiled.short), codings),
    (err) => err instanceof ProtocolError && err.message.includes("codings need"));
  // without the roster the frame cannot be read: refused, not misread
  assert.throws(() => decodeMessage(bytes(fixture.coded.wire)),
    (err) => err instanceof ProtocolError && err.message.includes("codings need"));
  learnCodings(codings, { type: "avatar_roster", avatars: [], removed: [21] });
  assert.equal(codings.has(21), false);
});

test("malformed server messages are refused with a ProtocolError", { skip }, () => {
  for (const { wire, words } of fixture.bad_messages) {
    assert.throws(() => decodeMessage(bytes(wire)),
      (err) => err instanceof ProtocolError && err.message.includes(words), words);
  }
});

test("a batch's lost bits name the devices on the label and in the HUD", { skip }, () => {
  const batch = decodeMessage(bytes(fixture.batch.wire));
  const avatars = fixture.lost.avatars.map((a, b) => ({ ...a, lost: batch.lost[b] }));
  // the HUD: the desktop viewer's lines, only for the avatar that lost some
  assert.deepEqual(lostLines(avatars), fixture.lost.lines);
  assert.deepEqual(lostLines(avatars.map((a) => ({ ...a, lost: 0 }))), []);
  // the label under each name: its tracker set, and what it lost now
  const [whole, partial] = avatars;
  assert.equal(deviceText(whole.devices, whole.lost), "11 devices");
  assert.equal(deviceText(partial.devices, partial.lost),
    "6 devices — lost: hip, left_foot, chest");
  assert.equal(deviceText([], 0), ""); // an older recording's avatar: no line
  assert.equal(deviceText([], 1 << 6), "lost: left_foot");
});

test("the clock estimate follows protocol/clock.py sample by sample", { skip }, () => {
  const clock = new ClockEstimator();
  for (const { sample, accepted, offset, rtt } of fixture.clock) {
    assert.equal(clock.add(...sample), accepted);
    assert.equal(clock.offset, offset);
    assert.equal(clock.rtt, rtt ?? Infinity); // JSON has no infinity: null before a sample
  }
});

test("the mesh is fitted and posed as the desktop viewer fits and poses it", { skip }, () => {
  const bind = bindSkeleton(fixture.avatar_json);
  const roster = decodeMessage(bytes(fixture.skinning.roster));
  const fitted = fitAvatar(bind, roster.avatars[0]);
  const { rotations, root, matrices, anchor } = fixture.skinning;
  const posed = pose(bind, fitted, Float64Array.from(rotations.flat()), 0, Float64Array.from(root));
  const got = boneMatrices(bind, fitted, posed);
  matrices.forEach((m, j) => {
    for (let r = 0; r < 4; r++) {
      for (let c = 0; c < 4; c++) {
        const diff = Math.abs(got[16 * j + 4 * c + r] - m[r][c]);
        assert.ok(diff < 1e-9, `joint ${j} [${r}][${c}]: ${got[16 * j + 4 * c + r]} vs ${m[r][c]}`);
      }
    }
  });
  labelAnchor(bind, fitted, posed).forEach((v, k) => assert.ok(Math.abs(v - anchor[k]) < 1e-9));
});

test("client messages are encoded for Python to decode", { skip }, () => {
  const out = {
    hello: Buffer.from(encodeHello("lab-1", "browser", "a.token")).toString("hex"),
    ping: Buffer.from(encodePing(12.375)).toString("hex"),
    leave: Buffer.from(encodeLeave("page closed")).toString("hex"),
    report: Buffer.from(encodeViewerReport([1.0, 2.5], [1.25, 2.75], [1.5, 3.0])).toString("hex"),
    // a shown pose alone (no rows): an avatar's root and two joints, as the page sends them
    shown: Buffer.from(encodeViewerReport([], [], [], [{ id: 7, t: 3.5,
      root: Float64Array.of(0.1, 0.9, -0.2),
      rotations: Float64Array.of(0, 0, 0, 1, 0.5, -0.5, 0.5, 0.5) }], "predict")).toString("hex"),
  };
  assert.throws(() => encodeViewerReport([], [], []), RangeError);
  const pose = { id: 1, t: 1.5, root: [0, 0, 0], rotations: [0, 0, 0, 1] };
  assert.throws(() => encodeViewerReport([], [], [], Array(5).fill(pose), "predict"), RangeError);
  writeFileSync(process.env.POSECAST_JS_OUT, JSON.stringify(out));
});
