"""Leave-one-clip-out for the body model's constants (``solver.tracking.body_model``).

The body model fills in what a 3-point or 4-point player has no device for, and its
constants (how far the hips go back in a squat, when and how a foot steps) were chosen by
looking at the shared clips. Here each clip is scored with the constants chosen on the
*other* clips: the figure to expect from a clip nobody tuned for.

As in ``solver.crossval``: the configurations are the shipped constants and each constant
moved alone to one of its candidates, each scored once on every clip, with both sets the
model serves (3: head and hands, 4: + hip). A fold chooses the configuration with the
lowest mean objective over its training clips (the mean of the two sets' figures), and
the held-out clip's score in that configuration is its figure. The naive baseline is
scored beside it. Mocap clips and Vive recordings fold together: the body moves the same.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from posecast.solver.evaluation import ClipResult, EvalOptions, evaluate_bvh, evaluate_vive
from posecast.solver.motion import Motion, ViveRecording
from posecast.solver.readers.gltf import load_makehuman
from posecast.solver.rig import Rig, build_rig
from posecast.solver.tracking.body_model import CANDIDATES, SHIPPED, BodyModel
from posecast.solver.tracking.devices import PRESETS

DEFAULT_OPTIONS = EvalOptions()
SETS = ("3", "4")  # the sets the body model fills (a hip, feet, knees, elbows, a chest)
Clip = ViveRecording | Motion
Progress = Callable[[str], None]


def figure(clip: ClipResult) -> float:
    """A clip's figure (mm): over every joint for mocap (the acceptance's MPJPE), over the
    devices the set predicts for a Vive recording (the held-out ones)."""
    return clip.mean_error_mm if clip.kind == "bvh" else clip.heldout_error_mm


def configurations() -> list[BodyModel]:
    """The shipped constants, then each moved alone to each of its other candidates."""
    out = [SHIPPED]
    for name, values in CANDIDATES.items():
        out += [dataclasses.replace(SHIPPED, **{name: v}) for v in values
                if v != getattr(SHIPPED, name)]
    return out


@dataclass
class Fold:
    file: str
    kind: str
    choice: BodyModel  # what the other clips chose
    loco: dict[str, float]  # set -> the clip's figure with that choice (mm)
    shipped: dict[str, float]  # set -> with the shipped constants
    naive: dict[str, float]  # set -> the naive baseline's


@dataclass
class BodyCrossValidation:
    folds: list[Fold]
    full_fit: BodyModel  # the choice on every clip at once

    def summary(self) -> dict[str, dict[str, dict[str, float]]]:
        """kind -> set -> {"loco", "shipped", "naive"}: the means over that kind's clips."""
        out: dict[str, dict[str, dict[str, float]]] = {}
        for kind in sorted({f.kind for f in self.folds}):
            mine = [f for f in self.folds if f.kind == kind]
            out[kind] = {s: {key: round(float(np.mean([getattr(f, key)[s] for f in mine])), 2)
                             for key in ("loco", "shipped", "naive")} for s in SETS}
        return out

    def as_json(self) -> dict[str, object]:
        return {
            "cross_validate": "body", "sets": list(SETS),
            "shipped": dataclasses.asdict(SHIPPED), "candidates": CANDIDATES,
            "all_clips": dataclasses.asdict(self.full_fit),
            "clips": [{"file": f.file, "kind": f.kind, "constants": f.choice.moved(),
                       "loco_mm": f.loco, "shipped_mm": f.shipped, "naive_mm": f.naive}
                      for f in self.folds],
            "summary": self.summary()}


def _score(clip: Clip, options: EvalOptions, rig: Rig) -> float:
    if isinstance(clip, ViveRecording):
        return figure(evaluate_vive(clip, options, rig))
    return figure(evaluate_bvh(clip, options))


def score_all(clips: list[Clip], base: EvalOptions, models: list[BodyModel],
              progress: Progress | None = None) -> dict[tuple[str, int], list[float]]:
    """(set, configuration index, -1 for the naive baseline) -> each clip's figure."""
    rig = build_rig(load_makehuman().skeleton)
    out: dict[tuple[str, int], list[float]] = {}
    runs = [(s, k) for s in SETS for k in range(-1, len(models))]
    for n, (s, k) in enumerate(runs):
        if progress is not None:
            what = "naive" if k < 0 else (", ".join(f"{a}={b:g}" for a, b in
                                                     models[k].moved().items()) or "shipped")
            progress(f"[{n + 1}/{len(runs)}] set {s}: {what}")
        options = dataclasses.replace(base, devices=PRESETS[s], naive=k < 0,
                                      body=models[max(k, 0)])
        out[(s, k)] = [_score(c, options, rig) for c in clips]
    return out


def leave_one_out(names: list[tuple[str, str]], models: list[BodyModel],
                  scores: dict[tuple[str, int], list[float]]) -> BodyCrossValidation:
    """Each clip (file, kind) scored with the configuration chosen on the others."""
    per_clip = np.mean([[scores[(s, k)] for k in range(len(models))] for s in SETS], axis=0)

    def choose(train: list[int]) -> int:  # the first of equals: the shipped if it ties
        return int(np.argmin(per_clip[:, train].mean(axis=1)))

    everything = list(range(len(names)))
    folds = []
    for i, (file, kind) in enumerate(names):
        k = choose([j for j in everything if j != i])
        folds.append(Fold(file, kind, models[k],
                          {s: round(scores[(s, k)][i], 2) for s in SETS},
                          {s: round(scores[(s, 0)][i], 2) for s in SETS},
                          {s: round(scores[(s, -1)][i], 2) for s in SETS}))
    return BodyCrossValidation(folds, models[choose(everything)])


def cross_validate_body(clips: list[Clip], names: list[tuple[str, str]],
                        base: EvalOptions = DEFAULT_OPTIONS,
                        progress: Progress | None = None) -> BodyCrossValidation:
    """Leave one clip out over the body model's constants (``names``: each clip's file
    and kind, "bvh" or "vive")."""
    if len(clips) < 2:
        raise ValueError("leave-one-clip-out needs at least two clips")
    models = configurations()
    return leave_one_out(names, models, score_all(clips, base, models, progress))
