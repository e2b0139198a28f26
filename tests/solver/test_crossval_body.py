"""Leave-one-clip-out over the body model's constants (solver.crossval_body): each clip
at 3 and 4 points with the constants the other clips chose."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO_ROOT

from posecast.solver.crossval_body import SETS, configurations, leave_one_out
from posecast.solver.evaluation import EvalOptions, evaluate_bvh, evaluate_vive
from posecast.solver.readers.bvh import read_bvh
from posecast.solver.readers.vive import read_vive
from posecast.solver.tracking.body_model import CANDIDATES, SHIPPED, BodyModel
from posecast.solver.tracking.devices import PRESETS
from posecast.solver.tracking.layout import S_MODEL, S_REACH, S_STEP_DIST, SHAPE_SIZE

ROOT = REPO_ROOT
WALK = ROOT / "client" / "assets" / "cmu_02_01_walk.bvh"


def test_the_model_s_constants_reach_the_kernels_through_the_shape() -> None:
    shape = np.zeros(SHAPE_SIZE)
    BodyModel(step_dist=0.11, reach=0.77).write(shape)
    assert shape[S_STEP_DIST] == 0.11 and shape[S_REACH] == 0.77
    assert shape[S_MODEL] == SHIPPED.drop_back
    # and they change what the body does: on a walk, feet that step only 1 m behind
    # the hips are far from the performer's feet, the shipped ones are not
    clip = read_bvh(WALK)
    shipped = evaluate_bvh(clip, EvalOptions(devices=PRESETS["4"]))
    lazy = evaluate_bvh(clip, EvalOptions(devices=PRESETS["4"],
                                          body=BodyModel(step_dist=1.0, reach=3.0)))
    assert lazy.mean_error_mm > 1.25 * shipped.mean_error_mm  # 67 against 50 mm


def test_configurations_move_one_constant_at_a_time() -> None:
    configs = configurations()
    assert configs[0] == SHIPPED
    assert len(configs) == 1 + sum(len(v) - 1 for v in CANDIDATES.values())
    assert all(len(c.moved()) == 1 for c in configs[1:])
    for name, values in CANDIDATES.items():
        assert getattr(SHIPPED, name) in values, name  # the shipped value is a candidate


def test_each_fold_chooses_on_the_other_clips_only() -> None:
    # two configurations: the shipped and one moved; clip 0 alone prefers the moved one
    models = [SHIPPED, dataclasses.replace(SHIPPED, lead=1.0)]
    per = {0: [10.0, 5.0, 5.0], 1: [2.0, 6.0, 9.0]}  # configuration -> the three clips
    scores = {(s, k): per[k] for s in SETS for k in (0, 1)}
    scores.update({(s, -1): [7.0, 7.0, 7.0] for s in SETS})
    cv = leave_one_out([("a", "bvh"), ("b", "bvh"), ("c", "vive")], models, scores)
    # fold 0 trains on clips 1, 2 (shipped 5.0 vs moved 7.5); fold 1 on 0, 2 (7.5 vs
    # 5.5); fold 2 on 0, 1 (7.5 vs 4.0)
    assert [f.choice for f in cv.folds] == [models[0], models[1], models[1]]
    assert [f.loco["3"] for f in cv.folds] == [10.0, 6.0, 9.0]
    assert [f.shipped["4"] for f in cv.folds] == [10.0, 5.0, 5.0]
    assert cv.full_fit == models[1]  # all three: 6.67 vs 5.67
    summary = cv.summary()
    assert summary["bvh"]["3"] == {"loco": 8.0, "shipped": 7.5, "naive": 7.0}
    assert summary["vive"]["4"]["loco"] == 9.0


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "posecast.client.cli", "eval",
                           "--cross-validate-body", *args], capture_output=True,
                          text=True, timeout=900)


def test_bad_uses_are_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "broken.bvh"
    bad.write_text("HIERARCHY\nnonsense\n")
    for args, words in (((str(WALK),), "at least two readable clips, got 1"),
                        ((str(WALK), str(WALK), "--devices", "4"), "--devices does not go"),
                        ((str(WALK), str(WALK), "--naive"), "--naive does not go"),
                        ((str(bad), str(WALK)), "broken.bvh")):
        out = _cli(*args)
        assert out.returncode in (1, 2), args
        assert words in out.stderr, (args, out.stderr)
        assert "Traceback" not in out.stderr


def test_each_clip_is_scored_with_the_other_s_choice(walk_vive: Path) -> None:
    """A mocap clip and a Vive recording, through the CLI: the JSON's figures are those
    of eval with the constants the other clip chose."""
    out = _cli(str(WALK), str(walk_vive), "--json")
    assert out.returncode == 0, out.stderr
    doc = json.loads(out.stdout)
    assert [c["kind"] for c in doc["clips"]] == ["bvh", "vive"]
    for clip in doc["clips"]:
        model = dataclasses.replace(SHIPPED, **clip["constants"])
        for s in SETS:
            options = EvalOptions(devices=PRESETS[s], body=model)
            again = (evaluate_bvh(read_bvh(WALK), options) if clip["kind"] == "bvh"
                     else evaluate_vive(read_vive(walk_vive), options))
            figure = again.mean_error_mm if clip["kind"] == "bvh" else again.heldout_error_mm
            assert clip["loco_mm"][s] == pytest.approx(figure, abs=0.01), (clip["file"], s)
            assert clip["naive_mm"][s] > 0.0
    assert set(doc["summary"]) == {"bvh", "vive"}
