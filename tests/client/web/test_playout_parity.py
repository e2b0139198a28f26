"""One algorithm, two languages: the browser page's playout (client/web/src/playout.js)
against the desktop viewer's (client/viewer/interpolation.py). Both run on the same
recorded stream of frames and arrival times (a 40 +- 10 ms link with a stall, late and
duplicated frames, a clock that syncs after a while), and present the same pose at every
presentation instant, in each of the three modes; the page's constants are the viewer's."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from node_js import node_path, run_node_test

from posecast.client.viewer import interpolation as I
from posecast.client.viewer.interpolation import Interpolator, Mode, Snapshot
from posecast.solver import prediction
from posecast.solver import rotations as R

AVATARS = (3, 8)
JOINTS = 6
OFFSET = 0.5  # the server clock minus the page's
SYNCED_AFTER_S = 0.6  # before this, no clock offset: predict falls back on the least transit
RATE_HZ = 90.0
SECONDS = 2.5
STALL = (101.2, 101.35)  # frames captured then arrive together after it (server clock)


def stream(seed: int = 31) -> list[tuple[float, int, int, float, np.ndarray, np.ndarray]]:
    """(local arrival, avatar, seq, capture on the server clock, rotations (J, 4), root),
    in arrival order: smooth motion, transit 40 +- 10 ms, a stall, late and repeated
    frames."""
    rng = np.random.default_rng(seed)
    out = []
    for a in AVATARS:
        speed = rng.normal(size=(JOINTS, 3)) * 1.5
        phase = rng.uniform(0, 6, (JOINTS, 1))
        for i in range(int(SECONDS * RATE_HZ)):
            tc = 100.0 + i / RATE_HZ + a * 1e-3
            rot = R.from_rotvec(speed * np.sin(2.0 * tc + phase))
            root = np.array([np.sin(tc), 0.9 + 0.05 * np.sin(7 * tc), 0.5 * np.cos(tc)])
            transit = 0.040 + float(np.clip(rng.normal(0.0, 0.010), -0.03, 0.05))
            arrival = tc - OFFSET + transit
            if STALL[0] <= tc <= STALL[1]:
                arrival = max(arrival, STALL[1] - OFFSET + 0.045)
            out.append((arrival, a, i, tc, rot, root))
            if rng.random() < 0.03:  # the same frame again, later
                out.append((arrival + 0.02, a, i, tc, rot, root))
    out.sort(key=lambda f: f[0])
    return out


def events() -> list[dict[str, Any]]:
    """The stream as the page sees it: frames pushed as they arrive, and a presentation
    every 1/60 s (with the clock offset once synced)."""
    frames = stream()
    start, end = frames[0][0], frames[-1][0] + 0.1
    out: list[dict[str, Any]] = []
    k = 0
    for now in np.arange(start, end, 1.0 / 60.0):
        while k < len(frames) and frames[k][0] <= now:
            arrival, a, seq, tc, rot, root = frames[k]
            out.append({"push": [a, seq, tc, arrival, rot.ravel().tolist(), root.tolist()]})
            k += 1
        out.append({"now": float(now),
                    "offset": OFFSET if now - start >= SYNCED_AFTER_S else None})
    return out


def present(stream_events: list[dict[str, Any]], mode: Mode, **settings: float
            ) -> tuple[list[dict[int, dict[str, Any]]], list[list[int]]]:
    """What the desktop viewer's Interpolator presents at each instant, and each avatar's
    underruns and drops."""
    interp = Interpolator(mode, **settings)  # type: ignore[arg-type]
    shown = []
    for event in stream_events:
        if "push" in event:
            a, seq, tc, arrival, rot, root = event["push"]
            interp.buffer(a).add(Snapshot(seq, tc, arrival, np.array(rot).reshape(JOINTS, 4),
                                          np.array(root)))
            continue
        offset = event["offset"]
        sampled = interp.sample(event["now"], None if offset is None
                                else lambda t, o=offset: t + o)
        shown.append({a: {"rotations": s.rotations.ravel().tolist(),
                          "root": np.asarray(s.root).tolist(), "t_capture": s.t_capture,
                          "held": s.held, "newest_seq": s.newest.seq}
                      for a, s in sampled.items()})
    counts = [[interp.buffers[a].underruns, interp.buffers[a].dropped]
              for a in sorted(interp.buffers)]
    return shown, counts


def run_page(node: str, tmp_path: Path, stream_events: list[dict[str, Any]],
             consts: dict[str, Any], modes: dict[str, Any]) -> str:
    fixture = tmp_path / "playout.json"
    fixture.write_text(json.dumps({
        "constants": consts, "events": stream_events,
        "presented": {m: shown for m, (shown, _) in modes.items()},
        "counts": {m: counts for m, (_, counts) in modes.items()}}))
    return run_node_test(node, "playout.test.mjs", {"POSECAST_PLAYOUT_FIXTURE": str(fixture)})


def constants() -> dict[str, Any]:
    """The viewer's constants as the page names them."""
    p = prediction.DEFAULT
    assert p.kind == "posecast" and not (np.isfinite(p.fast_speed) or np.isfinite(p.fast_turn))
    return {"default_mode": Mode.INTERPOLATE.value, "modes": [m.value for m in Mode],
            "capacity": I.DEFAULT_CAPACITY, "window": I.DEFAULT_WINDOW, "k": I.DEFAULT_K,
            "min_delay": I.DEFAULT_MIN_DELAY, "max_delay": I.DEFAULT_MAX_DELAY,
            "fallback_interval": I.FALLBACK_INTERVAL,
            "predictor": {"windowS": p.window_s, "decayS": p.decay_s,
                          "accelGain": p.accel_gain, "maxHorizonS": p.max_horizon_s}}


def test_the_stream_exercises_every_path() -> None:
    """Holds, drops, interpolation and prediction all happen in the recorded stream (so
    that the parity below covers them)."""
    stream_events = events()
    interpolated, counts = present(stream_events, Mode.INTERPOLATE)
    assert all(dropped > 0 for _, dropped in counts)  # repeated and late frames
    assert all(underruns > 0 for underruns, _ in counts)  # the stall
    shown = [s for instant in interpolated for s in instant.values()]
    assert any(s["held"] for s in shown) and sum(not s["held"] for s in shown) > 100
    # predict carries poses past the newest frame's capture
    ahead = [s["t_capture"] for i in present(stream_events, Mode.PREDICT)[0] for s in i.values()]
    newest = [s["t_capture"] for i in present(stream_events, Mode.LATEST)[0] for s in i.values()]
    assert sum(a > n + 1e-3 for a, n in zip(ahead, newest, strict=True)) > 100


def test_the_page_presents_what_the_desktop_viewer_presents(tmp_path: Path) -> None:
    stream_events = events()
    modes = {m.value: present(stream_events, m) for m in Mode}
    out = run_page(node_path(), tmp_path, stream_events, constants(), modes)
    assert "# pass 4" in out, out  # the constants and the three modes


def test_a_changed_constant_is_caught(tmp_path: Path) -> None:
    """The parity fails when the page's numbers are not the viewer's: here the viewer's
    k (the jitter percentile's multiplier) changed on the Python side only, its poses and
    its constants both."""
    stream_events = events()
    modes = {"interpolate": present(stream_events, Mode.INTERPOLATE, k=2.0)}
    with pytest.raises(AssertionError, match="fail 2"):
        run_page(node_path(), tmp_path, stream_events, {**constants(), "k": 2.0}, modes)
