"""`posecast eval` end to end: real files in, the DESIGN.md JSON contract out; bad files
give one clear line and a failing exit status, never a traceback."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from posecast.client.builtin import builtin_motion_path
from posecast.client.cli import main

CLIP_KEYS = {"file", "kind", "frames", "position_error_mm", "mean_error_mm",
             "heldout_error_mm", "rotation_error_deg", "solve_us_p50", "lag_ms",
             "p99_error_mm", "p99_frame_error_mm",  # the worst 1% of frames, added
             "max_step_mm"}  # the largest frame-to-frame move, added with tracker sets
SUMMARY_KEYS = {"mean_error_mm", "heldout_error_mm", "rotation_error_deg", "solve_us_p50",
                "p99_frame_error_mm", "p99_error_mm", "max_step_mm"}
VIVE_DEVICES = {"head", "hip", "left_hand", "right_hand", "left_forearm", "right_forearm",
                "left_foot", "right_foot"}  # walking.csv has no knee trackers


def run_json(capsys: pytest.CaptureFixture[str], *argv: str) -> dict:
    assert main(["eval", *argv, "--json"]) == 0
    out = capsys.readouterr().out
    return json.loads(out)


def test_eval_vive_recording(shared_data: Callable[[str], Path],
                             capsys: pytest.CaptureFixture[str]) -> None:
    path = shared_data("vive/walking.csv")
    doc = run_json(capsys, str(path))
    assert doc["solver"] == "analytic"
    (clip,) = doc["clips"]
    assert set(clip) == CLIP_KEYS and set(doc["summary"]) == SUMMARY_KEYS
    assert clip["kind"] == "vive" and clip["frames"] == 677  # 678 minus the T-pose frame
    assert set(clip["position_error_mm"]) == VIVE_DEVICES
    # the driving devices are reached; walking is the easiest clip (about 7 mm on average)
    for device in ("head", "hip", "left_hand", "right_hand", "left_foot", "right_foot"):
        assert clip["position_error_mm"][device] < 10.0, device
    assert 0.0 < clip["mean_error_mm"] < 15.0
    assert clip["heldout_error_mm"] > clip["mean_error_mm"]  # forearms are predicted, not driven
    assert 0.0 < clip["rotation_error_deg"] < 10.0
    assert abs(clip["lag_ms"]) < 12.0  # within one 90 Hz frame: solving adds no delay
    assert doc["summary"]["mean_error_mm"] == clip["mean_error_mm"]


def test_eval_bvh_clip(capsys: pytest.CaptureFixture[str]) -> None:
    # the built-in CMU clip is a real motion-capture file shipped with the project
    doc = run_json(capsys, str(builtin_motion_path()))
    (clip,) = doc["clips"]
    assert clip["kind"] == "bvh" and clip["frames"] > 300
    assert "LeftForeArm" in clip["position_error_mm"]  # every joint of the file is scored
    assert 0.0 < clip["mean_error_mm"] < 25.0
    # this clip measures 11.6 deg: its fingers and CMU's hip joints have no tracker and stay
    # at rest (about 4 deg of it); the <= 9 deg target is on the summary over all clips
    assert 0.0 < clip["rotation_error_deg"] < 15.0
    assert clip["heldout_error_mm"] >= clip["mean_error_mm"]


def test_eval_iteration_sweep_reports_each_run(shared_data: Callable[[str], Path],
                                               capsys: pytest.CaptureFixture[str]) -> None:
    path = shared_data("vive/walking.csv")
    doc = run_json(capsys, str(path), "--solver", "paper", "--max-iterations", "5,100")
    assert [r["max_iterations"] for r in doc["runs"]] == [5, 100]
    few, many = (r["clips"][0] for r in doc["runs"])
    # more iterations reach the hands better: the error and the lag both fall
    assert many["position_error_mm"]["left_hand"] < few["position_error_mm"]["left_hand"]
    assert many["lag_ms"] <= few["lag_ms"]


def _truncated_vive(tmp_path: Path, source: Path) -> Path:
    lines = source.read_text().splitlines()
    bad = tmp_path / "cut.csv"
    # stop half-way through a device line, as a recording killed mid-write does
    bad.write_text("\n".join(lines[:45]) + "\n" + lines[45][: len(lines[45]) // 2] + "\n")
    return bad


def _malformed_bvh(tmp_path: Path) -> Path:
    lines = builtin_motion_path().read_text().splitlines()
    frames_at = next(i for i, line in enumerate(lines) if line.startswith("Frame Time"))
    row = frames_at + 3
    words = lines[row].split()
    words[5] = "1.2.3"
    lines[row] = " ".join(words)
    bad = tmp_path / "bad.bvh"
    bad.write_text("\n".join(lines) + "\n")
    return bad


@pytest.mark.parametrize("kind", ["vive", "bvh"])
def test_bad_file_gives_one_line_with_file_and_line(kind: str, tmp_path: Path,
                                                    shared_data: Callable[[str], Path],
                                                    capsys: pytest.CaptureFixture[str]
                                                    ) -> None:
    if kind == "vive":
        bad, line = _truncated_vive(tmp_path, shared_data("vive/walking.csv")), 46
    else:
        bad = _malformed_bvh(tmp_path)
        frames_at = bad.read_text().splitlines().index(
            next(x for x in bad.read_text().splitlines() if x.startswith("Frame Time")))
        line = frames_at + 4
    assert main(["eval", str(bad)]) == 1
    captured = capsys.readouterr()
    err_lines = [x for x in captured.err.splitlines() if x.strip() and "\r" not in x]
    messages = [x for x in err_lines if x.startswith("posecast eval:")]
    assert len(messages) == 1, captured.err
    assert str(bad) in messages[0] and f":{line}:" in messages[0], messages[0]
    assert "Traceback" not in captured.err


def test_bad_file_through_the_real_command(tmp_path: Path) -> None:
    bad = _malformed_bvh(tmp_path)
    proc = subprocess.run([sys.executable, "-m", "posecast.client.cli", "eval", str(bad), "--json"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr
    assert str(bad) in proc.stderr and "line" not in proc.stderr.split(str(bad))[0]


def test_missing_file_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # refused with the other bad arguments, before any file is scored
    with pytest.raises(SystemExit) as exit_info:
        main(["eval", str(builtin_motion_path()), str(tmp_path / "nope.csv")])
    assert exit_info.value.code == 2
    captured = capsys.readouterr()
    assert captured.err.count("\n") == 1 and "nope.csv" in captured.err
    assert "Traceback" not in captured.err and captured.out == ""
