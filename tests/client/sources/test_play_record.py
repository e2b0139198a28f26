"""``posecast play --record FILE``: the player's raw device poses kept as a Vive recording,
which eval scores and a player replays."""

from __future__ import annotations

import asyncio
import subprocess
import sys
from pathlib import Path

import numpy as np
from conftest import serving

from posecast.client.builtin import builtin_motion_path
from posecast.client.sources import open_source
from posecast.client.sources.base import DeviceSample
from posecast.client.sources.recording_source import RecordingSource
from posecast.server.app import Session
from posecast.solver.evaluation import evaluate_vive
from posecast.solver.readers.vive import read_vive

WALK = f"bvh:{builtin_motion_path()}"


class Scripted:
    """A source of fixed samples: a T-pose, then frames, one of them missing a device."""

    rate_hz = 90.0

    def __init__(self, frames: list[DeviceSample], tpose: DeviceSample) -> None:
        self.frames = list(frames)
        self.tpose = tpose
        self.closed = False

    def calibration(self) -> DeviceSample:
        return self.tpose

    def read(self) -> DeviceSample | None:
        return self.frames.pop(0) if self.frames else None

    def close(self) -> None:
        self.closed = True


def test_the_recording_has_the_t_pose_first_then_every_whole_frame(tmp_path: Path) -> None:
    walk = open_source(WALK)
    tpose = walk.calibration()
    frames = [s for s in (walk.read() for _ in range(5)) if s is not None]
    walk.close()
    lost = DeviceSample(frames[2].t_capture, frames[2].roles[1:], frames[2].poses[1:])
    order = list(reversed(range(len(frames[3].roles))))  # the same devices, another order
    shuffled = DeviceSample(frames[3].t_capture, tuple(frames[3].roles[i] for i in order),
                            frames[3].poses[order])
    script = Scripted([frames[0], frames[1], lost, shuffled, frames[4]], tpose)
    path = tmp_path / "me.csv"
    source = RecordingSource(script, path)
    source.calibration()
    source.calibration()  # a recalibration is not a frame of the file
    while source.read() is not None:
        pass
    source.close()
    assert script.closed and source.frames == 5 and source.skipped == 1
    rec = read_vive(path)
    assert rec.num_frames == 5
    expected = [tpose, frames[0], frames[1], frames[3], frames[4]]
    for f, sample in enumerate(expected):
        for d, device in enumerate(rec.devices):
            row = sample.poses[sample.roles.index(device)]
            assert np.allclose(rec.positions[f, d], row[:3], atol=5e-6)
            assert abs(abs(np.dot(rec.rotations[f, d], row[3:])) - 1) < 1e-9


def test_play_record_through_the_real_command(tmp_path: Path) -> None:
    """A player recorded for a second, then eval scores the file and a player replays it."""
    path = tmp_path / "session.csv"

    async def main() -> tuple[int, str, str]:
        async with serving(Session()) as url:
            proc = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "posecast.client.cli", "play", "--server", url,
                "--room", "rec", "--source", WALK, "--seconds", "1", "--record", str(path),
                stdout=subprocess.PIPE, stderr=subprocess.PIPE)
            out, err = await asyncio.wait_for(proc.communicate(), 60)
            return proc.returncode or 0, out.decode(), err.decode()

    code, out, err = asyncio.run(main())
    assert code == 0, err
    rec = read_vive(path)
    assert f"kept {rec.num_frames} frames in {path}" in out
    assert rec.num_frames >= 45 and len(rec.devices) == 10  # the T-pose and ~1 s at 90 Hz
    result = evaluate_vive(rec)  # solved again, later, from the raw poses
    assert result.mean_error_mm < 30.0
    again = subprocess.run([sys.executable, "-m", "posecast.client.cli", "play", "--server",
                            "ws://127.0.0.1:9", "--room", "rec", "--source", WALK,
                            "--record", str(path)], capture_output=True, text=True)
    assert again.returncode == 2 and "exists" in again.stderr  # never written over
    assert again.stderr.count("\n") <= 2 and "Traceback" not in again.stderr
