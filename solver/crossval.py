"""Leave-one-clip-out for the constants calibration reads off the Vive recordings.

Every constant of ``solver.calibration`` that was chosen by looking at the shared
recordings (pivot raises, the trackers' mount shares, the arm roll, the controller's
distance past the wrist) gets a grid of candidates around its shipped value. Each clip is
then scored with the constants chosen on the *other* clips: the figure a recording that
was never looked at can expect (``cross_validate``).

The configurations are the shipped constants and each constant moved alone to one of its
candidates; each is scored on every clip once (a full solve). A fold chooses the
configuration with the lowest mean error over its training clips, and the held-out clip's
score in that configuration is its figure: no further solve. (Choosing each constant
apart and combining the choices was worse: 14.3 mm against 13.3; the moves interact.)
C constants with V candidates cost 1 + C (V - 1) solves of every clip, however many folds.

The compiled solver's own constants (``ELBOW_DOWN_SHARE``, ``BEND_LO``/``BEND_HI`` in
``solver/ik/analytic.py``) are frozen into its kernels and are not refitted here.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from posecast.solver import calibration
from posecast.solver.evaluation import ClipResult, EvalOptions, evaluate_vive
from posecast.solver.motion import ViveRecording
from posecast.solver.readers.gltf import load_makehuman
from posecast.solver.rig import Rig, build_rig


@dataclass(frozen=True)
class Constant:
    """A module constant of ``solver.calibration`` and the candidates a fold chooses from."""

    name: str
    candidates: tuple[float, ...]  # the shipped value among them
    unit: str = ""  # "deg": candidates in degrees, the module holds radians

    @property
    def shipped(self) -> float:
        value = float(getattr(calibration, self.name))
        # rounded, so that a shipped value in degrees matches its candidate exactly
        return round(math.degrees(value) if self.unit == "deg" else value, 9)

    def module_value(self, value: float) -> float:
        return math.radians(value) if self.unit == "deg" else value


# Grids: the shipped value and two neighbours either side, about as far apart as the
# recordings can tell (each constant's reason:
# docs/decisions/0024-calibration-fits-the-person.md).
CONSTANTS: tuple[Constant, ...] = (
    Constant("HIP_PIVOT_RAISE", (0.0, 0.03, 0.06, 0.09, 0.12)),
    Constant("KNEE_PIVOT_RAISE", (0.06, 0.09, 0.12, 0.15, 0.18)),
    Constant("KNEE_BEND_SHARE", (0.0, 0.125, 0.25, 0.375, 0.5)),
    Constant("KNEE_TURN_OUT", (0.0, 4.0, 8.0, 12.0, 16.0), "deg"),
    Constant("FOREARM_TWIST_SHARE", (0.3, 0.4, 0.5, 0.6, 0.7)),
    Constant("ARM_ROLL", (70.0, 80.0, 90.0, 100.0, 110.0), "deg"),
    Constant("CONTROLLER_BEYOND_WRIST", (0.08, 0.10, 0.12, 0.14, 0.16)),
)

DEFAULT_OPTIONS = EvalOptions()
Choice = dict[str, float]  # constant name -> value (degrees for "deg" constants)
Progress = Callable[[str], None]


@contextmanager
def constants_set(constants: tuple[Constant, ...], choice: Choice) -> Iterator[None]:
    """``solver.calibration``'s constants set to ``choice`` for the block, then restored."""
    saved = {c.name: getattr(calibration, c.name) for c in constants}
    try:
        for c in constants:
            if c.name in choice:
                setattr(calibration, c.name, c.module_value(choice[c.name]))
        yield
    finally:
        for name, value in saved.items():
            setattr(calibration, name, value)


@dataclass
class Fold:
    clip: ClipResult  # the held-out clip, scored with the constants chosen without it
    shipped: ClipResult  # the same clip with the shipped constants
    choice: Choice  # what the other clips chose


@dataclass
class CrossValidation:
    constants: tuple[Constant, ...]
    folds: list[Fold]
    full_fit: Choice  # the choice on every clip at once

    def as_json(self) -> dict[str, object]:
        chosen: dict[str, dict[str, int]] = {}
        for c in self.constants:
            counts: dict[str, int] = {}
            for f in self.folds:
                key = f"{f.choice[c.name]:g}"
                counts[key] = counts.get(key, 0) + 1
            chosen[c.name] = counts
        return {
            "constants": {c.name: {"shipped": c.shipped, "candidates": list(c.candidates),
                                   "unit": c.unit or None, "all_clips": self.full_fit[c.name],
                                   "folds": chosen[c.name]}
                          for c in self.constants},
            "clips": [{**f.clip.as_json(), "constants": f.choice,
                       "shipped": {"mean_error_mm": round(f.shipped.mean_error_mm, 2),
                                   "heldout_error_mm": round(f.shipped.heldout_error_mm, 2),
                                   "rotation_error_deg": round(f.shipped.rotation_error_deg,
                                                               2)}}
                      for f in self.folds]}


def _score(recordings: list[ViveRecording], options: EvalOptions, rig: Rig,
           constants: tuple[Constant, ...], choice: Choice) -> list[ClipResult]:
    with constants_set(constants, choice):
        return [evaluate_vive(rec, options, rig) for rec in recordings]


Objective = Callable[[ClipResult], float]


def mean_error(clip: ClipResult) -> float:
    """The default objective: the clip's mean error over every recorded device (mm), the
    figure the acceptance is stated in. Adding the rotation error (deg) kept more of the
    shipped rotation figure (5.3 deg against 6.0) for 0.5 mm of position."""
    return clip.mean_error_mm


@dataclass
class Grid:
    """Every clip scored with the shipped constants and with each candidate in turn."""

    recordings: list[ViveRecording]
    options: EvalOptions
    rig: Rig
    constants: tuple[Constant, ...]
    base: list[ClipResult]
    varied: dict[tuple[str, float], list[ClipResult]]

    def configurations(self) -> list[tuple[Choice, list[ClipResult]]]:
        """The shipped constants, then each constant moved alone, with their clips."""
        shipped: Choice = {c.name: c.shipped for c in self.constants}
        out = [(shipped, self.base)]
        for (name, v), clips in self.varied.items():
            out.append(({**shipped, name: v}, clips))
        return out

    def choose(self, train: list[int], objective: Objective
               ) -> tuple[Choice, list[ClipResult]]:
        """The configuration with the lowest mean objective over the ``train`` clips."""
        return min(self.configurations(),
                   key=lambda cfg: float(np.mean([objective(cfg[1][i]) for i in train])))


def score_grid(recordings: list[ViveRecording], options: EvalOptions = DEFAULT_OPTIONS,
               constants: tuple[Constant, ...] = CONSTANTS,
               progress: Progress | None = None) -> Grid:
    rig = build_rig(load_makehuman().skeleton)
    shipped: Choice = {c.name: c.shipped for c in constants}
    base = _score(recordings, options, rig, constants, shipped)
    varied: dict[tuple[str, float], list[ClipResult]] = {}
    for c in constants:
        for v in c.candidates:
            if v != c.shipped:
                if progress is not None:
                    progress(f"{c.name} = {v:g}")
                varied[(c.name, v)] = _score(recordings, options, rig, constants,
                                             {**shipped, c.name: v})
    return Grid(recordings, options, rig, constants, base, varied)


def leave_one_out(grid: Grid, objective: Objective = mean_error
                  ) -> CrossValidation:
    """Each recording scored with the constants chosen on the others."""
    everything = list(range(len(grid.recordings)))
    folds = []
    for k in everything:
        choice, clips = grid.choose([i for i in everything if i != k], objective)
        folds.append(Fold(clips[k], grid.base[k], choice))
    return CrossValidation(grid.constants, folds, grid.choose(everything, objective)[0])


def cross_validate(recordings: list[ViveRecording], options: EvalOptions = DEFAULT_OPTIONS,
                   constants: tuple[Constant, ...] = CONSTANTS,
                   objective: Objective = mean_error,
                   progress: Progress | None = None) -> CrossValidation:
    """Leave one clip out: each recording scored with the constants fitted on the others."""
    if len(recordings) < 2:
        raise ValueError("leave-one-clip-out needs at least two recordings")
    return leave_one_out(score_grid(recordings, options, constants, progress), objective)
