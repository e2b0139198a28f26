"""Leave-one-clip-out: each recording is scored with constants chosen without it."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO_ROOT

from posecast.solver import calibration
from posecast.solver.crossval import Constant, Grid, constants_set, cross_validate
from posecast.solver.evaluation import ClipResult, EvalOptions, evaluate_vive
from posecast.solver.readers.vive import read_vive

SharedData = Callable[[str], Path]
ROOT = REPO_ROOT


def _clip(mean: float) -> ClipResult:
    return ClipResult("c", "vive", 10, {}, mean, mean, 1.0, 1.0, 0.0)


def test_each_fold_chooses_on_the_other_clips_only() -> None:
    # one constant, shipped 0.5, candidate 0.7: clip 0 alone prefers 0.7 (2 mm vs 10),
    # clips 1 and 2 prefer the shipped value (5 vs 6 and 5 vs 9)
    k = Constant("FOREARM_TWIST_SHARE", (0.5, 0.7))
    assert k.shipped == 0.5
    base = [_clip(10.0), _clip(5.0), _clip(5.0)]
    moved = [_clip(2.0), _clip(6.0), _clip(9.0)]
    grid = Grid([None, None, None], EvalOptions(), None, (k,), base,  # type: ignore[list-item,arg-type]
                {(k.name, 0.7): moved})
    from posecast.solver.crossval import leave_one_out

    cv = leave_one_out(grid)
    # fold 0 trains on clips 1, 2 (shipped 5.0 vs moved 7.5): shipped, so clip 0 scores 10
    # fold 1 trains on 0, 2 (7.5 vs 5.5): moved; fold 2 on 0, 1 (7.5 vs 4.0): moved
    assert [f.choice[k.name] for f in cv.folds] == [0.5, 0.7, 0.7]
    assert [f.clip.mean_error_mm for f in cv.folds] == [10.0, 6.0, 9.0]
    assert [f.shipped.mean_error_mm for f in cv.folds] == [10.0, 5.0, 5.0]
    assert cv.full_fit[k.name] == 0.7  # all three: 6.67 vs 5.67


def test_constants_are_set_for_the_block_and_restored() -> None:
    k = Constant("KNEE_TURN_OUT", (0.0, 8.0), "deg")
    before = calibration.KNEE_TURN_OUT
    assert k.shipped == 8.0
    with constants_set((k,), {k.name: 0.0}):
        assert calibration.KNEE_TURN_OUT == 0.0
    assert before == calibration.KNEE_TURN_OUT


def test_leave_one_out_on_two_recordings(shared_data: SharedData) -> None:
    recs = [read_vive(shared_data("vive/walking.csv")), read_vive(shared_data("vive/yoga1.csv"))]
    k = Constant("FOREARM_TWIST_SHARE", (0.5, 0.7))
    cv = cross_validate(recs, constants=(k,))
    for i, fold in enumerate(cv.folds):
        # the fold's figure is that clip's eval with the constant the other clip chose
        with constants_set((k,), fold.choice):
            again = evaluate_vive(recs[i])
        assert fold.clip.mean_error_mm == pytest.approx(again.mean_error_mm, abs=1e-9)
        other = [0.5, 0.7]
        scores = []
        for v in other:
            with constants_set((k,), {k.name: v}):
                scores.append(evaluate_vive(recs[1 - i]).mean_error_mm)
        assert fold.choice[k.name] == other[int(np.argmin(scores))]
    assert cv.folds[0].shipped.mean_error_mm == pytest.approx(
        evaluate_vive(recs[0]).mean_error_mm, abs=1e-9)


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "posecast.client.cli", "eval",
                           "--cross-validate", *args], capture_output=True, text=True,
                          timeout=900)


def test_cross_validate_needs_two_vive_recordings(walk_vive: Path) -> None:
    walk = str(walk_vive)
    bvh = str(ROOT / "client" / "assets" / "cmu_02_01_walk.bvh")
    for args in ((walk,), (walk, bvh), (walk, walk, "--delay-ms", "50")):
        out = _cli(*args)
        assert out.returncode == 2
        assert out.stderr.count("\n") == 1 and "--cross-validate" in out.stderr
        assert "Traceback" not in out.stderr


def test_cross_validate_json_over_the_shared_recordings(shared_data: SharedData,
                                                        tmp_path: Path) -> None:
    """A file that cannot be read is one line; the others are cross-validated; exit 1."""
    bad = tmp_path / "broken.csv"
    bad.write_text("not a recording\n")
    files = [str(shared_data(f"vive/{n}.csv")) for n in ("walking", "squats", "yoga1")]
    out = _cli(*files, str(bad), "--json")
    assert out.returncode == 1
    assert out.stderr.count("\n") == 1 and "broken.csv" in out.stderr
    doc = json.loads(out.stdout)
    assert [c["file"] for c in doc["clips"]] == files
    assert doc["failures"][0]["file"] == str(bad)
    for clip in doc["clips"]:
        assert set(clip["constants"]) == set(doc["constants"])
        assert clip["p99_error_mm"]["left_forearm"] > clip["position_error_mm"]["left_forearm"]
    assert set(doc["summary"]["p99_error_mm"]) >= {"left_knee", "right_forearm"}
    assert doc["summary"]["mean_error_mm"] < 20.0
