"""`posecast bench prediction`: how much of the error a delay adds motion prediction removes.

Every recording is solved once (``solver.evaluation.reconstruct_*``); what a viewer shows
D ms after capture is then scored for D = 0, 25, 50, 100 ms, as it is and carried forward
by each predictor (``solver.prediction``): constant velocity, SlimeVR's filter, posecast's.
posecast's constants are chosen on a small grid at 50 ms by leave-one-clip-out: each clip
is scored with the constants that do best on the other clips, so every figure of the
posecast rows is on motion its constants were not chosen on. The constants chosen on all
clips are the shipped ones (``prediction.DEFAULT``); the bench says if they differ.

The objective, per data set, is the share of the delay's error left:
(E_predicted - E_0) / (E_delayed - E_0), E being the mean position error over a set's
clips; the Vive and BVH shares are added, plus 0.01 x each set's jerk relative to the
delayed pose's, so that of two equally accurate settings the smoother one wins.
"""

from __future__ import annotations

import glob
import itertools
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np

from posecast.client.progress import ProgressBar
from posecast.solver.evaluation import (
    ClipResult,
    Reconstruction,
    reconstruct_bvh,
    reconstruct_vive,
    score,
)
from posecast.solver.prediction import BASELINES, DEFAULT, PredictorParams, lags_needed
from posecast.solver.readers.bvh import read_bvh
from posecast.solver.readers.vive import read_vive

DELAYS_MS = (0.0, 25.0, 50.0, 100.0)
FIT_DELAY_MS = 50.0
JERK_WEIGHT = 0.01
DEFAULT_GLOBS = ("../shared/data/vive/*.csv", "../shared/data/mocap/*.bvh")


def grid() -> list[PredictorParams]:
    """The settings tried: window, how fast old samples fade from the fit, trusted
    acceleration, and the speed-adaptive short window (off, or taking over at 8 rad/s and
    1.6 m/s). Windows stop at 120 ms: a 200 ms one scored the same (0.30 / 0.26 of the
    error left at 50 ms) and costs the viewer twice the logarithms per avatar."""
    out = []
    for window, decay, accel, adaptive in itertools.product(
            (0.06, 0.09, 0.12), (0.02, 0.04, np.inf), (0.0, 0.3), (False, True)):
        fast = (1.6, 8.0) if adaptive else (np.inf, np.inf)
        out.append(PredictorParams(window_s=window, decay_s=decay, short_window_s=0.06,
                                   accel_gain=accel, fast_speed=fast[0], fast_turn=fast[1]))
    return out


def default_files() -> list[Path]:
    return [Path(p) for pattern in DEFAULT_GLOBS for p in sorted(glob.glob(pattern))]


def _share(e: np.ndarray, e0: np.ndarray, ed: np.ndarray) -> float:
    """Share of the delay's error left, over clips (means over the clips first)."""
    added = float(ed.mean() - e0.mean())
    return float(e.mean() - e0.mean()) / added if added > 0 else float("nan")


def choose(errors: np.ndarray, jerk: np.ndarray, e0: np.ndarray, ed: np.ndarray,
           j0: np.ndarray, kinds: list[str], clips: np.ndarray) -> int:
    """Index of the grid setting with the least objective over ``clips`` (a mask).
    errors, jerk: (settings, clips); e0, ed, j0: (clips,)."""
    cost = np.zeros(errors.shape[0])
    for kind in sorted(set(kinds)):
        m = clips & (np.array(kinds) == kind)
        if not m.any():
            continue
        for s in range(errors.shape[0]):
            cost[s] += _share(errors[s, m], e0[m], ed[m])
            cost[s] += JERK_WEIGHT * float(np.mean(jerk[s, m] / j0[m]))
    return int(np.argmin(cost))


def _reconstruct(path: Path) -> Reconstruction:
    if path.suffix.lower() == ".bvh":
        return reconstruct_bvh(read_bvh(path))
    return reconstruct_vive(read_vive(path))


def _row(kind: str, delay: float, name: str, results: list[ClipResult],
         base0: list[ClipResult], based: list[ClipResult]) -> dict[str, object]:
    e = np.array([r.mean_error_mm for r in results])
    rot = np.array([r.rotation_error_deg for r in results])
    e0 = np.array([r.mean_error_mm for r in base0])
    ed = np.array([r.mean_error_mm for r in based])
    r0 = np.array([r.rotation_error_deg for r in base0])
    rd = np.array([r.rotation_error_deg for r in based])
    row: dict[str, object] = {
        "set": kind, "delay_ms": delay, "predictor": name,
        "position_error_mm": round(float(e.mean()), 2),
        "rotation_error_deg": round(float(rot.mean()), 2),
        "jitter_m_s3": round(float(np.mean([r.extra["jitter_m_s3"] for r in results])), 0)}
    if delay > 0:
        row["position_left"] = round(_share(e, e0, ed), 3)
        row["rotation_left"] = round(_share(rot, r0, rd), 3)
    return row


def bench_prediction(files: list[Path], progress: bool = True) -> dict[str, object]:
    say = ProgressBar("prediction") if progress else None
    recons = []
    steps = len(files) + len(grid()) + 2
    done = 0

    def tick(label: str) -> None:
        nonlocal done
        done += 1
        if say is not None:
            say.label = label
            say(done, steps)

    for path in files:
        recons.append(_reconstruct(path))
        tick(f"solve {path.name}")
    kinds = [r.kind for r in recons]
    lags = max(lags_needed(p, r.fps) for p in [*grid(), *BASELINES.values(), DEFAULT]
               for r in recons)
    for r in recons:
        r.deltas(lags)
    base = {d: [score(r, d) for r in recons] for d in DELAYS_MS}
    e0 = np.array([c.mean_error_mm for c in base[0.0]])
    ed = np.array([c.mean_error_mm for c in base[FIT_DELAY_MS]])
    j0 = np.array([c.extra["jitter_m_s3"] for c in base[FIT_DELAY_MS]])
    settings = grid()
    errors = np.empty((len(settings), len(recons)))
    jerk = np.empty_like(errors)
    for s, params in enumerate(settings):
        for c, r in enumerate(recons):
            res = score(r, FIT_DELAY_MS, params)
            errors[s, c] = res.mean_error_mm
            jerk[s, c] = res.extra["jitter_m_s3"]
        tick("fit constants")
    everyone = np.ones(len(recons), bool)
    shipped = settings[choose(errors, jerk, e0, ed, j0, kinds, everyone)]
    loo = [choose(errors, jerk, e0, ed, j0, kinds, everyone & (np.arange(len(recons)) != c))
           for c in range(len(recons))]
    rows: list[dict[str, object]] = []
    for kind in sorted(set(kinds), reverse=True):  # vive first
        idx = [c for c, k in enumerate(kinds) if k == kind]
        for d in DELAYS_MS:
            b0 = [base[0.0][c] for c in idx]
            bd = [base[d][c] for c in idx]
            rows.append(_row(kind, d, "none", bd, b0, bd))
            if d == 0:
                continue
            for name, params in BASELINES.items():
                rows.append(_row(kind, d, name, [score(recons[c], d, params) for c in idx],
                                 b0, bd))
            rows.append(_row(kind, d, "posecast (leave-one-out)",
                             [score(recons[c], d, settings[loo[c]]) for c in idx], b0, bd))
    per_clip = []  # 50 ms, leave-one-out: does it hold on runs, kicks, dance?
    for c, r in enumerate(recons):
        ahead = score(r, FIT_DELAY_MS, settings[loo[c]]).mean_error_mm
        late, at0 = base[FIT_DELAY_MS][c].mean_error_mm, base[0.0][c].mean_error_mm
        per_clip.append({"file": Path(r.file).name, "set": r.kind,
                         "error_0_mm": round(at0, 2), "delayed_mm": round(late, 2),
                         "predicted_mm": round(ahead, 2),
                         "position_left": round((ahead - at0) / (late - at0), 3)
                         if late > at0 else None})
    tick("score")
    where = []  # joints (the viewer) against trackers (before the server's solve)
    for on in ("joints", "trackers"):
        for kind in sorted(set(kinds), reverse=True):
            idx = [c for c, k in enumerate(kinds) if k == kind]
            where.append(_row(kind, FIT_DELAY_MS, f"posecast on {on}",
                              [score(recons[c], FIT_DELAY_MS, DEFAULT, on) for c in idx],
                              [base[0.0][c] for c in idx],
                              [base[FIT_DELAY_MS][c] for c in idx]))
    tick("joints or trackers")
    if say is not None:
        say.close()
    return {"files": [str(f) for f in files], "fit_delay_ms": FIT_DELAY_MS,
            "constants": _constants(shipped),
            "shipped_constants": _constants(DEFAULT),
            "shipped_match_fit": _constants(shipped) == _constants(DEFAULT),
            "leave_one_out": [{"file": Path(r.file).name, "constants": _constants(settings[i])}
                              for r, i in zip(recons, loo, strict=True)],
            "rows": rows, "where": where, "clips_at_50_ms": per_clip}


def _constants(p: PredictorParams) -> dict[str, object]:
    return {k: (None if isinstance(v, float) and not np.isfinite(v) else v)
            for k, v in asdict(p).items()}


def format_prediction_table(doc: dict[str, object]) -> str:
    rows = doc["rows"]
    assert isinstance(rows, list)
    where = doc["where"]
    assert isinstance(where, list)
    head = ("set", "delay ms", "predictor", "pos mm", "left", "rot deg", "left",
            "jerk m/s3")
    lines: list[tuple[str, ...]] = [head]

    def cells(r: dict[str, object]) -> tuple[str, ...]:
        pl, rl = r.get("position_left"), r.get("rotation_left")
        return (str(r["set"]), f"{r['delay_ms']:g}", str(r["predictor"]),
                f"{r['position_error_mm']:.1f}", "" if pl is None else f"{pl:.2f}",
                f"{r['rotation_error_deg']:.2f}", "" if rl is None else f"{rl:.2f}",
                f"{r['jitter_m_s3']:.0f}")

    lines += [cells(r) for r in rows]
    widths = [max(len(line[i]) for line in [*lines, *(cells(r) for r in where)])
              for i in range(len(head))]

    def fmt(line: tuple[str, ...]) -> str:
        return "  ".join(v.ljust(w) if i in (0, 2) else v.rjust(w)
                         for i, (v, w) in enumerate(zip(line, widths, strict=True)))

    out = [fmt(lines[0]), fmt(tuple("-" * w for w in widths))]
    out += [fmt(line) for line in lines[1:]]
    out += ["", "where to predict, at 50 ms with the shipped constants:"]
    out += [fmt(cells(r)) for r in where]
    clips = doc["clips_at_50_ms"]
    assert isinstance(clips, list)
    out += ["", "each clip at 50 ms, leave-one-out (share left):",
            "  " + ", ".join(f"{Path(str(c['file'])).stem} {c['position_left']}"
                             for c in clips)]
    out += ["", "left: share of the error the delay adds that is left "
            "((E - E_0) / (E_delayed - E_0)); jerk: mean jerk of what is shown",
            f"constants fitted on every clip: {_short(doc['constants'])}"]
    if not doc["shipped_match_fit"]:
        out.append(f"shipped constants differ: {_short(doc['shipped_constants'])}")
    return "\n".join(out)


def _short(constants: object) -> str:
    assert isinstance(constants, dict)
    return ", ".join(f"{k} {v}" for k, v in constants.items() if k != "kind")


def main_files(files: list[Path]) -> list[Path] | None:
    """The recordings to use: those given, else the shared data set; None (after one line
    on stderr) when there are none."""
    files = files or default_files()
    if not files:
        print("posecast bench prediction: no recordings: give Vive .csv and .bvh files "
              "(the data set is looked for in ../shared/data/)", file=sys.stderr)
        return None
    return files
