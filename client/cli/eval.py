"""`posecast eval`: read each recording, reconstruct and score it, print a table or JSON.

A file that cannot be read gives one line naming the file and the line, and the command
exits with status 1 after scoring the others (with --json, each failure is also in the
document's ``failures``: file and reason)."""

from __future__ import annotations

import dataclasses
import json
import math
import sys
from pathlib import Path

from posecast.client.builtin import builtin_motion_path
from posecast.client.progress import ProgressBar
from posecast.solver.evaluation import (
    ClipResult,
    EvalOptions,
    evaluate_bvh,
    evaluate_vive,
    summarize,
    summarize_p99,
)
from posecast.solver.ik import SolverOptions
from posecast.solver.prediction import BASELINES, DEFAULT, PredictorParams
from posecast.solver.readers.bvh import read_bvh
from posecast.solver.readers.errors import FormatError
from posecast.solver.readers.joint_map import read_joint_map
from posecast.solver.readers.vive import read_vive
from posecast.solver.skeleton import SkeletonError
from posecast.solver.tracking.devices import DEFAULT_SET, PRESETS
from posecast.solver.tracking.dropouts import DropoutSpec


def evaluate_file(path: Path, options: EvalOptions, progress: ProgressBar | None,
                  joint_map: dict[str, str] | None = None) -> ClipResult:
    suffix = path.suffix.lower()
    if suffix == ".bvh":
        motion = read_bvh(path)
        if joint_map:  # --map: these joints play these roles, whatever their names
            motion = dataclasses.replace(motion, skeleton=dataclasses.replace(
                motion.skeleton, role_names=joint_map))
        return evaluate_bvh(motion, options, progress)
    if suffix in (".csv", ".txt"):
        return evaluate_vive(read_vive(path), options, progress=progress)
    raise FormatError(str(path), None, "unknown kind of recording: expected .csv (Vive) or .bvh")


def _why(path: Path, err: Exception) -> str:
    """One line: the file and why it cannot be scored."""
    if isinstance(err, FormatError):
        return str(err)  # names the file and the line already
    if isinstance(err, OSError):
        return f"{path}: {err.strerror}"
    return f"{path}: {err}"


def predictor_named(name: str) -> PredictorParams:
    return DEFAULT if name == "posecast" else BASELINES[name]


def run_eval(files: list[Path], solver: str, iterations: list[int] | None,
             calibration: str, smoothing: float, as_json: bool,
             delay_ms: float | None = None, predict: bool = False,
             predictor: str = "posecast", predict_on: str = "joints",
             joint_map: Path | None = None,
             devices: tuple[str, ...] = PRESETS[DEFAULT_SET],
             dropouts: DropoutSpec | None = None, naive: bool = False) -> int:
    if predict and delay_ms is None:
        print("posecast eval: --predict carries poses forward by the delay: give "
              "--delay-ms D too", file=sys.stderr)
        return 2
    if not files:
        files = [builtin_motion_path()]
    try:
        roles = read_joint_map(joint_map) if joint_map is not None else None
    except (FormatError, OSError) as err:
        msg = err if isinstance(err, FormatError) else f"{joint_map}: {err.strerror}"
        print(f"posecast eval: --map: {msg}", file=sys.stderr)
        return 2
    runs: list[int | None] = list(iterations) if iterations else [None]
    params = predictor_named(predictor) if predict else None
    failed = False
    documents = []
    for limit in runs:
        failures: list[dict[str, str]] = []
        options = EvalOptions(solver, SolverOptions(max_iterations=limit), calibration,
                              smoothing, delay_ms, params, predict_on, devices, dropouts,
                              naive)
        clips: list[ClipResult] = []
        for path in files:
            bar = None if as_json else ProgressBar(path.name)
            try:
                clips.append(evaluate_file(path, options, bar, roles))
            except (FormatError, SkeletonError, OSError) as err:
                # one line per file that cannot be scored; the others still are
                msg = _why(path, err)
                print(f"posecast eval: {msg}", file=sys.stderr)
                failures.append({"file": str(path), "error": msg})
            finally:
                if bar is not None:
                    bar.close()
        doc: dict[str, object] = {"solver": solver, "devices": list(devices),
                                  "clips": [c.as_json() for c in clips],
                                  "summary": summarize(clips) if clips else {}}
        if dropouts is not None:
            doc["dropouts"] = str(dropouts)
        if naive:
            doc["body"] = "naive"
        p99 = summarize_p99(clips)
        if p99:  # the worst 1% of frames per device, beside the means
            doc["summary"] = {**summarize(clips), "p99_error_mm": p99}
        if failures:
            doc["failures"] = failures
            failed = True
        if limit is not None:
            doc["max_iterations"] = limit
        if delay_ms is not None:
            doc["delay_ms"] = delay_ms
            doc["predict"] = predictor if predict else None
            if predict:
                doc["predict_on"] = predict_on
        documents.append((limit, clips, doc))
    if as_json:
        out = documents[0][2] if len(documents) == 1 else {
            "solver": solver, "runs": [d for _, _, d in documents]}
        print(json.dumps(_no_nan(out)))
    else:
        for limit, clips, _ in documents:
            print(format_table(clips, solver, limit, delay_ms, predictor if predict else None,
                               _set_words(devices, dropouts, naive)))
    return 1 if failed else 0


def _set_words(devices: tuple[str, ...], dropouts: DropoutSpec | None, naive: bool) -> str:
    """The tracker set, its losses and the body model, as the table's heading says them."""
    name = next((f"{k}-point" for k, v in PRESETS.items() if v == devices), None)
    words = f"devices {name or ', '.join(devices)}"
    if dropouts is not None:
        words += f", dropouts {dropouts}"
    return words + (", naive body" if naive else "")


def _no_nan(value: object) -> object:
    """JSON has no NaN: a figure with nothing to average (no held-out device when every
    device drives) is null."""
    if isinstance(value, float) and math.isnan(value):
        return None
    if isinstance(value, dict):
        return {k: _no_nan(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_no_nan(v) for v in value]
    return value


def format_table(clips: list[ClipResult], solver: str, limit: int | None,
                 delay_ms: float | None = None, predict: str | None = None,
                 setting: str = "") -> str:
    head = (f"solver {solver}" + (f", {setting}" if setting else "")
            + (f", at most {limit} iterations" if limit else ""))
    if delay_ms is not None:
        head += (f", shown {delay_ms:g} ms after capture"
                 + (f", predicted ({predict})" if predict else ", not predicted"))
    delayed = delay_ms is not None
    dropped = any("dropout_frames" in c.extra for c in clips)
    rows = [("clip", "kind", "frames", "mean mm", "held-out mm", "p99 mm", "rot deg",
             "max step mm", *(("lost frames", "lost mm") if dropped else ()),
             "solve us", "jerk m/s3" if delayed else "lag ms")]
    for c in clips:
        last = c.extra["jitter_m_s3"] if delayed else c.lag_ms
        lost = (str(int(c.extra["dropout_frames"])),
                f"{c.extra.get('dropout_error_mm', float('nan')):.1f}") if dropped else ()
        rows.append((c.file.split("/")[-1], c.kind, str(c.frames), f"{c.mean_error_mm:.1f}",
                     f"{c.heldout_error_mm:.1f}", f"{c.extra['p99_frame_error_mm']:.1f}",
                     f"{c.rotation_error_deg:.1f}", f"{c.extra['max_step_mm']:.0f}", *lost,
                     f"{c.solve_us_p50:.1f}", f"{last:.0f}" if delayed else f"{last:.1f}"))
    if clips:
        s = summarize(clips)
        lost = (str(s["dropout_frames"]), f"{s.get('dropout_error_mm', float('nan')):.1f}"
                ) if dropped else ()
        rows.append(("summary", "", "", f"{s['mean_error_mm']:.1f}",
                     f"{s['heldout_error_mm']:.1f}", f"{s['p99_frame_error_mm']:.1f}",
                     f"{s['rotation_error_deg']:.1f}", f"{s['max_step_mm']:.0f}", *lost,
                     f"{s['solve_us_p50']:.1f}",
                     f"{s['jitter_m_s3']:.0f}" if delayed else ""))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = [head]
    for n, r in enumerate(rows):
        lines.append("  ".join(v.ljust(w) if i == 0 else v.rjust(w)
                               for i, (v, w) in enumerate(zip(r, widths, strict=True))))
        if n == 0 or n == len(rows) - 2:
            lines.append("  ".join("-" * w for w in widths))
    return "\n".join(lines)
