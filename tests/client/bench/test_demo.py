"""`posecast demo` end to end: a server process, players and spectators on loopback."""

from __future__ import annotations

import json
import os
import shutil
import time

import pytest

from posecast.client.cli import main


def test_demo_delivers_every_solved_frame_to_every_spectator(
        capsys: pytest.CaptureFixture[str]) -> None:
    cores = os.sched_getaffinity(0)
    t_start = time.monotonic()
    assert main(["demo", "--players", "2", "--spectators", "2", "--seconds", "2",
                 "--json"]) == 0
    run_ms = (time.monotonic() - t_start) * 1e3
    assert os.sched_getaffinity(0) == cores  # the spectators' pinning is undone
    doc = json.loads(capsys.readouterr().out)
    assert doc["players"] == 2 and doc["spectators"] == 2
    # two players at 90 Hz for two seconds: a loaded machine skips late slots, so only
    # the schedule's bound is exact (181 slots in the 2 s after a player's first frame,
    # plus that frame's own when it came late)
    assert 0 < doc["frames_sent"] <= 2 * (2 * 90 + 2)
    # exact accounting, whatever the load: the server solves every frame sent, but one
    # that a newer frame of the same player superseded before its burst was solved (or
    # one still unsolved when its player left); the demo's players send none it rejects,
    # nor any whose solved row a spectator would refuse (unsendable)
    assert doc["frames_rejected"] == 0 and doc["rejected"] == {}
    assert doc["frames_unsendable"] == 0
    assert doc["frames_sent"] == (doc["frames_solved"] + doc["frames_superseded"]
                                  + doc["frames_discarded"] + doc["frames_rejected"]
                                  + doc["frames_unsendable"])
    # every solved avatar-frame reaches every spectator, but one that a spectator's
    # outbox replaced with a newer frame of the avatar before it could send it
    assert doc["frames_solved"] > 0
    assert doc["frames_delivered"] + doc["frames_dropped"] == doc["frames_solved"] * 2
    stages = doc["latency_ms"]
    for stage in ("capture_to_server", "solve", "server", "network_to_spectator",
                  "capture_to_spectator", "capture_to_decoded"):
        p = stages[stage]
        # within the run: a stage that spans two clocks is off by the errors of their
        # offset estimates, at most half a ping's round trip each (on a loaded machine
        # more than a short stage itself: no sign is certain)
        assert -run_ms < p["p50"] <= p["p95"] <= p["p99"] < 2 * run_ms, stage
    # on the server's clock alone: each frame is solved after it came, sent after that
    assert stages["solve"]["p50"] > 0.0
    for q in ("p50", "p95", "p99"):
        assert stages["solve"][q] <= stages["server"][q], q
        # on a spectator's clock alone: each frame is decoded after it was received
        assert stages["capture_to_spectator"][q] <= stages["capture_to_decoded"][q], q


def test_demo_renders_moving_avatars(tmp_path, capsys: pytest.CaptureFixture[str]) -> None:
    import numpy as np
    from PIL import Image

    out = tmp_path / "frames"
    t_start = time.monotonic()
    assert main(["demo", "--players", "2", "--spectators", "1", "--seconds", "3",
                 "--render", str(out), "--json"]) == 0
    run_ms = (time.monotonic() - t_start) * 1e3
    doc = json.loads(capsys.readouterr().out)
    files = sorted(out.glob("*.png"))
    # every frame drawn (with avatars) is written; how many: ~30 a second on an idle
    # machine, a few on a loaded one (the software renderer's CPU time)
    assert doc["frames_rendered"] == len(files) >= 2
    render = doc["latency_ms"]["capture_to_render"]
    assert -run_ms < render["p50"] <= render["p99"] < 2 * run_ms  # two clocks: see above
    # the presented frame comes after the viewer received it (one process, one clock)
    assert doc["latency_ms"]["receive_to_render"]["p50"] > 0.0
    # the first and the last frame drawn: the whole session apart, however few between
    first, last = (np.asarray(Image.open(f), dtype=np.int16) for f in (files[0], files[-1]))
    background = np.median(last.reshape(-1, 3), axis=0)
    # avatars are drawn (pixels far from the floor colour) and they moved between frames
    assert (np.abs(last - background).sum(axis=2) > 60).mean() > 0.01
    assert (np.abs(first - last).sum(axis=2) > 30).mean() > 0.002


def test_demo_over_two_server_processes_relays_every_solved_frame(
        capsys: pytest.CaptureFixture[str]) -> None:
    """`demo --servers 2`: the players on the first process, the spectators spread over
    both (the second's through Redis); every solved frame reaches the other process, and
    every spectator gets it or counts it dropped; the relay hop is in the table."""
    if shutil.which("redis-server") is None:
        pytest.skip("no redis-server here (apt-get install redis-server)")
    assert main(["demo", "--players", "2", "--spectators", "2", "--seconds", "2",
                 "--servers", "2", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["servers"] == 2 and doc["frames_solved"] > 0
    assert doc["frames_relayed"] == doc["frames_solved"]  # to the one other process
    assert doc["frames_delivered"] + doc["frames_dropped"] == doc["frames_solved"] * 2
    relay = doc["latency_ms"]["relay"]
    assert 0.0 < relay["p50"] <= relay["p99"] < 2000.0


def test_demo_servers_must_be_one_or_more(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["demo", "--servers", "0"])
    assert exit_.value.code == 2
    assert "--servers" in capsys.readouterr().err


def test_a_room_of_3_4_and_6_point_players_losing_devices(
        capsys: pytest.CaptureFixture[str]) -> None:
    """`demo --devices 3 --devices 4 --devices 6 --dropouts ...`: every frame solved or
    superseded (none refused for a missing device), both identities hold, and the losses
    are counted by device."""
    assert main(["demo", "--players", "3", "--spectators", "1", "--seconds", "3",
                 "--devices", "3", "--devices", "4", "--devices", "6",
                 "--dropouts", "60,max=0.5,seed=3"]) == 0
    out = capsys.readouterr().out
    assert "tracker sets 3 x1 / 4 x1 / 6 x1" in out and "dropouts 60/min" in out
    counts = {line.split()[0]: line.split()[1] for line in out.splitlines()
              if line.startswith("  ") and len(line.split()) > 1}
    assert counts["rejected"] == "0", out
    assert "= solved + superseded + discarded + rejected + unsendable: yes" in out, out
    assert "= delivered + dropped: yes" in out, out
    assert int(counts["lost"]) > 0
    assert "losses by device:" in out


def test_demo_json_names_the_sets_and_counts_losses(
        capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "--players", "2", "--spectators", "1", "--seconds", "2",
                 "--devices", "3", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["devices"] == ["3", "3"] and doc["dropouts"] is None
    assert doc["frames_rejected"] == 0 and doc["rejected"] == {}
    assert doc["frames_sent"] == (doc["frames_solved"] + doc["frames_superseded"]
                                  + doc["frames_discarded"])
    assert doc["device_lost_frames"] == {}  # head and hands only, none of them lost
