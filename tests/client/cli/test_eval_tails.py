"""eval reports the worst 1% of frames beside the means, and BVH rotations over the joints
the trackers constrain apart from the whole skeleton."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from conftest import REPO_ROOT

from posecast.solver.evaluation import tracked_chain

ROOT = REPO_ROOT
WALK_BVH = ROOT / "client" / "assets" / "cmu_02_01_walk.bvh"


def test_the_tracked_chain_runs_from_the_root_to_each_tracker() -> None:
    # root 0 -> spine 1 -> head 2, spine -> arm 3 -> hand 4 -> finger 5, root -> toe 6
    parents = np.array([-1, 0, 1, 1, 3, 4, 0])
    assert tracked_chain(parents, np.array([2, 4])) == [0, 1, 2, 3, 4]
    assert tracked_chain(parents, np.array([6])) == [0, 6]


def _eval_json(*files: Path) -> dict[str, object]:
    out = subprocess.run([sys.executable, "-m", "posecast.client.cli", "eval", *map(str, files),
                          "--json"], capture_output=True, text=True, timeout=600, check=True)
    doc: dict[str, object] = json.loads(out.stdout)
    return doc


def test_eval_json_has_p99_per_device_and_tracked_rotations(walk_vive: Path) -> None:
    doc = _eval_json(walk_vive, WALK_BVH)
    vive, bvh = doc["clips"]  # type: ignore[misc]
    for clip in (vive, bvh):
        # every scored point has its p99, no smaller than its mean
        assert set(clip["p99_error_mm"]) == set(clip["position_error_mm"])
        for name, mean in clip["position_error_mm"].items():
            assert clip["p99_error_mm"][name] >= mean - 0.01
        assert clip["p99_frame_error_mm"] >= clip["mean_error_mm"] - 0.01
    assert "rotation_error_tracked_deg" not in vive
    # the CMU walk's fingers and toes stay at rest: the tracked chains' MPJRE is lower
    assert 0.0 < bvh["rotation_error_tracked_deg"] < bvh["rotation_error_deg"]
    summary = doc["summary"]
    assert set(summary["p99_error_mm"]) == set(vive["position_error_mm"])  # type: ignore[index]
    assert summary["rotation_error_tracked_deg"] == round(  # type: ignore[index]
        bvh["rotation_error_tracked_deg"], 2)
