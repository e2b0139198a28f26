"""`posecast demo --network`: the real CLI with the emulator between every client and the
server; its display error per viewer mode against a loopback run."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from typing import Any

from posecast.client.viewer.interpolation import Mode

WAIT = 300.0  # a subprocess that spawns a server, players and the emulator, on 2 cores


# the first second of an avatar is not scored (display_error.SETTLE_S): 3 s once left
# 11 scored frames in a mode (~190 as a rule, also beside a CPU hog or a 16 + 16 demo)
# while the suite ran on two workers; the cause was not found, so a failure says more
DEMO_S = 5


def _demo(*extra: str) -> dict[str, Any]:
    done = subprocess.run([sys.executable, "-m", "posecast.client.cli", "demo",
                           "--players", "2", "--spectators", "1", "--seconds", str(DEMO_S),
                           "--json", *extra], capture_output=True, text=True, timeout=WAIT,
                          env={**os.environ, "PYTHONWARNINGS": "ignore"})
    assert done.returncode == 0, done.stderr
    doc: dict[str, Any] = json.loads(done.stdout)
    return doc


def test_demo_over_an_emulated_link_reports_the_display_error_of_each_mode() -> None:
    loopback = _demo()
    far = _demo("--network", "40ms+-10ms")
    assert loopback["network"] == "loopback" and far["network"] == "40ms+-10ms"
    modes = {m.value for m in Mode}  # interpolate, zero-buffer and predict
    for doc in (loopback, far):
        errors = doc["display_error_mm"]
        assert set(errors) == modes
        for e in errors.values():
            # ~3.5 s per avatar at 60 Hz, once the buffers settled
            assert e["n"] > 30, {k: doc[k] for k in ("network", "display_error_mm",
                                                     "latency_ms", "frames_sent")}
            assert 0.0 < e["p50"] <= e["p95"]
    # each way 30 to 50 ms: nothing reaches a spectator in less than 60 ms
    assert far["latency_ms"]["capture_to_spectator"]["p50"] >= 60.0
    assert loopback["latency_ms"]["capture_to_spectator"]["p50"] < 60.0
    # what the spectator shows lags the body further in the modes that show received
    # poses as they are: the walker's joints move ~1.3 mm a millisecond (~117 mm at
    # 91 ms, p50), and nothing arrives in under 60 ms, so at least ~75 mm, where a quiet
    # loopback shows 9-16 mm. A floor, not loopback's plus 30 mm: that failed once under
    # the suite's two workers, loopback's interpolate buffer then holding ~100 ms
    # (130 mm); load only adds to the far run's error
    for mode in (Mode.LATEST.value, Mode.INTERPOLATE.value):
        assert far["display_error_mm"][mode]["p50"] > 60.0, (mode, far["display_error_mm"])
    # the buffer holds frames longer as it measures the link's jitter: +-10 ms each way
    # spreads arrivals over ~40 ms, and a capture interval (11 ms) comes on top (load
    # only adds jitter; tests/client/bench/test_network.py compares a calm and a jittery link)
    assert far["playout_delay_ms"]["p50"] >= 25.0


def test_a_player_the_server_disconnects_ends_the_demo_in_one_line() -> None:
    """A server that takes 10 frames a second and calls 10 more a flood: the 90 Hz
    player is closed (1008, flooding). The demo says so in one line (after the player's
    own warning), exit 1. (A network stall no longer does it: the server counts frames
    per 1 s window and drops what a longer stall piles up, tests/server/test_limits.py.)"""
    done = subprocess.run([sys.executable, "-m", "posecast.client.cli", "demo",
                           "--players", "1", "--spectators", "1", "--seconds", "8",
                           "--network", "20ms", "--limit", "frames_per_s=10",
                           "--limit", "frame_flood_factor=1", "--json"],
                          capture_output=True, text=True, timeout=WAIT,
                          env={**os.environ, "PYTHONWARNINGS": "ignore"})
    assert done.returncode == 1, done.stderr
    assert done.stdout == ""
    last = done.stderr.strip().splitlines()[-1]
    assert last.startswith("posecast demo: a player was disconnected: "), done.stderr
    assert "flooding" in last and "rate_limited" in done.stderr, done.stderr
    assert "Traceback" not in done.stderr
