"""`posecast latency-video` end to end: videos made here with OpenCV's VideoWriter (a
textured marker swinging, another following it D frames later, noise, 240 fps) go
through the real CLI in a subprocess, which must find D within one frame, draw its plot,
and answer bad input with one line and a non-zero status."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from swing_video import FPS, HEIGHT, WIDTH, write_swing_video

from posecast.client.measure.latency_plot import AVATAR_COLOR, TRACKER_COLOR

WAIT = 300.0  # seconds for one run: KCF over 720 frames takes a few, more under load
DELAYS = (3, 8, 15)


def latency_video(*args: str, env: dict[str, str] | None = None
                  ) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "posecast.client.cli", "latency-video",
                           *args], capture_output=True, text=True, timeout=WAIT, env=env)


def box_text(box: tuple[int, int, int, int]) -> str:
    return ",".join(str(v) for v in box)


def one_line(result: subprocess.CompletedProcess[str]) -> str:
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.stderr
    assert lines[0].startswith("posecast latency-video: ")
    return lines[0]


@pytest.fixture(scope="module")
def videos(tmp_path_factory: pytest.TempPathFactory
           ) -> dict[int, tuple[Path, tuple[int, int, int, int], tuple[int, int, int, int]]]:
    folder = tmp_path_factory.mktemp("videos")
    out = {}
    for delay in DELAYS:
        path = folder / f"swing_{delay}.avi"
        out[delay] = (path, *write_swing_video(path, delay))
    return out


@pytest.mark.parametrize("delay", DELAYS)
def test_finds_the_delay_within_one_frame(videos: dict, delay: int) -> None:  # type: ignore[type-arg]
    path, tracker, avatar = videos[delay]
    result = latency_video(str(path), "--tracker-box", box_text(tracker), "--avatar-box",
                           box_text(avatar), "--json")
    assert result.returncode == 0, result.stderr
    doc = json.loads(result.stdout)
    assert {"latency_ms", "frames", "peaks", "fps"} <= doc.keys()
    assert doc["fps"] == FPS
    assert abs(doc["frames"] - delay) <= 1.0, doc
    assert abs(doc["latency_ms"] - delay * 1000.0 / FPS) <= 1000.0 / FPS
    assert abs(doc["xcorr_frames"] - delay) <= 1.0, doc
    # 3 s of a swing at 1 to 2 per second: about 9 turns, nearly all of them paired
    assert doc["peaks"] >= 6 and doc["tracker_peaks"] >= doc["peaks"]
    assert doc["latency_std_ms"] < 1000.0 / FPS
    assert doc["tracker"] == "kcf" and doc["video_frames"] == 720
    assert doc["lost_frames"] == {"tracker": 0, "avatar": 0}
    assert not doc["mirrored"]


def test_a_90_hz_screen_adds_its_hold_to_the_delay(tmp_path: Path) -> None:
    """The avatar shows each pose 8 frames late, but only at 90 Hz refreshes: held for
    1.125 more frames on average (swing_video's refresh times), 9.125 in all."""
    path = tmp_path / "refresh.avi"
    tracker, avatar = write_swing_video(path, 8, display_hz=90.0)
    result = latency_video(str(path), "--tracker-box", box_text(tracker), "--avatar-box",
                           box_text(avatar), "--json")
    assert result.returncode == 0, result.stderr
    doc = json.loads(result.stdout)
    assert abs(doc["frames"] - 9.125) <= 0.5 and abs(doc["xcorr_frames"] - 9.125) <= 0.5
    assert 0.0 < doc["latency_std_ms"] < 1000.0 / FPS  # the hold spreads the turns a little


def test_plot_shows_both_traces_and_the_table_reads(videos: dict,  # type: ignore[type-arg]
                                                   tmp_path: Path) -> None:
    path, tracker, avatar = videos[8]
    plot = tmp_path / "latency.png"
    result = latency_video(str(path), "--tracker-box", box_text(tracker), "--avatar-box",
                           box_text(avatar), "--plot", str(plot))
    assert result.returncode == 0, result.stderr
    assert "latency (turns, eq. 15)" in result.stdout
    assert "33.3 ms" in result.stdout  # 8 frames at 240 fps
    pixels = np.asarray(Image.open(plot).convert("RGB")).reshape(-1, 3)
    for color in (TRACKER_COLOR, AVATAR_COLOR):  # each trace is a long line of its colour
        assert (pixels == color).all(axis=1).sum() > 2000


def test_bad_input_is_one_line(videos: dict, tmp_path: Path) -> None:  # type: ignore[type-arg]
    path, tracker, avatar = videos[3]
    boxes = ["--tracker-box", box_text(tracker), "--avatar-box", box_text(avatar)]

    missing = latency_video(str(tmp_path / "nope.mp4"), *boxes)
    assert missing.returncode == 2 and "no such file" in one_line(missing)

    garbage = tmp_path / "garbage.mp4"
    garbage.write_bytes(os.urandom(50_000))
    unreadable = latency_video(str(garbage), *boxes)
    assert unreadable.returncode == 1
    assert "cannot read" in one_line(unreadable)

    outside = latency_video(str(path), "--tracker-box", f"{WIDTH - 20},10,48,48",
                            "--avatar-box", box_text(avatar))
    assert outside.returncode == 2
    assert f"outside the video's {WIDTH}x{HEIGHT} frame" in one_line(outside)

    still = tmp_path / "still.avi"
    still_boxes = write_swing_video(still, 0, seconds=1.0, still=True)
    no_motion = latency_video(str(still), "--tracker-box", box_text(still_boxes[0]),
                              "--avatar-box", box_text(still_boxes[1]))
    assert no_motion.returncode == 1 and "does not move" in one_line(no_motion)

    no_boxes = latency_video(str(path))
    assert no_boxes.returncode == 2 and "--tracker-box" in one_line(no_boxes)

    bad_box = latency_video(str(path), "--tracker-box", "10,10,48", "--avatar-box", "1,1,9,9")
    assert bad_box.returncode == 2 and "X,Y,W,H" in one_line(bad_box)

    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    no_display = latency_video(str(path), "--select", env=env)
    assert no_display.returncode == 2 and "needs a display" in one_line(no_display)
