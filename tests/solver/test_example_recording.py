"""A Vive recording made by posecast's own code from the built-in CMU clip (the tests'
``walk_vive``), in the format of the paper authors' files, read back by the project's
reader."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from posecast.client.builtin import builtin_motion_path
from posecast.client.sources.bvh_source import tracker_recording
from posecast.solver.motion import ViveRecording
from posecast.solver.readers.vive import format_vive, read_vive


def test_the_built_in_clip_as_trackers_reads_back_as_made(walk_vive: Path) -> None:
    shipped = read_vive(walk_vive)
    made = tracker_recording(builtin_motion_path(), seconds=0.5)
    assert shipped.num_frames == made.num_frames == 46
    order = [made.device(d) for d in shipped.devices]
    assert sorted(shipped.devices) == sorted(made.devices) and len(shipped.devices) == 10
    # 6 significant digits in the file
    assert np.allclose(shipped.positions, made.positions[:, order], atol=5e-6)
    q = np.abs(np.sum(shipped.rotations * made.rotations[:, order], axis=-1))
    assert np.all(q > 1 - 1e-9)


def test_frame_zero_is_a_t_pose(walk_vive: Path) -> None:
    rec = read_vive(walk_vive)
    left, right = (rec.positions[0, rec.device(d)] for d in ("left_hand", "right_hand"))
    hip = rec.positions[0, rec.device("hip")]
    assert np.linalg.norm(left - right) > 1.2  # arms stretched sideways
    assert abs(left[1] - right[1]) < 0.02 and left[1] > hip[1] + 0.2


def test_format_and_read_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    q = rng.normal(size=(3, 6, 4))
    rec = ViveRecording(devices=("head", "hip", "left_hand", "right_hand", "left_foot",
                                 "right_foot"),
                        positions=rng.uniform(-2, 2, size=(3, 6, 3)),
                        rotations=q / np.linalg.norm(q, axis=-1, keepdims=True), fps=90.0,
                        source="random")
    path = tmp_path / "r.csv"
    path.write_text(format_vive(rec))
    back = read_vive(path)
    assert back.devices == ("head", "hip", "left_hand", "right_hand", "left_foot",
                            "right_foot")
    assert np.allclose(back.positions, rec.positions, rtol=1e-5, atol=1e-6)
    assert np.allclose(np.abs(np.sum(back.rotations * rec.rotations, axis=-1)), 1, atol=1e-9)
