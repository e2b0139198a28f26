"""The bench commands keep DESIGN.md's JSON contract (other tools read it)."""

from __future__ import annotations

import json

import pytest

from posecast.client.cli import main


def test_bench_solver_json(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "solver", "--avatars", "1,3", "--seconds", "0.2", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["solver"] == "analytic"
    assert [r["avatars"] for r in doc["results"]] == [1, 3]
    for r in doc["results"]:
        assert 0.0 < r["us_per_avatar_frame"] < 10_000.0


def test_bench_solver_paper_by_name(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "solver", "--solver", "paper", "--avatars", "2",
                 "--seconds", "0.2", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["solver"] == "paper" and doc["results"][0]["avatars"] == 2


def test_bench_protocol_json(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "protocol", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    # issue 30: <= 120 bytes an avatar-frame, no more error than the 5-byte bound
    assert doc["joints"] == 53 and doc["driven_joints"] == 20
    assert 100 < doc["bytes_per_avatar_frame"] <= 120
    assert 300 < doc["bytes_per_avatar_frame_every_joint"] < 320
    assert doc["quantization_worst_deg_measured"] <= doc["quantization_bound_deg"] <= 0.1
    assert 0.02 < doc["coded_worst_deg_measured"] <= doc["quantization_bound_deg"]
    assert doc["tracker_frame_bytes"] <= 350


def test_bad_batch_sizes_are_refused(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["bench", "solver", "--avatars", "0,x"])
    assert exit_info.value.code == 2
    assert "expected" in capsys.readouterr().err


def test_bench_startup_times_fresh_processes(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "startup", "--runs", "1", "--json"]) == 0
    out = capsys.readouterr()
    doc = json.loads(out.out)
    commands = [r["command"] for r in doc["results"]]
    assert [c.split()[1] for c in commands] == ["--version", "play", "serve", "eval"]
    # progress to a pipe: whole lines, no carriage-return fragments
    assert "\r" not in out.err and "posecast --version: run 1/1\n" in out.err
    for r in doc["results"]:
        assert r["runs"] == 1 and 0.0 < r["seconds_p50"] == r["seconds_max"]
        assert isinstance(r["compiled"], bool)
