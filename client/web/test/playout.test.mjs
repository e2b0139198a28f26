// The page's playout against the desktop viewer's: tests/client/web/test_playout_parity.py
// runs client/viewer/interpolation.py on a recorded stream of frames and arrival times,
// writes the stream, the presentation instants and what Python presented at each to
// POSECAST_PLAYOUT_FIXTURE, and runs this file with node --test.
import assert from "node:assert/strict";
import { readFileSync } from "node:fs";
import { test } from "node:test";
import * as playout from "../src/playout.js";

const path = process.env.POSECAST_PLAYOUT_FIXTURE;
const fixture = path ? JSON.parse(readFileSync(path, "utf8")) : null;
const skip = fixture ? false : "run by pytest tests/client/web/test_playout_parity.py (it writes the fixture)";
const TOLERANCE = 1e-9; // both sides compute in doubles; the wire's own error is ~1e-3

test("the page's constants are the desktop viewer's", { skip }, () => {
  const c = fixture.constants;
  assert.equal(playout.DEFAULT_MODE, c.default_mode);
  assert.deepEqual(playout.MODES, c.modes);
  assert.equal(playout.DEFAULT_CAPACITY, c.capacity);
  assert.equal(playout.DEFAULT_WINDOW, c.window);
  assert.equal(playout.DEFAULT_K, c.k);
  assert.equal(playout.DEFAULT_MIN_DELAY, c.min_delay);
  assert.equal(playout.DEFAULT_MAX_DELAY, c.max_delay);
  assert.equal(playout.FALLBACK_INTERVAL, c.fallback_interval);
  assert.deepEqual(playout.PREDICTOR, c.predictor);
});

for (const mode of fixture ? Object.keys(fixture.presented) : ["interpolate"]) {
  test(`${mode}: every pose presented is the desktop viewer's`, { skip }, () => {
    const p = new playout.Playout(mode);
    const want = fixture.presented[mode];
    let shown = 0;
    for (const event of fixture.events) {
      if (event.push) {
        const [id, seq, tCapture, tArrival, rotations, root] = event.push;
        p.push(id, { seq, tCapture, tArrival, rotations: Float64Array.from(rotations),
          root: Float64Array.from(root) });
        continue;
      }
      const got = p.sample(event.now, event.offset);
      const expected = want[shown++];
      assert.deepEqual([...got.keys()].sort(), Object.keys(expected).map(Number).sort(),
        `instant ${event.now}`);
      for (const [id, s] of got) {
        const e = expected[id];
        const where = `avatar ${id} at ${event.now} (${mode})`;
        assert.equal(s.held, e.held, where);
        assert.equal(s.newest.seq, e.newest_seq, where);
        assert.ok(Math.abs(s.tCapture - e.t_capture) <= 1e-12, `${where}: t_capture`);
        for (let i = 0; i < 3; i++) assert.ok(Math.abs(s.root[i] - e.root[i]) <= TOLERANCE, `${where}: root`);
        for (let i = 0; i < e.rotations.length; i++) {
          assert.ok(Math.abs(s.rotations[i] - e.rotations[i]) <= TOLERANCE,
            `${where}: rotation ${i}: ${s.rotations[i]} against ${e.rotations[i]}`);
        }
      }
    }
    assert.equal(shown, want.length);
    const buffers = [...p.buffers.entries()].sort(([a], [b]) => a - b);
    assert.deepEqual(buffers.map(([, b]) => [b.underruns, b.dropped]), fixture.counts[mode]);
  });
}
