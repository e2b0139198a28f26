"""`posecast demo` end to end: a server process, players and spectators on loopback."""

from __future__ import annotations

import json
import os

import pytest

from posecast.client.cli import main


def test_demo_delivers_every_solved_frame_to_every_spectator(
        capsys: pytest.CaptureFixture[str]) -> None:
    cores = os.sched_getaffinity(0)
    assert main(["demo", "--players", "2", "--spectators", "2", "--seconds", "2",
                 "--json"]) == 0
    assert os.sched_getaffinity(0) == cores  # the spectators' pinning is undone
    doc = json.loads(capsys.readouterr().out)
    assert doc["players"] == 2 and doc["spectators"] == 2
    # two players at 90 Hz for two seconds (the schedule may skip a late slot or two)
    assert 280 <= doc["frames_sent"] <= 362
    assert doc["frames_solved"] >= doc["frames_sent"] - 8  # superseded ones are counted
    assert doc["frames_delivered"] == doc["frames_solved"] * 2
    stages = doc["latency_ms"]
    for stage in ("capture_to_server", "server", "capture_to_spectator"):
        p = stages[stage]
        assert 0.0 < p["p50"] <= p["p95"] <= p["p99"], stage
    # each stage is part of the whole: receive-to-sent is inside capture-to-spectator
    assert stages["server"]["p50"] < stages["capture_to_spectator"]["p50"]


def test_demo_renders_moving_avatars(tmp_path, capsys: pytest.CaptureFixture[str]) -> None:
    import numpy as np
    from PIL import Image

    out = tmp_path / "frames"
    assert main(["demo", "--players", "2", "--spectators", "1", "--seconds", "3",
                 "--render", str(out), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    files = sorted(out.glob("*.png"))
    assert doc["frames_rendered"] == len(files) >= 30  # ~30 fps for 3 s
    render = doc["latency_ms"]["capture_to_render"]
    assert 0.0 < render["p50"] <= render["p99"]
    # the presented frame comes after the spectator received it
    assert render["p50"] > doc["latency_ms"]["capture_to_spectator"]["p50"]
    first, last = (np.asarray(Image.open(f), dtype=np.int16) for f in (files[5], files[-1]))
    background = np.median(last.reshape(-1, 3), axis=0)
    # avatars are drawn (pixels far from the floor colour) and they moved between frames
    assert (np.abs(last - background).sum(axis=2) > 60).mean() > 0.01
    assert (np.abs(first - last).sum(axis=2) > 30).mean() > 0.002
