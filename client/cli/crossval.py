"""`posecast eval --cross-validate FILE...`: leave-one-clip-out over Vive recordings.

Each recording is scored with the calibration constants chosen on the other recordings
(``solver.crossval``): the accuracy to expect on a recording nobody tuned for. A file that
cannot be read gives one line and the others are still scored; the exit status is then 1.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from posecast.solver.crossval import CrossValidation, cross_validate
from posecast.solver.evaluation import EvalOptions, summarize, summarize_p99
from posecast.solver.ik import SolverOptions
from posecast.solver.motion import HELDOUT_DEVICES, ViveRecording
from posecast.solver.readers.errors import FormatError
from posecast.solver.readers.vive import read_vive


def _usage(msg: str) -> int:
    print(f"posecast eval: --cross-validate {msg}", file=sys.stderr)
    return 2


def run_cross_validate(files: list[Path], solver: str, iterations: list[int] | None,
                       calibration: str, smoothing: float, as_json: bool,
                       given: list[str] | None = None) -> int:
    if given:  # options of eval that cross-validation does not take
        return _usage(f"scores recordings as solved: {given[0]} does not go with it")
    if iterations is not None and len(iterations) > 1:
        return _usage("takes one --max-iterations, not several")
    if calibration != "fit":
        return _usage("refits the constants of --calibration fit only")
    others = [str(p) for p in files if p.suffix.lower() not in (".csv", ".txt")]
    if others:
        return _usage(f"fits the Vive calibration's constants: give Vive .csv recordings, "
                      f"not {others[0]}")
    recordings: list[ViveRecording] = []
    failures: list[dict[str, str]] = []
    for path in files:
        try:
            recordings.append(read_vive(path))
        except (FormatError, OSError) as err:
            msg = str(err) if isinstance(err, FormatError) else f"{path}: {err.strerror}"
            print(f"posecast eval: {msg}", file=sys.stderr)
            failures.append({"file": str(path), "error": msg})
    if len(recordings) < 2:
        print("posecast eval: --cross-validate leaves one recording out at a time: it needs "
              f"at least two readable recordings, got {len(recordings)}", file=sys.stderr)
        return 1 if failures else 2
    limit = iterations[0] if iterations else None
    options = EvalOptions(solver, SolverOptions(max_iterations=limit), calibration, smoothing)
    progress = None if as_json else (lambda what: print(f"  scoring {what}", file=sys.stderr))
    cv = cross_validate(recordings, options, progress=progress)
    clips = [f.clip for f in cv.folds]
    shipped = [f.shipped for f in cv.folds]
    doc: dict[str, object] = {"solver": solver, "cross_validate": "leave-one-clip-out",
                              **cv.as_json(),
                              "summary": {**summarize(clips), "p99_error_mm": summarize_p99(clips)},
                              "shipped_summary": summarize(shipped)}
    if failures:
        doc["failures"] = failures
    if as_json:
        print(json.dumps(doc))
    else:
        print(format_table(cv, solver))
    return 1 if failures else 0


def format_table(cv: CrossValidation, solver: str) -> str:
    rows = [("clip", "mean mm", "held-out mm", "rot deg", "p99 mm", "p99 held-out",
             "shipped mean", "constants moved (fitted without the clip)")]
    shipped = {c.name: c.shipped for c in cv.constants}

    def p99_held(p99: dict[str, float]) -> str:
        held = [p99[d] for d in HELDOUT_DEVICES if d in p99]
        return f"{sum(held) / len(held):.1f}" if held else ""

    for f in cv.folds:
        c = f.clip
        moved = ", ".join(f"{k}={v:g}" for k, v in f.choice.items() if v != shipped[k]) or "-"
        rows.append((c.file.split("/")[-1], f"{c.mean_error_mm:.1f}",
                     f"{c.heldout_error_mm:.1f}", f"{c.rotation_error_deg:.1f}",
                     f"{c.extra['p99_frame_error_mm']:.1f}", p99_held(c.p99_error_mm),
                     f"{f.shipped.mean_error_mm:.1f}", moved))
    clips = [f.clip for f in cv.folds]
    s, p99 = summarize(clips), summarize_p99(clips)
    rows.append(("summary", f"{s['mean_error_mm']:.1f}", f"{s['heldout_error_mm']:.1f}",
                 f"{s['rotation_error_deg']:.1f}", f"{s['p99_frame_error_mm']:.1f}",
                 p99_held(p99), f"{summarize([f.shipped for f in cv.folds])['mean_error_mm']:.1f}",
                 ""))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = [f"solver {solver}, leave-one-clip-out (each clip scored with the calibration "
             "constants fitted on the others)"]
    for n, r in enumerate(rows):
        lines.append("  ".join(v.ljust(w) if i in (0, 7) else v.rjust(w)
                               for i, (v, w) in enumerate(zip(r, widths, strict=True)))
                     .rstrip())
        if n == 0 or n == len(rows) - 2:
            lines.append("  ".join("-" * w for w in widths))
    lines.append("")
    lines.append("p99 per device (mm, mean over clips): " + ", ".join(
        f"{k} {v:.1f}" for k, v in p99.items()))
    lines.append("constant: shipped -> fitted on all clips; what the folds chose")
    for k in cv.constants:
        unit = " deg" if k.unit == "deg" else ""
        counts: dict[float, int] = {}
        for f in cv.folds:
            counts[f.choice[k.name]] = counts.get(f.choice[k.name], 0) + 1
        folds = ", ".join(f"{v:g} x{n}" for v, n in sorted(counts.items()))
        lines.append(f"  {k.name}: {k.shipped:g}{unit} -> {cv.full_fit[k.name]:g}{unit}; {folds}")
    return "\n".join(lines)
