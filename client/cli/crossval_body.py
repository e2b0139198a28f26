"""`posecast eval --cross-validate-body FILE...`: leave-one-clip-out over the body
model's constants, on mocap clips (.bvh) and Vive recordings (.csv) together.

Each clip is scored at 3 points (head and hands) and 4 (+ hip) with the constants chosen
on the other clips (``solver.crossval_body``), beside the shipped constants and the naive
baseline. A file that cannot be read gives one line and the others are still scored; the
exit status is then 1.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from posecast.solver.crossval_body import SETS, BodyCrossValidation, Clip, cross_validate_body
from posecast.solver.evaluation import EvalOptions
from posecast.solver.ik import SolverOptions
from posecast.solver.naming import roles as role_map
from posecast.solver.readers.bvh import read_bvh
from posecast.solver.readers.errors import FormatError
from posecast.solver.readers.vive import read_vive
from posecast.solver.skeleton import SkeletonError
from posecast.solver.tracking.body_model import SHIPPED


def _usage(msg: str) -> int:
    print(f"posecast eval: --cross-validate-body {msg}", file=sys.stderr)
    return 2


def _read(path: Path) -> tuple[Clip, str]:
    suffix = path.suffix.lower()
    if suffix == ".bvh":
        motion = read_bvh(path)
        role_map(motion.skeleton)  # a skeleton without the body's joints fails here
        return motion, "bvh"
    if suffix in (".csv", ".txt"):
        return read_vive(path), "vive"
    raise FormatError(str(path), None, "unknown kind of recording: expected .csv (Vive) or .bvh")


def run_cross_validate_body(files: list[Path], solver: str, iterations: list[int] | None,
                            as_json: bool, given: list[str] | None = None) -> int:
    if given:  # options of eval that this cross-validation does not take
        return _usage(f"scores sets 3 and 4 as solved: {given[0]} does not go with it")
    if iterations is not None and len(iterations) > 1:
        return _usage("takes one --max-iterations, not several")
    clips: list[Clip] = []
    names: list[tuple[str, str]] = []
    failures: list[dict[str, str]] = []
    for path in files:
        try:
            clip, kind = _read(path)
        except (FormatError, SkeletonError, OSError) as err:
            msg = (f"{path}: {err.strerror}" if isinstance(err, OSError)
                   else str(err) if isinstance(err, FormatError) else f"{path}: {err}")
            print(f"posecast eval: {msg}", file=sys.stderr)
            failures.append({"file": str(path), "error": msg})
            continue
        clips.append(clip)
        names.append((str(path), kind))
    if len(clips) < 2:
        print("posecast eval: --cross-validate-body leaves one clip out at a time: it needs "
              f"at least two readable clips, got {len(clips)}", file=sys.stderr)
        return 1 if failures else 2
    options = EvalOptions(solver, SolverOptions(max_iterations=iterations[0] if iterations
                                                else None))
    progress = None if as_json else (lambda what: print(f"  scoring {what}", file=sys.stderr,
                                                        flush=True))
    cv = cross_validate_body(clips, names, options, progress)
    doc: dict[str, object] = {"solver": solver, **cv.as_json()}
    if failures:
        doc["failures"] = failures
    print(json.dumps(doc) if as_json else format_table(cv))
    return 1 if failures else 0


def format_table(cv: BodyCrossValidation) -> str:
    head = ["clip"] + [f"{s}-pt {w}" for s in SETS for w in ("loco", "shipped", "naive")]
    rows = [[*head, "constants moved (chosen without the clip)"]]
    for f in cv.folds:
        moved = ", ".join(f"{k}={v:g}" for k, v in f.choice.moved().items()) or "-"
        rows.append([Path(f.file).name, *(f"{getattr(f, w)[s]:.1f}" for s in SETS
                                          for w in ("loco", "shipped", "naive")), moved])
    for kind, sets in cv.summary().items():
        rows.append([f"mean, {kind}", *(f"{sets[s][w]:.1f}" for s in SETS
                                         for w in ("loco", "shipped", "naive")), ""])
    widths = [max(len(r[i]) for r in rows) for i in range(len(head) + 1)]
    lines = ["leave-one-clip-out over the body model's constants: each clip scored with the "
             "constants chosen on the others (mm: mocap over every joint, Vive over the "
             "devices the set lacks)"]
    last = len(rows) - len(cv.summary())
    for n, r in enumerate(rows):
        lines.append("  ".join(v.ljust(w) if i in (0, len(head)) else v.rjust(w)
                               for i, (v, w) in enumerate(zip(r, widths, strict=True)))
                     .rstrip())
        if n in (0, last - 1):
            lines.append("  ".join("-" * w for w in widths))
    full = cv.full_fit.moved()
    lines.append("")
    lines.append("shipped: " + ", ".join(f"{k}={v:g}" for k, v in vars(SHIPPED).items()))
    lines.append("chosen on every clip: " + (", ".join(f"{k}={v:g}" for k, v in full.items())
                                             or "the shipped constants"))
    return "\n".join(lines)
